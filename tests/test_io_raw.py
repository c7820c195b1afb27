"""Tests of linear RAW loading (rawpy) and the torch Bayer utilities."""

from __future__ import annotations

import os

import numpy as np
import pytest
import torch
from torch.testing import assert_close

from hsi_torch.io import FileFormatError
from hsi_torch.io.raw import (
    bayer_half,
    cfa_masks,
    demosaic,
    demosaic_bilinear,
    demosaic_saturation,
    load_raw,
    mosaic,
    validate_cfa_pattern,
)

PATTERNS = ["RGGB", "BGGR", "GRBG", "GBRG"]
KDC = "raw/RAW_KODAK_DC50.KDC"


def _tol(dtype: torch.dtype) -> dict[str, float]:
    return (
        {"rtol": 1e-5, "atol": 1e-4} if dtype == torch.float32 else {"rtol": 1e-12, "atol": 1e-10}
    )


# --------------------------------------------------------------------------- CFA utilities


def test_validate_cfa_pattern():
    assert validate_cfa_pattern("rggb") == "RGGB"
    for bad in ["RGB", "RRGB", "RGGBX", "CMYG"]:
        with pytest.raises(ValueError, match="cfa_pattern"):
            validate_cfa_pattern(bad)
    with pytest.raises(TypeError):
        validate_cfa_pattern(3)  # type: ignore[arg-type]


@pytest.mark.parametrize("pattern", PATTERNS)
def test_cfa_masks_partition(pattern):
    m = cfa_masks(pattern, 5, 7)
    assert_close(m.sum(0), torch.ones(5, 7))  # every pixel samples exactly one colour
    assert m[1].sum() == pytest.approx(np.ceil(35 / 2), abs=1)  # half the pixels are green
    ch = {"R": 0, "G": 1, "B": 2}
    for i, c in enumerate(pattern):
        assert m[ch[c], i // 2, i % 2] == 1 and m[ch[c], i // 2 + 2, i % 2 + 2] == 1


@pytest.mark.parametrize("pattern", PATTERNS)
def test_bayer_half_matches_numpy(pattern, device, dtype):
    rng = np.random.default_rng(0)
    raw = rng.uniform(0, 1000, size=(9, 12))  # odd height: last row dropped
    x = torch.tensor(raw, dtype=dtype, device=device)[None]
    out = bayer_half(x, pattern)
    assert out.shape == (3, 4, 6)
    cells = {pos: raw[pos // 2 : 8 : 2, pos % 2 :: 2] for pos in range(4)}
    greens = [cells[i] for i, c in enumerate(pattern) if c == "G"]
    expected = np.stack([cells[pattern.index("R")], 0.5 * (greens[0] + greens[1]),
                         cells[pattern.index("B")]])  # fmt: skip
    assert_close(out, torch.tensor(expected, dtype=dtype, device=device), **_tol(dtype))


@pytest.mark.parametrize("pattern", PATTERNS)
def test_bilinear_keeps_samples_and_reproduces_ramps(pattern, device, dtype):
    h, w = 10, 14
    yy, xx = torch.meshgrid(
        torch.arange(h, dtype=dtype, device=device),
        torch.arange(w, dtype=dtype, device=device),
        indexing="ij",
    )
    # three different affine ramps (bilinear interpolation is exact for affine functions)
    rgb = torch.stack([3 * xx + 2 * yy + 5, -xx + 4 * yy + 50, 0.5 * xx - 0.25 * yy + 20])
    raw = mosaic(rgb, pattern)
    out = demosaic_bilinear(raw, pattern)
    assert out.shape == (3, h, w) and out.dtype == dtype and out.device == raw.device
    # measured samples are kept exactly
    assert_close(mosaic(out, pattern), raw, **_tol(dtype))
    # interior reproduces the ramps exactly
    assert_close(out[:, 1:-1, 1:-1], rgb[:, 1:-1, 1:-1], **_tol(dtype))
    # a constant image stays constant everywhere, borders included (normalised convolution)
    const = demosaic_bilinear(torch.full((1, h, w), 7.0, dtype=dtype, device=device), pattern)
    assert_close(const, torch.full((3, h, w), 7.0, dtype=dtype, device=device), **_tol(dtype))


def test_bilinear_matches_scipy_normalised_convolution():
    from scipy.ndimage import convolve

    rng = np.random.default_rng(1)
    raw = rng.uniform(0, 100, size=(8, 11))
    m = cfa_masks("GBRG", 8, 11, dtype=torch.float64).numpy()
    k_rb = np.array([[1, 2, 1], [2, 4, 2], [1, 2, 1]]) / 4
    k_g = np.array([[0, 1, 0], [1, 4, 1], [0, 1, 0]]) / 4
    expected = np.stack([
        convolve(raw * m[c], k, mode="constant") / convolve(m[c], k, mode="constant")
        for c, k in enumerate([k_rb, k_g, k_rb])
    ])  # fmt: skip
    out = demosaic_bilinear(torch.tensor(raw)[None], "GBRG")
    assert_close(out, torch.tensor(expected))


def test_demosaic_batched_and_differentiable():
    x = torch.rand(2, 4, 1, 6, 8, dtype=torch.float64)
    out = demosaic(x, "RGGB", "bilinear")
    assert out.shape == (2, 4, 3, 6, 8)
    assert_close(out[1, 2], demosaic_bilinear(x[1, 2], "RGGB"))
    assert demosaic(x, "RGGB", "half").shape == (2, 4, 3, 3, 4)
    xs = torch.rand(1, 4, 6, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: demosaic_bilinear(t, "BGGR"), (xs,))
    assert torch.autograd.gradcheck(lambda t: bayer_half(t, "BGGR"), (xs,))
    with pytest.raises(ValueError, match="half' or 'bilinear"):
        demosaic(x, "RGGB", "vng")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"\(\.\.\., 1, H, W\)"):
        demosaic_bilinear(torch.rand(3, 4, 4), "RGGB")


def test_demosaic_saturation_propagation():
    sat = torch.zeros(1, 6, 6, dtype=torch.bool)
    sat[0, 2, 2] = True  # with RGGB, (row 2, col 2) is an R sample
    s = demosaic_saturation(sat, "RGGB", "bilinear")
    assert s[1].sum() == 0 and s[2].sum() == 0  # G and B never use an R sample
    assert s[0, 1:4, 1:4].all() and s[0].sum() == 9  # R at the 3x3 neighbourhood
    sat2 = torch.zeros(1, 6, 6, dtype=torch.bool)
    sat2[0, 2, 3] = True  # a G sample: G plane flags the plus-shaped support
    g = demosaic_saturation(sat2, "RGGB", "bilinear")[1]
    assert g.sum() == 5 and g[2, 3] and g[1, 3] and g[3, 3] and g[2, 2] and g[2, 4]
    h = demosaic_saturation(sat2, "RGGB", "half")
    assert h.shape == (3, 3, 3) and h[1, 1, 1] and h.sum() == 1


@pytest.mark.parametrize("pattern", PATTERNS)
def test_demosaic_saturation_matches_conv_reference(pattern):
    import torch.nn.functional as F

    sat = torch.rand(2, 1, 9, 12, generator=torch.Generator().manual_seed(3)) > 0.9
    m = cfa_masks(pattern, 9, 12)
    k_rb = torch.ones(3, 3)
    k_g = torch.tensor([[0.0, 1, 0], [1, 1, 1], [0, 1, 0]])
    support = torch.stack([k_rb, k_g, k_rb])[:, None]
    ref = F.conv2d(sat.float() * m, support, padding=1, groups=3) > 0
    assert torch.equal(demosaic_saturation(sat, pattern, "bilinear"), ref)


# --------------------------------------------------------------------------- rawpy files


def test_load_raw_real_kodak(real_data):
    import rawpy

    path = real_data / KDC
    r = load_raw(path)
    with rawpy.imread(str(path)) as ref:
        visible = ref.raw_image_visible.astype(np.float64)
    assert r.mosaic.shape == (1, 512, 768) and r.mosaic.dtype == torch.float32
    # raw_pattern [[1,0],[2,3]] with colour description RGBG -> G R / B G
    assert r.cfa_pattern == "GRBG"
    assert r.white_level == 16383 and r.black_level == (0.0, 0.0, 0.0, 0.0)
    assert_close(r.mosaic[0].double(), torch.from_numpy(visible))  # black 0: DN unchanged
    assert int(r.saturated.sum()) == int((visible >= 16383).sum())
    assert r.rgb is None

    half = load_raw(path, demosaic="half")
    assert half.rgb.shape == (3, 256, 384)
    assert_close(half.rgb[0].double(), torch.from_numpy(visible[0::2, 1::2]))  # R
    assert_close(half.rgb[2].double(), torch.from_numpy(visible[1::2, 0::2]))  # B
    g = 0.5 * (visible[0::2, 0::2] + visible[1::2, 1::2])
    assert_close(half.rgb[1].double(), torch.from_numpy(g))

    bil = load_raw(path, demosaic="bilinear", normalize=True, dtype=torch.float64)
    assert bil.rgb.shape == (3, 512, 768) and bil.normalized
    assert_close(mosaic(bil.rgb, "GRBG"), torch.from_numpy(visible / 16383.0)[None])
    assert bil.rgb_saturated.shape == (3, 512, 768)
    assert int(bil.rgb_saturated.sum()) >= int(r.saturated.sum())


def test_load_raw_errors(tmp_path, real_data):
    with pytest.raises(FileNotFoundError, match="nope.dng"):
        load_raw(tmp_path / "nope.dng")
    junk = tmp_path / "junk.dng"
    junk.write_bytes(os.urandom(4096))
    with pytest.raises(FileFormatError, match="junk.dng"):
        load_raw(junk)
    data = (real_data / KDC).read_bytes()
    trunc = tmp_path / "truncated.kdc"
    trunc.write_bytes(data[: len(data) // 2])
    with pytest.raises(FileFormatError, match="truncated.kdc.*corrupt, truncated"):
        load_raw(trunc)
    with pytest.raises(FileFormatError, match="directory"):
        load_raw(tmp_path)
    with pytest.raises(ValueError, match="demosaic"):
        load_raw(real_data / KDC, demosaic="ahd")  # type: ignore[arg-type]


def test_load_raw_corrupt_without_real_data(tmp_path):
    bad = tmp_path / "empty.nef"
    bad.write_bytes(b"")
    with pytest.raises(FileFormatError, match="empty.nef"):
        load_raw(bad)


def test_bayer_utilities_are_reexported_by_the_readers():
    """One implementation: ``hsi_torch.io.raw`` and ``hsi_torch.io`` hand out ``hsi_torch.bayer``'s
    functions (the sensor model uses the same module)."""
    import hsi_torch.bayer as bayer
    import hsi_torch.io as io
    import hsi_torch.io.raw as raw

    for name in bayer.__all__:
        assert getattr(raw, name) is getattr(bayer, name), name
        if not name[0].isupper():
            assert getattr(io, name) is getattr(bayer, name), name


@pytest.mark.parametrize("pattern", ["RGGB", "GBRG", "BGGR", "GRBG"])
def test_banded_demosaic_equals_whole_image(pattern, monkeypatch):
    """Large mosaics are demosaiced in bands of rows (bounded temporaries): bit for bit the same
    as one pass, odd heights and band edges included."""
    import hsi_torch.bayer as bayer

    g = torch.Generator().manual_seed(3)
    x = torch.rand(2, 1, 75, 31, generator=g)
    sat = torch.rand(2, 1, 75, 31, generator=g) > 0.97
    whole = bayer.demosaic_bilinear(x, pattern), bayer.demosaic_saturation(sat, pattern)
    monkeypatch.setattr(bayer, "_BAND_ROWS", 8)
    banded = bayer.demosaic_bilinear(x, pattern), bayer.demosaic_saturation(sat, pattern)
    assert torch.equal(whole[0], banded[0]) and torch.equal(whole[1], banded[1])
