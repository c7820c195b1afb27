"""One file-safety layer (:mod:`hsi_torch.io.atomic`): every lock, marker, record, staging file
and output goes through it, and an output folder is data, not instructions.

- a walk over the package's syntax trees finds no file write, rename or deletion outside the
  layer (a short allow-list, each entry with its reason);
- locks and markers written in place are never opened through a symlink or a hard link
  (reconstruct's name lock, the run store's lock, simulate's marker), and ``demo`` /
  ``experiment`` hold a lock of their own (two runs into one folder never mix);
- done-markers hold paths relative to ``--out``, confined to it, and the folder's identity: a
  marker planted in an untrusted folder, or one copied with the folder, deletes nothing outside
  it and ties the copy to nothing;
- a FIFO planted in ``--out`` cannot hang the pre-checks; ``view --screenshot`` never writes over
  a file of the viewed cube, nor over any file it did not write without ``--overwrite``; a
  plaintext scheduler named by a ``--scheduler-file`` is warned about; a kill between a commit's
  renames is undone by the next run; sizes and full disks are reported usefully.
"""

from __future__ import annotations

import ast
import contextlib
import errno
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from hsi_torch.cli import main

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "hsi_torch"

pytestmark = pytest.mark.skipif(os.name != "posix", reason="POSIX file semantics")


# --- the layer is the only writer ------------------------------------------------------------

#: Modules allowed to write, rename or delete files directly, each with its reason.
ALLOWED = {
    "hsi_torch/io/atomic.py": "the file-safety layer itself",
    "hsi_torch/recon/precompute_cache.py": "the precompute cache's own entries and eviction "
    "(a folder of the cache's own, checked and bounded there)",
}

_WRITE_MODES = set("wax+")
_OS_FUNCS = {"replace", "rename", "renames", "remove", "unlink", "rmdir", "removedirs", "link",
             "symlink", "truncate", "ftruncate", "mkfifo"}  # fmt: skip
_SHUTIL = {"move", "copy", "copy2", "copyfile", "copytree", "rmtree", "copyfileobj"}
_NUMPY = {"save", "savez", "savez_compressed", "savetxt"}
_METHODS = {"write_text", "write_bytes", "savefig", "imwrite", "imsave", "tofile", "touch",
            "symlink_to", "hardlink_to", "unlink", "rmdir", "rename", "to_netcdf",
            "to_zarr"}  # fmt: skip
_WRITE_FLAGS = ("O_WRONLY", "O_RDWR", "O_CREAT", "O_TRUNC", "O_APPEND")
#: Context managers whose ``as`` name is a safe target: the layer's staged temporary file, and
#: the cube writer's staged folder (``io/cube.py``, renamed into place with the layer's
#: ``replace_file``).
_LAYER_CMS = {"atomic_write", "_atomic_dir"}


def _dotted(node: ast.AST) -> str:
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        return f"{_dotted(node.value)}.{node.attr}"
    return "?"


def _mode(call: ast.Call, pos: int) -> ast.AST | None:
    for k in call.keywords:
        if k.arg == "mode":
            return k.value
    return call.args[pos] if len(call.args) > pos else None


def _safe_targets(tree: ast.AST) -> set[str]:
    """Names bound to an in-memory buffer (``io.BytesIO()``) or to the layer's staged file
    (``with atomic_write(...) as f``): writing to them writes no file directly."""
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Assign) and isinstance(node.value, ast.Call) \
                and _dotted(node.value.func).endswith(("BytesIO", "StringIO")):
            names |= {t.id for t in node.targets if isinstance(t, ast.Name)}
        if isinstance(node, ast.withitem) and isinstance(node.context_expr, ast.Call) \
                and _dotted(node.context_expr.func).split(".")[-1] in _LAYER_CMS \
                and isinstance(node.optional_vars, ast.Name):
            names.add(node.optional_vars.id)
    return names


def _file_writes(call: ast.Call, safe: set[str]) -> str | None:
    """What ``call`` writes, renames or deletes directly (``None``: nothing)."""
    f = call.func
    full = _dotted(f)
    attr = f.attr if isinstance(f, ast.Attribute) else full
    # the file written: the first argument (the second of shutil.copyfileobj)
    target = call.args[1 if attr == "copyfileobj" else 0] if len(call.args) > 1 or (
        call.args and attr != "copyfileobj") else None
    if isinstance(target, ast.Attribute) and target.attr == "name":  # f.name: the staged file
        target = target.value
    if isinstance(target, ast.Name) and target.id in safe:
        return None
    if full in ("open", "io.open") or (attr == "open" and full != "os.open"):
        m = _mode(call, 1 if full in ("open", "io.open") else 0)
        if isinstance(m, ast.Constant) and isinstance(m.value, str) \
                and set(m.value) & _WRITE_MODES:
            return f"open(mode={m.value!r})"
        return None
    if full == "os.open":
        flags = ast.unparse(call.args[1]) if len(call.args) > 1 else ""
        return "os.open for writing" if any(x in flags for x in _WRITE_FLAGS) else None
    if full.startswith("os.") and attr in _OS_FUNCS:
        return full
    if full.startswith("shutil.") and attr in _SHUTIL:
        return full
    if full.split(".")[0] in ("np", "numpy") and attr in _NUMPY:
        return full
    if attr in _METHODS:
        return f".{attr}()"
    if attr == "replace" and isinstance(f, ast.Attribute) and len(call.args) == 1 \
            and not call.keywords and _dotted(f.value) not in ("dataclasses", "str"):
        return ".replace() of a path"
    return None


def _writes_outside_layer() -> list[str]:
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(REPO).as_posix()
        if rel in ALLOWED:
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=rel)
        safe = _safe_targets(tree)
        for node in ast.walk(tree):
            if isinstance(node, ast.Call):
                what = _file_writes(node, safe)
                if what:
                    found.append(f"{rel}:{node.lineno}: {what}: {ast.unparse(node)[:90]}")
    return found


def test_no_file_is_written_renamed_or_deleted_outside_the_layer():
    """Every lock, marker, record, staging file and output of every command goes through
    :mod:`hsi_torch.io.atomic`; the few modules that write directly are listed with a reason."""
    found = _writes_outside_layer()
    assert not found, "file writes outside hsi_torch.io.atomic:\n" + "\n".join(found)
    for rel in ALLOWED:
        assert (REPO / rel).is_file(), f"the allow-list names a module that is gone: {rel}"


def test_the_write_scanner_finds_each_kind_of_write(tmp_path):
    """The scanner is not blind: each kind of direct write in a snippet is reported, and the
    layer's own ways (a BytesIO, ``atomic_write``'s staged file) are not."""
    src = textwrap.dedent("""
        import io, os, shutil
        import numpy as np
        open(p, "w"); open(p, mode="ab"); Path(p).open("x")
        Path(p).write_text("x"); Path(p).write_bytes(b"")
        os.open(p, os.O_RDWR | os.O_CREAT); np.save(p, a); np.savez(p, a=a)
        tifffile.imwrite(p, a); fig.savefig(p); shutil.move(a, b); shutil.copy(a, b)
        os.replace(a, b); os.remove(p); os.unlink(p); shutil.rmtree(d); Path(p).unlink()
        Path(a).replace(b); da.to_netcdf(p)
        buf = io.BytesIO(); fig.savefig(buf); np.save(buf, a)
        with atomic_write(p) as f:
            np.save(f, a)
            shutil.copyfileobj(src, f)
            da.to_netcdf(f.name)
        open(p); open(p, "rb"); os.open(p, os.O_RDONLY); "a".replace("a", "b")
    """)
    tree = ast.parse(src)
    safe = _safe_targets(tree)
    hits = [n.lineno for n in ast.walk(tree) if isinstance(n, ast.Call) and _file_writes(n, safe)]
    assert len(hits) == 19, hits
    assert max(hits) == 9  # nothing from the BytesIO and atomic_write lines on


# --- fixtures --------------------------------------------------------------------------------


def _rec(bpath: Path, out: Path, *extra: str) -> int:
    return main(["reconstruct", "--bundle", str(bpath), "--out", str(out), "--no-progress",
                 "--set", "dtype=float64", "--set", "beta=0", *extra])  # fmt: skip


def _snapshot(folder: Path) -> dict[str, str]:
    """SHA-256 of every file below ``folder`` (relative path → digest)."""
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}  # fmt: skip


def _users_file(tmp: Path, name: str = "notes.txt") -> Path:
    f = tmp / name
    f.write_bytes(b"the user's own notes, not to be touched\n")
    return f


def _plant(at: Path, target: Path, how: str) -> None:
    at.parent.mkdir(parents=True, exist_ok=True)
    if how == "symlink":
        at.symlink_to(target)
    else:
        os.link(target, at)


def _within(seconds: float, fn, *fifos: Path):
    """``fn()``'s result (or its exception) if it returns within ``seconds``; otherwise the test
    fails, and the ``fifos`` get a writer so that the blocked thread ends. (A thread, not an
    alarm: a signal may reach another of the process's threads and leave ``open`` blocked.)"""
    import threading

    box: dict = {}

    def run():
        try:
            box["value"] = fn()
        except BaseException as exc:  # noqa: BLE001 - handed to the test
            box["error"] = exc

    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(seconds)
    if t.is_alive():
        for f in fifos:  # release a reader blocked on the FIFO
            with contextlib.suppress(OSError):
                os.close(os.open(f, os.O_WRONLY | os.O_NONBLOCK))
        t.join(5)
        pytest.fail(f"still blocked after {seconds} s (a FIFO was opened)")
    if "error" in box:
        raise box["error"]
    return box.get("value")


# --- locks never written through (H1, H2, H3) ------------------------------------------------


@pytest.mark.parametrize("how", ["symlink", "hardlink"])
def test_reconstruct_name_lock_planted_as_a_link_is_never_written_through(ws, capsys, how):
    """A symlink or a hard link at ``OUT/.hsi_torch_done/a.lock`` had its target truncated and
    the process id written into it, exit 0. Now the input fails naming the lock file, and the
    user's file is unchanged."""
    tmp, bpath, caps = ws
    users = _users_file(tmp)
    out = tmp / "out"
    _plant(out / ".hsi_torch_done" / "a.lock", users, how)
    assert _rec(bpath, out, str(caps / "a.npy")) == 1
    err = capsys.readouterr().err
    assert "a.lock" in err and "not a lock file this program wrote" in err
    assert users.read_bytes() == b"the user's own notes, not to be touched\n"


@pytest.mark.parametrize("how", ["symlink", "hardlink"])
def test_run_store_lock_planted_as_a_link_is_never_written_through(ws, capsys, how):
    """The same at the run store's lock ``OUT/cubes.zarr/.hsi_torch.lock`` (``--format
    zarr``)."""
    pytest.importorskip("numcodecs")
    tmp, bpath, caps = ws
    users = _users_file(tmp)
    out = tmp / "out"
    _plant(out / "cubes.zarr" / ".hsi_torch.lock", users, how)
    assert _rec(bpath, out, "--format", "zarr", str(caps / "a.npy")) == 1
    err = capsys.readouterr().err
    assert ".hsi_torch.lock" in err and "not a lock file this program wrote" in err
    assert users.read_bytes() == b"the user's own notes, not to be touched\n"


def test_simulate_marker_that_is_a_hard_link_is_never_written_through(tmp_path):
    """A hard link at ``OUT/.hsi_torch_simulate_incomplete`` (to ``precious.txt``) was opened,
    truncated and the process id written into it. Now refused, the file unchanged."""
    from hsi_torch.errors import InputError
    from hsi_torch.simulate.cli_entry import INCOMPLETE_MARKER, incomplete_run

    users = _users_file(tmp_path, "precious.txt")
    out = tmp_path / "out"
    _plant(out / INCOMPLETE_MARKER, users, "hardlink")
    (out / "manifest.json").write_text("{}")
    with pytest.raises(InputError, match="2 hard links"):
        with incomplete_run(out, fresh=False):
            pass
    assert users.read_bytes() == b"the user's own notes, not to be touched\n"


def test_own_lock_files_are_reused_and_foreign_ones_refused(tmp_path):
    """The layer's rules on a lock file already there: ours (regular, one link) is reused;
    a FIFO is refused without blocking; a symlink, a hard link are refused."""
    from hsi_torch.errors import InputError
    from hsi_torch.io.atomic import hold_lock, open_own_file

    lock = tmp_path / "x.lock"
    with hold_lock(lock, lambda h: f"busy {h}"):
        assert lock.read_text() == str(os.getpid())
        with pytest.raises(InputError, match=f"busy {os.getpid()}"):  # a second holder
            with hold_lock(lock, lambda h: f"busy {h}"):
                pass
    assert not lock.exists()
    lock.write_text("left by a killed run")
    fd, created = open_own_file(lock)
    os.close(fd)
    assert not created
    fifo = tmp_path / "f.lock"
    os.mkfifo(fifo)
    with pytest.raises(InputError, match="FIFO"):
        _within(5, lambda: open_own_file(fifo), fifo)


# --- demo and experiment take a lock (H11) ---------------------------------------------------


def _hold_flock(path: Path):
    """A separate process holding an exclusive ``flock`` on ``path`` (as a running demo would);
    returns it (its pid is written into the file)."""
    code = ("import fcntl, os, sys, time\n"
            "fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT, 0o644)\n"
            "fcntl.flock(fd, fcntl.LOCK_EX)\n"
            "os.write(fd, str(os.getpid()).encode())\n"
            "print('held', flush=True)\n"
            "time.sleep(60)\n")  # fmt: skip
    proc = subprocess.Popen([sys.executable, "-c", code, str(path)], stdout=subprocess.PIPE,
                            text=True)  # fmt: skip
    assert proc.stdout.readline().strip() == "held"
    return proc


def test_a_second_demo_into_the_same_folder_is_refused_naming_the_first(tmp_path, monkeypatch,
                                                                        capsys):  # fmt: skip
    """Two ``demo --quick --out D`` at once mixed their files (seed-7 captures beside seed-0
    cubes) and the first to finish marked the folder complete. Now a demo holds
    ``D/.hsi_torch_run.lock`` while it runs: a second one is refused at once, naming the first
    one's process, and writes nothing."""
    from hsi_torch.experiments import demo as demo_mod

    ran = []

    def tiny_demo(out, cfg, *, quick, log):
        ran.append(out)
        (out / "summary.json").write_text('{"scenes": {}, "files": []}')

    monkeypatch.setattr(demo_mod, "demo", tiny_demo)
    out = tmp_path / "demo"
    out.mkdir()
    (out / ".hsi_torch_demo").write_text("a folder written by hsi-torch demo\n")
    first = _hold_flock(out / ".hsi_torch_run.lock")
    try:
        assert main(["demo", "--quick", "--out", str(out), "--set", "progress=false"]) == 1
        err = capsys.readouterr().err
        assert f"process {first.pid}" in err and "another run" in err
        assert not ran and sorted(p.name for p in out.iterdir()) == [
            ".hsi_torch_demo", ".hsi_torch_run.lock"]
    finally:
        first.kill()
        first.wait()
    # the first run is gone: the folder is free again, and the lock is removed when done
    assert main(["demo", "--quick", "--out", str(out), "--set", "progress=false"]) == 0
    assert ran == [out] and not (out / ".hsi_torch_run.lock").exists()


def test_a_second_experiment_into_the_same_folder_is_refused(tmp_path, capsys):
    """The same for ``experiment NAME --out D``."""
    from hsi_torch.experiments import cli_entry as ce

    ce.register_experiment("fs_tiny", "test_never_destroy", "_TinyCfg", "_tiny_run")
    try:
        out = tmp_path / "exp"
        out.mkdir()
        first = _hold_flock(out / ".hsi_torch_run.lock")
        try:
            assert main(["experiment", "fs_tiny", "--out", str(out), "-q"]) == 1
            assert f"process {first.pid}" in capsys.readouterr().err
            assert not (out / "summary.json").exists()
        finally:
            first.kill()
            first.wait()
        assert main(["experiment", "fs_tiny", "--out", str(out), "-q"]) == 0
        assert (out / "summary.json").is_file()
    finally:
        ce.EXPERIMENTS.pop("fs_tiny")


# --- done-markers are data (H5, H6) ----------------------------------------------------------


def test_a_copied_output_folder_is_never_tied_to_the_original(ws, capsys):
    """``cp -a results copy``; a rerun into the copy with other settings is refused (its cubes
    are not its own there); the copy's cubes moved away as the refusal says, and a rerun: the
    *original* folder's cubes were deleted ("removed … an earlier run's output"). Now nothing
    outside the copy is touched."""
    tmp, bpath, caps = ws
    inp = caps / "a.npy"
    orig = tmp / "results"
    assert _rec(bpath, orig, str(inp)) == 0
    before = _snapshot(orig)
    copy = tmp / "copy"
    shutil.copytree(orig, copy, symlinks=True)  # cp -a: times kept
    capsys.readouterr()
    assert _rec(bpath, copy, "--set", "beta=1000", str(inp)) == 1
    assert "refusing to write over" in capsys.readouterr().err
    moved = tmp / "moved"
    moved.mkdir()
    for p in copy.iterdir():
        if p.name.startswith("a"):
            p.rename(moved / p.name)
    assert _rec(bpath, copy, "--set", "beta=1000", str(inp)) == 0
    cap = capsys.readouterr()
    assert "an earlier run's output" not in cap.out + cap.err
    assert _snapshot(orig) == before, "the original folder changed"


def _plant_marker(out: Path, inp: Path, victim: Path, rel: str | None = None) -> Path:
    """A done-marker for ``inp`` in ``out`` that lists ``victim`` (by its absolute path, or by
    ``rel``) with its current size and time, as an earlier run's output."""
    from hsi_torch.io.atomic import folder_identity

    digest = hashlib.sha1(os.fsencode(os.path.abspath(inp))).hexdigest()[:10]
    marker = out / ".hsi_torch_done" / f"{inp.stem}-{digest}.json"
    marker.parent.mkdir(parents=True, exist_ok=True)
    st = victim.stat()
    name = rel if rel is not None else str(victim)
    marker.write_text(json.dumps({
        "status": "done", "input": os.path.abspath(inp),
        "input_stamp": [st.st_size, st.st_mtime_ns], "fingerprint": "x",
        "outputs": [name], "owned": [name],
        "output_stamps": {name: [st.st_size, st.st_mtime_ns]},
        "out_id": folder_identity(out),
    }))  # fmt: skip
    return marker


@pytest.mark.parametrize("form", ["absolute", "dotdot", "symlinked"])
def test_a_marker_planted_in_an_untrusted_out_deletes_nothing_outside_it(ws, capsys, form):
    """A done-marker planted in ``--out`` (its name is predictable) listing ``~/thesis.tex``
    with that file's size and time made reconstruct delete it, exit 0. Now a marker's paths are
    confined to ``--out`` (absolute, ``..`` and paths through a symlinked folder are void) and
    the file stays."""
    tmp, bpath, caps = ws
    inp = caps / "a.npy"
    home = tmp / "home"
    home.mkdir()
    thesis = _users_file(home, "thesis.tex")
    out = tmp / "out"
    out.mkdir()
    if form == "symlinked":
        (out / "docs").symlink_to(home)
    rel = {"absolute": None, "dotdot": "../home/thesis.tex", "symlinked": "docs/thesis.tex"}
    _plant_marker(out, inp, thesis, rel[form])
    assert _rec(bpath, out, str(inp)) == 0
    assert thesis.read_bytes() == b"the user's own notes, not to be touched\n"
    assert (out / "a.npz").is_file()


def test_markers_hold_paths_relative_to_out_and_its_identity(ws):
    """What a marker holds: output paths relative to ``--out`` and ``out_id`` (device, inode);
    a rerun still resumes (skips) the finished input from such a marker."""
    tmp, bpath, caps = ws
    out = tmp / "out"
    assert _rec(bpath, out, str(caps / "a.npy")) == 0
    (marker,) = (out / ".hsi_torch_done").glob("a-*.json")
    rec = json.loads(marker.read_text())
    st = out.stat()
    assert rec["out_id"] == [st.st_dev, st.st_ino]
    assert "a.npz" in rec["outputs"] and all(not os.path.isabs(p) for p in rec["outputs"])
    assert set(rec["output_stamps"]) == set(rec["outputs"])
    before = _snapshot(out)
    assert _rec(bpath, out, str(caps / "a.npy")) == 0
    assert {k: v for k, v in _snapshot(out).items() if "runs/" not in k and
            not k.startswith(".hsi_torch_done")} == {
        k: v for k, v in before.items() if "runs/" not in k and
        not k.startswith(".hsi_torch_done")}  # fmt: skip


def test_confined_refuses_paths_leaving_the_folder(tmp_path):
    from hsi_torch.errors import InputError
    from hsi_torch.io.atomic import confined, remove_confined

    (tmp_path / "sub").mkdir()
    (tmp_path / "link").symlink_to(tmp_path / "sub")
    assert confined(tmp_path, "sub/x.tif") == tmp_path / "sub" / "x.tif"
    for bad in ("/etc/passwd", "../x", "sub/../../x", "", "a//b", "./x", "link/x.tif", 3):
        with pytest.raises(InputError):
            confined(tmp_path, bad)
    outside = _users_file(tmp_path.parent, f"{tmp_path.name}-outside.txt")
    assert not remove_confined(tmp_path, outside)
    assert not remove_confined(tmp_path, tmp_path / "link")  # a symlink is not a file of ours
    assert outside.exists() and (tmp_path / "link").is_symlink()
    ours = tmp_path / "sub" / "x.tif"
    ours.write_bytes(b"x")
    assert remove_confined(tmp_path, ours) and not ours.exists()


# --- a FIFO in an untrusted --out cannot hang the pre-checks (M10) ---------------------------


def test_a_fifo_in_out_does_not_hang_the_pre_checks(tmp_path, ws):
    """A FIFO named ``summary.json`` (demo), ``.hsi_torch_experiment`` (experiment) or a
    done-marker (reconstruct) hung the pre-checks forever. Now each is refused or ignored at
    once."""
    from hsi_torch.errors import InputError
    from hsi_torch.experiments.cli_entry import check_demo_out, check_experiment_out
    from hsi_torch.recon.batch.targets import FilesTarget, _marker_path

    demo_out = tmp_path / "d"
    demo_out.mkdir()
    os.mkfifo(demo_out / "summary.json")
    with pytest.raises(InputError, match="holds no earlier demo run"):
        _within(10, lambda: check_demo_out(demo_out), demo_out / "summary.json")
    exp_out = tmp_path / "e"
    exp_out.mkdir()
    os.mkfifo(exp_out / ".hsi_torch_experiment")
    with pytest.raises(InputError, match="holds a run of the experiment"):
        _within(10, lambda: check_experiment_out(exp_out, "design"),
                exp_out / ".hsi_torch_experiment")  # fmt: skip
    _tmp, _bpath, caps = ws
    out = tmp_path / "r"
    marker = _marker_path(out, caps / "a.npy")
    marker.parent.mkdir(parents=True)
    os.mkfifo(marker)
    assert _within(10, lambda: FilesTarget(out).is_done(caps / "a.npy"), marker) is False


def test_own_files_are_read_bounded_and_regular_only(tmp_path):
    from hsi_torch.errors import FileFormatError
    from hsi_torch.io.atomic import read_own_bytes, read_own_json

    big = tmp_path / "big.json"
    big.write_bytes(b" " * 2000)
    with pytest.raises(FileFormatError, match="larger than"):
        read_own_bytes(big, 1000)
    assert read_own_json(big, 1000) is None
    fifo = tmp_path / "fifo.json"
    os.mkfifo(fifo)
    assert _within(5, lambda: read_own_json(fifo), fifo) is None
    with pytest.raises(FileFormatError, match="FIFO"):
        _within(5, lambda: read_own_bytes(fifo), fifo)
    if os.path.exists("/dev/zero"):
        with pytest.raises(FileFormatError, match="character device"):
            _within(5, lambda: read_own_bytes("/dev/zero", follow=True))
    (tmp_path / "ok.json").write_text('{"a": 1}')
    assert read_own_json(tmp_path / "ok.json") == {"a": 1}


# --- view --screenshot (H4) ------------------------------------------------------------------


def _fake_view(paths, *, screenshot=None, points=(), band_nm=None):
    """What the viewer does to the screenshot's path (without napari): write a PNG there."""
    from hsi_torch.io.atomic import atomic_write

    with atomic_write(screenshot, "wb") as f:
        f.write(b"\x89PNG\r\n\x1a\n" + b"a window")


@pytest.fixture
def envi_cube(tmp_path):
    from hsi_torch.io.cube import save_cube_formats

    wl = np.arange(430.0, 671.0, 10.0)
    cube = np.random.default_rng(0).random((wl.size, 6, 7)).astype(np.float32)
    save_cube_formats(tmp_path / "c", cube, wl, np.ones((6, 7), bool), {}, formats=("envi",))
    return tmp_path / "c.hdr"


def test_screenshot_over_a_file_of_the_viewed_cube_is_refused(envi_cube, monkeypatch, capsys):
    """``view c.hdr --screenshot c.img`` wrote the PNG over the ENVI data file (only the files
    named on the command line were checked). Now every file the cube consists of is refused,
    even with ``--overwrite``, before the viewer starts."""
    pytest.importorskip("napari")
    from hsi_torch.viewer import plugin

    monkeypatch.setattr(plugin, "view", _fake_view)
    img = envi_cube.with_suffix(".img")
    before = img.read_bytes()
    for extra in ([], ["--overwrite"]):
        assert main(["view", str(envi_cube), "--screenshot", str(img), *extra]) == 1
        assert "is an input of this command" in capsys.readouterr().err
    assert img.read_bytes() == before


def test_screenshot_over_a_file_it_did_not_write_needs_overwrite(tmp_path, envi_cube,
                                                                 monkeypatch, capsys):  # fmt: skip
    """An existing file that is not a screenshot of ``view`` (a user's notes, a PNG of another
    program) is replaced only with ``--overwrite``; an earlier screenshot is replaced."""
    pytest.importorskip("napari")
    from hsi_torch.viewer import plugin
    from hsi_torch.viewer.cli_entry import SCREENSHOT_SOFTWARE, check_screenshot

    monkeypatch.setattr(plugin, "view", _fake_view)
    notes = _users_file(tmp_path, "shot.png")
    assert main(["view", str(envi_cube), "--screenshot", str(notes)]) == 1
    assert "not a screenshot written by hsi-torch view" in capsys.readouterr().err
    assert notes.read_bytes() == b"the user's own notes, not to be touched\n"
    assert main(["view", str(envi_cube), "--screenshot", str(notes), "--overwrite"]) == 0
    assert notes.read_bytes().startswith(b"\x89PNG")
    # an earlier screenshot (tagged) may be replaced without --overwrite
    import matplotlib.image as mpimg

    ours = tmp_path / "ours.png"
    mpimg.imsave(ours, np.zeros((4, 5, 3)), metadata={"Software": SCREENSHOT_SOFTWARE})
    check_screenshot(ours, [envi_cube])
    other = tmp_path / "other.png"
    mpimg.imsave(other, np.zeros((4, 5, 3)))
    with pytest.raises(Exception, match="not a screenshot"):
        check_screenshot(other, [envi_cube])


# --- a plaintext scheduler named by a scheduler file (M4) ------------------------------------


@pytest.mark.parametrize(("address", "warned"), [
    ("tcp://10.1.2.3:8786", True), ("ws://10.1.2.3:8786", True), ("ucx://10.1.2.3:8786", True),
    ("tcp://127.0.0.1:8786", False), ("tls://10.1.2.3:8786", False),
])  # fmt: skip
def test_a_scheduler_file_naming_a_plaintext_scheduler_is_warned_about(tmp_path, monkeypatch,
                                                                        capsys, address, warned):
    """``--scheduler-file`` naming ``tcp://`` off this machine, ``ws://`` or ``ucx://`` got no
    warning (``--scheduler tcp://...`` did). Now the same warning, before connecting."""
    from hsi_torch.recon import distributed as dist

    class _Fake:
        @staticmethod
        def Client(*args, **kwargs):  # noqa: N802 - distributed's name
            raise OSError("connection refused (test)")

    monkeypatch.setattr(dist, "_distributed", lambda: _Fake)
    f = tmp_path / "scheduler.json"
    f.write_text(json.dumps({"type": "Scheduler", "address": address}))
    with pytest.raises(OSError, match="cannot connect"):
        with dist.connect(scheduler_file=f):
            pass
    err = capsys.readouterr().err
    assert ("without encryption or authentication" in err) == warned, err


# --- a kill between a commit's renames (L4) --------------------------------------------------

_KILL_MID_COMMIT = """
import os, signal, sys
from pathlib import Path
from hsi_torch.io import atomic

folder = Path(sys.argv[1])
real = os.replace
moves = []

def replace_then_die(src, dst):
    real(src, dst)
    if not str(dst).endswith(".json"):  # not the journal
        moves.append(dst)
    if len(moves) == 1:  # after the first output's move
        os.kill(os.getpid(), signal.SIGKILL)

atomic.os.replace = replace_then_die
with atomic.replace_then_commit() as tx:
    tx.write(folder / "calib_diagnostics.png", lambda t: t.write_bytes(b"new figure"))
    tx.write(folder / "calib.npz", lambda t: t.write_bytes(b"new bundle"))
"""


def test_a_kill_between_a_commits_renames_is_marked_and_undone(tmp_path):
    """SIGKILL between calibrate's commit renames left a new ``calib_diagnostics.png`` beside
    the old bundle, unmarked. Now the commit's journal marks the folder, and the next
    transaction into it (a rerun) puts the earlier figure back before anything else."""
    from hsi_torch.io.atomic import ReplaceTransaction, clean_stale_temp_files

    folder = tmp_path / "calib"
    folder.mkdir()
    (folder / "calib_diagnostics.png").write_bytes(b"old figure")
    (folder / "calib.npz").write_bytes(b"old bundle")
    env = {**os.environ, "PYTHONPATH": f"{REPO}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    proc = subprocess.run([sys.executable, "-c", _KILL_MID_COMMIT, str(folder)], env=env,
                          capture_output=True, text=True, timeout=120)  # fmt: skip
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    assert (folder / "calib_diagnostics.png").read_bytes() == b"new figure"  # the kill's state
    assert (folder / "calib.npz").read_bytes() == b"old bundle"
    journals = list(folder.glob(".hsi_torch_commit-*.json"))
    assert len(journals) == 1, "the half-done commit is not marked"
    assert "calib_diagnostics.png" in journals[0].read_text()
    ReplaceTransaction().check(folder / "calib.npz")  # what a rerun does first
    assert (folder / "calib_diagnostics.png").read_bytes() == b"old figure"
    assert (folder / "calib.npz").read_bytes() == b"old bundle"
    assert not list(folder.glob(".hsi_torch_commit-*.json"))
    clean_stale_temp_files(folder)
    assert sorted(p.name for p in folder.iterdir()) == ["calib.npz", "calib_diagnostics.png"]


def test_calibrate_moves_the_bundle_last():
    """The bundle is the last file calibrate's commit moves into place (so a kill before it
    never leaves a new bundle beside old diagnostics)."""
    src = (PACKAGE / "calibrate" / "cli_entry.py").read_text()
    tree = ast.parse(src)
    for fn in ast.walk(tree):
        writes = [ast.unparse(n.args[0]) for n in ast.walk(fn) if isinstance(n, ast.Call)
                  and ast.unparse(n.func) == "tx.write"] if isinstance(fn, ast.With) else []
        if "bundle_path" in writes:
            assert writes[-1] == "bundle_path", writes


# --- sizes and full disks (L5) ---------------------------------------------------------------


def test_sizes_are_shown_in_a_readable_unit():
    """``0.0 GiB free … needs 0.0 GiB``: small sizes are now shown in MiB, KiB or bytes."""
    from hsi_torch.io.atomic import human_size

    assert human_size(3 << 30) == "3.0 GiB"
    assert human_size(40 << 20) == "40.0 MiB"
    assert human_size(1536) == "1.5 KiB"
    assert human_size(17) == "17 bytes"


def test_a_full_disk_names_the_destination_not_the_staging_path(tmp_path, monkeypatch):
    """A full disk at the rename, or while a staged tree is written, named the temporary path
    (``.x.123-abc.tmp``, ``.staging.123-abc.tmp/...``). Now the destination file."""
    from hsi_torch.io import atomic

    dest = tmp_path / "summary.json"

    def full(src, dst):
        raise OSError(errno.ENOSPC, "No space left on device", str(src))

    monkeypatch.setattr(atomic.os, "replace", full)
    with pytest.raises(OSError, match=r"No space left on device while writing .*summary\.json$"):
        atomic.atomic_write_text(dest, "{}")
    monkeypatch.undo()
    out = tmp_path / "set"
    with pytest.raises(OSError) as info:
        with atomic.replace_then_commit() as tx:
            staged = tx.stage_tree(out) / "captures" / "x.tif"
            raise OSError(errno.ENOSPC, "No space left on device", str(staged))
    assert str(info.value).endswith(str(out / "captures" / "x.tif"))
    assert ".tmp" not in str(info.value)
    assert not [p for p in tmp_path.rglob("*") if p.name.endswith(".tmp")]


def test_cache_full_disk_message_shows_small_sizes(tmp_path, monkeypatch, capsys):
    """The cache's "not written" message showed ``0.0 GiB free … needs 0.0 GiB``."""
    from collections import namedtuple

    from hsi_torch.recon import precompute_cache as pc

    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(pc.shutil, "disk_usage", lambda p: usage(1 << 30, 0, 5 << 20))
    messages = []
    monkeypatch.setattr(pc, "_warn", messages.append)
    assert not pc.save_entry(tmp_path / "x.entry", "key", {"a": np.zeros(1000)})
    assert any("5.0 MiB free" in m and "needs 7.8 KiB" in m for m in messages), messages
