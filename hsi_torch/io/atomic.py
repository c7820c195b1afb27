"""Atomic file writes: a temporary file in the destination folder, then ``os.replace``.

A reader (or a resumed batch run) therefore sees either the complete old file, the complete new
file, or no file — never a partial one. On any error inside the ``with`` block the temporary file
is removed and the destination is left untouched.

Also re-exports :class:`~hsi_torch.errors.FileFormatError`, the error raised by
:mod:`hsi_torch.io` for unreadable, truncated or inconsistent files (a ``ValueError`` whose message
names the file).
"""

from __future__ import annotations

import contextlib
import glob
import itertools
import json
import os
import re
import tempfile
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path
from typing import IO, Any

import numpy as np

from hsi_torch.errors import FileFormatError, InputError

__all__ = [
    "FileFormatError",
    "atomic_write",
    "atomic_write_bytes",
    "atomic_write_text",
    "atomic_write_json",
    "atomic_save_npz",
    "atomic_write_new",
    "clean_stale_temp_files",
    "clean_stale_temp_files_of",
    "lock_or_refuse",
    "mark_lock_holder",
]

#: Name of a temporary file of :func:`atomic_write`: ``.<name>.<pid>-<random>.tmp``.
TEMP_FILE_RE = re.compile(r"^\.(?P<name>.+)\.(?P<pid>[0-9]+)-[A-Za-z0-9_]+\.tmp$")


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "wb") -> Iterator[IO[Any]]:
    """Open a temporary file beside ``path`` for writing; rename it onto ``path`` on success.

    The temporary file lives in the same folder (same file system, so ``os.replace`` is atomic)
    and is named ``.<name>.<pid>-<random>.tmp`` (``pid``: the writing process, so that
    :func:`clean_stale_temp_files` can tell a killed writer's leftover from a live one). Parent
    folders are created. If the block raises, the temporary file is deleted and ``path`` keeps its
    previous content (or stays absent); a process killed inside the block (SIGKILL, power loss)
    leaves only the temporary file.

    Args:
        path: destination file.
        mode: ``"wb"`` (default) or ``"w"`` (text, UTF-8).

    Yields:
        The open file object. Writers that need a *file name* rather than a file object can use
        ``f.name`` (the temporary path) — the rename still happens on exit.

    Example:
        >>> with atomic_write("out/result.json", "w") as f:  # doctest: +SKIP
        ...     f.write("{}")
    """
    if mode not in ("wb", "w"):
        raise ValueError(f"mode must be 'wb' or 'w', got {mode!r}")
    dest = Path(path)
    dest.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{dest.name}.{os.getpid()}-", suffix=".tmp",
                               dir=dest.parent)
    try:
        kwargs: dict[str, Any] = {} if mode == "wb" else {"encoding": "utf-8", "newline": ""}
        os.close(fd)
        with open(tmp, mode, **kwargs) as f:  # opened by name so that f.name is a path
            yield f
            f.flush()
            os.fsync(f.fileno())
        # mkstemp creates 0600 files; give the result ordinary permissions (respecting umask).
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, dest)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically; returns the path."""
    with atomic_write(path, "wb") as f:
        f.write(data)
    return Path(path)


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write UTF-8 ``text`` to ``path`` atomically; returns the path."""
    with atomic_write(path, "w") as f:
        f.write(text)
    return Path(path)


def atomic_write_new(folder: str | os.PathLike, names: Iterable[str], data: bytes) -> Path:
    """Write ``data`` as a *new* file: the first of ``names`` (in ``folder``) that does not exist.

    The content goes to a temporary file first (named as :func:`atomic_write`'s, so
    :func:`clean_stale_temp_files` removes it if the process is killed), which is then
    hard-linked under the name: atomic and exclusive. An existing file is never replaced (a
    concurrent writer gets the next name) and the file only ever appears complete. Where hard
    links are not supported, the name is created exclusively and written in place.

    Returns:
        The path written.

    Raises:
        FileExistsError: every name is taken.
    """
    d = Path(folder)
    d.mkdir(parents=True, exist_ok=True)
    it = iter(names)
    first = next(it, None)
    if first is None:
        raise ValueError("atomic_write_new: no file name given")
    fd, tmp = tempfile.mkstemp(prefix=f".{first}.{os.getpid()}-", suffix=".tmp", dir=d)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        for name in itertools.chain([first], it):
            dest = d / name
            try:
                os.link(tmp, dest)
                return dest
            except FileExistsError:
                continue
            except OSError:  # no hard links on this file system: exclusive create, then write
                try:
                    with open(dest, "xb") as g:
                        g.write(data)
                    return dest
                except FileExistsError:
                    continue
        raise FileExistsError(f"no free file name in {d} (from {first!r} on)")
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)


def json_default(obj: Any) -> Any:
    """``json.dumps(default=...)`` for numpy scalars/arrays, tensors, paths, sets and tuples."""
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if hasattr(obj, "tolist"):  # torch tensors without importing torch here
        return obj.tolist()
    if isinstance(obj, (set, frozenset, tuple)):
        return list(obj)
    raise TypeError(f"object of type {type(obj).__name__} is not JSON serialisable")


def atomic_write_json(path: str | os.PathLike, obj: Any, indent: int | None = 2) -> Path:
    """Serialise ``obj`` as JSON (numpy/torch arrays → lists, paths → str) and write atomically.

    Serialisation happens before the file is touched, so an unserialisable object leaves nothing.
    """
    text = json.dumps(obj, indent=indent, default=json_default, allow_nan=True)
    return atomic_write_text(path, text + "\n")


def atomic_save_npz(
    path: str | os.PathLike, arrays: Mapping[str, Any], compressed: bool = False
) -> Path:
    """Save arrays to an ``.npz`` file atomically (the name is used as given, no suffix added).

    Args:
        path: destination, conventionally ending in ``.npz``.
        arrays: name → array-like (numpy arrays, scalars, strings; torch tensors are moved to CPU).
        compressed: use ``np.savez_compressed``.
    """
    converted: dict[str, np.ndarray] = {}
    for k, v in arrays.items():
        if hasattr(v, "detach"):  # torch.Tensor
            v = v.detach().cpu().numpy()
        converted[k] = np.asarray(v)
    with atomic_write(path, "wb") as f:
        (np.savez_compressed if compressed else np.savez)(f, **converted)
    return Path(path)


def _pid_alive(pid: int) -> bool:
    """Whether a process ``pid`` exists (``True`` when that cannot be told, e.g. on Windows)."""
    if os.name == "nt":  # os.kill(pid, 0) would send CTRL_C_EVENT there
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True  # exists (another user's), or unknown: keep its file
    return True


def clean_stale_temp_files(folder: str | os.PathLike) -> list[Path]:
    """Delete the temporary files that killed :func:`atomic_write` callers left in ``folder``.

    Only files named like this module's own temporary files (``.<name>.<pid>-<random>.tmp``, see
    :data:`TEMP_FILE_RE`) whose writing process no longer exists are removed; a live writer's file
    (a concurrent run into the same folder) and every other file are left alone. Not recursive.

    Returns:
        The files removed (a missing or unreadable folder gives ``[]``).
    """
    removed: list[Path] = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    for entry in entries:
        m = TEMP_FILE_RE.match(entry.name)
        if m is None or not entry.is_file(follow_symlinks=False):
            continue
        if _pid_alive(int(m["pid"])):
            continue
        with contextlib.suppress(FileNotFoundError):  # a concurrent cleaner got it first
            os.unlink(entry.path)
            removed.append(Path(entry.path))
    return removed


def clean_stale_temp_files_of(path: str | os.PathLike) -> list[Path]:
    """Delete the temporary files that killed :func:`atomic_write` callers of ``path`` left
    (as :func:`clean_stale_temp_files`, for one file's name only); returns them."""
    p = Path(path)
    removed: list[Path] = []
    for t in p.parent.glob(f".{glob.escape(p.name)}.*.tmp"):
        m = TEMP_FILE_RE.match(t.name)
        if m is None or m["name"] != p.name or _pid_alive(int(m["pid"])):
            continue
        with contextlib.suppress(FileNotFoundError):
            t.unlink()
            removed.append(t)
    return removed


def lock_or_refuse(fd: int, busy: Callable[[str], str]) -> None:
    """Take an exclusive, non-blocking ``flock`` on the open file ``fd``; when another process
    holds it, close ``fd`` and raise :class:`~hsi_torch.errors.InputError` with ``busy(holder)``
    (``holder``: the process id that :func:`mark_lock_holder` wrote, or ``"?"``). No locking where
    ``fcntl`` does not exist."""
    try:
        import fcntl  # lazy: POSIX only
    except ImportError:  # not POSIX
        return
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.pread(fd, 32, 0).decode("ascii", "replace").strip() or "?"
        os.close(fd)
        raise InputError(busy(holder)) from None


def mark_lock_holder(fd: int) -> None:
    """Write this process's id into a lock file it holds (read by :func:`lock_or_refuse`)."""
    os.ftruncate(fd, 0)
    os.pwrite(fd, str(os.getpid()).encode("ascii"), 0)
