"""The spatial solve of one frame of the pipeline, warm-started from its per-pixel solution."""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor

from hsi_torch.forward_model import SensingModel
from hsi_torch.recon import precompute_cache as disk
from hsi_torch.recon.nnls import _compiled as nnls_compiled
from hsi_torch.recon.nnls.constants import BPP_ROUNDS, REFINE_STEPS
from hsi_torch.recon.nnls.kkt import _default_tol
from hsi_torch.recon.sensing import BundleSensing
from hsi_torch.recon.spatial import _compiled as compiled
from hsi_torch.recon.spatial.admm import CHECK_EVERY, SpatialResult, solve_spatial
from hsi_torch.recon.spatial.lam import DEFAULT_LAM, LAM_RULES
from hsi_torch.recon.spatial.noise import (
    NOISE_SAMPLES,
    frame_noise_level,
    gram_trace_median,
    lam_scale,
    mean_square_residual,
)
from hsi_torch.recon.spatial.problem import SpatialProblem, bundle_spatial_problem, guide_weights
from hsi_torch.recon.spatial.subspace import restore_nonneg, spectral_basis, subspace_problem

__all__ = ["FRAME_TOL", "FRAME_INNER_ITERS", "BRIGHTNESS_WEIGHT", "solve_frame"]

#: Tolerance of :func:`solve_frame` (the pipeline) on the relative primal/dual residuals, and its
#: dual iterations per ADMM step. The relative primal residual mostly measures the
#: well-determined directions, where ``x`` and ``z`` agree slowly with a small ``ρ`` but the
#: answer hardly moves: at this tolerance (10 iterations on the full-size frames) the answers
#: score within 0.15 dB of the ``tol = 1e-6`` answers (100–400 iterations).
FRAME_TOL = 1e-2
FRAME_INNER_ITERS = 5

#: The pipeline's brightness weight ``α`` of the TV
#: (:func:`~hsi_torch.recon.spatial.operators.brightness_weighted`): a jump of the flat-spectrum
#: component (brightness, shading, texture) costs ``α`` times a jump of the
#: spectral shape. Natural scenes vary in brightness at every scale while their spectra vary
#: little, so with ``α < 1`` the prior can smooth the spectral shape's noise harder without
#: flattening brightness texture (as colour denoisers smooth chroma more than luma): on the
#: full-size CAVE frame the brighter half's median spectral angle fell from 2.41° (α = 1, its
#: best) to 2.13° (α = 0.3, lam 2), 0.8 dB higher PSNR; 0.1 scored the same as 0.3.
BRIGHTNESS_WEIGHT = 0.3


def solve_frame(
    sens: BundleSensing,
    y: Tensor,
    mask: Tensor,
    ok: Tensor,
    changed: Tensor,
    x0: Tensor,
    *,
    lam: float | str = DEFAULT_LAM,
    iters: int | None = None,
    inner_iters: int = FRAME_INNER_ITERS,
    tol: float | None = FRAME_TOL,
    max_iter: int = 2000,
    guided: bool = False,
    brightness_weight: float = BRIGHTNESS_WEIGHT,
    rank: int | None = None,
    start: Tensor | None = None,
    dual: tuple | None = None,
    u0: Tensor | None = None,
    u0_mask: Tensor | None = None,
    check_every: int = CHECK_EVERY,
    sigma: float | None = None,
    workspace: dict | None = None,
    relax: float = 1.0,
) -> tuple[Tensor, dict[str, Any]]:
    """The spatial solve of one frame, warm-started from its per-pixel solution.

    Args:
        sens: the bundle's :class:`~hsi_torch.recon.sensing.BundleSensing`.
        y: ``(P, 3V)`` observations, 0 where ``mask`` is False; mask: ``(P, 3V)`` frame mask;
            ok: ``(P,)`` valid pixels (the TV graph); changed: ``(P,)`` pixels whose frame mask
            differs from the static one (their own Gram matrices are used).
        x0: ``(P, M)`` per-pixel NNLS solution (warm start and noise estimate; detached).
        lam: relative TV weight: ``λ = lam · σ̂ · sqrt(median trace G)`` (:func:`lam_scale`) with
            ``σ̂`` = :func:`frame_noise_level`; ``"auto"``: chosen per frame by minimising a
            Monte-Carlo SURE estimate of the prediction risk of this very estimator over
            :data:`SURE_LAMS` (one more per-pixel solve, eleven spatial solves);
            ``"discrepancy"``: Morozov's discrepancy principle (:func:`mean_square_residual` =
            ``σ̂²``; nine solves).
        iters, inner_iters, tol, max_iter: see :func:`solve_spatial` (``iters``: fixed,
            differentiable with respect to ``y``); defaults :data:`FRAME_INNER_ITERS` and
            :data:`FRAME_TOL` (``None``: :func:`solve_spatial`'s own).
        guided: weight the TV's edges by the reference view's own colour steps
            (:func:`guide_weights`): less smoothing across edges the RGB image shows.
        brightness_weight: the TV's weight ``α`` on jumps of the flat-spectrum component
            (:data:`BRIGHTNESS_WEIGHT`; 1: plain vectorial TV).
        rank: ``k < M``: the prior on the ``k`` leading spectral components of ``x0`` and the
            complement per pixel (:mod:`~hsi_torch.recon.spatial.subspace`; the compiled CPU
            path with a fixed ``lam``; elsewhere, and for ``None`` or ``k = M``, the full-band
            solve).
        start: ``(P, M)`` the ADMM's start instead of ``x0`` (e.g. the previous frame's answer
            in a sequence; ``x0`` still gives the noise estimate); dual: the TV prox's dual to
            start from (``info["spatial_dual"]`` of a previous frame, :func:`solve_spatial`'s
            ``dual0``); u0, u0_mask: the ADMM's scaled dual to start from on the masked rows
            (``info["spatial_u"]`` of a previous frame; :func:`solve_spatial`'s); check_every:
            iterations between two checks of the stopping rule (:func:`solve_spatial`'s);
            sigma: the noise level ``σ̂`` (DN) to use instead of this frame's estimate (e.g. the
            previous frame's in a sequence of the same exposure; ``info["noise_sigma_given"]``
            says so); workspace: :func:`solve_spatial`'s (the ADMM's buffers kept between
            frames: a sequence's, or the bundle sensing's for frames without a warm start);
            relax: :func:`solve_spatial`'s over-relaxation.

    Returns:
        ``x (P, M)`` and ``info``: ``lam`` (relative), ``lam_abs`` (``λ``), ``lam_rule``
        (``"fixed"``, ``"sure"`` with the ``sure_curve`` ``[lam, SURE per observation]`` pairs,
        or ``"discrepancy"`` with ``discrepancy_target`` and the search's
        ``[lam, mean square residual]`` pairs), ``noise_sigma`` (``σ̂``, DN),
        ``mean_square_residual`` (DN², of the answer, on the noise estimate's
        :data:`NOISE_SAMPLES` pixels), ``spatial_iterations``,
        ``spatial_converged``, ``spatial_primal_residual``, ``spatial_dual_residual``, ``rho``,
        ``brightness_weight``, ``spectral_rank`` (``k``, or ``M``: the full-band solve),
        ``spatial_dual`` (the final dual state, for ``dual``), ``spatial_u`` (the final scaled
        dual, for ``u0``; ``None`` in the fixed-iteration and subspace modes).
    """
    alpha = brightness_weight
    auto = isinstance(lam, str)
    if auto and lam not in LAM_RULES:
        raise ValueError(f"lam must be a number >= 0, 'auto' or 'discrepancy', got {lam!r}")
    if not auto:
        lam = float(lam)
        if not (lam >= 0 and math.isfinite(lam)):
            raise ValueError(f"lam must be finite and >= 0, got {lam}")
    model, prob = sens.model, sens.problem
    base = bundle_spatial_problem(sens)
    rows = changed.nonzero().squeeze(1)
    row_gram = model.gram(mask.index_select(0, rows), rows, prob.reg) if rows.numel() else None
    x0 = x0.detach()
    given = sigma is not None and math.isfinite(sigma) and sigma > 0
    sigma = float(sigma) if given else frame_noise_level(sens, y, mask, ok, x0)
    # a sequence's per-frame constants (the TV graph and its compiled layout, λ's data scale
    # median trace G): kept in the workspace with the valid pixels they were made for, reused
    # only for the same bundle and exactly the same valid pixels (else made again)
    kept = None if workspace is None else workspace.get("frame_constants")
    if not (kept is not None and kept[0] is base and kept[1].shape == ok.shape
            and torch.equal(kept[1], ok)):
        kept = None
    with torch.no_grad():
        if kept is not None:
            sp = kept[2].with_rows(rows, row_gram)
        else:
            sp = base.for_frame(ok, rows, row_gram)
        plain = sp
        if guided and math.isfinite(sigma):
            sp = base.for_frame(ok, rows, row_gram, guide_weights(sp, y.detach(), mask, sigma))
    med = kept[3] if kept is not None else gram_trace_median(prob.gram, ok)
    scale = lam_scale(sigma, prob.gram, ok, med) if math.isfinite(sigma) else 0.0
    if workspace is not None and kept is None:
        workspace["frame_constants"] = (base, ok.clone(), plain, med)
    b = _adjoint(model, y.to(model.dtype), mask)
    extra: dict[str, Any] = {"lam_rule": "fixed"}
    if auto:
        if scale > 0:
            rule = LAM_RULES[lam]
            with torch.no_grad():
                lam, x0, extra = rule(sp, sens, b.detach(), y, mask, ok, x0, sigma, scale,
                                      inner_iters, max_iter, tol, changed, alpha)
        else:
            lam, extra = 0.0, {"lam_rule": f"{lam} (no noise estimate: lam = 0)"}
    lam_abs = lam * scale
    m = x0.shape[1]
    if (rank is not None and int(rank) < m and iters is None and not auto
            and compiled.AVAILABLE and nnls_compiled.AVAILABLE and b.device.type == "cpu"
            and sp.compiled_inputs() is not None):
        res, k = _solve_subspace(sens, sp, b, lam_abs, x0, ok, int(rank), row_gram, tol,
                                 max_iter, inner_iters, alpha), int(rank)
    else:
        # the per-pixel G⁻¹ is not read by the spatial solve: its pages of a mapped
        # precomputation cache entry leave the resident set until the next frame's warm start
        disk.release_pages(prob.gram_inv)
        z0 = x0 if start is None else start.detach().to(device=x0.device, dtype=x0.dtype)
        res = solve_spatial(sp, b, lam_abs, x0=z0, tol=tol, max_iter=max_iter, iters=iters,
                            inner_iters=inner_iters, brightness_weight=alpha, dual0=dual,
                            u0=u0, u0_mask=u0_mask, check_every=check_every,
                            workspace=workspace, relax=relax)
        k = m
    info = {
        "prior": "tv", "lam": lam, "lam_abs": lam_abs, **extra, "noise_sigma": sigma,
        "noise_sigma_given": given,
        "brightness_weight": alpha, "spectral_rank": k,
        "mean_square_residual": mean_square_residual(sens, res.x, y, mask, ok, NOISE_SAMPLES),
        "spatial_iterations": res.iterations, "spatial_converged": res.converged,
        "spatial_primal_residual": res.primal_residual,
        "spatial_dual_residual": res.dual_residual, "rho": res.rho, "spatial_dual": res.dual,
        "spatial_u": res.u,
    }  # fmt: skip
    return res.x, info


def _adjoint(model: Any, y: Tensor, mask: Tensor) -> Tensor:
    """``Aᵀ y`` of every pixel (``y`` 0 where ``mask`` is False): the NNLS kernel's compiled
    right-hand side on the CPU (one pass over the factors, ~4× the torch batched products), the
    model's operator elsewhere or where ``y`` needs a gradient."""
    if (nnls_compiled.AVAILABLE and y.device.type == "cpu" and isinstance(model, SensingModel)
            and not model.shared and not (y.requires_grad and torch.is_grad_enabled())):
        out = nnls_compiled.adjoint_frame(
            y.detach().numpy(), mask.numpy(), model.transmittance.numpy(), model.gain.numpy(),
            model.response.numpy(), torch.get_num_threads())
        return torch.from_numpy(out)
    return model.A_adjoint(y)


def _solve_subspace(
    sens: BundleSensing, sp: SpatialProblem, b: Tensor, lam_abs: float, x0: Tensor, ok: Tensor,
    rank: int, row_gram: Tensor | None, tol: float | None, max_iter: int, inner_iters: int,
    alpha: float,
) -> SpatialResult:
    """The prior on the ``rank`` leading components of ``x0`` (:mod:`.subspace`): the reduced
    ADMM without the bound, then every pixel's exact NNLS with the TV's pull held fixed."""
    prob = sens.problem
    with torch.no_grad():
        basis = spectral_basis(x0, rank, ok)
        row_ginv = None
        if sp.row_index is not None:
            row_ginv = torch.cholesky_inverse(torch.linalg.cholesky(row_gram))
        sub = subspace_problem(sp, prob.gram_inv, b, basis, row_ginv)
        res = solve_spatial(sub.problem, sub.b, lam_abs, x0=sub.start, tol=tol, max_iter=max_iter,
                            inner_iters=inner_iters, brightness_weight=alpha, nonneg=False)
        P = x0.shape[0]
        skip = (prob.singular | prob.no_data).expand(P)
        x, _ = restore_nonneg(sub, res.x, b, prob.gram, prob.gram_inv, prob.gram_diag,
                              prob.gram_norm, skip, _default_tol(b.dtype, x0.shape[1]),
                              BPP_ROUNDS, REFINE_STEPS, torch.get_num_threads(), row_gram)
    return SpatialResult(x, res.iterations, res.converged, res.primal_residual,
                         res.dual_residual, res.lam, res.rho)
