"""Which code made an output: the package version, the git commit and the command.

:func:`package_version` is a version that changes with the code. Run from a git checkout (the
package folder's parent is the repository's top level) it is the release plus the commit as a
PEP 440 local version, ``0.1.0+g<12 hex>`` with ``.dirty`` appended when tracked files differ
from that commit (what ``git describe --dirty`` calls dirty); otherwise the installed
distribution's version (a wheel), else :data:`RELEASE`. It is computed once per process, by two
``git`` calls without a shell and with a short timeout; git missing, slow or refusing the folder
gives the installed version. ``hsi_torch.__version__`` and ``hsi-torch --version`` are this
version.

:func:`provenance` is the one block every run record holds (``experiment_run.json``,
``demo_run.json``, the reconstruct run's :class:`~hsi_torch.recon.batch.driver.RunSummary` and
run configuration, simulate's ``manifest.json``, calibrate's report and bundle, the layout):
the full command line (``argv``, with ``--config`` and every ``--set``) when the run came from
the command line, the working folder, the package version, the git commit, the versions of
Python, torch and NumPy, and the platform. The command line sets the command for the duration
of a command (:func:`command_line`); a record made through the Python API has ``command: null``.
"""

from __future__ import annotations

import contextlib
import contextvars
import functools
import importlib.metadata
import os
import platform
import shlex
import subprocess
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

__all__ = ["RELEASE", "package_version", "git_state", "provenance", "command_line"]

#: The release this source tree is (``pyproject.toml``'s ``version``; a test keeps them equal).
RELEASE = "0.1.0"

#: The distribution's name (its installed metadata is the version outside a git checkout).
DISTRIBUTION = "hsi-torch"

#: Seconds a ``git`` call may take before the installed version is used instead.
GIT_TIMEOUT_S = 2.0

_PACKAGE_DIR = Path(__file__).resolve().parent

_COMMAND: contextvars.ContextVar[tuple[str, ...] | None] = contextvars.ContextVar(
    "hsi_torch_command", default=None)


def _git(*args: str) -> str | None:
    """``git -C <package folder> args`` (no shell, :data:`GIT_TIMEOUT_S`); its stdout, or
    ``None`` when git is missing, fails or times out."""
    try:
        r = subprocess.run(
            ["git", "-C", str(_PACKAGE_DIR), *args], capture_output=True, text=True,
            timeout=GIT_TIMEOUT_S, check=False, stdin=subprocess.DEVNULL,
            env={**os.environ, "GIT_OPTIONAL_LOCKS": "0", "LC_ALL": "C"})  # fmt: skip
    except (OSError, subprocess.SubprocessError, ValueError):
        return None
    return r.stdout if r.returncode == 0 else None


@functools.lru_cache(maxsize=1)
def git_state() -> dict[str, Any] | None:
    """``{"commit": 40 hex, "dirty": bool}`` of the git checkout this package runs from, or
    ``None`` when it does not run from one (an installed wheel, a package copied elsewhere, a
    repository that does not hold this package at its top level) or git cannot tell."""
    out = _git("rev-parse", "--show-toplevel", "HEAD")
    lines = out.split() if out else []
    if len(lines) != 2 or len(lines[1]) < 40:
        return None
    try:
        if Path(lines[0]).resolve() != _PACKAGE_DIR.parent:
            return None  # e.g. installed into a virtual environment inside another repository
    except OSError:
        return None
    status = _git("status", "--porcelain", "--untracked-files=no")
    if status is None:
        return None
    return {"commit": lines[1], "dirty": bool(status.strip())}


def _installed_version() -> str:
    try:
        return importlib.metadata.version(DISTRIBUTION)
    except importlib.metadata.PackageNotFoundError:
        return RELEASE


@functools.lru_cache(maxsize=1)
def package_version() -> str:
    """This code's version: ``RELEASE+g<commit[:12]>[.dirty]`` from a git checkout, else the
    installed distribution's version (else :data:`RELEASE`)."""
    git = git_state()
    if git is None:
        return _installed_version()
    return f"{RELEASE}+g{git['commit'][:12]}{'.dirty' if git['dirty'] else ''}"


def _printable(word: object) -> str:
    """A word of the command line as text that encodes as UTF-8: a file name's undecodable bytes
    (kept by Python as lone surrogates) are written as ``\\xNN``."""
    text = str(word)
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        try:
            text = text.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")
        except UnicodeEncodeError:  # a surrogate that is no escaped byte
            text = text.encode("utf-8", "backslashreplace").decode("utf-8")
    return text


@contextlib.contextmanager
def command_line(argv: Sequence[str], prog: str = "hsi-torch") -> Iterator[None]:
    """While the block runs, :func:`provenance` records ``prog argv...`` as the command (the
    command line wraps each command in it)."""
    token = _COMMAND.set((prog, *map(_printable, argv)))
    try:
        yield
    finally:
        _COMMAND.reset(token)


def _module_version(name: str) -> str | None:
    module = sys.modules.get(name)
    if module is not None and isinstance(getattr(module, "__version__", None), str):
        return str(module.__version__)
    try:
        return importlib.metadata.version(name)
    except importlib.metadata.PackageNotFoundError:
        return None


def provenance() -> dict[str, Any]:
    """The provenance block of a run record (JSON-serialisable).

    Returns:
        ``command`` (the shell-quoted command line, ``None`` outside the command line), ``argv``
        (its words, ``None`` likewise), ``cwd`` (the folder relative paths in it are relative
        to), ``hsi_torch_version`` (:func:`package_version`), ``git_commit`` and ``git_dirty``
        (``None`` outside a git checkout), ``python``, ``torch``, ``numpy`` (versions) and
        ``platform``.
    """
    argv = _COMMAND.get()
    git = git_state()
    try:
        cwd: str | None = os.getcwd()
    except OSError:  # the working folder was removed
        cwd = None
    return {
        "command": shlex.join(argv) if argv else None,
        "argv": list(argv) if argv else None,
        "cwd": cwd,
        "hsi_torch_version": package_version(),
        "git_commit": git["commit"] if git else None,
        "git_dirty": git["dirty"] if git else None,
        "python": platform.python_version(),
        "torch": _module_version("torch"),
        "numpy": _module_version("numpy"),
        "platform": platform.platform(terse=True),
    }
