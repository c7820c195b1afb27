"""ADMM over the cube: one loop, one stopping rule, a step per backend.

Method (scaled form, splitting ``x = z``; ``x`` carries the data terms, ``z`` the prior and
``z ≥ 0``), with the scalar penalty ``ρ`` of the :class:`~.problem.SpatialProblem`:

    ``x ← (G + ρI)⁻¹ (b + ρ (z − u))``   per pixel
    ``z ← prox_{(λ/2ρ)(TV + ι_{≥0})}(x + u)``   on the cube
    ``u ← u + x − z``

* x-update: the stored ``(G_p + ρI)⁻¹`` (one factorisation per problem and ``ρ``) applied by a
  batched matrix–vector product.
* z-update: the proximal operator of TV restricted to ``z ≥ 0`` (no closed form) by the fast
  gradient projection on the dual (:func:`~.operators.prox_tv_nonneg`): ``inner_iters`` dual
  iterations per step warm-started from the previous step's dual, so the prox is inexact early
  and its accuracy improves as ADMM settles (the tests check optimality against an independent
  solver). Non-negativity is exact (the prox's projection), so the returned ``z`` is ``≥ 0``.
  Inactive pixels have no TV edge: their prox is the projection.
* Warm start from the per-pixel NNLS solution ``x0``: ``z = x0``, ``u = (b − G x0)/ρ`` (the
  multiplier of the per-pixel optimum). With ``λ = 0`` this is already the fixed point.
* Warm start from a previous solve (a sequence's previous frame, ``u0``): ``z`` from the given
  start, the scaled dual ``u`` carried over (:attr:`SpatialResult.u`) on the rows ``u0_mask``
  selects (the rest as above) and the TV prox's dual (``dual0``). With ``z`` and ``u`` those of
  the previous optimum, the first x-update is ``x = z + (G + ρI)⁻¹ (b − b_prev)``: the
  iterations start from the change of the data alone, not from the per-pixel multiplier.
* Over-relaxation (Boyd et al. §3.4.3; ``relax = a ∈ (0, 2)``, 1: none): ``x̂ = a·x + (1 − a)·z``
  (``z`` the previous one) replaces ``x`` in the z- and u-updates. The fixed point, so the
  answer at convergence, is the same; with ``a > 1`` the iterations absorb a change of the data
  faster. The pipeline relaxes warm-started solves only (where the rule is checked every
  iteration and the saving counts; a cold solve checks first after 10 iterations and keeps its
  measured answers).
* Stopping (Boyd et al.), checked every ``check_every`` iterations (default
  :data:`CHECK_EVERY`): relative primal residual ``‖x − z‖ / ‖z‖`` (of ``x``, not ``x̂``) and
  relative dual residual
  ``ρ ‖z − z_prev‖ / ‖b‖`` both ``≤ tol``. ``ρ`` stays fixed (no residual balancing), so the
  factorisation is never recomputed. A warm start that is already near the optimum meets the
  rule in a few iterations; checking every iteration then saves the rest of the 10.

One loop (:func:`_admm`) runs the iterations and applies the stopping rule for every backend; a
backend is one iteration on its own storage (:class:`_Step`):

* :class:`_TorchStep` with the out-of-place prox: ``iters=N`` runs exactly ``N`` iterations, the
  answer differentiable with respect to ``b`` (hence ``y``), ``G`` and ``λ``;
* :class:`_TorchStep` with the in-place prox (:class:`~.operators._ProxWorkspace`): the
  tolerance-driven mode on any device;
* :class:`_CompiledStep`: the tolerance-driven mode on the CPU with numba
  (:mod:`~hsi_torch.recon.spatial._compiled`, the valid pixels only, each step in one pass), the
  same iterations (the answers agree to rounding).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch
from torch import Tensor

from hsi_torch.devices import to_numpy
from hsi_torch.recon import precompute_cache as disk
from hsi_torch.recon._numba import threads
from hsi_torch.recon.nnls._threads import cpu_threads
from hsi_torch.recon.spatial import _compiled as compiled
from hsi_torch.recon.spatial.operators import (
    _ProxWorkspace,
    fgp_dual_step,
    fista_momentum,
    prox_tv_nonneg,
)
from hsi_torch.recon.spatial.problem import SpatialProblem

__all__ = ["CHECK_EVERY", "SpatialResult", "solve_spatial"]

#: ADMM iterations between two checks of the stopping rule (tolerance-driven mode).
CHECK_EVERY = 10


@dataclass
class SpatialResult:
    """Output of :func:`solve_spatial`.

    Attributes:
        x: ``(P, M)`` solution, ``≥ 0``.
        iterations: ADMM iterations run; converged: the stopping rule was met (always True in
            the fixed-iteration mode); primal_residual, dual_residual: the last relative residuals
            (see the module docstring); lam: the ``λ`` used (objective scale); rho: the penalty.
        dual: the TV prox's final dual state (compiled backend: band-major arrays; ``None``
            elsewhere), for ``dual0`` of the next frame's solve.
        u: ``(P, M)`` the final scaled dual (after the last iteration's update ``u ← u + x −
            z``; the multiplier of ``x = z`` over ``ρ``), for ``u0`` of the next frame's solve
            (``None`` in the fixed-iteration mode).
    """

    x: Tensor
    iterations: int
    converged: bool
    primal_residual: float
    dual_residual: float
    lam: float
    rho: float
    dual: tuple | None = None
    u: Tensor | None = None


def solve_spatial(
    problem: SpatialProblem,
    b: Tensor,
    lam: float | Tensor,
    *,
    x0: Tensor | None = None,
    tol: float | None = None,
    max_iter: int = 2000,
    iters: int | None = None,
    inner_iters: int = 10,
    num_threads: int | None = 1,
    backend: str = "auto",
    brightness_weight: float = 1.0,
    nonneg: bool = True,
    dual0: tuple | None = None,
    u0: Tensor | None = None,
    u0_mask: Tensor | None = None,
    check_every: int = CHECK_EVERY,
    workspace: dict | None = None,
    relax: float = 1.0,
) -> SpatialResult:
    """ADMM for ``min_{s ≥ 0} Σ_p s_pᵀG_p s_p − 2 b_pᵀ s_p + λ·TV(s)`` (see the module docstring).

    Args:
        problem: :func:`~.problem.prepare_spatial`.
        b: ``(P, M)`` right-hand sides ``A_pᵀ W_p y_p`` (same device/dtype as ``G``).
        lam: ``λ ≥ 0`` on the objective's scale (DN² per unit of ``s``; see :func:`lam_scale`).
            A 0-d tensor is differentiated through in the fixed-iteration mode.
        x0: ``(P, M)`` warm start, normally the per-pixel NNLS solution (default ``max(G⁻¹b, 0)``
            approximated by one x-update from 0).
        tol: relative primal/dual residual tolerance (default ``1e-4`` in float32, ``1e-6`` in
            float64).
        max_iter: ADMM iterations at most (tolerance-driven mode).
        iters: run exactly this many iterations, out of place (differentiable w.r.t. ``b``,
            ``G`` and a tensor ``lam``).
        inner_iters: dual iterations of the TV prox per ADMM iteration (warm-started).
        num_threads: torch's CPU intra-op threads in the torch path's iterations (default 1:
            its kernels are small, and on a loaded machine multi-threaded kernels wait at their
            barriers — one gradient of a 25 × 104 × 120 cube took 44 ms with 2 threads under
            load vs 0.24 ms with one); ``None`` keeps torch's setting. No effect on other
            devices. The compiled kernels run on torch's intra-op thread count at the call (as
            the per-pixel solver's do).
        backend: ``"auto"`` (the compiled CPU kernels of
            :mod:`hsi_torch.recon.spatial._compiled` for the tolerance-driven mode on the CPU
            when numba is installed, else torch), ``"torch"`` or ``"compiled"`` (an error where
            it does not apply). Both run the same iterations; they agree to rounding.
        brightness_weight: ``α ∈ (0, 1]``, the TV's weight on the flat-spectrum component of
            every jump (:func:`~.operators.brightness_weighted`; 1: plain vectorial TV).
        nonneg: the bound ``s ≥ 0`` (default). ``False`` solves the problem without it (the
            TV prox alone; the spectral-subspace mode's coefficients, :mod:`.subspace`): the
            compiled backend only (tolerance-driven, CPU, numba).
        dual0: the TV prox's dual to start from (:attr:`SpatialResult.dual` of a previous solve
            of the same problem size, e.g. the previous frame of a sequence; compiled backend
            only, ignored elsewhere and where its shape differs). Default: zeros. With a
            ``workspace`` its arrays are taken over as the solve's first dual buffer (no
            copy; they are overwritten: pass a copy to keep them).
        u0: ``(P, M)`` the scaled dual to start from (:attr:`SpatialResult.u` of a previous
            solve of the same problem size; tolerance-driven mode). Default, and on the rows
            where ``u0_mask`` is False: ``(b − G z)/ρ``, the multiplier of the start ``z``.
        u0_mask: ``(P,)`` bool, the rows of ``u0`` used (default all).
        check_every: iterations between two checks of the stopping rule (``≥ 1``; default
            :data:`CHECK_EVERY`); 1 or 2 for a warm start near the optimum.
        workspace: a dict the compiled backend keeps its frame-sized iteration buffers in
            between solves of the same size (a sequence's frames: no fresh allocation, and no
            page faults on it, per frame; every buffer is written before it is read, so the
            answer is the same; the returned ``u`` and ``dual`` are not among them; an entry
            that is not a C-contiguous writable array of the buffer's shape and dtype is not
            used); ``None``: allocated per solve.
        relax: the over-relaxation ``a ∈ (0, 2)`` (module docstring; 1: none, the default).

    Returns:
        :class:`SpatialResult`.
    """
    if backend not in ("auto", "torch", "compiled"):
        raise ValueError(f"backend must be 'auto', 'torch' or 'compiled', got {backend!r}")
    if not 0.0 < float(brightness_weight) <= 1.0:
        raise ValueError(f"brightness_weight must be in (0, 1], got {brightness_weight}")
    if int(check_every) < 1:
        raise ValueError(f"check_every must be >= 1, got {check_every}")
    if not 0.0 < float(relax) < 2.0:
        raise ValueError(f"relax must be in (0, 2), got {relax}")
    P, m = problem.num_pixels, problem.num_bands
    if u0 is not None and tuple(u0.shape) != (P, m):
        raise ValueError(f"u0 must be ({P}, {m}), got {tuple(u0.shape)}")
    if u0_mask is not None and tuple(u0_mask.shape) != (P,):
        raise ValueError(f"u0_mask must be ({P},), got {tuple(u0_mask.shape)}")
    warm_u = None if u0 is None else (u0, u0_mask)
    return _solve_spatial(problem, b, lam, x0, tol, max_iter, iters, inner_iters, backend,
                          num_threads, float(brightness_weight), bool(nonneg), dual0, warm_u,
                          int(check_every), workspace, float(relax))


def _solve_spatial(
    problem: SpatialProblem, b: Tensor, lam: float | Tensor, x0: Tensor | None,
    tol: float | None, max_iter: int, iters: int | None, inner_iters: int,
    backend: str = "auto", num_threads: int | None = 1, alpha: float = 1.0,
    nonneg: bool = True,
    dual0: tuple | None = None,
    warm_u: tuple[Tensor, Tensor | None] | None = None,
    check_every: int = CHECK_EVERY,
    workspace: dict | None = None,
    relax: float = 1.0,
) -> SpatialResult:
    kernel_threads = torch.get_num_threads()
    P, m = problem.num_pixels, problem.num_bands
    if b.shape != (P, m):
        raise ValueError(f"b must be ({P}, {m}), got {tuple(b.shape)}")
    if b.device != problem.gram.device or b.dtype != problem.gram.dtype:
        raise ValueError(
            f"b is {b.dtype} on {b.device} but G is {problem.gram.dtype} on {problem.gram.device}"
        )
    lam_f = float(lam.detach()) if isinstance(lam, Tensor) else float(lam)
    if not (lam_f >= 0 and math.isfinite(lam_f)):
        raise ValueError(f"lam must be finite and >= 0, got {lam_f}")
    if iters is not None and iters < 0:
        raise ValueError(f"iters must be >= 0, got {iters}")
    if inner_iters < 1:
        raise ValueError(f"inner_iters must be >= 1, got {inner_iters}")
    if tol is None:
        tol = 1e-6 if b.dtype == torch.float64 else 1e-4
    rho = problem.rho
    t = (lam if isinstance(lam, Tensor) else lam_f) / (2.0 * rho)
    if x0 is None:
        z = problem.apply_inv(b)
        z = z.clamp_min(0) if nonneg else z
    else:
        if x0.shape != (P, m):
            raise ValueError(f"x0 must be ({P}, {m}), got {tuple(x0.shape)}")
        z = x0.to(b.dtype)
        z = z.clamp_min(0) if nonneg else z
    inputs = None
    if iters is None and backend != "torch":
        inputs = problem.compiled_inputs()
    if inputs is not None:  # the warm start's u is formed by the compiled pass itself
        with torch.no_grad():
            cstep = _CompiledStep(problem, inputs, b, z, float(t), lam_f, inner_iters, alpha,
                                  kernel_threads, nonneg, dual0, workspace, warm_u, relax)
            with threads(kernel_threads):
                it, done, prim, dual = _admm(cstep, rho, tol, max_iter,
                                             check_every=check_every)
            # the TV factor is not read again until the next frame's ADMM: its pages of the
            # mapped precomputation cache leave the resident set (the warm start is next)
            disk.release_pages(inputs[0])
            z_out = torch.from_numpy(cstep.result()).to(b.device)
            res = SpatialResult(z_out, it, done, prim, dual, lam_f, rho, cstep.final_dual(),
                                torch.from_numpy(cstep.final_u()).to(b.device))
            cstep.release(workspace)
            return res
    if not nonneg:
        raise ValueError("nonneg=False needs the compiled backend (numba, a CPU problem, pixels "
                         "in row-major order, the tolerance-driven mode)")
    if backend == "compiled" and iters is None:
        raise ValueError("the compiled spatial solver needs numba, a CPU problem and pixels in "
                         "row-major order")
    u = (b - problem.apply_gram(z)) / rho
    if warm_u is not None and iters is None:
        u0 = warm_u[0].to(u)
        u = u0 if warm_u[1] is None else torch.where(warm_u[1].to(u.device).view(-1, 1), u0, u)

    if iters is not None:  # fixed iterations, out of place: differentiable
        prox = None if lam_f == 0.0 else _DualProx(problem, t, inner_iters, alpha)
        step = _TorchStep(problem, b, z, u, prox, relax)
        with cpu_threads(b.device, num_threads):
            _admm(step, rho, 0.0, 0, int(iters))
        return SpatialResult(step.z, int(iters), True, float("nan"), float("nan"), lam_f, rho)
    with torch.no_grad(), cpu_threads(b.device, num_threads):
        prox = None
        if lam_f > 0:
            ws = _ProxWorkspace((m, *problem.frame_size), problem.ex, problem.ey, b.dtype,
                                b.device, alpha)
            tf = float(t)
            prox = lambda cube: ws.prox(cube, tf, inner_iters)  # noqa: E731
        step = _TorchStep(problem, b, z, u, prox, relax)
        it, done, prim, dual = _admm(step, rho, tol, max_iter, check_every=check_every)
    return SpatialResult(step.z, it, done, prim, dual, lam_f, rho, u=step.u)  # (updated)


# -- the loop and the stopping rule ----------------------------------------------------------
class _Step(Protocol):
    """One ADMM iteration of a backend, on its own storage of ``x``, ``z``, ``u``."""

    def __call__(self, i: int, keep: bool) -> None:
        """Iteration ``i`` (from 0); ``keep``: remember ``z`` before it (the dual residual)."""

    def norms(self) -> tuple[float, float, float]:
        """``‖z‖``, ``‖x − z‖``, ``‖z − z_kept‖`` after the last iteration."""

    def bnorm(self) -> float:
        """``‖b‖`` (1 where it is 0), the scale of the dual residual."""


def _admm(step: _Step, rho: float, tol: float, max_iter: int,
          iters: int | None = None, check_every: int = CHECK_EVERY
          ) -> tuple[int, bool, float, float]:
    """Run ``step``: exactly ``iters`` iterations, or until the stopping rule holds (checked
    every ``check_every`` iterations, at most ``max_iter`` rounded up to a multiple of it).

    Returns:
        the iterations run, whether the rule was met (True in the fixed mode), and the last
        relative primal and dual residuals (NaN in the fixed mode).
    """
    if iters is not None:
        for i in range(iters):
            step(i, False)
        return iters, True, float("nan"), float("nan")
    bnorm = step.bnorm()
    it, prim, dual, done = 0, float("inf"), float("inf"), False
    while it < max_iter:
        for k in range(check_every):
            step(it + k, k == check_every - 1)
        it += check_every
        zn, xz, dz = step.norms()
        prim = xz / (zn or 1.0)
        dual = rho * dz / bnorm
        if prim <= tol and dual <= tol:
            done = True
            break
    return it, done, prim, dual


# -- the backends ----------------------------------------------------------------------------
class _DualProx:
    """The out-of-place TV prox of the fixed-iteration mode, carrying its dual between steps."""

    def __init__(self, problem: SpatialProblem, t: float | Tensor, inner_iters: int,
                 alpha: float) -> None:
        self.problem, self.t, self.inner_iters, self.alpha = problem, t, inner_iters, alpha
        self.dual: Tensor | None = None

    def __call__(self, cube: Tensor) -> Tensor:
        zc, self.dual = prox_tv_nonneg(cube, self.t, self.problem.ex, self.problem.ey,
                                       self.inner_iters, self.dual, brightness_weight=self.alpha)
        return zc


class _TorchStep:
    """An ADMM iteration with torch operations on ``(P, M)`` tensors, the prox on the cube
    (``prox``: ``(M, h, w)`` → ``(M, h, w)``, ``None`` for ``λ = 0``: the projection)."""

    def __init__(self, problem: SpatialProblem, b: Tensor, z: Tensor, u: Tensor,
                 prox: Callable[[Tensor], Tensor] | None, relax: float = 1.0) -> None:
        self.problem, self.b, self.z, self.u, self.prox = problem, b, z, u, prox
        self.x = self.z_prev = z
        self.act = problem.active.view(-1, 1)
        self.relax = relax

    def __call__(self, i: int, keep: bool) -> None:
        p = self.problem
        self.z_prev = self.z
        x = p.apply_inv(self.b + p.rho * (self.z - self.u))
        xr = x if self.relax == 1.0 else torch.lerp(self.z, x, self.relax)  # a·x + (1 − a)·z
        v = xr + self.u
        if self.prox is None:
            z = v.clamp_min(0)
        else:  # inactive pixels: the projection (exact, whatever the dual holds)
            z = torch.where(self.act, p.from_cube(self.prox(p.to_cube(v))), v.clamp_min(0))
        self.u = self.u + xr - z
        self.x, self.z = x, z

    def norms(self) -> tuple[float, float, float]:
        return (float(self.z.norm()), float((self.x - self.z).norm()),
                float((self.z - self.z_prev).norm()))

    def bnorm(self) -> float:
        return float(self.b.norm()) or 1.0


class _CompiledStep:
    """An ADMM iteration with the compiled CPU kernels: the x-update, the FGP dual steps and the
    primal in one fused pass over the valid pixels (:func:`~._compiled.fgp_block`; with ``λ =
    0`` the x-update and the projection), on band-major ``(M, P)`` numpy state, every array
    double-buffered. Arguments as in :func:`solve_spatial`; ``inputs``:
    :meth:`~.problem.SpatialProblem.compiled_inputs`; ``num_blocks``: the fused pass's blocks of
    rows (one per thread)."""

    def __init__(self, problem: SpatialProblem, inputs: tuple[np.ndarray, tuple[np.ndarray, ...]],
                 b: Tensor, z0: Tensor, t: float, lam: float, inner_iters: int, alpha: float,
                 num_blocks: int = 1, nonneg: bool = True, dual0: tuple | None = None,
                 workspace: dict | None = None,
                 warm_u: tuple[Tensor, Tensor | None] | None = None,
                 relax: float = 1.0) -> None:
        self.inv_rows, graph = inputs
        self.rho, self.lam, self.alpha, self.nonneg = problem.rho, lam, alpha, nonneg
        self.relax = relax
        self.t = t if lam > 0 else 0.0
        self.step = fgp_dual_step(t) if t > 0 else 0.0

        P, m = b.shape
        self.row_slot = np.full(P, -1, np.int64)
        if problem.row_index is not None:
            self.row_slot[problem.row_index.numpy()] = np.arange(problem.row_index.shape[0])
            self.row_inv = np.ascontiguousarray(problem.row_inv.numpy())
            row_gram = np.ascontiguousarray(problem.row_gram.numpy())
        else:
            self.row_inv = row_gram = np.zeros((1, m, m), b.numpy().dtype)
        gram = problem.gram.detach().numpy()
        ws = {} if workspace is None else workspace
        dt = gram.dtype

        def buf(name: str, shape: tuple[int, ...], zero: bool) -> np.ndarray:
            a = ws.pop(name, None)  # taken out while this solve uses it
            if not (isinstance(a, np.ndarray) and a.shape == shape and a.dtype == dt
                    and a.flags.c_contiguous and a.flags.writeable):
                return np.zeros(shape, dt) if zero else np.empty(shape, dt)
            if zero:
                a.fill(0)
            return a

        u0 = use_u0 = None
        if warm_u is not None:  # the given scaled dual, band-major (a transposed view: no copy)
            u0 = to_numpy(warm_u[0], dt).T
            use_u0 = np.ones(P, np.bool_) if warm_u[1] is None else to_numpy(warm_u[1], np.bool_)
        # band-major b, z = max(z0, 0) and u = (b − G z)/ρ (the multiplier of the per-pixel
        # optimum; the given u0 where use_u0, without reading G there), in one pass
        self.b, self.z, self.u = compiled.start_state(
            np.ascontiguousarray(b.detach().numpy()), np.ascontiguousarray(z0.numpy()),
            np.ascontiguousarray(gram), self.row_slot, row_gram, self.rho, nonneg, u0, use_u0,
            (buf("b", (m, P), False), buf("z", (m, P), False), buf("u", (m, P), False)))
        # G is not read by the iterations: its pages of a mapped cache entry leave the
        # resident set while the ADMM state exists (the next frame reads them back)
        disk.release_pages(problem.gram)

        self.x = buf("x", self.z.shape, True)
        self.x2, self.u2, self.z2 = (buf(k, self.z.shape, False) for k in ("x2", "u2", "z2"))
        self.z_prev = self.z
        # the dual (band-major) and its band sums (brightness weighting), double-buffered too
        warm_dual = (dual0 is not None and dual0[0].shape == (2, m, P)
                     and dual0[1].shape == (2, P))
        if (warm_dual and workspace is not None
                and all(isinstance(a, np.ndarray) and a.dtype == dt and a.flags.c_contiguous
                        and a.flags.writeable for a in dual0)):
            # a sequence's dual (the previous solve's, not a buffer of the workspace): taken
            # over as this solve's first dual buffer, no frame-sized copy
            self.p, self.psum = dual0[0], dual0[1]
        else:
            self.p = buf("p", (2, m, P), not warm_dual)
            self.psum = buf("psum", (2, P), not warm_dual)
            if warm_dual:  # a warm start of the dual
                self.p[...] = dual0[0]
                self.psum[...] = dual0[1]
        self.p2 = buf("p2", (2, m, P), True)
        self.psum2 = buf("psum2", (2, P), True)
        self.grid = problem.fgp_grid()
        self.blocks = compiled.fgp_blocks(self.grid[0], num_blocks)
        row_ptr = self.grid[0]
        self.row_has_slot = np.zeros(row_ptr.shape[0] - 1, np.bool_)
        if problem.row_index is not None:
            rows = problem.row_index.numpy()
            self.row_has_slot[np.searchsorted(row_ptr, rows, side="right") - 1] = True
        moms, kk = [], 1.0
        for _ in range(inner_iters if lam > 0 else 0):  # FISTA from r = p (the last dual)
            kk, mom = fista_momentum(kk)
            moms.append(mom)
        self.moms = np.asarray(moms, self.z.dtype)

    def __call__(self, i: int, keep: bool) -> None:
        # u ← u + x − z from the second iteration on (x and z of the previous one)
        compiled.fgp_block(self.inv_rows, self.row_slot, self.row_inv, self.row_has_slot, self.b,
                           self.x, self.u, self.z, self.x2, self.u2, self.rho, i > 0, self.t,
                           self.step, self.moms, self.p, self.psum, self.p2, self.psum2, self.z2,
                           self.grid, self.blocks, self.alpha, self.nonneg, self.relax)
        self.z_prev = self.z  # the previous z, kept until the next iteration writes over it
        self.x, self.x2, self.u, self.u2 = self.x2, self.x, self.u2, self.u
        self.z, self.z2 = self.z2, self.z
        if self.moms.shape[0]:  # (λ = 0: no dual)
            self.p, self.p2, self.psum, self.psum2 = self.p2, self.p, self.psum2, self.psum

    def release(self, workspace: dict | None) -> None:
        """Hand the iteration buffers to ``workspace`` for the next solve of this size (not
        ``u`` nor the dual: :meth:`final_u` and :meth:`final_dual` returned them; ``z`` after
        :meth:`result` copied it)."""
        if workspace is not None:
            workspace.update(x=self.x, x2=self.x2, u2=self.u2, z2=self.z2, b=self.b, z=self.z,
                             p2=self.p2, psum2=self.psum2)

    def final_dual(self) -> tuple[np.ndarray, np.ndarray]:
        """The TV prox's final dual ``(2, M, P)`` and its band sums ``(2, P)``: the step's own
        arrays, not copies (not handed to a workspace by :meth:`release`; a later solve with a
        workspace takes them over as its first dual buffer when given them as ``dual0``)."""
        return self.p, self.psum

    def result(self) -> np.ndarray:
        """``z`` pixel-major ``(P, M)``."""
        return np.ascontiguousarray(self.z.T)

    def final_u(self) -> np.ndarray:
        """The scaled dual after the last iteration, ``u + x − z``, pixel-major ``(P, M)``: a
        transposed view of the step's own ``u``, updated in place (no frame-sized copy on every
        solve, warm-started or not; the step is done after this)."""
        self.u += self.x
        self.u -= self.z
        return self.u.T

    def norms(self) -> tuple[float, float, float]:
        return compiled.norms3(self.z, self.x, self.z_prev, self.relax)

    def bnorm(self) -> float:
        return float(np.linalg.norm(self.b)) or 1.0
