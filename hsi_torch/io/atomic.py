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
import shutil
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
    "check_not_input",
    "InputFiles",
    "ReplaceTransaction",
    "replace_then_commit",
    "clean_stale_temp_files",
    "clean_stale_temp_files_of",
    "lock_or_refuse",
    "mark_lock_holder",
]

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
        path: destination file.
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
    fd, tmp = tempfile.mkstemp(prefix=f".{dest.name}.{os.getpid()}-", suffix=".tmp",
                               dir=dest.parent)
    try:
        kwargs: dict[str, Any] = {} if mode == "wb" else {"encoding": "utf-8", "newline": ""}
        os.close(fd)
        with open(tmp, mode, **kwargs) as f:  # opened by name so that f.name is a path
            yield f
            f.flush()
            if fsync:
                os.fsync(f.fileno())
        # mkstemp creates 0600 files; give the result ordinary permissions (respecting umask).
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, dest)
    except OSError as exc:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise named_os_error(exc, dest) from None
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


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
    :data:`TEMP_FILE_RE`) whose writing process no longer exists are removed — and the staging
    folders of :meth:`ReplaceTransaction.stage_tree` named the same way, with what is in them; a
    live writer's file (a concurrent run into the same folder) and every other file are left
    alone. Not recursive.

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
        if m is None or _pid_alive(int(m["pid"])):
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
            "output folder"
        )
    return out


def _check_replaceable(dest: Path) -> None:
    """Refuse a destination that a file cannot replace (a folder), naming it."""
    if dest.is_dir() and not dest.is_symlink():
        raise InputError(f"cannot write {dest}: a folder of that name is in the way (a file is "
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

    def check(self, dest: str | os.PathLike) -> Path:
        """Check a destination now (not an input, no folder in the way); returns it."""
        d = Path(dest)
        check_not_input(d, self.inputs)
        _check_replaceable(d)
        return d

    def stage(self, dest: str | os.PathLike) -> Path:
        """The temporary path to write ``dest``'s new content to (created empty here; a writer
        may replace it, e.g. with its own atomic write). Its folder is created."""
        if self.done:
            raise RuntimeError("the transaction is already committed or rolled back")
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
        if self.done:
            raise RuntimeError("the transaction is already committed or rolled back")
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
        """Move every staged output into place; returns the destinations."""
        if self.done:
            raise RuntimeError("the transaction is already committed or rolled back")
        moves = self._plan()
        for src, dest in moves:  # every check before the first move
            if not src.is_file():
                raise InputError(f"the new {dest} was not written completely (its staged file "
                                 f"{src.name} is missing)")
            self.check(dest)
        backups: list[tuple[Path, Path | None]] = []  # (destination, backup or None if new)
        try:
            for src, dest in moves:
                backup = None
                if dest.is_file() or dest.is_symlink():
                    backup = _temp_name(dest, ".old")
                    try:
                        os.link(dest, backup, follow_symlinks=False)
                    except OSError:
                        backup = None  # no hard links here: the move is still atomic per file
                    self.replaced.append(dest)
                dest.parent.mkdir(parents=True, exist_ok=True)
                try:
                    os.replace(src, dest)
                except OSError as exc:
                    if backup is not None:
                        os.unlink(backup)
                    raise named_os_error(exc, dest, "replacing", rename=True) from None
                backups.append((dest, backup))
        except BaseException:
            for dest, backup in reversed(backups):  # put back what was already moved
                with contextlib.suppress(OSError):
                    if backup is not None:
                        os.replace(backup, dest)
                    else:
                        os.unlink(dest)
            self.replaced.clear()
            self.rollback()
            raise
        for _dest, backup in backups:
            if backup is not None:
                with contextlib.suppress(OSError):
                    os.unlink(backup)
        for tmp_dir in self._trees.values():
            shutil.rmtree(tmp_dir, ignore_errors=True)
        self.done = True
        self.committed = [dest for _src, dest in moves]
        return self.committed

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
    except BaseException:
        tx.rollback()
        raise
    if not tx.done:
        tx.commit()
