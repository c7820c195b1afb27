"""Gram matrices, KKT residuals and the small batched helpers of the NNLS solver.

Normal-equation form of every pixel's problem: ``min ½ xᵀGx − bᵀx, x ≥ 0`` with
``G = Aᵀ W A + β DᵀD`` and ``b = Aᵀ W y``; KKT conditions ``x ≥ 0``, ``g = Gx − b ≥ 0``,
``x ⊙ g = 0``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from hsi_torch.errors import InputError
from hsi_torch.spectral import difference_matrix

__all__ = ["smoothness_gram", "nnls_kkt_residual"]


def _rowvec(
    v: Tensor, mat: Tensor, *, out: Tensor | None = None, sub: Tensor | None = None
) -> Tensor:
    """``v[p] @ mat[p]`` (minus ``sub[p]``) for ``v (n, K)``, ``mat (n|1, K, L)`` -> ``(n, L)``.

    The row-vector form of a batched mat-vec is the fast one on CPU (a symmetric ``mat`` gives
    ``mat @ v``). ``out``: contiguous ``(n, L)`` to write into; ``sub``: ``(n, L)`` subtracted in
    the same kernel.
    """
    if mat.shape[0] == 1 and v.shape[0] != 1:
        if sub is not None:
            return torch.addmm(sub, v, mat[0], beta=-1, out=out)
        return torch.mm(v, mat[0], out=out)
    o3 = None if out is None else out.unsqueeze(1)
    if sub is not None:
        r = torch.baddbmm(sub.unsqueeze(1), v.unsqueeze(1), mat, beta=-1, out=o3)
    else:
        r = torch.bmm(v.unsqueeze(1), mat, out=o3)
    return r.squeeze(1) if out is None else out


def _take(t: Tensor | None, sl: slice | Tensor) -> Tensor | None:
    """Rows ``sl`` (a slice or an index tensor) of a per-pixel tensor; shared (leading dim 1)
    and ``None`` pass through."""
    if t is None or t.shape[0] == 1:
        return t
    return t[sl]


def _expand_rows(t: Tensor, n: int) -> Tensor:
    return t.expand(n, *t.shape[1:]) if t.shape[0] == 1 and n != 1 else t


def _default_tol(dtype: torch.dtype, num_bands: int) -> float:
    return float(num_bands * torch.finfo(dtype).eps)


def _admm_tol(dtype: torch.dtype) -> float:
    return float(torch.finfo(dtype).eps) ** 0.5


def _default_chunk(device: torch.device) -> int:
    # Measured on the 2-core CPU: chunks of a few thousand pixels keep the batched 25×25 LAPACK
    # calls in cache and are ~2× faster than one huge batch. GPUs prefer large batches.
    return 8192 if device.type == "cpu" else 262144


def _default_stream_chunk(device: torch.device) -> int:
    # per-frame solve, streamed stages (b = AᵀWy, x = Hb, KKT check): on the 2-core CPU chunks of
    # ~16k pixels keep the (n, M) temporaries in cache (measured ~3x faster than one full-frame
    # batch with 2 threads); GPUs prefer one large batch
    return 16384 if device.type == "cpu" else 1 << 20


def _default_solve_chunk(device: torch.device) -> int:
    # correction sub-batch: as large as memory comfortably allows (fewer Python-level rounds)
    return 131072 if device.type == "cpu" else 1 << 20


def _chunk_len(
    num: int, per_pixel_bytes: int, chunk_size: int | None, max_memory: int | None,
    device: torch.device, default: int | None = None,
) -> int:
    if chunk_size is not None:
        if int(chunk_size) < 1:
            raise ValueError(f"chunk_size must be >= 1, got {chunk_size}")
        n = int(chunk_size)
    elif max_memory is not None:
        if int(max_memory) < 1:
            raise ValueError(f"max_memory must be >= 1 byte, got {max_memory}")
        n = max(1, int(max_memory) // max(1, per_pixel_bytes))
    else:
        n = _default_chunk(device) if default is None else default
    return max(1, min(n, max(num, 1)))


def smoothness_gram(
    num_bands: int, beta: float, diff_order: int, *, device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
) -> Tensor:
    """The regulariser's Gram matrix ``β DᵀD`` ``(M, M)`` (zeros for ``β = 0``), ``D`` from
    :func:`hsi_torch.spectral.difference_matrix`."""
    if beta > 0:
        D = difference_matrix(num_bands, diff_order, device=device, dtype=dtype)
        return beta * (D.T @ D)
    return torch.zeros((num_bands, num_bands), dtype=dtype, device=device)


def _gram_norm(G: Tensor) -> Tensor:
    """Lower bound of ``‖G‖₂`` (largest eigenvalue of the PSD ``G``): ``(P|1, M, M)`` -> ``(P|1,)``.

    The larger of ``max_m G_mm`` and the Rayleigh quotient after three power-iteration steps from
    the all-ones vector (close to the Perron vector of the non-negative Gram matrices of this
    camera). Both never exceed ``‖G‖₂``, so the KKT residual built on it is never underestimated.
    """
    tiny = torch.finfo(G.dtype).tiny
    v = torch.ones(G.shape[:2], dtype=G.dtype, device=G.device)
    for _ in range(3):
        v = _rowvec(v, G)
        v = v / v.square().sum(1, keepdim=True).sqrt().clamp_min(tiny)
    rq = (_rowvec(v, G) * v).sum(1)
    return torch.maximum(rq, G.diagonal(dim1=1, dim2=2).amax(1)).clamp_min(0)


def _norm2(v: Tensor) -> Tensor:
    """Row 2-norms of ``(n, K)`` (a sum of squares: the fast reduction on CPU)."""
    return (v * v).sum(1).sqrt()


def nnls_kkt_residual(G: Tensor, b: Tensor, x: Tensor, gram_norm: Tensor | None = None) -> Tensor:
    """Relative KKT residual (a normwise backward error) of ``min ½xᵀGx − bᵀx, x ≥ 0`` per pixel.

    Args:
        G: ``(P|1, M, M)`` symmetric positive semi-definite Gram matrices.
        b: ``(P, M)`` right-hand sides.
        x: ``(P, M)`` candidate solutions.
        gram_norm: ``(P|1,)`` a lower bound of ``‖G‖₂`` if already known (default: computed as
            in :class:`NNLSProblem`).

    Returns:
        ``(P,)`` ``‖min(diag(G) ⊙ x, g)‖₂ / (‖G‖₂ ‖x‖₂ + ‖b‖₂)`` with ``g = Gx − b`` (0 where the
        denominator is 0). The numerator vanishes exactly when ``x ≥ 0``, ``g ≥ 0`` and
        ``x ⊙ g = 0``; dividing by ``‖G‖₂‖x‖₂ + ‖b‖₂`` (the size of the terms that make up ``g``)
        makes it the relative perturbation of ``(G, b)`` the answer is exact for (Rigal–Gaches),
        so a well-solved pixel scores ``O(eps)`` whatever ``cond(G)``.
    """
    g = _rowvec(x, G) - b
    gn = _gram_norm(G) if gram_norm is None else gram_norm
    return _kkt_ratio(g, x, G.diagonal(dim1=-2, dim2=-1), gn, _norm2(b))


def _kkt_ratio(g: Tensor, x: Tensor, gd: Tensor, gn: Tensor, bnorm: Tensor) -> Tensor:
    """:func:`nnls_kkt_residual` from ``g``, ``diag(G)``, the ``‖G‖₂`` bound and ``‖b‖₂``.

    The denominator is 0 only where ``x = 0`` and ``b = 0``; then ``g = 0`` and the ratio is 0.
    """
    t = gd * x
    torch.minimum(t, g, out=t)
    return _norm2(t) / (gn * _norm2(x) + bnorm).clamp_min(torch.finfo(x.dtype).tiny)


def _first_used(bad: Tensor, mask: Tensor | None) -> tuple[int, int, int, int] | None:
    """Of the entries ``bad (P, O)`` that ``mask`` uses (``None``: all): how many, in how many
    pixels, and the first as ``(pixel, observation)``; ``None`` when there are none."""
    if mask is not None:
        bad = bad & mask
    px = bad.any(1)
    n_px = int(px.sum())
    if n_px == 0:
        return None
    p = int(px.nonzero()[0, 0])
    return int(bad.sum()), n_px, p, int(bad[p].nonzero()[0, 0])


class NonFiniteObservations(InputError):
    """NaN or ±inf in an observation the mask uses (:func:`check_finite_rhs`)."""


def non_finite_observations(y: Tensor, mask: Tensor | None) -> NonFiniteObservations | None:
    """The error naming the used observations of ``y (P, O)`` that are NaN or ±inf (``mask``
    ``(P, O)`` bool or ``None`` = all used): how many, in how many pixels, the first by pixel
    and observation index, and the fix. ``None`` when there are none. A full pass over ``y``:
    for the error path only."""
    found = _first_used(~torch.isfinite(y.detach()), mask)
    if found is None:
        return None
    count, n_px, p, o = found
    return NonFiniteObservations(
        f"y holds NaN or inf in {count} used observation(s) of {n_px} pixel(s), the "
        f"first at pixel {p}, observation {o} (y[{p}, {o}] = {float(y[p, o])}); the solver "
        "cannot use them: mask them out (mask=False there: solve_nnls / prepare_nnls take a "
        "(P, O) bool mask; the reconstruction pipeline's frame mask drops non-finite samples "
        "this way) or replace them with finite values"
    )


class ObservationsOverflow(InputError):
    """Finite observations too large for the problem's dtype: ``b = Aᵀ W y`` overflows it
    (:func:`rhs_overflow`), or casting ``y`` to it makes them inf (:func:`cast_overflow`)."""


_OVERFLOW_FIX = ("scale the data (divide y by a constant, and the solution with it) or solve in "
                 "float64 (a float64 A or sensing model, and y)")  # fmt: skip


def rhs_overflow(b: Tensor, y: Tensor, mask: Tensor | None,
                 offset: int = 0) -> ObservationsOverflow | None:  # fmt: skip
    """The error naming the pixels whose right-hand side ``b (n, M)`` is not finite although
    their used observations ``y`` are (``b`` of the pixels ``offset … offset + n`` of ``y (P,
    O)``): the values overflow the problem's dtype, which would give those pixels ``x = 0``.
    ``None`` when ``b`` is finite. For the error path only."""
    bad = ~torch.isfinite(b.detach()).all(1)
    n_px = int(bad.sum())
    if n_px == 0:
        return None
    i = int(bad.nonzero()[0, 0])
    p = offset + i
    yp = y[p].detach().abs()
    if mask is not None:
        yp = torch.where(mask[min(p, mask.shape[0] - 1)], yp, torch.zeros((), dtype=yp.dtype))
    dt = b.dtype
    n = b.shape[0]  # a chunk's b counts its own pixels only: say which
    among = "" if n >= y.shape[0] else f" (of the pixels {offset} to {offset + n - 1})"
    return ObservationsOverflow(
        f"b = A^T W y overflows {str(dt).removeprefix('torch.')} in {n_px} pixel(s){among} whose "
        f"used observations are finite, the first at pixel {p} (largest |y| there "
        f"{float(yp.max()):.4g}, largest {str(dt).removeprefix('torch.')} "
        f"{torch.finfo(dt).max:.4g}): the values overflow the problem's dtype and the solver "
        f"would give those pixels x = 0; {_OVERFLOW_FIX}"
    )


def cast_overflow(
    y: Tensor, dtype: torch.dtype, mask: Tensor | None
) -> ObservationsOverflow | None:
    """The error naming the used observations of ``y (P, O)`` that are finite but become inf when
    ``y`` is cast to the problem's ``dtype`` (a float64 ``y`` of a float32 problem); ``None``
    when there are none. A full pass over ``y``: for the error path only."""
    if y.dtype == dtype or not y.is_floating_point():
        return None
    yd = y.detach()
    found = _first_used(torch.isfinite(yd) & ~torch.isfinite(yd.to(dtype)), mask)
    if found is None:
        return None
    count, n_px, p, o = found
    src, dst = str(y.dtype).removeprefix("torch."), str(dtype).removeprefix("torch.")
    return ObservationsOverflow(
        f"y is {src} and the problem {dst}: casting y to {dst} made {count} used "
        f"observation(s) of {n_px} pixel(s) inf, the first at pixel {p}, observation {o} "
        f"(y[{p}, {o}] = {float(yd[p, o]):.4g}, largest {dst} {torch.finfo(dtype).max:.4g}): "
        f"the values overflow the problem's dtype; {_OVERFLOW_FIX}"
    )


def check_finite_rhs(b: Tensor, y: Tensor, mask: Tensor | None, offset: int = 0) -> None:
    """Raise :class:`NonFiniteObservations` when a used observation of ``y (P, O)`` is NaN or
    ±inf, and :class:`ObservationsOverflow` when the observations are finite but a pixel's
    right-hand side is not (they overflow the problem's dtype). ``b (n, M)`` are right-hand
    sides ``Aᵀ W y`` of the pixels ``offset … offset + n``: a non-finite used observation makes
    its pixel's ``b`` non-finite (``0·inf`` is NaN too), so one sum over ``b`` (``M`` floats a
    pixel, ~1 ms a full float32 frame) decides whether ``y`` and ``b`` are looked at at all; a
    finite ``b`` whose sum overflows costs that look and raises nothing."""
    if bool(torch.isfinite(b.detach().sum())):
        return
    err = non_finite_observations(y, mask) or rhs_overflow(b, y, mask, offset)
    if err is not None:
        raise err
