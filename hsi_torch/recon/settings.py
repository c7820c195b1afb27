"""The reconstruction's settings as one frozen, nested object, validated where it is built.

:class:`ReconstructSettings` groups what shapes a reconstruction: ``solve`` (β, the difference
order, the solver, chunking, ``min_views``, NaN for invalid pixels, device, precision), ``prior``
(none or TV, λ, iterations), ``input`` (demosaic, CFA pattern, black and white level, exposure
correction, saturation threshold), ``output`` (cube formats, preview, spectra plot, the
fit-residual warning), ``uncertainty`` (on/off and the sensor's noise model) and
``registration`` (the drift measured from each frame, its warning and correction). It is built once
per run from flat keys (:meth:`ReconstructSettings.from_flat`: a YAML file, ``--set key=value``,
the keyword overrides of :class:`~hsi_torch.recon.pipeline.Reconstructor`) and passed whole to the
reconstructor, the nn.Module and the workers of a distributed run.

**One definition**: every setting is one field of one group, with its default, its help text
(``metadata["help"]``, the field's documentation) and, where it differs from the field's name,
its flat key (``metadata["key"]``). The flat names (:data:`FLAT_KEYS`) and the YAML schema of
``reconstruct.yaml`` (:class:`~hsi_torch.recon.config.ReconstructConfig`, with its help texts
and defaults) are generated from these groups; a field marked ``metadata["yaml"] = False`` is a
setting of the Python API only.

**Validation happens here and only here**: each group checks its values in ``__post_init__``;
errors are :class:`~hsi_torch.config.ConfigError` (a ``ValueError``) that name the flat key
(``key 'lam': ...``), so the same message reaches a YAML file, ``--set`` and a keyword argument.

**One identity**: the object is frozen and hashable (sequences are kept as tuples), and
:meth:`ReconstructSettings.key` is a stable digest of every field (SHA-256 of its JSON), so a
field added to any group is part of the key without being listed anywhere (the workers' cache
of prepared reconstructors uses it).

No torch here (the configuration is importable without it).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

from hsi_torch.config import ConfigError

__all__ = [
    "ReconstructSettings",
    "SolveSettings",
    "PriorSettings",
    "InputSettings",
    "OutputSettings",
    "UncertaintySettings",
    "RegistrationSettings",
    "SequenceSettings",
    "TEMPORAL_KINDS",
    "DEFAULT_BETA",
    "SOLVERS",
    "PRIORS",
    "LAM_RULES",
    "CUBE_FORMATS",
    "MAX_PREVIEW_SIZE",
    "FLAT_KEYS",
    "RENAMED_KEYS",
    "with_overrides",
]

#: Default smoothness weight β on ‖D s‖² (DN² scale; best measured on the default prototype).
DEFAULT_BETA = 1e4
#: Largest accepted ``beta``: far above any useful smoothness weight (1e-2..1e6 on the DN²
#: scale), far below what overflows the float32 solve (an all-zero cube).
BETA_MAX = 1e12
#: ``lam`` default (= :data:`hsi_torch.recon.spatial.DEFAULT_LAM`, kept importable without torch).
_DEFAULT_LAM = 1.0
SOLVERS = ("active_set", "admm")
#: spatial priors: ``"none"`` (per-pixel NNLS) or ``"tv"`` (:mod:`hsi_torch.recon.spatial`)
PRIORS = ("none", "tv")
#: ``lam`` chosen per frame: SURE risk minimum, Morozov's discrepancy principle
LAM_RULES = ("auto", "discrepancy")
CUBE_FORMATS = ("tiff", "envi", "npz", "netcdf", "zarr")
DTYPES = ("float32", "float64")
DEMOSAICS = ("bilinear", "half")
CFA_PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")
#: largest ``preview_size`` (px): a 16384² RGB preview is already 0.8 GB in memory
MAX_PREVIEW_SIZE = 16384


CubeFormat = Literal["tiff", "envi", "npz", "netcdf", "zarr"]
CfaPattern = Literal["RGGB", "BGGR", "GRBG", "GBRG"]


def _set(default: Any, help: str, key: str | None = None, yaml: bool = True) -> Any:
    """A settings field: its default, help text, flat key (``None``: the field's name) and
    whether ``reconstruct.yaml`` has it (``False``: the Python API only)."""
    meta: dict[str, Any] = {"help": help, "yaml": yaml}
    if key is not None:
        meta["key"] = key
    if isinstance(default, (list, tuple)):
        return field(default_factory=lambda: _frozen(default), metadata=meta)
    return field(default=default, metadata=meta)


def _bad(key: str, message: str) -> ConfigError:
    return ConfigError(message, key=key)


def _number(key: str, value: Any) -> float:
    """A finite real number (bool refused)."""
    if isinstance(value, bool):
        raise _bad(key, f"must be a number, got {value!r}")
    try:
        v = float(value)
    except (TypeError, ValueError, OverflowError):
        raise _bad(key, f"must be a number, got {type(value).__name__}") from None
    if not math.isfinite(v):
        raise _bad(key, f"must be finite, got {v}")
    return v


def _checked(obj: Any, name: str, key: str, ok: Any, want: str) -> None:
    """Check the field ``name`` of a frozen settings group (``key``: its flat key, named in the
    error): a finite number for which ``ok`` holds (else "must be ``want``"), stored as a float."""
    v = _number(key, getattr(obj, name))
    if not ok(v):
        raise _bad(key, f"must be {want}, got {getattr(obj, name)}")
    object.__setattr__(obj, name, v)


def _positive_or_none(obj: Any, name: str, key: str, unit: str = "") -> None:
    """:func:`_checked` for ``None`` or a number ``> 0``."""
    if getattr(obj, name) is not None:
        _checked(obj, name, key, lambda v: v > 0, f"> 0{unit} or null")


def _count(key: str, value: Any, minimum: int, allow_none: bool = True) -> None:
    if value is None and allow_none:
        return
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        null = " or null" if allow_none else ""
        raise _bad(key, f"must be an integer >= {minimum}{null}, got {value!r}")


def _choice(key: str, value: Any, choices: tuple[Any, ...]) -> None:
    if value not in choices:
        raise _bad(key, f"must be one of {', '.join(map(str, choices))}, got {value!r}")


def _frozen(value: Any) -> Any:
    """Lists (and lists of lists) as tuples: the settings stay hashable."""
    if isinstance(value, (list, tuple)):
        return tuple(_frozen(v) for v in value)
    return value


def thaw(value: Any) -> Any:
    """Tuples (and tuples of tuples) as lists: the YAML form."""
    if isinstance(value, tuple):
        return [thaw(v) for v in value]
    return value


@dataclass(frozen=True)
class SolveSettings:
    """The per-pixel solve (flat keys: the field names)."""

    beta: float = _set(
        DEFAULT_BETA,
        "smoothness weight on ||D s||^2, on the data's scale (DN^2); "
        "1e-2..1e6 (1e4: best measured on the default prototype)",
    )
    diff_order: int = _set(1, "order of the difference operator D: 1, 2, or 0 (Tikhonov)")
    solver: Literal["active_set", "admm"] = _set("active_set", "exact active set, or ADMM")
    admm_iters: int | None = _set(None, "ADMM: fixed iteration count (null: run to tolerance)")
    chunk_size: int | None = _set(None, "pixels per solver chunk (null: solver default)")
    min_views: int = _set(3, "views a pixel needs to be valid")
    nan_invalid: bool = _set(True, "invalid pixels are NaN (else 0) in the cube")
    device: str | None = _set("cpu", "torch device (cpu, cuda, cuda:1, ...; null: the bundle's)")
    dtype: Literal["float32", "float64"] = _set(
        "float32", "precision of the sensing matrices and the solve"
    )
    precompute_cache: str = _set(
        "auto",
        "where the per-bundle precomputation (sensing model, masks, factorisation) is "
        "cached between runs: auto (the user cache folder, $HSI_TORCH_CACHE or "
        "~/.cache/hsi_torch), beside (a .hsi_torch_cache folder beside the bundle), off, or a "
        "folder",
    )

    def __post_init__(self) -> None:
        if not isinstance(self.dtype, str):  # a torch dtype given as an override
            object.__setattr__(self, "dtype", str(self.dtype).removeprefix("torch."))
        if (
            self.device is not None
            and not isinstance(self.device, str)
            and type(self.device).__name__ == "device"
        ):  # a torch.device given as an override
            object.__setattr__(self, "device", str(self.device))
        beta = _number("beta", self.beta)
        if not 0 <= beta <= BETA_MAX:
            raise _bad(
                "beta",
                f"must be between 0 and {BETA_MAX:g}, got {self.beta:g} (the "
                "useful range is about 1e-2..1e6)",
            )
        object.__setattr__(self, "beta", beta)
        if self.diff_order not in (0, 1, 2) or isinstance(self.diff_order, bool):
            raise _bad("diff_order", f"must be 0, 1 or 2, got {self.diff_order!r}")
        _choice("solver", self.solver, SOLVERS)
        _count("admm_iters", self.admm_iters, 1)
        _count("chunk_size", self.chunk_size, 1)
        _count("min_views", self.min_views, 1, allow_none=False)
        _choice("dtype", self.dtype, DTYPES)
        if self.device is not None and not isinstance(self.device, str):
            raise _bad("device", f"must be a device name such as 'cpu' or 'cuda:1', got "
                                 f"{type(self.device).__name__}")  # fmt: skip
        pc = self.precompute_cache
        if not isinstance(pc, str) or not pc.strip() or "\0" in pc:
            raise _bad("precompute_cache", f"must be auto, beside, off or a folder, got {pc!r}")


@dataclass(frozen=True)
class PriorSettings:
    """The spatial prior. Flat keys: ``prior`` (= ``kind``), ``lam``, ``spatial_iters``,
    ``spectral_rank``."""

    kind: Literal["none", "tv"] = _set(
        "none",
        "none: per-pixel NNLS; tv: spatial-spectral reconstruction with a vectorial "
        "total-variation prior, warm-started from the per-pixel answer",
        key="prior",
    )
    lam: float | Literal["auto", "discrepancy"] = _set(
        _DEFAULT_LAM,
        "prior=tv: relative TV weight, lambda = lam * sigma * sqrt(median trace G) "
        "with sigma the frame's noise level (DN) from its per-pixel residuals; auto: per frame, "
        "minimum of a Monte-Carlo SURE risk estimate; discrepancy: per frame, Morozov's "
        "discrepancy principle",
    )
    spatial_iters: int | None = _set(
        None, "prior=tv: fixed ADMM iterations (null: run to tolerance)"
    )
    spectral_rank: int | None = _set(
        None,
        "prior=tv: the TV on the k leading spectral components of the frame's per-pixel "
        "answer, the complement per pixel (null: on all bands)",
    )

    def __post_init__(self) -> None:
        _choice("prior", self.kind, PRIORS)
        if isinstance(self.lam, str):
            if self.lam not in LAM_RULES:
                raise _bad("lam", f"must be a number >= 0, 'auto' or 'discrepancy', got "
                                  f"{self.lam[:40]!r}")  # fmt: skip
        else:
            _checked(self, "lam", "lam", lambda v: v >= 0, ">= 0, 'auto' or 'discrepancy'")
        _count("spatial_iters", self.spatial_iters, 1)
        _count("spectral_rank", self.spectral_rank, 1)


@dataclass(frozen=True)
class InputSettings:
    """How a capture file is read (flat keys: the field names; ``sat_threshold`` is a keyword
    of the Python API)."""

    demosaic: Literal["bilinear", "half"] = _set(
        "bilinear",
        "Bayer inputs: bilinear (full resolution) or half (2x2 binning; needs a "
        "bundle made at half resolution)",
    )
    cfa_pattern: CfaPattern | None = _set(
        None,
        "Bayer inputs: CFA pattern (null: the file's metadata, else the pattern the "
        "bundle was calibrated with)",
    )
    black_level: float | tuple[float, ...] | None = _set(
        None,
        "black level subtracted from the stored values, DN: scalar, 4 values (Bayer cell) "
        "or 3 (R, G, B) (null: the file's metadata, else the calibration's, recorded in the "
        "bundle, else 0)",
    )
    white_level: float | None = _set(
        None,
        "saturation level, DN, > 0 (null: the file's metadata, else the integer type's maximum)",
    )
    exposure_correction: bool = _set(
        True, "scale observations by t_white / t_capture when both exposures are known"
    )
    exposure_s: float | None = _set(
        None,
        "exposure time of the captures, s, for a file whose metadata has none "
        "(RAW/DNG/TIFF EXIF, exposure_s); scaled by t_white / t_capture against the bundle's "
        "white reference (null: unknown, the cube's scale is relative)",
    )
    sat_threshold: float = _set(
        1e-3, "warped saturation weight above which an observation is saturated", yaml=False
    )

    def __post_init__(self) -> None:
        _choice("demosaic", self.demosaic, DEMOSAICS)
        if self.cfa_pattern is not None:
            _choice("cfa_pattern", self.cfa_pattern, CFA_PATTERNS)
        bl = self.black_level
        if isinstance(bl, (list, tuple)):
            if len(bl) not in (3, 4):
                raise _bad("black_level", "must be a scalar, 3 values (R, G, B) or 4 (the Bayer "
                                          f"cell), got {len(bl)} values")  # fmt: skip
            object.__setattr__(self, "black_level", tuple(_number("black_level", v) for v in bl))
        elif bl is not None:
            object.__setattr__(self, "black_level", _number("black_level", bl))
        _positive_or_none(self, "white_level", "white_level")
        if self.exposure_s is not None:  # (a number is finite: _number)
            _checked(self, "exposure_s", "exposure_s", lambda v: v > 0, "> 0 and finite or null")
        _checked(self, "sat_threshold", "sat_threshold", lambda v: 0 <= v < 1, "in [0, 1)")


@dataclass(frozen=True)
class OutputSettings:
    """What a run writes per input (flat keys: the field names)."""

    formats: tuple[CubeFormat, ...] = _set(
        ("tiff", "envi", "npz"),
        "cube files written per input: tiff (OME-TIFF .tif + GDAL "
        ".vrt), envi (.hdr/.img), npz, netcdf (.nc), zarr (.zarr); netcdf/zarr need pip "
        "install 'hsi-torch[formats]'",
    )
    preview: bool = _set(True, "write an sRGB preview PNG (D65)")
    preview_size: int = _set(
        512,
        "the preview's longer side is enlarged (integer factor, nearest neighbour) to at "
        f"least this many px; 0: native; at most {MAX_PREVIEW_SIZE}",
    )
    spectra_pixels: tuple[tuple[int, int], ...] = _set(
        (), "reference-frame pixels [row, col] whose spectra are plotted (PNG)"
    )
    fit_residual_warning: float | None = _set(
        0.15,
        "warn when a frame's relative fit residual (pooled over its brighter half, see "
        "recon.frame.fit_residual) exceeds this: a bundle of another geometry gives 0.21-0.25, "
        "the right bundle 0.01-0.03 (0.11 with 1/20 of the exposure); null: never",
    )
    fit_residual_limit: float | None = _set(
        0.5,
        "refuse a frame whose relative fit residual exceeds this (the bundle does not "
        "explain the capture: an sRGB PNG gives 1.0, another camera's RAW 0.27); no cube is "
        "written; null: never",
    )
    pedestal_refuse_factor: float | None = _set(
        10.0,
        "refuse a frame whose sensor outside the views reads more than this many times "
        "the pedestal warning limit after black subtraction (an all-wrong black level); null: "
        "never",
    )
    strict: bool = _set(
        False,
        "every warning about a frame is an error: the frame is refused, no cube is "
        "written (reconstruct --strict)",
    )

    def __post_init__(self) -> None:
        object.__setattr__(self, "formats", _frozen(self.formats))
        object.__setattr__(self, "spectra_pixels", _frozen(self.spectra_pixels))
        for f in self.formats:
            _choice("formats", f, CUBE_FORMATS)
        if len(set(self.formats)) != len(self.formats):
            raise _bad("formats", f"has duplicates: {list(self.formats)}")
        if not self.formats and not self.preview:
            raise _bad("formats", "nothing to write: formats is empty and preview is false")
        if (
            isinstance(self.preview_size, bool)
            or not isinstance(self.preview_size, int)
            or not (0 <= self.preview_size <= MAX_PREVIEW_SIZE)
        ):
            raise _bad("preview_size", f"must be an integer in 0..{MAX_PREVIEW_SIZE} (px), got "
                                       f"{self.preview_size!r}")  # fmt: skip
        for p in self.spectra_pixels:
            if len(p) != 2 or not all(isinstance(v, int) and not isinstance(v, bool) for v in p):
                raise _bad("spectra_pixels", f"pixels must be [row, col] integer pairs, got {p!r}")
        for key in ("fit_residual_warning", "fit_residual_limit", "pedestal_refuse_factor"):
            _positive_or_none(self, key, key)
        if not isinstance(self.strict, bool):
            raise _bad("strict", f"must be true or false, got {self.strict!r}")


@dataclass(frozen=True)
class UncertaintySettings:
    """The per-band standard deviation. Flat keys: ``uncertainty`` (= ``enabled``),
    ``noise_electrons_per_dn``, ``noise_read_e``."""

    enabled: bool = _set(
        False,
        "also write the standard deviation of every band from the sensor noise: "
        "<stem>_std.* beside the cube in the non-NPZ formats, the key 'std' in <stem>.npz and a "
        "map <stem>_std.png (see docs/reconstruct.md)",
        key="uncertainty",
    )
    electrons_per_dn: float | None = _set(
        None,
        "uncertainty: sensor conversion gain, e-/DN (null: the simulator's default sensor, "
        "30000 e- / (16383 - 512) DN = 1.89)",
        key="noise_electrons_per_dn",
    )
    read_e: float = _set(3.0, "uncertainty: sensor read noise sigma, electrons", key="noise_read_e")
    quantization_dn: float = _set(
        1.0, "uncertainty: the ADC step, DN", key="noise_quantization_dn", yaml=False
    )

    def __post_init__(self) -> None:
        _positive_or_none(self, "electrons_per_dn", "noise_electrons_per_dn")
        _checked(self, "read_e", "noise_read_e", lambda v: v >= 0, ">= 0")
        _checked(self, "quantization_dn", "noise_quantization_dn", lambda v: v >= 0, ">= 0")


@dataclass(frozen=True)
class RegistrationSettings:
    """The sensor drift measured from each frame (:mod:`hsi_torch.recon.drift`). Flat keys:
    ``drift_check``, ``drift_warn_px``, ``refine_registration``, ``drift_min_views``."""

    check: bool = _set(
        True,
        "measure each frame's drift against the bundle's registration (views aligned to "
        "the reference view; a sensor shift and rotation fitted) and store it in the cube's "
        "metadata (stats.drift)",
        key="drift_check",
    )
    warn_px: float | None = _set(
        0.5,
        "warn when the measured sensor motion moves a view's pixel by more than this many "
        "px (null: never)",
        key="drift_warn_px",
    )
    refine: bool | Literal["auto"] = _set(
        "auto",
        "correct the measured sensor motion before solving (every view sampled where "
        "the moved sensor put it; see docs/reconstruct.md): auto when it is measured reliably "
        "and above drift_warn_px (a drift that cannot be measured is left, with a finding), "
        "true always (one that cannot be measured refuses the frame), false never",
        key="refine_registration",
    )
    min_views: int = _set(
        4,
        "the fewest views that must agree on the measured drift (within 1 px of the fitted "
        "motion) for it to be trusted; fewer, or a drift beyond the measurable range: "
        "refine_registration fails the frame, the check warns that the drift could not be "
        "measured",
        key="drift_min_views",
    )

    def __post_init__(self) -> None:
        if not isinstance(self.check, bool):
            raise _bad("drift_check", f"must be true or false, got {self.check!r}")
        if not (isinstance(self.refine, bool) or self.refine == "auto"):
            raise _bad("refine_registration", f"must be true, false or auto, got {self.refine!r}")
        _positive_or_none(self, "warn_px", "drift_warn_px", " (px)")
        _count("drift_min_views", self.min_views, 2, allow_none=False)


#: the temporal prior's kinds (``sequence_temporal``)
TEMPORAL_KINDS = ("none", "quadratic")


@dataclass(frozen=True)
class SequenceSettings:
    """Frames of one sequence reconstructed in order (:mod:`hsi_torch.recon.sequence`; flat keys:
    the field names, in ``reconstruct.yaml`` and ``--set``, acting on ``reconstruct --sequence``,
    ``watch`` and :class:`~hsi_torch.recon.sequence.SequenceReconstructor`). What each setting
    does, the temporal prior's penalty ``w‖s_t − s_{t−1}‖²_G`` and its motion gate,
    ``warm_noise``'s deviation from the noise rule and the measured effects:
    ``docs/sequences.md``.
    """

    warm_start: bool = _set(
        False,
        "start each frame's per-pixel active-set solve from the previous frame's zero set",
    )
    warm_spatial: bool = _set(
        True,
        "start each frame's spatial-prior ADMM from the previous "
        "frame's answer (static pixels) and TV dual",
    )
    warm_noise: bool = _set(
        False,
        "warm_spatial: reuse the noise level (and lambda) of the frame it was last estimated "
        "on while the light and exposure stay within 10 % of it",
    )
    temporal: str = _set(
        "none",
        "temporal prior: none or quadratic (a gated penalty on the "
        "change of each pixel's spectrum since the previous frame)",
    )
    temporal_weight: float = _set(
        1.0,
        "the temporal penalty's weight: the previous answer counts as this many frames of data",
    )
    temporal_gate: float = _set(
        4.0,
        "motion gate: how much worse (in the pixel's noise "
        "variance per free band) the previous answer may fit this "
        "frame's data",
    )
    drift_track: bool = _set(
        False,
        "measure the drift of every frame and correct a smooth path fitted over the recent frames",
    )
    drift_window: int = _set(
        10, "frames the drift path is fitted over"
    )
    drift_jump_px: float = _set(
        0.5,
        "a measured drift this far (px) from the path's "
        "prediction is a jump: flagged, and the path restarts",
    )

    def __post_init__(self) -> None:
        for key, v in (
            ("warm_start", self.warm_start),
            ("warm_spatial", self.warm_spatial),
            ("warm_noise", self.warm_noise),
            ("drift_track", self.drift_track),
        ):
            if not isinstance(v, bool):
                raise _bad(key, f"must be true or false, got {v!r}")
        _choice("temporal", self.temporal, TEMPORAL_KINDS)
        for key in ("temporal_weight", "temporal_gate", "drift_jump_px"):
            v = _number(key, getattr(self, key))
            if not v > 0:
                raise _bad(key, f"must be > 0, got {v}")
            object.__setattr__(self, key, v)
        _count("drift_window", self.drift_window, 2, allow_none=False)


#: Keys of earlier releases, refused with what to write instead. ``spectra_points`` was
#: ``[x, y]`` = ``[col, row]``; every point option is now ``[row, col]`` (napari's order).
RENAMED_KEYS: dict[str, str] = {
    "spectra_points": "renamed to spectra_pixels, whose pixels are [row, col] (the order of "
                      "'hsi-torch view --point' and napari); spectra_points was [x, y] = "
                      "[col, row]: swap each pair, e.g. spectra_points=[[400, 300]] becomes "
                      "spectra_pixels=[[300, 400]]",
}  # fmt: skip


@dataclass(frozen=True)
class ReconstructSettings:
    """Every setting of a reconstruction, grouped (see the module docstring)."""

    solve: SolveSettings = field(default_factory=SolveSettings)
    prior: PriorSettings = field(default_factory=PriorSettings)
    input: InputSettings = field(default_factory=InputSettings)
    output: OutputSettings = field(default_factory=OutputSettings)
    uncertainty: UncertaintySettings = field(default_factory=UncertaintySettings)
    registration: RegistrationSettings = field(default_factory=RegistrationSettings)
    sequence: SequenceSettings = field(default_factory=SequenceSettings)

    def __post_init__(self) -> None:  # rules across groups
        if self.prior.kind != "none" and self.uncertainty.enabled:
            raise _bad(
                "uncertainty",
                "true is the per-pixel solver's noise model; it does not "
                f"hold for prior={self.prior.kind} (use prior: none)",
            )
        if self.sequence.temporal != "none" and self.prior.kind != "none":
            raise _bad(
                "temporal",
                f"{self.sequence.temporal!r} is a prior of the per-pixel "
                f"solve; it does not combine with prior={self.prior.kind} "
                "(use prior: none)",
            )

    @classmethod
    def from_flat(
        cls, values: Mapping[str, Any] | None = None, **keywords: Any
    ) -> ReconstructSettings:
        """Settings from flat keys (those of ``reconstruct.yaml``, or the reconstructor's
        keywords); keys left out keep their defaults.

        Raises:
            ConfigError: an unknown key or an invalid value (naming the key).
        """
        groups = _grouped({**(values or {}), **keywords})
        return cls(**{g: GROUPS[g](**groups.get(g, {})) for g in GROUPS})

    def flat(self) -> dict[str, Any]:
        """The flat keys and values (lists, as in a YAML file); ``from_flat(s.flat()) == s``."""
        return {k: thaw(getattr(getattr(self, g), f)) for k, (g, f) in FLAT_KEYS.items()}

    def replace(self, **keywords: Any) -> ReconstructSettings:
        """A copy with some flat keys changed (the groups changed are validated again).

        Raises:
            ConfigError: an unknown key or an invalid value (naming the key).
        """
        changed = {g: dataclasses.replace(getattr(self, g), **kw)
                   for g, kw in _grouped(keywords).items()}  # fmt: skip
        return dataclasses.replace(self, **changed)

    def inert(self) -> list[str]:
        """Messages for the keys set away from their defaults that have no effect with the
        other settings (``lam`` without ``prior: tv``, ``admm_iters`` with the active-set
        solver, the noise model without ``uncertainty``, ...): one line each, naming the key,
        its value and why. A run shows them once (not once per frame)."""
        d = _DEFAULTS
        out: list[str] = []

        def changed(key: str) -> bool:
            group, name = FLAT_KEYS[key]
            return getattr(getattr(self, group), name) != getattr(getattr(d, group), name)

        def note(key: str, why: str) -> None:
            if changed(key):
                value = thaw(getattr(getattr(self, FLAT_KEYS[key][0]), FLAT_KEYS[key][1]))
                out.append(f"setting {key}={value!r} has no effect: {why}")

        if self.prior.kind == "none":
            for key in ("lam", "spatial_iters", "spectral_rank"):
                note(key, "it applies to the spatial prior only (prior: tv), and prior is none")
            for key in ("warm_spatial", "warm_noise"):
                note(key, "it starts the spatial prior's solve (prior: tv), and prior is none")
        if self.solve.solver == "active_set":
            note("admm_iters", "it applies to solver: admm only, and the solver is active_set")
        if not self.uncertainty.enabled:
            for key in ("noise_electrons_per_dn", "noise_read_e", "noise_quantization_dn"):
                note(key, "the noise model is used only with uncertainty: true, which is off")
        if not self.output.preview:
            note("preview_size", "preview is false (no preview image is written)")
        if not (self.registration.check or self.registration.refine):
            for key in ("drift_warn_px", "drift_min_views"):
                note(key, "the drift is not measured (drift_check and refine_registration are "
                          "false)")  # fmt: skip
        return out

    def key(self) -> str:
        """A stable digest of every field of every group (hex SHA-256 of the JSON form)."""
        text = json.dumps(dataclasses.asdict(self), sort_keys=True, default=repr)
        return hashlib.sha256(text.encode("utf-8")).hexdigest()


#: group name → its settings class
GROUPS: dict[str, Any] = {
    f.name: f.default_factory for f in dataclasses.fields(ReconstructSettings)
}

#: flat key → (group, field) of :class:`ReconstructSettings`, generated from the groups' fields
#: (``metadata["key"]``, else the field's name): the keys of ``reconstruct.yaml`` and ``--set``,
#: plus the Python API's own (``sat_threshold``, ``noise_quantization_dn``)
FLAT_KEYS: dict[str, tuple[str, str]] = {
    f.metadata.get("key", f.name): (g, f.name)
    for g, cls in GROUPS.items()
    for f in dataclasses.fields(cls)
}

_DEFAULTS = ReconstructSettings()


def _grouped(flat: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """Flat keys as ``{group: {field: value}}`` (lists frozen); an unknown key is refused."""
    groups: dict[str, dict[str, Any]] = {}
    for k, v in flat.items():
        where = FLAT_KEYS.get(k)
        if where is None:
            raise _bad(k, RENAMED_KEYS.get(k, "unknown reconstruction setting"))
        groups.setdefault(where[0], {})[where[1]] = _frozen(v)
    return groups


def with_overrides(
    settings: ReconstructSettings | None, overrides: Mapping[str, Any]
) -> ReconstructSettings:
    """``settings`` (``None``: the defaults) with some flat keys changed — the keyword
    convenience of the reconstructors. Keys that then have no effect
    (:meth:`ReconstructSettings.inert`) are a ``UserWarning`` at the reconstructor's caller;
    settings given whole without overrides are not warned about (a run warns once, in its
    driver).

    Raises:
        TypeError: ``settings`` is not :class:`ReconstructSettings`.
        ConfigError: an unknown key or an invalid value (naming the key).
    """
    if settings is None:
        settings = _DEFAULTS
    elif not isinstance(settings, ReconstructSettings):
        raise TypeError(f"settings must be a ReconstructSettings, got {type(settings).__name__}")
    if not overrides:
        return settings
    out = settings.replace(**overrides)
    for msg in out.inert():
        warnings.warn(msg, UserWarning, stacklevel=3)
    return out
