"""deepinv's generic ADMM with a TV prior beside our solvers, on a crop of a full-size capture.

    # the full-size CAVE capture with its ground truth (2896 × 2784 sensor; the monochromator
    # scan, grid and dark shots left out: the bundle is the oracle's)
    hsi-torch simulate --config simulate_full --out sim_full \\
        --set 'captures.scan_wavelengths_nm=[550]' --set captures.white_shots=1 \\
        --set captures.dark_frames=0 --set 'captures.grid.poses=[]' \\
        --set 'captures.scenes=[{kind: cave, name: cave, params: {folder: DATA/cave_stuffed_toys,
               width_mm: 7.0, center_mm: [0.0, 0.9]}}]'     # DATA: the real-data folder
    python scripts/deepinv_fullsize.py --captures sim_full --scene cave --crop 48 [--iters 25]

Needs deepinv (``pip install 'hsi-torch[deepinv]'``; beside a CPU torch its torchvision needs the
test suite's operator schemas, which this script declares the same way). The bundle is the
simulator's oracle (:func:`hsi_torch.simulate.oracle.bundle_from_truth`: true B, φ, g and
homographies, so that only the solvers differ), cut to a ``crop × crop`` window of the reference
frame centred on the scene (``--center`` to move it): the window's reference-bbox, per-pixel
arrays and valid mask, the homographies unchanged (they map sensor pixels to sensor pixels), so
the crop is reconstructed from the same full-size capture exactly as the whole frame would be,
without the pixels outside it. Three answers on that crop:

* ours, per pixel (:class:`~hsi_torch.recon.Reconstructor`, the default settings: β = 1e4);
* ours, TV mode (``prior="tv"``, its default weight; it reports the λ it used);
* deepinv's ``ADMM`` with :class:`~hsi_torch.recon.deepinv_physics.VectorialTVPrior` on
  :class:`~hsi_torch.recon.deepinv_physics.CameraPhysics` (the same λ and brightness weight K,
  no β‖Dx‖² term: the physics is the camera alone), ``--iters`` iterations started, as our TV
  mode is, from our per-pixel answer (``--start lsq``: from the clipped least-squares cube
  ``prox_l2(0, y, 1e3)``, the documented start for noise-free data, which on a noisy capture is
  orders of magnitude off), step ``4/ρ`` with the TV mode's penalty ρ, ``--inner`` dual
  iterations per TV prox (each prox starts from a zero dual: with few, the prox is inexact and
  ADMM drifts away from the optimum; 20 were too few on the full-size CAVE window).

Each is scored against the crop's true cube per pixel over the valid pixels on the scene (true
reflectance > 0 in some band)
(:func:`hsi_torch.experiments.metrics.cube_scores`: PSNR, mean SAM where the true mean reflectance
is ≥ 0.01) and on the TV problem's objective ``‖A x − y‖² + λ·TV(x)`` with the same ``y``
(:meth:`~hsi_torch.recon.camera.CameraOperator.objective`); wall and CPU times are printed (ours:
one frame after a warm-up; deepinv: its iterations alone). Torch runs one thread by default
(``--threads``): the per-pixel kernels are small, and on a shared machine several threads wait at
their barriers. Writes nothing.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import sys
import time
from pathlib import Path

import numpy as np
import torch


def _declare_torchvision_schemas() -> None:
    """deepinv imports torchvision; where its compiled extension does not load beside a CPU
    torch, declare the two operator schemas its import needs (as tests/conftest.py does)."""
    spec = importlib.util.find_spec("torchvision")
    if spec is None or "torchvision" in sys.modules or not spec.submodule_search_locations:
        return
    folder = Path(next(iter(spec.submodule_search_locations)))
    for ext in sorted(folder.glob("_C*.so")):
        try:
            torch.ops.load_library(str(ext))
        except (OSError, ImportError, RuntimeError):
            continue
    if not hasattr(torch.ops.torchvision, "nms"):
        lib = torch.library.Library("torchvision", "DEF")
        for name in ("nms", "qnms"):
            lib.define(f"{name}(Tensor dets, Tensor scores, float iou_threshold) -> Tensor")
        _KEEP.append(lib)


_KEEP: list = []


def crop_bundle(bundle, y0: int, x0: int, size: int):
    """The bundle cut to the reference-frame window ``[y0, y0+size) × [x0, x0+size)``."""
    sl = (slice(y0, y0 + size), slice(x0, x0 + size))
    bx, by = int(bundle.reference_bbox[0]), int(bundle.reference_bbox[1])
    return dataclasses.replace(
        bundle,
        reference_bbox=np.array([bx + x0, by + y0, size, size], np.int64),
        B=bundle.B[(..., *sl)], gain=bundle.gain[(..., *sl)],
        view_mask=bundle.view_mask[(..., *sl)], modulated=bundle.modulated[(..., *sl)],
        valid=bundle.valid[sl],
    )  # fmt: skip


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--captures", required=True, type=Path, help="simulated set with truth")
    ap.add_argument("--scene", default="cave")
    ap.add_argument("--crop", type=int, default=48, help="window side, px (0: the whole frame)")
    ap.add_argument(
        "--center",
        type=int,
        nargs=2,
        metavar=("ROW", "COL"),
        help="window centre (default: the centre of the scene's valid pixels)",
    )
    ap.add_argument("--iters", type=int, default=25, help="deepinv ADMM iterations")
    ap.add_argument(
        "--inner", type=int, default=200, help="dual iterations per TV prox (the prior's default)"
    )
    ap.add_argument("--start", choices=("perpixel", "lsq"), default="perpixel")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (0: torch's default)")
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    _declare_torchvision_schemas()
    from deepinv.optim import ADMM, L2

    from hsi_torch.experiments.metrics import cube_scores
    from hsi_torch.io import read_any
    from hsi_torch.io.capture_set import read_capture_set, read_truth
    from hsi_torch.recon import Reconstructor
    from hsi_torch.recon.deepinv_physics import L2_SIGMA, CameraPhysics, VectorialTVPrior
    from hsi_torch.recon.spatial import prepare_spatial
    from hsi_torch.simulate.oracle import bundle_from_truth

    truth, _ = read_truth(args.captures)
    full = bundle_from_truth(args.captures)
    on_scene = np.asarray(truth[f"scene_{args.scene}"]).max(0) > 0
    h, w = full.valid.shape
    if args.center is None:
        rows, cols = np.nonzero(on_scene & full.valid)
        cy, cx = int(np.median(rows)), int(np.median(cols))
    else:
        cy, cx = args.center
    if args.crop:  # a square window
        n = nx = args.crop
        y0, x0 = min(max(cy - n // 2, 0), h - n), min(max(cx - n // 2, 0), w - n)
        bundle = crop_bundle(full, y0, x0, n)
    else:  # the whole frame
        (y0, x0, n, nx), bundle = (0, 0, h, w), full
    true_cube = np.asarray(truth[f"scene_{args.scene}"], np.float64)[:, y0 : y0 + n, x0 : x0 + nx]
    mask = bundle.valid & on_scene[y0 : y0 + n, x0 : x0 + nx]
    cap_path = read_capture_set(args.captures).scenes[args.scene]
    print(f"{args.captures}: sensor {tuple(int(v) for v in full.sensor_size)}, reference frame "
          f"{h} × {w}, {int(full.valid.sum())} valid px; crop rows {y0}:{y0 + n}, cols "
          f"{x0}:{x0 + nx}: {int(bundle.valid.sum())} valid px, {int(mask.sum())} on the scene; "
          f"torch threads {torch.get_num_threads()}")  # fmt: skip

    rows: dict[str, dict] = {}
    cubes: dict[str, torch.Tensor] = {}
    rec = Reconstructor(bundle, dtype="float64", precompute_cache="off")
    for name, r in (("ours, per pixel", rec),
                    ("ours, TV mode", Reconstructor(rec.sensing, prior="tv"))):  # fmt: skip
        r.reconstruct_file(cap_path)  # warm-up (per-bundle factorisations)
        t0, c0 = time.perf_counter(), time.process_time()
        res = r.reconstruct_file(cap_path)
        rows[name] = {"seconds": time.perf_counter() - t0, "cpu_s": time.process_time() - c0,
                      "stats": res.stats}  # fmt: skip
        cubes[name] = torch.nan_to_num(res.cube.double())[None]
    spatial = rows["ours, TV mode"]["stats"]
    lam = float(spatial.get("lam_abs", spatial.get("spatial", {}).get("lam_abs")))
    alpha = float(spatial.get("brightness_weight", spatial.get("spatial", {}).get(
        "brightness_weight", 1.0)))  # fmt: skip
    scale = float(rows["ours, per pixel"]["stats"]["exposure_scale"])

    physics = CameraPhysics(bundle, dtype=torch.float64)
    cam = physics.camera
    cap = read_any(cap_path, expected_size=cam.sensing.sensor_size, dtype=torch.float64,
                   defaults=rec.capture_defaults())  # fmt: skip
    sat = None if cap.saturated is None else cap.saturated[None]
    y, ok = cam.observe(cap.image[None].double(), sat, exposure_scale=scale)
    lost = int((cam.mask() & ~ok).sum())  # observations the frame masks (saturated, ...)
    lsq = cam.prox_l2(torch.zeros(1, *physics.img_size, dtype=y.dtype), y, 1e3).clamp(0)
    x0 = cubes["ours, per pixel"] if args.start == "perpixel" else lsq
    t0, c0 = time.perf_counter(), time.process_time()
    rho = prepare_spatial(cam.gram(), cam.sensing.pixel_index, cam.frame_size).rho
    solver = ADMM(data_fidelity=L2(sigma=L2_SIGMA),
                  prior=VectorialTVPrior(cam.valid, brightness_weight=alpha,
                                         inner_iters=args.inner),
                  lambda_reg=lam, stepsize=4.0 / rho, max_iter=args.iters)  # fmt: skip
    with torch.no_grad():
        x = solver(y, physics, init=(x0, torch.zeros_like(x0))).clamp_min(0)
    name = f"deepinv ADMM + VectorialTVPrior, {args.iters} it."
    rows[name] = {"seconds": time.perf_counter() - t0, "cpu_s": time.process_time() - c0}
    cubes[name] = x
    cubes["clipped least squares (β = 0)"] = lsq
    rows["clipped least squares (β = 0)"] = {"seconds": float("nan"), "cpu_s": float("nan")}

    print(
        f"λ = {lam:.4g} (the TV mode's), K = {alpha}, exposure scale {scale:.4g}, ρ = {rho:.4g}, "
        f"{lost} observations masked by the frame (deepinv's data term keeps them at 0)"
    )
    print(f"deepinv started from: {args.start}; {args.inner} dual iterations per TV prox")
    print(f"{'method':<44} {'PSNR dB':>8} {'SAM °':>7} {'objective':>12} {'wall s':>8} "
          f"{'CPU s':>8}")  # fmt: skip
    out = {}
    for name, c in cubes.items():
        sc = cube_scores(c[0].numpy(), true_cube, mask)
        obj = float(cam.objective(c, y, mask=ok, lam=lam, brightness_weight=alpha))
        out[name] = {"psnr_db": sc["psnr_db"], "mean_sam_deg": sc["mean_sam_deg"],
                     "objective": obj, "seconds": rows[name]["seconds"],
                     "cpu_s": rows[name]["cpu_s"]}  # fmt: skip
        print(f"{name:<44} {sc['psnr_db']:8.2f} {sc['mean_sam_deg']:7.2f} {obj:12.5g} "
              f"{rows[name]['seconds']:8.2f} {rows[name]['cpu_s']:8.2f}")  # fmt: skip
    return out


if __name__ == "__main__":
    main(sys.argv[1:])
