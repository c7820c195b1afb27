"""Moving scenes for the virtual prototype: frame sequences with their ground truth.

A sequence is a scene that moves between exposures, seen by the prototype frame after frame:

* **Scene motion** (:class:`Motion`): each layer of a :class:`LayeredScene` is translated,
  rotated and scaled per frame on the diffuser plane (``x' = c + s·R(θ)(x − c) + t``, mm, deg),
  e.g. the CAVE scene panning behind a rotating ColorChecker (:func:`cave_and_chart`). A layer
  covers what lies inside its own moved extent; the top layer wins.
* **Illuminant change** (:class:`Illumination`): per frame a factor ``k_t`` (flicker,
  ``1 + flicker·sin(2π t / period)``) and a spectral tilt ``1 + tilt_t·(λ − 550 nm)/100 nm``
  (``tilt_t = tilt_per_frame·t``) on the light; the truth of frame ``t`` is the reflectance times
  that relative spectrum (what a reconstruction with the calibration's white recovers).
* **Sensor drift** growing over the sequence: the sensor shifted by ``t·drift_px_per_frame``
  (and turned by ``t·drift_deg_per_frame``) relative to the optics since calibration, in the
  convention of :func:`~hsi_torch.simulate.mismatch.drift_points`.

Two engines make the captures (:func:`simulate_sequence`):

* ``"forward"`` (default; fast at the full size): the true sensing model of every reference
  pixel (:meth:`~hsi_torch.simulate.render.CaptureRenderer.forward_model` of the renderer's
  ground truth) gives each view's noise-free observations in the reference frame; every sensor
  pixel inside a view's triangle samples them (bilinear) at its reference position through the
  view's true homography (with the drift applied to the pixel first); the sensor model
  (:meth:`~hsi_torch.simulate.render.CaptureRenderer.expose`) adds shot and read noise,
  quantisation, saturation and the Bayer mosaic. Light between the views (the higher-order
  tiles) is absent, and each view's image is resampled once on the way in (the reconstruction
  samples it again), so this is the prototype's model, not its ray-traced render.
* ``"render"``: every frame ray-traced by the renderer (:meth:`render_captures`, the drift as
  its after-calibration mismatch); exact but slow (small size; spectral tilt not supported).

``noise_gain`` multiplies the noise of every capture (``dn = mean + g·(noisy − mean)``): 4 is
"low light: shot noise ×4" at the same signal level.

Each frame's truth is kept as for still scenes: the ``(M, h, w)`` reflectance in the reference
frame (pixel-footprint mean, :meth:`~hsi_torch.simulate.render.CaptureRenderer.scene_truth`)
times the frame's relative illuminant, with the moving-edge mask (pixels whose truth changed
from the previous frame by more than ``edge_threshold`` in any band).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from hsi_torch.io.bundle import CalibrationBundle
from hsi_torch.optics.geometry import apply_homography, points_in_triangle
from hsi_torch.simulate.capture_sets import build_renderer, build_scene
from hsi_torch.simulate.config import SceneSpec, SimulateConfig
from hsi_torch.simulate.mismatch import drift_points
from hsi_torch.simulate.render import CaptureRenderer, CaptureSpec
from hsi_torch.simulate.scenes.base import Extent

__all__ = [
    "Motion",
    "Layer",
    "LayeredScene",
    "Illumination",
    "SequenceFrame",
    "cave_and_chart",
    "oracle_bundle",
    "sequence_renderer",
    "simulate_sequence",
    "ENGINES",
]

ENGINES = ("forward", "render")


@dataclass(frozen=True)
class Motion:
    """Per-frame similarity motion of a layer on the diffuser plane.

    Frame ``t`` maps a point ``x`` of the still layer to ``c + s_t·R(θ_t)(x − c) + t·shift``
    with ``θ_t = t·rotation_deg_per_frame``, ``s_t = (1 + scale_per_frame)^t``, ``c`` =
    ``centre_mm`` (default: the layer's extent centre).
    """

    shift_mm_per_frame: tuple[float, float] = (0.0, 0.0)
    rotation_deg_per_frame: float = 0.0
    scale_per_frame: float = 0.0
    centre_mm: tuple[float, float] | None = None

    def params(self, t: float) -> tuple[float, float, float, float]:
        """``(tx, ty, θ rad, s)`` at frame ``t``."""
        return (
            t * self.shift_mm_per_frame[0],
            t * self.shift_mm_per_frame[1],
            math.radians(t * self.rotation_deg_per_frame),
            (1.0 + self.scale_per_frame) ** t,
        )


@dataclass
class Layer:
    """A scene and its motion (``scene``: any :class:`~hsi_torch.simulate.scenes.base.Scene`)."""

    scene: Any
    motion: Motion = field(default_factory=Motion)


def _centre(ext: Extent) -> tuple[float, float]:
    return ((ext[0] + ext[1]) / 2.0, (ext[2] + ext[3]) / 2.0)


class LayeredScene:
    """The layers at frame ``t``: each layer's scene moved by its :class:`Motion`; at a point the
    top (last) layer whose moved extent holds it gives the reflectance; outside all, 0.

    Args:
        layers: bottom first.
        t: frame index (any float).
    """

    def __init__(self, layers: Sequence[Layer], t: float) -> None:
        if not layers:
            raise ValueError("a LayeredScene needs at least one layer")
        self.layers, self.t = list(layers), float(t)
        self._moves = []
        for ly in self.layers:
            ext = tuple(float(v) for v in ly.scene.extent)
            c = ly.motion.centre_mm or _centre(ext)
            self._moves.append((ext, c, *ly.motion.params(self.t)))

    @property
    def extent(self) -> Extent:
        xs, ys = [], []
        for ext, c, tx, ty, th, s in self._moves:
            for x in (ext[0], ext[1]):
                for y in (ext[2], ext[3]):
                    dx, dy = x - c[0], y - c[1]
                    xs.append(c[0] + s * (math.cos(th) * dx - math.sin(th) * dy) + tx)
                    ys.append(c[1] + s * (math.sin(th) * dx + math.cos(th) * dy) + ty)
        return (min(xs), max(xs), min(ys), max(ys))

    def reflectance(self, xy_mm: Tensor, wavelengths_nm: Any) -> Tensor:
        """``(N, M)`` reflectance at diffuser points ``xy_mm (N, 2)`` (mm)."""
        wl = torch.as_tensor(wavelengths_nm, dtype=torch.float64)
        out = torch.zeros(xy_mm.shape[0], wl.numel(), dtype=xy_mm.dtype, device=xy_mm.device)
        for ly, (ext, c, tx, ty, th, s) in zip(self.layers, self._moves, strict=True):
            cc = torch.tensor(c, dtype=xy_mm.dtype, device=xy_mm.device)
            d = xy_mm - cc - torch.tensor((tx, ty), dtype=xy_mm.dtype, device=xy_mm.device)
            ct, st = math.cos(th) / s, math.sin(th) / s  # the inverse motion R(−θ)/s
            src = torch.stack([ct * d[:, 0] + st * d[:, 1], -st * d[:, 0] + ct * d[:, 1]], 1) + cc
            inside = (
                (src[:, 0] >= ext[0])
                & (src[:, 0] <= ext[1])
                & (src[:, 1] >= ext[2])
                & (src[:, 1] <= ext[3])
            )
            idx = inside.nonzero().squeeze(1)
            if idx.numel():
                r = ly.scene.reflectance(src.index_select(0, idx), wavelengths_nm)
                out.index_copy_(0, idx, r.to(out.dtype))
        return out


@dataclass(frozen=True)
class Illumination:
    """Per-frame change of the light relative to the calibration's: a flicker factor
    ``1 + flicker·sin(2π t / period_frames)`` and a spectral tilt growing by
    ``tilt_per_frame`` a frame (``1 + tilt·(λ − 550)/100``, clamped at 0)."""

    flicker: float = 0.0
    period_frames: float = 8.0
    tilt_per_frame: float = 0.0

    def spectrum(self, t: float, wavelengths_nm: Tensor) -> Tensor:
        """``(M,)`` relative illuminant of frame ``t`` (1 everywhere: unchanged)."""
        k = 1.0 + self.flicker * math.sin(2.0 * math.pi * t / self.period_frames)
        tilt = self.tilt_per_frame * t
        return (k * (1.0 + tilt * (wavelengths_nm.to(torch.float64) - 550.0) / 100.0)).clamp_min(0)


@dataclass
class SequenceFrame:
    """One simulated frame.

    Attributes:
        index: frame number ``t``; time_s: ``t / fps``.
        image: ``(C, H, W)`` DN above black (``C = 1`` Bayer mosaic or ``3`` RGB), float32.
        saturated: same shape, bool.
        truth: ``(M, h, w)`` float32 reflectance × the frame's relative illuminant, reference frame.
        moved: ``(h, w)`` bool, the truth changed since the previous frame (the moving edges;
            all False for frame 0).
        drift_px: ``(tx, ty)`` sensor shift (px) and drift_deg its rotation, as
            :func:`~hsi_torch.simulate.mismatch.drift_points` applies them.
        illuminant: ``(M,)`` the frame's relative illuminant.
        metadata: what a capture file's metadata would hold (``exposure``, ``cfa_pattern``,
            ``kind``, ``time_s``, ``frame``).
    """

    index: int
    time_s: float
    image: Tensor
    saturated: Tensor
    truth: Tensor
    moved: Tensor
    drift_px: tuple[float, float]
    drift_deg: float
    illuminant: Tensor
    metadata: dict[str, Any]


def cave_and_chart(
    pan_mm_per_frame: tuple[float, float] = (0.02, 0.0),
    rotation_deg_per_frame: float = 1.0,
    chart_width_mm: float = 3.0,
    chart_centre_mm: tuple[float, float] = (0.8, 1.2),
    cave_folder: str | None = None,
) -> list[Layer]:
    """The CAVE ``stuffed_toys`` cube panning (``pan_mm_per_frame``) behind a ColorChecker
    rotating about its centre (``rotation_deg_per_frame``); a plain ColorChecker when the CAVE
    data is absent is an error (``FileNotFoundError`` naming the folder)."""
    params: dict[str, Any] = {} if cave_folder is None else {"folder": cave_folder}
    cave = build_scene(SceneSpec(kind="cave", name="cave", params=params))
    chart = build_scene(
        SceneSpec(
            kind="colorchecker",
            name="colorchecker",
            params={"width_mm": chart_width_mm, "center_mm": list(chart_centre_mm)},
        )
    )
    return [
        Layer(cave, Motion(shift_mm_per_frame=tuple(pan_mm_per_frame))),
        Layer(chart, Motion(rotation_deg_per_frame=rotation_deg_per_frame)),
    ]


def sequence_renderer(
    size: str = "small", overrides: Sequence[str] = (), device: str | None = None
) -> tuple[CaptureRenderer, SimulateConfig]:
    """The renderer of the shipped ``simulate`` (``size="small"``, 400 × 384 px) or
    ``simulate_full`` (``"full"``, 2896 × 2784 px) prototype, with config ``overrides``
    (``key=value`` strings as on the command line)."""
    from hsi_torch.config import load_config  # lazy: the schema loader (start-up time)
    from hsi_torch.resources import shipped_config  # lazy: as above

    names = {"small": "simulate", "full": "simulate_full"}
    if size not in names:
        raise ValueError(f"size must be 'small' or 'full', got {size!r}")
    cfg = load_config(shipped_config(names[size]), SimulateConfig, list(overrides))
    return build_renderer(cfg, device), cfg


def oracle_bundle(
    renderer: CaptureRenderer, truth: dict[str, Tensor] | None = None
) -> CalibrationBundle:
    """A calibration bundle of the renderer's ground truth (as
    :func:`~hsi_torch.simulate.oracle.bundle_from_truth`, without writing a capture set);
    ``truth``: :meth:`~hsi_torch.simulate.render.CaptureRenderer.ground_truth` if already made."""
    gt = renderer.ground_truth() if truth is None else truth
    lay = renderer.layout
    s = renderer.sensor
    return CalibrationBundle(
        wavelengths_nm=gt["wavelengths_nm"], triangles=lay.triangles, parity=lay.parity,
        view_homographies=lay.view_homographies,
        sensor_size=torch.tensor(renderer.sensor_size), reference_bbox=torch.tensor(
            lay.reference_bbox), B=gt["B"], phi=gt["phi"], gain=gt["gain"],
        view_mask=gt["view_mask"], modulated=gt["modulated"], valid=gt["valid"],
        reflection_sequences=[tuple(q) for q in lay.reflection_sequences],
        settings={"oracle": True, "source": "simulate_sequence",
                  "cfa_pattern": s.cfa_pattern if s.output == "bayer" else None,
                  "white_exposure_s": renderer.scene_exposure,
                  "white_exposure_unit": "relative"},
    )  # fmt: skip


class _ForwardImager:
    """Sensor images of reference-frame observations (the ``"forward"`` engine): per sensor
    pixel, the view whose triangle holds it and its reference position (cached per drift)."""

    def __init__(self, renderer: CaptureRenderer, truth: dict[str, Tensor]) -> None:
        self.r, self.truth = renderer, truth
        lay = renderer.layout
        H, W = renderer.sensor_size
        ys, xs = torch.meshgrid(
            torch.arange(H, dtype=torch.float64),
            torch.arange(W, dtype=torch.float64),
            indexing="ij",
        )
        self.pts = torch.stack([xs.reshape(-1), ys.reshape(-1)], 1).to(renderer.device)
        self._key: tuple | None = None
        self._plan: list[tuple[Tensor, Tensor]] = []
        self.lay = lay

    def _views(self, shift: tuple[float, float], deg: float) -> list[tuple[Tensor, Tensor]]:
        key = (shift, deg)
        if key == self._key:
            return self._plan
        lay, (H, W) = self.lay, self.r.sensor_size
        p = self.pts
        if shift != (0.0, 0.0) or deg != 0.0:
            p = drift_points(p, shift, deg, ((W - 1) / 2.0, (H - 1) / 2.0))
        x0, y0, w, h = lay.reference_bbox
        plan = []
        for v in range(lay.num_views):
            inside = points_in_triangle(p, lay.triangles[v].to(p), 0.0)
            idx = inside.nonzero().squeeze(1)
            q = apply_homography(lay.view_homographies[v].to(p), p.index_select(0, idx))
            g = torch.stack([(q[:, 0] - x0) / max(w - 1, 1), (q[:, 1] - y0) / max(h - 1, 1)], 1)
            plan.append((idx, g * 2.0 - 1.0))
        self._key, self._plan = key, plan
        return plan

    def image(self, cube: Tensor, shift: tuple[float, float], deg: float) -> Tensor:
        """``(3, H, W)`` float64 noise-free DN of the reference-frame ``cube (M, h, w)``."""
        y = self.r.forward_model(self.truth, cube)  # (V, 3, h, w)
        H, W = self.r.sensor_size
        out = torch.zeros(3, H * W, dtype=torch.float64, device=y.device)
        for v, (idx, g) in enumerate(self._views(shift, deg)):
            if idx.numel() == 0:
                continue
            s = torch.nn.functional.grid_sample(
                y[v : v + 1],
                g.view(1, 1, -1, 2).to(y),
                mode="bilinear",
                padding_mode="zeros",
                align_corners=True,
            )  # (1, 3, 1, n)
            out[:, idx] = s[0, :, 0]
        return out.view(3, H, W)


def simulate_sequence(
    renderer: CaptureRenderer,
    layers: Sequence[Layer],
    num_frames: int,
    *,
    illumination: Illumination | None = None,
    drift_px_per_frame: tuple[float, float] = (0.0, 0.0),
    drift_deg_per_frame: float = 0.0,
    noise_gain: float = 1.0,
    engine: str = "forward",
    truth: dict[str, Tensor] | None = None,
    fps: float = 10.0,
    seed: int = 0,
    edge_threshold: float = 0.01,
) -> Iterator[SequenceFrame]:
    """Frames of a moving scene seen by the prototype, each with its ground truth.

    Args:
        renderer: the prototype (:func:`sequence_renderer`).
        layers: the scene and its motion (bottom first), e.g. :func:`cave_and_chart`.
        num_frames: frames ``t = 0 … num_frames − 1``.
        illumination: the light's change per frame (default none).
        drift_px_per_frame, drift_deg_per_frame: sensor drift growing linearly: frame ``t`` has
            the shift ``t·drift_px_per_frame`` (px, ``(x, y)``) and rotation
            ``t·drift_deg_per_frame`` (deg).
        noise_gain: factor on every capture's noise (4: low light, shot noise ×4).
        engine: ``"forward"`` or ``"render"`` (see the module docstring).
        truth: the renderer's :meth:`ground_truth` if already made (the forward engine needs it).
        fps: frames per second (``time_s``).
        seed: the first frame's noise seed (frame ``t``: ``seed + t``).
        edge_threshold: the truth change (reflectance) that marks a pixel as moved.

    Yields:
        :class:`SequenceFrame` per frame (generated lazily: one frame in memory at a time).
    """
    if engine not in ENGINES:
        raise ValueError(f"engine must be one of {ENGINES}, got {engine!r}")
    if num_frames < 1:
        raise ValueError(f"num_frames must be >= 1, got {num_frames}")
    if not (noise_gain >= 0 and math.isfinite(noise_gain)):
        raise ValueError(f"noise_gain must be finite and >= 0, got {noise_gain}")
    ill = illumination or Illumination()
    if engine == "render" and ill.tilt_per_frame != 0:
        raise ValueError("engine='render' supports a flicker of the light, not a spectral tilt")
    wl = renderer.wavelengths
    imager = None
    if engine == "forward":
        truth = renderer.ground_truth() if truth is None else truth
        imager = _ForwardImager(renderer, truth)
    base_mismatch = renderer.mismatch
    exposure = renderer.scene_exposure
    unit = exposure * renderer.dn_per_unit
    prev: Tensor | None = None
    for t in range(num_frames):
        scene = LayeredScene(layers, t)
        refl = renderer.scene_truth(scene)  # (M, h, w) float32
        spec = ill.spectrum(t, wl)
        cube = refl * spec.view(-1, 1, 1).to(refl.dtype)
        shift = (t * float(drift_px_per_frame[0]), t * float(drift_px_per_frame[1]))
        deg = t * float(drift_deg_per_frame)
        if imager is not None:
            irr = imager.image(cube, shift, deg) / unit
        else:
            drifted = shift != (0.0, 0.0) or deg != 0.0
            renderer.mismatch = dataclasses.replace(
                base_mismatch, drift_shift_px=shift, drift_rotation_deg=deg
            )
            try:
                (irr,) = renderer.render_captures(
                    [CaptureSpec(f"frame_{t:04d}", "scene", scene)], after_calibration=drifted
                )
            finally:
                renderer.mismatch = base_mismatch
                renderer.release_scenes()
            irr = irr * float(spec.mean()) if ill.flicker else irr
        dn, sat = _expose(renderer, irr.to(renderer.dtype), exposure, seed + t, noise_gain)
        moved = (
            torch.zeros(cube.shape[1:], dtype=torch.bool)
            if prev is None
            else ((cube - prev).abs() > edge_threshold).any(0)
        )
        prev = cube
        s = renderer.sensor
        meta = {
            "exposure": exposure,
            "kind": s.output,
            "frame": t,
            "time_s": t / fps,
            "black_level": float(s.black_level),
            "white_level": float(s.white),
            "source": "hsi_torch virtual prototype (sequence)",
        }
        if s.output == "bayer":
            meta["cfa_pattern"] = s.cfa_pattern
        yield SequenceFrame(
            t,
            t / fps,
            (dn - float(s.black_level)).to(torch.float32),
            sat,
            cube.to(torch.float32),
            moved,
            shift,
            deg,
            spec.to(torch.float32),
            meta,
        )


def _expose(
    renderer: CaptureRenderer, irr: Tensor, exposure: float, seed: int, noise_gain: float
) -> tuple[Tensor, Tensor]:
    """Sensor readout with the noise scaled by ``noise_gain`` about the noise-free level."""
    dn, sat = renderer.expose(irr, exposure, seed)
    if noise_gain == 1.0:
        return dn, sat
    s = renderer.sensor
    mean = renderer.noise_free_dn(irr, exposure)
    if s.output == "bayer" and mean.shape[-3] == 3:
        mean = s.mosaic(mean)
    mean = mean + float(s.black_level)
    dn = (mean + noise_gain * (dn - mean)).clamp(0.0, float(s.white))
    return dn, sat | (dn >= float(s.white))
