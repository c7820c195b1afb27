"""Marking an output folder that a command writes into in place while the run is incomplete.

``hsi-torch experiment NAME --out DIR`` and ``hsi-torch demo --out DIR`` write into an earlier
run's folder in place (experiments reuse what an earlier or interrupted run left there), so an
interrupted rerun would leave a mix of new and old files with nothing saying so. Instead
:func:`start_out_run` writes :data:`INCOMPLETE_FILE` before the run starts, listing the files
already there with their size, modification time and inode, and :func:`finish_out_run` writes
the run's record (:data:`RUN_RECORD`, :data:`DEMO_RUN_RECORD`: the files it wrote and those left
from an earlier run, and the run's provenance: the whole command line, the package version and
git commit, the torch / NumPy / Python versions) and then removes :data:`INCOMPLETE_FILE`. While a
run writes there it holds :data:`RUN_LOCK` (:func:`out_run_lock`): a second run into the same
folder is refused.
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from hsi_torch.console import info
from hsi_torch.io.atomic import atomic_write_json, hold_lock, remove_file
from hsi_torch.io.paths import file_states
from hsi_torch.provenance import provenance

__all__ = ["INCOMPLETE_FILE", "RUN_RECORD", "DEMO_RUN_RECORD", "RUN_LOCK", "start_out_run",
           "finish_out_run", "out_run_lock"]  # fmt: skip

#: The prefix of the hidden markers that commands and scripts write into their ``--out`` (e.g.
#: ``.hsi_torch_experiment``, ``.hsi_torch_demo``): not counted as files of a run.
MARKER_PREFIX = ".hsi_torch_"

#: Written into ``experiment NAME --out`` (and ``demo --out``) before the run starts and removed
#: when it is complete: a folder holding it holds a run that has not finished (still running, or
#: interrupted), and it says which files are from an earlier run.
INCOMPLETE_FILE = "INCOMPLETE_RUN.json"

#: Written into ``experiment NAME --out`` when a run completes: when it ran, the files it wrote
#: and the files from an earlier run that it left as they were.
RUN_RECORD = "experiment_run.json"

#: The same record of ``demo --out`` (:data:`INCOMPLETE_FILE` marks a demo's folder the same way).
DEMO_RUN_RECORD = "demo_run.json"

#: The lock that ``demo --out`` and ``experiment NAME --out`` hold while they write there (one
#: run per folder at a time; removed when the run ends).
RUN_LOCK = ".hsi_torch_run.lock"

_STATUS_FILES = (INCOMPLETE_FILE, RUN_RECORD, DEMO_RUN_RECORD)


@contextlib.contextmanager
def out_run_lock(out: Path, command: str) -> Iterator[None]:
    """Hold :data:`RUN_LOCK` in ``out`` (created) while ``command`` writes there in place: a
    second run into the same folder meanwhile is refused at once, naming the process that holds
    it (two runs would mix their files, and the first to finish would mark the folder
    complete). The lock is never opened through a symlink or a hard link planted at its name.

    Raises:
        InputError: another run holds it (the message names its process id).
    """
    out.mkdir(parents=True, exist_ok=True)
    with hold_lock(out / RUN_LOCK, lambda holder: (
            f"--out {out} is being written by another run (process {holder}) right now; "
            f"'{command}' would mix its files with that run's: run again when it has "
            "finished, or choose another folder")):  # fmt: skip
        yield


def _now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


def _earlier_files(out: Path) -> dict[str, tuple[int, int, int]]:
    """The files below ``out`` other than the runs' status files and the writers' hidden
    markers (``.hsi_torch_*`` in ``out`` itself)."""
    return {k: v for k, v in file_states(out).items()
            if k not in _STATUS_FILES and not k.startswith(MARKER_PREFIX)}  # fmt: skip


def start_out_run(out: Path, command: str, record: str, **fields: Any) -> dict[str, Any]:
    """Mark ``out`` incomplete before ``command`` (e.g. ``hsi-torch demo``) writes there in
    place: write :data:`INCOMPLETE_FILE` (atomically) with ``fields`` (e.g. ``experiment=NAME``),
    the start time, this process, the run's provenance (:func:`hsi_torch.provenance.provenance`:
    the whole command line, the package version and git commit, the torch / NumPy / Python
    versions; ``command`` is the whole command line when the run came from it) and every file
    already there (``files_before``: relative path → size, modification time in ns and inode),
    and say on stderr when the folder holds files of an earlier run. ``record`` is the file
    :func:`finish_out_run` writes. Returns what was written (passed on to
    :func:`finish_out_run`)."""
    before = _earlier_files(out)
    prov = provenance()
    state: dict[str, Any] = {
        **fields,
        "command": prov["command"] or command,
        "provenance": prov,
        "state": "incomplete",
        "note": (f"this run of '{command}' has not finished: it is still running, or it was "
                 "interrupted. A file listed under files_before whose size and modification "
                 "time are unchanged is from an earlier run; every other file was written by "
                 "this run. Run the same command again to complete it; this file is removed "
                 f"when a run completes (and {record} written)."),
        "started": _now(),
        "pid": os.getpid(),
        "earlier_run_incomplete": (out / INCOMPLETE_FILE).is_file(),
        "record": record,
        "files_before": {k: {"size": v[0], "mtime_ns": v[1], "inode": v[2]}
                         for k, v in sorted(before.items())},
    }  # fmt: skip
    atomic_write_json(out / INCOMPLETE_FILE, state)
    if before:
        info(f"--out {out} holds {len(before)} file(s) of an earlier "
             f"{'interrupted ' if state['earlier_run_incomplete'] else ''}run; this run "
             f"writes over them in place, and {INCOMPLETE_FILE} marks the folder incomplete "
             "until it has finished", file=sys.stderr)  # fmt: skip
    return state


def finish_out_run(out: Path, state: dict[str, Any]) -> tuple[dict[str, Any], str]:
    """The run that :func:`start_out_run` began is complete: write its record (``state
    ["record"]``; ``written``: files new or changed since the start; ``from_earlier_runs``:
    files already there that are unchanged), then remove :data:`INCOMPLETE_FILE`. Returns the
    record and a text for the run's last line naming the files from an earlier run (``""``
    when there are none)."""
    skip = ("state", "note", "started", "pid", "earlier_run_incomplete", "record",
            "files_before")  # fmt: skip
    before = {k: (v["size"], v["mtime_ns"], v["inode"]) for k, v in state["files_before"].items()}
    after = _earlier_files(out)
    record = {
        **{k: v for k, v in state.items() if k not in skip},
        "state": "complete",
        "started": state["started"],
        "finished": _now(),
        "written": sorted(k for k, v in after.items() if before.get(k) != v),
        "from_earlier_runs": sorted(k for k, v in after.items() if before.get(k) == v),
    }
    atomic_write_json(out / state["record"], record)
    remove_file(out / INCOMPLETE_FILE)
    kept = record["from_earlier_runs"]
    left = (f"; {len(kept)} file(s) are from an earlier run and were not rewritten by this one "
            f"(listed in {state['record']}): {', '.join(kept[:5])}"
            f"{', ...' if len(kept) > 5 else ''}" if kept else "")  # fmt: skip
    return record, left
