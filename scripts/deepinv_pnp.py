"""A deepinv plug-and-play prior on a capture: HQS with a grey-image denoiser run on every band.

    python scripts/deepinv_pnp.py --bundle calib/calib.npz --capture shots/scene.tif \\
        --weights drunet_gray.pth --out pnp.npz [--truth truth_cube.npz] [--iters 8]

Needs deepinv (``pip install 'hsi-torch[deepinv]'``). The denoiser is deepinv's DRUNet with one
input channel, its weights read from the local file ``--weights`` (a ``state_dict`` saved with
``torch.save``; e.g. deepinv's published grey-image DRUNet weights, downloaded once by you):
nothing is downloaded at run time. The solver is deepinv's HQS on
:class:`~hsi_torch.recon.deepinv_physics.CameraPhysics`: the data step is the exact per-pixel
proximal step of ``‖A x − y‖²`` (``prox_l2``), the prior step the denoiser on every band
(:class:`~hsi_torch.recon.deepinv_physics.BandwiseDenoiser`), with the denoiser's σ decreasing
geometrically from ``--sigma-start`` to ``--sigma-end`` (reflectance units). The start is the
clipped per-pixel least-squares cube. Writes the cube (NPZ, same keys as the pipeline's) and,
with ``--truth`` (an NPZ or cube file of the same size), prints the metrics of
:mod:`hsi_torch.metrics` of the start and of the answer. An existing ``--out`` is refused before
any work unless this script wrote it (its key ``written_by``); the file is written atomically.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

#: Stored in the output ``.npz`` (key ``written_by``): a file holding it may be written over.
WRITTEN_BY = "scripts/deepinv_pnp.py"


def _check_out(out: Path) -> None:
    """Refuse an ``--out`` that exists and is not an earlier output of this script (an ``.npz``
    whose ``written_by`` is :data:`WRITTEN_BY`), before any work: it may be the user's cube."""
    if not out.exists():
        return
    try:
        with np.load(out, allow_pickle=False) as z:
            ours = "written_by" in z.files and str(z["written_by"]) == WRITTEN_BY
    except (OSError, ValueError, EOFError):
        ours = False
    if not ours:
        raise SystemExit(f"deepinv_pnp.py: error: --out {out} exists and was not written by "
                         "this script (it may be your own data): choose a new file name")


def run(argv: list[str] | None = None) -> dict:
    """The script's work; returns ``{"cube", "valid", "start", "metrics"}`` (numpy / dicts)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bundle", required=True, type=Path)
    ap.add_argument("--capture", required=True, type=Path)
    ap.add_argument("--weights", required=True, type=Path,
                    help="local DRUNet weights (in_channels=1), torch.save'd state_dict")
    ap.add_argument("--out", required=True, type=Path, help="output .npz")
    ap.add_argument("--truth", type=Path, help="true cube (.npz / cube file) to score against")
    ap.add_argument("--iters", type=int, default=8)
    ap.add_argument("--sigma-start", type=float, default=0.05)
    ap.add_argument("--sigma-end", type=float, default=0.01)
    ap.add_argument("--data-weight", type=float, default=4.0,
                    help="HQS step γ in units of 1/ρ (ρ: the TV mode's penalty)")
    ap.add_argument("--drunet-channels", type=int, nargs=4, default=(64, 128, 256, 512),
                    help="DRUNet widths of the weights file (deepinv's default)")
    ap.add_argument("--drunet-blocks", type=int, default=4)
    args = ap.parse_args(argv)
    _check_out(args.out)

    from deepinv.models import DRUNet
    from deepinv.optim import HQS, L2, PnP

    from hsi_torch.io import read_any
    from hsi_torch.metrics import cube_metrics
    from hsi_torch.recon.deepinv_physics import L2_SIGMA, BandwiseDenoiser, CameraPhysics

    if not args.weights.is_file():
        raise FileNotFoundError(f"--weights {args.weights}: no such file (nothing is downloaded)")
    physics = CameraPhysics(args.bundle, dtype=torch.float32)
    cam = physics.camera
    cap = read_any(args.capture, expected_size=cam.sensing.sensor_size)
    y, _ = cam.observe(cap.image[None].float())
    x0 = cam.prox_l2(torch.zeros(1, *physics.img_size), y, 1e3).clamp(0, 1)
    G = cam.gram()
    rho = 0.1 * float(G.diagonal(dim1=-2, dim2=-1).sum(-1).median()) / G.shape[-1]
    net = DRUNet(1, 1, nc=tuple(args.drunet_channels), nb=args.drunet_blocks,
                 pretrained=str(args.weights)).eval()  # fmt: skip
    prior = PnP(denoiser=BandwiseDenoiser(net, valid=cam.valid))
    k = max(args.iters - 1, 1)
    sigmas = [args.sigma_start * (args.sigma_end / args.sigma_start) ** (i / k)
              for i in range(args.iters)]  # fmt: skip
    solver = HQS(data_fidelity=L2(sigma=L2_SIGMA), prior=prior, max_iter=args.iters,
                 params_algo={"stepsize": [args.data_weight / rho] * args.iters,
                              "g_param": sigmas, "lambda": [1.0] * args.iters})  # fmt: skip
    with torch.no_grad():
        x = solver(y, physics, init=x0).clamp_min(0)
    valid = cam.valid.cpu().numpy()
    cube = np.where(valid, x[0].cpu().numpy(), np.nan).astype(np.float32)
    out = {"cube": cube, "valid": valid, "start": x0[0].cpu().numpy(), "metrics": {}}
    if args.truth is not None:
        if args.truth.suffix == ".npz":
            with np.load(args.truth) as z:
                truth = np.asarray(z["cube"], np.float64)
        else:
            from hsi_torch.io.cube import load_cube

            truth = load_cube(args.truth).cube.double().numpy()
        for name, c in (("start (least squares, clipped)", out["start"]), ("PnP", cube)):
            m = cube_metrics(torch.from_numpy(np.asarray(c, np.float64)),
                             torch.from_numpy(truth), torch.from_numpy(valid))  # fmt: skip
            out["metrics"][name] = m
            print(f"{name}: " + ", ".join(f"{k} {v:.4g}" for k, v in m.items()))
    from hsi_torch.io.atomic import atomic_save_npz

    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_save_npz(args.out, {"cube": cube, "valid": valid, "written_by": WRITTEN_BY,
                               "wavelengths_nm": cam.wavelengths_nm.cpu().numpy()},
                    compressed=True)  # fmt: skip
    print(f"wrote {args.out}")
    return out


if __name__ == "__main__":
    run(sys.argv[1:])
