"""On-disk cache of the per-bundle precomputation, keyed by content, safe to load.

The per-bundle precomputation (:func:`hsi_torch.recon.sensing.precompute_sensing`: the sensing
model of the valid pixels, the static masks, the sampling grid and the solver's per-pixel
factorisation) costs seconds at full size. It depends only on the bundle file's content, on
``(beta, diff_order)``, on the precision and the device type, and on the code that computes it,
so a process can store it once and every later process (a second run, a Dask worker, a notebook
restarted) loads it instead.

**What is stored.** One file per entry: an uncompressed ``.npz`` of named numeric arrays (the
caller decides which: this module stores and returns a ``{name: array}`` dict and does not care
about the layout of the solver's factors) plus ``__meta__``, a JSON string with the key, the
arrays' names and anything else the caller records. It is written atomically
(:func:`hsi_torch.io.atomic.atomic_write`: a reader sees the whole file or none) and never over
an input: entries live in a cache folder, never over the bundle.

**The key** (:func:`entry_key`) is the SHA-256 of a JSON object holding the caller's parts (the
bundle file's SHA-256, ``beta``, ``diff_order``, dtype, device type, the number of pixels), this
module's :data:`FORMAT_VERSION`, the caller's layout version, the torch version, and a digest of
the source files that compute the precomputation (:data:`SOURCE_FILES`): editing the solver's
factorisation therefore misses every old entry by itself.

**Loading is safe** (:func:`load_entry`): no pickle (``allow_pickle`` never set; object arrays
refused); the members must be stored uncompressed, of a numeric or bool dtype, with the sizes the
zip directory declares; the recorded key must equal the key asked for (a foreign file, a renamed
one); the CRC-32 the zip directory records for every member is recomputed over the data (a
truncated or altered file). Any failure is a *miss*: a :class:`PrecomputeCacheWarning` names the
file and the reason, and the caller recomputes (and replaces the entry). The arrays come back
memory-mapped copy-on-write (``numpy.memmap`` mode ``"c"``): their pages are shared with the page
cache and the file never changes.

**Where** (:func:`cache_folder`, the reconstruction setting ``precompute_cache``):

- ``"auto"`` (default): the user cache folder, ``$HSI_TORCH_CACHE``, else
  ``$XDG_CACHE_HOME/hsi_torch``, else ``~/.cache/hsi_torch``, subfolder ``precompute/``;
- ``"beside"``: a folder ``.hsi_torch_cache/`` beside the bundle (falls back to the user cache
  folder, with a note, where the bundle's folder is not writable);
- ``"off"``: no cache;
- a folder path: that folder (the user cache folder, with a note, when it cannot be written).

The folder is bounded: after a write the least recently used entries (file modification time,
refreshed on every hit) are removed until the entries take at most ``$HSI_TORCH_CACHE_MAX_GB``
GiB (default :data:`DEFAULT_MAX_GB`). An entry is not written when the disk would keep less than
:data:`MIN_FREE_BYTES` free.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import struct
import threading
import warnings
import zipfile
import zlib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from hsi_torch.io.atomic import atomic_write, json_default

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
    "entry_key",
    "entry_path",
    "content_sha256",
    "load_entry",
    "save_entry",
]

#: Version of the entry file format (this module); part of every key.
FORMAT_VERSION = 1
#: The named policies of the ``precompute_cache`` setting (anything else is a folder path).
POLICIES = ("auto", "beside", "off")
#: Environment variable naming the user cache folder (entries go to its ``precompute/``).
CACHE_ENV = "HSI_TORCH_CACHE"
#: Environment variable bounding the size of one cache folder, GiB.
MAX_GB_ENV = "HSI_TORCH_CACHE_MAX_GB"
#: Default bound of a cache folder, GiB (one full-size float32 entry is about 2.1 GiB).
DEFAULT_MAX_GB = 16.0
#: An entry is not written when the disk would keep less than this free, bytes.
MIN_FREE_BYTES = 2 << 30
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
    "recon/nnls/kkt.py",
    "recon/nnls/_threads.py",
)
#: Counts of this process: ``hits``, ``misses`` (no entry), ``rejected`` (an entry refused:
#: foreign, corrupt, unreadable), ``writes``, ``write_skipped`` (no space, not writable).
CACHE_STATS: dict[str, int] = {"hits": 0, "misses": 0, "rejected": 0, "writes": 0,
                               "write_skipped": 0}  # fmt: skip

_META = "__meta__"
_ENTRY_RE = re.compile(r"^.+-[0-9a-f]{24}\.npz$")
_LOCK = threading.Lock()
_SOURCE_DIGEST: list[str] = []
#: (realpath, device, inode, size, mtime_ns) -> hex SHA-256 of the file's content
_HASHES: dict[tuple[str, int, int, int, int], str] = {}


class PrecomputeCacheWarning(UserWarning):
    """An entry of the precomputation cache was refused or could not be written (the
    reconstruction goes on: it recomputes, or keeps what it computed)."""


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


def cache_folder(
    policy: str | os.PathLike | None, bundle_path: str | os.PathLike | None
) -> tuple[Path | None, str | None]:
    """The folder of the entries for a ``precompute_cache`` setting.

    Args:
        policy: ``"auto"``, ``"beside"``, ``"off"`` or a folder path (``None``: ``"off"``).
        bundle_path: the bundle file (``None``: an in-memory bundle, which is never cached).

    Returns:
        ``(folder, note)``: the folder (``None``: no cache) and, when the setting could not be
        followed as given, why (a sentence) — e.g. ``"beside"`` for a read-only bundle folder
        falls back to the user cache folder.
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
    if _writable_folder(want):
        return want, None
    if want != user and _writable_folder(user):
        return user, (f"precomputation cache folder {want} is not writable: using the user "
                      f"cache folder {user}")  # fmt: skip
    return None, f"precomputation cache folder {want} is not writable: no cache"


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
    """``<folder>/<bundle stem>-<first 24 hex digits of key>.npz``."""
    stem = re.sub(r"[^A-Za-z0-9_.-]", "_", Path(bundle_path).stem)[:48] or "bundle"
    return Path(folder) / f"{stem}-{key[:24]}.npz"


def content_sha256(path: str | os.PathLike) -> str:
    """Hex SHA-256 of a file's content, remembered in this process while the file's identity,
    size and modification time stay the same (a bundle read again by the same process is not
    hashed again)."""
    p = Path(path)
    st = p.stat()
    ident = (str(p.resolve()), st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)
    sha = _HASHES.get(ident)
    if sha is None:
        h = hashlib.sha256()
        with open(p, "rb") as f:
            while block := f.read(1 << 22):
                h.update(block)
        sha = h.hexdigest()
        if len(_HASHES) > 64:
            _HASHES.clear()
        _HASHES[ident] = sha
    return sha


# ---------------------------------------------------------------------------------- reading


class _Refused(Exception):
    """An entry that must not be used (the message says why)."""


def _data_offset(f: Any, info: zipfile.ZipInfo) -> int:
    """Offset of a stored member's data: after its local header (which has its own name and
    extra-field lengths)."""
    f.seek(info.header_offset)
    head = f.read(30)
    if len(head) != 30 or head[:4] != b"PK\x03\x04":
        raise _Refused(f"member {info.filename!r}: bad local header")
    n, e = struct.unpack("<HH", head[26:30])
    return info.header_offset + 30 + n + e


def _member_array(path: Path, f: Any, info: zipfile.ZipInfo) -> tuple[np.ndarray, int]:
    """A stored ``.npy`` member memory-mapped copy-on-write, and its expected CRC-32."""
    if info.compress_type != zipfile.ZIP_STORED:
        raise _Refused(f"member {info.filename!r} is compressed")
    start = _data_offset(f, info)
    f.seek(start)
    version = np.lib.format.read_magic(f)
    if version == (1, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_1_0(f)
    elif version in ((2, 0), (3, 0)):
        shape, fortran, dtype = np.lib.format.read_array_header_2_0(f)
    else:
        raise _Refused(f"member {info.filename!r}: npy version {version}")
    if dtype.hasobject or dtype.kind not in "biufc":
        raise _Refused(f"member {info.filename!r} has dtype {dtype} (numbers only)")
    offset = f.tell()
    nbytes = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    if offset - start + nbytes != info.file_size:
        raise _Refused(f"member {info.filename!r}: {info.file_size} bytes declared, its header "
                       f"says {offset - start + nbytes}")  # fmt: skip
    if nbytes == 0:
        return np.zeros(shape, dtype=dtype), info.CRC
    mm = np.memmap(path, dtype=dtype, mode="c", offset=offset, shape=tuple(shape),
                   order="F" if fortran else "C")  # fmt: skip
    return mm, info.CRC


def _read_entry(path: Path, key: str) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    if not zipfile.is_zipfile(path):
        raise _Refused("not a zip archive")
    size = path.stat().st_size
    with zipfile.ZipFile(path) as zf, open(path, "rb") as f:
        infos = {i.filename: i for i in zf.infolist()}
        mi = infos.get(_META + ".npy")
        if mi is None:
            raise _Refused(f"no {_META} member")
        if mi.file_size > 16 << 20:
            raise _Refused(f"{_META} is {mi.file_size} bytes")
        for i in infos.values():
            if i.header_offset + i.file_size > size:
                raise _Refused(f"member {i.filename!r} runs past the end of the file (truncated)")
        with zf.open(mi) as m:  # zipfile checks this member's CRC itself
            raw = np.lib.format.read_array(m, allow_pickle=False)
        if raw.ndim != 0 or raw.dtype.kind != "U":
            raise _Refused(f"{_META} is not a JSON string")
        meta = json.loads(str(raw))
        if not isinstance(meta, dict):
            raise _Refused(f"{_META} is not a JSON object")
        if meta.get("format") != FORMAT_VERSION:
            raise _Refused(f"format {meta.get('format')!r}, this software reads {FORMAT_VERSION}")
        if meta.get("key") != key:
            raise _Refused("it was made for another bundle, settings or software (key differs)")
        names = meta.get("arrays")
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise _Refused(f"{_META} 'arrays' is not a list of names")
        members = {n + ".npy" for n in names} | {_META + ".npy"}
        if set(infos) != members:
            odd = sorted(set(infos) ^ members)[:5]
            raise _Refused(f"members differ from the recorded arrays: {odd}")
        arrays: dict[str, np.ndarray] = {}
        spans: dict[str, tuple[int, int, int]] = {}
        for n in names:
            info = infos[n + ".npy"]
            arrays[n], crc = _member_array(path, f, info)
            spans[n] = (_data_offset(f, info), info.file_size, crc)
    bad: list[str] = []

    def check(part: list[str]) -> None:
        """The CRC-32 of each member's stored bytes (its ``.npy`` header and data) against the
        zip directory's (zlib releases the GIL: two threads share the members)."""
        for n in part:
            start, length, crc = spans[n]
            try:
                raw = np.memmap(path, dtype=np.uint8, mode="r", offset=start, shape=(length,))
                c, step = 0, 1 << 26
                for s in range(0, length, step):
                    c = zlib.crc32(memoryview(raw[s:s + step]), c)
                del raw
            except (OSError, ValueError):
                c = None
            if c != crc:
                bad.append(n)

    order = sorted(arrays, key=lambda n: -spans[n][1])
    threads = [threading.Thread(target=check, args=(part,))
               for part in (order[0::2], order[1::2]) if part]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    if bad:
        raise _Refused(f"CRC-32 mismatch in {sorted(bad)} (the file was altered or damaged)")
    return arrays, meta


def load_entry(path: str | os.PathLike, key: str) -> tuple[dict[str, np.ndarray], dict] | None:
    """The arrays and metadata of the entry ``path`` if it holds ``key`` and is intact.

    Returns:
        ``({name: array}, meta)`` with the arrays memory-mapped copy-on-write, or ``None``:
        no entry (a miss), or an entry refused (foreign, altered, truncated, unreadable: a
        :class:`PrecomputeCacheWarning` names the file and why).
    """
    p = Path(path)
    if not p.is_file():
        CACHE_STATS["misses"] += 1
        return None
    try:
        arrays, meta = _read_entry(p, key)
    except (_Refused, OSError, ValueError, zipfile.BadZipFile, EOFError, struct.error,
            RecursionError) as exc:  # fmt: skip
        CACHE_STATS["rejected"] += 1
        _warn(f"precomputation cache entry {p} refused ({exc}); recomputing")
        return None
    CACHE_STATS["hits"] += 1
    try:
        os.utime(p)  # recently used: kept by the size bound
    except OSError:
        pass
    return arrays, meta


# ---------------------------------------------------------------------------------- writing


def _max_bytes() -> int:
    raw = os.environ.get(MAX_GB_ENV)
    try:
        gb = float(raw) if raw else DEFAULT_MAX_GB
    except ValueError:
        gb = DEFAULT_MAX_GB
    return int(max(gb, 0.0) * (1 << 30))


def _evict(folder: Path, keep: Path, limit: int) -> None:
    """Remove the least recently used entries of ``folder`` (not ``keep``) until the entries
    take at most ``limit`` bytes."""
    entries = []
    for p in folder.iterdir():
        if p.name.startswith(".") or not _ENTRY_RE.match(p.name) or p == keep:
            continue
        try:
            st = p.stat()
        except OSError:
            continue
        entries.append((st.st_mtime_ns, st.st_size, p))
    total = sum(e[1] for e in entries) + (keep.stat().st_size if keep.exists() else 0)
    for _mtime, size, p in sorted(entries):
        if total <= limit:
            break
        try:
            p.unlink()
            total -= size
        except OSError:
            pass


def save_entry(
    path: str | os.PathLike, key: str, arrays: Mapping[str, np.ndarray],
    meta: Mapping[str, Any] | None = None,
) -> bool:
    """Write an entry atomically (never over anything but an older entry of the same name).

    Args:
        path: the entry (from :func:`entry_path`); key: its key (:func:`entry_key`).
        arrays: ``{name: array}``, numeric or bool numpy arrays (names: letters, digits,
            ``_ . -``).
        meta: JSON-serialisable values stored beside the arrays (returned by
            :func:`load_entry`).

    Returns:
        Whether the entry was written. Not written (a :class:`PrecomputeCacheWarning` says why):
        the folder cannot be written, the disk would keep less than :data:`MIN_FREE_BYTES`
        free, an entry is larger than the folder's bound.
    """
    p = Path(path)
    for n, a in arrays.items():
        if not re.fullmatch(r"[A-Za-z0-9_.-]+", n) or n == _META:
            raise ValueError(f"cache array name {n!r}: letters, digits, '_', '.', '-' only")
        if a.dtype.hasobject or a.dtype.kind not in "biufc":
            raise TypeError(f"cache array {n!r} has dtype {a.dtype}: numbers only")
    nbytes = sum(int(a.nbytes) for a in arrays.values())
    limit = _max_bytes()
    if nbytes > limit:
        CACHE_STATS["write_skipped"] += 1
        _warn(f"precomputation cache: the entry for {p.name} ({nbytes / 2**30:.1f} GiB) exceeds "
              f"the folder's bound {limit / 2**30:.1f} GiB (${MAX_GB_ENV}); not written")
        return False
    text = json.dumps({**dict(meta or {}), "format": FORMAT_VERSION, "key": key,
                       "arrays": list(arrays)}, default=json_default)  # fmt: skip
    with _LOCK:
        try:
            p.parent.mkdir(parents=True, exist_ok=True)
            free = shutil.disk_usage(p.parent).free
            if free - nbytes < MIN_FREE_BYTES:
                CACHE_STATS["write_skipped"] += 1
                _warn(f"precomputation cache: {free / 2**30:.1f} GiB free in {p.parent}, the "
                      f"entry needs {nbytes / 2**30:.1f} GiB; not written")
                return False
            with atomic_write(p, "wb", fsync=False) as f:  # checked (CRC-32) when read
                np.savez(f, **{_META: np.array(text)}, **dict(arrays))
            _evict(p.parent, p, limit)
        except OSError as exc:
            CACHE_STATS["write_skipped"] += 1
            _warn(f"precomputation cache: could not write {p} ({exc}); not cached")
            return False
    CACHE_STATS["writes"] += 1
    return True
