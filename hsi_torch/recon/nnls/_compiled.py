"""Compiled CPU kernel of the block-principal-pivoting correction (numba), pixel by pixel.

The batched torch kernels of :mod:`hsi_torch.recon.nnls.active_set` run the same algorithm on any
device, one exchange round of the whole working set at a time; on CPU each round streams
``(n, k, M)`` gathers through memory with ~20 small kernels. Natural scenes make that the
bottleneck: dark pixels pivot 3–5 rounds each through 5–12-variable systems. This kernel runs the
rounds of one pixel back to back in registers and cache (numba ``prange`` over chunks of pixels,
float64 arithmetic on the stored float32/float64 ``G`` and ``H``), several times faster than the
batched rounds on CPU. Same method and exchange rules as the batched
:func:`~hsi_torch.recon.nnls.active_set._bpp`:

* zero set ``Z`` with ``|Z| ≤ M/2`` (:func:`~hsi_torch.recon.nnls.constants.zero_set_limit`):
  ``λ_Z = −H_ZZ⁻¹ x0_Z``, ``x = x0 + H[:, Z] λ_Z``;
* otherwise the free set ``F``: ``x_F = G_FF⁻¹ b_F``, ``λ_Z = (G x − b)_Z``;
* exchange every infeasible variable (``λ_Z < −t`` or ``x_F G_mm < −t``), Murty's single
  largest-index exchange after three rounds without fewer infeasible variables
  (:data:`~hsi_torch.recon.nnls.constants.MURTY_PATIENCE`).

numba is an optional accelerator (:mod:`hsi_torch.recon._numba`): without it (or with
``HSI_TORCH_NO_NUMBA=1``) the batched torch kernels are used. The exchange rules (the threshold,
Murty's counter, the zero-set/free-set switch) come from :mod:`~hsi_torch.recon.nnls.constants`
as arguments. The first call in a new environment compiles the kernel (~15 s, cached on disk
by numba next to this file, or in ``NUMBA_CACHE_DIR``).
"""

from __future__ import annotations

import numpy as np

from hsi_torch.recon._numba import AVAILABLE, threads
from hsi_torch.recon._numba import nb as _nb
from hsi_torch.recon.nnls.constants import (
    COMPILED_FLOOR,
    INFEASIBILITY_FRACTION,
    MURTY_PATIENCE,
    zero_set_limit,
)

__all__ = ["AVAILABLE", "solve_frame_cpu", "adjoint_frame"]

#: status codes of :func:`solve_frame_cpu`
DONE, NOT_FINISHED, FACTOR_FAILED = 0, 1, 2

if AVAILABLE:

    @_nb.njit(cache=True, inline="always", error_model="numpy")
    def _chol_solve(S, rhs, k):  # pragma: no cover - compiled
        """In-place Cholesky ``S[:k, :k] = L Lᵀ`` (``L`` in the lower triangle, ``1 / L_jj`` on
        the diagonal: multiplications instead of divisions) and solve ``S x = rhs`` into
        ``rhs``; False if ``S`` is not positive definite."""
        for j in range(k):
            s = S[j, j]
            for col in range(j):
                s -= S[j, col] * S[j, col]
            if not (s > 0.0):
                return False
            inv = 1.0 / np.sqrt(s)
            S[j, j] = inv
            for i in range(j + 1, k):
                t = S[i, j]
                for col in range(j):
                    t -= S[i, col] * S[j, col]
                S[i, j] = t * inv
        for i in range(k):  # L z = rhs
            t = rhs[i]
            for col in range(i):
                t -= S[i, col] * rhs[col]
            rhs[i] = t * S[i, i]
        for i in range(k - 1, -1, -1):  # Lᵀ x = z, by columns of Lᵀ (rows of L: contiguous)
            xi = rhs[i] * S[i, i]
            rhs[i] = xi
            for r in range(i):
                rhs[r] -= S[i, r] * xi
        return True

    @_nb.njit(cache=True, inline="always", error_model="numpy")
    def _bpp_pixel(G, H, p, x0, b, gd, t, max_rounds, half, patience, S, rhs, idx, x, lam,
                   Z, viol):  # pragma: no cover - compiled
        """One pixel's rounds (``G[p]``, ``H[p]``: its ``(M, M)`` matrices, indexed in place:
        a slice per pixel would cost numba a reference count); returns ``(status, rounds)``;
        ``x``, ``Z`` hold the answer; ``viol (M,)`` int64 scratch."""
        m = x0.shape[0]
        for j in range(m):
            Z[j] = x0[j] * gd[p, j] < -t
        best = m + 1
        backup = patience
        rnd = 0
        while rnd < max_rounds:
            rnd += 1
            kz = 0
            for j in range(m):  # branch-free: a zero set is no pattern a predictor learns
                kz += np.int64(Z[j])
            k = 0
            if kz <= half:  # zero-set solve through H
                for j in range(m):
                    idx[k] = j
                    k += np.int64(Z[j])
                for a in range(k):
                    for c in range(a + 1):
                        S[a, c] = H[p, idx[a], idx[c]]
                    rhs[a] = -x0[idx[a]]
                if not _chol_solve(S, rhs, k):
                    return FACTOR_FAILED, rnd
                for j in range(m):
                    x[j] = x0[j]
                    lam[j] = 0.0
                for a in range(k):
                    ra = rhs[a]
                    for j in range(m):
                        x[j] += H[p, idx[a], j] * ra
                for a in range(k):
                    x[idx[a]] = 0.0
                    lam[idx[a]] = rhs[a]
            else:  # free-set solve through G
                for j in range(m):
                    idx[k] = j
                    k += 1 - np.int64(Z[j])
                for a in range(k):
                    for c in range(a + 1):
                        S[a, c] = G[p, idx[a], idx[c]]
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
                        lam[j] += G[p, idx[a], j] * ra
                for j in range(m):
                    lam[j] = lam[j] if Z[j] else 0.0
            nv = 0
            last = -1
            for j in range(m):  # infeasible: λ_j < −t on Z, x_j G_jj < −t on F (branch-free)
                zj = np.int64(Z[j])
                vj = zj * np.int64(lam[j] < -t) + (1 - zj) * np.int64(x[j] * gd[p, j] < -t)
                viol[j] = vj
                nv += vj
                last = j if vj else last
            if nv == 0:
                return DONE, rnd
            improved = nv < best
            full = improved or backup >= 1
            backup = patience if improved else max(backup - 1, 0)
            if improved:
                best = nv
            if full:
                for j in range(m):
                    Z[j] = (np.int64(Z[j]) ^ viol[j]) != 0
            else:
                Z[last] = not Z[last]
        return NOT_FINISHED, rnd

    @_nb.njit(cache=True, inline="always", error_model="numpy")
    def _symv(S, p, v, out, sign):  # pragma: no cover - compiled
        """``out ← out + sign·S[p] v`` for a symmetric ``S[p]``, by rows:
        ``out[i] += S[p, j, i]·v[j]`` in the order of ``j`` (the order of a row's dot product,
        so the same sums): the inner loop over ``i`` has independent accumulators and
        vectorises, where a dot product per row is a chain of dependent additions. ``S`` is
        indexed in place (a per-pixel slice costs numba a reference count)."""
        m = v.shape[0]
        for j in range(m):
            vj = sign * v[j]
            for i in range(m):
                out[i] += S[p, j, i] * vj

    @_nb.njit(cache=True, inline="always", error_model="numpy")
    def _kkt(G, p, x, b, gd, gn, bn, g, floor):  # pragma: no cover - compiled
        """``g = G[p] x − b`` into ``g``; returns the relative KKT residual (``_kkt_ratio``)."""
        m = x.shape[0]
        for i in range(m):
            g[i] = -b[i]
        for j in range(m):  # by rows, as _symv, skipping the zero set (dark pixels: most bands)
            xj = x[j]
            if xj != 0.0:
                for i in range(m):
                    g[i] += G[p, j, i] * xj
        num = 0.0
        xn = 0.0
        for i in range(m):
            v = g[i]
            t = gd[p, i] * x[i]
            t = t if t < v else v
            num += t * t
            xn += x[i] * x[i]
        den = gn * np.sqrt(xn) + bn
        return np.sqrt(num) / (den if den > floor else floor)

    @_nb.njit(cache=True, inline="always", error_model="numpy")
    def _rhs(y, mask, Bt, gain, resp, r, out):  # pragma: no cover - compiled
        """``out = Aᵀ W y`` of pixel ``r`` from its factors: ``y (P, O)``, ``mask (P, O)``,
        ``Bt (P, V, M)``, ``gain (P, V)``, ``resp (C, M)`` (``o = C·v + c``):
        ``out = Σ_v B_v ⊙ Σ_c u_vc resp_c`` with ``u_vc = g_v y_o`` (0 where masked)."""
        V, M = Bt.shape[1], Bt.shape[2]
        C = resp.shape[0]
        for j in range(M):
            out[j] = 0.0
        if C == 3:  # the RGB camera: the three weights in registers
            for v in range(V):
                gv = gain[r, v]
                o = 3 * v
                u0 = y[r, o] * gv if mask[r, o] else 0.0
                u1 = y[r, o + 1] * gv if mask[r, o + 1] else 0.0
                u2 = y[r, o + 2] * gv if mask[r, o + 2] else 0.0
                for j in range(M):
                    out[j] += Bt[r, v, j] * ((u0 * resp[0, j] + u1 * resp[1, j])
                                             + u2 * resp[2, j])
            return
        for v in range(V):
            gv = gain[r, v]
            for c in range(C):
                o = v * C + c
                if mask[r, o]:
                    uc = y[r, o] * gv
                    for j in range(M):
                        out[j] += uc * resp[c, j] * Bt[r, v, j]

    @_nb.njit(parallel=True, cache=True, error_model="numpy")
    def _frame_kernel(G, H, b, gd, gn, skip, tol, max_rounds, refine, frac, half, patience,
                      floor, x_out, z_out, r_out, status, rounds, num_chunks, fused, y, mask,
                      Bt, gain, resp):  # pragma: no cover - compiled
        n, m = b.shape
        shared = G.shape[0] == 1
        for ch in _nb.prange(num_chunks):
            S = np.empty((m, m))
            rhs = np.empty(m)
            idx = np.empty(m, np.int64)
            x = np.empty(m)
            x0 = np.empty(m)
            xn = np.empty(m)
            lam = np.empty(m)
            g = np.empty(m)
            br = np.empty(m)
            Z = np.empty(m, np.bool_)
            viol = np.empty(m, np.int64)
            for r in range(ch * n // num_chunks, (ch + 1) * n // num_chunks):
                p = 0 if shared else r
                if fused:  # b = Aᵀ W y from the factors, stored (rounded to b's dtype)
                    _rhs(y, mask, Bt, gain, resp, r, rhs)
                    for j in range(m):
                        b[r, j] = rhs[j]
                bn = 0.0
                for j in range(m):
                    br[j] = b[r, j]
                    bn += br[j] * br[j]
                bn = np.sqrt(bn)
                for i in range(m):  # x0 = H b
                    x0[i] = 0.0
                _symv(H, p, br, x0, 1.0)
                nrm = 0.0
                for i in range(m):
                    nrm += x0[i] * x0[i]
                t = frac * tol * (gn[p] * np.sqrt(nrm) + bn)
                t = t if t > floor else floor
                need = False
                if not skip[r]:
                    for j in range(m):
                        if x0[j] * gd[p, j] < -t:
                            need = True
                st, rnd = DONE, 0
                if need:
                    st, rnd = _bpp_pixel(G, H, p, x0, br, gd, t, max_rounds, half, patience,
                                         S, rhs, idx, x, lam, Z, viol)
                    for j in range(m):
                        x[j] = x[j] if x[j] > 0.0 else 0.0
                else:
                    for j in range(m):
                        x[j] = x0[j] if x0[j] > 0.0 else 0.0
                        Z[j] = False
                res = _kkt(G, p, x, br, gd, gn[p], bn, g, floor)
                if not need and not skip[r]:  # all-free pixels: refinement x <- max(0, x - H g)
                    for _ in range(refine):
                        if res <= tol:
                            break
                        for i in range(m):
                            xn[i] = x[i]
                        _symv(H, p, g, xn, -1.0)
                        for i in range(m):
                            xn[i] = xn[i] if xn[i] > 0.0 else 0.0
                        rn = _kkt(G, p, xn, br, gd, gn[p], bn, lam, floor)
                        if rn < res:
                            res = rn
                            for i in range(m):
                                x[i] = xn[i]
                                g[i] = lam[i]
                        else:
                            break
                for j in range(m):
                    x_out[r, j] = x[j]
                    z_out[r, j] = Z[j]
                r_out[r] = res
                status[r] = st
                rounds[r] = rnd

    @_nb.njit(parallel=True, cache=True, error_model="numpy")
    def _adjoint_kernel(y, mask, Bt, gain, resp, out, num_chunks):  # pragma: no cover
        n, m = out.shape
        for ch in _nb.prange(num_chunks):
            acc = np.empty(m)
            for r in range(ch * n // num_chunks, (ch + 1) * n // num_chunks):
                _rhs(y, mask, Bt, gain, resp, r, acc)
                for j in range(m):
                    out[r, j] = acc[j]


def solve_frame_cpu(
    G: np.ndarray, H: np.ndarray, b: np.ndarray, gd: np.ndarray, gn: np.ndarray,
    skip: np.ndarray, tol: float, max_rounds: int, refine: int, num_threads: int,
    factors: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Steps 1–3 of the active-set solve for every pixel in one compiled pass.

    Per pixel: with ``factors``, the right-hand side ``b = Aᵀ W y`` from the camera's factored
    sensing matrix (written into ``b``); ``x0 = H b``; the infeasibility threshold
    ``t = ¼·tol·(‖G‖‖x0‖ + ‖b‖)``
    (:data:`~hsi_torch.recon.nnls.constants.INFEASIBILITY_FRACTION`); block
    principal pivoting where ``x0`` has an entry with ``x0_m G_mm < −t`` (unless ``skip``);
    the KKT residual of the answer with the exact ``G`` and ``b``; for pixels without a zero set,
    up to ``refine`` refinement steps ``x ← max(0, x − H(Gx − b))`` kept while they lower it.
    Each pixel's bytes are read once and nothing of frame size is allocated but the outputs.
    ``G`` and ``H`` must be symmetric (they are read by rows as columns).

    Args:
        G, H: ``(P|1, M, M)``; b: ``(P, M)`` right-hand sides (with ``factors``: written);
        gd: ``(P|1, M)`` ``diag G``; gn: ``(P|1,)`` the ``‖G‖₂`` bound; skip: ``(P,)`` bool
        (singular or without data: no pivoting); factors: ``None`` (``b`` given), or
        ``(y (P, O), mask (P, O) bool, transmittance (P, V, M), gain (P, V), response (C, M))``
        with ``O = V·C`` and ``o = C·v + c`` (:class:`~hsi_torch.forward_model.SensingModel`).

    Returns:
        ``x (P, M) ≥ 0``, ``Z (P, M)`` bool zero sets, ``residual (P,)`` float64, ``status (P,)``
        int8 (:data:`DONE` also for pixels that needed no pivoting), ``rounds (P,)`` int32.
    """
    if not AVAILABLE:  # pragma: no cover
        raise RuntimeError("numba is not installed")
    n, m = b.shape
    x = np.empty((n, m), b.dtype)
    z = np.empty((n, m), np.bool_)
    res = np.empty(n, np.float64)
    status = np.empty(n, np.int8)
    rounds = np.empty(n, np.int32)
    if n == 0:
        return x, z, res, status, rounds
    if factors is None:  # placeholders of the right types (numba compiles one kernel per dtype)
        fac = (np.zeros((1, 1), b.dtype), np.zeros((1, 1), np.bool_),
               np.zeros((1, 1, m), b.dtype), np.zeros((1, 1), b.dtype),
               np.zeros((1, m), b.dtype))
    else:
        fac = tuple(np.ascontiguousarray(a) for a in factors)
        y, mask, Bt, gain, resp = fac
        V, C = Bt.shape[1], resp.shape[0]
        if (y.shape != (n, V * C) or mask.shape != y.shape or Bt.shape != (n, V, m)
                or gain.shape != (n, V) or resp.shape != (C, m)):
            raise ValueError(
                f"solve_frame_cpu: factors y {y.shape}, mask {mask.shape}, transmittance "
                f"{Bt.shape}, gain {gain.shape}, response {resp.shape} do not match "
                f"b {b.shape} as (P, V·C), (P, V·C), (P, V, M), (P, V), (C, M)")
    with threads(num_threads):
        _frame_kernel(G, H, b, gd, gn, skip, float(tol), int(max_rounds), int(refine),
                      float(INFEASIBILITY_FRACTION), int(zero_set_limit(m)), int(MURTY_PATIENCE),
                      float(COMPILED_FLOOR), x, z, res, status, rounds, min(n, 512),
                      factors is not None, *fac)
    return x, z, res, status, rounds


def adjoint_frame(y: np.ndarray, mask: np.ndarray, transmittance: np.ndarray, gain: np.ndarray,
                  response: np.ndarray, num_threads: int) -> np.ndarray:
    """``b = Aᵀ W y`` of every pixel from the camera's factored sensing matrix (the compiled
    pass's own right-hand side, float64 arithmetic), ``(P, M)`` in ``y``'s dtype: the factors
    as in :func:`solve_frame_cpu`."""
    if not AVAILABLE:  # pragma: no cover
        raise RuntimeError("numba is not installed")
    n, m = y.shape[0], transmittance.shape[2]
    out = np.empty((n, m), y.dtype)
    if n:
        with threads(num_threads):
            _adjoint_kernel(*(np.ascontiguousarray(a) for a in (y, mask, transmittance, gain,
                                                                   response)),
                            out, min(n, 512))
    return out
