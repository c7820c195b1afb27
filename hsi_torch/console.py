"""What the package prints while it works: progress bars and messages, one switch for each.

- :func:`progress_bar` is the only way the package makes a progress bar. A bar is shown when the
  caller's own setting allows it (a config key ``progress``), the process-wide switch allows it
  (``hsi-torch --no-progress`` / ``--quiet``, or :func:`configure`), **and** stderr is a terminal
  (or a Jupyter kernel): redirected to a file, nothing is drawn, so logs hold no ``\\r`` lines.
- :func:`info` prints a message (stdout by default) unless quiet; :func:`warn` always prints to
  stderr. Both go through ``tqdm.write`` so that an open bar is not torn.

``hsi-torch -q/--quiet`` = no bars and no informational messages (warnings, errors and a batch's
failures still print); ``--no-progress`` = no bars.
"""

from __future__ import annotations

import sys
from collections.abc import Iterable
from typing import IO, Any

__all__ = ["configure", "settings", "is_quiet", "progress_enabled", "progress_bar", "info", "warn"]

_state = {"quiet": False, "progress": True}


def configure(*, quiet: bool | None = None, progress: bool | None = None) -> dict[str, bool]:
    """Set the process-wide switches (``None``: leave as is); returns the previous settings."""
    before = dict(_state)
    if quiet is not None:
        _state["quiet"] = bool(quiet)
    if progress is not None:
        _state["progress"] = bool(progress)
    return before


def settings() -> dict[str, bool]:
    """The current switches ``{"quiet": ..., "progress": ...}``."""
    return dict(_state)


def is_quiet() -> bool:
    return _state["quiet"]


def _stderr_is_terminal() -> bool:
    if "ipykernel" in sys.modules:  # a notebook draws bars as widgets
        return True
    try:
        return bool(sys.stderr.isatty())
    except (AttributeError, ValueError):  # replaced or closed stream
        return False


def progress_enabled(enabled: bool = True) -> bool:
    """Whether a bar that the caller wants (``enabled``) is drawn (see the module docstring)."""
    return bool(enabled) and _state["progress"] and not _state["quiet"] and _stderr_is_terminal()


def progress_bar(iterable: Iterable | None = None, *, enabled: bool = True, **kwargs: Any):
    """A ``tqdm`` bar on stderr (``tqdm.auto``: a widget in notebooks), disabled unless
    :func:`progress_enabled` (a disabled bar still iterates and accepts ``update``/``close``).
    ``kwargs`` go to ``tqdm`` (``desc``, ``total``, ``unit``, ``leave``, ...)."""
    from tqdm.auto import tqdm

    kwargs.setdefault("file", sys.stderr)
    kwargs.setdefault("dynamic_ncols", True)
    return tqdm(iterable, disable=not progress_enabled(enabled), **kwargs)


def _write(msg: str, file: IO[str]) -> None:
    from tqdm import tqdm

    tqdm.write(msg, file=file)
    file.flush()


def info(msg: str, file: IO[str] | None = None) -> None:
    """Print an informational message (default stdout) unless quiet."""
    if not _state["quiet"]:
        _write(str(msg), file if file is not None else sys.stdout)


def warn(msg: str) -> None:
    """Print a warning on stderr (also when quiet)."""
    _write(str(msg), sys.stderr)
