"""BRF transmittance from a monochromator scan, and carrying maps into the reference frame."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hsi_torch.calibrate.transmittance import (
    brf_transmittance,
    match_wavelengths,
    to_reference_frame,
)
from hsi_torch.optics.geometry import view_masks


def _tol(dtype):
    if dtype == torch.float32:
        return {"atol": 2e-5, "rtol": 2e-5}
    return {"atol": 1e-10, "rtol": 1e-10}


def _scan(device, dtype, J=7, H=24, W=30, dark_level=5.0):
    """Scan with known transmittance: lit block rows 2..21, cols 2..27; patch = rows 4..7, 4..9."""
    wl = torch.linspace(430, 670, J, dtype=torch.float64)
    yy, xx = torch.meshgrid(torch.arange(H, dtype=torch.float64),
                            torch.arange(W, dtype=torch.float64), indexing="ij")
    T = 0.55 + 0.4 * torch.cos(2 * np.pi * (2000 + 40 * xx + 25 * yy)[None] / wl[:, None, None])
    lit = (yy >= 2) & (yy < 22) & (xx >= 2) & (xx < 28)
    patch = (yy >= 4) & (yy < 8) & (xx >= 4) & (xx < 10)
    T = torch.where(patch[None], torch.ones_like(T), T)
    T = torch.where(lit[None], T, torch.zeros_like(T))
    sens = torch.stack([torch.exp(-0.5 * ((wl - c) / 45) ** 2) for c in (600.0, 540.0, 460.0)], 1)
    lamp = 1000 + 2 * (wl - 430)
    signal = (lamp[:, None] * sens)[..., None, None] * T[:, None]  # (J, 3, H, W)
    scan = (signal + dark_level).to(device=device, dtype=dtype)
    dark = torch.full((3, H, W), dark_level, device=device, dtype=dtype)
    return scan, wl, patch.to(device), T.to(device=device, dtype=dtype), lit.to(device), dark


def test_noise_free_scan_recovers_transmittance(device, dtype):
    scan, wl, patch, T, lit, dark = _scan(device, dtype)
    res = brf_transmittance(scan, wl, patch, dark=dark)
    assert res.transmittance.shape == T.shape and res.transmittance.dtype == dtype
    torch.testing.assert_close(res.transmittance, T, **_tol(dtype))
    assert torch.equal(res.lit, lit)
    assert bool(res.reliable[:, lit].all()) and not bool(res.reliable[:, ~lit].any())
    ones = torch.ones(7, device=device, dtype=dtype)
    torch.testing.assert_close(res.channel_weights.sum(1), ones)


def test_signal_weighting_and_saturation(device):
    dtype = torch.float64
    scan, wl, patch, T, lit, dark = _scan(device, dtype)
    g = torch.Generator().manual_seed(0)
    noisy = scan + torch.randn(scan.shape, generator=g, dtype=dtype).to(device) * 3.0
    sat_level = float(scan.max()) * 0.9
    res = brf_transmittance(noisy, wl, patch, dark=dark, saturation_level=sat_level)
    # independent numpy computation of the documented formula
    x = noisy.cpu().numpy() - dark.cpu().numpy()
    pm = patch.cpu().numpy()
    u = noisy.cpu().numpy() < sat_level
    # the patch mean over its unsaturated samples; a colour with a saturated one is not used
    mu = np.where(u[:, :, pm], x[:, :, pm], 0).sum(-1) / u[:, :, pm].sum(-1).clip(1)  # (J, 3)
    usable = u[:, :, pm].all(-1)
    w = np.where(usable, mu, 0) / np.where(usable, mu, 0).sum(1, keepdims=True)
    mu = np.where(usable, mu, 1.0)
    num = (w[..., None, None] * u * x / mu[..., None, None]).sum(1)
    den = (w[..., None, None] * u).sum(1)
    expect = np.where(den > 0, num / np.where(den > 0, den, 1), 0.0)
    expect = np.where(lit.cpu().numpy()[None], expect, 0.0)
    np.testing.assert_allclose(res.transmittance.cpu().numpy(), expect, rtol=1e-10, atol=1e-12)
    assert bool((noisy >= sat_level).any())  # the test exercises saturation
    assert not usable.all()  # in the patch too
    # weighting by signal beats an unweighted channel mean on the dim-channel wavelengths
    err_w = (res.transmittance - T)[:, lit].pow(2).mean().sqrt()
    plain = (x / mu[..., None, None]).mean(1)
    err_plain = np.sqrt(((plain - T.cpu().numpy())[:, lit.cpu().numpy()] ** 2).mean())
    assert float(err_w) < 0.5 * err_plain


def test_all_channels_saturated_marks_unreliable(device):
    scan, wl, patch, T, lit, dark = _scan(device, torch.float64)
    scan[3, :, 15, 20] = 1e6
    res = brf_transmittance(scan, wl, patch, dark=dark, saturation_level=1e5)
    assert not bool(res.reliable[3, 15, 20]) and bool(res.reliable[2, 15, 20])


def test_grid_selection_and_errors():
    scan, wl, patch, T, lit, dark = _scan("cpu", torch.float64, J=7)
    perm = torch.tensor([3, 0, 6, 1, 5, 2, 4])
    res = brf_transmittance(scan[perm], wl[perm], patch, dark=dark, grid_nm=wl[1:6])
    torch.testing.assert_close(res.transmittance, T[1:6])
    torch.testing.assert_close(res.wavelengths_nm, wl[1:6])
    with pytest.raises(ValueError, match=r"missing wavelengths \[450.0\]"):
        match_wavelengths([430.0, 440.0, 460.0], [430.0, 440.0, 450.0, 460.0])
    with pytest.raises(ValueError, match="missing wavelengths"):
        brf_transmittance(scan, wl, patch, grid_nm=[430.0, 435.0])
    with pytest.raises(ValueError, match="no BRF-free patch"):
        brf_transmittance(scan, wl, torch.zeros_like(patch))
    with pytest.raises(ValueError, match=r"\(J, 3, H, W\)"):
        brf_transmittance(scan[:, :2], wl, patch)
    with pytest.raises(ValueError, match="brf_free_mask"):
        brf_transmittance(scan, wl, patch[:-1])
    with pytest.raises(ValueError, match="entries"):
        brf_transmittance(scan, wl[:-1], patch)
    dark_scan = scan.clone()
    dark_scan[2] = 0
    with pytest.raises(ValueError, match="dark in every colour channel"):
        brf_transmittance(dark_scan, wl, patch)


def test_to_reference_frame_integer_homographies(device, dtype):
    g = torch.Generator().manual_seed(1)
    M, H, W = 4, 30, 40
    m = torch.rand(M, H, W, generator=g, dtype=dtype).to(device)
    bbox = (3, 2, 12, 10)
    H1 = torch.tensor([[-1.0, 0, 36], [0, 1, -1], [0, 0, 1]], dtype=torch.float64)
    Hs = torch.stack([torch.eye(3, dtype=torch.float64), H1])
    tris = torch.tensor([[[2.0, 1.0], [17.0, 1.0], [9.0, 14.0]],
                         [[34.0, 2.0], [19.0, 2.0], [27.0, 15.0]]], dtype=torch.float64)
    src_mask = torch.ones(H, W, dtype=torch.bool, device=device)
    src_mask[6, 28] = False
    maps, masks = to_reference_frame(m, Hs, tris, bbox, source_mask=src_mask)
    assert maps.shape == (2, M, 10, 12) and maps.dtype == dtype and masks.dtype == torch.bool
    x0, y0, w, h = bbox
    torch.testing.assert_close(maps[0], m[:, y0 : y0 + h, x0 : x0 + w], **_tol(dtype))
    xs = 36 - torch.arange(x0, x0 + w)  # view px x = 36 - x_ref
    ys = torch.arange(y0, y0 + h) + 1  # view px y = y_ref + 1
    torch.testing.assert_close(maps[1], m[:, ys][:, :, xs], **_tol(dtype))
    analytic = view_masks(Hs.to(device), tris, bbox, (H, W))
    # the source pixel (28, 6) of view 1 is reference px (8, 5) -> frame (5, 3)
    assert bool(analytic[1, 3, 5]) and not bool(masks[1, 3, 5])
    expect = analytic.clone()
    expect[1, 3, 5] = False
    assert torch.equal(masks, expect)
    assert 0 < int(masks[0].sum()) < w * h


def test_a_saturated_sample_in_the_patch_never_enters_its_mean(device):
    """The pipeline replaces saturated samples by a huge sentinel: one of them in the BRF-free
    patch made that colour's patch mean ~1e20/n and its weight ~1, so B of the whole band came
    out ~0 (in a lab's scan with 9 clipped pixels, B at 530 nm was 100 % off and the
    ColorChecker 1.5 dB lower, exit 0). Now that colour is left out at that wavelength and B is
    the one without the saturated sample."""
    scan, wl, patch, T, lit, dark = _scan(device, torch.float64)
    clean = brf_transmittance(scan, wl, patch, dark=dark, saturation_level=1e19)
    hit = scan.clone()
    hit[3, 0, 5, 5] = 1e20  # one saturated red sample inside the patch
    res = brf_transmittance(hit, wl, patch, dark=dark, saturation_level=1e19)
    torch.testing.assert_close(res.transmittance, clean.transmittance, atol=1e-9, rtol=1e-9)
    assert float(res.channel_weights[3, 0]) == 0.0 and float(res.patch_mean[3, 0]) < 1e6
    hit[3, :, 5, 5] = 1e20  # every colour: no patch mean is known at that wavelength
    with pytest.raises(ValueError, match=r"patch is saturated in every colour channel at "
                                         r"\[55\d\.\d+\] nm"):
        brf_transmittance(hit, wl, patch, dark=dark, saturation_level=1e19)
