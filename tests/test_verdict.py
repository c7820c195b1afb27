"""Every cube carries its verdict: the checks' findings reach the result, Python warnings and the
run's lines; a result the data contradicts is refused (no cube, the frame failed, exit 1).

On the tiny 4-view bundle of ``test_pipeline`` (recording the black and white levels a
calibration records: 512 and 16383 DN) and a capture rendered from it: the capture as an 8-bit sRGB
PNG, ``--strict``, the warning classes. The foreign camera's RAW and the ``nn.Module``'s pedestal
guard need the simulated small prototype: ``tests/test_drift.py``.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
from test_pipeline import make_bundle, render_capture, true_spectra

from hsi_torch.cli import main
from hsi_torch.findings import CaptureWarning, FitWarning, HSIWarning, RefusedError
from hsi_torch.recon.pipeline import Reconstructor


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> dict[str, Path]:
    """The bundle, a capture with its 512 DN black level (NPY, float: the bundle's black level
    applies) and the same capture as an 8-bit sRGB PNG (/ its maximum, gamma 1/2.2)."""
    root = tmp_path_factory.mktemp("verdict")
    b = make_bundle(black_level_rgb=[512.0] * 3, white_level_dn=16383.0, white_exposure_s=0.01,
                    cfa_pattern="RGGB")  # fmt: skip
    b.save(root / "calib.npz")
    img = render_capture(b, true_spectra()).numpy()
    np.save(root / "cap.npy", (img + 512).astype(np.float32))
    srgb = np.clip(img / img.max(), 0, 1) ** (1 / 2.2)
    png = root / "srgb.png"
    assert cv2.imwrite(str(png), (srgb.transpose(1, 2, 0)[:, :, ::-1] * 255).round()
                       .astype(np.uint8))  # fmt: skip
    return {"bundle": root / "calib.npz", "capture": root / "cap.npy", "png": png}


def _run(tiny: dict[str, Path], out: Path, *args: str, inp: str = "capture") -> int:
    return main(["reconstruct", "--bundle", str(tiny["bundle"]), "--out", str(out),
                 "--no-progress", "--set", "formats=[npz]", "--set", "preview=false",
                 "--set", "drift_check=false", *args, str(tiny[inp])])  # fmt: skip


def test_an_srgb_png_of_a_capture_is_refused(tiny, tmp_path, capsys):
    """Formerly warnings, a cube and exit 0: the bundle's black level (512 DN) subtracted from
    8-bit values leaves nothing, and the fit residual (1.0) refuses the frame."""
    assert _run(tiny, tmp_path / "out", inp="png") == 1
    err = capsys.readouterr().err
    assert "FAILED" in err and "RefusedError" in err and "srgb.png" in err
    assert "error [fit.residual]" in err and "fit_residual_limit=0.5" in err
    assert not list((tmp_path / "out").glob("srgb*"))  # no cube
    # the Python API: the same refusal, every finding attached
    with pytest.raises(RefusedError) as exc:
        Reconstructor(tiny["bundle"]).reconstruct_file(tiny["png"])
    codes = {f.code: f for f in exc.value.findings}
    assert codes["fit.residual"].severity == "error" and codes["fit.residual"].measured > 0.9
    assert codes["capture.data_scale"].severity == "warning"
    assert codes["capture.data_scale"].measured == 255.0
    assert codes["capture.data_scale"].limit == 16383.0
    # the limit is a setting: off, the frame passes with its warnings
    with pytest.warns(HSIWarning):
        res = Reconstructor(tiny["bundle"], fit_residual_limit=None).reconstruct_file(tiny["png"])
    assert ("fit.residual", "warning") in [(f.code, f.severity) for f in res.findings]


def test_strict_turns_a_warning_into_a_failed_frame(tiny, tmp_path, capsys):
    assert _run(tiny, tmp_path / "a") == 0
    said = capsys.readouterr()
    assert "WARNING" in said.err and "[capture.exposure_unknown]" in said.err
    assert "cap.npy: black level 512 DN from the calibration bundle" in said.out  # a note
    assert "[capture.black_level_from_bundle]" in said.out
    assert (tmp_path / "a" / "cap.npz").is_file()
    assert _run(tiny, tmp_path / "b", "--strict") == 1
    err = capsys.readouterr().err
    assert "FAILED" in err and "RefusedError" in err and "error [capture.exposure_unknown]" in err
    assert not (tmp_path / "b" / "cap.npz").exists()
    # the same as a setting; nothing left to escalate once the exposure and scale are given
    fixed = ("--set", "exposure_s=0.01", "--set", "white_level=16383")
    assert _run(tiny, tmp_path / "c", "--set", "strict=true", *fixed) == 0
    assert (tmp_path / "c" / "cap.npz").is_file()


def test_a_warning_reaches_python_as_its_class_and_the_result(tiny):
    rec = Reconstructor(tiny["bundle"], fit_residual_warning=1e-6, exposure_s=0.01,
                        white_level=16383, drift_check=False)  # fmt: skip
    with pytest.warns(FitWarning) as said:
        res = rec.reconstruct_file(tiny["capture"])
    (w,) = [w for w in said if isinstance(w.message, HSIWarning)]
    assert w.message.finding.code == "fit.residual" and w.message.finding.limit == 1e-6
    assert w.filename == __file__  # points at the caller
    assert [(f.code, f.severity) for f in res.findings] == [
        ("capture.black_level_from_bundle", "info"),
        ("fit.residual", "warning"),
    ]
    assert res.findings[1].source == str(tiny["capture"])
    with pytest.warns(CaptureWarning, match="exposure unknown"):  # another area, its class
        Reconstructor(tiny["bundle"], white_level=16383,
                      drift_check=False).reconstruct_file(tiny["capture"])  # fmt: skip
    # the default limits and a complete capture: no warning
    with warnings.catch_warnings():
        warnings.simplefilter("error", HSIWarning)
        res = Reconstructor(tiny["bundle"], exposure_s=0.01, white_level=16383,
                            drift_check=False).reconstruct_file(tiny["capture"])  # fmt: skip
    assert [f.severity for f in res.findings] == ["info"]


def test_frame_findings_codes_and_limits():
    """The table of docs/bad_inputs.md: each statistic gives its code and severity."""
    from hsi_torch.recon.checks import frame_findings
    from hsi_torch.recon.drift import drift_finding
    from hsi_torch.recon.settings import ReconstructSettings

    s = ReconstructSettings()
    ped = {"pedestal_dn": [50.0, 2.0, 2.0], "pedestal_limit_dn": [40.0, 40.0, 40.0],
           "black_level_rgb": [512.0] * 3, "black_level_source": "file"}  # fmt: skip
    (f,) = frame_findings(ped, s, "a.tif")
    assert (f.code, f.severity, f.measured, f.limit, f.source) == (
        "capture.pedestal",
        "warning",
        50.0,
        40.0,
        "a.tif",
    )
    assert "black_level=562" in f.fix
    (f,) = frame_findings({**ped, "pedestal_dn": [-501.0, 2.0, 2.0]}, s)
    assert f.severity == "error"
    (f,) = frame_findings(
        {**ped, "pedestal_dn": [-501.0, 2.0, 2.0]}, s.replace(pedestal_refuse_factor=None)
    )
    assert f.severity == "warning"
    drift = {
        "refused": "drift not measurable: 1 of 9 views with texture agree",
        "agreeing_views": 1,
        "min_views": 4,
        "textured_views": 9,
    }
    (f,) = frame_findings({"drift": drift, "fit_residual": 0.05}, s)
    assert (f.code, f.severity) == ("drift.unmeasurable", "warning")
    codes = [(f.code, f.severity) for f in frame_findings({"drift": drift, "fit_residual": 0.3},
                                                          s)]  # fmt: skip
    assert codes == [("fit.residual", "warning"), ("drift.unmeasurable", "error")]
    moved = {
        "sensor_motion_px": 2.1,
        "sensor_shift_px": [2.0, 0.0],
        "measured_views": 9,
        "textured_views": 9,
        "refused": None,
    }
    (f,) = frame_findings({"drift": moved}, s)
    assert (f.code, f.severity, f.measured, f.limit) == ("drift.moved", "warning", 2.1, 0.5)
    (f,) = frame_findings({"drift": {**moved, "corrected": True}}, s)
    assert (f.code, f.severity) == ("drift.corrected", "info")
    # the finding the front door stored when it measured the drift is the one the cube gets
    # (not made again), under the source judged; a stored "nothing to say" stays nothing
    said = drift_finding(moved, "auto", 1.0, "frame 3").to_dict()  # made with drift_warn_px=1
    (f,) = frame_findings({"drift": {**moved, "finding": said}}, s, "a.tif")
    assert f.to_dict() == {**said, "source": "a.tif"} and f.limit == 1.0
    assert frame_findings({"drift": {**moved, "finding": None}}, s) == []
    (f,) = frame_findings({"black_level_source": "bundle", "black_level": 512.0}, s)
    assert (f.code, f.severity) == ("capture.black_level_from_bundle", "info")
    many = {"radiometric_scale": "relative", "exposure_note": "exposure unknown",
            "camera_mismatch": ["make: A vs B"], "mosaic_note": "rgb", "data_scale_note": "x",
            "saturated_observations": 5, "observations": 100}  # fmt: skip
    got = [(f.code, f.severity) for f in frame_findings(many, s)]
    assert got == [
        ("capture.saturated", "info"),
        ("capture.exposure_unknown", "warning"),
        ("capture.data_scale", "warning"),
        ("capture.rgb_for_mosaic", "warning"),
        ("capture.camera_mismatch", "warning"),
    ]
    strict = [(f.code, f.severity) for f in frame_findings(many, s.replace(strict=True))]
    assert strict == [(c, "info" if v == "info" else "error") for c, v in got]
