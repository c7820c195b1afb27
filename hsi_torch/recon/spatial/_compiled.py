"""Compiled CPU kernels of the spatial (TV) solve (numba): the ADMM x-update and the TV prox.

The torch step of :mod:`hsi_torch.recon.spatial.admm` runs every step as ~20 whole-cube kernels
on the ``(M, h, w)`` frame (the invalid corners included) and a batched ``(P, M, M)``
matrix–vector product; at the full-size prototype's frame (25 × 744 × 858, 306 000 valid
pixels) one ADMM iteration streams several GB through memory. These kernels run the same
iterations on the valid pixels only:

* :func:`fgp_block`: one whole ADMM iteration in one pass over the frame — the x-update of
  every row from ``(G + ρI)⁻¹`` packed by rows (:func:`pack_inverse_rows`: the upper triangle,
  half the memory of the dense matrices), the ``J`` dual iterations of the fast gradient
  projection (the same formulas as :func:`hsi_torch.recon.spatial.operators.prox_tv_nonneg`)
  and the final primal, as a wavefront down the rows with each iteration's rows in small rings;
  the state is band-major ``(M, P)``, so every loop runs along a row's pixels and vectorises.
* :func:`sym_apply`: ``S_p x_p`` for symmetric ``S (P|1, M, M)`` (the warm start's ``G x₀``),
  pixel by pixel with ``S`` read as ``M`` contiguous columns.

Two numba details the speed depends on (measured on the full-size frame): a loop over ``M = 25``
bands does not vectorise (LLVM's vector loop takes 64 iterations at a time), and a loop whose
index numba cannot prove non-negative does not either (numba checks a signed index for
wrap-around): the fused pass's loops run along a row's pixels with unsigned indices.

The graph is the valid pixels sorted by their flat frame index, row by row (:func:`fgp_grid`:
each row's pixels, their columns and span, the edge weights on the padded frame grid; a missing
edge has weight 0 and reads a finite entry). Arithmetic in the arrays' dtype; numba is optional
(:mod:`hsi_torch.recon._numba`; the torch step runs without it). The ADMM loop that calls these
kernels, and its stopping rule, is :mod:`hsi_torch.recon.spatial.admm`
(:class:`~hsi_torch.recon.spatial.admm._CompiledStep`).
"""

from __future__ import annotations

import numpy as np

from hsi_torch.recon._numba import AVAILABLE
from hsi_torch.recon._numba import nb as _nb

__all__ = ["AVAILABLE", "sym_apply", "start_state", "norms3", "fgp_grid", "fgp_blocks",
           "fgp_block", "pack_inverse_rows", "row_chunks"]


#: numba's fast-math flags for the TV kernels: reassociation lets the per-pixel sums over bands
#: vectorise (no assumptions about NaN or infinities)
_FAST = {"reassoc", "contract", "nsz", "arcp"}
#: Pixels of a row taken at a time by the x-update of :func:`fgp_block`, and the pixels of one
#: block of the packed inverse (:func:`pack_inverse_rows`): its scratch stays in the first-level
#: cache, and the inverse is read as one sequential stream.
_ROW_CHUNK = 64

if AVAILABLE:

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

    @_nb.njit(parallel=True, cache=True, error_model="numpy")
    def _start_state(b, z0, gram, row_slot, row_gram, rho, bT, zT, uT, num_chunks,
                     lo, u0T, use_u0):  # pragma: no cover - compiled
        n, m = b.shape
        shared = gram.shape[0] == 1
        for ch in _nb.prange(num_chunks):
            z = np.empty(m)
            g = np.empty(m)
            for i in range(ch * n // num_chunks, (ch + 1) * n // num_chunks):
                for j in range(m):
                    zj = z0[i, j]
                    z[j] = zj if zj > lo else lo
                    bT[j, i] = b[i, j]
                    zT[j, i] = z[j]
                if use_u0[i]:  # a given u: this pixel's G is not read
                    for j in range(m):
                        uT[j, i] = u0T[j, i]
                    continue
                for j in range(m):
                    g[j] = 0.0
                k = row_slot[i]
                S = row_gram[k] if k >= 0 else (gram[0] if shared else gram[i])
                for c in range(m):  # S symmetric: column c = row c, contiguous
                    zc = z[c]
                    for j in range(m):
                        g[j] += S[c, j] * zc
                for j in range(m):
                    uT[j, i] = (b[i, j] - g[j]) / rho

    @_nb.njit(parallel=True, cache=True, error_model="numpy")
    def _norms3(z, x, zp, relax, num_chunks):  # pragma: no cover - compiled
        m, n = z.shape
        keep, inv = 1.0 - relax, 1.0 / relax
        acc = np.zeros((num_chunks, 3))
        for ch in _nb.prange(num_chunks):
            a0, a1, a2 = 0.0, 0.0, 0.0
            lo, hi = ch * n // num_chunks, (ch + 1) * n // num_chunks
            for j in range(m):
                for i in range(lo, hi):
                    zi = np.float64(z[j, i])
                    e = zi - np.float64(zp[j, i])
                    d = (np.float64(x[j, i]) - zi + keep * e) * inv
                    a0 += zi * zi
                    a1 += d * d
                    a2 += e * e
            acc[ch, 0], acc[ch, 1], acc[ch, 2] = a0, a1, a2
        return acc.sum(0)

    @_nb.njit(error_model="numpy", fastmath=_FAST)
    def _primal_row(v, t, r, rs, r_up, rs_up, wrow, wfrom, wto, out, a, b, c, off,
                    lo):  # pragma: no cover - compiled
        """``max(v − t (KD)ᵀr, lo)`` (``lo``: 0, or ``−∞`` for no bound) of one row into
        ``out (M, W + 2)``, every column of ``a:b`` (padded indices; the row's span) at once:
        ``r``, ``rs`` the row's dual ``(2, M, W + 2)`` and band sums ``(2, W + 2)``, ``r_up``,
        ``rs_up`` the row above's; ``wrow`` the row's horizontal edge weights (``wrow[X]``:
        column ``X − 1`` to ``X``), ``wfrom`` the vertical ones from the row above, ``wto``
        those to the row below (1-D rows: a 2-D slice is typed non-contiguous). ``K``'s part is
        the same for every band: ``c·(wl Σr_l,x + wu Σr_u,y − wx Σr_x − wy Σr_y)``,
        ``c = (α − 1)/M``; ``off`` ``(W + 2,)`` scratch.
        Columns are unsigned indices: numba checks a signed index for wrap-around, which keeps
        LLVM from vectorising the loops."""
        m = v.shape[0]
        ua, n, one = np.uint64(a), np.uint64(b - a), np.uint64(1)
        for x in range(n):
            X = ua + x
            off[X] = c * (wrow[X - one] * rs[0, X - one] + wfrom[X] * rs_up[1, X]
                          - wrow[X] * rs[0, X] - wto[X] * rs[1, X])
        for j in range(m):
            for x in range(n):
                X = ua + x
                d = (wrow[X - one] * r[0, j, X - one] + wfrom[X] * r_up[1, j, X]
                     - wrow[X] * r[0, j, X] - wto[X] * r[1, j, X] + off[X])
                val = v[j, X] - t * d
                out[j, X] = val if val > lo else lo

    @_nb.njit(error_model="numpy", fastmath=_FAST)
    def _dual_row(zk, zn, r, p_old, p_new, ps_new, r_new, rs_new, want_r, step, mom, one, c,
                  wrow, wdown, a, b, q, sums, scale):  # pragma: no cover - compiled
        """One FGP dual update of one row, every column of ``a:b`` at once (band-major rows, see
        :func:`_primal_row`): ``p_new = Π(r + step·K D z)`` with ``z`` of this row ``zk`` and of
        the next ``zn``, ``r_new = p_new + mom·(p_new − p_old)`` (``want_r``), with the band
        sums; ``wrow`` the horizontal weights, ``wdown`` the vertical ones to the next row;
        ``q (2, M, W + 2)``, ``sums (2, W + 2)``, ``scale (W + 2,)`` scratch."""
        m = zk.shape[0]
        zero = one - one
        ua, n, u1 = np.uint64(a), np.uint64(b - a), np.uint64(1)
        for x in range(n):
            X = ua + x
            sums[0, X] = zero
            sums[1, X] = zero
        for j in range(m):  # D z, and its band sums (K's part)
            for x in range(n):
                X = ua + x
                zi = zk[j, X]
                d0 = step * wrow[X] * (zk[j, X + u1] - zi)
                d1 = step * wdown[X] * (zn[j, X] - zi)
                q[0, j, X] = d0
                q[1, j, X] = d1
                sums[0, X] += d0
                sums[1, X] += d1
        for x in range(n):
            X = ua + x
            sums[0, X] *= c
            sums[1, X] *= c
            scale[X] = zero
        for j in range(m):  # r + step·K D z, and its norm over (2, M)
            for x in range(n):
                X = ua + x
                q0 = r[0, j, X] + q[0, j, X] + sums[0, X]
                q1 = r[1, j, X] + q[1, j, X] + sums[1, X]
                q[0, j, X] = q0
                q[1, j, X] = q1
                scale[X] += q0 * q0 + q1 * q1
        for x in range(n):
            X = ua + x
            n2 = scale[X]
            scale[X] = one / np.sqrt(n2) if n2 > one else one
            sums[0, X] = zero
            sums[1, X] = zero
        for k in range(2):  # the projection, the momentum step, the band sums
            if want_r:  # (the branch outside the loops: a loop with one does not vectorise)
                for x in range(n):
                    rs_new[k, ua + x] = zero
                for j in range(m):
                    for x in range(n):
                        X = ua + x
                        a0 = q[k, j, X] * scale[X]
                        p_new[k, j, X] = a0
                        sums[k, X] += a0
                        b0 = a0 + mom * (a0 - p_old[k, j, X])
                        r_new[k, j, X] = b0
                        rs_new[k, X] += b0
            else:
                for j in range(m):
                    for x in range(n):
                        X = ua + x
                        a0 = q[k, j, X] * scale[X]
                        p_new[k, j, X] = a0
                        sums[k, X] += a0
        for x in range(n):
            X = ua + x
            ps_new[0, X] = sums[0, X]
            ps_new[1, X] = sums[1, X]

    @_nb.njit(error_model="numpy")
    def _load_row(src, dst, lo, hi, x0, col, contiguous):  # pragma: no cover - compiled
        """``dst[k, col_i + 1] = src[k, i]`` for the pixels ``i`` of one row (``src`` band-major
        over pixels, ``dst`` over padded columns: ``(K, P)`` → ``(K, W + 2)``; unsigned
        indices, see :func:`_primal_row`)."""
        n, ulo, u1 = np.uint64(hi - lo), np.uint64(lo), np.uint64(1)
        ux = np.uint64(x0) + u1
        for k in range(src.shape[0]):
            if contiguous:
                for x in range(n):
                    dst[k, ux + x] = src[k, ulo + x]
            else:
                for x in range(n):
                    dst[k, np.uint64(col[ulo + x]) + u1] = src[k, ulo + x]

    @_nb.njit(error_model="numpy")
    def _store_row(src, dst, lo, hi, x0, col, contiguous):  # pragma: no cover - compiled
        """The inverse of :func:`_load_row`: ``dst[k, i] = src[k, col_i + 1]``."""
        n, ulo, u1 = np.uint64(hi - lo), np.uint64(lo), np.uint64(1)
        ux = np.uint64(x0) + u1
        for k in range(dst.shape[0]):
            if contiguous:
                for x in range(n):
                    dst[k, ulo + x] = src[k, ux + x]
            else:
                for x in range(n):
                    dst[k, ulo + x] = src[k, np.uint64(col[ulo + x]) + u1]

    @_nb.njit(error_model="numpy", fastmath=_FAST)
    def _x_row(inv_rows, row_slot, row_inv, has_slot, b, x_in, u_in, z_in, x_out, u_out, rho,
               update_u, own, vrow, lo, hi, x0, col, contiguous, rhs, acc,
               uu, relax):  # pragma: no cover - compiled
        """The ADMM x-update of the pixels of one row on band-major ``(M, P)`` state: ``u ← u_in
        + x_in − z_in`` (``update_u``), ``x = (G + ρI)⁻¹ (b + ρ(z_in − u))`` from the packed
        inverse (:func:`pack_inverse_rows`), ``v = x + u`` into ``vrow (M, W + 2)`` at the
        pixels' padded columns; ``x``, ``u`` into ``x_out``, ``u_out`` only where ``own``
        (a neighbouring block's rows are computed for their ``v`` alone). Pixels with
        ``row_slot ≥ 0`` use ``row_inv[row_slot]`` (their own Gram matrix in this frame;
        ``has_slot``: the row has one). Every loop runs along the row's pixels (vectorised);
        ``rhs``, ``acc``, ``uu``: ``(M, CH)`` scratch, one chunk of the row at a time."""
        m = b.shape[0]
        npair = m * (m + 1) // 2
        ulo, u1 = np.uint64(lo), np.uint64(1)
        ch = np.uint64(rhs.shape[1])
        n_all = np.uint64(hi - lo)
        c0 = np.uint64(0)
        while c0 < n_all:
            n = min(ch, n_all - c0)
            i0 = ulo + c0
            if update_u:
                for j in range(m):
                    for x in range(n):
                        i = i0 + x
                        uj = u_in[j, i] + (x_in[j, i] - z_in[j, i])
                        uu[j, x] = uj
                        rhs[j, x] = b[j, i] + rho * (z_in[j, i] - uj)
                        acc[j, x] = 0
            else:
                for j in range(m):
                    for x in range(n):
                        i = i0 + x
                        uj = u_in[j, i]
                        uu[j, x] = uj
                        rhs[j, x] = b[j, i] + rho * (z_in[j, i] - uj)
                        acc[j, x] = 0
            off = np.uint64(npair) * i0  # this chunk's (npair, n) block
            for cc in range(m):  # the upper triangle by rows: S_cc,j for j ≥ cc
                for x in range(n):
                    acc[cc, x] += inv_rows[off + x] * rhs[cc, x]
                off += n
                for j in range(cc + 1, m):
                    for x in range(n):
                        sv = inv_rows[off + x]
                        acc[j, x] += sv * rhs[cc, x]
                        acc[cc, x] += sv * rhs[j, x]
                    off += n
            if has_slot:  # pixels with their own factor in this frame
                for x in range(n):
                    k = row_slot[i0 + x]
                    if k >= 0:
                        for j in range(m):
                            a = rhs[0, x] * row_inv[k, 0, j]
                            for cc in range(1, m):
                                a += rhs[cc, x] * row_inv[k, cc, j]
                            acc[j, x] = a
            if relax != 1:  # over-relaxation: x̂ = a·x + (1 − a)·z_in replaces x
                keep = 1 - relax
                for j in range(m):
                    for x in range(n):
                        acc[j, x] = relax * acc[j, x] + keep * z_in[j, i0 + x]
            if contiguous:
                ux = np.uint64(x0) + u1 + c0
                for j in range(m):
                    for x in range(n):
                        vrow[j, ux + x] = acc[j, x] + uu[j, x]
            else:
                for j in range(m):
                    for x in range(n):
                        vrow[j, np.uint64(col[i0 + x]) + u1] = acc[j, x] + uu[j, x]
            if own:
                for j in range(m):
                    for x in range(n):
                        x_out[j, i0 + x] = acc[j, x]
                        u_out[j, i0 + x] = uu[j, x]
            c0 += ch

    @_nb.njit(parallel=True, cache=True, error_model="numpy")
    def _pack_rows(inv, start, row_ptr, out, ch):  # pragma: no cover - compiled
        """Pack ``inv (n, M, M)`` (the pixels ``start:start + n``) into ``out`` (the layout of
        :func:`pack_inverse_rows`), rows of pixels in parallel."""
        n, m = inv.shape[0], inv.shape[1]
        npair = m * (m + 1) // 2
        h = row_ptr.shape[0] - 1
        for y in _nb.prange(h):
            lo, hi = row_ptr[y], row_ptr[y + 1]
            if hi <= start or lo >= start + n:
                continue
            c0 = lo
            while c0 < hi:
                c1 = min(c0 + ch, hi)
                if c0 >= start and c1 <= start + n:
                    length = c1 - c0
                    off = npair * c0
                    for cc in range(m):
                        for j in range(cc, m):
                            for x in range(length):
                                out[off + x] = inv[c0 - start + x, cc, j]
                            off += length
                c0 = c1

    @_nb.njit(error_model="numpy", fastmath=_FAST)
    def _fgp_one_block(bi, inv_rows, row_slot, row_inv, row_has_slot, b, x_in, u_in, z_in,
                       x_out, u_out, rho, update_u, t, step, moms, one, c, p_in, ps_in, p_out,
                       ps_out, z_out, blocks, row_ptr, col, span, ex, ey, zlo,
                       relax):  # pragma: no cover
        """One block of rows of :func:`_fgp_block` (its own thread)."""
        n_it = moms.shape[0]
        m = b.shape[0]
        dt = b.dtype
        h = row_ptr.shape[0] - 1
        width = ex.shape[1]  # W + 2: a zero column on each side
        nv = n_it + 3  # rows of v in flight: loaded one row ahead, read until the final primal
        ra, rb = blocks[bi], blocks[bi + 1]
        if ra >= rb:
            return
        # band-major rows over padded columns, finite everywhere (missing edges read 0·x):
        # per dual iteration j its input r (ring of 4 rows; j = 0: the rows of p_in), the p
        # of its momentum (j ≥ 1; j = 0 reads r), the primal z (ring of 2 rows)
        ring_v = np.zeros((nv, m, width), dt)
        ring_r = np.zeros((n_it + 1, 4, 2, m, width), dt)
        ring_rs = np.zeros((n_it + 1, 4, 2, width), dt)
        ring_p = np.zeros((n_it + 1, 4, 2, m, width), dt)
        ring_ps = np.zeros((n_it + 1, 4, 2, width), dt)
        ring_z = np.zeros((n_it, 2, m, width), dt)
        q = np.empty((2, m, width), dt)
        sums = np.empty((2, width), dt)
        scale = np.empty(width, dt)
        zrow = np.zeros((m, width), dt)
        rhs = np.empty((m, _ROW_CHUNK), dt)
        acc = np.empty((m, _ROW_CHUNK), dt)
        uu = np.empty((m, _ROW_CHUNK), dt)
        first0 = max(ra - n_it, 0)
        for s in range(ra - n_it - 2, rb + n_it):
            # the input rows of iteration 0 one row ahead: p_in, its sums, and v from the
            # row's x-update
            y_in = s + 1
            if first0 - 1 <= y_in < min(rb + n_it + 1, h) and y_in >= 0:
                lo, hi = row_ptr[y_in], row_ptr[y_in + 1]
                x0 = span[y_in, 0]
                cont = span[y_in, 1] - x0 == hi - lo
                sl = y_in & 3
                for k in range(2):
                    _load_row(p_in[k], ring_r[0, sl, k], lo, hi, x0, col, cont)
                _load_row(ps_in, ring_rs[0, sl], lo, hi, x0, col, cont)
                _x_row(inv_rows, row_slot, row_inv, row_has_slot[y_in], b, x_in, u_in, z_in,
                       x_out, u_out, rho, update_u, ra <= y_in < rb, ring_v[y_in % nv], lo,
                       hi, x0, col, cont, rhs, acc, uu, relax)
            for j in range(n_it + 1):
                y = s - j
                if j < n_it:
                    ylo = max(ra - (n_it - j), 0)
                    yhi = min(rb + (n_it - j), h)
                else:
                    ylo, yhi = ra, rb
                if y < ylo or y >= yhi:
                    continue
                xa = span[y, 0] + 1
                xb = span[y, 1] + 1
                wrow = ex[y]
                wfrom, wto = ey[y], ey[y + 1]  # the edges from the row above, to the next
                up = (y - 1) & 3
                if j == n_it:  # the primal of the final dual, scattered into z_out
                    _primal_row(ring_v[y % nv], t, ring_p[n_it, y & 3], ring_ps[n_it, y & 3],
                                ring_p[n_it, up], ring_ps[n_it, up], wrow, wfrom, wto, zrow,
                                xa, xb, c, scale, zlo)
                    lo, hi = row_ptr[y], row_ptr[y + 1]
                    x0 = span[y, 0]
                    cont = span[y, 1] - x0 == hi - lo
                    _store_row(zrow, z_out, lo, hi, x0, col, cont)
                    continue
                rr, rrs = ring_r[j], ring_rs[j]
                p_old = rr[y & 3] if j == 0 else ring_p[j, y & 3]
                if y == ylo:  # this iteration's first row: its own primal first
                    _primal_row(ring_v[y % nv], t, rr[y & 3], rrs[y & 3], rr[up], rrs[up],
                                wrow, wfrom, wto, ring_z[j, y & 1], xa, xb, c, scale, zlo)
                if y + 1 < h:  # the next row's primal, from r before this row's update
                    a2, b2 = span[y + 1, 0] + 1, span[y + 1, 1] + 1
                    _primal_row(ring_v[(y + 1) % nv], t, rr[(y + 1) & 3], rrs[(y + 1) & 3],
                                rr[y & 3], rrs[y & 3], ex[y + 1], ey[y + 1], ey[y + 2],
                                ring_z[j, (y + 1) & 1], a2, b2, c, scale, zlo)
                last = j + 1 == n_it
                _dual_row(ring_z[j, y & 1], ring_z[j, (y + 1) & 1], rr[y & 3], p_old,
                          ring_p[j + 1, y & 3], ring_ps[j + 1, y & 3], ring_r[j + 1, y & 3],
                          ring_rs[j + 1, y & 3], not last, step, moms[j], one, c, wrow,
                          wto, xa, xb, q, sums, scale)
                if last and ra <= y < rb:  # the final dual of the owned rows
                    lo, hi = row_ptr[y], row_ptr[y + 1]
                    x0 = span[y, 0]
                    cont = span[y, 1] - x0 == hi - lo
                    for k in range(2):
                        _store_row(ring_p[n_it, y & 3, k], p_out[k], lo, hi, x0, col, cont)
                    _store_row(ring_ps[n_it, y & 3], ps_out, lo, hi, x0, col, cont)

    @_nb.njit(parallel=True, cache=True, error_model="numpy", fastmath=_FAST)
    def _fgp_block(inv_rows, row_slot, row_inv, row_has_slot, b, x_in, u_in, z_in, x_out, u_out,
                   rho, update_u, t, step, moms, one, c, p_in, ps_in, p_out, ps_out, z_out, blocks,
                   row_ptr, col, span, ex, ey, zlo, relax):  # pragma: no cover - compiled
        for bi in _nb.prange(blocks.shape[0] - 1):
            # int64 both when typed and when lowered (prange's index is then
            # uint64): one compiled signature, not two
            _fgp_one_block(np.int64(bi), inv_rows, row_slot, row_inv, row_has_slot, b, x_in, u_in,
                           z_in, x_out, u_out, rho, update_u, t, step, moms, one, c, p_in, ps_in,
                           p_out, ps_out, z_out, blocks, row_ptr, col, span, ex, ey, zlo, relax)


def _chunks(n: int) -> int:
    return max(1, min(n, 64))


def sym_apply(mat: np.ndarray, x: np.ndarray, out: np.ndarray) -> None:
    """``out_p = S_p x_p`` for symmetric ``mat (P|1, M, M)`` and ``x, out (P, M)`` (all
    C-contiguous, one dtype; ``out`` may not be ``x``)."""
    n = x.shape[0]
    if n:
        _sym_apply(mat, x, out, _chunks(n // 256))


def start_state(b: np.ndarray, z0: np.ndarray, gram: np.ndarray, row_slot: np.ndarray,
                row_gram: np.ndarray, rho: float, nonneg: bool = True,
                u0: np.ndarray | None = None, use_u0: np.ndarray | None = None,
                out: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ADMM warm start on band-major state, in one pass: ``z = max(z0, 0)`` (``z = z0``
    without ``nonneg``), ``u = (b − G z)/ρ`` (pixels with ``row_slot ≥ 0``: their
    ``row_gram``), with ``b``, as ``(M, P)`` arrays (``b``, ``z0`` pixel-major ``(P, M)``;
    ``gram (P|1, M, M)`` symmetric).

    Args:
        u0: ``(M, P)`` band-major scaled dual to start from on the pixels ``use_u0`` (``(P,)``
            bool): there ``u = u0`` and the pixel's ``G`` is not read (a sequence's static
            pixels: most of a mapped Gram stack's pages are not touched); ``None``: nowhere.
        out: ``(bT, zT, uT)`` ``(M, P)`` C-contiguous arrays of ``b``'s dtype to write into
            (buffers kept between solves; every element is written); ``None``: new arrays.

    Returns:
        ``bT``, ``zT``, ``uT``.
    """
    n, m = b.shape
    if out is not None and all(a.shape == (m, n) and a.dtype == b.dtype
                               and a.flags.c_contiguous for a in out):
        bT, zT, uT = out
    else:
        bT, zT, uT = (np.empty((m, n), b.dtype) for _ in range(3))
    if u0 is None or use_u0 is None:
        u0, use_u0 = np.zeros((m, 1), b.dtype), np.zeros(n, np.bool_)
    else:
        if u0.shape != (m, n) or use_u0.shape != (n,):
            raise ValueError(f"u0 must be ({m}, {n}) and use_u0 ({n},), got "
                             f"{u0.shape} and {use_u0.shape}")
        u0 = np.ascontiguousarray(u0, b.dtype)
        use_u0 = np.ascontiguousarray(use_u0, np.bool_)
    if n:
        _start_state(b, z0, gram, row_slot, row_gram, float(rho), bT, zT, uT,
                     _chunks(n // 256), 0.0 if nonneg else -np.inf, u0, use_u0)
    return bT, zT, uT


def norms3(z: np.ndarray, x: np.ndarray, z_prev: np.ndarray,
           relax: float = 1.0) -> tuple[float, float, float]:
    """``‖z‖``, ``‖x − z‖``, ``‖z − z_prev‖`` of three ``(M, P)`` C-contiguous arrays of one
    dtype in one parallel pass, no temporaries (sums in float64). With ``relax = a ≠ 1`` the
    given ``x`` is the relaxed ``x̂ = a·x + (1 − a)·z_prev`` that :func:`fgp_block` stores, and
    the second norm is that of the unrelaxed ``x``: ``(x̂ − z + (1 − a)(z − z_prev))/a``."""
    n = z.shape[1]
    acc = _norms3(z, x, z_prev, float(relax), _chunks(n // 4096))
    return float(np.sqrt(acc[0])), float(np.sqrt(acc[1])), float(np.sqrt(acc[2]))


def fgp_grid(graph: tuple[np.ndarray, ...], pixel_index: np.ndarray, frame_size: tuple[int, int],
             ex: np.ndarray, ey: np.ndarray) -> tuple[np.ndarray, ...]:
    """The row layout of :func:`fgp_block`: ``(row_ptr, col, span, EX, EY)`` — the pixels of
    row ``y`` are ``row_ptr[y]:row_ptr[y + 1]`` at columns ``col``, spanning ``span[y] = [x0,
    x1)`` (``x0 = x1 = 0`` for an empty row); ``EX (h, w + 2)``: the horizontal edge weights
    (``EX[y, x + 1]``: column ``x`` to ``x + 1``), ``EY (h + 2, w + 2)``: the vertical ones
    (``EY[y + 1, x + 1]``: row ``y`` to ``y + 1``), zero-padded so that every neighbour read
    is in range."""
    h, w = frame_size
    row_ptr = graph[0]
    col = (pixel_index % w).astype(np.int64)
    span = np.zeros((h, 2), np.int64)
    rows = np.nonzero(np.diff(row_ptr) > 0)[0]
    span[rows, 0] = col[row_ptr[rows]]
    span[rows, 1] = col[row_ptr[rows + 1] - 1] + 1
    EX = np.zeros((h, w + 2), ex.dtype)
    EX[:, 1:w + 1] = ex
    EY = np.zeros((h + 2, w + 2), ey.dtype)
    EY[1:h + 1, 1:w + 1] = ey
    return row_ptr, col, span, EX, EY


def fgp_blocks(row_ptr: np.ndarray, num_blocks: int) -> np.ndarray:
    """Row boundaries ``(B + 1,)`` of :func:`fgp_block`'s blocks: ``num_blocks`` runs of whole
    rows with about the same number of pixels each (one per thread: every block also computes
    a few rows of its neighbours' iterations, see :func:`fgp_block`)."""
    h = row_ptr.shape[0] - 1
    n = int(row_ptr[-1])
    nb = max(1, min(int(num_blocks), h))
    cuts = np.searchsorted(row_ptr, np.arange(1, nb) * n / nb, side="left")
    return np.unique(np.concatenate([[0], np.clip(cuts, 0, h), [h]])).astype(np.int64)


def pack_inverse_rows(inverse_chunks, row_ptr: np.ndarray, m: int,
                      dtype: np.dtype) -> np.ndarray:
    """The symmetric ``(G_p + ρI)⁻¹`` of every pixel, packed for :func:`fgp_block`: the upper
    triangle (``M(M + 1)/2`` numbers a pixel instead of ``M²``), blocked by runs of up to
    :data:`_ROW_CHUNK` pixels of one row, each run's ``(M(M + 1)/2, n)`` block contiguous (entry
    ``(cc, j ≥ cc)`` of the run's pixel ``x`` at ``npair·start + t·n + x``, ``t`` the pair's
    index by rows). The x-update then reads it as one sequential stream and every operation
    runs along a run's pixels.

    Args:
        inverse_chunks: an iterable of ``(start, inv)`` with ``inv (n, M, M)`` the inverses of
            the pixels ``start:start + n``, each chunk whole rows (in order).
        row_ptr: ``(h + 1,)`` the rows' pixel ranges.

    Returns:
        ``(P·M(M + 1)/2,)`` array of ``dtype``.
    """
    P = int(row_ptr[-1])
    out = np.empty(P * (m * (m + 1) // 2), dtype)
    for start, inv in inverse_chunks:
        _pack_rows(np.ascontiguousarray(inv, dtype), int(start), row_ptr, out, _ROW_CHUNK)
    return out


def row_chunks(row_ptr: np.ndarray, max_pixels: int) -> list[tuple[int, int]]:
    """Ranges ``(start, stop)`` of whole rows with at most ``max_pixels`` pixels each (a row
    larger than that alone)."""
    out, start = [], 0
    h = row_ptr.shape[0] - 1
    y = 0
    while y < h:
        y1 = y + 1
        while y1 < h and row_ptr[y1 + 1] - row_ptr[y] <= max_pixels:
            y1 += 1
        stop = int(row_ptr[y1])
        if stop > start:
            out.append((start, stop))
        start, y = stop, y1
    return out


def fgp_block(inv_rows: np.ndarray, row_slot: np.ndarray, row_inv: np.ndarray,
              row_has_slot: np.ndarray, b: np.ndarray, x_in: np.ndarray, u_in: np.ndarray,
              z_in: np.ndarray, x_out: np.ndarray, u_out: np.ndarray, rho: float,
              update_u: bool, t: float, step: float, moms: np.ndarray, p_in: np.ndarray,
              ps_in: np.ndarray, p_out: np.ndarray, ps_out: np.ndarray, z_out: np.ndarray,
              grid: tuple[np.ndarray, ...], blocks: np.ndarray,
              brightness_weight: float = 1.0, nonneg: bool = True, relax: float = 1.0) -> None:
    """One ADMM iteration in one pass over the frame, on band-major ``(M, P)`` state: the
    x-update (``u ← u_in + x_in − z_in`` if ``update_u``, ``x = (G + ρI)⁻¹(b + ρ(z_in − u))``,
    ``v = x + u``), then ``J = len(moms)`` FGP dual iterations of the TV prox from ``r = p_in``
    and the primal of the last: ``p ← Π(r + step·K D z(r))``, ``r ← p_new + moms[j]·(p_new −
    p_old)``, ``z(r) = max(v − t (KD)ᵀr, 0)``; out: ``x_out``, ``u_out``, the final dual
    ``p_out`` (band sums ``ps_out``) and ``z_out = z(p_out)``. With ``J = 0`` and ``t = 0``
    (``λ = 0``): ``z_out = max(v, 0)`` and the dual is left alone. Over-relaxed (``relax = a ≠
    1``): ``x̂ = a·x + (1 − a)·z_in`` replaces ``x`` in ``v``, in ``x_out`` and so in the next
    iteration's ``u`` update.

    The iterations of :func:`hsi_torch.recon.spatial.operators.prox_tv_nonneg` on the valid
    pixels, fused: dual iteration ``j`` of row ``y`` needs iteration ``j − 1`` of rows ``y − 1 …
    y + 1`` only, so the iterations run as a wavefront down the rows (at step ``s`` iteration
    ``j`` updates row ``s − j``; the x-update of row ``s + 1`` feeds it), each iteration's rows
    kept in a ring of four; a pixel's bytes cross the memory bus once per ADMM iteration, and the
    x-update's stream of the packed inverse overlaps the prox's arithmetic. A row is held
    band-major over its columns (``(2, M, W + 2)``), so every operation runs along the row's
    columns and vectorises (a loop over ``M = 25`` bands per pixel does not). The rows are split
    into ``blocks`` (one per thread); a block also computes the rows its iterations need from
    its neighbours (``J − j`` rows on each side for iteration ``j``, one more for the
    x-update: redundant work; the inputs are only read, every output is double-buffered), so
    blocks never wait for each other. ``K``: the brightness weighting ``I − (1 − α) u uᵀ``
    (``u`` the flat spectrum), applied through band sums. Without ``nonneg`` the primal is not
    projected (``z(r) = v − t (KD)ᵀr``: the prox of the TV alone).

    Args:
        inv_rows: :func:`pack_inverse_rows`; row_slot: ``(P,)`` int64, ``≥ 0`` where a pixel
            uses ``row_inv[row_slot]`` ``(k ≥ 1, M, M)`` instead; row_has_slot: ``(h,)`` bool,
            the rows holding such a pixel; b, x_*, u_*, z_*: ``(M, P)`` band-major (``_in`` and
            ``_out`` distinct); p_in, p_out: ``(2, M, P)``, ps_in, ps_out: ``(2, P)`` their band
            sums; moms: ``(J,)`` FISTA weights (``moms[0] = 0``); grid: :func:`fgp_grid`;
            blocks: :func:`fgp_blocks`.
    """
    row_ptr, col, span, EX, EY = grid
    ty = b.dtype.type
    c = ty((brightness_weight - 1.0) / b.shape[0])
    _fgp_block(inv_rows, row_slot, row_inv, row_has_slot, b, x_in, u_in, z_in, x_out, u_out,
               ty(rho), bool(update_u), ty(t), ty(step), np.asarray(moms, b.dtype), ty(1), c,
               p_in, ps_in, p_out, ps_out, z_out, blocks, row_ptr, col, span, EX, EY,
               ty(0 if nonneg else -np.inf), ty(relax))
