"""Non-ideal effects of the virtual prototype: where a real device departs from the model.

Calibration and reconstruction assume perfect homographies between views, the monochromator
line the manifest states, no stray light, a uniform filter, an ideal linear sensor, the white
reference's illuminant for the scene, and nothing moving between calibration and capture.
:class:`Mismatch` (the ``mismatch:`` section of the simulate config) breaks each of these
assumptions on its own key. Every key's default switches its effect off, and with every effect
off the renderer takes exactly its ideal code path (bit-identical captures and truth).

Two kinds of effect (see ``docs/simulate.md``, "Non-ideal effects"):

- **device** effects act on every capture, calibration included (lens distortion, stray light,
  BRF thickness map, sensor non-linearity, hot/dead pixels, PRNU) or only on the monochromator
  scan (wavelength offset and actual line width, which calibration takes on trust);
- **calibration → capture** effects (``drift_*``, ``brf_delta_t_k``, ``scene_illuminant``) change
  the device *after* calibration: they act on the scene captures only (``type: scene``), never on
  the scan, white, grid or dark frames.

The sensor effects are fields of :class:`~hsi_torch.optics.sensor.SensorModel`; this module
holds the geometric, optical and spectral ones as small pure functions of the renderer's rays
and images.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from hsi_torch.config import option

__all__ = ["DOCUMENTED_EFFECTS", "Mismatch", "radial_undistort", "drift_points", "stray_light_veil"]

#: Each effect at its documented realistic magnitude (``docs/simulate.md``, "Non-ideal
#: effects"): ``mismatch.<key>: value`` overrides per effect name. Applied alone or together,
#: e.g. ``--set mismatch.distortion_k1=-0.1``.
DOCUMENTED_EFFECTS: dict[str, dict[str, object]] = {
    "monochromator": {"scan_wavelength_offset_nm": 0.5, "scan_fwhm_actual_nm": 12.0},
    "distortion": {"distortion_k1": -0.1},
    "stray_light": {"stray_light_fraction": 0.02},
    "brf_thickness": {"brf_thickness_gradient_um_per_mm": (0.15, 0.0),
                      "brf_thickness_curvature_um": 0.3},
    "brf_temperature": {"brf_delta_t_k": 5.0},
    "drift": {"drift_shift_px": (2.0, 0.0), "drift_rotation_deg": 0.05},
    "sensor_nonlinearity": {"sensor_nonlinearity": 0.03},
    "sensor_defects": {"prnu_sigma": 0.01, "hot_pixel_fraction": 1e-4,
                       "dead_pixel_fraction": 1e-5},
    "scene_illuminant": {"scene_illuminant": "A"},
}


@dataclass
class Mismatch:
    """Non-ideal effects of the virtual prototype (all off by default).

    Magnitudes worth simulating, with their sources, are tabulated in ``docs/simulate.md``.
    """

    # --- monochromator (scan frames only; calibration takes the manifest's line on trust)
    scan_wavelength_offset_nm: float = option(0.0, "true line centre minus the wavelength the "
                                                   "manifest states, nm (scan only)")
    scan_fwhm_actual_nm: float | None = option(None, "true line FWHM, nm; null = "
                                                     "captures.scan_fwhm_nm (scan only)")
    # --- objective/relay lens (every capture)
    distortion_k1: float = option(0.0, "radial distortion k1 (OpenCV convention, radius in focal "
                                       "lengths)")
    distortion_k2: float = option(0.0, "radial distortion k2")
    # --- stray light (every lit capture)
    stray_light_fraction: float = option(0.0, "veiling glare: mean of the veil / mean irradiance "
                                              "of the sensor, per colour")
    stray_light_width: float = option(0.5, "Gaussian sigma of the veil around the principal "
                                           "point, in sensor half-diagonals")
    # --- birefringent filter
    brf_thickness_gradient_um_per_mm: tuple[float, float] = option(
        (0.0, 0.0), "thickness wedge (x, y) across the aperture, um per mm of diffuser")
    brf_thickness_curvature_um: float = option(0.0, "quadratic thickness change at the entrance "
                                                    "circumradius, um")
    brf_delta_t_k: float = option(0.0, "filter temperature at capture minus at calibration, K "
                                       "(scenes only)")
    brf_retardance_temp_coeff_per_k: float = option(
        -1.23e-4, "(1/OPD) dOPD/dT, 1/K (crystal quartz, thickness expansion included)")
    # --- mechanics (scenes only)
    drift_shift_px: tuple[float, float] = option(
        (0.0, 0.0), "sensor shift (x, y) relative to the optics since calibration, px (scenes "
                    "only)")
    drift_rotation_deg: float = option(0.0, "sensor rotation about its centre since calibration, "
                                            "deg (scenes only)")
    # --- sensor (every capture; SensorModel fields)
    sensor_nonlinearity: float = option(0.0, "fraction of the charge lost at the full well (0 = "
                                             "linear)")
    sensor_nonlinearity_knee: float = option(0.7, "fraction of the full well where the response "
                                                  "starts to bend")
    prnu_sigma: float = option(0.0, "pixel gain non-uniformity (PRNU), relative sigma")
    hot_pixel_fraction: float = option(0.0, "fraction of hot pixels")
    hot_pixel_level: float = option(0.2, "a hot pixel's extra charge, fraction of the full well")
    dead_pixel_fraction: float = option(0.0, "fraction of dead pixels (no photo-charge)")
    pattern_seed: int = option(1, "seed of the fixed patterns (PRNU, hot and dead pixels)")
    # --- illumination (scenes only)
    scene_illuminant: str | None = option(None, "illuminant of the scene captures (CIE name or "
                                                "CSV); null = `illuminant` (white references and "
                                                "grids always use `illuminant`)")

    def __post_init__(self) -> None:
        self.brf_thickness_gradient_um_per_mm = tuple(  # type: ignore[assignment]
            float(v) for v in self.brf_thickness_gradient_um_per_mm)
        self.drift_shift_px = tuple(float(v) for v in self.drift_shift_px)  # type: ignore
        for name, vals in (("brf_thickness_gradient_um_per_mm",
                            self.brf_thickness_gradient_um_per_mm),
                           ("drift_shift_px", self.drift_shift_px)):
            if len(vals) != 2:
                raise ValueError(f"mismatch.{name} must have 2 values (x, y), got {vals}")
        if self.scan_fwhm_actual_nm is not None and not self.scan_fwhm_actual_nm > 0:
            raise ValueError(f"mismatch.scan_fwhm_actual_nm must be > 0, got "
                             f"{self.scan_fwhm_actual_nm}")
        for name in ("stray_light_fraction", "sensor_nonlinearity", "sensor_nonlinearity_knee",
                     "hot_pixel_fraction", "dead_pixel_fraction"):
            v = getattr(self, name)
            if not 0 <= v < 1:
                raise ValueError(f"mismatch.{name} must be in [0, 1), got {v}")
        for name in ("stray_light_width", "hot_pixel_level"):
            if not getattr(self, name) > 0:
                raise ValueError(f"mismatch.{name} must be > 0, got {getattr(self, name)}")
        if self.prnu_sigma < 0:
            raise ValueError(f"mismatch.prnu_sigma must be >= 0, got {self.prnu_sigma}")

    # ------------------------------------------------------------------ which effects are on
    @property
    def distorted(self) -> bool:
        return self.distortion_k1 != 0 or self.distortion_k2 != 0

    @property
    def drifted(self) -> bool:
        return any(v != 0 for v in self.drift_shift_px) or self.drift_rotation_deg != 0

    @property
    def thickness_map(self) -> bool:
        return (any(v != 0 for v in self.brf_thickness_gradient_um_per_mm)
                or self.brf_thickness_curvature_um != 0)

    @property
    def after_calibration(self) -> bool:
        """Any effect that changes the device between calibration and the scene captures."""
        return self.drifted or self.brf_delta_t_k != 0 or self.scene_illuminant is not None

    @property
    def scan_changed(self) -> bool:
        return self.scan_wavelength_offset_nm != 0 or self.scan_fwhm_actual_nm is not None

    def sensor_kwargs(self) -> dict[str, float | int]:
        """The :class:`~hsi_torch.optics.sensor.SensorModel` fields these keys set."""
        return {"nonlinearity": self.sensor_nonlinearity,
                "nonlinearity_knee": self.sensor_nonlinearity_knee,
                "prnu_sigma": self.prnu_sigma, "hot_pixel_fraction": self.hot_pixel_fraction,
                "hot_pixel_level": self.hot_pixel_level,
                "dead_pixel_fraction": self.dead_pixel_fraction,
                "pattern_seed": int(self.pattern_seed)}

    def active(self) -> dict[str, object]:
        """The keys that differ from their defaults (what the manifest records)."""
        ref = Mismatch()
        out: dict[str, object] = {}
        for name in self.__dataclass_fields__:
            v = getattr(self, name)
            if v != getattr(ref, name):
                out[name] = list(v) if isinstance(v, tuple) else v
        return out

    # ------------------------------------------------------------------ filter OPD
    def opd_factor(
        self, xy_mm: torch.Tensor, thickness_mm: float, r2_mm2: float, after_calibration: bool
    ) -> torch.Tensor | None:
        """``(N,)`` factor on every ray's OPD, or ``None`` when it is 1 everywhere.

        The OPD of a plate is proportional to its thickness, so a thickness map
        ``d(X) = d₀ + g·X + c·|X|²/R²`` (``X`` the diffuser point behind which the filter is
        crossed, mm; ``R²`` = ``r2_mm2``) scales it by ``d(X)/d₀``; after calibration a
        temperature change ``ΔT`` scales it by ``1 + γ·ΔT`` (``γ`` =
        ``brf_retardance_temp_coeff_per_k``, which holds both the thermal expansion and
        ``dΔn/dT``).
        """
        fac = None
        if self.thickness_map:
            gx, gy = self.brf_thickness_gradient_um_per_mm
            d_um = (gx * xy_mm[:, 0] + gy * xy_mm[:, 1]
                    + self.brf_thickness_curvature_um * xy_mm.pow(2).sum(-1) / r2_mm2)
            fac = 1.0 + d_um / (1000.0 * thickness_mm)
        if after_calibration and self.brf_delta_t_k != 0:
            t = 1.0 + self.brf_retardance_temp_coeff_per_k * self.brf_delta_t_k
            fac = torch.full(xy_mm.shape[:1], t, dtype=xy_mm.dtype, device=xy_mm.device) \
                if fac is None else fac * t
        return fac


def radial_undistort(
    points_px: torch.Tensor, k1: float, k2: float, focal_px: float, cx: float, cy: float,
    iterations: int = 10,
) -> torch.Tensor:
    """Pinhole position of sensor points under radial distortion (OpenCV's ``k1, k2``).

    The lens maps an ideal (pinhole) normalised point ``x_u`` to ``x_d = x_u·(1 + k1 r² + k2 r⁴)``
    (``r = |x_u|``, normalised by the focal length around the principal point). A sensor pixel
    sees what the pinhole camera sees at ``x_u``, found by fixed-point iteration
    ``x_u ← x_d / (1 + k1|x_u|² + k2|x_u|⁴)`` (converges for the ≤ 1 % distortions of a
    photographic lens; 10 iterations reach float64 rounding at 1 %).

    Args:
        points_px: ``(N, 2)`` sensor points (x, y) in px.
    Returns:
        ``(N, 2)`` pinhole points in px, dtype of the input.
    """
    c = torch.tensor([cx, cy], dtype=points_px.dtype, device=points_px.device)
    xd = (points_px - c) / focal_px
    xu = xd
    for _ in range(iterations):
        r2 = xu.pow(2).sum(-1, keepdim=True)
        xu = xd / (1.0 + k1 * r2 + k2 * r2 * r2)
    return xu * focal_px + c


def drift_points(
    points_px: torch.Tensor, shift_px: tuple[float, float], rotation_deg: float,
    centre_px: tuple[float, float],
) -> torch.Tensor:
    """Where the pixels of a moved sensor lie in the calibrated sensor's frame.

    ``p' = c + R(θ)(p − c) + t``: the sensor turned by ``θ`` about its centre ``c`` and shifted
    by ``t`` relative to the optics, so its pixel ``p`` sees what the calibrated sensor saw at
    ``p'`` (the image appears moved by ``−t``, turned by ``−θ``).
    """
    c = torch.tensor(centre_px, dtype=points_px.dtype, device=points_px.device)
    t = torch.tensor(shift_px, dtype=points_px.dtype, device=points_px.device)
    if rotation_deg == 0:
        return points_px + t
    a = math.radians(rotation_deg)
    rot = torch.tensor([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]],
                       dtype=points_px.dtype, device=points_px.device)
    return (points_px - c) @ rot.T + c + t


def stray_light_veil(
    image: torch.Tensor, fraction: float, width: float, centre_px: tuple[float, float],
    cfa: torch.Tensor | None = None,
) -> torch.Tensor:
    """The image plus a smooth veil of scattered light, per colour.

    The veil of colour ``c`` is ``fraction · mean_c · P(p)``: ``mean_c`` the mean irradiance of
    colour ``c`` over the whole sensor (dark tiles included) and ``P`` a Gaussian around the
    principal point of ``σ = width`` sensor half-diagonals, normalised to mean 1 over the sensor,
    so the veil adds ``fraction`` of the sensor's light, spread over every pixel (also where no
    view reaches).

    Args:
        image: ``(C, H, W)`` irradiance; ``C = 1`` with ``cfa`` ``(H, W)`` long (each pixel's
            colour index), or ``C = 3``.
    Returns:
        ``(C, H, W)`` new tensor.
    """
    c_, h, w = image.shape
    ys = torch.arange(h, dtype=image.dtype, device=image.device)[:, None] - centre_px[1]
    xs = torch.arange(w, dtype=image.dtype, device=image.device)[None, :] - centre_px[0]
    sig = width * 0.5 * math.hypot(h, w)
    p = torch.exp(-(xs * xs + ys * ys) / (2.0 * sig * sig))
    p = p / p.mean()
    if c_ == 1 and cfa is not None:
        veil = torch.zeros_like(image[0])
        for c in range(3):
            m = cfa == c
            if bool(m.any()):
                veil = torch.where(m, fraction * image[0][m].mean() * p, veil)
        return image + veil[None]
    means = image.reshape(c_, -1).mean(1)
    return image + fraction * means[:, None, None] * p[None]
