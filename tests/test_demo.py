"""``hsi-torch demo --quick``: simulate → calibrate → reconstruct → score, at a smaller sensor."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from hsi_torch.cli import main
from hsi_torch.experiments.demo import metrics_lines
from hsi_torch.experiments.demo_full import report_lines
from hsi_torch.experiments.metrics import colorchecker_scores, cube_scores
from hsi_torch.metrics import METRIC_NAMES, cube_metrics


def test_colorchecker_scores_against_formula():
    rng = np.random.default_rng(0)
    spectra = rng.uniform(0.1, 0.9, size=(24, 5))
    pidx = -np.ones((12, 48), np.int16)
    for k in range(24):
        r, c = divmod(k, 8)
        pidx[r * 4 : r * 4 + 4, c * 6 : c * 6 + 6] = k
    cube = spectra[np.maximum(pidx, 0)].transpose(2, 0, 1).copy()
    cube[:, pidx < 0] = 0.0
    cube[0, pidx == 3] += 0.1  # one band of patch 3 off by 0.1 everywhere
    valid = np.ones(pidx.shape, bool)
    s = colorchecker_scores(cube, valid, pidx, spectra, erode_px=0.0)
    assert s["patches"] == 24
    assert s["psnr_db"][3] == pytest.approx(10 * np.log10(1 / (0.1**2 / 5)))
    e, t = cube[:, pidx == 3].mean(1), spectra[3]
    ang = np.degrees(np.arccos(e @ t / np.linalg.norm(e) / np.linalg.norm(t)))
    assert s["sam_deg"][3] == pytest.approx(ang)
    assert s["psnr_db"][0] > 200 and s["sam_deg"][0] == pytest.approx(0.0, abs=1e-5)
    # eroding a 4-row patch by 2 px leaves no interior pixel
    assert colorchecker_scores(cube, valid, pidx, spectra, erode_px=2.0)["patches"] == 0
    c = cube_scores(cube, cube + 0.01, valid)
    assert c["psnr_db"] == pytest.approx(40.0)


def test_summaries_print_the_fields_metrics_of_hsi_torch_metrics():
    """A known cube: the scene scores' metrics are hsi_torch.metrics' (PSNR both conventions
    checked by hand), and both demos' summaries print all of them, per bundle."""
    rng = np.random.default_rng(0)
    truth = rng.uniform(0.05, 0.9, (6, 20, 24))
    cube = truth + rng.normal(0.0, 0.02, truth.shape)
    mask = np.ones((20, 24), bool)
    mask[:3] = False
    sc = cube_scores(cube, truth, mask)
    direct = cube_metrics(torch.from_numpy(cube), torch.from_numpy(truth), torch.from_numpy(mask))
    assert set(sc["metrics"]) == set(METRIC_NAMES)
    assert sc["metrics"] == pytest.approx(direct, rel=1e-12)
    e, t = cube[:, mask], truth[:, mask]  # (M, P)
    assert direct["psnr_db"] == pytest.approx(10 * np.log10(1 / np.mean((e - t) ** 2)))
    se_b = ((np.clip(e, 0, 1) - np.clip(t, 0, 1)) ** 2 * 255**2).mean(1)
    assert direct["psnr_bands_db"] == pytest.approx(np.mean(10 * np.log10(255**2 / se_b)))
    entry = {"calibrated": sc, "oracle": cube_scores(truth, truth + 0.01, mask)}
    lines = metrics_lines(entry)
    assert len(lines) == 3
    cal = lines[1]
    for text in (f"PSNR {direct['psnr_db']:.2f} dB",
                 f"per band 0-255: {direct['psnr_bands_db']:.2f}", f"SSIM {direct['ssim']:.4f}",
                 f"SAM {direct['sam_deg']:.2f} deg",
                 f"ERGAS {direct['ergas']:.2f}", f"RMSE {direct['rmse']:.4f}",
                 f"MRAE {direct['mrae']:.4f}"):  # fmt: skip
        assert text in cal, text
    full = report_lines({"scenes": {"known": entry}, "stages": {}, "total_s": 1.0}, Path("o"))
    assert all(line in full for line in lines)  # demo --full's summary carries the same lines


def test_demo_quick_meets_targets(tmp_path: Path, capsys):
    out = tmp_path / "demo"
    rc = main(["demo", "--out", str(out), "--quick", "--set", "progress=false", "--set",
               "cave=false"])  # fmt: skip
    assert rc == 0
    printed = capsys.readouterr().out
    assert "colorchecker: 24 patches" in printed
    # labelled a smoke run; the calibration targets (set for the demo's sensor) are not judged
    assert "[quick] a smoke run" in printed and "judged at the demo's size only" in printed
    assert " MISSED" not in printed and "(target < 2 %) ok" not in printed
    s = json.loads((out / "summary.json").read_text())
    cc = s["scenes"]["colorchecker"]
    assert cc["calibrated"]["patches"] == 24
    assert cc["calibrated"]["mean_psnr_db"] >= 30.0
    assert cc["calibrated"]["mean_sam_deg"] <= 5.0
    assert cc["oracle"]["mean_psnr_db"] >= 30.0
    # the field's metrics of every scene and bundle, in summary.json and in the printed summary
    for name, e in s["scenes"].items():
        src = e.get("per_pixel_valid", e)
        for key in ("calibrated", "oracle"):
            m = src[key]["metrics"]
            assert set(m) == set(METRIC_NAMES) and all(np.isfinite(v) for v in m.values()), name
            assert f"PSNR {m['psnr_db']:.2f} dB (per band 0-255: {m['psnr_bands_db']:.2f} dB)" \
                in printed
    syn = s["scenes"]["synthetic"]  # built-in scene when CAVE is off
    assert syn["calibrated"]["pixels"] > 500 and np.isfinite(syn["calibrated"]["psnr_db"])
    # the TV prior (calibrated bundle, default weight) beside per-pixel: better per pixel
    pv = cc["per_pixel_valid"]
    assert pv["tv"]["psnr_db"] > pv["calibrated"]["psnr_db"]
    assert pv["tv"]["median_sam_deg"] < pv["calibrated"]["median_sam_deg"]
    assert np.isfinite(cc["tv"]["mean_psnr_db"]) and np.isfinite(syn["tv"]["psnr_db"])
    assert "TV prior" in printed
    for f in ("calib.npz", "colorchecker.npz", "colorchecker.tif", "colorchecker_preview.png",
              "colorchecker_spectra.png", "synthetic_preview.png", "synthetic_spectra.png",
              "resolved_config.yaml", "calib_diagnostics.png", "colorchecker_panel.png",
              "synthetic_truth_preview.png", "synthetic_oracle_preview.png"):  # fmt: skip
        assert (out / f).is_file(), f
    import cv2

    panel = cv2.imread(str(out / "synthetic_panel.png"))
    prev = cv2.imread(str(out / "synthetic_preview.png"))
    assert prev.shape[1] >= 512 and panel.shape[1] > 3 * 360  # enlarged, three tiles
    cal = s["calibration"]
    assert cal["B_rel_rms"] < 0.03 and min(cal["phi_corr"]) > 0.99


@pytest.mark.slow
def test_demo_full_orchestration_on_the_small_prototype(tmp_path):
    """``demo --full`` (every stage its own process, measured) run on the small prototype's
    config to stay quick: the summary holds every stage's time and peak memory, the calibration
    scores, and both bundles' scores of every scene in the documented forms."""
    import json

    from hsi_torch.cli import main
    from hsi_torch.resources import shipped_config

    out = tmp_path / "full"
    assert main(["-q", "demo", "--full", "--out", str(out), "--no-progress",
                 "--set", f"simulate_config={shipped_config('simulate')}",
                 "--set", "cave=false"]) == 0  # fmt: skip
    s = json.loads((out / "summary.json").read_text())
    for stage in ("simulate", "calibrate", "oracle", "reconstruct_calibrated",
                  "reconstruct_oracle"):
        st = s["stages"][stage]
        assert st["wall_s"] > 0 and 0.05 < st["peak_rss_gib"] < 8, (stage, st)
    assert all(s["calibration_targets_met"].values())
    assert set(s["scenes"]) == {"colorchecker", "usaf", "synthetic"}
    cc = s["scenes"]["colorchecker"]
    for key in ("calibrated", "oracle"):
        assert cc[key]["mean_psnr_db"] > 30  # patch-interior means
        assert cc["per_pixel_interiors"][key]["psnr_db"] > 20
        syn = s["scenes"]["synthetic"][key]
        assert syn["bright_half"]["pixels"] >= syn["pixels"] // 2 > 0
    assert (out / "oracle" / "oracle.npz").is_file() and (out / "calib" / "calib.npz").is_file()
    assert (out / "colorchecker_panel.png").is_file() and (out / "usaf_spectra.png").is_file()
    # the scoring stage alone, on the run's outputs: the same scores as the run's summary
    from hsi_torch.experiments.demo import DemoConfig
    from hsi_torch.experiments.demo_full import score_full

    again = score_full(out, DemoConfig(simulate_config=shipped_config("simulate"), cave=False),
                       log=lambda *a: None)
    assert json.loads(json.dumps(again["scenes"], default=str)) == s["scenes"]
