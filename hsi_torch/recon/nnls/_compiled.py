"""Compiled CPU kernel of the block-principal-pivoting correction (numba), pixel by pixel.

The batched torch kernels of :mod:`hsi_torch.recon.nnls.active_set` run the same algorithm on any
device, one exchange round of the whole working set at a time; on CPU each round streams
``(n, k, M)`` gathers through memory with ~20 small kernels. Natural scenes make that the
bottleneck: dark pixels pivot 3–5 rounds each through 5–12-variable systems. This kernel runs the
rounds of one pixel back to back in registers and cache (numba ``prange`` over chunks of pixels,
float64 arithmetic on the stored float32/float64 ``G`` and ``H``), several times faster than the
batched rounds on CPU. Same method and exchange rules as the batched
:func:`~hsi_torch.recon.nnls.active_set._bpp`:

* zero set ``Z`` with ``|Z| ≤ M/2``: ``λ_Z = −H_ZZ⁻¹ x0_Z``, ``x = x0 + H[:, Z] λ_Z``;
* otherwise the free set ``F``: ``x_F = G_FF⁻¹ b_F``, ``λ_Z = (G x − b)_Z``;
* exchange every infeasible variable (``λ_Z < −t`` or ``x_F G_mm < −t``), Murty's single
  largest-index exchange after three rounds without fewer infeasible variables.

numba is an optional accelerator: without it (or with ``HSI_TORCH_NO_NUMBA=1``) the batched torch
kernels are used. The first call in a new environment compiles the kernel (~15 s, cached on disk
by numba next to this file, or in ``NUMBA_CACHE_DIR``).
"""

from __future__ import annotations

import os

import numpy as np

try:  # optional accelerator
    if os.environ.get("HSI_TORCH_NO_NUMBA", "") not in ("", "0"):
        raise ImportError("disabled by HSI_TORCH_NO_NUMBA")
    import numba as _nb

    AVAILABLE = True
except ImportError:  # pragma: no cover - exercised when numba is absent
    _nb = None
    AVAILABLE = False

__all__ = ["AVAILABLE", "bpp_cpu"]

#: status codes of :func:`bpp_cpu`
DONE, NOT_FINISHED, FACTOR_FAILED = 0, 1, 2

if AVAILABLE:

    @_nb.njit(cache=True, inline="always", error_model="numpy")
    def _chol_solve(S, rhs, k):  # pragma: no cover - compiled
        """In-place Cholesky of ``S[:k, :k]`` (lower) and solve ``S x = rhs`` into ``rhs``."""
        for j in range(k):
            s = S[j, j]
            for col in range(j):
                s -= S[j, col] * S[j, col]
            if not (s > 0.0):
                return False
            d = np.sqrt(s)
            S[j, j] = d
            for i in range(j + 1, k):
                t = S[i, j]
                for col in range(j):
                    t -= S[i, col] * S[j, col]
                S[i, j] = t / d
        for i in range(k):
            t = rhs[i]
            for col in range(i):
                t -= S[i, col] * rhs[col]
            rhs[i] = t / S[i, i]
        for i in range(k - 1, -1, -1):
            t = rhs[i]
            for col in range(i + 1, k):
                t -= S[col, i] * rhs[col]
            rhs[i] = t / S[i, i]
        return True

    @_nb.njit(cache=True, error_model="numpy")
    def _bpp_pixel(G, H, x0, b, gd, t, max_rounds, S, rhs, idx, x, lam, Z):  # pragma: no cover
        """One pixel's rounds (``G``, ``H``: its ``(M, M)`` matrices); returns
        ``(status, rounds)``; ``x``, ``Z`` hold the answer."""
        m = x0.shape[0]
        half = m // 2
        for j in range(m):
            Z[j] = x0[j] * gd[j] < -t
        best = m + 1
        backup = 3
        rnd = 0
        while rnd < max_rounds:
            rnd += 1
            kz = 0
            for j in range(m):
                if Z[j]:
                    kz += 1
            k = 0
            if kz <= half:  # zero-set solve through H
                for j in range(m):
                    if Z[j]:
                        idx[k] = j
                        k += 1
                for a in range(k):
                    for c in range(a + 1):
                        S[a, c] = H[idx[a], idx[c]]
                    rhs[a] = -x0[idx[a]]
                if not _chol_solve(S, rhs, k):
                    return FACTOR_FAILED, rnd
                for j in range(m):
                    x[j] = x0[j]
                    lam[j] = 0.0
                for a in range(k):
                    ra = rhs[a]
                    for j in range(m):
                        x[j] += H[idx[a], j] * ra
                for a in range(k):
                    x[idx[a]] = 0.0
                    lam[idx[a]] = rhs[a]
            else:  # free-set solve through G
                for j in range(m):
                    if not Z[j]:
                        idx[k] = j
                        k += 1
                for a in range(k):
                    for c in range(a + 1):
                        S[a, c] = G[idx[a], idx[c]]
                    rhs[a] = b[idx[a]]
                if not _chol_solve(S, rhs, k):
                    return FACTOR_FAILED, rnd
                for j in range(m):
                    x[j] = 0.0
                    lam[j] = -b[j]
                for a in range(k):
                    ra = rhs[a]
                    x[idx[a]] = ra
                    for j in range(m):
                        lam[j] += G[idx[a], j] * ra
                for j in range(m):
                    if not Z[j]:
                        lam[j] = 0.0
            nv = 0
            last = -1
            for j in range(m):
                if (lam[j] < -t) if Z[j] else (x[j] * gd[j] < -t):
                    nv += 1
                    last = j
            if nv == 0:
                return DONE, rnd
            improved = nv < best
            full = improved or backup >= 1
            backup = 3 if improved else max(backup - 1, 0)
            if improved:
                best = nv
            if full:
                for j in range(m):
                    if (lam[j] < -t) if Z[j] else (x[j] * gd[j] < -t):
                        Z[j] = not Z[j]
            else:
                Z[last] = not Z[last]
        return NOT_FINISHED, rnd

    @_nb.njit(parallel=True, cache=True, error_model="numpy")
    def _bpp_kernel(G, H, gi, x0, b, gd, thr, max_rounds, x_out, z_out, status, rounds,
                    num_chunks):  # pragma: no cover - compiled
        n, m = x0.shape
        shared = G.shape[0] == 1
        for ch in _nb.prange(num_chunks):
            S = np.empty((m, m))
            rhs = np.empty(m)
            idx = np.empty(m, np.int64)
            x = np.empty(m)
            lam = np.empty(m)
            Z = np.empty(m, np.bool_)
            for r in range(ch * n // num_chunks, (ch + 1) * n // num_chunks):
                p = 0 if shared else gi[r]
                st, rnd = _bpp_pixel(G[p], H[p], x0[r], b[r], gd[r], thr[r], max_rounds, S,
                                     rhs, idx, x, lam, Z)
                for j in range(m):
                    x_out[r, j] = x[j] if x[j] > 0.0 else 0.0
                    z_out[r, j] = Z[j]
                status[r] = st
                rounds[r] = rnd


def bpp_cpu(
    G: np.ndarray, H: np.ndarray, gi: np.ndarray, x0: np.ndarray, b: np.ndarray, gd: np.ndarray,
    thr: np.ndarray, max_rounds: int, num_threads: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Run the compiled correction on ``n`` pixels.

    Args:
        G, H: ``(P|1, M, M)`` Gram matrices and inverses (float32/float64, C-contiguous).
        gi: ``(n,)`` int64 rows of ``G``/``H``; x0, b, gd: ``(n, M)`` ``H b``, ``b``, ``diag G``;
        thr: ``(n,)`` infeasibility thresholds; max_rounds: exchange rounds before giving up.
        num_threads: numba threads.

    Returns:
        ``x (n, M)`` (dtype of ``x0``, ≥ 0), ``Z (n, M)`` bool, ``status (n,)`` int8
        (:data:`DONE`, :data:`NOT_FINISHED`, :data:`FACTOR_FAILED`), ``rounds (n,)`` int32.
    """
    if not AVAILABLE:  # pragma: no cover
        raise RuntimeError("numba is not installed")
    n, m = x0.shape
    x = np.empty((n, m), x0.dtype)
    z = np.empty((n, m), np.bool_)
    status = np.empty(n, np.int8)
    rounds = np.empty(n, np.int32)
    if n == 0:
        return x, z, status, rounds
    old = _nb.get_num_threads()
    _nb.set_num_threads(max(1, min(int(num_threads), _nb.config.NUMBA_NUM_THREADS)))
    try:
        _bpp_kernel(G, H, gi, x0, b, gd, thr, int(max_rounds), x, z, status, rounds,
                    min(n, 256))
    finally:
        _nb.set_num_threads(old)
    return x, z, status, rounds
