#!/usr/bin/env python
"""What sensor drift costs on the small prototype, and what ``refine_registration`` gets back.

The small default prototype (``simulate.yaml``: 400 × 384 px, ColorChecker) is simulated ideal
and with a sensor drift since calibration (``mismatch.drift_*``: the documented 2 px + 0.05°,
and a 2 px shift alone), calibrated with the shipped ``calibrate.yaml`` from its own captures
(the drift acts on the scene captures only, so the bundle is the ideal device's), and the
ColorChecker reconstructed (default β, per pixel) with the calibrated and the oracle bundle,
without and with ``refine_registration``. Scores (reflectance, peak 1): PSNR of the patch-
interior mean spectra (≥ 0.3 mm inside each patch) and per pixel over the patch interiors, and
the sensor motion measured from the frame and how many views agree on it (``stats["drift"]``;
a refused drift fails the row: :class:`hsi_torch.recon.drift.DriftError`).

Usage::

    OMP_NUM_THREADS=1 python scripts/drift_small.py --out /tmp/drift_small   # ~1 min per row

A row's capture set, once written, is reused by a rerun (delete its folder to redo it).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from hsi_torch.calibrate.config import CalibrateConfig
from hsi_torch.calibrate.pipeline import calibrate_capture_set
from hsi_torch.config import load_config
from hsi_torch.experiments.metrics import colorchecker_scores, cube_scores, erode_px, interior_mask
from hsi_torch.io.capture_set import read_truth
from hsi_torch.io.paths import claim_out_dir
from hsi_torch.recon import Reconstructor
from hsi_torch.resources import shipped_config
from hsi_torch.simulate import SimulateConfig, simulate_capture_set
from hsi_torch.simulate.oracle import bundle_from_truth

ROWS = {
    "ideal": [],
    "drift 2 px + 0.05°": ["mismatch.drift_shift_px=[2.0, 0.0]",
                           "mismatch.drift_rotation_deg=0.05"],
    "drift 2 px": ["mismatch.drift_shift_px=[2.0, 0.0]"],
}


def score(out: Path, res) -> dict:
    """Means and per-pixel PSNR (dB) of a ColorChecker reconstruction against the truth."""
    truth, _ = read_truth(out)
    pidx = truth["colorchecker_patch_index"]
    spectra = np.asarray(truth["colorchecker_spectra"], np.float64)
    e = erode_px(truth, 0.3)
    cube = res.cube.detach().cpu().double().numpy()
    valid = res.valid.detach().cpu().numpy()
    inner = valid & (pidx >= 0) & np.logical_or.reduce(
        [interior_mask(pidx == k, e) for k in range(len(spectra))])
    means = colorchecker_scores(cube, valid, pidx, spectra, e)
    px = cube_scores(cube, np.asarray(truth["scene_colorchecker"], np.float64), inner)
    d = res.stats["drift"]
    return {"means_db": means["mean_psnr_db"], "pixel_db": px["psnr_db"],
            "sensor_shift_px": d["sensor_shift_px"], "rotation_deg": d["sensor_rotation_deg"],
            "agreement": d["agreement"], "fit_residual": res.stats["fit_residual"]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True,
                    help="output folder: new, empty or this script's own")
    args = ap.parse_args(argv)
    claim_out_dir(args.out, ".hsi_torch_drift_small", "run of drift_small.py",
                  "it writes a capture set per row (ideal/, drift_2_px/, ...), drift_small.json "
                  "and drift_small.md", script="drift_small.py",
                  earlier_names=("drift_small.json",))  # fmt: skip
    rows: dict = {}
    for name, keys in ROWS.items():
        out = args.out / name.replace(" ", "_").replace("°", "deg").replace("+", "")
        if not (out / "manifest.json").is_file():
            cfg = load_config(shipped_config("simulate"), SimulateConfig,
                              ["render.progress=false", "render.figures=false", *keys])
            simulate_capture_set(cfg, out, progress=False, log=lambda *a: None)
        ccfg = load_config(shipped_config("calibrate"), CalibrateConfig, ["progress=false"])
        bundle, _ = calibrate_capture_set(out, ccfg)
        cap = out / "scenes" / "colorchecker.tif"
        rows[name] = {f"{b} {'refined' if refine else 'as is'}":
                      score(out, Reconstructor(bb, refine_registration=refine)
                            .reconstruct_file(cap))
                      for b, bb in (("calibrated", bundle), ("oracle", bundle_from_truth(out)))
                      for refine in (False, True)}
        print(name, json.dumps(rows[name]))
    ideal = rows["ideal"]
    lines = ["| capture | bundle | means dB (lost), as is | refined | per pixel dB (lost), as "
             "is | refined | measured shift px, rotation ° |", "| --- " * 7 + "|"]
    for name, r in rows.items():
        for b in ("calibrated", "oracle"):
            a, f, i = r[f"{b} as is"], r[f"{b} refined"], ideal[f"{b} as is"]
            lines.append(
                f"| {name} | {b} | {a['means_db']:.2f} ({i['means_db'] - a['means_db']:+.2f}) "
                f"| {f['means_db']:.2f} ({i['means_db'] - f['means_db']:+.2f}) | "
                f"{a['pixel_db']:.2f} ({i['pixel_db'] - a['pixel_db']:+.2f}) | "
                f"{f['pixel_db']:.2f} ({i['pixel_db'] - f['pixel_db']:+.2f}) | "
                f"{a['sensor_shift_px']}, {a['rotation_deg']} |")
    md = "\n".join(lines)
    (args.out / "drift_small.json").write_text(json.dumps(rows, indent=1))
    (args.out / "drift_small.md").write_text(md + "\n")
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
