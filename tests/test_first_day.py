"""A new lab's first-day slips: camera names as people write them, error messages that name the
key at fault, help texts that list everything, no stray warnings."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch

from hsi_torch import cli, refdata
from hsi_torch.errors import MissingFileError
from hsi_torch.experiments.cli_entry import EXPERIMENTS
from hsi_torch.resources import real_data_dir

CAMERAS = real_data_dir("camera_sensitivities")


@pytest.mark.parametrize("argv", [["--help"], ["experiment", "--help"]])
def test_experiment_help_lists_every_registered_experiment(capsys, argv):
    try:
        assert cli.main(argv) == 0
    except SystemExit as exc:  # argparse's own exit for --help
        assert exc.code == 0
    text = " ".join(capsys.readouterr().out.split())  # argparse wraps lines
    for name in EXPERIMENTS:
        assert name in text, (name, text)


@pytest.mark.parametrize("name", ["canon eos 5d mark ii", "CANON_EOS_5D_MARK_II",
                                  "Canon-EOS-5D-Mark-II", "nikon 5100 (npl)"])
def test_camera_names_match_without_regard_to_case(name):
    canonical = {"c": "Canon EOS 5D Mark II", "n": "Nikon 5100 (NPL)"}[name[0].lower()]
    got = refdata.camera_sensitivities(name, [450.0, 550.0, 650.0])
    want = refdata.camera_sensitivities(canonical, [450.0, 550.0, 650.0])
    torch.testing.assert_close(got, want)
    assert refdata.resolve_camera(name).lower() == canonical.lower()


@pytest.mark.real_data
@pytest.mark.skipif(CAMERAS is None, reason="real-data folder (camera_sensitivities) absent")
def test_real_data_cameras_by_name():
    assert "Nikon D850" in refdata.list_cameras()
    path = refdata.resolve_camera("nikon d850")
    assert path.endswith("Nikon_D850_380_780_5.json")
    torch.testing.assert_close(refdata.camera_sensitivities("NIKON D850", [550.0]),
                               refdata.camera_sensitivities(path, [550.0]))
    # the built-in measurement of a camera wins over a real-data file of the same camera
    assert refdata.resolve_camera("canon eos 5d mark ii") == "Canon EOS 5D Mark II"


def test_missing_camera_file_names_file_and_key(tmp_path, capsys):
    missing = tmp_path / "my_camera.json"
    with pytest.raises(MissingFileError, match="my_camera.json"):
        refdata.camera_sensitivities(missing, [550.0])
    code = cli.main(["simulate", "--out", str(tmp_path / "sim"), "--set",
                     f"camera_sensitivity={missing}"])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 1
    assert "camera_sensitivity" in err and "my_camera.json" in err and "Errno" not in err


def test_unknown_camera_lists_the_names():
    with pytest.raises(ValueError, match="Canon EOS 5D Mark II"):
        refdata.camera_sensitivities("Nikon D9000", [550.0])


def test_synthetic_with_one_seed_warns_nothing(tmp_path):
    r = subprocess.run(
        [sys.executable, "-W", "error::UserWarning", "-m", "hsi_torch", "experiment", "synthetic",
         "--out", str(tmp_path / "s"), "--set", "num_seeds=1", "--set", "noise_sigmas=[1]",
         "--set", "betas=[100, 1000]", "--set", "designs=[{kind: three_camera, name: 3Camera}]",
         "--set", "reference=3Camera"],
        capture_output=True, text=True, timeout=300, cwd=tmp_path,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert "UserWarning" not in r.stderr
