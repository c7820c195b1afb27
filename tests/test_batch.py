"""Tests of the run's driver loop over files: globs, failures collected, resume, summaries.

:func:`run_batch` below drives a plain ``process(path)`` through the driver of every
reconstruction run (:func:`hsi_torch.recon.batch.driver.drive`, in this process, into a
:class:`~hsi_torch.recon.batch.targets.FilesTarget`); other test files import it.
"""

from __future__ import annotations

import json
import os
import traceback
from pathlib import Path

import pytest

from hsi_torch.io.atomic import atomic_write_text
from hsi_torch.io.paths import ensure_out_dir, expand_inputs
from hsi_torch.recon.batch.driver import (
    InlineExecutor,
    RunSummary,
    drive,
    print_summary,
)
from hsi_torch.recon.batch.targets import DONE_DIR, FilesTarget


def call_process(process, input_path: str, frame: int | None = None) -> dict:
    """A task of :func:`drive` from a plain ``process(path) -> output path(s) or None`` that
    raises on failure (the driver's result protocol)."""
    try:
        result = process(Path(input_path))
    except Exception as exc:  # noqa: BLE001 - reported to the driver with its traceback
        return {"ok": False, "error": f"{type(exc).__name__}: {exc}",
                "traceback": traceback.format_exc()}  # fmt: skip
    if result is None:
        outputs: list[str] = []
    elif isinstance(result, (str, os.PathLike)):
        outputs = [os.fspath(result)]
    else:
        outputs = [os.fspath(p) for p in result]
    return {"ok": True, "outputs": outputs, "warnings": []}


def run_batch(inputs, process, out_dir, *, resume=True, progress=True, planned_outputs=None,
              fingerprint=None, desc="processing") -> RunSummary:  # fmt: skip
    """``process`` over every input (files or globs), through the run's driver loop."""
    out = ensure_out_dir(out_dir)
    return drive(expand_inputs(inputs), FilesTarget(out, fingerprint, planned_outputs),
                 InlineExecutor(), call_process, lambda p, frame: (process, str(p), frame),
                 resume=resume, progress=progress, desc=desc)  # fmt: skip


@pytest.fixture
def inputs(tmp_path) -> Path:
    d = tmp_path / "in"
    d.mkdir()
    for name in ["a.txt", "b.txt", "bad.txt", "c.txt"]:
        (d / name).write_text(name.upper())
    (d / "sub").mkdir()
    (d / "sub" / "d.txt").write_text("D")
    return d


def _processor(out_dir: Path, calls: list[str]):
    def process(p: Path) -> Path:
        calls.append(p.name)
        if p.stem == "bad":
            raise ValueError(f"{p}: not a valid capture")
        return atomic_write_text(out_dir / f"{p.stem}.out", p.read_text().lower())

    return process


def test_expand_inputs(inputs):
    got = expand_inputs([str(inputs / "*.txt"), str(inputs / "a.txt"), str(inputs / "**/d.txt")])
    assert [p.name for p in got] == ["a.txt", "b.txt", "bad.txt", "c.txt", "d.txt"]  # sorted, dedup
    assert [p.name for p in expand_inputs(str(inputs / "[ab]*.txt"))] == [
        "a.txt",
        "b.txt",
        "bad.txt",
    ]
    with pytest.raises(ValueError, match=r"pattern '.*\*\.tif' matches no files"):
        expand_inputs([str(inputs / "*.tif")])
    with pytest.raises(ValueError, match="is a directory"):
        expand_inputs([str(inputs / "sub")])
    assert expand_inputs([str(inputs / "missing.txt")]) == [inputs / "missing.txt"]


def test_run_batch_continues_and_resumes(tmp_path, inputs, capsys):
    out = tmp_path / "out"
    calls: list[str] = []
    items = [str(inputs / "*.txt"), str(inputs / "missing.txt")]
    s = run_batch(items, _processor(out, calls), out, progress=False)
    assert [p.name for p in s.processed] == ["a.txt", "b.txt", "c.txt"]
    assert [f.input.name for f in s.failed] == ["bad.txt", "missing.txt"]
    assert s.failed[0].error == f"ValueError: {inputs / 'bad.txt'}: not a valid capture"
    assert s.failed[1].error.startswith("FileNotFoundError: input file not found")
    assert "Traceback" in s.failed[0].traceback
    assert (out / "a.out").read_text() == "a.txt" and not (out / "bad.out").exists()
    assert s.outputs[inputs / "a.txt"] == [out / "a.out"]
    assert s.exit_code == 1 and not s.ok and s.total == 5
    markers = sorted((out / DONE_DIR).iterdir())
    assert len(markers) == 3  # only successes are marked
    rec = json.loads(markers[0].read_text())
    assert rec["outputs"] == ["a.out"]  # relative to the output folder

    print_summary(s)
    err = capsys.readouterr().err
    assert "5 input(s): 3 processed, 0 skipped (outputs exist), 2 failed" in err
    assert f"FAILED {inputs / 'bad.txt'}: ValueError" in err and "FAILED" in err.splitlines()[-1]

    # resume: only the failures are retried
    calls.clear()
    s2 = run_batch(items, _processor(out, calls), out, progress=False)
    assert calls == ["bad.txt"] and len(s2.skipped) == 3 and len(s2.failed) == 2
    # an output deleted since: that input is redone
    (out / "b.out").unlink()
    calls.clear()
    run_batch(items, _processor(out, calls), out, progress=False)
    assert calls == ["b.txt", "bad.txt"]
    # --no-resume processes everything again
    calls.clear()
    run_batch(items, _processor(out, calls), out, resume=False, progress=False)
    assert calls == ["a.txt", "b.txt", "bad.txt", "c.txt"]


def test_run_batch_progress_and_changed_settings(tmp_path, inputs, capsys, monkeypatch):
    from hsi_torch import console

    monkeypatch.setattr(console, "_stderr_is_terminal", lambda: True)  # bars need a terminal
    out = tmp_path / "o2"
    calls: list[str] = []
    items = [inputs / "a.txt", inputs / "c.txt"]
    s = run_batch(items, _processor(out, calls), out, desc="reconstructing", fingerprint="x")
    assert calls == ["a.txt", "c.txt"] and s.ok
    assert "reconstructing" in capsys.readouterr().err  # tqdm bar on stderr
    calls.clear()
    s = run_batch(items, _processor(out, calls), out, progress=False, fingerprint="x")
    assert calls == [] and len(s.skipped) == 2
    # another fingerprint (other settings, another bundle): redone
    s = run_batch(items, _processor(out, calls), out, progress=False, fingerprint="y")
    assert calls == ["a.txt", "c.txt"] and not s.skipped


def test_run_batch_interrupt_propagates(tmp_path, inputs):
    def process(p: Path) -> None:
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_batch([inputs / "a.txt"], process, tmp_path / "o3", progress=False)
    assert not (tmp_path / "o3" / DONE_DIR).exists()


def test_a_writer_killed_mid_run_leaves_no_temporary_file(inputs, tmp_path):
    """A temporary file whose writer died during the run (a cluster worker killed mid-file, its
    task retried elsewhere) is removed once every task has ended; a live writer's is kept."""
    out = tmp_path / "out"
    dead = out / ".b.out.999999999-abcdef.tmp"  # no such process
    live = out / f".x.out.{os.getpid()}-abcdef.tmp"
    process = _processor(out, [])

    def killed_mid_file(p: Path) -> Path:
        if p.stem == "b":  # planted while the run is going, after its start-of-run cleaning
            dead.write_bytes(b"partial")
            live.write_bytes(b"being written")
        return process(p)

    s = run_batch([str(inputs / "[abc].txt")], killed_mid_file, out, progress=False)
    assert s.exit_code == 0 and len(s.processed) == 3
    assert dead in s.cleaned and not dead.exists()
    assert live.exists() and live not in s.cleaned
    assert "killed worker" in s.report()
