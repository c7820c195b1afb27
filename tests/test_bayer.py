"""The row-wise bilinear demosaic and saturation propagation of ``hsi_torch.bayer`` against the
masked-plane evaluation they replaced (kept verbatim in ``scripts/bench_demosaic.py``): the same
values (``torch.equal``) on odd and even sizes, every CFA pattern, batch dimensions and mosaics
taller than a band; non-finite mosaics and autograd take the reference itself."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import bench_demosaic as ref  # noqa: E402

from hsi_torch import bayer  # noqa: E402

PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")
SIZES = ((2, 2), (2, 3), (3, 2), (3, 5), (4, 4), (5, 7), (8, 9), (11, 6), (13, 13))


def _bits(t: torch.Tensor) -> torch.Tensor:
    """The tensor's bit patterns (integers of the same width)."""
    return t.view({2: torch.int16, 4: torch.int32, 8: torch.int64}[t.element_size()])


@pytest.mark.parametrize("pattern", PATTERNS)
@pytest.mark.parametrize("band", [4, 256])
def test_bilinear_equals_masked_plane_reference(pattern, band, device, dtype, monkeypatch):
    """Bit for bit on mosaics without zeros (random signs: cancellations happen), every odd and
    even size from 2 x 2, a batch of (2, 3) mosaics; band 4 puts most rows near a band edge."""
    monkeypatch.setattr(bayer, "_BAND_ROWS", band)
    g = torch.Generator().manual_seed(7)
    for h, w in (*SIZES, (17, 10), (18, 5)):
        x = (torch.randn(2, 3, 1, h, w, generator=g) * 100).to(device=device, dtype=dtype)
        out = bayer.demosaic_bilinear(x, pattern)
        expected = ref.reference_bilinear(x, pattern, band=band)
        assert out.shape == (2, 3, 3, h, w) and out.dtype == dtype and out.device == x.device
        assert torch.equal(_bits(out), _bits(expected)), (h, w)


@pytest.mark.parametrize("low", [torch.float16, torch.bfloat16])
def test_bilinear_equals_reference_in_half_precision(low, monkeypatch):
    """Every addition and product is rounded to the mosaic's dtype in the same order, so half
    precision (where a reordered or fused sum would show) agrees too."""
    monkeypatch.setattr(bayer, "_BAND_ROWS", 4)
    g = torch.Generator().manual_seed(8)
    for pattern in PATTERNS:
        x = (torch.rand(3, 1, 15, 9, generator=g) * 1000).to(low)
        assert torch.equal(bayer.demosaic_bilinear(x, pattern), ref.reference_bilinear(x, pattern))


def test_bilinear_equal_values_with_zeros_and_edge_values():
    """Zeros, negative zeros, tiny (subnormal) and huge values: equal values (a zero's sign may
    differ: the reference adds ``+0`` to samples, which turns ``-0`` into ``+0``)."""
    g = torch.Generator().manual_seed(9)
    vals = torch.tensor([0.0, -0.0, 1e-45, -1e-45, 1e-38, 3e38, -3e38, 1.0, -2.5])
    for pattern in PATTERNS:
        x = vals[torch.randint(0, len(vals), (2, 1, 12, 11), generator=g)]
        out = bayer.demosaic_bilinear(x, pattern)
        expected = ref.reference_bilinear(x, pattern)
        torch.testing.assert_close(out, expected, rtol=0, atol=0, equal_nan=True)


def test_bilinear_non_finite_mosaic_spreads_like_the_reference():
    """A NaN or inf sample takes the masked-plane evaluation: NaN·0 spreads it into the other
    colours of its neighbourhood, as before."""
    x = torch.rand(1, 1, 9, 10, dtype=torch.float64)
    x[0, 0, 4, 4] = float("nan")  # an R sample of RGGB
    x[0, 0, 1, 7] = float("inf")  # a G sample
    out = bayer.demosaic_bilinear(x, "RGGB")
    torch.testing.assert_close(out, ref.reference_bilinear(x, "RGGB"), rtol=0, atol=0,
                               equal_nan=True)  # fmt: skip
    assert out[0, 1, 4, 4].isnan() and out[0, 2, 3, 3].isnan()  # G and B beside the R NaN


def test_bilinear_requires_grad_and_empty_batch():
    x = torch.rand(2, 1, 7, 8, dtype=torch.float64)
    xg = x.clone().requires_grad_()
    out = bayer.demosaic_bilinear(xg, "GBRG")
    assert torch.equal(out.detach(), bayer.demosaic_bilinear(x, "GBRG"))
    (grad,) = torch.autograd.grad(out.sum(), xg)
    xr = x.clone().requires_grad_()
    (grad_ref,) = torch.autograd.grad(ref.reference_bilinear(xr, "GBRG").sum(), xr)
    assert torch.equal(grad, grad_ref)
    empty = bayer.demosaic_bilinear(torch.zeros(0, 4, 1, 5, 6), "RGGB")
    assert empty.shape == (0, 4, 3, 5, 6)


@pytest.mark.parametrize("pattern", PATTERNS)
@pytest.mark.parametrize("band", [4, 256])
def test_saturation_equals_masked_plane_reference(pattern, band, device, monkeypatch):
    monkeypatch.setattr(bayer, "_BAND_ROWS", band)
    g = torch.Generator().manual_seed(10)
    for h, w in (*SIZES, (17, 10)):
        for frac in (0.0, 0.05, 0.5):
            sat = (torch.rand(2, 2, 1, h, w, generator=g) < frac).to(device)
            out = bayer.demosaic_saturation(sat, pattern)
            assert out.shape == (2, 2, 3, h, w) and out.dtype == torch.bool
            assert torch.equal(out, ref.reference_saturation(sat, pattern, band=band)), (h, w)


def test_saturation_bad_pattern_refused_even_without_flags():
    with pytest.raises(ValueError, match="cfa_pattern"):
        bayer.demosaic_saturation(torch.zeros(1, 4, 4, dtype=torch.bool), "RGGR")
    assert bayer.demosaic_saturation(torch.zeros(0, 1, 4, 4, dtype=torch.bool), "RGGB").shape == (
        0, 3, 4, 4)  # fmt: skip


def test_non_contiguous_inputs():
    """Transposed and strided views are read as they are (the band copy takes any strides)."""
    g = torch.Generator().manual_seed(11)
    x = torch.rand(2, 1, 40, 31, generator=g).transpose(-1, -2)
    assert torch.equal(bayer.demosaic_bilinear(x, "GRBG"), ref.reference_bilinear(x, "GRBG"))
    x = torch.rand(3, 1, 40, 62, generator=g)[..., ::2]
    assert torch.equal(bayer.demosaic_bilinear(x, "BGGR"), ref.reference_bilinear(x, "BGGR"))
    sat = (torch.rand(2, 1, 40, 31, generator=g) > 0.9).transpose(-1, -2)
    expected = ref.reference_saturation(sat, "GRBG")
    assert torch.equal(bayer.demosaic_saturation(sat, "GRBG"), expected)
