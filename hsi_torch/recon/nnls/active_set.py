"""Exact active-set kernels of the batched NNLS solver (no per-pixel Python loops).

* :func:`_bpp`: block principal pivoting on the zero set ``Z`` through the stored inverses
  ``H = G⁻¹`` (Júdice–Pires; Kim–Park's NNLS variant) with Murty's rule for finite termination.
* :func:`_lawson_hanson`: Lawson–Hanson on a principal-pivot tableau of ``G``, for singular or
  badly conditioned pixels.
* :func:`_zero_set_solve`: the equality-constrained solution for a given zero set.
"""

from __future__ import annotations

import torch
from torch import Tensor

from hsi_torch.recon.nnls.constants import MURTY_PATIENCE, zero_set_limit
from hsi_torch.recon.nnls.kkt import _expand_rows, _rowvec


def _pivot(T: Tensor, c: Tensor, k: Tensor, has: Tensor | None = None) -> Tensor:
    """One principal pivot on index ``k[i]`` of every tableau ``T[i]``, in place.

    The tableau represents ``v = T u + c`` with ``v = (x_F, g_Z)`` and ``u = (g_F, x_Z)`` for the
    free set ``F`` and the active (zero) set ``Z``; pivoting on ``k`` moves ``k`` between the two
    sets. ``c`` then holds ``x_F`` and ``g_Z`` of the equality-constrained solution. Rows with
    ``has[i] = False`` are left unchanged (masked rank-1 update, no gather/scatter of ``T``).

    Returns:
        ``(n,)`` bool: the pivot was positive and finite (otherwise ``T`` of that row is invalid).
    """
    n, m = c.shape
    kk = k.view(n, 1, 1)
    col = T.gather(2, kk.expand(n, m, 1))  # T[:, :, k]
    row = T.gather(1, kk.expand(n, 1, m))  # T[:, k, :]
    p0 = col.gather(1, kk)  # (n, 1, 1)
    ok = (p0 > 0) & torch.isfinite(p0)
    use = ok if has is None else ok & has.view(n, 1, 1)
    p = torch.where(use, p0, torch.ones((), dtype=p0.dtype, device=p0.device))
    colp = torch.where(use, col / p, torch.zeros((), dtype=p.dtype, device=p.device))
    ck = c.gather(1, k.view(n, 1))
    # entries off row/column k get the rank-1 update; row k, column k and (k, k) are written
    # explicitly (no cancellation whatever the scale of p)
    T.addcmul_(colp, row, value=-1.0)
    T.scatter_(1, kk.expand(n, 1, m), torch.where(use, -row / p, row))
    T.scatter_(2, kk.expand(n, m, 1), torch.where(use, colp, col))
    T.view(n, m * m).scatter_(1, (k * (m + 1)).view(n, 1), torch.where(use, 1.0 / p, p0).view(n, 1))
    c.addcmul_(colp.squeeze(2), ck, value=-1.0)
    c.scatter_(1, k.view(n, 1), torch.where(use.view(n, 1), -ck / p.view(n, 1), ck))
    return ok.view(n)


def _pivot_rows(T: Tensor, c: Tensor, free: Tensor, k: Tensor, has: Tensor | None) -> Tensor:
    """Masked pivot (see :func:`_pivot`) that also toggles ``free[i, k[i]]``; returns ok."""
    ok = _pivot(T, c, k, has)
    flip = ok if has is None else ok & has
    fk = free.gather(1, k.view(-1, 1))
    free.scatter_(1, k.view(-1, 1), fk ^ flip.view(-1, 1))
    return ok


def _refine(T: Tensor, c: Tensor, free: Tensor, G: Tensor, b: Tensor) -> Tensor:
    """One step of iterative refinement of the equality-constrained solution; returns new ``c``.

    Uses the exact ``G`` for the gradient and the tableau block ``T_FF = G_FF⁻¹`` as the
    (approximate) inverse; ``c`` becomes ``(x_F, g_Z)`` recomputed from the refined ``x``.
    """
    zero = torch.zeros((), dtype=c.dtype, device=c.device)
    x = torch.where(free, c, zero)
    g = _rowvec(x, G) - b
    d = torch.bmm(T, torch.where(free, g, zero).unsqueeze(2)).squeeze(2)
    x = torch.where(free, x - d, zero)
    g = _rowvec(x, G) - b
    return torch.where(free, x, g)


def _zero_set_solve(
    H: Tensor, idx: Tensor, Z: Tensor, v: Tensor, k: int
) -> tuple[Tensor, Tensor, Tensor, Tensor | None]:
    """Equality-constrained solve through the precomputed inverse ``H = G⁻¹``.

    For every row: ``λ = −H_ZZ⁻¹ v_Z``, ``x = v + H[:, Z] λ`` (so ``x_Z = 0``). With ``v = G⁻¹ b``
    this is the minimiser of ``½xᵀGx − bᵀx`` subject to ``x_Z = 0`` and ``λ = (Gx − b)_Z`` its
    gradient (the multipliers) on ``Z``. Only ``|Z|`` rows of ``H`` are read and only a
    ``k × k`` system (``k = max |Z|``, padded with identity rows) is factorised per pixel.

    Args:
        H: ``(P|1, M, M)`` symmetric inverses (all pixels); idx: ``(n,)`` rows of ``H`` to use.
        Z: ``(n, M)`` bool zero set; v: ``(n, M)``; k: ``max |Z|`` over the rows (host int).

    Returns:
        ``x (n, M)`` with exact zeros on ``Z``; ``lam (n, M)`` (0 off ``Z``); ``ok (n,)`` the
        ``k × k`` Cholesky succeeded; the Cholesky data ``(zi, R, L)`` packed for reuse (or None
        when ``k = 0``).
    """
    n, m = v.shape
    if k == 0:
        return (
            v.clone(),
            torch.zeros_like(v),
            torch.ones((n,), dtype=torch.bool, device=v.device),
            None,
        )
    zero = torch.zeros((), dtype=v.dtype, device=v.device)
    # indices of Z first (ascending), then free ones as padding (their λ comes out exactly 0)
    zi = torch.argsort((~Z).to(torch.uint8), dim=1, stable=True)[:, :k]
    zv = Z.gather(1, zi)  # (n, k) valid entries
    # rows H[Z, :] (n, k, M): one contiguous row copy each (H symmetric: also the columns)
    rows = zi if H.shape[0] == 1 else idx.unsqueeze(1) * m + zi
    R = H.view(-1, m).index_select(0, rows.reshape(-1)).view(n, k, m)
    L, ok = _padded_cholesky(R, zi, zv)
    rhs = torch.where(zv, v.gather(1, zi), zero).unsqueeze(2)
    t = torch.linalg.solve_triangular(L, rhs, upper=False)
    lam_k = -torch.linalg.solve_triangular(L.transpose(1, 2), t, upper=True).squeeze(2)
    x = (v + _rowvec(lam_k, R)).masked_fill(Z, 0.0)
    lam = torch.zeros_like(v).scatter_(1, zi, lam_k)
    return x, lam, ok, (zi, R, L)


def _padded_cholesky(rows: Tensor, cols: Tensor, valid: Tensor) -> tuple[Tensor, Tensor]:
    """Cholesky factors ``L (n, k, k)`` of the blocks ``rows[:, :, cols]`` (``rows (n, k, M)``,
    ``cols (n, k)``), entries where ``valid (n, k)`` is False padded with identity rows and
    columns, and ``ok (n,)``: the factorisation succeeded (identity where it did not)."""
    n, k = cols.shape
    block = rows.gather(2, cols.unsqueeze(1).expand(n, k, k))
    eye = torch.eye(k, dtype=rows.dtype, device=rows.device)
    block = torch.where(valid.unsqueeze(2) & valid.unsqueeze(1), block, eye)
    L, info = torch.linalg.cholesky_ex(block)
    ok = info == 0
    return torch.where(ok.view(n, 1, 1), L, eye), ok


#: bucket bounds on the padded system size k (pixels with k in (e_i, e_{i+1}] share one padded
#: size e_{i+1}); k = |Z| for zero-set solves, |F| for free-set solves
_K_EDGES = (0, 1, 2, 3, 4, 5, 6, 8, 10, 13, 17)


class FreeSetSolver:
    """Equality-constrained solves on the free set ``F`` through the stored Gram matrices.

    For pixels with many zeros (dark pixels: typically 15–25 of 25 bands) the zero-set solve of
    :func:`_zero_set_solve` needs a large ``|Z| × |Z|`` block of ``H``; solving the small
    ``|F| × |F|`` system ``G_FF x_F = b_F`` instead reads ``|F|`` columns of ``G`` (which also give
    the multipliers ``λ = (G x − b)_Z``).

    Args:
        gram: ``(P|1, M, M)`` Gram matrices of every pixel.
    """

    def __init__(self, gram: Tensor) -> None:
        self.gram = gram

    def __call__(self, gi: Tensor, F: Tensor, b: Tensor, k: int) -> tuple[Tensor, Tensor, Tensor]:
        """``x`` (zeros off ``F``), ``λ = (Gx − b)`` on ``Z`` (0 on ``F``) and ``ok`` for rows
        with global pixel indices ``gi``, free sets ``F (n, M)`` (``|F| ≤ k``) and ``b (n, M)``."""
        n, m = b.shape
        zero = torch.zeros((), dtype=b.dtype, device=b.device)
        if k == 0:
            return torch.zeros_like(b), -b, torch.ones((n,), dtype=torch.bool, device=b.device)
        fi = torch.argsort((~F).to(torch.uint8), dim=1, stable=True)[:, :k]
        fv = F.gather(1, fi)  # (n, k) valid entries (the rest pads with Z indices)
        G = self.gram
        rows = fi if G.shape[0] == 1 else gi.unsqueeze(1) * m + fi
        C = G.view(-1, m).index_select(0, rows.reshape(-1)).view(n, k, m)  # G[F, :] = G[:, F]ᵀ
        L, ok = _padded_cholesky(C, fi, fv)
        rhs = torch.where(fv, b.gather(1, fi), zero).unsqueeze(2)
        xf = torch.where(fv, torch.cholesky_solve(rhs, L).squeeze(2), zero)  # (n, k)
        x = torch.zeros_like(b).scatter_(1, fi, xf)
        g = _rowvec(xf, C, sub=b)  # G[:, F] x_F − b
        return x, torch.where(F, zero, g), ok


def _bucketed_solve(
    H: Tensor,
    gi: Tensor,
    Z: Tensor,
    v: Tensor,
    b: Tensor | None,
    free_solve,
    sizes: list[int],
    modes: list[bool],
    bounds: list[int],
) -> tuple[Tensor, Tensor, Tensor]:
    """Equality-constrained solves for rows sorted into buckets of one padded size and mode.

    Rows ``bounds[i-1]:bounds[i]`` are solved with size ``sizes[i]``, on the zero set through
    ``H`` (:func:`_zero_set_solve`) or, where ``modes[i]``, on the free set
    (``free_solve(gi, F, b, k)``).
    """
    x = torch.empty_like(v)
    lam = torch.empty_like(v)
    ok = torch.empty((v.shape[0],), dtype=torch.bool, device=v.device)
    start = 0
    for k, free, stop in zip(sizes, modes, bounds, strict=True):
        if stop > start:
            sl = slice(start, stop)
            if free:
                x[sl], lam[sl], ok[sl] = free_solve(gi[sl], ~Z[sl], b[sl], k)
            else:
                x[sl], lam[sl], ok[sl], _ = _zero_set_solve(H, gi[sl], Z[sl], v[sl], k)
            start = stop
    return x, lam, ok


def _zero_set_solve_any(H: Tensor, gi: Tensor, Z: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`_zero_set_solve` for rows in any order (sorted into ``|Z|`` buckets inside).

    Returns ``x`` and ``ok`` in the input order.
    """
    m = v.shape[1]
    sizes = [e for e in _K_EDGES if e < m] + [m]
    cnt = Z.sum(1)
    order = torch.argsort(cnt, stable=True)
    bounds = torch.searchsorted(
        cnt[order], torch.tensor(sizes, device=v.device), right=True
    ).tolist()
    xs, _, oks = _bucketed_solve(
        H, gi[order], Z[order], v[order], None, None, sizes, [False] * len(sizes), bounds
    )
    x = torch.empty_like(v)
    ok = torch.empty_like(oks)
    x[order] = xs
    ok[order] = oks
    return x, ok


def _bucket_plan(
    m: int, hybrid: bool, device: torch.device
) -> tuple[Tensor, list[int], list[bool]]:
    """Bucket edges on the sort key of :func:`_bpp` with each bucket's padded size and mode.

    Key: ``|Z|`` for zero-set rows, ``(m + 1) + |F|`` for free-set rows (hybrid only), so one
    sort makes every bucket a contiguous slice.
    """
    half = zero_set_limit(m) if hybrid else m
    zs = [e for e in _K_EDGES if e < half] + [half]
    keys, sizes, modes = list(zs), list(zs), [False] * len(zs)
    if hybrid:
        fs = [e for e in _K_EDGES if e < m - half - 1] + [m - half - 1]
        keys += [m + 1 + e for e in fs]
        sizes += fs
        modes += [True] * len(fs)
    return torch.tensor(keys, device=device), sizes, modes


def _bpp(
    H: Tensor,
    idx: Tensor,
    x0: Tensor,
    gd: Tensor,
    thr: Tensor,
    max_iter: int,
    b: Tensor | None = None,
    free_solve: FreeSetSolver | None = None,
    z0: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Block principal pivoting (Júdice–Pires, Kim–Park) with zero-set or free-set solves.

    Starts with the zero set ``Z`` = the negative entries of the unconstrained solution ``x0``.
    Each round solves the equality-constrained problem for the current ``Z`` — through
    ``H = G⁻¹`` on ``Z`` (:func:`_zero_set_solve`, a ``|Z| × |Z|`` system) when ``|Z| ≤ M/2``
    (:func:`~hsi_torch.recon.nnls.constants.zero_set_limit`), else on the free set
    (``free_solve``, a ``|F| × |F|`` system from the operator) — and exchanges the infeasible
    set (``x_F < 0`` or ``λ_Z < 0``); after three rounds without fewer infeasible variables
    (:data:`~hsi_torch.recon.nnls.constants.MURTY_PATIENCE`) only the largest infeasible index
    is exchanged (Murty's rule, which guarantees finite termination for positive definite
    ``G``). Finished pixels leave the working set, so every round works on the still-active rows
    only.

    Args:
        H: ``(P|1, M, M)`` inverses; idx: ``(n,)`` global pixel indices into ``H``.
        x0: ``(n, M)`` unconstrained solutions ``H b``; gd: ``(n, M)`` ``diag(G)``.
        thr: ``(n, 1)`` infeasibility threshold in gradient units (``x_m G_mm`` and ``λ_m``).
        max_iter: maximum number of exchange rounds.
        b: ``(n, M)`` right-hand sides and free_solve: a :class:`FreeSetSolver`; without them
            every solve is a zero-set solve.
        z0: ``(n, M)`` bool first zero sets (a warm start) instead of the negative entries of
            ``x0``.

    Returns:
        ``x (n, M)``, ``Z (n, M)`` final zero sets, ``done (n,)``, ``failed (n,)`` (a small
        Cholesky failed: re-solve another way), ``iterations (n,)``.
    """
    n, m = x0.shape
    dev = x0.device
    hybrid = free_solve is not None and b is not None
    x_out = torch.zeros_like(x0)
    z_out = torch.zeros((n, m), dtype=torch.bool, device=dev)
    done = torch.zeros((n,), dtype=torch.bool, device=dev)
    failed = torch.zeros((n,), dtype=torch.bool, device=dev)
    iters = torch.zeros((n,), dtype=torch.long, device=dev)
    edges, sizes, modes = _bucket_plan(m, hybrid, dev)
    half = zero_set_limit(m) if hybrid else m

    def sort_key(Zs: Tensor) -> Tensor:
        kz = Zs.sum(1)
        return torch.where(kz > half, (m + 1) + (m - kz), kz) if hybrid else kz

    Z = x0 * gd < -thr if z0 is None else z0.clone()
    z0_empty = ~Z.any(1)  # candidates without a clearly negative entry: 0 rounds if done at once
    # working set, kept sorted by the bucket key so that each bucket is a contiguous slice
    key = sort_key(Z)
    order = torch.argsort(key, stable=True)
    w = order  # local row (into the outputs) of each working pixel
    gi, v, gdw, tw, Z = idx[order], x0[order], gd[order], thr[order], Z[order]
    bw = b[order] if hybrid else None
    best = torch.full((n,), m + 1, dtype=torch.long, device=dev)
    backup = torch.full((n,), MURTY_PATIENCE, dtype=torch.long, device=dev)
    bounds = torch.searchsorted(key[order], edges, right=True).tolist()
    for rnd in range(1, max_iter + 1):
        x, lam, ok = _bucketed_solve(H, gi, Z, v, bw, free_solve, sizes, modes, bounds)
        infeas = torch.where(Z, lam < -tw, x * gdw < -tw)
        nv = infeas.sum(1)
        fin = (nv == 0) | ~ok
        if rnd == max_iter:
            fin = torch.ones_like(fin)
        iters[w] = rnd
        x_out[w] = x
        z_out[w] = Z
        done[w] = (nv == 0) & ok
        failed[w] = ~ok
        improved = nv < best
        full_block = improved | (backup >= 1)
        backup = torch.where(
            improved, torch.full_like(backup, MURTY_PATIENCE), (backup - 1).clamp_min(0)
        )
        best = torch.where(improved, nv, best)
        last = (m - 1) - infeas.flip(1).to(torch.uint8).argmax(1)  # Murty: largest index
        single = torch.zeros_like(infeas).scatter_(1, last.view(-1, 1), True)
        Z = Z ^ torch.where(full_block.view(-1, 1), infeas, single)
        # compact (finished rows sort last) and re-sort by the new key: one host sync a round
        key = torch.where(fin, 2 * m + 2, sort_key(Z))
        order = torch.argsort(key, stable=True)
        bounds = torch.searchsorted(key[order], edges, right=True).tolist()
        n_keep = bounds[-1]
        if n_keep == 0:
            break
        order = order[:n_keep]
        w, gi, v, gdw, tw = w[order], gi[order], v[order], gdw[order], tw[order]
        Z, best, backup = Z[order], best[order], backup[order]
        if hybrid:
            bw = bw[order]
    return x_out.clamp_min(0), z_out, done, failed, iters - z0_empty.long()


def _lawson_hanson(
    G: Tensor, b: Tensor, thr: Tensor, piv_tol: float, max_iter: int
) -> tuple[Tensor, Tensor, Tensor]:
    """Lawson–Hanson active set on the tableau, for singular or ill-conditioned ``G``.

    Starts from ``x = 0`` (``T = G``, ``c = −b``). Outer step: the most negative gradient among
    the active variables whose reduced pivot ``T_kk > piv_tol · G_kk`` enters the free set. Inner
    step: while the equality-constrained solution ``z`` has a non-positive free entry, move ``x``
    towards ``z`` up to the first blocking bound and drop that variable. One pivot per pixel per
    loop iteration.

    Returns:
        ``x (n, M)``, ``done (n,)``, ``iterations (n,)``.
    """
    n, m = b.shape
    dev, dt = b.device, b.dtype
    Gn = _expand_rows(G, n)
    gd = Gn.diagonal(dim1=1, dim2=2)
    T = Gn.clone()
    c = -b.clone()
    free = torch.zeros((n, m), dtype=torch.bool, device=dev)
    x = torch.zeros((n, m), dtype=dt, device=dev)
    iters = torch.zeros((n,), dtype=torch.long, device=dev)
    done = torch.zeros((n,), dtype=torch.bool, device=dev)
    zero = torch.zeros((), dtype=dt, device=dev)
    inf = torch.full((), float("inf"), dtype=dt, device=dev)
    refined = False
    refinements = 0
    for _ in range(max_iter + 3):
        nonpos = free & (c <= 0)
        inner = nonpos.any(1)
        diag_t = T.diagonal(dim1=1, dim2=2)
        cand = ~free & (c < -thr) & (diag_t > piv_tol * gd)
        outer = ~inner & cand.any(1)
        act = inner | outer
        finished = ~act
        x = torch.where(finished.view(-1, 1), torch.where(free, c, zero), x)
        if not bool(act.any()):
            if refined or refinements >= 3:
                done = torch.ones_like(done)
                break
            c = _refine(T, c, free, G, b)
            refined = True
            refinements += 1
            continue
        if int(iters.max()) >= max_iter:
            done = finished
            break
        refined = False
        z = torch.where(free, c, zero)
        # outer: x = z, k = most negative admissible gradient
        k_out = torch.where(cand, c, inf).argmin(1)
        # inner: step to the first blocking bound
        ratio = torch.where(nonpos, x / (x - z).clamp_min(torch.finfo(dt).tiny), inf)
        alpha, k_in = ratio.min(1)
        alpha = torch.where(inner, alpha, torch.zeros_like(alpha)).clamp(0, 1).view(-1, 1)
        x_in = torch.where(free, x + alpha * (z - x), zero).clamp_min(0)
        x_in = x_in.scatter(1, k_in.view(-1, 1), zero.expand(n, 1))
        x = torch.where(inner.view(-1, 1), x_in, torch.where(outer.view(-1, 1), z, x))
        k = torch.where(inner, k_in, k_out)
        _pivot_rows(T, c, free, k, act)
        iters += act.long()
    return x.clamp_min(0), done, iters
