"""Spectral reconstruction metrics, shared by the experiments and the demo.

Convention:
    Spectra lie along the last axis ``(..., M)``; metrics reduce that axis (and, for
    :func:`psnr`, every axis unless ``dim`` is given). Reflectance peak is 1 by default.
    The scene scores (:func:`colorchecker_scores`, :func:`cube_scores`) take numpy cubes
    ``(M, h, w)`` and masks ``(h, w)`` and compute in float64 with the same
    :func:`spectral_angle_deg` and :func:`psnr_from_mse`.
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np
import torch

__all__ = [
    "mse",
    "psnr",
    "spectral_angle_deg",
    "rmse",
    "psnr_from_mse",
    "erode_px",
    "interior_mask",
    "colorchecker_scores",
    "cube_scores",
]


def _check(estimate: torch.Tensor, truth: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    estimate = torch.as_tensor(estimate)
    truth = torch.as_tensor(truth, device=estimate.device)
    if estimate.shape != truth.shape:
        raise ValueError(
            f"estimate shape {tuple(estimate.shape)} != truth shape {tuple(truth.shape)}"
        )
    dtype = torch.promote_types(estimate.dtype, truth.dtype)
    if not dtype.is_floating_point:
        dtype = torch.get_default_dtype()
    return estimate.to(dtype), truth.to(dtype)


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
    """Root mean squared error over ``dim``."""
    return mse(estimate, truth, dim).sqrt()


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
    """
    m = mse(estimate, truth, dim)
    return 10.0 * torch.log10(torch.as_tensor(peak, dtype=m.dtype, device=m.device) ** 2 / m)


def spectral_angle_deg(
    estimate: torch.Tensor, truth: torch.Tensor, eps: float = 1e-12
) -> torch.Tensor:
    """Spectral angle (SAM) in degrees between spectra along the last axis, shape ``(...)``."""
    e, t = _check(estimate, truth)
    cos = (e * t).sum(-1) / (e.norm(dim=-1) * t.norm(dim=-1)).clamp_min(eps)
    return torch.rad2deg(torch.arccos(cos.clamp(-1.0, 1.0)))


def psnr_from_mse(value: float) -> float:
    """PSNR (dB, peak 1) of a scalar MSE."""
    return 10.0 * math.log10(1.0 / value) if value > 0 else math.inf


def erode_px(truth: dict[str, np.ndarray], erode_mm: float) -> float:
    """``erode_mm`` on the diffuser in reference-frame pixels (from the truth's diffuser
    coordinates of the reference pixels ``(h, w, 2)``: the median pixel spacing along x)."""
    xy = np.asarray(truth["diffuser_xy"], np.float64)
    step = np.linalg.norm(np.diff(xy, axis=1), axis=-1)
    return float(erode_mm / np.median(step))


def interior_mask(mask: np.ndarray, erode_px: float) -> np.ndarray:
    """Pixels of a bool mask ``(h, w)`` at least ``erode_px`` from its outside (Euclidean; the
    frame border counts as outside); ``erode_px <= 0`` returns the mask."""
    if erode_px <= 0:
        return mask
    padded = np.pad(mask.astype(np.uint8), 1)  # the frame border counts as outside
    d = cv2.distanceTransform(padded, cv2.DIST_L2, 5)[1:-1, 1:-1]
    return d > erode_px


def _sam_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """:func:`spectral_angle_deg` of float64 numpy spectra, as numpy."""
    return spectral_angle_deg(torch.from_numpy(np.asarray(a, np.float64)),
                              torch.from_numpy(np.asarray(b, np.float64))).numpy()


def colorchecker_scores(
    cube: np.ndarray,
    valid: np.ndarray,
    patch_index: np.ndarray,
    spectra: np.ndarray,
    erode_px: float = 2.0,
) -> dict[str, Any]:
    """Per-patch scores of a reconstructed ColorChecker.

    Args:
        cube: ``(M, h, w)`` reconstruction (NaN allowed where invalid).
        valid: ``(h, w)`` bool pixels to use.
        patch_index: ``(h, w)`` patch under each pixel (−1 off-patch).
        spectra: ``(24, M)`` true patch reflectances.
        erode_px: interior margin (0: whole patches).

    Returns:
        ``{"psnr_db": [...], "sam_deg": [...], "pixels": [...], "mean_psnr_db", "mean_sam_deg",
        "patches"}``; a patch with no usable pixel gets NaN and is left out of the means.
    """
    K = spectra.shape[0]
    ps, sa, npx, est = [], [], [], []
    for k in range(K):
        m = interior_mask(patch_index == k, erode_px) & valid
        npx.append(int(m.sum()))
        if not m.any():
            ps.append(float("nan"))
            sa.append(float("nan"))
            est.append([float("nan")] * spectra.shape[1])
            continue
        s = cube[:, m].mean(1)
        est.append(s.tolist())
        ps.append(psnr_from_mse(float(((s - spectra[k]) ** 2).mean())))
        sa.append(float(_sam_deg(s, spectra[k])))
    ok = [i for i in range(K) if npx[i] > 0]
    return {
        "psnr_db": ps,
        "sam_deg": sa,
        "pixels": npx,
        "estimated_spectra": est,
        "patches": len(ok),
        "mean_psnr_db": float(np.mean([ps[i] for i in ok])) if ok else float("nan"),
        "mean_sam_deg": float(np.mean([sa[i] for i in ok])) if ok else float("nan"),
    }


def cube_scores(
    cube: np.ndarray, truth: np.ndarray, mask: np.ndarray, sam_min_reflectance: float = 0.01
) -> dict[str, Any]:
    """Per-pixel scores over ``mask``: PSNR of the pooled MSE, mean and median SAM (SAM only
    where the true mean reflectance is ≥ ``sam_min_reflectance``), and the same on the brighter
    half (``bright_half``: pixels whose true mean reflectance is at least the median over
    ``mask``; in shadows and dark regions a spectral angle measures noise, not colour)."""

    def scores(m: np.ndarray) -> dict[str, Any]:
        e = cube[:, m].T
        t = truth[:, m].T
        if e.size == 0:
            return {"pixels": 0, "psnr_db": float("nan"), "mean_sam_deg": float("nan"),
                    "median_sam_deg": float("nan")}  # fmt: skip
        mse = float(((e - t) ** 2).mean())
        bright = t.mean(1) >= sam_min_reflectance
        sam = _sam_deg(e[bright], t[bright]) if bright.any() else np.array([math.nan])
        return {
            "pixels": int(m.sum()),
            "psnr_db": psnr_from_mse(mse),
            "rmse": math.sqrt(mse),
            "mean_sam_deg": float(np.mean(sam)),
            "median_sam_deg": float(np.median(sam)),
            "sam_pixels": int(bright.sum()),
        }

    out = scores(mask)
    level = truth.mean(0)
    if mask.any():
        half = mask & (level >= np.median(level[mask]))
        out["bright_half"] = scores(half)
    return out
