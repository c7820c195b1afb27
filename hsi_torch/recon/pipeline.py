"""The file front door: :class:`Reconstructor` turns a bundle plus settings into cubes from
tensors, captures or files, through the one frame function
(:func:`hsi_torch.recon.frame.reconstruct_frame`).

The per-frame maths are :mod:`hsi_torch.recon.frame`; the bundle's sensor corrections
:mod:`hsi_torch.recon.corrections`; what is measured about a capture (pedestal, camera,
exposure) :mod:`hsi_torch.recon.checks`; the ``nn.Module`` (batches, gradients,
``torch.compile``) :class:`hsi_torch.recon.module.HSIReconstructor`, on the same frame function.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from hsi_torch.devices import torch_dtype
from hsi_torch.errors import FileFormatError, InputError
from hsi_torch.io import read_any
from hsi_torch.io.bundle import CalibrationBundle
from hsi_torch.io.captures import CaptureDefaults
from hsi_torch.io.cube import cube_to_xarray
from hsi_torch.recon.checks import exposure_info, exposure_scale, measure_capture
from hsi_torch.recon.corrections import apply_bundle_corrections, correct_frames
from hsi_torch.recon.drift import (
    corrected_sensing,
    drift_decision,
    drift_motion_px,
    estimate_drift,
)
from hsi_torch.recon.frame import (
    _sync,
    check_min_views,
    prepare_input,
    reconstruct_frame,
)
from hsi_torch.recon.illuminant import illuminant_finding
from hsi_torch.recon.sensing import BundleSensing, precompute_sensing, refreshed_sensing
from hsi_torch.recon.settings import DEFAULT_BETA, FLAT_KEYS, ReconstructSettings, with_overrides
from hsi_torch.recon.uncertainty import RAW_LAYOUTS, sampling_variance_factor

__all__ = [
    "ReconstructionResult",
    "Reconstructor",
    "DEFAULT_BETA",
    "ReconstructSettings",
    "exposure_scale",
    "apply_bundle_corrections",
]


@dataclass
class ReconstructionResult:
    """One reconstructed frame.

    Attributes:
        cube: ``(M, h, w)`` spectra on the reference frame (NaN or 0 where ``valid`` is False).
        valid: ``(h, w)`` bool, pixel reconstructed from ≥ ``min_views`` views.
        wavelengths_nm: ``(M,)`` float64, nm.
        stats: counts and solver diagnostics — ``num_valid``, ``num_lost`` (valid in the bundle,
            invalid in this frame), ``num_resolved`` (exact re-solves with a frame mask),
            ``num_pivoted`` (active-set corrections), ``converged_fraction``,
            ``num_not_converged`` (valid pixels whose solve did not reach the KKT tolerance),
            ``max_kkt``, ``fit_residual`` (median over up to :data:`FIT_RESIDUAL_SAMPLES` evenly
            spaced valid pixels of ``‖W(A s − y)‖ / ‖W y‖``, W = the frame mask; ≈ the noise
            level for a matching bundle, large when the bundle belongs to another geometry),
            ``exposure_scale``, ``observations`` (the bundle's static observations),
            ``usable_observations`` (of those: unsaturated and finite in this frame),
            ``saturated_observations``, ``no_valid_reason`` (``None``, or why not a single pixel
            is valid: saturation, non-finite data, ``min_views``).
        timings: seconds per stage (``load`` when read from a file, ``warp``, ``observations``,
            ``solve``, ``uncertainty`` (with ``uncertainty=True``), ``assemble``, ``total``).
        std: ``(M, h, w)`` standard deviation of every band from the sensor noise
            (:mod:`hsi_torch.recon.uncertainty`; 0 on bands at the bound, NaN where ``valid``
            is False), or ``None`` when the reconstructor was made without ``uncertainty=True``.
    """

    cube: Tensor
    valid: Tensor
    wavelengths_nm: Tensor
    stats: dict[str, Any] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)
    std: Tensor | None = None

    def to_xarray(self, metadata: dict[str, Any] | None = None):
        """The cube as an ``xarray.DataArray`` ``(wavelength, y, x)``, wavelength in nm, the
        valid mask as a coordinate (:func:`hsi_torch.io.cube.cube_to_xarray`; needs
        ``pip install 'hsi-torch[formats]'``)."""
        return cube_to_xarray(self.cube.detach().cpu(), self.wavelengths_nm.detach().cpu(),
                              self.valid.detach().cpu(), metadata)  # fmt: skip



class Reconstructor:
    """Reconstruct frames that share one calibration bundle (all precomputation done once).

    Args:
        bundle: :class:`CalibrationBundle`, its path, or a ready :class:`BundleSensing`.
        settings: every setting (:class:`~hsi_torch.recon.settings.ReconstructSettings`; what a
            run passes; default: the defaults): β and the difference order, the solver,
            ``device``/``dtype`` of the bundle tensors and the solve, ``min_views``, the prior
            (``prior="tv"``: spatial-spectral reconstruction with a vectorial total-variation
            prior, warm-started from the per-pixel answer, :mod:`hsi_torch.recon.spatial`),
            ``exposure_correction``, ``uncertainty`` (the standard deviation of every band,
            :attr:`ReconstructionResult.std`, from the settings' sensor noise model), the drift
            check and correction (:mod:`hsi_torch.recon.drift`; a drift the frame cannot support —
            too few views agree, beyond the measurable range — raises
            :class:`~hsi_torch.recon.drift.DriftError` under ``refine_registration``), and where
            the per-bundle precomputation is cached between processes (``precompute_cache``,
            :mod:`hsi_torch.recon.precompute_cache`).
        overrides: flat settings keys changed on ``settings``
            (:meth:`~hsi_torch.recon.settings.ReconstructSettings.replace`, e.g. ``beta=1e3``,
            ``prior="tv"``, ``dtype=torch.float64``); keys that then have no effect are a
            ``UserWarning``. :attr:`settings` holds the result, validated.

    Example:
        >>> rec = Reconstructor("calib.npz", beta=1e4)  # doctest: +SKIP
        >>> res = rec.reconstruct_file("scene.tif")  # doctest: +SKIP
        >>> res.cube.shape, res.valid.sum(), res.timings  # doctest: +SKIP
    """

    def __init__(
        self,
        bundle: CalibrationBundle | BundleSensing | str | os.PathLike,
        settings: ReconstructSettings | None = None,
        **overrides: Any,
    ) -> None:
        s = with_overrides(settings, overrides)
        #: the settings, grouped and frozen (:class:`~hsi_torch.recon.settings.ReconstructSettings`)
        self.settings = s
        sv = s.solve
        if isinstance(bundle, BundleSensing):
            self.sensing = bundle.with_regularisation(sv.beta, sv.diff_order)
        else:
            self.sensing = precompute_sensing(
                bundle, beta=sv.beta, diff_order=sv.diff_order, device=sv.device,
                dtype=torch_dtype(sv.dtype), chunk_size=sv.chunk_size,
                disk_cache=sv.precompute_cache,
            )  # fmt: skip
        check_min_views(sv.min_views, self.sensing.num_views)
        self._factors: dict[tuple[str, str | None, torch.dtype], Tensor] = {}

    @property
    def wavelengths_nm(self) -> Tensor:
        return self.sensing.wavelengths_nm

    def sampling_factor(self, layout: str, cfa_pattern: str | None = None) -> Tensor:
        """``(P, 3V)`` variance factor of the observations for captures made as ``layout``
        (:func:`~hsi_torch.recon.uncertainty.sampling_variance_factor`); kept per layout."""
        sens = self.sensing
        key = (layout, cfa_pattern if layout == "bayer" else None, sens.dtype)
        if key not in self._factors:
            self._factors[key] = sampling_variance_factor(
                sens.grid(), sens.sensor_size, layout, cfa_pattern)  # type: ignore[arg-type]
        return self._factors[key]

    def reconstruct_frame(
        self,
        image: Tensor,
        saturated: Tensor | None = None,
        *,
        exposure_s: float | None = None,
        cfa_pattern: str | None = None,
        source: str = "capture",
        raw_layout: str | None = None,
        bundle_corrections: bool = True,
    ) -> ReconstructionResult:
        """Reconstruct one capture.

        Args:
            image: ``(3, H, W)`` linear RGB (DN above black) or ``(1, H, W)`` Bayer mosaic
                (demosaiced bilinearly with ``cfa_pattern`` or the bundle's), sensor size.
            saturated: same shape, bool, or ``None``.
            exposure_s: the capture's exposure time (s); see :func:`exposure_scale`.
            source: name used in error messages (the file).
            raw_layout: with ``uncertainty``, how an RGB ``image`` was made from raw samples:
                ``"rgb"`` (independent samples, the default), ``"bayer"`` (bilinear demosaic
                with ``cfa_pattern``) or ``"half"`` (2 × 2 binning); a ``(1, H, W)`` mosaic is
                ``"bayer"``.
            bundle_corrections: apply the corrections the bundle's calibration applied
                (:func:`correct_frames`: veil subtracted, hot and dead pixels masked; reported
                in the statistics); ``False`` for an image already corrected.

        Returns:
            :class:`ReconstructionResult`.
        """
        # the disk-cache entry changed under its mapping?
        self.sensing = refreshed_sensing(self.sensing, self.settings.solve.chunk_size)
        sens = self.sensing
        if not isinstance(image, Tensor) or image.ndim != 3:
            raise ValueError(
                f"{source}: image must be a (3, H, W) or (1, H, W) tensor, got "
                f"{tuple(image.shape) if isinstance(image, Tensor) else type(image).__name__}"
            )
        sens.check_capture_size(image.shape, source)
        t0 = time.perf_counter()
        img = image.to(device=sens.device)
        sat = None if saturated is None else saturated.to(device=sens.device)
        pattern = cfa_pattern or sens.cfa_pattern
        img, sat = prepare_input(img, sat, pattern)
        corr: dict[str, Any] = {}
        if bundle_corrections:
            img, sat, corr = correct_frames(img, sat, sens.radiometry)
        settings = self.settings
        scale = (exposure_scale(exposure_s, sens.exposure_s) if settings.input.exposure_correction
                 else 1.0)  # fmt: skip
        factor = None
        if settings.uncertainty.enabled:
            layout = "bayer" if image.shape[0] == 1 else (raw_layout or "rgb")
            if layout not in RAW_LAYOUTS:
                raise ValueError(f"raw_layout must be one of {RAW_LAYOUTS}, got {raw_layout!r}")
            if layout == "bayer" and pattern is None:
                raise ValueError(f"{source}: raw_layout='bayer' needs a CFA pattern")
            factor = self.sampling_factor(layout, pattern)
        _sync(sens.device)
        t_demosaic = time.perf_counter() - t0
        drift = None
        if settings.registration.check or settings.registration.refine:
            t1 = time.perf_counter()
            drift = estimate_drift(sens, img, settings.registration.min_views)
            motion_px = drift_motion_px(sens, drift)
            reg = settings.registration
            correct, drift_finding = drift_decision(drift, motion_px, reg.refine, reg.warn_px,
                                                    source)
            if correct:
                sens = corrected_sensing(sens, drift.sensor_shift_px,
                                         drift.sensor_rotation_deg or 0.0)
            t_drift = time.perf_counter() - t1
        with torch.no_grad():
            out = reconstruct_frame(
                sens, img.unsqueeze(0), settings, None if sat is None else sat.unsqueeze(0),
                scale=None if scale == 1.0 else scale, sampling_factor=factor,
            )  # fmt: skip
        cube, valid, stats, t = out.cube, out.valid, out.stats, out.timings
        st = stats[0]
        ill = illuminant_finding(cube[0], valid[0], sens.wavelengths_nm, source=source)
        if ill is not None:  # the scene's light against the white reference's (a finding)
            st["illuminant"] = ill.to_dict()
        st["exposure_scale"] = scale
        st.update(corr)
        timings = {"demosaic": t_demosaic, **t} if image.shape[0] == 1 else dict(t)
        if drift is not None:
            st["drift"] = {**drift.to_dict(), "corrected": sens is not self.sensing,
                           "sensor_motion_px": round(motion_px, 3),
                           "refine_registration": settings.registration.refine,
                           "finding": None if drift_finding is None
                           else drift_finding.to_dict()}
            timings["drift"] = t_drift
        timings["total"] = time.perf_counter() - t0
        std = None if out.std is None else out.std[0]
        return ReconstructionResult(cube[0], valid[0], sens.wavelengths_nm, st, timings, std)

    def reconstruct_capture(self, capture: Any) -> ReconstructionResult:
        """Reconstruct a :class:`hsi_torch.io.LinearCapture` (``image``, ``saturated``, the
        exposure from ``metadata``: ``exposure_s``, else the simulator's relative ``exposure``,
        compared with the bundle's white reference in the same unit; the statistics say
        ``radiometric_scale`` and ``exposure_note``, :func:`hsi_torch.recon.checks.exposure_info`).
        """
        src = str(getattr(capture, "path", "capture"))
        corr = apply_bundle_corrections(capture, self.sensing.radiometry)
        meta = capture.metadata
        layout, pattern = "rgb", None
        if meta.get("kind") == "bayer":  # demosaiced by the reader: the noise went through it
            layout = "half" if meta.get("demosaic") == "half" else "bayer"
            pattern = meta.get("cfa_pattern")
        sens = self.sensing
        try:
            t, exp_stats = exposure_info(meta, sens.radiometry, sens.exposure_s,
                                         self.settings.input.exposure_correction)  # fmt: skip
            res = self.reconstruct_frame(
                capture.image, capture.saturated, exposure_s=t,
                source=src, raw_layout=layout, cfa_pattern=pattern, bundle_corrections=False,
            )  # fmt: skip
            res.stats.update(exp_stats)
            res.stats.update(corr)
            return res
        except InputError as exc:
            if "'exposure_s'" in str(exc) and getattr(capture, "path", None) is not None:
                raise FileFormatError(f"{src}: {exc}") from None  # the file's metadata at fault
            raise

    def reconstruct_file(self, path: str | os.PathLike, **overrides: Any) -> ReconstructionResult:
        """Read a capture (:func:`hsi_torch.io.read_any`) and reconstruct it.

        The reading follows the settings' ``input`` group (``demosaic``, ``cfa_pattern``,
        ``black_level``, ``white_level`` override the file's metadata; ``overrides``: flat keys of
        that group changed for this file, e.g. ``demosaic="half"``). What a file does not say it
        gets from the bundle, in the reader (:meth:`capture_defaults`): a Bayer file without a
        pattern the bundle's, a file without a black level the calibration's, a file without an
        exposure the ``exposure_s`` setting. The file's full-resolution size is checked against
        the bundle (errors name the file): the sensor size, or for Bayer files read with
        ``demosaic="half"`` (a bundle made at half resolution) twice the sensor size. The
        statistics also hold the black level used and its source, the pedestal outside the views,
        the camera and its differences from the bundle's
        (:func:`hsi_torch.recon.checks.measure_capture`, which only measures);
        :func:`hsi_torch.recon.checks.check_warnings` turns them into warnings.
        ``timings["load"]`` is the read (and demosaic).
        """
        s = self.settings
        if overrides:
            groups = {k: FLAT_KEYS.get(k, ("?", k))[0] for k in overrides}
            other = sorted(k for k, g in groups.items() if g != "input")
            if other:
                raise TypeError(f"reconstruct_file takes reading settings only (the input "
                                f"group), not {', '.join(other)}")  # fmt: skip
            s = s.replace(**overrides)
        read = s.input
        p = Path(path)
        sens = self.sensing
        t0 = time.perf_counter()
        cap = read_any(
            p, expected_size=sens.sensor_size if read.demosaic == "bilinear" else None,
            demosaic=read.demosaic, cfa_pattern=read.cfa_pattern, black_level=_listed(
                read.black_level), white_level=read.white_level, dtype=sens.dtype,
            device=sens.device, defaults=self.capture_defaults(read.exposure_s),
        )  # fmt: skip
        if read.demosaic == "half":
            _check_half_size(cap, sens, p)
        apply_bundle_corrections(cap, sens.radiometry)  # before the pedestal is measured
        checks = measure_capture(cap, sens.radiometry, sensor_size=sens.sensor_size)
        _sync(sens.device)
        t_load = time.perf_counter() - t0
        res = self.reconstruct_capture(cap)
        res.timings = {"load": t_load, **res.timings}
        res.timings["total"] += t_load
        res.stats.update(checks)
        res.stats["metadata"] = cap.metadata
        return res

    def capture_defaults(self, exposure_s: float | None = None) -> CaptureDefaults:
        """What :func:`~hsi_torch.io.read_any` gives a file that does not say: the bundle's
        black level (R, G, B, as its calibration subtracted) and CFA pattern, and
        ``exposure_s`` (default: the settings')."""
        sens = self.sensing
        rad = sens.radiometry
        t = self.settings.input.exposure_s if exposure_s is None else exposure_s
        return CaptureDefaults(black_level_rgb=None if rad is None else rad.black_level_rgb,
                               cfa_pattern=sens.cfa_pattern, exposure_s=t)  # fmt: skip


def _listed(level: Any) -> Any:
    """A settings black level (a number or a tuple) in read_any's form."""
    return list(level) if isinstance(level, tuple) else level


def _check_half_size(cap: Any, sens: BundleSensing, path: Path) -> None:
    """``demosaic="half"``: a Bayer mosaic must be exactly twice the bundle's sensor size (odd
    sizes included, which binning would silently crop); an RGB file is not binned."""
    H, W = sens.sensor_size
    if cap.mosaic is not None:
        full = tuple(int(v) for v in cap.mosaic.shape[-2:])
        if full != (2 * H, 2 * W):
            raise FileFormatError(
                f"{path}: Bayer mosaic size (H, W) = {full} does not match the calibration "
                f"bundle: with demosaic='half' it must be twice the bundle's sensor size "
                f"{(H, W)}, i.e. {(2 * H, 2 * W)}"
            )
    else:
        full = tuple(int(v) for v in cap.image.shape[-2:])
        if full != (H, W):
            raise FileFormatError(
                f"{path}: RGB image size (H, W) = {full} does not match the calibration bundle's "
                f"sensor size {(H, W)} (demosaic='half' bins Bayer mosaics only)"
            )

