"""What the ``hsi-torch`` commands share: the configuration file a command runs with.

The command line (:mod:`hsi_torch.cli`) parses the arguments and calls each command's entry
function (``run_<command>(args)`` in the owning ``*/cli_entry.py``) by name; the entry functions
load their configuration through :func:`load_args_config` here. This module sits below both, so
the imports go one way: ``cli`` → (by name) ``*/cli_entry`` → ``cli_common`` → ``config``,
``resources``; nothing in the package imports :mod:`hsi_torch.cli`.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

__all__ = ["config_source", "load_args_config"]


def config_source(args: argparse.Namespace, default: str | None = None) -> Path | None:
    """The configuration file a command runs with: ``--config`` if given, else the shipped file
    ``default`` (e.g. ``"simulate"``) when there is one, else ``None`` (the schema's defaults).

    ``--config NAME`` with the name of a shipped file (``simulate_full``, ``simulate_full.yaml``)
    and no such file or folder here means the shipped file."""
    from hsi_torch.resources import shipped_config, shipped_config_names  # lazy: start-up time

    given = getattr(args, "config", None)
    if given is not None:
        p = Path(given)
        stem = p.name[: -len(".yaml")] if p.name.endswith(".yaml") else p.name
        if not p.exists() and p.parent == Path(".") and stem in shipped_config_names():
            return shipped_config(stem)
        return p
    if default is None:
        return None
    return shipped_config(default) if default in shipped_config_names() else None


def load_args_config(args: argparse.Namespace, schema_cls: type, default: str | None = None) -> Any:
    """Convenience for entry functions: ``load_config(config_source(args, default), schema_cls,
    args.overrides)`` (``default``: the shipped config used without ``--config``)."""
    from hsi_torch.config import load_config  # lazy: config loads YAML and torch (start-up time)

    return load_config(
        config_source(args, default), schema_cls, getattr(args, "overrides", []))
