"""Time the spatial-spectral (TV) reconstruction against the per-pixel solve of the same frames.

    python scripts/bench_spatial.py --bundle calib.npz CAPTURE.tif [CAPTURE.tif ...] [--lam 0.3]

Both reconstructors share the bundle's precomputation; each frame is reconstructed once to warm
up, then ``--repeats`` times per method, alternating, in this process. Prints per frame the
median solve-stage time of each method (the per-pixel NNLS is part of the TV solve: it is the
warm start), their ratio, the ADMM iterations, and the peak resident memory of the process.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch

from hsi_torch.profiling import peak_rss_gib
from hsi_torch.recon import Reconstructor
from hsi_torch.recon.spatial import DEFAULT_LAM


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("captures", nargs="+", type=Path)
    ap.add_argument("--bundle", required=True, type=Path)
    ap.add_argument("--beta", type=float, default=1e4)
    ap.add_argument("--lam", default=str(DEFAULT_LAM), help="relative TV weight, or auto")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--spectral-rank", type=int, default=None,
                    help="the TV on this many leading spectral components (default: all bands)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    args = ap.parse_args()
    lam: float | str = args.lam if args.lam in ("auto", "discrepancy") else float(args.lam)
    dt = {"float32": torch.float32, "float64": torch.float64}[args.dtype]
    t0 = time.perf_counter()
    pp = Reconstructor(args.bundle, beta=args.beta, device=args.device, dtype=dt)
    tv = Reconstructor(pp.sensing, prior="tv", lam=lam, spectral_rank=args.spectral_rank)
    print(f"precomputation {time.perf_counter() - t0:.1f} s; {pp.sensing.num_pixels} pixels, "
          f"{pp.sensing.num_bands} bands, frame {pp.sensing.frame_size}")
    print("capture | per-pixel solve s | TV solve s | ratio | ADMM iterations | lam")
    for cap in args.captures:
        pp.reconstruct_file(cap)  # warm-up: sampling grid, caches
        tv.reconstruct_file(cap)  # warm-up: the factorisation of G + rho I
        t_pp, t_tv, its = [], [], 0
        for _ in range(max(1, args.repeats)):
            t_pp.append(pp.reconstruct_file(cap).timings["solve"])
            r = tv.reconstruct_file(cap)
            t_tv.append(r.timings["solve"])
            its = r.stats["spatial_iterations"]
        a, b = statistics.median(t_pp), statistics.median(t_tv)
        print(f"{cap.name} | {a:.3f} | {b:.3f} | {b / a:.1f}x | {its} | {r.stats['lam']:.3g}")
    print(f"peak RSS {peak_rss_gib():.2f} GiB")


if __name__ == "__main__":
    main()
