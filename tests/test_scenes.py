"""Tests of the diffuser-plane scenes and their rendering."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from hsi_torch import refdata
from hsi_torch.resources import real_data_dir
from hsi_torch.simulate.scenes import (
    CircleGridScene,
    ColorCheckerScene,
    CubeScene,
    FlatScene,
    Scene,
    USAF1951Scene,
    has_abundances,
    load_cave_cube,
    make_scene,
    pixel_centres_mm,
    render_scene_abundances,
    render_scene_image,
    usaf_frequency,
)
from hsi_torch.spectral import DEFAULT_GRID

CAVE = real_data_dir("cave_stuffed_toys") or Path("<real-data>/cave_stuffed_toys")


def test_colorchecker_layout_and_values(device, dtype):
    sc = ColorCheckerScene(width_mm=12.0, center_mm=(1.0, -0.5))
    assert isinstance(sc, Scene)
    assert sc.height_mm == 8.0 and sc.extent == (-5.0, 7.0, -4.5, 3.5)
    wl = torch.tensor(DEFAULT_GRID.wavelengths_nm, device=device, dtype=dtype)
    centres = sc.patch_centres().to(device=device, dtype=dtype)
    got = sc.reflectance(centres, wl)
    expected, names = refdata.colorchecker_reflectances(wl)
    assert got.shape == (24, 25) and got.dtype == dtype and got.device.type == device.type
    torch.testing.assert_close(got, expected)
    # top-left is 'dark skin', bottom-left 'white', x grows to the right, y downwards
    assert names[sc.patch_index(torch.tensor([[-4.0, -3.5]]))[0]] == "dark skin"
    assert names[sc.patch_index(torch.tensor([[-4.0, 2.5]]))[0]].startswith("white")
    assert names[sc.patch_index(torch.tensor([[6.0, -3.5]]))[0]] == "bluish green"
    # gaps (cell boundaries) and outside read the gap reflectance
    gaps = torch.tensor([[-3.0, 0.0], [1.0, -0.5], [0.0, -4.49], [20.0, 0.0]], device=device,
                        dtype=dtype)
    torch.testing.assert_close(sc.reflectance(gaps, wl), torch.full((4, 25), 0.03, device=device,
                                                                     dtype=dtype))


def test_flat_scene():
    xy = torch.rand(5, 2) * 100 - 50
    assert torch.equal(FlatScene().reflectance(xy, DEFAULT_GRID), torch.ones(5, 25))
    sc = FlatScene(spectrum_nm=[400.0, 700.0], spectrum_values=[0.2, 0.8])
    got = sc.reflectance(xy, [400.0, 550.0, 700.0])
    torch.testing.assert_close(got, torch.tensor([0.2, 0.5, 0.8]).expand(5, 3))
    with pytest.raises(ValueError, match="both spectrum_nm and spectrum_values"):
        FlatScene(spectrum_nm=[400.0, 500.0])


def test_usaf_frequencies_and_geometry():
    assert usaf_frequency(0, 1) == 1.0
    assert abs(usaf_frequency(-1, 6) - 0.891) < 1e-3  # the paper's 0.89 lp/mm
    assert abs(usaf_frequency(0, 2) - 1.122) < 1e-3  # the paper's 1.12 lp/mm
    assert abs(usaf_frequency(2, 4) - 2 ** (2 + 3 / 6)) < 1e-12
    mag = 0.5
    sc = USAF1951Scene(groups=(1, 2), magnification=mag)
    els = sc.elements()
    assert len(els) == 2 * 2 * 6
    for el in els:
        r = usaf_frequency(el.group, el.element)
        assert el.lp_per_mm_target == pytest.approx(r)
        assert el.lp_per_mm == pytest.approx(r / mag)
        assert el.bar_width_mm == pytest.approx(1.0 / (2.0 * el.lp_per_mm))
        assert el.bar_length_mm == pytest.approx(5.0 * el.bar_width_mm)
    # sample a line across each triplet: three bars, period 2w, bar fraction 1/2 over 5w
    for el in (els[0], els[1], els[-2], els[-1]):
        x0, x1, y0, y1 = el.bbox_mm
        t = torch.linspace(0, 1, 5001, dtype=torch.float64)[:-1] + 0.5 / 5000
        if el.orientation == "horizontal":
            xy = torch.stack([torch.full_like(t, (x0 + x1) / 2), y0 + t * (y1 - y0)], 1)
        else:
            xy = torch.stack([x0 + t * (x1 - x0), torch.full_like(t, (y0 + y1) / 2)], 1)
        m = sc.bar_mask(xy).to(torch.int8)
        runs = int((m[1:] - m[:-1] == 1).sum()) + int(m[0])
        assert runs == 3
        assert float(m.double().mean()) == pytest.approx(3 / 5, abs=2e-3)
        edges = torch.nonzero(m[1:] != m[:-1]).flatten().double() / 5000 * (5 * el.bar_width_mm)
        np.testing.assert_allclose(np.diff(edges.numpy()), el.bar_width_mm, rtol=0.01)
    r = sc.reflectance(torch.tensor([[100.0, 100.0]]), [500.0, 600.0])
    torch.testing.assert_close(r, torch.full((1, 2), 0.05))


def test_usaf_supersampled_render_area():
    sc = USAF1951Scene(groups=(0,), magnification=1.0)
    ext = sc.extent
    img = render_scene_image(sc, ext, 120, 80, [550.0], supersample=4, dtype=torch.float64)
    bar_area = sum(3 * el.bar_width_mm * el.bar_length_mm for el in sc.elements())
    area = (ext[1] - ext[0]) * (ext[3] - ext[2])
    expected = 0.05 + 0.85 * bar_area / area
    assert float(img.mean()) == pytest.approx(expected, rel=0.01)
    assert 0.05 < float(img.min()) or float(img.min()) == pytest.approx(0.05)
    assert ((img > 0.06) & (img < 0.89)).any()  # anti-aliased edge pixels exist


def _render_u8(sc: CircleGridScene, ext, n=256):
    img = render_scene_image(sc, ext, n, n, [550.0], supersample=2, dtype=torch.float64)[0]
    return (img.clamp(0, 1) * 255).round().to(torch.uint8).numpy()


@pytest.mark.parametrize("pose", [
    dict(),
    dict(rotation_rad=0.4, tilt_x_rad=0.35, translation_mm=(0.6, -0.4)),
    dict(rotation_rad=math.pi / 2 + 0.2, tilt_y_rad=-0.4),
    dict(rotation_rad=-2.5),
    dict(pattern_size=(3, 7), spacing_mm=1.1, radius_mm=0.4, rotation_rad=0.1),
    dict(pattern_size=(3, 6), spacing_mm=1.1, radius_mm=0.4, rotation_rad=0.1),
])
def test_circle_grid_found_by_opencv_in_order(pose):
    cv2 = pytest.importorskip("cv2")
    sc = CircleGridScene(**pose)
    ext, n = (-7.0, 7.0, -7.0, 7.0), 256
    u8 = _render_u8(sc, ext, n)
    ok, found = cv2.findCirclesGrid(u8, sc.pattern_size, flags=cv2.CALIB_CB_ASYMMETRIC_GRID)
    assert ok
    found = found.reshape(-1, 2).astype(np.float64)
    c = sc.true_centres().numpy()
    px = (c - np.array([ext[0], ext[2]])) / (14.0 / n) - 0.5  # mm → pixel (centres at integers)
    if sc.pattern_size[1] % 2 == 0:
        # an even number of rows makes the grid symmetric under a 180° turn, so OpenCV's order is
        # ambiguous (it returns a permutation): compare as point sets only
        err = np.hypot(*(found[:, None, :] - px[None, :, :]).transpose(2, 0, 1)).min(axis=1)
    else:
        err = np.hypot(*(found - px).T)  # same order as OpenCV's
    assert err.max() < 0.15  # pixels
    # the homography maps object points onto the true centres
    obj = sc.object_points()
    cols, _ = sc.pattern_size
    k = cols + 1  # row 1, column 1
    assert obj[k, 0] == pytest.approx(3 * sc.spacing_mm) and obj[k, 1] == pytest.approx(
        sc.spacing_mm)


def test_circle_grid_reflectance_and_validation():
    sc = CircleGridScene(translation_mm=(2.0, 1.0))
    c = sc.true_centres()
    r = sc.reflectance(c, [500.0])
    assert torch.all(r == 0.05)
    between = (c[0] + c[1]) / 2  # two circles in a row are 2s apart
    assert float(sc.reflectance(between[None], [500.0])) == pytest.approx(0.9)
    # centroid is placed at the translation
    torch.testing.assert_close(c.mean(0), torch.tensor([2.0, 1.0], dtype=torch.float64))
    with pytest.raises(ValueError, match="radius_mm"):
        CircleGridScene(radius_mm=0.8)


def test_cube_scene_sampling(device, dtype):
    torch.manual_seed(0)
    cube = torch.rand(4, 6, 8, dtype=torch.float64)
    wl = [450.0, 500.0, 550.0, 600.0]
    sc = CubeScene(cube, wl, extent_mm=(-4.0, 4.0, -3.0, 3.0))  # 1 mm pixels
    # rendering at native resolution reproduces the cube exactly (pixel centres coincide)
    img = render_scene_image(sc, sc.extent, 6, 8, torch.tensor(wl, device=device, dtype=dtype))
    assert img.device.type == device.type and img.dtype == dtype
    torch.testing.assert_close(img.cpu(), cube.to(dtype))
    # bilinear half-way between 4 pixel centres, spectral interpolation to 525 nm
    xy = torch.tensor([[-3.0, -2.0]], device=device, dtype=dtype)  # between px (0..1, 0..1)
    got = sc.reflectance(xy, torch.tensor([525.0], device=device, dtype=dtype))
    exp = 0.25 * cube[1:3, 0:2, 0:2].sum(dim=(1, 2)).mean()
    assert float(got) == pytest.approx(float(exp), rel=1e-5)
    out = sc.reflectance(torch.tensor([[10.0, 0.0]], device=device, dtype=dtype), wl)
    assert torch.all(out == 0)
    with pytest.raises(ValueError, match="cube covers"):
        sc.reflectance(xy, [700.0])
    with pytest.raises(ValueError, match="bands but wavelengths_nm"):
        CubeScene(cube, [1.0, 2.0])


def _mixture_scenes() -> dict[str, Scene]:
    g = torch.Generator().manual_seed(2)
    cube = torch.rand(5, 7, 9, generator=g, dtype=torch.float64)
    wl5 = [420.0, 480.0, 540.0, 600.0, 680.0]
    return {
        "colorchecker": ColorCheckerScene(width_mm=6.0, center_mm=(0.5, -0.5)),
        "flat": FlatScene(value=0.7),
        "flat_spectrum": FlatScene(spectrum_nm=[400, 550, 700], spectrum_values=[0.2, 0.8, 0.4]),
        "usaf": USAF1951Scene(groups=(0, 1), center_mm=(0.2, 0.1)),
        "circle_grid": CircleGridScene(radius_mm=0.3, rotation_rad=0.2, tilt_x_rad=0.1),
        "cube": CubeScene(cube, wl5, width_mm=4.0, extrapolate="edge"),
        "cube_outside": CubeScene(cube, wl5, width_mm=4.0, outside_value=0.3,
                                  extrapolate="zero"),
        "cube_one_band": CubeScene(cube[:1], [550.0], width_mm=4.0, extrapolate="edge"),
        "cube_endmembers": CubeScene(cube[:2], wl5, width_mm=4.0, extrapolate="edge",
                                     endmembers=torch.rand(2, 5, generator=g,
                                                           dtype=torch.float64)),
    }


def test_abundances_times_endmembers_is_the_reflectance(device, dtype):
    """Every scene's linear-mixture form reproduces its reflectance (the renderer uses it)."""
    g = torch.Generator().manual_seed(0)
    xy = ((torch.rand(4000, 2, generator=g, dtype=torch.float64) - 0.5) * 8).to(device, dtype)
    wl = torch.linspace(410.0, 690.0, 57, device=device, dtype=dtype)
    tol = 1e-12 if dtype == torch.float64 else 1e-6
    for name, sc in _mixture_scenes().items():
        assert has_abundances(sc), name
        ab, em = sc.abundances(xy), sc.endmember_spectra(wl)
        assert ab.dtype == em.dtype == dtype and ab.device.type == device.type, name
        assert ab.shape[0] == 4000 and em.shape == (ab.shape[1], 57), name
        ref = sc.reflectance(xy, wl)
        if name != "flat":
            assert float(ref.max() - ref.min()) > 0.05, name  # the points see structure
        torch.testing.assert_close(ab @ em, ref, rtol=0, atol=tol, msg=name)
    assert not has_abundances(object())
    with pytest.raises(ValueError, match="endmembers must have shape"):
        CubeScene(torch.zeros(2, 3, 3), [500.0, 600.0], endmembers=torch.zeros(3, 2))


def test_abundance_raster_matches_reflectance_raster():
    sc = _mixture_scenes()["colorchecker"]
    wl = torch.tensor([450.0, 550.0, 650.0], dtype=torch.float64)
    img = render_scene_image(sc, sc.extent, 40, 60, wl, supersample=3, chunk_points=1000)
    ab = render_scene_abundances(sc, sc.extent, 40, 60, supersample=3, chunk_points=1000)
    assert ab.shape == (25, 40, 60)
    torch.testing.assert_close(torch.einsum("khw,kl->lhw", ab, sc.endmember_spectra(wl)), img)
    with pytest.raises(TypeError, match="abundances"):
        render_scene_abundances(object(), (0.0, 1.0, 0.0, 1.0), 4, 4)


def test_pixel_centres_and_make_scene():
    p = pixel_centres_mm((0.0, 4.0, 0.0, 2.0), 2, 4)
    assert p.shape == (2, 4, 2)
    torch.testing.assert_close(p[0, 0], torch.tensor([0.5, 0.5]))
    torch.testing.assert_close(p[1, 3], torch.tensor([3.5, 1.5]))
    sc = make_scene("circle_grid", rotation_deg=30.0, pattern_size=[4, 5])
    assert isinstance(sc, CircleGridScene) and sc.rotation_rad == pytest.approx(math.pi / 6)
    assert isinstance(make_scene("white"), FlatScene)
    with pytest.raises(ValueError, match="unknown scene kind"):
        make_scene("mandelbrot")
    with pytest.raises(TypeError, match="colorchecker"):
        make_scene("colorchecker", colour="red")


@pytest.mark.real_data
@pytest.mark.skipif(not CAVE.is_dir(), reason=f"real data folder {CAVE} is absent")
def test_cave_loader():
    cube, wl, info = load_cave_cube(CAVE)
    assert cube.shape == (31, 512, 512) and cube.dtype == torch.float32
    torch.testing.assert_close(wl, torch.arange(400.0, 701.0, 10.0, dtype=torch.float64))
    assert float(cube.min()) >= 0.0 and 1.0 < float(cube.max()) < 2.0  # highlights exceed 1
    r0, c0 = info["white_centre_rc"]
    assert 256 <= r0 < 512 and 100 <= c0 < 356
    ref, names = refdata.colorchecker_reflectances(wl, dtype=torch.float32)
    white = cube[:, r0 - 5:r0 + 6, c0 - 5:c0 + 6].reshape(31, -1).median(1).values
    torch.testing.assert_close(white, ref[18], atol=0.02, rtol=0)
    # an independent patch: 'neutral 8' is one patch pitch (~48 px) right of the white one
    n8 = cube[:, r0 - 7:r0 + 8, c0 + 48 - 7:c0 + 48 + 8].reshape(31, -1).median(1).values
    # measured: |Δ| ≤ 0.03 over 430–670 nm; the end bands are worse (−0.09 at 400, +0.06 at 700)
    assert float((n8 - ref[19])[3:28].abs().max()) < 0.04
    raw, _, _ = load_cave_cube(CAVE, normalise=None)
    assert float(raw.max()) <= 1.0
