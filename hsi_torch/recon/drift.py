"""Drift of the sensor since calibration, measured from the scene itself, and its correction.

The method, its limits, the refusal rules and measurements: ``docs/reconstruct.md``, *Drift*.
Conventions: :func:`estimate_drift` aligns each view, warped to the reference frame by the
bundle's own sampling grid, to the reference view (view 0) on gradient-magnitude images (phase
correlation, then ECC translation); ``d_v`` (reference-frame px, ``(x, y)``): view ``v``'s content
at ``x`` is the reference view's at ``x + d_v`` (``d_0 = 0``). Reference frames at least 320 px on
the shorter side are aligned on ``2 × 2`` block means (:func:`_block_factor`); what no frame
changes is kept per bundle (:func:`_static`). :func:`corrected_sensing` corrects a rigid sensor
motion ``p' = c + R(θ)(p − c) + t`` (pixel ``p`` sees what the calibrated sensor saw at ``p'``,
``c`` the sensor centre): view ``v``'s content moves by ``u_v(x) = H_v(M(H_v⁻¹ x)) − x``, ``(t, θ)``
is the weighted least-squares fit of ``d_v`` to ``u_v − u_0``, and every view samples the frame
at ``M⁻¹(H_v⁻¹ x)``; ``A`` is unchanged. :func:`drift_decision` says whether to correct,
:func:`drift_finding` what is said.
"""

from __future__ import annotations

import dataclasses
import math
import weakref
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from hsi_torch.findings import Finding, RefusedError

__all__ = [
    "DriftEstimate",
    "DriftError",
    "estimate_drift",
    "corrected_sensing",
    "DRIFT_MIN_CORRELATION",
    "DRIFT_AGREE_PX",
    "DRIFT_MIN_VIEWS",
    "DRIFT_MAX_VIEW_SHIFT_PX",
    "VIEW_STATUSES",
    "motion_points",
    "drift_motion_px",
    "drift_decision",
    "drift_finding",
]

#: ECC correlation coefficient below which a view's alignment is not trusted (left out of the
#: fit and reported as ``null``).
DRIFT_MIN_CORRELATION = 0.5
#: px: the views' masks are shrunk by this much before their gradients are taken (the view
#: boundary's own edge is not scene texture), then tapered to 0 over :data:`_TAPER_PX`.
_ERODE_PX = 2
_TAPER_PX = 6
#: px: the common area compared is shrunk by this much more (so that a shifted view's content
#: stays on it).
_MARGIN_PX = 8
#: fewest common pixels for a view to be measured
_MIN_PIXELS = 400
#: least mean gradient magnitude (relative to the view's mean) for a view to have texture
_MIN_TEXTURE = 1e-4
#: px: a measured shift larger than this is not trusted. 32 px: on the small prototype the
#: views of a textured scene (USAF, CAVE) still align at the 21 px that a 12 px drift moves
#: them, where 16 px refused them; a false match further out is left to the agreement rules
#: (:func:`_refusal`), which refused every one measured (docs/reconstruct.md)
_MAX_SHIFT_PX = 4 * _MARGIN_PX
#: px: the largest view shift that can be measured (reference-frame px): the search window
DRIFT_MAX_VIEW_SHIFT_PX = float(_MAX_SHIFT_PX)
#: px: a measured view agrees with the fitted motion when its shift is within this of the fit's
#: (the simulator's drifts within the measurable range: at most 0.36 px on the small prototype)
DRIFT_AGREE_PX = 1.0
#: the default fewest agreeing views for a drift to be trusted (``drift_min_views``): on the
#: small prototype's ColorChecker, drifts within the measurable range agree in 7–9 of 9 views
#: (4–5 at its edge, 8–9 px); a foreign image, a drift beyond the range or a repeating
#: pattern's false match in 0–3
DRIFT_MIN_VIEWS = 4
#: the views are aligned on images averaged over ``f × f`` pixel blocks (:func:`_block_factor`):
#: ``f`` is the largest power of two up to this ...
_MAX_BLOCK = 2
#: ... that leaves at least this many blocks on the reference frame's shorter side
_MIN_BLOCKS = 160
#: ECC's stopping rule: at most this many iterations, or a step below this (block px)
_ECC_ITERATIONS = 100
_ECC_EPS = 1e-5


class DriftError(RefusedError):
    """A drift the frame cannot support was to be corrected (``refine_registration``): measured
    from too few views, by views that disagree, or beyond the measurable range. The message
    names the views' agreement, the measured motion and the limit (:attr:`DriftEstimate.refusal`);
    nothing is corrected and no cube is written for the frame. A
    :class:`~hsi_torch.findings.RefusedError`: ``.findings`` holds its ``drift.unmeasurable``
    error finding."""


#: what :attr:`DriftEstimate.view_status` says of a view
VIEW_STATUSES = {
    "reference": "the reference view (shift 0 by definition)",
    "agrees": "measured, and within DRIFT_AGREE_PX of the fitted motion",
    "disagrees": "measured, but farther than DRIFT_AGREE_PX from the motion the others agree on",
    "low_correlation": "aligned with a correlation below DRIFT_MIN_CORRELATION",
    "beyond_range": "aligned to a shift beyond DRIFT_MAX_VIEW_SHIFT_PX",
    "not_converged": "the alignment failed (no translation maximises the correlation)",
    "no_texture": "no texture on the view's common area (nothing to align)",
    "no_overlap": "too little area in common with the reference view",
}


@dataclass
class DriftEstimate:
    """The drift of one frame (see the module docstring).

    Attributes:
        view_shift_px: ``(V, 2)`` float64, measured ``d_v = (dx, dy)`` of every view relative to
            the reference view, reference-frame px; NaN where not measured (too few common
            pixels, too little texture, correlation below :data:`DRIFT_MIN_CORRELATION`, a
            shift beyond :data:`DRIFT_MAX_VIEW_SHIFT_PX`).
        correlation: ``(V,)`` ECC correlation coefficient of each view's alignment (NaN: not
            measured; 1 for the reference view).
        sensor_shift_px: ``(2,)`` fitted sensor translation ``t`` (sensor px), or ``None``
            without at least one agreeing view.
        sensor_rotation_deg: fitted rotation ``θ`` about the sensor centre (degrees), or
            ``None`` (fewer than two agreeing views: only ``t`` is fitted, ``θ`` is 0).
        residual_px: ``(V,)`` ``|d_v − (u_v − u_0)|`` after the fit to the agreeing views
            (NaN: not measured; a disagreeing view's is above :data:`DRIFT_AGREE_PX`).
        max_view_shift_px: the largest measured ``|d_v|`` (0 without any).
        view_status: ``(V,)`` what became of each view (a key of :data:`VIEW_STATUSES`).
        range_px: the measurable sensor translation (px) for this bundle: the one that moves
            the most sensitive view by :data:`DRIFT_MAX_VIEW_SHIFT_PX` (15.9 px on the small
            prototype, whose mirrored views move 2.01× the sensor; ``inf`` without any view
            pair). An upper limit: a scene may measure less.
        predicted_view_shift_px: the largest ``|u_v − u_0|`` the fitted motion gives any view
            with texture, measured or not (0 without a fit); above
            :data:`DRIFT_MAX_VIEW_SHIFT_PX`, the motion is beyond the measurable range.
        min_views: the fewest agreeing views asked for (``drift_min_views``).
        orientations: how many different orientations the agreeing views have (views whose
            sensitivities to the motion differ by more than a quarter: mirrored, turned; views
            of one orientation match a repeating pattern falsely alike, so at least 2 are
            needed).
        refusal: why the estimate cannot be trusted (too few views agree, the views disagree,
            beyond the measurable range), one line naming the views' agreement, the measured
            motion and the limit; ``None`` when it can, or when no view has texture (nothing
            measured, nothing to refuse).
    """

    view_shift_px: np.ndarray
    correlation: np.ndarray
    sensor_shift_px: np.ndarray | None
    sensor_rotation_deg: float | None
    residual_px: np.ndarray
    max_view_shift_px: float
    view_status: np.ndarray = dataclasses.field(default_factory=lambda: np.array([], object))
    range_px: float = math.inf
    predicted_view_shift_px: float = 0.0
    min_views: int = DRIFT_MIN_VIEWS
    orientations: int = 0
    refusal: str | None = None

    @property
    def measured_views(self) -> int:
        """Views other than the reference whose shift was measured (agreeing or not)."""
        return int(np.isfinite(self.view_shift_px[1:, 0]).sum())

    @property
    def agreeing_views(self) -> int:
        """Measured views within :data:`DRIFT_AGREE_PX` of the fitted motion (those fitted)."""
        return int((self.view_status == "agrees").sum())

    @property
    def textured_views(self) -> int:
        """Views other than the reference that had texture to align (measured or not)."""
        return int(sum(s not in ("reference", "no_texture", "no_overlap")
                       for s in self.view_status))

    @property
    def spread_px(self) -> float:
        """The largest residual of an agreeing view (px; 0 without any)."""
        r = self.residual_px[self.view_status == "agrees"]
        return float(r.max()) if r.size else 0.0

    def agreement(self) -> str:
        """One line: how many views agree and by how much, e.g. ``"9 of 9 views with texture
        agree within 1 px (spread 0.34 px)"``."""
        n, a = self.agreeing_views, self.textured_views
        text = (f"{n} of {a} views with texture agree within {DRIFT_AGREE_PX:g} px"
                + (f" (spread {self.spread_px:.2f} px, {self.orientations} orientation"
                   f"{'s' if self.orientations != 1 else ''})" if n else ""))
        counts: dict[str, int] = {}
        for s in self.view_status[1:]:
            if s not in ("agrees", "no_texture", "no_overlap"):
                counts[str(s)] = counts.get(str(s), 0) + 1
        if counts.get("disagrees"):
            d = self.residual_px[self.view_status == "disagrees"]
            counts.pop("disagrees")
            text += f"; {len(d)} disagree by {float(d.min()):.2f}–{float(d.max()):.2f} px"
        if counts:
            text += "; " + ", ".join(f"{v} {k.replace('_', ' ')}" for k, v in counts.items())
        return text

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form (NaN → ``None``), as stored in the cube's metadata."""

        def arr(a: np.ndarray, nd: int = 3) -> list:
            return [None if not np.isfinite(v) else round(float(v), nd) for v in a.ravel()] \
                if a.ndim == 1 else [arr(r, nd) for r in a]

        return {
            "view_shift_px": arr(self.view_shift_px),
            "correlation": arr(self.correlation),
            "sensor_shift_px": None if self.sensor_shift_px is None
            else arr(self.sensor_shift_px),
            "sensor_rotation_deg": None if self.sensor_rotation_deg is None
            else round(float(self.sensor_rotation_deg), 4),
            "residual_px": arr(self.residual_px),
            "max_view_shift_px": round(float(self.max_view_shift_px), 3),
            "measured_views": self.measured_views,
            "view_status": [str(v) for v in self.view_status],
            "agreeing_views": self.agreeing_views,
            "orientations": self.orientations,
            "textured_views": self.textured_views,
            "spread_px": round(self.spread_px, 3),
            "agree_px": DRIFT_AGREE_PX,
            "min_views": self.min_views,
            "range_px": None if not math.isfinite(self.range_px) else round(self.range_px, 2),
            "predicted_view_shift_px": round(float(self.predicted_view_shift_px), 3),
            "agreement": self.agreement(),
            "refused": self.refusal,
        }


def motion_points(points: Tensor, shift_px: Any, rotation_deg: float,
                  centre_px: tuple[float, float], inverse: bool = False) -> Tensor:
    """``M(p) = c + R(θ)(p − c) + t`` (or ``M⁻¹``) of ``(…, 2)`` sensor points (px)."""
    t = torch.as_tensor(np.asarray(shift_px, dtype=np.float64), dtype=points.dtype,
                        device=points.device)
    c = torch.tensor(centre_px, dtype=points.dtype, device=points.device)
    a = math.radians(rotation_deg)
    rot = torch.tensor([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]],
                       dtype=points.dtype, device=points.device)
    if inverse:
        return (points - c - t) @ rot + c  # R⁻¹ = Rᵀ; (q R) = (Rᵀ qᵀ)ᵀ
    return (points - c) @ rot.T + c + t


def _centre(sensor_size: tuple[int, int]) -> tuple[float, float]:
    H, W = sensor_size
    return ((W - 1) / 2.0, (H - 1) / 2.0)


def _grid_px(sens: Any) -> Tensor:
    """The bundle's sampling grid as sensor px, ``(V, P, 2)`` float64."""
    from kornia.geometry.conversions import denormalize_pixel_coordinates

    H, W = sens.sensor_size
    return denormalize_pixel_coordinates(sens.grid()[0].double(), H, W)


def _block_factor(frame_size: tuple[int, int]) -> int:
    """The alignment's block size ``f``: the largest power of two up to :data:`_MAX_BLOCK`
    that leaves the reference frame at least :data:`_MIN_BLOCKS` blocks on its shorter side."""
    f = 1
    while 2 * f <= _MAX_BLOCK and min(frame_size) // (2 * f) >= _MIN_BLOCKS:
        f *= 2
    return f


def _homography_np(h: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """``apply_homography`` for one ``(3, 3)`` matrix and ``(N, 2)`` points, elementwise in
    NumPy (float64): no BLAS call, so no thread pool woken for a few thousand points."""
    x, y = pts[:, 0], pts[:, 1]
    z = h[2, 0] * x + h[2, 1] * y + h[2, 2]
    return np.stack([(h[0, 0] * x + h[0, 1] * y + h[0, 2]) / z,
                     (h[1, 0] * x + h[1, 1] * y + h[1, 2]) / z], 1)


def _jacobian(hs: np.ndarray, v: int, pts: np.ndarray, centre: tuple[float, float]) -> np.ndarray:
    """``(N, 2, 3)``: ``∂(u_v − u_0)/∂(t_x, t_y, θ°)`` at reference sensor points ``(N, 2)``, as
    finite differences (a 1 px shift, a 0.01° turn) of ``u_v(x) = H_v(M(H_v⁻¹ x)) − x``."""
    c = np.asarray(centre, np.float64)

    def disp(k: int, t: tuple[float, float], deg: float) -> np.ndarray:
        src = _homography_np(np.linalg.inv(hs[k]), pts)
        a = math.radians(deg)
        rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        return _homography_np(hs[k], (src - c) @ rot.T + c + np.asarray(t)) - pts

    cols = [(disp(v, t, deg) - disp(0, t, deg)) * scale
            for t, deg, scale in (((1.0, 0.0), 0.0, 1.0), ((0.0, 1.0), 0.0, 1.0),
                                  ((0.0, 0.0), 0.01, 100.0))]
    return np.stack(cols, axis=2)


@dataclass
class _Pair:
    """What a view's alignment to the reference view needs that no frame changes (block px)."""

    view: int
    box: tuple[int, int, int, int]  # y0, y1, x0, x1 of the compared crop
    mask: np.ndarray  # (y1 − y0, x1 − x0) uint8, the common area
    window: np.ndarray  # Hanning window of the crop, float32
    points: tuple[np.ndarray, np.ndarray]  # (ys, xs) of ≈ 2000 common blocks (the fit's weights)
    jacobian: np.ndarray  # (N, 2, 3) at those blocks' centres (:func:`_jacobian`)


@dataclass
class _Static:
    """Per-bundle part of the drift check (masks, crops, windows, the fit's Jacobians)."""

    key: tuple
    factor: int
    size: tuple[int, int]  # (h // f, w // f) blocks
    block_of_pixel: tuple[Tensor | None, Tensor]  # (valid pixels inside the blocks or None:
    # all, and their block's flat index)
    inner: list[np.ndarray]  # per view, uint8: the view's blocks shrunk by the erosion
    taper: list[np.ndarray | None]  # per view, float32 0–1 (None: nothing of the view left)
    pairs: list[_Pair]
    range_px: float  # the measurable sensor translation (DriftEstimate.range_px)


def _present(sens: Any) -> np.ndarray:
    """``(V, h, w)`` bool: the reference pixels each view observes (any colour)."""
    h, w = sens.frame_size
    V = sens.num_views
    present = torch.zeros((V, h * w), dtype=torch.bool)
    present[:, sens.pixel_index.cpu()] = sens.obs_mask.view(-1, V, 3).any(2).T.cpu()
    return present.view(V, h, w).numpy()


def _refs(tensors: tuple) -> tuple:
    """Weak references to ``tensors`` (a cache key that neither keeps them alive nor matches
    a later tensor at the same address)."""
    return tuple(weakref.ref(t) for t in tensors)


def _same(refs: tuple, tensors: tuple) -> bool:
    return len(refs) == len(tensors) and all(r() is t for r, t in zip(refs, tensors, strict=True))


def _static(sens: Any) -> _Static:
    """:class:`_Static` of ``sens``, kept on it (shared with its copies of the same masks and
    homographies; rebuilt when those differ)."""
    tensors = (sens.obs_mask, sens.pixel_index, sens.homographies)
    bbox = tuple(int(v) for v in sens.reference_bbox)
    cache = getattr(sens, "_drift_static", None)
    st = cache.get("static") if isinstance(cache, dict) else None
    if st is not None and st.key[1] == bbox and _same(st.key[0], tensors):
        return st
    st = _build_static(sens, (_refs(tensors), bbox))
    if isinstance(cache, dict):
        cache["static"] = st
    return st


def _build_static(sens: Any, key: tuple) -> _Static:
    import cv2  # lazy: OpenCV only when a frame's drift is measured, not at import

    f = _block_factor(sens.frame_size)
    present = _present(sens)
    V, h, w = present.shape
    hf, wf = h // f, w // f
    # a block belongs to a view when all its pixels do
    blocks = present[:, :hf * f, :wf * f].reshape(V, hf, f, wf, f).all((2, 4))
    erode, taper_px, margin = (max(1, round(v / f)) for v in (_ERODE_PX, _TAPER_PX, _MARGIN_PX))
    inner, taper = [], []
    for v in range(V):
        m = cv2.erode(blocks[v].astype(np.uint8), np.ones((2 * erode + 1,) * 2, np.uint8))
        inner.append(m)
        taper.append(np.clip(cv2.distanceTransform(m, cv2.DIST_L2, 3) / taper_px, 0, 1)
                     .astype(np.float32) if m.any() else None)
    kernel = np.ones((2 * (erode + taper_px + margin) + 1,) * 2, np.uint8)
    hs = sens.homographies.detach().cpu().double().numpy()
    x0, y0 = sens.reference_bbox[:2]
    centre = _centre(sens.sensor_size)
    pad = margin + taper_px
    pairs = []
    for v in range(1, V):
        common = cv2.erode((blocks[v] & blocks[0]).astype(np.uint8), kernel) > 0
        if int(common.sum()) * f * f < _MIN_PIXELS:
            continue
        ys, xs = np.nonzero(common)
        by0, bx0 = max(0, int(ys.min()) - pad), max(0, int(xs.min()) - pad)
        by1, bx1 = min(hf, int(ys.max()) + 1 + pad), min(wf, int(xs.max()) + 1 + pad)
        if min(by1 - by0, bx1 - bx0) < 16:
            continue  # too small to align
        step = max(1, len(ys) // 2000)
        ys, xs = ys[::step], xs[::step]
        pts = np.stack([xs * f + (f - 1) / 2 + x0, ys * f + (f - 1) / 2 + y0], 1).astype(
            np.float64)  # block centres, reference sensor px
        pairs.append(_Pair(
            view=v, box=(by0, by1, bx0, bx1),
            mask=np.ascontiguousarray(common[by0:by1, bx0:bx1]).astype(np.uint8),
            window=cv2.createHanningWindow((bx1 - bx0, by1 - by0), cv2.CV_32F),
            points=(ys, xs), jacobian=_jacobian(hs, v, pts, centre)))
    pix = sens.pixel_index.cpu()
    ys, xs = pix // w, pix % w
    inside = (ys < hf * f) & (xs < wf * f)
    sel = None if bool(inside.all()) else torch.nonzero(inside)[:, 0]
    if sel is not None:
        ys, xs = ys[sel], xs[sel]
    block_of_pixel = (sel, (ys // f) * wf + xs // f)
    # the sensor translation that moves the most sensitive view by the largest measurable shift
    gain = max((float(np.linalg.norm(p.jacobian[:, :, :2].mean(0), 2)) for p in pairs),
               default=0.0)
    range_px = _MAX_SHIFT_PX / gain if gain > 0 else math.inf
    return _Static(key, f, (hf, wf), block_of_pixel, inner, taper, pairs, range_px)


def _view_images(sens: Any, image: Tensor, st: _Static) -> np.ndarray:
    """The frame's colour sum warped to the reference frame in every view on the bundle's
    valid pixels (0 elsewhere), averaged over ``f × f`` blocks: ``(V, h // f, w // f)``
    float32."""
    dtype = image.dtype if image.dtype in (torch.float32, torch.float64) else torch.float32
    grid = sens.grid().to(device=image.device, dtype=dtype)  # (1, V, P, 2) normalised (x, y)

    def warp(gray: Tensor) -> Tensor:
        return F.grid_sample(gray[None, None].to(dtype), grid, mode="bilinear",
                             padding_mode="zeros", align_corners=True)[0, 0]  # (V, P)

    s = warp(image.sum(0))
    if not bool(torch.isfinite(s).all()):  # a sample touched a NaN or ±inf: those count as 0
        s = warp(torch.nan_to_num(image).sum(0))
    V = s.shape[0]
    hf, wf = st.size
    sel, index = st.block_of_pixel
    if sel is not None:  # pixels beyond the last whole block
        s = s[:, sel.to(s.device)]
    blocks = torch.zeros((V, hf * wf), dtype=torch.float32, device=s.device)
    blocks.index_add_(1, index.to(s.device), s.float())
    imgs = blocks.view(V, hf, wf) / (st.factor**2)
    return imgs.cpu().numpy()


def _features(img: np.ndarray, inner: np.ndarray, taper: np.ndarray | None) -> np.ndarray:
    """Gradient magnitude of ``img`` over its mean on the view (``inner``), tapered to 0 at the
    view's edge: ``(h, w)`` float32."""
    import cv2  # lazy: OpenCV only when a frame's drift is measured, not at import

    if taper is None:
        return np.zeros_like(img, np.float32)
    mean = cv2.mean(img, inner)[0]
    g = img / np.float32(mean) if mean > 0 else img
    mag = cv2.magnitude(cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3),
                        cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3))
    return mag * taper


def _align(ref: np.ndarray, img: np.ndarray, pair: _Pair,
           f: int) -> tuple[np.ndarray, float, str]:
    """Shift ``d`` (px) with ``img(x) ≈ ref(x + d)`` on the pair's common area, from ``f × f``
    block images, its ECC correlation and the view's status (a key of :data:`VIEW_STATUSES`;
    ``d`` is ``(nan, nan)`` unless ``"agrees"``, which :func:`estimate_drift` may revise)."""
    import cv2  # lazy: OpenCV only when a frame's drift is measured, not at import

    nan2 = np.full(2, np.nan)
    y0, y1, x0, x1 = pair.box
    a = np.ascontiguousarray(ref[y0:y1, x0:x1])
    b = np.ascontiguousarray(img[y0:y1, x0:x1])
    mask = pair.mask
    ma, mb = cv2.mean(a, mask)[0], cv2.mean(b, mask)[0]
    if min(ma, mb) < _MIN_TEXTURE:
        return nan2, float("nan"), "no_texture"  # a flat field
    on = mask.astype(np.float32)
    (sx, sy), _ = cv2.phaseCorrelate((a - np.float32(ma)) * on, (b - np.float32(mb)) * on,
                                     pair.window)
    # phaseCorrelate: b(x) ≈ a(x − s); ECC's warp maps the template (ref) to the input:
    # b(x + w) ≈ a(x), so w = s to begin with
    warp = np.array([[1, 0, sx], [0, 1, sy]], np.float32)
    if not (abs(sx) < 3 * _MARGIN_PX / f and abs(sy) < 3 * _MARGIN_PX / f):
        warp[:, 2] = 0
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, _ECC_ITERATIONS, _ECC_EPS)
    try:
        rho, warp = cv2.findTransformECC(a, b, warp, cv2.MOTION_TRANSLATION, crit, mask, 3)
    except cv2.error:
        return nan2, float("nan"), "not_converged"
    if not (np.isfinite(rho) and rho >= DRIFT_MIN_CORRELATION):
        return nan2, float(rho), "low_correlation"
    # b(x + w) ≈ a(x) ⇔ img(x) ≈ ref(x − w): d = −w (blocks → px)
    d = -warp[:, 2].astype(np.float64) * f
    if not np.hypot(*d) <= _MAX_SHIFT_PX:
        return nan2, float(rho), "beyond_range"
    return d, float(rho), "agrees"


def _fit(K: list[np.ndarray], y: list[np.ndarray], w: list[float]) -> np.ndarray:
    """``(t_x, t_y, θ°)``: the weighted least-squares fit of the views' shifts ``y`` (each
    ``(2,)``) to their sensitivities ``K`` (each ``(2, 3)``), weights ``w``; ``θ`` is 0 (not
    fitted) from one view."""
    Km, ym = np.concatenate(K, 0), np.concatenate(y, 0)
    sw = np.sqrt(np.repeat(np.asarray(w, np.float64), 2))
    if len(K) >= 2:
        return np.linalg.lstsq(Km * sw[:, None], ym * sw, rcond=None)[0]
    return np.append(np.linalg.lstsq(Km[:, :2] * sw[:, None], ym * sw, rcond=None)[0], 0.0)


def estimate_drift(sens: Any, image: Tensor, min_views: int = DRIFT_MIN_VIEWS) -> DriftEstimate:
    """Measure each view's shift against the reference view and fit a sensor motion.

    The motion is fitted to the views that agree: the view farthest from the fit is left out
    (``"disagrees"``) and the rest fitted again, while one is farther than
    :data:`DRIFT_AGREE_PX`. The estimate is refused (:attr:`DriftEstimate.refusal`) when views
    had texture to align and fewer than ``min_views`` agree, when no more agree than disagree,
    or when the fitted motion moves a view with texture beyond the measurable
    :data:`DRIFT_MAX_VIEW_SHIFT_PX`.

    Args:
        sens: the bundle's :class:`~hsi_torch.recon.sensing.BundleSensing` (its sampling grid
            is what the frame is warped with: pass a corrected one to measure what is left).
        image: ``(3, H, W)`` linear RGB of one frame (sensor size, any device and dtype).
        min_views: the fewest agreeing views for a trusted estimate (``drift_min_views``).

    Returns:
        :class:`DriftEstimate`.
    """
    if image.ndim != 3 or image.shape[0] != 3:
        raise ValueError(f"image must be (3, H, W) linear RGB, got {tuple(image.shape)}")
    st = _static(sens)
    f = st.factor
    imgs = _view_images(sens, image.detach(), st)
    V = imgs.shape[0]
    ref = _features(imgs[0], st.inner[0], st.taper[0])
    shifts = np.full((V, 2), np.nan)
    corr = np.full(V, np.nan)
    status = np.full(V, "no_overlap", dtype=object)
    shifts[0], corr[0], status[0] = 0.0, 1.0, "reference"
    rows: dict[int, np.ndarray] = {}  # view → (2, 3) its sensitivity, weighted by the texture
    for pair in st.pairs:
        v = pair.view
        shifts[v], corr[v], status[v] = _align(
            ref, _features(imgs[v], st.inner[v], st.taper[v]), pair, f)
        if status[v] != "no_texture":
            ys, xs = pair.points
            w = ref[ys, xs].astype(np.float64) + 1e-6
            rows[v] = np.einsum("n,nij->ij", w, pair.jacobian) / w.sum()
    used = [v for v in range(1, V) if status[v] == "agrees"]
    p: np.ndarray | None = None
    while used:  # fit; leave out the view farthest from the fit while one is beyond the limit
        p = _fit([rows[v] for v in used], [shifts[v] for v in used], [corr[v] for v in used])
        far = {v: float(np.hypot(*(shifts[v] - rows[v] @ p))) for v in used}
        worst = max(far, key=far.__getitem__)
        if far[worst] <= DRIFT_AGREE_PX or len(used) == 1:
            break
        status[worst] = "disagrees"
        used.remove(worst)
    resid = np.full(V, np.nan)
    t: np.ndarray | None = None
    theta: float | None = None
    predicted = 0.0
    if p is not None:
        t, theta = p[:2], float(p[2]) if len(used) >= 2 else None
        for v in range(1, V):
            if np.isfinite(shifts[v, 0]):
                resid[v] = float(np.hypot(*(shifts[v] - rows[v] @ p)))
        resid[0] = 0.0
        predicted = max(float(np.hypot(*(k @ p))) for k in rows.values())
    mags = np.hypot(shifts[:, 0], shifts[:, 1])
    mx = float(np.nanmax(mags)) if np.isfinite(mags[1:]).any() else 0.0
    est = DriftEstimate(shifts, corr, t, theta, resid, mx, status, st.range_px, predicted,
                        int(min_views), _orientations([rows[v] for v in used]))
    est.refusal = _refusal(est)
    return est


def _orientations(rows: list[np.ndarray]) -> int:
    """How many groups of alike sensitivities ``rows`` (each ``(2, 3)``) fall into: two views
    are alike when their translation columns differ by less than a quarter of the larger."""
    groups: list[np.ndarray] = []
    for k in rows:
        j = k[:, :2]
        if not any(np.linalg.norm(j - g) < 0.25 * max(np.linalg.norm(j), np.linalg.norm(g))
                   for g in groups):
            groups.append(j)
    return len(groups)


def _refusal(est: DriftEstimate) -> str | None:
    """Why ``est`` cannot be trusted (:attr:`DriftEstimate.refusal`), or ``None``."""
    textured = est.textured_views
    if textured == 0:
        return None  # nothing to align (a flat field): nothing measured, nothing to refuse
    n = est.agreeing_views
    disagree = int((est.view_status == "disagrees").sum())
    why = []
    if n < est.min_views:
        why.append(f"fewer than drift_min_views={est.min_views}")
    elif n <= disagree:
        why.append("no more views agree than disagree")
    elif est.orientations < 2:
        why.append("the views that agree all see the scene in one orientation (a repeating "
                   "pattern's false match looks alike in them)")
    if est.predicted_view_shift_px > DRIFT_MAX_VIEW_SHIFT_PX:
        why.append(f"the fitted motion would move a view by {est.predicted_view_shift_px:.1f} px,"
                   f" beyond the {DRIFT_MAX_VIEW_SHIFT_PX:g} px search window")
    if not why:
        return None
    fitted = "" if est.sensor_shift_px is None else (
        f"; fitted shift [{est.sensor_shift_px[0]:.2f}, {est.sensor_shift_px[1]:.2f}] px"
        + ("" if est.sensor_rotation_deg is None
           else f", rotation {est.sensor_rotation_deg:.3f}°"))
    return (f"drift not measurable: {est.agreement()}{fitted}: {'; '.join(why)}; at most "
            f"±{est.range_px:.1f} px of sensor motion can be measured, less on a repeating "
            "pattern (recalibrate if the sensor moved more)")


def _sample_box(sens: Any) -> Tensor | None:
    """``(4, 2)`` corners (sensor px, float64) of the box around the views' samples, or
    ``None`` without any; kept on ``sens`` for its grid and masks."""
    grid = sens.grid()
    cache = getattr(sens, "_drift_static", None)
    hit = cache.get("sample_box") if isinstance(cache, dict) else None
    if hit is not None and _same(hit[0], (grid, sens.obs_mask)):
        return hit[1]
    px = _grid_px(sens)[sens.obs_mask.view(-1, sens.num_views, 3).any(2).T.to(
        grid.device)]  # (n, 2) the views' samples
    corners = None
    if px.numel():
        lo, hi = px.min(0).values, px.max(0).values
        corners = torch.stack([lo, torch.stack([hi[0], lo[1]]), torch.stack([lo[0], hi[1]]), hi])
    if isinstance(cache, dict):
        cache["sample_box"] = (_refs((grid, sens.obs_mask)), corners)
    return corners


def drift_motion_px(sens: Any, est: DriftEstimate) -> float:
    """The largest displacement (px) the fitted sensor motion gives a sensor pixel that a view
    uses: ``max |M(p) − p|`` over the corners of the box around the views' samples (the
    maximum of ``|M(p) − p|`` over a box is at a corner). 0 without a fit."""
    if est.sensor_shift_px is None:
        return 0.0
    corners = _sample_box(sens)
    if corners is None:
        return 0.0
    moved = motion_points(corners, est.sensor_shift_px, est.sensor_rotation_deg or 0.0,
                          _centre(sens.sensor_size))
    return float((moved - corners).norm(dim=1).max())


def corrected_sensing(sens: Any, shift_px: Any, rotation_deg: float) -> Any:
    """A copy of ``sens`` whose sampling grid undoes a sensor motion ``(t, θ)``.

    Every view samples the frame at ``M⁻¹(p)`` instead of the calibrated ``p``
    (:func:`motion_points`); ``sample_inside (V, P)`` marks the samples that stay on the sensor
    (the others are dropped from the frame's observations). The factorisation, ``A`` and the
    static masks are shared with ``sens``.
    """
    H, W = sens.sensor_size
    # M⁻¹(p) = (p − c − t) R + c (row vectors, as motion_points(inverse=True)), with the sensor
    # px p = (g + 1)·half of the normalised grid g: one affine map of g, g' = g·A + b
    half = np.array([(W - 1) / 2.0, (H - 1) / 2.0])
    c, t = np.asarray(_centre(sens.sensor_size)), np.asarray(shift_px, np.float64)
    a = math.radians(float(rotation_deg))
    rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    A = half[:, None] * rot / half[None, :]
    b = ((half - c - t) @ rot + c) / half - 1.0
    g = sens.grid()  # (1, V, P, 2)
    A_t = torch.as_tensor(A, device=g.device)
    b_t = torch.as_tensor(b, device=g.device)
    grid = torch.empty(g.shape, dtype=sens.dtype, device=g.device)
    inside = torch.empty(g.shape[1:3], dtype=torch.bool, device=g.device)
    for v in range(g.shape[1]):  # view by view: float64 temporaries that stay in the cache
        moved = torch.addmm(b_t, g[0, v].double(), A_t)
        grid[0, v] = moved
        torch.all(moved.abs() <= 1, -1, out=inside[v])  # 0 ≤ x ≤ W − 1 and 0 ≤ y ≤ H − 1
    return dataclasses.replace(sens, sample_grid=grid, sample_inside=inside.to(sens.device))


def drift_decision(
    est: DriftEstimate, motion_px: float, refine: bool | str, warn_px: float | None,
    source: str | None = None,
) -> bool:
    """Whether to correct a frame's measured drift (what is said of it: :func:`drift_finding`).

    Args:
        est: the frame's :func:`estimate_drift`.
        motion_px: :func:`drift_motion_px` of ``est`` (the largest displacement of a pixel a
            view uses, px).
        refine: ``refine_registration`` (``True``, ``False`` or ``"auto"``).
        warn_px: ``drift_warn_px`` (px; ``None``: ``"auto"`` corrects any reliable drift).
        source: what the frame is (a file), for the error.

    Returns:
        ``True`` to correct: ``refine`` is ``True``, or ``"auto"`` and the drift is measured
        reliably and moves a view's pixel by more than ``warn_px``.

    Raises:
        DriftError: ``refine is True`` and the drift cannot be measured (``est.refusal``), with
            its ``drift.unmeasurable`` error finding.
    """
    if refine is False:
        return False
    if est.refusal is not None:
        if refine is True:
            raise DriftError(f"{source or 'frame'}: refine_registration: {est.refusal}",
                             [drift_finding(est.to_dict(), True, warn_px, source)])
        return False
    if est.textured_views == 0 or est.sensor_shift_px is None:
        return False
    return refine is True or warn_px is None or motion_px > warn_px


def drift_finding(
    drift: Mapping[str, Any], refine: bool | str, warn_px: float | None,
    source: str | None = None, fit_residual: float | None = None,
    fit_warning: float | None = None,
) -> Finding | None:
    """The one ``drift.*`` finding of a frame (stored as ``stats["drift"]["finding"]`` and, when
    it is more than a measurement within its limit, among the cube's findings).

    Args:
        drift: the frame's ``stats["drift"]`` (:meth:`DriftEstimate.to_dict` plus
            ``sensor_motion_px`` and ``corrected``; missing keys read as unknown).
        refine: ``refine_registration``; warn_px: ``drift_warn_px`` (px, or ``None``).
        source: what the frame is (a file).
        fit_residual, fit_warning: the frame's relative fit residual and
            ``fit_residual_warning``: a drift that cannot be measured while the residual is
            above its warning is an error (neither the bundle nor a drift explains the capture).

    Returns:
        ``drift.unmeasurable`` (warning; error under ``refine is True`` or with the residual
        above its warning), ``drift.no_texture`` (warning under ``refine is True``, else info),
        ``drift.corrected`` (info), ``drift.moved`` (warning: above ``warn_px``, not corrected),
        ``drift.below_warning`` (info: within ``warn_px``, not corrected), or ``None`` (no
        motion measured). Not escalated.
    """
    refused = drift.get("refused")
    if isinstance(refused, str):  # not measurable: no motion is claimed
        fit = fit_residual
        unexplained = isinstance(fit, float) and fit_warning is not None and fit > fit_warning
        if unexplained and refine is not True:
            tail = (f"; with the fit residual {fit:.3f} > fit_residual_warning={fit_warning:g}, "
                    "neither the bundle nor a drift of the sensor explains the capture: refused")
        else:
            tail = "" if refine is True else ", and refine_registration would refuse the frame"
        return Finding(
            "drift.unmeasurable", "error" if refine is True or unexplained else "warning",
            f"{refused}; not corrected{tail}", measured=drift.get("agreeing_views"),
            limit=drift.get("min_views"), source=source,
            fix="check that the bundle is this device's, or recalibrate (grid shots)")
    if drift.get("textured_views") == 0:
        if refine is True:
            return Finding("drift.no_texture", "warning", "refine_registration: nothing "
                           "corrected, no view has texture to measure the drift from (a flat "
                           "field)", measured=0, limit=1, source=source,
                           fix="measure the drift on a textured capture of the same session")
        return Finding("drift.no_texture", "info", "no view has texture to measure the drift "
                       "from (a flat field): nothing measured, nothing corrected", measured=0,
                       limit=1, source=source)  # fmt: skip
    moved = drift.get("sensor_motion_px")
    if not isinstance(moved, (int, float)) or drift.get("sensor_shift_px") is None:
        return None
    above = warn_px is not None and moved > warn_px
    agree = drift.get("agreement")
    detail = (f"fitted shift {drift.get('sensor_shift_px')} px, rotation "
              f"{drift.get('sensor_rotation_deg')}°, from {drift.get('measured_views')} views "
              "aligned to the reference view" + (f"; {agree}" if isinstance(agree, str) else ""))
    limit = "" if warn_px is None else f" {'>' if above else '<='} drift_warn_px={warn_px:g}"
    what = f"the sensor moved since calibration: up to {moved:.2f} px{limit} ({detail})"
    m = round(float(moved), 3)
    if drift.get("corrected"):
        return Finding("drift.corrected", "info", what + "; corrected (refine_registration)",
                       measured=m, limit=warn_px, source=source)
    if above:
        return Finding("drift.moved", "warning", what + "; the views are misaligned and the "
                       "spectra are biased", measured=m, limit=warn_px,
                       fix="--set refine_registration=true (or auto, the default) corrects it, "
                       "or recalibrate", source=source)  # fmt: skip
    if warn_px is None:  # not corrected, and no level to compare with: nothing to say
        return None
    return Finding("drift.below_warning", "info", what + "; within it, not corrected",
                   measured=m, limit=warn_px, source=source)
