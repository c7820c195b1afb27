"""The field's spectral-reconstruction metrics, with the convention of each written beside it.

Cubes are ``(M, h, w)`` or ``(N, M, h, w)`` tensors (bands before space), spectra lie along the
band axis, values are reflectance on a peak-1 scale. ``mask`` (``(h, w)`` or ``(N, h, w)`` bool)
selects the pixels that count; NaN in the estimate outside the mask is allowed (our cubes are NaN
where not valid). Everything is computed in the inputs' floating dtype (float64 recommended for
reported numbers) on the inputs' device.

Conventions (papers differ; these are the common ones, named so that numbers can be set beside
published tables):

=================  ==============================================================================
``psnr``           **whole cube, peak 1**: ``10·log10(1 / MSE)``, the MSE pooled over every band
                   of every selected pixel. No clipping.
``psnr_bands``     **per band on 0–255, averaged over bands**: both cubes clipped to ``[0, 1]``,
                   multiplied by 255 (optionally rounded to integers, ``quantize=True``), then
                   ``10·log10(255² / MSE_b)`` for each band ``b`` over the selected pixels, and the
                   mean of these dB values over the bands. A mean of logarithms, so it differs
                   from the whole-cube PSNR when the error is not spread evenly over the bands.
``ssim``           Wang et al. 2004 on each band as a grey image, data range 1 (= 255 on the
                   0–255 scale: SSIM is scale-free when the range scales with the data), Gaussian
                   window 11 × 11, σ = 1.5, K1 = 0.01, K2 = 0.03, population (biased) moments;
                   the SSIM map is averaged over the window positions that lie wholly inside the
                   image and the mask (the "valid" region: skimage's, kornia's ``padding="valid"``
                   and torchmetrics' convention of cropping the border), then over the bands.
``sam``            spectral angle ``arccos(⟨e, t⟩ / (‖e‖·‖t‖))`` of every selected pixel, in
                   **degrees**, averaged over pixels (some papers report radians: × π/180).
``ergas``          ``(100 / ratio) · sqrt(mean_b (RMSE_b / μ_b)²)``, ``RMSE_b`` the band's RMSE
                   and ``μ_b`` the band's mean of the truth over the selected pixels; ``ratio`` is
                   the resolution factor between the high- and the low-resolution image (4 for 4×
                   super-resolution or fusion; 1, the default, for reconstruction at the truth's
                   resolution), as in torchmetrics.
``rmse``           ``sqrt(MSE)`` pooled over every band of every selected pixel, on the peak-1
                   scale (× 255 for tables on the 0–255 scale).
``mrae``           mean relative absolute error ``mean |e − t| / t`` over the elements whose truth
                   is ≥ ``min_truth`` (default 1e-3; relative errors of black samples are noise).
=================  ==============================================================================

``cube_metrics`` returns all of them in one dict (the keys the demos and experiments report).

The tensor-valued metrics are differentiable (losses for training). Where the estimate equals the
truth, ``sqrt`` and ``log`` of a zero MSE and ``arccos`` of a cosine of 1 have infinite
derivatives; there the gradient is 0 (the minimum of RMSE, ERGAS and the angle; PSNR is +inf)
instead of ``inf·0 = NaN``, and the values are unchanged, bit for bit.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = [
    "mse",
    "rmse",
    "psnr",
    "psnr_from_mse",
    "psnr_bands",
    "ssim",
    "spectral_angle_deg",
    "sam",
    "ergas",
    "mrae",
    "cube_metrics",
    "METRIC_NAMES",
]

#: The keys of :func:`cube_metrics`, in the order tables print them.
METRIC_NAMES = ("psnr_db", "psnr_bands_db", "ssim", "sam_deg", "ergas", "rmse", "mrae")


def _check(estimate: torch.Tensor, truth: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    estimate = torch.as_tensor(estimate)
    truth = torch.as_tensor(truth, device=estimate.device)
    if estimate.shape != truth.shape:
        raise ValueError(
            f"estimate shape {tuple(estimate.shape)} != truth shape {tuple(truth.shape)}")
    dtype = torch.promote_types(estimate.dtype, truth.dtype)
    if not dtype.is_floating_point:
        dtype = torch.get_default_dtype()
    return estimate.to(dtype), truth.to(dtype)


def _finite_grad(f: Callable[[Tensor], Tensor], x: Tensor, at: Tensor, fill: float) -> Tensor:
    """Elementwise ``f(x)`` with the gradient 0 where ``at`` (bool, ``x``'s shape), the points
    where ``f``'s derivative is infinite (``sqrt``, ``log`` at 0; ``arccos`` at ±1), instead of
    ``inf·0 = NaN``. The values are ``f(x)``'s, bit for bit: ``f`` of the detached ``x`` where
    ``at``, elsewhere ``f`` of ``x`` with ``fill`` (a point of finite derivative) in the ``at``
    places. Without autograd it is ``f(x)``."""
    if not (torch.is_grad_enabled() and x.requires_grad):
        return f(x)
    safe = torch.where(at, torch.full((), fill, dtype=x.dtype, device=x.device), x)
    return torch.where(at, f(x.detach()), f(safe))


def _sqrt(x: Tensor) -> Tensor:
    """``sqrt(x)`` with the gradient 0 at ``x = 0`` (:func:`_finite_grad`)."""
    return _finite_grad(torch.sqrt, x, x == 0, 1.0)


def mse(
    estimate: torch.Tensor, truth: torch.Tensor, dim: int | tuple[int, ...] | None = None
) -> torch.Tensor:
    """Mean squared error over ``dim`` (all elements when None)."""
    e, t = _check(estimate, truth)
    d = (e - t).square()
    return d.mean() if dim is None else d.mean(dim=dim)


def rmse(
    estimate: torch.Tensor, truth: torch.Tensor, dim: int | tuple[int, ...] | None = None
) -> torch.Tensor:
    """Root mean squared error over ``dim`` (all elements when None), in the data's units; the
    gradient is 0 where the estimate equals the truth (``sqrt`` of a zero MSE)."""
    return _sqrt(mse(estimate, truth, dim))


def psnr(
    estimate: torch.Tensor,
    truth: torch.Tensor,
    *,
    peak: float = 1.0,
    dim: int | tuple[int, ...] | None = None,
) -> torch.Tensor:
    """PSNR in dB, ``10·log10(peak² / MSE)``; with ``peak = 1`` this is ``10·log10(1/MSE)``.

    Args:
        estimate, truth: same shape.
        peak: signal peak (1 for reflectance).
        dim: axes the MSE averages over (None = all), e.g. ``-1`` for a PSNR per spectrum.

    Returns:
        dB, ``+inf`` where the MSE is 0 (there the gradient is 0, not NaN).
    """
    m = mse(estimate, truth, dim)
    p2 = torch.as_tensor(peak, dtype=m.dtype, device=m.device) ** 2
    return _finite_grad(lambda v: 10.0 * torch.log10(p2 / v), m, m == 0, 1.0)


def psnr_from_mse(value: float) -> float:
    """PSNR (dB, peak 1) of a scalar MSE; ``inf`` for 0."""
    return 10.0 * math.log10(1.0 / value) if value > 0 else math.inf


def spectral_angle_deg(
    estimate: torch.Tensor, truth: torch.Tensor, eps: float = 1e-12
) -> torch.Tensor:
    """Spectral angle (SAM) in degrees between spectra along the **last** axis, shape ``(...)``.

    Where the cosine is ±1 (parallel spectra, e.g. the estimate equal to the truth) the gradient
    is 0, not NaN (``arccos``' derivative is infinite there)."""
    e, t = _check(estimate, truth)
    cos = ((e * t).sum(-1) / (e.norm(dim=-1) * t.norm(dim=-1)).clamp_min(eps)).clamp(-1.0, 1.0)
    return torch.rad2deg(_finite_grad(torch.arccos, cos, cos.abs() == 1, 0.0))


# ------------------------------------------------------------------------------------ cubes --


def _cubes(
    estimate: torch.Tensor, truth: torch.Tensor, mask: torch.Tensor | None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(N, M, h, w)`` estimate and truth and an ``(N, h, w)`` bool mask (all True when None;
    pixels with a non-finite value in either cube are dropped from it), cropped to the box
    around the given mask."""
    e, t = _check(estimate, truth)
    if e.ndim not in (3, 4):
        raise ValueError(f"cubes must be (M, h, w) or (N, M, h, w), got {tuple(e.shape)}")
    if e.ndim == 3:
        e, t = e[None], t[None]
    n, _, h, w = e.shape
    if mask is None:
        m = torch.ones(n, h, w, dtype=torch.bool, device=e.device)
    else:
        m = torch.as_tensor(mask, device=e.device).to(torch.bool)
        if m.ndim == 2 and tuple(m.shape) == (h, w):
            m = m[None].expand(n, h, w)
        if tuple(m.shape) != (n, h, w):
            raise ValueError(f"mask shape {tuple(m.shape)} does not match cubes "
                             f"{tuple(estimate.shape)} (expected (h, w) or (N, h, w))")  # fmt: skip
        # only the box around the mask counts: every metric below reads the same pixels (in the
        # same order) and SSIM the same windows from it
        rows = torch.nonzero(m.any(2).any(0))[:, 0]
        cols = torch.nonzero(m.any(1).any(0))[:, 0]
        if rows.numel():
            y0, y1, x0, x1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
            if (y1 - y0, x1 - x0) != (h, w):
                e, t, m = e[..., y0:y1, x0:x1], t[..., y0:y1, x0:x1], m[..., y0:y1, x0:x1]
    finite = torch.isfinite(e).all(1) & torch.isfinite(t).all(1)
    m = m & finite
    if not bool(m.any()):
        raise ValueError("no pixel to score: the mask selects no pixel with finite values")
    return e, t, m


def _pixels(cube: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Selected spectra ``(P, M)`` of an ``(N, M, h, w)`` cube and ``(N, h, w)`` mask."""
    return cube.permute(0, 2, 3, 1)[mask]


def psnr_bands(
    estimate: torch.Tensor,
    truth: torch.Tensor,
    mask: torch.Tensor | None = None,
    *,
    quantize: bool = False,
) -> torch.Tensor:
    """PSNR per band on the 0–255 scale, averaged over bands (dB, scalar).

    Both cubes are clipped to ``[0, 1]`` and multiplied by 255 (rounded to integers when
    ``quantize``); each band's PSNR is ``10·log10(255² / MSE_b)`` over the selected pixels; the
    result is the mean over the bands of those dB values.
    """
    e, t, m = _cubes(estimate, truth, mask)
    return _psnr_bands(_pixels(e, m), _pixels(t, m), quantize)


def _psnr_bands(pe: Tensor, pt: Tensor, quantize: bool = False) -> Tensor:
    """:func:`psnr_bands` of selected spectra ``(P, M)``."""
    e = pe.clamp(0, 1) * 255
    t = pt.clamp(0, 1) * 255
    if quantize:
        e, t = e.round(), t.round()
    per_band = (e - t).square().mean(0)  # (M,)
    db = _finite_grad(lambda v: 10.0 * torch.log10(255.0**2 / v), per_band, per_band == 0, 1.0)
    return db.mean()


def _gaussian_window(size: int, sigma: float, dtype: torch.dtype, device: torch.device):
    x = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def _filter_valid(z: Tensor, kernel: Tensor) -> Tensor:
    """``z (k, 1, h, w)`` correlated with the separable ``kernel ⊗ kernel`` (``(n,)``), 'valid'
    part ``(k, 1, h − n + 1, w − n + 1)``: along the rows, then the columns. On the CPU in
    float32/64 and without a gradient to keep, through OpenCV's ``sepFilter2D`` (the two
    ``conv2d`` to rounding, many times faster in float64), else ``conv2d`` (differentiable)."""
    n = kernel.shape[0]
    differentiable = torch.is_grad_enabled() and (z.requires_grad or kernel.requires_grad)
    if (z.device.type == "cpu" and z.dtype in (torch.float32, torch.float64)
            and not differentiable):
        import cv2  # lazy: only when an SSIM is computed on the CPU

        r = n // 2
        k_np = kernel.detach().numpy()
        a = z.detach().contiguous().numpy()
        _, _, h, w = a.shape
        out = torch.empty((a.shape[0], 1, h - n + 1, w - n + 1), dtype=z.dtype)
        o = out.numpy()
        for i in range(a.shape[0]):
            o[i, 0] = cv2.sepFilter2D(a[i, 0], -1, k_np, k_np, anchor=(r, r),
                                      borderType=cv2.BORDER_REFLECT)[r:h - n + 1 + r,
                                                                     r:w - n + 1 + r]
        return out
    return F.conv2d(F.conv2d(z, kernel.view(1, 1, 1, n)), kernel.view(1, 1, n, 1))


def ssim(
    estimate: torch.Tensor,
    truth: torch.Tensor,
    mask: torch.Tensor | None = None,
    *,
    data_range: float = 1.0,
    window: int = 11,
    sigma: float = 1.5,
    k1: float = 0.01,
    k2: float = 0.03,
    per_band: bool = False,
) -> torch.Tensor:
    """Structural similarity of each band as a grey image, averaged over bands (scalar).

    Gaussian window ``window × window`` (σ = ``sigma``), ``C1 = (k1·L)²``, ``C2 = (k2·L)²`` with
    ``L = data_range``, population moments; the SSIM map is averaged over the window positions
    wholly inside the image and the mask, then over the bands (and images).

    Args:
        estimate, truth: ``(M, h, w)`` or ``(N, M, h, w)``, ``h, w ≥ window``.
        mask: ``(h, w)`` / ``(N, h, w)`` bool, pixels that count (None = all finite ones).
        per_band: return the ``(M,)`` SSIM of each band (mean over images) instead.
    """
    h, w = torch.as_tensor(estimate).shape[-2:]
    if h < window or w < window:
        raise ValueError(f"ssim: cube {h}x{w} px is smaller than the {window}x{window} window")
    e, t, m = _cubes(estimate, truth, mask)
    return _ssim(e, t, m, data_range=data_range, window=window, sigma=sigma, k1=k1, k2=k2,
                 per_band=per_band)


def _ssim(e: Tensor, t: Tensor, m: Tensor, *, data_range: float, window: int, sigma: float,
          k1: float, k2: float, per_band: bool) -> Tensor:
    """:func:`ssim` of :func:`_cubes`' output."""
    n, M, h, w = e.shape
    if h < window or w < window:  # the box around the mask is smaller than a window
        raise ValueError(f"ssim: no {window}x{window} window lies wholly inside the mask")
    g = _gaussian_window(window, sigma, e.dtype, e.device)

    def blur(z: Tensor) -> Tensor:  # separable 'valid' Gaussian: no (k², h, w) unfolding
        return _filter_valid(z, g)

    # window positions wholly inside the mask: a box filter of the mask equals the window area
    keep = m[:, None].to(e.dtype)
    box = _filter_valid(keep, torch.ones(window, dtype=e.dtype, device=e.device))
    inside = (box[:, 0] > window * window - 0.5).to(e.dtype)  # (n, h', w')
    if not bool(inside.any()):
        raise ValueError(f"ssim: no {window}x{window} window lies wholly inside the mask")
    # only the rows and columns of the image that those windows cover are filtered
    rows = torch.nonzero(inside.any(2).any(0))[:, 0]
    cols = torch.nonzero(inside.any(1).any(0))[:, 0]
    y0, y1, x0, x1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
    inside = inside[:, y0:y1, x0:x1]
    e, t, m = (z[..., y0:y1 + window - 1, x0:x1 + window - 1] for z in (e, t, m))
    h, w = e.shape[-2:]
    c1, c2 = (k1 * data_range) ** 2, (k2 * data_range) ** 2
    zero = torch.zeros((), dtype=e.dtype, device=e.device)
    sums = torch.zeros(M, dtype=e.dtype, device=e.device)
    chunk = max(1, int(2**22 // (h * w)))  # bands per step: bounded memory on large frames
    for i in range(n):
        for b0 in range(0, M, chunk):
            x = torch.where(m[i], e[i, b0:b0 + chunk], zero)[:, None]  # (k, 1, h, w)
            y = torch.where(m[i], t[i, b0:b0 + chunk], zero)[:, None]
            mu_x, mu_y = blur(x), blur(y)
            sxx = blur(x * x) - mu_x**2
            syy = blur(y * y) - mu_y**2
            sxy = blur(x * y) - mu_x * mu_y
            smap = ((2 * mu_x * mu_y + c1) * (2 * sxy + c2)) / (
                (mu_x**2 + mu_y**2 + c1) * (sxx + syy + c2))
            sums[b0:b0 + chunk] += (smap[:, 0] * inside[i]).sum((1, 2))
    band = sums / inside.sum()  # (M,): mean over the windows of every image
    return band if per_band else band.mean()


def sam(
    estimate: torch.Tensor, truth: torch.Tensor, mask: torch.Tensor | None = None
) -> torch.Tensor:
    """Mean spectral angle in degrees over the selected pixels (scalar)."""
    e, t, m = _cubes(estimate, truth, mask)
    return spectral_angle_deg(_pixels(e, m), _pixels(t, m)).mean()


def ergas(
    estimate: torch.Tensor,
    truth: torch.Tensor,
    mask: torch.Tensor | None = None,
    *,
    ratio: float = 1.0,
) -> torch.Tensor:
    """ERGAS ``(100 / ratio) · sqrt(mean_b (RMSE_b / μ_b)²)`` over the selected pixels (scalar).

    ``ratio`` is the resolution factor between the high- and the low-resolution image (1 when
    the estimate is at the truth's resolution)."""
    e, t, m = _cubes(estimate, truth, mask)
    return _ergas(_pixels(e, m), _pixels(t, m), ratio)


def _ergas(pe: Tensor, pt: Tensor, ratio: float) -> Tensor:
    """:func:`ergas` of selected spectra ``(P, M)``."""
    rmse_b = _sqrt((pe - pt).square().mean(0))
    mu_b = pt.mean(0)
    if bool((mu_b == 0).any()):
        raise ValueError("ergas: a band of the truth has mean 0 over the selected pixels")
    return (100.0 / ratio) * _sqrt((rmse_b / mu_b).square().mean())


def mrae(
    estimate: torch.Tensor,
    truth: torch.Tensor,
    mask: torch.Tensor | None = None,
    *,
    min_truth: float = 1e-3,
) -> torch.Tensor:
    """Mean relative absolute error ``mean |e − t| / t`` over the selected pixels' elements whose
    truth is ≥ ``min_truth`` (scalar)."""
    e, t, m = _cubes(estimate, truth, mask)
    return _mrae(_pixels(e, m), _pixels(t, m), min_truth)


def _mrae(pe: Tensor, pt: Tensor, min_truth: float) -> Tensor:
    """:func:`mrae` of selected spectra ``(P, M)``."""
    ok = pt >= min_truth
    if not bool(ok.any()):
        raise ValueError(f"mrae: no element of the truth is >= min_truth = {min_truth}")
    return ((pe - pt).abs()[ok] / pt[ok]).mean()


def cube_metrics(
    estimate: torch.Tensor,
    truth: torch.Tensor,
    mask: torch.Tensor | None = None,
    *,
    ergas_ratio: float = 1.0,
    mrae_min_truth: float = 1e-3,
) -> dict[str, float]:
    """All the field's metrics of a cube against its truth, as floats keyed by
    :data:`METRIC_NAMES`: ``psnr_db`` (whole cube, peak 1), ``psnr_bands_db`` (per band on 0–255,
    mean over bands), ``ssim``, ``sam_deg`` (mean), ``ergas``, ``rmse`` (peak-1 scale), ``mrae``.

    SSIM is NaN when no 11 × 11 window lies inside the mask (e.g. a scattered set of pixels).
    Accepts numpy arrays too.
    """
    e, t, m = _cubes(torch.as_tensor(estimate), torch.as_tensor(truth),
                     None if mask is None else torch.as_tensor(mask))  # fmt: skip
    pe, pt = _pixels(e, m), _pixels(t, m)  # validated, cropped and gathered once for all
    mse_v = float((pe - pt).square().mean())
    return {
        "psnr_db": psnr_from_mse(mse_v),
        "psnr_bands_db": float(_psnr_bands(pe, pt)),
        "ssim": _or_nan(lambda: _ssim(e, t, m, data_range=1.0, window=11, sigma=1.5, k1=0.01,
                                      k2=0.03, per_band=False)),
        "sam_deg": float(spectral_angle_deg(pe, pt).mean()),
        "ergas": _or_nan(lambda: _ergas(pe, pt, ergas_ratio)),
        "rmse": math.sqrt(mse_v),
        "mrae": _or_nan(lambda: _mrae(pe, pt, mrae_min_truth)),
    }


def _or_nan(value: Callable[[], Tensor]) -> float:
    """``float(value())``, or NaN where the metric does not apply (it raises ``ValueError``)."""
    try:
        return float(value())
    except ValueError:
        return math.nan
