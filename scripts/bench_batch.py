#!/usr/bin/env python
"""Benchmark: many frames with one bundle — the serial run against Dask ``local:1`` and
``local:2`` (worker processes on this machine), in one run.

Each mode runs in a child process of its own (its peak RSS measured by the kernel); every mode
reconstructs the same ``--frames`` inputs (the given captures repeated under new names) with the
same configuration and writes the same files (the shipped ``reconstruct.yaml``: TIFF, ENVI, NPZ,
preview, unless ``--set`` says otherwise).

- **serial**: the bundle prepared once (:meth:`ReconstructRun.reconstructor`), then every frame
  as a serial run does it (read, reconstruct, write), all threads of
  the machine: a *cold* pass (the first frame loads numba's compiled kernels) and a *warm* one.
- **dask local:N**: a ``LocalCluster`` of N worker processes (one task thread each, ``cores / N``
  torch and numba threads per frame) — started (*processes*), the package imported on every
  worker (*imports*), then :func:`hsi_torch.recon.batch.reconstruct_many` twice: a *cold* pass
  (each worker prepares the bundle on its first frame: *preparation*, per worker) and a *warm*
  pass (``resume=False``: every frame again, bundles already prepared).

Printed: frames/s of the steady state (the warm pass of every mode) and its ratio to the serial
run measured here; the end-to-end time of ``--frames`` frames from nothing (serial: preparation +
cold pass; Dask: processes + imports + cold pass) and its ratio; the per-worker start-up cost;
peak RSS of the serial process, of the Dask driver and of each worker; bytes written per frame;
the load average (the machine may be shared).

Usage::

    python scripts/bench_batch.py --small                      # small prototype (simulated here)
    python scripts/bench_batch.py --bundle DEMO/calib/calib.npz \\
        --captures 'DEMO/captures/scenes/*.tif' --frames 12    # e.g. after hsi-torch demo --full
    python scripts/bench_batch.py --small --workers 1 2 4 --json out.json
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from hsi_torch.profiling import peak_rss_gib, release_freed_memory, run_child


def _prepare_small(root: Path) -> tuple[Path, list[Path]]:
    """The small prototype's oracle bundle and one simulated ColorChecker capture."""
    from hsi_torch.cli import main
    from hsi_torch.simulate.oracle import bundle_from_truth

    sim = root / "sim"
    rc = main(["-q", "simulate", "--out", str(sim),
               "--set", "captures.scan_wavelengths_nm=[]", "--set", "captures.white_shots=0",
               "--set", "captures.grid.poses=[]", "--set", "render.figures=false",
               "--set", "render.dtype=float32", "--set", "captures.dark_frames=0"])  # fmt: skip
    if rc != 0:
        raise SystemExit("simulating the small prototype failed")
    bundle = root / "oracle.npz"
    bundle_from_truth(sim).save(bundle)
    return bundle, [sim / "scenes" / "colorchecker.tif"]


def _frames(captures: list[Path], n: int, folder: Path) -> list[Path]:
    """``n`` inputs named ``f000.<ext>``, ... (symbolic links to the captures, in turn)."""
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for k in range(n):
        src = captures[k % len(captures)].resolve()
        dst = folder / f"f{k:03d}{src.suffix}"
        dst.symlink_to(src)
        out.append(dst)
    return out


def _bytes_per_frame(out: Path, n: int) -> float:
    total = sum(p.stat().st_size for p in out.iterdir() if p.is_file())
    return total / max(n, 1)


# --- the child processes ----------------------------------------------------------------------

def child_serial(spec: dict[str, Any]) -> dict[str, Any]:
    import torch

    from hsi_torch.recon.batch.entry import load_run_config
    from hsi_torch.recon.batch.run import check_run, reconstruct_input, write_outputs
    from hsi_torch.recon.config import ReconstructConfig

    cfg: ReconstructConfig = load_run_config(None, spec["overrides"])
    inputs = [Path(p) for p in spec["inputs"]]
    out = Path(spec["out"])
    run = check_run(inputs, spec["bundle"], out, cfg)
    run.start()
    t0 = time.perf_counter()
    rec = run.reconstructor()
    prep = time.perf_counter() - t0
    passes = []
    for _ in range(2):  # cold (first frames: numba's kernels loaded), then warm
        t1 = time.perf_counter()
        for p in inputs:  # as the serial driver's task does, without the markers
            res, meta, _ = reconstruct_input(rec, p, run)
            write_outputs(res, run.out_dir / p.stem, run.settings, meta,
                          inputs=[p, run.bundle_path])  # fmt: skip
            del res
            release_freed_memory()
        passes.append(time.perf_counter() - t1)
    return {"prepare_s": prep, "cold_s": passes[0], "warm_s": passes[1], "n": len(inputs),
            "threads": torch.get_num_threads(),
            "bytes_per_frame": _bytes_per_frame(out, len(inputs)),
            "peak_rss_gib": peak_rss_gib()}  # fmt: skip


def _import_package() -> float:
    t0 = time.perf_counter()
    import hsi_torch.recon.batch.entry  # noqa: F401

    return time.perf_counter() - t0


def child_dask(spec: dict[str, Any]) -> dict[str, Any]:
    from hsi_torch.recon.batch import reconstruct_many
    from hsi_torch.recon.distributed import connect

    n = int(spec["workers"])
    inputs = [Path(p) for p in spec["inputs"]]
    out = Path(spec["out"])
    threads = max(1, (os.cpu_count() or 1) // n)
    t0 = time.perf_counter()
    ctx = connect(f"local:{n}")  # the cluster of hsi-torch reconstruct --scheduler local:N
    client, _ = ctx.__enter__()
    client.wait_for_workers(n)
    start_s = time.perf_counter() - t0
    t1 = time.perf_counter()
    imports = client.run(_import_package)
    imports_wall = time.perf_counter() - t1
    try:
        t2 = time.perf_counter()
        cold = reconstruct_many(inputs, spec["bundle"], out, client=client,
                                overrides=spec["overrides"], progress=False,
                                threads_per_worker=threads)  # fmt: skip
        cold_s = time.perf_counter() - t2
        t3 = time.perf_counter()
        warm = reconstruct_many(inputs, spec["bundle"], out, client=client,
                                overrides=spec["overrides"], progress=False, resume=False,
                                threads_per_worker=threads)  # fmt: skip
        warm_s = time.perf_counter() - t3
        workers_rss = client.run(peak_rss_gib)
    finally:
        ctx.__exit__(None, None, None)
    if cold.failed or warm.failed:
        raise SystemExit(f"failures: {cold.report()}\n{warm.report()}")
    return {"workers": n, "threads": threads, "start_s": start_s, "imports_s": imports,
            "imports_wall_s": imports_wall, "prepare_s": cold.prepare_s, "cold_s": cold_s,
            "warm_s": warm_s, "warm_prepared": len(warm.prepare_s), "n": len(inputs),
            "frames_per_worker": _count(warm.workers.values()),
            "bytes_per_frame": _bytes_per_frame(out, len(inputs)),
            "driver_peak_rss_gib": peak_rss_gib(), "workers_peak_rss_gib": workers_rss}  # fmt: skip


def _count(names: Any) -> dict[str, int]:
    out: dict[str, int] = {}
    for n in names:
        out[n] = out.get(n, 0) + 1
    return out


# --- the parent -------------------------------------------------------------------------------

def _child(mode: str, spec: dict[str, Any], tmp: Path) -> tuple[dict[str, Any], float]:
    """Run one mode in a child process; its result and its peak RSS (GiB)."""
    spec_path = tmp / f"{mode}.spec.json"
    res_path = tmp / f"{mode}.result.json"
    spec_path.write_text(json.dumps(spec))
    cmd = [sys.executable, os.path.abspath(__file__), "--child", mode, str(spec_path),
           str(res_path)]  # fmt: skip
    run = run_child(cmd)
    if run.returncode != 0:
        raise SystemExit(f"{mode} failed (exit code {run.returncode})")
    return json.loads(res_path.read_text()), run.peak_rss_gib


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--small", action="store_true",
                    help="simulate the small prototype's frames and oracle bundle here")
    ap.add_argument("--bundle", type=Path, help="calibration bundle (.npz)")
    ap.add_argument("--captures", nargs="+", help="capture files or globs (repeated to --frames)")
    ap.add_argument("--frames", type=int, default=12, help="frames per mode (default 12)")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2],
                    help="Dask local:N modes to run (default: 1 2)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="reconstruct configuration overrides (as hsi-torch reconstruct --set)")
    ap.add_argument("--json", type=Path, help="also write the results here")
    ap.add_argument("--keep", type=Path, help="write the scratch files here and keep them")
    ap.add_argument("--child", nargs=3, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        mode, spec_path, res_path = args.child
        spec = json.loads(Path(spec_path).read_text())
        res = child_serial(spec) if mode == "serial" else child_dask(spec)
        Path(res_path).write_text(json.dumps(res))
        return 0
    if not args.small and not (args.bundle and args.captures):
        ap.error("give --small, or --bundle and --captures")

    tmp = args.keep or Path(tempfile.mkdtemp(prefix="bench_batch_"))
    tmp.mkdir(parents=True, exist_ok=True)
    try:
        if args.small:
            bundle, caps = _prepare_small(tmp)
            size = "small prototype (simulated here, oracle bundle)"
        else:
            bundle = args.bundle
            caps = [Path(m) for c in args.captures for m in sorted(glob.glob(c))]
            if not caps:
                raise SystemExit(f"no captures match {args.captures}")
            size = f"bundle {bundle} ({bundle.stat().st_size / 2**20:.0f} MiB)"
        inputs = _frames(caps, args.frames, tmp / "inputs")
        base = {"bundle": str(bundle), "inputs": [str(p) for p in inputs],
                "overrides": args.overrides}  # fmt: skip
        results: dict[str, Any] = {"size": size, "frames": args.frames,
                                   "cores": os.cpu_count(), "overrides": args.overrides,
                                   "load_before": os.getloadavg()[0]}
        print(f"{args.frames} frames, {size}, {os.cpu_count()} cores; "
              f"configuration overrides {args.overrides or 'none'}", flush=True)
        ser, ser_rss = _child("serial", {**base, "out": str(tmp / "out_serial")}, tmp)
        ser["child_peak_rss_gib"] = ser_rss
        results["serial"] = ser
        modes = {}
        for n in args.workers:
            # (the kernel's peak of the child counts its worker processes too: not used)
            r, _ = _child(f"dask{n}", {**base, "out": str(tmp / f"out_dask{n}"),
                                       "workers": n}, tmp)  # fmt: skip
            modes[n] = r
        results["dask"] = modes
        results["load_after"] = os.getloadavg()[0]
        _print(results)
        if args.json:
            args.json.write_text(json.dumps(results, indent=2))
    finally:
        if args.keep is None:
            shutil.rmtree(tmp, ignore_errors=True)
    return 0


def _print(res: dict[str, Any]) -> None:
    ser = res["serial"]
    n = ser["n"]
    ser_rate = n / ser["warm_s"]
    ser_total = ser["prepare_s"] + ser["cold_s"]
    print()
    print(f"{'mode':<14}{'steady frames/s':>16}{'ratio':>7}{'end-to-end s':>14}{'ratio':>7}"
          f"{'peak RSS GiB':>30}")
    print(f"{'serial':<14}{ser_rate:>16.2f}{1.0:>7.2f}{ser_total:>14.1f}{1.0:>7.2f}"
          f"{ser['child_peak_rss_gib']:>30.2f}")
    for k, r in res["dask"].items():
        rate = r["n"] / r["warm_s"]
        total = r["start_s"] + r["imports_wall_s"] + r["cold_s"]
        workers = max(r["workers_peak_rss_gib"].values())
        rss = f"driver {r['driver_peak_rss_gib']:.2f}, worker max {workers:.2f}"
        print(f"{'dask local:' + str(k):<14}{rate:>16.2f}{rate / ser_rate:>7.2f}{total:>14.1f}"
              f"{ser_total / total:>7.2f}{rss:>30}")
    print()
    print(f"serial: {ser['threads']} torch thread(s); bundle preparation {ser['prepare_s']:.1f} s, "
          f"cold pass {ser['cold_s']:.1f} s, warm pass {ser['warm_s']:.1f} s; "
          f"{ser['bytes_per_frame'] / 2**20:.1f} MiB written per frame")
    for k, r in res["dask"].items():
        prep = ", ".join(f"{v:.1f}" for v in r["prepare_s"].values())
        imp = ", ".join(f"{v:.1f}" for v in r["imports_s"].values())
        split = ", ".join(str(v) for v in r["frames_per_worker"].values())
        print(f"dask local:{k}: {r['threads']} torch/numba thread(s) per frame; processes up in "
              f"{r['start_s']:.1f} s, imports {imp} s, bundle preparation {prep} s (per worker); "
              f"cold pass {r['cold_s']:.1f} s, warm pass {r['warm_s']:.1f} s (frames per worker "
              f"{split}; prepared again in the warm pass: {r['warm_prepared']})")
    print("ratios: > 1 means faster than the serial run measured above; load average (1 min) "
          f"{res['load_before']:.1f} before, {res['load_after']:.1f} after")


if __name__ == "__main__":
    sys.exit(main())
