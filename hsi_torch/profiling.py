"""Time and memory of a piece of work: a child-process runner, this process's peak memory.

Used by the benchmarks (``scripts/bench_*.py``; their finer memory probes are in
``scripts/memory_probes.py``) and by ``hsi-torch demo --full``, which runs each
stage (simulate, calibrate, reconstruct) in its own process so that each stage's peak memory is
its own: a process's peak resident set size only grows, so stages sharing a process could not be
told apart.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass

__all__ = ["ChildRun", "run_child", "peak_rss_gib", "release_freed_memory"]


def peak_rss_gib() -> float:
    """Peak resident set size of this process so far (GiB; ``ru_maxrss``)."""
    import resource

    scale = 1 if sys.platform == "darwin" else 1024  # ru_maxrss: bytes on macOS, KiB on Linux
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * scale / 2**30


@dataclass
class ChildRun:
    """What :func:`run_child` measured: exit code, wall and CPU seconds, peak RSS (GiB)."""

    returncode: int
    wall_s: float
    cpu_s: float
    peak_rss_gib: float


def run_child(cmd: Sequence[str], *, env: dict[str, str] | None = None,
              stdout=None, stderr=None) -> ChildRun:
    """Run ``cmd`` in a child process and measure it (``os.wait4``: its own peak RSS and CPU)."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(list(cmd), env=env, stdout=stdout, stderr=stderr)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    scale = 1 if sys.platform == "darwin" else 1024
    return ChildRun(proc.returncode, wall, usage.ru_utime + usage.ru_stime,
                    usage.ru_maxrss * scale / 2**30)


def release_freed_memory() -> None:
    """Give memory that was freed back to the operating system (glibc ``malloc_trim``).

    Work done in chunks by several threads (the per-bundle factorisation, a frame's solve)
    leaves freed blocks in the allocator's per-thread arenas that still count as resident:
    ~0.3 GiB after the full-size factorisation. A no-op where glibc is not the C library.
    """
    if not sys.platform.startswith("linux"):
        return
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # pragma: no cover - another C library
        pass
