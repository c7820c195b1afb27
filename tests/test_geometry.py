"""optics.geometry: the one homography, point-in-triangle and view-warping code of the package."""

from __future__ import annotations

import cv2
import numpy as np
import torch

from hsi_torch.optics import DEFAULT_CAMERA, DEFAULT_GEOMETRY, build_view_layout
from hsi_torch.optics.geometry import (
    apply_homography,
    points_in_triangle,
    reference_to_view_points,
    triangle_edge_distance,
    view_masks,
    view_sample_grid,
    warp_views,
)


def test_points_in_triangle_inset_and_either_orientation(device, dtype):
    tri = torch.tensor([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]], dtype=dtype, device=device)
    p = torch.tensor([[1.0, 1.0], [0.5, 5.0], [6.0, 6.0], [5.0, 5.0], [0.0, 0.0]], dtype=dtype,
                     device=device)  # fmt: skip
    # edges and vertices are inside for inset = 0 (the one edge rule)
    assert points_in_triangle(p, tri).tolist() == [True, True, False, True, True]
    assert points_in_triangle(p, tri, inset=0.8).tolist() == [True, False, False, False, False]
    # either orientation (the one orientation rule)
    for t in (tri.flip(0), tri[[1, 2, 0]], tri[[0, 2, 1]]):
        assert points_in_triangle(p, t).tolist() == [True, True, False, True, True]
        assert points_in_triangle(p, t, inset=0.8).tolist() == [True, False, False, False, False]
    d = triangle_edge_distance(p, tri)
    assert d.dtype == dtype and d.device.type == device.type
    torch.testing.assert_close(d[:2].cpu().double(), torch.tensor([1.0, 0.5], dtype=torch.float64))


def test_edge_distance_matches_opencv_point_polygon_test():
    g = np.random.default_rng(0)
    for _ in range(5):
        tri = g.uniform(-50, 50, (3, 2))
        pts = g.uniform(tri.min(0) - 5, tri.max(0) + 5, (400, 2))
        ours = triangle_edge_distance(pts, tri)  # numpy in, numpy out
        assert isinstance(ours, np.ndarray) and ours.shape == (400,)
        contour = tri.astype(np.float32).reshape(-1, 1, 2)
        ref = np.array([cv2.pointPolygonTest(contour, (float(x), float(y)), True)
                        for x, y in pts])  # fmt: skip
        inside, outside = ref > 1e-3, ref < -1e-3
        # inside, OpenCV's distance is the distance to the nearest edge (as ours)
        np.testing.assert_allclose(ours[inside], ref[inside], rtol=1e-5, atol=1e-3)
        assert (ours[outside] < 0).all() and outside.sum() > 20 and inside.sum() > 20


def test_points_in_triangle_batched_over_views():
    tris = torch.tensor([[[0.0, 0.0], [4.0, 0.0], [0.0, 4.0]],
                         [[10.0, 10.0], [10.0, 14.0], [14.0, 10.0]]], dtype=torch.float64)
    p = torch.tensor([[1.0, 1.0], [11.0, 11.0]], dtype=torch.float64)
    got = points_in_triangle(p.unsqueeze(0), tris)  # (2 views, 2 points)
    assert got.tolist() == [[True, False], [False, True]]
    single = torch.stack([points_in_triangle(p, t) for t in tris])
    assert torch.equal(got, single)


def test_apply_homography_numpy_torch_batched(dtype):
    g = np.random.default_rng(1)
    H = np.eye(3) + 0.01 * g.standard_normal((3, 3))
    pts = g.uniform(0, 100, (50, 2))
    ref = cv2.perspectiveTransform(pts[None], H)[0]
    np.testing.assert_allclose(apply_homography(H, pts), ref, rtol=1e-12, atol=1e-10)
    got = apply_homography(torch.from_numpy(H), torch.from_numpy(pts).to(dtype))
    assert got.dtype == dtype
    tol = 1e-12 if dtype == torch.float64 else 1e-4
    np.testing.assert_allclose(got.double().numpy(), ref, rtol=tol, atol=tol)
    Hs = torch.from_numpy(np.stack([H, np.linalg.inv(H)]))
    both = apply_homography(Hs, torch.from_numpy(pts).unsqueeze(0))  # (2, 50, 2)
    torch.testing.assert_close(apply_homography(Hs[1], both[0]), torch.from_numpy(pts))


def test_view_warps_agree_at_the_prototypes_layout():
    """warp_views (full frame, kornia warp_perspective), view_sample_grid + grid_sample (sparse
    pixels) and the masks agree on the default prototype's homographies and triangles."""
    lay = build_view_layout(DEFAULT_GEOMETRY, DEFAULT_CAMERA)
    Hs, tris, bbox = lay.view_homographies, lay.triangles, lay.reference_bbox
    H, W = lay.sensor_size
    img = torch.rand(2, H, W, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    warped, masks = warp_views(img, Hs, bbox, tris, inset_px=1.0)
    V, _, h, w = warped.shape
    grid = view_sample_grid(Hs, bbox, (H, W))[0].reshape(V, h, w, 2)
    sampled = torch.nn.functional.grid_sample(img.expand(V, -1, -1, -1), grid,
                                              align_corners=True)  # fmt: skip
    m = masks.unsqueeze(1).expand_as(sampled)
    torch.testing.assert_close(sampled[m], warped[m], rtol=0, atol=1e-6)
    # a pixel is in a view's mask iff its source point is 1 px inside that view's triangle
    x0, y0 = bbox[0], bbox[1]
    q = torch.tensor([[x0 + w / 2, y0 + h / 2]], dtype=torch.float64)
    src = reference_to_view_points(Hs, q)  # (V, 1, 2)
    inside = points_in_triangle(src, tris, 1.0)[:, 0]
    assert torch.equal(masks[:, h // 2, w // 2], inside)
    assert torch.equal(view_masks(Hs, tris, bbox, (H, W)), masks)


def test_numpy_views_with_negative_strides():
    """OpenCV-side callers pass reversed views (``pts[::-1]``); numpy in, numpy out."""
    H = np.array([[1.0, 0.1, 3.0], [0.0, 0.9, -2.0], [1e-4, 0.0, 1.0]])
    pts = np.arange(20.0).reshape(10, 2)
    np.testing.assert_array_equal(apply_homography(H, pts[::-1]), apply_homography(H, pts)[::-1])
    tri = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]])
    np.testing.assert_array_equal(triangle_edge_distance(pts[::-1], tri[::-1]),
                                  triangle_edge_distance(pts, tri)[::-1])
