"""ADMM for the batched NNLS problems (``solver="admm"`` of :meth:`NNLSProblem.solve`).

Splitting ``x = z, z ≥ 0`` of ``min ½ xᵀGx − bᵀx``: with a per-pixel penalty ``ρ`` (default
``trace(G)/M``) and ``K = (G + ρI)⁻¹`` precomputed once per problem and ``ρ``, an iteration is

    ``x ← K (b + ρ (z − u))``,  ``z ← max(x + u, 0)``,  ``u ← u + x − z``

started from the clamped unconstrained solution ``max(H b, 0)`` or a given warm start ``x0``.

* ``admm_iters=N``: exactly ``N`` iterations with out-of-place torch operations, so the answer is
  differentiable with respect to ``y`` (and converged means only "ran"; the KKT residual is
  reported).
* ``admm_iters=None``: iterations in groups of 10 until the relative primal and dual residuals
  ``‖x − z‖∞ / ‖z‖∞`` and ``‖z − z_prev‖∞ / ‖z‖∞`` are both ``≤ tol``; pixels leave the working
  set as they converge.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import Tensor

from hsi_torch.recon.nnls.kkt import (
    _chunk_len,
    _expand_rows,
    _rowvec,
    _take,
    check_finite_rhs,
    nnls_kkt_residual,
)

if TYPE_CHECKING:
    from hsi_torch.recon.nnls.problem import NNLSProblem

__all__ = ["admm_factors", "solve_admm"]

#: iterations between two convergence checks of the tolerance-driven mode
_CHECK_EVERY = 10


def admm_factors(problem: NNLSProblem, rho: float | None) -> tuple[Tensor, Tensor]:
    """``K = (G + ρI)⁻¹ (1|P, M, M)`` and ``ρ (1|P,)`` of ``problem``, cached on it per ``rho``."""
    cache = problem._admm_cache
    key = "auto" if rho is None else repr(float(rho))
    if key in cache:
        return cache[key]
    H = problem.gram_inv
    m = problem.num_bands
    gd = problem.gram_diag
    if rho is None:
        r = gd.mean(1)
        r = torch.where(r > 0, r, torch.ones_like(r))
    else:
        if not float(rho) > 0:
            raise ValueError(f"rho must be > 0, got {rho}")
        r = torch.full((gd.shape[0],), float(rho), dtype=H.dtype, device=H.device)
    K = torch.empty_like(H)
    eye = torch.eye(m, dtype=H.dtype, device=H.device)
    n = _chunk_len(H.shape[0], 8 * m * m * H.element_size(), None, None, H.device)
    with torch.no_grad():
        for s in range(0, H.shape[0], n):
            sl = slice(s, s + n)
            G = problem.gram_matrices(sl)
            L, _ = torch.linalg.cholesky_ex(G + r[sl].view(-1, 1, 1) * eye)
            K[sl] = torch.cholesky_inverse(L)
    cache[key] = (K, r)
    return K, r


def solve_admm(
    problem: NNLSProblem, y: Tensor, tol: float, max_iter: int, chunk_size: int | None,
    max_memory: int | None, admm_iters: int | None, rho: float | None, x0: Tensor | None,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """ADMM on every pixel of ``y (P, O)``, chunked over pixels.

    Returns:
        ``x (P, M)``, ``converged (P,)``, ``iterations (P,)``, ``kkt_residual (P,)``,
        ``no_data (P,)`` (the fields of :class:`~hsi_torch.recon.nnls.NNLSResult`).
    """
    P, m = y.shape[0], problem.num_bands
    item = torch.finfo(problem.dtype).bits // 8
    per_px = item * (2 * problem.num_obs + 16 * m + 4 * m * m)
    n = _chunk_len(P, per_px, chunk_size, max_memory, problem.device)
    outs = []
    for s in range(0, P, n):
        sl = slice(s, min(P, s + n))
        fixed = admm_iters is not None
        with torch.set_grad_enabled(fixed and torch.is_grad_enabled()):
            outs.append(_solve_chunk(problem, y, sl, tol, max_iter, admm_iters, rho,
                                     None if x0 is None else x0[sl]))  # fmt: skip
    cat = [torch.cat([o[i] for o in outs]) for i in range(5)]
    return cat[0], cat[1], cat[2], cat[3], cat[4]


def _finish(
    G: Tensor, b: Tensor, x: Tensor, nod: Tensor, done: Tensor, tol: float
) -> tuple[Tensor, Tensor, Tensor]:
    """``x`` with 0 for pixels without data, converged flags and the KKT residual."""
    zero = torch.zeros((), dtype=x.dtype, device=x.device)
    x = torch.where(nod.view(-1, 1), zero, x)
    with torch.no_grad():
        r = nnls_kkt_residual(G, b, x.detach())
        r = torch.where(nod, zero, r)
        r = torch.where(torch.isfinite(r), r, torch.full_like(r, float("inf")))
    return x, done & (r <= tol), r


def _solve_chunk(
    problem: NNLSProblem, y: Tensor, sl: slice, tol: float, max_iter: int,
    admm_iters: int | None, rho: float | None, x0: Tensor | None,
) -> tuple[Tensor, ...]:
    K, r = admm_factors(problem, rho)
    K, r = _take(K, sl), _take(r, sl)
    b = problem.rhs(y, sl)
    check_finite_rhs(b, y, problem.mask, sl.start or 0)  # NaN/inf, or overflow: an error
    n, m = b.shape
    dev, dt = b.device, b.dtype
    G = problem.gram_matrices(sl)
    Gi = _take(problem.gram_inv, sl)
    sing = _expand_rows(_take(problem.singular, sl), n)
    nod = _expand_rows(_take(problem.no_data, sl), n)
    r = _expand_rows(r.view(-1, 1), n)
    zero = torch.zeros((), dtype=dt, device=dev)
    if x0 is None:
        z = torch.where((sing | nod).view(-1, 1), zero, _rowvec(b, Gi)).clamp_min(0)
    else:
        z = x0.to(dt).clamp_min(0)
    u = (b - _rowvec(z, G)) / r
    if admm_iters is not None:  # fixed iterations, out of place: differentiable
        for _ in range(int(admm_iters)):
            x = _rowvec(b + r * (z - u), K)
            z = (x + u).clamp_min(0)
            u = u + x - z
        iters = torch.full((n,), int(admm_iters), dtype=torch.long, device=dev)
        done = torch.ones((n,), dtype=torch.bool, device=dev)
        x, conv, res = _finish(G, b, z, nod, done, tol)
        return x, conv, iters, res, nod.clone()
    # tolerance-driven: iterate on the sub-batch that has not converged
    iters = torch.zeros((n,), dtype=torch.long, device=dev)
    done = torch.zeros((n,), dtype=torch.bool, device=dev)
    act = torch.arange(n, device=dev)
    Ka, ra, ba, za, ua = _expand_rows(K, n), r, b, z, u
    it = 0
    while act.numel() > 0 and it < max_iter:
        z_prev = za
        for _ in range(_CHECK_EVERY):
            x = _rowvec(ba + ra * (za - ua), Ka)
            z_prev = za
            za = (x + ua).clamp_min(0)
            ua = ua + x - za
        it += _CHECK_EVERY
        xs = za.abs().amax(1).clamp_min(torch.finfo(dt).tiny)
        prim = (x - za).abs().amax(1) / xs
        dual = (za - z_prev).abs().amax(1) / xs
        ok = (prim <= tol) & (dual <= tol)
        iters[act] = it
        if bool(ok.any()):
            fin = act[ok]
            z[fin] = za[ok]
            done[fin] = True
            keep = ~ok
            act, Ka, ra = act[keep], Ka[keep], ra[keep]
            ba, za, ua = ba[keep], za[keep], ua[keep]
    if act.numel() > 0:
        z[act] = za
    x, _, res = _finish(G, b, z, nod, done, tol)
    return x, done | nod, iters, res, nod.clone()
