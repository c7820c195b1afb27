"""Tests of the sensor model: noise statistics, saturation, CFA mosaic/demosaic/binning, PSF."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from hsi_torch.optics.sensor import (
    CFA_PATTERNS,
    DiffuserModel,
    SensorModel,
    bin_bayer,
    cfa_index,
    cfa_masks,
    cfa_pattern_from_rawpy,
    demosaic_bilinear,
    diffuser_falloff,
    gaussian_blur,
    mosaic,
)
from hsi_torch.resources import real_data_dir

REAL = real_data_dir() or Path("<real-data>")


@pytest.mark.parametrize("shot", [True, False])
def test_noise_statistics_match_theory(device, dtype, shot):
    gain, read, mu, black = 2.0, 5.0, 1000.0, 100.0
    s = SensorModel(output="rgb", input_units="electrons", electrons_per_dn=gain,
                    full_well_e=None, read_noise_e=read, black_level=black, shot_noise=shot,
                    bit_depth=16, seed=1)
    x = torch.full((1, 3, 256, 256), mu, device=device, dtype=dtype)
    dn, sat = s.expose(x)
    assert dn.shape == x.shape and dn.dtype == dtype and dn.device.type == device.type
    assert not bool(sat.any())
    assert torch.equal(dn, dn.round())
    n = dn.numel()
    var_theory = ((mu if shot else 0.0) + read**2) / gain**2 + 1.0 / 12.0  # + quantisation
    mean_theory = mu / gain + black
    d = dn.double()
    # 5-sigma bounds on the sample mean and the sample variance
    assert abs(float(d.mean()) - mean_theory) < 5 * math.sqrt(var_theory / n)
    assert abs(float(d.var()) / var_theory - 1) < 5 * math.sqrt(2.0 / n)


def test_pure_shot_noise_is_poisson():
    s = SensorModel(output="rgb", input_units="electrons", electrons_per_dn=1.0, full_well_e=None,
                    read_noise_e=0.0, black_level=0.0, quantize=False, bit_depth=16, seed=3)
    mu = torch.tensor([0.5, 4.0, 50.0], dtype=torch.float64).view(1, 3, 1, 1)
    dn, _ = s.expose(mu.expand(1, 3, 200, 200).contiguous())
    d = dn.reshape(3, -1)
    assert torch.equal(d, d.round())  # Poisson counts are integers
    torch.testing.assert_close(d.mean(1), mu.flatten(), rtol=0.03, atol=0.01)
    torch.testing.assert_close(d.var(1), mu.flatten(), rtol=0.05, atol=0.01)


def test_saturation_at_white_level(device):
    s = SensorModel(seed=0)  # relative units: 1.0 = full well = white level
    assert s.white == 2**14 - 1
    assert abs(s.gain_e_per_dn - 30000 / (16383 - 512)) < 1e-12
    x = torch.tensor([0.2, 0.999, 1.2, 5.0], device=device).view(1, 1, 1, 4).expand(1, 3, 4, 4)
    dn, sat = s.expose(x.contiguous())
    assert dn.shape == (1, 1, 4, 4)
    assert torch.all(dn[..., 2:] == s.white) and torch.all(sat[..., 2:])
    assert not bool(sat[..., 0].any()) and torch.all(dn[..., 0] < s.white)
    # exposure scales the signal: halving it brings 1.2 below saturation
    s2 = SensorModel(seed=0, exposure=0.5, shot_noise=False, read_noise_e=0.0)
    dn2, sat2 = s2.expose(x.contiguous())
    assert not bool(sat2[..., 2].any())
    expected = round(0.6 * 30000 / s2.gain_e_per_dn + 512)
    assert torch.all(dn2[..., 2] == expected)


def test_reproducible_seed_and_errors():
    x = torch.full((3, 16, 16), 0.3)
    a = SensorModel(seed=7).expose(x).dn
    m = SensorModel(seed=7)
    b1, b2 = m.expose(x).dn, m.expose(x).dn
    assert torch.equal(a, b1) and not torch.equal(b1, b2)  # advances between calls
    m.reseed()
    assert torch.equal(m.expose(x).dn, a)
    clone = SensorModel(**SensorModel(seed=7, output="rgb", black_level=64.0).to_dict())
    assert clone.to_dict() == SensorModel(seed=7, output="rgb", black_level=64.0).to_dict()
    g = torch.Generator().manual_seed(7)
    assert torch.equal(SensorModel(seed=99).expose(x, generator=g).dn, a)
    with pytest.raises(ValueError, match="output"):
        SensorModel(output="ycbcr")
    with pytest.raises(ValueError, match="cfa pattern"):
        SensorModel(cfa_pattern="RGBW")
    with pytest.raises(ValueError, match="black_level"):
        SensorModel(bit_depth=8, black_level=300)
    with pytest.raises(ValueError, match="3 input channels"):
        SensorModel(output="rgb").expose(torch.ones(1, 4, 4))


@pytest.mark.parametrize("pattern", CFA_PATTERNS)
def test_mosaic_pattern_layout(pattern):
    rgb = torch.tensor([10.0, 20.0, 30.0]).view(3, 1, 1).expand(3, 4, 6)
    raw = mosaic(rgb, pattern)
    assert raw.shape == (1, 4, 6)
    names = {10.0: "R", 20.0: "G", 30.0: "B"}
    tile = "".join(names[float(raw[0, r, c])] for r in range(2) for c in range(2))
    assert tile == pattern
    assert torch.equal(raw[0, :2, :2], raw[0, 2:, 4:])  # periodic
    m = cfa_masks(pattern, 4, 6)
    assert torch.equal(m.sum(0), torch.ones(4, 6)) and float(m[1].sum()) == 12


@pytest.mark.parametrize("pattern", ["RGGB", "GBRG"])
def test_mosaic_demosaic_round_trip(device, dtype, pattern):
    h, w = 48, 64
    yy, xx = torch.meshgrid(torch.arange(h, device=device, dtype=dtype),
                            torch.arange(w, device=device, dtype=dtype), indexing="ij")
    # exact for linear ramps in the interior
    ramp = torch.stack([0.1 + 0.01 * xx + 0.02 * yy, 0.5 - 0.003 * xx, 0.2 + 0.004 * yy])
    rec = demosaic_bilinear(mosaic(ramp, pattern), pattern)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    assert float((rec - ramp)[:, 1:-1, 1:-1].abs().max()) < tol
    # known samples are kept exactly everywhere
    m = cfa_masks(pattern, h, w, device=device, dtype=dtype)
    torch.testing.assert_close(rec * m, ramp * m)
    # smooth image, batched: small error, also at the borders
    smooth = torch.stack([torch.sin(xx / 9.0) * torch.cos(yy / 7.0), torch.cos(xx / 11.0),
                          torch.sin((xx + yy) / 13.0)]) * 0.4 + 0.5
    batch = torch.stack([smooth, 1 - smooth])  # (2, 3, H, W)
    rec = demosaic_bilinear(mosaic(batch, pattern), pattern)
    assert rec.shape == batch.shape
    assert float((rec - batch)[..., 1:-1, 1:-1].abs().max()) < 0.01
    # borders are one-sided (≤ 1 px extrapolation): bounded by the gradient (≤ 0.044/px here)
    assert float((rec - batch).abs().max()) < 0.08


def test_bin_bayer_against_manual():
    torch.manual_seed(0)
    raw = torch.rand(2, 1, 6, 9, dtype=torch.float64)
    out = bin_bayer(raw, "GRBG")  # row0: G R, row1: B G
    assert out.shape == (2, 3, 3, 4)
    r = raw[:, 0, :6, :8]
    torch.testing.assert_close(out[:, 0], r[:, 0::2, 1::2])
    torch.testing.assert_close(out[:, 1], 0.5 * (r[:, 0::2, 0::2] + r[:, 1::2, 1::2]))
    torch.testing.assert_close(out[:, 2], r[:, 1::2, 0::2])
    assert cfa_index("GRBG") == [[1, 0], [2, 1]]


def test_cfa_from_rawpy_and_real_raw():
    assert cfa_pattern_from_rawpy([[1, 0], [2, 3]], b"RGBG") == "GRBG"
    assert cfa_pattern_from_rawpy(np.array([[0, 1], [3, 2]]), "RGBG") == "RGGB"
    path = REAL / "raw" / "RAW_KODAK_DC50.KDC"
    if not path.is_file():
        pytest.skip(f"real data {path} is absent")
    rawpy = pytest.importorskip("rawpy")
    with rawpy.imread(str(path)) as r:
        pattern = cfa_pattern_from_rawpy(r.raw_pattern, r.color_desc)
        img = r.raw_image_visible.astype(np.float64)
    assert pattern == "GRBG"
    raw = torch.from_numpy(img)[None]
    half = bin_bayer(raw, pattern)
    assert half.shape == (3, 256, 384)
    assert abs(float(half[0].mean()) - img[0::2, 1::2].mean()) < 1e-9


def test_gaussian_blur_matches_scipy(device):
    from scipy.ndimage import gaussian_filter

    torch.manual_seed(0)
    img = torch.rand(2, 3, 40, 50, dtype=torch.float64, device=device)
    sigma = 1.5
    got = gaussian_blur(img, sigma).cpu().numpy()
    ref = gaussian_filter(img.cpu().numpy(), sigma=(0, 0, sigma, sigma), truncate=3.0,
                          mode="mirror")
    k = 5  # interior, away from border-mode differences
    np.testing.assert_allclose(got[..., k:-k, k:-k], ref[..., k:-k, k:-k], atol=2e-3)
    assert torch.equal(gaussian_blur(img, 0.0), img)
    s = SensorModel(output="rgb", psf_sigma_px=2.0, shot_noise=False, read_noise_e=0.0,
                    quantize=False)
    edge = torch.zeros(3, 20, 20, dtype=torch.float64)
    edge[:, :, 10:] = 0.5
    dn = s.expose(edge).dn
    assert 512 < float(dn[0, 10, 9]) < float(dn[0, 10, 10]) < float(dn[0, 10, 19])


def test_diffuser_falloff():
    a = torch.tensor([0.0, 0.3, 1.0, 2.0])
    torch.testing.assert_close(diffuser_falloff(a, 3.0),
                               torch.cos(a).clamp_min(0) ** 3)
    assert torch.equal(diffuser_falloff(a[:3], 0.0), torch.ones(3))
    d = DiffuserModel(falloff_k=4.0, blur_sigma_mm=0.1)
    assert abs(float(d.falloff(torch.tensor(math.radians(60)))) - 0.5**4) < 1e-7
    img = torch.zeros(1, 21, 21)
    img[0, 10, 10] = 1.0
    out = d.blur(img, pixel_size_mm=0.05)  # sigma = 2 px
    yy, xx = torch.meshgrid(torch.arange(21.0), torch.arange(21.0), indexing="ij")
    var_x = float((out[0] * (xx - 10) ** 2).sum() / out.sum())
    assert abs(var_x - 4.0) < 0.1
    with pytest.raises(ValueError, match="falloff_k"):
        DiffuserModel(falloff_k=-1)
