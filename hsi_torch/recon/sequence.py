"""Sequences: frames of one bundle reconstructed in order, each using what the last one left.

:class:`SequenceReconstructor` wraps the front door (:class:`~hsi_torch.recon.pipeline.
Reconstructor`, its one frame function) and carries three things from frame to frame, each set
in the settings' ``sequence`` group (:class:`~hsi_torch.recon.settings.SequenceSettings`):

* **Warm starts** (``warm_start``, ``warm_spatial``, ``warm_noise``; only ``warm_spatial`` is
  on by default, see ``docs/sequences.md`` for why; :class:`~hsi_torch.recon.frame.WarmStart`):
  the per-pixel active-set solve of the pixels that pivot starts from the previous frame's zero
  set (the same KKT points as cold solves, in another number of rounds); the spatial prior's
  ADMM starts from the previous frame's state (answer and scaled dual times the frame's gain on
  the pixels whose observations did not move, this frame's per-pixel solution and its
  multiplier elsewhere, the TV prox's dual) and checks its stopping rule every iteration (the
  same optimum to the solver's tolerance; the per-pixel problem solved only on the moved pixels
  and the noise estimate's samples); ``warm_noise`` also reuses the last estimated noise level
  (so ``λ``) while the light holds (a deviation from the noise rule: the optimum of the problem
  with that ``λ``).
* **A temporal prior** (``temporal="quadratic"``, per-pixel solve only): each pixel solves
  ``min_{s≥0} ‖W(As − y)‖² + β‖Ds‖² + w·‖s − s_prev‖²_G`` with ``s_prev`` the previous frame's
  answer and ``‖v‖²_G = vᵀGv`` the pixel's own data metric (``G = AᵀWA + βDᵀD``), where the data
  say the pixel did not change: the previous answer counts as ``w`` (``temporal_weight``) more
  frames of data, in every direction as well determined as the data make it. The minimiser is
  the per-pixel NNLS solution for ``b̃ = (b + wGs_prev)/(1 + w)`` with the same ``G``, so the
  bundle's factorisation is reused and the exact active-set solver gives it. The **motion
  gate**: a pixel is static when its previous answer fits this frame's observations at most
  ``temporal_gate · |F_p| · σ̂_p²`` worse than its own per-pixel fit (``|F_p|`` its free bands;
  ``σ̂_p²`` the pixel's noise variance: its own fit residual per spare observation, so shot noise
  that grows with brightness does not read as motion, and at least the frame's pooled ``σ̂²`` of
  the spatial prior's rule, :func:`~hsi_torch.recon.spatial.noise.frame_noise_level`, for pixels
  with few spare observations). Moving pixels, pixels whose observation mask changed and the
  first frame keep their per-pixel answer.
* **Drift as a path** (``drift_track``): every frame's sensor motion is measured
  (:func:`~hsi_torch.recon.drift.estimate_drift`) and a straight line in time is fitted to the
  last ``drift_window`` measurements (least squares in shift x, y and rotation); the frame is
  corrected with the line's value at its time (:func:`~hsi_torch.recon.drift.corrected_sensing`),
  which averages the per-frame measurement noise. A measurement farther than ``drift_jump_px``
  from the line's prediction is a **jump**: a ``drift.jump`` :class:`~hsi_torch.findings.Finding`
  (warning), and the path restarts from that frame. A frame whose drift cannot be measured
  (refused) is corrected with the prediction (a ``drift.unmeasured`` finding, info).

The iterator form (:meth:`SequenceReconstructor.reconstruct_sequence`, also ``__call__``) takes
frames as tensors ``(C, H, W)``, ``(image, saturated)`` pairs or objects with ``image`` and
``saturated`` (a :class:`~hsi_torch.io.LinearCapture`, a simulated
:class:`~hsi_torch.simulate.motion.SequenceFrame`) and yields one
:class:`~hsi_torch.recon.pipeline.ReconstructionResult` per frame, lazily, so it can sit inside a
torch data pipeline. Each result's ``stats["sequence"]`` holds the frame index, whether it was
warm-started, the drift path and the temporal gate's counts; ``stats["findings"]`` the frame's
findings as dicts.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Iterable, Iterator
from typing import Any

import numpy as np
import torch
from torch import Tensor

from hsi_torch.findings import Finding
from hsi_torch.io.bundle import CalibrationBundle
from hsi_torch.recon.checks import exposure_scale
from hsi_torch.recon.drift import corrected_sensing, estimate_drift
from hsi_torch.recon.frame import (
    WarmStart,
    assemble_cube,
    observations_from_samples,
    sample_views,
)
from hsi_torch.recon.nnls import NNLSProblem
from hsi_torch.recon.pipeline import (
    ReconstructionResult,
    Reconstructor,
    prepare_image,
    with_load_time,
)
from hsi_torch.recon.sensing import BundleSensing
from hsi_torch.recon.settings import ReconstructSettings, with_overrides
from hsi_torch.recon.spatial.noise import frame_noise_level

__all__ = ["SequenceReconstructor", "DriftPath", "temporal_problem"]

#: A frame as :meth:`SequenceReconstructor._prepare` made it: the image ``(3, H, W)`` and
#: saturation mask on the bundle's device, the corrections' statistics, the seconds it took.
_Prepared = tuple[Tensor, Tensor | None, dict[str, Any], float]


class DriftPath:
    """A smooth path of the sensor's drift over the frames of a sequence.

    Args:
        window: measurements the straight line is fitted over (the last ones).
        jump_px: distance (px) from the line's prediction that makes a measurement a jump.
    """

    def __init__(self, window: int = 10, jump_px: float = 0.5) -> None:
        if window < 2:
            raise ValueError(f"window must be >= 2, got {window}")
        self.window, self.jump_px = int(window), float(jump_px)
        self.times: list[float] = []
        self.values: list[np.ndarray] = []  # (tx, ty, θ deg)

    def _fit(self, t: float) -> np.ndarray | None:
        n = len(self.times)
        if n == 0:
            return None
        if n == 1:
            return self.values[0].copy()
        ts = np.asarray(self.times[-self.window :])
        vs = np.stack(self.values[-self.window :])
        A = np.stack([np.ones_like(ts), ts - ts.mean()], 1)
        coef, *_ = np.linalg.lstsq(A, vs, rcond=None)
        return coef[0] + coef[1] * (t - ts.mean())

    def predict(self, t: float) -> np.ndarray | None:
        """``(tx, ty, θ)`` of the path at time ``t`` (``None`` before any measurement)."""
        return self._fit(t)

    def update(
        self, t: float, measured: np.ndarray | None, source: str = "frame"
    ) -> tuple[np.ndarray | None, list[Finding]]:
        """Add frame ``t``'s measurement ``(tx, ty, θ deg)`` (``None``: not measured) and return
        the path's value at ``t`` (the correction to apply) and the findings."""
        found: list[Finding] = []
        pred = self._fit(t) if len(self.times) >= 2 else None
        if measured is None:
            p = self._fit(t)
            found.append(
                Finding(
                    "drift.unmeasured",
                    "info",
                    "the drift of this frame could not be measured; "
                    "corrected with the path's prediction"
                    if p is not None
                    else "the drift of this frame could not be measured and no path exists "
                    "yet: not corrected",
                    source=source,
                )
            )
            return p, found
        m = np.asarray(measured, dtype=np.float64)
        if pred is not None:
            d = float(np.hypot(*(m[:2] - pred[:2])))
            if d > self.jump_px:
                found.append(
                    Finding(
                        "drift.jump",
                        "warning",
                        f"the measured drift jumped {d:.2f} px from the path of the last "
                        f"{min(len(self.times), self.window)} frames; the path restarts here",
                        measured=round(d, 3),
                        limit=self.jump_px,
                        fix="check the camera's mounting (a knock, a loose lens) or recalibrate",
                        source=source,
                    )
                )
                self.times, self.values = [], []
        self.times.append(float(t))
        self.values.append(m)
        return self._fit(t), found


class _Identity:
    """The sensing of a problem whose "observations" are already its right-hand sides
    (``Aᵀ W y`` computed outside): ``A_adjoint`` returns them as they are. As for every sensing,
    ``A_adjoint(y, idx)`` gets the rows ``y`` of the pixels ``idx`` (a chunk), not the whole
    frame's: ``idx`` selects the operator's rows, and this operator has none to select."""

    def __init__(
        self, num_pixels: int, num_bands: int, dtype: torch.dtype, device: torch.device
    ) -> None:
        self.num_pixels, self.num_obs, self.num_bands = num_pixels, num_bands, num_bands
        self.dtype, self.device, self.shared = dtype, device, False

    def A_adjoint(self, y: Tensor, idx: Tensor | slice | None = None) -> Tensor:  # noqa: ARG002
        return y


def temporal_problem(problem: NNLSProblem, num_pixels: int) -> NNLSProblem:
    """The per-pixel problems of the temporal prior, solved with their right-hand sides given
    directly as ``y``: the prior ``w‖s − s_prev‖²_G`` (``G`` the pixel's own Gram matrix) turns
    ``½sᵀGs − bᵀs`` into ``½(1 + w)sᵀGs − (b + wGs_prev)ᵀs``, whose minimiser over ``s ≥ 0`` is
    that of ``½sᵀGs − b̃ᵀs`` with ``b̃ = (b + wGs_prev)/(1 + w)``: the same ``G`` and its stored
    factorisation, shared with ``problem`` (nothing is factorised again)."""
    G = problem.gram
    op = _Identity(num_pixels, G.shape[-1], G.dtype, G.device)
    return NNLSProblem(
        op,  # type: ignore[arg-type]
        None,
        problem.beta,
        problem.diff_order,
        G,
        problem.gram_inv,
        problem.gram_diag,
        problem.gram_norm,
        problem.singular,
        problem.no_data,
    )


class SequenceReconstructor:
    """Reconstruct the frames of a sequence in order (see the module docstring).

    Args:
        bundle: as :class:`~hsi_torch.recon.pipeline.Reconstructor` (a bundle, its path or a
            ready :class:`~hsi_torch.recon.sensing.BundleSensing`).
        settings: every setting; the ``sequence`` group is this class's own.
        overrides: flat keys (``warm_start=False``, ``temporal="quadratic"``, ``prior="tv"``,
            ``drift_track=True``, …).

    Example:
        >>> seq = SequenceReconstructor("calib.npz", prior="tv")  # doctest: +SKIP
        >>> for res in seq(frames):  # doctest: +SKIP
        ...     print(res.stats["sequence"]["frame"], res.timings["solve"])
    """

    def __init__(
        self,
        bundle: CalibrationBundle | BundleSensing | str | os.PathLike,
        settings: ReconstructSettings | None = None,
        **overrides: Any,
    ) -> None:
        s = with_overrides(settings, overrides)
        self.settings = s
        inner = s
        if s.sequence.drift_track:  # measured and corrected here, along the path
            inner = s.replace(drift_check=False, refine_registration=False)
        #: the front door every frame goes through
        self.reconstructor = Reconstructor(bundle, inner)
        self.base_sensing = self.reconstructor.sensing
        sq = s.sequence
        self.warm = (
            WarmStart(per_pixel=sq.warm_start, spatial=sq.warm_spatial, reuse_noise=sq.warm_noise)
            if sq.warm_start or sq.warm_spatial
            else None
        )
        self.path = DriftPath(s.sequence.drift_window, s.sequence.drift_jump_px)
        self._temporal: NNLSProblem | None = None
        self._prev: Tensor | None = None  # (P, M) the last answer (temporal prior)
        self._prev_ok: Tensor | None = None
        self.frame_index = 0
        #: findings of every frame so far
        self.findings: list[Finding] = []

    def reset(self) -> None:
        """Start a new sequence: no warm start, no drift path, no previous answer."""
        if self.warm is not None:
            self.warm.reset()
        self.path = DriftPath(
            self.settings.sequence.drift_window, self.settings.sequence.drift_jump_px
        )
        self._prev = self._prev_ok = None
        self.frame_index = 0
        self.findings = []

    def __call__(self, frames: Iterable[Any]) -> Iterator[ReconstructionResult]:
        return self.reconstruct_sequence(frames)

    def reconstruct_sequence(self, frames: Iterable[Any]) -> Iterator[ReconstructionResult]:
        """One result per frame, in order, lazily (frames: tensors ``(C, H, W)``,
        ``(image, saturated)`` pairs, or objects with ``image``/``saturated`` and optionally
        ``metadata``)."""
        for f in frames:
            if isinstance(f, Tensor):
                yield self.reconstruct(f)
            elif isinstance(f, tuple):
                yield self.reconstruct(*f)
            else:
                meta = getattr(f, "metadata", None) or {}
                yield self.reconstruct(
                    f.image,
                    getattr(f, "saturated", None),
                    cfa_pattern=meta.get("cfa_pattern"),
                    exposure_s=meta.get("exposure_s"),
                    source=str(getattr(f, "path", None) or f"frame {self.frame_index}"),
                )

    def reconstruct(
        self,
        image: Tensor,
        saturated: Tensor | None = None,
        *,
        exposure_s: float | None = None,
        cfa_pattern: str | None = None,
        source: str | None = None,
    ) -> ReconstructionResult:
        """Reconstruct the next frame (arguments as
        :meth:`~hsi_torch.recon.pipeline.Reconstructor.reconstruct_frame`)."""
        rec = self.reconstructor
        src = source or f"frame {self.frame_index}"

        def solve(sens: BundleSensing, prepared: _Prepared | None) -> ReconstructionResult:
            if prepared is None:
                return rec.reconstruct_frame(image, saturated, exposure_s=exposure_s,
                                             cfa_pattern=cfa_pattern, source=src,
                                             warm=self.warm, sensing=sens)  # fmt: skip
            # the frame as this class prepared it: not demosaiced and corrected a second time
            img, sat, corr, seconds = prepared
            mosaic = image.shape[0] == 1
            res = rec.reconstruct_frame(img, sat, exposure_s=exposure_s, cfa_pattern=cfa_pattern,
                                        source=src, raw_layout="bayer" if mosaic else None,
                                        bundle_corrections=False, warm=self.warm,
                                        sensing=sens)  # fmt: skip
            res.stats.update(corr)
            if mosaic:
                res.timings = {"demosaic": seconds, **res.timings}
            res.timings["total"] += seconds
            return res

        return self._frame(image, saturated, exposure_s, cfa_pattern, src, False, solve)

    def reconstruct_file(
        self, path: str | os.PathLike, *, page: int | None = None
    ) -> ReconstructionResult:
        """Read the next frame from a file and reconstruct it through the file front door
        (:meth:`~hsi_torch.recon.pipeline.Reconstructor.reconstruct_file`: the reading's checks
        and findings as for a single capture; ``page``: a page of a multi-page TIFF), with the
        sequence's warm start, drift path and temporal prior."""
        rec = self.reconstructor
        cap, checks, t_load = rec.read_capture(path, page=page)
        t_exp, _, _, pattern = rec.capture_frame_arguments(cap)

        def solve(sens: BundleSensing, _: _Prepared | None) -> ReconstructionResult:
            return with_load_time(
                rec.reconstruct_capture(cap, warm=self.warm, sensing=sens, stats=checks), t_load
            )

        src = str(getattr(cap, "path", None) or path)
        return self._frame(cap.image, cap.saturated, t_exp, pattern, src, True, solve)

    def _frame(
        self,
        image: Tensor,
        saturated: Tensor | None,
        exposure_s: float | None,
        cfa_pattern: str | None,
        src: str,
        corrected: bool,
        solve: Callable[[BundleSensing, _Prepared | None], ReconstructionResult],
    ) -> ReconstructionResult:
        """One frame: the drift path (on the image, ``corrected``: the bundle's corrections
        already applied), ``solve`` with the frame's sensing and the frame as prepared for the
        drift path and the temporal step (``None`` without either), the temporal step."""
        t = self.frame_index
        sq = self.settings.sequence
        found: list[Finding] = []
        seq_stats: dict[str, Any] = {
            "frame": t,
            "warm": self.warm is not None
            and (self.warm.x is not None or self.warm.spatial_x is not None),
        }
        sens = self.base_sensing
        pattern = cfa_pattern or sens.cfa_pattern
        prepared = None
        if sq.drift_track or sq.temporal == "quadratic":  # prepared once, for all three
            prepared = self._prepare(image, saturated, pattern, corrected, src)
        if sq.drift_track:
            assert prepared is not None
            est = estimate_drift(sens, prepared[0], self.settings.registration.min_views)
            meas = None
            if est.refusal is None and est.sensor_shift_px is not None:
                meas = np.array(
                    [
                        *np.asarray(est.sensor_shift_px, np.float64),
                        float(est.sensor_rotation_deg or 0.0),
                    ]
                )
            path, fd = self.path.update(float(t), meas, src)
            found += fd
            seq_stats["drift_measured"] = (
                None if meas is None else [round(float(v), 4) for v in meas]
            )
            seq_stats["drift_path"] = None if path is None else [round(float(v), 4) for v in path]
            if path is not None:
                sens = corrected_sensing(self.base_sensing, path[:2], float(path[2]))
        res = solve(sens, prepared)
        if sq.temporal == "quadratic":
            assert prepared is not None
            self._temporal_step(res, sens, exposure_s, prepared, seq_stats)
        res.stats["sequence"] = seq_stats
        res.stats["findings"] = [f.to_dict() for f in found]
        self.findings += found
        self.frame_index += 1
        return res

    def _prepare(
        self,
        image: Tensor,
        saturated: Tensor | None,
        pattern: str | None,
        corrected: bool,
        src: str,
    ) -> _Prepared:
        """The frame as the front door prepares it: on the bundle's device, demosaiced,
        corrected (unless ``corrected``); with the corrections' statistics and the seconds it
        took. A bad image is refused naming ``src``, as by the front door."""
        t0 = time.perf_counter()
        img, sat, corr = prepare_image(self.base_sensing, image, saturated, pattern, src,
                                       not corrected)
        return img, sat, corr, time.perf_counter() - t0

    def _temporal_step(
        self,
        res: ReconstructionResult,
        sens: BundleSensing,
        exposure_s: float | None,
        prepared: _Prepared,
        seq_stats: dict[str, Any],
    ) -> None:
        """The gated temporal solve of one frame (per-pixel answers in ``res`` replaced where
        the pixel is static); ``prepared``: the frame as solved (:meth:`_prepare`)."""
        sq = self.settings.sequence
        M = sens.num_bands
        pix = sens.pixel_index.to(res.cube.device)
        # (P, M) rows in memory: on a transposed view torch.bmm (the sensing's A) runs one BLAS
        # call per pixel on CPU (hundreds of seconds a full-size frame instead of a fraction of
        # a second); every later frame's s_prev is a copy of these rows
        x = res.cube.reshape(M, -1).index_select(1, pix).T.nan_to_num(0.0)
        x = x.to(sens.dtype).contiguous()
        ok = res.valid.reshape(-1).index_select(0, pix)
        prev, prev_ok = self._prev, self._prev_ok
        self._prev_ok = ok.clone()
        if prev is None or prev.shape != x.shape:
            self._prev = x.clone()
            seq_stats["temporal_static"] = 0
            return
        img, sat = prepared[0].to(sens.dtype), prepared[1]  # cast as the front door's solve
        if sat is not None and not bool(sat.any()):
            sat = None
        with torch.no_grad():
            samples, wsat = sample_views(
                sens, img.unsqueeze(0), None if sat is None else sat.unsqueeze(0)
            )
            y, mask, _ = observations_from_samples(
                sens, samples, wsat, self.settings.input.sat_threshold
            )
            y, mask = y[0], mask[0]
            scale = (
                exposure_scale(exposure_s, sens.exposure_s)
                if self.settings.input.exposure_correction
                else 1.0
            )
            y = torch.where(mask, y * scale, torch.zeros((), dtype=y.dtype, device=y.device))
            model, prob = sens.model, sens.problem
            w = mask.to(sens.dtype)
            r_fit = ((model.A(x) - y) * w).square().sum(1)
            r_prev = ((model.A(prev) - y) * w).square().sum(1)
            n = w.sum(1)
            k = (x > 0).sum(1).to(sens.dtype)
            # the pixel's noise variance: its own fit residual per spare observation, at least
            # the frame's pooled estimate (the spatial prior's rule, with the fit's effective
            # degrees of freedom): a pixel with few spare observations has no estimate of its own
            sigma = frame_noise_level(sens, y, mask, ok, x)
            var = r_fit / (n - k).clamp_min(1.0)
            if math.isfinite(sigma):
                var = var.clamp_min(sigma * sigma)
            changed = (mask != sens.obs_mask.to(mask.device)).any(1)
            static = (
                ok
                & prev_ok
                & ~changed
                & (r_prev - r_fit <= sq.temporal_gate * k.clamp_min(1.0) * var)
            )
            if self._temporal is None or self._temporal.gram is not prob.gram:
                self._temporal = temporal_problem(prob, x.shape[0])
            wt = sq.temporal_weight
            b = model.A_adjoint(y)
            bt = (b + wt * prob.gram_apply(prev)) / (1.0 + wt)
            sol = self._temporal.solve(bt, x0=x if self.warm is not None else None)
            xt = torch.where(static.unsqueeze(1), sol.x, x)
        cube, valid = assemble_cube(sens, xt, ok, self.settings.solve.nan_invalid)
        res.cube, res.valid = cube[0] if cube.ndim == 4 else cube, valid
        self._prev = xt.clone()
        n_static = int(static.sum())
        seq_stats["temporal_static"] = n_static
        seq_stats["temporal_static_fraction"] = n_static / max(1, int(ok.sum()))
        seq_stats["temporal_max_kkt"] = (
            float(torch.where(static, sol.kkt_residual, torch.zeros_like(sol.kkt_residual)).max())
            if n_static
            else 0.0
        )
        if not math.isfinite(seq_stats["temporal_max_kkt"]):
            seq_stats["temporal_max_kkt"] = None
