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
def sim(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("never_destroy")
    assert main(["simulate", "--out", str(root / "sim"), "--no-progress", "-q"]) == 0
    assert main(["calibrate", "--captures", str(root / "sim"), "--out", str(root / "calib"),
                 "--no-progress", "-q"]) == 0  # fmt: skip
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
