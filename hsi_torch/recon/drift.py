"""Drift of the sensor since calibration, measured from the scene itself, and its correction.

The views of one capture see the same scene. Warped into the reference frame with the bundle's
registration they line up, unless the sensor has moved relative to the optics since the
calibration: then every view's content is displaced in the reference frame, and by a different
amount, because each view's homography maps a sensor motion differently (a mirrored view moves
the other way, a tapered view by a scaled amount).

**What is measured** (:func:`estimate_drift`): each view, warped to the reference frame by the
bundle's own sampling grid, is aligned to the reference view (view 0) by a translation —
phase correlation (``cv2.phaseCorrelate``) for a first guess, then OpenCV's enhanced correlation
coefficient (``cv2.findTransformECC``, ``MOTION_TRANSLATION``) on the common area of the two
views — of their *gradient-magnitude* images, each normalised by its mean: the views see the
scene through different spectral filters, so their intensities differ, but the edges lie in the
same places. The result is a per-view shift ``d_v`` (reference-frame px, ``(x, y)``): view
``v``'s content at ``x`` is the reference view's content at ``x + d_v`` (``d_0 = 0``).

**What is corrected** (:func:`corrected_sensing`): a rigid motion of the sensor,
``p' = c + R(θ)(p − c) + t`` (its pixel ``p`` sees what the calibrated sensor saw at ``p'``;
``c`` the sensor centre). With the bundle's ``H_v`` (view sensor px → reference sensor px), it
displaces view ``v``'s content in the reference frame by ``u_v(x) = H_v(M(H_v⁻¹ x)) − x``; the
measured ``d_v`` are the differences ``u_v − u_0`` over each view's common area. ``(t, θ)`` is
their weighted least-squares fit (3 unknowns from 2 numbers per view; the views' different
orientations make the absolute motion, the reference view's included, measurable). The
correction samples view ``v`` of the frame at ``M⁻¹(H_v⁻¹ x)`` instead of ``H_v⁻¹ x`` — exact
for a rigid sensor motion, for every view, including the reference view and the rotation inside
each view — and a sample whose moved position falls off the sensor is dropped from that frame
(the pixels concerned are solved again with their own observation mask). The spectral model
``A`` is unchanged: the optics did not move, each reference pixel still sees the same scene
point through the same filters.

**What it cannot see**: motion of parts of the optics relative to each other (a kaleidoscope
that shifts against the relay lens changes each view's homography in its own way; that shows
as a large per-view fit residual, :attr:`DriftEstimate.residual_px`, but is not corrected),
motion along the optical axis (a change of scale), drift within a view finer than the
translation measured per view, and anything in a scene without texture (a flat white field:
no view is measured, nothing is corrected, ``DriftEstimate.measured_views == 0``).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from hsi_torch.optics.geometry import apply_homography

__all__ = [
    "DriftEstimate",
    "estimate_drift",
    "corrected_sensing",
    "DRIFT_MIN_CORRELATION",
    "motion_points",
    "drift_motion_px",
]

#: ECC correlation coefficient below which a view's alignment is not trusted (left out of the
#: fit and reported as ``null``).
DRIFT_MIN_CORRELATION = 0.5
#: px: the views' masks are shrunk by this much before their gradients are taken (the view
#: boundary's own edge is not scene texture), then tapered to 0 over :data:`_TAPER_PX`.
_ERODE_PX = 2
_TAPER_PX = 6
#: px: the common area compared is shrunk by this much more (the largest drift measured well
#: is about this size).
_MARGIN_PX = 8
#: fewest common pixels for a view to be measured
_MIN_PIXELS = 400
#: least mean gradient magnitude (relative to the view's mean) for a view to have texture
_MIN_TEXTURE = 1e-4
#: px: a measured shift larger than this is not trusted (beyond what the common area allows)
_MAX_SHIFT_PX = 2 * _MARGIN_PX


@dataclass
class DriftEstimate:
    """The drift of one frame (see the module docstring).

    Attributes:
        view_shift_px: ``(V, 2)`` float64, measured ``d_v = (dx, dy)`` of every view relative to
            the reference view, reference-frame px; NaN where not measured (too few common
            pixels, too little texture, correlation below :data:`DRIFT_MIN_CORRELATION`, a
            shift beyond 16 px).
        correlation: ``(V,)`` ECC correlation coefficient of each view's alignment (NaN: not
            measured; 1 for the reference view).
        sensor_shift_px: ``(2,)`` fitted sensor translation ``t`` (sensor px), or ``None``
            without at least one measured view.
        sensor_rotation_deg: fitted rotation ``θ`` about the sensor centre (degrees), or
            ``None`` (fewer than two measured views: only ``t`` is fitted, ``θ`` is 0).
        residual_px: ``(V,)`` ``|d_v − (u_v − u_0)|`` after the fit (NaN: not measured).
        max_view_shift_px: the largest measured ``|d_v|`` (0 without any).
    """

    view_shift_px: np.ndarray
    correlation: np.ndarray
    sensor_shift_px: np.ndarray | None
    sensor_rotation_deg: float | None
    residual_px: np.ndarray
    max_view_shift_px: float

    @property
    def measured_views(self) -> int:
        """Views other than the reference whose shift was measured."""
        return int(np.isfinite(self.view_shift_px[1:, 0]).sum())

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


def _view_images(sens: Any, image: Tensor) -> tuple[np.ndarray, np.ndarray]:
    """The frame's colour sum warped to the reference frame in every view, on the bundle's
    valid pixels: ``(V, h, w)`` float32 (0 elsewhere) and ``(V, h, w)`` bool view presence."""
    from kornia.geometry.transform import remap

    h, w = sens.frame_size
    grid = sens.grid().to(device=image.device, dtype=image.dtype)
    gray = image.sum(0, keepdim=True).unsqueeze(0)  # (1, 1, H, W)
    s = remap(gray, grid[..., 0], grid[..., 1], mode="bilinear", padding_mode="zeros",
              align_corners=True, normalized_coordinates=True)[0, 0]  # (V, P)
    V = s.shape[0]
    pix = sens.pixel_index.to(s.device)
    imgs = torch.zeros((V, h * w), dtype=torch.float32, device=s.device)
    imgs[:, pix] = s.float()
    present = torch.zeros((V, h * w), dtype=torch.bool, device=s.device)
    present[:, pix] = sens.obs_mask.view(-1, V, 3).any(2).T.to(s.device)
    return (imgs.view(V, h, w).cpu().numpy(),
            present.view(V, h, w).cpu().numpy())


def _features(img: np.ndarray, present: np.ndarray) -> np.ndarray:
    """Gradient magnitude of ``img`` over its mean on the view, tapered to 0 at the view's
    edge: ``(h, w)`` float32."""
    import cv2  # lazy: OpenCV only when a frame's drift is measured, not at import

    m = present.astype(np.uint8)
    inner = cv2.erode(m, np.ones((2 * _ERODE_PX + 1,) * 2, np.uint8))
    if not inner.any():
        return np.zeros_like(img, np.float32)
    mean = float(img[inner > 0].mean())
    g = img / mean if mean > 0 else img
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3)
    mag = np.sqrt(gx * gx + gy * gy)
    taper = np.clip(cv2.distanceTransform(inner, cv2.DIST_L2, 3) / _TAPER_PX, 0, 1)
    return (mag * taper).astype(np.float32)


def _align(ref: np.ndarray, img: np.ndarray, common: np.ndarray) -> tuple[np.ndarray, float]:
    """Shift ``d`` with ``img(x) ≈ ref(x + d)`` on ``common`` and its ECC correlation
    (``(nan, nan), nan`` when not measurable)."""
    import cv2  # lazy: OpenCV only when a frame's drift is measured, not at import

    ys, xs = np.nonzero(common)
    y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
    pad = _MARGIN_PX + _TAPER_PX
    y0, x0 = max(0, y0 - pad), max(0, x0 - pad)
    y1, x1 = min(ref.shape[0], y1 + pad), min(ref.shape[1], x1 + pad)
    a = np.ascontiguousarray(ref[y0:y1, x0:x1])
    b = np.ascontiguousarray(img[y0:y1, x0:x1])
    mask = np.ascontiguousarray(common[y0:y1, x0:x1]).astype(np.uint8)
    if min(a.shape) < 16 or min(a[mask > 0].mean(), b[mask > 0].mean()) < _MIN_TEXTURE:
        return np.full(2, np.nan), float("nan")  # too small, or no texture (a flat field)
    win = cv2.createHanningWindow((a.shape[1], a.shape[0]), cv2.CV_32F)
    ma, mb = a[mask > 0].mean(), b[mask > 0].mean()
    (sx, sy), _ = cv2.phaseCorrelate((a - ma) * (mask > 0), (b - mb) * (mask > 0), win)
    # phaseCorrelate: b(x) ≈ a(x − s); ECC's warp maps the template (ref) to the input:
    # b(x + w) ≈ a(x), so w = s to begin with
    warp = np.array([[1, 0, sx], [0, 1, sy]], np.float32)
    if not (abs(sx) < 3 * _MARGIN_PX and abs(sy) < 3 * _MARGIN_PX):
        warp[:, 2] = 0
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-5)
    try:
        rho, warp = cv2.findTransformECC(a, b, warp, cv2.MOTION_TRANSLATION, crit, mask, 3)
    except cv2.error:
        return np.full(2, np.nan), float("nan")
    # b(x + w) ≈ a(x) ⇔ img(x) ≈ ref(x − w): d = −w
    d = -warp[:, 2].astype(np.float64)
    if not np.hypot(*d) <= _MAX_SHIFT_PX:
        return np.full(2, np.nan), float(rho)
    return d, float(rho)


def _displacements(sens: Any, pts_ref: Tensor, v: int, shift: Any, rot_deg: float) -> Tensor:
    """``u_v(x)`` (reference px) of reference sensor points ``(N, 2)`` for the motion."""
    Hv = sens.homographies[v].to(device=pts_ref.device, dtype=torch.float64)
    src = apply_homography(torch.linalg.inv(Hv), pts_ref)
    moved = motion_points(src, shift, rot_deg, _centre(sens.sensor_size))
    return apply_homography(Hv, moved) - pts_ref


def _sensitivity(sens: Any, pts_ref: Tensor, weights: Tensor, v: int) -> np.ndarray:
    """``(2, 3)``: weighted mean over the points of ``∂(u_v − u_0)/∂(tx, ty, θ°)``."""
    cols = []
    for shift, rot in (((1.0, 0.0), 0.0), ((0.0, 1.0), 0.0), ((0.0, 0.0), 0.01)):
        du = _displacements(sens, pts_ref, v, shift, rot) - _displacements(sens, pts_ref, 0,
                                                                           shift, rot)
        scale = 1.0 if rot == 0 else 1 / 0.01
        cols.append((du * weights[:, None]).sum(0).numpy() / float(weights.sum()) * scale)
    return np.stack(cols, axis=1)


def estimate_drift(sens: Any, image: Tensor) -> DriftEstimate:
    """Measure each view's shift against the reference view and fit a sensor motion.

    Args:
        sens: the bundle's :class:`~hsi_torch.recon.sensing.BundleSensing` (its sampling grid
            is what the frame is warped with: pass a corrected one to measure what is left).
        image: ``(3, H, W)`` linear RGB of one frame (sensor size, any device and dtype).

    Returns:
        :class:`DriftEstimate`.
    """
    if image.ndim != 3 or image.shape[0] != 3:
        raise ValueError(f"image must be (3, H, W) linear RGB, got {tuple(image.shape)}")
    import cv2  # lazy: OpenCV only when a frame's drift is measured, not at import

    imgs, present = _view_images(sens, torch.nan_to_num(image.detach()))
    V = imgs.shape[0]
    feats = [_features(imgs[v], present[v]) for v in range(V)]
    shifts = np.full((V, 2), np.nan)
    corr = np.full(V, np.nan)
    shifts[0], corr[0] = 0.0, 1.0
    x0, y0 = sens.reference_bbox[:2]
    rows, rhs, wts, used = [], [], [], []
    kernel = np.ones((2 * (_ERODE_PX + _TAPER_PX + _MARGIN_PX) + 1,) * 2, np.uint8)
    for v in range(1, V):
        common = cv2.erode((present[v] & present[0]).astype(np.uint8), kernel) > 0
        if int(common.sum()) < _MIN_PIXELS:
            continue
        d, rho = _align(feats[0], feats[v], common)
        if not (np.isfinite(rho) and rho >= DRIFT_MIN_CORRELATION and np.all(np.isfinite(d))):
            corr[v] = rho
            continue
        shifts[v], corr[v] = d, rho
        ys, xs = np.nonzero(common)
        step = max(1, len(ys) // 2000)
        pts = torch.tensor(np.stack([xs[::step] + x0, ys[::step] + y0], 1), dtype=torch.float64)
        w = torch.as_tensor(feats[0][ys[::step], xs[::step]].astype(np.float64)) + 1e-6
        rows.append(_sensitivity(sens, pts, w, v))
        rhs.append(d)
        wts.append(rho)
        used.append(v)
    resid = np.full(V, np.nan)
    t: np.ndarray | None = None
    theta: float | None = None
    if used:
        K = np.concatenate(rows, 0)  # (2n, 3)
        y = np.concatenate(rhs, 0)
        sw = np.sqrt(np.repeat(np.asarray(wts), 2))
        if len(used) >= 2:
            p = np.linalg.lstsq(K * sw[:, None], y * sw, rcond=None)[0]
        else:
            p = np.append(np.linalg.lstsq(K[:, :2] * sw[:, None], y * sw, rcond=None)[0], 0.0)
        t, theta = p[:2], float(p[2]) if len(used) >= 2 else None
        pred = (K @ p).reshape(-1, 2)
        for k, v in enumerate(used):
            resid[v] = float(np.hypot(*(shifts[v] - pred[k])))
        resid[0] = 0.0
    mags = np.hypot(shifts[:, 0], shifts[:, 1])
    mx = float(np.nanmax(mags)) if np.isfinite(mags[1:]).any() else 0.0
    return DriftEstimate(shifts, corr, t, theta, resid, mx)


def drift_motion_px(sens: Any, est: DriftEstimate) -> float:
    """The largest displacement (px) the fitted sensor motion gives a sensor pixel that a view
    uses: ``max |M(p) − p|`` over the corners of the box around the views' samples (the
    maximum of ``|M(p) − p|`` over a box is at a corner). 0 without a fit."""
    if est.sensor_shift_px is None:
        return 0.0
    px = _grid_px(sens)[sens.obs_mask.view(-1, sens.num_views, 3).any(2).T.to(
        sens.grid().device)]  # (n, 2) the views' samples
    if px.numel() == 0:
        return 0.0
    lo, hi = px.min(0).values, px.max(0).values
    corners = torch.stack([lo, torch.stack([hi[0], lo[1]]), torch.stack([lo[0], hi[1]]), hi])
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
    from kornia.geometry.conversions import normalize_pixel_coordinates

    H, W = sens.sensor_size
    px = _grid_px(sens)
    moved = motion_points(px, shift_px, float(rotation_deg), _centre(sens.sensor_size),
                          inverse=True)
    inside = ((moved[..., 0] >= 0) & (moved[..., 0] <= W - 1)
              & (moved[..., 1] >= 0) & (moved[..., 1] <= H - 1))
    grid = normalize_pixel_coordinates(moved, H, W).unsqueeze(0).to(sens.dtype)
    return dataclasses.replace(sens, sample_grid=grid, sample_inside=inside.to(sens.device))
