"""The benchmarks' memory probes (Linux ``/proc``): a sampler of this process's resident set,
a process's resident memory split into private and file-mapped parts, and a child process
sampled while it runs. Scripts import it from their own folder (``sys.path``)."""

from __future__ import annotations

import os
import subprocess
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass

__all__ = ["RssSampler", "ChildMemory", "run_child_memory", "process_memory"]


class RssSampler(threading.Thread):
    """Samples this process's resident set size (bytes) every ``period_s`` (Linux ``statm``).

    ``peak(t0, t1)`` is the largest sample in a time window (``time.perf_counter`` clock), so the
    stages of one process can be told apart by their start and end times.
    """

    def __init__(self, period_s: float = 0.02) -> None:
        super().__init__(daemon=True)
        self.period_s = period_s
        self.samples: list[tuple[float, int]] = []
        self._halt = threading.Event()
        self._page = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096

    def _rss(self) -> int | None:
        try:
            with open("/proc/self/statm") as f:
                return int(f.read().split()[1]) * self._page
        except OSError:
            return None

    def run(self) -> None:
        while not self._halt.is_set():
            rss = self._rss()
            if rss is None:
                return
            self.samples.append((time.perf_counter(), rss))
            self._halt.wait(self.period_s)

    def stop(self) -> None:
        self._halt.set()
        self.join()

    def peak(self, t0: float = float("-inf"), t1: float = float("inf")) -> float | None:
        """Largest sample in ``[t0, t1]`` in GiB (``None`` without samples there)."""
        inside = [r for t, r in self.samples if t0 <= t <= t1]
        return max(inside) / 2**30 if inside else None


def process_memory(pid: int | str = "self") -> dict[str, int] | None:
    """Resident memory of a process, bytes, from Linux ``/proc/<pid>/status``: ``rss`` (all
    resident pages), ``anon`` (private memory: the heap, arrays), ``file`` (resident pages of
    mapped files: shared libraries and memory-mapped data such as the precomputation cache,
    clean pages the kernel can drop and read again), ``shmem``. ``None`` where unavailable."""
    keys = {"VmRSS": "rss", "RssAnon": "anon", "RssFile": "file", "RssShmem": "shmem"}
    out: dict[str, int] = {}
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                name, _, value = line.partition(":")
                if name in keys:
                    out[keys[name]] = int(value.split()[0]) * 1024  # kB
    except (OSError, ValueError):
        return None
    return out if "rss" in out else None


@dataclass
class ChildMemory:
    """What :func:`run_child_memory` measured (memory in GiB): exit code, wall seconds, the
    peak resident set and, at that moment, its private (anonymous) and file-mapped parts; the
    peaks of the private and of the file-mapped part alone; the number of samples."""

    returncode: int
    wall_s: float
    peak_rss_gib: float
    anon_at_peak_gib: float
    file_at_peak_gib: float
    peak_anon_gib: float
    peak_file_gib: float
    samples: int


def run_child_memory(cmd: Sequence[str], *, env: dict[str, str] | None = None,
                     period_s: float = 0.005, preexec_fn=None, stdout=None,
                     stderr=None) -> ChildMemory:
    """Run ``cmd`` in a child process, sampling its ``/proc/<pid>/status`` every ``period_s``
    (Linux): the peak resident set split into private and file-mapped memory
    (:func:`process_memory`). ``preexec_fn`` runs in the child before ``cmd`` (e.g. joining a
    memory-limited control group)."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(list(cmd), env=env, stdout=stdout, stderr=stderr,
                            preexec_fn=preexec_fn)
    peak = {"rss": 0, "anon": 0, "file": 0}
    peak_anon = peak_file = n = 0
    while proc.poll() is None:
        m = process_memory(proc.pid)
        if m is not None:
            n += 1
            peak_anon = max(peak_anon, m.get("anon", 0))
            peak_file = max(peak_file, m.get("file", 0))
            if m["rss"] > peak["rss"]:
                peak = {"rss": m["rss"], "anon": m.get("anon", 0), "file": m.get("file", 0)}
        time.sleep(period_s)
    wall = time.perf_counter() - t0
    g = 2.0**30
    return ChildMemory(proc.returncode, wall, peak["rss"] / g, peak["anon"] / g,
                       peak["file"] / g, peak_anon / g, peak_file / g, n)
