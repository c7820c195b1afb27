#!/usr/bin/env python
"""Benchmark: batched NNLS (hsi_torch) vs a per-pixel ``scipy.optimize.nnls`` loop, in one run.

A frame of the original prototype: 324 000 pixels, 30 observations (10 views × RGB), 25 bands,
per-pixel sensing matrices with BRF-like cosine transmittances (``synthetic_brf_problem``), ~10 %
masked observations, ``beta = 1e2`` on a DN scale (y ≈ 0…255), two kinds of spectra:

* ``reflectance`` (realistic): mixtures of ColorChecker reflectances under D65, positive in every
  band; only dark, noisy pixels need the active-set correction;
* ``bumps`` (hard case): Gaussian bumps on a small floor; many bands near 0, so ~30 % of the
  pixels need the correction.

For each it reports

* cold time: ``solve_nnls`` (factorisation included, chunked),
* per-frame time: ``NNLSProblem.solve`` with the factorisations reused (several noisy frames),
* the SciPy loop on a random subset of pixels (stacked system ``[A_p[mask]; √β D]``), scaled to
  the frame; the ratios; the max deviation between the two answers on the subset,
* the fraction of pixels corrected by the active set, pivot rounds, the solver's own KKT
  residual and an independent float64 KKT check of the whole frame from ``(A, y, mask)``,
* peak memory (``ru_maxrss``; on CUDA also ``torch.cuda.max_memory_allocated``).

Usage::

    python scripts/bench_solver.py                      # full frame, float32, cpu, both spectra
    python scripts/bench_solver.py --spectra reflectance --pixels 20000 --dtype float64
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch
from scipy.optimize import nnls

from hsi_torch.recon.nnls import prepare_nnls, solve_nnls
from hsi_torch.spectral import difference_matrix

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # the tests' problems
from synthetic_data import synthetic_brf_problem  # noqa: E402


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux


def independent_kkt(A: torch.Tensor, y: torch.Tensor, mask: torch.Tensor, x: torch.Tensor,
                    beta: float, diff_order: int, chunk: int = 32768) -> torch.Tensor:
    """Per-pixel KKT violation in float64 from ``(A, y, mask)`` (as in tests/test_solvers.py).

    ``max(‖x⁻‖·max G_mm, max_{x=0} g⁻, max |min(G_mm x_m, g_m)|) / (‖AᵀWy‖∞ + ‖diag(G) x‖∞)``
    with ``g = AᵀW(Ax − y) + β DᵀD x``.
    """
    M = x.shape[1]
    D = difference_matrix(M, diff_order, dtype=torch.float64, device=x.device)
    R = beta * (D.T @ D)
    out = []
    for s in range(0, x.shape[0], chunk):
        a = A[s:s + chunk].double()
        w = mask[s:s + chunk].double()
        yy = torch.where(mask[s:s + chunk], y[s:s + chunk], torch.zeros_like(y[s:s + chunk]))
        yy = yy.double()
        xx = x[s:s + chunk].double()
        r = torch.einsum("pom,pm->po", a, xx) - yy
        g = torch.einsum("pom,po->pm", a, w * r) + xx @ R
        gd = torch.einsum("pom,po->pm", a * a, w) + torch.diagonal(R)
        b = torch.einsum("pom,po->pm", a, w * yy)
        scale = (b.abs().amax(1) + (gd * xx).abs().amax(1)).clamp_min(1e-300)
        neg_x = (-xx).clamp_min(0).amax(1) * gd.amax(1)
        neg_g = torch.where(xx <= 0, (-g).clamp_min(0), torch.zeros_like(g)).amax(1)
        comp = torch.minimum(gd * xx, g).abs().amax(1)
        out.append(torch.stack([neg_x, neg_g, comp]).amax(0) / scale)
    return torch.cat(out)


def run_case(args: argparse.Namespace, spectra: str, device: torch.device,
             dtype: torch.dtype) -> dict[str, float]:
    P, V = args.pixels, args.views
    t0 = time.perf_counter()
    A, y, mask, _ = synthetic_brf_problem(
        P, num_views=V, mask_fraction=args.mask_fraction, noise_dn=args.noise_dn,
        spectra=spectra, seed=args.seed, dtype=dtype, device=device)
    O, M = A.shape[-2:]
    print(f"\n=== spectra={spectra}: P={P} O={O} M={M} beta={args.beta:g} "
          f"masked={1 - mask.float().mean():.3f} y in [{float(y.min()):.1f}, "
          f"{float(y.max()):.1f}] DN (generated in {time.perf_counter() - t0:.1f} s)")
    kw = dict(num_threads=args.threads)

    # --- ours, cold (factorisation included) -------------------------------------------------
    _sync(device)
    t0 = time.perf_counter()
    res = solve_nnls(A, y, beta=args.beta, mask=mask, diff_order=args.diff_order,
                     chunk_size=args.chunk_size, **kw)
    _sync(device)
    t_cold = time.perf_counter() - t0

    # --- ours, per frame (factorisations reused) ---------------------------------------------
    t0 = time.perf_counter()
    prob = prepare_nnls(A, mask=mask, beta=args.beta, diff_order=args.diff_order,
                        chunk_size=args.chunk_size, **kw)
    _sync(device)
    t_prep = time.perf_counter() - t0
    gen = torch.Generator(device="cpu").manual_seed(args.seed + 1)
    times = []
    frame_res = None
    for f in range(args.frames):
        yf = y if f == 0 else y + args.noise_dn * torch.randn(
            y.shape, generator=gen, dtype=torch.float64).to(device=device, dtype=dtype)
        _sync(device)
        t0 = time.perf_counter()
        r = prob.solve(yf, chunk_size=args.chunk_size, **kw)
        _sync(device)
        times.append(time.perf_counter() - t0)
        if f == 0:
            frame_res = r
    t_frame = statistics.median(times)
    assert frame_res is not None
    same = float((frame_res.x - res.x).abs().max())

    # --- SciPy loop on a subset ---------------------------------------------------------------
    rng = np.random.default_rng(args.seed)
    n_sub = min(args.subset, P)
    idx = np.sort(rng.choice(P, size=n_sub, replace=False))
    tidx = torch.as_tensor(idx, device=device)
    A_np = A[tidx].double().cpu().numpy()
    y_np = y[tidx].double().cpu().numpy()
    m_np = mask[tidx].cpu().numpy()
    D = difference_matrix(M, args.diff_order, dtype=torch.float64).numpy()
    sD = np.sqrt(args.beta) * D
    zeros = np.zeros(D.shape[0])
    x_sp = np.zeros((n_sub, M))
    t_nnls = 0.0
    t0 = time.perf_counter()
    for i in range(n_sub):
        a = np.vstack([A_np[i][m_np[i]], sD])
        b = np.concatenate([y_np[i][m_np[i]], zeros])
        t1 = time.perf_counter()
        x_sp[i] = nnls(a, b)[0]
        t_nnls += time.perf_counter() - t1
    t_loop_sub = time.perf_counter() - t0
    t_loop = t_loop_sub * P / n_sub
    t_loop_nnls = t_nnls * P / n_sub

    x_ours = frame_res.x[tidx].double().cpu().numpy()
    dev_abs = float(np.abs(x_ours - x_sp).max())
    rel = np.linalg.norm(x_ours - x_sp, axis=1) / np.maximum(np.linalg.norm(x_sp, axis=1), 1e-30)
    kkt = independent_kkt(A, y, mask, frame_res.x, args.beta, args.diff_order)
    corrected = float((frame_res.iterations > 0).double().mean())

    print(f"ours cold  (prepare + solve, chunked): {t_cold:8.3f} s")
    print(f"ours prepare only (factorise, stored): {t_prep:8.3f} s")
    print(f"ours per frame (factorisations reused): {t_frame:8.3f} s  "
          f"(median of {args.frames}; min {min(times):.3f} s, max {max(times):.3f} s)")
    print(f"scipy nnls loop, scaled from {n_sub} px: {t_loop:8.3f} s "
          f"({1e6 * t_loop_sub / n_sub:.1f} µs/px incl. stacking; nnls calls alone "
          f"{t_loop_nnls:.3f} s, {1e6 * t_nnls / n_sub:.1f} µs/px)")
    print(f"ratio loop / per-frame: {t_loop / t_frame:7.1f}x   "
          f"(best frame {t_loop / min(times):.1f}x; nnls calls only: {t_loop_nnls / t_frame:.1f}x)")
    print(f"ratio loop / cold     : {t_loop / t_cold:7.1f}x   "
          f"(nnls calls only: {t_loop_nnls / t_cold:.1f}x)")
    print(f"pixels corrected by the active set: {corrected:.3f}, max rounds "
          f"{int(frame_res.iterations.max())}, converged {frame_res.converged.float().mean():.5f}, "
          f"solver KKT residual max {float(frame_res.kkt_residual.max()):.2e} (backward error), "
          f"independent float64 KKT check max {float(kkt.max()):.2e}, "
          f"no-data {int(frame_res.no_data.sum())}")
    print(f"max |x_ours - x_scipy| on subset: {dev_abs:.3e} (x max {np.abs(x_sp).max():.3f}); "
          f"per-pixel relative L2: max {rel.max():.3e}, median {np.median(rel):.3e}")
    print(f"cold vs per-frame answers: max |diff| {same:.3e}")
    print(f"peak RSS so far: {_rss_mib():.0f} MiB (the prepared problem stores 2·P·M² floats = "
          f"{2 * P * M * M * A.element_size() / 2**20:.0f} MiB; A is "
          f"{A.numel() * A.element_size() / 2**20:.0f} MiB)")
    del prob, res, frame_res
    return dict(frame=t_frame, cold=t_cold, loop=t_loop, corrected=corrected)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pixels", type=int, default=324_000, help="pixels per frame (P)")
    ap.add_argument("--views", type=int, default=10, help="views; observations O = 3·views")
    ap.add_argument("--subset", type=int, default=3000, help="pixels timed with the SciPy loop")
    ap.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    ap.add_argument("--device", default="cpu", help="torch device, e.g. cpu or cuda")
    ap.add_argument("--spectra", choices=("reflectance", "bumps", "both"), default="both",
                    help="realistic reflectance mixtures, the hard Gaussian-bump case, or both")
    ap.add_argument("--beta", type=float, default=1e2, help="smoothness weight (DN² scale)")
    ap.add_argument("--diff-order", type=int, default=1)
    ap.add_argument("--mask-fraction", type=float, default=0.1)
    ap.add_argument("--noise-dn", type=float, default=1.0)
    ap.add_argument("--frames", type=int, default=5, help="per-frame solves to time")
    ap.add_argument("--chunk-size", type=int, default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=None,
                    help="solver CPU threads (default: torch.get_num_threads())")
    args = ap.parse_args(argv)

    device = torch.device(args.device)
    dtype = getattr(torch, args.dtype)
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    workers = args.threads if args.threads is not None else torch.get_num_threads()
    print(f"torch {torch.__version__}, torch threads {torch.get_num_threads()}, solver threads "
          f"{workers if device.type == 'cpu' else 1}, device {device}, dtype {args.dtype}, "
          f"cpus {os.cpu_count()}, load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    cases = ("reflectance", "bumps") if args.spectra == "both" else (args.spectra,)
    out = {c: run_case(args, c, device, dtype) for c in cases}
    print("\n--- summary ---")
    for c, o in out.items():
        print(f"{c:<12} corrected {o['corrected']:.3f}  per frame {o['frame']:.3f} s "
              f"({o['loop'] / o['frame']:.1f}x)  cold {o['cold']:.3f} s "
              f"({o['loop'] / o['cold']:.1f}x)  SciPy loop {o['loop']:.2f} s")
    print(f"peak RSS: {_rss_mib():.0f} MiB")
    if device.type == "cuda":
        print(f"peak CUDA memory allocated: {torch.cuda.max_memory_allocated(device) / 2**20:.0f} "
              "MiB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
