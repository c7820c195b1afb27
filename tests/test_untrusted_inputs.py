"""What the package does with inputs it must not trust, and with outputs it must not lose.

Replace-then-commit writes (a failed ``calibrate`` or ``simulate --overwrite`` keeps the previous
good outputs, errors name the file), the same-file check of outputs against inputs, and the
readers' refusals of crafted files: decompression bombs, unknown bundle members, zarr codecs that
are not ours, manifest entries outside the capture set, special files, YAML alias bombs and
enormous values.
"""

from __future__ import annotations

import errno
import json
import os
from pathlib import Path

import numpy as np
import pytest
from test_pipeline import make_bundle

from hsi_torch.cli import main
from hsi_torch.errors import HSIError, InputError
from hsi_torch.io.atomic import (
    InputFiles,
    ReplaceTransaction,
    check_not_input,
    replace_then_commit,
)


def _rec(bpath, out, *extra):
    return main(["reconstruct", "--bundle", str(bpath), "--out", str(out), "--no-progress",
                 "--set", "dtype=float64", "--set", "beta=0", *extra])  # fmt: skip


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes()
            for p in sorted(folder.rglob("*")) if p.is_file()}  # fmt: skip


# ---------------------------------------------------------------------------------------------
# the transaction and the same-file check


def test_check_not_input_by_identity_whatever_the_name(tmp_path):
    a = tmp_path / "in" / "a.tif"
    a.parent.mkdir()
    a.write_bytes(b"raw")
    (tmp_path / "link").symlink_to(a.parent)
    os.link(a, tmp_path / "hard.tif")
    inputs = InputFiles([a])
    for same in (a, tmp_path / "link" / "a.tif", tmp_path / "hard.tif",
                 tmp_path / "in" / ".." / "in" / "a.tif"):
        with pytest.raises(InputError, match="is an input"):
            check_not_input(same, inputs)
    assert check_not_input(tmp_path / "in" / "b.tif", [a]) == tmp_path / "in" / "b.tif"
    with pytest.raises(InputError, match="a.tif"):  # a folder stands for its files
        check_not_input(tmp_path / "hard.tif", [tmp_path / "in"])


def test_transaction_keeps_old_files_until_every_new_one_is_complete(tmp_path):
    a, b = tmp_path / "a.bin", tmp_path / "b.bin"
    a.write_bytes(b"old a")
    b.write_bytes(b"old b")
    with pytest.raises(RuntimeError, match="boom"), replace_then_commit() as tx:
        tx.stage(a).write_bytes(b"new a")
        assert a.read_bytes() == b"old a"  # not yet
        raise RuntimeError("boom")
    assert a.read_bytes() == b"old a" and b.read_bytes() == b"old b"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.bin", "b.bin"]  # no temp file left

    def full_disk(path):
        Path(path).write_bytes(b"half")
        raise OSError(errno.ENOSPC, "No space left on device")

    with pytest.raises(OSError, match=r"No space left on device while writing .*b\.bin") as ei:
        with replace_then_commit() as tx:
            tx.write(a, lambda p: Path(p).write_bytes(b"new a"))
            tx.write(b, full_disk)
    assert ei.value.errno == errno.ENOSPC
    assert a.read_bytes() == b"old a" and b.read_bytes() == b"old b"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.bin", "b.bin"]

    with replace_then_commit() as tx:
        tx.write(a, lambda p: Path(p).write_bytes(b"new a"))
        tx.write(tmp_path / "c.bin", lambda p: Path(p).write_bytes(b"c"))
    assert a.read_bytes() == b"new a" and tx.replaced == [a]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.bin", "b.bin", "c.bin"]


def test_transaction_puts_back_what_it_moved_when_a_move_fails(tmp_path, monkeypatch):
    a, b = tmp_path / "a.bin", tmp_path / "b.bin"
    a.write_bytes(b"old a")
    tx = ReplaceTransaction()
    tx.stage(a).write_bytes(b"new a")
    tx.stage(b).write_bytes(b"new b")
    real = os.replace

    def flaky(src, dst, *args, **kw):
        if Path(dst) == b:
            raise OSError(errno.EIO, "Input/output error")
        return real(src, dst, *args, **kw)

    monkeypatch.setattr(os, "replace", flaky)
    with pytest.raises(OSError, match=r"while replacing .*b\.bin"):
        tx.commit()
    monkeypatch.undo()
    assert a.read_bytes() == b"old a" and not b.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.bin"]


def test_transaction_refuses_a_folder_in_the_way_before_moving_anything(tmp_path):
    (tmp_path / "a.bin").write_bytes(b"old a")
    (tmp_path / "b.bin").mkdir()
    with pytest.raises(InputError, match=r"b\.bin: a folder"), replace_then_commit() as tx:
        tx.write(tmp_path / "a.bin", lambda p: Path(p).write_bytes(b"new"))
        tx.write(tmp_path / "b.bin", lambda p: Path(p).write_bytes(b"new"))
    assert (tmp_path / "a.bin").read_bytes() == b"old a"


# ---------------------------------------------------------------------------------------------
# calibrate: a failed rerun keeps the previous bundle, report, figure and configuration


class _Report:
    registration: list = []

    def to_dict(self) -> dict:
        return {"fake": True}

    def __str__(self) -> str:
        return "fake calibration report"


@pytest.fixture
def fake_calibration(monkeypatch):
    """``calibrate`` with the calibration itself replaced by a tiny bundle (the write path is
    what is tested here)."""
    import hsi_torch.calibrate.pipeline as pipeline

    state = {"seed": 0}

    def fake(captures, cfg, device=None):
        state["seed"] += 1
        return make_bundle(seed=state["seed"]), _Report()

    monkeypatch.setattr(pipeline, "calibrate_capture_set", fake)
    return state


def _calibrate(caps: Path, out: Path) -> int:
    return main(["calibrate", "--captures", str(caps), "--out", str(out), "--no-progress"])


def test_failed_calibrate_rerun_keeps_the_previous_bundle(tmp_path, fake_calibration, capsys):
    caps, out = tmp_path / "caps", tmp_path / "cal"
    caps.mkdir()
    (caps / "manifest.json").write_text("{}")
    assert _calibrate(caps, out) == 0
    assert "replaced" not in capsys.readouterr().err
    names = ["calib.npz", "calib.report.json", "calib_diagnostics.png", "resolved_config.yaml"]
    assert sorted(p.name for p in out.iterdir()) == sorted(names)
    (out / "calib.report.json").unlink()
    (out / "calib.report.json").mkdir()  # a folder in the way of one output
    before = _snapshot(out)
    assert _calibrate(caps, out) == 1
    err = capsys.readouterr().err
    assert "calib.report.json" in err and "folder" in err and "Errno" not in err
    assert _snapshot(out) == before  # the bundle and the figure are still there, unchanged
    (out / "calib.report.json").rmdir()


def test_calibrate_on_a_full_disk_names_the_file_and_keeps_the_old_ones(
        tmp_path, fake_calibration, capsys, monkeypatch):
    import hsi_torch.calibrate.figures as figures

    caps, out = tmp_path / "caps", tmp_path / "cal"
    caps.mkdir()
    assert _calibrate(caps, out) == 0
    before = _snapshot(out)
    real = figures.plot_calibration

    def full(bundle, path, **kw):
        real(bundle, path, **kw)
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(figures, "plot_calibration", full)
    capsys.readouterr()
    assert _calibrate(caps, out) == 1
    err = capsys.readouterr().err
    assert "No space left on device" in err and "calib_diagnostics.png" in err
    assert _snapshot(out) == before
    assert sorted(p.name for p in out.iterdir()) == sorted(before)  # no temporary file left
    monkeypatch.setattr(figures, "plot_calibration", real)
    assert _calibrate(caps, out) == 0
    assert "replaced the existing bundle" in capsys.readouterr().err
    assert _snapshot(out)["calib.npz"] != before["calib.npz"]


def test_calibrate_refuses_to_write_over_a_capture(tmp_path, fake_calibration, capsys):
    caps = tmp_path / "caps"
    caps.mkdir()
    (caps / "scan_550nm.tif").write_bytes(b"a capture")
    (tmp_path / "b.npz").symlink_to(caps / "scan_550nm.tif")
    assert main(["calibrate", "--captures", str(caps), "--out", str(tmp_path / "b.npz")]) == 1
    assert "is an input" in capsys.readouterr().err
    assert (caps / "scan_550nm.tif").read_bytes() == b"a capture"


# ---------------------------------------------------------------------------------------------
# simulate into a folder that holds files


_TINY = ["--set", "camera.scale=0.25", "--set", "render.supersample=1",
         "--set", "captures.scan_wavelengths_nm=[550]", "--set", "captures.white_shots=1",
         "--set", "captures.grid.poses=[]", "--set", "render.figures=false",
         "--set", "captures.scenes=[]", "--set", "captures.dark_frames=0",
         "--set", "render.progress=false"]  # fmt: skip


def _capture_set_like(d: Path) -> dict[str, bytes]:
    (d / "scan").mkdir(parents=True)
    (d / "white").mkdir()
    (d / "scan" / "scan_550nm.tif").write_bytes(b"device scan")
    (d / "white" / "white_00.tif").write_bytes(b"device white")
    (d / "manifest.json").write_text('{"device": true}')
    return _snapshot(d)


def test_simulate_refuses_a_non_empty_folder_without_overwrite(tmp_path, capsys):
    d = tmp_path / "device_set"
    before = _capture_set_like(d)
    assert main(["simulate", "--out", str(d), *_TINY]) == 1
    err = capsys.readouterr().err
    assert "not empty" in err and "capture set" in err and "--overwrite" in err
    assert _snapshot(d) == before


def test_simulate_overwrite_replaces_only_when_complete(tmp_path, capsys):
    d = tmp_path / "device_set"
    before = _capture_set_like(d)
    # a failing run with --overwrite leaves the old files as they were
    assert main(["simulate", "--out", str(d), "--overwrite", *_TINY,
                 "--set", "geometry.pupil_distance_mm=0"]) == 1  # fmt: skip
    assert _snapshot(d) == before
    assert main(["simulate", "--out", str(d), "--overwrite", *_TINY]) == 0
    assert "replaced" in capsys.readouterr().err
    after = _snapshot(d)
    assert after["scan/scan_550nm.tif"] != before["scan/scan_550nm.tif"]
    assert json.loads(after["manifest.json"])["generator"] == "hsi-torch simulate"
    assert not [p for p in d.iterdir() if p.name.startswith(".")]  # the staging folder is gone
    from hsi_torch.io.capture_set import read_capture_set

    assert len(read_capture_set(d).scan) == 1


def test_simulate_rerun_after_an_interruption_finishes_without_overwrite(tmp_path, monkeypatch,
                                                                         capsys):  # fmt: skip
    """A ``simulate`` stopped part-way (Ctrl-C after its captures were written) left a partial
    folder, and the same command then refused it unless ``--overwrite`` was given. Now the
    folder is marked as an incomplete run of simulate until the set is complete: the rerun
    finishes it without ``--overwrite``, deletes nothing (a file the tool did not write is kept
    and named), a run still writing the folder makes it refuse, and a complete set is still
    refused."""
    import fcntl

    from hsi_torch.io.capture_set import read_capture_set
    from hsi_torch.simulate import capture_sets

    real_write_truth = capture_sets.write_truth

    def interrupted_run(d: Path) -> None:
        def stop(*args, **kwargs):
            raise KeyboardInterrupt

        monkeypatch.setattr(capture_sets, "write_truth", stop)  # after the captures
        assert main(["simulate", "--out", str(d), *_TINY]) == 130
        monkeypatch.setattr(capture_sets, "write_truth", real_write_truth)
        assert (d / "scan" / "scan_550nm.tif").is_file() and not (d / "manifest.json").exists()

    d = tmp_path / "sim"
    interrupted_run(d)
    (d / "notes.txt").write_text("the user's own notes")  # not the tool's: never deleted
    capsys.readouterr()
    assert main(["simulate", "--out", str(d), *_TINY]) == 0  # used to refuse: "not empty"
    err = capsys.readouterr().err
    assert "holds an incomplete earlier simulate run" in err
    assert "left in place: notes.txt" in err
    assert (d / "notes.txt").read_text() == "the user's own notes"
    assert len(read_capture_set(d).scan) == 1
    assert not [p for p in d.rglob("*") if p.name.endswith(".tmp")]
    assert [p.name for p in d.iterdir() if p.name.startswith(".")] == []  # no marker left
    # the complete set carries no marker: refused without --overwrite as before
    assert main(["simulate", "--out", str(d), *_TINY]) == 1
    assert "--overwrite" in capsys.readouterr().err

    # another run still holding an incomplete folder: refused, naming it
    from hsi_torch.simulate.cli_entry import INCOMPLETE_MARKER

    d2 = tmp_path / "sim2"
    interrupted_run(d2)
    fd = os.open(d2 / INCOMPLETE_MARKER, os.O_RDWR)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        capsys.readouterr()
        assert main(["simulate", "--out", str(d2), *_TINY]) == 1
        assert "being written by another simulate run" in capsys.readouterr().err
    finally:
        os.close(fd)
    # a folder found empty that another run wrote into before the marker was taken: refused
    from hsi_torch.simulate.cli_entry import incomplete_run

    (tmp_path / "sim3").mkdir()
    (tmp_path / "sim3" / "manifest.json").write_text("{}")
    with pytest.raises(InputError, match="written by another simulate run"):
        with incomplete_run(tmp_path / "sim3", fresh=True):
            raise AssertionError("not reached")
    assert [p.name for p in (tmp_path / "sim3").iterdir()] == ["manifest.json"]


# ---------------------------------------------------------------------------------------------
# the run's Zarr store: read only with its own codecs


class _Payload:
    """Unpickling this creates a file: the proof that code ran."""

    def __init__(self, marker: Path) -> None:
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def _craft_pickle_store(store: Path, marker: Path) -> None:
    import pickle

    meta = json.loads((store / "source" / ".zarray").read_text())
    meta["filters"], meta["compressor"] = [{"id": "pickle"}], None
    (store / "source" / ".zarray").write_text(json.dumps(meta))
    zm = json.loads((store / ".zmetadata").read_text())
    zm["metadata"]["source/.zarray"] = meta
    (store / ".zmetadata").write_text(json.dumps(zm))
    (store / "source" / "0").write_bytes(pickle.dumps(_Payload(marker)))


@pytest.fixture
def unsafe_numcodecs(monkeypatch):
    """numcodecs as before 0.16.6, which unpickled without asking."""
    pickles = pytest.importorskip("numcodecs.pickles")
    monkeypatch.setattr(pickles, "ALLOW_UNSAFE_PICKLE_DECODE", True, raising=False)


def test_dataset_store_with_a_pickle_codec_is_refused_without_running_it(tmp_path,
                                                                         unsafe_numcodecs):
    from hsi_torch.io.dataset import CubeDataset, open_dataset, write_frame

    store, marker = tmp_path / "cubes.zarr", tmp_path / "pwned"
    with CubeDataset.open(store, ["/data/a.tif"], [430.0, 440.0], (3, 4)) as ds:
        write_frame(store, ds.index["/data/a.tif"], np.ones((2, 3, 4)), np.ones((3, 4), bool),
                    {"x": 1})
    _craft_pickle_store(store, marker)
    with pytest.raises(HSIError, match=r"array 'source' names the filter codec 'pickle'"):
        with CubeDataset.open(store, ["/data/a.tif"], [430.0, 440.0], (3, 4)):
            pass
    with pytest.raises(HSIError, match=r"'pickle'"):
        open_dataset(store)
    assert not marker.exists()
    # every other array, and other codecs and settings, likewise
    meta = json.loads((store / "cube" / ".zarray").read_text())
    meta["compressor"] = {"id": "zstd", "level": 1, "evil": 1}
    (store / "cube" / ".zarray").write_text(json.dumps(meta))
    with pytest.raises(HSIError, match=r"array 'cube'.*unexpected settings \['evil'\]"):
        with CubeDataset.open(store, [], [430.0, 440.0], (3, 4)):
            pass


def test_cube_file_zarr_with_a_pickle_codec_is_refused(tmp_path, unsafe_numcodecs):
    pytest.importorskip("xarray")
    pytest.importorskip("zarr")
    import pickle

    from hsi_torch.io import load_cube, save_cube

    p, marker = tmp_path / "c.zarr", tmp_path / "pwned"
    save_cube(p, np.ones((2, 3, 4), np.float32), np.array([430.0, 440.0]))
    assert load_cube(p).cube.shape == (2, 3, 4)
    meta = json.loads((p / "x" / ".zarray").read_text())
    meta["compressor"], meta["filters"], meta["dtype"] = None, [{"id": "pickle"}], "|O"
    (p / "x" / ".zarray").write_text(json.dumps(meta))
    zm = json.loads((p / ".zmetadata").read_text())
    zm["metadata"]["x/.zarray"] = meta
    (p / ".zmetadata").write_text(json.dumps(zm))
    (p / "x" / "0").write_bytes(pickle.dumps(_Payload(marker)))
    with pytest.raises(HSIError, match=r"array 'x' names the filter codec 'pickle'"):
        load_cube(p)
    assert not marker.exists()


def test_reconstruct_into_a_crafted_store_is_refused_with_a_clear_error(ws, capsys,
                                                                       unsafe_numcodecs):
    pytest.importorskip("numcodecs")
    tmp, bpath, caps = ws
    out, marker = tmp / "run", tmp / "pwned"
    assert _rec(bpath, out, "--format", "zarr", str(caps / "a.npy")) == 0
    _craft_pickle_store(out / "cubes.zarr", marker)
    capsys.readouterr()
    assert _rec(bpath, out, "--format", "zarr", "--no-resume", str(caps / "a.npy")) == 1
    err = capsys.readouterr().err
    assert "array 'source' names the filter codec 'pickle'" in err
    assert "unexpected error" not in err and "UnsafeDecodeError" not in err
    assert not marker.exists()


# ---------------------------------------------------------------------------------------------
# capture readers: decompression bombs, special files


@pytest.fixture
def no_decoding(monkeypatch):
    """Record every TIFF page decoded (a refusal from the header decodes none)."""
    import tifffile

    calls: list = []
    real = tifffile.TiffPage.asarray

    def spy(self, *a, **k):
        calls.append(self.shape)
        return real(self, *a, **k)

    monkeypatch.setattr(tifffile.TiffPage, "asarray", spy)
    return calls


def test_compressed_tiff_with_extra_samples_is_refused_before_decoding(tmp_path, no_decoding):
    import tifffile

    from hsi_torch.io import read_any, read_capture

    p = tmp_path / "bomb.tif"  # (H, W, K): the sensor's H and W, K samples per pixel
    tifffile.imwrite(p, np.zeros((40, 48, 500), np.uint16), compression="zlib",
                     photometric="minisblack", planarconfig="contig")  # fmt: skip
    assert p.stat().st_size < 100_000 < 40 * 48 * 500 * 2
    with pytest.raises(HSIError, match=r"bomb\.tif.*\(40, 48, 500\).*refused before decoding"):
        read_any(p, expected_size=(40, 48))
    with pytest.raises(HSIError, match=r"bomb\.tif.*refused before decoding"):
        read_capture(p)
    assert no_decoding == []


def test_compressed_npz_bombs_are_refused_from_the_member_headers(tmp_path):
    from hsi_torch.io import read_any

    p = tmp_path / "bomb.npz"
    np.savez_compressed(p, image=np.zeros((40, 48, 500), np.uint16))
    with pytest.raises(HSIError, match=r"bomb\.npz.*\(40, 48, 500\).*refused before decoding"):
        read_any(p, expected_size=(40, 48))
    q = tmp_path / "meta_bomb.npz"  # a valid image, and a 200 MB "metadata" text
    np.savez_compressed(q, image=np.zeros((40, 48), np.uint16),
                        metadata=np.array("x" * (50 << 20)))  # fmt: skip
    assert q.stat().st_size < 2 << 20
    with pytest.raises(HSIError, match=r"meta_bomb\.npz: 'metadata' must be .* at most 16 MiB"):
        read_any(q, expected_size=(40, 48))


def _alarm(seconds: float):
    import signal

    def on_alarm(signum, frame):
        raise TimeoutError("hang")

    signal.signal(signal.SIGALRM, on_alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs here")
def test_a_fifo_is_refused_before_opening(tmp_path):
    import signal

    from hsi_torch.io import read_any, read_capture
    from hsi_torch.io.bundle import CalibrationBundle

    fifo = tmp_path / "scene.tif"
    os.mkfifo(fifo)
    _alarm(10)
    try:
        for fn in (lambda: read_any(fifo), lambda: read_capture(fifo),
                   lambda: CalibrationBundle.load(fifo)):  # fmt: skip
            with pytest.raises(HSIError, match=r"scene\.tif: is a FIFO"):
                fn()
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs here")
def test_an_npy_metadata_sidecar_must_be_a_regular_file(tmp_path):
    """The NPY capture's ``x.npy.json`` used to be opened as it was: a FIFO hung the batch,
    ``/dev/zero`` raised a MemoryError with an empty message."""
    import signal

    from hsi_torch.io import read_any

    np.save(tmp_path / "x.npy", np.full((8, 8), 100, np.uint16))
    side = tmp_path / "x.npy.json"
    os.mkfifo(side)
    _alarm(10)
    try:
        with pytest.raises(HSIError, match=r"x\.npy\.json: is a FIFO"):
            read_any(tmp_path / "x.npy", cfa_pattern="RGGB")
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
    side.unlink()
    side.symlink_to("/dev/zero")
    with pytest.raises(HSIError, match=r"x\.npy\.json: is a character device"):
        read_any(tmp_path / "x.npy", cfa_pattern="RGGB")
    side.unlink()
    side.write_text('{"cfa_pattern": "GRBG"}')
    assert read_any(tmp_path / "x.npy").metadata["cfa_pattern"] == "GRBG"


@pytest.mark.parametrize("dtype, value", [(np.uint64, 2**63 + 5), (np.int64, 2**52)])
def test_64_bit_integer_captures_are_bounded_like_float_ones(tmp_path, dtype, value):
    """int64/uint64 samples beyond 2^50 gave cubes of ~1e17 (a uint64 beyond 2^63 wrapped when
    shifted); they are refused as float ones are. A 64-bit file of sensor counts still reads."""
    from hsi_torch.io import read_any

    a = np.full((8, 8), 1000, dtype)
    a[3, 4] = value
    np.save(tmp_path / "big.npy", a)
    with pytest.raises(HSIError, match=r"big\.npy: image values reach .*2\^50"):
        read_any(tmp_path / "big.npy", cfa_pattern="RGGB")
    a[3, 4] = 2**16
    np.save(tmp_path / "ok.npy", a)
    assert float(read_any(tmp_path / "ok.npy", cfa_pattern="RGGB").image.max()) == 2**16


def test_a_file_named_npz_that_is_not_an_npz_capture_says_so(tmp_path):
    from hsi_torch.io import read_any

    (tmp_path / "shot.npz").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 64)
    with pytest.raises(HSIError, match=r"shot\.npz: not an NPZ file") as e:
        read_any(tmp_path / "shot.npz", cfa_pattern="RGGB")
    assert "allow_pickle" not in str(e.value)


@pytest.fixture
def no_tiff_decoding(monkeypatch):
    """Any TIFF pixel decoding fails the test: what is checked must be checked from headers."""
    import tifffile

    def refuse(*_a, **_k):
        raise AssertionError("a TIFF was decoded")

    for cls in (tifffile.TiffFile, tifffile.TiffPage, tifffile.TiffPageSeries):
        monkeypatch.setattr(cls, "asarray", refuse)


def test_layout_white_shot_of_another_size_is_refused_from_its_header(tmp_path, capsys,
                                                                      no_tiff_decoding):
    """A 140 kB zlib TIFF that inflates to 32 MB (the trial's 0.5 MB one: 2 GB) given as
    ``layout --white``: refused from its header against the design camera, nothing decoded."""
    import tifffile

    big = tmp_path / "white.tif"
    tifffile.imwrite(big, np.zeros((4000, 4000), np.uint16), compression="zlib")
    assert big.stat().st_size < 1 << 20
    rc = main(["layout", "--white", str(big), "--out", str(tmp_path / "lay.json")])
    err = capsys.readouterr().err
    assert rc == 1 and "white.tif: shot size (H, W) = (4000, 4000) differs from the design " in err
    assert "decoded" not in err and not (tmp_path / "lay.json").exists()


def test_captures_import_reads_no_pixel(tmp_path, no_tiff_decoding):
    """The import takes a scan frame's wavelength from the file's metadata only (before, the
    whole image was decoded, with no expected size: a small zlib TIFF inflated to 1.7 GB)."""
    import tifffile

    from hsi_torch.io.capture_import import import_captures, read_sheet

    for name, lam in (("a.tif", 430.0), ("b.tif", 440.0)):
        tifffile.imwrite(tmp_path / name, np.full((40, 40), int(lam), np.uint16),
                         compression="zlib", metadata=None,
                         description=json.dumps({"wavelength_nm": lam, "kind": "bayer"}))
    (tmp_path / "sheet.csv").write_text("file,role\na.tif,scan\nb.tif,scan\n")
    rep = import_captures(read_sheet(tmp_path / "sheet.csv"), tmp_path / "set")
    assert rep.bands[430.0] == ["a.tif"] and rep.bands[440.0] == ["b.tif"]


def test_a_raw_of_another_size_is_refused_before_libraw_unpacks_it(tmp_path, monkeypatch):
    import rawpy
    from synthetic_data import write_dng

    from hsi_torch.io import read_any

    f = write_dng(tmp_path / "big.dng", np.full((64, 96), 600, np.uint16), black_level=512,
                  white_level=4095)  # fmt: skip

    def refuse(*_a, **_k):
        raise AssertionError("the RAW was unpacked")

    monkeypatch.setattr(rawpy, "imread", refuse)  # (load_raw's way in: open and unpack)
    with pytest.raises(HSIError, match=r"big\.dng: image size \(H, W\) = \(64, 96\) does not "
                       r"match the expected sensor size \(30, 32\)"):
        read_any(f, expected_size=(30, 32))


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs here")
def test_a_fifo_among_the_inputs_does_not_hang_the_batch(ws, capsys):
    import signal

    tmp, bpath, caps = ws
    os.mkfifo(caps / "pipe.tif")
    _alarm(120)
    try:
        rc = _rec(bpath, tmp / "out", str(caps / "pipe.tif"), str(caps / "a.npy"))
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
    assert rc == 1
    err = capsys.readouterr().err
    assert "pipe.tif" in err and "FIFO" in err
    assert (tmp / "out" / "a.npz").is_file()  # the other input was reconstructed


# ---------------------------------------------------------------------------------------------
# bundle members: a known list, sizes bounded before decompressing


def _rezip(src: Path, dst: Path, replace: dict[str, np.ndarray | None]) -> Path:
    """A copy of the NPZ ``src`` with members replaced, added (arrays) or dropped (None)."""
    import io
    import zipfile

    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w", zipfile.ZIP_DEFLATED) as zout:
        for info in zin.infolist():
            name = info.filename[:-4]
            if name not in replace:
                zout.writestr(info.filename, zin.read(info))
        for name, arr in replace.items():
            if arr is not None:
                buf = io.BytesIO()
                np.lib.format.write_array(buf, arr, allow_pickle=False)
                zout.writestr(name + ".npy", buf.getvalue())
    return dst


def test_bundle_with_an_unknown_member_is_refused_by_name(tmp_path):
    from hsi_torch.io.bundle import CalibrationBundle

    good = make_bundle().save(tmp_path / "good.npz")
    CalibrationBundle.load(good)
    bad = _rezip(good, tmp_path / "bad.npz", {"payload": np.zeros(1000, np.uint8)})
    with pytest.raises(HSIError, match=r"bad\.npz: unknown member 'payload\.npy'"):
        CalibrationBundle.load(bad)
    # an extra_ member that meta does not list is unknown too
    bad2 = _rezip(good, tmp_path / "bad2.npz", {"extra_x": np.zeros(3)})
    with pytest.raises(HSIError, match=r"unknown member 'extra_x\.npy'"):
        CalibrationBundle.load(bad2)


def test_bundle_member_larger_than_its_layout_is_refused_before_decompressing(tmp_path,
                                                                              monkeypatch):
    from hsi_torch.io.bundle import CalibrationBundle

    b = make_bundle()
    good = b.save(tmp_path / "good.npz")
    V, M, h, w = b.B.shape
    big = np.zeros((V, M, h, w * 400), np.float32)  # 64 MB of zeros: ~60 kB deflated
    bad = _rezip(good, tmp_path / "big.npz", {"B": big})
    assert bad.stat().st_size < 2 << 20
    reads = []
    real = np.lib.format.read_array
    monkeypatch.setattr(np.lib.format, "read_array",
                        lambda f, *a, **k: reads.append(1) or real(f, *a, **k))  # fmt: skip
    with pytest.raises(HSIError, match=r"big\.npz: member 'B' declares shape .* at most "
                                       rf"{V * M * h * w} elements\); refusing to decompress"):
        CalibrationBundle.load(bad)
    assert len(reads) <= 3  # only meta, the reference box and the sensor size were decoded


# ---------------------------------------------------------------------------------------------
# manifests: entries confined to the set's folder, entries of the wrong type


def _manifest_set(tmp_path: Path, entries: list, **top) -> Path:
    root = tmp_path / "set"
    (root / "scan").mkdir(parents=True)
    (root / "scan" / "scan_550nm.tif").write_bytes(b"x")
    (tmp_path / "outside.tif").write_bytes(b"secret")
    (root / "manifest.json").write_text(json.dumps({"schema_version": 1, "captures": entries,
                                                    **top}))  # fmt: skip
    return root


@pytest.mark.parametrize("where", ["../outside.tif", "ABS", "scan/link.tif"])
def test_manifest_entries_outside_the_folder_are_refused_unless_allowed(tmp_path, where):
    from hsi_torch.io.capture_set import read_capture_set

    if where == "ABS":
        where = str(tmp_path / "outside.tif")
    entries = [{"file": where, "type": "scan", "wavelength_nm": 550}]
    root = _manifest_set(tmp_path, entries)
    (root / "scan" / "link.tif").symlink_to(tmp_path / "outside.tif")
    with pytest.raises(HSIError, match=r"manifest\.json: captures\[0\]\.file .* points outside "
                                       r"the capture set's folder"):
        read_capture_set(root)
    root.joinpath("manifest.json").write_text(json.dumps(
        {"schema_version": 1, "captures": entries, "allow_files_outside": True}))
    cs = read_capture_set(root)
    assert cs.scan[0][0].resolve() == (tmp_path / "outside.tif").resolve()
    for key in ("nominal_layout", "brf_free_mask"):  # the other paths a manifest names
        root.joinpath("manifest.json").write_text(json.dumps(
            {"schema_version": 1, "captures": [], key: "../outside.tif"}))
        with pytest.raises(HSIError, match=rf"{key} .* points outside"):
            read_capture_set(root)


def test_inside_paths_with_dotdot_still_work(tmp_path):
    from hsi_torch.io.capture_set import read_capture_set

    root = _manifest_set(tmp_path, [{"file": "scan/../scan/scan_550nm.tif", "type": "scan",
                                     "wavelength_nm": 550}])  # fmt: skip
    assert read_capture_set(root).scan[0][1] == 550.0


@pytest.mark.parametrize("entry, key", [
    ({"file": 5, "type": "scan"}, r"captures\[0\] \(5\): 'file' must be a non-empty string, got 5"),
    ({"file": None, "type": "scan"}, r"captures\[0\] \(None\): 'file' must be a non-empty string"),
    ({"file": ["a"], "type": "scan"}, r"captures\[0\] \(\['a'\]\): 'file' must be a non-empty"),
    ({"file": "scan/scan_550nm.tif", "type": "scan", "wavelength_nm": "abc"},
     r"captures\[0\] \('scan/scan_550nm.tif'\): 'wavelength_nm' must be a number > 0, got 'abc'"),
    ({"file": "scan/scan_550nm.tif", "type": "scan", "wavelength_nm": -5},
     r"captures\[0\] \('scan/scan_550nm.tif'\): 'wavelength_nm' must be a number > 0, got -5"),
    ({"file": "scan/scan_550nm.tif", "type": 3}, r"captures\[0\] \('scan/scan_550nm.tif'\): "
                                                  r"'type' must be one of"),
])  # the manifest schema's check (io.capture_manifest) names file, entry and key
def test_manifest_entries_of_the_wrong_type_name_the_file_and_key(tmp_path, entry, key):
    from hsi_torch.io.capture_set import read_capture_set

    root = _manifest_set(tmp_path, [entry])
    with pytest.raises(HSIError, match=r"set[/\\]manifest\.json: " + key):
        read_capture_set(root)


# ---------------------------------------------------------------------------------------------
# configuration: YAML alias bombs, bounded messages


def _alias_bomb(levels: int = 9, key: str = "beta") -> str:
    """A few hundred bytes of YAML that expand to 9**levels strings."""
    text = 'l0: &l0 ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]\n'
    for k in range(1, levels):
        text += f"l{k}: &l{k} [" + ",".join([f"*l{k - 1}"] * 9) + "]\n"
    return text + f"{key}: *l{levels - 1}\n"


@pytest.mark.parametrize("key", ["beta", "black_level"])
def test_yaml_alias_bomb_in_a_config_file_or_override_is_refused_quickly(tmp_path, capsys, ws,
                                                                         key):
    import time

    tmp, bpath, caps = ws
    cfg = tmp / "bomb.yaml"
    cfg.write_text(_alias_bomb(key=key))
    assert cfg.stat().st_size < 600
    t0 = time.perf_counter()
    assert _rec(bpath, tmp / "o1", "--config", str(cfg), str(caps / "a.npy")) == 1
    flow = "{" + _alias_bomb(key="x").replace("\n", ", ") + "}"
    assert _rec(bpath, tmp / "o2", "--set", f"{key}={flow}", str(caps / "a.npy")) == 1
    assert time.perf_counter() - t0 < 30
    err = capsys.readouterr().err
    assert err.count("expands to more than") == 2 and len(err) < 2000
    assert "MemoryError" not in err and not (tmp / "o1").exists()


def test_config_error_messages_never_print_a_value_whole():
    from hsi_torch.config import ConfigError, load_config
    from hsi_torch.recon.config import ReconstructConfig

    with pytest.raises(ConfigError) as ei:
        load_config({"beta": list(range(50_000))}, ReconstructConfig)
    assert "expected" in str(ei.value) and len(str(ei.value)) < 600
    from hsi_torch.io.safety import short_repr

    nested: list = ["x"] * 9
    for _ in range(40):  # 9**40 leaves if printed whole
        nested = [nested] * 9
    assert len(short_repr(nested)) <= 200


# ---------------------------------------------------------------------------------------------
# finite but enormous values: a clear error, never an all-zero cube marked valid


@pytest.mark.parametrize("beta", ["1e308", "1e13"])
def test_enormous_beta_is_refused_before_anything_is_written(ws, capsys, beta):
    tmp, bpath, caps = ws
    main(["reconstruct", "--bundle", str(bpath), "--out", str(tmp / "o"), "--no-progress",
          "--set", f"beta={beta}", str(caps / "a.npy")])  # fmt: skip
    err = capsys.readouterr().err
    assert "key 'beta': must be between 0 and 1e+12" in err
    assert not (tmp / "o").exists()


def test_enormous_beta_is_refused_by_the_solver(device):
    import torch

    from hsi_torch.recon.nnls import solve_nnls

    A = torch.rand(4, 6, 5, device=device)
    y = torch.rand(4, 6, device=device)
    with pytest.raises(ValueError, match=r"beta = 1e\+308 overflows the torch.float32 solve"):
        solve_nnls(A, y, beta=1e308)
    assert solve_nnls(A.double(), y.double(), beta=1e12).x.abs().max() > 0


@pytest.mark.parametrize("scale", [1e34, 1e38])
def test_enormous_float_capture_values_are_a_clear_failure(ws, capsys, scale):
    tmp, bpath, caps = ws
    img = np.load(caps / "a.npy").astype(np.float64)
    np.save(caps / "big.npy", (img / img.max() * scale).astype(np.float32))
    rc = _rec(bpath, tmp / "o", str(caps / "big.npy"), str(caps / "a.npy"))
    assert rc == 1
    err = capsys.readouterr().err
    assert "big.npy" in err and "beyond any sensor's range" in err
    assert not (tmp / "o" / "big.npz").exists() and (tmp / "o" / "a.npz").is_file()


# ---------------------------------------------------------------------------------------------
# the cluster: tls:// with certificates


def _self_signed(folder: Path) -> tuple[Path, Path]:
    """A self-signed certificate (its own CA) and its key, PEM files, valid for 127.0.0.1."""
    import datetime
    import ipaddress

    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "hsi-torch test cluster")])
    now = datetime.datetime.now(datetime.timezone.utc)
    cert = (x509.CertificateBuilder().subject_name(name).issuer_name(name)
            .public_key(key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(minutes=5))
            .not_valid_after(now + datetime.timedelta(days=1))
            .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
            .add_extension(x509.SubjectAlternativeName(
                [x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]),
                critical=False)
            .sign(key, hashes.SHA256()))  # fmt: skip
    cpath, kpath = folder / "cluster.pem", folder / "cluster.key"
    cpath.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    kpath.write_bytes(key.private_bytes(serialization.Encoding.PEM,
                                        serialization.PrivateFormat.PKCS8,
                                        serialization.NoEncryption()))  # fmt: skip
    return cpath, kpath


def test_reconstruct_on_a_tls_scheduler_with_certificates(ws, capsys):
    distributed = pytest.importorskip("distributed")
    pytest.importorskip("cryptography")
    from distributed.security import Security

    from hsi_torch.io import load_cube
    from hsi_torch.recon.distributed import connect, make_security

    tmp, bpath, caps = ws
    cert, key = _self_signed(tmp)
    sec = Security(tls_ca_file=str(cert), tls_scheduler_cert=str(cert),
                   tls_scheduler_key=str(key), tls_worker_cert=str(cert),
                   tls_worker_key=str(key), tls_client_cert=str(cert),
                   tls_client_key=str(key), require_encryption=True)  # fmt: skip
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                                  protocol="tls://", host="127.0.0.1", security=sec,
                                  dashboard_address=None) as cluster:  # fmt: skip
        addr = cluster.scheduler_address
        assert addr.startswith("tls://")
        with pytest.raises(ValueError, match="tls:// scheduler needs certificates"):
            with connect(addr):
                pass
        with connect(addr, security=make_security(cert, cert, key)) as (client, _):
            assert client.submit(lambda: 41 + 1).result(timeout=20) == 42
        out = tmp / "out"
        rc = main(["reconstruct", "--bundle", str(bpath), "--out", str(out), "--no-progress",
                   "--scheduler", addr, "--tls-ca-file", str(cert), "--tls-cert", str(cert),
                   "--tls-key", str(key), str(caps / "a.npy")])  # fmt: skip
        assert rc == 0, capsys.readouterr().err
    assert load_cube(out / "a.npz").valid.any()


def test_tls_options_are_checked_before_connecting(ws, capsys):
    pytest.importorskip("distributed")
    tmp, bpath, caps = ws
    base = ["reconstruct", "--bundle", str(bpath), "--out", str(tmp / "o"), "--no-progress"]
    assert main([*base, "--tls-cert", str(bpath), str(caps / "a.npy")]) == 1
    assert "--tls-cert (tls_cert) needs a cluster: --scheduler" in capsys.readouterr().err
    assert main([*base, "--scheduler", "tls://127.0.0.1:1", "--tls-ca-file", str(tmp / "no.pem"),
                 "--tls-cert", str(bpath), str(caps / "a.npy")]) == 1  # fmt: skip
    err = capsys.readouterr().err
    assert "--tls-ca-file" in err and "not found" in err
    assert main([*base, "--scheduler", "tcp://127.0.0.1:1", "--tls-ca-file", str(bpath),
                 "--tls-cert", str(bpath), str(caps / "a.npy")]) == 1  # fmt: skip
    assert "must start with tls://" in capsys.readouterr().err


def test_png_header_gives_the_decoded_size_before_decoding(tmp_path):
    import cv2

    from hsi_torch.io.safety import png_header

    p = tmp_path / "x.png"
    cv2.imwrite(str(p), np.zeros((30, 40, 3), np.uint16))
    assert png_header(p) == ((30, 40, 3), 16)
    (tmp_path / "bad.png").write_bytes(b"\x89PNG\r\n\x1a\nxxxx")
    with pytest.raises(HSIError, match=r"bad\.png: not a PNG"):
        png_header(tmp_path / "bad.png")


def test_dataset_store_is_never_written_into_a_users_folder_of_that_name(tmp_path):
    """``--format zarr`` writes ``OUT/cubes.zarr``; where that is the user's own folder (not a
    store) holding their files, the arrays were written in among them. Now it is refused naming
    the folder and nothing is written; a folder left by an interrupted creation is redone."""
    from hsi_torch.io.dataset import CubeDataset

    store = tmp_path / "cubes.zarr"
    store.mkdir()
    (store / "notes.txt").write_text("the lab's notes")
    with pytest.raises(HSIError, match=r"cubes.zarr is a folder but not a dataset store.*"
                       r"notes.txt"):
        with CubeDataset.open(store, ["/data/a.tif"], [430.0, 440.0], (3, 4)):
            pass
    assert sorted(p.name for p in store.iterdir()) == ["notes.txt"]
    # an interrupted creation: the store's own entries without .zgroup
    other = tmp_path / "again.zarr"
    with CubeDataset.open(other, ["/data/a.tif"], [430.0, 440.0], (3, 4)):
        pass
    (other / ".zgroup").unlink()
    with CubeDataset.open(other, ["/data/a.tif"], [430.0, 440.0], (3, 4)) as ds:
        assert len(ds) == 1
    assert (other / ".zgroup").is_file()
