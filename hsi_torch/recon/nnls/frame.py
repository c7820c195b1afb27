"""The active-set solve of a whole frame: one driver, the per-pixel steps by either kernel.

The driver (:func:`solve_active_set`) runs the steps of the method (see
:mod:`hsi_torch.recon.nnls`) in one order for both kernels:

1–3. per pixel: the unconstrained solution ``x₀ = H b``, the infeasibility threshold
     (:data:`~hsi_torch.recon.nnls.constants.INFEASIBILITY_FRACTION`), block principal pivoting
     where ``x₀`` has a clearly negative entry, the independent KKT check with the exact ``G``
     and ``b``, and refinement of the pixels without a zero set — by the batched torch kernels
     streamed over pixel chunks (:func:`_steps_torch`, any device), or in one compiled pass on
     the CPU (:func:`_steps_compiled`, numba: each pixel's matrices read once, the rounds in
     registers and cache);
4.   for the pixels that still fail (:func:`_finish`, shared): refinement on their zero set,
     then Lawson–Hanson with the singular and unfinished pixels.

Both kernels apply the same rules (:mod:`~hsi_torch.recon.nnls.constants`) and return the same
record (:class:`_Steps`), so everything after step 3 is one code path.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from hsi_torch.forward_model import SensingModel
from hsi_torch.recon.nnls import _compiled
from hsi_torch.recon.nnls._threads import for_chunks
from hsi_torch.recon.nnls.active_set import (
    FreeSetSolver,
    _bpp,
    _lawson_hanson,
    _zero_set_solve_any,
)
from hsi_torch.recon.nnls.constants import BPP_ROUNDS, INFEASIBILITY_FRACTION
from hsi_torch.recon.nnls.kkt import (
    _expand_rows,
    _kkt_ratio,
    _norm2,
    _rowvec,
    _take,
    check_finite_rhs,
    nnls_kkt_residual,
)

if TYPE_CHECKING:
    from hsi_torch.recon.nnls.problem import NNLSProblem

__all__ = ["solve_active_set", "use_compiled"]


@dataclass
class _Steps:
    """Steps 1–3 of every pixel (``P`` pixels, ``M`` bands).

    Attributes:
        x: ``(P, M)``; b: ``(P, M)`` right-hand sides; r: ``(P,)`` KKT residuals; zset:
            ``(P, M)`` bool final zero sets; done: ``(P,)`` pivoting finished; iters: ``(P,)``
            int64 exchange rounds; redo: ``(P,)`` pixels for Lawson–Hanson (singular with data,
            unfinished, a small factorisation failed); plain: ``(P,)`` pixels without a zero set
            (already refined in step 3).
    """

    x: Tensor
    b: Tensor
    r: Tensor
    zset: Tensor
    done: Tensor
    iters: Tensor
    redo: Tensor
    plain: Tensor


def use_compiled(problem: NNLSProblem, backend: str) -> bool:
    """Whether steps 1–3 run the compiled CPU kernel (``backend``: ``"auto"``, ``"torch"`` or
    ``"compiled"``, the latter an error where it does not apply)."""
    if backend == "torch":
        return False
    ok = problem.device.type == "cpu" and _compiled.AVAILABLE
    if backend == "compiled" and not ok:
        raise RuntimeError(
            "backend='compiled' needs numba and a CPU problem "
            f"(numba installed: {_compiled.AVAILABLE}, device: {problem.device})"
        )
    return ok


def solve_active_set(
    problem: NNLSProblem, y: Tensor, tol: float, max_iter: int, refine: int, n: int, n_corr: int,
    workers: int, backend: str = "auto", zero_set: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Active-set solve of the whole frame ``y (P, O)`` (see the module docstring).

    Args:
        tol: the KKT tolerance; max_iter: Lawson–Hanson iterations (the exchange rounds are at
            most :data:`~hsi_torch.recon.nnls.constants.BPP_ROUNDS` of them); refine: steps of
            iterative refinement; n: pixels per chunk of the streamed stages; n_corr: pixels per
            correction batch; workers: CPU threads sharing the chunks (1 elsewhere); backend:
            :func:`use_compiled`; zero_set: ``(P, M)`` bool first zero set of the pixels that
            pivot (a warm start; default: each kernel's own start).

    Returns:
        ``x (P, M)``, ``converged (P,)``, ``iterations (P,)``, ``kkt_residual (P,)``,
        ``no_data (P,)`` (the fields of :class:`~hsi_torch.recon.nnls.NNLSResult`).

    Raises:
        NonFiniteObservations: (an ``InputError``, a ``ValueError``) NaN or ±inf in ``y`` where
            the mask uses it (found from ``b``, before the fallback runs).
    """
    P = y.shape[0]
    sing = _expand_rows(problem.singular, P)
    nod = _expand_rows(problem.no_data, P)
    irregular = sing | nod  # x = H b = 0 there (H = 0 or b = 0)
    steps = _steps_compiled if use_compiled(problem, backend) else _steps_torch
    st = steps(problem, y, tol, min(max_iter, BPP_ROUNDS), refine, n, n_corr, workers, sing, nod,
               irregular, zero_set)
    check_finite_rhs(st.b, y, problem.mask)  # NaN/inf, or b overflowing: an error
    return _finish(problem, st, irregular, nod, tol, max_iter, refine, n_corr)


def _steps_compiled(
    problem: NNLSProblem, y: Tensor, tol: float, rounds: int, refine: int, n: int, n_corr: int,
    workers: int, sing: Tensor, nod: Tensor, irregular: Tensor, zero_set: Tensor | None = None,
) -> _Steps:
    """Steps 1–3 pixel by pixel in one compiled pass (:func:`_compiled.solve_frame_cpu`)."""
    P, m = y.shape[0], problem.num_bands
    b = torch.empty((P, m), dtype=problem.dtype, device=y.device)
    factors = _fused_factors(problem, y)
    if factors is None:  # b = Aᵀ W y by the operator, then the compiled pass

        def rhs(sl: slice) -> None:
            b[sl] = problem.rhs(y, sl)

        for_chunks(rhs, P, n, workers)
    out = _compiled.solve_frame_cpu(
        problem.gram.numpy(), problem.gram_inv.numpy(), b.numpy(), problem.gram_diag.numpy(),
        problem.gram_norm.numpy(), irregular.numpy(), tol, rounds, refine, workers, factors,
        None if zero_set is None else zero_set.numpy(),
    )  # fmt: skip
    x, zset = torch.from_numpy(out[0]), torch.from_numpy(out[1])
    r = torch.from_numpy(out[2]).to(problem.dtype)
    done = torch.from_numpy(out[3]) == _compiled.DONE
    iters = torch.from_numpy(out[4]).long()
    redo = (sing & ~nod) | ~done
    plain = torch.from_numpy(out[5])  # ~zset.any(1) & ~irregular, counted in the pass
    return _Steps(x, b, r, zset, done, iters, redo, plain)


def _fused_factors(problem: NNLSProblem, y: Tensor) -> tuple | None:
    """The camera's factored ``A`` as NumPy arrays for the compiled pass to form ``b = Aᵀ W y``
    itself (``y``, mask, transmittance, gain, response), or ``None`` where ``b`` is formed by
    the operator first (dense or shared ``A``)."""
    sens = problem.sensing
    if not isinstance(sens, SensingModel) or sens.shared:
        return None
    P = y.shape[0]
    mask = problem.mask
    if mask is None:
        mask = torch.ones((1, 1), dtype=torch.bool).expand(P, sens.num_obs)
    return (y.contiguous().numpy(), mask.contiguous().numpy(),
            sens.transmittance.contiguous().numpy(), sens.gain.contiguous().numpy(),
            sens.response.contiguous().numpy())


def _steps_torch(
    problem: NNLSProblem, y: Tensor, tol: float, rounds: int, refine: int, n: int, n_corr: int,
    workers: int, sing: Tensor, nod: Tensor, irregular: Tensor, zero_set: Tensor | None = None,
) -> _Steps:
    """Steps 1–3 with the batched torch kernels, streamed over pixel chunks."""
    P, m = y.shape[0], problem.num_bands
    dev, dt = y.device, problem.dtype
    H = problem.gram_inv
    tiny = torch.finfo(dt).tiny
    gn_all = problem.gram_norm
    # 1. right-hand sides and unconstrained solutions x = H b, streamed over pixel chunks
    #    (cache-sized on CPU), with the per-pixel norms the thresholds need
    b = torch.empty((P, m), dtype=dt, device=dev)
    x = torch.empty((P, m), dtype=dt, device=dev)
    bnorm = torch.empty((P,), dtype=dt, device=dev)
    xnorm = torch.empty((P,), dtype=dt, device=dev)
    xneg = torch.empty((P,), dtype=dt, device=dev)

    def stage1(sl: slice) -> None:
        bs, xs = b[sl], x[sl]
        bs.copy_(problem.rhs(y, sl))
        _rowvec(bs, _take(H, sl), out=xs)
        bnorm[sl] = _norm2(bs)
        xnorm[sl] = _norm2(xs)
        xneg[sl] = xs.clamp_max(0).sum(1)

    for_chunks(stage1, P, n, workers)
    # infeasibility threshold in gradient units. x_m·G_mm < −thr for some m needs
    # Σ_m min(x_m, 0) · max_m G_mm < −thr: a cheap test that selects a superset
    thr = (INFEASIBILITY_FRACTION * tol * (_expand_rows(gn_all, P) * xnorm + bnorm)).clamp_min(
        tiny)
    need = xneg * _expand_rows(problem.gram_diag_max, P) < -thr
    if bool(irregular.any()):
        need &= ~irregular
    # 2. exact correction of the pixels with negative entries: one compacted sub-batch
    iters = torch.zeros((P,), dtype=torch.long, device=dev)
    done = torch.ones((P,), dtype=torch.bool, device=dev)
    zset = torch.zeros((P, m), dtype=torch.bool, device=dev)
    redo = sing & ~nod
    idx = need.nonzero().squeeze(1)
    if idx.numel():
        gd = _expand_rows(problem.gram_diag, P)
        free_solve = FreeSetSolver(problem.gram)

        def correct(sl: slice) -> None:
            ic = idx[sl]
            xs, zs, ds, fs, its = _bpp(H, ic, x[ic], gd[ic], thr[ic].unsqueeze(1), rounds, b[ic],
                                       free_solve, None if zero_set is None else zero_set[ic])
            x[ic], zset[ic], done[ic], iters[ic] = xs, zs, ds, its
            redo[ic] |= fs | ~ds

        # split between the workers (compacted sub-batches of at most n_corr pixels)
        nw = min(workers, max(1, idx.numel() // 2048))
        for_chunks(correct, idx.numel(), min(n_corr, -(-idx.numel() // nw)), nw)
    # 3. independent KKT check with the exact G and b (streamed); refine where it fails
    r = torch.empty((P,), dtype=dt, device=dev)

    plain = ~zset.any(1) & ~irregular  # all-free pixels: refined right here, streamed

    def stage3(sl: slice) -> None:
        Hs, gns, bs = _take(H, sl), _take(gn_all, sl), b[sl]
        gd = _take(problem.gram_diag, sl)
        xs = x[sl].clamp_min_(0)
        g = problem.gram_apply(xs, sl).sub_(bs)
        rs = _kkt_ratio(g, xs, gd, gns, bnorm[sl])
        for _ in range(refine):
            fix = ~(rs <= tol) & plain[sl]
            nf = int(fix.sum())
            if nf == 0:
                break
            if 4 * nf >= fix.numel():  # many: whole chunk, masked
                xn = (xs - _rowvec(g, Hs)).clamp_min_(0)
                gn = problem.gram_apply(xn, sl).sub_(bs)
                rn = _kkt_ratio(gn, xn, gd, gns, bnorm[sl])
                fix &= rn < rs
                xs.copy_(torch.where(fix.unsqueeze(1), xn, xs))
                g = torch.where(fix.unsqueeze(1), gn, g)
                rs = torch.where(fix, rn, rs)
                continue
            li = fix.nonzero().squeeze(1)  # few: those rows only
            gl = li + sl.start
            Hl = _take(Hs, li)
            xl = xs[li]
            xn = (xl - _rowvec(g[li], Hl)).clamp_min_(0)
            gn = problem.gram_apply(xn, gl).sub_(bs[li])
            rn = _kkt_ratio(gn, xn, _take(gd, li), _take(gns, li), bnorm[sl][li])
            ok = (rn < rs[li]).unsqueeze(1)
            xs[li] = torch.where(ok, xn, xl)
            g[li] = torch.where(ok, gn, g[li])
            rs[li] = torch.minimum(rn, rs[li])
        r[sl] = rs

    for_chunks(stage3, P, n, workers)
    return _Steps(x, b, r, zset, done, iters, redo, plain)


def _finish(
    problem: NNLSProblem, st: _Steps, irregular: Tensor, nod: Tensor, tol: float, max_iter: int,
    refine: int, n_corr: int,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Step 4 for the pixels that still fail: refinement on their zero set, then the
    Lawson–Hanson fallback (with singular and unfinished pixels)."""
    x, b, r, zset, done, iters, redo = st.x, st.b, st.r, st.zset, st.done, st.iters, st.redo
    m, dt = x.shape[1], x.dtype
    tiny = torch.finfo(dt).tiny
    gn_all = problem.gram_norm
    any_irregular = bool(irregular.any())
    bad = ~(r <= tol) & ~irregular & ~redo & ~st.plain
    for _ in range(refine):
        idx = bad.nonzero().squeeze(1)
        if idx.numel() == 0:
            break
        for s in range(0, idx.numel(), n_corr):
            ic = idx[s:s + n_corr]
            xs, rs = _refine_rows(problem, ic, x[ic], zset[ic], b[ic])
            better = rs < r[ic]
            x[ic] = torch.where(better.view(-1, 1), xs, x[ic])
            r[ic] = torch.where(better, rs, r[ic])
            bad[ic] = better & ~(rs <= tol)  # unchanged x: the next step would repeat this one
    # 4. robust fallback: singular G, Cholesky failures, unfinished or still failing pixels
    redo |= ~(r <= tol) & ~irregular
    if any_irregular:
        redo &= ~nod
    idx = redo.nonzero().squeeze(1)
    for s in range(0, idx.numel(), n_corr):
        ic = idx[s:s + n_corr]
        Gs = problem.gram_matrices(ic)
        bs = b[ic]
        thr_s = (INFEASIBILITY_FRACTION * tol * _norm2(bs)).clamp_min(tiny).view(-1, 1)
        eps = float(torch.finfo(dt).eps)
        piv_tol = min(eps**0.5, 100.0 * m * eps)
        xs, ds, its = _lawson_hanson(Gs, bs, thr_s, piv_tol, max_iter)
        rs = nnls_kkt_residual(Gs, bs, xs, _take(gn_all, ic))
        better = ~(rs >= r[ic])  # keep the earlier answer where it was at least as good
        x[ic] = torch.where(better.view(-1, 1), xs, x[ic])
        done[ic] = torch.where(better, ds, done[ic])
        r[ic] = torch.where(better, rs, r[ic])
        iters[ic] = iters[ic] + its
    if any_irregular:
        inod = nod.nonzero().squeeze(1)
        if inod.numel():  # usually few: rows, not a frame-sized select
            x.index_fill_(0, inod, 0.0)
            r.index_fill_(0, inod, 0.0)
    r = torch.where(torch.isfinite(r), r, torch.full_like(r, float("inf")))
    return x, done & (r <= tol), iters, r, nod.clone()


def _refine_rows(
    problem: NNLSProblem, idx: Tensor, x: Tensor, Z: Tensor, b: Tensor
) -> tuple[Tensor, Tensor]:
    """One step of iterative refinement on the zero set ``Z`` with the exact ``G``.

    ``x ← x − G_FF⁻¹ g_F`` (``g = Gx − b``; ``G_FF⁻¹`` applied through ``H`` and the ``Z``
    block, :func:`~hsi_torch.recon.nnls.active_set._zero_set_solve`). Returns the refined ``x``
    (clamped at 0) and its KKT residual.
    """
    H = problem.gram_inv
    Gs = problem.gram_matrices(idx)
    Hs = _take(H, idx)
    g = _rowvec(x, Gs) - b
    u = -_rowvec(torch.where(Z, torch.zeros((), dtype=x.dtype, device=x.device), g), Hs)
    d, ok = _zero_set_solve_any(H, idx, Z, u)
    xs = torch.where(ok.view(-1, 1), x + d, x).clamp_min(0)
    return xs, nnls_kkt_residual(Gs, b, xs, _take(problem.gram_norm, idx))
