"""Sensor drift measured from the scene itself (:mod:`hsi_torch.recon.drift`): the estimate on
known shifts (an exact whole-sensor roll and the simulator's drift), zero on an undrifted
capture, the metadata and the warning of a run, the correction's dB, the settings keys, and
the refusals (too few views agree, views that disagree, beyond the measurable range, a foreign
image). Small prototype (400 × 384 px), ColorChecker only, oracle bundle."""

from __future__ import annotations

import dataclasses
import json
import math
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

import hsi_torch.recon.drift as drift
from hsi_torch.cli import main
from hsi_torch.config import ConfigError, load_config
from hsi_torch.experiments.metrics import colorchecker_scores, erode_px
from hsi_torch.findings import DriftWarning, RefusedError
from hsi_torch.io import load_cube, read_any, read_capture
from hsi_torch.io.capture_set import read_truth
from hsi_torch.recon import Reconstructor
from hsi_torch.recon.config import ReconstructConfig
from hsi_torch.recon.drift import (
    DRIFT_AGREE_PX,
    DriftError,
    corrected_sensing,
    estimate_drift,
    motion_points,
)
from hsi_torch.recon.settings import ReconstructSettings
from hsi_torch.simulate.oracle import bundle_from_truth

_SCENES_ONLY = ["--set", "captures.scan_wavelengths_nm=[]", "--set", "captures.white_shots=0",
                "--set", "captures.grid.poses=[]", "--set", "captures.dark_frames=0",
                "--set", "render.figures=false", "--set", "render.dtype=float32",
                "--set", "captures.scenes=[{kind: colorchecker, name: colorchecker, params: "
                             "{width_mm: 8.4, center_mm: [0.0, 1.4]}}]"]  # fmt: skip


_USAF = ("captures.scenes=[{kind: usaf, name: usaf, params: {groups: [2, 3, 4], magnification: "
         "1.0, center_mm: [0.0, 1.0]}}]")


def _simulate(out: Path, *extra: str) -> Path:
    assert main(["-q", "simulate", "--out", str(out), *_SCENES_ONLY, *extra]) == 0
    return out


@pytest.fixture(scope="module")
def sims(tmp_path_factory) -> dict[str, Path]:
    """The small prototype's ColorChecker, ideal and with a (2, 0), (12, 0) and (30, 0) px
    sensor drift, its USAF target with a (12, 0) and (30, 0) px drift, and the oracle bundle of
    the ideal device."""
    root = tmp_path_factory.mktemp("drift")
    ideal = _simulate(root / "ideal")
    drift = _simulate(root / "drift", "--set", "mismatch.drift_shift_px=[2, 0]")
    far = {f"drift{d}": _simulate(root / f"drift{d}", "--set",
                                  f"mismatch.drift_shift_px=[{d}, 0]") for d in (12, 30)}
    usaf = {f"usaf{d}": _simulate(root / f"usaf{d}", "--set", _USAF, "--set",
                                  f"mismatch.drift_shift_px=[{d}, 0]") for d in (12, 30)}
    bundle = root / "oracle.npz"
    bundle_from_truth(ideal).save(bundle)
    return {"ideal": ideal, "drift": drift, "bundle": bundle, **far, **usaf}


def _image(sim: Path) -> torch.Tensor:
    return read_any(sim / "scenes" / "colorchecker.tif").image.double()


def _means_db(sim: Path, res) -> float:
    truth, _ = read_truth(sim)
    return colorchecker_scores(res.cube.double().cpu().numpy(), res.valid.cpu().numpy(),
                               truth["colorchecker_patch_index"],
                               np.asarray(truth["colorchecker_spectra"], np.float64),
                               erode_px(truth, 0.3))["mean_psnr_db"]


@pytest.mark.parametrize("shift", [(2, 0), (0, -1), (-3, 2)])
def test_a_whole_sensor_shift_is_measured_within_a_fifth_of_a_pixel(sims, shift, device):
    """The ideal capture rolled by whole pixels is a sensor moved by exactly ``t``: the pixel
    ``p`` reads what the calibrated sensor saw at ``p + t``."""
    rec = Reconstructor(sims["bundle"], device=device, dtype=torch.float64)
    img = torch.roll(_image(sims["ideal"]), shifts=(-shift[1], -shift[0]), dims=(1, 2))
    est = estimate_drift(rec.sensing, img.to(device))
    assert est.measured_views >= 6
    np.testing.assert_allclose(est.sensor_shift_px, shift, atol=0.2)
    assert abs(est.sensor_rotation_deg) < 0.02
    # every measured view agrees with the fitted motion
    assert np.nanmax(est.residual_px) < 0.5
    # the views' measured shifts differ (mirrored views move the other way): not all alike
    d = est.view_shift_px[np.isfinite(est.view_shift_px[:, 0])]
    assert np.ptp(np.hypot(d[:, 0], d[:, 1])) > math.hypot(*shift)


def test_the_simulated_drift_is_measured_and_none_without_it(sims):
    rec = Reconstructor(sims["bundle"])
    est = estimate_drift(rec.sensing, _image(sims["drift"]).float())
    np.testing.assert_allclose(est.sensor_shift_px, (2.0, 0.0), atol=0.2)
    assert abs(est.sensor_rotation_deg) < 0.02
    assert est.max_view_shift_px > 3.0  # mirrored views: ~2 t relative to the reference
    zero = estimate_drift(rec.sensing, _image(sims["ideal"]).float())
    assert zero.measured_views >= 6
    assert np.hypot(*zero.sensor_shift_px) < 0.1 and abs(zero.sensor_rotation_deg) < 0.01


def test_a_rotation_is_measured(sims):
    """A 0.1° turn of the ideal capture about the sensor centre, by exact resampling."""
    rec = Reconstructor(sims["bundle"], dtype=torch.float64)
    img = _image(sims["ideal"])
    H, W = img.shape[-2:]
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float64),
                            torch.arange(W, dtype=torch.float64), indexing="ij")
    p = motion_points(torch.stack([xs, ys], -1), (0.5, 0.0), 0.1, ((W - 1) / 2, (H - 1) / 2))
    grid = torch.stack([2 * p[..., 0] / (W - 1) - 1, 2 * p[..., 1] / (H - 1) - 1], -1)
    moved = torch.nn.functional.grid_sample(img[None], grid[None], align_corners=True)[0]
    est = estimate_drift(rec.sensing, moved)
    assert est.sensor_rotation_deg == pytest.approx(0.1, abs=0.02)
    np.testing.assert_allclose(est.sensor_shift_px, (0.5, 0.0), atol=0.2)


def test_the_block_factor_rule():
    """2 × 2 blocks from a 320 px shorter side (the full-size frame is 744 × 858 px), none on the
    small prototype's frame."""
    assert drift._block_factor((744, 858)) == 2
    assert drift._block_factor((320, 400)) == 2
    assert drift._block_factor((319, 400)) == 1
    assert drift._block_factor((104, 120)) == 1


def test_block_images_are_the_block_means_and_measure_a_shift(sims, monkeypatch):
    """Forced onto the small frame, the ``2 × 2`` path: its view images are exactly the block
    means of the full-resolution ones, and a whole-pixel sensor shift is still measured (to
    0.2 px: the 52 × 60-block frame is coarse; at full size see docs/reconstruct.md)."""
    rec = Reconstructor(sims["bundle"], dtype=torch.float64)
    sens = rec.sensing
    img = _image(sims["ideal"])
    full = drift._view_images(sens, img, drift._static(sens))
    monkeypatch.setattr(drift, "_MIN_BLOCKS", 32)
    sens._drift_static.clear()
    # the sensing is shared (kept per bundle): its 2 × 2 part must not outlive this test
    monkeypatch.setattr(sens, "_drift_static", {})
    st = drift._static(sens)
    assert st.factor == 2 and len(st.pairs) == 9
    blocks = drift._view_images(sens, img, st)
    hf, wf = st.size
    want = full[:, :2 * hf, :2 * wf].reshape(-1, hf, 2, wf, 2).mean((2, 4))
    np.testing.assert_allclose(blocks, want, rtol=1e-5, atol=1e-3)
    est = estimate_drift(sens, torch.roll(img, shifts=(-2, 3), dims=(1, 2)))
    assert est.measured_views >= 6
    np.testing.assert_allclose(est.sensor_shift_px, (-3, 2), atol=0.2)


def test_the_per_bundle_part_is_built_once_and_shared(sims, monkeypatch):
    rec = Reconstructor(sims["bundle"])
    sens = rec.sensing
    sens._drift_static.clear()
    built = []
    orig = drift._build_static
    monkeypatch.setattr(drift, "_build_static", lambda s, k: built.append(k) or orig(s, k))
    img = _image(sims["drift"]).float()
    first = estimate_drift(sens, img)
    again = estimate_drift(sens, img)
    np.testing.assert_array_equal(first.view_shift_px, again.view_shift_px)
    # the corrected copy shares the bundle's masks and homographies, and so the static part
    estimate_drift(corrected_sensing(sens, first.sensor_shift_px, 0.0), img)
    assert len(built) == 1
    # a copy with other masks gets its own
    other = dataclasses.replace(sens, obs_mask=sens.obs_mask.clone())
    estimate_drift(other, img)
    assert len(built) == 2


def test_non_finite_samples_count_as_zero(sims):
    """NaN and inf pixels in a frame are read as 0 (and the largest float), as before."""
    rec = Reconstructor(sims["bundle"])
    img = _image(sims["drift"]).float()
    bad = img.clone()
    bad[:, 100:104, 150:160] = float("nan")
    bad[1, 200, 40] = float("inf")
    got = estimate_drift(rec.sensing, bad)
    want = estimate_drift(rec.sensing, torch.nan_to_num(bad))
    np.testing.assert_array_equal(got.view_shift_px, want.view_shift_px)
    assert got.measured_views >= 6


def test_refine_registration_recovers_the_lost_db(sims):
    ideal_res = Reconstructor(sims["bundle"]).reconstruct_file(
        sims["ideal"] / "scenes" / "colorchecker.tif")
    ideal = _means_db(sims["ideal"], ideal_res)
    drifted = Reconstructor(sims["bundle"], refine_registration=False).reconstruct_file(
        sims["drift"] / "scenes" / "colorchecker.tif")
    fixed = Reconstructor(sims["bundle"], refine_registration=True).reconstruct_file(
        sims["drift"] / "scenes" / "colorchecker.tif")
    lost, left = ideal - _means_db(sims["drift"], drifted), ideal - _means_db(sims["drift"], fixed)
    assert lost > 4.0, (ideal, lost)  # the drift costs (about 9 dB here) ...
    assert left < 0.5, (ideal, left)  # ... and the correction gets it back
    assert drifted.stats["drift"]["corrected"] is False
    assert fixed.stats["drift"]["corrected"] is True
    assert fixed.stats["drift"]["sensor_motion_px"] == pytest.approx(2.0, abs=0.2)
    # the default (auto): the reliable 2 px drift is corrected, the same cube as true; the
    # undrifted capture's measured motion is below drift_warn_px and left alone
    auto = Reconstructor(sims["bundle"]).reconstruct_file(
        sims["drift"] / "scenes" / "colorchecker.tif")
    assert auto.stats["drift"]["corrected"] is True
    assert auto.stats["drift"]["finding"]["code"] == "drift.corrected"
    torch.testing.assert_close(auto.cube, fixed.cube, equal_nan=True)
    assert ideal_res.stats["drift"]["corrected"] is False
    assert ideal_res.stats["drift"]["finding"]["code"] == "drift.below_warning"


def test_corrected_samples_off_the_sensor_are_dropped(sims):
    rec = Reconstructor(sims["bundle"])
    sens = rec.sensing
    moved = corrected_sensing(sens, (40.0, 0.0), 0.0)
    W = sens.sensor_size[1]
    x = (moved.grid()[0, ..., 0].double() + 1) * (W - 1) / 2
    inside = moved.sample_inside
    assert inside.shape == (sens.num_views, sens.num_pixels) and not bool(inside.all())
    assert bool(((x[~inside] < 0) | (x[~inside] > W - 1)).all())
    assert bool(((x[inside] >= 0) & (x[inside] <= W - 1)).all())
    # the grid is the calibrated one moved by M⁻¹ (a turn too), in px
    H = sens.sensor_size[0]
    g = sens.grid()[0].double()
    px = torch.stack([(g[..., 0] + 1) * (W - 1) / 2, (g[..., 1] + 1) * (H - 1) / 2], -1)
    want = motion_points(px, (3.0, -2.0), 0.3, ((W - 1) / 2, (H - 1) / 2), inverse=True)
    turned = corrected_sensing(sens, (3.0, -2.0), 0.3).grid()[0].double()
    got = torch.stack([(turned[..., 0] + 1) * (W - 1) / 2, (turned[..., 1] + 1) * (H - 1) / 2],
                      -1)
    torch.testing.assert_close(got, want, rtol=0, atol=1e-3)  # float32 grid
    # the original is untouched, the factorisation shared
    assert sens.sample_inside is None and moved.problem is sens.problem
    # a frame solved on it drops those observations (and re-solves the pixels concerned)
    from hsi_torch.recon.frame import reconstruct_frame
    from hsi_torch.recon.settings import ReconstructSettings

    img = _image(sims["ideal"]).float()[None]
    _, valid, infos, _, _ = reconstruct_frame(moved, img, ReconstructSettings())
    assert infos[0]["num_resolved"] > 0
    assert infos[0]["usable_observations"] < infos[0]["observations"]
    assert infos[0]["num_valid"] <= sens.num_pixels


def test_a_flat_field_measures_nothing_and_corrects_nothing(sims):
    rec = Reconstructor(sims["bundle"], refine_registration=True)
    H, W = rec.sensing.sensor_size
    res = rec.reconstruct_frame(torch.full((3, H, W), 500.0))
    d = res.stats["drift"]
    assert d["measured_views"] == 0 and d["sensor_shift_px"] is None
    assert d["corrected"] is False and d["sensor_motion_px"] == 0.0
    assert d["view_shift_px"][0] == [0.0, 0.0] and d["view_shift_px"][1] == [None, None]
    # nothing to measure is not refused, but the run says nothing was corrected
    assert d["textured_views"] == 0 and d["refused"] is None
    (said,) = [f for f in res.findings if f.code.startswith("drift.")]
    assert said.code == "drift.no_texture" and said.severity == "warning"
    assert "nothing corrected, no view has texture" in said.message


def test_run_metadata_holds_the_drift_and_warns_above_the_threshold(sims, tmp_path, capsys):
    cap = sims["drift"] / "scenes" / "colorchecker.tif"
    base = ["reconstruct", "--bundle", str(sims["bundle"]), "--no-progress", "--set",
            "formats=[npz]", "--set", "preview=false"]  # fmt: skip
    # the check alone (refine_registration=false): a warning
    checked = [*base, "--set", "refine_registration=false"]
    assert main([*checked, "--out", str(tmp_path / "a"), str(cap)]) == 0
    err = capsys.readouterr().err
    assert "WARNING" in err and "drift_warn_px=0.5" in err and "refine_registration" in err
    # how many views agree, and by how much
    assert f"9 of 9 views with texture agree within {DRIFT_AGREE_PX:g} px (spread 0." in err
    meta = load_cube(tmp_path / "a" / "colorchecker.npz").metadata
    d = meta["stats"]["drift"]
    assert d["agreeing_views"] == 9 and d["textured_views"] == 9 and d["refused"] is None
    assert 0 < d["spread_px"] <= DRIFT_AGREE_PX and d["view_status"][1:] == ["agrees"] * 9
    V = len(d["view_shift_px"])
    assert V == 10 and len(d["correlation"]) == V and len(d["residual_px"]) == V
    assert d["sensor_shift_px"][0] == pytest.approx(2.0, abs=0.2)
    assert max(math.hypot(*s) for s in d["view_shift_px"] if s[0] is not None) > 3.0
    json.dumps(meta)  # JSON-ready
    # a higher threshold: no warning; corrected: the warning says so
    assert main([*checked, "--out", str(tmp_path / "b"), "--set", "drift_warn_px=5",
                 str(cap)]) == 0
    assert "drift_warn_px" not in capsys.readouterr().err  # (the fit residual still warns)
    assert main([*base, "--out", str(tmp_path / "c"), "--set", "refine_registration=true",
                 str(cap)]) == 0
    said = capsys.readouterr()
    # corrected: a note (info, stdout), no longer a warning
    assert "[drift.corrected]" in said.out and "corrected (refine_registration)" in said.out
    assert "WARNING" not in said.err  # the corrected views explain the capture again
    assert load_cube(tmp_path / "c" / "colorchecker.npz").metadata["stats"]["drift"]["corrected"]
    # the default (auto): measured reliably above drift_warn_px, so corrected too
    assert main([*base, "--out", str(tmp_path / "f"), str(cap)]) == 0
    said = capsys.readouterr()
    assert "[drift.corrected]" in said.out and "WARNING" not in said.err
    # an undrifted capture: no warning; drift_check=false: nothing measured
    ideal = sims["ideal"] / "scenes" / "colorchecker.tif"
    assert main([*base, "--out", str(tmp_path / "d"), str(ideal)]) == 0
    assert "WARNING" not in capsys.readouterr().err
    # (refine_registration: auto measures the drift to decide: false too)
    assert main([*base, "--out", str(tmp_path / "e"), "--set", "drift_check=false",
                 "--set", "refine_registration=false", str(ideal)]) == 0
    assert "drift" not in load_cube(tmp_path / "e" / "colorchecker.npz").metadata["stats"]


@pytest.mark.parametrize("key, value", [("refine_registration", "maybe"),
                                        ("refine_registration", 1), ("drift_check", "no"),
                                        ("drift_warn_px", 0), ("drift_warn_px", -1.0),
                                        ("drift_warn_px", "far"), ("drift_min_views", 1),
                                        ("drift_min_views", "many"), ("drift_min_views", 4.5),
                                        ("drift_min_views", True)])
def test_registration_keys_are_validated_and_errors_name_them(key, value):
    with pytest.raises((ConfigError, ValueError), match=key):
        ReconstructSettings.from_flat({key: value})
    with pytest.raises((ConfigError, ValueError), match=key):
        load_config({key: value}, ReconstructConfig)


def test_registration_keys_load_and_default():
    s = ReconstructSettings()
    assert s.registration.check and s.registration.refine == "auto"
    assert s.registration.warn_px == 0.5
    assert s.registration.min_views == 4
    cfg = load_config({"refine_registration": True, "drift_warn_px": None,
                       "drift_min_views": 6}, ReconstructConfig)
    r = cfg.settings().registration
    assert r.refine and r.warn_px is None and r.min_views == 6


def test_an_integer_drift_renders_as_the_ideal_capture_moved(tmp_path):
    """The simulator's drift by whole pixels is the ideal capture moved (noise-free): what the
    full-size measurement in docs/reconstruct.md uses to make its drifted capture."""
    nf = ["--set", "sensor.shot_noise=false", "--set", "sensor.read_noise_e=0", "--set",
          "sensor.quantize=false"]  # fmt: skip
    ideal, _ = read_capture(_simulate(tmp_path / "i", *nf) / "scenes" / "colorchecker.tif")
    moved, _ = read_capture(_simulate(tmp_path / "d", *nf, "--set",
                                      "mismatch.drift_shift_px=[2, 0]") / "scenes" /
                            "colorchecker.tif")  # raw Bayer mosaics (1, H, W)
    # sensor pixel p reads what the calibrated one read at p + (2, 0) (float32 render: rounding)
    torch.testing.assert_close(moved[..., :-2], torch.roll(ideal, -2, dims=-1)[..., :-2],
                               rtol=1e-5, atol=1e-3)
    assert float((moved - ideal).abs().mean()) > 10.0


# ------------------------------------------------------------------------ refusals


def _only_views(sens, img: torch.Tensor, keep: tuple[int, ...]) -> torch.Tensor:
    """``img`` with every sensor pixel that the views ``keep`` do not sample (beyond 2 px) set
    to a flat grey: only those views have texture."""
    px = drift._grid_px(sens).round().long()  # (V, P, 2) sensor (x, y)
    H, W = img.shape[-2:]
    near = torch.zeros(H, W, dtype=torch.bool)
    for v in keep:
        x, y = px[v, :, 0].clamp(0, W - 1), px[v, :, 1].clamp(0, H - 1)
        near[y, x] = True
    near = torch.nn.functional.max_pool2d(near[None, None].float(), 5, 1, 2)[0, 0] > 0
    return torch.where(near, img, img.mean())


def _natural_texture(shape: tuple[int, int], seed: int) -> torch.Tensor:
    """``(3, H, W)`` a random natural-like (1/f amplitude) texture, 100–900 DN."""
    H, W = shape
    gen = torch.Generator().manual_seed(seed)
    f2 = torch.fft.fftfreq(H)[:, None] ** 2 + torch.fft.fftfreq(W)[None] ** 2
    phase = torch.exp(2j * math.pi * torch.rand(H, W, generator=gen, dtype=torch.float64))
    tex = torch.fft.ifft2(phase / f2.clamp(min=1e-4).sqrt()).real
    tex = (tex - tex.min()) / (tex.max() - tex.min())
    return (100 + 800 * tex)[None] * torch.tensor([1.0, 0.8, 0.6], dtype=torch.float64)[:, None,
                                                                                        None]


def test_the_measurable_range_is_the_search_window_over_the_most_sensitive_view(sims):
    """The most sensitive views move 2.01× the sensor shift relative to the reference view: the
    32 px window allows ≈ 16 px of sensor motion. On the ColorChecker (a grid of patches)
    whole-pixel rolls up to 7 px are measured within 0.1 px and agreed on; from 10 px on the
    patches match falsely or not at all, too few views agree, and it is refused (below)."""
    sens = Reconstructor(sims["bundle"], dtype=torch.float64).sensing
    img = _image(sims["ideal"])
    for shift in ((3, 0), (-5, 0), (0, 6), (5, 5), (7, 0)):
        est = estimate_drift(sens, torch.roll(img, shifts=(-shift[1], -shift[0]), dims=(1, 2)))
        assert est.refusal is None, (shift, est.refusal)
        assert est.agreeing_views >= 7 and est.orientations >= 3
        np.testing.assert_allclose(est.sensor_shift_px, shift, atol=0.1)
    assert est.range_px == pytest.approx(drift.DRIFT_MAX_VIEW_SHIFT_PX / 2.01, abs=0.05)
    for shift in ((10, 0), (0, 12), (-12, 0), (30, 0)):
        est = estimate_drift(sens, torch.roll(img, shifts=(-shift[1], -shift[0]), dims=(1, 2)))
        assert est.refusal is not None and est.agreeing_views < 4, shift


def test_a_12_px_drift_of_a_textured_scene_is_measured_and_corrected(sims):
    """The USAF target drifted 12 px (its mirrored views move 21 px): every view agrees on the
    motion, within 0.1 px, and it is corrected; drifted 30 px (beyond the window) it is
    refused."""
    rec = Reconstructor(sims["bundle"], refine_registration=True)
    res = rec.reconstruct_file(sims["usaf12"] / "scenes" / "usaf.tif")
    d = res.stats["drift"]
    assert d["corrected"] is True and d["refused"] is None
    assert d["agreeing_views"] == 9 and d["spread_px"] < 0.5
    np.testing.assert_allclose(d["sensor_shift_px"], (12.0, 0.0), atol=0.1)
    assert d["max_view_shift_px"] > drift._MARGIN_PX * 2  # beyond the former 16 px window
    with pytest.raises(DriftError, match="fewer than drift_min_views=4"):
        rec.reconstruct_file(sims["usaf30"] / "scenes" / "usaf.tif")


@pytest.mark.parametrize("far", [12, 30])
def test_a_colorchecker_drift_it_cannot_measure_is_refused_never_corrected(sims, far, tmp_path,
                                                                           capsys):
    """A 12 px or 30 px sensor drift of the ColorChecker (its patches match falsely or not at
    all): formerly fitted from one view as 30.65 / 21.33 px and "corrected"; now the
    reconstructor raises DriftError naming the views' agreement and the range, the run lists
    the frame as failed (exit 1, no cube). The check alone refuses it too (the fit residual is
    above its warning: neither the bundle nor a drift explains the capture); with that warning
    off, it warns that the drift could not be measured."""
    cap = sims[f"drift{far}"] / "scenes" / "colorchecker.tif"
    rec = Reconstructor(sims["bundle"], refine_registration=True)
    with pytest.raises(DriftError) as err:
        rec.reconstruct_file(cap)
    msg = str(err.value)
    assert str(cap) in msg and "refine_registration" in msg
    assert "views with texture agree within 1 px" in msg and "drift_min_views=4" in msg
    assert "at most ±15.9 px of sensor motion can be measured" in msg
    assert isinstance(err.value, ValueError)  # an InputError: bad input, not a crash
    # the check alone: refused, the drift not measurable and the fit residual above its warning
    with pytest.raises(RefusedError, match="neither the bundle nor a drift") as refused:
        Reconstructor(sims["bundle"]).reconstruct_file(cap)
    found = {f.code: f for f in refused.value.findings}
    assert found["drift.unmeasurable"].severity == "error"
    assert found["drift.unmeasurable"].measured < 4 and found["fit.residual"].measured > 0.15
    # without the fit residual's limits: the cube is made, its drift marked refused, a warning
    with pytest.warns(DriftWarning, match="drift not measurable"):
        res = Reconstructor(sims["bundle"], fit_residual_warning=None,
                            fit_residual_limit=None).reconstruct_file(cap)  # fmt: skip
    d = res.stats["drift"]
    assert d["refused"] and d["corrected"] is False and d["agreeing_views"] < 4
    assert d["finding"]["code"] == "drift.unmeasurable" and d["finding"]["severity"] == "warning"
    # the command line: the frame failed, named with the reason; nothing written for it
    base = ["reconstruct", "--bundle", str(sims["bundle"]), "--no-progress", "--set",
            "formats=[npz]", "--set", "preview=false"]  # fmt: skip
    out = tmp_path / "refined"
    assert main([*base, "--out", str(out), "--set", "refine_registration=true", str(cap)]) == 1
    err_text = capsys.readouterr().err
    assert "FAILED" in err_text and "DriftError" in err_text
    assert "views with texture agree" in err_text and "corrected" not in err_text.replace(
        "not corrected", "")
    assert not (out / "colorchecker.npz").exists()
    assert main([*base, "--out", str(tmp_path / "checked"), str(cap)]) == 1
    err_text = capsys.readouterr().err
    assert "FAILED" in err_text and "RefusedError" in err_text
    assert "drift not measurable" in err_text
    assert "the sensor moved since calibration" not in err_text


def test_a_single_textured_view_is_refused(sims):
    """Only view 2 (beside the reference) has texture: one view measures the shift, which
    is never enough (formerly: a motion fitted from it and corrected)."""
    sens = Reconstructor(sims["bundle"]).sensing
    img = _only_views(sens, _image(sims["drift"]).float(), (0, 2))
    est = estimate_drift(sens, img)
    assert est.textured_views == 1 and est.agreeing_views == 1
    assert "fewer than drift_min_views=4" in est.refusal
    assert "1 of 1 views with texture agree" in est.refusal
    # even with the smallest minimum
    assert estimate_drift(sens, img, min_views=2).refusal is not None
    rec = Reconstructor(sims["bundle"], refine_registration=True)
    with pytest.raises(DriftError, match="1 of 1 views with texture agree"):
        rec.reconstruct_frame(img)


def test_views_that_disagree_are_refused(sims):
    """The left half of the sensor moved 3 px right, the right half 3 px left (not a rigid
    motion): the views split into two groups of four; no more agree than disagree."""
    sens = Reconstructor(sims["bundle"]).sensing
    img = _image(sims["ideal"]).float()
    W = img.shape[-1]
    split = torch.cat([torch.roll(img, -3, dims=2)[..., :W // 2],
                       torch.roll(img, 3, dims=2)[..., W // 2:]], dim=2)
    est = estimate_drift(sens, split)
    disagree = est.view_status == "disagrees"
    assert disagree.sum() >= 3
    assert np.all(est.residual_px[disagree] > DRIFT_AGREE_PX)
    assert est.refusal is not None and "disagree by" in est.refusal
    assert est.agreeing_views <= int(disagree.sum()) or est.agreeing_views < est.min_views


@pytest.mark.parametrize("seed", [0, 1])
def test_a_foreign_image_is_refused(sims, seed):
    """A natural-like random texture over the whole sensor (no kaleidoscope views): every
    view has texture, none aligns with the reference view."""
    rec = Reconstructor(sims["bundle"], refine_registration=True)
    img = _natural_texture(rec.sensing.sensor_size, seed).float()
    est = estimate_drift(rec.sensing, img)
    assert est.textured_views == 9 and est.agreeing_views == 0 and est.sensor_shift_px is None
    with pytest.raises(DriftError, match="0 of 9 views with texture agree"):
        rec.reconstruct_frame(img)


def test_drift_min_views_is_the_threshold(sims):
    """A 9 px roll, at the edge of the range: 4 views agree (3 orientations), the motion is
    right; accepted at the default minimum of 4, refused at 5."""
    sens = Reconstructor(sims["bundle"]).sensing
    img = torch.roll(_image(sims["ideal"]).float(), shifts=-9, dims=2)
    est = estimate_drift(sens, img)
    assert est.agreeing_views == 4 and est.refusal is None
    np.testing.assert_allclose(est.sensor_shift_px, (9, 0), atol=0.1)
    assert "fewer than drift_min_views=5" in estimate_drift(sens, img, min_views=5).refusal
    rec = Reconstructor(sims["bundle"], settings=ReconstructSettings.from_flat(
        {"refine_registration": True, "drift_min_views": 5}))
    with pytest.raises(DriftError, match="drift_min_views=5"):
        rec.reconstruct_frame(img)


def test_a_foreign_cameras_raw_is_refused(sims, real_data):
    """A real camera's RAW (another camera, no kaleidoscope), its mosaic cropped to the small
    prototype's sensor: formerly "the sensor moved … up to 253 px (… from 1 views)" and
    corrected; now one view of nine agrees and the frame is refused, wherever it is cropped."""
    from hsi_torch.io.raw import load_raw

    raw = load_raw(real_data / "raw" / "RAW_KODAK_DC50.KDC")
    rec = Reconstructor(sims["bundle"], refine_registration=True)
    H, W = rec.sensing.sensor_size
    for y, x in ((0, 0), (64, 184), (128, 368)):
        crop = raw.mosaic[:, y:y + H, x:x + W]
        with pytest.raises(DriftError, match="of 9 views with texture agree") as err:
            rec.reconstruct_frame(crop, cfa_pattern=raw.cfa_pattern)
        assert "fewer than drift_min_views=4" in str(err.value)
        (f,) = err.value.findings  # a RefusedError with its finding
        assert (f.code, f.severity) == ("drift.unmeasurable", "error") and f.measured < 4
    # without refine_registration: the drift cannot be measured and the fit residual (0.25) is
    # above its warning: neither the bundle nor a drift explains the capture, refused too
    check = Reconstructor(sims["bundle"])
    with pytest.raises(RefusedError, match="neither the bundle nor a drift") as err:
        check.reconstruct_frame(raw.mosaic[:, :H, :W], cfa_pattern=raw.cfa_pattern)
    found = {f.code: f for f in err.value.findings}
    assert found["drift.unmeasurable"].severity == "error"
    assert found["fit.residual"].severity == "warning" and found["fit.residual"].measured > 0.15


def test_the_module_guards_against_a_pedestal(sims):
    """The simulator's DN with their 512 DN black level fed to the nn.Module: refused (formerly a
    cube 5.5x too bright, no warning); a pedestal a few times its limit: a CaptureWarning; DN
    above black: nothing."""
    from hsi_torch.findings import CaptureWarning, HSIWarning
    from hsi_torch.recon.checks import batch_pedestal_findings
    from hsi_torch.recon.module import HSIReconstructor

    rec = HSIReconstructor.from_bundle(sims["bundle"])
    x = _image(sims["ideal"]).float()[None]  # (1, 3, H, W) DN above black
    with warnings.catch_warnings():
        warnings.simplefilter("error", HSIWarning)
        assert bool(rec(x).valid.any())
    with pytest.raises(RefusedError, match=r"\[capture.pedestal\].*subtract the black level"):
        rec(x + 512.0)
    (f,) = batch_pedestal_findings(x + 512.0, rec.radiometry, rec.settings)
    assert f.measured > 10 * f.limit
    with pytest.warns(CaptureWarning, match="capture.pedestal"):
        rec(x + 3 * f.limit)
    with pytest.raises(RefusedError):  # strict: the warning refuses
        HSIReconstructor.from_bundle(sims["bundle"], strict=True)(x + 3 * f.limit)
