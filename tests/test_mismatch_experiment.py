"""The mismatch experiment and its remedies: the veil of stray light measured where no light
reaches, hot and dead pixels found and dropped, the experiment's rows and their cache."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
import pytest
import torch

from hsi_torch.cli import main
from hsi_torch.config import load_config
from hsi_torch.io import read_any, read_capture
from hsi_torch.io.bundle import CalibrationBundle
from hsi_torch.io.captures import LinearCapture
from hsi_torch.io.radiometry import outside_views_index
from hsi_torch.io.raw import demosaic_bilinear
from hsi_torch.io.sensor_corrections import estimate_veil, find_defects, unreached_index
from hsi_torch.optics.sensor import SensorModel
from hsi_torch.recon import HSIReconstructor, Reconstructor
from hsi_torch.recon.checks import BundleRadiometry
from hsi_torch.recon.pipeline import apply_bundle_corrections
from hsi_torch.simulate.config import SimulateConfig
from hsi_torch.simulate.mismatch import stray_light_veil
from hsi_torch.simulate.oracle import bundle_from_truth
from hsi_torch.simulate.rerender import rerender_after_calibration

H, W = 120, 128
TRI = np.array([[[34.0, 90.0], [94.0, 90.0], [64.0, 30.0]]])  # one view, sensor px (x, y)


def _inside(tri: np.ndarray, pad: float = 0.0) -> np.ndarray:
    """(H, W) bool: inside the triangle grown by ``pad`` px."""
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    out = np.ones((H, W), bool)
    area = (tri[1, 0] - tri[0, 0]) * (tri[2, 1] - tri[0, 1]) \
        - (tri[1, 1] - tri[0, 1]) * (tri[2, 0] - tri[0, 0])
    sgn = -1.0 if area > 0 else 1.0
    for i in range(3):
        a, b = tri[i], tri[(i + 1) % 3]
        n = math.hypot(b[0] - a[0], b[1] - a[1])
        d = sgn * ((b[0] - a[0]) * (ys - a[1]) - (b[1] - a[1]) * (xs - a[0])) / n
        out &= d <= pad
    return out


def _lit_frame(device, dtype, extra_tile: bool = False) -> torch.Tensor:
    """(3, H, W) textured light inside the view (and a second, higher-order tile beside it)."""
    g = torch.Generator().manual_seed(3)
    lit = torch.from_numpy(_inside(TRI[0]))
    if extra_tile:
        lit |= torch.from_numpy(_inside(TRI[0] + np.array([50.0, 0.0])))
    tex = 500 + 1000 * torch.rand(3, H, W, generator=g, dtype=torch.float64)
    return (tex * lit).to(device=device, dtype=dtype)


# ------------------------------------------------------------------------------ stray light


def test_veil_estimate_recovers_a_simulated_veil(device, dtype):
    img = _lit_frame(device, dtype)
    centre = ((W - 1) / 2, (H - 1) / 2)
    veiled = stray_light_veil(img, 0.02, 0.5, centre)
    g = torch.Generator().manual_seed(4)
    noisy = veiled + 2.0 * torch.randn(veiled.shape, generator=g, dtype=torch.float64).to(
        device=device, dtype=dtype)
    idx = outside_views_index(TRI, (H, W))
    est, info = estimate_veil(noisy, idx)
    true = (veiled - img).double()
    assert est.shape == img.shape and est.dtype == dtype and est.device == img.device
    assert info["model"] == ["exp-quadratic"] * 3
    # the veil's level within 3 % per colour, and under the view (where it is never seen,
    # extrapolated) within 10 % at the centre
    np.testing.assert_allclose(info["mean_dn"], true.mean((1, 2)).cpu().numpy(), rtol=0.03)
    c = (slice(None), slice(H // 2 - 5, H // 2 + 5), slice(W // 2 - 5, W // 2 + 5))
    np.testing.assert_allclose(est[c].double().mean((1, 2)).cpu().numpy(),
                               true[c].mean((1, 2)).cpu().numpy(), rtol=0.10)
    # no veil: nothing (a constant at the noise's mean, ~0) is subtracted
    clean = img + 2.0 * torch.randn(img.shape, generator=g, dtype=torch.float64).to(
        device=device, dtype=dtype)
    est0, info0 = estimate_veil(clean, idx)
    assert max(info0["mean_dn"]) < 0.3 and float(est0.abs().max()) < 0.3


def test_unreached_samples_leave_out_tiles_the_views_do_not_use(device):
    white = _lit_frame(device, torch.float32, extra_tile=True)
    geo = outside_views_index(TRI, (H, W), margin_px=2.0)
    idx = unreached_index(white, geo, margin_px=3.0)
    lit2 = _inside(TRI[0] + np.array([50.0, 0.0])).reshape(-1)
    assert lit2[geo].sum() > 100  # the geometric outside of the views holds the second tile
    assert lit2[idx].sum() == 0 and set(idx.tolist()) <= set(geo.tolist())
    assert idx.size > 0.5 * (~lit2[geo]).sum()


# ------------------------------------------------------------------------------ defects


def test_defect_mask_finds_hot_and_dead_pixels(device):
    s, hs = 256, 0.2 * 16383
    sensor = SensorModel(hot_pixel_fraction=1e-3, dead_pixel_fraction=1e-3, pattern_seed=7)
    _, hot, dead = sensor.fixed_pattern(s, s, device=device)
    g = torch.Generator().manual_seed(5)
    noise = lambda: torch.randn(1, s, s, generator=g).to(device)  # noqa: E731
    dark_raw = 1.5 * noise() + hs * hot[None].float()
    ys, xs = torch.meshgrid(torch.arange(s), torch.arange(s), indexing="ij")
    field = (2000 + 4 * xs - 3 * ys).float().to(device)
    field = torch.where((xs < 90).to(device) | ((ys > 200) & (xs > 150)).to(device),
                        torch.zeros_like(field), field)  # sharp tile edges
    white_raw = (field[None] + 10 * noise()) * (~dead)[None].float() + dark_raw
    dark = demosaic_bilinear(dark_raw[None], "RGGB")[0]
    white = demosaic_bilinear(white_raw[None], "RGGB")[0] - dark
    truth = hot | (dead & (field > 0))
    assert int(truth.sum()) > 80
    found = find_defects(dark, white, dilate_px=0)
    tp = int((found & truth).sum())
    assert tp / int(truth.sum()) >= 0.95, "recall"
    assert tp / max(1, int(found.sum())) >= 0.9, "precision (tile edges are not dead pixels)"
    wide = find_defects(dark, white)  # dilated over the demosaic's footprint
    assert bool(wide[found].all()) and int(wide.sum()) <= 9 * int(found.sum())


def test_bundle_corrections_mark_defects_and_subtract_the_veil_once(device):
    img = stray_light_veil(_lit_frame(device, torch.float32), 0.02, 0.5, (63.5, 59.5))
    cap = LinearCapture(image=img.clone(), saturated=torch.zeros(3, H, W, dtype=torch.bool,
                                                                  device=device),
                        metadata={}, path=Path("x.tif"))
    rad = BundleRadiometry(veil_index=outside_views_index(TRI, (H, W)),
                           defect_index=np.array([5, 77, 1000], np.int64))
    st = apply_bundle_corrections(cap, rad)
    assert st["defect_pixels"] == 3
    assert cap.saturated.reshape(3, -1)[:, [5, 77, 1000]].all()
    assert int(cap.saturated.sum()) == 9
    out = ~torch.from_numpy(_inside(TRI[0], pad=3.0)).to(device)
    assert float(cap.image[:, out].abs().mean()) < 0.05 * float(img[:, out].mean())
    before = cap.image.clone()
    assert apply_bundle_corrections(cap, rad) == st and torch.equal(cap.image, before)


# ------------------------------------------------------------------------------ small set


@pytest.fixture(scope="module")
def small_set(small_sim: Path) -> Path:
    return small_sim  # the session's shared, read-only set (float32 render, no figures)


def test_rerender_without_an_effect_reproduces_the_set(small_set: Path, tmp_path: Path):
    cfg = load_config(small_set / "resolved_config.yaml", SimulateConfig)
    files = rerender_after_calibration(cfg, small_set, tmp_path / "again", whites=True,
                                       log=lambda *a: None)
    assert "scenes/colorchecker.tif" in files and "white/white_00.tif" in files
    for f in files:
        a, _ = read_capture(small_set / f)
        b, _ = read_capture(tmp_path / "again" / f)
        assert np.array_equal(np.asarray(a), np.asarray(b)), f
    cfg.mismatch.distortion_k1 = -0.1
    with pytest.raises(ValueError, match="distortion_k1"):
        rerender_after_calibration(cfg, small_set, tmp_path / "no")
    # a base with a device effect needs the same device keys (checked before rendering)
    fake = tmp_path / "fake"
    (fake / "ground_truth").mkdir(parents=True)
    (fake / "ground_truth" / "truth.json").write_text(json.dumps(
        {"mismatch": {"stray_light_fraction": 0.02}}))
    cfg.mismatch.distortion_k1 = 0.0
    with pytest.raises(ValueError, match="stray_light_fraction"):
        rerender_after_calibration(cfg, fake, tmp_path / "no")


def test_rerender_white_references_only(small_set: Path, tmp_path: Path):
    """White references re-shot under the scene's light: the whites change, the scenes and
    every other file are the base's, the truth records the whites' illuminant."""
    cfg = load_config(small_set / "resolved_config.yaml", SimulateConfig)
    cfg.mismatch.scene_illuminant = "A"
    with pytest.raises(ValueError, match="neither"):
        rerender_after_calibration(cfg, small_set, tmp_path / "no", scenes=False)
    out = tmp_path / "white"
    files = rerender_after_calibration(cfg, small_set, out, whites=True, scenes=False,
                                       log=lambda *a: None)
    assert files and all(f.startswith("white/") for f in files)
    assert os.path.samefile(out / "scenes" / "colorchecker.tif",
                            small_set / "scenes" / "colorchecker.tif")

    def red_over_blue(f: Path) -> float:  # RGGB mosaic: R at (0, 0), B at (1, 1)
        img, meta = read_capture(f)
        x = np.asarray(img, np.float64) - float(meta["black_level"])
        return float(x[..., 0::2, 0::2].sum() / x[..., 1::2, 1::2].sum())

    # tungsten (A) is far redder than D65: measured 1.91 against 0.59
    assert red_over_blue(out / files[0]) > 2.0 * red_over_blue(small_set / files[0])
    meta = json.loads((out / "ground_truth" / "truth.json").read_text())
    assert meta["mismatch"] == {} and meta["white_mismatch"] == {"scene_illuminant": "A"}


def test_reconstruction_drops_observations_of_defect_pixels(small_set: Path):
    bundle = bundle_from_truth(small_set)
    cap = read_any(small_set / "scenes" / "colorchecker.tif")
    ref = Reconstructor(bundle).reconstruct_capture(cap).cube
    # corrupt a few sensor pixels inside the views (a hot pixel's offset)
    Hs, Ws = cap.image.shape[-2:]
    rng = np.random.default_rng(0)
    lit = (cap.image.sum(0) > 0.2 * cap.image.sum(0).max()).reshape(-1).cpu().numpy()
    bad = rng.choice(np.flatnonzero(lit), 40, replace=False)
    bad_cap = read_any(small_set / "scenes" / "colorchecker.tif")
    bad_cap.image.reshape(3, -1)[:, bad] += 3000.0
    hurt = Reconstructor(bundle).reconstruct_capture(bad_cap).cube
    masked = CalibrationBundle(**{**bundle.__dict__, "extras": {
        **bundle.extras, "defect_pixels": np.unique(np.concatenate(
            [bad + dy * Ws + dx for dy in (-1, 0, 1) for dx in (-1, 0, 1)]))}})
    bad_cap2 = read_any(small_set / "scenes" / "colorchecker.tif")
    bad_cap2.image.reshape(3, -1)[:, bad] += 3000.0
    fixed = Reconstructor(masked).reconstruct_capture(bad_cap2).cube
    ok = torch.isfinite(ref) & torch.isfinite(hurt) & torch.isfinite(fixed)
    err_hurt = float((hurt - ref)[ok].abs().max())
    err_fixed = float((fixed - ref)[ok].abs().max())
    assert err_hurt > 0.2  # the corrupt samples wreck some spectra
    assert err_fixed < 0.2 * err_hurt  # dropped, they cannot


def test_tensor_paths_apply_the_bundles_corrections(small_set: Path, device):
    """reconstruct_frame and HSIReconstructor repeat the bundle's veil subtraction and defect
    mask as reconstruct_capture does; without them the veil and the hot pixels bias the cube."""
    bundle = bundle_from_truth(small_set)
    clean = read_any(small_set / "scenes" / "colorchecker.tif")
    ref = Reconstructor(bundle, device=device).reconstruct_capture(clean).cube
    img = clean.image.clone()
    dark = (img.sum(0) < 0.01 * img.sum(0).max()).reshape(-1).cpu().numpy()
    lit = (img.sum(0) > 0.2 * img.sum(0).max()).reshape(-1).cpu().numpy()
    bad = np.random.default_rng(1).choice(np.flatnonzero(lit), 30, replace=False)
    Ws = img.shape[-1]
    bad_hood = np.unique(np.concatenate([bad + dy * Ws + dx for dy in (-1, 0, 1)
                                         for dx in (-1, 0, 1)]))
    img += 40.0  # a flat veil of stray light
    img.reshape(3, -1)[:, bad] += 3000.0  # hot pixels
    sat = torch.zeros(img.shape, dtype=torch.bool)
    fixed_bundle = CalibrationBundle(**{
        **bundle.__dict__, "settings": {**bundle.settings, "stray_light": "subtract"}, "extras": {
        **bundle.extras, "unreached_index": np.flatnonzero(dark), "defect_pixels": bad_hood}})
    rec = Reconstructor(fixed_bundle, device=device)
    by_capture = rec.reconstruct_capture(LinearCapture(image=img.clone(), saturated=sat.clone(),
                                                       metadata={}, path=Path("v.tif")))
    by_frame = rec.reconstruct_frame(img, sat)
    raw = rec.reconstruct_frame(img, sat, bundle_corrections=False)
    assert by_frame.stats["defect_pixels"] == bad_hood.size
    assert by_frame.stats["stray_light_veil_dn"] == pytest.approx([40.0] * 3, abs=2.0)
    assert "defect_pixels" not in raw.stats
    torch.testing.assert_close(by_frame.cube, by_capture.cube, equal_nan=True)
    module = HSIReconstructor.from_bundle(fixed_bundle, device=device)
    cube_m, valid_m = module(img.unsqueeze(0).to(device), sat.unsqueeze(0).to(device))
    ok = torch.isfinite(ref) & torch.isfinite(by_frame.cube) & torch.isfinite(raw.cube)
    assert bool(valid_m[0][ok.all(0)].all())
    torch.testing.assert_close(cube_m[0][ok], by_frame.cube[ok], rtol=1e-4, atol=1e-4)
    err_raw = float((raw.cube - ref)[ok].abs().max())
    err_fixed = float((by_frame.cube - ref)[ok].abs().max())
    assert err_raw > 0.2
    assert err_fixed < 0.2 * err_raw


@pytest.fixture(scope="module")
def mm_run(small_set: Path, tmp_path_factory) -> tuple[Path, list[str], dict]:
    """The experiment on the small set: the stray-light, drift and all-together rows with
    their remedies (one run shared by the tests below)."""
    out = tmp_path_factory.mktemp("mmrun") / "mm"
    args = ["experiment", "mismatch", "--out", str(out), "--set", f"ideal_captures={small_set}",
            "--set", "effects=[stray_light,drift,all]"]
    assert main(args) == 0
    return out, args, json.loads((out / "mismatch.json").read_text())


def _cc(data: dict, row: str, variant: str, key: str = "means_db") -> float:
    return data[row][variant]["colorchecker"][key]


@pytest.mark.slow
def test_mismatch_experiment_rows_remedy_and_cache(mm_run, small_set: Path, monkeypatch):
    out, args, data = mm_run
    assert list(data) == ["ideal", "stray_light", "drift", "all"]
    md = (out / "mismatch.md").read_text()
    assert md.count("\n") == 6 and "veil subtracted" in md
    cc = lambda row, variant: _cc(data, row, variant)  # noqa: E731
    lost = cc("ideal", "calibrated") - cc("stray_light", "calibrated")
    lost_after = cc("ideal", "calibrated") - cc("stray_light", "remedy")
    assert lost > 1.0 and lost_after < lost - 0.5  # the veil costs, subtracting it wins back
    assert abs(cc("ideal", "remedy") - cc("ideal", "calibrated")) < 0.2  # harmless when ideal
    assert data["ideal"]["remedy"]["applied"] == {
        "stray_light": True, "defects": True, "refine_registration": True, "white_mismatch": {}}
    assert cc("ideal", "calibrated") - cc("drift", "calibrated") > 3.0
    # the shipped defaults: nothing switched on for the ideal device (its calibration is the
    # calibrated column's, not done twice), the veil measured and subtracted (the remedy's own
    # calibration, reused), the drift corrected; each within 1 dB of the ideal device
    rows = out / "rows"
    assert (rows / "ideal" / "calib_defaults.npz").is_file()
    assert not (rows / "ideal" / "calib.npz").exists()
    assert not (rows / "stray_light" / "calib_stray_light.npz").exists()
    assert cc("stray_light", "defaults") == cc("stray_light", "remedy")
    assert data["ideal"]["defaults"]["applied"]["stray_light"] is False
    assert data["stray_light"]["defaults"]["applied"]["stray_light"] is True
    assert data["drift"]["defaults"]["drift"]["colorchecker"]["corrected"] is True
    for row in ("stray_light", "drift"):
        assert cc("ideal", "calibrated") - cc(row, "defaults") < 1.0, row
    lines = {line.split(" | ")[0].strip("| "): line for line in md.splitlines()[2:]}
    assert "veil subtracted" in lines["stray_light"]
    assert "drift corrected (colorchecker)" in lines["drift"]
    # the scene under A with a D65 white: not correctable, but said (measured ratio 7.4)
    assert "illuminant warning (colorchecker" in lines["all"]
    # a scene-only effect: the ideal calibration frames linked, its scenes rendered anew
    drift = out / "rows" / "drift" / "captures"
    assert os.path.samefile(drift / "white" / "white_00.tif", small_set / "white" / "white_00.tif")
    assert not os.path.samefile(drift / "scenes" / "colorchecker.tif",
                                small_set / "scenes" / "colorchecker.tif")
    assert not (out / "rows" / "drift" / "calib.npz").exists()
    assert json.loads((drift / "ground_truth" / "truth.json").read_text())["mismatch"] == {
        "drift_shift_px": [2.0, 0.0], "drift_rotation_deg": 0.05}
    assert json.loads((small_set / "ground_truth" / "truth.json").read_text())["mismatch"] == {}
    # a rerun reuses every row: nothing is simulated, calibrated or reconstructed again
    import hsi_torch.experiments.mismatch as mm

    def refuse(*a, **k):
        raise AssertionError("recomputed a cached row")

    for name in ("simulate_capture_set", "calibrate_capture_set", "rerender_after_calibration",
                 "score_captures"):
        monkeypatch.setattr(mm, name, refuse)
    assert main(args) == 0
    assert json.loads((out / "mismatch.json").read_text()) == data


@pytest.mark.slow
def test_mismatch_drift_remedy_refines_the_registration(mm_run):
    """The drift row's remedy: the same bundle, each scene's drift measured and corrected."""
    out, _, data = mm_run
    rem, cal = data["drift"]["remedy"], data["drift"]["calibrated"]
    assert data["drift"]["remedy_name"] == "registration refined from the scene"
    assert rem["applied"] == {"stray_light": False, "defects": False,
                              "refine_registration": True, "white_mismatch": {}}
    assert rem["drift"]["colorchecker"]["corrected"] is True
    assert cal["drift"]["colorchecker"]["corrected"] is False
    # the fitted motion is the simulated one (2 px, 0.05°): measured 2.00 px, 0.050°
    assert rem["drift"]["colorchecker"]["sensor_shift_px"] == pytest.approx([2.0, 0.0], abs=0.1)
    assert rem["drift"]["colorchecker"]["sensor_rotation_deg"] == pytest.approx(0.05, abs=0.02)
    assert not list((out / "rows" / "drift").glob("calib*.npz"))  # no calibration of its own
    for key, lost_min in (("means_db", 3.0), ("pixel_db", 6.0)):
        ideal = _cc(data, "ideal", "calibrated", key)
        lost = ideal - _cc(data, "drift", "calibrated", key)
        lost_after = ideal - _cc(data, "drift", "remedy", key)
        # measured (this float32 set): CC means 8.4 → 0.3 dB, per pixel 13.2 → 0.4 dB (the
        # noise realisations alone move a row by up to 0.5 dB)
        assert lost > lost_min and lost_after < 1.0 and lost_after < lost - 3.0, key


@pytest.mark.slow
def test_mismatch_all_row_takes_every_remedy(mm_run):
    """The all-together row's remedy: the white reference re-shot under the scene's light,
    calibrated with the veil subtracted and the defects masked, reconstructed with the
    registration refined."""
    out, _, data = mm_run
    rem = data["all"]["remedy"]
    assert data["all"]["remedy_name"] == ("veil subtracted + defects masked + white under the "
                                          "scene's light + registration refined from the scene")
    assert rem["applied"] == {"stray_light": True, "defects": True,
                              "refine_registration": True,
                              "white_mismatch": {"scene_illuminant": "A"}}
    assert rem["drift"]["colorchecker"]["corrected"] is True
    b = CalibrationBundle.load(out / "rows" / "all" / "calib_white_stray_light_defects.npz")
    assert b.settings["stray_light"] == "subtract" and b.extras["unreached_index"].size > 1000
    assert b.extras["defect_pixels"].size > 0  # the simulated hot pixels, found and masked
    white = out / "rows" / "all" / "captures_white"
    truth = json.loads((white / "ground_truth" / "truth.json").read_text())
    assert truth["white_mismatch"] == {"scene_illuminant": "A"}
    assert truth["mismatch"]["drift_shift_px"] == [2.0, 0.0]  # the scenes: the row's own
    assert os.path.samefile(white / "scenes" / "colorchecker.tif",
                            out / "rows" / "all" / "captures" / "scenes" / "colorchecker.tif")
    ideal = _cc(data, "ideal", "calibrated")
    # measured (this float32 set): 20.6 dB lost, −0.9 dB with every remedy
    assert ideal - _cc(data, "all", "calibrated") > 15.0
    assert ideal - _cc(data, "all", "remedy") < 1.0
    assert "registration refined" in (out / "mismatch.md").read_text().splitlines()[-1]


def test_an_interrupted_capture_set_is_not_taken_for_a_finished_one(tmp_path: Path):
    from hsi_torch.experiments.mismatch import _complete

    d = tmp_path / "rows" / "x" / "captures"

    def broken(folder: Path) -> None:
        folder.mkdir(parents=True)
        (folder / "manifest.json").write_text("{}")  # linked first, as a re-render does
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        _complete(d, broken)
    assert not d.exists()

    def works(folder: Path) -> None:
        folder.mkdir(parents=True)
        (folder / "manifest.json").write_text("{}")
        (folder / "scenes").mkdir()

    _complete(d, works)  # the partial folder of the interrupted try is replaced
    assert (d / "scenes").is_dir() and not d.with_name("captures.partial").exists()


def test_all_but_one_rows_keys_and_remedies():
    from hsi_torch.experiments.mismatch import (
        REMEDIES,
        MismatchConfig,
        remedy_name,
        remedy_parts,
        row_keys,
    )
    from hsi_torch.simulate.mismatch import DOCUMENTED_EFFECTS

    every = row_keys("all")
    assert set(every) == {k for keys in DOCUMENTED_EFFECTS.values() for k in keys}
    for effect, keys in DOCUMENTED_EFFECTS.items():
        rest = row_keys(f"all-{effect}")
        assert set(rest) == set(every) - set(keys) and set(keys) <= set(every)
    assert remedy_parts("all") == ("stray_light", "defects", "white", "refine")
    assert remedy_parts("all-monochromator") == remedy_parts("all")  # it has no remedy
    assert remedy_parts("all-drift") == ("stray_light", "defects", "white")
    assert remedy_parts("all-scene_illuminant") == ("stray_light", "defects", "refine")
    assert remedy_parts("distortion") == () and remedy_name("distortion") is None
    assert remedy_name("all") == REMEDIES["all"] and "registration refined" in REMEDIES["drift"]
    MismatchConfig(effects=["all-monochromator", "drift"])
    with pytest.raises(ValueError, match="all-nope"):
        MismatchConfig(effects=["all-nope"])


def test_a_white_shot_otherwise_is_re_shot(tmp_path: Path, monkeypatch):
    """A row's re-shot white references are reused only when their record says they were
    shot with the effects the row's remedy asks for (an older run's set, shot otherwise, is
    re-shot and the bundles calibrated from it dropped); a remedy whose scores do not show its
    parts raises before anything is kept."""
    import hsi_torch.experiments.mismatch as mm

    calls = []

    def fake_rerender(sim, caps, out, **kw):
        calls.append(kw)
        (out / "ground_truth").mkdir(parents=True)
        (out / "manifest.json").write_text("{}")
        (out / "ground_truth" / "truth.json").write_text(json.dumps(
            {"white_mismatch": mm.white_mismatch_of(sim.mismatch)}))

    monkeypatch.setattr(mm, "rerender_after_calibration", fake_rerender)
    cfg = mm.MismatchConfig(effects=["all"])
    row = tmp_path / "rows" / "all"
    old = row / "captures_white"
    (old / "ground_truth").mkdir(parents=True)
    (old / "manifest.json").write_text("{}")
    (old / "ground_truth" / "truth.json").write_text(json.dumps(
        {"white_mismatch": {"scene_illuminant": "A", "drift_shift_px": [2.0, 0.0]}}))
    (row / "calib_white_stray_light_defects.npz").write_bytes(b"stale")
    got = mm._white_captures(cfg, tmp_path, "all", tmp_path / "caps")
    assert got == old and len(calls) == 1 and calls[0]["whites"] and not calls[0]["scenes"]
    assert not (row / "calib_white_stray_light_defects.npz").exists()
    truth = json.loads((old / "ground_truth" / "truth.json").read_text())
    assert truth["white_mismatch"] == {"scene_illuminant": "A"}  # not drifted, not warmed
    mm._white_captures(cfg, tmp_path, "all", tmp_path / "caps")
    assert len(calls) == 1  # shot as asked: reused

    r = mm._Row(tmp_path, "all")
    with pytest.raises(RuntimeError, match="remedy applied"):
        mm._score_variant(r, "remedy", lambda: {"applied": {"stray_light": True}},
                          ("stray_light", "defects"))
    assert "remedy" not in r.scores and not (row / "scores.json").exists()
