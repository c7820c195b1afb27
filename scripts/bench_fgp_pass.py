#!/usr/bin/env python
"""The TV solve's fused ADMM pass against the machine: its GFLOP/s and the attainable ones.

    python scripts/bench_fgp_pass.py [--bands 25] [--threads 1] [--repeats 5]

Times one :func:`hsi_torch.recon.spatial._compiled.fgp_block` pass (one ADMM iteration: the
x-update, 5 dual iterations of the TV prox, the primals) at the full-size prototype's frame
(744 × 858, an elliptic valid region of ≈ 3.6·10⁵ pixels; random inputs of the right shapes:
the arithmetic does not depend on the values), with and without the dual iterations, and beside
it on the same threads: a float32 matrix product (NumPy's BLAS), a numba FMA loop in the
first-level cache and a numba read of an array of the packed inverse's size (GB/s). Times are
the process's CPU seconds (best of ``--repeats``), which a shared machine inflates less than
wall time; GFLOP/s use the operation count of the pass's loops per pixel (x-update
``8M + 2M(M − 1)``, dual iterations ``28M`` each but the last ``20M``, six primals ``12M``).
``--bands 20`` gives the pass of a ``k = 20`` spectral subspace (``spectral_rank``).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from hsi_torch.recon._numba import AVAILABLE
from hsi_torch.recon._numba import nb as _nb
from hsi_torch.recon.spatial import _compiled as C


def _flops_x(m: int) -> int:
    return 8 * m + 2 * m * (m - 1)


def _flops_dual(m: int, inner: int) -> int:
    return (28 * inner - 8) * m + (inner + 1) * 12 * m if inner else 0


def _cpu_best(fn, repeats: int) -> float:
    fn()
    best = float("inf")
    for _ in range(repeats):
        t = time.process_time()
        fn()
        best = min(best, time.process_time() - t)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bands", type=int, default=25, help="channels M (or a subspace's k)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    if not AVAILABLE:
        raise SystemExit("numba is not available (or disabled): the fused pass needs it")
    _nb.set_num_threads(args.threads)
    rng = np.random.default_rng(0)
    h, w, m = 744, 858, args.bands
    yy, xx = np.mgrid[:h, :w]
    mask = ((yy - h / 2) / (h / 2)) ** 2 + ((xx - w / 2) / (w / 2)) ** 2 < 0.72
    pix = np.flatnonzero(mask.ravel())
    P = pix.size
    row_ptr = np.searchsorted(pix // w, np.arange(h + 1)).astype(np.int64)
    ex = np.zeros((h, w), np.float32)
    ex[:, :-1] = mask[:, :-1] & mask[:, 1:]
    ey = np.zeros((h, w), np.float32)
    ey[:-1] = mask[:-1] & mask[1:]
    grid = C.fgp_grid((row_ptr,), pix, (h, w), ex, ey)
    blocks = C.fgp_blocks(row_ptr, args.threads)
    a = rng.standard_normal((256, m, m)).astype(np.float32) * 0.1
    inv = np.einsum("pij,pkj->pik", a, a) + np.eye(m, dtype=np.float32)
    chunks = ((s, inv[np.arange(s, e) % 256]) for s, e in C.row_chunks(row_ptr, 20000))
    inv_rows = C.pack_inverse_rows(chunks, row_ptr, m, np.float32)
    b, x, u, z = (rng.random((m, P), dtype=np.float32) for _ in range(4))
    x2, u2, z2 = (np.empty_like(b) for _ in range(3))
    p = (rng.random((2, m, P), dtype=np.float32) - 0.5) * 0.1
    p2, ps = np.empty_like(p), p.sum(1)
    ps2 = np.empty_like(ps)
    moms = np.array([0.0, 0.28, 0.43, 0.53, 0.6], np.float32)
    slot, slot_inv = np.full(P, -1, np.int64), np.zeros((1, m, m), np.float32)
    has = np.zeros(h, np.bool_)

    def one(inner: int) -> None:
        C.fgp_block(inv_rows, slot, slot_inv, has, b, x, u, z, x2, u2, 1.0, True, 0.5, 0.25,
                    moms[:inner], p, ps, p2, ps2, z2, grid, blocks, 0.3, True)

    print(f"{P} pixels, {m} channels, {args.threads} thread(s); CPU seconds, best of "
          f"{args.repeats}")
    t_all = _cpu_best(lambda: one(5), args.repeats)
    t_x = _cpu_best(lambda: one(0), args.repeats)
    f_x, f_d = _flops_x(m) * P, _flops_dual(m, 5) * P
    print(f"  fused pass: {t_all * 1e3:.1f} ms, {(f_x + f_d) / t_all / 1e9:.1f} GFLOP/s "
          f"({(f_x + f_d) / P:.0f} flops a pixel)")
    nbytes = inv_rows.nbytes
    print(f"    x-update alone: {t_x * 1e3:.1f} ms, {f_x / t_x / 1e9:.1f} GFLOP/s, the packed "
          f"inverse ({nbytes / 1e6:.0f} MB) read at {nbytes / t_x / 1e9:.1f} GB/s")
    t_d = max(t_all - t_x, 1e-9)
    print(f"    dual iterations and primals: {t_d * 1e3:.1f} ms, {f_d / t_d / 1e9:.1f} GFLOP/s")

    big = rng.random((2048, 2048), dtype=np.float32)
    t_mm = _cpu_best(lambda: big @ big, args.repeats)
    print(f"  machine: float32 matmul 2048 {2 * 2048**3 / t_mm / 1e9:.1f} GFLOP/s (the BLAS's "
          f"own threads: set OMP_NUM_THREADS/OPENBLAS_NUM_THREADS to --threads)")
    xs = rng.random((args.threads, 1024), dtype=np.float32)
    reps = 100_000
    t_fma = _cpu_best(lambda: _fma_loop(xs, reps), 2)
    print(f"  machine: numba FMA loop in L1 {2 * xs.size * reps / t_fma / 1e9:.1f} GFLOP/s")
    t_rd = _cpu_best(lambda: _read(inv_rows), args.repeats)
    print(f"  machine: numba read of the packed inverse {inv_rows.nbytes / t_rd / 1e9:.1f} GB/s")


if AVAILABLE:

    @_nb.njit(parallel=True, fastmath=True, cache=True)
    def _fma_loop(xs, reps):  # pragma: no cover - compiled
        tot = np.float32(0)
        for c in _nb.prange(xs.shape[0]):
            v = xs[c]
            acc = np.zeros_like(v)
            for _ in range(reps):
                for i in range(v.shape[0]):
                    acc[i] = acc[i] * np.float32(0.999) + v[i]
            tot += acc.sum()
        return tot

    @_nb.njit(parallel=True, fastmath=True, cache=True)
    def _read(a):  # pragma: no cover - compiled
        t = np.float32(0)
        for i in _nb.prange(a.shape[0]):
            t += a[i]
        return t


if __name__ == "__main__":
    main()
