"""Batched non-negative, smoothness-regularised least squares: one small problem per pixel.

Every pixel ``p`` solves

.. math::

    x_p = \\arg\\min_{x \\ge 0} \\sum_o w_{po} (A_p x - y_p)_o^2 + \\beta \\lVert D x \\rVert^2

with ``A_p`` of shape ``(O, M)`` (``O`` observations, ``M`` bands), a 0/1 observation mask ``w``
and ``D`` the difference operator of :func:`hsi_torch.spectral.difference_matrix`. In
normal-equation form this is the convex quadratic programme ``min ½ xᵀGx − bᵀx, x ≥ 0`` with
``G = Aᵀ W A + β DᵀD`` and ``b = Aᵀ W y``; its KKT conditions are ``x ≥ 0``, ``g = Gx − b ≥ 0`` and
``x ⊙ g = 0``.

Solver ``"active_set"`` (exact, finite termination):

1. Per calibration (:func:`prepare_nnls`, done once when ``A``, mask and ``beta`` are fixed):
   the Gram matrices ``G_p``, their explicit inverses ``H_p = G_p⁻¹`` (batched Cholesky) and a
   lower bound of ``‖G_p‖₂``. A frame then costs, streamed over cache-sized pixel chunks,
   ``b = Aᵀ W y`` and ``x = H b`` (two batched row-vector products).
2. Pixels whose ``x`` has a negative entry are gathered into one compacted sub-batch and run
   *block principal pivoting* (Júdice & Pires; Kim & Park's NNLS variant) on the zero set ``Z``,
   starting from ``Z`` = the negative entries (usually already the answer). The solution with
   ``x_Z = 0`` is ``x = x₀ − H[:, Z] H_ZZ⁻¹ x₀_Z`` and its multipliers ``λ_Z = −H_ZZ⁻¹ x₀_Z``
   (the gradient on ``Z``), so a round reads ``|Z|`` rows of ``H`` and factorises a
   ``|Z| × |Z|`` system per pixel (pixels bucketed by ``|Z|``, padded within a bucket). Infeasible
   variables (``x_F < 0`` or ``λ_Z < 0``) are exchanged; after three rounds without progress
   only the largest one (Murty's rule: finite termination for positive definite ``G``). Pixels
   leave the working set as they finish; those not settled after 16 rounds (badly conditioned
   ``G`` cycling through single pivots) continue with Lawson–Hanson (3.).
3. An independent KKT check with the exact ``G`` and ``b`` for every pixel (streamed), as a
   normwise backward error (:func:`nnls_kkt_residual`); pixels above ``tol`` (default ``M·eps``)
   get up to ``refine`` steps of iterative refinement on their zero set. Pixels whose ``G`` is
   singular or numerically so (``beta = 0`` with rank-deficient ``A``, few observations), or that
   still fail, use the Lawson–Hanson active-set method on a principal-pivot tableau of ``G``
   starting from ``x = 0``; a variable only enters the free set while its reduced pivot is safely
   positive, so the free columns stay independent and the KKT conditions hold at the end.

On CPU every kernel runs single-threaded and the pixels are split between ``num_threads`` Python
threads instead (default ``torch.get_num_threads()``): thousands of small multi-threaded kernels
stall at their barriers whenever another process holds a core (see
:func:`~hsi_torch.recon.nnls._threads.workers_for`).

``solver="admm"`` (:mod:`hsi_torch.recon.nnls.admm`): ADMM on ``x = z, z ≥ 0`` with per-pixel
``(G + ρI)⁻¹`` precomputed, warm started from the clamped unconstrained solution (or a given
``x0``). With ``admm_iters=N`` it runs exactly ``N`` iterations with out-of-place torch ops
only, so the result is differentiable w.r.t. ``y``.

Convention:
    ``A``: ``(O, M)`` shared by all pixels or ``(P, O, M)`` one per pixel; ``y``: ``(P, O)``;
    ``mask``: ``(P, O)`` bool, ``True`` = observation used. ``y`` may hold non-finite values where
    the mask is ``False``; ``A`` must be finite. Observation index ``o = 3·v + c`` (view-major)
    as in the rest of the package, but the solver itself is agnostic of it. No per-pixel Python
    loops: all loops run over iterations or pivots of a whole (sub-)batch; memory is bounded by
    chunking over pixels.

Modules: :mod:`~hsi_torch.recon.nnls.problem` (:class:`NNLSProblem`, :func:`prepare_nnls`,
:func:`solve_nnls`), :mod:`~hsi_torch.recon.nnls.frame` (the active-set solve of a frame: one
driver for both kernels), :mod:`~hsi_torch.recon.nnls.constants` (the exchange rules both
kernels apply), :mod:`~hsi_torch.recon.nnls.kkt` (Gram matrices, KKT residuals, chunk sizes),
:mod:`~hsi_torch.recon.nnls.active_set` (block principal pivoting and Lawson–Hanson kernels),
:mod:`~hsi_torch.recon.nnls.admm`, :mod:`~hsi_torch.recon.nnls._compiled` (the numba CPU kernel;
numba itself through :mod:`hsi_torch.recon._numba`) and :mod:`~hsi_torch.recon.nnls._threads`
(CPU thread pools). This package is the one import path of
the solver: ``from hsi_torch.recon.nnls import solve_nnls, prepare_nnls``.
"""

from hsi_torch.recon.nnls._threads import cpu_threads
from hsi_torch.recon.nnls.kkt import masked_gram, nnls_kkt_residual, smoothness_gram
from hsi_torch.recon.nnls.problem import (
    NNLSProblem,
    NNLSResult,
    SolveOptions,
    prepare_nnls,
    solve_nnls,
)

__all__ = [
    "NNLSResult",
    "NNLSProblem",
    "prepare_nnls",
    "solve_nnls",
    "SolveOptions",
    "nnls_kkt_residual",
    "smoothness_gram",
    "masked_gram",
    "cpu_threads",
]
