"""The file-safety layer: every output, lock, marker, record and staging file goes through it.

- **Outputs** are written create-new-then-rename (:func:`atomic_write` and its helpers, the
  :class:`ReplaceTransaction` of a step's outputs): a temporary file in the destination folder,
  created exclusively, then ``os.replace``. A reader (or a resumed batch run) sees the complete
  old file, the complete new file, or no file — never a partial one; a file already at the name
  (a symlink, a hard link to the user's data) is replaced, never written through. On any error
  the temporary file is removed and the destination is left untouched.
- **Locks and markers written in place** (:func:`open_own_file`, :func:`hold_lock`) are created
  with ``O_CREAT | O_EXCL | O_NOFOLLOW``; one already there is opened ``O_NOFOLLOW |
  O_NONBLOCK`` and used only when it is a regular file with one link, owned by this user — a
  file this process did not just create is never truncated.
- **Our own small files read back** (done-markers, run records, folder markers) are read by
  :func:`read_own_bytes` / :func:`read_own_json`: regular files only (a FIFO or a device is
  refused without blocking: opened ``O_NONBLOCK``, then ``fstat``), at most a bounded size.
- **Paths read from a folder's own files** are data: :func:`confined` resolves a path relative
  to a root and refuses an absolute path, ``..`` or a symlinked component, and
  :func:`remove_confined` deletes only a regular file so confined. :func:`folder_identity` tells
  a copied folder from the original.

``tests/test_file_safety.py`` walks the package's syntax trees and fails on a file write,
rename or deletion outside this layer (a short, justified allow-list).

Also re-exports :class:`~hsi_torch.errors.FileFormatError`, the error raised by
:mod:`hsi_torch.io` for unreadable, truncated or inconsistent files (a ``ValueError`` whose message
names the file).
"""

from __future__ import annotations

import contextlib
import errno
import functools
import glob
import itertools
import json
import os
import re
import shutil
import stat
import tempfile
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path
from typing import IO, Any

import numpy as np

from hsi_torch.devices import to_numpy
from hsi_torch.errors import FileFormatError, InputError
from hsi_torch.io.safety import file_kind

__all__ = [
    "FileFormatError",
    "atomic_write",
    "atomic_write_bytes",
    "atomic_write_text",
    "atomic_write_json",
    "atomic_save_npz",
    "atomic_write_new",
    "check_not_input",
    "InputFiles",
    "ReplaceTransaction",
    "replace_then_commit",
    "clean_stale_temp_files",
    "clean_stale_temp_files_of",
    "lock_or_refuse",
    "mark_lock_holder",
    "open_own_file",
    "hold_lock",
    "read_own_bytes",
    "read_own_json",
    "read_file_head",
    "confined",
    "relative_to_root",
    "remove_confined",
    "remove_file",
    "remove_tree",
    "remove_empty_folder",
    "link_or_copy",
    "replace_file",
    "folder_identity",
    "human_size",
    "pid_alive",
    "MAX_OWN_FILE",
]

#: Largest of our own markers and records that :func:`read_own_bytes` reads (bytes).
MAX_OWN_FILE = 16 << 20

_NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)
_NONBLOCK = getattr(os, "O_NONBLOCK", 0)
_CLOEXEC = getattr(os, "O_CLOEXEC", 0)


@functools.cache
def _umask() -> int:
    """The process's umask (read once: reading it means setting it, which threads would race)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _nofollow_opener(path: str, flags: int) -> int:
    """``open(..., opener=)`` that never follows a symlink at the last component."""
    return os.open(path, flags | _NOFOLLOW | _CLOEXEC, 0o600)


#: Name of a temporary file of :func:`atomic_write`: ``.<name>.<pid>-<random>.tmp``.
TEMP_FILE_RE = re.compile(r"^\.(?P<name>.+)\.(?P<pid>[0-9]+)-[A-Za-z0-9_]+\.tmp$")


@contextlib.contextmanager
def atomic_write(
    path: str | os.PathLike, mode: str = "wb", *, fsync: bool = True
) -> Iterator[IO[Any]]:
    """Open a temporary file beside ``path`` for writing; rename it onto ``path`` on success.

    The temporary file lives in the same folder (same file system, so ``os.replace`` is atomic)
    and is named ``.<name>.<pid>-<random>.tmp`` (``pid``: the writing process, so that
    :func:`clean_stale_temp_files` can tell a killed writer's leftover from a live one). Parent
    folders are created. If the block raises, the temporary file is deleted and ``path`` keeps its
    previous content (or stays absent); a process killed inside the block (SIGKILL, power loss)
    leaves only the temporary file.

    Args:
        mode: ``"wb"`` (default) or ``"w"`` (text, UTF-8).
        fsync: flush the data to the disk before the rename (default). ``False`` for files
            that are checked when read and can be made again (a cache): after a power loss the
            renamed file may then hold zeros, never a mix of two versions.

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
    fd, tmp = tempfile.mkstemp(
        prefix=f".{dest.name}.{os.getpid()}-", suffix=".tmp", dir=dest.parent)
    try:
        kwargs: dict[str, Any] = {} if mode == "wb" else {"encoding": "utf-8", "newline": ""}
        os.close(fd)
        # opened by name so that f.name is a path; never through a link planted at that name
        with open(tmp, mode, opener=_nofollow_opener, **kwargs) as f:
            yield f
            f.flush()
            if fsync:
                os.fsync(f.fileno())
        # mkstemp creates 0600 files; give the result ordinary permissions (respecting umask).
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, dest)
    except OSError as exc:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        # an error naming the temporary file (a full disk at the rename) names the destination
        raise named_os_error(exc, dest, rename=_names_temp(exc, tmp)) from None
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def _names_temp(exc: OSError, tmp: str | os.PathLike) -> bool:
    """Whether ``exc`` names the temporary file ``tmp`` (or no file at all)."""
    names = {os.fspath(x) for x in (exc.filename, getattr(exc, "filename2", None)) if x}
    return (
        not names or os.fspath(tmp) in names or any(TEMP_FILE_RE.match(Path(n).name) for n in names)
    )


def human_size(nbytes: float) -> str:
    """A size for a message: ``"12.3 GiB"``, ``"512.0 MiB"``, ``"3.2 KiB"`` or ``"17 bytes"``
    (never ``"0.0 GiB"`` for a small, non-zero size)."""
    n = float(nbytes)
    for unit, shift in (("GiB", 30), ("MiB", 20), ("KiB", 10)):
        if abs(n) >= 1 << shift:
            return f"{n / (1 << shift):.1f} {unit}"
    return f"{int(n)} bytes"


def named_os_error(
    exc: OSError, dest: str | os.PathLike, what: str = "writing", *, rename: bool = False
) -> OSError:
    """``exc`` (e.g. ENOSPC, EIO, a read-only file system) as an ``OSError`` of the same type
    whose message names ``dest``: ``"<reason> while writing <dest>"``. An error that already
    names a file is returned unchanged, unless ``rename`` (the file it names is only a
    temporary stand-in for ``dest``)."""
    if getattr(exc, "filename", None) and not rename:
        return exc
    reason = getattr(exc, "hsi_reason", None) or exc.strerror or str(exc) or type(exc).__name__
    text = f"{reason} while {what} {os.fspath(dest)}"
    try:
        new = type(exc)(exc.errno, text) if exc.errno else type(exc)(text)
    except Exception:  # noqa: BLE001 - a subclass with another constructor
        new = OSError(exc.errno, text) if exc.errno else OSError(text)
    new.hsi_reason = reason  # type: ignore[attr-defined]
    return new


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
        os.chmod(tmp, 0o666 & ~_umask())
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
    converted = {k: to_numpy(v) for k, v in arrays.items()}
    with atomic_write(path, "wb") as f:
        (np.savez_compressed if compressed else np.savez)(f, **converted)
    return Path(path)


def pid_alive(pid: int) -> bool:
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
    :data:`TEMP_FILE_RE`) whose writing process no longer exists are removed — and the staging
    folders of :meth:`ReplaceTransaction.stage_tree` named the same way, with what is in them; a
    live writer's file (a concurrent run into the same folder) and every other file are left
    alone. Not recursive.

    Returns:
        The files removed (a missing or unreadable folder gives ``[]``).
    """
    removed: list[Path] = []
    recover_commits(folder)  # an interrupted commit's backups are needed first
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    for entry in entries:
        m = TEMP_FILE_RE.match(entry.name)
        if m is None or pid_alive(int(m["pid"])):
            continue
        if entry.is_dir(follow_symlinks=False):  # a killed transaction's staging folder
            shutil.rmtree(entry.path, ignore_errors=True)
            removed.append(Path(entry.path))
            continue
        if not entry.is_file(follow_symlinks=False):
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
        if m is None or m["name"] != p.name or pid_alive(int(m["pid"])):
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


def _not_own(path: Path, st: os.stat_result) -> str | None:
    """Why the open file ``st`` at ``path`` is not one of our own files (``None``: it is)."""
    if not stat.S_ISREG(st.st_mode):
        return f"is {file_kind(st.st_mode)}, not a regular file"
    if st.st_nlink != 1:
        return f"has {st.st_nlink} hard links (another name of some other file)"
    if hasattr(os, "geteuid") and st.st_uid != os.geteuid():
        return f"belongs to another user (uid {st.st_uid})"
    return None


def open_own_file(path: str | os.PathLike, what: str = "lock file") -> tuple[int, bool]:
    """Open a lock or marker that is written in place, read-write, never through a link.

    Created with ``O_CREAT | O_EXCL | O_NOFOLLOW`` when absent. One already at ``path`` (left by
    an earlier or a concurrent run) is opened ``O_NOFOLLOW | O_NONBLOCK`` and kept only when it
    is a regular file with a single link, owned by this user; anything else (a symlink, a hard
    link to the user's file, a FIFO, a device, someone else's file) is refused before a byte of
    it is changed.

    Args:
        what: what it is, for the message (``"lock file"``).

    Returns:
        ``(fd, created)``: the open descriptor (the caller closes it) and whether this call
        created the file.

    Raises:
        InputError: it is not one of our own files (the message names it and says why).
        OSError: it cannot be opened or created (names it).
    """
    p = Path(path)
    try:
        return os.open(p, os.O_RDWR | os.O_CREAT | os.O_EXCL | _NOFOLLOW | _CLOEXEC, 0o644), True
    except FileExistsError:
        pass
    except OSError as exc:
        raise named_os_error(exc, p, "creating") from None
    try:
        fd = os.open(p, os.O_RDWR | _NOFOLLOW | _NONBLOCK | _CLOEXEC)
    except OSError as exc:
        try:
            reason = _not_own(p, os.lstat(p)) or str(exc.strerror or exc)
        except OSError:
            raise named_os_error(exc, p, "opening") from None
    else:
        reason = _not_own(p, os.fstat(fd))
        if reason is None:
            os.set_blocking(fd, True)
            return fd, False
        os.close(fd)
    raise InputError(
        f"{p} {reason}: not a {what} this program wrote; nothing was written "
        "to it: remove it, or choose another folder"
    ) from None


def _same_file(path: Path, fd: int) -> bool:
    """Whether ``path`` (not followed) still names the open file ``fd``."""
    try:
        a, b = os.lstat(path), os.fstat(fd)
    except OSError:
        return False
    return (a.st_dev, a.st_ino) == (b.st_dev, b.st_ino)


@contextlib.contextmanager
def hold_lock(path: str | os.PathLike, busy: Callable[[str], str], *,
              remove: bool = True) -> Iterator[int]:  # fmt: skip
    """Hold the lock file ``path`` (an exclusive ``flock``, this process's id written into it)
    while the block runs.

    The file is opened by :func:`open_own_file` (never through a symlink or a hard link). When
    another process holds it, :class:`~hsi_torch.errors.InputError` with ``busy(holder)`` is
    raised at once (``holder``: that process's id). With ``remove`` the file is deleted when
    the block ends (while still held: a run waiting on the old file re-opens the name).
    No locking where ``fcntl`` does not exist (the file is still created safely).

    Yields:
        The open, locked descriptor.
    """
    p = Path(path)
    while True:
        fd, _created = open_own_file(p)
        lock_or_refuse(fd, busy)
        if _same_file(p, fd):  # not removed by its previous holder meanwhile
            break
        os.close(fd)
    try:
        mark_lock_holder(fd)
        yield fd
    finally:
        if remove and _same_file(p, fd):
            with contextlib.suppress(OSError):
                os.unlink(p)
        os.close(fd)


def read_own_bytes(path: str | os.PathLike, max_bytes: int = MAX_OWN_FILE, *,
                   follow: bool = False, what: str = "file", dir_fd: int | None = None,
                   error: type[Exception] = FileFormatError) -> bytes:  # fmt: skip
    """The content of one of our own small files (a marker, a record, a cache index), read safely.

    Opened ``O_NONBLOCK`` (a FIFO cannot block) and without following a symlink unless
    ``follow`` (``dir_fd``: ``path`` relative to that open folder); then only a regular file of at
    most ``max_bytes`` is read.

    Raises:
        FileNotFoundError: it does not exist.
        error: (default :class:`FileFormatError`) it is a symbolic link, not a regular file, or
            larger than ``max_bytes`` (names it); the precompute cache passes its own, a miss.
        OSError: it cannot be read.
    """
    p = Path(path)
    try:
        fd = os.open(p, os.O_RDONLY | _NONBLOCK | _CLOEXEC | (0 if follow else _NOFOLLOW),
                     dir_fd=dir_fd)  # fmt: skip
    except FileNotFoundError:
        raise
    except OSError as exc:
        if not follow and (exc.errno == errno.ELOOP or (dir_fd is None and os.path.islink(p))):
            raise error(f"{p}: is a symbolic link, not this program's {what}") from None
        raise named_os_error(exc, p, "reading") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise error(f"{p}: is {file_kind(st.st_mode)}, not a regular file; not this "
                        f"program's {what}")  # fmt: skip
        if st.st_size > max_bytes:
            raise error(f"{p}: {human_size(st.st_size)}, larger than this program's "
                        f"{what} can be ({human_size(max_bytes)})")  # fmt: skip
        with open(fd, "rb", closefd=False) as f:
            data = f.read(max_bytes + 1)  # until the end, or one byte too many
        if len(data) > max_bytes:  # grew while read
            raise error(f"{p}: larger than this program's {what} can be "
                        f"({human_size(max_bytes)})")  # fmt: skip
        return data
    finally:
        os.close(fd)


def read_file_head(path: str | os.PathLike, nbytes: int) -> bytes | None:
    """The first ``nbytes`` of the regular file ``path`` (not followed through a symlink; a
    FIFO or a device is not read and cannot block), or ``None`` when it is not such a file."""
    try:
        fd = os.open(path, os.O_RDONLY | _NONBLOCK | _CLOEXEC | _NOFOLLOW)
    except OSError:
        return None
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            return None
        return os.pread(fd, nbytes, 0)
    except OSError:
        return None
    finally:
        os.close(fd)


def read_own_json(path: str | os.PathLike, max_bytes: int = MAX_OWN_FILE, *,
                  follow: bool = False) -> Any:  # fmt: skip
    """The JSON value of one of our own small files (:func:`read_own_bytes`), or ``None`` when
    it is missing, not a regular file, too large, unreadable or not JSON."""
    try:
        return json.loads(read_own_bytes(path, max_bytes, follow=follow).decode("utf-8"))
    except (OSError, ValueError):  # FileFormatError and UnicodeDecodeError are ValueErrors
        return None


def folder_identity(path: str | os.PathLike) -> list[int] | None:
    """``[st_dev, st_ino]`` of the folder ``path`` (followed), or ``None``: recorded in a
    folder's markers, a copy of the folder (another inode) is told from the original."""
    ident = _identity(path)
    return None if ident is None else list(ident)


def relative_to_root(root: str | os.PathLike, path: str | os.PathLike) -> str:
    """``path`` (below ``root``) as a ``/``-separated path relative to ``root``, for a marker.

    Raises:
        ValueError: ``path`` is not below ``root``.
    """
    rel = os.path.relpath(os.path.abspath(path), os.path.abspath(root))
    if rel == os.curdir or rel.startswith(os.pardir) or os.path.isabs(rel):
        raise ValueError(f"{path} is not inside {root}")
    return Path(rel).as_posix()


def confined(root: str | os.PathLike, rel: Any) -> Path:
    """The path that ``rel`` (read from a file inside ``root``: data, not an instruction) names
    below ``root``, checked to stay there.

    ``rel`` must be a relative, ``/``-separated path without ``.``/``..`` components or
    empty parts, and no folder on the way below ``root`` may be a symbolic link (the last
    component may be anything, even absent: it is only ever examined with ``lstat``).

    Raises:
        InputError: it is not such a path (the message names it and ``root``).
    """
    r = Path(root)
    bad = (
        not isinstance(rel, str)
        or not rel
        or "\0" in rel
        or rel.startswith("/")
        or os.path.isabs(rel)
    )
    parts = [] if bad else rel.split("/")
    if bad or any(part in ("", ".", "..") for part in parts):
        raise InputError(
            f"{r}: the path {str(rel)[:200]!r} in this folder's records does not "
            "stay inside it; ignored")
    here = r
    for part in parts[:-1]:
        here = here / part
        if os.path.islink(here):
            raise InputError(
                f"{r}: the path {rel[:200]!r} in this folder's records passes "
                f"through the symbolic link {here}; ignored")
    return r.joinpath(*parts)


def remove_confined(root: str | os.PathLike, path: str | os.PathLike) -> bool:
    """Delete ``path`` only when it is a regular file (not a symlink) inside ``root`` reached
    without a symlinked folder (:func:`confined`); returns whether it was deleted. Whatever a
    file inside ``root`` says, nothing outside ``root`` is ever deleted."""
    try:
        p = confined(root, relative_to_root(root, path))
        if not stat.S_ISREG(os.lstat(p).st_mode):
            return False
        os.unlink(p)
    except (InputError, ValueError, OSError):
        return False
    return True


def remove_file(path: str | os.PathLike, *, missing_ok: bool = True) -> None:
    """Delete one of our own files (a marker, a lock, a record, a staged file) — a symlink at
    the name is removed, never followed."""
    try:
        os.unlink(path)
    except FileNotFoundError:
        if not missing_ok:
            raise


def link_or_copy(src: str | os.PathLike, dest: str | os.PathLike) -> Path:
    """Make ``dest`` the same content as ``src``: a hard link (a snapshot that every writer
    of this package replaces, never writes through), or a copy where links are not supported;
    made under a temporary name, then renamed onto ``dest`` (a file there is replaced, never
    written through). Returns ``Path(dest)``."""
    d = Path(dest)
    d.parent.mkdir(parents=True, exist_ok=True)
    tmp = _temp_name(d)
    try:
        try:
            os.link(src, tmp)
        except OSError:
            shutil.copy2(src, tmp, follow_symlinks=True)
        os.replace(tmp, d)
    except OSError as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise named_os_error(exc, d, rename=True) from None
    return d


def remove_empty_folder(path: str | os.PathLike) -> bool:
    """Remove the folder ``path`` if it is empty (not a symlink); returns whether it was."""
    try:
        if os.path.islink(path):
            return False
        os.rmdir(path)
    except OSError:
        return False
    return True


def remove_tree(path: str | os.PathLike) -> None:
    """Delete one of our own folders (a staging folder, a replaced store) and what is in it;
    symlinks inside are removed, never followed; errors are ignored."""
    shutil.rmtree(path, ignore_errors=True)


def replace_file(src: str | os.PathLike, dest: str | os.PathLike) -> None:
    """``os.replace(src, dest)`` of one of our own complete files or folders onto ``dest``;
    an error names ``dest``."""
    try:
        os.replace(src, dest)
    except OSError as exc:
        raise named_os_error(exc, dest, "replacing", rename=True) from None


# ---------------------------------------------------------------------------------------------
# never write over an input; replace a step's outputs all at once


def _identity(path: str | os.PathLike) -> tuple[int, int] | None:
    """``(st_dev, st_ino)`` of what ``path`` names (symlinks followed), or ``None``."""
    try:
        st = os.stat(path)
    except (OSError, ValueError):
        return None
    return st.st_dev, st.st_ino


class InputFiles:
    """The files a command reads, by identity (device and inode: symlinks and hard links
    resolved), so that :func:`check_not_input` can refuse an output that *is* one of them,
    whatever folder or name reaches it.

    Args:
        paths: input files; a folder stands for every file below it (recursively, symlinks
            followed to files; at most ``max_files`` of them).
        max_files: bound on the files collected from folders.
    """

    def __init__(self, paths: Iterable[str | os.PathLike] = (), max_files: int = 100_000):
        self._ids: dict[tuple[int, int], Path] = {}
        self.max_files = max_files
        for p in paths:
            self.add(p)

    def add(self, path: str | os.PathLike) -> None:
        """Add one input file, or every file below a folder."""
        p = Path(path)
        if p.is_dir():
            n = 0
            for root, _dirs, files in os.walk(p):
                for name in files:
                    self.add(Path(root) / name)
                    n += 1
                    if n >= self.max_files:
                        return
            return
        ident = _identity(p)
        if ident is not None:
            self._ids.setdefault(ident, p)

    def which(self, path: str | os.PathLike) -> Path | None:
        """The input that ``path`` is (same file), or ``None``."""
        ident = _identity(path)
        return None if ident is None else self._ids.get(ident)

    def __len__(self) -> int:
        return len(self._ids)


def check_not_input(
    output_path: str | os.PathLike, input_paths: InputFiles | Iterable[str | os.PathLike]
) -> Path:
    """Refuse to write ``output_path`` when it is one of the inputs (the same file by
    ``os.path.samefile``'s test: device and inode, symlinks resolved, whatever the folder or the
    name).

    Args:
        output_path: a file the command is about to write (it may not exist yet: then it cannot
            be an input).
        input_paths: the command's input files (an :class:`InputFiles`, or paths; a folder
            stands for every file below it).

    Returns:
        ``Path(output_path)``.

    Raises:
        InputError: the output is an input (the message names both).
    """
    inputs = input_paths if isinstance(input_paths, InputFiles) else InputFiles(input_paths)
    out = Path(output_path)
    hit = inputs.which(out)
    if hit is not None:
        same = "" if os.path.abspath(hit) == os.path.abspath(out) else f" (the same file as {hit})"
        raise InputError(
            f"refusing to write {out}: it is an input of this command{same}; choose another "
            "output folder")
    return out


def _check_replaceable(dest: Path) -> None:
    """Refuse a destination that a file cannot replace (a folder), naming it."""
    if dest.is_dir() and not dest.is_symlink():
        raise InputError(
            f"cannot write {dest}: a folder of that name is in the way (a file is "
            "written there; move the folder away)")
    if dest.parent.exists() and not dest.parent.is_dir():
        raise InputError(f"cannot write {dest}: {dest.parent} is not a folder")


def _temp_name(dest: Path, kind: str = "") -> Path:
    """A fresh name beside ``dest`` in :data:`TEMP_FILE_RE`'s pattern (removed by
    :func:`clean_stale_temp_files` when the writer is killed)."""
    rnd = os.urandom(6).hex()
    return dest.with_name(f".{dest.name}{kind}.{os.getpid()}-{rnd}.tmp")


class ReplaceTransaction:
    """Replace-then-commit: stage every output of a step, then move them into place together.

    Each output is first written to a temporary file beside its destination (same folder, so
    same file system; named like :func:`atomic_write`'s temporary files, so a killed run's
    leftovers are cleaned by :func:`clean_stale_temp_files`). Only :meth:`commit`, called when
    every output is complete, moves them into place (``os.replace`` each). Until then the
    previous outputs are untouched; a failure before the commit removes the staged files and
    nothing else. Destinations are checked when staged and again before the first move (not an
    input of the command, not a folder), so the usual failures (a folder in the way, a full
    disk while writing) happen before anything is replaced. Should a move itself fail midway
    (a concurrent change), the outputs already moved are put back: each replaced file was first
    hard-linked to a backup name, and the backups are removed after a successful commit.

    Use :func:`replace_then_commit` (a context manager that commits on success and rolls back
    on any exception)::

        with replace_then_commit(inputs=[capture]) as tx:
            save_cube(tx.stage(out / "x.npz"), cube)          # write to the staged path
            tx.write(out / "x.png", lambda p: write_png(p))   # or: OSErrors name x.png
        tx.replaced       # the destinations that existed before (now replaced)

    Args:
        inputs: the command's input files (see :func:`check_not_input`).
    """

    def __init__(self, inputs: InputFiles | Iterable[str | os.PathLike] = ()) -> None:
        self.inputs = inputs if isinstance(inputs, InputFiles) else InputFiles(inputs)
        self._files: dict[Path, Path] = {}  # destination -> staged file
        self._trees: dict[Path, Path] = {}  # destination folder -> staged folder
        self.replaced: list[Path] = []
        self.committed: list[Path] = []
        self.done = False
        self._recovered: set[Path] = set()

    def _check_open(self) -> None:
        if self.done:
            raise RuntimeError("the transaction is already committed or rolled back")

    def check(self, dest: str | os.PathLike) -> Path:
        """Check a destination now (not an input, no folder in the way); returns it."""
        d = Path(dest)
        if d.parent not in self._recovered:
            self._recovered.add(d.parent)
            recover_commits(d.parent)
        check_not_input(d, self.inputs)
        _check_replaceable(d)
        return d

    def stage(self, dest: str | os.PathLike) -> Path:
        """The temporary path to write ``dest``'s new content to (created empty here; a writer
        may replace it, e.g. with its own atomic write). Its folder is created."""
        self._check_open()
        d = self.check(dest)
        if d in self._files:
            return self._files[d]
        d.parent.mkdir(parents=True, exist_ok=True)
        tmp = _temp_name(d)
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        except OSError as exc:
            raise named_os_error(exc, d) from None
        os.close(fd)
        self._files[d] = tmp
        return tmp

    def write(self, dest: str | os.PathLike, writer: Callable[[Path], Any]) -> Path:
        """Stage ``dest`` and call ``writer(staged_path)``; an ``OSError`` (a full disk, ...)
        names ``dest``. Returns ``Path(dest)``."""
        tmp = self.stage(dest)
        try:
            writer(tmp)
        except OSError as exc:
            raise named_os_error(exc, dest, rename=True) from None
        return Path(dest)

    def stage_tree(self, dest_dir: str | os.PathLike) -> Path:
        """A temporary folder inside ``dest_dir`` in which a writer lays out files; at
        :meth:`commit` every file below it moves to the same relative path below ``dest_dir``
        (files of ``dest_dir`` the writer did not produce are kept)."""
        self._check_open()
        d = Path(dest_dir)
        if d.exists() and not d.is_dir():
            raise InputError(f"output folder {d} exists and is not a folder")
        d.mkdir(parents=True, exist_ok=True)
        tmp = _temp_name(d / "staging")
        tmp.mkdir()
        self._trees[d] = tmp
        return tmp

    def _plan(self) -> list[tuple[Path, Path]]:
        moves = [(tmp, dest) for dest, tmp in self._files.items()]
        for dest_dir, tmp_dir in self._trees.items():
            for root, _dirs, files in os.walk(tmp_dir):
                for name in sorted(files):
                    src = Path(root) / name
                    moves.append((src, dest_dir / src.relative_to(tmp_dir)))
        return moves

    def commit(self) -> list[Path]:
        """Move every staged output into place; returns the destinations.

        Before the first move, every replaced file is hard-linked to a backup name and a
        journal (``.hsi_torch_commit-<pid>-<random>.json`` in the first destination's folder)
        lists the moves: a process killed between two moves (SIGKILL, power loss) leaves the
        journal, and the next transaction into that folder (or :func:`clean_stale_temp_files`)
        puts the earlier files back (:func:`recover_commits`) — never new files beside old ones
        unmarked."""
        self._check_open()
        moves = self._plan()
        for src, dest in moves:  # every check before the first move
            if not src.is_file():
                raise InputError(
                    f"the new {dest} was not written completely (its staged file "
                    f"{src.name} is missing)")
            self.check(dest)
        backups: list[tuple[Path, Path | None]] = []  # (destination, backup or None if new)
        journal: Path | None = None
        moved = 0
        existed = [dest.is_file() or dest.is_symlink() for _src, dest in moves]
        try:
            for (_src, dest), there in zip(moves, existed, strict=True):
                backup = None
                if there:
                    backup = _temp_name(dest, ".old")
                    try:
                        os.link(dest, backup, follow_symlinks=False)
                    except OSError:
                        backup = None  # no hard links here: the move is still atomic per file
                backups.append((dest, backup))
            journal = _write_journal(moves, backups)
            for (src, dest), there in zip(moves, existed, strict=True):
                if there:
                    self.replaced.append(dest)
                dest.parent.mkdir(parents=True, exist_ok=True)
                try:
                    os.replace(src, dest)
                except OSError as exc:
                    raise named_os_error(exc, dest, "replacing", rename=True) from None
                moved += 1
        except BaseException:
            done = list(zip(backups, existed, strict=False))[:moved]
            for (dest, backup), there in reversed(done):  # put back what was already moved
                with contextlib.suppress(OSError):
                    if backup is not None:
                        os.replace(backup, dest)
                    elif not there:
                        os.unlink(dest)
            _discard(journal, backups)
            self.replaced.clear()
            self.rollback()
            raise
        _discard(journal, backups)  # complete
        for tmp_dir in self._trees.values():
            shutil.rmtree(tmp_dir, ignore_errors=True)
        self.done = True
        self.committed = [dest for _src, dest in moves]
        return self.committed

    def staged_dest(self, path: str | os.PathLike) -> Path | None:
        """The destination whose staged file (or staged folder's file) ``path`` is, or
        ``None``."""
        p = os.path.abspath(path)
        for dest, tmp in self._files.items():
            if os.path.abspath(tmp) == p:
                return dest
        for dest_dir, tmp_dir in self._trees.items():
            t = os.path.abspath(tmp_dir)
            if p == t or p.startswith(t + os.sep):
                return dest_dir / os.path.relpath(p, t)
        return None

    def rollback(self) -> None:
        """Remove every staged file and folder; the destinations are left as they are."""
        for tmp in self._files.values():
            with contextlib.suppress(OSError):
                os.unlink(tmp)
        for tmp_dir in self._trees.values():
            shutil.rmtree(tmp_dir, ignore_errors=True)
        self.done = True


@contextlib.contextmanager
def replace_then_commit(
    inputs: InputFiles | Iterable[str | os.PathLike] = (),
) -> Iterator[ReplaceTransaction]:
    """A :class:`ReplaceTransaction` that commits when the block ends normally and rolls back
    (removing only its staged files) when it raises."""
    tx = ReplaceTransaction(inputs)
    try:
        yield tx
    except OSError as exc:  # a full disk while staging: name the file, not its staged path
        tx.rollback()
        names = [x for x in (exc.filename, getattr(exc, "filename2", None)) if x]
        dest = next((d for d in map(tx.staged_dest, names) if d is not None), None)
        if dest is None:
            raise
        raise named_os_error(exc, dest, rename=True) from None
    except BaseException:
        tx.rollback()
        raise
    if not tx.done:
        tx.commit()


#: A :class:`ReplaceTransaction`'s journal while it moves files: ``.hsi_torch_commit-<pid>-<rnd>
#: .json`` in the folder of its first destination.
JOURNAL_RE = re.compile(r"^\.hsi_torch_commit-(?P<pid>[0-9]+)-[0-9a-f]+\.json$")


def _discard(journal: Path | None, backups: list[tuple[Path, Path | None]]) -> None:
    """Remove a finished commit's journal first, then its backups (a backup left by a kill
    in between is a stale temporary file, removed by :func:`clean_stale_temp_files`)."""
    for f in (journal, *(b for _d, b in backups)):
        if f is not None:
            with contextlib.suppress(OSError):
                os.unlink(f)


def _write_journal(moves: list[tuple[Path, Path]],
                   backups: list[tuple[Path, Path | None]]) -> Path | None:  # fmt: skip
    """Write the journal of the moves (paths relative to its folder: the moves in that folder
    only) and the inode each new file will have; ``None`` when there is nothing to move."""
    if not moves:
        return None
    folder = moves[0][1].parent
    entries = []
    for (src, dest), (_d, backup) in zip(moves, backups, strict=True):
        if dest.parent != folder:
            continue
        entries.append({"dest": dest.name, "backup": backup.name if backup else None,
                        "new_inode": os.stat(src).st_ino})  # fmt: skip
    path = folder / f".hsi_torch_commit-{os.getpid()}-{os.urandom(6).hex()}.json"
    note = ("a replacement of these files was interrupted; the next run into this folder puts "
            "the earlier files back")
    return atomic_write_text(path, json.dumps({"note": note, "moves": entries}))


def recover_commits(folder: str | os.PathLike) -> list[Path]:
    """Undo the replacements that a killed :class:`ReplaceTransaction` left half done in
    ``folder`` (its journal is there and its process is gone): each file it had already moved
    into place (still the same inode) gets its backup back, or is removed when it was new.
    The journal's names are confined to ``folder``. Returns the files put back or removed."""
    done: list[Path] = []
    try:
        entries = [e for e in os.scandir(folder) if JOURNAL_RE.match(e.name)]
    except OSError:
        return done
    for entry in entries:
        m = JOURNAL_RE.match(entry.name)
        if m is None or pid_alive(int(m["pid"])):
            continue
        rec = read_own_json(entry.path, 1 << 20)
        moves = rec.get("moves") if isinstance(rec, dict) else None
        for mv in moves if isinstance(moves, list) else []:
            try:
                dest = confined(folder, mv["dest"])
                if "/" in mv["dest"] or os.lstat(dest).st_ino != int(mv["new_inode"]):
                    continue  # not moved yet, or changed since
                backup = mv.get("backup")
                if backup is None:
                    os.unlink(dest)
                else:
                    b = confined(folder, backup)
                    if (
                        "/" in backup
                        or not TEMP_FILE_RE.match(b.name)
                        or not stat.S_ISREG(os.lstat(b).st_mode)
                    ):
                        continue
                    os.replace(b, dest)
                done.append(dest)
            except (InputError, OSError, KeyError, TypeError, ValueError):
                continue
        with contextlib.suppress(OSError):
            os.unlink(entry.path)
    return done
