"""Peak memory of ``hsi-torch reconstruct`` per mode, split into private and file-mapped memory,
and (optionally) the same runs under a hard memory limit.

    python scripts/bench_memory.py --bundle calib.npz CAPTURE.tif [CAPTURE.tif ...]
        [--modes none,tv] [--limits-gib 3,2 --drop-caches]

Each mode runs the command line a user runs, in a child process, once to warm up (numba's
compiled kernels, the precomputation cache entry beside the bundle's content hash, the TV
factor) and once measured. The parent samples the child's ``/proc/<pid>/status`` every 5 ms and
prints the peak resident set (RSS) with, at that moment, its two parts:

* **private** (``RssAnon``): the arrays and heap of the process;
* **file-mapped** (``RssFile``): shared libraries and the memory-mapped precomputation cache
  entry (the per-pixel ``G``, ``G⁻¹``, the TV factor). These pages are clean: the kernel drops
  them under memory pressure and reads them back from the file when they are touched again,
  and processes mapping the same entry (Dask workers on one machine) share them. A TV frame
  hands back the pages its stages are done with (``precompute_cache.release_pages``), so the
  entry is not resident all at once.

``--limits-gib`` then reruns each mode in a Linux memory control group limited to each value
(cgroup v2 ``memory.max`` or v1 ``memory.limit_in_bytes``, swap off for the group: needs root and
a writable cgroup mount; otherwise it says so and skips), and checks that the cubes are
bit-identical to the unlimited run's. Pages already in the page cache are charged to whichever
group read them first, so a fair limited run needs an empty page cache: ``--drop-caches`` (root)
empties it system-wide (``/proc/sys/vm/drop_caches``) before every run, limited or not; without
it the limited runs are marked as optimistic.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # memory_probes beside this file
from memory_probes import ChildMemory, run_child_memory  # noqa: E402

CGROUP_ROOT = Path("/sys/fs/cgroup")


def _drop_caches() -> bool:
    try:
        subprocess.run(["sync"], check=False)
        Path("/proc/sys/vm/drop_caches").write_text("3\n")
        return True
    except OSError:
        return False


def _memory_cgroup(name: str, limit: int) -> Path | None:
    """A memory control group limited to ``limit`` bytes without swap, or ``None``."""
    v2 = CGROUP_ROOT / "cgroup.controllers"
    try:
        if v2.is_file() and "memory" in v2.read_text().split():
            d = CGROUP_ROOT / name
            d.mkdir(exist_ok=True)
            (d / "memory.max").write_text(f"{limit}\n")
            if (d / "memory.swap.max").exists():
                (d / "memory.swap.max").write_text("0\n")
            return d
        v1 = CGROUP_ROOT / "memory"
        if (v1 / "memory.limit_in_bytes").is_file():
            d = v1 / name
            d.mkdir(exist_ok=True)
            (d / "memory.limit_in_bytes").write_text(f"{limit}\n")
            if (d / "memory.memsw.limit_in_bytes").exists():  # swap included: no swapping
                (d / "memory.memsw.limit_in_bytes").write_text(f"{limit}\n")
            return d
    except OSError:
        return None
    return None


def _join(group: Path):
    def enter() -> None:  # runs in the child before exec
        (group / "cgroup.procs").write_text(f"{os.getpid()}\n")
    return enter


def _reconstruct(args: argparse.Namespace, mode: str, out: Path, group: Path | None) -> ChildMemory:
    cmd = [sys.executable, "-m", "hsi_torch", "reconstruct", "-q", "--no-progress", "--bundle",
           str(args.bundle), "--out", str(out), "--no-resume", "--set", f"prior={mode}",
           *map(str, args.captures)]  # fmt: skip
    if args.drop_caches:
        _drop_caches()
    run = run_child_memory(cmd, preexec_fn=None if group is None else _join(group),
                           stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    if run.returncode != 0:
        print(f"  {mode}: reconstruct exited {run.returncode}", file=sys.stderr)
    return run


def _same_cubes(a: Path, b: Path, captures: list[Path]) -> bool:
    for cap in captures:
        fa, fb = np.load(a / f"{cap.stem}.npz"), np.load(b / f"{cap.stem}.npz")
        for key in ("cube", "valid"):
            if not np.array_equal(fa[key], fb[key], equal_nan=True):
                return False
    return True


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("captures", nargs="+", type=Path)
    ap.add_argument("--bundle", required=True, type=Path)
    ap.add_argument("--modes", default="none,tv", help="comma-separated priors (none, tv)")
    ap.add_argument("--limits-gib", default="", help="comma-separated hard memory limits (GiB)")
    ap.add_argument("--drop-caches", action="store_true",
                    help="empty the page cache before every run (root; system-wide)")
    args = ap.parse_args()
    if args.drop_caches and not _drop_caches():
        ap.error("--drop-caches: cannot write /proc/sys/vm/drop_caches (needs root)")
    limits = [float(v) for v in args.limits_gib.split(",") if v.strip()]
    work = Path(tempfile.mkdtemp(prefix="hsi_bench_memory_"))
    rows = []
    try:
        for mode in args.modes.split(","):
            _reconstruct(args, mode, work / f"{mode}_warm", None)
            ref = work / f"{mode}_ref"
            r = _reconstruct(args, mode, ref, None)
            rows.append((mode, "none", r, None))
            for gib in limits:
                group = _memory_cgroup(f"hsi_bench_memory_{os.getpid()}", int(gib * 2**30))
                if group is None:
                    print(f"  limit {gib:g} GiB: no writable memory cgroup here (needs root): "
                          "skipped")
                    continue
                out = work / f"{mode}_{gib:g}"
                lr = _reconstruct(args, mode, out, group)
                same = lr.returncode == 0 and _same_cubes(ref, out, args.captures)
                rows.append((mode, f"{gib:g} GiB", lr, same))
                try:
                    group.rmdir()
                except OSError:
                    pass
    finally:
        shutil.rmtree(work, ignore_errors=True)
    print(f"hsi-torch reconstruct, {len(args.captures)} captures, cached precomputation"
          f"{'' if args.drop_caches else ' (page cache not emptied: limited runs optimistic)'}")
    print(f"{'mode':<6}{'limit':>9}{'exit':>6}{'wall s':>8}{'peak RSS':>10}{'private':>9}"
          f"{'mapped':>8}{'peak private':>14}  cubes identical")
    for mode, lim, r, same in rows:
        print(f"{mode:<6}{lim:>9}{r.returncode:>6}{r.wall_s:>8.1f}{r.peak_rss_gib:>10.2f}"
              f"{r.anon_at_peak_gib:>9.2f}{r.file_at_peak_gib:>8.2f}{r.peak_anon_gib:>14.2f}  "
              f"{'-' if same is None else ('yes' if same else 'NO')}")
    print("(GiB; private = RssAnon, mapped = RssFile at the RSS peak: libraries and the "
          "memory-mapped cache entry)")


if __name__ == "__main__":
    main()
