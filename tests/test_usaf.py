"""USAF resolution: the contrast criterion on synthetic bar profiles, the limit rule, contrasts
on a rendered target, and a reduced end-to-end run (RGB reference vs HSI)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hsi_torch.config import load_config
from hsi_torch.experiments.usaf import (
    ABLATIONS,
    USAFConfig,
    _sim_config,
    check_reusable_capture_set,
    element_contrasts,
    elements_below,
    ideal_observations,
    michelson_bar_contrast,
    resolution_limit,
    run_usaf,
    triplet_sample_points,
)
from hsi_torch.metrics import METRIC_NAMES
from hsi_torch.recon import Reconstructor
from hsi_torch.resources import shipped_config
from hsi_torch.simulate.capture_sets import build_renderer, simulate_capture_set
from hsi_torch.simulate.oracle import bundle_from_truth
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
    cfg = USAFConfig(prototype=shipped_config("simulate"),
                     prototype_overrides=["render.supersample=1"], progress=False)
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
    # ``capture_set``: the same row from the capture set just simulated gives the same numbers
    again = USAFConfig(**{**cfg.__dict__, "capture_set": tmp_path / "capture_set"})
    r = run_usaf(again, tmp_path / "reused")
    assert r["capture_set_reused"] and r["capture_set"] == str(tmp_path / "capture_set")
    assert not (tmp_path / "reused" / "capture_set").exists()  # nothing simulated
    assert r["stats"] == s["stats"] and r["metrics"] == s["metrics"]


def test_capture_set_reuse_is_checked(oracle_small, tmp_path):
    """A capture set is reused only for rows whose capture would be the same (beta, prior):
    a row that changes the capture (noise, demosaic, seed, the scene rendered) or an incomplete
    folder is refused, naming what differs — before anything is reconstructed."""
    from dataclasses import replace

    _, _, _, cs = oracle_small  # a warp row's capture set: the ground truth only
    cfg = USAFConfig(prototype=shipped_config("simulate"),
                     prototype_overrides=["render.supersample=1", "diffuser.blur_sigma_mm=0"],
                     ablate=["warp"], progress=False)
    cfg.target.groups, cfg.target.magnification = [0], 0.25
    for ab in (["warp"], ["warp", "beta"], ["warp", "noise"], ["warp", "demosaic"]):
        s2 = _sim_config(USAFConfig(**{**cfg.__dict__, "ablate": ab}), calibrated=False)
        s2 = replace(s2, captures=replace(s2.captures, scenes=[]))
        if ab[-1] in ("warp", "beta"):
            check_reusable_capture_set(cs, [s2])  # the same capture: accepted
        else:
            key = {"noise": "sensor.read_noise_e", "demosaic": "sensor.output"}[ab[-1]]
            with pytest.raises(ValueError, match=rf"differs in .*{key}"):
                check_reusable_capture_set(cs, [s2])
    # a warp row on it runs (its truth holds no rendered scene: the renderer's truth is used)
    w = run_usaf(USAFConfig(**{**cfg.__dict__, "capture_set": cs}), tmp_path / "w")
    assert w["capture_set_reused"] and np.isfinite(w["metrics"]["psnr_db"])
    assert not (tmp_path / "w" / "capture_set").exists()
    with pytest.raises(ValueError, match=r"differs in .*render\.seed"):
        run_usaf(USAFConfig(**{**cfg.__dict__, "seed": 1, "capture_set": cs}), tmp_path / "o")
    assert not (tmp_path / "o" / "summary.json").exists()
    # a row that renders the scene cannot use a truth-only set
    with pytest.raises(ValueError, match=r"captures\.scenes"):
        run_usaf(USAFConfig(**{**cfg.__dict__, "ablate": [], "capture_set": cs}),
                 tmp_path / "o")
    with pytest.raises(ValueError, match="not a complete capture set"):
        run_usaf(USAFConfig(**{**cfg.__dict__, "capture_set": tmp_path / "nowhere"}),
                 tmp_path / "o")


# ---------------------------------------------------------------------------------------------
# ablations
# ---------------------------------------------------------------------------------------------


def test_ablate_key_is_validated(tmp_path):
    assert USAFConfig().ablate == []
    # the default is the seed's scale: full-size prototype, 1/16 magnification, 10 µm diffuser
    d = USAFConfig()
    assert d.prototype is None and d.target.magnification == 0.0625
    full = _sim_config(d, calibrated=False)
    assert full.camera.width_px == 2896 and full.diffuser.blur_sigma_mm == 0.01
    assert USAFConfig(ablate="warp").ablate == ["warp"]
    with pytest.raises(ValueError, match=r"ablate: unknown factor\(s\) \['blur'\]"):
        USAFConfig(ablate=["blur"])
    with pytest.raises(ValueError, match="names a factor twice"):
        USAFConfig(ablate=["noise", "noise"])
    cfg = load_config(shipped_config("usaf"), USAFConfig, ["ablate=[diffuser,beta]"])
    assert cfg.ablate == ["diffuser", "beta"]
    with pytest.raises(ValueError, match="ablate"):
        load_config(shipped_config("usaf"), USAFConfig, ["ablate=[demosaicing]"])
    # the ideal observations are made with the bundle's matrix: only with the oracle bundle
    bad = USAFConfig(ablate=["warp"], bundle="calibrated", progress=False)
    with pytest.raises(ValueError, match="'warp' needs bundle: oracle"):
        run_usaf(bad, tmp_path)
    assert not (tmp_path / "capture_set").exists()  # refused before simulating anything


def test_ablations_switch_the_prototype():
    cfg = USAFConfig(prototype=shipped_config("simulate"),
                     prototype_overrides=["camera.scale=2", "diffuser.blur_sigma_mm=0.05"])
    base = _sim_config(cfg, calibrated=False)
    assert base.diffuser.blur_sigma_mm == 0.05 and base.sensor.output == "bayer"
    assert base.sensor.shot_noise and base.sensor.read_noise_e > 0 and base.sensor.quantize
    cfg.ablate = list(ABLATIONS)
    off = _sim_config(cfg, calibrated=False)
    assert off.diffuser.blur_sigma_mm == 0.0 and off.sensor.output == "rgb"
    assert not off.sensor.shot_noise and off.sensor.read_noise_e == 0 and not off.sensor.quantize
    assert off.camera.scale == 2  # nothing else changes
    same = _sim_config(cfg, calibrated=False, ablate=False)
    assert same.diffuser.blur_sigma_mm == 0.05 and same.sensor.output == "bayer"


def _fine_element_contrast(renderer, scene, lp_diffuser):
    """Contrast (both orientations, min) of the element nearest ``lp_diffuser`` in the
    renderer's reference-frame truth (the scene sampled as rendered, diffuser blur included)."""
    img = renderer.scene_truth(scene)[12:13].double()  # one band: the target is grey
    els = scene.elements()
    pts = torch.stack([triplet_sample_points(e) for e in els])
    px = renderer.diffuser_to_reference(pts.reshape(-1, 2)).reshape(pts.shape)
    c = element_contrasts(img, px)[0]
    f = torch.tensor([e.lp_per_mm for e in els])
    pick = (f - lp_diffuser).abs() == (f - lp_diffuser).abs().min()
    return float(c[pick].min())


def test_diffuser_ablation_raises_fine_contrast():
    """No diffuser → a fine element keeps a higher contrast than through a 0.1 mm blur."""
    cfg = USAFConfig(prototype=shipped_config("simulate"),
                     prototype_overrides=["render.supersample=1", "diffuser.blur_sigma_mm=0.15"])
    cfg.target.groups, cfg.target.magnification = [0, 1], 1.0
    from hsi_torch.simulate.capture_sets import build_scene

    with_d = _sim_config(cfg, calibrated=False)
    cfg.ablate = ["diffuser"]
    without = _sim_config(cfg, calibrated=False)
    scene = build_scene(with_d.captures.scenes[0])
    # G1 E1 = 2 lp/mm on the diffuser: 3.7 px per line pair of the 400 px sensor (Nyquist 3.7)
    c_with = _fine_element_contrast(build_renderer(with_d), scene, 2.0)
    c_without = _fine_element_contrast(build_renderer(without), scene, 2.0)
    assert c_without > c_with + 0.2, (c_without, c_with)  # measured 0.78 vs 0.15
    assert c_with < 0.5 < c_without
    assert c_with < 0.5 < c_without


@pytest.fixture(scope="module")
def oracle_small(tmp_path_factory):
    """Small prototype's ground truth only (no capture rendered) and its oracle bundle."""
    cfg = USAFConfig(prototype=shipped_config("simulate"),
                     prototype_overrides=["render.supersample=1", "diffuser.blur_sigma_mm=0"],
                     ablate=["warp"])
    cfg.target.groups, cfg.target.magnification = [0], 0.25
    sim = _sim_config(cfg, calibrated=False)
    from dataclasses import replace

    from hsi_torch.simulate.capture_sets import build_scene

    out = tmp_path_factory.mktemp("usaf_truth")
    simulate_capture_set(replace(sim, captures=replace(sim.captures, scenes=[])), out,
                         progress=False, log=lambda *a: None)
    return sim, bundle_from_truth(out), build_scene(sim.captures.scenes[0]), out


def test_ideal_observations_reconstruct_the_truth(oracle_small, device):
    """Noise-free ideally registered observations of the (spectrally flat) target give back its
    reflectance exactly (β does not bias a flat spectrum); with sensor noise, close to it."""
    sim, bundle, scene, _ = oracle_small
    renderer = build_renderer(sim)
    rec = Reconstructor(bundle, beta=1000.0, device=device, dtype=torch.float64)
    truth = renderer.scene_truth(scene).double()
    cube, valid, info = ideal_observations(rec, renderer, scene, noise=False)
    assert info["num_valid"] == int(valid.sum()) > 1000
    v = valid.cpu()
    err = (cube.cpu()[:, v] - truth[:, v]).abs()
    assert float(err.max()) < 1e-6
    noisy, valid2, _ = ideal_observations(rec, renderer, scene, noise=True, seed=3)
    e2 = (noisy.cpu()[:, v] - truth[:, v]).abs()
    assert 1e-4 < float(e2.median()) < 0.05  # noise is there, and small
    again, _, _ = ideal_observations(rec, renderer, scene, noise=True, seed=3)
    torch.testing.assert_close(again, noisy, equal_nan=True)  # seeded


def test_elements_below():
    f = torch.tensor([1.0, 2 ** (-1 / 6), 2 ** (-2 / 6), 0.0, 2 ** (1 / 6)], dtype=torch.float64)
    assert elements_below(f, 1.0) == [0, 1, 2, None, -1]
    assert elements_below(f, 0.0) == [None] * 5

