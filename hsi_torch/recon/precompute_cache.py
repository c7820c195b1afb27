"""On-disk cache of the per-bundle precomputation, keyed by content, authenticated, safe to load.

The per-bundle precomputation (:func:`hsi_torch.recon.sensing.precompute_sensing`) costs seconds at
full size and depends only on the bundle file's content, ``(beta, diff_order)``, the precision,
the device type and the code that computes it; a process stores it once and later processes load
it. The rules (key, format, trust, folders, bound, measured cost) are ``docs/reconstruct.md``,
*The precomputation cache*. Here: an entry is a folder ``<bundle stem>-<key>.hsicache/`` of
``<name>.npy`` files (data at multiples of :data:`ALIGN` bytes) and :data:`INDEX`, keyed by
:func:`entry_key`, authenticated by a keyed BLAKE3 MAC (:func:`_mac`, the folder's secret in
:data:`KEY_FILE`; the hash memo :data:`HASH_MEMO` likewise), in a folder trusted by
:func:`folder_problem`, chosen by :func:`cache_folder`; :func:`load_entry` maps it copy-on-write
(refusals are misses with a :class:`PrecomputeCacheWarning`), :func:`changed_since_load` tells a
file changed under the mapping, :func:`save_entry` writes it, ``hsi-torch cache info | clear``.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import math
import os
import re
import secrets
import shutil
import stat
import sys
import threading
import time
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import blake3
import numpy as np

from hsi_torch import console
from hsi_torch.io.atomic import (
    atomic_write_text,
    human_size,
    json_default,
    pid_alive,
    read_file_head,
    read_own_bytes,
)
from hsi_torch.io.bounded import npy_header
from hsi_torch.io.safety import file_sha256

__all__ = [
    "FORMAT_VERSION",
    "POLICIES",
    "CACHE_ENV",
    "MAX_GB_ENV",
    "DEFAULT_MAX_GB",
    "SOURCE_FILES",
    "CACHE_STATS",
    "PrecomputeCacheWarning",
    "user_cache_dir",
    "cache_folder",
    "folder_problem",
    "entry_key",
    "entry_path",
    "content_sha256",
    "remember_sha256",
    "load_entry",
    "changed_since_load",
    "loaded_stamp",
    "release_pages",
    "save_entry",
    "cache_info",
    "clear_cache",
    "run_cache",
]

#: Version of the entry format (this module); part of every key.
FORMAT_VERSION = 2
#: The named policies of the ``precompute_cache`` setting (anything else is a folder path).
POLICIES = ("auto", "beside", "off")
#: Environment variable naming the user cache folder (entries go to its ``precompute/``).
CACHE_ENV = "HSI_TORCH_CACHE"
#: Environment variable bounding the size of one cache folder, GiB.
MAX_GB_ENV = "HSI_TORCH_CACHE_MAX_GB"
#: Default bound of a cache folder, GiB (one full-size float32 entry is about 1.9 GiB).
DEFAULT_MAX_GB = 16.0
#: An entry is not written when the disk would keep less than this free, bytes.
MIN_FREE_BYTES = 2 << 30
#: Writing an entry at least this large says so on stderr (its size and folder), bytes.
NOTE_BYTES = 256 << 20
#: Source files (relative to the package) whose content is part of every key: the code that
#: computes what is stored.
SOURCE_FILES = (
    "forward_model.py",
    "spectral.py",
    "optics/geometry.py",
    "io/radiometry.py",
    "recon/checks.py",
    "recon/sensing.py",
    "recon/precompute_cache.py",
    "recon/nnls/problem.py",
    "recon/nnls/_compiled.py",
    "recon/nnls/constants.py",
    "recon/nnls/kkt.py",
    "recon/nnls/_threads.py",
    "recon/spatial/problem.py",
    "recon/spatial/_compiled.py",
)
#: Counts of this process: ``hits``, ``misses`` (no entry), ``rejected`` (an entry refused:
#: foreign, corrupt, unreadable, untrusted folder), ``writes``, ``write_skipped`` (no space, not
#: writable, untrusted folder).
CACHE_STATS: dict[str, int] = {"hits": 0, "misses": 0, "rejected": 0, "writes": 0,
                               "write_skipped": 0}  # fmt: skip

#: The index file of an entry folder.
INDEX = "index.json"
#: File of a cache folder holding its secret (the MAC key of its entries and hash memo).
KEY_FILE = ".hsi_torch_cache_key"
#: Arrays start at multiples of this many bytes (NumPy's ``.npy`` header padding).
ALIGN = 64
#: Largest index (and ``.npy`` header, and hash memo) accepted, bytes.
MAX_HEADER_BYTES = 16 << 20
#: First bytes of an entry of format 1 (one file; recognised by eviction and ``cache clear``).
OLD_MAGIC = b"HSI_TORCH_PRECOMPUTE\n"
#: The dtypes an entry may hold: plain booleans, integers, floats and complex numbers.
_DTYPE_RE = re.compile(r"[<>|=]?(b1|[iu][1248]|f[248]|c(8|16))")
_NAME_RE = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]*")
_ENTRY_RE = re.compile(r"^[A-Za-z0-9_.-]+-(?P<key>[0-9a-f]{24})\.hsicache$")
_MEMBER_RE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]*\.npy$")
#: A writer's temporary entry folder / a replaced entry on its way out.
_TEMP_RE = re.compile(r"^\.(?P<name>.+\.hsicache)\.(?P<pid>[0-9]+)-[A-Za-z0-9_]+\.(tmp|old)$")
_NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)
_OPEN_FLAGS = os.O_RDONLY | _NOFOLLOW | getattr(os, "O_NONBLOCK", 0)
_LOCK = threading.Lock()
_SOURCE_DIGEST: list[str] = []
#: (realpath, device, inode, size, mtime_ns, ctime_ns) -> hex SHA-256 of the file's content
_HASHES: dict[tuple[str, int, int, int, int, int], str] = {}
#: File of a cache folder remembering the SHA-256 of the bundles seen (by file identity).
HASH_MEMO = "bundle_hashes.json"


class PrecomputeCacheWarning(UserWarning):
    """An entry of the precomputation cache was refused or could not be written (the
    reconstruction goes on: it recomputes, or keeps what it computed)."""


class _Refused(Exception):
    """An entry that must not be used (the message says why)."""


def _warn(message: str) -> None:
    warnings.warn(message, PrecomputeCacheWarning, stacklevel=3)


def user_cache_dir() -> Path:
    """The user cache folder of precomputations: ``$HSI_TORCH_CACHE/precompute``, else
    ``$XDG_CACHE_HOME/hsi_torch/precompute``, else ``~/.cache/hsi_torch/precompute``."""
    root = os.environ.get(CACHE_ENV)
    if root:
        return Path(root).expanduser() / "precompute"
    xdg = os.environ.get("XDG_CACHE_HOME")
    base = Path(xdg).expanduser() if xdg else Path.home() / ".cache"
    return base / "hsi_torch" / "precompute"


def _writable_folder(folder: Path) -> bool:
    """The folder exists and is writable, or can be created (its nearest existing parent is)."""
    p = folder
    while not p.exists():
        if p.parent == p:
            return False
        p = p.parent
    return p.is_dir() and os.access(p, os.W_OK | os.X_OK)


def folder_problem(folder: str | os.PathLike) -> str | None:
    """Why the entries of an existing cache folder must not be trusted, or ``None``.

    The folder must be a folder of this user (``st_uid`` the effective user id) that neither its
    group nor others may write (mode ``& 0o022 == 0``), as ssh checks ``~/.ssh``; a group that is
    the user's private group (named as the user, no other member: the ``umask 002`` systems)
    counts as the user's own, as Debian's ssh allows. A folder that does not exist yet is
    ``None`` (it is made ``0700``). Not checked where the system has no user ids (Windows)."""
    if not hasattr(os, "geteuid"):  # pragma: no cover - Windows
        return None
    try:
        st = os.stat(folder)
    except (FileNotFoundError, NotADirectoryError):  # not there (yet): made 0700
        return None
    except OSError as exc:
        return f"cannot be read ({exc.strerror})"
    if not stat.S_ISDIR(st.st_mode):
        return "is not a folder"
    if st.st_uid != os.geteuid():
        return f"belongs to another user (uid {st.st_uid}, this process runs as {os.geteuid()})"
    if st.st_mode & 0o022 and (st.st_mode & 0o002 or not _private_group(st.st_gid)):
        return (f"is writable by {'group and others' if st.st_mode & 0o002 else 'its group'} "
                f"(mode {stat.S_IMODE(st.st_mode):04o}; chmod go-w it)")  # fmt: skip
    return None


def _private_group(gid: int) -> bool:
    """``gid`` is this user's private group: named as the user, the user's primary group, and no
    other user in it (listed as a member or with it as primary group)."""
    try:
        import grp
        import pwd

        me = pwd.getpwuid(os.geteuid())
        g = grp.getgrgid(gid)
        others = [u.pw_name for u in pwd.getpwall() if u.pw_gid == gid and u.pw_uid != me.pw_uid]
    except (ImportError, KeyError, OSError):
        return False
    return (
        g.gr_name == me.pw_name
        and me.pw_gid == gid
        and set(g.gr_mem) <= {me.pw_name}
        and (not others)
    )


def _make_folder(folder: Path) -> None:
    folder.mkdir(mode=0o700, parents=True, exist_ok=True)


def cache_folder(
    policy: str | os.PathLike | None, bundle_path: str | os.PathLike | None
) -> tuple[Path | None, str | None]:
    """The folder of the entries for a ``precompute_cache`` setting.

    Args:
        policy: ``"auto"``, ``"beside"``, ``"off"`` or a folder path (``None``: ``"off"``).
        bundle_path: the bundle file (``None``: an in-memory bundle, which is never cached).

    Returns:
        ``(folder, note)``: the folder (``None``: no cache) and, when the setting could not be
        followed as given, why (a sentence) — e.g. ``"beside"`` for a read-only bundle folder, or
        a folder of another user or writable by others (:func:`folder_problem`), falls back to
        the user cache folder.
    """
    if policy is None or bundle_path is None or str(policy) == "off":
        return None, None
    user = user_cache_dir()
    if str(policy) == "auto":
        want = user
    elif str(policy) == "beside":
        want = Path(bundle_path).resolve().parent / ".hsi_torch_cache"
    else:
        want = Path(policy).expanduser()
    why = folder_problem(want)
    if why is None and not _writable_folder(want):
        why = "is not writable"
    if why is None:
        return want, None
    user_why = folder_problem(user)
    if want != user and user_why is None and _writable_folder(user):
        return user, (f"precomputation cache folder {want} {why}: its entries are ignored; "
                      f"using the user cache folder {user}")  # fmt: skip
    return None, f"precomputation cache folder {want} {why}: no cache"


def _source_digest() -> str:
    """SHA-256 of the :data:`SOURCE_FILES` (computed once per process)."""
    if not _SOURCE_DIGEST:
        root = Path(__file__).resolve().parents[1]
        h = hashlib.sha256()
        for rel in SOURCE_FILES:
            h.update(rel.encode())
            try:
                h.update((root / rel).read_bytes())
            except OSError:
                h.update(b"<missing>")
        _SOURCE_DIGEST.append(h.hexdigest())
    return _SOURCE_DIGEST[0]


def entry_key(parts: Mapping[str, Any], layout_version: int) -> str:
    """Hex SHA-256 of ``parts`` (JSON, sorted keys) with :data:`FORMAT_VERSION`,
    ``layout_version`` (the caller's: bump it when what is stored changes meaning), the torch
    version and the digest of :data:`SOURCE_FILES`."""
    import torch  # lazy: the cache module loads without torch

    full = {"parts": dict(parts), "format": FORMAT_VERSION, "layout": int(layout_version),
            "torch": torch.__version__, "source": _source_digest()}  # fmt: skip
    text = json.dumps(full, sort_keys=True, default=json_default)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def entry_path(folder: str | os.PathLike, bundle_path: str | os.PathLike, key: str) -> Path:
    """``<folder>/<bundle stem>-<first 24 hex digits of key>.hsicache`` (an entry folder)."""
    stem = re.sub(r"[^A-Za-z0-9_.-]", "_", Path(bundle_path).stem)[:48] or "bundle"
    return Path(folder) / f"{stem}-{key[:24]}.hsicache"


# ------------------------------------------------------------------------ the folder's secret


def _secret(folder: Path, create: bool) -> bytes | None:
    """The folder's secret (:data:`KEY_FILE`), made when ``create`` and missing (``None``: none).

    Raises:
        _Refused: the key file is not a regular ``0600`` file of this user of 32 bytes.
    """
    path = folder / KEY_FILE
    try:
        fd = os.open(path, _OPEN_FLAGS)
    except FileNotFoundError:
        if not create:
            return None
        # made complete under a temporary name, then linked into place: a reader never sees a
        # partial key, and of two processes making it at once, one key wins
        tmp = folder / f".{KEY_FILE}.{os.getpid()}-{secrets.token_hex(6)}.tmp"
        try:
            _write_new(tmp, lambda f: f.write(secrets.token_bytes(32)))
            with contextlib.suppress(FileExistsError):
                os.link(tmp, path)
        finally:
            tmp.unlink(missing_ok=True)
        return _secret(folder, create=False)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise _Refused(f"the key file {path} is a symbolic link") from None
        raise
    with os.fdopen(fd, "rb") as f:
        st = os.fstat(fd)
        mine = not hasattr(os, "geteuid") or st.st_uid == os.geteuid()
        if not (stat.S_ISREG(st.st_mode) and mine and not st.st_mode & 0o077
                and st.st_size == 32):  # fmt: skip
            raise _Refused(
                f"the key file {path} is not a 32-byte file of this user with mode "
                f"0600 (mode {stat.S_IMODE(st.st_mode):04o}, {st.st_size} bytes)"
            )
        return f.read(32)


def _hasher(secret: bytes, domain: bytes) -> Any:
    h = blake3.blake3(key=secret, max_threads=blake3.blake3.AUTO)
    h.update(b"hsi_torch precompute cache\0" + domain + b"\0")
    return h


def _canonical(obj: Any) -> bytes:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=True).encode("utf-8")


def _mac(secret: bytes, index: Mapping[str, Any], arrays: Mapping[str, np.ndarray]) -> str:
    """Keyed BLAKE3 of an entry: its index (less ``mac``) and every array's bytes, by name."""
    head = _canonical({k: v for k, v in index.items() if k != "mac"})
    h = _hasher(secret, b"entry")
    h.update(len(head).to_bytes(8, "little") + head)
    for name in sorted(arrays):
        a = arrays[name]
        h.update(name.encode("utf-8") + b"\0" + int(a.nbytes).to_bytes(8, "little"))
        if a.size:
            h.update(memoryview(a.reshape(-1).view(np.uint8)))
    return h.hexdigest()


# ------------------------------------------------------------------------ the bundle's hash


def _memo_mac(secret: bytes, ident: str, sha: str) -> str:
    h = _hasher(secret, b"bundle hash")
    h.update(_canonical([ident, sha]))
    return h.hexdigest()


def _memo_secret(memo_folder: str | os.PathLike | None) -> tuple[Path, bytes] | None:
    """The memo file and the folder's secret, where the folder may be trusted (else ``None``)."""
    if memo_folder is None:
        return None
    folder = Path(memo_folder)
    try:
        if folder_problem(folder) is not None or not _writable_folder(folder):
            return None
        _make_folder(folder)
        if folder_problem(folder) is not None:
            return None
        secret = _secret(folder, create=True)
    except (OSError, _Refused):
        return None
    return (folder / HASH_MEMO, secret) if secret else None


def _identity(p: Path, st: os.stat_result) -> tuple:
    return (str(p.resolve()), st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)


def remember_sha256(path: str | os.PathLike, sha: str, before: os.stat_result) -> None:
    """Remember in this process that the file at ``path`` hashes to ``sha`` (computed by the
    caller from the bytes it read, e.g. :meth:`~hsi_torch.io.bundle.CalibrationBundle.load_hashed`)
    — only if its identity (:func:`content_sha256`) is still ``before``, taken before the read."""
    p = Path(path)
    ident = _identity(p, before)
    if _identity(p, p.stat()) == ident:
        _HASHES[ident] = sha


def content_sha256(path: str | os.PathLike, memo_folder: str | os.PathLike | None = None) -> str:
    """Hex SHA-256 of a file's content, remembered while the file's identity stays the same.

    The identity is the resolved path, device, inode, size, modification *and change* time
    (``st_ctime_ns``: set by the system on every write or metadata change, never by a user), so
    a rewritten or edited file is always hashed again. Remembered in this process, and, with
    ``memo_folder`` (a trusted cache folder: :func:`folder_problem`), in its
    ``bundle_hashes.json`` (:data:`HASH_MEMO`) for later processes: a second process then reads no
    byte of an unchanged bundle. Each remembered hash carries a MAC keyed by the folder's secret:
    a line written by anyone else (mapping this bundle to another's hash) is ignored.
    """
    p = Path(path)
    ident = _identity(p, p.stat())
    sha = _HASHES.get(ident)
    if sha is not None:
        return sha
    where = _memo_secret(memo_folder)
    memo: dict[str, Any] = {}
    if where is not None:
        try:
            got = json.loads(
                read_own_bytes(where[0], MAX_HEADER_BYTES, what="cache file", error=_Refused)
            )
            memo = dict(got) if isinstance(got, dict) else {}
        except (OSError, ValueError, _Refused, RecursionError):
            memo = {}
    text = json.dumps(ident)
    line = memo.get(text)
    sha = line.get("sha256") if isinstance(line, dict) else None
    if not (isinstance(sha, str) and re.fullmatch(r"[0-9a-f]{64}", sha) and where is not None
            and line.get("mac") == _memo_mac(where[1], text, sha)):  # fmt: skip
        sha = file_sha256(p)
        if where is not None:
            memo = dict(list(memo.items())[-255:])
            memo[text] = {"sha256": sha, "mac": _memo_mac(where[1], text, sha)}
            with contextlib.suppress(OSError):  # a read-only folder: hashed again next time
                atomic_write_text(where[0], json.dumps(memo, indent=0))
    if len(_HASHES) > 64:
        _HASHES.clear()
    _HASHES[ident] = sha
    return sha


# ---------------------------------------------------------------------------------- reading


class _Stamp:
    """The open files of a loaded entry and their size, modification and change times when
    checked: :meth:`changed` tells whether one was written to since (closed with the arrays)."""

    def __init__(self, entry: Path) -> None:
        self.entry = entry
        self.files: list[tuple[str, int, tuple[int, int, int]]] = []

    def add(self, name: str, fd: int) -> None:
        st = os.fstat(fd)
        self.files.append((name, fd, (st.st_size, st.st_mtime_ns, st.st_ctime_ns)))

    def changed(self) -> str | None:
        for name, fd, (size, mtime, ctime) in self.files:
            try:
                st = os.fstat(fd)
            except OSError as exc:  # pragma: no cover - closed under us
                return f"{name} cannot be checked ({exc})"
            if st.st_size != size:
                return f"{name} was truncated or extended ({size} -> {st.st_size} bytes)"
            if (st.st_mtime_ns, st.st_ctime_ns) != (mtime, ctime):
                return f"{name} was written to"
        return None

    def close(self) -> None:
        for _name, fd, _st in self.files:
            with contextlib.suppress(OSError):
                os.close(fd)
        self.files = []

    def __del__(self) -> None:
        self.close()


class _Mapped(np.memmap):
    """A memory-mapped array of an entry; keeps the entry's :class:`_Stamp` (open files)."""

    _hsi_stamp: _Stamp | None = None


def loaded_stamp(arrays: Mapping[str, np.ndarray]) -> _Stamp | None:
    """The stamp of the entry ``arrays`` were loaded from (:func:`load_entry`), for
    :func:`changed_since_load`; ``None`` when none of them is mapped from an entry."""
    for a in arrays.values():
        while a is not None:
            s = getattr(a, "_hsi_stamp", None)
            if s is not None:
                return s
            a = a.base if isinstance(a.base, np.ndarray) else None
    return None


def changed_since_load(stamp: _Stamp | None) -> str | None:
    """Why the entry of ``stamp`` (:func:`loaded_stamp`) must not be used any more — one of its
    files was written to, truncated or extended since it was checked — or ``None``.

    A few ``fstat`` calls on the files held open: cheap enough before every frame. A file
    replaced by a new one (renamed over, removed) is no change: the mapping keeps the old one.
    """
    return None if stamp is None else stamp.changed()


def _check_table(table: Any) -> dict[str, tuple[np.dtype, tuple[int, ...]]]:
    """The array table of an index, checked: ``{name: (dtype, shape)}``."""
    if not isinstance(table, dict):
        raise _Refused("'arrays' is not an object")
    out: dict[str, tuple[np.dtype, tuple[int, ...]]] = {}
    for name, d in table.items():
        if not _NAME_RE.fullmatch(str(name)):
            raise _Refused(f"array name {name!r}")
        if not isinstance(d, dict) or not isinstance(d.get("dtype"), str):
            raise _Refused(f"array {name!r}: no dtype")
        if not _DTYPE_RE.fullmatch(d["dtype"]):
            raise _Refused(f"array {name!r} has dtype {d['dtype']!r} (plain numbers only)")
        shape = d.get("shape")
        if not (isinstance(shape, list) and all(type(v) is int and v >= 0 for v in shape)):
            raise _Refused(f"array {name!r}: bad shape {shape!r}")
        out[str(name)] = (np.dtype(d["dtype"]), tuple(shape))
    return out


def _map_member(dir_fd: int, name: str, dt: np.dtype, shape: tuple[int, ...],
                stamp: _Stamp) -> np.ndarray:  # fmt: skip
    """The array of ``<name>.npy`` (its header must declare ``dt`` and ``shape`` in C order and
    the file hold exactly its bytes), memory-mapped copy-on-write."""
    fname = f"{name}.npy"
    try:
        fd = os.open(fname, _OPEN_FLAGS, dir_fd=dir_fd)
    except OSError as exc:
        raise _Refused(f"{fname}: {exc.strerror}") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise _Refused(f"{fname} is not a regular file")
        f = os.fdopen(os.dup(fd), "rb")
    except BaseException:
        os.close(fd)
        raise
    stamp.add(fname, fd)
    with f:
        try:
            got_shape, got_dt = npy_header(f, MAX_HEADER_BYTES, c_order=True)
        except (ValueError, SyntaxError, TypeError, OSError) as exc:
            raise _Refused(f"{fname}: not a NumPy array file ({exc})") from None
        if got_dt != dt or got_shape != shape:
            raise _Refused(f"{fname} holds {got_dt} {tuple(got_shape)}, the index says {dt} "
                           f"{shape}")  # fmt: skip
        offset = f.tell()
        nbytes = int(np.prod(shape, dtype=np.int64)) * dt.itemsize
        if st.st_size != offset + nbytes:
            raise _Refused(f"{fname} has {st.st_size} bytes, {offset + nbytes} expected "
                           "(truncated or altered)")  # fmt: skip
        if offset % ALIGN:
            raise _Refused(f"{fname}: data at byte {offset}, not a multiple of {ALIGN}")
        if nbytes == 0:
            return np.zeros(shape, dtype=dt)
        a = _Mapped(f, dtype=dt, mode="c", offset=offset, shape=shape)
    a._hsi_stamp = stamp
    return a


def _read_entry(path: Path, key: str, secret: bytes) -> tuple[dict[str, np.ndarray], dict]:
    try:
        dir_fd = os.open(path, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0) | _NOFOLLOW)
    except OSError as exc:
        if exc.errno in (errno.ENOTDIR, errno.ELOOP):
            raise _Refused("not an entry folder (a file or a symbolic link)") from None
        raise
    stamp = _Stamp(path)
    try:
        index = json.loads(
            read_own_bytes(
                INDEX, MAX_HEADER_BYTES, what="cache index", dir_fd=dir_fd, error=_Refused
            ).decode("utf-8")
        )
        if not isinstance(index, dict):
            raise _Refused("the index is not a JSON object")
        if index.get("format") != FORMAT_VERSION:
            raise _Refused(f"format {index.get('format')!r}, this software reads "
                           f"{FORMAT_VERSION}")  # fmt: skip
        if index.get("key") != key:
            raise _Refused("it was made for another bundle, settings or software (key differs)")
        table = _check_table(index.get("arrays"))
        arrays = {name: _map_member(dir_fd, name, dt, shape, stamp)
                  for name, (dt, shape) in table.items()}  # fmt: skip
        if not isinstance(index.get("mac"), str) or index["mac"] != _mac(secret, index, arrays):
            raise _Refused("its MAC does not verify (not written by this user's software for "
                           "this key, or altered)")  # fmt: skip
        with contextlib.suppress(OSError, NotImplementedError):  # recently used: kept
            os.utime(INDEX, dir_fd=dir_fd, follow_symlinks=False)
    except BaseException:
        stamp.close()
        raise
    finally:
        os.close(dir_fd)
    return arrays, index


def load_entry(path: str | os.PathLike, key: str) -> tuple[dict[str, np.ndarray], dict] | None:
    """The arrays and index of the entry ``path`` if it holds ``key``, was written by this
    user's software (its MAC) in a trusted folder (:func:`folder_problem`) and is intact.

    Returns:
        ``({name: array}, index)`` with the arrays memory-mapped copy-on-write (their files stay
        open: :func:`loaded_stamp`, :func:`changed_since_load`), or ``None``: no entry (a miss),
        or an entry refused (untrusted folder, foreign, altered, truncated, unreadable: a
        :class:`PrecomputeCacheWarning` names the file and why).
    """
    p = Path(path)
    try:
        os.lstat(p)
    except OSError:
        CACHE_STATS["misses"] += 1
        return None
    try:
        why = folder_problem(p.parent)
        if why is not None:
            raise _Refused(f"the cache folder {p.parent} {why}")
        secret = _secret(p.parent, create=False)
        if secret is None:
            raise _Refused(f"no key file {KEY_FILE} in its folder: it cannot be authenticated")
        arrays, meta = _read_entry(p, key, secret)
    except (_Refused, OSError, ValueError, UnicodeDecodeError, RecursionError) as exc:
        CACHE_STATS["rejected"] += 1
        _warn(f"precomputation cache entry {p} refused ({exc}); recomputing")
        return None
    CACHE_STATS["hits"] += 1
    return arrays, meta


_MAPS_LINE = re.compile(r"^([0-9a-f]+)-([0-9a-f]+) \S+ \S+ ([0-9a-f]+):([0-9a-f]+) (\d+) +(/.*)$")
_MADV_DONTNEED = 4  # Linux


def _file_mappings(spans: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """This process's mappings of regular files that overlap ``spans``, ``(start, end)``, from
    ``/proc/self/maps``: the named file must be a regular file with the mapping's device and
    inode. A non-zero inode alone also marks mappings of devices and kernel objects
    (``anon_inode:[io_uring]``, a GPU driver's ``/dev/...``), whose pages no file holds:
    dropped, they are lost."""
    out = []
    seen: dict[tuple[str, int, int, int], bool] = {}
    with open("/proc/self/maps") as f:
        for line in f:
            m = _MAPS_LINE.match(line.rstrip("\n"))
            if not m or m[5] == "0":
                continue
            ms, me = int(m[1], 16), int(m[2], 16)
            if not any(ms < e and me > s for s, e in spans):
                continue
            key = (m[6], int(m[3], 16), int(m[4], 16), int(m[5]))
            if key not in seen:
                try:
                    st = os.stat(key[0])
                    seen[key] = (stat.S_ISREG(st.st_mode) and st.st_ino == key[3]
                                 and os.major(st.st_dev) == key[1]
                                 and os.minor(st.st_dev) == key[2])  # fmt: skip
                except (OSError, ValueError):  # deleted, renamed, unreadable: left alone
                    seen[key] = False
            if seen[key]:
                out.append((ms, me))
    return out


def _unwritten(start: int, end: int, page: int) -> bool:
    """No page of ``[start, end)`` holds data of its own: every page present in memory is the
    file's page (``/proc/self/pagemap`` bit 61), none is swapped out (bit 62) — a page written to
    in a copy-on-write mapping is an anonymous copy and fails this."""
    try:
        with open("/proc/self/pagemap", "rb") as f:
            f.seek(start // page * 8)
            entries = np.frombuffer(f.read((end - start) // page * 8), np.uint64)
    except OSError:  # pragma: no cover - no pagemap here: nothing is released
        return False
    if entries.shape[0] != (end - start) // page:  # pragma: no cover - a short read
        return False
    flags = entries >> np.uint64(61)  # bit 0: file page, 1: swapped, 2: present
    own = ((flags & np.uint64(4)) != 0) & ((flags & np.uint64(1)) == 0)
    return not bool(own.any() or ((flags & np.uint64(2)) != 0).any())


def release_pages(*arrays: Any) -> int:
    """Drop this process's resident pages of arrays memory-mapped from an entry
    (:func:`load_entry`) that it will not read for a while (Linux; elsewhere a no-op).

    The pages stay in the page cache: touched again they come back as minor page faults (no
    disk read, no copy). Only whole pages inside mappings of a regular file are dropped, and only
    where no page of the range was written (``/proc/self/pagemap``: every resident page is the
    file's, none a copy-on-write copy or swapped out), so nothing is lost — the data is read back
    from the unchanged file; anything else (private memory, a written mapping) is left as it is.
    The check and the release are two steps: no other thread may write to the arrays during the
    call (a copy-on-write page made between them would be dropped; reading is harmless). A
    full-size TV frame uses it between its stages: the per-pixel ``G``/``G⁻¹`` are not read by
    the ADMM iterations, nor the TV factor by the next frame's warm start. Cost: ≈ 5 ms a GiB.

    Args:
        arrays: numpy arrays or CPU tensors (their whole storage), ``None`` skipped.

    Returns:
        The bytes whose pages were released (0 where nothing was eligible).
    """
    if not sys.platform.startswith("linux"):
        return 0
    spans = []
    for a in arrays:
        if a is None:
            continue
        if hasattr(a, "untyped_storage"):  # a torch tensor: its whole storage
            if a.device.type != "cpu":
                continue
            st = a.untyped_storage()
            spans.append((st.data_ptr(), st.nbytes()))
        elif isinstance(a, np.ndarray) and a.flags.c_contiguous:
            spans.append((a.__array_interface__["data"][0], a.nbytes))
    page = os.sysconf("SC_PAGE_SIZE")
    spans = [(-(-s // page) * page, (s + n) // page * page) for s, n in spans]
    spans = [(s, e) for s, e in spans if e > s]
    if not spans:
        return 0
    try:
        import ctypes

        maps = _file_mappings(spans)
        madvise = ctypes.CDLL(None, use_errno=True).madvise
    except (OSError, AttributeError):  # pragma: no cover - no /proc or no madvise
        return 0
    madvise.argtypes = (ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int)
    done = 0
    for s, e in spans:
        pos = s
        for ms, me in maps:  # sorted by address: the file mappings must cover [s, e)
            if me <= pos or ms >= e:
                continue
            if ms > pos:
                break
            pos = min(me, e)
            if pos == e:
                break
        if pos == e and _unwritten(s, e, page) and madvise(s, e - s, _MADV_DONTNEED) == 0:
            done += e - s
    return done


# ---------------------------------------------------------------------------------- writing


def _max_bytes() -> int:
    """``$HSI_TORCH_CACHE_MAX_GB`` in bytes (a value that is not a finite number ≥ 0: a warning
    naming the variable, and the default)."""
    raw = os.environ.get(MAX_GB_ENV)
    if raw is None or not raw.strip():
        return int(DEFAULT_MAX_GB * (1 << 30))
    try:
        gb = float(raw)
    except ValueError:
        gb = math.nan
    if not (math.isfinite(gb) and 0.0 <= gb <= 1e9):
        _warn(f"${MAX_GB_ENV}={raw!r} is not a size in GiB (a finite number >= 0): using the "
              f"default {DEFAULT_MAX_GB:g} GiB")  # fmt: skip
        gb = DEFAULT_MAX_GB
    return int(gb * (1 << 30))


def _entry_kind(path: Path) -> str | None:
    """What a cache folder's child is, recognised by its name *and* content: ``"entry"`` (an
    entry folder whose index names its format and a key), ``"old"`` (an entry
    of format 1: one file starting with :data:`OLD_MAGIC`), ``"temp"`` (a writer's leftover
    folder whose process is gone), or ``None`` (anything else: never removed). Symbolic links
    are never followed (``None``)."""
    m = _ENTRY_RE.match(path.name)
    t = _TEMP_RE.match(path.name)
    if not (m or t):
        return None
    try:
        st = os.lstat(path)
    except OSError:
        return None
    if m and stat.S_ISREG(st.st_mode):
        return "old" if read_file_head(path, len(OLD_MAGIC)) == OLD_MAGIC else None
    if not stat.S_ISDIR(st.st_mode):
        return None
    if t:
        return "temp" if not pid_alive(int(t["pid"])) else None
    try:
        index = json.loads(
            read_own_bytes(path / INDEX, MAX_HEADER_BYTES, what="cache index", error=_Refused)
        )
    except (OSError, ValueError, _Refused, RecursionError):
        return None
    if not isinstance(index, dict) or not isinstance(index.get("format"), int):
        return None  # (an index that is not a JSON object: not the cache's)
    key = index.get("key")
    return "entry" if isinstance(key, str) and re.fullmatch(r"[0-9a-f]{64}", key) else None


def _entry_bytes(path: Path) -> int:
    try:
        if os.path.isdir(path) and not os.path.islink(path):
            return sum(e.stat(follow_symlinks=False).st_size for e in os.scandir(path))
        return os.lstat(path).st_size
    except OSError:
        return 0


def _remove_entry(path: Path) -> bool:
    """Remove an entry (folder or format-1 file) the cache wrote: only its ``index.json`` and
    ``*.npy`` files (unlinked, never followed), then the folder if that left it empty."""
    try:
        if not stat.S_ISDIR(os.lstat(path).st_mode):
            path.unlink()
            return True
        for e in os.scandir(path):
            if e.name == INDEX or _MEMBER_RE.match(e.name):
                os.unlink(e.path)  # a symbolic link is removed, not followed
        os.rmdir(path)
        return True
    except OSError:
        return False


def _entries(folder: Path) -> list[tuple[int, int, Path]]:
    """``(last used ns, bytes, path)`` of every entry of ``folder`` (format 1 and 2)."""
    out = []
    try:
        children = list(folder.iterdir())
    except OSError:
        return out
    for p in children:
        kind = _entry_kind(p) if _ENTRY_RE.match(p.name) else None
        if kind is None:
            continue
        try:
            used = os.lstat(p / INDEX if kind == "entry" else p).st_mtime_ns
        except OSError:
            continue
        out.append((used, _entry_bytes(p), p))
    return out


def _evict(folder: Path, keep: Path, limit: int) -> None:
    """Remove the least recently used entries of ``folder`` (not ``keep``) until the entries
    take at most ``limit`` bytes."""
    entries = [e for e in _entries(folder) if e[2] != keep]
    total = sum(e[1] for e in entries) + _entry_bytes(keep)
    for _used, size, p in sorted(entries):
        if total <= limit:
            break
        if _remove_entry(p):
            total -= size


def _write_new(path: Path, write: Any) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | _NOFOLLOW, 0o600)
    with os.fdopen(fd, "wb") as f:
        write(f)


def _replaceable(dest: Path) -> bool:
    """``dest`` (at an entry's own name) holds nothing but an entry's files: a folder of only
    ``index.json`` and ``*.npy`` files (whatever they hold: a damaged entry is replaced), or an
    entry of format 1. A symbolic link, or a folder with anything else in it, is not."""
    if _entry_kind(dest) in ("entry", "old"):
        return True
    try:
        if not stat.S_ISDIR(os.lstat(dest).st_mode):
            return False
        return all((e.name == INDEX or _MEMBER_RE.match(e.name)) and not e.is_dir(
            follow_symlinks=False) for e in os.scandir(dest))  # fmt: skip
    except OSError:
        return False


def _install(tmp: Path, dest: Path) -> None:
    """Rename the complete entry folder ``tmp`` onto ``dest``; an entry already there (an
    older or refused one) is moved aside first and removed; anything else there is left alone
    (OSError)."""
    try:
        os.rename(tmp, dest)
        return
    except OSError as exc:
        if exc.errno not in (errno.EEXIST, errno.ENOTEMPTY, errno.ENOTDIR, errno.EISDIR):
            raise
    if not _replaceable(dest):
        raise FileExistsError(errno.EEXIST, "something else than a cache entry is there",
                              str(dest))  # fmt: skip
    aside = dest.parent / f".{dest.name}.{os.getpid()}-{secrets.token_hex(6)}.old"
    os.rename(dest, aside)
    try:
        os.rename(tmp, dest)
    except OSError as exc:  # another process put its entry there meanwhile: it stays
        if exc.errno not in (errno.EEXIST, errno.ENOTEMPTY):
            raise
    _remove_entry(aside)


def _note_size(path: Path, nbytes: int, limit: int) -> None:
    total = sum(e[1] for e in _entries(path.parent))
    console.info(
        f"hsi-torch: precomputation cached in {path} ({nbytes / 2**30:.2f} GiB; the folder "
        f"holds {total / 2**30:.2f} GiB, at most {limit / 2**30:.1f} GiB: ${MAX_GB_ENV}; "
        "'hsi-torch cache info' / 'hsi-torch cache clear')",
        sys.stderr,
    )


def save_entry(
    path: str | os.PathLike,
    key: str,
    arrays: Mapping[str, np.ndarray],
    meta: Mapping[str, Any] | None = None,
) -> bool:
    """Write an entry atomically (never over anything but an older entry of the same name).

    Args:
        path: the entry (from :func:`entry_path`); key: its key (:func:`entry_key`).
        arrays: ``{name: array}``, numeric or bool numpy arrays (names: letters, digits,
            ``_ . -``, not starting with ``.`` or ``-``).
        meta: JSON-serialisable values stored beside the arrays (returned by
            :func:`load_entry`).

    Returns:
        Whether the entry was written. Not written (a :class:`PrecomputeCacheWarning` says why):
        the folder cannot be written or is not the user's own (:func:`folder_problem`), the disk
        would keep less than :data:`MIN_FREE_BYTES` free, an entry is larger than the folder's
        bound. An entry of at least :data:`NOTE_BYTES` says its size on stderr (not when quiet).
    """
    p = Path(path)
    for n, a in arrays.items():
        if not _NAME_RE.fullmatch(n):
            raise ValueError(f"cache array name {n!r}: letters, digits, '_', '.', '-' only")
        if a.dtype.hasobject or a.dtype.kind not in "biufc":
            raise TypeError(f"cache array {n!r} has dtype {a.dtype}: numbers only")
    nbytes = sum(int(a.nbytes) for a in arrays.values())
    limit = _max_bytes()
    if nbytes > limit:
        CACHE_STATS["write_skipped"] += 1
        _warn(
            f"precomputation cache: the entry for {p.name} ({nbytes / 2**30:.1f} GiB) exceeds "
            f"the folder's bound {limit / 2**30:.1f} GiB (${MAX_GB_ENV}); not written"
        )
        return False
    flat = {n: np.ascontiguousarray(a) for n, a in arrays.items()}
    index: dict[str, Any] = {**dict(meta or {}), "format": FORMAT_VERSION, "key": key,
                             "arrays": {n: {"dtype": a.dtype.str, "shape": list(a.shape)}
                                        for n, a in flat.items()}}  # fmt: skip
    index = json.loads(json.dumps(index, default=json_default))  # as it will be read back
    with _LOCK:
        tmp = None
        try:
            _make_folder(p.parent)
            why = folder_problem(p.parent)
            if why is not None:
                CACHE_STATS["write_skipped"] += 1
                _warn(f"precomputation cache folder {p.parent} {why}: not written")
                return False
            free = shutil.disk_usage(p.parent).free
            if free - nbytes < MIN_FREE_BYTES:
                CACHE_STATS["write_skipped"] += 1
                _warn(
                    f"precomputation cache: {human_size(free)} free in {p.parent}, the "
                    f"entry needs {human_size(nbytes)}; not written"
                )
                return False
            secret = _secret(p.parent, create=True)
            assert secret is not None
            tmp = p.parent / f".{p.name}.{os.getpid()}-{secrets.token_hex(6)}.tmp"
            tmp.mkdir(mode=0o700)
            for n, a in flat.items():
                _write_new(
                    tmp / f"{n}.npy",
                    lambda f, a=a: np.lib.format.write_array(f, a, allow_pickle=False),
                )
            index["mac"] = _mac(secret, index, flat)
            text = json.dumps(index, indent=0).encode("utf-8")
            _write_new(tmp / INDEX, lambda f: f.write(text))
            _install(tmp, p)
            tmp = None
            _evict(p.parent, p, limit)
        except (OSError, _Refused) as exc:
            CACHE_STATS["write_skipped"] += 1
            _warn(f"precomputation cache: could not write {p} ({exc}); not cached")
            return False
        finally:
            if tmp is not None and tmp.exists():
                _remove_entry(tmp)
    CACHE_STATS["writes"] += 1
    if nbytes >= NOTE_BYTES:
        _note_size(p, nbytes, limit)
    return True


# ------------------------------------------------------------------------ hsi-torch cache


def cache_info(folder: str | os.PathLike | None = None) -> dict[str, Any]:
    """What a cache folder holds (default: the user cache folder, :func:`user_cache_dir`).

    Returns:
        ``{"folder", "exists", "problem"`` (:func:`folder_problem`, ``None``: trusted),
        ``"entries"`` (``[{"name", "bytes", "last_used"`` (POSIX seconds)``, "format"}]``, most
        recently used first), ``"total_bytes"``, ``"max_bytes"`` (the bound,
        ``$HSI_TORCH_CACHE_MAX_GB``)``}``.
    """
    f = Path(folder) if folder is not None else user_cache_dir()
    rows = [{"name": p.name, "bytes": size, "last_used": used / 1e9,
             "format": 2 if p.is_dir() else 1}
            for used, size, p in sorted(_entries(f), reverse=True)]  # fmt: skip
    return {"folder": str(f), "exists": f.is_dir(), "problem": folder_problem(f),
            "entries": rows, "total_bytes": sum(r["bytes"] for r in rows),
            "max_bytes": _max_bytes()}  # fmt: skip


def clear_cache(folder: str | os.PathLike | None = None) -> dict[str, Any]:
    """Remove what the cache wrote in a folder (default: the user cache folder): its entries
    (recognised by name *and* content, :func:`_entry_kind`), the leftovers of killed writers and
    the memo of bundle hashes. Nothing else is touched; symbolic links are removed, never
    followed; nothing outside the folder is removed. The folder and its key file stay.

    Returns:
        ``{"folder", "removed"`` (names)``, "bytes"`` (freed)``, "kept"`` (names of other
        files left alone)``}``.
    """
    f = Path(folder) if folder is not None else user_cache_dir()
    removed, kept, freed = [], [], 0
    try:
        children = sorted(f.iterdir())
    except FileNotFoundError:
        children = []
    for p in children:
        if p.name == KEY_FILE:
            continue
        if p.name == HASH_MEMO and os.path.isfile(p) and not os.path.islink(p):
            size = _entry_bytes(p)
            p.unlink(missing_ok=True)
            removed.append(p.name)
            freed += size
            continue
        if _entry_kind(p) is None:
            kept.append(p.name)
            continue
        size = _entry_bytes(p)
        if _remove_entry(p):
            removed.append(p.name)
            freed += size
        else:
            kept.append(p.name)
    return {"folder": str(f), "removed": removed, "bytes": freed, "kept": kept}


def run_cache(args: Any) -> int:
    """``hsi-torch cache info | clear [--folder DIR]`` (:func:`cache_info`, :func:`clear_cache`)."""
    folder = getattr(args, "folder", None)
    if args.action == "clear":
        got = clear_cache(folder)
        n = sum(1 for name in got["removed"] if name != HASH_MEMO)
        print(f"{got['folder']}: removed {n} entr{'y' if n == 1 else 'ies'} "
              f"({got['bytes'] / 2**30:.2f} GiB)")  # fmt: skip
        if got["kept"]:
            print(f"  left alone (not written by the cache): {', '.join(got['kept'])}")
        return 0
    info = cache_info(folder)
    n = len(info["entries"])
    print(f"precomputation cache: {info['folder']}" + ("" if info["exists"] else " (not made yet)"))
    if info["problem"]:
        print(f"  not used: the folder {info['problem']}")
    print(f"  {n} entr{'y' if n == 1 else 'ies'}, {info['total_bytes'] / 2**30:.2f} GiB of at most "
          f"{info['max_bytes'] / 2**30:.1f} GiB (${MAX_GB_ENV})")  # fmt: skip
    for e in info["entries"]:
        used = time.strftime("%Y-%m-%d %H:%M", time.localtime(e["last_used"]))
        print(
            f"  {e['name']}  {e['bytes'] / 2**30:.2f} GiB  last used {used}"
            + ("  (format 1: unused, 'clear' removes it)" if e["format"] == 1 else "")
        )
    return 0
