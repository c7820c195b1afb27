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

Only the first zero set differs (:data:`~hsi_torch.recon.nnls.constants.START_SWEEPS`,
:func:`_start_zero_set`): same answers (to rounding and the KKT tolerance), fewer rounds.

numba is an optional accelerator (:mod:`hsi_torch.recon._numba`): without it (or with
``HSI_TORCH_NO_NUMBA=1``) the batched torch kernels are used. The first call in a new
environment compiles the kernel (~15 s, cached on disk by numba next to this file, or in
``NUMBA_CACHE_DIR``).
"""

from __future__ import annotations

import numpy as np

from hsi_torch.recon._numba import AVAILABLE, threads
from hsi_torch.recon._numba import nb as _nb
from hsi_torch.recon.nnls.constants import (
    COMPILED_FLOOR,
    INFEASIBILITY_FRACTION,
    MURTY_PATIENCE,
    START_SWEEPS,
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
    def _start_zero_set(G, p, x0, gd, sweeps, xc, gc, w, Z):  # pragma: no cover - compiled
        """The first zero set ``Z`` of pixel ``p`` (:data:`START_SWEEPS`): ``sweeps`` sweeps of
        projected coordinate descent on ``½xᵀGx − bᵀx`` from ``max(x0, 0)``, then
        ``Z = {j : x_j − g_j / G_jj ≤ 0}``. Runs in the dtype of ``G`` (the scratch ``xc (M,)``,
        ``gc (M + 1,)``, ``w (M,)``): it only chooses where to start. The gradient at the start
        is ``g = G(max(x0, 0) − x0)`` (``G x0 = b``): the columns of the negative entries only.
        Each step updates ``g`` by a row of ``G``; the next coordinate's ``g_j`` is carried in a
        register (read before the row update, plus its own term), not re-read from the stored
        row."""
        m = x0.shape[0]
        zero = gc[m] - gc[m]  # 0 in the dtype of G
        for i in range(m + 1):
            gc[i] = zero
        for j in range(m):
            xc[j] = x0[j]
            w[j] = 1.0 / gd[p, j]
        for j in range(m):
            xj = xc[j]
            if xj < zero:
                xc[j] = zero
                for i in range(m):
                    gc[i] -= G[p, j, i] * xj
        for _ in range(sweeps):
            gj = gc[0]
            for j in range(m):
                xj = xc[j]
                if xj == zero and gj >= zero:  # at the bound, and the gradient keeps it there
                    gj = gc[j + 1]
                    continue
                nv = xj - gj * w[j]
                nv = nv if nv > zero else zero
                d = nv - xj
                xc[j] = nv
                gn = gc[j + 1]
                if j + 1 < m:
                    gn += G[p, j, j + 1] * d
                for i in range(m):
                    gc[i] += G[p, j, i] * d
                gj = gn
        for j in range(m):
            Z[j] = xc[j] - gc[j] * w[j] <= zero

    @_nb.njit(cache=True, inline="always", error_model="numpy")
    def _bpp_pixel(G, H, p, x0, b, gd, t, max_rounds, half, patience, S, rhs, idx, x, lam,
                   Z, viol):  # pragma: no cover - compiled
        """One pixel's rounds from the zero set in ``Z`` (``G[p]``, ``H[p]``: its ``(M, M)``
        matrices, indexed in place: a slice per pixel would cost numba a reference count);
        returns ``(status, rounds, gradient)``: ``x``, ``Z`` hold the answer, and where
        ``gradient`` the last round was a free-set solve, whose ``lam`` holds the whole
        ``G x − b`` (summed as :func:`_kkt` sums it); ``viol (M,)`` int64 scratch."""
        m = x0.shape[0]
        best = m + 1
        backup = patience
        rnd = 0
        kz = 0
        for j in range(m):
            kz += np.int64(Z[j])
        while rnd < max_rounds:
            rnd += 1
            k = 0
            free = kz > half
            if not free:  # zero-set solve through H
                for j in range(m):  # branch-free: a zero set is no pattern a predictor learns
                    idx[k] = j
                    k += np.int64(Z[j])
                for a in range(k):
                    ia = idx[a]
                    for c in range(a + 1):
                        S[a, c] = H[p, ia, idx[c]]
                    rhs[a] = -x0[ia]
                if not _chol_solve(S, rhs, k):
                    return FACTOR_FAILED, rnd, False
                for j in range(m):
                    x[j] = x0[j]
                for a in range(k):
                    ra = rhs[a]
                    ia = idx[a]
                    for j in range(m):
                        x[j] += H[p, ia, j] * ra
                for a in range(k):
                    x[idx[a]] = 0.0
                    lam[idx[a]] = rhs[a]
            else:  # free-set solve through G
                for j in range(m):
                    idx[k] = j
                    k += 1 - np.int64(Z[j])
                for a in range(k):
                    ia = idx[a]
                    for c in range(a + 1):
                        S[a, c] = G[p, ia, idx[c]]
                    rhs[a] = b[ia]
                if not _chol_solve(S, rhs, k):
                    return FACTOR_FAILED, rnd, False
                for j in range(m):
                    x[j] = 0.0
                    lam[j] = -b[j]
                for a in range(k):
                    ra = rhs[a]
                    ia = idx[a]
                    x[ia] = ra
                    for j in range(m):
                        lam[j] += G[p, ia, j] * ra
            nv = 0
            dk = 0
            for j in range(m):  # infeasible: λ_j < −t on Z, x_j G_jj < −t on F (vectorises)
                zj = Z[j]
                v = lam[j] if zj else x[j] * gd[p, j]
                vj = np.int64(v < -t)
                viol[j] = vj
                nv += vj
                dk += vj * (1 - 2 * np.int64(zj))  # change of |Z| by a full exchange
            if nv == 0:
                return DONE, rnd, free
            improved = nv < best
            full = improved or backup >= 1
            backup = patience if improved else max(backup - 1, 0)
            if improved:
                best = nv
            if full:
                for j in range(m):
                    Z[j] = (np.int64(Z[j]) ^ viol[j]) != 0
                kz += dk
            else:  # Murty: the largest infeasible index only
                last = m - 1
                while not viol[last]:
                    last -= 1
                kz += 1 - 2 * np.int64(Z[last])
                Z[last] = not Z[last]
        return NOT_FINISHED, rnd, False

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
        return _kkt_of(p, x, gd, gn, bn, g, floor)

    @_nb.njit(cache=True, inline="always", error_model="numpy")
    def _kkt_of(p, x, gd, gn, bn, g, floor):  # pragma: no cover - compiled
        """The relative KKT residual of ``x`` with its gradient ``g = G x − b`` given."""
        m = x.shape[0]
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

    @_nb.njit(cache=True, error_model="numpy")
    def _frame_kernel_chunk(ch, G, H, b, gd, gn, skip, tol, max_rounds, refine, frac, half,
                            patience, floor, sweeps, x_out, z_out, plain, r_out, status, rounds,
                            num_chunks, fused, y, mask, Bt, gain, resp, zinit,
                            use_init):  # pragma: no cover
        """One chunk of :func:`_frame_kernel`'s pixels (one thread's work)."""
        n, m = b.shape
        shared = G.shape[0] == 1
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
        xc = np.empty(m, G.dtype)  # the start's coordinate descent, in G's dtype
        gc = np.zeros(m + 1, G.dtype)
        wc = np.empty(m, G.dtype)
        for r in range(ch * n // num_chunks, (ch + 1) * n // num_chunks):
            p = 0 if shared else r
            if fused:  # b = Aᵀ W y from the factors, stored (rounded to b's dtype)
                dark = True  # no observation: b = 0 without reading the pixel's factors
                for o in range(y.shape[1]):
                    if y[r, o] != 0.0:
                        dark = False
                        break
                if dark:
                    for j in range(m):
                        rhs[j] = 0.0
                else:
                    _rhs(y, mask, Bt, gain, resp, r, rhs)
                for j in range(m):
                    b[r, j] = rhs[j]
            bn = 0.0
            for j in range(m):
                br[j] = b[r, j]
                bn += br[j] * br[j]
            bn = np.sqrt(bn)
            if bn == 0.0:  # b = 0: x = 0 is the answer (KKT residual 0); G and H not read
                for j in range(m):
                    x_out[r, j] = 0.0
                    z_out[r, j] = False
                plain[r] = not skip[r]
                r_out[r] = 0.0
                status[r] = DONE
                rounds[r] = 0
                continue
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
            st, rnd, have_g = DONE, 0, False
            if need:
                if use_init:  # a given start (the previous frame's zero set)
                    for j in range(m):
                        Z[j] = zinit[r, j]
                elif sweeps > 0:
                    _start_zero_set(G, p, x0, gd, sweeps, xc, gc, wc, Z)
                else:
                    for j in range(m):
                        Z[j] = x0[j] * gd[p, j] < -t
                st, rnd, have_g = _bpp_pixel(G, H, p, x0, br, gd, t, max_rounds, half,
                                             patience, S, rhs, idx, x, lam, Z, viol)
                for j in range(m):
                    if not (x[j] > 0.0):
                        have_g = have_g and x[j] == 0.0  # a clamped entry changes G x
                        x[j] = 0.0
            else:
                for j in range(m):
                    x[j] = x0[j] if x0[j] > 0.0 else 0.0
                    Z[j] = False
            if have_g:  # the last round's G x − b, the same sums as _kkt
                for j in range(m):
                    g[j] = lam[j]
                res = _kkt_of(p, x, gd, gn[p], bn, g, floor)
            else:
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
            anyz = False
            for j in range(m):
                x_out[r, j] = x[j]
                z_out[r, j] = Z[j]
                anyz |= Z[j]
            plain[r] = not (anyz or skip[r])
            r_out[r] = res
            status[r] = st
            rounds[r] = rnd

    @_nb.njit(parallel=True, cache=True, error_model="numpy")
    def _frame_kernel(G, H, b, gd, gn, skip, tol, max_rounds, refine, frac, half, patience,
                      floor, sweeps, x_out, z_out, plain, r_out, status, rounds, num_chunks,
                      fused, y, mask, Bt, gain, resp, zinit,
                      use_init):  # pragma: no cover - compiled
        for ch in _nb.prange(num_chunks):
            # int64 both when typed and when lowered (prange's index is then
            # uint64): one compiled signature, not two
            _frame_kernel_chunk(np.int64(ch), G, H, b, gd, gn, skip, tol, max_rounds, refine, frac,
                                half, patience, floor, sweeps, x_out, z_out, plain, r_out, status,
                                rounds, num_chunks, fused, y, mask, Bt, gain, resp, zinit,
                                use_init)

    @_nb.njit(parallel=True, cache=True, error_model="numpy")
    def _adjoint_kernel(y, mask, Bt, gain, resp, out, num_chunks):  # pragma: no cover
        n, m = out.shape
        for ch in _nb.prange(num_chunks):
            acc = np.empty(m)
            for r in range(ch * n // num_chunks, (ch + 1) * n // num_chunks):
                _rhs(y, mask, Bt, gain, resp, r, acc)
                for j in range(m):
                    out[r, j] = acc[j]

    @_nb.njit(cache=True, error_model="numpy")
    def _factor_kernel_chunk(ch, Bt, gain, resp, mask, masked, R, rel, G, H, gd, gn, singular,
                             no_data, num_chunks):  # pragma: no cover - compiled
        """One chunk of :func:`_factor_kernel`'s pixels (one thread's work)."""
        n, V, m = Bt.shape
        C = resp.shape[0]
        S = np.empty((m, m))
        T = np.empty((m, m))
        RR = np.empty((m, m))
        a = np.empty(m)
        v = np.empty(m)
        u = np.empty(m)
        for i in range(m):  # Σ_c r_ci r_cj: the response part of a whole view
            for j in range(m):
                RR[i, j] = 0.0
            for c in range(C):
                ri = np.float64(resp[c, i])
                for j in range(m):
                    RR[i, j] += ri * resp[c, j]
        for r in range(ch * n // num_chunks, (ch + 1) * n // num_chunks):
            for i in range(m):
                for j in range(m):
                    T[i, j] = 0.0
                    S[i, j] = 0.0
            nobs = 0
            for vv in range(V):
                g2 = np.float64(gain[r, vv]) * gain[r, vv]
                non = 0
                for c in range(C):
                    non += np.int64((not masked) or mask[r, vv * C + c])
                nobs += non
                if non == C:  # a whole view: g_v² B_v B_vᵀ, ⊙ Σ_c r_c r_cᵀ below
                    for i in range(m):
                        bi = g2 * Bt[r, vv, i]
                        for j in range(m):
                            T[i, j] += bi * Bt[r, vv, j]
                elif non > 0:  # a view split by the mask: one observation at a time
                    for c in range(C):
                        if not mask[r, vv * C + c]:
                            continue
                        for j in range(m):
                            a[j] = np.float64(Bt[r, vv, j]) * resp[c, j]
                        for i in range(m):
                            ai = g2 * a[i]
                            for j in range(m):
                                S[i, j] += ai * a[j]
            for i in range(m):
                for j in range(m):
                    T[i, j] = T[i, j] * RR[i, j] + S[i, j]
            dmax = 0.0
            for i in range(m):  # G = T + R from the lower triangle: exactly symmetric
                for j in range(i + 1):
                    G[r, i, j] = T[i, j] + R[i, j]  # rounded to G's dtype
                    G[r, j, i] = G[r, i, j]
                    S[i, j] = G[r, i, j]  # the stored G is what is factorised
                gd[r, i] = G[r, i, i]
                dmax = max(dmax, np.float64(gd[r, i]))
            # lower bound of ‖G‖₂: three power steps from the ones vector, Rayleigh quotient
            for i in range(m):
                v[i] = 1.0
            for _ in range(3):
                for i in range(m):
                    u[i] = 0.0
                _symv(G, r, v, u, 1.0)
                nrm = 0.0
                for i in range(m):
                    nrm += u[i] * u[i]
                nrm = np.sqrt(nrm)
                nrm = nrm if nrm > COMPILED_FLOOR else COMPILED_FLOOR
                for i in range(m):
                    v[i] = u[i] / nrm
            for i in range(m):
                u[i] = 0.0
            _symv(G, r, v, u, 1.0)
            rq = 0.0
            for i in range(m):
                rq += u[i] * v[i]
            rq = rq if rq > dmax else dmax
            gn[r] = rq if rq > 0.0 else 0.0
            # Cholesky G = L Lᵀ (float64, rows of L); the smallest pivot decides singularity
            pmin = np.inf
            failed = False  # a pivot ≤ 0 or not finite (NaN or inf in the data)
            for j in range(m):
                sj = S[j, j]
                for c in range(j):
                    sj -= S[j, c] * S[j, c]
                pmin = sj if sj < pmin else pmin
                if not (sj > 0.0) or not np.isfinite(sj):
                    failed = True
                    break
                d = np.sqrt(sj)
                inv = 1.0 / d
                S[j, j] = d
                for i in range(j + 1, m):
                    t = S[i, j]
                    for c in range(j):
                        t -= S[i, c] * S[j, c]
                    S[i, j] = t * inv
            bad = (failed or not (pmin > rel * dmax) or not (pmin < np.inf)
                   or not np.isfinite(dmax) or nobs == 0)
            singular[r] = bad
            no_data[r] = nobs == 0
            if bad:
                for i in range(m):
                    for j in range(m):
                        H[r, i, j] = 0.0
                continue
            for i in range(m):  # T = L⁻¹ (lower), by rows: T_i = −(Σ_c<i L_ic T_c) / L_ii
                for j in range(i):
                    u[j] = 0.0
                for c in range(i):
                    lic = S[i, c]
                    for j in range(c + 1):
                        u[j] -= lic * T[c, j]
                inv = 1.0 / S[i, i]
                for j in range(i):
                    T[i, j] = u[j] * inv
                T[i, i] = inv
            for i in range(m):  # H = L⁻ᵀ L⁻¹, lower triangle: Σ_{k ≥ i} T_ki T_kj
                for j in range(i + 1):
                    S[i, j] = 0.0
            for k in range(m):
                for i in range(k + 1):
                    tki = T[k, i]
                    for j in range(i + 1):
                        S[i, j] += tki * T[k, j]
            for i in range(m):
                for j in range(i + 1):
                    H[r, i, j] = S[i, j]
                    H[r, j, i] = H[r, i, j]

    @_nb.njit(parallel=True, cache=True, error_model="numpy")
    def _factor_kernel(Bt, gain, resp, mask, masked, R, rel, G, H, gd, gn, singular, no_data,
                       num_chunks):  # pragma: no cover - compiled
        for ch in _nb.prange(num_chunks):
            # int64 both when typed and when lowered (prange's index is then
            # uint64): one compiled signature, not two
            _factor_kernel_chunk(np.int64(ch), Bt, gain, resp, mask, masked, R, rel, G, H, gd, gn,
                                 singular, no_data, num_chunks)


def solve_frame_cpu(
    G: np.ndarray, H: np.ndarray, b: np.ndarray, gd: np.ndarray, gn: np.ndarray,
    skip: np.ndarray, tol: float, max_rounds: int, refine: int, num_threads: int,
    factors: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None,
    zero_set: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Steps 1–3 of the active-set solve for every pixel in one compiled pass.

    Per pixel: with ``factors``, the right-hand side ``b = Aᵀ W y`` from the camera's factored
    sensing matrix (written into ``b``); ``x0 = H b``; the infeasibility threshold
    ``t = ¼·tol·(‖G‖‖x0‖ + ‖b‖)``
    (:data:`~hsi_torch.recon.nnls.constants.INFEASIBILITY_FRACTION`); block
    principal pivoting where ``x0`` has an entry with ``x0_m G_mm < −t`` (unless ``skip``), from
    the zero set of a few coordinate-descent sweeps (:func:`_start_zero_set`);
    the KKT residual of the answer with the exact ``G`` and ``b``; for pixels without a zero set,
    up to ``refine`` refinement steps ``x ← max(0, x − H(Gx − b))`` kept while they lower it.
    Each pixel's bytes are read once and nothing of frame size is allocated but the outputs; a
    pixel whose ``b`` is 0 (with ``factors``: whose observations are all 0, e.g. zeroed to solve
    a subset of a frame) is answered ``x = 0`` (its KKT point) without reading its ``G``, ``H``
    or factors.
    ``G`` and ``H`` must be symmetric (they are read by rows as columns).

    Args:
        G, H: ``(P|1, M, M)``; b: ``(P, M)`` right-hand sides (with ``factors``: written);
        gd: ``(P|1, M)`` ``diag G``; gn: ``(P|1,)`` the ``‖G‖₂`` bound; skip: ``(P,)`` bool
        (singular or without data: no pivoting); factors: ``None`` (``b`` given), or
        ``(y (P, O), mask (P, O) bool, transmittance (P, V, M), gain (P, V), response (C, M))``
        with ``O = V·C`` and ``o = C·v + c`` (:class:`~hsi_torch.forward_model.SensingModel`);
        zero_set: ``(P, M)`` bool first zero set of the pixels that pivot (a warm start, e.g.
        the previous frame's ``x == 0``) instead of the coordinate-descent start; the exchange
        rules terminate from any start, so only the rounds change.

    Returns:
        ``x (P, M) ≥ 0``, ``Z (P, M)`` bool zero sets, ``residual (P,)`` float64, ``status (P,)``
        int8 (:data:`DONE` also for pixels that needed no pivoting), ``rounds (P,)`` int32,
        ``plain (P,)`` bool: an empty zero set and not ``skip``.
    """
    if not AVAILABLE:  # pragma: no cover
        raise RuntimeError("numba is not installed")
    n, m = b.shape
    x = np.empty((n, m), b.dtype)
    z = np.empty((n, m), np.bool_)
    plain = np.empty(n, np.bool_)
    res = np.empty(n, np.float64)
    status = np.empty(n, np.int8)
    rounds = np.empty(n, np.int32)
    if n == 0:
        return x, z, res, status, rounds, plain
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
    if zero_set is not None and zero_set.shape != (n, m):
        raise ValueError(f"solve_frame_cpu: zero_set must be {(n, m)}, got {zero_set.shape}")
    zinit = (np.zeros((1, m), np.bool_) if zero_set is None
             else np.ascontiguousarray(zero_set, dtype=np.bool_))
    if not H.flags.c_contiguous and H.transpose(0, 2, 1).flags.c_contiguous:
        # H is symmetric: a column-major one (torch's batched Cholesky inverse) is passed as its
        # transpose, C-contiguous without a copy: one compiled kernel per dtype, not per layout
        H = H.transpose(0, 2, 1)
    with threads(num_threads):
        _frame_kernel(G, H, b, gd, gn, skip, float(tol), int(max_rounds), int(refine),
                      float(INFEASIBILITY_FRACTION), int(zero_set_limit(m)), int(MURTY_PATIENCE),
                      float(COMPILED_FLOOR), int(START_SWEEPS), x, z, plain, res, status,
                      rounds, min(n, 512), factors is not None, *fac, zinit,
                      zero_set is not None)
    return x, z, res, status, rounds, plain


def factor_sensing_cpu(
    transmittance: np.ndarray, gain: np.ndarray, response: np.ndarray, mask: np.ndarray | None,
    reg: np.ndarray, dtype: np.dtype, num_threads: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The per-pixel factorisation of :func:`~hsi_torch.recon.nnls.prepare_nnls` for the camera's
    factored sensing matrix, in one compiled pass (float64 arithmetic, results in ``dtype``).

    Per pixel: ``G = Aᵀ W A + reg`` from the factors (the whole views in the factored form
    ``(Σ_v g_v² B_v B_vᵀ) ⊙ (Σ_c r_c r_cᵀ)``, views split by the mask one observation at a
    time), exactly symmetric; ``diag G``; the lower bound of ``‖G‖₂`` (three power steps from the
    ones vector and the Rayleigh quotient, at least ``max diag G``); the Cholesky factor, whose
    smallest pivot below ``20·M·eps(dtype)·max diag G`` marks the pixel singular (``H = 0``);
    else ``H = G⁻¹ = L⁻ᵀ L⁻¹``, exactly symmetric. The same tests as the torch factorisation.

    Args:
        transmittance: ``(P, V, M)``; gain: ``(P, V)``; response: ``(C, M)``; mask:
            ``(P, V·C)`` bool (``o = C·v + c``) or ``None`` (all used); reg: ``(M, M)``
            float64 ``β DᵀD``; dtype: of the results.

    Returns:
        ``G (P, M, M)``, ``H (P, M, M)``, ``diag G (P, M)``, ``‖G‖₂ bound (P,)``,
        ``singular (P,)`` bool (including the pixels without data), ``no_data (P,)`` bool.
    """
    if not AVAILABLE:  # pragma: no cover
        raise RuntimeError("numba is not installed")
    Bt = np.ascontiguousarray(transmittance)
    n, V, m = Bt.shape
    dt = np.dtype(dtype)
    G = np.empty((n, m, m), dt)
    H = np.empty((n, m, m), dt)
    gd = np.empty((n, m), dt)
    gn = np.empty(n, dt)
    singular = np.empty(n, np.bool_)
    no_data = np.empty(n, np.bool_)
    if n == 0:
        return G, H, gd, gn, singular, no_data
    masked = mask is not None
    mk = np.ascontiguousarray(mask) if masked else np.ones((1, 1), np.bool_)
    rel = 20.0 * m * float(np.finfo(dt).eps)
    with threads(num_threads):
        _factor_kernel(Bt, np.ascontiguousarray(gain), np.ascontiguousarray(response), mk,
                       masked, np.ascontiguousarray(reg, dtype=np.float64), rel, G, H, gd, gn,
                       singular, no_data, min(n, 512))
    return G, H, gd, gn, singular, no_data


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
