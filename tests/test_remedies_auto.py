"""The remedies switched on by what the data shows: the veil of stray light (calibrate
``stray_light: auto``), hot and dead pixels (``defects: auto``), the sensor drift
(``refine_registration: auto``) and the scene-illuminant check, each decision a finding."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from test_mismatch_experiment import TRI, H, W, _lit_frame
from test_pipeline import make_bundle, render_capture, true_spectra

import hsi_torch.recon.pipeline as recon_pipeline
from hsi_torch.calibrate.config import CalibrateConfig
from hsi_torch.calibrate.pipeline import sensor_corrections
from hsi_torch.calibrate.remedies import VEIL_THRESHOLD
from hsi_torch.config import ConfigError, load_config
from hsi_torch.experiments.mismatch import decisions
from hsi_torch.findings import CalibrationWarning, Finding, warn_findings
from hsi_torch.io.radiometry import outside_views_index
from hsi_torch.recon import Reconstructor
from hsi_torch.recon.drift import DriftError, DriftEstimate, drift_decision, drift_finding
from hsi_torch.recon.illuminant import ILLUMINANT_RATIO_LIMIT, illuminant_finding
from hsi_torch.recon.settings import ReconstructSettings
from hsi_torch.resources import shipped_config
from hsi_torch.simulate.mismatch import stray_light_veil

# ------------------------------------------------------------------------------ calibration


class _Reader:
    """What :func:`sensor_corrections` reads of the calibration's reader: the mean white, the
    dark frames' per-pixel mean, the sensor size; it records the veil index it is given."""

    def __init__(self, white: torch.Tensor, dark: torch.Tensor | None) -> None:
        self._white, self.dark_pixels = white, dark
        self.size = (H, W)
        self._recording = True
        self.veil_index = None

    def read_mean(self, files: list) -> tuple[torch.Tensor, None, dict]:
        assert files == ["w.tif"] and not self._recording  # a pre-read
        return self._white, None, {}


class _Set:
    white = ["w.tif"]


def _decide(white: torch.Tensor, dark: torch.Tensor | None = None, **cfg) -> tuple[dict, _Reader]:
    reader = _Reader(white, dark)
    notes: list[str] = []
    out = sensor_corrections(_Set(), reader, outside_views_index(TRI, (H, W)),
                             CalibrateConfig(**cfg), notes)  # fmt: skip
    return out, reader


def _white(veil: float = 0.0, seed: int = 5) -> torch.Tensor:
    """The one-view white (textured, 500-1500 DN) plus a glare veil of ``veil`` of its mean and
    1 DN of noise everywhere."""
    img = _lit_frame("cpu", torch.float64)
    if veil:
        img = stray_light_veil(img, veil, 0.5, ((W - 1) / 2, (H - 1) / 2))
    g = torch.Generator().manual_seed(seed)
    return img + torch.randn(img.shape, generator=g, dtype=torch.float64)


def test_shipped_calibration_decides_by_the_data():
    cfg = load_config(shipped_config("calibrate"), CalibrateConfig)
    assert cfg.stray_light == "auto" and cfg.defects == "auto"
    assert cfg.stray_light_threshold == VEIL_THRESHOLD
    for bad in ("stray_light_threshold=1.5", "defect_min_pixels=0", "stray_light=maybe"):
        with pytest.raises((ConfigError, ValueError), match=bad.split("=")[0]):
            load_config(shipped_config("calibrate"), CalibrateConfig, [bad])


def test_a_veil_above_the_threshold_is_subtracted_with_a_finding():
    out, reader = _decide(_white(veil=0.02))
    f = Finding.from_dict(out["findings"][0].to_dict())
    assert f.code == "calibration.stray_light" and f.severity == "info"
    # the veil's level is measured (2 % of the white's mean by construction) against the limit
    assert f.measured == pytest.approx(0.02, rel=0.15) and f.limit == VEIL_THRESHOLD
    assert "subtracted" in f.message
    assert out["settings"]["stray_light"] == "subtract"
    assert reader.veil_index is not None and reader.veil_index.size >= 64
    np.testing.assert_array_equal(out["extras"]["unreached_index"], reader.veil_index)


def test_no_veil_no_subtraction_and_an_info_finding():
    out, reader = _decide(_white(veil=0.0))
    f = out["findings"][0]
    assert f.code == "calibration.stray_light" and f.severity == "info"
    assert f.measured < VEIL_THRESHOLD / 5 and "not subtracted" in f.message
    assert "stray_light" not in out["settings"] and "unreached_index" not in out["extras"]
    assert reader.veil_index is None
    # subtract: subtracted all the same; none with a veil: a warning naming the fix
    out, reader = _decide(_white(veil=0.0), stray_light="subtract")
    assert out["settings"]["stray_light"] == "subtract" and reader.veil_index is not None
    out, reader = _decide(_white(veil=0.02), stray_light="none")
    f = out["findings"][0]
    assert f.severity == "warning" and "stray_light=auto" in f.fix and reader.veil_index is None
    with pytest.warns(CalibrationWarning, match="not subtracted"):
        warn_findings([f])


def test_an_unmeasurable_veil_is_said():
    lit = torch.full((3, H, W), 800.0, dtype=torch.float64)  # light everywhere: nothing unreached
    out, reader = _decide(lit)
    f = out["findings"][0]
    assert f.code == "calibration.stray_light_unmeasured" and f.severity == "info"  # auto
    assert f.measured < f.limit and reader.veil_index is None
    out, reader = _decide(lit, stray_light="subtract")  # asked for: a warning
    assert out["findings"][0].severity == "warning" and reader.veil_index is None


def test_defects_present_are_masked_absent_are_not():
    white = _white()
    dark = torch.randn(3, H, W, generator=torch.Generator().manual_seed(6), dtype=torch.float64)
    out, _ = _decide(white, dark)
    f = out["findings"][1]
    assert f.code == "calibration.defects" and f.measured == 0 and f.severity == "info"
    assert "defect_pixels" not in out["extras"] and "defects" not in out["settings"]
    # one hot pixel in the dark, one dead pixel in the lit view
    dark[1, 10, 100] += 200.0
    inside = np.argwhere(_lit_frame("cpu", torch.float64)[0].numpy() > 0)
    y, x = inside[len(inside) // 2]
    white[:, y, x] = 0.0
    out, _ = _decide(white, dark)
    f = out["findings"][1]
    assert f.measured == 2 and f.severity == "info" and "masked" in f.message
    pix = out["extras"]["defect_pixels"]
    assert 10 * W + 100 in pix and y * W + x in pix and pix.size == 18  # with the 3 x 3
    assert out["settings"]["defects"]["raw_pixels"] == 2
    out, _ = _decide(white, dark, defects="none")
    assert out["findings"][1].severity == "warning" and "defect_pixels" not in out["extras"]


# ------------------------------------------------------------------------------ drift


def _estimate(
    refusal: str | None = None, textured: bool = True, shift: tuple[float, float] = (2.0, 0.0)
) -> DriftEstimate:
    status = ["reference"] + (["agrees"] * 5 if textured else ["no_texture"] * 5)
    return DriftEstimate(
        view_shift_px=np.zeros((6, 2)),
        correlation=np.ones(6),
        sensor_shift_px=np.array(shift) if textured else None,
        sensor_rotation_deg=0.05 if textured else None,
        residual_px=np.zeros(6),
        max_view_shift_px=4.0,
        view_status=np.array(status, object),
        refusal=refusal,
    )


def test_drift_decision_rules():
    ok, bad = _estimate(), _estimate(refusal="drift not measurable: 1 of 5 views agree")

    def said(est, motion, refine, corrected, **fit):
        d = {**est.to_dict(), "sensor_motion_px": motion, "corrected": corrected}
        return drift_finding(d, refine, 0.5, "a.tif", **fit)

    # auto: a reliable drift above the warning level is corrected
    assert drift_decision(ok, 2.3, "auto", 0.5, "a.tif")
    f = said(ok, 2.3, "auto", True)
    assert f.code == "drift.corrected" and f.severity == "info"
    assert f.measured == 2.3 and f.limit == 0.5 and f.source == "a.tif"
    # ... below it, measured and left
    assert not drift_decision(ok, 0.3, "auto", 0.5)
    assert said(ok, 0.3, "auto", False).code == "drift.below_warning"
    # ... not measurable: refused, never corrected, and a warning says so (an error when the
    # fit residual is above its warning too)
    assert not drift_decision(bad, 2.3, "auto", 0.5)
    f = said(bad, 2.3, "auto", False)
    assert f.code == "drift.unmeasurable" and f.severity == "warning"
    assert "not measurable" in f.message and "recalibrate" in f.fix
    f = said(bad, 2.3, "auto", False, fit_residual=0.3, fit_warning=0.15)
    assert f.severity == "error" and "neither the bundle nor a drift" in f.message
    # ... a flat field: nothing to measure (a warning only when the correction was asked for)
    flat = _estimate(textured=False)
    assert not drift_decision(flat, 0.0, "auto", 0.5)
    assert said(flat, 0.0, "auto", False).severity == "info"
    assert said(flat, 0.0, True, False).severity == "warning"
    assert said(flat, 0.0, True, False).code == "drift.no_texture"
    # true: whatever is measured; not measurable refuses the frame with its error finding
    assert drift_decision(ok, 0.3, True, 0.5)
    with pytest.raises(DriftError, match="b.tif: refine_registration: drift not measurable") as e:
        drift_decision(bad, 2.3, True, 0.5, "b.tif")
    assert [(f.code, f.severity) for f in e.value.findings] == [("drift.unmeasurable", "error")]
    # false: never corrected; the check still says the sensor moved
    assert not drift_decision(ok, 2.3, False, 0.5)
    f = said(ok, 2.3, False, False)
    assert f.code == "drift.moved" and f.severity == "warning" and "refine_registration" in f.fix


def test_refine_registration_auto_is_the_default_and_validated():
    s = ReconstructSettings()
    assert s.registration.refine == "auto"
    assert ReconstructSettings.from_flat(refine_registration=True).registration.refine is True
    with pytest.raises((ConfigError, ValueError), match="refine_registration"):
        ReconstructSettings.from_flat(refine_registration="sometimes")


@pytest.mark.parametrize("est, motion, corrected, code", [
    (_estimate(), 2.3, True, "drift.corrected"),
    (_estimate(refusal="drift not measurable: 1 of 5 views agree"), 2.3, False,
     "drift.unmeasurable"),
])  # fmt: skip
def test_reconstruction_applies_the_drift_decision(monkeypatch, est, motion, corrected, code):
    """The frame's decision reaches the sensing and the cube's statistics (the estimate is
    given: what is measured is tested in test_drift)."""
    bundle = make_bundle()
    img = render_capture(bundle, true_spectra()).to(torch.float32)
    monkeypatch.setattr(recon_pipeline, "estimate_drift", lambda *a, **k: est)
    monkeypatch.setattr(recon_pipeline, "drift_motion_px", lambda *a, **k: motion)
    seen = []
    real = recon_pipeline.corrected_sensing
    monkeypatch.setattr(
        recon_pipeline,
        "corrected_sensing",
        lambda sens, t, r: seen.append((list(t), r)) or real(sens, t, r),
    )
    res = Reconstructor(bundle).reconstruct_frame(img)
    d = res.stats["drift"]
    assert d["corrected"] is corrected and d["refine_registration"] == "auto"
    assert d["finding"]["code"] == code
    assert seen == ([([2.0, 0.0], 0.05)] if corrected else [])
    if not corrected:  # the cube is the uncorrected one (the frame is kept)
        assert torch.isfinite(res.cube[:, res.valid]).all()


# ------------------------------------------------------------------------------ illuminant


def _scene(light: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A grey-and-colour scene: a white card (reflectance 0.9) on 5 % of the pixels, the rest
    coloured (0.1-0.6), times ``light`` (the scene's light over the white's), 25 bands."""
    wl = torch.linspace(430, 670, 25, dtype=torch.float64)
    g = torch.Generator().manual_seed(2)
    cube = 0.1 + 0.5 * torch.rand(25, 40, 40, generator=g, dtype=torch.float64)
    cube[:, :2, :] = 0.9
    return cube * light.view(-1, 1, 1), torch.ones(40, 40, dtype=torch.bool), wl


def test_scene_lit_otherwise_than_the_white_is_a_finding():
    wl = torch.linspace(430, 670, 25, dtype=torch.float64)
    same = _scene(torch.ones(25))
    f = illuminant_finding(*same)
    assert f.code == "capture.illuminant" and f.severity == "info"
    assert f.measured == pytest.approx(1.0, abs=0.05) and f.limit == ILLUMINANT_RATIO_LIMIT
    # a tungsten-like light over a daylight white: ~6x redder at 650 nm than at 450 nm
    tungsten = torch.exp(math.log(6.0) * (wl - 430) / 240)
    f = illuminant_finding(*_scene(tungsten), source="s.tif")
    assert f.severity == "warning" and f.measured > ILLUMINANT_RATIO_LIMIT
    assert "redder" in f.message and "white reference" in f.fix and f.source == "s.tif"
    f = illuminant_finding(*_scene(1 / tungsten))
    assert f.severity == "warning" and "bluer" in f.message
    cube, valid, wl = same
    assert illuminant_finding(cube, torch.zeros_like(valid), wl) is None  # nothing valid
    with pytest.raises(ValueError, match="cube"):
        illuminant_finding(cube[0], valid, wl)


def test_mismatch_table_names_what_the_defaults_decided():
    fs = [Finding("calibration.stray_light", "info", "veil …; above the threshold: subtracted "
                  "from every lit frame", 0.02, 0.002).to_dict(),
          Finding("calibration.defects", "info", "13 found; 117 pixels masked with their "
                  "demosaic neighbours", 13, 1).to_dict(),
          {**Finding("drift.corrected", "info", "corrected").to_dict(), "source": "cave"},
          {**Finding("capture.illuminant", "warning", "redder", 5.9, 3.0).to_dict(),
           "source": "colorchecker"},
          Finding("drift.below_warning", "info", "left").to_dict()]  # fmt: skip
    assert decisions(fs) == (
        "veil subtracted; 13 defects masked; drift corrected (cave); "
        "illuminant warning (colorchecker: ratio 5.9)"
    )
    assert decisions([]) == "—"


def test_calibration_report_prints_and_stores_the_findings(tmp_path: Path):
    from hsi_torch.calibrate.pipeline import CalibrationReport
    from hsi_torch.calibrate.validity import ValidRegionSummary

    f = Finding("calibration.stray_light", "info", "veil 2 %: subtracted", 0.02, 0.002)
    valid = ValidRegionSummary(0, 3, (0, 0, 0, 0), 0, 0.0, 0, 0.0)
    rep = CalibrationReport("caps", {}, [], valid, [], [], 0, [[1.0]], [1.0], 1.0, None, "none",
                            None, findings=[f.to_dict()])  # fmt: skip
    assert "finding: info [calibration.stray_light] veil 2 %: subtracted" in str(rep)
    assert rep.to_dict()["findings"][0]["measured"] == 0.02
