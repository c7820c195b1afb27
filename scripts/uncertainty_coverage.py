#!/usr/bin/env python
"""Monte-Carlo check of the per-band standard deviation on a simulated prototype.

One scene of a simulated capture set (default: the ColorChecker) is rendered noise-free once by
the simulator, then read out ``--draws`` times by the simulated sensor with independent noise
(shot, read, quantisation, Bayer mosaic, black level, clipping), and each readout is
reconstructed with the capture set's oracle bundle and ``uncertainty=True``. Per band of every
valid pixel, the spread of the ``N`` answers around their own mean is compared with the predicted
standard deviation: the fraction of ``|ŝ − mean(ŝ)| ≤ kσ·sqrt((N−1)/N)`` for k = 1, 2 (ideal
68.3 % / 95.4 %; the factor accounts for the sample mean),
over the bands that are free (``> 0``) in every realisation, and the median ratio of empirical to
predicted standard deviation. For comparison it also reports the standard deviation computed as
if the demosaiced RGB samples were independent raw samples (``raw_layout="rgb"``), i.e. without
the demosaic's correlations, and times one frame with and without the uncertainty (interleaved,
same process: min / median of the stage timings and the ratio of the frame times).

Usage::

    python scripts/uncertainty_coverage.py --captures CAPTURE_SET_DIR [--draws 100]
        [--scene colorchecker] [--beta 1e4] [--dtype float32]

``CAPTURE_SET_DIR`` is the output of ``hsi-torch simulate`` (its ``resolved_config.yaml`` rebuilds
the renderer; its ground truth gives the oracle bundle).
"""

from __future__ import annotations

import argparse
import math
import resource
import statistics
import time
from pathlib import Path

import torch

from hsi_torch.config import load_config
from hsi_torch.io.raw import demosaic_bilinear, demosaic_saturation
from hsi_torch.recon.pipeline import Reconstructor
from hsi_torch.recon.uncertainty import SensorNoise
from hsi_torch.simulate.capture_sets import build_renderer, plan_captures
from hsi_torch.simulate.config import SimulateConfig
from hsi_torch.simulate.oracle import bundle_from_truth


def coverage(c: torch.Tensor, sd: torch.Tensor) -> dict[str, float]:
    """``c, sd (N, M, P)``: coverage of ±1σ/±2σ and empirical/predicted spread on the bands
    free in every realisation."""
    free = (c > 0).all(0)
    n = c.shape[0]  # spread around the sample mean of n draws: sqrt((n-1)/n) of the true one
    z = ((c - c.mean(0)).abs() / (sd * math.sqrt((n - 1) / n)))[:, free]
    ratio = c.std(0)[free] / sd.mean(0)[free]  # c.std: unbiased (n - 1)
    return {
        "free_fraction": float(free.double().mean()),
        "cover1": float((z <= 1).double().mean()),
        "cover2": float((z <= 2).double().mean()),
        "ratio_median": float(ratio.median()),
        "ratio_p05": float(ratio.quantile(0.05)),
        "ratio_p95": float(ratio.quantile(0.95)),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--captures", required=True, type=Path)
    ap.add_argument("--scene", default="colorchecker")
    ap.add_argument("--draws", type=int, default=100)
    ap.add_argument("--beta", type=float, default=1e4)
    ap.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    ap.add_argument("--bench-reps", type=int, default=15,
                    help="frames timed with and without the uncertainty (interleaved)")
    args = ap.parse_args()
    dtype = torch.float64 if args.dtype == "float64" else torch.float32

    t0 = time.perf_counter()
    cfg = load_config(args.captures / "resolved_config.yaml", SimulateConfig)
    cfg.captures.scan_wavelengths_nm = []
    cfg.captures.white_shots = 0
    cfg.captures.grid.poses = []
    cfg.captures.scenes = [s for s in cfg.captures.scenes if s.name == args.scene]
    if not cfg.captures.scenes:
        raise SystemExit(f"no scene named {args.scene!r} in {args.captures}")
    renderer = build_renderer(cfg, "cpu")
    specs, planned, _ = plan_captures(cfg, renderer, log=lambda *a, **k: None)
    (pc,) = [p for p in planned if p.type == "scene"][:1]
    irr = renderer.render(specs)[pc.render_key]
    exposure = renderer.exposure_of(pc.spec)
    t_render = time.perf_counter() - t0

    sensor = renderer.sensor
    noise = SensorNoise(sensor.gain_e_per_dn, sensor.read_noise_e,
                        1.0 if sensor.quantize else 0.0)  # fmt: skip
    bundle = bundle_from_truth(args.captures)
    rec = Reconstructor(bundle, beta=args.beta, dtype=dtype, uncertainty=True,
                        noise_electrons_per_dn=noise.electrons_per_dn,
                        noise_read_e=noise.read_noise_e,
                        noise_quantization_dn=noise.quantization_dn)
    pattern = sensor.cfa_pattern
    cubes, stds, stds_rgb = [], [], []
    t0 = time.perf_counter()
    t_solve = t_unc = 0.0
    for k in range(args.draws):
        dn, sat = renderer.expose(irr, exposure, 10_000 + k)
        lin = (dn - sensor.black_level).to(dtype)
        res = rec.reconstruct_frame(lin, sat, cfa_pattern=pattern)
        t_solve += res.timings["solve"]
        t_unc += res.timings["uncertainty"]
        valid = res.valid
        cubes.append(res.cube[:, valid].double())
        stds.append(res.std[:, valid].double())
        # the same frame, its demosaiced RGB taken as independent samples (no correlations)
        rgb = demosaic_bilinear(lin, pattern)
        r2 = rec.reconstruct_frame(rgb, demosaic_saturation(sat, pattern), raw_layout="rgb")
        stds_rgb.append(r2.std[:, valid].double())
    t_all = time.perf_counter() - t0
    # cost: the same frame with and without the uncertainty, interleaved, in this process
    plain = Reconstructor(bundle, beta=args.beta, dtype=dtype)
    dn, sat = renderer.expose(irr, exposure, 10_000)
    lin = (dn - sensor.black_level).to(dtype)
    runs: dict[bool, list[dict[str, float]]] = {False: [], True: []}
    for _ in range(args.bench_reps):
        for u, r in ((False, plain), (True, rec)):
            runs[u].append(r.reconstruct_frame(lin, sat, cfa_pattern=pattern).timings)
    c = torch.stack(cubes)
    full = coverage(c, torch.stack(stds))
    naive = coverage(c, torch.stack(stds_rgb))
    P = int(c.shape[2])
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"scene {args.scene}: {P} valid pixels x {c.shape[1]} bands, {args.draws} noise draws, "
          f"beta {args.beta:g}, {args.dtype}; render {t_render:.1f} s, draws {t_all:.1f} s")
    print(f"per frame: solve {t_solve / args.draws * 1e3:.1f} ms, uncertainty "
          f"{t_unc / args.draws * 1e3:.1f} ms (ratio {t_unc / max(t_solve, 1e-12):.2f}); "
          f"peak RSS {peak:.0f} MiB")
    for u in (False, True):
        keys = ("solve", "uncertainty", "total") if u else ("solve", "total")
        txt = ", ".join(f"{k} {1e3 * min(t[k] for t in runs[u]):.1f} / "
                        f"{1e3 * statistics.median(t[k] for t in runs[u]):.1f}" for k in keys)
        print(f"{'uncertainty=True ' if u else 'uncertainty=False'} ms (min / median of "
              f"{args.bench_reps}): {txt}")
    tot = [statistics.median(t["total"] for t in runs[u]) for u in (False, True)]
    print(f"frame time with / without the uncertainty (medians): {tot[1] / tot[0]:.2f}")
    for name, r in (("bayer sampling factor", full), ("demosaic ignored (rgb)", naive)):
        print(f"  {name:24s} free {100 * r['free_fraction']:.1f} %  within 1 sigma "
              f"{100 * r['cover1']:.1f} % (68.3)  within 2 sigma {100 * r['cover2']:.1f} % (95.4)"
              f"  empirical/predicted std median {r['ratio_median']:.3f} "
              f"[p5 {r['ratio_p05']:.3f}, p95 {r['ratio_p95']:.3f}]")


if __name__ == "__main__":
    main()
