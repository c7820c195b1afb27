"""Batch reconstruction on Dask workers (``--scheduler``) and into one Zarr store (``--format``).

Every test here runs on small-prototype frames (the shipped simulator's 400 x 384 px sensor, one
ColorChecker capture rendered once per module and varied in brightness and noise) with the oracle
bundle. The cluster tests share one ``LocalCluster`` of 2 worker processes with one thread each
(what CI's 2 cores hold); they skip cleanly where Dask is not installed.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from hsi_torch.cli import main
from hsi_torch.io import load_cube, read_capture, write_capture
from hsi_torch.recon.batch import reconstruct_many
from hsi_torch.recon.distributed import connect, parse_scheduler
from hsi_torch.simulate.oracle import bundle_from_truth

ROOT = Path(__file__).resolve().parents[1]
# cube files and the preview; no spectra plot (its PNG holds matplotlib's date)
_FILES = ["formats=[npz, tiff]", "preview=true"]
_FACTORS = (1.0, 0.8, 0.65, 0.9, 0.75, 0.55)


@pytest.fixture(scope="module")
def frames(tmp_path_factory) -> tuple[Path, list[Path]]:
    """The oracle bundle of the small prototype and six captures of its ColorChecker scene
    (brightness x 1.0 ... 0.55, each with its own Poisson noise): ``(bundle, [capture, ...])``."""
    root = tmp_path_factory.mktemp("frames")
    sim = root / "sim"
    rc = main(["-q", "simulate", "--out", str(sim),
               "--set", "captures.scan_wavelengths_nm=[]", "--set", "captures.white_shots=0",
               "--set", "captures.grid.poses=[]", "--set", "captures.dark_frames=0",
               "--set", "render.figures=false", "--set", "render.dtype=float32"])  # fmt: skip
    assert rc == 0
    bundle = root / "oracle.npz"
    bundle_from_truth(sim).save(bundle)
    img, meta = read_capture(sim / "scenes" / "colorchecker.tif")
    black = float(meta["black_level"])
    g = np.random.default_rng(0)
    caps = root / "caps"
    paths = []
    for k, f in enumerate(_FACTORS):
        signal_dn = (img.numpy().astype(np.float64) - black).clip(0) * f
        dn = black + g.poisson(signal_dn)
        paths.append(write_capture(caps / f"shot{k}.tif", dn.clip(0, 65535), dict(meta)))
    return bundle, paths


@pytest.fixture(scope="module")
def serial(frames, tmp_path_factory) -> Path:
    """The serial run's outputs for every frame (the reference of the distributed runs)."""
    bundle, caps = frames
    out = tmp_path_factory.mktemp("serial")
    s = reconstruct_many(caps, bundle, out, overrides=_FILES, progress=False)
    assert s.exit_code == 0 and len(s.processed) == len(caps)
    return out


@pytest.fixture(scope="module")
def client():
    """A ``LocalCluster`` of 2 worker processes, one task thread each, for the module (as
    ``--scheduler local:2`` makes it)."""
    pytest.importorskip("distributed")
    nanny_vars = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS",
                  "MALLOC_TRIM_THRESHOLD_", "PYTHONHASHSEED")  # fmt: skip
    before = {k: os.environ.get(k) for k in nanny_vars}
    with connect("local:2") as (cl, _):
        yield cl
    # the variables a nanny sets in its parent's environment do not leak into later tests
    assert {k: os.environ.get(k) for k in nanny_vars} == before


def _same_cube(a: Path, b: Path) -> None:
    """Two cube files hold the same cube, mask, wavelengths and (timings and run aside)
    metadata."""
    ca, cb = load_cube(a), load_cube(b)
    assert torch.equal(ca.valid, cb.valid), (a, b)
    assert np.array_equal(ca.cube.numpy(), cb.cube.numpy(), equal_nan=True), (a, b)
    assert torch.equal(ca.wavelengths, cb.wavelengths)
    ma, mb = dict(ca.metadata), dict(cb.metadata)
    for m in (ma, mb):
        m.pop("timings_s", None)
        m.pop("run_config", None)
    assert ma == mb


def _same_outputs(out: Path, ref: Path, stems: list[str]) -> None:
    for stem in stems:
        for suf in (".npz", ".tif"):
            _same_cube(out / f"{stem}{suf}", ref / f"{stem}{suf}")
        png = f"{stem}_preview.png"
        assert (out / png).read_bytes() == (ref / png).read_bytes(), png


def _temp_files(out: Path) -> list[Path]:
    return [p for p in out.rglob(".*.tmp")]


def test_dask_two_workers_same_outputs_as_serial(frames, serial, client, tmp_path):
    bundle, caps = frames
    out = tmp_path / "out"
    s = reconstruct_many(caps, bundle, out, client=client, overrides=_FILES, progress=False)
    assert s.exit_code == 0 and s.processed == caps and not s.failed
    _same_outputs(out, serial, [p.stem for p in caps])
    assert not _temp_files(out)
    # the bundle was prepared once per worker process, not once per frame, and both worked
    assert 1 <= len(s.prepare_s) <= 2 < len(caps)
    assert len(set(s.workers.values())) == 2
    # the workers run without the nanny's malloc setting (see docs/cluster.md)
    assert set(client.run(os.environ.get, "MALLOC_TRIM_THRESHOLD_").values()) == {None}
    # one torch and one numba thread per frame (2 workers on 2 cores)
    assert all(t == {"torch": 1, "numba": 1} for t in s.threads.values()), s.threads
    # a second run on the warm workers: nothing prepared again (resume off: every frame redone)
    s2 = reconstruct_many(caps[:2], bundle, out, client=client, overrides=_FILES,
                          progress=False, resume=False)  # fmt: skip
    assert s2.exit_code == 0 and s2.prepare_s == {}
    _same_outputs(out, serial, [p.stem for p in caps[:2]])


def test_dask_bad_input_reported_others_written(frames, serial, client, tmp_path):
    bundle, caps = frames
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "corrupt.tif").write_bytes(b"II*\x00garbage")
    np.save(bad / "small.npy", np.zeros((3, 30, 30), np.float32))  # not the sensor's size
    inputs = [caps[0], bad / "corrupt.tif", caps[1], bad / "small.npy", bad / "missing.tif"]
    out = tmp_path / "out"
    s = reconstruct_many(inputs, bundle, out, client=client, overrides=_FILES, progress=False)
    assert s.exit_code == 1
    assert s.processed == [caps[0], caps[1]]
    failed = {f.input.name: f.error for f in s.failed}
    assert set(failed) == {"corrupt.tif", "small.npy", "missing.tif"}
    assert "corrupt.tif" in failed["corrupt.tif"]
    assert "30" in failed["small.npy"]  # the size mismatch is named
    assert "not found" in failed["missing.tif"]
    _same_outputs(out, serial, [caps[0].stem, caps[1].stem])
    assert not any(p.name.startswith(("corrupt", "small", "missing")) for p in out.iterdir())
    assert "FAILED" in s.report() and "corrupt.tif" in s.report()


def test_dask_worker_killed_mid_run_outputs_complete(frames, serial, client, tmp_path):
    """A worker process killed (SIGKILL) while it reconstructs a frame: its task is retried on
    another worker (or the restarted one); every output ends complete, no temporary file is
    left, nothing failed."""
    bundle, caps = frames
    out = tmp_path / "out"
    pids = client.run(os.getpid)  # worker address -> process id
    killed: list[int] = []

    def killer() -> None:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not killed:
            # after the first frame is written (bundles prepared), kill a worker that is busy
            if any(out.glob("*_preview.png")):
                busy = [a for a, keys in client.processing().items() if keys and a in pids]
                if busy:
                    os.kill(pids[busy[0]], signal.SIGKILL)
                    killed.append(pids[busy[0]])
                    return
            time.sleep(0.005)

    t = threading.Thread(target=killer, daemon=True)
    t.start()
    s = reconstruct_many(caps, bundle, out, client=client, overrides=_FILES, progress=False)
    t.join()
    client.wait_for_workers(2, timeout=60)  # the nanny restarts it for the other tests
    assert killed, "no worker was busy to be killed"
    assert s.exit_code == 0 and s.processed == caps, s.report()
    _same_outputs(out, serial, [p.stem for p in caps])
    assert not _temp_files(out)
    # the resume markers say done for all: a rerun skips everything
    s2 = reconstruct_many(caps, bundle, out, client=client, overrides=_FILES, progress=False)
    assert s2.skipped == caps and not s2.processed


def test_dask_resume(frames, serial, client, tmp_path):
    """An interrupted run (the first three frames written, a dead writer's temporary file left)
    is completed by a rerun that skips what is done; a changed input or a damaged output is
    redone."""
    bundle, caps = frames
    out = tmp_path / "out"
    s1 = reconstruct_many(caps[:3], bundle, out, client=client, overrides=_FILES,
                          progress=False)  # fmt: skip
    assert s1.exit_code == 0
    stale = out / ".shot3.npz.999999999-abcdef.tmp"  # a killed writer's (no such process)
    stale.write_bytes(b"partial")
    with open(out / "shot1.npz", "r+b") as f:  # damaged after the run
        f.truncate(100)
    # (the bundle's bytes sent to the workers this time: the same content, the same outputs)
    s2 = reconstruct_many(caps, bundle, out, client=client, overrides=_FILES, progress=False,
                          send_bundle=True)  # fmt: skip
    assert s2.exit_code == 0
    assert s2.skipped == [caps[0], caps[2]]
    assert s2.processed == [caps[1]] + caps[3:]
    assert stale in s2.cleaned and not stale.exists()
    _same_outputs(out, serial, [p.stem for p in caps])


def test_cli_zarr_store_on_a_running_scheduler(frames, serial, client, tmp_path, capsys):
    """``--scheduler tcp://...`` ``--format zarr``: one store, one frame per input; it opens in
    xarray with the bundle's wavelengths and equals the per-file cubes; the failed input's frame
    is not ``done``; a rerun resumes."""
    xr = pytest.importorskip("xarray")
    bundle, caps = frames
    bad = tmp_path / "corrupt.tif"
    bad.write_bytes(b"II*\x00garbage")
    inputs = [str(caps[0]), str(bad), str(caps[1]), str(caps[2])]
    out = tmp_path / "out"
    argv = ["reconstruct", "--bundle", str(bundle), "--out", str(out), "--no-progress",
            "--scheduler", client.scheduler.address, "--format", "zarr", *inputs]  # fmt: skip
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert "FAILED" in err and "corrupt.tif" in err and "3 processed" in err
    ds = xr.open_zarr(out / "cubes.zarr")
    ref = load_cube(serial / f"{caps[0].stem}.npz")
    np.testing.assert_array_equal(ds.wavelength.values, ref.wavelengths.numpy())
    assert ds.wavelength.attrs["units"] == "nm"
    assert ds.cube.dims == ("frame", "wavelength", "y", "x")
    assert ds.cube.chunks[0] == (1,) * 4  # one frame per chunk
    assert list(ds.done.values) == [True, False, True, True]
    assert list(ds.source.values) == [os.path.abspath(p) for p in inputs]
    for i, cap in ((0, caps[0]), (2, caps[1]), (3, caps[2])):
        c = load_cube(serial / f"{cap.stem}.npz")
        np.testing.assert_array_equal(ds.cube[i].values, c.cube.numpy())
        np.testing.assert_array_equal(ds.valid[i].values, c.valid.numpy())
        meta = json.loads(str(ds.metadata[i].values))
        assert meta["source"] == str(cap) and meta["frame"] == i
        assert meta["stats"] == c.metadata["stats"]
    assert np.isnan(ds.cube[1].values).all() and not ds.valid[1].values.any()
    ds.close()
    # resume, through the scheduler file a scheduler writes (dask scheduler --scheduler-file):
    # the complete frames are skipped, the bad one fails again
    sched = tmp_path / "scheduler.json"
    sched.write_text(json.dumps({"type": "Scheduler", "address": client.scheduler.address}))
    i = argv.index("--scheduler")
    assert main(argv[:i] + ["--scheduler-file", str(sched)] + argv[i + 2:]) == 1
    assert "3 skipped" in capsys.readouterr().err


def test_cli_local_cluster_started_and_stopped(frames, serial, tmp_path, capsys):
    """``--scheduler local:2`` starts 2 worker processes for the run and stops them."""
    pytest.importorskip("distributed")
    bundle, caps = frames
    out = tmp_path / "out"
    argv = ["reconstruct", "--bundle", str(bundle), "--out", str(out), "--no-progress",
            "--scheduler", "local:2", *[a for o in _FILES for a in ("--set", o)],
            str(caps[0]), str(caps[1])]  # fmt: skip
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert "2 processed" in err and "once per worker" in err
    _same_outputs(out, serial, [caps[0].stem, caps[1].stem])


def _run_python(code: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                          timeout=300)  # fmt: skip


def test_without_scheduler_dask_is_not_imported(frames, tmp_path):
    """The serial run and the dataset store without a cluster never load Dask."""
    bundle, caps = frames
    code = (
        "import sys\nfrom hsi_torch.cli import main\n"
        f"a = main(['-q', 'reconstruct', '--bundle', {str(bundle)!r}, '--out', "
        f"{str(tmp_path / 'a')!r}, '--no-progress', '--set', 'formats=[npz]', {str(caps[0])!r}])\n"
        f"b = main(['-q', 'reconstruct', '--bundle', {str(bundle)!r}, '--out', "
        f"{str(tmp_path / 'b')!r}, '--no-progress', '--format', 'zarr', {str(caps[0])!r}])\n"
        "print(a, b, sorted(m for m in sys.modules if m.split('.')[0] in ('dask', "
        "'distributed')))\n"
    )
    r = _run_python(code)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["0", "0", "[]"]
    assert (tmp_path / "a" / f"{caps[0].stem}.npz").is_file()
    assert (tmp_path / "b" / "cubes.zarr" / ".zmetadata").is_file()


def test_scheduler_without_dask_says_what_to_install(frames, tmp_path):
    bundle, caps = frames
    code = (
        "import sys\nsys.modules['distributed'] = None\nfrom hsi_torch.cli import main\n"
        f"sys.exit(main(['reconstruct', '--bundle', {str(bundle)!r}, '--out', "
        f"{str(tmp_path)!r}, '--scheduler', 'local:2', {str(caps[0])!r}]))\n"
    )
    r = _run_python(code)
    assert r.returncode != 0
    assert "hsi-torch[cluster]" in r.stderr


@pytest.mark.parametrize("spec, expected", [
    ("local:3", ("local", 3)),
    ("tcp://head:8786", ("address", "tcp://head:8786")),
    ("tls://10.0.0.1:8786", ("address", "tls://10.0.0.1:8786")),
])  # fmt: skip
def test_parse_scheduler(spec, expected):
    assert parse_scheduler(spec) == expected


@pytest.mark.parametrize("spec", ["local:0", "local", "head:8786", "4"])
def test_parse_scheduler_rejects(spec):
    with pytest.raises(ValueError, match="local:N"):
        parse_scheduler(spec)

