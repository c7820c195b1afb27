"""On-disk cache of the per-bundle precomputation, keyed by content, safe to load.

The per-bundle precomputation (:func:`hsi_torch.recon.sensing.precompute_sensing`: the sensing
model of the valid pixels, the static masks, the sampling grid and the solver's per-pixel
factorisation) costs seconds at full size. It depends only on the bundle file's content, on
``(beta, diff_order)``, on the precision and the device type, and on the code that computes it,
so a process can store it once and every later process (a second run, a Dask worker, a notebook
restarted) loads it instead.

**What is stored.** One file per entry (``<bundle stem>-<key>.hsicache``): a JSON header and
named numeric arrays (the caller decides which: this module stores and returns a
``{name: array}`` dict and does not care about the layout of the solver's factors). The file is
the magic line :data:`MAGIC`, the header's length and CRC-32 (little-endian ``uint64``,
``uint32``), the header — ``format``, ``key``, ``arrays`` (per array: ``dtype``, ``shape``,
``offset``, ``crc32``) and whatever else the caller records — then the raw C-order bytes of every
array at an offset that is a multiple of :data:`ALIGN` (so the memory-mapped data is aligned as a
fresh allocation is, and the kernels that read it take the same paths). It is written atomically
(:func:`hsi_torch.io.atomic.atomic_write`: a reader sees the whole file or none) and never over
an input: entries live in a cache folder, never over the bundle.

**The key** (:func:`entry_key`) is the SHA-256 of a JSON object holding the caller's parts (the
bundle file's SHA-256, ``beta``, ``diff_order``, dtype, device type, which factorisation — the
compiled CPU pass or the torch kernels), this module's
:data:`FORMAT_VERSION`, the caller's layout version, the torch version, and a digest of the
source files that compute the precomputation (:data:`SOURCE_FILES`): editing the solver's
factorisation therefore misses every old entry by itself.

**Loading is safe** (:func:`load_entry`): nothing is unpickled or evaluated — the header is JSON,
the arrays raw numbers of plain dtypes (booleans, integers, floats; anything else refused); the
header's CRC-32 must match, the recorded key must equal the key asked for (a foreign file, a
renamed one), every array must lie inside the file (a truncated one), and every array's CRC-32 is
recomputed over its bytes (an altered or damaged file). Any failure is a *miss*: a
:class:`PrecomputeCacheWarning` names the file and the reason, and the caller recomputes (and
replaces the entry). The arrays come back memory-mapped copy-on-write (``numpy.memmap`` mode
``"c"``): their pages are shared with the page cache and the file never changes.

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
import stat
import struct
import sys
import threading
import warnings
import zlib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from hsi_torch.io.atomic import atomic_write, atomic_write_text, human_size, json_default

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
    "release_pages",
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
    "recon/nnls/_compiled.py",
    "recon/nnls/constants.py",
    "recon/nnls/kkt.py",
    "recon/nnls/_threads.py",
    "recon/spatial/problem.py",
    "recon/spatial/_compiled.py",
)
#: Counts of this process: ``hits``, ``misses`` (no entry), ``rejected`` (an entry refused:
#: foreign, corrupt, unreadable), ``writes``, ``write_skipped`` (no space, not writable).
CACHE_STATS: dict[str, int] = {"hits": 0, "misses": 0, "rejected": 0, "writes": 0,
                               "write_skipped": 0}  # fmt: skip

#: First bytes of an entry file.
MAGIC = b"HSI_TORCH_PRECOMPUTE\n"
#: Arrays start at multiples of this many bytes (memory-mapped data aligned as freshly allocated).
ALIGN = 64
#: Largest header accepted, bytes.
MAX_HEADER_BYTES = 16 << 20
#: The dtypes an entry may hold: plain booleans, integers, floats and complex numbers.
_DTYPE_RE = re.compile(r"[<>|=]?(b1|[iu][1248]|f[248]|c(8|16))")
_ENTRY_RE = re.compile(r"^.+-[0-9a-f]{24}\.hsicache$")
_LOCK = threading.Lock()
_SOURCE_DIGEST: list[str] = []
#: (realpath, device, inode, size, mtime_ns, ctime_ns) -> hex SHA-256 of the file's content
_HASHES: dict[tuple[str, int, int, int, int, int], str] = {}
#: File of a cache folder remembering the SHA-256 of the bundles seen (by file identity).
HASH_MEMO = "bundle_hashes.json"


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
    """``<folder>/<bundle stem>-<first 24 hex digits of key>.hsicache``."""
    stem = re.sub(r"[^A-Za-z0-9_.-]", "_", Path(bundle_path).stem)[:48] or "bundle"
    return Path(folder) / f"{stem}-{key[:24]}.hsicache"


def _hash_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(1 << 22):
            h.update(block)
    return h.hexdigest()


def content_sha256(path: str | os.PathLike, memo_folder: str | os.PathLike | None = None) -> str:
    """Hex SHA-256 of a file's content, remembered while the file's identity stays the same.

    The identity is the resolved path, device, inode, size, modification *and change* time
    (``st_ctime_ns``: set by the system on every write or metadata change, never by a user), so
    a rewritten or edited file is always hashed again. Remembered in this process, and, with
    ``memo_folder``, in its ``bundle_hashes.json`` (:data:`HASH_MEMO`) for later processes: a
    second process then reads no byte of an unchanged bundle.
    """
    p = Path(path)
    st = p.stat()
    ident = (str(p.resolve()), st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)
    sha = _HASHES.get(ident)
    if sha is not None:
        return sha
    memo_path = None if memo_folder is None else Path(memo_folder) / HASH_MEMO
    memo: dict[str, str] = {}
    if memo_path is not None and memo_path.is_file():
        try:
            got = json.loads(memo_path.read_text("utf-8"))
            memo = {str(k): str(v) for k, v in got.items()} if isinstance(got, dict) else {}
        except (OSError, ValueError):
            memo = {}
    text = json.dumps(ident)
    sha = memo.get(text)
    if sha is None or not re.fullmatch(r"[0-9a-f]{64}", sha):
        sha = _hash_file(p)
        if memo_path is not None:
            memo = dict(list(memo.items())[-255:])
            memo[text] = sha
            try:
                atomic_write_text(memo_path, json.dumps(memo, indent=0))
            except OSError:
                pass  # a read-only folder: hashed again next time
    if len(_HASHES) > 64:
        _HASHES.clear()
    _HASHES[ident] = sha
    return sha


# ---------------------------------------------------------------------------------- reading


class _Refused(Exception):
    """An entry that must not be used (the message says why)."""


def _aligned(n: int) -> int:
    return -(-n // ALIGN) * ALIGN


def _crc32(buf: Any) -> int:
    """CRC-32 of a buffer, in 64 MiB steps (zlib releases the GIL on each)."""
    mv = memoryview(buf).cast("B")
    c, step = 0, 1 << 26
    for s in range(0, len(mv), step):
        c = zlib.crc32(mv[s:s + step], c)
    return c


def _check_arrays(table: Any, size: int, start: int) -> dict[str, tuple[np.dtype, tuple, int, int]]:
    """The array table of a header, checked: ``{name: (dtype, shape, offset, crc)}``."""
    if not isinstance(table, dict):
        raise _Refused("'arrays' is not an object")
    out: dict[str, tuple[np.dtype, tuple, int, int]] = {}
    for name, d in table.items():
        if not isinstance(d, dict) or not isinstance(d.get("dtype"), str):
            raise _Refused(f"array {name!r}: no dtype")
        if not _DTYPE_RE.fullmatch(d["dtype"]):
            raise _Refused(f"array {name!r} has dtype {d['dtype']!r} (plain numbers only)")
        dt = np.dtype(d["dtype"])
        shape, off, crc = d.get("shape"), d.get("offset"), d.get("crc32")
        if not (isinstance(shape, list) and all(type(v) is int and v >= 0 for v in shape)
                and type(off) is int and type(crc) is int):  # fmt: skip
            raise _Refused(f"array {name!r}: bad shape, offset or checksum")
        nbytes = int(np.prod(shape, dtype=np.int64)) * dt.itemsize
        if off % ALIGN or off < start or off + nbytes > size:
            raise _Refused(f"array {name!r}: bytes {off}..{off + nbytes} outside the file's "
                           f"{size} bytes (truncated?)")  # fmt: skip
        out[str(name)] = (dt, tuple(shape), off, crc)
    return out


def _read_entry(path: Path, key: str) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(len(MAGIC) + 12)
        if len(head) < len(MAGIC) + 12 or head[:len(MAGIC)] != MAGIC:
            raise _Refused("not a precomputation cache entry (no magic bytes)")
        length, crc = struct.unpack("<QI", head[len(MAGIC):])
        if length > MAX_HEADER_BYTES or len(MAGIC) + 12 + length > size:
            raise _Refused(f"header of {length} bytes")
        text = f.read(length)
    if zlib.crc32(text) != crc:
        raise _Refused("the header's CRC-32 differs (the file was altered or damaged)")
    meta = json.loads(text.decode("utf-8"))
    if not isinstance(meta, dict):
        raise _Refused("the header is not a JSON object")
    if meta.get("format") != FORMAT_VERSION:
        raise _Refused(f"format {meta.get('format')!r}, this software reads {FORMAT_VERSION}")
    if meta.get("key") != key:
        raise _Refused("it was made for another bundle, settings or software (key differs)")
    table = _check_arrays(meta.get("arrays"), size, len(MAGIC) + 12 + length)
    arrays: dict[str, np.ndarray] = {}
    for name, (dt, shape, off, _crc) in table.items():
        n = int(np.prod(shape, dtype=np.int64))
        arrays[name] = (np.memmap(path, dtype=dt, mode="c", offset=off, shape=shape) if n
                        else np.zeros(shape, dtype=dt))  # fmt: skip
    bad: list[str] = []

    def check(part: list[str]) -> None:
        """Each array's CRC-32 against the header's (two threads share the arrays)."""
        for n in part:
            a = arrays[n]
            if (_crc32(a.reshape(-1).view(np.uint8)) if a.size else 0) != table[n][3]:
                bad.append(n)

    order = sorted(arrays, key=lambda n: -arrays[n].nbytes)
    threads = [threading.Thread(target=check, args=(part,))
               for part in (order[0::2], order[1::2]) if part]  # fmt: skip
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
    except (_Refused, OSError, ValueError, UnicodeDecodeError, struct.error,
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


def _write(f: Any, header: dict[str, Any], arrays: Mapping[str, np.ndarray]) -> None:
    """The entry's bytes: magic, header length and CRC-32, the JSON header (padded with spaces),
    then every array at a multiple of :data:`ALIGN` bytes."""
    room = 4096
    while True:
        start = _aligned(len(MAGIC) + 12 + room)
        pos = start
        for n, a in arrays.items():
            header["arrays"][n]["offset"] = pos
            pos = _aligned(pos + a.nbytes)
        text = json.dumps(header, default=json_default).encode("utf-8")
        if len(MAGIC) + 12 + len(text) <= start:
            break
        room = 2 * len(text)
    text += b" " * (start - len(MAGIC) - 12 - len(text))
    f.write(MAGIC + struct.pack("<QI", len(text), zlib.crc32(text)) + text)
    pos = start
    for n, a in arrays.items():
        off = header["arrays"][n]["offset"]
        f.write(b"\0" * (off - pos))
        if a.size:
            f.write(memoryview(a.reshape(-1).view(np.uint8)))
        pos = off + a.nbytes


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
        if not re.fullmatch(r"[A-Za-z0-9_.-]+", n):
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
    flat = {n: np.ascontiguousarray(a) for n, a in arrays.items()}
    header = {**dict(meta or {}), "format": FORMAT_VERSION, "key": key,
              "arrays": {n: {"dtype": a.dtype.str, "shape": list(a.shape),
                             "crc32": _crc32(a.reshape(-1).view(np.uint8)) if a.size else 0}
                         for n, a in flat.items()}}  # fmt: skip
    with _LOCK:
        try:
            p.parent.mkdir(parents=True, exist_ok=True)
            free = shutil.disk_usage(p.parent).free
            if free - nbytes < MIN_FREE_BYTES:
                CACHE_STATS["write_skipped"] += 1
                _warn(f"precomputation cache: {human_size(free)} free in {p.parent}, the "
                      f"entry needs {human_size(nbytes)}; not written")
                return False
            with atomic_write(p, "wb", fsync=False) as f:  # checked (CRC-32) when read
                _write(f, header, flat)
            _evict(p.parent, p, limit)
        except OSError as exc:
            CACHE_STATS["write_skipped"] += 1
            _warn(f"precomputation cache: could not write {p} ({exc}); not cached")
            return False
    CACHE_STATS["writes"] += 1
    return True
