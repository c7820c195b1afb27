"""``ReconstructConfig``: schema of the shipped ``reconstruct.yaml`` (``hsi-torch reconstruct``).

Loaded by :func:`hsi_torch.config.load_config`; every key can be overridden on the command line
(``--set beta=100``). ``describe_schema(ReconstructConfig)`` prints the reference. The values are
checked by :class:`hsi_torch.recon.settings.ReconstructSettings` (the grouped, frozen form a run
passes on), which every instance builds once on creation: an invalid value fails here, before a
run creates its output folder.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from hsi_torch.config import help_meta
from hsi_torch.recon.settings import (
    BETA_MAX,
    MAX_PREVIEW_SIZE,
    RENAMED_KEYS,
    ReconstructSettings,
)

__all__ = ["ReconstructConfig", "BETA_MAX"]

CubeFormatName = Literal["tiff", "envi", "npz", "netcdf", "zarr"]


_help = help_meta




@dataclass
class ReconstructConfig:
    """Settings of a reconstruction run (see the field help texts)."""

    #: keys of earlier releases, refused by the loader with what to write instead
    __renamed_keys__ = RENAMED_KEYS

    beta: float = field(
        default=1e4,  # = hsi_torch.recon.pipeline.DEFAULT_BETA (kept importable without torch)
        metadata=_help("smoothness weight on ||D s||^2, on the data's scale (DN^2); 1e-2..1e6 "
                       "(1e4: best measured on the default prototype)"),
    )
    diff_order: int = field(
        default=1, metadata=_help("order of the difference operator D: 1, 2, or 0 (Tikhonov)")
    )
    solver: Literal["active_set", "admm"] = field(
        default="active_set", metadata=_help("exact active set, or ADMM")
    )
    admm_iters: int | None = field(
        default=None, metadata=_help("ADMM: fixed iteration count (null: run to tolerance)")
    )
    prior: Literal["none", "tv"] = field(
        default="none",
        metadata=_help("none: per-pixel NNLS; tv: spatial-spectral reconstruction with a "
                       "vectorial total-variation prior, warm-started from the per-pixel answer"),
    )
    lam: float | Literal["auto", "discrepancy"] = field(
        default=1.0,  # = hsi_torch.recon.spatial.DEFAULT_LAM (kept importable without torch)
        metadata=_help("prior=tv: relative TV weight, lambda = lam * sigma * sqrt(median "
                       "trace G) with sigma the frame's noise level (DN) from its per-pixel "
                       "residuals; auto: per frame, minimum of a Monte-Carlo SURE risk "
                       "estimate; discrepancy: per frame, Morozov's discrepancy principle"),
    )
    spatial_iters: int | None = field(
        default=None,
        metadata=_help("prior=tv: fixed ADMM iterations (null: run to tolerance)"),
    )
    device: str = field(default="cpu", metadata=_help("torch device (cpu, cuda, cuda:1, ...)"))
    dtype: Literal["float32", "float64"] = field(
        default="float32", metadata=_help("precision of the sensing matrices and the solve")
    )
    precompute_cache: str = field(
        default="auto",
        metadata=_help("where the per-bundle precomputation (sensing model, masks, "
                       "factorisation) is cached between runs: auto (the user cache folder, "
                       "$HSI_TORCH_CACHE or ~/.cache/hsi_torch), beside (a .hsi_torch_cache "
                       "folder beside the bundle), off, or a folder"),
    )
    formats: list[CubeFormatName] = field(
        default_factory=lambda: ["tiff", "envi", "npz"],
        metadata=_help("cube files written per input: tiff (OME-TIFF .tif + GDAL .vrt), envi "
                       "(.hdr/.img), npz, netcdf (.nc), zarr (.zarr); netcdf/zarr need "
                       "pip install 'hsi-torch[formats]'"),
    )
    preview: bool = field(default=True, metadata=_help("write an sRGB preview PNG (D65)"))
    preview_size: int = field(
        default=512, metadata=_help("the preview's longer side is enlarged (integer factor, "
                                    "nearest neighbour) to at least this many px; 0: native; "
                                    f"at most {MAX_PREVIEW_SIZE}"))
    spectra_pixels: list[tuple[int, int]] = field(
        default_factory=list,
        metadata=_help("reference-frame pixels [row, col] whose spectra are plotted (PNG)"),
    )
    chunk_size: int | None = field(
        default=None, metadata=_help("pixels per solver chunk (null: solver default)")
    )
    nan_invalid: bool = field(
        default=True, metadata=_help("invalid pixels are NaN (else 0) in the cube")
    )
    demosaic: Literal["bilinear", "half"] = field(
        default="bilinear",
        metadata=_help("Bayer inputs: bilinear (full resolution) or half (2x2 binning; needs a "
                       "bundle made at half resolution)"),
    )
    exposure_correction: bool = field(
        default=True,
        metadata=_help("scale observations by t_white / t_capture when both exposures are known"),
    )
    min_views: int = field(default=3, metadata=_help("views a pixel needs to be valid"))
    cfa_pattern: Literal["RGGB", "BGGR", "GRBG", "GBRG"] | None = field(
        default=None,
        metadata=_help("Bayer inputs: CFA pattern (null: the file's metadata, else the pattern "
                       "the bundle was calibrated with)"),
    )
    black_level: float | list[float] | None = field(
        default=None,
        metadata=_help("black level subtracted from the stored values, DN: scalar, 4 values "
                       "(Bayer cell) or 3 (R, G, B) (null: the file's metadata, else the "
                       "calibration's, recorded in the bundle, else 0)"),
    )
    exposure_s: float | None = field(
        default=None,
        metadata=_help("exposure time of the captures, s, for a file whose metadata has none "
                       "(RAW/DNG/TIFF EXIF, exposure_s); scaled by t_white / t_capture against "
                       "the bundle's white reference (null: unknown, the cube's scale is "
                       "relative)"),
    )
    white_level: float | None = field(
        default=None,
        metadata=_help("saturation level, DN, > 0 (null: the file's metadata, else the "
                       "integer type's maximum)"),
    )
    uncertainty: bool = field(
        default=False,
        metadata=_help("also write the standard deviation of every band from the sensor noise: "
                       "<stem>_std.* beside the cube in the non-NPZ formats, the key 'std' in "
                       "<stem>.npz and a map <stem>_std.png (see docs/reconstruct.md)"),
    )
    noise_electrons_per_dn: float | None = field(
        default=None,
        metadata=_help("uncertainty: sensor conversion gain, e-/DN (null: the simulator's default "
                       "sensor, 30000 e- / (16383 - 512) DN = 1.89)"),
    )
    noise_read_e: float = field(
        default=3.0, metadata=_help("uncertainty: sensor read noise sigma, electrons")
    )

    fit_residual_warning: float | None = field(
        default=0.15,
        metadata=_help("warn when a frame's relative fit residual (pooled over its brighter half, "
                       "see recon.pipeline.fit_residual) exceeds this: a bundle of another "
                       "geometry gives 0.21-0.25, the right bundle 0.01-0.03 (0.11 with 1/20 of "
                       "the exposure); null: never"),
    )

    drift_check: bool = field(
        default=True,
        metadata=_help("measure each frame's drift against the bundle's registration (views "
                       "aligned to the reference view; a sensor shift and rotation fitted) and "
                       "store it in the cube's metadata (stats.drift)"),
    )
    drift_warn_px: float | None = field(
        default=0.5,
        metadata=_help("warn when the measured sensor motion moves a view's pixel by more than "
                       "this many px (null: never)"),
    )
    refine_registration: bool = field(
        default=False,
        metadata=_help("correct the measured sensor motion before solving (every view sampled "
                       "where the moved sensor put it; see docs/reconstruct.md)"),
    )
    drift_min_views: int = field(
        default=4,
        metadata=_help("the fewest views that must agree on the measured drift (within 1 px "
                       "of the fitted motion) for it to be trusted; fewer, or a drift beyond "
                       "the measurable range: refine_registration fails the frame, the check "
                       "warns that the drift could not be measured"),
    )

    def __post_init__(self) -> None:
        self.settings()  # every value checked where the settings are built (errors name the key)

    def settings(self) -> ReconstructSettings:
        """These settings, grouped and frozen
        (:class:`~hsi_torch.recon.settings.ReconstructSettings`; built once per run and passed
        whole to the reconstructor and the workers).

        Raises:
            ConfigError: an invalid value (naming its key).
        """
        return ReconstructSettings.from_config(self)
