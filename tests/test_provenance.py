"""Provenance: a version that changes with the code, and run records holding the whole command.

``experiment synthetic --config my.yaml --set ...`` recorded ``hsi-torch experiment synthetic``
(no ``--config``, no ``--set``) and ``hsi_torch 0.1.0``, the same over hundreds of commits, with
no git commit and no torch version. The version now names the commit when the package runs from
a git checkout (checked against ``git`` itself and against a scratch repository whose tracked
file is changed), and every run record holds the one provenance block."""

from __future__ import annotations

import dataclasses
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from test_pipeline import make_bundle, render_capture, true_spectra

import hsi_torch
from hsi_torch import provenance as prov
from hsi_torch.cli import main

ROOT = Path(__file__).resolve().parents[1]
HAS_GIT = shutil.which("git") is not None


def _git(cwd: Path, *args: str) -> str:
    return subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@example.invalid",
                           "-C", str(cwd), *args], capture_output=True, text=True, check=True,
                          timeout=30).stdout.strip()  # fmt: skip


def _in_checkout() -> bool:
    if not HAS_GIT:
        return False
    try:
        return Path(_git(ROOT, "rev-parse", "--show-toplevel")).resolve() == ROOT
    except (subprocess.CalledProcessError, OSError):
        return False


needs_checkout = pytest.mark.skipif(not _in_checkout(), reason="not run from a git checkout")


@pytest.fixture
def fresh_version(monkeypatch):
    """Forget the cached version (and restore it afterwards)."""
    prov.git_state.cache_clear()
    prov.package_version.cache_clear()
    yield
    prov.git_state.cache_clear()
    prov.package_version.cache_clear()


def test_release_is_the_projects_version():
    text = (ROOT / "pyproject.toml").read_text(encoding="utf-8")
    (version,) = re.findall(r'^version = "([^"]+)"$', text, flags=re.MULTILINE)
    assert prov.RELEASE == version


@needs_checkout
def test_the_version_names_the_checkouts_commit(capsys):
    head = _git(ROOT, "rev-parse", "HEAD")
    dirty = bool(_git(ROOT, "status", "--porcelain", "--untracked-files=no"))
    want = f"{prov.RELEASE}+g{head[:12]}{'.dirty' if dirty else ''}"
    assert hsi_torch.__version__ == want  # was "0.1.0" whatever the commit
    assert prov.git_state() == {"commit": head, "dirty": dirty}
    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"hsi-torch {want}"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    r = subprocess.run([sys.executable, "-m", "hsi_torch", "--version"], capture_output=True,
                       text=True, cwd="/", env=env, timeout=120)  # fmt: skip
    assert r.returncode == 0 and r.stdout.strip() == f"hsi-torch {want}"


@pytest.mark.skipif(not HAS_GIT, reason="git is not installed")
def test_a_scratch_checkout_commit_and_dirty_state(tmp_path, monkeypatch, fresh_version):
    """A repository holding the package at its top level: its commit, then ``.dirty`` once a
    tracked file changes; a package inside a repository that does not hold it at the top level
    (e.g. a virtual environment inside a project's repository) is not that repository's code."""
    repo = tmp_path / "repo"
    pkg = repo / "hsi_torch"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("x = 1\n")
    _git(repo, "init", "-q")
    _git(repo, "add", ".")
    _git(repo, "commit", "-q", "-m", "one")
    head = _git(repo, "rev-parse", "HEAD")
    monkeypatch.setattr(prov, "_PACKAGE_DIR", pkg)
    assert prov.package_version() == f"{prov.RELEASE}+g{head[:12]}"
    assert prov.provenance()["git_commit"] == head and prov.provenance()["git_dirty"] is False

    (pkg / "__init__.py").write_text("x = 2\n")
    prov.git_state.cache_clear()
    prov.package_version.cache_clear()
    assert prov.package_version() == f"{prov.RELEASE}+g{head[:12]}.dirty"

    nested = repo / "venv" / "site-packages" / "hsi_torch"
    nested.mkdir(parents=True)
    monkeypatch.setattr(prov, "_PACKAGE_DIR", nested)
    prov.git_state.cache_clear()
    prov.package_version.cache_clear()
    assert prov.git_state() is None
    assert "+g" not in prov.package_version()  # the installed metadata's version


def test_no_git_gives_the_installed_version(tmp_path, monkeypatch, fresh_version):
    monkeypatch.setattr(prov, "_PACKAGE_DIR", tmp_path / "hsi_torch")
    monkeypatch.setenv("PATH", str(tmp_path))  # no git on the path
    assert prov.git_state() is None
    v = prov.package_version()
    assert "+g" not in v and v.split(".")[0].isdigit()
    block = prov.provenance()
    assert block["git_commit"] is None and block["hsi_torch_version"] == v


@dataclasses.dataclass
class _TinyCfg:
    n: int = 1


def _tiny_run(cfg: _TinyCfg, out: Path, *, device=None) -> dict:
    (out / "summary.json").write_text(json.dumps({"n": cfg.n}))
    return {}


def _check_block(block: dict, argv: list[str]) -> None:
    assert block["argv"] == ["hsi-torch", *argv]
    assert block["hsi_torch_version"] == hsi_torch.__version__
    assert block["torch"] == torch.__version__ and block["numpy"] == np.__version__
    assert block["python"] == ".".join(map(str, sys.version_info[:3]))
    if _in_checkout():
        assert block["git_commit"] == _git(ROOT, "rev-parse", "HEAD")


def test_experiment_run_records_the_whole_command(tmp_path, capsys):
    from hsi_torch.experiments import cli_entry as ce

    cfg = tmp_path / "my.yaml"
    cfg.write_text("n: 2\n")
    out = tmp_path / "out"
    argv = ["experiment", "prov_tiny", "--config", str(cfg), "--set", "n=3", "--out", str(out),
            "-q"]  # fmt: skip
    ce.register_experiment("prov_tiny", __name__, "_TinyCfg", "_tiny_run")
    try:
        assert main(argv) == 0
    finally:
        ce.EXPERIMENTS.pop("prov_tiny")
    rec = json.loads((out / "experiment_run.json").read_text())
    # was "hsi-torch experiment prov_tiny": neither --config nor --set
    assert rec["command"] == (f"hsi-torch experiment prov_tiny --config {cfg} --set n=3 "
                              f"--out {out} -q")  # fmt: skip
    _check_block(rec["provenance"], argv)
    assert json.loads((out / "summary.json").read_text()) == {"n": 3}


def test_the_python_api_records_no_command(tmp_path):
    from hsi_torch.io.run_record import RUN_RECORD, finish_out_run, start_out_run

    state = start_out_run(tmp_path, "hsi-torch experiment x", RUN_RECORD)
    rec, _ = finish_out_run(tmp_path, state)
    assert rec["command"] == "hsi-torch experiment x"  # the command's name, as before
    assert rec["provenance"]["command"] is None and rec["provenance"]["argv"] is None
    assert rec["provenance"]["hsi_torch_version"] == hsi_torch.__version__


def test_reconstruct_run_records_the_whole_command(tmp_path):
    from hsi_torch.recon.batch.driver import RunSummary

    bundle = make_bundle()
    bpath = tmp_path / "calib.npz"
    bundle.save(bpath)
    np.save(tmp_path / "a.npy", render_capture(bundle, true_spectra()).numpy())
    out = tmp_path / "out"
    argv = ["reconstruct", "--bundle", str(bpath), "--out", str(out), "--no-progress", "-q",
            "--set", "beta=0", "--set", "dtype=float64", str(tmp_path / "a.npy")]  # fmt: skip
    assert main(argv) == 0
    (run_cfg,) = (out / "runs").glob("*.yaml")
    head = [ln for ln in run_cfg.read_text().splitlines() if ln.startswith("#")]
    text = "\n".join(head)
    assert f"hsi_torch {hsi_torch.__version__}" in text
    assert "# command: hsi-torch reconstruct --bundle" in text and "--set beta=0" in text
    assert f"torch {torch.__version__}" in text
    # the Python API's summary carries the block too (no command line there)
    block = RunSummary().provenance
    assert block["hsi_torch_version"] == hsi_torch.__version__ and block["command"] is None


def test_a_bundle_records_the_version_and_the_run(tmp_path):
    from hsi_torch.io.bundle import make_provenance

    b = make_bundle()
    assert b.software_version == hsi_torch.__version__
    p = make_provenance(extra_key=1)
    assert p["run"]["hsi_torch_version"] == hsi_torch.__version__ and p["extra_key"] == 1
    assert p["run"]["torch"] == torch.__version__


def test_a_file_name_that_is_not_utf8_is_recorded_readably():
    name = os.fsdecode(b"shot_\xff.npy")  # a lone surrogate in Python: not writable as UTF-8
    with prov.command_line(["reconstruct", name]):
        block = prov.provenance()
    assert block["command"].encode("utf-8") and "shot_\\xff.npy" in block["command"]
    assert prov.provenance()["command"] is None  # only while the command runs
