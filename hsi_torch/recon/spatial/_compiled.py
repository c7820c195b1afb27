"""Compiled CPU kernels of the spatial (TV) solve (numba): the ADMM x-update and the TV prox.

The torch step of :mod:`hsi_torch.recon.spatial.admm` runs every step as ~20 whole-cube kernels
on the ``(M, h, w)`` frame (the invalid corners included) and a batched ``(P, M, M)``
matrix–vector product; at the full-size prototype's frame (25 × 744 × 858, 306 000 valid
pixels) one ADMM iteration streams several GB through memory. These kernels run the same
iterations on the valid pixels only, in their ``(P, M)`` storage (bands contiguous), each step
in one pass:

* :func:`x_update`: ``u ← u + x − z`` (from the second iteration on), ``x = (G + ρI)⁻¹
  (b + ρ(z − u))``, ``v = x + u``, pixel by pixel with the symmetric inverse read as ``M``
  contiguous columns (vectorised axpy's; :func:`sym_apply` is the same product alone, for
  ``G x`` of the warm start).
* :func:`fgp_step`: one dual iteration of the fast gradient projection (the same formulas as
  :func:`hsi_torch.recon.spatial.operators.prox_tv_nonneg`), row by row: the primal ``z`` of row
  ``k + 1`` is formed just before the dual update of row ``k`` needs it, so ``z`` stays in cache.
  The dual is double-buffered (read the old arrays, write new ones), so chunks of rows run on
  ``prange`` threads without ordering constraints.
* :func:`fgp_primal`: ``z = max(v − t Dᵀp, 0)``.

The graph is stored per pixel (sorted by the flat frame index): the right, lower, left and upper
neighbour's position and the edge weight (0: no edge, the position is then the pixel itself).
Arithmetic in the arrays' dtype; numba is optional (:mod:`hsi_torch.recon._numba`; the torch
step runs without it). The ADMM loop that calls these kernels, and its stopping rule, is
:mod:`hsi_torch.recon.spatial.admm` (:class:`~hsi_torch.recon.spatial.admm._CompiledStep`).
"""

from __future__ import annotations

import numpy as np

from hsi_torch.recon._numba import AVAILABLE
from hsi_torch.recon._numba import nb as _nb

__all__ = ["AVAILABLE", "x_update", "sym_apply", "fgp_workspace", "fgp_step", "fgp_primal"]


#: numba's fast-math flags for the TV kernels: reassociation lets the per-pixel sums over bands
#: vectorise (no assumptions about NaN or infinities)
_FAST = {"reassoc", "contract", "nsz", "arcp"}

if AVAILABLE:

    @_nb.njit(parallel=True, cache=True, error_model="numpy", fastmath=_FAST)
    def _x_update(inv, b, z, u, x, v, rho, update_u, num_chunks):  # pragma: no cover - compiled
        n, m = b.shape
        shared = inv.shape[0] == 1
        for ch in _nb.prange(num_chunks):
            rhs = np.empty(m, b.dtype)
            acc = np.empty(m, b.dtype)
            for i in range(ch * n // num_chunks, (ch + 1) * n // num_chunks):
                for j in range(m):
                    if update_u:
                        u[i, j] += x[i, j] - z[i, j]
                    rhs[j] = b[i, j] + rho * (z[i, j] - u[i, j])
                    acc[j] = 0
                S = inv[0] if shared else inv[i]
                for c in range(m):  # S symmetric: column c = row c, contiguous (vectorises)
                    xc = rhs[c]
                    for j in range(m):
                        acc[j] += S[c, j] * xc
                for j in range(m):
                    x[i, j] = acc[j]
                    v[i, j] = acc[j] + u[i, j]

    @_nb.njit(parallel=True, cache=True, error_model="numpy", fastmath=_FAST)
    def _sym_apply(mat, xin, out, num_chunks):  # pragma: no cover - compiled
        n, m = xin.shape
        shared = mat.shape[0] == 1
        for ch in _nb.prange(num_chunks):
            acc = np.empty(m, xin.dtype)
            for i in range(ch * n // num_chunks, (ch + 1) * n // num_chunks):
                S = mat[0] if shared else mat[i]
                for j in range(m):
                    acc[j] = 0
                for c in range(m):
                    xc = xin[i, c]
                    for j in range(m):
                        acc[j] += S[c, j] * xc
                for j in range(m):
                    out[i, j] = acc[j]

    @_nb.njit(inline="always", error_model="numpy")
    def _kt_offset(rs, i, li, ui, a, bb, cl, cu, c):  # pragma: no cover - compiled
        """The brightness weighting's part of ``(Dᵀ K r)_i`` (the same for every band):
        ``c·(cl Σr_l,x + cu Σr_u,y − a Σr_i,x − bb Σr_i,y)``, ``c = (α − 1)/M``, from the band
        sums ``rs (P, 2)`` of ``r``."""
        return c * (cl * rs[li, 0] + cu * rs[ui, 1] - a * rs[i, 0] - bb * rs[i, 1])

    @_nb.njit(inline="always", error_model="numpy", fastmath=_FAST)
    def _primal(v, t, r, rs, out, base, lo, hi, left, up, wx, wy, wl, wu, c):  # pragma: no cover
        """``max(v − t (KD)ᵀr, 0)`` of pixels ``lo:hi`` into ``out[i − base]`` (``base`` 0: the
        whole ``(P, M)`` array; ``lo``: a row buffer)."""
        m = v.shape[1]
        for i in range(lo, hi):
            li, ui = left[i], up[i]
            a, bb, cl, cu = wx[i], wy[i], wl[i], wu[i]
            o = i - base
            off = _kt_offset(rs, i, li, ui, a, bb, cl, cu, c)
            for j in range(m):
                d = cl * r[li, 0, j] + cu * r[ui, 1, j] - a * r[i, 0, j] - bb * r[i, 1, j] + off
                val = v[i, j] - t * d
                out[o, j] = val if val > 0 else 0

    @_nb.njit(parallel=True, cache=True, error_model="numpy")
    def _fgp_first_rows(v, t, r_in, rin_sum, zb, row_ptr, left, up, wx, wy, wl, wu, c,
                        num_chunks):  # pragma: no cover - compiled
        h = row_ptr.shape[0] - 1
        for ch in _nb.prange(num_chunks):
            ra = ch * h // num_chunks
            if ra < h:
                lo = row_ptr[ra]
                _primal(v, t, r_in, rin_sum, zb[ch], lo, lo, row_ptr[ra + 1], left, up, wx, wy,
                        wl, wu, c)

    @_nb.njit(parallel=True, cache=True, error_model="numpy", fastmath=_FAST)
    def _fgp_step(v, t, step, mom, one, c, r_in, rin_sum, p, psum, r_out, rsum, zb, row_ptr,
                  right, down, left, up, wx, wy, wl, wu, num_chunks):  # pragma: no cover
        m = v.shape[1]
        h = row_ptr.shape[0] - 1
        width = zb.shape[1]
        for ch in _nb.prange(num_chunks):
            ra, rb = ch * h // num_chunks, (ch + 1) * h // num_chunks
            if ra >= rb:
                continue
            ring = np.zeros((2, width, m), v.dtype)  # finite everywhere (weight-0 reads)
            q = np.empty((2, m), v.dtype)
            ring[ra & 1] = zb[ch]
            for k in range(ra, rb):
                lo, hi = row_ptr[k], row_ptr[k + 1]
                if k + 1 < h:  # the next row's primal, from the dual before this row's update
                    if k + 1 < rb:
                        _primal(v, t, r_in, rin_sum, ring[(k + 1) & 1], hi, hi, row_ptr[k + 2],
                                left, up, wx, wy, wl, wu, c)
                    else:
                        ring[(k + 1) & 1] = zb[ch + 1]
                zk, zn = ring[k & 1], ring[(k + 1) & 1]
                for i in range(lo, hi):
                    sa, sb = step * wx[i], step * wy[i]
                    o = i - lo
                    ro = right[i] - lo
                    do = down[i] - hi if sb != 0 else 0  # 0: a finite entry, weight 0
                    zero = one - one
                    s0, s1 = zero, zero  # Σ_j (D z)_j per direction: K's part c·Σ
                    for j in range(m):
                        zi = zk[o, j]
                        d0 = sa * (zk[ro, j] - zi)
                        d1 = sb * (zn[do, j] - zi)
                        q[0, j] = d0
                        q[1, j] = d1
                        s0 += d0
                        s1 += d1
                    k0, k1 = c * s0, c * s1
                    n2 = zero
                    for j in range(m):
                        q0 = r_in[i, 0, j] + q[0, j] + k0
                        q1 = r_in[i, 1, j] + q[1, j] + k1
                        q[0, j] = q0
                        q[1, j] = q1
                        n2 += q0 * q0 + q1 * q1
                    sc = one / np.sqrt(n2) if n2 > one else one
                    p0, p1, r0, r1 = zero, zero, zero, zero
                    for j in range(m):
                        a0 = q[0, j] * sc
                        a1 = q[1, j] * sc
                        b0 = a0 + mom * (a0 - p[i, 0, j])
                        b1 = a1 + mom * (a1 - p[i, 1, j])
                        r_out[i, 0, j] = b0
                        r_out[i, 1, j] = b1
                        p[i, 0, j] = a0
                        p[i, 1, j] = a1
                        p0 += a0
                        p1 += a1
                        r0 += b0
                        r1 += b1
                    psum[i, 0], psum[i, 1] = p0, p1
                    rsum[i, 0], rsum[i, 1] = r0, r1

    @_nb.njit(parallel=True, cache=True, error_model="numpy")
    def _fgp_primal(v, t, p, psum, z, row_ptr, left, up, wx, wy, wl, wu, c,
                    num_chunks):  # pragma: no cover - compiled
        h = row_ptr.shape[0] - 1
        for ch in _nb.prange(num_chunks):
            ra, rb = ch * h // num_chunks, (ch + 1) * h // num_chunks
            if ra < rb:
                _primal(v, t, p, psum, z, 0, row_ptr[ra], row_ptr[rb], left, up, wx, wy, wl, wu,
                        c)


def _chunks(n: int) -> int:
    return max(1, min(n, 64))


def x_update(inv: np.ndarray, b: np.ndarray, z: np.ndarray, u: np.ndarray, x: np.ndarray,
             v: np.ndarray, rho: float, update_u: bool) -> None:
    """In place: (``u += x − z`` if ``update_u``), ``x = S (b + ρ(z − u))``, ``v = x + u``.

    Args:
        inv: ``(P|1, M, M)`` C-contiguous symmetric ``S = (G + ρI)⁻¹`` (read as columns: each
            pixel's product is ``M`` contiguous axpy's, which vectorise — 2.1× faster than the
            packed triangle's row/column sweep, measured); b, z, u, x, v: ``(P, M)``
            C-contiguous, one dtype.
    """
    n = b.shape[0]
    if n:
        _x_update(inv, b, z, u, x, v, b.dtype.type(rho), bool(update_u), _chunks(n // 256))


def sym_apply(mat: np.ndarray, x: np.ndarray, out: np.ndarray) -> None:
    """``out_p = S_p x_p`` for symmetric ``mat (P|1, M, M)`` and ``x, out (P, M)`` (all
    C-contiguous, one dtype; ``out`` may not be ``x``)."""
    n = x.shape[0]
    if n:
        _sym_apply(mat, x, out, _chunks(n // 256))


def fgp_workspace(graph: tuple[np.ndarray, ...], m: int, dtype: np.dtype) -> np.ndarray:
    """The first-row buffer of :func:`fgp_step`: ``(chunks, widest row, M)``."""
    row_ptr = graph[0]
    width = int(np.diff(row_ptr).max()) if row_ptr.size > 1 else 0
    return np.empty((_chunks((row_ptr.shape[0] - 1) // 4), max(width, 1), m), dtype)


def fgp_step(v: np.ndarray, t: float, step: float, mom: float, r_in: np.ndarray,
             rin_sum: np.ndarray, p: np.ndarray, psum: np.ndarray, r_out: np.ndarray,
             rsum: np.ndarray, first_rows: np.ndarray, graph: tuple[np.ndarray, ...],
             brightness_weight: float = 1.0) -> None:
    """One FGP dual iteration in place: ``p ← Π(r_in + step·D z(r_in))``, ``r_out ← p_new +
    mom·(p_new − p_old)``, with ``z(r) = max(v − t Dᵀr, 0)`` formed row by row in a two-row
    buffer (never stored whole).

    Row ``k``'s update needs the primal of rows ``k`` and ``k + 1``, formed from the dual before
    either row is updated: within a chunk of rows the next row's primal is formed just before
    the current row is updated; each chunk's first row is formed by all chunks beforehand
    (``first_rows``, :func:`fgp_workspace`), so neighbouring chunks never read a row another
    thread has updated. ``r_in`` may be ``p`` (the first iteration of a prox, where ``r = p``).
    ``brightness_weight`` ``α``: the operator is ``K D`` with ``K = I − (1 − α) u uᵀ`` on the
    bands (``u`` the flat spectrum), applied through band sums: ``rin_sum``, ``psum``, ``rsum``
    ``(P, 2)`` hold the band sums of ``r_in``, ``p`` and ``r_out`` (the last two are written
    with them; ``rin_sum`` is ``psum`` when ``r_in`` is ``p``).

    Args:
        v: ``(P, M)``; r_in, p, r_out: ``(P, 2, M)``; graph: ``(row_ptr, right, down, left, up,
            wx, wy, wl, wu)``.
    """
    row_ptr, right, down, left, up, wx, wy, wl, wu = graph
    ty = v.dtype.type
    chunks = first_rows.shape[0]
    c = ty((brightness_weight - 1.0) / v.shape[1])
    _fgp_first_rows(v, ty(t), r_in, rin_sum, first_rows, row_ptr, left, up, wx, wy, wl, wu, c,
                    chunks)
    _fgp_step(v, ty(t), ty(step), ty(mom), ty(1), c, r_in, rin_sum, p, psum, r_out, rsum,
              first_rows, row_ptr, right, down, left, up, wx, wy, wl, wu, chunks)


def fgp_primal(v: np.ndarray, t: float, p: np.ndarray, psum: np.ndarray, z: np.ndarray,
               graph: tuple[np.ndarray, ...], brightness_weight: float = 1.0) -> None:
    """``z = max(v − t (KD)ᵀp, 0)`` in place (``K``, ``psum``: see :func:`fgp_step`)."""
    row_ptr, _, _, left, up, wx, wy, wl, wu = graph
    ty = v.dtype.type
    _fgp_primal(v, ty(t), p, psum, z, row_ptr, left, up, wx, wy, wl, wu,
                ty((brightness_weight - 1.0) / v.shape[1]), _chunks((row_ptr.shape[0] - 1) // 4))
