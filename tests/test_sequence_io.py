"""Sequences of captures (hsi_torch.io.sequence), the sequence store
(hsi_torch.io.sequence_store), ``reconstruct --sequence`` and ``hsi-torch watch``.

Frames are tiny captures rendered from the 4-view test bundle of test_pipeline (20×20 frame);
every reconstructed frame is compared with an independent single-frame reconstruction of the same
file (``Reconstructor.reconstruct_file``), so the store is checked to hold each frame's own cube.
"""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import tifffile
import torch
from test_pipeline import make_bundle, render_capture, true_spectra

from hsi_torch.cli import main
from hsi_torch.errors import InputError
from hsi_torch.findings import Finding
from hsi_torch.io.sequence import (
    exif_time,
    looks_complete,
    open_sequence,
    time_from_name,
)
from hsi_torch.io.sequence_store import (
    SequenceStore,
    iter_store_frames,
    open_sequence_store,
    write_animated_preview,
)
from hsi_torch.recon.batch.sequence_run import sequence_cubes
from hsi_torch.recon.batch.watch import FolderWatcher, watch_folder
from hsi_torch.recon.config import ReconstructConfig
from hsi_torch.recon.pipeline import Reconstructor

xr = pytest.importorskip("xarray")
pytest.importorskip("zarr")

SET = ["--set", "dtype=float64", "--set", "beta=0"]


@pytest.fixture(scope="module")
def bundle_path(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("seqbundle")
    p = d / "calib.npz"
    make_bundle(white_exposure_s=0.01, cfa_pattern="RGGB").save(p)
    return p


def _frame(k: int) -> np.ndarray:
    """A capture of frame ``k``: different spectra every frame."""
    return render_capture(make_bundle(), true_spectra(seed=10 + k)).numpy()


def _npy_bytes(arr: np.ndarray) -> bytes:
    import io

    buf = io.BytesIO()
    np.save(buf, arr)
    return buf.getvalue()


def _cold(bundle_path: Path, path: Path) -> torch.Tensor:
    rec = Reconstructor(bundle_path, dtype=torch.float64, beta=0.0)
    res = rec.reconstruct_file(path)
    return torch.where(res.valid, res.cube, torch.nan)


# ---------------------------------------------------------------------------------------------
# sequences in


def test_name_times_and_natural_order(tmp_path):
    for name in ("f_t=10s.npy", "f_t=2.5s.npy", "f_t=0.25s.npy", ".f_t=11s.npy", "x.npy.part"):
        np.save(tmp_path / "tmp.npy", np.zeros((3, 4, 4), np.uint16))
        (tmp_path / "tmp.npy").rename(tmp_path / name)
    seq = open_sequence(tmp_path)  # folder: hidden and partial names skipped
    assert seq.kind == "folder" and seq.time_source == "name"
    assert [f.path.name for f in seq] == ["f_t=0.25s.npy", "f_t=2.5s.npy", "f_t=10s.npy"]
    assert [f.time_s for f in seq] == [0.25, 2.5, 10.0]
    assert seq.frame_size == (4, 4)
    assert time_from_name("shot_t=250ms.tif") == (0.25, None)
    assert time_from_name("shot_20261207-130500.250.dng")[1].microsecond == 250000
    assert time_from_name("frame_0001.tif") == (None, None)


def test_index_times_and_errors_name_the_file(tmp_path):
    for k in (1, 2, 10):
        np.save(tmp_path / f"frame_{k}.npy", np.zeros((3, 4, 4), np.uint16))
    seq = open_sequence(str(tmp_path / "frame_*.npy"), frame_interval_s=0.5)
    assert [f.path.name for f in seq] == ["frame_1.npy", "frame_2.npy", "frame_10.npy"]
    assert seq.time_source == "index" and [f.time_s for f in seq] == [0.0, 0.5, 1.0]
    # mixed sizes: the odd file is named
    np.save(tmp_path / "frame_11.npy", np.zeros((3, 5, 4), np.uint16))
    with pytest.raises(InputError, match=r"frame_11\.npy.*\(5, 4\)"):
        open_sequence(tmp_path)
    (tmp_path / "frame_11.npy").unlink()
    # a file listed twice
    with pytest.raises(InputError, match="frame_1.npy is listed twice"):
        open_sequence([tmp_path / "frame_1.npy", tmp_path / "frame_2.npy",
                       tmp_path / "frame_1.npy"])  # fmt: skip
    # times against the given order
    np.save(tmp_path / "b_t=1s.npy", np.zeros((3, 4, 4), np.uint16))
    np.save(tmp_path / "a_t=2s.npy", np.zeros((3, 4, 4), np.uint16))
    with pytest.raises(InputError, match=r"b_t=1s\.npy.*earlier than.*a_t=2s\.npy"):
        open_sequence(str(tmp_path / "*_t=*.npy"))
    with pytest.raises(InputError, match="no time in the name"):
        open_sequence(tmp_path / "frame_*.npy", time_from="name")


def test_exif_times_with_subseconds(tmp_path):
    stamps = [("2026:12:07 13:00:00", "250"), ("2026:12:07 13:00:00", "750"),
              ("2026:12:07 13:00:01", "5")]  # fmt: skip
    for k, (dt, sub) in enumerate(stamps):
        tifffile.imwrite(tmp_path / f"img{k}.tif", np.full((4, 4, 3), 100, np.uint16),
                         photometric="rgb", extratags=[(36867, "s", 0, dt, True),
                                                       (37521, "s", 0, sub, True)])  # fmt: skip
    assert exif_time(tmp_path / "img0.tif").microsecond == 250000
    seq = open_sequence(tmp_path)
    assert seq.time_source == "exif" and seq.origin == "2026-12-07T13:00:00.250000"
    assert np.allclose([f.time_s for f in seq], [0.0, 0.5, 1.25])
    # the same second twice: refused, naming both files
    tifffile.imwrite(tmp_path / "img3.tif", np.full((4, 4, 3), 100, np.uint16),
                     photometric="rgb", extratags=[(36867, "s", 0, stamps[2][0], True),
                                                   (37521, "s", 0, "5", True)])  # fmt: skip
    with pytest.raises(InputError, match=r"img3\.tif.*same time.*img2\.tif"):
        open_sequence(tmp_path)


def test_sheet_and_multipage_tiff(tmp_path):
    for k in range(3):
        np.save(tmp_path / f"c{k}.npy", np.zeros((3, 4, 4), np.uint16))
    (tmp_path / "seq.csv").write_text("file,time_s\nc2.npy,0.1\n# a comment\nc0.npy,0.3\n"
                                      "c1.npy,0.9\n")  # fmt: skip
    seq = open_sequence(tmp_path / "seq.csv")
    assert [f.path.name for f in seq] == ["c2.npy", "c0.npy", "c1.npy"]
    assert [f.time_s for f in seq] == [0.1, 0.3, 0.9] and seq.time_source == "sheet"
    (tmp_path / "bad.csv").write_text("file,time_s\nc0.npy,1\nc1.npy,0.5\n")
    with pytest.raises(InputError, match=r"c1\.npy.*earlier than.*sheet's order"):
        open_sequence(tmp_path / "bad.csv")
    (tmp_path / "bad2.csv").write_text("file,when\nc0.npy,1\n")
    with pytest.raises(ValueError, match="unknown column 'when'"):
        open_sequence(tmp_path / "bad2.csv")
    pages = np.stack([np.full((4, 4), 10 * k, np.uint16) for k in range(1, 4)])
    with tifffile.TiffWriter(tmp_path / "stack.tif") as tw:
        for k, page in enumerate(pages):
            tw.write(page, description=json.dumps({"kind": "bayer", "cfa_pattern": "RGGB",
                                                   "time_s": 0.2 * k}))  # fmt: skip
    seq = open_sequence(tmp_path / "stack.tif")
    assert seq.kind == "multipage" and len(seq) == 3 and seq.time_source == "name"
    assert np.allclose([f.time_s for f in seq], [0.0, 0.2, 0.4])
    cap = seq.read(1)  # one page decoded alone, through the capture reader
    assert cap.metadata["page"] == 1 and float(cap.mosaic.max()) == 20.0


def test_looks_complete_sees_a_half_written_file(tmp_path):
    data = _npy_bytes(np.arange(3 * 40 * 40, dtype=np.float64).reshape(3, 40, 40))
    p = tmp_path / "a.npy"
    p.write_bytes(data[: len(data) // 2])
    assert not looks_complete(p)
    p.write_bytes(data)
    assert looks_complete(p)
    tifffile.imwrite(tmp_path / "t.tif", np.ones((40, 40), np.uint16))
    whole = (tmp_path / "t.tif").read_bytes()
    (tmp_path / "t.tif").write_bytes(whole[: len(whole) - 100])
    assert not looks_complete(tmp_path / "t.tif")


# ---------------------------------------------------------------------------------------------
# sequences out


def test_store_appends_resumes_and_cuts_back(tmp_path):
    wl = np.linspace(430, 670, 5)
    rng = np.random.default_rng(0)
    cubes = rng.random((4, 5, 3, 4)).astype(np.float32)
    valid = np.ones((3, 4), bool)
    valid[0, 0] = False
    store = tmp_path / "s.zarr"
    with SequenceStore.open(store, wl, (3, 4)) as st:
        for k in range(3):
            st.append(
                cubes[k],
                valid,
                time_s=0.1 * k,
                source=f"f{k}",
                timestamp=None,
                findings=[Finding("fit.residual", "warning", "high", measured=0.2)],
            )
        with pytest.raises(InputError, match="f9.*not after the store's last frame"):
            st.append(cubes[3], valid, time_s=0.1, source="f9")
    # a writer killed between two .zarray updates: the longer arrays are cut back when opened
    za = json.loads((store / "cube" / ".zarray").read_text())
    za["shape"][0] = 4
    (store / "cube" / ".zarray").write_text(json.dumps(za))
    with SequenceStore.open(store, wl, (3, 4)) as st:
        assert len(st) == 3 and st.sources == ["f0", "f1", "f2"]
        st.append(cubes[3], valid, time_s=0.35, source="f3")
    ds = open_sequence_store(store)
    assert ds.cube.dims == ("time", "wavelength", "y", "x") and ds.sizes["time"] == 4
    assert np.allclose(ds.time.values, [0.0, 0.1, 0.2, 0.35])
    got = ds.cube.isel(time=2).values
    assert np.isnan(got[:, 0, 0]).all() and np.allclose(got[:, 1:, 1:], cubes[2][:, 1:, 1:])
    assert json.loads(ds.findings[0].values.item())[0]["code"] == "fit.residual"
    assert ds.valid.values[:, 0, 0].tolist() == [False] * 4
    frames = list(iter_store_frames(store, [3]))
    assert frames[0][0] == 3 and np.allclose(frames[0][2], cubes[3][:, :, :] * np.where(
        valid, 1, np.nan), equal_nan=True)  # fmt: skip
    gif = write_animated_preview(store, tmp_path / "p.gif")
    from PIL import Image

    with Image.open(gif) as im:
        assert im.n_frames == 4 and im.size == (4, 3)
    with pytest.raises(InputError, match="5 bands"):
        with SequenceStore.open(store, np.linspace(430, 670, 6), (3, 4)):
            pass


def test_the_viewer_reads_a_sequence_lazily(tmp_path):
    from hsi_torch.viewer.data import read_layers, spectrum_at

    wl = np.linspace(430, 670, 5)
    with SequenceStore.open(tmp_path / "sequence.zarr", wl, (3, 4)) as st:
        for k in range(3):
            st.append(np.full((5, 3, 4), 0.1 * (k + 1), np.float32), np.ones((3, 4), bool),
                      time_s=float(k), source=f"f{k}")  # fmt: skip
    (cube, kw, _), (rgb, rgb_kw, _) = read_layers(tmp_path / "sequence.zarr")
    assert cube.shape == (3, 5, 3, 4) and rgb.shape == (3, 3, 4, 3)
    assert not isinstance(cube, np.ndarray)  # lazy (Dask): one frame decoded when shown
    assert kw["axis_labels"][0] == "time" and rgb_kw["axis_labels"] == ["time", "y", "x"]
    assert kw["metadata"]["frames"] == ["f0", "f1", "f2"]
    sp = spectrum_at(cube, kw["metadata"], 1, 2, frame=2)
    assert sp is not None and np.allclose(sp.values, 0.3)
    assert np.asarray(rgb[1]).shape == (3, 4, 3)


# ---------------------------------------------------------------------------------------------
# reconstruct --sequence


def test_reconstruct_sequence_cli_resumes_and_matches_single_frames(tmp_path, bundle_path, capsys):
    shots = tmp_path / "shots"
    shots.mkdir()
    for k in range(3):
        np.save(shots / f"s_t={0.5 * k}s.npy", _frame(k))
    out = tmp_path / "out"
    cmd = ["reconstruct", "--bundle", str(bundle_path), "--out", str(out), "--no-progress", *SET]
    assert main([*cmd, str(shots)]) == 0  # a folder: detected as a sequence, and said
    assert "reconstructed as a sequence" in capsys.readouterr().out
    ds = open_sequence_store(out / "sequence.zarr")
    assert ds.sizes["time"] == 3 and np.allclose(ds.time.values, [0.0, 0.5, 1.0])
    assert ds.attrs["time_source"] == "name"
    for k in range(3):
        src = shots / f"s_t={0.5 * k}s.npy"
        assert ds.source.values[k] == str(src.resolve())
        ref = _cold(bundle_path, src).numpy()
        assert np.allclose(ds.cube.isel(time=k).values, ref, rtol=1e-5, atol=1e-6,
                           equal_nan=True)  # fmt: skip
        meta = json.loads(ds.metadata[k].values.item())
        assert meta["time_s"] == 0.5 * k and meta["stats"]["num_valid"] > 0
        assert isinstance(json.loads(ds.findings[k].values.item()), list)
    assert (out / "sequence_preview.gif").is_file()
    # a new frame: the rerun skips the three and appends it
    np.save(shots / "s_t=1.5s.npy", _frame(3))
    assert main([*cmd, "--sequence", str(shots / "*.npy")]) == 0
    report = capsys.readouterr().err
    assert "1 processed, 3 skipped" in report
    ds = open_sequence_store(out / "sequence.zarr")
    assert ds.sizes["time"] == 4 and float(ds.time[-1]) == 1.5
    # the store grows forward only: an earlier frame cannot be added afterwards
    np.save(shots / "s_t=0.2s.npy", _frame(4))
    assert main([*cmd, str(shots)]) == 1
    assert "only grows forward in time" in capsys.readouterr().err
    # and the Python iterator gives the same cubes, frame by frame
    rec = Reconstructor(bundle_path, dtype=torch.float64, beta=0.0)
    it = sequence_cubes(rec, [shots / "s_t=0.0s.npy", shots / "s_t=0.5s.npy"])
    frame, res = next(it)
    assert frame.time_s == 0.0
    ref = _cold(bundle_path, shots / "s_t=0.0s.npy")
    assert torch.allclose(torch.where(res.valid, res.cube, torch.nan), ref, equal_nan=True)


def test_multipage_tiff_frames_are_reconstructed_page_by_page(tmp_path, bundle_path):
    frames = [_frame(k) for k in range(2)]
    with tifffile.TiffWriter(tmp_path / "burst.tif") as tw:
        for k, f in enumerate(frames):
            tw.write(np.ascontiguousarray(f.transpose(1, 2, 0)), photometric="rgb",
                     description=json.dumps({"time_s": 0.04 * k}))  # fmt: skip
    for k, f in enumerate(frames):  # the same images as single files: the reference
        np.save(tmp_path / f"single{k}.npy", f)
    out = tmp_path / "out"
    assert main(["reconstruct", "--bundle", str(bundle_path), "--out", str(out), "--no-progress",
                 *SET, str(tmp_path / "burst.tif")]) == 0  # fmt: skip
    ds = open_sequence_store(out / "sequence.zarr")
    assert ds.sizes["time"] == 2 and np.allclose(ds.time.values, [0.0, 0.04])
    assert ds.source.values[1].endswith("burst.tif#page=1")
    for k in range(2):
        ref = _cold(bundle_path, tmp_path / f"single{k}.npy").numpy()
        assert np.allclose(ds.cube.isel(time=k).values, ref, rtol=1e-5, atol=1e-6,
                           equal_nan=True)  # fmt: skip


# ---------------------------------------------------------------------------------------------
# hsi-torch watch


def test_watch_waits_for_a_half_written_file(tmp_path, bundle_path, capsys):
    live = tmp_path / "tether"
    live.mkdir()
    names = [f"cap_t={k}s.npy" for k in range(3)]
    frames = [_frame(k) for k in range(3)]

    def camera() -> None:
        time.sleep(0.3)
        (live / names[0]).write_bytes(_npy_bytes(frames[0]))
        time.sleep(0.3)
        data = _npy_bytes(frames[1])  # written in two parts with a pause longer than settle_s
        with open(live / names[1], "wb") as f:
            f.write(data[: len(data) // 2])
            f.flush()
            time.sleep(1.2)
            f.write(data[len(data) // 2 :])
        time.sleep(0.2)
        (live / "cap_t=2s.npy.part").write_bytes(_npy_bytes(frames[2]))  # a temporary name
        time.sleep(0.3)
        (live / "cap_t=2s.npy.part").rename(live / names[2])

    th = threading.Thread(target=camera)
    th.start()
    cfg = ReconstructConfig(dtype="float64", beta=0.0)
    try:
        summary = watch_folder(live, bundle_path, tmp_path / "out", cfg, max_frames=3,
                               idle_timeout_s=20, settle_s=0.3, poll_s=0.05)  # fmt: skip
    finally:
        th.join()
    assert summary.ok, summary.report()
    assert len(summary.processed) == 3
    out = capsys.readouterr().out
    assert "frame 1: cap_t=1s.npy" in out and ("keeping up" in out or "behind" in out)
    ds = open_sequence_store(tmp_path / "out" / "sequence.zarr")
    assert ds.sizes["time"] == 3 and ds.time.values.tolist() == [0.0, 1.0, 2.0]
    for k in range(3):  # each frame whole: the cube of the complete file
        ref = _cold(bundle_path, live / names[k]).numpy()
        assert np.allclose(ds.cube.isel(time=k).values, ref, rtol=1e-5, atol=1e-6,
                           equal_nan=True)  # fmt: skip
    assert (tmp_path / "out" / "latest_preview.png").is_file()
    assert (tmp_path / "out" / "sequence_preview.gif").is_file()
    # a batch run resumes the watch's store: nothing left to do, then one more frame
    np.save(live / "cap_t=3s.npy", _frame(3))
    assert main(["reconstruct", "--bundle", str(bundle_path), "--out", str(tmp_path / "out"),
                 "--no-progress", *SET, "--sequence", str(live)]) == 0  # fmt: skip
    assert "1 processed, 3 skipped" in capsys.readouterr().err
    assert open_sequence_store(tmp_path / "out" / "sequence.zarr").sizes["time"] == 4


def test_watcher_stops_when_idle_and_skips_known_files(tmp_path):
    np.save(tmp_path / "a.npy", np.zeros((3, 4, 4)))
    np.save(tmp_path / "b.npy", np.zeros((3, 4, 4)))
    w = FolderWatcher(tmp_path, settle_s=0.05, poll_s=0.02, idle_timeout_s=0.3,
                      known={str((tmp_path / "a.npy").resolve())})  # fmt: skip
    got = [p.name for p in w.files()]
    assert got == ["b.npy"] and "idle-timeout" in (w.stop_reason or "")
    # an abandoned half-written file is given up (reported), not waited for forever
    data = _npy_bytes(np.zeros((3, 40, 40)))
    (tmp_path / "c.npy").write_bytes(data[: len(data) // 2])
    w = FolderWatcher(
        tmp_path,
        settle_s=0.05,
        poll_s=0.02,
        idle_timeout_s=0.6,
        stale_s=0.2,
        known={str((tmp_path / n).resolve()) for n in ("a.npy", "b.npy")},
    )
    assert list(w.files()) == [] and [p.name for p, _ in w.given_up] == ["c.npy"]
    stop = threading.Event()
    stop.set()  # e.g. Ctrl-C in another thread
    w = FolderWatcher(tmp_path, stop=stop)
    assert list(w.files()) == [] and w.stop_reason == "stopped"
    with pytest.raises(InputError, match="not a folder"):
        FolderWatcher(tmp_path / "a.npy")
