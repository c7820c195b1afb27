"""``hsi-torch simulate [--config C] --out DIR [--set key=value ...] [--device D] [--overwrite]``
(without ``--config``: the shipped ``simulate.yaml``, the README's default prototype).

``--out`` must be a new or empty folder: a folder that holds files (above all one laid out like a
device's capture set: ``manifest.json``, ``scan/``, ``white/``) is refused unless
``--overwrite`` is given. With ``--overwrite`` the new set is rendered into a temporary folder
inside ``DIR`` and its files are moved into place only when all of them are complete
(:func:`hsi_torch.io.atomic.replace_then_commit`): a failed run leaves the old files as they
were, and files of ``DIR`` the new set does not contain are kept. No output may be one of the
command's inputs (its configuration file, a scene cube, a spectrum file)."""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
from pathlib import Path
from typing import Any

#: entries that mark a folder as a capture set (named in the refusal)
_CAPTURE_SET_MARKS = ("manifest.json", "nominal_layout.json", "scan", "white", "grid", "dark",
                      "scenes", "truth.npz")


def existing_entries(out: Path) -> list[str]:
    """The entries of ``out`` other than this package's temporary files (sorted names)."""
    from hsi_torch.io.atomic import TEMP_FILE_RE

    if not out.is_dir():
        return []
    return sorted(e.name for e in os.scandir(out) if not TEMP_FILE_RE.match(e.name))


def check_simulate_out(out: Path, overwrite: bool) -> bool:
    """Refuse a non-empty ``--out`` without ``overwrite``; returns whether ``out`` holds files.

    Raises:
        InputError: ``out`` holds files and ``overwrite`` is false (the message names a few of
            them, and says when the folder looks like a capture set).
    """
    from hsi_torch.errors import InputError

    names = existing_entries(out)
    if not names or overwrite:
        return bool(names)
    marks = [n for n in names if n in _CAPTURE_SET_MARKS]
    what = (f"it looks like a capture set ({', '.join(marks[:4])})" if marks
            else f"it holds {len(names)} entr{'y' if len(names) == 1 else 'ies'}, e.g. "
                 f"{', '.join(names[:3])}")  # fmt: skip
    raise InputError(
        f"--out {out} is not empty: {what}. simulate would overwrite its files; give "
        "--overwrite to replace them (the new set is written completely first), or choose a "
        "new folder"
    )


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
    from hsi_torch.io.atomic import InputFiles, replace_then_commit
    from hsi_torch.simulate.capture_sets import simulate_capture_set
    from hsi_torch.simulate.config import SimulateConfig

    out = Path(args.out)
    had_files = check_simulate_out(out, bool(getattr(args, "overwrite", False)))
    cfg = load_args_config(args, SimulateConfig, default="simulate")
    device = getattr(args, "device", None)
    inputs = InputFiles(_config_inputs(cfg, config_source(args, "simulate")))

    def log(m: str) -> None:
        info(m, file=sys.stderr)

    if not had_files:  # a new or empty folder: nothing to lose, write in place
        summary = simulate_capture_set(cfg, out, device=device, log=log)
    else:
        with replace_then_commit(inputs) as tx:
            staging = tx.stage_tree(out)
            summary = simulate_capture_set(cfg, staging, device=device, log=log)
        summary = dataclasses.replace(summary, out_dir=out)
        print(f"hsi-torch: replaced {len(tx.replaced)} existing file(s) in {out} "
              f"(--overwrite)", file=sys.stderr)
    info(summary.report())
    return 0
