import numpy as np
import pytest
import torch
from torch.testing import assert_close

from hsi_torch.spectral import (
    DEFAULT_GRID,
    SpectralGrid,
    band_widths,
    difference_matrix,
    resample_spectra,
)


def test_default_grid():
    wl = DEFAULT_GRID.wavelengths(dtype=torch.float64)
    assert DEFAULT_GRID.num_bands == 25
    assert float(wl[0]) == 430.0 and float(wl[-1]) == 670.0
    assert_close(
        DEFAULT_GRID.band_widths(dtype=torch.float64), torch.full((25,), 10.0, dtype=torch.float64)
    )
    assert_close(DEFAULT_GRID.wavenumbers(dtype=torch.float64), 1.0 / wl)


def test_band_widths_nonuniform():
    bw = band_widths(torch.tensor([400.0, 410.0, 430.0, 460.0], dtype=torch.float64))
    assert_close(bw, torch.tensor([10.0, 15.0, 25.0, 30.0], dtype=torch.float64))
    # trapezoid-like weights integrate a constant over the span plus half end cells
    assert float(bw.sum()) == pytest.approx(60.0 + 10.0 / 2 + 30.0 / 2)


@pytest.mark.parametrize("bad", [(), (500.0, 400.0), (-1.0, 2.0)])
def test_grid_rejects_bad(bad):
    with pytest.raises(ValueError):
        SpectralGrid(bad)


def test_resample_matches_numpy_interp(device, dtype):
    src = torch.linspace(380, 780, 81, dtype=dtype, device=device)
    vals = torch.stack([torch.sin(src / 37.0), torch.cos(src / 53.0)])
    tgt = DEFAULT_GRID.wavelengths(device=device, dtype=dtype) + 2.5
    out = resample_spectra(vals, src, tgt)
    ref = np.stack(
        [
            np.interp(
                tgt.cpu().double().numpy(), src.cpu().double().numpy(), v.cpu().double().numpy()
            )
            for v in vals
        ]
    )
    assert_close(out.cpu().double(), torch.from_numpy(ref), rtol=1e-5, atol=1e-5)


def test_resample_extrapolation_modes():
    src = torch.tensor([500.0, 600.0])
    vals = torch.tensor([1.0, 3.0])
    tgt = torch.tensor([450.0, 550.0, 650.0])
    assert_close(resample_spectra(vals, src, tgt), torch.tensor([0.0, 2.0, 0.0]))
    assert_close(
        resample_spectra(vals, src, tgt, extrapolate="edge"), torch.tensor([1.0, 2.0, 3.0])
    )
    with pytest.raises(ValueError, match="outside"):
        resample_spectra(vals, src, tgt, extrapolate="error")
    with pytest.raises(ValueError, match="samples"):
        resample_spectra(vals, torch.tensor([1.0, 2.0, 3.0]), tgt)


def test_resample_other_dim():
    src = torch.tensor([400.0, 500.0, 600.0])
    cube = torch.arange(3.0).view(3, 1, 1).expand(3, 2, 2)
    out = resample_spectra(cube, src, torch.tensor([450.0, 550.0]), dim=0)
    assert out.shape == (2, 2, 2)
    assert_close(out[:, 0, 0], torch.tensor([0.5, 1.5]))


@pytest.mark.parametrize("order", [0, 1, 2])
def test_difference_matrix(order):
    D = difference_matrix(6, order, dtype=torch.float64)
    assert D.shape == (6 - order, 6)
    x = torch.arange(6, dtype=torch.float64) ** 2
    expected = {0: x, 1: x[1:] - x[:-1], 2: torch.full((4,), 2.0, dtype=torch.float64)}[order]
    assert_close(D @ x, expected)
    # constants are in the null space of first and second differences
    if order:
        assert_close(
            D @ torch.ones(6, dtype=torch.float64), torch.zeros(6 - order, dtype=torch.float64)
        )
    with pytest.raises(ValueError):
        difference_matrix(6, 3)
