"""Tapered-kaleidoscope ray tracer and view layout."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from hsi_torch.optics import (
    DEFAULT_CAMERA,
    DEFAULT_GEOMETRY,
    FULL_CAMERA,
    BRFConfig,
    CameraModel,
    KaleidoscopeGeometry,
    ViewLayout,
    apply_homography,
    build_view_layout,
    diffuser_to_sensor_homography,
    enumerate_sequences,
    fit_homography_dlt,
    trace_rays,
    trace_sensor,
)
from hsi_torch.spectral import DEFAULT_GRID, resample_spectra

SMALL_CAM = DEFAULT_CAMERA.scaled(0.5)  # 200 x 192 px, same optics


@pytest.fixture(scope="module")
def default_trace():
    return trace_sensor(DEFAULT_GEOMETRY, DEFAULT_CAMERA, dtype=torch.float64)


@pytest.fixture(scope="module")
def default_layout(default_trace) -> ViewLayout:
    return build_view_layout(DEFAULT_GEOMETRY, DEFAULT_CAMERA, trace=default_trace)


def _reflect_2d(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Reflect points ``p (N, 2)`` across the line through ``a`` and ``b``."""
    u = (b - a) / np.linalg.norm(b - a)
    q = p - a
    return a + 2 * (q @ u)[:, None] * u - q


def _fold(u: np.ndarray, seq, verts: np.ndarray) -> np.ndarray:
    """Diffuser point of the unfolded point ``u`` seen through ``seq``: S_mn(…S_m1(u))."""
    for m in seq:
        u = _reflect_2d(u, verts[m], verts[(m + 1) % 3])
    return u


def _inside(p: np.ndarray, verts: np.ndarray, margin: float = 0.0) -> np.ndarray:
    ok = np.ones(len(p), dtype=bool)
    for i in range(3):
        a, b = verts[i], verts[(i + 1) % 3]
        e = (b - a) / np.linalg.norm(b - a)
        ok &= (e[0] * (p[:, 1] - a[1]) - e[1] * (p[:, 0] - a[0])) >= margin
    return ok


@pytest.mark.parametrize(
    "vertices",
    [None, ((-6.0, -5.0), (8.0, -1.0), (-2.0, 6.0))],
    ids=["equilateral", "scalene"],
)
def test_straight_tube_reproduces_mirror_unfolding(device, dtype, vertices):
    geo = KaleidoscopeGeometry(
        a_in_mm=16,
        a_out_mm=16,
        length_mm=160,
        pupil_distance_mm=12,
        max_reflections=3,
        vertices_in=vertices,
    )
    tr = trace_sensor(geo, SMALL_CAM, device=device, dtype=dtype)
    assert tr.hit_xy.dtype == dtype and tr.hit_xy.device.type == device.type
    verts = geo.entrance_vertices(dtype=torch.float64).numpy()
    cam = SMALL_CAM
    pix = cam.pixel_grid(dtype=torch.float64).numpy()
    scale = cam.pixel_pitch_mm * geo.pupil_z / cam.focal_length_mm
    unf = (pix - [cam.cx, cam.cy]) * scale  # straight ray from the pupil to z = 0
    view = tr.view_index.reshape(-1).cpu().numpy()
    hit = tr.hit_xy.reshape(-1, 2).cpu().double().numpy()
    alpha = tr.alpha.reshape(-1).cpu().double().numpy()
    parity = tr.parity.reshape(-1).cpu().numpy()
    tol = 1e-9 if dtype == torch.float64 else 2e-3
    seen = 0
    for v, seq in enumerate(tr.sequences):
        sel = view == v
        if not sel.any():
            continue
        seen += 1
        folded = _fold(unf[sel], seq, verts)
        np.testing.assert_allclose(hit[sel], folded, atol=tol, rtol=0)
        assert _inside(folded, verts, margin=-tol).all()
        assert (parity[sel] == (-1) ** len(seq)).all()
        np.testing.assert_allclose(
            alpha[sel],
            np.arctan2(np.linalg.norm(unf[sel], axis=1), geo.pupil_z),
            atol=10 * tol,
            rtol=0,
        )
    assert seen >= 10
    # brute force: the traced view is the unique <= 2-reflection unfolded tile containing the point
    if vertices is None and dtype == torch.float64:
        seqs2 = enumerate_sequences(2)
        interior = np.stack([_inside(_fold(unf, s, verts), verts, margin=1e-6) for s in seqs2], 1)
        exit_ok = _inside(unf * (geo.pupil_distance_mm / geo.pupil_z), verts * geo.taper_ratio)
        inner = interior.any(1) & exit_ok
        assert (interior.sum(1) <= 1).all()
        assert (view[inner] == np.argmax(interior[inner], 1)).all()
        assert inner.sum() > 0.5 * (view >= 0).sum() - 1


def test_default_geometry_gives_ten_views(default_layout):
    lay = default_layout
    assert lay.num_views == 10
    n_ref = [len(s) for s in lay.reflection_sequences]
    assert [n_ref.count(k) for k in (0, 1, 2)] == [1, 3, 6]
    assert lay.reflection_sequences[0] == ()
    torch.testing.assert_close(lay.parity, torch.tensor([(-1) ** n for n in n_ref]))
    # every view is complete: about as many pixels as the reference triangle
    assert bool((lay.pixel_count > 0.9 * lay.pixel_count[0]).all())
    # reference triangle ≈ 120 px on a side, views inside the sensor
    side = (lay.triangles[0, 1] - lay.triangles[0, 0]).norm()
    assert 110 < float(side) < 130
    h, w = lay.sensor_size
    assert (h, w) == (DEFAULT_CAMERA.height_px, DEFAULT_CAMERA.width_px) and 380 <= min(h, w) <= 500
    assert float(lay.triangles[..., 0].min()) > 0 and float(lay.triangles[..., 0].max()) < w - 1
    assert float(lay.triangles[..., 1].min()) > 0 and float(lay.triangles[..., 1].max()) < h - 1


@pytest.mark.parametrize("max_refl,expected", [(0, 1), (1, 4), (2, 10)])
def test_view_count_by_max_reflections(max_refl, expected):
    geo = KaleidoscopeGeometry(max_reflections=max_refl)
    tr = trace_sensor(geo, SMALL_CAM)
    present = torch.unique(tr.view_index[tr.view_index >= 0])
    assert present.numel() == expected == len(enumerate_sequences(max_refl))
    torch.testing.assert_close(
        tr.throughput[tr.valid], geo.mirror_reflectance ** tr.n_reflections[tr.valid].double()
    )


def test_taper_widens_angle_spread():
    straight = build_view_layout(KaleidoscopeGeometry(a_out_mm=16.0), SMALL_CAM)
    tapered = build_view_layout(KaleidoscopeGeometry(a_out_mm=28.0), SMALL_CAM)
    assert straight.num_views == tapered.num_views == 10
    spread_s = float(straight.mean_alpha.max() - straight.mean_alpha.min())
    spread_t = float(tapered.mean_alpha.max() - tapered.mean_alpha.min())
    assert spread_t > 1.3 * spread_s
    # each reflection adds about 2τ (τ = mirror tilt) to the angle at the filter
    tau = math.atan((28.0 - 16.0) / (2 * math.sqrt(3)) / 160.0)
    for k in (1, 2):
        sel = [i for i, s in enumerate(tapered.reflection_sequences) if len(s) == k]
        gain = float((tapered.mean_alpha[sel] - straight.mean_alpha[sel]).mean())
        assert 0.8 * k * 2 * tau < gain < 1.1 * k * 2 * tau


def test_homographies_exact(default_layout):
    lay = default_layout
    assert float(lay.homography_residual_px.max()) < 1e-6
    torch.testing.assert_close(lay.view_homographies[0], torch.eye(3, dtype=torch.float64))
    for v, seq in enumerate(lay.reflection_sequences):
        ref = diffuser_to_sensor_homography(
            DEFAULT_GEOMETRY, DEFAULT_CAMERA, seq, dtype=torch.float64
        )
        torch.testing.assert_close(lay.diffuser_homographies[v], ref, rtol=1e-7, atol=1e-7)
    # odd views are mirrored: negative determinant of the affine part
    det = torch.linalg.det(lay.diffuser_homographies[:, :2, :2])
    torch.testing.assert_close(torch.sign(det).long(), lay.parity)


def test_dlt_recovers_known_homography():
    h = torch.tensor([[1.2, 0.1, 5.0], [-0.2, 0.9, -3.0], [1e-3, -2e-3, 1.0]], dtype=torch.float64)
    src = torch.rand(50, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 100
    torch.testing.assert_close(fit_homography_dlt(src, apply_homography(h, src)), h)
    with pytest.raises(ValueError, match="at least 4"):
        fit_homography_dlt(src[:3], src[:3])


def test_subpixel_trace_maps_reference_points_to_views(device, default_layout):
    lay = default_layout.to(device)
    g = torch.Generator().manual_seed(1)
    bary = torch.rand(200, 3, generator=g, dtype=torch.float64) + 0.05
    bary = bary / bary.sum(1, keepdim=True)
    pts = (bary @ DEFAULT_GEOMETRY.entrance_vertices(dtype=torch.float64)).to(device)
    for v in range(lay.num_views):
        px = apply_homography(lay.diffuser_homographies[v], pts)
        tr = trace_rays(DEFAULT_GEOMETRY, DEFAULT_CAMERA, px)
        assert bool((tr.view_index == v).all())
        torch.testing.assert_close(tr.hit_xy, pts, rtol=0, atol=1e-9)
        # reference-frame pixel → view pixel and back
        ref_px = apply_homography(lay.diffuser_homographies[0], pts)
        torch.testing.assert_close(lay.reference_to_view(v, ref_px), px, rtol=0, atol=1e-6)


def test_float32_trace_agrees_with_float64(device):
    t64 = trace_sensor(DEFAULT_GEOMETRY, SMALL_CAM, device=device, dtype=torch.float64)
    t32 = trace_sensor(DEFAULT_GEOMETRY, SMALL_CAM, device=device, dtype=torch.float32)
    same = t64.view_index == t32.view_index
    assert float(same.double().mean()) > 0.995
    both = same & t64.valid
    torch.testing.assert_close(t32.hit_xy[both].double(), t64.hit_xy[both], rtol=0, atol=2e-3)
    torch.testing.assert_close(t32.alpha[both].double(), t64.alpha[both], rtol=0, atol=1e-5)


def test_brf_free_patch_in_reference_view(default_layout, default_trace):
    lay, geo, cam = default_layout, DEFAULT_GEOMETRY, DEFAULT_CAMERA
    c = torch.tensor(geo.brf_free_center(), dtype=torch.float64)
    verts = geo.entrance_vertices(dtype=torch.float64).numpy()
    # whole disk inside the entrance triangle
    assert _inside(c.numpy()[None], verts, margin=geo.brf_free_radius_mm)[0]
    mask = lay.brf_free_mask_sensor(0)
    px_per_mm = cam.focal_length_mm / (cam.pixel_pitch_mm * geo.pupil_z)
    expect = math.pi * (geo.brf_free_radius_mm * px_per_mm) ** 2
    assert abs(int(mask.sum()) - expect) < 0.1 * expect
    tr = default_trace
    traced = (tr.view_index == 0) & geo.brf_free_mask(tr.hit_xy)
    assert int((traced ^ mask).sum()) <= 2
    x0, y0, w, h = lay.reference_bbox
    ys, xs = torch.nonzero(mask, as_tuple=True)
    assert (
        int(xs.min()) >= x0
        and int(xs.max()) < x0 + w
        and int(ys.min()) >= y0
        and int(ys.max()) < y0 + h
    )
    # the same diffuser disk shows up in every view
    for v in range(lay.num_views):
        assert abs(int(lay.brf_free_mask_sensor(v).sum()) - expect) < 0.25 * expect


def test_layout_dict_roundtrip(default_layout):
    lay = default_layout
    for d in (json.loads(json.dumps(lay.to_dict())), lay.to_dict(arrays=True)):
        again = ViewLayout.from_dict(d)
        assert again.reflection_sequences == lay.reflection_sequences
        assert again.sensor_size == lay.sensor_size and again.reference_bbox == lay.reference_bbox
        for name in ViewLayout._TENSORS:
            torch.testing.assert_close(getattr(again, name), getattr(lay, name))
    with pytest.raises(ValueError, match="missing keys"):
        ViewLayout.from_dict({"triangles": []})


def test_layout_opd_matches_brf(default_layout, default_trace):
    brf = BRFConfig()
    tr = default_trace
    for v in (0, 3, 7):
        sel = tr.view_index == v
        opd = brf.opd_nm(
            tr.alpha[sel], tr.sigma[sel], torch.tensor(550.0, dtype=torch.float64)
        ).mean()
        torch.testing.assert_close(default_layout.opd_nm[v], opd)
    # the views see genuinely different OPDs, all with a period >= 30 nm at 430 nm
    opd = default_layout.opd_nm
    assert float(opd.max() - opd.min()) > 1000 and float(opd.abs().max()) < 430**2 / 30


def test_full_preset_reference_triangle_size():
    h = diffuser_to_sensor_homography(DEFAULT_GEOMETRY, FULL_CAMERA, (), dtype=torch.float64)
    tri = apply_homography(h, DEFAULT_GEOMETRY.entrance_vertices(dtype=torch.float64))
    e1, e2 = tri[1] - tri[0], tri[2] - tri[0]
    area = 0.5 * abs(float(e1[0] * e2[1] - e1[1] * e2[0]))
    assert 3.0e5 < area < 3.4e5
    assert float(tri[:, 0].min()) > 0 and float(tri[:, 0].max()) < FULL_CAMERA.width_px


def test_sensing_matrix_much_better_conditioned_than_rgb(default_layout):
    colour = pytest.importorskip("colour")
    wl = DEFAULT_GRID.wavelengths(dtype=torch.float64)
    cs = colour.MSDS_CAMERA_SENSITIVITIES["Nikon 5100 (NPL)"]
    d65 = colour.SDS_ILLUMINANTS["D65"]
    phi = resample_spectra(torch.tensor(np.asarray(cs.values).T), torch.tensor(cs.wavelengths), wl)
    phi = phi * resample_spectra(torch.tensor(d65.values), torch.tensor(d65.wavelengths), wl)
    lay, dl = default_layout, DEFAULT_GRID.band_widths(dtype=torch.float64)
    px = torch.stack(
        [
            apply_homography(lay.diffuser_homographies[v], torch.zeros(1, 2, dtype=torch.float64))[
                0
            ]
            for v in range(lay.num_views)
        ]
    )
    tr = trace_rays(DEFAULT_GEOMETRY, DEFAULT_CAMERA, px)
    b = BRFConfig().transmittance(tr.alpha[:, None], tr.sigma[:, None], wl)
    a = (tr.throughput[:, None, None] * b[:, None, :] * dl * phi).reshape(-1, wl.numel())
    assert a.shape == (30, 25)
    rgb10 = (dl * phi).repeat(10, 1)
    assert float(torch.linalg.cond(a)) < 1e5
    assert float(torch.linalg.cond(rgb10)) > 1e12


def test_input_validation():
    with pytest.raises(ValueError, match=r"\(N, 2\)"):
        trace_rays(DEFAULT_GEOMETRY, DEFAULT_CAMERA, torch.zeros(5, 3))
    with pytest.raises(TypeError):
        trace_rays(DEFAULT_GEOMETRY, DEFAULT_CAMERA, [[0.0, 0.0]])
    with pytest.raises(ValueError, match="a_out_mm"):
        KaleidoscopeGeometry(a_out_mm=-1)
    with pytest.raises(ValueError, match="counter-clockwise"):
        KaleidoscopeGeometry(vertices_in=((0, 0), (0, 1), (1, 0)))
    with pytest.raises(ValueError, match="unknown CameraModel keys"):
        CameraModel.from_dict({"width": 3})
    geo = KaleidoscopeGeometry.from_dict(DEFAULT_GEOMETRY.to_dict())
    assert geo == DEFAULT_GEOMETRY
