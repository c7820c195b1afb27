"""The choice of ``λ`` per frame: the fixed relative weight, SURE (``lam="auto"``) and Morozov's
discrepancy principle (``lam="discrepancy"``).

``λ = lam · lam_scale`` (:func:`~hsi_torch.recon.spatial.noise.lam_scale`): a dimensionless
``lam`` means the same at any exposure, gain or prototype size. The rules search ``lam`` by
solving the frame several times (:func:`~hsi_torch.recon.spatial.admm.solve_spatial`, each warm
started) and return the chosen ``lam``, a warm start for the final solve and the search's
record.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor

from hsi_torch.recon.sensing import BundleSensing
from hsi_torch.recon.spatial.admm import solve_spatial
from hsi_torch.recon.spatial.noise import mean_square_residual
from hsi_torch.recon.spatial.problem import SpatialProblem

__all__ = ["DEFAULT_LAM", "AUTO_LAM_RANGE", "AUTO_LAM_STEPS", "SURE_LAMS", "LAM_RULES"]

#: Default relative TV weight ``lam`` (``λ = lam · σ̂ · sqrt(median trace G)``, :func:`lam_scale`)
#: with the pipeline's :data:`BRIGHTNESS_WEIGHT`: on the full-size prototype's frames 1.0 scores
#: close to the best fixed weight (2.0 gains a little more on the CAVE scene), and it still
#: improves every per-pixel score of the small prototype but its 10-px patch interiors, where
#: 2.0 falls below per-pixel on the whole ColorChecker patches (docs/spatial.md).
DEFAULT_LAM = 1.0


#: ``lam="discrepancy"``: the relative weights searched (log-bisection between these) and the
#: steps.
AUTO_LAM_RANGE = (1e-3, 10.0)
AUTO_LAM_STEPS = 8

#: ``lam="auto"``: the relative weights on which the risk estimate is evaluated.
SURE_LAMS = (0.03, 0.1, 0.3, 1.0, 3.0)

def _discrepancy_lam(
    sp: SpatialProblem, sens: BundleSensing, b: Tensor, y: Tensor, mask: Tensor, ok: Tensor,
    x0: Tensor, sigma: float, scale: float, inner_iters: int, max_iter: int,
    tol: float | None = None, changed: Tensor | None = None, alpha: float = 1.0,
) -> tuple[float, Tensor, dict[str, Any]]:
    """Morozov's discrepancy principle: the relative ``lam`` whose solution leaves a mean square
    residual per observation equal to ``σ̂²`` (log-bisection over :data:`AUTO_LAM_RANGE`,
    :data:`AUTO_LAM_STEPS` steps, each solve warm-started from the nearest one at the frame's
    tolerance ``tol``). Returns ``lam``, the last solution and the search's record."""
    target = sigma * sigma
    lo, hi = (math.log(v) for v in AUTO_LAM_RANGE)
    x_lo, x_hi = x0, None
    tried: list[tuple[float, float]] = []
    for _ in range(AUTO_LAM_STEPS):
        mid = 0.5 * (lo + hi)
        start = x_lo if x_hi is None else x_hi
        res = solve_spatial(sp, b, math.exp(mid) * scale, x0=start, tol=tol,
                            max_iter=max_iter, inner_iters=inner_iters, brightness_weight=alpha)
        r2 = mean_square_residual(sens, res.x, y, mask, ok)
        tried.append((math.exp(mid), r2))
        if r2 > target:
            hi, x_hi = mid, res.x
        else:
            lo, x_lo = mid, res.x
    lam = math.exp(0.5 * (lo + hi))
    info = {"lam_rule": "discrepancy", "discrepancy_target": target,
            "discrepancy_search": [[a, r] for a, r in tried]}  # fmt: skip
    return lam, (x_lo if x_hi is None else x_hi), info


def _sure_lam(
    sp: SpatialProblem, sens: BundleSensing, b: Tensor, y: Tensor, mask: Tensor, ok: Tensor,
    x0: Tensor, sigma: float, scale: float, inner_iters: int, max_iter: int,
    tol: float | None = None, changed: Tensor | None = None, alpha: float = 1.0,
) -> tuple[float, Tensor, dict[str, Any]]:
    """Monte-Carlo SURE (Stein's unbiased risk estimate of the prediction error
    ``E‖W A(s_λ − s_true)‖²``): ``SURE(λ) = ‖W(A s_λ − y)‖² − N σ̂² + 2 σ̂² div``, the
    divergence of ``y ↦ W A s_λ(y)`` estimated with one random probe ``δ ~ N(0, I)`` on the used
    observations, ``div ≈ δᵀ W A (s_λ(y + εδ) − s_λ(y)) / ε`` with ``ε = 0.1 σ̂``.

    ``s_λ(y)`` is the estimator the pipeline returns: the per-pixel NNLS warm start followed by
    the ADMM iterations to the tolerance ``tol``. The perturbed answer re-solves the per-pixel
    warm start for ``y + εδ`` (pixels with their own frame mask keep the unperturbed one) and
    runs the same number of ADMM iterations, so ``div`` is that estimator's divergence whatever
    its convergence. It estimates the error of the predicted observations, not of the spectra:
    where ``A`` hardly sees a direction, the spectral error at the chosen ``λ`` can be larger
    than at the best ``λ``. Evaluated at :data:`SURE_LAMS`; the minimum is refined by a parabola
    in ``log λ`` through it and its neighbours. Returns ``lam``, the per-pixel warm start ``x0``
    and the record (``[lam, SURE / N]`` pairs)."""
    model = sens.model
    w = (mask & ok.unsqueeze(1)).to(b.dtype)
    n_obs = float(w.sum())
    gen = torch.Generator(device="cpu").manual_seed(0)
    delta = torch.randn(tuple(y.shape), generator=gen, dtype=torch.float64)
    delta = delta.to(device=b.device, dtype=b.dtype) * w
    eps = 0.1 * sigma
    b_pert = b + eps * model.A_adjoint(delta)
    y32 = y.to(b.dtype)
    x0_pert = sens.problem.solve(torch.where(mask, y32 + eps * delta, 0)).x
    x0_pert = torch.where(ok.unsqueeze(1), x0_pert, x0)
    if changed is not None:
        x0_pert = torch.where(changed.unsqueeze(1), x0, x0_pert)
    curve: list[tuple[float, float]] = []
    for lam in SURE_LAMS:
        r0 = solve_spatial(sp, b, lam * scale, x0=x0, tol=tol, max_iter=max_iter,
                           inner_iters=inner_iters, brightness_weight=alpha)
        r1 = solve_spatial(sp, b_pert, lam * scale, x0=x0_pert, tol=0.0,
                           max_iter=r0.iterations, inner_iters=inner_iters,
                           brightness_weight=alpha)
        pred0 = model.A(r0.x) * w
        pred1 = model.A(r1.x) * w
        div = float((delta * (pred1 - pred0)).double().sum()) / eps
        rss = float(((pred0 - y32 * w).double()).square().sum())
        curve.append((lam, (rss - n_obs * sigma**2 + 2 * sigma**2 * div) / n_obs))
    vals = [c for _, c in curve]
    k = int(min(range(len(vals)), key=vals.__getitem__))
    lam = SURE_LAMS[k]
    if 0 < k < len(vals) - 1:  # parabola in log λ through the minimum and its neighbours
        xs = [math.log(SURE_LAMS[i]) for i in (k - 1, k, k + 1)]
        f = [vals[i] for i in (k - 1, k, k + 1)]
        den = (xs[0] - xs[1]) * (xs[0] - xs[2]) * (xs[1] - xs[2])
        a = (xs[2] * (f[1] - f[0]) + xs[1] * (f[0] - f[2]) + xs[0] * (f[2] - f[1])) / den
        bb = (xs[2] ** 2 * (f[0] - f[1]) + xs[1] ** 2 * (f[2] - f[0])
              + xs[0] ** 2 * (f[1] - f[2])) / den
        if a > 0:
            lam = math.exp(min(max(-bb / (2 * a), xs[0]), xs[2]))
    info = {"lam_rule": "sure", "sure_curve": [[a_, c] for a_, c in curve]}
    return lam, x0, info




#: The λ rules by name (``lam="auto"``, ``lam="discrepancy"``): ``rule(sp, sens, b, y, mask, ok,
#: x0, sigma, scale, inner_iters, max_iter, tol, changed, alpha)`` → ``(lam, x0, record)``.
LAM_RULES = {"auto": _sure_lam, "discrepancy": _discrepancy_lam}
