"""End to end: ``hsi-torch simulate`` (default prototype) → ``hsi-torch calibrate`` → scores against
the simulator's truth, plus the bad-input errors (nothing written on failure)."""

from __future__ import annotations

import json
import shutil
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pytest
import tifffile
import torch

from hsi_torch.calibrate.cli_entry import output_paths
from hsi_torch.cli import main
from hsi_torch.experiments.calibration_scores import (
    format_scores,
    score_against_truth,
    targets_met,
)
from hsi_torch.io.bundle import CalibrationBundle, file_sha256
from hsi_torch.io.capture_set import read_capture_set, wavelength_from_name


@pytest.fixture(scope="module")
def sim(small_sim: Path) -> Path:
    """The default small capture set (shipped simulate.yaml, realistic noise), rendered in
    float32 (the simulator's documented fast setting) to keep the test short: the session's
    shared, read-only set (calibration reads no scene capture)."""
    return small_sim


@pytest.fixture(scope="module")
def calibrated(small_sim_calib: Path) -> Path:
    """``calibrate --out DIR`` (the shipped calibrate.yaml) of ``sim``: the session's shared,
    read-only run; returns ``DIR/calib.npz``."""
    return small_sim_calib / "calib.npz"


def test_targets_on_default_simulated_set(sim: Path, calibrated: Path):
    s = score_against_truth(calibrated, sim)
    print(format_scores(s))
    assert s["B_rel_rms"] < 0.02  # RMS(B - B_true) / RMS(B_true) over the common valid region
    assert min(s["phi_corr"]) > 0.99
    assert s["gain_max_rel_rms"] < 0.02  # after the same (g, phi) gauge on both sides
    assert s["homography_worst_rms_px"] < 0.3  # against the true mapping, reference px
    # the grid shots are flat-fielded by the mean white shot before detection: without it the
    # views' transmittance fringes bias the blob centres (0.13 px worst view here, 0.49 px at
    # full size); with it 0.03 px at both sizes
    assert s["homography_worst_rms_px"] < 0.08
    assert s["valid_iou"] > 0.95
    assert targets_met(s) == {"B": True, "phi": True, "gain": True, "homography": True}


def test_cli_outputs_settings_and_provenance(sim: Path, calibrated: Path):
    b = CalibrationBundle.load(calibrated)
    bundle_path, report_path, cfg_path = output_paths(calibrated.parent)
    assert bundle_path == calibrated and report_path.is_file() and cfg_path.is_file()
    assert sorted(p.name for p in calibrated.parent.iterdir()) == [
        "calib.npz", "calib.report.json", "calib_diagnostics.png", "resolved_config.yaml"]
    manifest = json.loads((sim / "manifest.json").read_text())
    s = b.settings
    assert s["cfa_pattern"] == manifest["cfa_pattern"] == "RGGB"
    assert s["white_exposure_s"] == pytest.approx(manifest["exposure"])
    assert s["beta_phi"] == 1e-2 and s["gamma_h"] == 1e-2 and s["beta_phi_effective"] > 1e3
    assert s["detector"]["pattern_size"] == [4, 5] and s["detector"]["blob"]["min_area"] == 5.0
    h = b.provenance["inputs_sha256"]
    assert h["scan/scan_550nm.tif"] == file_sha256(sim / "scan" / "scan_550nm.tif")
    assert h["nominal_layout.json"] == file_sha256(sim / "nominal_layout.json")
    assert len(h) == 25 + 3 + 3 + 1 + 2  # scan, white, grid, dark, layout, mask
    rep = json.loads(report_path.read_text())
    assert len(rep["registration"]) == 10
    for r in rep["registration"][1:]:  # every view found in >= 2 poses, nearly all inliers
        assert r["images_with_detections"] >= 2 and r["inliers"] >= 0.9 * r["points_used"]
        assert r["rms_px"] < 0.3
    assert rep["valid"]["num_valid"] == int(b.valid.sum())
    # the bundle's phi/gain reproduce the white shots' level through the forward model
    assert np.all(b.gain[b.view_mask] > 0.5) and np.all(b.gain[b.view_mask] < 1.5)


def test_diagnostics_figure_and_registration_residuals(calibrated: Path):
    """The figure is a PNG of a readable size; the residual vectors stored in the bundle give
    back, per view, the inlier count and RMS of the registration report."""
    import cv2

    img = cv2.imread(str(calibrated.with_name("calib_diagnostics.png")))
    assert img is not None and img.shape[0] >= 500 and img.shape[1] >= 1000
    res = CalibrationBundle.load(calibrated).extras["registration_residuals"]
    rep = json.loads(calibrated.with_name("calib.report.json").read_text())
    for r in rep["registration"][1:]:
        rows = res[res[:, 0] == r["view"]]
        inl = rows[:, 5] > 0.5
        assert len(rows) == r["points_used"] and int(inl.sum()) == r["inliers"]
        rms = np.sqrt(np.mean(np.sum(rows[inl, 3:5] ** 2, axis=1)))
        assert rms == pytest.approx(r["rms_px"], rel=1e-9)
    assert not np.any(res[:, 0] == 0)  # the reference view has no residual (identity)


def test_reconstruct_refuses_bundle_of_other_geometry(calibrated: Path):
    from hsi_torch.recon import Reconstructor

    rec = Reconstructor(calibrated, beta=1e3)
    with pytest.raises(ValueError, match="384x400"):
        rec.reconstruct_frame(torch.zeros(3, 192, 200))
    with pytest.raises(ValueError, match="does not match the calibration"):
        CalibrationBundle.load(calibrated).check_compatible((3, 192, 200))


def _copy_set(sim: Path, dst: Path) -> Path:
    """A modifiable copy of the capture set: JSON/PNG copied, capture folders linked (the
    manifest opts in to files outside its folder, since the links lead there)."""
    dst.mkdir(parents=True, exist_ok=True)
    for name in ("scan", "white", "grid", "dark", "scenes", "ground_truth"):
        (dst / name).symlink_to(sim / name, target_is_directory=True)
    for name in ("manifest.json", "nominal_layout.json", "brf_free_mask.png"):
        shutil.copy(sim / name, dst / name)
    m = json.loads((dst / "manifest.json").read_text())
    m["allow_files_outside"] = True  # the linked folders lead out of the copy: opted in
    (dst / "manifest.json").write_text(json.dumps(m))
    return dst


def _calibrate_fails(captures: Path, tmp_path: Path, capsys, *extra: str) -> str:
    out = tmp_path / "out" / "bad.npz"
    rc = main(["calibrate", "--captures", str(captures), "--out", str(out),
               "--set", "progress=false", *extra])  # fmt: skip
    assert rc == 1
    assert not out.exists() and not out.with_name("bad.report.json").exists()
    assert not output_paths(out)[2].exists() and not (out.parent / "resolved_config.yaml").exists()
    return capsys.readouterr().err


def test_missing_wavelengths(sim: Path, tmp_path: Path, capsys):
    d = _copy_set(sim, tmp_path / "set")
    m = json.loads((d / "manifest.json").read_text())
    m["captures"] = [c for c in m["captures"] if c.get("wavelength_nm") not in (550.0, 600.0)]
    (d / "manifest.json").write_text(json.dumps(m))
    err = _calibrate_fails(d, tmp_path, capsys)
    assert "missing wavelengths [550.0, 600.0]" in err


def test_scan_without_brf_free_patch(sim: Path, tmp_path: Path, capsys):
    d = _copy_set(sim, tmp_path / "set")
    (d / "brf_free_mask.png").unlink()
    lay = json.loads((d / "nominal_layout.json").read_text())
    lay.pop("brf_free_patch")
    (d / "nominal_layout.json").write_text(json.dumps(lay))
    err = _calibrate_fails(d, tmp_path, capsys)
    assert "no BRF-free patch" in err


def test_empty_and_misplaced_brf_free_mask(sim: Path, tmp_path: Path, capsys):
    import cv2

    d = _copy_set(sim, tmp_path / "set")
    lay = json.loads((d / "nominal_layout.json").read_text())
    cv2.imwrite(str(d / "brf_free_mask.png"), np.zeros(tuple(lay["sensor_size"]), np.uint8))
    assert "selects no pixels" in _calibrate_fails(d, tmp_path, capsys)
    # a patch of the same size in the filtered centre of the reference view: B ratio ~ 1 there
    x0, y0, w, h = lay["reference_bbox"]
    tri = np.asarray(lay["triangles_px"][0])
    cx, cy = tri.mean(0)
    m = np.zeros(tuple(lay["sensor_size"]), np.uint8)
    m[int(cy) : int(cy) + 10, int(cx) - 5 : int(cx) + 5] = 255
    cv2.imwrite(str(d / "brf_free_mask.png"), m)
    lay["brf_free_patch"].pop("polygon_px")  # the disk itself is no longer known
    (d / "nominal_layout.json").write_text(json.dumps(lay))
    assert "does not mark a BRF-free patch" in _calibrate_fails(d, tmp_path, capsys)


def test_grid_found_in_no_image(sim: Path, tmp_path: Path, capsys):
    d = _copy_set(sim, tmp_path / "set")
    m = json.loads((d / "manifest.json").read_text())
    # a flat white re-shot as each grid (a copy of the white, its last pixel changed: one file in
    # two roles, or a byte copy of it, is refused before the grid search)
    # (written into a folder of the copy's own: its grid/ is a link to the shared set)
    src = d / "white" / "white_00.tif"
    (d / "flat_grids").mkdir()
    for i, c in enumerate(c for c in m["captures"] if c["type"] == "grid"):
        c["file"] = f"flat_grids/flat_{i}.tif"
        shutil.copy(src, d / c["file"])
        with tifffile.TiffFile(d / c["file"]) as tf:  # the pixel data's place in the file
            page = tf.pages[0]
            offset = page.dataoffsets[-1] + page.databytecounts[-1] - 1
        with open(d / c["file"], "r+b") as f:  # its last byte changed: a distinct re-shot
            f.seek(offset)
            last = f.read(1)[0]
            f.seek(offset)
            f.write(bytes([(last + 1 + i) % 256]))
    (d / "manifest.json").write_text(json.dumps(m))
    err = _calibrate_fails(d, tmp_path, capsys)
    assert "circle grid (4, 5) found in none" in err and "reference view 0" in err
    # a wrong pattern size is reported the same way
    err = _calibrate_fails(sim, tmp_path, capsys, "--set", "registration.pattern_size=[4,11]")
    assert "circle grid (4, 11)" in err


def test_captures_of_another_geometry(sim: Path, tmp_path: Path, capsys):
    d = _copy_set(sim, tmp_path / "set")
    lay = json.loads((d / "nominal_layout.json").read_text())
    lay["sensor_size"] = [400, 384]
    (d / "nominal_layout.json").write_text(json.dumps(lay))
    err = _calibrate_fails(d, tmp_path, capsys, "--set", f"brf_free_mask={sim}/brf_free_mask.png")
    assert "does not match" in err


def test_plain_folders_without_manifest(sim: Path, calibrated: Path, tmp_path: Path):
    """A real-device layout: scan/ white/ grid/ dark/ folders, wavelengths from the file names
    (or the TIFF metadata): same bundle as with the manifest."""
    d = _copy_set(sim, tmp_path / "set")
    (d / "manifest.json").unlink()
    cs = read_capture_set(d)
    assert cs.manifest is None and len(cs.scan) == 25 and len(cs.white) == 3
    assert sorted(w for _, w in cs.scan) == [430.0 + 10 * k for k in range(25)]
    assert wavelength_from_name("mono_552p5nm.dng") == 552.5
    assert wavelength_from_name("scan_7.tif") is None
    out = tmp_path / "plain.npz"
    assert main(["calibrate", "--captures", str(d), "--out", str(out),
                 "--set", "progress=false"]) == 0  # fmt: skip
    a, b = CalibrationBundle.load(out), CalibrationBundle.load(calibrated)
    np.testing.assert_array_equal(a.view_homographies, b.view_homographies)
    np.testing.assert_array_equal(a.B, b.B)
    np.testing.assert_array_equal(a.valid, b.valid)


def test_cli_oracle_bundle_is_the_truth(sim: Path, tmp_path):
    """``calibrate --oracle`` writes the ground truth as a bundle: it scores perfectly against the
    truth it came from, and the calibrated bundle scores worse (what calibration costs)."""
    out = tmp_path / "oracle.npz"
    assert main(["calibrate", "--oracle", "--captures", str(sim), "--out", str(out)]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["oracle.npz", "oracle_diagnostics.png"]
    b = CalibrationBundle.load(out)
    assert b.settings["oracle"] is True
    s = score_against_truth(out, sim)
    assert s["B_rel_rms"] == 0 and s["gain_max_rel_rms"] < 1e-6 and s["valid_iou"] == 1
    assert min(s["phi_corr"]) > 1 - 1e-12 and s["homography_worst_rms_px"] < 1e-6
    # not a simulated set: a one-line error naming the missing truth, nothing written
    with pytest.raises(FileNotFoundError, match="ground truth"):
        import argparse

        from hsi_torch.calibrate.cli_entry import run_calibrate

        run_calibrate(argparse.Namespace(captures=tmp_path, out=tmp_path / "x", oracle=True))
    assert not (tmp_path / "x").exists()


def _saturate_whites(sim: Path, dst: Path, which: Sequence[int]) -> Path:
    """A copy of the set whose white shots ``which`` are overexposed: every sample at the white
    level (the other shots copied as they are)."""
    from hsi_torch.io import read_capture, write_capture

    d = _copy_set(sim, dst)
    (d / "white").unlink()
    (d / "white").mkdir()
    for i, f in enumerate(sorted((sim / "white").iterdir())):
        if i in which:
            img, meta = read_capture(f)
            write_capture(d / "white" / f.name, torch.full_like(img, meta["white_level"]), meta)
        else:
            shutil.copy(f, d / "white" / f.name)
    return d


def test_one_saturated_white_shot_is_dropped_with_a_warning(sim: Path, calibrated: Path,
                                                            tmp_path: Path, capsys):
    d = _saturate_whites(sim, tmp_path / "set", which=[1])
    out = tmp_path / "sat.npz"
    assert main(["calibrate", "--captures", str(d), "--out", str(out),
                 "--set", "progress=false"]) == 0  # fmt: skip
    cap = capsys.readouterr()
    warn = [ln for ln in cap.err.splitlines() if "warning" in ln]
    assert len(warn) == 1 and "white_01.tif" in warn[0] and "saturated" in warn[0]
    assert "dropped" in warn[0] and "100.0 %" in warn[0]
    assert "white_01.tif dropped" in cap.out  # also in the report's notes
    a, b = CalibrationBundle.load(out), CalibrationBundle.load(calibrated)
    # the other two shots give the same calibration, up to their own noise (they also flat-field
    # the grid shots, so a few edge pixels of the valid region may differ)
    assert int((a.valid != b.valid).sum()) <= 0.001 * a.valid.size
    assert np.corrcoef(a.phi.ravel(), b.phi.ravel())[0, 1] > 0.999
    m = a.view_mask
    assert np.abs(a.gain[m] / b.gain[m] - 1).max() < 0.02


def test_all_white_shots_saturated_is_an_error_naming_them(sim: Path, tmp_path: Path, capsys):
    d = _saturate_whites(sim, tmp_path / "set", which=[0, 1, 2])
    err = _calibrate_fails(d, tmp_path, capsys)
    assert "all 3 white-reference shot(s) are saturated" in err
    for i in range(3):
        assert f"white_0{i}.tif 100.0 % saturated" in err
    assert "reduce the exposure" in err and err.count("\n") == 1
