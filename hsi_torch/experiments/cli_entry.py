"""``hsi-torch experiment NAME [--config C] --out DIR``: dispatch to the named experiment; and
``hsi-torch demo`` (:func:`run_demo`).

:data:`EXPERIMENTS` maps a name to ``(module, schema class name, run function name)``; the module
is imported only when its experiment runs (so ``hsi-torch --help`` starts fast). A run function
``run(cfg, out: Path, *, device: str | None = None) -> dict`` writes its tables and figures into
``out``; this entry point loads the config (``--config``, else the shipped ``NAME.yaml`` or the
schema's defaults; ``--set``), calls it and writes ``out/resolved_config.yaml``.

A run may write into a folder holding an earlier run of the same experiment; until it completes
the folder is marked ``INCOMPLETE_RUN.json``, and ``experiment_run.json`` (the demo:
``demo_run.json``) then lists what it wrote and what it left (:mod:`hsi_torch.io.run_record`;
docs/experiments.md). To add an experiment, add a line to :data:`EXPERIMENTS` (or call
:func:`register_experiment`).
"""

from __future__ import annotations

import argparse
import importlib
import time
from pathlib import Path
from typing import Any

__all__ = ["EXPERIMENTS", "register_experiment", "resolve_experiment", "run_experiment", "run_demo"]

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
    """CLI entry: ``args.name``, ``args.config`` (Path or None), ``args.overrides``,
    ``args.out``, ``args.device``. Returns the exit status (0)."""
    from hsi_torch.cli_common import load_args_config
    from hsi_torch.config import write_resolved_config
    from hsi_torch.console import info
    from hsi_torch.io.atomic import atomic_write_text
    from hsi_torch.io.paths import ensure_out_dir
    from hsi_torch.io.run_record import RUN_RECORD, finish_out_run, out_run_lock, start_out_run

    schema, run = resolve_experiment(args.name)
    cfg = load_args_config(args, schema, default=args.name)
    out = Path(args.out)
    check_experiment_out(out, args.name)
    out = ensure_out_dir(out)
    command = f"hsi-torch experiment {args.name}"
    with out_run_lock(out, command):  # one run per folder; checked again under the lock
        check_experiment_out(out, args.name)
        atomic_write_text(out / EXPERIMENT_MARKER, f"{args.name}\n")
        run_state = start_out_run(out, command, RUN_RECORD, experiment=args.name)
        t0 = time.perf_counter()
        run(cfg, out, device=getattr(args, "device", None))
        write_resolved_config(cfg, out)
        _record, left = finish_out_run(out, run_state)
    files = sorted(p.name for p in out.iterdir() if p.is_file() and not p.name.startswith("."))
    info(f"experiment '{args.name}' finished in {time.perf_counter() - t0:.1f} s; "
         f"{len(files)} files in {out}: {', '.join(files)}{left}")  # fmt: skip
    return 0


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
    from hsi_torch.io.atomic import read_own_bytes
    from hsi_torch.io.paths import out_entries, refuse_not_empty
    from hsi_torch.io.run_record import RUN_LOCK

    names = [n for n in out_entries(out) if n != RUN_LOCK]
    if not names:
        return
    if EXPERIMENT_MARKER in names:
        try:  # bounded, regular files only: a FIFO planted there cannot hang the check
            owner = read_own_bytes(out / EXPERIMENT_MARKER, 4096).decode("utf-8").strip()
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
    from hsi_torch.io.atomic import read_own_json
    from hsi_torch.io.paths import out_entries, refuse_not_empty
    from hsi_torch.io.run_record import RUN_LOCK

    names = [n for n in out_entries(out) if n != RUN_LOCK]
    if not names or DEMO_MARKER in names:
        return
    # bounded, regular files only: a FIFO named summary.json cannot hang the check
    summary = read_own_json(out / "summary.json", 16 << 20, follow=True)
    if isinstance(summary, dict) and "scenes" in summary and ("files" in summary
                                                              or "stages" in summary):
        return  # a demo's summary (quick or --full), written before the marker existed
    refuse_not_empty(out, names, "demo run", "the demo writes captures/, calib.npz, "
                      "summary.json and a cube and previews per scene")


def run_demo(args: argparse.Namespace) -> int:
    """Entry point of ``hsi-torch demo`` (``--out DIR``, ``--quick``, ``--full``, ``--set``):
    :func:`hsi_torch.experiments.demo.demo`, or with ``--full``
    :func:`hsi_torch.experiments.demo_full.demo_full`; the folder is marked and locked as for an
    experiment."""
    from hsi_torch.cli_common import load_args_config
    from hsi_torch.config import write_resolved_config
    from hsi_torch.console import info
    from hsi_torch.experiments.demo import DemoConfig, demo
    from hsi_torch.io.atomic import atomic_write_text
    from hsi_torch.io.run_record import (
        DEMO_RUN_RECORD,
        finish_out_run,
        out_run_lock,
        start_out_run,
    )

    cfg = load_args_config(args, DemoConfig)
    if getattr(args, "device", None):
        cfg.device = args.device
    out = Path(getattr(args, "out", None) or "demo_output")
    check_demo_out(out)
    out.mkdir(parents=True, exist_ok=True)
    full, quick = bool(getattr(args, "full", False)), bool(getattr(args, "quick", False))
    if full and quick:
        raise ValueError("--full and --quick exclude each other")
    command = "hsi-torch demo" + (" --full" if full else " --quick" if quick else "")
    with out_run_lock(out, command):  # one run per folder; checked again under the lock
        check_demo_out(out)
        # atomically: a symlink at the marker's name is replaced, never written through
        atomic_write_text(out / DEMO_MARKER, "a folder written by hsi-torch demo\n")
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
