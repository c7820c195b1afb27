"""What reconstruction checks about a capture against its calibration bundle, and says (the
rules and every finding's code: ``docs/bad_inputs.md``; the black-level rule is the reader's,
:func:`hsi_torch.io.captures.black_level_rule`, only reported here).

:func:`measure_capture` (black level as read, pedestal outside the views, camera, data scale)
and :func:`exposure_info` (observations scaled by ``t_white / t_capture``,
:func:`exposure_scale`, when both exposures are known in the same unit: ``radiometric_scale:
"reflectance"``, else ``"relative"``) fill a frame's statistics; :func:`frame_findings` turns
them (with the solve's fit residual and the drift) into :class:`~hsi_torch.findings.Finding`
objects: facts (info), doubts (warning) and refusals (error: no cube is written).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from hsi_torch.errors import InputError
from hsi_torch.findings import Finding, escalated
from hsi_torch.io.bundle import CalibrationBundle
from hsi_torch.io.radiometry import (
    CameraIdentity,
    black_level_rgb,
    camera_mismatches,
    capture_exposure,
    outside_views_index,
    pedestal_level,
    pedestal_limit,
)
from hsi_torch.recon.drift import drift_finding
from hsi_torch.recon.settings import ReconstructSettings

__all__ = [
    "BundleRadiometry",
    "batch_pedestal_findings",
    "capture_findings",
    "drift_findings",
    "exposure_info",
    "exposure_scale",
    "fit_findings",
    "frame_findings",
    "measure_capture",
]


@dataclass(frozen=True)
class BundleRadiometry:
    """What a bundle says about the calibration's captures (``None``: not recorded, e.g. a bundle
    written before these were kept).

    Attributes:
        white_exposure_s: the white reference's exposure; white_exposure_unit: ``"s"`` or
            ``"relative"`` (the simulator's ``exposure``), ``None`` when not recorded.
        black_level_rgb: ``[R, G, B]`` DN subtracted at calibration (black level + dark mean);
            black_level_source: how it was found (a sentence).
        camera: the camera's identity.
        outside_index: flat indices of sampled sensor pixels that no view reaches.
        veil_index: flat indices of sensor pixels no light reaches, when the calibration
            subtracted the veil of stray light measured there (``stray_light: subtract``; the
            captures get the same subtraction), else ``None``.
        defect_index: flat indices of the hot and dead sensor pixels the calibration found
            (``defects: mask``; their observations are dropped), else ``None``.
    """

    white_exposure_s: float | None = None
    white_exposure_unit: str | None = None
    black_level_rgb: tuple[float, float, float] | None = None
    black_level_source: str | None = None
    camera: CameraIdentity | None = None
    white_level_dn: float | None = None
    white_level_source: str | None = None
    outside_index: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64), repr=False)
    veil_index: np.ndarray | None = field(default=None, repr=False)
    defect_index: np.ndarray | None = field(default=None, repr=False)

    @classmethod
    def from_bundle(cls, bundle: CalibrationBundle, white_exposure_s: float | None = None
                    ) -> BundleRadiometry:  # fmt: skip
        """From a bundle's ``settings`` and layout (``white_exposure_s``: as found by
        :func:`~hsi_torch.recon.sensing.bundle_exposure`)."""
        s = bundle.settings if isinstance(bundle.settings, Mapping) else {}
        unit = s.get("white_exposure_unit")
        black = black_level_rgb(s.get("black_level_rgb"))
        src = s.get("black_level_source")
        return cls(
            white_exposure_s=white_exposure_s,
            white_exposure_unit=unit if unit in ("s", "relative") else None,
            black_level_rgb=None if black is None else (black[0], black[1], black[2]),
            black_level_source=src if isinstance(src, str) else None,
            camera=CameraIdentity.from_dict(s.get("camera")),
            white_level_dn=_positive(s.get("white_level_dn")),
            white_level_source=(s.get("white_level_source")
                                if isinstance(s.get("white_level_source"), str) else None),
            outside_index=outside_views_index(bundle.triangles, tuple(bundle.sensor_size)),
            veil_index=(np.asarray(bundle.extras["unreached_index"], np.int64)
                        if s.get("stray_light") == "subtract"
                        and "unreached_index" in bundle.extras else None),
            defect_index=(np.asarray(bundle.extras["defect_pixels"], np.int64)
                          if "defect_pixels" in bundle.extras else None),
        )  # fmt: skip


def _positive(v: Any) -> float | None:
    ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0
    return float(v) if ok else None


def data_scale_note(meta: Mapping[str, Any], radiometry: BundleRadiometry | None,
                    camera_mismatch: Sequence[str] = ()) -> str | None:
    """Why the capture's values may be on another scale than the calibration's, or ``None``.

    The bundle records the white level its white shots were read with (``white_level_dn``, and
    its source). A capture read with another one — an 8-bit PNG (255), 14-bit counts shifted
    into 16 bits or a 16-bit container (the integer type's maximum, taken for a file that states
    none), a ``white_level`` setting of another scale — or with none (a float file, e.g.
    normalised to 1) may hold values on another scale: then every spectrum is off by that
    factor, which neither the fit residual nor the pedestal check can see. Not said when the
    capture's level is the file's own and the bundle's was only the integer type's maximum (the
    bundle's is the guess), or when the camera check already compared the two
    (``camera_mismatch``)."""
    ref = radiometry.white_level_dn if radiometry is not None else None
    if ref is None:
        return None
    wl = meta.get("white_level")
    src = meta.get("white_level_source")
    if src in ("default", None):
        fix = (f"when the file holds the same sensor counts as the calibration's, give "
               f"white_level (--set white_level={ref:g}), which also marks saturation right")
    else:
        fix = "convert the file to the calibration's scale, or calibrate with files like it"
    if not isinstance(wl, (int, float)) or isinstance(wl, bool):
        return (f"data scale unknown: the capture states no white level (a float file) and the "
                f"calibration's white shots were read with {ref:g} DN; if its values are "
                f"normalised or on another scale, the cube is off by that factor; {fix}")
    if abs(float(wl) - ref) <= 0.5 or any("white level" in str(m) for m in camera_mismatch):
        return None
    if src == "file" and radiometry is not None and radiometry.white_level_source == "default":
        return None
    how = {"file": "the file's own", "default": "the integer type's maximum: the file states "
           "none", "config": "the white_level setting"}.get(str(src), f"from the {src}")
    return (f"data scale: the capture was read with white level {float(wl):g} DN ({how}), the "
            f"calibration's white shots with {ref:g} DN; if its values span that white level "
            f"instead of the calibration's (another bit depth, shifted or rescaled), every "
            f"spectrum is {float(wl) / ref:.3g}x what it should be; {fix}")


def _span(meta: Mapping[str, Any]) -> float | None:
    wl = meta.get("white_level")
    if not isinstance(wl, (int, float)) or isinstance(wl, bool):
        return None
    black = black_level_rgb(meta.get("black_level"), meta.get("cfa_pattern")) or [0.0]
    return float(wl) - float(np.mean(black))


def measure_capture(
    capture: Any,
    radiometry: BundleRadiometry | None,
    *,
    sensor_size: tuple[int, int] | None = None,
) -> dict[str, Any]:
    """Measure a capture read with :func:`~hsi_torch.io.read_any` (which already applied the
    bundle's defaults: :class:`~hsi_torch.io.captures.CaptureDefaults`) against what the bundle
    knows; the capture is not changed. Returns the statistics to add to the frame's.

    - ``black_level``, ``black_level_source`` (as read, :func:`~hsi_torch.io.captures.
      black_level_rule`) and ``black_level_rgb`` (per colour).
    - ``pedestal_dn`` / ``pedestal_limit_dn``: per colour, the median outside every view and its
      limit (full-resolution captures of the bundle's sensor size only).
    - ``camera`` and ``camera_mismatch``: the capture's camera and its differences from the
      bundle's.

    Args:
        capture: a :class:`~hsi_torch.io.LinearCapture` (``image (3, H, W)``, ``metadata``,
            ``path``).
        radiometry: the bundle's (``None``: nothing to complete or compare).
        sensor_size: ``(H, W)`` the outside-view indices refer to.
    """
    meta = capture.metadata
    src = meta.get("black_level_source")
    stats: dict[str, Any] = {}
    rad = radiometry
    stats["black_level"] = meta.get("black_level")
    stats["black_level_source"] = src
    # per colour, for the messages: a Bayer cell's 4 values need the pattern to be read so
    stats["black_level_rgb"] = black_level_rgb(meta.get("black_level"), meta.get("cfa_pattern"))
    if rad is None:
        return stats
    img = capture.image
    if rad.outside_index.size and (sensor_size is None
                                   or tuple(img.shape[-2:]) == tuple(sensor_size)):  # fmt: skip
        idx = rad.outside_index
        if capture.saturated is not None:  # a saturated sample says nothing of the black level
            sat = capture.saturated.reshape(capture.saturated.shape[0], -1).any(0)
            idx = idx[~sat[torch.as_tensor(idx, device=sat.device)].cpu().numpy()]
        st = pedestal_level(img, idx)
        if st is not None:
            span = _span(meta)
            if meta.get("white_level_source") in ("default", None) and \
                    rad.white_level_dn is not None:  # fmt: skip
                # the capture's white level is a guess (the integer type's maximum, 4x the
                # 14-bit span for a 16-bit file) or unknown: the calibration's span, not a
                # limit loosened by the guess (a 64 DN pedestal passed a 164 DN limit)
                span = rad.white_level_dn - float(np.mean(stats["black_level_rgb"] or [0.0]))
            stats["pedestal_dn"] = [round(v, 3) for v in st[0]]
            stats["pedestal_limit_dn"] = [round(pedestal_limit(span, s), 3) for s in st[1]]
    cam = CameraIdentity.from_metadata(meta, tuple(img.shape[-2:]) if capture.mosaic is None
                                       else tuple(capture.mosaic.shape[-2:]),
                                       levels_from_file=src == "file")  # fmt: skip
    stats["camera"] = cam.name
    mism = camera_mismatches(rad.camera, cam)
    if mism:
        stats["camera_mismatch"] = mism
    note = data_scale_note(meta, rad, mism)
    if note:
        stats["data_scale_note"] = note
        wl = meta.get("white_level")
        stats["white_level"] = float(wl) if isinstance(wl, (int, float)) else None
        stats["calibration_white_level"] = rad.white_level_dn
    cal_cfa = rad.camera.cfa_pattern if rad.camera is not None else None
    if meta.get("kind") == "rgb" and cal_cfa:
        # the fit cannot tell: a white-balanced RGB fits at 0.10, a tone-curved one at 0.09
        # (limit 0.15), with cubes 1.8x and 12x off on the small prototype's ColorChecker
        stats["mosaic_note"] = (
            f"the capture is an RGB image but the bundle was calibrated from {cal_cfa} Bayer "
            "mosaics, demosaiced here: an RGB file from a camera's or a raw converter's "
            "processing (white balance, colour matrix, tone curve) gives wrong spectra that the "
            "fit residual does not show; reconstruct the raw mosaic (RAW/DNG or a Bayer TIFF) "
            "instead, unless this RGB is a linear demosaic of the same sensor's counts"
        )
    return stats


def exposure_scale(capture_exposure_s: Any, white_exposure_s: float | None) -> float:
    """Factor applied to a capture's observations: ``t_white / t_capture`` (1 when unknown).

    The response ``phi`` (hence ``A``) is calibrated on white-reference shots taken with exposure
    ``t_white``: a white reflector imaged with exposure ``t`` reads ``t / t_white`` times the
    calibrated values. Scaling ``y`` by ``t_white / t`` keeps reconstructed spectra in
    reflectance units relative to the white reference, whatever the capture's exposure.
    """
    if white_exposure_s is None or capture_exposure_s is None:
        return 1.0
    try:
        t = float(capture_exposure_s)
    except (TypeError, ValueError, OverflowError):
        raise InputError(
            f"capture metadata 'exposure_s' is not a number: {capture_exposure_s!r}"
        ) from None
    if not t > 0 or t == float("inf"):
        raise InputError(f"capture metadata 'exposure_s' must be > 0, got {capture_exposure_s!r}")
    return float(white_exposure_s) / t



def _ratio_text(r: float) -> str:
    """``t_capture / t_white`` as words: ``"1/2"``, ``"2x"``, ``"0.37x"``."""
    for v, fmt in ((1 / r, "1/{}"), (r, "{}x")):
        n = round(v)
        if v >= 1.5 and abs(v - n) < 1e-3 * v:
            return fmt.format(n)
    return f"{r:.3g}x"


def exposure_info(
    metadata: Mapping[str, Any], radiometry: BundleRadiometry | None,
    white_exposure_s: float | None, correction: bool = True,
) -> tuple[Any, dict[str, Any]]:
    """The exposure to scale a capture by and what to say about it.

    Returns:
        ``(exposure, stats)``: the capture's exposure to pass on (``None``: no scaling) and
        ``radiometric_scale`` (``"reflectance"``: relative to the white reference,
        ``"relative"``: unknown ratio, ``"uncorrected"``: ``exposure_correction`` off),
        ``exposure_note`` (a sentence), ``capture_exposure``, ``capture_exposure_unit``,
        ``capture_exposure_source``, ``white_exposure``, ``white_exposure_unit``.
    """
    t, unit, src = capture_exposure(metadata)
    w = white_exposure_s
    w_unit = radiometry.white_exposure_unit if radiometry is not None else None
    stats: dict[str, Any] = {
        "capture_exposure": t if isinstance(t, (int, float)) else None,
        "capture_exposure_unit": unit, "capture_exposure_source": src,
        "white_exposure": w, "white_exposure_unit": w_unit,
    }  # fmt: skip
    if not correction:
        stats.update(radiometric_scale="uncorrected",
                     exposure_note="exposure correction off (exposure_correction=false)")
        return None, stats
    missing = []
    if t is None:
        missing.append("the capture's (no exposure_s in its metadata; give --set exposure_s=...)")
    if w is None:
        missing.append("the white reference's (not in the calibration bundle; give exposure_s "
                       "for the white shots in the sheet/manifest/metadata and calibrate again)")
    if missing:
        stats.update(radiometric_scale="relative",
                     exposure_note="exposure unknown: " + " and ".join(missing) + "; the cube's "
                     "scale is relative, not reflectance")  # fmt: skip
        return None, stats
    if unit and w_unit and unit != w_unit:
        words = {"s": "in seconds", "relative": "relative (the simulator's 'exposure')"}
        stats.update(radiometric_scale="relative",
                     exposure_note=f"the capture's exposure is {words[unit]} and the white "
                     f"reference's {words[w_unit]}: not comparable, not scaled; the cube's scale "
                     "is relative, not reflectance")  # fmt: skip
        return None, stats
    k = exposure_scale(t, w)
    r = 1.0 / k
    if abs(r - 1) < 1e-9:
        note = "exposure equal to the white reference's"
    else:
        note = f"exposure {_ratio_text(r)} of the white's: scaled x{1 / r:.4g}"
    stats.update(radiometric_scale="reflectance", exposure_note=note)
    return t, stats


def frame_findings(
    stats: Mapping[str, Any], settings: ReconstructSettings | None = None,
    source: str | None = None,
) -> list[Finding]:
    """Every check about one reconstructed frame, as :class:`~hsi_torch.findings.Finding` objects
    (codes, severities and limits: ``docs/bad_inputs.md``), from its statistics
    (:func:`measure_capture`, :func:`exposure_info` and the frame's solve): ``capture.*``, then
    ``fit.*``, then ``drift.*``, then the illuminant's; with ``strict`` every warning is an error
    (:func:`~hsi_torch.findings.escalated`). ``settings``: the limits (default: the defaults);
    ``source``: what the findings are about (the file), or ``None``.
    """
    s = settings if settings is not None else ReconstructSettings()
    out = capture_findings(stats, s, source) + fit_findings(stats, s, source)
    out += drift_findings(stats, s, source)
    # the scene's light against the white's (recon/illuminant.py): a finding when it differs;
    # the ratio within its limit stays in the statistics only (not a line on every frame)
    ill = stats.get("illuminant")
    if isinstance(ill, Mapping) and ill.get("severity") != "info":
        out.append(Finding.from_dict(ill))
    return escalated(out, s.output.strict)


def capture_findings(
    stats: Mapping[str, Any], settings: ReconstructSettings, source: str | None = None
) -> list[Finding]:
    """The ``capture.*`` findings of :func:`frame_findings` (not escalated)."""
    out: list[Finding] = []

    def add(code: str, severity: str, message: str, measured: Any = None, limit: Any = None,
            fix: str | None = None) -> None:
        out.append(Finding(code, severity, message, measured, limit, fix, source))

    if stats.get("black_level_source") == "bundle":
        b = black_level_rgb(stats.get("black_level")) or [0.0]
        lv = f"{b[0]:.4g}" if max(b) - min(b) < 0.05 else "[" + ", ".join(f"{v:.4g}"
                                                                          for v in b) + "]"
        add("capture.black_level_from_bundle", "info",
            f"black level {lv} DN from the calibration bundle (the file carries none)",
            measured=[round(v, 4) for v in b],
            fix="give black_level (--set black_level=...) if the file's black level differs")
    if stats.get("radiometric_scale") == "reflectance" and \
            abs(float(stats.get("exposure_scale", 1.0)) - 1) > 1e-9:  # fmt: skip
        add("capture.exposure_scaled", "info", str(stats.get("exposure_note")),
            measured=float(stats.get("exposure_scale", 1.0)))
    sat, obs = stats.get("saturated_observations"), stats.get("observations")
    if isinstance(sat, int) and sat > 0 and isinstance(obs, int) and obs > 0:
        add("capture.saturated", "info",
            f"{sat} of {obs} observations at the white level, left out of the fit",
            measured=round(sat / obs, 6), fix="a shorter exposure keeps the highlights")
    ped, lim = stats.get("pedestal_dn"), stats.get("pedestal_limit_dn")
    if isinstance(ped, list) and isinstance(lim, list) and len(ped) == len(lim) == 3:
        c = max(range(3), key=lambda i: abs(ped[i]) / max(lim[i], 1e-12))
        if abs(ped[c]) > lim[c]:
            b = (black_level_rgb(stats.get("black_level_rgb"))
                 or black_level_rgb(stats.get("black_level")) or [0.0, 0.0, 0.0])  # fmt: skip
            src = stats.get("black_level_source", "?")
            sub = b[c]
            if ped[c] > 0:
                fix = (f"the capture carries a black pedestal of ~{ped[c]:.0f} DN; give "
                       f"black_level (e.g. --set black_level={sub + ped[c]:.0f})")  # fmt: skip
            else:
                fix = (f"the black level subtracted is ~{-ped[c]:.0f} DN too high; give the right "
                       f"black_level (e.g. --set black_level={sub + ped[c]:.0f})")  # fmt: skip
            factor = settings.output.pedestal_refuse_factor
            hard = factor is not None and abs(ped[c]) > factor * lim[c]
            add("capture.pedestal", "error" if hard else "warning",
                f"the sensor outside the views reads {ped[c]:.1f} DN after black subtraction "
                f"({'RGB'[c]} channel; black level subtracted {sub:.4g} DN, source: {src})"
                + (f": more than pedestal_refuse_factor={factor:g} times the limit, the black "
                   "level is wrong" if hard else ""),
                measured=round(float(ped[c]), 3), limit=round(float(lim[c]), 3), fix=fix)
    if stats.get("radiometric_scale") == "relative":
        add("capture.exposure_unknown", "warning", str(stats.get("exposure_note")),
            measured=stats.get("capture_exposure"), limit=stats.get("white_exposure"),
            fix="give the capture's exposure (--set exposure_s=...) and calibrate with the "
                "white shots' exposure recorded")
    if stats.get("data_scale_note"):
        add("capture.data_scale", "warning", str(stats["data_scale_note"]),
            measured=stats.get("white_level"), limit=stats.get("calibration_white_level"))
    if stats.get("mosaic_note"):
        add("capture.rgb_for_mosaic", "warning", str(stats["mosaic_note"]), measured="rgb",
            fix="reconstruct the raw mosaic (RAW/DNG or a Bayer TIFF)")
    mism = stats.get("camera_mismatch")
    if isinstance(mism, list) and mism:
        add("capture.camera_mismatch", "warning",
            "camera: " + "; ".join(str(m) for m in mism) + " (a bundle of another camera gives "
            "wrong spectra)", measured=stats.get("camera"), fix="calibrate this camera")
    return out


def fit_findings(
    stats: Mapping[str, Any], settings: ReconstructSettings, source: str | None = None
) -> list[Finding]:
    """The ``fit.*`` findings of :func:`frame_findings` (not escalated)."""
    out: list[Finding] = []
    fit = stats.get("fit_residual")
    warn, hard = settings.output.fit_residual_warning, settings.output.fit_residual_limit
    if isinstance(fit, float) and math.isfinite(fit):
        over = [(lim, sev) for lim, sev in ((hard, "error"), (warn, "warning"))
                if lim is not None and fit > lim]
        if over:
            lim, sev = over[0]
            key = "fit_residual_limit" if sev == "error" else "fit_residual_warning"
            out.append(Finding(
                "fit.residual", sev,
                f"relative fit residual {fit:.3f} > {key}={lim:g}: the spectra do not explain "
                "the capture" + ("; refused" if sev == "error" else ""),
                measured=round(fit, 4), limit=lim, source=source,
                fix="is the calibration bundle from this camera and geometry, and are the black "
                    "level and exposure right?"))  # fmt: skip
    n = int(stats.get("num_not_converged", 0) or 0)
    if n:
        out.append(Finding(
            "fit.not_converged", "warning",
            f"{n} of {stats.get('num_valid', '?')} pixels did not converge (KKT residual above "
            "the solver tolerance)", measured=n, limit=0, source=source,
            fix="try dtype=float64 or a larger beta"))  # fmt: skip
    return out


def drift_findings(
    stats: Mapping[str, Any], settings: ReconstructSettings, source: str | None = None
) -> list[Finding]:
    """The ``drift.*`` findings of :func:`frame_findings` (not escalated): the frame's
    :func:`~hsi_torch.recon.drift.drift_finding`, the one stored when the drift was measured
    (``stats["drift"]["finding"]``), else made under ``settings``; a measurement within
    ``drift_warn_px`` (``drift.below_warning``, a corrected motion below it, ``drift.no_texture``
    but under ``refine_registration: true``) stays in the statistics only, not a line on every
    frame."""
    drift = stats.get("drift")
    if not isinstance(drift, Mapping):
        return []
    reg = settings.registration
    if "finding" in drift:  # said by the front door that measured it, under these settings
        said = drift["finding"]
        f = None if said is None else Finding.from_dict({**said, "source": source})
    else:
        f = drift_finding(drift, reg.refine, reg.warn_px, source, stats.get("fit_residual"),
                          settings.output.fit_residual_warning)  # fmt: skip
    if f is None:
        return []
    m = f.measured
    above = reg.warn_px is not None and isinstance(m, (int, float)) and m > reg.warn_px
    return [f] if f.severity != "info" or above else []


#: the most outside-the-views samples :func:`batch_pedestal_findings` reads per frame and colour
MODULE_PEDESTAL_SAMPLES = 4096


def batch_pedestal_findings(
    rgb: torch.Tensor, radiometry: BundleRadiometry | None, settings: ReconstructSettings,
    source: str = "input", saturated: torch.Tensor | None = None,
) -> list[Finding]:
    """The pedestal check of :func:`capture_findings` on a batch of linear RGB frames that are
    supposed to be DN above black (the :class:`~hsi_torch.recon.module.HSIReconstructor`'s input
    convention): per frame and colour, the median at the bundle's sampled pixels outside every
    view (``radiometry.outside_index``) against :func:`~hsi_torch.io.radiometry.pedestal_limit`
    (the calibration's white span, 5 robust σ). One finding (``capture.pedestal``, the worst
    frame and colour; an error beyond ``pedestal_refuse_factor`` times the limit), escalated
    under ``strict``; ``[]`` when the bundle records no outside pixels.

    Cost: one gather of about :data:`MODULE_PEDESTAL_SAMPLES` pixels per frame and colour (every
    k-th of the bundle's samples), two medians and one device-to-host copy of ``(B, 3)`` values.

    Args:
        rgb: ``(B, 3, H, W)`` at the bundle's sensor size.
        radiometry: the bundle's (``None``: nothing checked).
        settings: the limits (``pedestal_refuse_factor``, ``strict``).
        source: what the finding names.
        saturated: ``rgb``'s saturation mask (bool, same shape) or ``None``: saturated samples
            are left out (a frame with fewer than 16 unsaturated ones is not checked).
    """
    rad = radiometry
    if rad is None or rad.outside_index.size < 16 or rgb.ndim != 4 or rgb.shape[0] == 0:
        return []
    # every k-th of the bundle's samples, at most ~MODULE_PEDESTAL_SAMPLES: a median to a DN
    step = max(1, rad.outside_index.size // MODULE_PEDESTAL_SAMPLES)
    idx = torch.as_tensor(rad.outside_index[::step], device=rgb.device)
    b, c = rgb.shape[:2]
    x = rgb.detach().reshape(b, c, -1).index_select(2, idx).to(torch.float64)
    x = torch.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0)
    if saturated is not None:
        sat = saturated.reshape(b, c, -1).index_select(2, idx).any(1, keepdim=True)
        x = torch.where(sat, torch.nan, x)
    med = x.nanmedian(dim=2).values
    mad = (x - med[..., None]).abs().nanmedian(dim=2).values
    n = (~torch.isnan(x)).sum(2).to(med.dtype)
    both = np.nan_to_num(torch.stack([med, 1.4826 * mad, n]).cpu().numpy())  # one copy
    both[0][both[2] < 16] = 0.0  # too few unsaturated samples: not judged
    black = float(np.mean(rad.black_level_rgb)) if rad.black_level_rgb is not None else 0.0
    span = rad.white_level_dn - black if rad.white_level_dn is not None else None
    lim = np.vectorize(lambda s: pedestal_limit(span, float(s)))(both[1])
    ratio = np.abs(both[0]) / lim
    k, ch = np.unravel_index(int(np.argmax(ratio)), ratio.shape)
    ped, limit = float(both[0][k, ch]), float(lim[k, ch])
    if not abs(ped) > limit:
        return []
    factor = settings.output.pedestal_refuse_factor
    hard = factor is not None and abs(ped) > factor * limit
    f = Finding(
        "capture.pedestal", "error" if hard else "warning",
        f"frame {k} of {b}: the sensor outside the views reads {ped:.1f} DN ({'RGB'[ch]} "
        "channel); the input must be linear DN above black" + (
            f", and this is more than pedestal_refuse_factor={factor:g} times the limit"
            if hard else ""),
        measured=round(ped, 3), limit=round(limit, 3), source=source,
        fix=(f"subtract the black level (~{ped:.0f} DN) from the input" if ped > 0 else
             f"the black level subtracted is ~{-ped:.0f} DN too high"))  # fmt: skip
    return escalated([f], settings.output.strict)
