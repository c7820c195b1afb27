"""Batched non-negative, smoothness-regularised least squares: one small problem per pixel.

Every pixel ``p`` solves

.. math::

    x_p = \\arg\\min_{x \\ge 0} \\sum_o w_{po} (A_p x - y_p)_o^2 + \\beta \\lVert D x \\rVert^2

with ``A_p`` of shape ``(O, M)`` (``O`` observations, ``M`` bands), a 0/1 observation mask ``w``
and ``D`` the difference operator of :func:`hsi_torch.spectral.difference_matrix`. In
normal-equation form this is the convex quadratic programme ``min ½ xᵀGx − bᵀx, x ≥ 0`` with
``G = Aᵀ W A + β DᵀD`` and ``b = Aᵀ W y``; its KKT conditions are ``x ≥ 0``, ``g = Gx − b ≥ 0`` and
``x ⊙ g = 0``.

Solver ``"active_set"`` (exact, finite termination; the method and its measured choices in
``docs/solver.md``):

1. Per calibration (:func:`prepare_nnls`): ``G_p``, ``H_p = G_p⁻¹`` (batched Cholesky) and a
   lower bound of ``‖G_p‖₂``. A frame then costs ``b = Aᵀ W y`` and ``x₀ = H b``, streamed over
   pixel chunks.
2. Pixels whose ``x₀`` has a negative entry run *block principal pivoting* (Júdice & Pires; Kim &
   Park's NNLS variant) on the zero set ``Z``: ``x = x₀ − H[:, Z] H_ZZ⁻¹ x₀_Z``,
   ``λ_Z = −H_ZZ⁻¹ x₀_Z``; infeasible variables (``x_F < 0`` or ``λ_Z < 0``) are exchanged, after
   three rounds without progress only the largest (Murty's rule); pixels not settled after 16
   rounds continue with Lawson–Hanson.
3. An independent KKT check with the exact ``G`` and ``b`` (:func:`nnls_kkt_residual`, a
   normwise backward error); pixels above ``tol`` (default ``M·eps``) get up to ``refine`` steps
   of iterative refinement; singular pixels and those still failing use Lawson–Hanson on a
   principal-pivot tableau of ``G`` from ``x = 0``.

On CPU every kernel runs single-threaded and the pixels are split between ``num_threads`` Python
threads (:func:`~hsi_torch.recon.nnls._threads.workers_for`). ``solver="admm"``
(:mod:`hsi_torch.recon.nnls.admm`): ADMM on ``x = z, z ≥ 0``; with ``admm_iters=N`` it runs
exactly ``N`` iterations, differentiable w.r.t. ``y``.

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
from hsi_torch.recon.nnls.kkt import nnls_kkt_residual, smoothness_gram
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
    "cpu_threads",
]
