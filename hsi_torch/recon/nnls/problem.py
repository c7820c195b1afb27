"""The problem object of the batched NNLS solver: per-pixel factorisations kept between frames.

See :mod:`hsi_torch.recon.nnls` for the method. :class:`NNLSProblem` holds the sensing operator
(dense matrices, or the camera's factored :class:`~hsi_torch.forward_model.SensingModel`), the
static observation mask and, per pixel, the inverse ``H = G⁻¹`` of the Gram matrix
``G = Aᵀ W A + β DᵀD``, ``G`` itself, ``diag(G)`` and a lower bound of ``‖G‖₂``. The dense
sensing matrices are not kept: right-hand sides ``Aᵀ W y`` go through the operator.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TypedDict

import numpy as np
import torch
from torch import Tensor
from typing_extensions import Unpack  # Python 3.10 (a dependency of torch)

from hsi_torch.forward_model import DenseSensing, OnDevice, SensingModel
from hsi_torch.recon.nnls import _compiled
from hsi_torch.recon.nnls._threads import cpu_threads, for_chunks, workers_for
from hsi_torch.recon.nnls.admm import solve_admm
from hsi_torch.recon.nnls.constants import REFINE_STEPS
from hsi_torch.recon.nnls.frame import solve_active_set
from hsi_torch.recon.nnls.kkt import (
    NonFiniteObservations,
    ObservationsOverflow,
    _admm_tol,
    _chunk_len,
    _default_solve_chunk,
    _default_stream_chunk,
    _default_tol,
    _gram_norm,
    _rowvec,
    _take,
    cast_overflow,
    non_finite_observations,
    rhs_overflow,
    smoothness_gram,
)

__all__ = ["NNLSResult", "NNLSProblem", "SolveOptions", "prepare_nnls", "solve_nnls"]

_SOLVERS = ("active_set", "admm")
_BACKENDS = ("auto", "torch", "compiled")
Sensing = SensingModel | DenseSensing


@dataclass
class NNLSResult:
    """Output of :func:`solve_nnls` / :meth:`NNLSProblem.solve`.

    Attributes:
        x: ``(P, M)`` solution, ``≥ 0``, never NaN (0 for pixels without data).
        converged: ``(P,)`` bool, the method terminated and the relative KKT residual is ``≤ tol``.
        iterations: ``(P,)`` int64; active set: exchange rounds plus Lawson–Hanson iterations of
            the fallback (0 when the unconstrained solution was already non-negative); ADMM:
            iterations run.
        kkt_residual: ``(P,)`` KKT residual as a normwise backward error,
            ``‖min(diag(G) ⊙ x, g)‖₂ / (‖G‖₂ ‖x‖₂ + ‖b‖₂)`` with ``g = Gx − b`` (see
            :func:`nnls_kkt_residual`; 0 for an exact solution, O(eps) for a well-solved one).
        no_data: ``(P,)`` bool, pixel had no usable observation (all masked): ``x = 0``.
        solver: the solver used (``"active_set"`` or ``"admm"``).
    """

    x: Tensor
    converged: Tensor
    iterations: Tensor
    kkt_residual: Tensor
    no_data: Tensor
    solver: str = "active_set"

def _empty_result(m: int, dtype: torch.dtype, device: torch.device, solver: str) -> NNLSResult:
    """The result for zero pixels: ``x (0, M)`` and empty per-pixel fields."""
    return NNLSResult(
        torch.zeros((0, m), dtype=dtype, device=device),
        torch.zeros((0,), dtype=torch.bool, device=device),
        torch.zeros((0,), dtype=torch.long, device=device),
        torch.zeros((0,), dtype=dtype, device=device),
        torch.zeros((0,), dtype=torch.bool, device=device),
        solver,
    )


def _as_sensing(A: Tensor | Sensing) -> Sensing:
    if isinstance(A, (SensingModel, DenseSensing)):
        return A
    if not isinstance(A, Tensor):
        raise TypeError(f"A must be a torch.Tensor or a SensingModel, got {type(A).__name__}")
    if A.dtype not in (torch.float32, torch.float64):
        raise TypeError(f"A must be float32 or float64, got {A.dtype}")
    if A.ndim not in (2, 3):
        raise ValueError(f"A must have shape (O, M) or (P, O, M), got {tuple(A.shape)}")
    return DenseSensing(A)


def _check_inputs(
    A: Tensor | Sensing, mask: Tensor | None, beta: float, diff_order: int
) -> tuple[Sensing, Tensor | None, float]:
    op = _as_sensing(A)
    # the Gram matrices and their factorisations are formed without autograd: a gradient
    # through A would only see A's part in the right-hand side AᵀWy, a wrong derivative
    tensors = (op.matrices,) if isinstance(op, DenseSensing) else (
        op.transmittance, op.gain, op.response)
    if torch.is_grad_enabled() and any(t.requires_grad for t in tensors):
        raise ValueError(
            "A requires grad, but the NNLS solver is differentiable with respect to y only (its "
            "Gram matrices and their factorisations are constants for autograd, so a gradient "
            "with respect to A would be wrong): pass A.detach(), or run under torch.no_grad()"
        )
    if op.dtype not in (torch.float32, torch.float64):
        raise TypeError(f"the sensing operator must be float32 or float64, got {op.dtype}")
    o, m = op.num_obs, op.num_bands
    if o < 1 or m < 1:
        raise ValueError(f"A needs at least one observation and one band, got O={o}, M={m}")
    if diff_order not in (0, 1, 2):
        raise ValueError(f"diff_order must be 0, 1 or 2, got {diff_order}")
    beta = float(beta)
    if not (beta >= 0.0) or beta == float("inf"):
        raise ValueError(f"beta must be finite and >= 0, got {beta}")
    # ||beta D^T D|| <= 16 beta; the factorisation multiplies entries of G: keep them below
    # sqrt(max) of the dtype, or G overflows and every answer becomes 0 (or NaN)
    beta_max = math.sqrt(torch.finfo(op.dtype).max) / 16
    if beta > beta_max:
        raise ValueError(f"beta = {beta:g} overflows the {op.dtype} solve (at most {beta_max:.1e}; "
                         "the useful range is about 1e-2..1e6 on the DN^2 scale)")
    if beta > 0 and m < diff_order + 1:
        raise ValueError(f"diff_order={diff_order} needs at least {diff_order + 1} bands, got {m}")
    if mask is not None:
        if not isinstance(mask, Tensor):
            raise TypeError(f"mask must be a torch.Tensor or None, got {type(mask).__name__}")
        if mask.ndim != 2 or mask.shape[1] != o:
            raise ValueError(f"mask must have shape (P, {o}) to match A, got {tuple(mask.shape)}")
        if not op.shared and mask.shape[0] != op.num_pixels:
            raise ValueError(
                f"mask has {mask.shape[0]} pixels but A has {op.num_pixels}"
            )
        if mask.device != op.device:
            raise ValueError(f"mask is on {mask.device} but A is on {op.device}")
        if mask.dtype != torch.bool and bool(((mask != 0) & (mask != 1)).any()):
            # weights would be read as used / not used: a weighted least squares in silence
            raise TypeError(f"mask must be bool (True = observation used), got {mask.dtype} "
                            "values other than 0 and 1; the solver does not weight "
                            "observations (scale the rows of A and y by the square roots of "
                            "the weights instead)")
        mask = mask.to(torch.bool)
    return op, mask, beta


class NNLSProblem(OnDevice):
    """Precomputed per-pixel factorisations of one sensing configuration; reuse for every frame.

    Build with :func:`prepare_nnls`. Holds the sensing operator (a reference), the mask, the
    regulariser ``β DᵀD`` and per pixel the Gram matrix ``G`` and its inverse ``H = G⁻¹``, each
    ``(P, M, M)`` (or ``(1, M, M)`` when ``A`` is shared and there is no mask): ``2·P·M²``
    floats, ≈ 1.6 GB in float32 for 324 000 pixels × 25 bands.

    Attributes:
        sensing: :class:`~hsi_torch.forward_model.SensingModel` or
            :class:`~hsi_torch.forward_model.DenseSensing`; mask: ``(P, O)`` bool or ``None``;
            beta; diff_order; reg: ``(M, M)`` ``β DᵀD``.
        gram, gram_inv: ``(1|P, M, M)``; ``gram_inv`` is 0 where ``singular``.
        gram_diag: ``(1|P, M)`` ``diag(G)``; gram_norm: ``(1|P,)`` lower bound of ``‖G‖₂``;
            gram_diag_max: ``(1|P,)``.
        singular: ``(1|P,)`` bool, ``G`` (numerically) singular: those pixels use
            Lawson–Hanson. no_data: ``(1|P,)`` bool, all observations masked.
    """

    _ON = "sensing"

    def __init__(
        self,
        sensing: Sensing,
        mask: Tensor | None,
        beta: float,
        diff_order: int,
        gram: Tensor,
        gram_inv: Tensor,
        gram_diag: Tensor,
        gram_norm: Tensor,
        singular: Tensor,
        no_data: Tensor,
    ) -> None:
        self.sensing = sensing
        self.mask = mask
        self.beta = float(beta)
        self.diff_order = int(diff_order)
        self.reg = smoothness_gram(sensing.num_bands, self.beta, self.diff_order,
                                   device=sensing.device, dtype=sensing.dtype)
        self.gram = gram
        self.gram_inv = gram_inv
        self.gram_diag = gram_diag
        self.gram_norm = gram_norm
        self.gram_diag_max = gram_diag.amax(1)
        self.singular = singular
        self.no_data = no_data
        self._admm_cache: dict[str, tuple[Tensor, Tensor]] = {}

    # -- shapes -----------------------------------------------------------------------------
    @property
    def num_pixels(self) -> int | None:
        """``P``, or ``None`` when ``A`` is shared and unmasked (any ``P`` is accepted)."""
        if self.mask is not None:
            return self.mask.shape[0]
        return None if self.sensing.shared else self.sensing.num_pixels

    @property
    def num_obs(self) -> int:
        return self.sensing.num_obs

    @property
    def num_bands(self) -> int:
        return self.sensing.num_bands


    def memory_bytes(self) -> int:
        """Bytes held by the factorisation (not the operator or the mask)."""
        ts = (self.gram, self.gram_inv, self.gram_diag, self.gram_norm, self.singular,
              self.no_data)
        return int(sum(t.numel() * t.element_size() for t in ts))

    # -- Gram products ----------------------------------------------------------------------
    def gram_matrices(self, idx: Tensor | slice | None = None) -> Tensor:
        """Stored ``G`` of pixels ``idx`` ``(n, M, M)`` (``(1, M, M)`` when shared)."""
        G = self.gram
        if G.shape[0] == 1 or idx is None:
            return G
        return G[idx] if isinstance(idx, slice) else G.index_select(0, idx)

    def gram_apply(self, x: Tensor, idx: Tensor | slice | None = None) -> Tensor:
        """``G x`` ``(n, M)`` for pixels ``idx``."""
        return _rowvec(x, self.gram_matrices(idx))

    def _masked_y(self, y: Tensor, sl: slice) -> Tensor:
        """``y`` of the pixels ``sl`` with 0 where the mask is False (NaN-safe)."""
        yc = y[sl]
        w = _take(self.mask, sl)
        if w is not None:
            yc = torch.where(w, yc, torch.zeros((), dtype=yc.dtype, device=yc.device))
        return yc

    def rhs(self, y: Tensor, sl: slice) -> Tensor:
        """``b = Aᵀ W y`` for the pixels ``sl`` -> ``(n, M)``."""
        return self.sensing.A_adjoint(self._masked_y(y, sl), sl)

    def _check_y(self, y: Tensor) -> Tensor:
        if not isinstance(y, Tensor):
            raise TypeError(f"y must be a torch.Tensor, got {type(y).__name__}")
        if y.ndim != 2 or y.shape[1] != self.num_obs:
            raise ValueError(f"y must have shape (P, {self.num_obs}), got {tuple(y.shape)}")
        p = self.num_pixels
        if p is not None and y.shape[0] != p:
            raise ValueError(f"y has {y.shape[0]} pixels but the problem has {p}")
        if y.device != self.device:
            raise ValueError(f"y is on {y.device} but A is on {self.device}")
        if not y.is_floating_point():
            raise TypeError(f"y must be floating point, got {y.dtype}")
        return y.to(self.dtype)

    # -- solve ------------------------------------------------------------------------------
    def solve(
        self,
        y: Tensor,
        *,
        solver: str = "active_set",
        tol: float | None = None,
        max_iter: int | None = None,
        refine: int | None = None,
        chunk_size: int | None = None,
        max_memory: int | None = None,
        x0: Tensor | None = None,
        admm_iters: int | None = None,
        rho: float | None = None,
        num_threads: int | None = None,
        backend: str = "auto",
    ) -> NNLSResult:
        """Solve all pixels for observations ``y``.

        Args:
            y: ``(P, O)`` observations (same device as ``A``; cast to ``A``'s dtype).
            solver: ``"active_set"`` (exact) or ``"admm"``.
            tol: active set: tolerance on the KKT residual (a backward error, see
                :class:`NNLSResult`), default ``M·eps(dtype)``; ADMM: relative primal/dual
                residual tolerance (``‖x − z‖∞`` and ``‖z − z_prev‖∞`` over ``‖z‖∞``), default
                ``sqrt(eps)``.
            max_iter: active set: exchange rounds (at most 16, then Lawson–Hanson) and
                Lawson–Hanson iterations (default ``10·M``); ADMM: iterations in the
                tolerance-driven mode (default 5000).
            refine: at most this many steps of iterative refinement (on the final zero set), only
                for pixels whose KKT residual exceeds ``tol`` (default 2).
            chunk_size / max_memory: pixels per chunk, or a working-memory budget in bytes.
            x0: ``(P, M)`` warm start (e.g. the previous frame's solution): ADMM starts from
                it; the active-set method starts the pixels that need pivoting from its zero set
                ``x0 == 0`` (instead of the negative entries of ``G⁻¹b`` or the compiled
                kernel's coordinate-descent start). The answer is the same (the exchange rules
                terminate from any start); only the rounds change.
            admm_iters: run exactly this many ADMM iterations (no data-dependent stopping,
                differentiable w.r.t. ``y``). Ignored by the active-set method.
            rho: ADMM penalty; default per pixel ``trace(G)/M``.
            num_threads: CPU threads (default ``torch.get_num_threads()``); each runs
                single-threaded kernels on its share of the pixels, so no kernel waits at a
                thread barrier for a core another process holds.
            backend: the active-set correction's kernels: ``"auto"`` (the compiled CPU kernel
                when numba is installed and the problem is on the CPU, else the batched torch
                kernels), ``"torch"`` or ``"compiled"``. Same method and answers (to rounding).

        Returns:
            :class:`NNLSResult`. Gradients flow only in the fixed-iteration ADMM mode.

        Raises:
            ValueError: (an :class:`~hsi_torch.errors.InputError`) NaN or ±inf in ``y`` where
                the mask uses it, naming how many and the first (pixel, observation); NaN or inf
                where the mask is ``False`` is ignored. Finite observations too large for the
                problem's dtype (``b = Aᵀ W y`` overflows, or casting a float64 ``y`` to a
                float32 problem makes inf) raise ``ObservationsOverflow``, naming the first pixel.
        """
        if backend not in _BACKENDS:
            raise ValueError(f"backend must be one of {_BACKENDS}, got {backend!r}")
        workers = workers_for(self.device, num_threads)
        if solver not in _SOLVERS:
            raise ValueError(f"solver must be one of {_SOLVERS}, got {solver!r}")
        y_in, y = y, self._check_y(y)
        with cpu_threads(self.device, 1):
            try:
                return self._solve_cast(y, solver, tol, max_iter, refine, chunk_size,
                                        max_memory, x0, admm_iters, rho, workers, backend)
            except (NonFiniteObservations, ObservationsOverflow):
                err = cast_overflow(y_in, self.dtype, self.mask)  # inf made by the cast: say so
                if err is None:
                    raise
                raise err from None

    def _solve_cast(
        self, y: Tensor, solver: str, tol: float | None, max_iter: int | None,
        refine: int | None, chunk_size: int | None, max_memory: int | None, x0: Tensor | None,
        admm_iters: int | None, rho: float | None, workers: int, backend: str,
    ) -> NNLSResult:
        P, m = y.shape[0], self.num_bands
        if P == 0:
            return _empty_result(m, self.dtype, self.device, solver)
        if tol is None:
            tol = _default_tol(self.dtype, m) if solver == "active_set" else _admm_tol(self.dtype)
        tol = float(tol)
        if not tol > 0:
            raise ValueError(f"tol must be > 0, got {tol}")
        if refine is None:
            refine = REFINE_STEPS
        if int(refine) < 0:
            raise ValueError(f"refine must be >= 0, got {refine}")
        if x0 is not None and (x0.shape != (P, m) or x0.device != self.device):
            raise ValueError(f"x0 must have shape ({P}, {m}) on {self.device}, got "
                             f"{tuple(x0.shape)} on {x0.device}")
        if admm_iters is not None and int(admm_iters) < 0:
            raise ValueError(f"admm_iters must be >= 0, got {admm_iters}")
        item = torch.finfo(self.dtype).bits // 8
        if solver == "active_set":
            per_px = item * (2 * self.num_obs + 16 * m + 3 * m * m)
            n = _chunk_len(P, per_px, chunk_size, max_memory, self.device,
                           default=_default_stream_chunk(self.device))
            n_corr = _chunk_len(P, per_px, chunk_size, max_memory, self.device,
                                default=_default_solve_chunk(self.device))
            with torch.no_grad():
                out = solve_active_set(self, y, tol, max_iter or 10 * m, int(refine), n,
                                       n_corr, workers, backend,
                                       None if x0 is None else x0 == 0)
            return NNLSResult(*out, solver)
        out = solve_admm(self, y, tol, max_iter or 5000, chunk_size, max_memory, admm_iters, rho,
                         x0)
        return NNLSResult(*out, solver)


def prepare_nnls(
    A: Tensor | Sensing,
    *,
    mask: Tensor | None = None,
    beta: float = 0.0,
    diff_order: int = 1,
    chunk_size: int | None = None,
    max_memory: int | None = None,
    num_threads: int | None = None,
) -> NNLSProblem:
    """Factorise the per-pixel systems once (calibration fixed, only ``y`` changes per frame).

    Args:
        A: ``(O, M)`` shared or ``(P, O, M)`` per-pixel sensing matrices (float32/float64, any
            device, finite), or a :class:`~hsi_torch.forward_model.SensingModel` (the camera's
            factored ``A``, never expanded to dense matrices for the whole frame).
        mask: ``(P, O)`` bool, ``True`` = observation used; ``None`` = all used.
        beta: smoothness weight ``β ≥ 0`` on ``‖D x‖²`` (data scale, e.g. DN²).
        diff_order: order of ``D`` (0 identity, 1 first difference, 2 second difference).
        chunk_size / max_memory: pixels per chunk or working-memory budget (bytes) for the
            factorisation; the stored result is ``P·M²`` floats regardless.
        num_threads: CPU threads (default ``torch.get_num_threads()``); each runs
            single-threaded kernels on its share of the pixels.

    Returns:
        :class:`NNLSProblem`; call ``.solve(y)`` per frame.

    Example:
        >>> A = torch.rand(1000, 30, 25)
        >>> prob = prepare_nnls(A, beta=1e2)
        >>> res = prob.solve(torch.rand(1000, 30) * 255)
        >>> res.x.shape
        torch.Size([1000, 25])
    """
    op, mask, beta = _check_inputs(A, mask, beta, diff_order)
    workers = workers_for(op.device, num_threads)
    with cpu_threads(op.device, 1), torch.no_grad():
        return _prepare(op, mask, beta, diff_order, chunk_size, max_memory, workers)


def compiled_factorisation(device: torch.device | str) -> bool:
    """Whether :func:`prepare_nnls` factorises a per-pixel :class:`SensingModel` on ``device``
    with the compiled CPU pass (the CPU with numba) rather than the torch kernels."""
    return torch.device(device).type == "cpu" and _compiled.AVAILABLE


def _prepare(
    op: Sensing, mask: Tensor | None, beta: float, diff_order: int, chunk_size: int | None,
    max_memory: int | None, workers: int,
) -> NNLSProblem:
    o, m = op.num_obs, op.num_bands
    dev, dt = op.device, op.dtype
    if isinstance(op, SensingModel) and not op.shared and compiled_factorisation(dev):
        return _prepare_compiled(op, mask, beta, diff_order, workers)
    R = smoothness_gram(m, beta, diff_order, device=dev, dtype=dt)
    if op.shared and mask is None:
        P = 1
    else:
        P = mask.shape[0] if op.shared else op.num_pixels
    item = torch.finfo(dt).bits // 8
    n = _chunk_len(P, item * (o * m + 8 * m * m), chunk_size, max_memory, dev)
    gram = torch.empty((P, m, m), dtype=dt, device=dev)
    gram_inv = torch.empty((P, m, m), dtype=dt, device=dev)
    gram_diag = torch.empty((P, m), dtype=dt, device=dev)
    gram_norm = torch.empty((P,), dtype=dt, device=dev)
    singular = torch.empty((P,), dtype=torch.bool, device=dev)
    no_data = torch.zeros((P,), dtype=torch.bool, device=dev)
    eps = torch.finfo(dt).eps
    shared_masked = op.shared and mask is not None
    if shared_masked:  # G of a pixel = Σ_o w_o a_o a_oᵀ: one (P, O) × (O, M²) product
        a0 = op.dense()[0]
        outer = (a0.unsqueeze(2) * a0.unsqueeze(1)).reshape(o, m * m)

    def factor(sl: slice) -> None:
        w = None if mask is None else mask[sl]
        G = gram[sl]
        if shared_masked:
            torch.mm(w.to(dt), outer, out=G.view(-1, m * m))
            G.add_(R)
        else:
            G.copy_(op.gram(w, None if op.shared else sl, R))
        L, info = torch.linalg.cholesky_ex(G)
        gd = G.diagonal(dim1=1, dim2=2)
        ld2 = L.diagonal(dim1=1, dim2=2).square()
        bad = (info != 0) | ~(ld2.amin(1) > 20.0 * m * eps * gd.amax(1))
        bad |= ~torch.isfinite(ld2).all(1)
        any_bad = bool(bad.any())
        if any_bad:
            L = torch.where(bad.view(-1, 1, 1), torch.eye(m, dtype=dt, device=dev), L)
        Gi = gram_inv[sl]
        torch.cholesky_inverse(L, out=Gi)  # exactly symmetric
        if any_bad:
            Gi.masked_fill_(bad.view(-1, 1, 1), 0.0)
        singular[sl] = bad
        gram_diag[sl] = gd
        gram_norm[sl] = _gram_norm(G)
        if w is not None:
            no_data[sl] = ~w.any(1)

    for_chunks(factor, P, n, workers)
    singular |= no_data
    return NNLSProblem(op, mask, beta, diff_order, gram, gram_inv, gram_diag, gram_norm,
                       singular, no_data)


def _prepare_compiled(
    op: SensingModel, mask: Tensor | None, beta: float, diff_order: int, workers: int
) -> NNLSProblem:
    """:func:`_prepare` for the camera's factored ``A`` on the CPU: one compiled pass
    (:func:`~hsi_torch.recon.nnls._compiled.factor_sensing_cpu`, float64 arithmetic) forms each
    pixel's ``G`` from the factors, its Cholesky factor and ``H = G⁻¹``, ``diag G`` and the
    ``‖G‖₂`` bound, with the torch path's singularity test — pixel by pixel in cache, without
    the dense ``A`` or batched small LAPACK calls (about half the time, and on all threads)."""
    m = op.num_bands
    R = smoothness_gram(m, beta, diff_order, dtype=torch.float64)

    def host(t: Tensor) -> np.ndarray:
        return t.detach().contiguous().numpy()

    out = _compiled.factor_sensing_cpu(
        host(op.transmittance), host(op.gain), host(op.response),
        None if mask is None else host(mask), R.numpy(),
        torch.empty((), dtype=op.dtype).numpy().dtype, workers,
    )  # fmt: skip
    gram, gram_inv, gram_diag, gram_norm, singular, no_data = (torch.from_numpy(a) for a in out)
    return NNLSProblem(op, mask, beta, diff_order, gram, gram_inv, gram_diag, gram_norm,
                       singular, no_data)


class SolveOptions(TypedDict, total=False):
    """The options of :meth:`NNLSProblem.solve` (documented there), which :func:`solve_nnls`
    takes as keywords too: ``solver``, ``tol``, ``max_iter``, ``refine``, ``chunk_size``,
    ``max_memory``, ``x0``, ``admm_iters``, ``rho``, ``num_threads``, ``backend``."""

    solver: str
    tol: float | None
    max_iter: int | None
    refine: int | None
    chunk_size: int | None
    max_memory: int | None
    x0: Tensor | None
    admm_iters: int | None
    rho: float | None
    num_threads: int | None
    backend: str


_SOLVE_OPTIONS = frozenset(SolveOptions.__annotations__)


def solve_nnls(
    A: Tensor | Sensing,
    y: Tensor,
    *,
    beta: float = 0.0,
    mask: Tensor | None = None,
    diff_order: int = 1,
    **options: Unpack[SolveOptions],
) -> NNLSResult:
    """Batched non-negative smoothness-regularised least squares, one problem per pixel.

    ``x_p = argmin_{x ≥ 0} Σ_o mask_po (A_p x − y_p)_o² + beta ‖D x‖²``, ``D`` from
    :func:`hsi_torch.spectral.difference_matrix` (``M``, ``diff_order``).

    Args:
        A: ``(O, M)`` shared or ``(P, O, M)`` per pixel (float32 or float64, any device), or a
            :class:`~hsi_torch.forward_model.SensingModel`.
        y: ``(P, O)`` observations (e.g. DN). Entries where ``mask`` is False are ignored (may be
            NaN); a NaN or ±inf where it is True is a ``ValueError`` naming the first one.
        beta: smoothness weight (≥ 0) on the data's scale.
        mask: ``(P, O)`` bool, True = observation used; None = all.
        diff_order: 0, 1 (default) or 2.
        **options: :class:`SolveOptions`, as :meth:`NNLSProblem.solve` takes them.
            ``chunk_size`` / ``max_memory`` also bound the outer chunks here: each is factorised
            and solved on its own, so memory stays bounded (per-pixel ``A``; default 131 072
            pixels per outer chunk on CPU).

    Returns:
        :class:`NNLSResult` with ``x (P, M)``, ``converged``, ``iterations``, ``kkt_residual``,
        ``no_data``. Gradients flow to ``y`` only, and only in the fixed-iteration ADMM mode
        (``solver="admm", admm_iters=N``); an ``A`` that requires grad is refused
        (``ValueError``) while autograd is on.

    Example:
        >>> A = torch.rand(500, 30, 25, dtype=torch.float64)
        >>> y = torch.einsum("pom,pm->po", A, torch.rand(500, 25, dtype=torch.float64))
        >>> res = solve_nnls(A, y, beta=1e-2)
        >>> bool(res.converged.all()), bool((res.x >= 0).all())
        (True, True)
    """
    unknown = sorted(set(options) - _SOLVE_OPTIONS)
    if unknown:
        raise TypeError(f"solve_nnls() got unexpected keyword argument(s) {unknown}; the "
                        f"options are {sorted(_SOLVE_OPTIONS)}")
    solver = options.get("solver", "active_set")
    chunk_size, max_memory = options.get("chunk_size"), options.get("max_memory")
    x0 = options.get("x0")
    op, mask, beta = _check_inputs(A, mask, beta, diff_order)
    if not isinstance(y, Tensor) or y.ndim != 2:
        raise ValueError(f"y must be a (P, O) tensor, got {getattr(y, 'shape', type(y))}")
    P = y.shape[0]
    if not op.shared and op.num_pixels != P:
        raise ValueError(f"A has {op.num_pixels} pixels but y has {P}")
    if mask is not None and mask.shape[0] != P:
        raise ValueError(f"mask has {mask.shape[0]} pixels but y has {P}")
    if P == 0:  # nothing to solve: empty results of the right shapes
        if solver not in _SOLVERS:
            raise ValueError(f"solver must be one of {_SOLVERS}, got {solver!r}")
        return _empty_result(op.num_bands, op.dtype, op.device, solver)
    workers = workers_for(op.device, options.get("num_threads"))
    kw = {k: v for k, v in options.items() if k not in ("chunk_size", "max_memory", "x0")}
    kw["num_threads"] = workers
    if op.shared and mask is None:
        prob = prepare_nnls(op, beta=beta, diff_order=diff_order, num_threads=workers)
        return prob.solve(y, chunk_size=chunk_size, max_memory=max_memory, x0=x0, **kw)
    o, m = op.num_obs, op.num_bands
    item = torch.finfo(op.dtype).bits // 8
    # the factorisation of one outer chunk is held while it is solved: M² floats a pixel
    per_px = item * (o * m + 8 * m * m + 2 * o + 16 * m)
    n = _chunk_len(P, per_px, chunk_size, max_memory, op.device,
                   default=_default_solve_chunk(op.device))
    inner = n if chunk_size is not None or max_memory is not None else None
    parts: list[NNLSResult] = []
    for s in range(0, P, n):
        sl = slice(s, min(P, s + n))
        sub = op.select(sl)
        prob = prepare_nnls(sub, mask=None if mask is None else mask[sl], beta=beta,
                            diff_order=diff_order, chunk_size=inner, num_threads=workers)
        try:
            parts.append(prob.solve(y[sl], chunk_size=inner,
                                    x0=None if x0 is None else x0[sl], **kw))
        except NonFiniteObservations:  # named again from the whole y: its pixel indices
            raise non_finite_observations(y, mask) from None
        except ObservationsOverflow:  # likewise
            err = cast_overflow(y, op.dtype, mask)
            if err is None:
                yc = y[sl].to(op.dtype)
                err = rhs_overflow(prob.rhs(yc, slice(0, yc.shape[0])), y.to(op.dtype), mask,
                                   offset=s)  # fmt: skip
            raise err from None
    if len(parts) == 1:
        return parts[0]
    fields = ("x", "converged", "iterations", "kkt_residual", "no_data")
    return NNLSResult(*(torch.cat([getattr(r, f) for r in parts]) for f in fields), solver)
