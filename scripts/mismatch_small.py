#!/usr/bin/env python
"""What each non-ideal effect costs on the small prototype: dB lost per effect vs the ideal.

For the ideal device, each effect of ``DOCUMENTED_EFFECTS`` alone at its documented magnitude
(``docs/simulate.md``, "Non-ideal effects") and all of them together, the small default
prototype (``simulate.yaml``: 400 × 384 px, ColorChecker) is simulated, calibrated with the
shipped ``calibrate.yaml`` and the ColorChecker reconstructed (default β, per pixel) with the
calibrated bundle and with the oracle bundle (the truth of the calibrated, ideal-model device).
Scores (reflectance, peak 1): PSNR and spectral angle of the patch-interior mean spectra
(≥ 0.3 mm inside each patch) and per pixel over the patch interiors; "lost" = ideal − effect.
An effect changes the irradiance, so the Poisson draws of its captures differ from the ideal
set's: ``--noise-seeds N`` renders the ideal device with N other noise seeds, whose spread is
the noise floor below which a "lost" is not significant.

Usage::

    OMP_NUM_THREADS=1 python scripts/mismatch_small.py --out /tmp/mismatch   # ~1 min per row
    python scripts/mismatch_small.py --out /tmp/mismatch --effects drift distortion
    python scripts/mismatch_small.py --out /tmp/mismatch_nf --noise-free

A row's capture set, once written, is reused by a rerun (delete its folder to redo it).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from hsi_torch.calibrate.config import CalibrateConfig
from hsi_torch.calibrate.pipeline import calibrate_capture_set
from hsi_torch.config import load_config
from hsi_torch.experiments.metrics import colorchecker_scores, cube_scores, erode_px, interior_mask
from hsi_torch.io.capture_set import read_truth
from hsi_torch.recon import Reconstructor
from hsi_torch.resources import shipped_config
from hsi_torch.simulate import SimulateConfig, simulate_capture_set
from hsi_torch.simulate.mismatch import DOCUMENTED_EFFECTS
from hsi_torch.simulate.oracle import bundle_from_truth

NO_NOISE = ("sensor.shot_noise=false", "sensor.read_noise_e=0", "sensor.quantize=false")


def _overrides(keys: dict) -> list[str]:
    return [f"mismatch.{k}={json.dumps(list(v) if isinstance(v, tuple) else v)}"
            for k, v in keys.items()]


def run_row(out: Path, keys: dict, log=print, extra: tuple[str, ...] = ()) -> dict:
    """Simulate, calibrate, reconstruct and score one row (``extra``: further simulate
    overrides); returns its scores."""
    t0 = time.perf_counter()
    if not (out / "manifest.json").is_file():
        cfg = load_config(shipped_config("simulate"), SimulateConfig,
                          ["render.progress=false", "render.figures=false", *_overrides(keys),
                           *extra])
        simulate_capture_set(cfg, out, progress=False, log=lambda *a: None)
    ccfg = load_config(shipped_config("calibrate"), CalibrateConfig, ["progress=false"])
    bundle, _ = calibrate_capture_set(out, ccfg)
    truth, _ = read_truth(out)
    pidx = truth["colorchecker_patch_index"]
    spectra = np.asarray(truth["colorchecker_spectra"], np.float64)
    true_cube = np.asarray(truth["scene_colorchecker"], np.float64)
    e = erode_px(truth, 0.3)
    row: dict = {"keys": {k: list(v) if isinstance(v, tuple) else v for k, v in keys.items()}}
    for name, b in (("calibrated", bundle), ("oracle", bundle_from_truth(out))):
        res = Reconstructor(b).reconstruct_file(out / "scenes" / "colorchecker.tif")
        cube = res.cube.detach().cpu().double().numpy()
        valid = res.valid.detach().cpu().numpy()
        inner = valid & (pidx >= 0) & np.logical_or.reduce(
            [interior_mask(pidx == k, e) for k in range(len(spectra))])
        means = colorchecker_scores(cube, valid, pidx, spectra, e)
        px = cube_scores(cube, true_cube, inner)
        row[name] = {"means_db": means["mean_psnr_db"], "means_sam": means["mean_sam_deg"],
                     "pixel_db": px["psnr_db"], "pixel_sam": px["mean_sam_deg"]}
    row["seconds"] = time.perf_counter() - t0
    log(f"  {out.name}: calibrated {row['calibrated']['means_db']:.2f} dB, oracle "
        f"{row['oracle']['means_db']:.2f} dB ({row['seconds']:.0f} s)")
    return row


def table(rows: dict[str, dict]) -> str:
    """Markdown table: scores and dB lost against the ideal row."""
    ideal = rows["ideal"]
    lines = ["| effect | calibrated: means dB (lost) | per pixel dB (lost) | SAM ° | "
             "oracle: means dB (lost) | per pixel dB (lost) |",
             "| --- | --- | --- | --- | --- | --- |"]
    for name, r in rows.items():
        c, o = r["calibrated"], r["oracle"]
        ci, oi = ideal["calibrated"], ideal["oracle"]
        lines.append(
            f"| {name} | {c['means_db']:.2f} ({ci['means_db'] - c['means_db']:+.2f}) | "
            f"{c['pixel_db']:.2f} ({ci['pixel_db'] - c['pixel_db']:+.2f}) | "
            f"{c['means_sam']:.2f} | {o['means_db']:.2f} ({oi['means_db'] - o['means_db']:+.2f}) "
            f"| {o['pixel_db']:.2f} ({oi['pixel_db'] - o['pixel_db']:+.2f}) |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--effects", nargs="*", default=None,
                    help=f"subset of {sorted(DOCUMENTED_EFFECTS)} (default: all, then together)")
    ap.add_argument("--noise-seeds", type=int, default=0,
                    help="also render the ideal device with this many other noise seeds: the "
                         "spread of their rows is the table's noise floor")
    ap.add_argument("--noise-free", action="store_true",
                    help="no shot/read noise, no quantisation: each effect's own cost, without "
                         "the noise realisations' spread")
    args = ap.parse_args(argv)
    names = args.effects if args.effects is not None else [*DOCUMENTED_EFFECTS, "all"]
    unknown = sorted(set(names) - set(DOCUMENTED_EFFECTS) - {"all"})
    if unknown:
        raise SystemExit(f"unknown effect(s) {unknown}; known: {sorted(DOCUMENTED_EFFECTS)}")
    args.out.mkdir(parents=True, exist_ok=True)
    every: dict = {}
    for keys in DOCUMENTED_EFFECTS.values():
        every.update(keys)
    nf = NO_NOISE if args.noise_free else ()
    rows = {"ideal": run_row(args.out / "ideal", {}, extra=nf)}
    for k in range(1, args.noise_seeds + 1):
        rows[f"ideal, noise seed {k}"] = run_row(args.out / f"ideal_seed{k}", {},
                                                 extra=(*nf, f"render.seed={1000 * k}"))
    for n in names:
        rows[n] = run_row(args.out / n, every if n == "all" else DOCUMENTED_EFFECTS[n],
                          extra=nf)
    md = table(rows)
    (args.out / "mismatch_small.json").write_text(json.dumps(rows, indent=1))
    (args.out / "mismatch_small.md").write_text(md + "\n")
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
