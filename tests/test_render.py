"""Capture renderer: spectral discretisation, forward-model consistency with the ground truth,
monochromator-scan ratio = true B, reproducible noise. Small default sensor (400 × 384)."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from hsi_torch.optics import DEFAULT_CAMERA, DEFAULT_GEOMETRY, BRFConfig
from hsi_torch.optics.sensor import SensorModel
from hsi_torch.simulate.capture_sets import brf_free_patch_mask
from hsi_torch.simulate.render import (
    CaptureRenderer,
    CaptureSpec,
    fine_wavelengths,
    hat_weights,
    line_profile,
)
from hsi_torch.simulate.scenes import ColorCheckerScene
from hsi_torch.spectral import DEFAULT_GRID, band_widths


def test_fine_grid_tiles_band_pass_and_hats_partition_unity():
    g = DEFAULT_GRID.wavelengths(dtype=torch.float64)
    wl, dw = fine_wavelengths(g, 2.0)
    assert wl.numel() == 125
    torch.testing.assert_close(wl[[0, -1]], torch.tensor([426.0, 674.0], dtype=torch.float64))
    torch.testing.assert_close(dw.sum(), torch.tensor(250.0, dtype=torch.float64))
    h = hat_weights(g, wl)
    torch.testing.assert_close(h.sum(0), torch.ones_like(wl))
    # Σ_l Δλ_l h_m(λ_l) = Δλ_m: the hat decomposition conserves every band's width
    torch.testing.assert_close(h @ dw, band_widths(g))


def test_line_profile_fwhm():
    wl = torch.tensor([545.0, 550.0, 555.0], dtype=torch.float64)
    for shape in ("gaussian", "triangle"):
        p = line_profile(torch.tensor([550.0]), wl, 10.0, shape)[0]
        torch.testing.assert_close(p, torch.tensor([0.5, 1.0, 0.5], dtype=torch.float64))
    with pytest.raises(ValueError, match="line shape"):
        line_profile(torch.tensor([550.0]), wl, 10.0, "box")


@pytest.fixture(scope="module")
def setup():
    sensor = SensorModel(output="rgb", shot_noise=False, read_noise_e=0.0, quantize=False,
                         exposure=0.8)
    r = CaptureRenderer(DEFAULT_GEOMETRY, DEFAULT_CAMERA, BRFConfig(), sensor,
                        dtype=torch.float64, max_reflections=2)
    cc = ColorCheckerScene(width_mm=8.4, center_mm=(0.0, 1.4))
    specs = [CaptureSpec("cc", "scene", cc), CaptureSpec("s430", "scan", None, 430.0),
             CaptureSpec("s550", "scan", None, 550.0), CaptureSpec("dark", "dark")]
    irr = r.render(specs)
    truth = r.ground_truth()
    return r, cc, irr, truth


def _erode(mask: torch.Tensor, k: int) -> torch.Tensor:
    m = mask.float().reshape(-1, 1, *mask.shape[-2:])
    return (-F.max_pool2d(-m, k, 1, k // 2) > 0.5).reshape(mask.shape)


def test_knot_interpolated_transmittance_matches_exact(setup):
    r = setup[0]
    g = torch.Generator().manual_seed(0)
    a = torch.rand(2000, generator=g, dtype=torch.float64) * 0.25
    s = (torch.rand(2000, generator=g, dtype=torch.float64) - 0.5) * 2 * math.pi
    free = torch.zeros(2000, dtype=torch.bool)
    exact = r.stack_transmittance(a, s, free, r.fine, exact=True)
    fast = r.stack_transmittance(a, s, free, r.fine, exact=False)
    assert (exact - fast).abs().max() < 1e-3


def test_truth_structure(setup):
    r, _, irr, truth = setup
    V, M = r.layout.num_views, 25
    x0, y0, w, h = r.layout.reference_bbox
    assert truth["B"].shape == (V, M, h, w) and truth["phi"].shape == (3, M)
    assert V == 10 and int(truth["valid"].sum()) > 1000
    vm, B = truth["view_mask"], truth["B"]
    eta = r.polarizer_efficiency
    # filtered pixels: 0 ≤ B ≤ t·½η; BRF-free pixels: B = t exactly (no filter stack)
    mod = truth["modulated"]
    assert float(B.permute(1, 0, 2, 3)[:, mod].max()) <= 0.5 * eta + 1e-6
    free = vm & truth["brf_free"][None]
    assert int(free[0].sum()) > 5
    t = truth["throughput"][:, None].expand_as(B)
    torch.testing.assert_close(B.permute(1, 0, 2, 3)[:, free], t.permute(1, 0, 2, 3)[:, free])
    # reference view: no reflection, gain = cos^k α · vignetting
    torch.testing.assert_close(truth["throughput"][0][vm[0]],
                               torch.ones(int(vm[0].sum())))
    assert not bool(irr[3].any())  # dark capture


def test_forward_model_matches_rendering(setup):
    """The key consistency check: noise-free rendering = gain·(B·Δλ·φ)·s in the reference frame
    (bilinear sampling of each view at the true source point), away from edges."""
    r, cc, irr, truth = setup
    cube = r.scene_truth(cc)
    y = r.forward_model(truth, cube)
    img = r.noise_free_dn(irr[0], r.scene_exposure)
    ys = r.sample_views(img)
    pi = cc.patch_index(truth["diffuser_xy"].reshape(-1, 2).double()).reshape(cube.shape[1:])
    pf = pi.float()[None, None]
    uniform = (F.max_pool2d(pf, 5, 1, 2) == -F.max_pool2d(-pf, 5, 1, 2))[0, 0] & (pi >= 0)
    sel = _erode(truth["view_mask"], 5) & uniform[None]
    assert int(sel.sum()) > 2000
    rel = (ys - y).abs().div(y).permute(1, 0, 2, 3)[:, sel]
    print(f"forward model vs rendering: median {float(rel.median()):.4f}, "
          f"p99 {float(rel.quantile(0.99)):.4f}, max {float(rel.max()):.4f}")
    assert float(rel.median()) < 0.01
    assert float(rel.quantile(0.99)) < 0.03
    assert float(rel.max()) < 0.05


@pytest.mark.parametrize("k,lam", [(1, 430.0), (2, 550.0)])
def test_scan_ratio_equals_true_B(setup, k, lam):
    r, _, irr, truth = setup
    img = irr[k]
    patch = brf_free_patch_mask(r)
    assert int(patch.sum()) >= 4
    pm = (img * patch).sum((-2, -1)) / patch.sum()
    ratio = r.sample_views(img / pm[:, None, None])
    comb = (ratio * (pm / pm.sum())[None, :, None, None]).sum(1)  # signal-weighted colours
    m = int(round((lam - 430.0) / 10.0))
    bt = truth["B"][:, m].double()
    near_free = F.max_pool2d(truth["brf_free"].float()[None, None], 5, 1, 2)[0, 0] > 0
    sel = _erode(truth["modulated"], 3) & ~near_free[None]
    err = (comb - bt)[sel]
    assert float(err.abs().max()) < 0.01  # ≈ 2 % of the peak ½η
    assert float(err.pow(2).mean().sqrt()) < 0.005


def test_noise_is_reproducible_per_seed():
    sensor = SensorModel(output="bayer")
    rr = CaptureRenderer(DEFAULT_GEOMETRY, DEFAULT_CAMERA.scaled(0.25), BRFConfig(), sensor,
                         layout=None, max_reflections=2, dtype=torch.float32)
    irr = rr.render([CaptureSpec("w", "scene", None)])[0]
    assert irr.shape == (1, 96, 100)
    a = rr.expose(irr, 0.8, seed=5).dn
    b = rr.expose(irr, 0.8, seed=5).dn
    c = rr.expose(irr, 0.8, seed=6).dn
    assert torch.equal(a, b) and not torch.equal(a, c)
    nf = rr.noise_free_dn(irr, 0.8) + sensor.black_level
    lit = irr[0] > 0.05
    # mean over lit pixels equals the noise-free DN to < 0.5 % (noise statistics: test_sensor)
    assert abs(float(a[0][lit].mean() / nf[0][lit].mean()) - 1) < 5e-3
