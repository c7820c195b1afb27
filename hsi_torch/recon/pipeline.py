"""The one reconstructor: :class:`HSIReconstructor` turns a bundle plus settings into cubes from
tensors (``forward``: an ``nn.Module``), captures or files (:meth:`~HSIReconstructor.
reconstruct_frame`, :meth:`~HSIReconstructor.reconstruct_capture`,
:meth:`~HSIReconstructor.reconstruct_file`), all through the one frame function
:func:`hsi_torch.recon.frame.reconstruct_frame`; :class:`Reconstructor` is the same class without
the full-frame calibration arrays. Buffers, ``.to``/``.double``, ``torch.compile`` (one graph
break, at the eager solver) and the all-or-nothing ``load_state_dict`` (derived tensors rebuilt by
:func:`hsi_torch.recon.sensing.build_sensing`, bit for bit): ``docs/python_api.md``, *The module's
buffers and state*.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import threading
import time
from collections.abc import Callable
from contextvars import ContextVar
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any, NamedTuple

import torch
from torch import Tensor, nn

from hsi_torch.devices import torch_dtype
from hsi_torch.errors import FileFormatError, InputError
from hsi_torch.findings import Finding, refuse_or_warn
from hsi_torch.forward_model import SensingModel
from hsi_torch.io import read_any
from hsi_torch.io.bundle import CalibrationBundle
from hsi_torch.io.captures import CaptureDefaults
from hsi_torch.io.cube import cube_to_xarray
from hsi_torch.optics.geometry import view_sample_grid
from hsi_torch.recon.checks import (
    batch_pedestal_findings,
    exposure_info,
    exposure_scale,
    frame_findings,
    measure_capture,
)
from hsi_torch.recon.corrections import apply_bundle_corrections, correct_frames
from hsi_torch.recon.drift import (
    corrected_sensing,
    drift_decision,
    drift_finding,
    drift_motion_px,
    estimate_drift,
)
from hsi_torch.recon.frame import (
    WarmStart,
    _sync,
    check_min_views,
    prepare_input,
    reconstruct_frame,
)
from hsi_torch.recon.illuminant import illuminant_finding
from hsi_torch.recon.nnls import NNLSProblem, prepare_nnls
from hsi_torch.recon.sensing import (
    BundleSensing,
    build_sensing,
    load_bundle,
    precompute_sensing,
    refreshed_sensing,
)
from hsi_torch.recon.settings import DEFAULT_BETA, FLAT_KEYS, ReconstructSettings, with_overrides
from hsi_torch.recon.uncertainty import RAW_LAYOUTS, sampling_variance_factor

__all__ = [
    "ReconstructionResult",
    "ReconstructionOutput",
    "HSIReconstructor",
    "Reconstructor",
    "OUTPUTS",
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
        findings: what the checks found about the frame
            (:func:`hsi_torch.recon.checks.frame_findings`; info and warnings only — a frame
            with an error finding raises :class:`~hsi_torch.findings.RefusedError` instead).
    """

    cube: Tensor
    valid: Tensor
    wavelengths_nm: Tensor
    stats: dict[str, Any] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)
    std: Tensor | None = None
    findings: list[Finding] = field(default_factory=list)

    def to_xarray(self, metadata: dict[str, Any] | None = None):
        """The cube as an ``xarray.DataArray`` ``(wavelength, y, x)``, wavelength in nm, the
        valid mask as a coordinate (:func:`hsi_torch.io.cube.cube_to_xarray`; needs
        ``pip install 'hsi-torch[formats]'``)."""
        return cube_to_xarray(self.cube.detach().cpu(), self.wavelengths_nm.detach().cpu(),
                              self.valid.detach().cpu(), metadata)  # fmt: skip


#: set while a reconstructor's method judges its result: the calls it makes (capture → frame)
#: leave the judging to it
_JUDGING: ContextVar[bool] = ContextVar("hsi_torch_judging", default=False)


def _judged(method: Callable[..., ReconstructionResult]) -> Callable[..., ReconstructionResult]:
    """The front door's verdict, in one place: the outermost ``reconstruct_*`` call turns its
    result's statistics into findings (:func:`~hsi_torch.recon.checks.frame_findings`, under the
    reconstructor's settings), refuses the frame on an error finding
    (:class:`~hsi_torch.findings.RefusedError`, naming the source, each finding's measured value,
    limit and fix), raises the warnings as Python warnings
    (:func:`~hsi_torch.findings.warn_findings`) and attaches them all to
    :attr:`ReconstructionResult.findings`."""

    @functools.wraps(method)
    def judged(self: Any, *args: Any, **kwargs: Any) -> ReconstructionResult:
        if _JUDGING.get():
            return method(self, *args, **kwargs)
        token = _JUDGING.set(True)
        try:
            res = method(self, *args, **kwargs)
        finally:
            _JUDGING.reset(token)
        source = str(res.stats.get("source", "capture"))
        res.findings = refuse_or_warn(frame_findings(res.stats, self.settings, source),
                                      self.settings.output.strict, source)  # fmt: skip
        return res  # (the warnings point at the caller of reconstruct_*)

    return judged


#: What ``forward`` returns: ``"result"`` (cube and valid mask) or ``"cube"`` (the cube alone).
OUTPUTS = ("result", "cube")


class ReconstructionOutput(NamedTuple):
    """``cube (B, M, h, w)`` (NaN or 0 where invalid) and ``valid (B, h, w)`` bool."""

    cube: Tensor
    valid: Tensor


def _eager(fn: Any) -> Any:
    """``torch.compiler.disable(fn)``, applied on the first call (torch's own lazy form of it):
    importing the compiler takes about 70 MiB and a second, which a process that only
    reconstructs files never needs."""
    return torch._disable_dynamo(fn)  # type: ignore[attr-defined]


class HSIReconstructor(nn.Module):
    """Captures → spectral cubes on the bundle's reference frame: one object for tensors, batches
    and networks (``forward``) and for captures and files (:meth:`reconstruct_frame`,
    :meth:`reconstruct_capture`, :meth:`reconstruct_file`), all precomputation done once.

    ``forward(x)``: ``(B, 3, H, W)`` linear RGB (DN above black, on the calibration's exposure
    scale) or ``(B, 1, H, W)`` Bayer mosaics, ``H×W`` the bundle's sensor size, any float dtype,
    on the object's device → :class:`ReconstructionOutput` ``(cube (B, M, h, w), valid (B, h, w))``
    in the input's dtype, or with ``output="cube"`` the cube alone, ``fill_value`` where invalid
    (for ``nn.Sequential``). A bundle calibrated with ``stray_light: subtract`` or
    ``defects: mask`` has its corrections repeated on every frame (:meth:`correct`). The file
    methods add timings, statistics, the drift check (:mod:`hsi_torch.recon.drift`) and the
    per-band standard deviation (``uncertainty``).

    Args:
        bundle: :class:`CalibrationBundle`, its path, or a ready :class:`BundleSensing`.
        settings: every setting (:class:`~hsi_torch.recon.settings.ReconstructSettings`; default:
            the defaults); for gradients use ``solver="active_set"`` or ``admm_iters=N``, and
            ``spatial_iters=N`` with ``prior="tv"``.
        output: ``"result"`` (default) or ``"cube"`` (the module's output form, not a setting).
        fill_value: the value of invalid pixels with ``output="cube"``.
        keep_calibration: keep the bundle's full-frame calibration arrays (``B``, ``phi``,
            ``gain``, ``view_mask``) as persistent buffers, so that ``state_dict`` carries the
            calibration. Default: kept when ``bundle`` is a :class:`CalibrationBundle` (and by
            :meth:`from_bundle`); not for a path (whose precomputation may then come from the disk
            cache without reading the bundle) or a :class:`BundleSensing`. Without them
            ``forward`` and the file methods work the same, and ``load_state_dict`` refuses.
        overrides: flat settings keys changed on ``settings`` (e.g. ``beta=1e3``,
            ``prior="tv"``, ``dtype=torch.float64``); keys that then have no effect are a
            ``UserWarning``. :attr:`settings` holds the result, validated.

    Every ``reconstruct_*`` method judges its result (:func:`_judged`); ``forward`` checks the
    pedestal outside the views (:meth:`check_input`).

    Example:
        >>> rec = HSIReconstructor.from_bundle("calib.npz", beta=1e4).to("cuda")  # doctest: +SKIP
        >>> cube, valid = rec(rgb)          # rgb (B, 3, H, W) on cuda  # doctest: +SKIP
        >>> res = rec.reconstruct_file("scene.tif")  # the same object on a file  # doctest: +SKIP
    """

    #: ``keep_calibration``'s default (``None``: when ``bundle`` is a :class:`CalibrationBundle`)
    default_keep_calibration: bool | None = None
    wavelengths_nm: Tensor
    B: Tensor
    phi: Tensor
    gain: Tensor
    view_mask: Tensor
    valid_region: Tensor
    homographies: Tensor
    pixel_index: Tensor
    model_transmittance: Tensor
    model_gain: Tensor
    model_response: Tensor
    obs_mask: Tensor
    sample_grid: Tensor
    gram: Tensor
    gram_inv: Tensor
    gram_diag: Tensor
    gram_norm: Tensor
    singular: Tensor
    no_data: Tensor

    def __init__(
        self,
        bundle: CalibrationBundle | BundleSensing | str | os.PathLike,
        settings: ReconstructSettings | None = None,
        *,
        output: str = "result",
        fill_value: float = 0.0,
        keep_calibration: bool | None = None,
        **overrides: Any,
    ) -> None:
        super().__init__()
        if output not in OUTPUTS:
            raise ValueError(f"output must be one of {OUTPUTS}, got {output!r}")
        self.output = output
        self.fill_value = float(fill_value)
        s = with_overrides(settings, overrides)
        #: the settings, grouped and frozen (:class:`~hsi_torch.recon.settings.ReconstructSettings`)
        self.settings = s
        # forward returns no standard deviation, so it does not compute one
        self._frame_settings = s.replace(uncertainty=False) if s.uncertainty.enabled else s
        sv = s.solve
        if keep_calibration is None:
            keep_calibration = self.default_keep_calibration
        if keep_calibration is None:
            keep_calibration = isinstance(bundle, CalibrationBundle)
        calib: CalibrationBundle | None = None
        if isinstance(bundle, BundleSensing):
            if keep_calibration:
                raise ValueError("keep_calibration needs the bundle (a CalibrationBundle or its "
                                 "path), not a BundleSensing")  # fmt: skip
            sens = bundle.with_regularisation(sv.beta, sv.diff_order)
        else:
            if keep_calibration:
                calib = load_bundle(bundle)
                bundle = calib
            sens = precompute_sensing(
                bundle, beta=sv.beta, diff_order=sv.diff_order, device=sv.device,
                dtype=torch_dtype(sv.dtype), chunk_size=sv.chunk_size,
                disk_cache=sv.precompute_cache,
            )  # fmt: skip
        check_min_views(sv.min_views, sens.num_views)
        dev, dt = sens.device, sens.dtype
        self._factors: dict[tuple, Tensor] = {}
        self.cfa_pattern = s.input.cfa_pattern or sens.cfa_pattern
        self.beta = sens.beta
        self.diff_order = sens.diff_order
        self.sensor_size = sens.sensor_size
        self.reference_bbox = sens.reference_bbox
        self.exposure_s = sens.exposure_s
        #: what the bundle records about its sensor corrections (veil, hot and dead pixels):
        #: ``forward`` repeats them on every frame, as the calibration did
        self.radiometry = sens.radiometry
        rad = self.radiometry
        self._corrects = rad is not None and (
            rad.veil_index is not None
            or (rad.defect_index is not None and rad.defect_index.size > 0)
        )
        # φ as the bundle holds it (float64): the sensing model is formed from it, so a module
        # rebuilt from a state dict forms the same model bit for bit in any buffer precision
        self._phi64 = (
            None if calib is None else torch.as_tensor(calib.phi, dtype=torch.float64).cpu()
        )
        # calibration products (persistent; None without keep_calibration)
        self.register_buffer("wavelengths_nm", sens.wavelengths_nm.to(dev, dt))
        for name in ("B", "phi", "gain"):
            self.register_buffer(name, None if calib is None else torch.as_tensor(
                getattr(calib, name), device=dev, dtype=dt))  # fmt: skip
        self.register_buffer("view_mask", None if calib is None
                             else torch.as_tensor(calib.view_mask, device=dev))  # fmt: skip
        self.register_buffer("valid_region", sens.valid.to(dev))
        self.register_buffer("homographies", sens.homographies.to(dev))
        self.register_buffer("pixel_index", sens.pixel_index.to(dev))
        # derived per-bundle precomputation: the sensing's own tensors (not saved in state_dict)
        for name, t in _derived(sens).items():
            self.register_buffer(name, t, persistent=False)
        #: the sensing the buffers came from (its radiometry, disk-cache entry, work buffers)
        self._held = sens
        self._sensing_cache: tuple[tuple, BundleSensing] | None = None

    # ------------------------------------------------------------------------------ build
    @classmethod
    def from_bundle(
        cls,
        bundle: CalibrationBundle | str | os.PathLike,
        settings: ReconstructSettings | None = None,
        *,
        output: str = "result",
        fill_value: float = 0.0,
        **overrides: Any,
    ) -> HSIReconstructor:
        """Build from a bundle (object or ``.npz`` path), keeping its calibration arrays
        (``keep_calibration=True``: ``state_dict`` carries them); the arguments are those of the
        class."""
        return cls(load_bundle(bundle), settings, output=output, fill_value=fill_value,
                   keep_calibration=True, **overrides)  # fmt: skip

    def _apply(self, fn: Any, recurse: bool = True) -> HSIReconstructor:  # type: ignore[override]
        dt = self.model_transmittance.dtype
        # the solver factorises in float32 or float64 only: refuse another precision (.half(),
        # .bfloat16(), .to(torch.float16)) before any buffer is converted, leaving the module
        # as it was
        new_dt = fn(torch.zeros((), dtype=dt, device=self.model_transmittance.device)).dtype
        if new_dt not in (torch.float32, torch.float64):
            raise TypeError(
                f"HSIReconstructor runs in float32 or float64, not {new_dt} (the "
                "module is unchanged; its output follows the input's dtype anyway)"
            )
        out = super()._apply(fn, recurse)
        self._sensing_cache = None
        self._factors = {}
        if self.model_transmittance.dtype != dt:  # precision changed: refactorise in the new dtype
            # sampling positions recomputed in float64 from the bundle, not re-rounded
            self.sample_grid = view_sample_grid(
                self.homographies, self.reference_bbox, self.sensor_size, self.pixel_index,
                dtype=self.model_transmittance.dtype,
            )  # fmt: skip
            p = prepare_nnls(
                self._model(), mask=self.obs_mask, beta=self.beta, diff_order=self.diff_order,
                chunk_size=self.settings.solve.chunk_size,
            )  # fmt: skip
            self.gram, self.gram_inv, self.gram_diag, self.gram_norm = (
                p.gram, p.gram_inv, p.gram_diag, p.gram_norm)  # fmt: skip
            self.singular, self.no_data = p.singular, p.no_data
        return out

    # ------------------------------------------------------------------------------ state
    def get_extra_state(self) -> dict[str, Any]:
        """The bundle's geometry and white exposure (plain values, saved in ``state_dict``)."""
        return {
            "sensor_size": list(self.sensor_size),
            "reference_bbox": list(self.reference_bbox),
            "exposure_s": self.exposure_s,
            **({} if self._phi64 is None else {"phi_float64": self._phi64.tolist()}),
        }

    def set_extra_state(self, state: Any) -> None:
        """Set by :meth:`_load_from_state_dict` (checked there); kept for the ``nn.Module``
        protocol."""
        self.exposure_s = state.get("exposure_s") if isinstance(state, dict) else None

    def _load_from_state_dict(
        self,
        state_dict: dict[str, Any],
        prefix: str,
        local_metadata: dict[str, Any],
        strict: bool,
        missing_keys: list[str],
        unexpected_keys: list[str],
        error_msgs: list[str],
    ) -> None:
        """All or nothing: check every entry, rebuild the derived tensors, then swap them in.

        Missing or unexpected keys under ``strict`` load nothing (torch then raises naming
        them); a state dict of another geometry raises :class:`InputError`. With
        ``strict=False`` missing entries keep their current values.
        """
        if self.B is None:
            raise InputError(
                f"{type(self).__name__}.load_state_dict: this object was built without the "
                "bundle's calibration arrays (from a path, a BundleSensing, or as a "
                "Reconstructor); build it with HSIReconstructor.from_bundle to load a state dict"
            )
        names = [n for n in self._buffers if n not in self._non_persistent_buffers_set]
        extra_key = prefix + "_extra_state"
        given = {n: state_dict[prefix + n] for n in names if prefix + n in state_dict}
        missing = [prefix + n for n in names if prefix + n not in state_dict]
        unexpected = [
            k for k in state_dict
            if k.startswith(prefix) and k[len(prefix):] not in names and k != extra_key
            and "." not in k[len(prefix):]
        ]  # fmt: skip
        missing_keys.extend(missing)
        if strict:
            unexpected_keys.extend(unexpected)
            if missing or unexpected:
                return  # nothing changes; load_state_dict raises naming the keys
        new, extra = self._rebuilt(given, state_dict.get(extra_key))
        for name, tensor in new.items():
            setattr(self, name, tensor)
        self.exposure_s = extra.get("exposure_s", self.exposure_s)
        self._phi64 = extra["phi_float64"]
        self._sensing_cache = None

    def _rebuilt(
        self, given: dict[str, Any], extra: Any
    ) -> tuple[dict[str, Tensor], dict[str, Any]]:
        """Checked persistent buffers (``given`` over the current ones) and every derived tensor
        rebuilt from them; raises :class:`InputError` before anything is changed."""
        V, M, h, w = (int(v) for v in self.B.shape)
        geometry = f"{V} views, {M} bands, reference frame {h}x{w}"

        def fail(what: str) -> InputError:
            return InputError(
                f"HSIReconstructor.load_state_dict: a state dict of another geometry: {what}; "
                f"this module has {geometry} (build a new module with "
                "HSIReconstructor.from_bundle for that bundle)"
            )

        shapes = {
            "wavelengths_nm": (M,), "B": (V, M, h, w), "phi": (3, M), "gain": (V, h, w),
            "view_mask": (V, h, w), "valid_region": (h, w), "homographies": (V, 3, 3),
        }  # fmt: skip
        vals: dict[str, Tensor] = {}
        for name, cur in self._buffers.items():
            if name in self._non_persistent_buffers_set or cur is None:
                continue
            v = given.get(name, cur)
            if not isinstance(v, Tensor):
                raise InputError(
                    f"HSIReconstructor.load_state_dict: '{name}' must be a tensor, got "
                    f"{type(v).__name__}"
                )
            if name in shapes and tuple(v.shape) != shapes[name]:
                raise fail(f"'{name}' has shape {tuple(v.shape)}, expected {shapes[name]}")
            if cur.dtype == torch.bool and v.dtype != torch.bool:
                raise InputError(f"HSIReconstructor.load_state_dict: '{name}' must be bool, got "
                                 f"{v.dtype}")  # fmt: skip
            if cur.is_floating_point() and not (
                v.is_floating_point() and bool(torch.isfinite(v).all())
            ):
                raise InputError(f"HSIReconstructor.load_state_dict: '{name}' must be finite "
                                 f"floating point ({v.dtype})")  # fmt: skip
            vals[name] = v.detach().to(device=cur.device, dtype=cur.dtype).clone()
        pix = vals["valid_region"].reshape(-1).nonzero().squeeze(1)
        if not torch.equal(vals["pixel_index"].to(pix.device), pix):
            raise InputError(
                "HSIReconstructor.load_state_dict: 'pixel_index' is not the set of pixels of "
                "'valid_region' (an inconsistent state dict)"
            )
        ex: dict[str, Any] = {}
        if extra is not None:
            if not isinstance(extra, dict):
                raise InputError("HSIReconstructor.load_state_dict: '_extra_state' must be a "
                                 f"dict, got {type(extra).__name__}")  # fmt: skip
            for key, mine in (("sensor_size", self.sensor_size),
                              ("reference_bbox", self.reference_bbox)):  # fmt: skip
                theirs = extra.get(key)
                if theirs is not None and tuple(int(v) for v in theirs) != tuple(mine):
                    raise fail(f"{key} {tuple(int(v) for v in theirs)}, expected {tuple(mine)}")
            exp = extra.get("exposure_s")
            ex["exposure_s"] = float(exp) if isinstance(exp, (int, float)) else None
        # the float64 φ of the extra state when it is the φ buffer (not one changed since)
        phi64 = vals["phi"].to("cpu", torch.float64)
        given64 = extra.get("phi_float64") if isinstance(extra, dict) else None
        if given64 is not None:
            try:
                g = torch.as_tensor(given64, dtype=torch.float64)
            except (TypeError, ValueError, RuntimeError):
                g = None
            if g is not None and g.shape == phi64.shape and torch.equal(
                    g.to(vals["phi"].dtype), vals["phi"].cpu()):  # fmt: skip
                phi64 = g
        ex["phi_float64"] = phi64
        arrays = SimpleNamespace(
            wavelengths_nm=vals["wavelengths_nm"], B=vals["B"], gain=vals["gain"], phi=phi64,
            view_mask=vals["view_mask"], valid=vals["valid_region"],
            view_homographies=vals["homographies"], sensor_size=self.sensor_size,
            reference_bbox=self.reference_bbox,
        )  # fmt: skip
        sens = build_sensing([arrays], beta=self.beta, diff_order=self.diff_order,
                             device=self.gram.device, dtype=self.gram.dtype,
                             chunk_size=self.settings.solve.chunk_size)  # fmt: skip
        vals.update(_derived(sens))
        return vals, ex

    def __getstate__(self) -> dict[str, Any]:
        """Pickling / ``copy.deepcopy``: the derived views are rebuilt on use."""
        state = self.__dict__.copy()
        state["_sensing_cache"] = None
        return state

    # ------------------------------------------------------------------------------ use
    @property
    def num_bands(self) -> int:
        return int(self.model_transmittance.shape[2])

    def _model(self) -> SensingModel:
        return SensingModel(self.model_transmittance, self.model_gain, self.model_response)

    @property
    def frame_size(self) -> tuple[int, int]:
        return int(self.reference_bbox[3]), int(self.reference_bbox[2])

    @property
    def sensing(self) -> BundleSensing:
        """The :class:`BundleSensing` of the buffers: the one the object was built from while
        the buffers are its tensors; after ``.to()``, ``.double()`` or ``load_state_dict`` a view
        of the new buffers (shares their memory; kept while they are unchanged, so its frame work
        buffer is reused between calls)."""
        held = self._held
        mine = _derived(held)
        if (
            all(getattr(self, n) is t for n, t in mine.items())
            and held.exposure_s == self.exposure_s
        ):
            return held
        key = (
            self.gram.device, self.gram.dtype, self.model_transmittance.data_ptr(),
            self.gram.data_ptr(), self.sample_grid.data_ptr(), self.homographies.data_ptr(),
            self.exposure_s,
        )  # fmt: skip
        if self._sensing_cache is None or self._sensing_cache[0] != key:
            self._sensing_cache = (key, self._make_sensing())
        return self._sensing_cache[1]

    def _make_sensing(self) -> BundleSensing:
        model = self._model()
        return dataclasses.replace(
            self._held,
            wavelengths_nm=self.wavelengths_nm.detach().to("cpu", torch.float64),
            homographies=self.homographies, valid=self.valid_region, pixel_index=self.pixel_index,
            model=model, obs_mask=self.obs_mask, beta=self.beta, diff_order=self.diff_order,
            problem=NNLSProblem(
                model, self.obs_mask, self.beta, self.diff_order, self.gram, self.gram_inv,
                self.gram_diag, self.gram_norm, self.singular, self.no_data,
            ),
            exposure_s=self.exposure_s, sample_grid=self.sample_grid, sample_inside=None,
            _problems={}, staging_lock=threading.Lock(), _staging=[], disk_entry=None,
            _drift_static={}, spatial_workspace={},
        )  # fmt: skip

    def _refreshed(self) -> BundleSensing:
        """:attr:`sensing`, after re-mapping the disk-cache entry the buffers came from when it
        changed under its mapping (:func:`~hsi_torch.recon.sensing.refreshed_sensing`; cheap:
        a few ``fstat`` calls, asked before every frame)."""
        held = self._held
        sens = self.sensing
        if sens is held:
            new = refreshed_sensing(held, self.settings.solve.chunk_size)
            if new is not held:
                self._held = sens = new
                for name, t in {
                    "valid_region": new.valid,
                    "homographies": new.homographies,
                    "pixel_index": new.pixel_index,
                    **_derived(new),
                }.items():
                    setattr(self, name, t)
                self._sensing_cache = None
        return sens

    def forward(
        self,
        x: Tensor,
        saturated: Tensor | None = None,
        exposure_scale: Tensor | float | None = None,
    ) -> ReconstructionOutput | Tensor:
        """Reconstruct a batch ``x`` (see the class; ``saturated``: bool, ``x``'s shape;
        ``exposure_scale``: scalar or ``(B,)`` factor on the observations)."""
        if not isinstance(x, Tensor) or x.ndim != 4:
            raise ValueError(
                "x must be a (B, 3, H, W) or (B, 1, H, W) tensor, got "
                f"{tuple(x.shape) if isinstance(x, Tensor) else type(x).__name__}"
            )
        if not x.is_floating_point():
            raise TypeError(f"x must be floating point, got {x.dtype}")
        if tuple(x.shape[-2:]) != tuple(self.sensor_size):
            raise ValueError(
                f"x has sensor size {tuple(x.shape[-2:])} but the bundle expects "
                f"{tuple(self.sensor_size)}"
            )
        if x.device != self.gram.device:
            raise ValueError(
                f"x is on {x.device} but the module is on {self.gram.device}; call .to({x.device})"
            )
        out_dtype = x.dtype
        rgb, sat = prepare_input(x, saturated, self.cfa_pattern)
        if self._corrects:  # no graph break for a bundle without corrections
            rgb, sat = self.correct(rgb, sat)
        cube, valid = self.reconstruct_prepared(rgb, sat, exposure_scale)
        if self.output == "cube":
            fill = torch.full((), self.fill_value, dtype=cube.dtype, device=cube.device)
            return torch.where(valid.unsqueeze(1), cube, fill).to(out_dtype)
        return ReconstructionOutput(cube.to(out_dtype), valid)

    @_eager
    def correct(self, rgb: Tensor, saturated: Tensor | None) -> tuple[Tensor, Tensor | None]:
        """The bundle's sensor corrections on ``(B, 3, H, W)`` linear RGB and its saturation
        mask (:func:`~hsi_torch.recon.corrections.correct_frames`): for a bundle calibrated with
        ``stray_light: subtract`` the veil fitted on each frame's unreached pixels is subtracted
        (a constant for autograd: the gradient passes through unchanged); for ``defects: mask``
        the hot and dead pixels are marked saturated. Other bundles: returned as given."""
        rgb, saturated, _ = correct_frames(rgb, saturated, self.radiometry)
        return rgb, saturated

    @_eager
    def reconstruct_prepared(
        self, rgb: Tensor, saturated: Tensor | None, exposure_scale: Tensor | float | None
    ) -> tuple[Tensor, Tensor]:
        """Warp, observations, exact solve and assembly of ``(B, 3, H, W)`` linear RGB (the part
        of :meth:`forward` that ``torch.compile`` leaves to eager mode; no statistics, no
        timing)."""
        self.check_input(rgb, saturated)
        out = reconstruct_frame(self._refreshed(), rgb, self._frame_settings, saturated,
                                scale=exposure_scale, stats=False)  # fmt: skip
        return out.cube, out.valid

    def check_input(self, rgb: Tensor, saturated: Tensor | None = None) -> None:
        """The input convention's guard (``(B, 3, H, W)`` linear RGB must be DN above black):
        :func:`hsi_torch.recon.checks.batch_pedestal_findings`, warned or refused. Run inside
        :meth:`reconstruct_prepared`, so ``torch.compile`` sees no extra graph break."""
        found = batch_pedestal_findings(rgb, self.radiometry, self.settings,
                                        "HSIReconstructor input", saturated)  # fmt: skip
        refuse_or_warn(found, self.settings.output.strict, stacklevel=3)

    # ------------------------------------------------------------------------------ files
    def sampling_factor(self, layout: str, cfa_pattern: str | None = None) -> Tensor:
        """``(P, 3V)`` variance factor of the observations for captures made as ``layout``
        (:func:`~hsi_torch.recon.uncertainty.sampling_variance_factor`); kept per layout."""
        sens = self.sensing
        key = (layout, cfa_pattern if layout == "bayer" else None, sens.dtype, sens.device)
        if key not in self._factors:
            self._factors[key] = sampling_variance_factor(
                sens.grid(), sens.sensor_size, layout, cfa_pattern
            )  # type: ignore[arg-type]
        return self._factors[key]

    @_judged
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
        warm: WarmStart | None = None,
        sensing: BundleSensing | None = None,
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
            warm: the previous frame's solver state (:class:`~hsi_torch.recon.frame.WarmStart`;
                a sequence, :mod:`hsi_torch.recon.sequence`), read and replaced by this frame's.
            sensing: solve with this :class:`BundleSensing` instead of the object's own (the same
                bundle's geometry, e.g. corrected for a drift the caller tracked over a sequence;
                the statistics then say ``drift.corrected``).

        Returns:
            :class:`ReconstructionResult`.
        """
        own = self._refreshed()  # the disk-cache entry changed under its mapping?
        sens = own if sensing is None else sensing
        t0 = time.perf_counter()
        pattern = cfa_pattern or sens.cfa_pattern
        img, sat, corr = prepare_image(sens, image, saturated, pattern, source,
                                       bundle_corrections)
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
            if drift_decision(drift, motion_px, reg.refine, reg.warn_px, source):
                sens = corrected_sensing(
                    sens, drift.sensor_shift_px, drift.sensor_rotation_deg or 0.0
                )
            t_drift = time.perf_counter() - t1
        with torch.no_grad():
            out = reconstruct_frame(
                sens, img.unsqueeze(0), settings, None if sat is None else sat.unsqueeze(0),
                scale=None if scale == 1.0 else scale, sampling_factor=factor, warm=warm,
            )  # fmt: skip
        cube, valid, stats, t = out.cube, out.valid, out.stats, out.timings
        st = stats[0]
        ill = illuminant_finding(cube[0], valid[0], sens.wavelengths_nm, source=source)
        if ill is not None:  # the scene's light against the white reference's (a finding)
            st["illuminant"] = ill.to_dict()
        st["exposure_scale"] = scale
        st["source"] = source
        st.update(corr)
        timings = {"demosaic": t_demosaic, **t} if image.shape[0] == 1 else dict(t)
        if drift is not None:
            reg = settings.registration
            st["drift"] = {
                **drift.to_dict(),
                "corrected": sens is not own,
                "sensor_motion_px": round(motion_px, 3),
                "refine_registration": reg.refine,
            }
            said = drift_finding(st["drift"], reg.refine, reg.warn_px, source,
                                 st.get("fit_residual"), settings.output.fit_residual_warning)
            st["drift"]["finding"] = None if said is None else said.to_dict()
            timings["drift"] = t_drift
        timings["total"] = time.perf_counter() - t0
        std = None if out.std is None else out.std[0]
        return ReconstructionResult(cube[0], valid[0], sens.wavelengths_nm, st, timings, std)

    @_judged
    def reconstruct_capture(
        self,
        capture: Any,
        *,
        warm: WarmStart | None = None,
        sensing: BundleSensing | None = None,
        stats: dict[str, Any] | None = None,
    ) -> ReconstructionResult:
        """Reconstruct a :class:`hsi_torch.io.LinearCapture` (``image``, ``saturated``, the
        exposure from ``metadata``: ``exposure_s``, else the simulator's relative ``exposure``,
        compared with the bundle's white reference in the same unit; the statistics say
        ``radiometric_scale`` and ``exposure_note``, :func:`hsi_torch.recon.checks.exposure_info`).
        ``warm``, ``sensing``: as :meth:`reconstruct_frame` (a frame of a sequence); ``stats``:
        statistics added to the result's before it is judged (the reading's checks, see
        :meth:`reconstruct_file`).
        """
        src = str(getattr(capture, "path", "capture"))
        corr = apply_bundle_corrections(capture, self.sensing.radiometry)
        try:
            t, exp_stats, layout, pattern = self.capture_frame_arguments(capture)
            res = self.reconstruct_frame(
                capture.image, capture.saturated, exposure_s=t,
                source=src, raw_layout=layout, cfa_pattern=pattern, bundle_corrections=False,
                warm=warm, sensing=sensing,
            )  # fmt: skip
            res.stats.update(exp_stats)
            res.stats.update(corr)
            if stats:
                res.stats.update(stats)
            return res
        except InputError as exc:
            if "'exposure_s'" in str(exc) and getattr(capture, "path", None) is not None:
                raise FileFormatError(f"{src}: {exc}") from None  # the file's metadata at fault
            raise

    def capture_frame_arguments(
        self, capture: Any
    ) -> tuple[float | None, dict[str, Any], str, str | None]:
        """What a :class:`hsi_torch.io.LinearCapture` gives :meth:`reconstruct_frame`: its
        exposure (s, :func:`hsi_torch.recon.checks.exposure_info`, with that function's
        statistics), its raw layout (``"rgb"``, ``"bayer"`` or ``"half"``: a mosaic demosaiced by
        the reader, whose noise went through the demosaic) and its CFA pattern."""
        meta = capture.metadata
        layout, pattern = "rgb", None
        if meta.get("kind") == "bayer":
            layout = "half" if meta.get("demosaic") == "half" else "bayer"
            pattern = meta.get("cfa_pattern")
        sens = self.sensing
        t, exp_stats = exposure_info(meta, sens.radiometry, sens.exposure_s,
                                     self.settings.input.exposure_correction)  # fmt: skip
        return t, exp_stats, layout, pattern

    @_judged
    def reconstruct_file(
        self,
        path: str | os.PathLike,
        *,
        page: int | None = None,
        warm: WarmStart | None = None,
        sensing: BundleSensing | None = None,
        **overrides: Any,
    ) -> ReconstructionResult:
        """Read a capture (:meth:`read_capture`) and reconstruct it (``page``: one page of a
        multi-page TIFF; ``overrides``: flat keys of the ``input`` group for this file, e.g.
        ``demosaic="half"``; ``warm``, ``sensing``: as :meth:`reconstruct_frame`).
        ``timings["load"]`` is the read (and demosaic)."""
        cap, checks, t_load = self.read_capture(path, page=page, **overrides)
        return with_load_time(
            self.reconstruct_capture(cap, warm=warm, sensing=sensing, stats=checks), t_load
        )

    def read_capture(
        self, path: str | os.PathLike, *, page: int | None = None, **overrides: Any
    ) -> tuple[Any, dict[str, Any], float]:
        """The reading half of :meth:`reconstruct_file`: the capture read
        (:func:`hsi_torch.io.read_any`, the ``input`` group over the file's metadata, what the
        file does not say from :meth:`capture_defaults`), its full-resolution size checked (the
        sensor size; twice it for Bayer files with ``demosaic="half"``), corrected as the
        bundle's calibration was, and measured (:func:`hsi_torch.recon.checks.measure_capture`).

        Returns:
            the :class:`hsi_torch.io.LinearCapture`, the statistics of the reading's checks
            (with ``metadata``) and the time it took (s).
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
        black = read.black_level  # a tuple in the settings, a list for read_any
        cap = read_any(
            p, expected_size=sens.sensor_size if read.demosaic == "bilinear" else None,
            demosaic=read.demosaic, cfa_pattern=read.cfa_pattern,
            black_level=list(black) if isinstance(black, tuple) else black,
            white_level=read.white_level, dtype=sens.dtype,
            device=sens.device, defaults=self.capture_defaults(read.exposure_s), page=page,
        )  # fmt: skip
        if read.demosaic == "half":
            _check_half_size(cap, sens, p)
        apply_bundle_corrections(cap, sens.radiometry)  # before the pedestal is measured
        checks = measure_capture(cap, sens.radiometry, sensor_size=sens.sensor_size)
        checks["metadata"] = cap.metadata
        _sync(sens.device)
        return cap, checks, time.perf_counter() - t0

    def capture_defaults(self, exposure_s: float | None = None) -> CaptureDefaults:
        """What :func:`~hsi_torch.io.read_any` gives a file that does not say: the bundle's
        black level (R, G, B, as its calibration subtracted) and CFA pattern, and
        ``exposure_s`` (default: the settings')."""
        sens = self.sensing
        rad = sens.radiometry
        t = self.settings.input.exposure_s if exposure_s is None else exposure_s
        return CaptureDefaults(black_level_rgb=None if rad is None else rad.black_level_rgb,
                               cfa_pattern=sens.cfa_pattern, exposure_s=t)  # fmt: skip

    def extra_repr(self) -> str:
        h, w = self.frame_size
        s = self.settings
        return (f"views={self.homographies.shape[0]}, bands={self.num_bands}, "
                f"pixels={self.pixel_index.shape[0]}, sensor={self.sensor_size}, frame=({h}, {w}), "
                f"beta={self.beta:g}, diff_order={self.diff_order}, solver={s.solve.solver!r}"
                + (f", prior='tv', lam={s.prior.lam}" if s.prior.kind == "tv" else "")
                + (f", output='cube', fill_value={self.fill_value:g}" if self.output == "cube"
                   else ""))  # fmt: skip


class Reconstructor(HSIReconstructor):
    """:class:`HSIReconstructor` built for files: the same class, the same methods, ``forward``
    included, without the bundle's full-frame calibration arrays (``keep_calibration=False``
    by default: a bundle given as a path is then never read when its precomputation is in the
    disk cache, and its arrays are freed after the build).

    Example:
        >>> rec = Reconstructor("calib.npz", beta=1e4)  # doctest: +SKIP
        >>> res = rec.reconstruct_file("scene.tif")  # doctest: +SKIP
        >>> res.cube.shape, res.valid.sum(), res.timings  # doctest: +SKIP
    """

    #: ``keep_calibration``'s default: never
    default_keep_calibration: bool | None = False


def prepare_image(
    sens: BundleSensing, image: Tensor, saturated: Tensor | None, pattern: str | None,
    source: str, corrections: bool = True,
) -> tuple[Tensor, Tensor | None, dict[str, Any]]:
    """A frame as the front door solves it: ``image`` ``(3, H, W)`` RGB or ``(1, H, W)`` mosaic
    checked against the bundle's sensor size (errors name ``source``), on ``sens``'s device,
    demosaiced with ``pattern`` (:func:`~hsi_torch.recon.frame.prepare_input`) and, with
    ``corrections``, corrected (:func:`correct_frames`). Returns the image, the saturation mask
    and the corrections' statistics (empty without them)."""
    if not isinstance(image, Tensor) or image.ndim != 3:
        raise ValueError(
            f"{source}: image must be a (3, H, W) or (1, H, W) tensor, got "
            f"{tuple(image.shape) if isinstance(image, Tensor) else type(image).__name__}"
        )
    sens.check_capture_size(image.shape, source)
    img = image.to(device=sens.device)
    sat = None if saturated is None else saturated.to(device=sens.device)
    img, sat = prepare_input(img, sat, pattern)
    corr: dict[str, Any] = {}
    if corrections:
        img, sat, corr = correct_frames(img, sat, sens.radiometry)
    return img, sat, corr


def with_load_time(res: ReconstructionResult, load_s: float) -> ReconstructionResult:
    """``res`` with the file's read (s) as its first timing, ``"load"``, and in its total."""
    res.timings = {"load": load_s, **res.timings}
    res.timings["total"] += load_s
    return res


def _derived(sens: BundleSensing) -> dict[str, Tensor]:
    """The buffers made from the per-bundle precomputation, by name: ``sens``'s own tensors."""
    p = sens.problem
    return {
        "model_transmittance": sens.model.transmittance, "model_gain": sens.model.gain,
        "model_response": sens.model.response, "obs_mask": sens.obs_mask,
        "sample_grid": sens.grid(), "gram": p.gram, "gram_inv": p.gram_inv,
        "gram_diag": p.gram_diag, "gram_norm": p.gram_norm, "singular": p.singular,
        "no_data": p.no_data,
    }  # fmt: skip


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
