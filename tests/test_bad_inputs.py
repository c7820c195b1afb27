"""Regressions of a bad-input campaign on the CLI and the API: nothing goes wrong without a word.

Each test reproduces one case that used to pass silently or fail with a raw error (same-stem
inputs from different folders, a module whose ``load_state_dict`` did not change its output, a
frame with no usable pixel, stale temp files, one resolved config overwritten by the next run,
non-finite settings, bad metadata, 0-byte outputs on resume, oversized image headers, empty
batches, ...); see ``docs/bad_inputs.md`` for the table of cases and what each gets.
"""

from __future__ import annotations

import json
import os
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import tifffile
import torch
import yaml
from test_batch import run_batch
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
from hsi_torch.io import atomic, load_cube, read_any, read_capture, write_capture
from hsi_torch.io.atomic import atomic_write_text
from hsi_torch.recon.batch.targets import DONE_DIR
from hsi_torch.recon.module import HSIReconstructor
from hsi_torch.recon.nnls import solve_nnls


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
# 1. outputs keyed by the stem: an input of the same name from another folder


def test_same_stem_from_another_folder_is_refused_not_overwritten(ws, capsys):
    tmp, bpath, _, img = ws
    a, b = tmp / "A" / "x.npy", tmp / "B" / "x.npy"
    a.parent.mkdir()
    b.parent.mkdir()
    np.save(a, img.numpy())
    np.save(b, 0.5 * img.numpy())
    out = tmp / "O"
    assert _rec(bpath, out, str(a)) == 0
    first = load_cube(out / "x.npz")
    capsys.readouterr()
    assert _rec(bpath, out, str(b)) == 1  # used to overwrite O/x.* silently
    err = capsys.readouterr().err
    assert str(a) in err and str(b) in err and "1 failed" in err
    kept = load_cube(out / "x.npz")
    assert kept.metadata["source"] == os.path.abspath(a)
    torch.testing.assert_close(kept.cube, first.cube, equal_nan=True, rtol=0, atol=0)
    # the first input is still recognised as done (used to keep B's cube and skip A)
    assert _rec(bpath, out, str(a)) == 0
    assert "1 skipped" in capsys.readouterr().err
    # removing the old outputs frees the name for the other input
    for f in out.glob("x*"):
        f.unlink()
    assert _rec(bpath, out, str(b)) == 0
    assert load_cube(out / "x.npz").metadata["source"] == os.path.abspath(b)
    # both in one run: the second is refused, the first is written
    out2 = tmp / "O2"
    assert _rec(bpath, out2, str(a), str(b)) == 1
    err = capsys.readouterr().err
    assert "1 processed" in err and "1 failed" in err and str(a) in err
    assert load_cube(out2 / "x.npz").metadata["source"] == os.path.abspath(a)


def test_run_batch_refuses_outputs_claimed_by_another_input(tmp_path):
    """The ownership check is part of the files target (any ``planned_outputs`` user)."""
    a, b = tmp_path / "A" / "x.txt", tmp_path / "B" / "x.txt"
    for p, text in ((a, "from A"), (b, "from B")):
        p.parent.mkdir()
        p.write_text(text)
    out = tmp_path / "out"

    def process(p: Path) -> Path:
        return atomic_write_text(out / f"{p.stem}.out", p.read_text())

    planned = {"planned_outputs": lambda p: [out / f"{p.stem}.out"]}
    assert run_batch([a], process, out, progress=False, **planned).ok
    s = run_batch([b], process, out, progress=False, **planned)
    assert len(s.failed) == 1 and str(a) in s.failed[0].error
    assert (out / "x.out").read_text() == "from A"


def test_concurrent_runs_never_mix_the_outputs_of_one_name(ws, capsys):
    """A run writing the outputs named 'a' holds a lock; another run meanwhile fails that input
    (naming the holder) instead of interleaving its files with the first run's."""
    from hsi_torch.recon.batch.targets import _name_lock

    tmp, bpath, caps, _ = ws
    out = tmp / "out"
    out.mkdir()
    with _name_lock(out, "a"):  # as a concurrent run would while it writes a.*
        assert _rec(bpath, out, str(caps / "a.npy")) == 1
        err = capsys.readouterr().err
        assert "being written by another run" in err and f"process {os.getpid()}" in err
        assert not list(out.glob("a.*"))
    assert _rec(bpath, out, str(caps / "a.npy")) == 0  # once it is done: fine
    assert not list((out / DONE_DIR).glob("*.lock"))  # no lock file left behind


def test_claims_made_by_a_concurrent_run_are_seen(tmp_path):
    """An input of the same name that another run claimed after this run started is refused."""
    a1, a2, b = tmp_path / "A" / "y.txt", tmp_path / "A" / "x.txt", tmp_path / "B" / "x.txt"
    for p in (a1, a2, b):
        p.parent.mkdir(exist_ok=True)
        p.write_text(p.parent.name)
    out = tmp_path / "out"

    def process(p: Path) -> Path:
        if p == a1:  # meanwhile, "another run" reconstructs B/x.txt into the same folder
            assert run_batch([b], process, out, progress=False, **planned).ok
        return atomic_write_text(out / f"{p.stem}.out", p.read_text())

    planned = {"planned_outputs": lambda p: [out / f"{p.stem}.out"]}
    s = run_batch([a1, a2], process, out, progress=False, **planned)
    assert [f.input for f in s.failed] == [a2] and str(b) in s.failed[0].error
    assert (out / "x.out").read_text() == "B"


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
    for name in ("model_transmittance", "model_gain", "gram", "gram_inv", "sample_grid"):
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


def test_all_saturated_capture_is_a_failure_with_its_reason(ws, capsys):
    tmp, bpath, caps, img = ws
    np.save(caps / "white.npy", np.full(tuple(img.shape), 65535, np.uint16))
    out = tmp / "out"
    assert _rec(bpath, out, str(caps / "a.npy"), str(caps / "white.npy")) == 1
    err = capsys.readouterr().err
    assert "1 processed" in err and "1 failed" in err
    line = next(x for x in err.splitlines() if "FAILED" in x)
    assert "white.npy" in line and "no valid pixel" in line and "saturated" in line
    assert not list(out.glob("white*"))  # no all-NaN cube


def test_min_views_above_the_bundles_views_is_a_config_error(ws, capsys):
    tmp, bpath, caps, _ = ws
    out = tmp / "out"
    assert _rec(bpath, out, "--set", "min_views=100", str(caps / "a.npy")) == 1
    err = capsys.readouterr().err
    assert "min_views" in err and "4 views" in err and err.count("\n") == 1
    assert not out.exists()


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


def test_stale_temp_files_are_cleaned_at_the_start_of_a_run(ws, capsys):
    tmp, bpath, caps, _ = ws
    out = tmp / "out"
    (out / DONE_DIR).mkdir(parents=True)
    dead, alive = _dead_pid(), os.getpid()
    (out / "runs").mkdir()
    stale = [out / f".a.npz.{dead}-k3j2h1g0.tmp", out / DONE_DIR / f".a-1.json.{dead}-abc_1234.tmp",
             out / "runs" / f".20250101-000000-{dead}.yaml.{dead}-abcdefgh.tmp"]
    keep = [out / f".a.tif.{alive}-zzzzzzzz.tmp", out / "notes.tmp", out / ".x.tmp",
            out / "a.npz.tmp"]
    for f in stale + keep:
        f.write_bytes(b"partial")
    assert _rec(bpath, out, str(caps / "a.npy")) == 0
    assert not any(f.exists() for f in stale)
    assert all(f.exists() for f in keep)  # a live writer's file, and files that are not ours
    # (the count covers OUT and the marker folder; runs/ is cleaned before the run record)
    assert "removed 2 stale temporary file(s)" in capsys.readouterr().err


def test_atomic_write_new_never_replaces_and_appears_complete(tmp_path):
    (tmp_path / "a.yaml").write_text("earlier run")
    p = atomic.atomic_write_new(tmp_path, ["a.yaml", "a-2.yaml", "a-3.yaml"], b"this run")
    assert p == tmp_path / "a-2.yaml"
    assert (tmp_path / "a.yaml").read_text() == "earlier run" and p.read_bytes() == b"this run"
    with pytest.raises(FileExistsError):
        atomic.atomic_write_new(tmp_path, ["a.yaml", "a-2.yaml"], b"x")
    assert sorted(f.name for f in tmp_path.iterdir()) == ["a-2.yaml", "a.yaml"]  # no temp file


def test_atomic_write_temp_names_carry_the_writer_pid(tmp_path):
    from hsi_torch.io.atomic import atomic_write

    with atomic_write(tmp_path / "f.bin") as f:
        name = Path(f.name).name
        assert name.startswith(f".f.bin.{os.getpid()}-") and name.endswith(".tmp")
    assert atomic.clean_stale_temp_files(tmp_path) == []


# ---------------------------------------------------------------------------------------------
# 6. one resolved configuration per run


def test_every_run_keeps_its_own_resolved_config(ws, capsys):
    tmp, bpath, caps, img = ws
    np.save(caps / "b.npy", img.numpy())
    out = tmp / "out"
    assert _rec(bpath, out, "--set", "beta=0", str(caps / "a.npy")) == 0
    assert _rec(bpath, out, "--set", "beta=5", str(caps / "b.npy")) == 0
    runs = sorted((out / "runs").glob("*.yaml"))
    assert len(runs) == 2 and not (out / "resolved_config.yaml").exists()
    betas = {}
    for r in runs:
        betas[r.name] = yaml.safe_load(r.read_text())["beta"]
    assert sorted(betas.values()) == [0.0, 5.0]
    for stem, beta in (("a", 0.0), ("b", 5.0)):
        meta = load_cube(out / f"{stem}.npz").metadata
        assert meta["config"]["beta"] == beta
        assert betas[Path(meta["run_config"]).name] == beta  # the cube names its run's file
        assert (out / meta["run_config"]).is_file()
    # the file reproduces the run
    capsys.readouterr()
    first = next(r for r in runs if betas[r.name] == 5.0)
    assert main(["reconstruct", "--bundle", str(bpath), "--out", str(tmp / "again"),
                 "--no-progress", "--config", str(first), str(caps / "b.npy")]) == 0  # fmt: skip


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
    from hsi_torch.io.bundle import CalibrationBundle

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


def test_emptied_output_is_redone_on_resume(ws, capsys):
    tmp, bpath, caps, _ = ws
    out = tmp / "out"
    assert _rec(bpath, out, str(caps / "a.npy")) == 0
    (out / "a.npz").write_bytes(b"")  # emptied (disk full, a killed copy, ...)
    capsys.readouterr()
    assert _rec(bpath, out, str(caps / "a.npy")) == 0
    assert "1 processed" in capsys.readouterr().err
    assert load_cube(out / "a.npz").cube.shape == (8, 20, 20)
    # an output truncated to another non-zero size is redone too
    with open(out / "a.tif", "r+b") as f:
        f.truncate(100)
    assert _rec(bpath, out, str(caps / "a.npy")) == 0
    assert "1 processed" in capsys.readouterr().err
    load_cube(out / "a.tif")


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
    with pytest.raises(MissingFileError):
        load_cube("/nonexistent/cube.npz")
    with pytest.raises(MissingFileError):
        load_cube("/nonexistent/cube.hdr")
    from hsi_torch.io import load_raw

    with pytest.raises(MissingFileError):
        load_raw("/nonexistent/shot.dng")


def test_run_records_are_json(ws):
    """Done-markers stay readable JSON with the fields resume relies on."""
    tmp, bpath, caps, _ = ws
    out = tmp / "out"
    assert _rec(bpath, out, str(caps / "a.npy")) == 0
    (marker,) = (out / DONE_DIR).glob("*.json")
    rec = json.loads(marker.read_text())
    assert rec["status"] == "done" and rec["input"] == os.path.abspath(caps / "a.npy")
    assert {Path(p).name for p in rec["outputs"]} >= {"a.npz", "a.tif"}
    assert all(len(v) == 2 for v in rec["output_stamps"].values())


def test_damaged_tiff_gives_our_error_without_tifffile_log_lines(tmp_path, caplog):
    """tifffile logged unnamed lines ("incorrect StripOffsets count") to stderr beside our
    error; the reader now keeps them quiet and its own error names the file."""
    p = tmp_path / "bad.tif"
    tifffile.imwrite(p, np.zeros((6, 8), np.uint16), photometric="minisblack", metadata=None)
    data = bytearray(p.read_bytes())
    data[10] = 1  # the first IFD entry's count: the strip tables no longer match
    p.write_bytes(bytes(data))
    with pytest.raises(FileFormatError, match=r"bad\.tif"):
        read_any(p)
    assert not [r for r in caplog.records if r.name.startswith("tifffile")]


# ---------------------------------------------------------------------------------------------
# second campaign: a name that is not UTF-8, resume by the bundle's content, settings up front


def test_an_input_name_that_is_not_utf8_fails_alone(ws, capsys):
    """One input named with bytes that are not UTF-8 used to abort the whole batch
    (UnicodeEncodeError, later inputs not run, earlier failures not summarised)."""
    tmp, bpath, caps, img = ws
    bad = os.fsdecode(os.fsencode(caps) + b"/bad\xff.npy")
    np.save(bad, img.numpy())
    np.save(caps / "z.npy", img.numpy())
    out = tmp / "out"
    missing = str(caps / "gone.npy")
    assert _rec(bpath, out, missing, str(caps / "a.npy"), bad, str(caps / "z.npy")) == 1
    err = capsys.readouterr().err
    assert "4 input(s): 2 processed" in err and "2 failed" in err
    assert "not valid UTF-8" in err and "bad\\xff.npy" in err and "gone.npy" in err
    assert (out / "a.npz").is_file() and (out / "z.npz").is_file()  # the later input ran
    assert not any("bad" in p.name for p in out.iterdir())


def test_resume_knows_the_bundle_by_its_content(ws, capsys):
    """Another bundle with the same path, size and time is not the same bundle: the rerun
    reconstructs again (it used to skip and keep cubes 2x off)."""
    tmp, bpath, caps, _ = ws
    out = tmp / "out"
    assert _rec(bpath, out, str(caps / "a.npy")) == 0
    first = load_cube(out / "a.npz").cube
    st = bpath.stat()
    other = make_bundle(white_exposure_s=0.01, cfa_pattern="RGGB")
    other.phi = 2.0 * other.phi  # same arrays, same sizes: the cubes come out halved
    other.save(bpath)
    os.utime(bpath, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert bpath.stat().st_size == st.st_size and bpath.stat().st_mtime_ns == st.st_mtime_ns
    capsys.readouterr()
    assert _rec(bpath, out, str(caps / "a.npy")) == 0
    assert "1 processed" in capsys.readouterr().err
    again = load_cube(out / "a.npz").cube
    valid = torch.isfinite(first)
    torch.testing.assert_close(again[valid], first[valid] / 2, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("setting, key", [
    ("black_level=[1, 2]", "black_level"), ("white_level=-5", "white_level"),
    ("preview_size=100000", "preview_size"), ("black_level=[1, 2, 3, 4, 5]", "black_level"),
])  # fmt: skip
def test_reading_and_preview_settings_are_checked_before_the_folder_exists(ws, capsys,
                                                                            setting, key):
    """These used to be checked per input, after the folder was made: every input failed (a
    preview of 100000 px ran out of memory after each solve)."""
    tmp, bpath, caps, _ = ws
    out = tmp / "out"
    assert _rec(bpath, out, "--set", setting, str(caps / "a.npy")) == 1
    err = capsys.readouterr().err
    assert f"key '{key}'" in err and err.count("\n") == 1
    assert not out.exists()
