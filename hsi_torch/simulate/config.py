"""Configuration schema of ``hsi-torch simulate`` (loaded by :func:`hsi_torch.config.load_config`).

Every section mirrors the dataclass of the module that owns the physics, so a config key has the
same name and unit as the field it sets (lengths in mm, angles in degrees, wavelengths in nm):

- ``geometry`` → :class:`hsi_torch.optics.KaleidoscopeGeometry`
- ``camera`` → :class:`hsi_torch.optics.CameraModel` (+ ``scale`` = :meth:`CameraModel.scaled`)
- ``brf`` → :class:`hsi_torch.optics.BRFConfig` (+ ``polarizer_efficiency``)
- ``sensor`` → :class:`hsi_torch.optics.sensor.SensorModel` (noise seed: ``render.seed``)
- ``diffuser`` → :class:`hsi_torch.optics.sensor.DiffuserModel`
- ``objective``, ``illuminant``, ``camera_sensitivity``, ``render``, ``captures``: this package.
- ``mismatch`` → :class:`hsi_torch.simulate.mismatch.Mismatch` (non-ideal effects, all off by
  default; the sensor's go to :class:`~hsi_torch.optics.sensor.SensorModel`).
- ``design`` → :class:`hsi_torch.optics.PrototypeDesign` (the spectral coder: this system's BRF
  by default, or the ``manakov`` per-view filters, or the ``fujimoto`` thin section).

``describe_schema(SimulateConfig)`` prints one line per key with its default and help text.

The schema's defaults are the README's default prototype (exit 40 mm; quartz 2.5 mm, axis
70° / 40°; 0.1 mm diffuser blur), equal to the optics dataclasses' defaults and to the shipped
``simulate.yaml`` (``hsi_torch.resources.shipped_config("simulate")``); ``simulate_full.yaml``
changes only the camera (the original prototype's sensor) and the render settings.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from hsi_torch.config import option
from hsi_torch.optics.birefringence import BRFConfig
from hsi_torch.optics.designs import PrototypeDesign
from hsi_torch.optics.kaleidoscope import CameraModel, KaleidoscopeGeometry
from hsi_torch.optics.sensor import DiffuserModel, SensorModel
from hsi_torch.simulate.mismatch import Mismatch

__all__ = [
    "GeometryConfig",
    "CameraConfig",
    "BRFSection",
    "DesignSection",
    "SensorSection",
    "ObjectiveConfig",
    "DiffuserConfig",
    "RenderConfig",
    "GridPose",
    "GridConfig",
    "SceneSpec",
    "CapturesConfig",
    "SimulateConfig",
    "DEFAULT_GRID_POSES",
    "DEFAULT_SCENES",
]


_GEOMETRY = KaleidoscopeGeometry()
_CAMERA = CameraModel()
_BRF = BRFConfig()
_SENSOR = SensorModel()
_DIFFUSER = DiffuserModel()
_DESIGN = PrototypeDesign()


def _positive(obj: Any, *names: str) -> None:
    for n in names:
        v = getattr(obj, n)
        if v is not None and not v > 0:
            raise ValueError(f"{n} must be > 0, got {v}")


@dataclass
class GeometryConfig:
    """Tapered kaleidoscope (fields of :class:`~hsi_torch.optics.KaleidoscopeGeometry`)."""

    a_in_mm: float = option(_GEOMETRY.a_in_mm, "entrance side at the diffuser, mm")
    a_out_mm: float = option(_GEOMETRY.a_out_mm, "exit side, mm (taper: a_out > a_in)")
    length_mm: float = option(_GEOMETRY.length_mm, "tube length, mm")
    pupil_distance_mm: float = option(
        _GEOMETRY.pupil_distance_mm, "camera pupil beyond the exit, mm"
    )
    mirror_reflectance: float = option(_GEOMETRY.mirror_reflectance, "reflectance per bounce")
    max_reflections: int = option(_GEOMETRY.max_reflections, "reflections that count as views")
    vertices_in: list[tuple[float, float]] | None = option(
        None, "3 entrance vertices (mm, counter-clockwise) or null"
    )
    brf_free_center_mm: tuple[float, float] | None = option(
        None, "BRF-free disk centre (mm); null = 60 % towards vertex 0"
    )
    brf_free_radius_mm: float = option(_GEOMETRY.brf_free_radius_mm, "BRF-free disk radius, mm")


@dataclass
class CameraConfig:
    """Pinhole camera (fields of :class:`~hsi_torch.optics.CameraModel`)."""

    width_px: int = option(_CAMERA.width_px, "sensor width, px")
    height_px: int = option(_CAMERA.height_px, "sensor height, px")
    pixel_pitch_mm: float = option(_CAMERA.pixel_pitch_mm, "pixel pitch, mm")
    focal_length_mm: float = option(_CAMERA.focal_length_mm, "focal length, mm")
    cx: float | None = option(None, "principal point x, px (null = centre)")
    cy: float | None = option(None, "principal point y, px (null = centre)")
    scale: float = option(1.0, "resample the sensor (CameraModel.scaled)")

    def __post_init__(self) -> None:
        _positive(self, "scale")


@dataclass
class BRFSection:
    """Birefringent filter between polarizers (fields of :class:`~hsi_torch.optics.BRFConfig`)."""

    material: str = option(str(_BRF.material), "quartz | calcite | polymer")
    thickness_mm: float = option(_BRF.thickness_mm, "plate thickness, mm")
    axis_tilt_deg: float = option(_BRF.axis_tilt_deg, "optic axis tilt out of the plate")
    axis_azimuth_deg: float = option(_BRF.axis_azimuth_deg, "azimuth of the projected axis")
    psi_deg: float = option(_BRF.psi_deg, "retarder axis vs polarizer")
    chi_deg: float = option(_BRF.chi_deg, "analyser vs polarizer (90 = crossed)")
    outside_index: float = option(_BRF.outside_index, "index of the outside medium")
    polarizer_efficiency: float = option(
        0.9, "transmission of the polarizer pair for the passed polarization (stack = ½·eff·T_BRF)"
    )

    def __post_init__(self) -> None:
        if not 0 < self.polarizer_efficiency <= 1:
            raise ValueError(
                f"polarizer_efficiency must be in (0, 1], got {self.polarizer_efficiency}"
            )


@dataclass
class DesignSection:
    """The spectral coder (fields of :class:`~hsi_torch.optics.PrototypeDesign`).

    ``this_system``: the ``brf`` section between polarizers. ``manakov``: one filter per view,
    no BRF, no polarizers (``brf`` unused); the reference view is unfiltered. ``fujimoto``: the
    ``brf`` section is a thin section whose OPD each grain scales (``grain_*``).
    """

    kind: Literal["this_system", "manakov", "fujimoto"] = option(
        "this_system", "this_system | manakov | fujimoto"
    )
    filter_centers_nm: list[float] | None = option(
        None,
        "manakov: band-pass centres of views 1..V-1, nm; null = evenly spaced over filter_span_nm",
    )
    filter_span_nm: tuple[float, float] = option(
        _DESIGN.filter_span_nm, "manakov: first and last default centre, nm"
    )
    filter_fwhm_nm: float = option(_DESIGN.filter_fwhm_nm, "manakov: band-pass FWHM, nm")
    filter_peak: float = option(_DESIGN.filter_peak, "manakov: band-pass peak transmittance")
    filters: list[str] | None = option(
        None,
        "manakov: measured filters of views 1..V-1 (CSV wavelength_nm,T or gel "
        "codes such as L068); replace the band-pass set",
    )
    grain_size_mm: float = option(_DESIGN.grain_size_mm, "fujimoto: mean grain size, mm")
    grain_opd_factor: tuple[float, float] = option(
        _DESIGN.grain_opd_factor, "fujimoto: range of the per-grain factor on the plate's OPD"
    )
    grain_seed: int = option(_DESIGN.grain_seed, "fujimoto: grain map seed")

    def __post_init__(self) -> None:
        self.to_design()  # validates

    def to_design(self, filter_curves: tuple | None = None) -> PrototypeDesign:
        """The :class:`~hsi_torch.optics.PrototypeDesign` of this section (``filter_curves``:
        the resolved ``filters``, see :func:`hsi_torch.simulate.capture_sets.build_renderer`)."""
        return PrototypeDesign(
            kind=self.kind,
            filter_centers_nm=(
                None if self.filter_centers_nm is None else tuple(self.filter_centers_nm)
            ),
            filter_span_nm=tuple(self.filter_span_nm),  # type: ignore[arg-type]
            filter_fwhm_nm=self.filter_fwhm_nm,
            filter_peak=self.filter_peak,
            filter_curves=filter_curves,
            grain_size_mm=self.grain_size_mm,
            grain_opd_factor=tuple(self.grain_opd_factor),  # type: ignore[arg-type]
            grain_seed=int(self.grain_seed),
        )


@dataclass
class SensorSection:
    """Raw sensor (fields of :class:`~hsi_torch.optics.sensor.SensorModel`)."""

    output: Literal["bayer", "rgb"] = option(_SENSOR.output, "bayer | rgb")
    cfa_pattern: Literal["RGGB", "BGGR", "GRBG", "GBRG"] = _SENSOR.cfa_pattern  # type: ignore[assignment]
    bit_depth: int = option(_SENSOR.bit_depth, "ADC bits")
    white_level: float | None = option(_SENSOR.white_level, "DN; null = 2^bits - 1")
    black_level: float = option(_SENSOR.black_level, "DN offset")
    full_well_e: float | None = option(_SENSOR.full_well_e, "electrons")
    electrons_per_dn: float | None = option(_SENSOR.electrons_per_dn, "null = full well/range")
    read_noise_e: float = option(_SENSOR.read_noise_e, "read noise sigma, electrons")
    shot_noise: bool = option(_SENSOR.shot_noise, "Poisson photon noise")
    exposure: float = option(
        0.8,
        "scene/white/grid exposure: a white target seen without the "
        "filter stack fills this fraction of the full well",
    )
    quantize: bool = option(_SENSOR.quantize, "round to integer DN")
    psf_sigma_px: float = option(_SENSOR.psf_sigma_px, "lens PSF sigma, px (0 = none)")


@dataclass
class ObjectiveConfig:
    """Objective lens in front of the diffuser (absent during the monochromator scan)."""

    vignetting: float = option(
        0.2, "V(X) = 1 - vignetting·(|X|/R)², R = circumradius of the entrance triangle"
    )
    transmission: float = option(0.9, "flat transmission tau_obj")
    transmission_csv: str | None = option(None, "CSV wavelength_nm,value (replaces `transmission`)")

    def __post_init__(self) -> None:
        if not 0 <= self.vignetting < 1:
            raise ValueError(f"vignetting must be in [0, 1), got {self.vignetting}")
        if not 0 < self.transmission <= 1:
            raise ValueError(f"transmission must be in (0, 1], got {self.transmission}")


@dataclass
class DiffuserConfig:
    """Diffuser (fields of :class:`~hsi_torch.optics.sensor.DiffuserModel`)."""

    falloff_k: float = option(_DIFFUSER.falloff_k, "angular fall-off D(α) = cos^k α")
    blur_sigma_mm: float = option(_DIFFUSER.blur_sigma_mm, "scene blur on the diffuser, mm")

    def __post_init__(self) -> None:
        if self.falloff_k < 0 or self.blur_sigma_mm < 0:
            raise ValueError("falloff_k and blur_sigma_mm must be >= 0")


@dataclass
class RenderConfig:
    """Numerics of the renderer."""

    grid_start_nm: float = option(430.0, "reconstruction grid start, nm")
    grid_stop_nm: float = option(670.0, "reconstruction grid stop, nm")
    grid_step_nm: float = option(10.0, "reconstruction grid step, nm")
    fine_step_nm: float = option(
        2.0, "internal wavelength step; the band-pass is the grid +- half a grid step"
    )
    supersample: int = option(2, "s: s×s rays per sensor pixel")
    max_reflections: int = option(
        3, "reflections traced for the image (higher-order tiles are drawn but are no views)"
    )
    chunk: int = option(1 << 16, "rays per batch (memory bound)")
    device: str = option("cpu", "torch device (--device overrides)")
    dtype: Literal["float32", "float64"] = option("float64", "render dtype")
    seed: int = option(0, "noise seed (each capture gets seed + index)")
    progress: bool = option(True, "tqdm progress bars on stderr")
    figures: bool = option(True, "write OUT/figures/*.png")
    view_inset_px: float = option(
        1.0,
        "truth view_mask: distance a reference pixel's source point "
        "must keep from its triangle's edges, px",
    )

    def __post_init__(self) -> None:
        _positive(self, "grid_step_nm", "fine_step_nm", "supersample", "chunk")
        if self.grid_stop_nm < self.grid_start_nm:
            raise ValueError("grid_stop_nm must be >= grid_start_nm")
        if self.max_reflections < 0:
            raise ValueError(f"max_reflections must be >= 0, got {self.max_reflections}")


@dataclass
class GridPose:
    """One pose of the circle-grid target (see :class:`~.scenes.CircleGridScene`)."""

    rotation_deg: float = 0.0
    translation_mm: tuple[float, float] = (0.0, 0.9)
    tilt_x_deg: float = 0.0
    tilt_y_deg: float = 0.0


DEFAULT_GRID_POSES: tuple[GridPose, ...] = (
    GridPose(0.0, (0.0, 0.9), 0.0, 0.0),
    GridPose(7.0, (-0.4, 0.7), 12.0, 0.0),
    GridPose(-6.0, (0.4, 1.1), 0.0, 12.0),
)


@dataclass
class GridConfig:
    """OpenCV asymmetric circle grid used for registration."""

    pattern_size: tuple[int, int] = option((4, 5), "(cols, rows) as OpenCV")
    spacing_mm: float = option(1.0, "OpenCV squareSize on the diffuser, mm")
    radius_mm: float = option(0.38, "circle radius, mm")
    poses: list[GridPose] = option(
        text="poses (>= 3 recommended)", factory=lambda: list(DEFAULT_GRID_POSES)
    )


@dataclass
class SceneSpec:
    """A scene capture.

    ``kind``: ``colorchecker`` | ``usaf`` | ``white`` | ``flat`` | ``circle_grid`` | ``cave`` |
    ``cube``. ``params`` go to the scene constructor (:func:`hsi_torch.simulate.scenes.make_scene`;
    ``*_deg`` keys are converted). ``cube``: ``path`` to a cube file read with
    :func:`hsi_torch.io.load_cube`, placed with ``params`` ``width_mm``/``center_mm``.
    ``optional``: skip (with a message) when the data is missing, e.g. CAVE without the real-data
    folder (:func:`hsi_torch.resources.real_data_dir`).
    """

    kind: Literal["colorchecker", "usaf", "white", "flat", "circle_grid", "cave", "cube"]
    name: str | None = None
    path: Path | None = None
    params: dict[str, Any] = field(default_factory=dict)
    optional: bool = False


DEFAULT_SCENES: tuple[SceneSpec, ...] = (
    SceneSpec("colorchecker", "colorchecker", params={"width_mm": 8.4, "center_mm": [0.0, 1.4]}),
)


@dataclass
class CapturesConfig:
    """Which captures to render."""

    scan_wavelengths_nm: list[float] | None = option(
        None, "monochromator wavelengths; null = the reconstruction grid"
    )
    scan_fwhm_nm: float = option(10.0, "monochromator line FWHM, nm")
    scan_line: Literal["gaussian", "triangle"] = option(
        "gaussian", "line shape (triangle = equal entrance/exit slits)"
    )
    scan_exposure: float = option(
        0.8,
        "the BRF-free patch at the brightest scan line and colour "
        "fills this fraction of the full well",
    )
    white_shots: int = option(3, "white-reference captures")
    dark_frames: int = option(1, "dark frames (type 'dark')")
    grid: GridConfig = field(default_factory=GridConfig)
    scenes: list[SceneSpec] = field(default_factory=lambda: list(DEFAULT_SCENES))

    def __post_init__(self) -> None:
        _positive(self, "scan_fwhm_nm", "scan_exposure")
        if self.white_shots < 0 or self.dark_frames < 0:
            raise ValueError("white_shots and dark_frames must be >= 0")
        names = [s.name or s.kind for s in self.scenes]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"scene names must be unique; give `name` to {dup}")


@dataclass
class SimulateConfig:
    """``hsi-torch simulate`` configuration (see ``docs/simulate.md``)."""

    geometry: GeometryConfig = field(default_factory=GeometryConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    brf: BRFSection = field(default_factory=BRFSection)
    design: DesignSection = field(default_factory=DesignSection)
    sensor: SensorSection = field(default_factory=SensorSection)
    illuminant: str = option("D65", "CIE name (D65, A, ...) or CSV path")
    camera_sensitivity: str = option(
        "Canon EOS 5D Mark II", "camera name, CSV or rawtoaces JSON path"
    )
    objective: ObjectiveConfig = field(default_factory=ObjectiveConfig)
    diffuser: DiffuserConfig = field(default_factory=DiffuserConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    captures: CapturesConfig = field(default_factory=CapturesConfig)
    mismatch: Mismatch = field(default_factory=Mismatch)
