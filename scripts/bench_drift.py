#!/usr/bin/env python
"""Benchmark: what the per-frame drift check (:func:`hsi_torch.recon.drift.estimate_drift`)
costs, and what it measures, on full-size captures.

Each capture is reconstructed once with the bundle (``Reconstructor.reconstruct_file``, drift
check on, as the CLI runs it: its ``timings`` give the per-pixel solve beside ``drift``); the
frame the pipeline handed to the drift check is kept and :func:`estimate_drift` is timed on it
``--repeat`` times more with :func:`drift_motion_px` (the check as the pipeline runs it), and
the correction's sampling grid (:func:`corrected_sensing`) apart: CPU time of the process
(``time.process_time``) and wall time, in ``--threads`` threads (torch and OpenCV; default 1).
The measured sensor motion and per-view shifts are printed and written to ``--json``, so that
two versions of the code can be compared on the same frames.

``--score-sets`` scores capture sets (the ideal one, a drifted one rendered after calibration)
as ``hsi-torch experiment mismatch`` does (:func:`hsi_torch.experiments.mismatch.score_captures`:
ColorChecker patch-interior means and per pixel, CAVE per pixel, when the set holds them), with
``refine_registration`` false and true, and prints each run's measured drift.

Usage::

    python scripts/bench_drift.py --bundle /work/runs/full/calib/calib.npz \
        CAPTURES/scenes/colorchecker.tif CAPTURES/scenes/cave.tif --json drift.json
    python scripts/bench_drift.py --bundle calib.npz --score-sets CAPTURES DRIFTED_CAPTURES
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch

import hsi_torch.recon.pipeline as pipeline
from hsi_torch.io.atomic import atomic_write_json
from hsi_torch.recon import Reconstructor
from hsi_torch.recon.drift import corrected_sensing, drift_motion_px, estimate_drift


def score_set(bundle: Path, captures: Path) -> dict:
    """Scores of a capture set with ``refine_registration`` false and true (and the drift each
    run measured)."""
    import hsi_torch.experiments.mismatch as mm

    seen: list[dict] = []
    orig = mm.Reconstructor.reconstruct_file

    def keep(self, path, *a, **k):
        res = orig(self, path, *a, **k)
        seen.append({"file": Path(path).name, "drift": res.stats.get("drift"),
                     "drift_s": res.timings.get("drift"),
                     "fit_residual": res.stats.get("fit_residual")})
        return res

    out = {}
    mm.Reconstructor.reconstruct_file = keep
    try:
        for refine in (False, True):
            seen.clear()
            rec = Reconstructor(bundle, refine_registration=refine)
            sc = mm.score_captures(captures, rec, mm.MismatchConfig(size="full"))
            out[f"refine={refine}"] = {**sc, "runs": list(seen)}
            cc, cave = sc["colorchecker"], sc.get("cave", {})
            print(f"{captures} refine_registration={refine}: ColorChecker means "
                  f"{cc['means_db']:.3f} dB, SAM {cc['means_sam']:.3f} deg, per pixel "
                  f"{cc['pixel_db']:.3f} dB; CAVE {cave.get('pixel_db', float('nan')):.3f} dB")
            for r in seen:
                d = r["drift"]
                print(f"  {r['file']}: shift {d['sensor_shift_px']} px, rotation "
                      f"{d['sensor_rotation_deg']} deg, fit residual {r['fit_residual']:.3f}, "
                      f"drift check {r['drift_s']:.3f} s")
    finally:
        mm.Reconstructor.reconstruct_file = orig
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("captures", nargs="*", type=Path)
    ap.add_argument("--score-sets", nargs="*", type=Path, default=[])
    ap.add_argument("--bundle", type=Path, required=True)
    ap.add_argument("--threads", type=int, default=1, help="torch and OpenCV threads (default 1)")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    import cv2

    torch.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)
    rec = Reconstructor(args.bundle)
    frames: list[torch.Tensor] = []
    orig = pipeline.estimate_drift

    def keep(sens, image):  # the frame exactly as the pipeline hands it to the drift check
        frames.append(image.clone())
        return orig(sens, image)

    rows = {}
    pipeline.estimate_drift = keep
    try:
        for path in args.captures:
            frames.clear()
            res = rec.reconstruct_file(path)
            img = frames[0]
            cpu, wall, cpu_fix, wall_fix = [], [], [], []
            for _ in range(args.repeat):
                c0, w0 = time.process_time(), time.perf_counter()
                est = estimate_drift(rec.sensing, img)
                drift_motion_px(rec.sensing, est)
                cpu.append(time.process_time() - c0)
                wall.append(time.perf_counter() - w0)
                if est.sensor_shift_px is not None:
                    c0, w0 = time.process_time(), time.perf_counter()
                    corrected_sensing(rec.sensing, est.sensor_shift_px,
                                      est.sensor_rotation_deg or 0.0)
                    cpu_fix.append(time.process_time() - c0)
                    wall_fix.append(time.perf_counter() - w0)
            d = est.to_dict()
            rows[str(path)] = {
                "drift": d, "cpu_s": cpu, "wall_s": wall, "correction_cpu_s": cpu_fix,
                "correction_wall_s": wall_fix,
                "pipeline_timings_s": {k: round(v, 4) for k, v in res.timings.items()},
            }
            t = res.timings
            print(f"{path}: drift check CPU {min(cpu):.3f} s (median {statistics.median(cpu):.3f}),"
                  f" wall {min(wall):.3f} s (median {statistics.median(wall):.3f}) in "
                  f"{args.threads} thread(s); the correction's grid CPU "
                  f"{min(cpu_fix, default=float('nan')):.3f} s, wall "
                  f"{min(wall_fix, default=float('nan')):.3f} s; in the pipeline: drift "
                  f"{t['drift']:.3f} s, solve {t.get('solve', float('nan')):.3f} s, total "
                  f"{t['total']:.3f} s")
            print(f"  sensor shift {d['sensor_shift_px']} px, rotation "
                  f"{d['sensor_rotation_deg']} deg, {d['measured_views']} views; view shifts "
                  f"{d['view_shift_px']}; correlation {d['correlation']}")
    finally:
        pipeline.estimate_drift = orig
    for cap_set in args.score_sets:
        rows[str(cap_set)] = score_set(args.bundle, cap_set)
    if args.json:
        atomic_write_json(args.json, rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
