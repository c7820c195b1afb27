"""The errors hsi_torch raises for bad input: one base class, a few kinds.

Every error about the *user's* input (a file, a configuration, a bundle, a capture, an argument
value) is an :class:`HSIError`, and also the builtin exception it refines, so existing
``except ValueError`` / ``except FileNotFoundError`` code keeps working:

- :class:`HSIError` (``Exception``): the base; catch it for "any bad input".
- :class:`FileFormatError` (``ValueError``): a file exists but cannot be read as the expected
  format (corrupt, truncated, foreign, inconsistent, too large).
- :class:`MissingFileError` (``FileNotFoundError``): a required file does not exist.
- :class:`ConfigError` (``ValueError``): invalid configuration (file, key, value).
- :class:`InputError` (``ValueError``): an invalid argument value or shape passed to the API
  (a non-finite exposure scale, a state dict of another geometry, ...).
- :class:`NoValidPixelsError` (an :class:`InputError`): a capture from which not a single pixel
  could be reconstructed (the message says why).
- :class:`CalibrationError` (``ValueError``): calibration captures that cannot give a bundle
  (e.g. saturated white shots).

Messages are one line and name the file, key or shape at fault (a :class:`ConfigError` also
carries the key and the source file as attributes; :mod:`hsi_torch.config`, which raises it,
re-exports it); the command line prints an :class:`HSIError` as ``hsi-torch: error: <message>``
without a traceback.
"""

from __future__ import annotations

import importlib
import importlib.util
from collections.abc import Callable, Iterable, Mapping
from typing import Any

__all__ = [
    "require_packages",
    "lazy_attributes",
    "HSIError",
    "FileFormatError",
    "MissingFileError",
    "ConfigError",
    "InputError",
    "NoValidPixelsError",
    "CalibrationError",
]


class HSIError(Exception):
    """Base class of the errors hsi_torch raises for bad input (files, configs, arguments)."""


class FileFormatError(HSIError, ValueError):
    """A file exists but cannot be read as the expected format (corrupt, truncated, mismatched).

    The message always names the file.
    """


class MissingFileError(HSIError, FileNotFoundError):
    """A required file does not exist (the message names it)."""


class ConfigError(HSIError, ValueError):
    """Invalid configuration. ``key`` is the dotted key at fault (or ``None``), ``source`` the file.

    The message is a single line: ``"<source>: key 'a.b': <problem>"``.
    """

    def __init__(self, message: str, key: str | None = None, source: str | None = None):
        self.key = key
        self.source = source
        self.problem = message
        parts = [p for p in (source, f"key '{key}'" if key else None, message) if p]
        super().__init__(": ".join(parts))


class InputError(HSIError, ValueError):
    """An invalid argument value or shape (the message names the argument and what it got)."""


class NoValidPixelsError(InputError):
    """Not a single pixel of a capture could be reconstructed; the message says why."""


class CalibrationError(HSIError, ValueError):
    """Calibration captures that cannot give a bundle (the message names the files at fault)."""


def require_packages(modules: Iterable[str], what: str, hint: str) -> None:
    """Check, without importing them, that optional packages are installed.

    Raises:
        ModuleNotFoundError: the first one missing: ``"<what> needs the optional package
            '<module>': <hint>"`` (``name`` set to the module).
    """
    for mod in modules:
        if importlib.util.find_spec(mod) is None:
            raise ModuleNotFoundError(f"{what} needs the optional package {mod!r}: {hint}",
                                      name=mod)  # fmt: skip


def lazy_attributes(
    package: str, modules: Mapping[str, Iterable[str]]
) -> tuple[list[str], Callable[[str], Any]]:
    """``(__all__, __getattr__)`` of a package whose names are imported on first use:
    ``modules`` maps a module to the names it defines; ``__getattr__`` imports a name's module
    and returns the attribute, and raises ``AttributeError`` naming ``package`` for any other."""
    table = {name: mod for mod, names in modules.items() for name in names}

    def __getattr__(name: str) -> Any:
        if name in table:
            return getattr(importlib.import_module(table[name]), name)
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    return list(table), __getattr__
