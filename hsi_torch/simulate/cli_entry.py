"""``hsi-torch simulate [--config C] --out DIR [--set key=value ...] [--device D] [--overwrite]``
(without ``--config``: the shipped ``simulate.yaml``, the README's default prototype).

``--out`` must be a new or empty folder, a folder holding an incomplete run of this command (its
:data:`INCOMPLETE_MARKER`, written first, locked while the run lasts and removed once the whole
set is written: a rerun finishes it, deleting nothing), or ``--overwrite`` is given (the new set is
staged and moved into place when complete, :func:`hsi_torch.io.atomic.replace_then_commit`). No
output may be one of the command's inputs. docs/simulate.md, *The command*, tells the rules in
full."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import os
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

#: entries that mark a folder as a capture set (named in the refusal)
_CAPTURE_SET_MARKS = ("manifest.json", "nominal_layout.json", "scan", "white", "grid", "dark",
                      "scenes", "truth.npz")

#: Written into a new or empty ``--out`` before anything else and removed once the set is
#: complete: a folder holding it is an incomplete (interrupted or running) run of simulate. While
#: the run lasts its process holds an exclusive lock on it and its id is the file's content.
INCOMPLETE_MARKER = ".hsi_torch_simulate_incomplete"


def existing_entries(out: Path) -> list[str]:
    """The entries of ``out`` other than this package's temporary files (sorted names)."""
    from hsi_torch.io.atomic import TEMP_FILE_RE

    if not out.is_dir():
        return []
    return sorted(e.name for e in os.scandir(out) if not TEMP_FILE_RE.match(e.name))


def check_simulate_out(out: Path, overwrite: bool) -> str:
    """How ``simulate --out`` may write ``out``: ``"new"`` (new or empty folder), ``"resume"``
    (an incomplete earlier run: its :data:`INCOMPLETE_MARKER` is there) or ``"replace"`` (files,
    with ``overwrite``: the new set is staged and moved into place when complete).

    Raises:
        InputError: ``out`` holds files, no incomplete run and ``overwrite`` is false (the
            message names a few of them, and says when the folder looks like a capture set).
    """
    from hsi_torch.errors import InputError

    names = existing_entries(out)
    if not names:
        return "new"
    if INCOMPLETE_MARKER in names:
        return "resume"
    if overwrite:
        return "replace"
    marks = [n for n in names if n in _CAPTURE_SET_MARKS]
    what = (f"it looks like a capture set ({', '.join(marks[:4])})" if marks
            else f"it holds {len(names)} entr{'y' if len(names) == 1 else 'ies'}, e.g. "
                 f"{', '.join(names[:3])}")  # fmt: skip
    raise InputError(
        f"--out {out} is not empty: {what}. simulate would overwrite its files; give "
        "--overwrite to replace them (the new set is written completely first), or choose a "
        "new folder"
    )


def _only_marker_left(out: Path) -> bool:
    """Whether ``out`` holds nothing but the incomplete-run marker (and temporary files)."""
    return existing_entries(out) == [INCOMPLETE_MARKER]


@contextlib.contextmanager
def incomplete_run(out: Path, fresh: bool = True) -> Iterator[None]:
    """Mark ``out`` as holding an incomplete simulate run while the block runs.

    Writes :data:`INCOMPLETE_MARKER` (this process's id, flushed to the disk before any output
    is written) and holds an exclusive lock on it; removes it when the block ends normally (the
    set is complete). When the block raises, the marker stays if any output was written (the
    folder is an incomplete run: a rerun may finish it) and is removed if none was.

    Args:
        out: the output folder (created if needed).
        fresh: ``out`` was found new or empty (``False``: it holds an incomplete run); once the
            lock is held this is checked again, so that a concurrent run's files are never
            written over.

    Raises:
        InputError: another run holds the marker's lock (the message names its process), or
            wrote into ``out`` since it was checked, or the incomplete run found there completed
            since (its marker is gone); the marker is a symbolic link, a hard link, or not a
            regular file of this user (never written through).
    """
    from hsi_torch.errors import InputError
    from hsi_torch.io.atomic import lock_or_refuse, mark_lock_holder, open_own_file, remove_file
    from hsi_torch.io.paths import ensure_out_dir

    ensure_out_dir(out)
    path = out / INCOMPLETE_MARKER
    # never through a symlink or a hard link: the process id written below truncates the file
    fd, created = open_own_file(path, "marker")
    lock_or_refuse(fd, lambda holder: (
        f"--out {out} is being written by another simulate run (process {holder}) right now; "
        "run again when it has finished, or choose another folder"))
    try:
        try:  # still the marker at that name? (a run that just finished removed it)
            same = os.stat(path).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        # resuming (not fresh) needs the interrupted run's marker: had it to be created, the
        # run found incomplete has completed (or its marker was removed) since the check, and
        # the folder is a complete set, which only --overwrite replaces
        if not same or (fresh and not _only_marker_left(out)) or (not fresh and created):
            if same and created:
                remove_file(path)
            raise InputError(f"--out {out} was written by another simulate run while this one "
                             "started; run again")  # fmt: skip
        mark_lock_holder(fd)
        os.fsync(fd)
        try:
            yield
        except BaseException:
            if _only_marker_left(out):  # nothing written: no incomplete run to mark
                remove_file(path)
            raise
        # the set is complete (while still locked: a waiting rerun re-checks)
        remove_file(path, missing_ok=False)
    finally:
        os.close(fd)


def _clean_temp_files_below(folder: Path) -> None:
    """Remove the temporary files that killed writers left in ``folder`` and its sub-folders."""
    from hsi_torch.io.atomic import clean_stale_temp_files

    for root, _dirs, _files in list(os.walk(folder)):
        clean_stale_temp_files(root)


def _config_inputs(cfg: Any, config_file: Path | None) -> list[Path]:
    """Files the configuration names (scene cubes, spectrum CSVs) and the config file itself."""
    found: list[Path] = [] if config_file is None else [Path(config_file)]

    def walk(obj: Any) -> None:
        if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
            for f in dataclasses.fields(obj):
                walk(getattr(obj, f.name))
        elif isinstance(obj, dict):
            for v in obj.values():
                walk(v)
        elif isinstance(obj, (list, tuple)):
            for v in obj:
                walk(v)
        elif isinstance(obj, (str, os.PathLike)):
            try:
                p = Path(obj)
                if len(str(obj)) < 4096 and p.is_file():
                    found.append(p)
            except (OSError, ValueError):
                pass

    walk(cfg)
    return found


def run_simulate(args: argparse.Namespace) -> int:
    """Entry point called by :mod:`hsi_torch.cli`: render a capture set with ground truth."""
    from hsi_torch.cli_common import config_source, load_args_config
    from hsi_torch.console import info
    from hsi_torch.io.atomic import InputFiles, clean_stale_temp_files, replace_then_commit
    from hsi_torch.io.paths import file_states
    from hsi_torch.simulate.capture_sets import simulate_capture_set
    from hsi_torch.simulate.config import SimulateConfig

    out = Path(args.out)
    mode = check_simulate_out(out, bool(getattr(args, "overwrite", False)))
    cfg = load_args_config(args, SimulateConfig, default="simulate")
    device = getattr(args, "device", None)
    input_files = _config_inputs(cfg, config_source(args, "simulate"))
    inputs = InputFiles(input_files)

    def log(m: str) -> None:
        info(m, file=sys.stderr)

    if mode == "replace":
        clean_stale_temp_files(out)  # a killed --overwrite run's staging folder
        with replace_then_commit(inputs) as tx:
            staging = tx.stage_tree(out)
            summary = simulate_capture_set(cfg, staging, device=device, log=log)
        summary = dataclasses.replace(summary, out_dir=out)
        print(f"hsi-torch: replaced {len(tx.replaced)} existing file(s) in {out} "
              f"(--overwrite)", file=sys.stderr)
        info(summary.report())
        return 0
    before: dict[str, tuple[int, int, int]] = {}
    if mode == "resume":  # an interrupted run's folder: its files are this command's own
        _refuse_inputs_inside(out, input_files)
        _clean_temp_files_below(out)
        before = file_states(out)
        before.pop(INCOMPLETE_MARKER, None)
        print(f"hsi-torch: --out {out} holds an incomplete earlier simulate run "
              f"({len(before)} file(s)); writing the set into it again", file=sys.stderr)
    with incomplete_run(out, fresh=mode == "new"):
        summary = simulate_capture_set(cfg, out, device=device, log=log)
    if before:
        after = file_states(out)
        left = sorted(k for k, v in before.items() if after.get(k) == v)
        if left:
            shown = ", ".join(left[:5]) + (", ..." if len(left) > 5 else "")
            print(f"hsi-torch: {len(left)} file(s) of the interrupted run are not part of the "
                  f"new set and were left in place: {shown}", file=sys.stderr)
    info(summary.report())
    return 0


def _refuse_inputs_inside(out: Path, inputs: list[Path]) -> None:
    """Refuse to write into ``out`` when one of the command's input files lies inside it."""
    from hsi_torch.errors import InputError

    root = out.resolve()
    for p in inputs:
        if p.resolve().is_relative_to(root):
            raise InputError(
                f"{p} is an input of this command and lies inside --out {out}, which holds an "
                "incomplete earlier run that would be written into; move the file out, or "
                "choose another folder"
            )
