"""Scene scores of the experiments and the demo, built on the public metrics.

The metrics themselves (PSNR in both conventions, SSIM, SAM, ERGAS, RMSE, MRAE) live in
:mod:`hsi_torch.metrics`, with their conventions; ``mse``, ``rmse``, ``psnr``,
``spectral_angle_deg`` and ``psnr_from_mse`` are re-exported here for the callers that import them
from this module. The scene scores (:func:`colorchecker_scores`, :func:`cube_scores`) take numpy
cubes ``(M, h, w)`` and masks ``(h, w)`` and compute in float64. The experiments' tables share
the metrics' headers (:data:`METRIC_HEADERS`, :func:`metric_columns`), cell formats
(:data:`METRIC_FORMATS`), row values with :data:`NOT_APPLICABLE` where a metric does not apply
(:func:`metric_cells`) and the paragraph stating the conventions (:func:`metrics_note`).
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np
import torch

from hsi_torch.metrics import (
    METRIC_NAMES,
    cube_metrics,
    mse,
    psnr,
    psnr_from_mse,
    rmse,
    spectral_angle_deg,
)

__all__ = [
    "mse",
    "psnr",
    "spectral_angle_deg",
    "spectral_angle_deg_np",
    "rmse",
    "psnr_from_mse",
    "erode_px",
    "interior_mask",
    "colorchecker_scores",
    "cube_scores",
    "METRIC_NAMES",
    "cube_metrics",
    "format_metrics",
    "METRIC_HEADERS",
    "METRIC_FORMATS",
    "NOT_APPLICABLE",
    "metric_columns",
    "metric_cells",
    "metrics_note",
]

#: Table headers of :func:`hsi_torch.metrics.cube_metrics`' keys, the convention in short.
METRIC_HEADERS = {
    "psnr_db": "PSNR dB (cube, peak 1)",
    "psnr_bands_db": "PSNR dB (per band, 0-255)",
    "ssim": "SSIM",
    "sam_deg": "SAM °",
    "ergas": "ERGAS",
    "rmse": "RMSE",
    "mrae": "MRAE",
}
#: Cell formats of those keys (``format`` specs).
METRIC_FORMATS = {"psnr_db": ".2f", "psnr_bands_db": ".2f", "ssim": ".4f", "sam_deg": ".2f",
                  "ergas": ".2f", "rmse": ".4f", "mrae": ".4f"}  # fmt: skip
#: The cell of a metric that does not apply to an experiment (the table's text says why).
NOT_APPLICABLE = "n/a"


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


def format_metrics(m: dict[str, float]) -> str:
    """One line of :func:`hsi_torch.metrics.cube_metrics`' values, e.g. for a console summary."""
    return (f"PSNR {m['psnr_db']:.2f} dB (per band 0-255: {m['psnr_bands_db']:.2f} dB), "
            f"SSIM {m['ssim']:.4f}, SAM {m['sam_deg']:.2f} deg, ERGAS {m['ergas']:.2f}, "
            f"RMSE {m['rmse']:.4f}, MRAE {m['mrae']:.4f}")  # fmt: skip


def metric_columns(prefix: str = "") -> dict[str, str]:
    """``{prefix + key: header}`` of the field's metrics in :data:`METRIC_NAMES` order, for
    :func:`hsi_torch.experiments.report.markdown_table` (``prefix`` when a row holds them under
    prefixed keys)."""
    return {prefix + k: METRIC_HEADERS[k] for k in METRIC_NAMES}


def metric_cells(
    m: dict[str, float], not_applicable: tuple[str, ...] = (), prefix: str = ""
) -> dict[str, Any]:
    """The metrics of ``m`` (:func:`~hsi_torch.metrics.cube_metrics`' keys) as row values keyed
    ``prefix + key``: floats (NaN where ``m`` lacks one), :data:`NOT_APPLICABLE` for the keys in
    ``not_applicable``. Format them with :data:`METRIC_FORMATS` (strings pass through)."""
    return {prefix + k: NOT_APPLICABLE if k in not_applicable else float(m.get(k, math.nan))
            for k in METRIC_NAMES}  # fmt: skip


def metrics_note(not_applicable: dict[str, str] | None = None) -> str:
    """One paragraph for a table's header: the conventions of the field's metrics
    (:mod:`hsi_torch.metrics`) and, for each key of ``not_applicable``, why it does not apply."""
    text = ("Metrics (hsi_torch.metrics, reflectance): PSNR over the whole cube with peak 1 "
            "(10·log10(1/MSE)) and PSNR per band on 0-255 (both clipped to [0, 1] × 255), "
            "averaged over bands; SSIM per band (Gaussian 11×11, σ 1.5, data range 1), "
            "mean over bands; SAM mean spectral angle in degrees; ERGAS with ratio 1; RMSE on "
            "the peak-1 scale; MRAE over samples whose truth is ≥ 1e-3.")  # fmt: skip
    for k, why in (not_applicable or {}).items():
        text += f" {METRIC_HEADERS[k].split(' ')[0]}: {NOT_APPLICABLE} ({why})."
    return text


def spectral_angle_deg_np(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """:func:`spectral_angle_deg` of numpy spectra ``(..., M)`` (computed in float64), degrees,
    as numpy ``(...)``."""
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
        sa.append(float(spectral_angle_deg_np(s, spectra[k])))
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
    ``mask``; in shadows and dark regions a spectral angle measures noise, not colour).

    ``metrics`` (on the whole mask and on the brighter half) holds the field's metrics of
    :func:`hsi_torch.metrics.cube_metrics` over the same pixels: PSNR in both conventions (whole
    cube peak 1; per band on 0–255, mean over bands), SSIM, mean SAM (all pixels), ERGAS, RMSE,
    MRAE."""

    def scores(m: np.ndarray) -> dict[str, Any]:
        e = cube[:, m].T
        t = truth[:, m].T
        if e.size == 0:
            return {"pixels": 0, "psnr_db": float("nan"), "mean_sam_deg": float("nan"),
                    "median_sam_deg": float("nan")}  # fmt: skip
        mse = float(((e - t) ** 2).mean())
        bright = t.mean(1) >= sam_min_reflectance
        sam = spectral_angle_deg_np(e[bright], t[bright]) if bright.any() else np.array([math.nan])
        return {
            "pixels": int(m.sum()),
            "psnr_db": psnr_from_mse(mse),
            "rmse": math.sqrt(mse),
            "mean_sam_deg": float(np.mean(sam)),
            "median_sam_deg": float(np.median(sam)),
            "sam_pixels": int(bright.sum()),
            "metrics": cube_metrics(torch.from_numpy(np.asarray(cube, np.float64)),
                                    torch.from_numpy(np.asarray(truth, np.float64)),
                                    torch.from_numpy(np.asarray(m, bool))),
        }

    out = scores(mask)
    level = truth.mean(0)
    if mask.any():
        half = mask & (level >= np.median(level[mask]))
        out["bright_half"] = scores(half)
    return out
