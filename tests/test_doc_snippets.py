"""Every shell and Python snippet of README.md and docs/*.md runs, so a stale snippet fails CI.

The fenced blocks marked ``bash``/``sh`` and ``python`` are collected from the documents; each
runs in a fresh copy-on-demand workspace laid out the way the snippets name things (small
prototype, made once per test session):

=======================  ==========================================================
``sim/``                 the shipped small prototype's set (the session's shared ``small_sim``
                         of ``conftest.py``: ``simulate`` with a float32 render, no figures)
``calib/calib.npz``      ``hsi-torch calibrate --captures sim --out calib`` (+ ``calib.npz``)
``shots/scene_001.tif``  the simulated ColorChecker capture (``shots/scene_002.tif``: the
                         second scene; ``scene.tif``, ``shot.tif``: copies at the top)
``extra/scene.dng``      the first scene as a camera's DNG (black level 512, ExposureTime)
``lab/``                 the set as a lab names it: ``lab/captures.csv`` (the sheet),
                         DNG files in its own folders, ``lab/nominal_layout.json``
=======================  ==========================================================

A bash block runs with ``bash -e -o pipefail``, a Python block as ``python -c`` of the test's
interpreter, both with the workspace as the working folder, ``hsi-torch`` on ``PATH`` (this
interpreter's ``python -m hsi_torch``) and the source checkout as ``REPO``. Each ``hsi-torch`` call
and each Python block runs in a process forked from one server that imported torch and the
package once per session (``forkserver.py``: the streams, folder, environment and exit status
are the caller's, as in a fresh interpreter), not in a new interpreter importing them again. A
block that cannot run here is marked in the document by an HTML comment on the line right before
its fence::

    <!-- snippet: skip (needs a Dask cluster: the scheduler address is the reader's) -->

and is reported as skipped with that reason; a marker without a reason is an error. Blocks run
in document order inside one workspace per document, so a block may use what an earlier block
of the same document wrote.
"""

from __future__ import annotations

import os
import re
import select
import shutil
import signal
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from hsi_torch.resources import real_data_dir

REPO = Path(__file__).resolve().parents[1]
FORKSERVER = Path(__file__).resolve().parent / "forkserver.py"
DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
_FENCE = re.compile(r"^```(bash|sh|python)\s*$")
_MARK = re.compile(r"^<!--\s*snippet:\s*(\w+)(?:\s*\((.*)\))?\s*-->\s*$")
TIMEOUT_S = 600


@dataclass(frozen=True)
class Snippet:
    doc: Path
    line: int  # 1-based line of the opening fence
    lang: str
    code: str
    skip: str | None  # the reason, when marked skip

    @property
    def id(self) -> str:
        return f"{self.doc.relative_to(REPO).as_posix()}:{self.line}"


def collect(doc: Path) -> list[Snippet]:
    """The runnable fenced blocks of ``doc`` with their markers (see the module docstring)."""
    lines = doc.read_text(encoding="utf-8").splitlines()
    out: list[Snippet] = []
    i = 0
    while i < len(lines):
        m = _FENCE.match(lines[i])
        if m is None:
            i += 1
            continue
        j = i + 1
        while j < len(lines) and not lines[j].startswith("```"):
            j += 1
        skip = None
        mark = _MARK.match(lines[i - 1].strip()) if i > 0 else None
        if mark is not None:
            if mark.group(1) != "skip" or not (mark.group(2) or "").strip():
                raise ValueError(f"{doc}:{i}: snippet marker must be 'skip (reason)'")
            skip = mark.group(2).strip()
        out.append(Snippet(doc, i + 1, "python" if m.group(1) == "python" else "bash",
                           "\n".join(lines[i + 1 : j]) + "\n", skip))  # fmt: skip
        i = j + 1
    return out


SNIPPETS = [s for d in DOCS for s in collect(d)]


def _run(cmd: list[str], cwd: Path, env: dict[str, str]) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=TIMEOUT_S, stdin=subprocess.DEVNULL)  # fmt: skip


@pytest.fixture(scope="session")
def snippet_env(tmp_path_factory) -> Iterator[dict[str, str]]:
    """Environment of the snippets: ``hsi-torch`` (this interpreter, through the session's fork
    server) first on ``PATH``; ``SNIPPET_SOCKET`` names the server's socket."""
    bindir = tmp_path_factory.mktemp("snippet_bin")
    sock = bindir / "forkserver.sock"
    shim = bindir / "hsi-torch"
    shim.write_text(f'#!/bin/sh\nexec "{sys.executable}" -S -E "{FORKSERVER}" client "{sock}" '
                    'cli "$@"\n')  # fmt: skip
    shim.chmod(0o755)
    env = dict(os.environ)
    env["PATH"] = f"{bindir}{os.pathsep}{Path(sys.executable).parent}{os.pathsep}{env['PATH']}"
    env["REPO"] = str(REPO)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO), env.get("PYTHONPATH")) if p)
    env.setdefault("MPLBACKEND", "Agg")
    data = real_data_dir()
    if data is not None:
        env["HSI_TORCH_DATA"] = str(data)
    with open(bindir / "forkserver.log", "wb") as log:
        server = subprocess.Popen([sys.executable, str(FORKSERVER), "serve", str(sock)], env=env,
                                  stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=log,
                                  start_new_session=True)  # fmt: skip
    try:
        ready, _, _ = select.select([server.stdout], [], [], TIMEOUT_S)
        line = server.stdout.readline() if ready else b""
        assert line == b"ready\n", f"the fork server did not start: {bindir / 'forkserver.log'}"
        env["SNIPPET_SOCKET"] = str(sock)
        yield env
    finally:
        os.killpg(server.pid, signal.SIGKILL)  # the server and any child left running
        server.wait()
        server.stdout.close()


@pytest.fixture(scope="session")
def base_workspace(tmp_path_factory, small_sim: Path, small_sim_calib: Path) -> Path:
    """The small simulated set, its calibration and shots, made once (see the module docstring):
    copies of the session's shared set and calibration (simulated and calibrated in this process,
    not by two more commands that each import torch)."""
    ws = tmp_path_factory.mktemp("snippet_base")
    shutil.copytree(small_sim, ws / "sim")
    shutil.copytree(small_sim_calib, ws / "calib")
    shutil.copy(ws / "calib" / "calib.npz", ws / "calib.npz")
    scenes = sorted((ws / "sim" / "scenes").glob("*.tif"))
    assert scenes, "the simulated set has no scene capture"
    (ws / "shots").mkdir()
    for k, src in enumerate(scenes[:2], start=1):
        shutil.copy(src, ws / "shots" / f"scene_{k:03d}.tif")
    shutil.copy(scenes[0], ws / "scene.tif")
    shutil.copy(scenes[0], ws / "shot.tif")
    _lab_files(ws / "sim", ws)
    return ws


def _lab_files(sim: Path, ws: Path) -> None:
    """``extra/scene.dng`` and ``lab/`` (a sheet and DNGs named the lab's way) from ``sim``."""
    import csv
    import json

    from synthetic_data import write_dng

    from hsi_torch.io import read_capture

    def dng(src: Path, dst: Path, exposure_s: float) -> None:
        img, meta = read_capture(src)
        write_dng(dst, img[0].numpy(), cfa_pattern=meta.get("cfa_pattern", "RGGB"),
                  black_level=int(meta["black_level"]), white_level=int(meta["white_level"]),
                  exposure_s=exposure_s, make="Lab Optics", model="KaleidoCam 1")  # fmt: skip

    man = json.loads((sim / "manifest.json").read_text(encoding="utf-8"))
    rows = [["file", "role", "wavelength_nm", "name"]]
    folders = {"scan": "Monochromator", "white": "Flat field", "grid": "Dots", "dark": "Dark",
               "scene": "Shots"}  # fmt: skip
    for k, e in enumerate(man["captures"]):
        name = f"{folders[e['type']]}/IMG_{k:04d}.dng"
        dng(sim / e["file"], ws / "lab" / name, 0.5 if e["type"] == "scan" else 0.01)
        wl = f"{e['wavelength_nm']:g}" if e["type"] == "scan" else ""
        rows.append([name, e["type"], wl, e.get("name", "") if e["type"] == "scene" else ""])
        if e["type"] == "scene" and not (ws / "extra" / "scene.dng").exists():
            dng(sim / e["file"], ws / "extra" / "scene.dng", 0.01)
    with open(ws / "lab" / "captures.csv", "w", newline="", encoding="utf-8") as f:
        csv.writer(f).writerows(rows)
    shutil.copy(sim / "nominal_layout.json", ws / "lab" / "nominal_layout.json")
    if (sim / "brf_free_mask.png").exists():
        shutil.copy(sim / "brf_free_mask.png", ws / "lab" / "brf_free_mask.png")


_WORKSPACES: dict[Path, Path] = {}


@pytest.fixture
def workspace(request, base_workspace, tmp_path_factory) -> Path:
    """One copy of the base workspace per document (blocks of a document share it)."""
    snip: Snippet = request.node.callspec.params["snippet"]
    ws = _WORKSPACES.get(snip.doc)
    if ws is None:
        ws = tmp_path_factory.mktemp("snippet_" + snip.doc.stem.lower())
        shutil.copytree(base_workspace, ws, dirs_exist_ok=True)
        _WORKSPACES[snip.doc] = ws
    return ws


def test_markers_are_well_formed():
    for doc in DOCS:
        collect(doc)  # raises on a marker without a reason
    assert len(SNIPPETS) >= 30  # the documents are read (a broken collector runs nothing)


@pytest.mark.slow
@pytest.mark.parametrize("snippet", SNIPPETS, ids=[s.id for s in SNIPPETS])
def test_snippet_runs(snippet: Snippet, workspace: Path, snippet_env: dict[str, str]):
    if snippet.skip:
        pytest.skip(snippet.skip)
    if snippet.lang == "python":  # python -c, forked from the session's server
        cmd = [sys.executable, "-S", "-E", str(FORKSERVER), "client", snippet_env["SNIPPET_SOCKET"],
               "code", snippet.code]  # fmt: skip
    else:
        cmd = ["bash", "-e", "-o", "pipefail", "-c", snippet.code]
    r = _run(cmd, workspace, snippet_env)
    assert r.returncode == 0, (
        f"{snippet.id} failed (exit {r.returncode}):\n{snippet.code}\n--- stderr ---\n"
        f"{r.stderr[-3000:]}\n--- stdout ---\n{r.stdout[-1500:]}"
    )
