#!/usr/bin/env python
"""Benchmark: ``hsi-torch simulate`` in a child process, stage by stage, with peak memory.

Each config runs ``simulate_capture_set`` in a fresh child process (this script with
``--child``), so its memory is its own. Printed per config: sensor size, captures, sub-pixel rays
that reached the diffuser; the wall time of every stage (setup = renderer, view layout and scene
list; trace+render; sensor+write; truth; figures) and the peak RSS inside each stage (the child
samples its resident set every 20 ms from ``/proc/self/statm``, Linux only); the whole child's
wall time (interpreter start and imports included), user + system CPU and peak RSS
(``os.wait4`` resource usage).

There is no external baseline for a renderer: by default the small prototype
(the shipped ``simulate.yaml``) and the full-size one (``simulate_full.yaml``) run in the
same invocation, and the full size is reported relative to the small one (rays, wall time, time
per ray, peak RSS).

Usage::

    python scripts/bench_simulate.py                          # small, then full size
    python scripts/bench_simulate.py --config simulate_full --out simF --keep
    python scripts/bench_simulate.py --config simulate --set camera.scale=0.5
    hsi-torch bench simulate --config simulate

Full-size runs need about 4 GB of memory and a few minutes on 2 cores.

``--out`` must be new, empty, or an earlier run's folder of this script (its marker
``.hsi_torch_bench_simulate``, written before anything else): a folder holding other files is
refused, naming a few of them, as ``hsi-torch demo`` and ``experiment`` refuse theirs.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

from hsi_torch.profiling import run_child  # noqa: E402
from hsi_torch.resources import shipped_config  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))  # memory_probes beside this file
from memory_probes import RssSampler  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DEFAULT_CONFIGS = [shipped_config("simulate"), shipped_config("simulate_full")]
STAGES = ("setup", "trace+render", "sensor+write", "truth", "figures")

#: Written into ``--out`` before anything else: the folder holds this script's outputs (a rerun
#: may write into it again, also after an interrupted run).
BENCH_MARKER = ".hsi_torch_bench_simulate"


# =============================================================================================
# child: run one simulation and report
# =============================================================================================


def _child(config: str, out: str, report: str, overrides: list[str], threads: int | None) -> int:
    import torch

    from hsi_torch.config import load_config
    from hsi_torch.simulate.capture_sets import simulate_capture_set
    from hsi_torch.simulate.config import SimulateConfig

    if threads:
        torch.set_num_threads(threads)
    cfg = load_config(config, SimulateConfig, overrides)
    sampler = RssSampler()
    sampler.start()
    t0 = time.perf_counter()
    summary = simulate_capture_set(cfg, out, progress=False,
                                   log=lambda m: print(m, file=sys.stderr))
    sampler.stop()
    # stage windows from the summary's timings (stages run one after the other)
    peaks: dict[str, float] = {}
    start = t0
    for stage in STAGES:
        dur = summary.timings_s.get(stage)
        if dur is None:
            continue
        peak = sampler.peak(start, start + dur)
        if peak is not None:
            peaks[stage] = peak
        start += dur
    h, w = summary.sensor_size
    Path(report).write_text(json.dumps({
        "sensor": f"{w}x{h}", "captures": len(summary.files), "rays": summary.rays,
        "valid_pixels": summary.valid_pixels, "timings_s": summary.timings_s,
        "stage_peak_rss_gib": peaks, "threads": torch.get_num_threads(),
    }))
    return 0


# =============================================================================================
# parent: run the children, print the table
# =============================================================================================


def _run_one(config: Path, out: Path, overrides: list[str], threads: int | None) -> dict:
    with tempfile.NamedTemporaryFile(suffix=".json", delete=False) as f:
        report = Path(f.name)
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", str(config), str(out),
           str(report)]
    for o in overrides:
        cmd += ["--set", o]
    if threads:
        cmd += ["--threads", str(threads)]
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO), env.get("PYTHONPATH")) if p)
    run = run_child(cmd, env=env)
    try:
        if run.returncode != 0:
            raise SystemExit(f"simulation of {config} failed (exit code {run.returncode})")
        res = json.loads(report.read_text())
    finally:
        report.unlink(missing_ok=True)
    res.update(config=str(config), wall_s=run.wall_s, cpu_s=run.cpu_s,
               peak_rss_gib=run.peak_rss_gib)
    return res


def _print_table(results: list[dict]) -> None:
    cols = ["sensor", "caps", "rays (M)", *STAGES, "start+exit", "wall s", "CPU s", "peak GiB"]
    print("\nwall time per stage (s) | peak RSS inside the stage (GiB)")
    head = f"{'config':34s} " + " ".join(f"{c:>13s}" for c in cols)
    print(head)
    print("-" * len(head))
    for r in results:
        t, p = r["timings_s"], r["stage_peak_rss_gib"]
        stages = [f"{t[s]:6.1f}|{p.get(s, float('nan')):5.2f}" if s in t else "-" for s in STAGES]
        other = r["wall_s"] - t.get("total", 0.0)  # interpreter start, imports, exit
        vals = [r["sensor"], str(r["captures"]), f"{r['rays'] / 1e6:.2f}", *stages, f"{other:.1f}",
                f"{r['wall_s']:.1f}", f"{r['cpu_s']:.1f}", f"{r['peak_rss_gib']:.2f}"]
        print(f"{Path(r['config']).name[:34]:34s} " + " ".join(f"{v:>13s}" for v in vals))
    if len(results) >= 2:
        a, b = results[0], results[-1]
        ray_ratio = b["rays"] / max(a["rays"], 1)
        time_ratio = b["wall_s"] / a["wall_s"]
        print(f"\n{Path(b['config']).name} vs {Path(a['config']).name}: {ray_ratio:.1f}x the rays, "
              f"{time_ratio:.1f}x the wall time ({time_ratio / ray_ratio:.2f}x the time per ray), "
              f"{b['peak_rss_gib'] / a['peak_rss_gib']:.1f}x the peak RSS")


def _check_out(out: Path, configs: list[Path]) -> None:
    """Refuse an ``--out`` that holds files but no earlier run of this script (the refusal of
    ``hsi-torch demo`` and ``experiment``); then create it and write :data:`BENCH_MARKER`."""
    from hsi_torch.io.paths import claim_out_dir

    claim_out_dir(out, BENCH_MARKER, "run of bench_simulate.py", "it writes a capture set per "
                  f"config ({', '.join(f'{c.stem}/' for c in configs)})",
                  script="bench_simulate.py")  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", action="append", type=Path,
                    help="simulate config (repeatable; default: the small and the full-size one)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="config override for every run (as in hsi-torch simulate)")
    ap.add_argument("--out", type=Path, default=None,
                    help="output folder (one sub-folder per config; new, empty or this script's "
                         "own): default: a temporary folder")
    ap.add_argument("--keep", action="store_true", help="keep the outputs (always with --out)")
    ap.add_argument("--threads", type=int, default=None, help="torch threads in the child")
    ap.add_argument("--child", nargs=3, metavar=("CONFIG", "OUT", "REPORT"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        return _child(*args.child, args.set, args.threads)

    configs = args.config or DEFAULT_CONFIGS
    for c in configs:
        if not c.is_file():
            ap.error(f"config not found: {c}")
    if args.out is not None:
        _check_out(args.out, configs)
    base = args.out if args.out is not None else Path(tempfile.mkdtemp(prefix="bench_simulate_"))
    keep = args.keep or args.out is not None
    results = []
    try:
        for c in configs:
            out = base / c.stem
            print(f"simulating {c} -> {out}", flush=True)
            res = _run_one(c, out, args.set, args.threads)
            results.append(res)
            print(f"  {res['wall_s']:.1f} s wall, {res['cpu_s']:.1f} s CPU, peak RSS "
                  f"{res['peak_rss_gib']:.2f} GiB, {res['rays']} rays, {res['captures']} captures",
                  flush=True)
            if not keep:
                shutil.rmtree(out, ignore_errors=True)
    finally:
        if not keep:
            shutil.rmtree(base, ignore_errors=True)
    _print_table(results)
    if keep:
        print(f"\noutputs kept in {base}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
