"""``HSIReconstructor``: the whole reconstruction as a ``torch.nn.Module``.

All bundle tensors (``B``, ``phi``, ``gain``, masks, homographies) and the per-bundle
precomputation (the factored sensing model of the reconstructed pixels, static masks, the views'
sampling grid, the solver's Gram matrices and inverses) are
registered buffers, so ``.to(device)``/``.cuda()`` move everything and ``.double()`` switches the
precision (the factorisation is then recomputed in the new dtype). The forward pass is exactly
:func:`hsi_torch.recon.frame.reconstruct_frame` — the same code as the file pipeline, with the
same :class:`~hsi_torch.recon.settings.ReconstructSettings`.

Differentiable with respect to the input: see :mod:`hsi_torch.recon.frame` (straight-through
reduced solve on the solver's free set for the active-set method; fixed-iteration ADMM is
differentiated through its iterations).

``torch.compile``: the forward pass does no timing and computes no statistics (no ``.item()``);
the input checks and the Bayer demosaic are traced, and the warp + observations + solve +
assembly run in :meth:`HSIReconstructor.reconstruct_prepared`, wrapped with
``torch.compiler.disable``: the exact active-set solver's data-dependent control flow (which
pixels need pivoting, grouped by the size of their zero set) would otherwise break the graph
dozens of times and recompile for every frame. A network around the module therefore compiles
with one graph break at the solver, and the result equals the eager one (tested).

``state_dict()`` holds the calibration (``B``, ``phi``, ``gain``, masks, homographies, wavelengths,
the reconstructed pixels) and, as extra state, the sensor size, reference-frame box, white
exposure and ``phi`` in the bundle's float64. ``load_state_dict`` checks the whole state dict
first and then rebuilds everything derived from it (the factored sensing model, observation mask,
sampling grid, Gram matrices and their inverses) with the build of
:func:`hsi_torch.recon.sensing.build_sensing` that :meth:`HSIReconstructor.from_bundle` uses,
so the output is bit for bit that of a module built from the other bundle (float32 and
float64, tested); a
state dict of another geometry (views, bands, reference frame, sensor) raises
:class:`~hsi_torch.errors.InputError` and leaves the module as it was.
"""

from __future__ import annotations

import os
from types import SimpleNamespace
from typing import Any, NamedTuple

import torch
from torch import Tensor, nn

from hsi_torch.devices import torch_dtype
from hsi_torch.errors import InputError
from hsi_torch.findings import RefusedError, refusals, warn_findings
from hsi_torch.forward_model import SensingModel
from hsi_torch.io.bundle import CalibrationBundle
from hsi_torch.optics.geometry import view_sample_grid
from hsi_torch.recon.checks import batch_pedestal_findings
from hsi_torch.recon.corrections import correct_frames
from hsi_torch.recon.frame import check_min_views, prepare_input, reconstruct_frame
from hsi_torch.recon.nnls import NNLSProblem, prepare_nnls
from hsi_torch.recon.sensing import BundleSensing, build_sensing, load_bundle, precompute_sensing
from hsi_torch.recon.settings import ReconstructSettings, with_overrides

__all__ = ["HSIReconstructor", "ReconstructionOutput", "OUTPUTS"]

#: What ``forward`` returns: ``"result"`` (cube and valid mask) or ``"cube"`` (the cube alone).
OUTPUTS = ("result", "cube")


class ReconstructionOutput(NamedTuple):
    """``cube (B, M, h, w)`` (NaN or 0 where invalid) and ``valid (B, h, w)`` bool."""

    cube: Tensor
    valid: Tensor


class HSIReconstructor(nn.Module):
    """Linear RGB (or Bayer) captures → spectral cubes on the bundle's reference frame.

    Build with :meth:`from_bundle`. ``forward(x)`` takes ``(B, 3, H, W)`` linear RGB (DN above
    black, on the calibration's exposure scale) or ``(B, 1, H, W)`` Bayer mosaics, ``H×W`` the
    bundle's sensor size, and returns :class:`ReconstructionOutput` ``(cube (B, M, h, w),
    valid (B, h, w))`` — or, built with ``output="cube"``, the cube tensor alone with invalid
    pixels set to ``fill_value``, so that it drops into ``nn.Sequential``. The input may have any
    float dtype; the output has the input's dtype. The input must be on the module's device.
    A bundle calibrated with ``stray_light: subtract`` or ``defects: mask`` has its corrections
    repeated on every frame (:meth:`correct`), as ``hsi-torch reconstruct`` does.

    Example:
        >>> rec = HSIReconstructor.from_bundle("calib.npz", beta=1e4).to("cuda")  # doctest: +SKIP
        >>> cube, valid = rec(rgb)          # rgb (B, 3, H, W) on cuda  # doctest: +SKIP
        >>> loss = cube[valid.unsqueeze(1).expand_as(cube)].mean()  # doctest: +SKIP
        >>> loss.backward()  # doctest: +SKIP
        >>> net = nn.Sequential(HSIReconstructor.from_bundle("calib.npz", output="cube",
        ...                                                  fill_value=0.0),
        ...                     nn.Conv2d(25, 8, 3))  # doctest: +SKIP
    """

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
        sensing: BundleSensing,
        bundle: CalibrationBundle,
        settings: ReconstructSettings | None = None,
        *,
        output: str = "result",
        fill_value: float = 0.0,
        **overrides: Any,
    ) -> None:
        super().__init__()
        if output not in OUTPUTS:
            raise ValueError(f"output must be one of {OUTPUTS}, got {output!r}")
        self.output = output
        self.fill_value = float(fill_value)
        s = with_overrides(settings, overrides)
        #: the settings, grouped and frozen (β and the difference order: the sensing's; the
        #: module returns no standard deviation, so ``uncertainty`` is not computed)
        self.settings = s
        self._frame_settings = s.replace(uncertainty=False) if s.uncertainty.enabled else s
        dev, dt = sensing.device, sensing.dtype
        check_min_views(s.solve.min_views, sensing.num_views)
        self.cfa_pattern = s.input.cfa_pattern or sensing.cfa_pattern
        self.beta = sensing.beta
        self.diff_order = sensing.diff_order
        self.sensor_size = sensing.sensor_size
        self.reference_bbox = sensing.reference_bbox
        self.exposure_s = sensing.exposure_s
        # φ as the bundle holds it (float64): the sensing model is formed from it, so a module
        # rebuilt from a state dict forms the same model bit for bit in any buffer precision
        self._phi64 = torch.as_tensor(bundle.phi, dtype=torch.float64).cpu()
        #: what the bundle records about its sensor corrections (veil, hot and dead pixels):
        #: ``forward`` repeats them on every frame, as the calibration did
        self.radiometry = sensing.radiometry
        rad = self.radiometry
        self._corrects = rad is not None and (
            rad.veil_index is not None
            or (rad.defect_index is not None and rad.defect_index.size > 0))
        # calibration products (persistent)
        self.register_buffer("wavelengths_nm", sensing.wavelengths_nm.to(dev, dt))
        self.register_buffer("B", torch.as_tensor(bundle.B, device=dev, dtype=dt))
        self.register_buffer("phi", torch.as_tensor(bundle.phi, device=dev, dtype=dt))
        self.register_buffer("gain", torch.as_tensor(bundle.gain, device=dev, dtype=dt))
        self.register_buffer("view_mask", torch.as_tensor(bundle.view_mask, device=dev))
        self.register_buffer("valid_region", sensing.valid.to(dev))
        self.register_buffer("homographies", sensing.homographies.to(dev))
        self.register_buffer("pixel_index", sensing.pixel_index.to(dev))
        # derived per-bundle precomputation (not saved in state_dict; rebuilt by from_bundle)
        p = sensing.problem
        self.register_buffer("model_transmittance", sensing.model.transmittance, persistent=False)
        self.register_buffer("model_gain", sensing.model.gain, persistent=False)
        self.register_buffer("model_response", sensing.model.response, persistent=False)
        self.register_buffer("obs_mask", sensing.obs_mask, persistent=False)
        self.register_buffer("sample_grid", sensing.grid(), persistent=False)
        self.register_buffer("gram", p.gram, persistent=False)
        self.register_buffer("gram_inv", p.gram_inv, persistent=False)
        self.register_buffer("gram_diag", p.gram_diag, persistent=False)
        self.register_buffer("gram_norm", p.gram_norm, persistent=False)
        self.register_buffer("singular", p.singular, persistent=False)
        self.register_buffer("no_data", p.no_data, persistent=False)
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
        """Build from a bundle (object or ``.npz`` path).

        Args:
            settings: every reconstruction setting
                (:class:`~hsi_torch.recon.settings.ReconstructSettings`; default: the
                defaults): β and the difference order, the solver (``"active_set"``: exact,
                gradient of the final reduced solve; ``"admm"`` with ``admm_iters=N``: exactly
                ``N`` differentiable iterations), ``cfa_pattern`` for ``(B, 1, H, W)`` Bayer
                inputs (default: the bundle's), ``device``/``dtype`` of the buffers (movable
                later with ``.to``), the prior (``prior="tv"``; for gradients give
                ``spatial_iters=N``).
            output: ``"result"`` (default): ``forward`` returns
                :class:`ReconstructionOutput` ``(cube, valid)``; ``"cube"``: the cube tensor
                alone, ``(B, M, h, w)``, invalid pixels set to ``fill_value`` — the form for
                ``nn.Sequential(rec, nn.Conv2d(M, …))``. Not a reconstruction setting: the
                module's output form.
            fill_value: the value of invalid pixels with ``output="cube"`` (default 0.0).
            overrides: flat settings keys changed on ``settings`` (e.g. ``beta=1e3``,
                ``dtype=torch.float64``; :func:`~hsi_torch.recon.settings.with_overrides`).
        """
        s = with_overrides(settings, overrides)
        b = load_bundle(bundle)
        sens = precompute_sensing(
            b, beta=s.solve.beta, diff_order=s.solve.diff_order, device=s.solve.device,
            dtype=torch_dtype(s.solve.dtype), chunk_size=s.solve.chunk_size,
        )  # fmt: skip
        return cls(sens, b, s, output=output, fill_value=fill_value)

    def _apply(self, fn: Any, recurse: bool = True) -> HSIReconstructor:  # type: ignore[override]
        dt = self.model_transmittance.dtype
        # the solver factorises in float32 or float64 only: refuse another precision (.half(),
        # .bfloat16(), .to(torch.float16)) before any buffer is converted, leaving the module
        # as it was
        new_dt = fn(torch.zeros((), dtype=dt, device=self.model_transmittance.device)).dtype
        if new_dt not in (torch.float32, torch.float64):
            raise TypeError(f"HSIReconstructor runs in float32 or float64, not {new_dt} (the "
                            "module is unchanged; its output follows the input's dtype anyway)")
        out = super()._apply(fn, recurse)
        self._sensing_cache = None
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
                p.gram, p.gram_inv, p.gram_diag, p.gram_norm
            )
            self.singular, self.no_data = p.singular, p.no_data
        return out

    # ------------------------------------------------------------------------------ state
    def get_extra_state(self) -> dict[str, Any]:
        """The bundle's geometry and white exposure (plain values, saved in ``state_dict``)."""
        return {
            "sensor_size": list(self.sensor_size),
            "reference_bbox": list(self.reference_bbox),
            "exposure_s": self.exposure_s,
            "phi_float64": self._phi64.tolist(),
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
            if cur.is_floating_point() and not (v.is_floating_point() and
                                                bool(torch.isfinite(v).all())):
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
        model, obs, grid, p = sens.model, sens.obs_mask, sens.grid(), sens.problem
        vals.update(model_transmittance=model.transmittance, model_gain=model.gain,
                    model_response=model.response, obs_mask=obs, sample_grid=grid,
                    gram=p.gram, gram_inv=p.gram_inv, gram_diag=p.gram_diag,
                    gram_norm=p.gram_norm, singular=p.singular, no_data=p.no_data)  # fmt: skip
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

    def sensing(self) -> BundleSensing:
        """The :class:`BundleSensing` view of the buffers (shares their memory; kept while the
        buffers are unchanged, so its frame work buffer is reused between calls)."""
        key = (
            self.gram.device, self.gram.dtype, self.model_transmittance.data_ptr(),
            self.gram.data_ptr(),
            self.sample_grid.data_ptr(), self.homographies.data_ptr(), self.cfa_pattern,
        )  # fmt: skip
        if self._sensing_cache is None or self._sensing_cache[0] != key:
            self._sensing_cache = (key, self._make_sensing())
        return self._sensing_cache[1]

    def _make_sensing(self) -> BundleSensing:
        model = self._model()
        return BundleSensing(
            wavelengths_nm=self.wavelengths_nm.detach().to("cpu", torch.float64),
            sensor_size=self.sensor_size,
            reference_bbox=self.reference_bbox,
            homographies=self.homographies,
            valid=self.valid_region,
            pixel_index=self.pixel_index,
            model=model,
            obs_mask=self.obs_mask,
            beta=self.beta,
            diff_order=self.diff_order,
            problem=NNLSProblem(
                model, self.obs_mask, self.beta, self.diff_order, self.gram, self.gram_inv,
                self.gram_diag, self.gram_norm, self.singular, self.no_data,
            ),  # fmt: skip
            exposure_s=self.exposure_s,
            cfa_pattern=self.cfa_pattern,
            sample_grid=self.sample_grid,
        )

    def forward(
        self,
        x: Tensor,
        saturated: Tensor | None = None,
        exposure_scale: Tensor | float | None = None,
    ) -> ReconstructionOutput | Tensor:
        """Reconstruct a batch.

        Args:
            x: ``(B, 3, H, W)`` linear RGB or ``(B, 1, H, W)`` Bayer, float, on this module's
                device, in DN above black (the black level subtracted, as the calibration
                did); a pedestal left in is a :class:`~hsi_torch.findings.CaptureWarning` or,
                far beyond its limit, :class:`~hsi_torch.findings.RefusedError`
                (:meth:`check_input`).
            saturated: optional bool mask of ``x``'s shape (saturated samples are masked).
            exposure_scale: optional scalar or ``(B,)`` factor on the observations.

        Returns:
            :class:`ReconstructionOutput` ``(cube (B, M, h, w), valid (B, h, w))``; built with
            ``output="cube"``: the cube alone, ``(B, M, h, w)``, ``fill_value`` where invalid.
        """
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
                f"x is on {x.device} but the module is on {self.gram.device}; call "
                f".to({x.device})"
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

    @torch.compiler.disable
    def correct(self, rgb: Tensor, saturated: Tensor | None) -> tuple[Tensor, Tensor | None]:
        """The bundle's sensor corrections on ``(B, 3, H, W)`` linear RGB and its saturation
        mask (:func:`~hsi_torch.recon.corrections.correct_frames`): for a bundle calibrated with
        ``stray_light: subtract`` the veil fitted on each frame's unreached pixels is subtracted
        (a constant for autograd: the gradient passes through unchanged); for ``defects: mask``
        the hot and dead pixels are marked saturated. Other bundles: returned as given."""
        rgb, saturated, _ = correct_frames(rgb, saturated, self.radiometry)
        return rgb, saturated

    @torch.compiler.disable
    def reconstruct_prepared(
        self, rgb: Tensor, saturated: Tensor | None, exposure_scale: Tensor | float | None
    ) -> tuple[Tensor, Tensor]:
        """Warp, observations, exact solve and assembly of ``(B, 3, H, W)`` linear RGB (the part
        of :meth:`forward` that ``torch.compile`` leaves to eager mode; no statistics, no
        timing)."""
        self.check_input(rgb, saturated)
        out = reconstruct_frame(self.sensing(), rgb, self._frame_settings, saturated,
                                scale=exposure_scale, stats=False)  # fmt: skip
        return out.cube, out.valid

    def check_input(self, rgb: Tensor, saturated: Tensor | None = None) -> None:
        """The input convention's guard: ``(B, 3, H, W)`` linear RGB must be DN above black.
        The sensor pixels outside every view (the bundle's ``radiometry.outside_index``) must
        then read ≈ 0; a pedestal above its limit is a :class:`~hsi_torch.findings.CaptureWarning`
        (``capture.pedestal``), and beyond ``pedestal_refuse_factor`` times it (e.g. the
        simulator's ``expose()`` DN with their 512 DN black level: cubes 5.5x too bright)
        :class:`~hsi_torch.findings.RefusedError`; under ``strict`` the warning refuses too
        (:func:`hsi_torch.recon.checks.batch_pedestal_findings`; saturated samples left out).
        A gather of a few thousand pixels and one ``(B, 3)`` copy to the host per call; run inside
        :meth:`reconstruct_prepared`, so ``torch.compile`` sees no extra graph break."""
        found = batch_pedestal_findings(rgb, self.radiometry, self.settings,
                                        "HSIReconstructor input", saturated)  # fmt: skip
        refused = refusals(found)
        if refused:
            raise RefusedError("; ".join(f.text() for f in refused), found)
        warn_findings(found, stacklevel=3)

    def extra_repr(self) -> str:
        h, w = self.frame_size
        return (
            f"views={self.homographies.shape[0]}, bands={self.num_bands}, "
            f"pixels={self.pixel_index.shape[0]}, sensor={self.sensor_size}, frame=({h}, {w}), "
            f"beta={self.beta:g}, diff_order={self.diff_order}, "
            f"solver={self.settings.solve.solver!r}"
            + (f", prior='tv', lam={self.settings.prior.lam}" if self.settings.prior.kind == "tv"
               else "")
            + (f", output='cube', fill_value={self.fill_value:g}" if self.output == "cube" else "")
        )
