"""``hsi-torch experiment NAME [--config C] --out DIR``: dispatch to the named experiment; and
``hsi-torch demo`` (:func:`run_demo`).

Command modules import lazily (so ``hsi-torch --help`` starts fast): the experiment's module,
and everything a command needs, is imported when the command runs.

Without ``--config`` the shipped ``NAME.yaml`` is used (``hsi-torch config show NAME``), or the
schema's defaults for an experiment that ships none.

The registry maps a name to ``(module, schema class name, run function name)``; the module is
imported only when its experiment runs. A run function has the signature
``run(cfg, out: Path, *, device: str | None = None) -> dict`` and writes its tables and figures
into ``out``; this entry point loads and validates the config (``--config``, ``--set``), calls
it and writes ``out/resolved_config.yaml``.

A run into a folder that holds an earlier run writes its files in place (experiments such as
``mismatch`` reuse what an earlier or interrupted run left there), so until it completes the
folder is marked: :data:`INCOMPLETE_FILE` is written before the experiment starts, listing the
files already there (from earlier runs) with their size and modification time, and removed when
the run is complete; :data:`RUN_RECORD` then lists the files the run wrote and those it left from
an earlier run (see ``docs/experiments.md``). ``hsi-torch demo --out DIR`` marks its folder the
same way (:func:`start_out_run`, :func:`finish_out_run`; record :data:`DEMO_RUN_RECORD`).

To add an experiment, add a line to :data:`EXPERIMENTS` (or call :func:`register_experiment`).
"""

from __future__ import annotations

import argparse
import importlib
import sys
import time
from pathlib import Path
from typing import Any

__all__ = ["EXPERIMENTS", "register_experiment", "resolve_experiment", "run_experiment",
           "run_demo", "start_out_run", "finish_out_run"]

#: name → (module, schema class, run function)
EXPERIMENTS: dict[str, tuple[str, str, str]] = {
    "synthetic": ("hsi_torch.experiments.synthetic", "SyntheticConfig", "run_synthetic"),
    "design": ("hsi_torch.experiments.design", "DesignSweepConfig", "run_design"),
    "opd": ("hsi_torch.experiments.opd", "OPDConfig", "run_opd"),
    "usaf": ("hsi_torch.experiments.usaf", "USAFConfig", "run_usaf"),
    "spatial": ("hsi_torch.experiments.spatial", "SpatialConfig", "run_spatial"),
    "mismatch": ("hsi_torch.experiments.mismatch", "MismatchConfig", "run_mismatch"),
}


def register_experiment(name: str, module: str, schema: str, run: str) -> None:
    """Register (or replace) an experiment: ``module`` holds the dataclass ``schema`` and the
    function ``run(cfg, out, *, device=None)``."""
    EXPERIMENTS[name] = (module, schema, run)


def resolve_experiment(name: str) -> tuple[type, Any]:
    """Import the experiment's module lazily; return ``(schema class, run function)``.

    Raises:
        ValueError: unknown name (lists the known ones) or a module lacking the named objects.
    """
    if name not in EXPERIMENTS:
        raise ValueError(
            f"unknown experiment {name!r}; available: {', '.join(sorted(EXPERIMENTS))}"
        )
    modname, schema_name, run_name = EXPERIMENTS[name]
    module = importlib.import_module(modname)
    schema = getattr(module, schema_name, None)
    run = getattr(module, run_name, None)
    if schema is None or not callable(run):
        raise ValueError(
            f"experiment {name!r}: {modname} lacks {schema_name if schema is None else run_name}"
        )
    return schema, run


def run_experiment(args: argparse.Namespace) -> int:
    """CLI entry: ``args.name``, ``args.config`` (Path or None = the shipped ``<name>.yaml``,
    else the schema's defaults),
    ``args.overrides``, ``args.out``, ``args.device``. Returns the exit status (0)."""
    from hsi_torch.cli_common import load_args_config
    from hsi_torch.config import write_resolved_config
    from hsi_torch.console import info
    from hsi_torch.io.atomic import atomic_write_text
    from hsi_torch.io.paths import ensure_out_dir

    schema, run = resolve_experiment(args.name)
    cfg = load_args_config(args, schema, default=args.name)
    out = Path(args.out)
    check_experiment_out(out, args.name)
    out = ensure_out_dir(out)
    atomic_write_text(out / EXPERIMENT_MARKER, f"{args.name}\n")
    run_state = start_experiment_run(out, args.name)
    t0 = time.perf_counter()
    run(cfg, out, device=getattr(args, "device", None))
    write_resolved_config(cfg, out)
    left = finish_experiment_run(out, run_state)
    files = sorted(p.name for p in out.iterdir() if p.is_file() and not p.name.startswith("."))
    info(f"experiment '{args.name}' finished in {time.perf_counter() - t0:.1f} s; "
         f"{len(files)} files in {out}: {', '.join(files)}{left}")  # fmt: skip
    return 0


#: Written into ``experiment NAME --out`` (and ``demo --out``) before the run starts and removed
#: when it is complete: a folder holding it holds a run that has not finished (still running, or
#: interrupted), and it says which files are from an earlier run.
INCOMPLETE_FILE = "INCOMPLETE_RUN.json"

#: Written into ``experiment NAME --out`` when a run completes: when it ran, the files it wrote
#: and the files from an earlier run that it left as they were.
RUN_RECORD = "experiment_run.json"

#: The same record of ``demo --out`` (:data:`INCOMPLETE_FILE` marks a demo's folder the same way).
DEMO_RUN_RECORD = "demo_run.json"

_STATUS_FILES = (INCOMPLETE_FILE, RUN_RECORD, DEMO_RUN_RECORD)


def _now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


def _earlier_files(out: Path) -> dict[str, tuple[int, int, int]]:
    """The files below ``out`` other than the markers and the runs' status files."""
    from hsi_torch.io.paths import file_states

    return {k: v for k, v in file_states(out).items()
            if k not in _STATUS_FILES and k not in (EXPERIMENT_MARKER, DEMO_MARKER)}  # fmt: skip


def start_out_run(out: Path, command: str, record: str, **fields: Any) -> dict[str, Any]:
    """Mark ``out`` incomplete before ``command`` (e.g. ``hsi-torch demo``) writes there in
    place: write :data:`INCOMPLETE_FILE` (atomically) with ``fields`` (e.g. ``experiment=NAME``),
    the start time, this process and every file already there (``files_before``: relative path
    → size, modification time in ns and inode), and say on stderr when the folder holds files of
    an earlier run. ``record`` is the file :func:`finish_out_run` writes. Returns what was
    written (passed on to :func:`finish_out_run`)."""
    import os

    from hsi_torch.console import info
    from hsi_torch.io.atomic import atomic_write_json

    before = _earlier_files(out)
    state: dict[str, Any] = {
        **fields,
        "command": command,
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
    from hsi_torch.io.atomic import atomic_write_json

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
    (out / INCOMPLETE_FILE).unlink(missing_ok=True)
    kept = record["from_earlier_runs"]
    left = (f"; {len(kept)} file(s) are from an earlier run and were not rewritten by this one "
            f"(listed in {state['record']}): {', '.join(kept[:5])}"
            f"{', ...' if len(kept) > 5 else ''}" if kept else "")  # fmt: skip
    return record, left


def start_experiment_run(out: Path, name: str) -> dict[str, Any]:
    """:func:`start_out_run` for ``hsi-torch experiment NAME`` (record :data:`RUN_RECORD`)."""
    return start_out_run(out, f"hsi-torch experiment {name}", RUN_RECORD, experiment=name)


def finish_experiment_run(out: Path, state: dict[str, Any]) -> str:
    """:func:`finish_out_run` of :func:`start_experiment_run`; returns the text naming the files
    from an earlier run (``""`` when none)."""
    return finish_out_run(out, state)[1]


#: Written into ``experiment NAME --out`` before the experiment runs, holding ``NAME``: the folder
#: holds a run of that experiment (a rerun may replace its files, also after an interrupted run).
EXPERIMENT_MARKER = ".hsi_torch_experiment"


def check_experiment_out(out: Path, name: str) -> None:
    """Refuse an ``experiment NAME --out`` folder that holds files but no earlier run of ``NAME``.

    An experiment writes ``summary.json``, ``manifest.json``, tables (``*.csv``, ``*.md``),
    figures, ``resolved_config.yaml`` (some also ``calib.npz``, ``truth.npz``) into ``out``,
    replacing files of those names: a lab's folder, or another experiment's, would lose them. A
    folder whose marker :data:`EXPERIMENT_MARKER` names ``NAME`` (an earlier or interrupted run)
    may be replaced.

    Raises:
        InputError: ``out`` is a folder with files and no earlier run of ``NAME`` (names a few).
    """
    from hsi_torch.errors import InputError
    from hsi_torch.io.paths import out_entries, refuse_not_empty

    names = out_entries(out)
    if not names:
        return
    if EXPERIMENT_MARKER in names:
        try:
            owner = (out / EXPERIMENT_MARKER).read_text(encoding="utf-8").strip()
        except (OSError, ValueError):
            owner = ""
        if owner == name:
            return
        raise InputError(
            f"--out {out} holds a run of the experiment {owner[:40]!r}, not {name!r}; this run "
            "would replace files of the same names there: choose a new or empty folder"
        )
    refuse_not_empty(out, names, f"run of the experiment {name!r}",
                      "it writes summary.json, manifest.json, tables, figures and "
                      "resolved_config.yaml")


#: Written into ``demo --out`` before anything else: the folder holds a demo run (a rerun may
#: replace its files, also after an interrupted run).
DEMO_MARKER = ".hsi_torch_demo"


def check_demo_out(out: Path) -> None:
    """Refuse a ``demo --out`` folder that holds files but no earlier demo run.

    The demo writes ``captures/``, ``calib.npz``, ``summary.json``, a cube and previews per
    scene (``colorchecker.tif``, ...) into ``out``, replacing files of those names: a lab's
    folder holding its own ``calib.npz`` or ``colorchecker.tif`` would lose them. An earlier
    demo run (the marker :data:`DEMO_MARKER`, or a demo's ``summary.json``) may be replaced.

    Raises:
        InputError: ``out`` is a folder with files and no earlier demo run (names a few).
    """
    import json

    from hsi_torch.io.paths import out_entries, refuse_not_empty

    names = out_entries(out)
    if not names or DEMO_MARKER in names:
        return
    try:
        summary = json.loads((out / "summary.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        summary = None
    if isinstance(summary, dict) and "scenes" in summary and ("files" in summary
                                                              or "stages" in summary):
        return  # a demo's summary (quick or --full), written before the marker existed
    refuse_not_empty(out, names, "demo run", "the demo writes captures/, calib.npz, "
                      "summary.json and a cube and previews per scene")


def run_demo(args: argparse.Namespace) -> int:
    """Entry point of ``hsi-torch demo`` (``--out DIR``, ``--quick``, ``--full``, ``--set``):
    :func:`hsi_torch.experiments.demo.demo`, or with ``--full``
    :func:`hsi_torch.experiments.demo_full.demo_full`. The folder is marked incomplete
    (:data:`INCOMPLETE_FILE`) while the demo runs, and :data:`DEMO_RUN_RECORD` written when it
    completes, as for an experiment."""
    from hsi_torch.cli_common import load_args_config
    from hsi_torch.config import write_resolved_config
    from hsi_torch.console import info
    from hsi_torch.experiments.demo import DemoConfig, demo

    cfg = load_args_config(args, DemoConfig)
    if getattr(args, "device", None):
        cfg.device = args.device
    out = Path(getattr(args, "out", None) or "demo_output")
    check_demo_out(out)
    out.mkdir(parents=True, exist_ok=True)
    full, quick = bool(getattr(args, "full", False)), bool(getattr(args, "quick", False))
    if full and quick:
        raise ValueError("--full and --quick exclude each other")
    (out / DEMO_MARKER).write_text("a folder written by hsi-torch demo\n", encoding="utf-8")
    command = "hsi-torch demo" + (" --full" if full else " --quick" if quick else "")
    run_state = start_out_run(out, command, DEMO_RUN_RECORD)
    if full:
        from hsi_torch.experiments.demo_full import demo_full

        demo_full(out, cfg, log=info)
    else:
        demo(out, cfg, quick=quick, log=info)
    write_resolved_config(cfg, out)
    _record, left = finish_out_run(out, run_state)
    if left:
        info(f"demo finished in {out}{left}")
    return 0
