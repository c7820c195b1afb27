#!/usr/bin/env python
"""Error budget at full size: how many dB each cause costs the ColorChecker and CAVE scores.

The full-size prototype (``simulate_full.yaml``) films the ColorChecker and the real CAVE scene
four times, switching the causes on one by one, and every capture is reconstructed and scored
against the truth; each cause's cost is the score difference of consecutive rows:

1. **ideal observations**: ``y = A s_true`` in the reference frame (the oracle bundle's forward
   model applied to the true spectra at every valid pixel): no rendering, no warp, no demosaic,
   no noise. What is left is the smoothness prior's bias (and the 10 nm discretisation).
2. the same with ``β`` 1000× smaller: the **smoothness bias** is row 2 − row 1 (negative when
   the prior costs dB on noise-free data).
3. **rendered, RGB sensor, no noise** (three full colour planes, no shot/read noise, no
   quantisation), reconstructed through the pipeline with the oracle bundle: row 1 − row 3 is what
   **rendering, sampling and warping** cost (each view sees the scene at its own sub-pixel phase
   through the diffuser blur; the 2 nm rendering against the 10 nm model).
4. **Bayer sensor, no noise**: row 3 − row 4 is the **demosaicing** cost.
5. **Bayer with shot and read noise** (the simulator's defaults): row 4 − row 5 is the
   **noise** cost.
6. the same captures with the **calibrated** bundle (calibrated from a full capture set):
   row 5 − row 6 is what **calibration** costs.

Scores (reflectance, peak 1): ColorChecker per pixel over the patch interiors (≥ 0.3 mm inside) and
the patch-interior means; CAVE per pixel over the valid pixels on the scene and on its brighter
half. PSNR = 10·log10(1/MSE), spectral angle in degrees.

Usage::

    python scripts/error_budget.py --out /tmp/budget                  # ~6 min on 2 cores
    python scripts/error_budget.py --out /tmp/budget --calibrated DEMO_FULL/calib/calib.npz

Without ``--calibrated`` a full calibration capture set is simulated and calibrated first.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from hsi_torch.experiments.metrics import colorchecker_scores, cube_scores, erode_px, interior_mask
from hsi_torch.io.capture_set import read_truth
from hsi_torch.io.paths import claim_out_dir
from hsi_torch.profiling import run_child
from hsi_torch.recon.frame import assemble_cube
from hsi_torch.recon.pipeline import DEFAULT_BETA, Reconstructor
from hsi_torch.resources import real_data_dir, shipped_config
from hsi_torch.simulate.oracle import bundle_from_truth

NO_NOISE = ["sensor.shot_noise=false", "sensor.read_noise_e=0", "sensor.quantize=false"]


def _simulate(out: Path, scenes: list[dict], overrides: list[str], minimal: bool) -> Path:
    if (out / "manifest.json").is_file():
        print(f"  reusing {out}")
        return out
    cmd = [sys.executable, "-m", "hsi_torch", "-q", "simulate", "--config",
           str(shipped_config("simulate_full")), "--out", str(out),
           "--set", f"captures.scenes={json.dumps(scenes)}", "--set", "render.figures=false"]
    if minimal:
        cmd += ["--set", "captures.scan_wavelengths_nm=[550]", "--set", "captures.white_shots=0",
                "--set", "captures.grid.poses=[]", "--set", "captures.dark_frames=0"]
    for o in overrides:
        cmd += ["--set", o]
    run = run_child(cmd)
    if run.returncode != 0:
        raise SystemExit(f"simulation into {out} failed (exit {run.returncode})")
    print(f"  simulated {out.name}: {run.wall_s:.0f} s, peak {run.peak_rss_gib:.2f} GiB")
    return out


def _scores(cubes: dict[str, np.ndarray], valid: np.ndarray, truth: dict, scenes) -> dict:
    out = {}
    for name, cube in cubes.items():
        true_cube = np.asarray(truth[f"scene_{name}"], np.float64)
        if name == "colorchecker":
            pidx = truth[f"{name}_patch_index"]
            spectra = np.asarray(truth[f"{name}_spectra"], np.float64)
            e = erode_px(truth, 0.3)  # 0.3 mm: 3 sigma of the diffuser blur
            inner = valid & (pidx >= 0) & np.logical_or.reduce(
                [interior_mask(pidx == k, e) for k in range(len(spectra))])
            px = cube_scores(cube, true_cube, inner)
            means = colorchecker_scores(cube, valid, pidx, spectra, e)
            out[name] = {"per_pixel_db": px["psnr_db"], "per_pixel_sam": px["mean_sam_deg"],
                         "means_db": means["mean_psnr_db"], "means_sam": means["mean_sam_deg"]}
        else:
            xy = truth["diffuser_xy"]
            spec = next(s for s in scenes if s["name"] == name)
            half = spec["params"]["width_mm"] / 2
            cx, cy = spec["params"]["center_mm"]
            on = valid & (np.abs(xy[..., 0] - cx) <= half) & (np.abs(xy[..., 1] - cy) <= half)
            px = cube_scores(cube, true_cube, on)
            b = px["bright_half"]
            out[name] = {"per_pixel_db": px["psnr_db"], "median_sam": px["median_sam_deg"],
                         "bright_db": b["psnr_db"], "bright_median_sam": b["median_sam_deg"]}
    return out


def _reconstruct(bundle, cap_dir: Path, names: list[str], beta: float) -> tuple[dict, np.ndarray]:
    rec = Reconstructor(bundle, beta=beta)
    cubes, valid = {}, None
    for n in names:
        r = rec.reconstruct_file(cap_dir / "scenes" / f"{n}.tif")
        cubes[n] = r.cube.double().numpy()
        v = r.valid.numpy()
        valid = v if valid is None else valid & v
    return cubes, valid


def _ideal(bundle, truth: dict, names: list[str], beta: float) -> tuple[dict, np.ndarray]:
    """Observations from the forward model at every valid pixel, solved without the pipeline."""
    rec = Reconstructor(bundle, beta=beta, dtype=torch.float64)
    sens = rec.sensing
    cubes = {}
    for n in names:
        s = torch.as_tensor(truth[f"scene_{n}"], dtype=torch.float64).reshape(sens.num_bands, -1)
        s = s[:, sens.pixel_index].T.contiguous()
        y = sens.model.A(s) * sens.obs_mask
        res = sens.problem.solve(y)
        ok = torch.ones(sens.num_pixels, dtype=torch.bool)
        cube, valid = assemble_cube(sens, res.x[None], ok[None])
        cubes[n] = cube[0].numpy()
    return cubes, valid[0].numpy()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True,
                    help="work folder (simulated sets are reused): new, empty or this script's own")
    ap.add_argument("--calibrated", default=None, help="a calibrated full-size bundle")
    ap.add_argument("--beta", type=float, default=DEFAULT_BETA)
    args = ap.parse_args(argv)
    out = claim_out_dir(args.out, ".hsi_torch_error_budget", "run of error_budget.py",
                        "it writes simulated capture sets (rgb_clean/, bayer_clean/, "
                        "bayer_noisy/), calib/ and error_budget.json", script="error_budget.py",
                        earlier_names=("error_budget.json",))
    t0 = time.perf_counter()
    cave = real_data_dir("cave_stuffed_toys")
    scenes = [{"kind": "colorchecker", "name": "colorchecker",
               "params": {"width_mm": 8.4, "center_mm": [0.0, 1.4]}}]
    if cave is not None and cave.is_dir():
        scenes.append({"kind": "cave", "name": "cave",
                       "params": {"folder": str(cave), "width_mm": 7.0, "center_mm": [0.0, 0.9]}})
    else:
        print("no real CAVE scene (HSI_TORCH_DATA): ColorChecker only")
    names = [s["name"] for s in scenes]
    print("simulating the full-size captures ...")
    rgb = _simulate(out / "rgb_clean", scenes, ["sensor.output=rgb", *NO_NOISE], True)
    bayer = _simulate(out / "bayer_clean", scenes, NO_NOISE, True)
    noisy = _simulate(out / "bayer_noisy", scenes, [], args.calibrated is None)
    calibrated = args.calibrated
    if calibrated is None:
        calibrated = out / "calib" / "calib.npz"
        if not calibrated.is_file():
            run = run_child([sys.executable, "-m", "hsi_torch", "-q", "calibrate", "--captures",
                             str(noisy), "--out", str(calibrated.parent), "--no-progress"])
            if run.returncode != 0:
                raise SystemExit("calibration failed")
    truth, _ = read_truth(noisy)
    oracle = bundle_from_truth(noisy)
    rows = []

    def row(label: str, cubes, valid) -> None:
        sc = _scores(cubes, valid, truth, scenes)
        rows.append((label, sc))
        print(f"  {label}: " + json.dumps(sc, default=lambda v: round(v, 3)))

    print("reconstructing and scoring ...")
    row("1 ideal observations (A s_true), beta", *_ideal(oracle, truth, names, args.beta))
    row("2 ideal observations, beta/1000", *_ideal(oracle, truth, names, args.beta / 1000))
    row("3 rendered RGB sensor, no noise", *_reconstruct(oracle, rgb, names, args.beta))
    row("4 Bayer sensor, no noise", *_reconstruct(oracle, bayer, names, args.beta))
    row("5 Bayer, shot + read noise (oracle bundle)", *_reconstruct(oracle, noisy, names,
                                                                      args.beta))
    row("6 the same with the calibrated bundle", *_reconstruct(str(calibrated), noisy, names,
                                                                args.beta))
    causes = [("smoothness bias (2 - 1)", 1, 0), ("rendering, sampling and warping (1 - 3)", 0, 2),
              ("demosaicing (3 - 4)", 2, 3), ("photon and read noise (4 - 5)", 3, 4),
              ("calibration (5 - 6)", 4, 5)]
    key = {"colorchecker": ["per_pixel_db", "means_db"], "cave": ["per_pixel_db", "bright_db"]}
    print(f"\nscores (dB), beta = {args.beta:g}:")
    for label, sc in rows:
        print(f"  {label:<46}" + "".join(f"{sc[n][k]:>10.2f}" for n in names for k in key[n]))
    print("cost of each cause (dB; columns as above: " + ", ".join(
        f"{n} {k}" for n in names for k in key[n]) + "):")
    for label, a, b in causes:
        print(f"  {label:<46}" + "".join(
            f"{rows[a][1][n][k] - rows[b][1][n][k]:>10.2f}" for n in names for k in key[n]))
    (out / "error_budget.json").write_text(json.dumps({"beta": args.beta, "rows": rows},
                                                       indent=1, default=float))
    print(f"({time.perf_counter() - t0:.0f} s; {out / 'error_budget.json'})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
