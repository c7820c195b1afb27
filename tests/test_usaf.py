"""USAF resolution: the contrast criterion on synthetic bar profiles, the limit rule, contrasts
on a rendered target, and a reduced end-to-end run (RGB reference vs HSI)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hsi_torch.experiments.usaf import (
    USAFConfig,
    element_contrasts,
    michelson_bar_contrast,
    resolution_limit,
    run_usaf,
    triplet_sample_points,
)
from hsi_torch.metrics import METRIC_NAMES
from hsi_torch.simulate.scenes import USAF1951Scene, pixel_centres_mm


def _bar_profile(width_px: float, blur_px: float, n: int = 400) -> tuple[np.ndarray, np.ndarray]:
    """Three bright bars (0.9) on 0.05, blurred by a Gaussian; returns (x, profile)."""
    x = np.linspace(-3 * width_px, 8 * width_px, n)
    bars = np.zeros_like(x) + 0.05
    for b in range(3):
        bars[(x >= 2 * b * width_px) & (x < (2 * b + 1) * width_px)] = 0.9
    if blur_px > 0:
        k = np.exp(-0.5 * ((x - x.mean()) / blur_px) ** 2)
        bars = np.convolve(bars - 0.05, k / k.sum(), mode="same") + 0.05
    return x, bars


@pytest.mark.parametrize("blur", [0.0, 0.3, 0.6, 1.0, 2.0])
def test_contrast_on_blurred_bars(device, dtype, blur):
    w = 2.0
    x, prof = _bar_profile(w, blur * w)
    centres = np.array([(j + 0.5) * w for j in range(5)])
    vals = np.interp(centres, x, prof)
    bars = torch.tensor(vals[[0, 2, 4]], device=device, dtype=dtype)
    gaps = torch.tensor(vals[[1, 3]], device=device, dtype=dtype)
    c = michelson_bar_contrast(bars, gaps)
    expect = (vals[[0, 2, 4]].min() - vals[[1, 3]].max()) / (vals[[0, 2, 4]].min()
                                                               + vals[[1, 3]].max())
    torch.testing.assert_close(c, torch.tensor(expect, device=device, dtype=dtype))
    if blur == 0:
        torch.testing.assert_close(c.double().cpu(), torch.tensor(0.85 / 0.95,
                                   dtype=torch.float64), rtol=1e-6, atol=1e-6)
    if blur >= 2.0:  # blurred beyond recognition: below any sensible threshold
        assert float(c) < 0.1


def test_contrast_decreases_with_blur_and_nan():
    cs = []
    for blur in (0.0, 0.4, 0.8, 1.2):
        x, prof = _bar_profile(2.0, blur * 2.0)
        v = np.interp([(j + 0.5) * 2.0 for j in range(5)], x, prof)
        cs.append(float(michelson_bar_contrast(torch.tensor(v[[0, 2, 4]]),
                                               torch.tensor(v[[1, 3]]))))
    assert all(a > b for a, b in zip(cs, cs[1:], strict=False))
    c = michelson_bar_contrast(torch.tensor([[1.0, float("nan"), 1.0]]), torch.tensor([[0., 0.]]))
    assert torch.isnan(c).all()
    with pytest.raises(ValueError):
        michelson_bar_contrast(torch.ones(2), torch.ones(2))


def test_resolution_limit_stops_at_first_failure():
    freq = torch.tensor([1.0, 2.0, 1.5, 3.0], dtype=torch.float64)
    c = torch.tensor([[0.5, 0.3, 0.4, 0.05],     # 1, 1.5, 2 ok, 3 fails → 2
                      [0.5, 0.3, 0.02, 0.4],     # 1.5 fails → 1 (3 passes by aliasing: ignored)
                      [0.01, 0.5, 0.5, 0.5],     # coarsest fails → none
                      [0.5, float("nan"), 0.5, 0.5]], dtype=torch.float64)
    idx, f = resolution_limit(c, freq, 0.1)
    assert idx.tolist() == [1, 0, -1, 2]
    assert f.tolist() == [2.0, 1.0, 0.0, 1.5]
    idx, f = resolution_limit(c, freq, 0.1, usable=torch.tensor([True, False, True, True]))
    assert f.tolist()[3] == 3.0  # the NaN element is skipped when not usable


def test_contrasts_on_rendered_target():
    """A sharply rendered target: coarse elements have ≈ the full contrast 0.85/0.95; elements
    finer than 2 px per line pair fall below the threshold after box-filter sampling."""
    sc = USAF1951Scene(groups=(0, 1, 2), magnification=1.0)
    ext = sc.extent
    px = 0.1  # mm per pixel → Nyquist 5 lp/mm
    W = int(round((ext[1] - ext[0]) / px))
    H = int(round((ext[3] - ext[2]) / px))
    from hsi_torch.simulate.scenes import render_scene_image

    img = render_scene_image(sc, ext, H, W, [550.0], supersample=4, dtype=torch.float64)
    els = sc.elements()
    pts = torch.stack([triplet_sample_points(e) for e in els])
    # diffuser mm → px (pixel centres at integers)
    dx, dy = (ext[1] - ext[0]) / W, (ext[3] - ext[2]) / H
    pts_px = torch.stack([(pts[..., 0] - ext[0]) / dx - 0.5, (pts[..., 1] - ext[2]) / dy - 0.5],
                         -1)
    c = element_contrasts(img, pts_px)[0]
    freq = torch.tensor([e.lp_per_mm for e in els])
    coarse = freq <= 1.5
    assert (c[coarse] > 0.6).all()
    assert (c[freq > 5.0] < 0.3).all()
    # sanity of the px mapping used above: the element bbox corner matches the pixel grid
    centres = pixel_centres_mm(ext, H, W, dtype=torch.float64)
    assert abs(float(centres[0, 0, 0]) - (ext[0] + dx / 2)) < 1e-9


def test_reduced_run(tmp_path):
    """End to end on the small sensor (fast): files, scale, RGB reference at least as fine as
    the median HSI band."""
    cfg = USAFConfig(prototype_overrides=["render.supersample=1"], progress=False)
    cfg.target.groups = [0, 1]
    cfg.target.magnification = 0.25
    s = run_usaf(cfg, tmp_path)
    for f in ("resolution.csv", "resolution.md", "contrast.csv", "summary.json",
              "usaf_600nm_vs_rgb.png", "resolution_vs_wavelength.png"):
        assert (tmp_path / f).is_file(), f
    assert abs(s["nyquist_lp_mm_target"] - 0.25 / (2 * s["diffuser_mm_per_px"])) < 1e-9
    assert s["stats"]["rgb_gray_lp_mm"] >= s["stats"]["hsi_median_lp_mm"]
    # the field's metrics of the cube against the true target, in the summary and the table
    m = s["metrics"]
    assert set(m) == set(METRIC_NAMES) and all(np.isfinite(v) for v in m.values())
    assert m["rmse"] == pytest.approx(10 ** (-m["psnr_db"] / 20), rel=1e-9)  # one pooled MSE
    assert 0 < m["ssim"] <= 1 and 0 < m["sam_deg"] < 90 and m["ergas"] > 0 and m["mrae"] > 0
    md = (tmp_path / "resolution.md").read_text()
    for h in ("PSNR dB (cube, peak 1)", "PSNR dB (per band, 0-255)", "SSIM", "SAM °", "ERGAS",
              "RMSE", "MRAE", f"{m['psnr_bands_db']:.2f}", f"{m['ssim']:.4f}"):
        assert h in md, h
