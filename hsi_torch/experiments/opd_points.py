"""Measured transmittance spectra at image-plane positions, and their match to the ray tracer's
predicted views (the inputs of the OPD experiment, :mod:`hsi_torch.experiments.opd`).

Points are sampled in every view's triangle of a reference-frame ``B`` (ground truth or a
bundle, :func:`points_from_reference_frame`), of a sensor-coordinate map (the monochromator scan,
:func:`points_from_sensor_map`) or read from a CSV (:func:`read_points_csv`).
:func:`match_points` assigns each point the predicted view whose triangle contains it (else the
nearest centroid) and the OPD of the ray traced through it.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from hsi_torch.experiments.opd_estimate import group_opd_nm
from hsi_torch.optics import build_view_layout, trace_rays
from hsi_torch.optics.geometry import apply_homography, points_in_triangle

__all__ = [
    "MeasuredPoints",
    "PredictedViews",
    "predicted_views",
    "match_points",
    "sample_offsets",
    "triangle_sample_points",
    "points_from_reference_frame",
    "points_from_sensor_map",
    "read_points_csv",
]


@dataclass
class MeasuredPoints:
    """``P`` measured transmittance spectra at image-plane (sensor px) positions.

    Attributes:
        xy: ``(P, 2)`` sensor px ``(x, y)``.
        T: ``(P, M)`` transmittance on ``wavelengths_nm (M,)``.
        view: ``(P,)`` long: the input's own view label (−1 unknown, e.g. CSV).
        point: ``(P,)`` long: the sample-point id within the view (or row number).
        label: text per point (CSV labels or ``v<view>p<point>``).
    """

    xy: Tensor
    T: Tensor
    wavelengths_nm: Tensor
    view: Tensor
    point: Tensor
    label: list[str]

    def select(self, keep: Tensor) -> MeasuredPoints:
        idx = torch.nonzero(keep.to(torch.bool)).squeeze(1)
        return MeasuredPoints(self.xy[idx], self.T[idx], self.wavelengths_nm, self.view[idx],
                              self.point[idx], [self.label[i] for i in idx.tolist()])


def sample_offsets(num_ring: int, ring_fraction: float) -> list[tuple[float, float]]:
    """Barycentric-free sample pattern of a triangle: the centroid plus, when ``num_ring`` is
    3 or 6, points ``ring_fraction`` of the way to the vertices (and the edge midpoints).

    Returns ``(weight_vertex_or_mid_index, fraction)`` pairs; index ``-1`` = centroid, 0–2 =
    vertices, 3–5 = edge midpoints ``P_i P_{i+1}``."""
    out = [(-1, 0.0)]
    if num_ring not in (0, 3, 6):
        raise ValueError(f"points.num_ring must be 0, 3 or 6, got {num_ring}")
    if num_ring >= 3:
        out += [(i, ring_fraction) for i in range(3)]
    if num_ring == 6:
        out += [(3 + i, ring_fraction) for i in range(3)]
    return out


def triangle_sample_points(tri: Tensor, num_ring: int = 6, ring_fraction: float = 0.35) -> Tensor:
    """``(K, 2)`` sample points of triangles ``tri (3, 2)``: centroid (+ ring, see
    :func:`sample_offsets`)."""
    c = tri.mean(0)
    targets = torch.cat([tri, 0.5 * (tri + tri.roll(-1, 0))], 0)  # vertices, edge midpoints
    pts = []
    for idx, frac in sample_offsets(num_ring, ring_fraction):
        pts.append(c if idx < 0 else c + frac * (targets[idx] - c))
    return torch.stack(pts)


def _collect_points(xs: list[Tensor], ts: list[Tensor], vs: list[Tensor], ps: list[Tensor],
                    wavelengths_nm: Tensor) -> MeasuredPoints:
    """:class:`MeasuredPoints` from per-view lists (positions, spectra, view and point ids),
    labelled ``v<view>p<point>``."""
    view = torch.cat(vs)
    point = torch.cat(ps)
    return MeasuredPoints(torch.cat(xs), torch.cat(ts).to(torch.float64),
                          torch.as_tensor(wavelengths_nm, dtype=torch.float64).cpu(), view,
                          point, [f"v{a}p{b}" for a, b in
                                  zip(view.tolist(), point.tolist(), strict=True)])


def points_from_reference_frame(
    B: Tensor,
    wavelengths_nm: Tensor,
    view_homographies: Tensor,
    triangles: Tensor,
    reference_bbox: tuple[int, int, int, int],
    usable: Tensor,
    *,
    num_ring: int = 6,
    ring_fraction: float = 0.35,
) -> MeasuredPoints:
    """Sample points of a reference-frame ``B (V, M, h, w)`` (ground truth or a bundle).

    The points are the reference triangle's centroid and ring (:func:`triangle_sample_points`),
    rounded to reference-frame pixels; for view ``v`` the spectrum is ``B[v, :, q]`` and the
    image-plane position is ``H_v⁻¹ (q + (x0, y0))`` (sensor px of view ``v``). Points where
    ``usable[v]`` (``(V, h, w)`` bool, e.g. the modulated mask) is False are dropped.
    """
    V, M, h, w = B.shape
    x0, y0 = int(reference_bbox[0]), int(reference_bbox[1])
    tri0 = triangles[0].to(torch.float64).cpu()
    q = triangle_sample_points(tri0, num_ring, ring_fraction) - torch.tensor(
        [x0, y0], dtype=torch.float64)
    qi = q.round().long()
    qi[:, 0] = qi[:, 0].clamp(0, w - 1)
    qi[:, 1] = qi[:, 1].clamp(0, h - 1)
    xs, ts, vs, ps = [], [], [], []
    hom = view_homographies.to(torch.float64).cpu()
    for v in range(V):
        ok = usable[v].cpu()[qi[:, 1], qi[:, 0]]
        idx = torch.nonzero(ok).squeeze(1)
        if idx.numel() == 0:
            continue
        q_s = qi[idx].to(torch.float64) + torch.tensor([x0, y0], dtype=torch.float64)
        xs.append(apply_homography(torch.linalg.inv(hom[v]), q_s))
        ts.append(B[v][:, qi[idx, 1].to(B.device), qi[idx, 0].to(B.device)].T.cpu())
        vs.append(torch.full((idx.numel(),), v, dtype=torch.long))
        ps.append(idx)
    if not xs:
        raise ValueError("no usable sample point in any view (check the masks)")
    return _collect_points(xs, ts, vs, ps, wavelengths_nm)


def points_from_sensor_map(
    B_sensor: Tensor,
    wavelengths_nm: Tensor,
    triangles: Tensor,
    usable: Tensor | None = None,
    *,
    num_ring: int = 6,
    ring_fraction: float = 0.35,
) -> MeasuredPoints:
    """Sample points of a sensor-coordinate transmittance ``B_sensor (M, H, W)`` (a scan):
    centroid and ring of every triangle ``(V, 3, 2)`` (e.g. the nominal layout), nearest pixel.
    ``usable (H, W)`` bool drops points (e.g. unlit or BRF-free pixels)."""
    M, H, W = B_sensor.shape
    xs, ts, vs, ps = [], [], [], []
    for v in range(triangles.shape[0]):
        pts = triangle_sample_points(triangles[v].to(torch.float64).cpu(), num_ring,
                                     ring_fraction).round()
        pts[:, 0] = pts[:, 0].clamp(0, W - 1)
        pts[:, 1] = pts[:, 1].clamp(0, H - 1)
        pi = pts.long()
        ok = torch.ones(pi.shape[0], dtype=torch.bool)
        if usable is not None:
            ok = usable.cpu()[pi[:, 1], pi[:, 0]]
        idx = torch.nonzero(ok).squeeze(1)
        xs.append(pts[idx])
        ts.append(B_sensor[:, pi[idx, 1].to(B_sensor.device), pi[idx, 0].to(B_sensor.device)]
                  .T.cpu())
        vs.append(torch.full((idx.numel(),), v, dtype=torch.long))
        ps.append(idx)
    return _collect_points(xs, ts, vs, ps, wavelengths_nm)


def read_points_csv(path: str | Path) -> MeasuredPoints:
    """Measured spectra from a CSV: columns ``x_px, y_px`` (sensor px), optional ``label``, and
    one column per wavelength whose header is the wavelength in nm (e.g. ``430``, ``440.5``).

    Raises:
        FileNotFoundError, ValueError: missing file/columns, non-numeric values (file and row
        named).
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"OPD points CSV not found: {p}")
    with p.open(newline="") as fh:
        rows = list(csv.reader(fh))
    rows = [r for r in rows if r and not r[0].lstrip().startswith("#")]
    if len(rows) < 2:
        raise ValueError(f"{p}: needs a header and at least one row")
    head = [h.strip() for h in rows[0]]
    for need in ("x_px", "y_px"):
        if need not in head:
            raise ValueError(f"{p}: missing column {need!r} (header: {head})")
    wl_cols, wls = [], []
    for i, h in enumerate(head):
        if h in ("x_px", "y_px", "label"):
            continue
        try:
            wls.append(float(h.removesuffix("nm")))
        except ValueError as exc:
            raise ValueError(f"{p}: column {h!r} is neither x_px/y_px/label nor a wavelength "
                             "in nm") from exc
        wl_cols.append(i)
    if len(wl_cols) < 4:
        raise ValueError(f"{p}: needs at least 4 wavelength columns, got {len(wl_cols)}")
    order = np.argsort(wls)
    ix, iy = head.index("x_px"), head.index("y_px")
    il = head.index("label") if "label" in head else None
    xy, T, labels = [], [], []
    for n, r in enumerate(rows[1:], start=2):
        try:
            xy.append((float(r[ix]), float(r[iy])))
            T.append([float(r[wl_cols[o]]) for o in order])
        except (ValueError, IndexError) as exc:
            raise ValueError(f"{p}: row {n}: {exc}") from exc
        labels.append(r[il] if il is not None else f"row{n}")
    n_pts = len(xy)
    return MeasuredPoints(torch.tensor(xy, dtype=torch.float64),
                          torch.tensor(T, dtype=torch.float64),
                          torch.tensor(np.asarray(wls)[order], dtype=torch.float64),
                          torch.full((n_pts,), -1, dtype=torch.long), torch.arange(n_pts), labels)


@dataclass
class PredictedViews:
    """The ray tracer's views: ``layout`` (:class:`~hsi_torch.optics.ViewLayout`), ``centres
    (V, 2)`` triangle centroids (sensor px), and the optics to trace measured points with."""

    layout: Any
    centres: Tensor
    geometry: Any
    camera: Any
    brf: Any


def predicted_views(geometry: Any, camera: Any, brf: Any, layout: Any | None = None
                    ) -> PredictedViews:
    """Predicted view layout of a design (built with :func:`hsi_torch.optics.build_view_layout`
    when not given)."""
    lay = layout if layout is not None else build_view_layout(geometry, camera, brf)
    lay = lay.to("cpu", torch.float64)
    return PredictedViews(lay, lay.triangles.mean(1), geometry, camera, brf)


def match_points(pred: PredictedViews, xy: Tensor, wavelength_nm: float, k0_nm: float
                 ) -> dict[str, Tensor]:
    """Match image-plane points ``xy (P, 2)`` to predicted views and predict their OPD.

    A point belongs to the predicted view whose triangle contains it; points outside every
    triangle go to the nearest centroid. The ray traced through the point gives ``(α, σ)``
    when it lands in the matched view, else the view's mean angles are used
    (``traced = False``).

    Returns:
        dict of ``(P,)`` tensors: ``view``, ``distance_px`` (to the matched centre),
        ``inside``, ``traced``, ``alpha``, ``sigma`` (rad), ``opd_phase_nm`` (Δ at
        ``wavelength_nm``), ``opd_group_nm`` (Δ_g at ``k0_nm``), ``view_opd_phase_nm`` and
        ``view_opd_group_nm`` (at the view's mean angles).
    """
    lay = pred.layout
    xy = xy.to(torch.float64).cpu()
    inside = points_in_triangle(xy.unsqueeze(0), lay.triangles).T  # (P, V)
    dist = torch.cdist(xy, pred.centres)  # (P, V)
    big = torch.where(inside, dist, dist + 1e9)
    view = big.argmin(1)
    ins = inside.gather(1, view[:, None])[:, 0]
    tr = trace_rays(pred.geometry, pred.camera, xy, sequences=lay.reflection_sequences)
    traced = tr.view_index == view
    alpha = torch.where(traced, tr.alpha.to(torch.float64), lay.mean_alpha[view])
    sigma = torch.where(traced, tr.sigma.to(torch.float64), lay.mean_sigma[view])
    lam = torch.tensor([wavelength_nm], dtype=torch.float64)
    phase = pred.brf.opd_nm(alpha[:, None], sigma[:, None], lam)[:, 0]
    group = group_opd_nm(pred.brf, alpha, sigma, k0_nm)
    v_phase = pred.brf.opd_nm(lay.mean_alpha[:, None], lay.mean_sigma[:, None], lam)[:, 0]
    v_group = group_opd_nm(pred.brf, lay.mean_alpha, lay.mean_sigma, k0_nm)
    return {"view": view, "distance_px": dist.gather(1, view[:, None])[:, 0], "inside": ins,
            "traced": traced, "alpha": alpha, "sigma": sigma, "opd_phase_nm": phase,
            "opd_group_nm": group, "view_opd_phase_nm": v_phase[view],
            "view_opd_group_nm": v_group[view]}
