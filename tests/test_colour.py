"""Tests of colour rendering against colour-science."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from hsi_torch import refdata
from hsi_torch.colour import (
    cube_to_srgb,
    cube_to_xyz,
    illuminant_white_xyz,
    plot_spectra,
    save_preview_png,
    spectra_to_srgb,
    spectra_to_xyz,
    srgb_encode,
)
from hsi_torch.spectral import DEFAULT_GRID

colour = pytest.importorskip("colour")
WL_FULL = np.arange(380.0, 781.0, 5.0)


def _colour_science_srgb(illuminant: str = "D65") -> tuple[np.ndarray, np.ndarray]:
    """XYZ (Y=1 for white) and encoded, clipped sRGB of the Ohta patches by colour-science."""
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    ill = colour.SDS_ILLUMINANTS[illuminant]
    with colour.utilities.suppress_warnings(colour_runtime_warnings=True):
        xyz = np.array([colour.sd_to_XYZ(sd, cmfs, ill, method="Integration") / 100.0
                        for sd in colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"].values()])
    rgb = colour.XYZ_to_sRGB(xyz, apply_cctf_encoding=False)
    return xyz, np.asarray(colour.cctf_encoding(np.clip(rgb, 0, 1)))


def test_patch_xyz_and_srgb_match_colour_science(device, dtype):
    refl, _ = refdata.colorchecker_reflectances(WL_FULL, device=device, dtype=dtype)
    xyz_ref, srgb_ref = _colour_science_srgb()
    xyz = spectra_to_xyz(refl, torch.tensor(WL_FULL, device=device, dtype=dtype))
    assert xyz.dtype == dtype and xyz.device.type == device.type
    # same grid, same integration rule: agreement to 1e-4 (measured 8e-5)
    np.testing.assert_allclose(xyz.cpu().double().numpy(), xyz_ref, atol=2e-4)
    srgb = spectra_to_srgb(refl, WL_FULL, adapt=False)
    np.testing.assert_allclose(srgb.cpu().double().numpy(), srgb_ref, atol=5e-4)


def test_default_grid_patches_white_and_red():
    refl, names = refdata.colorchecker_reflectances(DEFAULT_GRID, dtype=torch.float64)
    srgb = spectra_to_srgb(refl, DEFAULT_GRID)
    white, red = srgb[names.index("white 9.5 (.05 D)")], srgb[names.index("red")]
    assert float(white.min()) > 0.93 and float(white.max() - white.min()) < 0.01
    assert float(red[0]) > 0.6 and float(red[0]) > 2.5 * float(red[1:].max())
    # the 430–670 nm grid vs colour-science on the full 380–780 nm table: measured max 0.013
    _, srgb_ref = _colour_science_srgb()
    assert float(np.abs(srgb.numpy() - srgb_ref).max()) < 0.02


def test_white_reflector_is_white_under_any_illuminant():
    wl = DEFAULT_GRID
    for ill in ("D65", "A"):
        w = illuminant_white_xyz(wl, ill, dtype=torch.float64)
        assert float(w[1]) == pytest.approx(1.0)
        rgb = spectra_to_srgb(torch.ones(1, 25, dtype=torch.float64), wl, ill)
        # the 4-decimal IEC matrix maps the D65 white to (0.99993, 1, 1)
        torch.testing.assert_close(rgb, torch.ones(1, 3, dtype=torch.float64), atol=2e-4, rtol=0)
    # without adaptation, illuminant A renders white as orange
    rgb = spectra_to_srgb(torch.ones(25, dtype=torch.float64), wl, "A", adapt=False)
    assert float(rgb[0]) > float(rgb[1]) > float(rgb[2])


def test_srgb_transfer_curve():
    x = torch.tensor([0.0, 0.0031308, 0.18, 0.5, 1.0], dtype=torch.float64)
    got = srgb_encode(x)
    ref = colour.cctf_encoding(x.numpy())
    np.testing.assert_allclose(got.numpy(), ref, atol=1e-6)
    assert float(got[1]) == pytest.approx(0.04045, abs=1e-5)


def test_cube_functions_are_batched(device):
    refl, _ = refdata.colorchecker_reflectances(DEFAULT_GRID, device=device)
    cube = refl.T.reshape(25, 4, 6)  # patch k at row k // 6, column k % 6
    batch = torch.stack([cube, 0.5 * cube])  # (2, M, H, W)
    xyz = cube_to_xyz(batch, DEFAULT_GRID)
    assert xyz.shape == (2, 3, 4, 6)
    torch.testing.assert_close(xyz[0].permute(1, 2, 0).reshape(24, 3),
                               spectra_to_xyz(refl, DEFAULT_GRID))
    torch.testing.assert_close(xyz[1], 0.5 * xyz[0])
    srgb = cube_to_srgb(batch, DEFAULT_GRID)
    torch.testing.assert_close(srgb[0].permute(1, 2, 0).reshape(24, 3),
                               spectra_to_srgb(refl, DEFAULT_GRID))
    # 'max' normalisation makes both images identical (each scaled to its brightest Y)
    norm = cube_to_srgb(batch, DEFAULT_GRID, normalise="max")
    torch.testing.assert_close(norm[0], norm[1])
    assert float(norm[0].max()) == pytest.approx(1.0, abs=1e-5)
    with pytest.raises(ValueError, match="normalise"):
        cube_to_srgb(cube, DEFAULT_GRID, normalise="auto")


def test_save_preview_png_is_atomic_and_correct(tmp_path):
    cv2 = pytest.importorskip("cv2")
    refl, names = refdata.colorchecker_reflectances(DEFAULT_GRID)
    cube = refl.T.reshape(25, 4, 6).repeat_interleave(8, 1).repeat_interleave(8, 2)
    path = save_preview_png(cube, DEFAULT_GRID, tmp_path / "sub" / "chart.png", normalise=None)
    assert sorted(p.name for p in path.parent.iterdir()) == ["chart.png"]  # no temp left
    img = cv2.imread(str(path))[..., ::-1]  # RGB
    assert img.shape == (32, 48, 3)
    expected = (spectra_to_srgb(refl, DEFAULT_GRID) * 255).round().numpy()
    got = img[4::8, 4::8].reshape(24, 3).astype(float)
    assert np.abs(got - expected).max() <= 1.0
    with pytest.raises(ValueError, match=r"\(M, H, W\)"):
        save_preview_png(cube[None], DEFAULT_GRID, tmp_path / "x.png")


def test_plot_spectra(tmp_path):
    refl, names = refdata.colorchecker_reflectances(DEFAULT_GRID)
    fig = plot_spectra(DEFAULT_GRID, refl * 0.98, refl, labels=names, title="patches",
                       path=tmp_path / "spectra.png")
    assert len([a for a in fig.axes if a.get_visible()]) == 24
    data = Path(tmp_path / "spectra.png").read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000
    fig = plot_spectra(DEFAULT_GRID, refl[:3], labels=names[:3])
    assert len(fig.axes[0].lines) == 3
    with pytest.raises(ValueError, match="labels"):
        plot_spectra(DEFAULT_GRID, refl[:3], labels=names[:2])
