"""Crash safety of ``hsi-torch reconstruct``: SIGKILL at random moments of a batch run.

For several fixed seeds a batch run over a dozen small captures (in a subprocess) is killed with
SIGKILL (no cleanup code runs) at a random moment: after a random number of finished inputs, a
random part of the next one. Afterwards every output that exists must be complete and readable
(cubes load, previews decode, markers parse, a "done" marker's outputs are all there), and a
rerun into the same folder must finish the batch with exit 0, leave no temporary file, and give
exactly the cubes of an uninterrupted run. ``HSI_SHOW_KILLS=1 pytest -s`` prints what each kill
left behind.
"""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from test_pipeline import make_bundle, render_capture, true_spectra

from hsi_torch.cli import main
from hsi_torch.io import load_cube, write_capture
from hsi_torch.recon.batch.targets import DONE_DIR

REPO = Path(__file__).resolve().parents[1]
NUM_FRAMES = 12
SEEDS = [0, 1, 2, 3, 4]

pytestmark = pytest.mark.skipif(os.name == "nt", reason="SIGKILL is POSIX")


def _command(bundle: Path, out: Path, inputs: list[Path]) -> list[str]:
    return [sys.executable, "-m", "hsi_torch", "reconstruct", "--bundle", str(bundle),
            "--out", str(out), "--no-progress", "--set", "beta=0", "--set", "dtype=float64",
            *map(str, inputs)]  # fmt: skip


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    return env


@pytest.fixture(scope="module")
def batch(tmp_path_factory):
    """A bundle, the captures, an uninterrupted reference run and its processing window (s)."""
    d = tmp_path_factory.mktemp("crash")
    b = make_bundle(white_exposure_s=0.01)
    bpath = d / "calib.npz"
    b.save(bpath)
    caps = d / "caps"
    caps.mkdir()
    inputs = []
    for i in range(NUM_FRAMES):
        img = render_capture(b, true_spectra(seed=i))
        if i % 3 == 0:  # some uint16 TIFFs, the rest float NPY
            p = write_capture(caps / f"f{i:02d}.tif", (img * 50).round().clamp(0, 65535).numpy(),
                              {"kind": "rgb", "exposure_s": 0.02})
        else:
            p = caps / f"f{i:02d}.npy"
            np.save(p, img.numpy())
        inputs.append(p)
    ref = d / "ref"
    t0 = time.perf_counter()
    assert main(_command(bpath, ref, inputs)[3:]) == 0  # in this process: no start-up time
    window = time.perf_counter() - t0  # about what the killed runs spend on the inputs
    return bpath, inputs, ref, window


def _wait_for_run_record(out: Path, proc: subprocess.Popen, t0: float) -> float:
    """Time at which the run's configuration record appeared (processing starts right after)."""
    while time.perf_counter() - t0 < 120:
        if (out / "runs").is_dir() and any((out / "runs").glob("*.yaml")):
            return time.perf_counter()
        if proc.poll() is not None:
            return time.perf_counter()
        time.sleep(0.005)
    raise AssertionError("the run did not start within 120 s")


def _finished(out: Path) -> int:
    """Inputs whose marker says done."""
    n = 0
    for r in (out / "runs").glob("*.yaml") if (out / "runs").is_dir() else []:
        assert yaml.safe_load(r.read_text())["beta"] == 0.0, r  # the run's record, complete
    for m in (out / DONE_DIR).glob("*.json") if (out / DONE_DIR).is_dir() else []:
        try:
            n += json.loads(m.read_text()).get("status") == "done"
        except (OSError, ValueError):
            pass
    return n


def _outputs(out: Path) -> list[Path]:
    return sorted(p for p in out.iterdir() if p.is_file() and not p.name.startswith("."))


def _check_readable(out: Path) -> None:
    """Every output present is complete: cubes load, PNGs decode, markers are whole JSON."""
    import cv2

    for p in _outputs(out):
        if p.suffix in (".npz", ".tif"):
            c = load_cube(p)
            assert c.cube.shape == (8, 20, 20), p
        elif p.suffix == ".hdr":  # the ENVI pair (the .img is written first, then the .hdr)
            assert load_cube(p).cube.shape == (8, 20, 20), p
        elif p.suffix == ".png":
            assert cv2.imread(str(p), cv2.IMREAD_UNCHANGED) is not None, p
    for r in (out / "runs").glob("*.yaml") if (out / "runs").is_dir() else []:
        assert yaml.safe_load(r.read_text())["beta"] == 0.0, r  # the run's record, complete
    for m in (out / DONE_DIR).glob("*.json") if (out / DONE_DIR).is_dir() else []:
        rec = json.loads(m.read_text())
        if rec["status"] == "done":
            for q in rec["outputs"]:
                assert (out / q).is_file(), (m, q)  # relative to --out


@pytest.mark.parametrize("seed", SEEDS)
def test_sigkill_at_a_random_moment_then_rerun(batch, tmp_path, capsys, seed):
    bpath, inputs, ref, window = batch
    rng = random.Random(seed)
    out = tmp_path / "out"
    t0 = time.perf_counter()
    proc = subprocess.Popen(_command(bpath, out, inputs), env=_env(),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    t_start = _wait_for_run_record(out, proc, t0)
    # a random moment: after a random number of finished inputs, a random part of the next one
    k = rng.randrange(NUM_FRAMES)
    while _finished(out) < k and proc.poll() is None and time.perf_counter() - t0 < 200:
        time.sleep(0.002)
    delay = rng.uniform(0.0, 1.5 * window / NUM_FRAMES)
    time.sleep(delay)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=60)
    if out.is_dir():
        _check_readable(out)
        left = [p for p in out.rglob("*") if p.is_file()]
        if os.environ.get("HSI_SHOW_KILLS") == "1":  # what each kill left, for the curious
            with capsys.disabled():
                print(f"seed {seed}: killed {delay:.3f} s after {k} finished input(s): "
                      f"{len(_outputs(out))} outputs, "
                      f"{sum(p.name.endswith('.tmp') for p in left)} temporary files, "
                      f"{len(list(out.glob(DONE_DIR + '/*.json')))} markers")
    # the rerun (in this process) completes the batch and leaves nothing behind
    capsys.readouterr()
    assert main(_command(bpath, out, inputs)[3:]) == 0
    err = capsys.readouterr().err
    assert f"{NUM_FRAMES} input(s)" in err and "0 failed" in err
    assert not [p for p in out.rglob("*") if p.name.endswith(".tmp")]
    _check_readable(out)
    names = sorted(p.name for p in _outputs(out))
    assert names == sorted(p.name for p in _outputs(ref))
    markers = [json.loads(m.read_text()) for m in (out / DONE_DIR).glob("*.json")]
    assert len(markers) == NUM_FRAMES and all(m["status"] == "done" for m in markers)
    for p in inputs:  # the same cubes as the uninterrupted run
        a, r = load_cube(out / f"{p.stem}.npz"), load_cube(ref / f"{p.stem}.npz")
        torch.testing.assert_close(a.cube, r.cube, equal_nan=True, rtol=0, atol=0)
    assert time.perf_counter() - t_start < 300
