"""Spatial-spectral reconstruction: per-pixel data terms coupled by a vectorial total variation.

Per-pixel NNLS (:mod:`hsi_torch.recon.nnls`) solves every pixel alone. This package solves the
whole frame at once,

    ``min_{s ≥ 0}  Σ_p ‖W_p (A_p s_p − y_p)‖² + β ‖D s_p‖²  +  λ · TV(s)``,

over the cube ``s (M, h, w)`` restricted to the active (valid) pixels. Up to a constant the data
terms are ``Σ_p s_pᵀ G_p s_p − 2 b_pᵀ s_p`` with the per-pixel Gram matrix
``G_p = A_pᵀ W_p A_p + β DᵀD`` and ``b_p = A_pᵀ W_p y_p``, so the solver only needs
``G (P|1, M, M)`` and ``b (P, M)`` (those of :class:`~hsi_torch.recon.nnls.NNLSProblem`). TV is
the vectorial isotropic total variation on the active-pixel grid: one norm over all bands per
pixel keeps edges aligned across bands and penalises a jump by its spectral magnitude, so an
edge between two spectra costs ``λ·‖s₁ − s₂‖₂`` per unit length. With ``brightness_weight``
``α < 1`` the TV is ``Σ‖K ∇s‖``: jumps of the flat-spectrum component cost ``α`` times less.

Modules, one idea each:

* :mod:`~hsi_torch.recon.spatial.operators`: the TV gradient and its adjoint, the brightness
  weighting ``K``, the TV and its proximal operator under ``z ≥ 0``;
* :mod:`~hsi_torch.recon.spatial.noise`: the frame's noise level and the data scale of ``λ``;
* :mod:`~hsi_torch.recon.spatial.problem`: the frame problem (``G``, ``ρ``, the factor, the
  grid; cached per bundle);
* :mod:`~hsi_torch.recon.spatial.admm`: the ADMM loop and its stopping rule, one step per
  backend (torch, or the compiled CPU kernels of :mod:`~hsi_torch.recon.spatial._compiled`);
* :mod:`~hsi_torch.recon.spatial.lam`: the ``λ`` rules (fixed, SURE, discrepancy);
* :mod:`~hsi_torch.recon.spatial.subspace`: the TV on ``k`` leading spectral components, the
  complement per pixel (``solve_frame(..., rank=k)``, the ``spectral_rank`` setting);
* :mod:`~hsi_torch.recon.spatial.frame`: one frame of the pipeline (:func:`solve_frame`).

The scale of ``λ``: with noise of standard deviation ``σ`` (DN) on the observations, the
reconstruction noise and the useful ``λ`` both scale as ``σ · sqrt(trace G)`` (:func:`lam_scale`),
so a dimensionless ``lam`` (the relative weight) carries over between prototypes, exposures and
bundles. Every public name is importable from this package:
``from hsi_torch.recon.spatial import solve_frame, DEFAULT_LAM``.
"""

from hsi_torch.recon.spatial.admm import CHECK_EVERY, SpatialResult, solve_spatial
from hsi_torch.recon.spatial.frame import (
    BRIGHTNESS_WEIGHT,
    FRAME_INNER_ITERS,
    FRAME_TOL,
    solve_frame,
)
from hsi_torch.recon.spatial.lam import AUTO_LAM_RANGE, AUTO_LAM_STEPS, DEFAULT_LAM, SURE_LAMS
from hsi_torch.recon.spatial.noise import (
    NOISE_SAMPLES,
    effective_dof,
    estimate_noise,
    frame_noise_level,
    lam_scale,
    mean_square_residual,
)
from hsi_torch.recon.spatial.operators import (
    brightness_weighted,
    grid_edges,
    grid_gradient,
    grid_gradient_adjoint,
    prox_tv_nonneg,
    total_variation,
)
from hsi_torch.recon.spatial.problem import (
    RHO_SCALE,
    SpatialProblem,
    bundle_spatial_problem,
    guide_weights,
    prepare_spatial,
)

__all__ = [
    "CHECK_EVERY",
    "RHO_SCALE",
    "FRAME_TOL",
    "FRAME_INNER_ITERS",
    "SpatialResult",
    "SpatialProblem",
    "grid_edges",
    "grid_gradient",
    "grid_gradient_adjoint",
    "total_variation",
    "brightness_weighted",
    "BRIGHTNESS_WEIGHT",
    "prox_tv_nonneg",
    "prepare_spatial",
    "solve_spatial",
    "effective_dof",
    "estimate_noise",
    "lam_scale",
    "DEFAULT_LAM",
    "NOISE_SAMPLES",
    "AUTO_LAM_RANGE",
    "AUTO_LAM_STEPS",
    "SURE_LAMS",
    "mean_square_residual",
    "bundle_spatial_problem",
    "guide_weights",
    "frame_noise_level",
    "solve_frame",
]
