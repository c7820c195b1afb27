"""Plane geometry shared by the simulator, calibration and reconstruction: homographies,
triangles and the warping of the kaleidoscope's views into the reference frame.

Conventions (one for the whole package):
    * Points are ``(x, y) = (column, row)`` in pixels with pixel centres at integer coordinates
      (kornia's ``align_corners=True``), or mm on the diffuser plane.
    * A homography ``H (3, 3)`` acts on homogeneous column vectors: ``q ~ H (x, y, 1)ᵀ``.
      ``view_homographies[v]`` maps sensor px of view ``v`` to sensor px of the reference view
      (``H_0 = I``; mirrored views have ``det H_v < 0``). The reference frame is the sensor crop
      ``reference_bbox = (x0, y0, w, h)``: reference-frame pixel ``(j, i)`` is reference sensor
      px ``(x0 + j, y0 + i)`` and has flat index ``p = i·w + j``.
    * Triangles ``(3, 2)`` may have either orientation; a point is *inside* when its signed
      distance to every edge, positive towards the interior, is at least ``inset`` (edges
      included for ``inset = 0``). :func:`triangle_edge_distance` is that distance; every
      point-in-triangle test of the package is :func:`points_in_triangle`.

All functions take torch tensors on any device (float32 or float64, computed in the input's
dtype unless stated); :func:`apply_homography` and :func:`triangle_edge_distance` also accept
numpy arrays and then return numpy arrays (the OpenCV side of calibration).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from kornia.geometry.conversions import normalize_pixel_coordinates
from kornia.geometry.transform import warp_perspective
from torch import Tensor

from hsi_torch.devices import to_numpy

__all__ = [
    "apply_homography",
    "triangle_edge_distance",
    "points_in_triangle",
    "reference_to_view_points",
    "reference_pixel_points",
    "pixel_centres",
    "view_sample_grid",
    "reference_to_source_matrices",
    "view_masks",
    "warp_views",
]


def apply_homography(h: Tensor | np.ndarray, pts: Tensor | np.ndarray) -> Tensor | np.ndarray:
    """Map points by homographies: ``q = (H p̃)_{xy} / (H p̃)_z`` with ``p̃ = (x, y, 1)``.

    Args:
        h: ``(3, 3)`` or ``(..., 3, 3)`` broadcasting against ``pts``' leading dimensions.
        pts: ``(..., N, 2)`` points (a ``(3, 3)`` ``h`` also takes any ``(..., 2)``).

    Returns:
        Mapped points of ``pts``' shape: a tensor in ``pts``' dtype and device, or a float64
        numpy array when both arguments are numpy arrays (the OpenCV side of calibration).
    """
    if not isinstance(pts, Tensor) and not isinstance(h, Tensor):
        return apply_homography(_f64(h), _f64(pts)).numpy()
    pts = torch.as_tensor(pts)
    h = torch.as_tensor(h).to(device=pts.device, dtype=pts.dtype)
    ph = torch.cat([pts, torch.ones_like(pts[..., :1])], dim=-1) @ h.transpose(-1, -2)
    return ph[..., :2] / ph[..., 2:]


def triangle_edge_distance(
    points: Tensor | np.ndarray, triangles: Tensor | np.ndarray
) -> Tensor | np.ndarray:
    """Signed distance of points to the nearest edge of triangles (positive inside).

    Args:
        points: ``(..., N, 2)``.
        triangles: ``(..., 3, 2)`` vertices, either orientation; leading dimensions broadcast
            against ``points``' (e.g. ``(V, 3, 2)`` with ``(V, N, 2)`` or ``(1, N, 2)``).

    Returns:
        ``(..., N)``: ``min_k s · cross(e_k, p − a_k) / |e_k|`` with ``s`` the sign of the
        triangle's signed area (``+1`` for a degenerate one). Numpy in, numpy out.
    """
    if not isinstance(points, Tensor) and not isinstance(triangles, Tensor):
        return triangle_edge_distance(_f64(points), _f64(triangles)).numpy()
    p = torch.as_tensor(points)
    tri = torch.as_tensor(triangles).to(device=p.device, dtype=p.dtype)
    a, b, c = tri[..., 0, :], tri[..., 1, :], tri[..., 2, :]
    area = (b[..., 0] - a[..., 0]) * (c[..., 1] - a[..., 1]) - (b[..., 1] - a[..., 1]) * (
        c[..., 0] - a[..., 0])  # fmt: skip
    sgn = torch.where(area >= 0, 1.0, -1.0).to(p.dtype)[..., None]
    px, py = p[..., 0], p[..., 1]
    out = None
    for u, v in ((a, b), (b, c), (c, a)):
        e = v - u
        cross = e[..., 0:1] * (py - u[..., 1:2]) - e[..., 1:2] * (px - u[..., 0:1])
        d = sgn * cross / e.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        out = d if out is None else torch.minimum(out, d)
    return out


def points_in_triangle(points: Tensor, triangles: Tensor, inset: float = 0.0) -> Tensor:
    """``(..., N)`` bool: the points lie inside the triangles, at least ``inset`` from every edge
    (edges included for ``inset = 0``). Shapes as :func:`triangle_edge_distance`; the test is
    ``triangle_edge_distance(points, triangles) >= inset``."""
    return triangle_edge_distance(points, triangles) >= inset


def reference_pixel_points(
    reference_bbox: Sequence[int], pixel_index: Tensor | None = None, *,
    device: torch.device | str | None = None, dtype: torch.dtype = torch.float64,
) -> Tensor:
    """Reference sensor px ``(P, 2)`` of reference-frame pixels (flat row-major ``pixel_index``,
    default all ``h·w``): ``(x0 + j, y0 + i)`` for ``p = i·w + j``."""
    x0, y0, w, h = _check_bbox(reference_bbox)
    if pixel_index is None:
        pixel_index = torch.arange(h * w, device=device)
    idx = torch.as_tensor(pixel_index, device=device)
    q = torch.stack([idx % w + x0, idx // w + y0], dim=1)
    return q.to(torch.float64).to(dtype)


def pixel_centres(height: int, width: int, *, device: torch.device | str | None = None,
                  dtype: torch.dtype = torch.float64) -> Tensor:
    """``(H, W, 2)`` sensor px ``(x, y)`` of every pixel centre."""
    ys, xs = torch.meshgrid(torch.arange(height, device=device, dtype=dtype),
                            torch.arange(width, device=device, dtype=dtype), indexing="ij")
    return torch.stack([xs, ys], -1)


def reference_to_view_points(view_homographies: Tensor, points: Tensor) -> Tensor:
    """Where reference sensor px ``points (P, 2)`` lie in every view: ``H_v⁻¹ q``, ``(V, P, 2)``
    (float64, on ``points``' device)."""
    _check_homographies(view_homographies)
    q = torch.as_tensor(points).to(torch.float64)
    hinv = torch.linalg.inv(view_homographies.to(device=q.device, dtype=torch.float64))
    return apply_homography(hinv, q.unsqueeze(0))


def view_sample_grid(
    view_homographies: Tensor,
    reference_bbox: Sequence[int],
    sensor_size: Sequence[int],
    pixel_index: Tensor | None = None,
    dtype: torch.dtype | None = None,
) -> Tensor:
    """Sensor positions of reference-frame pixels in every view, as a ``grid_sample`` grid.

    Reference-frame pixel ``p = i·w + j`` is reference sensor px ``q = (j + x0, i + y0)``; in view
    ``v`` it lies at ``H_v⁻¹ q`` (:func:`reference_to_view_points`, float64), normalised for
    ``grid_sample(align_corners=True)``: ``x_n = 2x/(W − 1) − 1``, ``y_n = 2y/(H − 1) − 1``
    (kornia's ``normalize_pixel_coordinates``). Sampling the sensor image there is what
    :func:`warp_views` computes at those pixels.

    Args:
        sensor_size: ``(H, W)``.
        pixel_index: ``(P,)`` flat row-major reference-frame indices (default all ``h·w``).
        dtype: of the result (default: ``view_homographies``' dtype).

    Returns:
        ``(1, V, P, 2)`` normalised ``(x, y)`` on ``pixel_index``' (else the homographies')
        device.
    """
    dev = pixel_index.device if pixel_index is not None else view_homographies.device
    H, W = (int(v) for v in sensor_size)
    q = reference_pixel_points(reference_bbox, pixel_index, device=dev)
    src = reference_to_view_points(view_homographies, q)  # (V, P, 2)
    grid = normalize_pixel_coordinates(src, H, W)
    return grid.unsqueeze(0).to(dtype or view_homographies.dtype)


def _f64(a: np.ndarray | Sequence) -> Tensor:
    """A float64 tensor of an array-like (a copy where numpy's strides torch cannot share)."""
    return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float64))


def _check_bbox(reference_bbox: Sequence[int] | Tensor) -> tuple[int, int, int, int]:
    bb = [int(v) for v in to_numpy(reference_bbox).reshape(-1).tolist()]
    if len(bb) != 4 or bb[2] <= 0 or bb[3] <= 0:
        raise ValueError(f"reference_bbox must be (x0, y0, w, h) with w, h > 0, got {bb}")
    return bb[0], bb[1], bb[2], bb[3]


def _check_homographies(view_homographies: Tensor) -> None:
    if not isinstance(view_homographies, Tensor):
        raise TypeError(f"view_homographies must be a tensor, got {type(view_homographies)}")
    if view_homographies.ndim != 3 or view_homographies.shape[1:] != (3, 3):
        raise ValueError(
            f"view_homographies must be (V, 3, 3), got {tuple(view_homographies.shape)}"
        )


def reference_to_source_matrices(
    view_homographies: Tensor, reference_bbox: Sequence[int] | Tensor
) -> Tensor:
    """Matrices ``M_v = T_crop · H_v`` mapping view-v sensor px → reference-frame px.

    ``T_crop`` translates by ``(−x0, −y0)``. These are the ``M`` that
    ``kornia.geometry.transform.warp_perspective`` expects (it samples ``src(M⁻¹ x)``);
    ``(V, 3, 3)``, dtype/device of ``view_homographies``.
    """
    _check_homographies(view_homographies)
    x0, y0, _, _ = _check_bbox(reference_bbox)
    T = torch.eye(3, dtype=view_homographies.dtype, device=view_homographies.device)
    T[0, 2] = -float(x0)
    T[1, 2] = -float(y0)
    return T @ view_homographies


def view_masks(
    view_homographies: Tensor,
    triangles: Tensor,
    reference_bbox: Sequence[int] | Tensor,
    sensor_size: Sequence[int] | None = None,
    inset_px: float = 1.0,
) -> Tensor:
    """Analytic per-view masks in the reference frame: pixels whose source lies inside the view.

    A reference-frame pixel ``q`` belongs to view ``v`` when ``H_v⁻¹ (q + (x0, y0))`` lies inside
    triangle ``v`` by at least ``inset_px`` (:func:`points_in_triangle`, so bilinear sampling does
    not mix in the dark border) and inside the sensor ``[0, W−1] × [0, H−1]`` when
    ``sensor_size = (H, W)`` is given.

    Args:
        triangles: ``(V, 3, 2)`` sensor px.
        inset_px: inward margin from the triangle edges (px of the view's sensor image).

    Returns:
        ``(V, h, w)`` bool tensor on the device of ``view_homographies``.
    """
    _check_homographies(view_homographies)
    x0, y0, w, h = _check_bbox(reference_bbox)
    V = view_homographies.shape[0]
    dev = view_homographies.device
    tri = torch.as_tensor(triangles, device=dev, dtype=torch.float64)
    if tri.shape != (V, 3, 2):
        raise ValueError(f"triangles must be (V, 3, 2) = ({V}, 3, 2), got {tuple(tri.shape)}")
    q = reference_pixel_points((x0, y0, w, h), device=dev)
    src = reference_to_view_points(view_homographies, q)  # (V, h·w, 2)
    inside = torch.isfinite(src).all(-1) & points_in_triangle(src, tri, inset_px)
    if sensor_size is not None:
        Hs, Ws = (int(s) for s in sensor_size)
        qx, qy = src[..., 0], src[..., 1]
        inside &= (qx >= 0) & (qx <= Ws - 1) & (qy >= 0) & (qy <= Hs - 1)
    return inside.reshape(V, h, w)


def warp_views(
    image: Tensor,
    view_homographies: Tensor,
    reference_bbox: Sequence[int] | Tensor,
    triangles: Tensor | None = None,
    inset_px: float = 1.0,
    mode: str = "bilinear",
) -> tuple[Tensor, Tensor | None]:
    """Warp every view of a sensor image into the reference frame with ONE kornia call.

    The image is expanded (not copied) along the view axis and warped with
    ``kornia.geometry.transform.warp_perspective(align_corners=True)`` using
    ``M_v = T_crop · H_v`` (see :func:`reference_to_source_matrices`).

    Args:
        image: ``(C, H, W)`` or ``(B, C, H, W)`` sensor image(s), any float dtype/device.
        triangles: optional ``(V, 3, 2)``; when given, the per-view validity masks are returned.
        inset_px: inward triangle margin of the masks (see :func:`view_masks`).
        mode: ``"bilinear"`` or ``"nearest"``.

    Returns:
        ``(warped, masks)``: ``warped`` is ``(V, C, h, w)`` for a ``(C, H, W)`` input or
        ``(B, V, C, h, w)`` for a batch; ``masks`` is ``(V, h, w)`` bool (or ``None``).
    """
    if not isinstance(image, Tensor):
        raise TypeError(f"image must be a torch.Tensor, got {type(image)}")
    if image.ndim not in (3, 4):
        raise ValueError(f"image must be (C, H, W) or (B, C, H, W), got {tuple(image.shape)}")
    if not image.is_floating_point():
        raise TypeError(f"image must be floating point, got {image.dtype}")
    _check_homographies(view_homographies)
    x0, y0, w, h = _check_bbox(reference_bbox)
    batched = image.ndim == 4
    img4 = image if batched else image[None]
    B, C, H, W = img4.shape
    V = view_homographies.shape[0]
    M = reference_to_source_matrices(
        view_homographies.to(device=image.device, dtype=image.dtype), (x0, y0, w, h)
    )
    src = img4.reshape(1, B * C, H, W).expand(V, B * C, H, W)
    out = warp_perspective(src, M, (h, w), mode=mode, align_corners=True)  # (V, B*C, h, w)
    out = out.reshape(V, B, C, h, w)
    out = out.permute(1, 0, 2, 3, 4) if batched else out[:, 0]
    masks = None
    if triangles is not None:
        masks = view_masks(
            view_homographies.to(image.device), triangles, (x0, y0, w, h), (H, W), inset_px
        )
    return out, masks
