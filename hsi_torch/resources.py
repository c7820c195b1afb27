"""Files shipped inside the package (configs, reference data) and the real-data folder.

Shipped configuration files live once, in ``configs/`` at the top of the repository; the build
installs them as ``hsi_torch/configs/`` (see ``setup.py``), where they are found with
:mod:`importlib.resources`. Without that folder in the package (an editable install, a source
checkout run with ``PYTHONPATH``) they are read from the checkout's ``configs/``
(:func:`shipped_config_dir`). Every ``hsi-torch`` command uses its shipped file when ``--config``
is not given (``hsi-torch config show NAME`` prints one, ``hsi-torch config copy NAME DEST``
starts your own).

The *real-data folder* (measured data that is not redistributed with the package: the CAVE
scene, real RAW files, circle-grid photos, camera sensitivities) is, in this order:

1. the folder given to :func:`set_real_data_dir` (the command line's ``--data-dir DIR``);
2. the environment variable ``HSI_TORCH_DATA``;
3. ``../shared/data/real`` beside a source checkout (the folder holding ``pyproject.toml`` and
   ``hsi_torch/``), when it exists.

:func:`real_data_dir` returns ``None`` when none applies; code that can do without the data
(optional scenes, tests) then skips it.
"""

from __future__ import annotations

import os
import sys
from importlib import resources
from pathlib import Path
from typing import Any

from hsi_torch.console import info

__all__ = [
    "DATA_ENV",
    "shipped_config",
    "shipped_config_dir",
    "shipped_config_names",
    "shipped_data",
    "set_real_data_dir",
    "get_real_data_dir_setting",
    "real_data_dir",
    "run_config",
    "source_checkout",
]

#: Environment variable naming the real-data folder.
DATA_ENV = "HSI_TORCH_DATA"

_data_dir_setting: Path | None = None


def _package_dir(sub: str) -> Path:
    res = resources.files("hsi_torch").joinpath(sub)
    if not isinstance(res, Path):  # e.g. a zip import: shipped files need a real folder
        raise RuntimeError(
            f"hsi_torch's {sub}/ folder is not on the file system ({res}); install the package "
            "as a regular folder (pip install, not a zip)")
    return res


def shipped_config_dir() -> Path:
    """The folder of the shipped configuration files: ``hsi_torch/configs/`` of an installed
    package (a wheel), else ``configs/`` of the source checkout the package is imported from
    (editable install, ``PYTHONPATH``).

    Raises:
        FileNotFoundError: neither exists (the message names both places).
    """
    installed = _package_dir("configs")
    if installed.is_dir():
        return installed
    root = source_checkout()
    if root is not None and (root / "configs").is_dir():
        return root / "configs"
    where = f" nor {root / 'configs'}" if root is not None else ""
    raise FileNotFoundError(
        f"the shipped configuration files are missing: neither {installed}{where} exists "
        "(reinstall hsi-torch)")


def shipped_config_names() -> list[str]:
    """Names of the shipped configuration files, without ``.yaml`` (e.g. ``"simulate"``)."""
    return sorted(p.stem for p in shipped_config_dir().glob("*.yaml"))


def shipped_config(name: str) -> Path:
    """Path of a shipped configuration file: ``"simulate"`` or ``"simulate.yaml"`` →
    ``…/configs/simulate.yaml`` (in :func:`shipped_config_dir`).

    Raises:
        FileNotFoundError: no such shipped file (the message lists the available names).
    """
    stem = name[: -len(".yaml")] if name.endswith(".yaml") else name
    path = shipped_config_dir() / f"{stem}.yaml"
    if not path.is_file():
        raise FileNotFoundError(
            f"no shipped config {name!r}; available: {', '.join(shipped_config_names())}")
    return path


def shipped_data(name: str) -> Path:
    """Path of a reference-data file shipped in ``hsi_torch/data/`` (see its ``README.md``)."""
    path = _package_dir("data") / name
    if not path.is_file():
        raise FileNotFoundError(f"shipped data file {name!r} not found in {path.parent}")
    return path


def source_checkout() -> Path | None:
    """The source checkout this package is imported from (the folder with ``pyproject.toml``
    beside ``hsi_torch/``), or ``None`` for an installed package."""
    root = Path(__file__).resolve().parents[1]
    if (root / "pyproject.toml").is_file() and (root / "hsi_torch" / "__init__.py").is_file():
        return root
    return None


def set_real_data_dir(path: str | os.PathLike | None) -> None:
    """Use ``path`` as the real-data folder (``None``: back to ``HSI_TORCH_DATA`` / the
    checkout's ``../shared/data/real``). The folder must exist."""
    global _data_dir_setting
    if path is None:
        _data_dir_setting = None
        return
    p = Path(os.path.expanduser(os.fspath(path)))
    if not p.is_dir():
        raise FileNotFoundError(f"real-data folder not found: {p}")
    _data_dir_setting = p


def get_real_data_dir_setting() -> Path | None:
    """The folder set with :func:`set_real_data_dir` (``None``: not set)."""
    return _data_dir_setting


def real_data_dir(sub: str | None = None) -> Path | None:
    """The real-data folder (see the module docstring), or ``sub`` inside it; ``None`` when there
    is none (or ``sub`` is absent there).

    Raises:
        FileNotFoundError: ``HSI_TORCH_DATA`` is set but names no folder (a typo should not look
            like "no data").
    """
    if _data_dir_setting is not None:
        base: Path | None = _data_dir_setting
    elif os.environ.get(DATA_ENV):
        base = Path(os.path.expanduser(os.environ[DATA_ENV]))
        if not base.is_dir():
            raise FileNotFoundError(f"{DATA_ENV}={os.environ[DATA_ENV]}: no such folder")
    else:
        root = source_checkout()
        base = root.parent / "shared" / "data" / "real" if root is not None else None
        if base is not None and not base.is_dir():
            base = None
    if base is None or sub is None:
        return base
    p = base / sub
    return p if p.exists() else None


def run_config(args: Any) -> int:
    """``hsi-torch config [list | show NAME | copy NAME DEST [--force]]``.

    ``copy`` writes ``DEST`` (or ``DEST/NAME.yaml`` when ``DEST`` is a folder) and refuses to
    overwrite an existing file without ``--force``; the copy then runs with ``--config DEST``.
    """
    action, name, dest = args.action, getattr(args, "name", None), getattr(args, "dest", None)
    if action == "list":
        if name is not None:
            raise ValueError(f"'config list' takes no NAME (got {name!r}); try "
                             f"'config show {name}'")
        for n in shipped_config_names():
            print(n)
        return 0
    if name is None:
        raise ValueError(f"'config {action}' needs a NAME, one of: "
                         f"{', '.join(shipped_config_names())}")
    src = shipped_config(name)
    if action == "show":
        if dest is not None:
            raise ValueError(f"'config show' takes no DEST (got {dest}); did you mean "
                             "'config copy'?")
        sys.stdout.write(src.read_text(encoding="utf-8"))
        return 0
    if dest is None:
        raise ValueError(f"'config copy {name}' needs a DEST file or folder")
    target = Path(dest) / src.name if Path(dest).is_dir() else Path(dest)
    if (target.exists() or target.is_symlink()) and not getattr(args, "force", False):
        raise FileExistsError(f"{target} exists; use --force to overwrite it")
    target.parent.mkdir(parents=True, exist_ok=True)
    from hsi_torch.io.atomic import atomic_write_bytes  # lazy: keeps 'config list' light

    # whole or not at all; a symlink at DEST is replaced, the file it points to is not written
    atomic_write_bytes(target, src.read_bytes())

    info(f"wrote {target} (run with --config {target})")
    return 0
