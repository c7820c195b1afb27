"""The memory probes the benchmarks use: a process's resident set split into private and
file-mapped memory, and a child process sampled while it runs."""

from __future__ import annotations

import sys
import textwrap
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
from memory_probes import process_memory, run_child_memory  # noqa: E402

linux_proc = pytest.mark.skipif(process_memory() is None, reason="needs Linux /proc/<pid>/status")


@linux_proc
def test_process_memory_parts_of_this_process():
    m = process_memory()
    assert m is not None and m["rss"] > 0
    assert 0 < m["anon"] <= m["rss"] and 0 < m["file"] <= m["rss"]
    assert process_memory(2**22 + 12345) is None  # no such process


@linux_proc
def test_child_memory_tells_private_from_mapped(tmp_path):
    """A child holding 200 MiB of its own array, then reading a 150 MiB memory-mapped file:
    the first shows as private memory, the second as file-mapped."""
    data = tmp_path / "mapped.bin"
    with open(data, "wb") as f:
        f.write(b"\1" * (150 * 2**20))
    code = textwrap.dedent(f"""
        import mmap, time
        import numpy as np
        a = np.ones(200 * 2**20, np.uint8)
        time.sleep(0.4)
        del a
        with open({str(data)!r}, "rb") as f:
            m = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
            s = sum(m[i] for i in range(0, len(m), 4096))
            time.sleep(0.4)
        assert s == len(m) // 4096
    """)
    run = run_child_memory([sys.executable, "-c", code], period_s=0.01)
    assert run.returncode == 0 and run.samples > 10
    assert run.peak_anon_gib >= 190 / 1024
    assert run.peak_rss_gib >= run.peak_anon_gib
    assert run.anon_at_peak_gib + run.file_at_peak_gib <= run.peak_rss_gib + 1e-6
    assert run.peak_file_gib >= 140 / 1024
