"""Regressions of a bad-input campaign on the CLI and the API: nothing goes wrong without a word.

Each test reproduces one case that used to pass silently or fail with a raw error (same-stem
inputs from different folders, a module whose ``load_state_dict`` did not change its output, a
frame with no usable pixel, stale temp files, one resolved config overwritten by the next run,
non-finite settings, bad metadata, 0-byte outputs on resume, oversized image headers, empty
batches, ...); see ``docs/bad_inputs.md`` for the table of cases and what each gets.
"""

from __future__ import annotations

import os
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import tifffile
from test_pipeline import make_bundle, render_capture, true_spectra

from hsi_torch.cli import main
from hsi_torch.errors import (
    ConfigError,
    FileFormatError,
    HSIError,
    MissingFileError,
    NoValidPixelsError,
)
from hsi_torch.io import atomic, read_any, read_capture, write_capture


@pytest.fixture
def ws(tmp_path):
    bundle = make_bundle(white_exposure_s=0.01, cfa_pattern="RGGB")
    bpath = tmp_path / "calib.npz"
    bundle.save(bpath)
    caps = tmp_path / "caps"
    caps.mkdir()
    img = render_capture(bundle, true_spectra())
    np.save(caps / "a.npy", img.numpy())
    return tmp_path, bpath, caps, img


def _rec(bpath, out, *extra):
    return main(["reconstruct", "--bundle", str(bpath), "--out", str(out), "--no-progress",
                 "--set", "dtype=float64", "--set", "beta=0", *extra])  # fmt: skip


def _files(d: Path) -> list[str]:
    return sorted(p.relative_to(d).as_posix() for p in d.rglob("*") if p.is_file())


def _doubled_gain(bundle):
    b = make_bundle()
    b.gain = 2.0 * bundle.gain
    return b


# ---------------------------------------------------------------------------------------------
# 5. stale temp files of killed runs


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_atomic_write_temp_names_carry_the_writer_pid(tmp_path):
    from hsi_torch.io.atomic import atomic_write

    with atomic_write(tmp_path / "f.bin") as f:
        name = Path(f.name).name
        assert name.startswith(f".f.bin.{os.getpid()}-") and name.endswith(".tmp")
    assert atomic.clean_stale_temp_files(tmp_path) == []


# ---------------------------------------------------------------------------------------------
# 7. non-finite settings


@pytest.mark.parametrize("value", [".inf", "-.inf", ".nan", "1e999"])
def test_non_finite_beta_is_refused_before_anything_is_written(ws, capsys, value):
    tmp, bpath, caps, _ = ws
    out = tmp / "out"
    assert _rec(bpath, out, "--set", f"beta={value}", str(caps / "a.npy")) == 1
    err = capsys.readouterr().err
    assert "key 'beta'" in err and "finite" in err and err.count("\n") == 1
    assert not out.exists()


def test_non_finite_numbers_are_refused_by_every_float_key():
    from hsi_torch.config import load_config
    from hsi_torch.recon.config import ReconstructConfig

    for key in ("fit_residual_warning", "white_level", "black_level"):
        with pytest.raises(ConfigError, match=f"key '{key}'.*finite"):
            load_config({key: float("inf")}, ReconstructConfig)
    with pytest.raises(ConfigError, match="finite"):
        load_config({"black_level": [1.0, float("nan"), 2.0]}, ReconstructConfig)
    with pytest.raises(ConfigError, match="key 'beta'"):
        load_config({"beta": 10**400}, ReconstructConfig)  # was a raw OverflowError


# ---------------------------------------------------------------------------------------------
# 8. smaller ones


def test_npz_capture_with_bad_json_metadata(tmp_path):
    p = tmp_path / "c.npz"
    np.savez(p, image=np.zeros((3, 8, 8), np.uint16), metadata=np.array("{not json"))
    with pytest.raises(FileFormatError, match=r"c\.npz.*'metadata'"):
        read_capture(p)
    np.savez(p, image=np.zeros((3, 8, 8), np.uint16), metadata=np.array("[1, 2]"))
    with pytest.raises(FileFormatError, match="JSON object"):
        read_any(p)
    side = tmp_path / "d.npy"
    np.save(side, np.zeros((3, 8, 8), np.uint16))
    side.with_name("d.npy.json").write_text('"a string"')
    with pytest.raises(FileFormatError, match="JSON object"):
        read_any(side)


@pytest.mark.parametrize("key", ["black_level", "white_level"])
def test_tiff_metadata_level_that_is_not_a_number(tmp_path, key):
    p = write_capture(tmp_path / "c.tif", np.zeros((3, 8, 8), np.uint16), {key: "abc"})
    with pytest.raises(FileFormatError, match=rf"c\.tif.*{key}.*'abc'"):
        read_any(p)
    p = write_capture(tmp_path / "d.tif", np.zeros((3, 8, 8), np.uint16), {key: [1, [2, 3]]})
    with pytest.raises(FileFormatError, match=rf"d\.tif.*{key}"):
        read_any(p)


def test_bundle_path_that_is_a_folder(ws, capsys):
    tmp, _, caps, _ = ws
    assert _rec(tmp / "caps", tmp / "out", str(caps / "a.npy")) == 1
    err = capsys.readouterr().err
    assert f"calibration bundle {caps} is a folder" in err and "does not exist" not in err
    from hsi_torch.calibrate import CalibrationBundle

    with pytest.raises(FileFormatError, match="is a folder"):
        CalibrationBundle.load(caps)
    with pytest.raises(MissingFileError, match="does not exist"):
        CalibrationBundle.load(tmp / "nope.npz")


def test_simulate_failing_on_its_geometry_leaves_no_folder(tmp_path, capsys):
    out = tmp_path / "sim"
    assert main(["simulate", "--out", str(out), "--set", "geometry.pupil_distance_mm=0"]) == 1
    assert "pupil_distance_mm" in capsys.readouterr().err
    assert not out.exists()  # used to leave an empty folder
    kept = tmp_path / "kept"
    kept.mkdir()
    assert main(["simulate", "--out", str(kept), "--set", "geometry.pupil_distance_mm=0"]) == 1
    assert kept.is_dir()  # a folder that existed before is never removed


def _tiff_claiming(path: Path, height: int, width: int) -> Path:
    """A small valid TIFF whose header is then edited to claim ``height × width`` pixels."""
    write_capture(path, np.zeros((3, 8, 8), np.uint16))
    with tifffile.TiffFile(path) as tif:
        tags = tif.pages[0].tags
        offsets = {n: tags[n].valueoffset for n in ("ImageWidth", "ImageLength")}
        dtypes = {n: tags[n].dtype for n in ("ImageWidth", "ImageLength")}
    with open(path, "r+b") as f:
        for name, value in (("ImageWidth", width), ("ImageLength", height)):
            f.seek(offsets[name])
            fmt = "<H" if dtypes[name] == 3 else "<I"
            f.write(struct.pack(fmt, value))
    return path


def test_huge_tiff_header_is_refused_before_decoding(tmp_path, monkeypatch):
    p = _tiff_claiming(tmp_path / "huge.tif", 30000, 30000)
    calls = []
    real = tifffile.TiffPage.asarray

    def spy(self, *a, **k):
        calls.append(self.shape)
        return real(self, *a, **k)

    monkeypatch.setattr(tifffile.TiffPage, "asarray", spy)
    with pytest.raises(FileFormatError, match=r"huge\.tif.*\(30000, 30000\).*\(40, 40\)"):
        read_any(p, expected_size=(40, 40))
    with pytest.raises(FileFormatError, match=r"huge\.tif"):
        read_capture(p)  # no expected size: the header claims more data than the file holds
    assert calls == []


def test_huge_npy_header_is_refused_before_loading(tmp_path):
    p = tmp_path / "huge.npy"
    with open(p, "wb") as f:
        np.lib.format.write_array_header_1_0(
            f, {"descr": "<u2", "fortran_order": False, "shape": (3, 30000, 30000)})
        f.write(b"\0" * 64)
    with pytest.raises(FileFormatError, match=r"huge\.npy.*\(30000, 30000\).*\(40, 40\)"):
        read_any(p, expected_size=(40, 40))
    with pytest.raises(FileFormatError, match=r"huge\.npy"):
        read_capture(p)


def test_error_classes_keep_their_builtin_bases():
    assert issubclass(FileFormatError, ValueError) and issubclass(FileFormatError, HSIError)
    assert issubclass(MissingFileError, FileNotFoundError)
    assert issubclass(ConfigError, ValueError) and issubclass(ConfigError, HSIError)
    assert issubclass(NoValidPixelsError, ValueError)
    with pytest.raises(MissingFileError):
        read_any("/nonexistent/capture.tif")
