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
import torch
from test_pipeline import make_bundle, render_capture, true_spectra

from hsi_torch.cli import main
from hsi_torch.errors import (
    ConfigError,
    FileFormatError,
    HSIError,
    InputError,
    MissingFileError,
    NoValidPixelsError,
)
from hsi_torch.io import atomic, read_any, read_capture, write_capture
from hsi_torch.recon.module import HSIReconstructor
from hsi_torch.recon.solvers import solve_nnls


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


# ---------------------------------------------------------------------------------------------
# 2. HSIReconstructor.load_state_dict


def _doubled_gain(bundle):
    b = make_bundle()
    b.gain = 2.0 * bundle.gain
    return b


def test_load_state_dict_rebuilds_the_derived_tensors():
    b1 = make_bundle()
    b2 = _doubled_gain(b1)
    x = render_capture(b1, true_spectra())[None]
    m1 = HSIReconstructor.from_bundle(b1, beta=0.0, dtype=torch.float64)
    m2 = HSIReconstructor.from_bundle(b2, beta=0.0, dtype=torch.float64)
    before = m1(x).cube
    m1.load_state_dict(m2.state_dict())
    after = m1(x).cube
    # doubled gain → A doubled → the (β = 0) spectra halve; equal to a module built from it
    v = m1(x).valid[0]
    torch.testing.assert_close(after[0][:, v], before[0][:, v] / 2, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(after, m2(x).cube, equal_nan=True, rtol=0, atol=0)
    for name in ("A", "gram", "gram_inv", "sample_grid"):
        assert torch.equal(getattr(m1, name), getattr(m2, name)), name


def test_load_state_dict_of_another_geometry_leaves_the_module_untouched():
    b1 = make_bundle()
    m1 = HSIReconstructor.from_bundle(b1, beta=1.0, dtype=torch.float64)
    x = render_capture(b1, true_spectra())[None]
    ref = m1(x).cube
    state = {k: v.clone() for k, v in m1.state_dict().items() if isinstance(v, torch.Tensor)}
    derived = {n: b.clone() for n, b in m1.named_buffers()}
    other = HSIReconstructor.from_bundle(make_bundle(t=16), beta=1.0, dtype=torch.float64)
    with pytest.raises(InputError, match="another geometry") as info:
        m1.load_state_dict(other.state_dict())
    assert "(4, 8, 16, 16)" in str(info.value) and "(4, 8, 20, 20)" in str(info.value)
    for k, v in m1.state_dict().items():
        if isinstance(v, torch.Tensor):
            assert torch.equal(v, state[k]), k  # nothing half-loaded
    assert m1.state_dict()["_extra_state"]["reference_bbox"] == [0, 0, 20, 20]
    for n, b in m1.named_buffers():
        assert torch.equal(b, derived[n]), n
    torch.testing.assert_close(m1(x).cube, ref, equal_nan=True, rtol=0, atol=0)
    # a state dict with a key missing is refused as a whole, too
    partial = dict(other.state_dict())
    sd = {k: v for k, v in m1.state_dict().items() if k != "gain"}
    with pytest.raises(RuntimeError, match="gain"):
        m1.load_state_dict(sd)
    assert partial  # (kept alive for the comparison above)
    torch.testing.assert_close(m1(x).cube, ref, equal_nan=True, rtol=0, atol=0)


# ---------------------------------------------------------------------------------------------
# 3. a frame with nothing usable


def test_no_valid_pixel_from_the_api():
    from hsi_torch.recon.pipeline import Reconstructor

    b = make_bundle()
    rec = Reconstructor(b, beta=0.0, dtype=torch.float64)
    img = render_capture(b, true_spectra())
    res = rec.reconstruct_frame(img, torch.ones_like(img, dtype=torch.bool))
    assert res.stats["num_valid"] == 0 and res.stats["usable_observations"] == 0
    assert "saturated" in res.stats["no_valid_reason"]
    assert rec.reconstruct_frame(img).stats["no_valid_reason"] is None


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


@pytest.mark.parametrize("scale", [float("nan"), float("inf"), -1.0, 0.0])
def test_module_refuses_a_non_finite_or_non_positive_exposure_scale(scale):
    b = make_bundle()
    mod = HSIReconstructor.from_bundle(b, beta=1.0)
    x = render_capture(b, true_spectra()).float()[None]
    with pytest.raises(InputError, match="exposure_scale"):
        mod(x, exposure_scale=scale)
    with pytest.raises(InputError, match="exposure_scale"):
        mod(x, exposure_scale=torch.tensor([scale]))
    with pytest.raises(InputError, match="exposure_scale"):
        mod(x, exposure_scale=torch.ones(3))  # 3 factors for a batch of 1


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


def test_capture_exposure_that_is_not_a_number_names_the_file(tmp_path):
    from hsi_torch.recon.pipeline import Reconstructor

    b = make_bundle(white_exposure_s=0.01)
    p = write_capture(tmp_path / "c.tif", np.zeros((3, 40, 40), np.uint16), {"exposure_s": "x"})
    with pytest.raises(FileFormatError, match=r"c\.tif.*exposure_s"):
        Reconstructor(b, beta=0.0).reconstruct_file(p)


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


def test_solve_nnls_with_zero_pixels():
    for A in (torch.rand(0, 6, 4, dtype=torch.float64), torch.rand(6, 4, dtype=torch.float64)):
        for mask in (None, torch.ones(0, 6, dtype=torch.bool)):
            res = solve_nnls(A, torch.zeros(0, 6, dtype=torch.float64), beta=1.0, mask=mask)
            assert res.x.shape == (0, 4) and res.converged.shape == (0,)
            assert res.no_data.shape == (0,) and res.kkt_residual.shape == (0,)


def test_module_with_an_empty_batch():
    b = make_bundle(cfa_pattern="RGGB")
    mod = HSIReconstructor.from_bundle(b, beta=1.0)
    cube, valid = mod(torch.zeros(0, 3, 40, 40))
    assert cube.shape == (0, 8, 20, 20) and valid.shape == (0, 20, 20)
    cube, valid = mod(torch.zeros(0, 1, 40, 40))  # Bayer
    assert cube.shape == (0, 8, 20, 20)


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
