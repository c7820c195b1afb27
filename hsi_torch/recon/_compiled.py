"""Compiled CPU pass of the pipeline's per-pixel bookkeeping (numba, optional).

:func:`~hsi_torch.recon.frame.solve_observations` needs, per frame, the pixels that keep
enough views, the pixels whose frame mask differs from the static one (they are re-solved with
their own mask) and the observations with the masked entries set to 0. As torch operations these
are five passes over ``(P, 3V)`` tensors (a masked copy, a comparison, two reductions over a
short trailing dimension); :func:`frame_masks_cpu` does them in one pass over the pixels, on all
threads. Without numba (or with ``HSI_TORCH_NO_NUMBA=1``) the pipeline runs the torch operations
(same results).
"""

from __future__ import annotations

import numpy as np

from hsi_torch.recon._numba import AVAILABLE, threads
from hsi_torch.recon._numba import nb as _nb

__all__ = ["AVAILABLE", "frame_masks_cpu"]

if AVAILABLE:

    @_nb.njit(parallel=True, cache=True, error_model="numpy")
    def _frame_masks_kernel(y, mask, static, channels, min_views, write, yc, zero, ok, changed,
                            num_chunks):  # pragma: no cover - compiled
        n, o = y.shape
        nv = o // channels
        for ch in _nb.prange(num_chunks):
            for r in range(ch * n // num_chunks, (ch + 1) * n // num_chunks):
                nd = 0  # separate short loops over the observations: they vectorise
                for k in range(o):
                    nd += np.int64(mask[r, k] != static[r, k])
                if write:
                    for k in range(o):
                        yc[r, k] = y[r, k] if mask[r, k] else zero  # NaN-safe, unlike y·mask
                views = 0
                for v in range(nv):
                    seen = 0
                    for c in range(channels):
                        seen += np.int64(mask[r, v * channels + c])
                    views += np.int64(seen > 0)
                good = views >= min_views
                ok[r] = good
                changed[r] = good and nd > 0


def frame_masks_cpu(
    y: np.ndarray, mask: np.ndarray, static: np.ndarray, channels: int, min_views: int,
    out_dtype: np.dtype | None, num_threads: int,
) -> tuple[np.ndarray | None, np.ndarray, np.ndarray]:
    """One pass over a frame's observations.

    Args:
        y: ``(P, O)`` observations (may be NaN where ``mask`` is False); mask: ``(P, O)`` bool
            frame mask; static: ``(P, O)`` bool static mask; channels: observations a view
            (``o = channels·v + c``); min_views: views with at least one usable observation a
            pixel needs; out_dtype: dtype of the masked copy, ``None``: no copy.

    Returns:
        ``yc (P, O)`` (``y`` where ``mask``, else 0; ``None`` without ``out_dtype``),
        ``ok (P,)`` bool (enough views), ``changed (P,)`` bool (``ok`` and the frame mask differs
        from the static one).
    """
    if not AVAILABLE:  # pragma: no cover
        raise RuntimeError("numba is not installed")
    n, o = y.shape
    if mask.shape != (n, o) or static.shape != (n, o) or o % channels:
        raise ValueError(f"frame_masks_cpu: y {y.shape}, mask {mask.shape}, static "
                         f"{static.shape} must share one shape (P, {channels}·V)")
    write = out_dtype is not None
    yc = np.empty((n, o) if write else (1, 1), np.dtype(out_dtype) if write else y.dtype)
    ok = np.empty(n, np.bool_)
    changed = np.empty(n, np.bool_)
    if n:
        with threads(num_threads):
            _frame_masks_kernel(np.ascontiguousarray(y), np.ascontiguousarray(mask),
                                np.ascontiguousarray(static), int(channels), int(min_views),
                                write, yc, yc.dtype.type(0), ok, changed, min(n, 256))
    return (yc if write else None), ok, changed
