"""``CalibrateConfig``: the schema of the shipped ``calibrate.yaml`` (``hsi-torch calibrate``).

Loaded and validated by :func:`hsi_torch.config.load_config`; every key can be overridden on the
command line (``--set response.beta_phi=1e2``). ``describe_schema(CalibrateConfig)`` prints the
reference. Wavelengths in nm, lengths on the sensor in px.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from hsi_torch.calibrate.registration import BlobDetectorParams
from hsi_torch.calibrate.response import DEFAULT_BETA_PHI, DEFAULT_GAMMA_H
from hsi_torch.config import help_meta, option, to_dict

__all__ = [
    "BlobSection",
    "RegistrationSection",
    "TransmittanceSection",
    "ResponseSection",
    "CalibrateConfig",
]


_h = help_meta
_BLOBS = BlobDetectorParams()


@dataclass
class BlobSection:
    """``cv2.SimpleBlobDetector`` limits (areas in px² of the parity-corrected view crop)."""

    min_area: float = option(
        _BLOBS.min_area,
        "smallest blob area, px^2 (small prototype's circles: r ~ 2.8 px, ~25 px^2)",
    )
    max_area: float = option(_BLOBS.max_area, "largest blob area, px^2")
    min_circularity: float = option(_BLOBS.min_circularity, "0 disables the filter")
    min_convexity: float = option(_BLOBS.min_convexity, "0 disables the filter")
    min_inertia_ratio: float = option(_BLOBS.min_inertia_ratio, "0 disables the filter")
    min_threshold: float = option(_BLOBS.min_threshold, "first binarisation threshold")
    max_threshold: float = option(_BLOBS.max_threshold, "last binarisation threshold")
    threshold_step: float = option(_BLOBS.threshold_step, "threshold step")
    min_dist_between_blobs: float = option(_BLOBS.min_dist_between_blobs, "px")
    min_repeatability: int = option(_BLOBS.min_repeatability, "thresholds a blob must survive")
    blob_color: int = option(_BLOBS.blob_color, "0: dark circles, 255: light circles")


@dataclass
class RegistrationSection:
    """Circle-grid detection and homography fit (:func:`hsi_torch.calibrate.register_views`)."""

    pattern_size: tuple[int, int] = option(
        (4, 5), "asymmetric grid (points per row, rows), OpenCV order"
    )
    blob: BlobSection = field(default_factory=BlobSection)
    equalize: Literal["none", "clahe", "auto"] = option(
        "auto", "auto: plain image, then CLAHE-equalised"
    )
    margin_px: int = option(6, "margin around each triangle's crop, px")
    fill_outside: bool = option(True, "paint pixels outside the triangle with the background")
    ransac_threshold_px: float = option(1.0, "RANSAC inlier threshold, px")
    min_inlier_fraction: float = option(
        0.8,
        "a view whose grid fit keeps fewer RANSAC inliers is refused (a flipped parity "
        "in the nominal layout keeps about a third)",
    )
    flat_field: bool = option(
        True,
        "divide the grid shots by the mean white shot before detection (removes the "
        "views' transmittance fringes and vignetting from the target)",
    )
    inset_px: float = option(1.0, "view masks: source point at least this far inside the triangle")

    def __post_init__(self) -> None:
        if len(self.pattern_size) != 2 or min(self.pattern_size) < 2:
            raise ValueError(f"pattern_size must be (cols, rows) >= 2, got {self.pattern_size}")
        if not self.ransac_threshold_px > 0:
            raise ValueError(f"ransac_threshold_px must be > 0, got {self.ransac_threshold_px}")
        if not 0 <= self.min_inlier_fraction <= 1:
            raise ValueError(
                f"min_inlier_fraction must lie in [0, 1], got {self.min_inlier_fraction}"
            )


@dataclass
class TransmittanceSection:
    """BRF transmittance from the monochromator scan (:func:`brf_transmittance`)."""

    lit_threshold: float = option(
        0.05, "a pixel is lit when max_j B >= this (between triangles: dark)"
    )
    weight_power: float = option(1.0, "colour weights ∝ BRF-free patch mean ** power (1: ∝ signal)")
    wavelength_tol_nm: float = option(
        0.5, "largest |scan wavelength - grid wavelength| accepted, nm"
    )
    brf_free_erode_px: float = option(
        1.5, "without brf_free_mask.png: keep polygon pixels this far inside the disk"
    )
    brf_free_margin_px: float = option(
        1.5, "reference-frame pixels within the disk + this margin are not modulated"
    )
    max_patch_ratio: float = option(
        0.8,
        "refuse a 'BRF-free' patch when the reference view elsewhere reaches this "
        "fraction of its brightness (median over the view): the patch is filtered",
    )
    frames_per_chunk: int = option(4, "scan frames processed together (memory bound at full scale)")

    def __post_init__(self) -> None:
        if self.frames_per_chunk < 1:
            raise ValueError(f"frames_per_chunk must be >= 1, got {self.frames_per_chunk}")
        if not self.wavelength_tol_nm > 0:
            raise ValueError(f"wavelength_tol_nm must be > 0, got {self.wavelength_tol_nm}")


@dataclass
class ResponseSection:
    """φ^c(λ) and the gain field g_v(p) from the white shots (:func:`estimate_response_field`)."""

    beta_phi: float = option(
        DEFAULT_BETA_PHI,
        "smoothness weight on ||D phi||^2, relative to the data scale "
        "s = sum w ||b||^2 / M when normalise (the original prototype's absolute 8e5 "
        "is 0.6 on the small simulated set, 0.011 at full size)",
    )
    gamma_h: float = option(
        DEFAULT_GAMMA_H, "weight of the shape prior ||phi - alpha f~||^2 (relative as beta_phi)"
    )
    normalise: bool = option(
        True,
        "beta_phi, gamma_h relative to the data scale (one setting for every sensor "
        "size); false: absolute weights, as the original prototype",
    )
    n_iter: int = option(3, "alternations (original prototype: 3)")
    refine_steps: int = option(20, "joint Levenberg-Marquardt steps after the alternations")
    degree: int = option(2, "total degree of the Legendre gain field")
    smoothness: float = option(1e-3, "relative ridge on the non-constant gain coefficients")
    diff_order: int = option(1, "order of D in the phi smoothness term")
    camera_sensitivity: str = option(
        "Canon EOS 5D Mark II",
        "shape prior f~: a camera name (hsi_torch.refdata.list_cameras), CSV or "
        "JSON file, or 'flat'",
    )
    saturation_margin: float = option(
        1e-3, "white sample counts as saturated above this warped weight"
    )
    max_pixels: int | None = option(
        100_000,
        "estimate phi and the gain field on a regular sub-grid of at most this many "
        "reference-frame pixels (null: all; the small prototype has ~12 500)",
    )
    max_saturated_fraction: float = option(
        0.05,
        "a white shot with more of its registered view pixels saturated is dropped "
        "(with a warning) while another shot is below; all above: an error",
    )

    def __post_init__(self) -> None:
        if self.beta_phi < 0 or self.gamma_h < 0:
            raise ValueError(f"beta_phi, gamma_h must be >= 0, got {self.beta_phi}, {self.gamma_h}")
        if self.degree < 0 or self.n_iter < 0 or self.refine_steps < 0:
            raise ValueError("degree, n_iter and refine_steps must be >= 0")
        if self.diff_order not in (1, 2):
            raise ValueError(f"diff_order must be 1 or 2, got {self.diff_order}")
        if self.max_pixels is not None and self.max_pixels < 1:
            raise ValueError(f"max_pixels must be >= 1 or null, got {self.max_pixels}")
        if not 0 <= self.max_saturated_fraction <= 1:
            raise ValueError(
                f"max_saturated_fraction must be in [0, 1], got {self.max_saturated_fraction}"
            )


@dataclass
class CalibrateConfig:
    """Settings of ``hsi-torch calibrate`` (see the field help texts)."""

    layout: Path | None = option(None, "nominal layout JSON (triangles, parity, reference_bbox, "
                                       "BRF-free patch); null: CAPTURES/nominal_layout.json")
    brf_free_mask: Path | None = option(None, "PNG of usable BRF-free pixels (255 = use); null: "
                                              "the layout's usable_mask / "
                                              "CAPTURES/brf_free_mask.png, else the layout's "
                                              "polygon eroded")
    grid_start_nm: float = option(430.0, "first band centre, nm")
    grid_stop_nm: float = option(670.0, "last band centre, nm")
    grid_step_nm: float = option(10.0, "band step, nm")
    demosaic: Literal["bilinear"] = option("bilinear", "Bayer captures: bilinear demosaic at "
                                                       "full resolution (read_any default)")
    cfa_pattern: str | None = option(None, "override the files' CFA pattern (e.g. RGGB)")
    black_level: float | None = option(None, "override the files' black level (DN)")
    white_level: float | None = option(None, "override the files' white (saturation) level (DN)")
    dark: Literal["per_pixel", "mean", "none"] = option(
        "per_pixel", "dark frames: subtract their per-pixel mean, their per-channel mean, or "
                     "nothing (the black level is always subtracted)")
    pedestal_check: Literal["error", "warn", "off"] = option(
        "error", "the sensor outside every view must read ~0 after black (and dark) subtraction: "
                 "error refuses captures that carry a black pedestal (a missing black level), "
                 "warn only says so")
    stray_light: Literal["auto", "none", "subtract"] = option(
        "auto", "the veil of stray light, measured on the white where no light reaches (judged "
                "on the white): auto subtracts it from every lit frame when it is above "
                "stray_light_threshold, subtract always, none never; the bundle records it, so "
                "reconstruction subtracts it from the captures too")
    stray_light_threshold: float = option(0.002, "stray_light: auto subtracts a veil above this "
                                                 "fraction of the white's mean (largest colour; "
                                                 "the ideal device reads ~0, the documented 2 % "
                                                 "veil ~0.02)")
    defects: Literal["auto", "none", "mask"] = option(
        "auto", "hot (dark frames) and dead (white frames) pixels: auto masks them when at least "
                "defect_min_pixels are found, mask always writes what is found, none never; "
                "reconstruction drops the observations that sample a masked pixel")
    defect_min_pixels: int = option(1, "defects: auto masks when at least this many raw pixels "
                                       "are found")
    defect_hot_sigma: float = option(10.0, "hot: dark above its median by this many robust sigmas")
    defect_dead_ratio: float = option(0.5, "dead: white below this fraction of its 3x3 median")
    device: str = option("cpu", "torch device")
    dtype: Literal["float32", "float64"] = option(
        "float32", "precision of the images and maps (float32 halves the memory at full size; "
                   "the response estimation always runs in float64)")
    min_views: int = option(3, "modulated views a valid pixel needs")
    registration: RegistrationSection = field(default_factory=RegistrationSection)
    transmittance: TransmittanceSection = field(default_factory=TransmittanceSection)
    response: ResponseSection = field(default_factory=ResponseSection)
    progress: bool = option(True, "progress bar on stderr")

    def __post_init__(self) -> None:
        if not (self.grid_step_nm > 0 and self.grid_stop_nm >= self.grid_start_nm):
            raise ValueError(
                f"grid must have step > 0 and stop >= start, got {self.grid_start_nm}, "
                f"{self.grid_stop_nm}, {self.grid_step_nm}"
            )
        if self.min_views < 1:
            raise ValueError(f"min_views must be >= 1, got {self.min_views}")
        if not self.defect_hot_sigma > 0:
            raise ValueError(f"defect_hot_sigma must be > 0, got {self.defect_hot_sigma}")
        if not 0 <= self.stray_light_threshold < 1:
            raise ValueError(
                f"stray_light_threshold must be in [0, 1), got {self.stray_light_threshold}"
            )
        if not (isinstance(self.defect_min_pixels, int) and self.defect_min_pixels >= 1):
            raise ValueError(
                f"defect_min_pixels must be an integer >= 1, got {self.defect_min_pixels!r}"
            )
        if not 0 < self.defect_dead_ratio < 1:
            raise ValueError(f"defect_dead_ratio must be in (0, 1), got {self.defect_dead_ratio}")

    def detector_dict(self) -> dict[str, Any]:
        """The registration settings as :meth:`GridDetectorConfig.from_dict` expects."""
        d = to_dict(self.registration)
        d.pop("inset_px")
        d.pop("flat_field")
        d.pop("min_inlier_fraction")
        return d
