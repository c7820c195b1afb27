"""Propose ``nominal_layout.json`` from the design's ray trace fitted to a white shot (the work
behind ``hsi-torch layout``; the method, step by step, is in ``docs/calibration.md``).

A real device differs from its design (axis off centre, tube turned, focal length off by a per
cent); each moves the whole kaleidoscope image by a **similarity** about the principal point
(exact for a pinhole camera on the tube's axis). :func:`trace_design` traces the design's tiles
(views and their neighbours) once; :func:`fit_similarity` finds the similarity that puts their
edges and the BRF-free disks' outlines on the white shot's :func:`edge_map` (coarse search with
FFT shifts, then coarse-to-fine Adam refinement); :func:`confirm_parity` checks each view's
mirror parity on the grid shots; :func:`layout_document` writes what
:func:`hsi_torch.io.capture_set.read_nominal_layout` reads, :func:`draw_layout_overlay` an image
to check by eye.

Coordinates: sensor px ``(x, y)`` = (column, row), pixel centres at integers; angles in radians
in code (degrees in the record), scales relative to the design.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from hsi_torch.calibrate.registration import (
    GridDetectorConfig,
    detect_in_views,
    fit_homography,
    view_orientation,
)
from hsi_torch.devices import to_numpy
from hsi_torch.errors import InputError
from hsi_torch.io.atomic import atomic_write_bytes
from hsi_torch.optics.geometry import apply_homography, triangle_edge_distance
from hsi_torch.optics.kaleidoscope import CameraModel, KaleidoscopeGeometry
from hsi_torch.optics.layout import build_view_layout

__all__ = [
    "DesignTiles",
    "SimilarityFit",
    "ParityEvidence",
    "LayoutProposal",
    "trace_design",
    "edge_map",
    "fit_similarity",
    "confirm_parity",
    "check_layout_confidence",
    "LayoutRefused",
    "MIN_EDGE_CONTRAST",
    "propose_layout",
    "layout_document",
    "draw_layout_overlay",
]


# --- the design's tiles


@dataclass
class DesignTiles:
    """The design's kaleidoscope image: every tile on the sensor (views first).

    Attributes:
        sequences: mirror sequence of each of the ``K`` tiles (views first, in the design's
            view order: by number of reflections, then lexicographic).
        num_views: the first ``num_views`` tiles are the views (at most
            ``geometry.max_reflections`` reflections); the rest only help the fit.
        triangles: ``(K, 3, 2)`` float64 sensor px of the design camera (images of the entrance
            vertices ``P_0, P_1, P_2``).
        diffuser_homographies: ``(K, 3, 3)`` float64, diffuser mm → sensor px.
        parity: ``(K,)`` int64, ``+1`` upright (even reflection count), ``−1`` mirrored.
        brf_free_center_mm, brf_free_radius_mm: the BRF-free disk on the diffuser (radius 0:
            none).
        sensor_size: ``(H, W)`` of the design camera.
        centre_px: ``(cx, cy)`` principal point of the design camera (the similarity's centre).
    """

    sequences: list[tuple[int, ...]]
    num_views: int
    triangles: np.ndarray
    diffuser_homographies: np.ndarray
    parity: np.ndarray
    brf_free_center_mm: tuple[float, float]
    brf_free_radius_mm: float
    sensor_size: tuple[int, int]
    centre_px: tuple[float, float]

    def disk_outline(self, tile: int, n: int = 64) -> np.ndarray:
        """``(n, 2)`` sensor px of the BRF-free disk's outline seen through tile ``tile``."""
        c = np.asarray(self.brf_free_center_mm, np.float64)
        a = np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
        circ = c + self.brf_free_radius_mm * np.stack([np.cos(a), np.sin(a)], -1)
        return apply_homography(self.diffuser_homographies[tile], circ)


def trace_design(
    geometry: KaleidoscopeGeometry,
    camera: CameraModel,
    *,
    extra_reflections: int = 1,
    max_trace_pixels: int = 400_000,
    device: torch.device | str | None = None,
) -> DesignTiles:
    """Trace the design and return its tiles (:class:`DesignTiles`).

    Args:
        geometry, camera: the design (``geometry.max_reflections`` reflections make a view).
        extra_reflections: tiles with up to this many more reflections are traced too (they
            border the views on the sensor; their edges help the fit).
        max_trace_pixels: the trace runs on a copy of the sensor with at most this many pixels
            (same field of view, coarser pitch); the tiles' homographies are exact either way.

    Raises:
        ValueError: the reference (direct) view is not on the sensor.
    """
    H, W = camera.height_px, camera.width_px
    a = min(1.0, math.sqrt(max_trace_pixels / float(H * W)))
    cx, cy = float(camera.cx), float(camera.cy)  # type: ignore[arg-type]
    small = CameraModel(
        width_px=max(8, math.ceil(W * a)), height_px=max(8, math.ceil(H * a)),
        pixel_pitch_mm=camera.pixel_pitch_mm / a, focal_length_mm=camera.focal_length_mm,
        cx=a * (cx + 0.5) - 0.5, cy=a * (cy + 0.5) - 0.5,
    )  # fmt: skip
    geo = dataclasses.replace(
        geometry, max_reflections=geometry.max_reflections + max(0, int(extra_reflections))
    )
    lay = build_view_layout(geo, small, min_pixels=max(8, int(50 * a * a)), device=device)
    # small px -> design px: x = (x_s + 0.5) / a - 0.5
    s_inv = np.array([[1 / a, 0, 0.5 / a - 0.5], [0, 1 / a, 0.5 / a - 0.5], [0, 0, 1.0]])
    hd = s_inv @ lay.diffuser_homographies.cpu().numpy()
    hd = hd / hd[:, 2:3, 2:3]
    seqs = [tuple(s) for s in lay.reflection_sequences]
    nv = sum(1 for s in seqs if len(s) <= geometry.max_reflections)
    tris = apply_homography(s_inv, lay.triangles.cpu().numpy())
    return DesignTiles(
        sequences=seqs, num_views=nv, triangles=tris, diffuser_homographies=hd,
        parity=lay.parity.cpu().numpy().astype(np.int64),
        brf_free_center_mm=tuple(map(float, lay.brf_free_center_mm)),  # type: ignore[arg-type]
        brf_free_radius_mm=float(lay.brf_free_radius_mm), sensor_size=(H, W),
        centre_px=(cx, cy),
    )  # fmt: skip


def _edge_points(tiles: DesignTiles, spacing_px: float, fine: bool = False) -> np.ndarray:
    """``(N, 2)`` points ``spacing_px`` apart (design sensor px) along the views' edges and every
    tile's BRF-free disk outline (disk points ≥ 1 px inside their tile) — or, ``fine``, along
    the views' disk outlines only.

    The outer edges of the tiles beyond the views are left out: the lit region ends where the
    tube's exit aperture cuts the rays, not on them. The fine set is what the last pyramid
    levels align: on simulated devices the tile boundaries (weak, with the fringes and the
    fall-off across them) pulled the scale by 0.1-0.2 % and the outer tiles' disks (near the
    edge of the lit region) the shift by 0.2 px; the views' disks alone land within 0.07 px.
    Without a BRF-free disk the fine set is the whole set."""
    fine = fine and tiles.brf_free_radius_mm > 0
    pts = []
    for k in range(len(tiles.sequences)):
        tri = tiles.triangles[k]
        if fine and k >= tiles.num_views:
            continue
        for i in range(3 if k < tiles.num_views and not fine else 0):
            p, q = tri[i], tri[(i + 1) % 3]
            n = max(2, int(math.ceil(np.linalg.norm(q - p) / spacing_px)))
            t = (np.arange(n) + 0.5) / n
            pts.append(p + t[:, None] * (q - p))
        if tiles.brf_free_radius_mm > 0:
            ring = tiles.disk_outline(k, 256)
            length = float(np.linalg.norm(np.diff(ring, axis=0, append=ring[:1]), axis=1).sum())
            n = max(8, int(math.ceil(length / spacing_px)))
            ring = tiles.disk_outline(k, n)
            # only the part seen through this tile: a disk on a tile boundary shows half of
            # itself in each of the two tiles, each half from a different mirror image
            pts.append(ring[triangle_edge_distance(ring, tri) >= 1.0])
    return np.concatenate(pts)


# --- the fit


def _blur(x: torch.Tensor, sigma_px: float) -> torch.Tensor:
    """Separable Gaussian blur of ``x (H, W)`` (replicated border)."""
    r = max(1, int(math.ceil(3 * sigma_px)))
    k = torch.exp(-0.5 * (torch.arange(-r, r + 1, dtype=torch.float32) / sigma_px) ** 2)
    k = (k / k.sum()).to(x.device)
    y = F.pad(x[None, None], (r, r, r, r), mode="replicate")
    return F.conv2d(F.conv2d(y, k.view(1, 1, 1, -1)), k.view(1, 1, -1, 1))[0, 0]


def edge_map(image: torch.Tensor, sigma_px: float, clip: float = 1.0) -> torch.Tensor:
    """Relative edge strength of a white shot:
    ``clip·tanh(√(2π)·σ·|∇ G_σ * I| / (G_3σ * I + ε) / clip)``.

    The gradient is taken on the linear image (its maximum sits on the middle of a blurred
    step, where the tile boundary is; a log image would move it towards the darker side) and
    divided by the local mean brightness (vignetting, fall-off and the views' throughputs do
    not weight the edges). With the factor ``√(2π)·σ`` a step from ``a`` to ``b`` reads
    ``≈ |b − a| / ((a + b)/2)`` on its edge whatever ``σ``; the soft clip (a strictly
    increasing function: every ridge stays where it is) keeps the edge of the lit region (a
    jump into the dark, ≈ 2) from outweighing the tile boundaries (0.05-0.3) and BRF-free
    disks (≈ 0.7) the fit aligns. ``ε`` = 2 % of the 99th percentile (dark areas do not
    amplify noise).

    ``image``: ``(H, W)`` linear grey image (any scale); ``sigma_px``: σ in its px. Returns
    ``(H, W)`` float32.
    """
    x = image.to(torch.float32).clamp_min(0)
    q = float(torch.quantile(x.flatten()[:: max(1, x.numel() // 100_000)], 0.99))
    eps = 0.02 * q if q > 0 else 1.0
    b = _blur(x, sigma_px)
    gx = torch.zeros_like(b)
    gy = torch.zeros_like(b)
    gx[:, 1:-1] = 0.5 * (b[:, 2:] - b[:, :-2])
    gy[1:-1] = 0.5 * (b[2:] - b[:-2])
    mean = _blur(x, 3 * sigma_px) + eps
    g = torch.sqrt(gx * gx + gy * gy) * (math.sqrt(2 * math.pi) * sigma_px) / mean
    return clip * torch.tanh(g / clip)


def _downsample(image: torch.Tensor, factor: float) -> torch.Tensor:
    """Area-average ``image (H, W)`` by ``factor`` (≥ 1)."""
    if factor <= 1.0:
        return image
    H, W = image.shape
    size = (max(8, int(round(H / factor))), max(8, int(round(W / factor))))
    return F.interpolate(image[None, None], size=size, mode="area")[0, 0]


def _similarity(params: torch.Tensor, centre: torch.Tensor, radius: float) -> torch.Tensor:
    """``(3, 3)`` similarity of ``params = (u_s, u_θ, t_x, t_y)`` (all in px at ``radius``):
    scale ``exp(u_s / radius)``, rotation ``u_θ / radius`` about ``centre``, shift ``t``."""
    s = torch.exp(params[0] / radius)
    th = params[1] / radius
    c, sn = s * torch.cos(th), s * torch.sin(th)
    a = torch.stack([torch.stack([c, -sn]), torch.stack([sn, c])])
    t = centre + params[2:] - a @ centre
    top = torch.cat([a, t[:, None]], 1)
    return torch.cat([top, torch.tensor([[0.0, 0.0, 1.0]], dtype=top.dtype)], 0)


def _sample(edges: torch.Tensor, pts: torch.Tensor, factor: float) -> torch.Tensor:
    """Bilinear samples of ``edges (h, w)`` (a pyramid level, ``factor`` design px per level
    px) at full-resolution points ``pts (N, 2)``; 0 outside."""
    h, w = edges.shape
    xl = (pts[:, 0] + 0.5) / factor - 0.5
    yl = (pts[:, 1] + 0.5) / factor - 0.5
    g = torch.stack([2 * xl / max(w - 1, 1) - 1, 2 * yl / max(h - 1, 1) - 1], -1)
    out = F.grid_sample(edges[None, None], g[None, None].to(edges.dtype), mode="bilinear",
                        padding_mode="zeros", align_corners=True)  # fmt: skip
    return out[0, 0, 0]


def _adam_ascent(
    objective: Any, x0: torch.Tensor, lr0: float, lr1: float, iterations: int
) -> torch.Tensor:
    """Maximise ``objective(x)`` by Adam steps (learning rate cosine-annealed from ``lr0`` to
    ``lr1``, in the units of ``x``); returns the last iterate. (torch.optim is not used: its
    import pulls in the compiler stack, seconds of start-up.)"""
    x = x0.clone()
    m = torch.zeros_like(x)
    v = torch.zeros_like(x)
    b1, b2 = 0.9, 0.999
    for k in range(1, iterations + 1):
        xr = x.clone().requires_grad_(True)
        (g,) = torch.autograd.grad(objective(xr), xr)
        m = b1 * m + (1 - b1) * g
        v = b2 * v + (1 - b2) * g * g
        lr = lr1 + 0.5 * (lr0 - lr1) * (1 + math.cos(math.pi * (k - 1) / max(1, iterations - 1)))
        x = x + lr * (m / (1 - b1**k)) / ((v / (1 - b2**k)).sqrt() + 1e-12)
    return x


@dataclass
class SimilarityFit:
    """The similarity that puts the design's tiles on the white shot.

    Attributes:
        matrix: ``(3, 3)`` float64, design sensor px → this sensor's px.
        scale: relative to the design; rotation_deg: about the principal point, from +x
            towards +y (clockwise as displayed, rows going down); shift_px: ``(dx, dy)`` of the
            principal point.
        edge_score: mean edge strength (:func:`edge_map`, σ = 1 px) at the fitted edge points
            (views' edges, disks); ``design_edge_score`` the same for the design as traced.
        coarse: the coarse search's best ``(scale, rotation_deg, dx, dy)``.
        background_edge_score: the same points displaced off the fit (the median over
            :data:`BACKGROUND_SHIFTS`): what the image's edges give a layout anywhere.
    """

    matrix: np.ndarray
    scale: float
    rotation_deg: float
    shift_px: tuple[float, float]
    edge_score: float
    design_edge_score: float
    coarse: tuple[float, float, float, float]
    background_edge_score: float = float("nan")

    @property
    def edge_contrast(self) -> float:
        """``edge_score / background_edge_score``: how much stronger the image's edges are on
        the fitted layout than off it (≈ 1: the image has no edges where the layout has them
        more than anywhere else)."""
        b = self.background_edge_score
        return self.edge_score / b if b > 0 else math.inf

    def to_dict(self) -> dict[str, Any]:
        return {
            "matrix": self.matrix.tolist(),
            "scale": self.scale,
            "rotation_deg": self.rotation_deg,
            "shift_px": list(self.shift_px),
            "edge_score": self.edge_score,
            "design_edge_score": self.design_edge_score,
            "background_edge_score": self.background_edge_score,
            "edge_contrast": self.edge_contrast,
        }


#: Displacements of the fitted edge points, as fractions of the image's shorter side (24: two
#: radii × 12 directions), at which :func:`fit_similarity` measures the background edge score.
#: They move every point off a tile edge (edges are a few px wide, the displacements ≥ 5 % of the
#: side) and keep most of them on the image.
BACKGROUND_SHIFTS = tuple(
    (r * math.cos(math.radians(a)), r * math.sin(math.radians(a)))
    for r in (0.05, 0.1) for a in range(15, 360, 30)
)  # fmt: skip


def _background_score(edges: torch.Tensor, pts: torch.Tensor) -> float:
    """The median over :data:`BACKGROUND_SHIFTS` of the mean edge strength at ``pts (N, 2)``
    (full-resolution px) displaced by each shift, counting only points on the image."""
    h, w = edges.shape
    D = float(min(h, w))
    vals = []
    for dx, dy in BACKGROUND_SHIFTS:
        q = pts + torch.tensor([dx * D, dy * D], dtype=pts.dtype)
        on = (q[:, 0] >= 0) & (q[:, 0] <= w - 1) & (q[:, 1] >= 0) & (q[:, 1] <= h - 1)
        if int(on.sum()) >= max(8, pts.shape[0] // 4):
            vals.append(float(_sample(edges, q[on], 1.0).mean()))
    return float(np.median(vals)) if vals else float("nan")


def fit_similarity(
    white: torch.Tensor,
    tiles: DesignTiles,
    *,
    max_shift: float = 0.15,
    max_rotation_deg: float = 8.0,
    max_scale_change: float = 0.06,
    coarse_size: int = 192,
    iterations: int = 80,
) -> SimilarityFit:
    """Fit the similarity ``T`` (design px → sensor px) that maximises the white shot's edge
    strength along the design's tile edges and BRF-free disk outlines.

    Args:
        white: ``(H, W)`` linear grey white shot (mean of the shots, black level subtracted).
        max_shift: search range of the shift, a fraction of the shorter image side.
        max_rotation_deg, max_scale_change: search ranges of rotation (±deg) and scale (±).
        coarse_size: the coarse search runs with the shorter side reduced to about this.
        iterations: gradient steps per pyramid level.
    """
    img = white.detach().to("cpu", torch.float32)
    if img.ndim != 2:
        raise InputError(f"white must be an (H, W) image, got shape {tuple(img.shape)}")
    H, W = img.shape
    D = float(min(H, W))
    radius = 0.5 * D
    centre = torch.tensor(tiles.centre_px, dtype=torch.float64)
    # ---- coarse: rotation x scale grid, shift by FFT cross-correlation
    f0 = max(1.0, D / coarse_size)
    e0 = edge_map(_downsample(img, f0), 1.5)
    h0, w0 = e0.shape
    pts_c = torch.from_numpy(_edge_points(tiles, 0.75 * f0))
    m = int(math.ceil(max_shift * D / f0)) + 2
    big = (h0 + 2 * m, w0 + 2 * m)
    fe = torch.fft.rfft2(F.pad(e0, (m, m, m, m)), s=big)
    step_deg = max(0.5, math.degrees(2.0 * f0 / radius))
    n_rot = int(math.ceil(max_rotation_deg / step_deg))
    rots = [k * step_deg for k in range(-n_rot, n_rot + 1)]
    step_s = 2.0 * f0 / radius
    n_s = int(math.ceil(math.log1p(max_scale_change) / step_s))
    scales = [math.exp(k * step_s) for k in range(-n_s, n_s + 1)]
    best = (-math.inf, 1.0, 0.0, 0.0, 0.0)
    for sc in scales:
        for rd in rots:
            p = torch.tensor([radius * math.log(sc), radius * math.radians(rd), 0.0, 0.0],
                             dtype=torch.float64)  # fmt: skip
            q = apply_homography(_similarity(p, centre, radius), pts_c)
            xl = (q[:, 0] + 0.5) / f0 - 0.5 + m
            yl = (q[:, 1] + 0.5) / f0 - 0.5 + m
            ok = (xl >= 0) & (yl >= 0) & (xl <= big[1] - 2) & (yl <= big[0] - 2)
            xl, yl = xl[ok], yl[ok]
            x0, y0 = xl.floor(), yl.floor()
            fx, fy = xl - x0, yl - y0
            splat = torch.zeros(big, dtype=torch.float32)
            for dx, dy, wgt in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)),
                                (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):  # fmt: skip
                splat.index_put_(((y0 + dy).long(), (x0 + dx).long()), wgt.float(), accumulate=True)
            corr = torch.fft.irfft2(fe * torch.conj(torch.fft.rfft2(splat)), s=big)
            # corr[ty, tx] = sum_x splat(x) e(x + t); shifts beyond +-m wrap: mask them
            corr = torch.roll(corr, shifts=(m, m), dims=(0, 1))[: 2 * m + 1, : 2 * m + 1]
            val, idx = corr.flatten().max(0)
            if float(val) > best[0]:
                ty, tx = divmod(int(idx), 2 * m + 1)
                best = (float(val), sc, rd, (tx - m) * f0, (ty - m) * f0)
    _, sc0, rd0, tx0, ty0 = best
    params = torch.tensor([radius * math.log(sc0), radius * math.radians(rd0), tx0, ty0],
                          dtype=torch.float64)  # fmt: skip
    # ---- refinement: pyramid of edge maps, Adam on the mean edge strength
    levels = []
    f = f0 / 2
    while f > 1.0:
        levels.append((f, 1.5))
        f /= 2
    levels += [(1.0, 1.5), (1.0, 1.0)]
    for i, (f, sigma) in enumerate(levels):
        e = edge_map(_downsample(img, f), sigma)
        pts = torch.from_numpy(_edge_points(tiles, 0.75 * f, fine=i >= len(levels) - 2))
        def objective(q: torch.Tensor, e=e, pts=pts, f=f) -> torch.Tensor:
            return _sample(e, apply_homography(_similarity(q, centre, radius), pts), f).mean()

        params = _adam_ascent(objective, params, 0.3 * f, 0.01 * f, iterations)
    with torch.no_grad():
        e = edge_map(img, 1.0)
        pts = torch.from_numpy(_edge_points(tiles, 0.75))
        mat = _similarity(params, centre, radius)
        fitted = apply_homography(mat, pts)
        score = float(_sample(e, fitted, 1.0).mean())
        design = float(_sample(e, pts, 1.0).mean())
        background = _background_score(e, fitted)
    a = mat[:2, :2].numpy()
    shift = apply_homography(mat, centre[None])[0] - centre
    return SimilarityFit(
        matrix=mat.numpy(), scale=float(math.sqrt(abs(np.linalg.det(a)))),
        rotation_deg=float(math.degrees(math.atan2(a[1, 0], a[0, 0]))),
        shift_px=(float(shift[0]), float(shift[1])), edge_score=score, design_edge_score=design,
        coarse=(sc0, rd0, tx0, ty0), background_edge_score=background,
    )  # fmt: skip


# --- parity from the grid shots


@dataclass
class ParityEvidence:
    """What the circle-grid shots say about one view's parity.

    Attributes:
        design, chosen: the design's parity and the parity proposed.
        status: ``"confirmed"`` (the design's parity is supported), ``"flipped"`` (only the other
            one is), ``"unconfirmed"`` (neither is: grid not found, too few inliers).
        inliers: per tried parity (``"+1"``, ``"-1"``): ``[RANSAC inliers, points]`` (``[0, 0]``
            when the grid was not found with it in any shot with the reference view).
        orientation: per tried parity: the fitted homography's orientation (±1, 0 if none).
    """

    view: int
    design: int
    chosen: int
    status: str
    inliers: dict[str, list[int]] = field(default_factory=dict)
    orientation: dict[str, int] = field(default_factory=dict)

    def __str__(self) -> str:
        parts = [f"{k}: {n[0]}/{n[1]} inliers" + (f", orientation {self.orientation[k]:+d}"
                                                   if n[1] else "")
                 for k, n in self.inliers.items()]  # fmt: skip
        return (f"view {self.view}: parity {self.chosen:+d} ({self.status}; "
                + "; ".join(parts) + ")")  # fmt: skip


def confirm_parity(
    grid_images: Sequence[np.ndarray | torch.Tensor],
    triangles: np.ndarray,
    parity: np.ndarray,
    config: GridDetectorConfig | None = None,
    *,
    min_inlier_fraction: float = 0.8,
) -> list[ParityEvidence]:
    """Each view's parity from the circle-grid shots: the grid is detected in the view with and
    without undoing a mirror flip and fitted to the reference view's detections by RANSAC
    (:func:`~hsi_torch.calibrate.registration.fit_homography`); a parity is supported when at
    least ``min_inlier_fraction`` of the points are inliers and the homography's orientation
    agrees with it (mirrored views reverse orientation). The better supported parity wins;
    without evidence the design's is kept and reported as unconfirmed.

    ``grid_images``: as :func:`~hsi_torch.calibrate.registration.to_gray_uint8` takes them,
    ideally flat-fielded by the white shot; ``triangles (V, 3, 2)`` sensor px (view 0 the
    reference, parity +1); ``parity (V,)`` the parities to check.

    Returns:
        One :class:`ParityEvidence` per view (view 0: always ``+1``, ``"confirmed"`` when the
        grid was found there).
    """
    cfg = config or GridDetectorConfig()
    tris = np.asarray(triangles, np.float64).reshape(-1, 3, 2)
    par = np.asarray(parity, np.int64).reshape(-1)
    V = len(tris)
    dets = {p: [detect_in_views(img, tris, np.full(V, p), cfg) for img in grid_images]
            for p in (1, -1)}  # fmt: skip
    ref = [d[0] for d in dets[1]]
    out = [ParityEvidence(0, 1, 1, "confirmed" if any(r is not None for r in ref)
                          else "unconfirmed")]  # fmt: skip
    for v in range(1, V):
        ev = ParityEvidence(v, int(par[v]), int(par[v]), "unconfirmed")
        support = {}
        for p in (1, -1):
            key = f"{p:+d}"
            pairs = [(d[v], r) for d, r in zip(dets[p], ref, strict=True)
                     if d[v] is not None and r is not None]  # fmt: skip
            ev.inliers[key], ev.orientation[key] = [0, 0], 0
            if not pairs:
                continue
            try:
                h, inl, _, _ = fit_homography([a for a, _ in pairs], [b for _, b in pairs],
                                              cfg.ransac_threshold_px)  # fmt: skip
            except ValueError:
                continue
            ev.inliers[key] = [int(inl.sum()), int(len(inl))]
            ev.orientation[key] = view_orientation(h, tris[v])
            frac = inl.sum() / max(1, len(inl))
            if frac >= min_inlier_fraction and ev.orientation[key] == p:
                support[p] = frac
        if support:
            ev.chosen = max(support, key=lambda p: (support[p], p == par[v]))
            ev.status = "confirmed" if ev.chosen == par[v] else "flipped"
        out.append(ev)
    return out


# --- the proposal


@dataclass
class LayoutProposal:
    """A proposed nominal layout.

    Attributes:
        sensor_size: ``(H, W)`` of the white shot.
        triangles: ``(V, 3, 2)`` fitted view triangles (sensor px).
        parity_evidence: per view (empty without grid shots).
        brf_free_polygon: ``(64, 2)`` sensor px of the BRF-free disk in view 0 (or ``None``).
        reference_bbox: ``(x0, y0, w, h)`` around view 0's triangle, clipped to the sensor.
        notes: remarks for the user (views partly off the sensor, parities not confirmed, …).
    """

    tiles: DesignTiles
    fit: SimilarityFit
    sensor_size: tuple[int, int]
    triangles: np.ndarray
    parity: np.ndarray
    parity_evidence: list[ParityEvidence]
    brf_free_polygon: np.ndarray | None
    reference_bbox: tuple[int, int, int, int]
    notes: list[str] = field(default_factory=list)

    def confidence(self) -> dict[str, Any]:
        """How far the proposal can be trusted: the edge scores (fitted, design as traced,
        background: the fitted edges displaced off the fit) and their ratio ``edge_contrast``,
        and per parity status the views other than the reference (``parities_confirmed`` also
        counts ``flipped``: the grid shots decided the parity; ``grid_shots``: whether there
        were any)."""
        f = self.fit
        status = [e.status for e in self.parity_evidence if e.view != 0]
        return {
            "edge_score": f.edge_score,
            "design_edge_score": f.design_edge_score,
            "background_edge_score": f.background_edge_score,
            "edge_contrast": f.edge_contrast,
            "grid_shots": bool(self.parity_evidence),
            "parities_confirmed": sum(s in ("confirmed", "flipped") for s in status),
            "parities_flipped": status.count("flipped"),
            "parities_unconfirmed": status.count("unconfirmed"),
        }

    def __str__(self) -> str:
        f = self.fit
        c = self.confidence()
        lines = [
            f"layout fitted to the white shot: scale {f.scale:.4f}, rotation "
            f"{f.rotation_deg:+.3f} deg, principal point shifted by ({f.shift_px[0]:+.2f}, "
            f"{f.shift_px[1]:+.2f}) px; edge score {f.edge_score:.3f} (design as traced "
            f"{f.design_edge_score:.3f}; off the fit {f.background_edge_score:.3f}: edge "
            f"contrast {f.edge_contrast:.2f}x)",
            f"{len(self.parity)} views, reference bbox {list(self.reference_bbox)}"
            + (f"; parities decided by the grid shots: {c['parities_confirmed']} of "
               f"{len(self.parity) - 1} views"
               + (f" ({c['parities_flipped']} flipped)" if c["parities_flipped"] else "")
               if c["grid_shots"] else ""),
        ]  # fmt: skip
        lines += ["  " + str(e) for e in self.parity_evidence]
        lines += [f"note: {n}" for n in self.notes]
        return "\n".join(lines)


def propose_layout(
    white: torch.Tensor,
    tiles: DesignTiles,
    grid_images: Sequence[np.ndarray | torch.Tensor] = (),
    detector: GridDetectorConfig | None = None,
    *,
    min_inlier_fraction: float = 0.8,
    **fit_kwargs: Any,
) -> LayoutProposal:
    """Fit the design to the white shot and check the parities on the grid shots.

    ``white``: ``(H, W)`` linear grey white shot (or ``(3, H, W)``: channels averaged);
    ``grid_images``: circle-grid shots (flat-fielded), optional; ``detector``: the
    ``registration`` settings of ``calibrate.yaml``; ``fit_kwargs`` go to :func:`fit_similarity`.

    Raises:
        InputError: the white shot's size differs from the design camera's.
    """
    img = white.mean(0) if white.ndim == 3 else white
    size = (int(img.shape[0]), int(img.shape[1]))
    if size != tuple(tiles.sensor_size):
        raise InputError(
            f"white shot size (H, W) = {size} differs from the design camera's "
            f"{tuple(tiles.sensor_size)}; give the design of this camera (camera.width_px, "
            "height_px, pixel_pitch_mm, focal_length_mm in the design config)"
        )
    fit = fit_similarity(img, tiles, **fit_kwargs)
    V = tiles.num_views
    tris = apply_homography(fit.matrix, tiles.triangles[:V])
    parity = tiles.parity[:V].copy()
    notes: list[str] = []
    H, W = size
    for v in range(V):
        t = tris[v]
        inside = np.all((t[:, 0] >= -0.5) & (t[:, 0] <= W - 0.5) & (t[:, 1] >= -0.5)
                        & (t[:, 1] <= H - 0.5))  # fmt: skip
        if not inside:
            notes.append(f"view {v}'s triangle reaches beyond the sensor")
    evidence: list[ParityEvidence] = []
    if grid_images:
        evidence = confirm_parity(grid_images, tris, parity, detector,
                                  min_inlier_fraction=min_inlier_fraction)  # fmt: skip
        for ev in evidence:
            parity[ev.view] = ev.chosen
        unconf = [e.view for e in evidence if e.status == "unconfirmed"]
        flipped = [e.view for e in evidence if e.status == "flipped"]
        if unconf:
            notes.append(f"parity of view(s) {unconf} not confirmed by the grid shots (the "
                         "design's is kept): check them on the overlay")  # fmt: skip
        if flipped:
            notes.append(f"the grid shots flip the design's parity of view(s) {flipped}")
    else:
        notes.append("no grid shots: the parities are the design's, unconfirmed")
    poly = None
    if tiles.brf_free_radius_mm > 0:
        poly = apply_homography(fit.matrix, tiles.disk_outline(0, 64))
    t0 = tris[0]
    x0 = int(max(0, math.floor(float(t0[:, 0].min()))))
    y0 = int(max(0, math.floor(float(t0[:, 1].min()))))
    x1 = int(min(W - 1, math.ceil(float(t0[:, 0].max()))))
    y1 = int(min(H - 1, math.ceil(float(t0[:, 1].max()))))
    return LayoutProposal(tiles, fit, size, tris, parity, evidence, poly,
                          (x0, y0, x1 - x0 + 1, y1 - y0 + 1), notes)  # fmt: skip


#: ``hsi-torch layout`` refuses a fit whose edge contrast (:attr:`SimilarityFit.edge_contrast`)
#: is below this. White shots of the simulated device (as designed, off the design, under a
#: veil of stray light) give 3.4-3.6; natural and building-like photos 1.0-1.2
#: (``docs/calibration.md``).
MIN_EDGE_CONTRAST = 2.0


class LayoutRefused(InputError):
    """The white (or grid) shots do not support the proposed layout (see
    :func:`check_layout_confidence`)."""


def check_layout_confidence(
    proposal: LayoutProposal, min_edge_contrast: float = MIN_EDGE_CONTRAST
) -> dict[str, Any]:
    """Refuse a proposal the shots do not support; returns :meth:`LayoutProposal.confidence`.

    Two limits: the fitted layout's edges must be at least ``min_edge_contrast`` times stronger
    on the white shot than the same edges displaced off the fit (a photo with edges everywhere,
    e.g. of buildings, scores about as well anywhere: the fit found nothing); and with grid
    shots, at least one view other than the reference must have its parity decided by them
    (none decided: the fitted triangles do not hold the grid's views).

    Raises:
        LayoutRefused: either limit is missed; the message names the measured scores, the
            limit and what to check.
    """
    c = proposal.confidence()
    if not c["edge_contrast"] >= min_edge_contrast:  # also NaN: no background measured
        raise LayoutRefused(
            f"the white shot does not show this design's views: the fitted layout's edge score "
            f"{c['edge_score']:.3f} is {c['edge_contrast']:.2f}x the score of the same edges "
            f"displaced off the fit ({c['background_edge_score']:.3f}; the design as traced "
            f"scores {c['design_edge_score']:.3f}), below the limit {min_edge_contrast:g}x (white "
            "shots of the simulated device give 3.4x or more). Give evenly lit, in-focus "
            "white shots of this device (objective on) and the design of this device; nothing "
            "was written"
        )
    if c["grid_shots"] and c["parities_confirmed"] == 0:
        V = len(proposal.parity)
        raise LayoutRefused(
            f"the grid shots confirm no view's parity (0 of {V - 1} views besides the "
            f"reference; edge contrast {c['edge_contrast']:.2f}x): the fitted triangles do not "
            "hold the grid's views, or the grid is not found in them. Check that the grid "
            "shots are of this device and the grid settings (registration.pattern_size of "
            "--calib-config), or run without --grid to keep the design's parities "
            "unconfirmed; nothing was written"
        )
    return c


def layout_document(proposal: LayoutProposal, sources: dict[str, Any] | None = None
                    ) -> dict[str, Any]:  # fmt: skip
    """The JSON object of ``nominal_layout.json`` (the keys
    :func:`~hsi_torch.io.capture_set.read_nominal_layout` reads, plus ``layout_fit``: the fitted
    transform, scores, parity evidence and ``sources``)."""
    pr = proposal
    V = len(pr.parity)
    doc: dict[str, Any] = {
        "schema_version": 1,
        "sensor_size": list(pr.sensor_size),
        "num_views": V,
        "reflection_sequences": [list(s) for s in pr.tiles.sequences[:V]],
        "triangles_px": pr.triangles.tolist(),
        "parity": [int(p) for p in pr.parity],
        "reference_view": 0,
        "reference_bbox": list(pr.reference_bbox),
    }
    if pr.brf_free_polygon is not None:
        hd0 = pr.fit.matrix @ pr.tiles.diffuser_homographies[0]
        centre = apply_homography(hd0, np.asarray([pr.tiles.brf_free_center_mm]))[0]
        r_px = float(np.linalg.norm(pr.brf_free_polygon - centre, axis=1).mean())
        doc["brf_free_patch"] = {"view": 0, "center_px": centre.tolist(), "radius_px": r_px,
                                 "polygon_px": pr.brf_free_polygon.tolist()}  # fmt: skip
    doc["conventions"] = ("pixel (x, y) = (column, row), centres at integers; triangle vertices "
                          "are the images of entrance vertices P0, P1, P2")  # fmt: skip
    doc["layout_fit"] = {
        "generator": "hsi-torch layout",
        "method": "design ray trace, similarity fitted to the white shot's edges; parity from "
                  "the circle-grid shots",
        **pr.fit.to_dict(),
        "confidence": pr.confidence(),
        "parity_evidence": [dataclasses.asdict(e) for e in pr.parity_evidence],
        "notes": list(pr.notes),
        **({"sources": sources} if sources else {}),
    }
    return doc


_VIEW_COLOURS = [(80, 220, 80), (255, 170, 40), (60, 200, 255), (230, 90, 230), (90, 140, 255),
                 (40, 230, 230), (200, 200, 60), (255, 110, 110), (150, 255, 150),
                 (180, 150, 255)]  # fmt: skip


def draw_layout_overlay(
    white: torch.Tensor | np.ndarray, proposal: LayoutProposal, path: str | Path,
    *, long_side: int = 800,
) -> Path:
    """Write a PNG: the white shot (square-root tone), the fitted view triangles (numbered, with
    their parity: green text = confirmed by the grids, orange = not confirmed, red = flipped
    against the design), the neighbouring tiles thin and grey, the BRF-free patch in yellow and
    the fitted transform as a caption. ``long_side``: the picture's longer side (px)."""
    img = to_numpy(white)
    img = img.mean(0) if img.ndim == 3 else img
    hi = float(np.percentile(img, 99.5)) or 1.0
    grey = (np.sqrt(np.clip(img / hi, 0, 1)) * 200).astype(np.uint8)
    H, W = grey.shape
    z = long_side / max(H, W)
    cap_h = 44
    canvas = cv2.resize(grey, (int(round(W * z)), int(round(H * z))),
                        interpolation=cv2.INTER_AREA if z < 1 else cv2.INTER_LINEAR)  # fmt: skip
    canvas = cv2.cvtColor(canvas, cv2.COLOR_GRAY2BGR)
    canvas = cv2.copyMakeBorder(canvas, cap_h, 0, 0, 0, cv2.BORDER_CONSTANT, value=(0, 0, 0))
    sh = 4

    def pts(p: np.ndarray) -> np.ndarray:
        q = (np.asarray(p) + 0.5) * z - 0.5
        q[:, 1] += cap_h
        return np.round(q * (1 << sh)).astype(np.int32)

    pr = proposal
    others = apply_homography(pr.fit.matrix, pr.tiles.triangles[pr.tiles.num_views:])
    for t in others:
        cv2.polylines(canvas, [pts(t)], True, (110, 110, 110), 1, cv2.LINE_AA, sh)
    for v, t in enumerate(pr.triangles):
        cv2.polylines(canvas, [pts(t)], True, _VIEW_COLOURS[v % len(_VIEW_COLOURS)][::-1], 2,
                      cv2.LINE_AA, sh)  # fmt: skip
    if pr.brf_free_polygon is not None:
        cv2.polylines(canvas, [pts(pr.brf_free_polygon)], True, (0, 230, 255), 1, cv2.LINE_AA, sh)
    status = {e.view: e.status for e in pr.parity_evidence}
    colour = {"confirmed": (90, 255, 90), "unconfirmed": (0, 170, 255), "flipped": (60, 60, 255)}
    scale = max(0.45, min(1.0, long_side / 1600))
    for v, t in enumerate(pr.triangles):
        c = (t.mean(0) + 0.5) * z - 0.5
        label = f"{v} {'+' if pr.parity[v] > 0 else '-'}"
        (tw, th), _ = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, scale, 2)
        org = (int(c[0] - tw / 2), int(c[1] + cap_h + th / 2))
        cv2.putText(canvas, label, org, cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 4, cv2.LINE_AA)
        col = colour.get(status.get(v, "unconfirmed"), (0, 170, 255))
        cv2.putText(canvas, label, org, cv2.FONT_HERSHEY_SIMPLEX, scale, col, 2, cv2.LINE_AA)
    f = pr.fit
    cap = [f"layout: scale {f.scale:.4f}, rotation {f.rotation_deg:+.2f} deg, shift "
           f"({f.shift_px[0]:+.1f}, {f.shift_px[1]:+.1f}) px, edge score {f.edge_score:.2f}",
           "view number, parity: green = confirmed by the grid shots, orange = not confirmed, "
           "red = flipped"]  # fmt: skip
    for i, line in enumerate(cap):
        cv2.putText(canvas, line, (6, 17 + 19 * i), cv2.FONT_HERSHEY_SIMPLEX, 0.45,
                    (230, 230, 230), 1, cv2.LINE_AA)  # fmt: skip
    ok, buf = cv2.imencode(".png", canvas)
    if not ok:
        raise RuntimeError("PNG encoding of the layout overlay failed")
    return atomic_write_bytes(Path(path), buf.tobytes())
