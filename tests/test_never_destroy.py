"""The whole command line pointed at its own inputs: every command refuses (or writes beside
them) and not one byte of what the user had changes — simulate, calibrate, reconstruct in this
process and on a two-worker Dask cluster."""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import pytest

from hsi_torch.cli import main


def _snapshot(folder: Path) -> dict[str, str]:
    """SHA-256 of every file below ``folder`` (relative path → digest)."""
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}  # fmt: skip


@pytest.fixture(scope="module")
def sim(small_sim: Path, small_sim_calib: Path, tmp_path_factory) -> Path:
    """``sim/`` (the small prototype's set) and ``calib/`` (its calibration): copies of the
    session's shared ones (the tests copy this folder again before pointing commands at it)."""
    root = tmp_path_factory.mktemp("never_destroy")
    shutil.copytree(small_sim, root / "sim")
    shutil.copytree(small_sim_calib, root / "calib")
    return root


def _has_dask() -> bool:
    try:
        import distributed  # noqa: F401
    except ModuleNotFoundError:
        return False
    return True


@pytest.mark.slow
@pytest.mark.parametrize("scheduler", [None, "local:2"])
def test_out_pointing_at_the_inputs_changes_no_input_byte(sim: Path, tmp_path: Path, scheduler,
                                                          capsys):  # fmt: skip
    if scheduler and not _has_dask():
        pytest.skip("Dask (distributed) is not installed")
    work = tmp_path / "w"
    shutil.copytree(sim, work)
    caps, calib = work / "sim", work / "calib"
    before = _snapshot(work)
    scenes = sorted((caps / "scenes").glob("*.tif"))
    assert scenes

    # simulate into the existing capture set: refused without --overwrite
    assert main(["simulate", "--out", str(caps), "--no-progress", "-q"]) == 1
    # calibrate into the capture set itself: its own files are inputs
    assert main(["calibrate", "--captures", str(caps), "--out", str(caps), "--no-progress",
                 "-q"]) == 1  # fmt: skip
    # reconstruct into the inputs' folder: <stem>.tif would be the input itself
    extra = ["--scheduler", scheduler] if scheduler else []
    code = main(["reconstruct", "--bundle", str(calib / "calib.npz"), "--out",
                 str(caps / "scenes"), "--no-progress", *extra, *map(str, scenes)])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 1
    assert "input" in err and scenes[0].name in err
    # and into the bundle's folder, with a scene named like the bundle's files
    twin = work / "calib.tif"
    shutil.copy(scenes[0], twin)
    before_twin = _snapshot(work)
    code = main(["reconstruct", "--bundle", str(calib / "calib.npz"), "--out", str(work),
                 "--no-progress", *extra, str(twin)])  # fmt: skip
    capsys.readouterr()
    assert code == 1  # work/calib.tif is the input: refused, not replaced by its cube

    after = _snapshot(work)
    changed = [k for k, v in before_twin.items() if after.get(k) != v]
    assert not changed, f"input files changed: {changed}"
    assert all(after.get(k) == v for k, v in before.items())


def _small_run(tmp_path: Path) -> tuple[Path, Path]:
    import numpy as np
    from test_pipeline import make_bundle, render_capture, true_spectra

    bundle = make_bundle(white_exposure_s=0.01)
    bpath = tmp_path / "calib.npz"
    bundle.save(bpath)
    np.save(tmp_path / "a.npy", render_capture(bundle, true_spectra()).numpy())
    return bpath, tmp_path / "a.npy"


def test_a_rerun_that_fails_while_writing_keeps_the_earlier_outputs(tmp_path, monkeypatch,
                                                                     capsys):  # fmt: skip
    """D5: the disk fills up while the rerun writes its preview: every earlier output of that
    input is kept byte for byte, and no staged file is left."""
    import errno

    from hsi_torch import colour

    bpath, inp = _small_run(tmp_path)
    out = tmp_path / "out"
    argv = ["reconstruct", "--bundle", str(bpath), "--out", str(out), "--no-progress", str(inp)]
    assert main(argv) == 0
    before = _snapshot(out)
    assert any(k.endswith("a_preview.png") for k in before)

    def full_disk(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(colour, "save_preview_png", full_disk)
    assert main([*argv[:-1], "--no-resume", "--set", "beta=100", str(inp)]) == 1
    assert "No space left on device" in capsys.readouterr().err
    after = _snapshot(out)
    kept = {k: v for k, v in before.items() if not k.startswith((".hsi_torch_done", "runs/"))}
    assert all(after.get(k) == v for k, v in kept.items()), "an earlier output changed"
    assert not [p for p in out.rglob("*") if p.name.endswith(".tmp")]


def test_an_output_that_is_an_input_is_refused_before_any_work(tmp_path, capsys):
    """D1: the run's output for an input would be the input itself (``--out`` its own folder);
    the input fails at once, its bytes unchanged, and another input still runs."""
    bpath, inp = _small_run(tmp_path)
    same = tmp_path / "same"
    same.mkdir()
    own = same / "a.npz"  # an NPZ capture: its cube file would be same/a.npz
    import numpy as np

    np.savez(own, image=np.load(inp))
    digest = hashlib.sha256(own.read_bytes()).hexdigest()
    other = inp.with_name("b.npy")  # another input (whose outputs are b.*) still runs
    inp.rename(other)
    code = main(["reconstruct", "--bundle", str(bpath), "--out", str(same), "--no-progress",
                 str(own), str(other)])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 1
    assert "refusing to write" in err and "a.npz" in err and "1 processed" in err
    assert hashlib.sha256(own.read_bytes()).hexdigest() == digest


def test_a_file_the_run_did_not_write_is_never_written_over(tmp_path, capsys):
    """A lab's folder holds ``a.npy`` (reconstructed into its own folder) and its own ``a.tif``
    (another capture of the same shot, not an input of this run): the ``a.tif`` cube would
    replace it. Before the fix it did, exit 0. Now that input fails naming the file, the file is
    unchanged and another input still runs; the run's own earlier outputs stay replaceable
    (a rerun with ``--no-resume``, the ``_std`` files of an earlier run with ``uncertainty``)."""
    bpath, inp = _small_run(tmp_path)
    theirs = tmp_path / "a.tif"
    theirs.write_bytes(b"the lab's own TIFF of the same shot")
    other = shutil.copy(inp, tmp_path / "b.npy")
    base = ["reconstruct", "--bundle", str(bpath), "--out", str(tmp_path), "--no-progress"]
    assert main([*base, str(inp), str(other)]) == 1
    err = capsys.readouterr().err
    assert "refusing to write over a.tif" in err and "not written there" in err
    assert "1 processed" in err and "1 failed" in err
    assert theirs.read_bytes() == b"the lab's own TIFF of the same shot"
    assert not (tmp_path / "a.npz").exists()  # nothing of that input was written

    # the run's own outputs: a rerun replaces them, with or without the _std files
    out = tmp_path / "out"
    run = ["reconstruct", "--bundle", str(bpath), "--out", str(out), "--no-progress"]
    assert main([*run, "--set", "uncertainty=true", str(inp)]) == 0
    assert main([*run, "--no-resume", str(inp)]) == 0
    assert main([*run, "--set", "uncertainty=true", str(inp)]) == 0
    capsys.readouterr()
    # a file put there by someone else is refused even after the run's own files
    (out / "a_spectra.png").write_bytes(b"someone's plot")
    assert main([*run, "--set", "spectra_pixels=[[1, 1]]", str(inp)]) == 1
    assert "refusing to write over a_spectra.png" in capsys.readouterr().err
    assert (out / "a_spectra.png").read_bytes() == b"someone's plot"


def test_demo_into_a_folder_with_the_users_files_is_refused(tmp_path, capsys):
    """``hsi-torch demo --out lab/`` on a folder holding the lab's own ``calib.npz``,
    ``summary.json`` and ``colorchecker.tif`` replaced all three, exit 0. Now it is refused up
    front, naming them; an earlier demo run (its marker or its summary) may be replaced."""
    from hsi_torch.experiments.cli_entry import DEMO_MARKER, check_demo_out

    mine = {"calib.npz": b"my bundle", "summary.json": b'{"mine": 1}',
            "colorchecker.tif": b"my capture"}  # fmt: skip
    lab = _users_folder(tmp_path / "lab", mine)
    assert main(["demo", "--quick", "--out", str(lab), "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert "is not empty (calib.npz, colorchecker.tif, summary.json)" in err
    assert "holds no earlier demo run" in err
    assert {p.name: p.read_bytes() for p in lab.iterdir()} == mine
    # what may be replaced: an empty or new folder, an earlier demo run
    check_demo_out(tmp_path / "new")
    (tmp_path / "empty").mkdir()
    check_demo_out(tmp_path / "empty")
    old = tmp_path / "old_demo"
    old.mkdir()
    (old / "summary.json").write_text('{"scenes": {}, "files": ["calib.npz"]}')
    (old / "calib.npz").write_bytes(b"the demo's")
    check_demo_out(old)
    killed = tmp_path / "killed"
    killed.mkdir()
    (killed / DEMO_MARKER).write_text("")
    (killed / "calib.npz").write_bytes(b"the demo's, before it was stopped")
    check_demo_out(killed)


def test_calibrate_out_naming_a_file_that_is_not_a_bundle_is_refused(tmp_path, capsys):
    """``calibrate --out lab/results.npz`` where ``results.npz`` is the lab's own file (not a
    bundle) replaced it with the bundle, exit 0. Now refused before the calibration starts, the
    file unchanged; an earlier bundle at that name is still replaced by a rerun."""
    from hsi_torch.calibrate.cli_entry import _check_replaces_a_bundle
    from hsi_torch.errors import InputError

    caps = tmp_path / "caps"
    caps.mkdir()
    mine = tmp_path / "results.npz"
    import numpy as np

    np.savez(mine, table=np.arange(3))  # an NPZ, but not a bundle
    before = mine.read_bytes()
    assert main(["calibrate", "--captures", str(caps), "--out", str(mine), "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert "results.npz exists and is not a calibration bundle" in err
    assert mine.read_bytes() == before
    (tmp_path / "text.npz").write_text("notes")
    with pytest.raises(InputError, match="not a calibration bundle"):
        _check_replaces_a_bundle(tmp_path / "text.npz")
    (tmp_path / "b").mkdir()
    bpath, _ = _small_run(tmp_path / "b")
    _check_replaces_a_bundle(bpath)  # an earlier bundle: may be replaced
    _check_replaces_a_bundle(tmp_path / "new.npz")  # nothing there


def test_a_rerun_removes_the_earlier_runs_outputs_it_does_not_make(tmp_path, capsys):
    """A run with ``uncertainty`` writes ``a_std.*`` beside the cube; a rerun without it left
    them there, describing the earlier cube. Now the rerun removes them once it is done and says
    so; an earlier output changed since that run wrote it is kept."""
    bpath, inp = _small_run(tmp_path)
    out = tmp_path / "out"
    run = ["reconstruct", "--bundle", str(bpath), "--out", str(out), "--no-progress"]
    assert main([*run, "--set", "uncertainty=true", str(inp)]) == 0
    std = sorted(p.name for p in out.iterdir() if "_std" in p.name)
    assert std, "the uncertainty run wrote no _std file"
    capsys.readouterr()
    assert main([*run, "--no-resume", str(inp)]) == 0
    cap = capsys.readouterr()
    assert not [p for p in out.iterdir() if "_std" in p.name]
    assert f"removed {std[0]}, an earlier run's output" in cap.out + cap.err
    assert (out / "a.npz").is_file()
    # again with uncertainty, then one _std file edited by the user: that one is kept
    assert main([*run, "--no-resume", "--set", "uncertainty=true", str(inp)]) == 0
    edited = out / std[0]
    edited.write_bytes(b"the user's own notes")
    assert main([*run, "--no-resume", str(inp)]) == 0
    assert edited.read_bytes() == b"the user's own notes"
    assert [p.name for p in out.iterdir() if "_std" in p.name] == [std[0]]


# a tiny experiment that writes what the real ones write (summary.json, a table)
from dataclasses import dataclass  # noqa: E402


@dataclass
class _TinyCfg:
    n: int = 1


def _tiny_run(cfg: _TinyCfg, out: Path, *, device=None) -> dict:
    (out / "summary.json").write_text(f'{{"n": {cfg.n}}}')
    (out / "ranking.csv").write_text("a,b\n")
    return {}


def test_experiment_into_a_folder_with_the_users_files_is_refused(tmp_path, capsys):
    """``hsi-torch experiment design --out lab/`` on a folder holding the lab's own
    ``summary.json``, ``ranking.csv`` and ``resolved_config.yaml`` replaced all three, exit 0.
    Now refused up front, naming them; a rerun into the experiment's own folder (also after an
    interrupted run: its marker is written first) still works; another experiment's folder is
    refused."""
    from hsi_torch.experiments import cli_entry as ce

    mine = {"summary.json": b'{"mine": 1}', "ranking.csv": b"my table",
            "resolved_config.yaml": b"my: config"}  # fmt: skip
    lab = _users_folder(tmp_path / "lab", mine)
    ce.register_experiment("nd_tiny", __name__, "_TinyCfg", "_tiny_run")
    ce.register_experiment("nd_other", __name__, "_TinyCfg", "_tiny_run")
    try:
        assert main(["experiment", "nd_tiny", "--out", str(lab), "-q"]) == 1
        err = capsys.readouterr().err
        assert "is not empty (ranking.csv, resolved_config.yaml, summary.json)" in err
        assert "holds no earlier run of the experiment 'nd_tiny'" in err
        assert {p.name: p.read_bytes() for p in lab.iterdir()} == mine
        # its own folder: new, rerun, interrupted (only the marker and part of the files)
        out = tmp_path / "out"
        assert main(["experiment", "nd_tiny", "--out", str(out), "-q"]) == 0
        assert main(["experiment", "nd_tiny", "--out", str(out), "-q", "--set", "n=2"]) == 0
        assert (out / "summary.json").read_text() == '{"n": 2}'
        killed = tmp_path / "killed"
        killed.mkdir()
        (killed / ce.EXPERIMENT_MARKER).write_text("nd_tiny\n")
        (killed / "summary.json").write_text("partial")
        assert main(["experiment", "nd_tiny", "--out", str(killed), "-q"]) == 0
        # another experiment's folder
        assert main(["experiment", "nd_other", "--out", str(out), "-q"]) == 1
        assert "holds a run of the experiment 'nd_tiny', not 'nd_other'" in capsys.readouterr().err
        assert (out / "summary.json").read_text() == '{"n": 2}'
    finally:
        ce.EXPERIMENTS.pop("nd_tiny")
        ce.EXPERIMENTS.pop("nd_other")


def _runs_tiny(cfg: _TinyCfg, out: Path, *, device=None) -> dict:
    (out / "summary.json").write_text(f'{{"n": {cfg.n}}}')
    if cfg.n == 1:
        (out / "extra.csv").write_text("only the first run writes this\n")
    return {}


def _runs_tiny_interrupted(cfg: _TinyCfg, out: Path, *, device=None) -> dict:
    (out / "summary.json").write_text(f'{{"n": {cfg.n}, "partial": true}}')
    raise KeyboardInterrupt  # Ctrl-C after the first file


def test_an_interrupted_experiment_rerun_marks_the_folder_incomplete(tmp_path, capsys):
    """``experiment NAME --out DIR`` rerun and interrupted midway left a mix of the new run's
    and the earlier run's files with nothing saying so. Now ``INCOMPLETE_RUN.json`` marks the
    folder until a run completes and lists the files that were there before it started (the
    earlier run's, with size and modification time: a changed one is the new run's); a run
    that completes removes it and records in ``experiment_run.json`` which files it wrote and
    which are left from an earlier run."""
    import json
    import os

    from hsi_torch.experiments import cli_entry as ce

    out = tmp_path / "out"
    argv = ["experiment", "nd_runs", "--out", str(out)]
    ce.register_experiment("nd_runs", __name__, "_TinyCfg", "_runs_tiny")
    try:
        assert main(argv) == 0
        first = json.loads((out / "experiment_run.json").read_text())
        assert first["state"] == "complete"
        assert first["written"] == ["extra.csv", "resolved_config.yaml", "summary.json"]
        assert not (out / "INCOMPLETE_RUN.json").exists()

        ce.register_experiment("nd_runs", __name__, "_TinyCfg", "_runs_tiny_interrupted")
        assert main([*argv, "--set", "n=2"]) == 130
        mark = json.loads((out / "INCOMPLETE_RUN.json").read_text())  # used not to exist
        assert mark["state"] == "incomplete" and mark["experiment"] == "nd_runs"
        before = mark["files_before"]
        assert sorted(before) == ["extra.csv", "resolved_config.yaml", "summary.json"]

        def unchanged(name: str) -> bool:
            st = os.stat(out / name)
            return (st.st_size, st.st_mtime_ns) == (before[name]["size"],
                                                    before[name]["mtime_ns"])  # fmt: skip

        assert unchanged("extra.csv") and unchanged("resolved_config.yaml")
        assert not unchanged("summary.json")  # the interrupted run's

        ce.register_experiment("nd_runs", __name__, "_TinyCfg", "_runs_tiny")
        capsys.readouterr()
        assert main([*argv, "--set", "n=2"]) == 0
        cap = capsys.readouterr()
        assert "holds 3 file(s) of an earlier interrupted run" in cap.err
        assert "1 file(s) are from an earlier run and were not rewritten" in cap.out
        assert not (out / "INCOMPLETE_RUN.json").exists()
        rec = json.loads((out / "experiment_run.json").read_text())
        assert rec["written"] == ["resolved_config.yaml", "summary.json"]
        assert rec["from_earlier_runs"] == ["extra.csv"]
        assert json.loads((out / "summary.json").read_text()) == {"n": 2}
    finally:
        ce.EXPERIMENTS.pop("nd_runs")


def test_an_interrupted_demo_rerun_marks_the_folder_incomplete(tmp_path, capsys, monkeypatch):
    """``demo --out DIR`` rerun into an earlier demo's folder and interrupted midway left a mix
    of the new run's and the earlier run's files with nothing saying so. Now it is marked as an
    experiment's folder is: ``INCOMPLETE_RUN.json`` until a run completes (listing the files
    that were there before), then ``demo_run.json`` (files written, files from earlier runs)."""
    import json
    import os

    from hsi_torch.experiments import demo as demo_mod
    from hsi_torch.experiments.cli_entry import DEMO_MARKER

    out = tmp_path / "demo"
    out.mkdir()
    (out / DEMO_MARKER).write_text("")
    earlier = {"calib.npz": b"the earlier demo's bundle", "colorchecker.tif": b"its cube",
               "summary.json": b'{"scenes": {}, "files": ["calib.npz"]}'}  # fmt: skip
    for name, data in earlier.items():
        (out / name).write_bytes(data)
    argv = ["demo", "--quick", "--out", str(out), "--set", "progress=false", "--set",
            "cave=false"]  # fmt: skip

    def interrupted_simulation(cfg, cap_dir, **kw):  # the demo's step 1 stopped by Ctrl-C
        Path(cap_dir).mkdir(parents=True)
        (Path(cap_dir) / "manifest.json").write_text("{}")
        raise KeyboardInterrupt

    monkeypatch.setattr(demo_mod, "simulate_capture_set", interrupted_simulation)
    assert main(argv) == 130
    assert "holds 3 file(s) of an earlier run" in capsys.readouterr().err
    mark = json.loads((out / "INCOMPLETE_RUN.json").read_text())  # used not to exist
    assert mark["state"] == "incomplete"
    assert mark["command"] == " ".join(["hsi-torch", *argv])  # the whole command line
    assert sorted(mark["files_before"]) == sorted(earlier)  # not the marker
    for name, st in mark["files_before"].items():
        now = os.stat(out / name)
        assert (now.st_size, now.st_mtime_ns) == (st["size"], st["mtime_ns"])
    assert (out / "captures" / "manifest.json").is_file()  # the interrupted run's
    assert (out / "synthetic_scene.npz").is_file()  # written before the simulation
    assert not (out / "demo_run.json").exists()

    def tiny_demo(out, cfg, *, quick, log):  # a run that completes, without the real work
        (out / "summary.json").write_text('{"scenes": {}, "files": []}')
        (out / "captures" / "manifest.json").write_text('{"set": 2}')

    monkeypatch.setattr(demo_mod, "demo", tiny_demo)
    assert main(argv) == 0
    cap = capsys.readouterr()
    assert "holds 5 file(s) of an earlier interrupted run" in cap.err
    assert "3 file(s) are from an earlier run and were not rewritten" in cap.out
    assert not (out / "INCOMPLETE_RUN.json").exists()
    rec = json.loads((out / "demo_run.json").read_text())
    assert rec["state"] == "complete" and rec["command"] == " ".join(["hsi-torch", *argv])
    assert rec["written"] == ["captures/manifest.json", "resolved_config.yaml", "summary.json"]
    assert rec["from_earlier_runs"] == ["calib.npz", "colorchecker.tif", "synthetic_scene.npz"]
    assert (out / "calib.npz").read_bytes() == earlier["calib.npz"]  # nothing deleted


def test_a_demo_marker_that_is_a_symlink_is_never_written_through(tmp_path, monkeypatch):
    """A ``.hsi_torch_demo`` in ``--out`` that is a symbolic link to the user's file: the demo
    used to write its marker text through the link (the user's file truncated and replaced);
    the marker is now written atomically, replacing the link, and the file is unchanged."""
    from hsi_torch.experiments import demo as demo_mod
    from hsi_torch.experiments.cli_entry import DEMO_MARKER

    users = tmp_path / "thesis.tex"
    users.write_bytes(b"the user's own file")
    out = tmp_path / "demo"
    out.mkdir()
    (out / DEMO_MARKER).symlink_to(users)

    def tiny_demo(out, cfg, *, quick, log):  # a run that completes, without the real work
        (out / "summary.json").write_text('{"scenes": {}, "files": []}')

    monkeypatch.setattr(demo_mod, "demo", tiny_demo)
    assert main(["demo", "--quick", "--out", str(out), "--set", "progress=false"]) == 0
    assert users.read_bytes() == b"the user's own file"
    assert not (out / DEMO_MARKER).is_symlink()


def _users_folder(folder: Path, files: dict[str, bytes]) -> Path:
    """``folder`` holding the user's own ``files`` (name → content)."""
    folder.mkdir()
    for name, data in files.items():
        (folder / name).write_bytes(data)
    return folder


_SCRIPTS_ROOT = Path(__file__).resolve().parents[1] / "scripts"


@pytest.mark.parametrize(("script", "args"), [
    ("drift_small.py", []),
    ("mismatch_small.py", []),
    ("error_budget.py", []),
    ("optics_report.py", []),
    ("usaf_demosaic.py", ["bilinear"]),
])  # fmt: skip
def test_scripts_refuse_an_out_folder_they_did_not_write(tmp_path, script, args):
    """``scripts/X.py --out lab`` wrote its simulated sets, tables and figures into ``lab``
    whatever it held (a lab's own files of the same names were replaced). Now each refuses a
    folder holding files but not its marker before any work, as ``bench_simulate.py``, ``demo``
    and ``experiment`` do (one helper, :func:`hsi_torch.io.paths.claim_out_dir`); a new folder
    gets the marker first, so the script's own folder is accepted again."""
    import runpy

    from hsi_torch.io.paths import claim_out_dir

    lab = _users_folder(tmp_path / "lab", {"notes.txt": b"the lab's", "calib.npz": b"mine"})
    main_ = runpy.run_path(str(_SCRIPTS_ROOT / script), run_name="not_main")["main"]
    with pytest.raises(SystemExit, match=f"{script}: error: --out .*lab is not empty \\(calib.npz, "
                                         f"notes.txt\\) and holds no earlier run of {script}"):
        main_([*args, "--out", str(lab)])
    assert {p.name: p.read_bytes() for p in lab.iterdir()} == {"notes.txt": b"the lab's",
                                                              "calib.npz": b"mine"}  # fmt: skip
    # the marker each script writes first: its own folder is accepted the next time
    marker = f".hsi_torch_{script.removesuffix('.py')}"
    assert f'"{marker}"' in (_SCRIPTS_ROOT / script).read_text()
    mine = claim_out_dir(tmp_path / "mine", marker, f"run of {script}", "it writes", script=script)
    (mine / "drift_small.json").write_text("{}")
    assert claim_out_dir(mine, marker, f"run of {script}", "it writes", script=script) == mine
    # a folder of a run from before the marker existed, named by what only the script writes
    old = _users_folder(tmp_path / "old", {"drift_small.json": b"{}", "notes.txt": b""})
    assert claim_out_dir(old, marker, "run", "it writes", earlier_names=("drift_small.json",))
    assert (old / marker).is_file()


def test_deepinv_pnp_refuses_an_out_file_it_did_not_write(tmp_path):
    """``scripts/deepinv_pnp.py --out cube.npz`` wrote over any file of that name (a user's own
    cube, with the pipeline's keys) after the solve, not atomically. Now an existing ``--out``
    that the script did not write (its key ``written_by``) is refused before any work."""
    import runpy

    import numpy as np

    mod = runpy.run_path(str(_SCRIPTS_ROOT / "deepinv_pnp.py"), run_name="not_main")
    theirs = tmp_path / "cube.npz"
    np.savez(theirs, cube=np.ones((2, 3, 3)))
    data = theirs.read_bytes()
    args = ["--bundle", "b.npz", "--capture", "c.tif", "--weights", "w.pth", "--out"]
    with pytest.raises(SystemExit, match="deepinv_pnp.py: error: --out .*cube.npz exists and "
                                         "was not written by this script"):  # fmt: skip
        mod["run"]([*args, str(theirs)])
    assert theirs.read_bytes() == data
    ours = tmp_path / "pnp.npz"
    np.savez(ours, cube=np.ones((2, 3, 3)), written_by=mod["WRITTEN_BY"])
    mod["_check_out"](ours)  # its own earlier output may be replaced
    mod["_check_out"](tmp_path / "new.npz")


def test_simulate_marker_that_is_a_symlink_never_writes_through_it(tmp_path):
    """A ``.hsi_torch_simulate_incomplete`` in ``--out`` that is a symbolic link (a folder copied
    with links, one made by hand) is refused: the run locks the marker and writes its process id
    into it, which through the link would truncate the file it points at."""
    from hsi_torch.errors import InputError
    from hsi_torch.simulate.cli_entry import INCOMPLETE_MARKER, incomplete_run

    users = tmp_path / "notes.txt"
    users.write_bytes(b"the user's notes\n")
    out = tmp_path / "out"
    out.mkdir()
    (out / INCOMPLETE_MARKER).symlink_to(users)
    (out / "manifest.json").write_text("{}")
    with pytest.raises(InputError, match="symbolic link"):
        with incomplete_run(out, fresh=False):
            pass
    assert users.read_bytes() == b"the user's notes\n"
    assert (out / INCOMPLETE_MARKER).is_symlink()


@pytest.mark.parametrize(("script", "cache"), [
    ("drift_small.py", "ideal"),
    ("mismatch_small.py", "rows"),
    ("error_budget.py", "rgb_clean"),
])  # fmt: skip
def test_a_users_folder_holding_a_cache_folders_name_is_not_taken_for_an_earlier_run(
        tmp_path, script, cache):
    """A lab's folder holding a sub-folder named like one of the script's cached sets (``ideal/``,
    ``rows/``, ``rgb_clean/``: common names) beside its own files was taken for an earlier run
    from before the marker and written into (the script's tables, figures and sets over the
    lab's files of those names, or the lab's set read as the script's). Only the script's result
    file marks such a run now; the folder is refused before any work."""
    import runpy

    lab = _users_folder(tmp_path / "lab", {"summary.json": b"the lab's", "notes.txt": b""})
    (lab / cache).mkdir()
    (lab / cache / "manifest.json").write_bytes(b"the lab's set")
    main_ = runpy.run_path(str(_SCRIPTS_ROOT / script), run_name="not_main")["main"]

    def work(*_a, **_k):
        raise AssertionError("the script started its work in the lab's folder")

    for name in ("simulate_capture_set", "calibrate_capture_set", "run_mismatch", "_simulate",
                 "real_data_dir"):  # fmt: skip
        if name in main_.__globals__:
            main_.__globals__[name] = work
    with pytest.raises(SystemExit, match=f"{script}: error: --out .*lab is not empty"):
        main_(["--out", str(lab)])
    assert sorted(p.name for p in lab.iterdir()) == sorted([cache, "notes.txt", "summary.json"])
    assert (lab / "summary.json").read_bytes() == b"the lab's"


def test_a_resume_whose_incomplete_run_completed_meanwhile_is_refused(tmp_path):
    """A rerun finds ``--out`` incomplete (the marker is there) and resumes without
    ``--overwrite``; when that run completes before the rerun takes the marker, the marker is
    gone and the folder is a complete set, which only ``--overwrite`` may replace. The rerun
    created a new marker and wrote into the complete set; it is refused now."""
    from hsi_torch.errors import InputError
    from hsi_torch.simulate.cli_entry import INCOMPLETE_MARKER, incomplete_run

    out = tmp_path / "sim"
    out.mkdir()
    (out / "manifest.json").write_text("{}")  # the complete set, its marker removed
    with pytest.raises(InputError, match="written by another simulate run"):
        with incomplete_run(out, fresh=False):
            raise AssertionError("a complete set was written into without --overwrite")
    assert sorted(p.name for p in out.iterdir()) == ["manifest.json"]
    assert not (out / INCOMPLETE_MARKER).exists()
