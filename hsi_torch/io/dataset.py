"""One Zarr store for a whole run: every frame's cube in one chunked dataset.

``hsi-torch reconstruct --format zarr`` writes ``OUT/cubes.zarr`` instead of files per input. It is
a Zarr (format 2, consolidated metadata) group that ``xarray.open_zarr`` opens as a Dataset:

===========  ===========================  ========  ============  ================================
variable     dims                         dtype     chunk         meaning
===========  ===========================  ========  ============  ================================
cube         (frame, wavelength, y, x)    float32   (1, M, h, w)  the cube; NaN where invalid or
                                                                  not (yet) reconstructed
valid        (frame, y, x)                bool      (1, h, w)     pixel reconstructed
done         (frame,)                     bool      (1,)          the frame is complete
metadata     (frame,)                     str       (1,)          the frame's metadata (JSON, as
                                                                  in a cube file)
source       (frame,)  coordinate         str       (4096,)       the input file (absolute path)
wavelength   (wavelength,) coordinate     float64                 band centres, nm
y, x         coordinates                  int64                   reference-frame pixel indices
===========  ===========================  ========  ============  ================================

``cube`` is compressed with Zstandard (level 1: 0.1–0.2 s and 27–43 % of the raw 61 MiB for the
full-size demo's three scenes). The root attributes hold ``hsi_torch_dataset`` (layout version),
``wavelengths_nm``, ``frame_size`` and ``bundle``.

**Written concurrently, without a lock on the store.** One frame is one chunk of each variable,
so every frame's data are files of their own (``cube/<i>.0.0.0``, ``valid/<i>.0.0``,
``metadata/<i>``, ``done/<i>``), each written atomically (temporary file + rename) by whichever
process reconstructed the frame (:func:`write_frame`: encoded here by the Zarr v2 rules with
``numcodecs``, so the writers need no Zarr library). ``done`` is written last: a frame is complete
exactly when ``done`` is True, and a frame being redone has its ``done`` chunk removed first (by
:meth:`CubeDataset.mark_pending`). The array metadata (shapes, the frame list) are written only by
the run's driver (:meth:`CubeDataset.open`) before any frame is handed out, while it holds the
store's lock file (``.hsi_torch.lock``, one run per store at a time).

**Frames belong to inputs.** A frame index is given to each input (by absolute path) when it is
first added; a later run with more inputs appends frames, one with the same inputs reuses them
(resume: a frame whose ``done`` is True, made from the same input file and settings, is skipped;
see :class:`hsi_torch.recon.batch.targets.StoreTarget`).

**Read only with its own codecs.** Before a chunk is decoded, every array's compressor and filters
are checked against the codecs this module writes (:data:`STORE_CODECS`: Zstandard, and the
``vlen-utf8`` filter of the string arrays); a store that names any other codec (e.g. ``pickle``,
which runs code when it decodes) is refused with an error naming the array and the codec
(:func:`check_zarr_codecs`). Cube files written as ``<stem>.zarr`` by xarray are opened with the
wider list :data:`SAFE_CODECS` (numcodecs' compressors and filters that only decode data).

Reading::

    ds = xarray.open_zarr("out/cubes.zarr")
    ds.cube.isel(frame=0).sel(wavelength=550)      # (h, w)
    ds.cube.where(ds.done, drop=True)              # complete frames only
    json.loads(ds.metadata[0].values.item())       # one frame's metadata; its "findings":
                                                   # the frame's findings (Finding.to_dict list)
"""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from hsi_torch.errors import FileFormatError, InputError, require_packages
from hsi_torch.io.atomic import (
    atomic_write,
    atomic_write_text,
    json_default,
    lock_or_refuse,
    mark_lock_holder,
    open_own_file,
    remove_file,
)
from hsi_torch.io.bounded import check_store_files, read_json_bounded
from hsi_torch.io.cube import _nan_where_invalid, _np
from hsi_torch.io.safety import short_repr
from hsi_torch.io.zarr_codecs import (
    SAFE_CODECS,
    STORE_CODECS,
    check_array_meta,
    check_zarr_codecs,
)

__all__ = [
    "CubeDataset",
    "write_frame",
    "open_dataset",
    "DATASET_NAME",
    "DATASET_VERSION",
    "require_dataset_packages",
    "check_zarr_codecs",
    "STORE_CODECS",
    "SAFE_CODECS",
]

#: The store's name inside a run's output folder.
DATASET_NAME = "cubes.zarr"
#: Layout version (root attribute ``hsi_torch_dataset``).
DATASET_VERSION = 1
SOURCE_CHUNK = 4096
_LOCK_NAME = ".hsi_torch.lock"
_FRAME_VARS = ("cube", "valid", "done", "metadata", "source")
#: Every array of the store: the frames' and the coordinates.
_ARRAYS = (*_FRAME_VARS, "wavelength", "y", "x")
_HINT = "pip install 'hsi-torch[cluster]'"


def require_dataset_packages(read: bool = False) -> None:
    """Check that ``numcodecs`` (writing; comes with ``zarr``) and, with ``read``, ``xarray``
    and ``zarr`` are installed.

    Raises:
        ModuleNotFoundError: one is missing (the message says what to install).
    """
    require_packages(("numcodecs",) + (("xarray", "zarr") if read else ()),
                     "the Zarr dataset store", _HINT)  # fmt: skip


def _codec(config: dict[str, Any] | None):
    if config is None:
        return None
    cid = config.get("id") if isinstance(config, dict) else None
    if cid not in STORE_CODECS:  # every metadata was checked; never decode with another codec
        raise FileFormatError(f"refusing to use the codec {short_repr(cid, 60)}: the dataset "
                              "store is read only with "
                              f"{', '.join(sorted(STORE_CODECS))}")  # fmt: skip
    import numcodecs  # lazy: optional dependency (comes with zarr, the cluster extra)

    return numcodecs.get_codec(dict(config))


def _encode(meta: dict[str, Any], data: np.ndarray) -> bytes:
    """One chunk's bytes by the Zarr v2 rules: C order, the filters in turn, the compressor."""
    obj = meta["dtype"] == "|O"
    buf: Any = np.ascontiguousarray(data, dtype=object if obj else np.dtype(meta["dtype"]))
    if tuple(buf.shape) != tuple(meta["chunks"]):
        raise ValueError(f"chunk shape {buf.shape} != {tuple(meta['chunks'])}")
    for f in meta.get("filters") or []:
        buf = _codec(f).encode(buf)
    comp = _codec(meta.get("compressor"))
    if comp is not None:
        buf = comp.encode(buf)
    return bytes(buf) if not isinstance(buf, bytes) else buf


def _decode(meta: dict[str, Any], raw: bytes) -> np.ndarray:
    comp = _codec(meta.get("compressor"))
    buf: Any = comp.decode(raw) if comp is not None else raw
    for f in reversed(meta.get("filters") or []):
        buf = _codec(f).decode(buf)
    if meta["dtype"] == "|O":
        return np.asarray(buf, dtype=object).reshape(meta["chunks"])
    return np.frombuffer(buf, dtype=np.dtype(meta["dtype"])).reshape(meta["chunks"])


def _chunk_key(name: str, index: int, ndim: int) -> str:
    return f"{name}/" + ".".join([str(index)] + ["0"] * (ndim - 1))


def _array_meta(
    shape: Sequence[int], chunks: Sequence[int], dtype: str, fill: Any,
    compressor: dict[str, Any] | None = None, filters: list[dict[str, Any]] | None = None,
) -> dict[str, Any]:  # fmt: skip
    return {
        "zarr_format": 2, "shape": list(shape), "chunks": list(chunks), "dtype": dtype,
        "fill_value": fill, "order": "C", "filters": filters, "compressor": compressor,
        "dimension_separator": ".",
    }  # fmt: skip


_ZSTD = {"id": "zstd", "level": 1}
#: each array's dtype, compressor id and filter ids in this layout
_LAYOUT_CODECS: dict[str, tuple[str, str | None, list[str]]] = {
    "cube": ("<f4", "zstd", []), "valid": ("|b1", "zstd", []), "done": ("|b1", None, []),
    "metadata": ("|O", "zstd", ["vlen-utf8"]), "source": ("|O", "zstd", ["vlen-utf8"]),
    "wavelength": ("<f8", None, []), "y": ("<i8", None, []), "x": ("<i8", None, []),
}  # fmt: skip
_VLEN = [{"id": "vlen-utf8"}]


class CubeDataset:
    """The run driver's handle on a store (creates it, adds frames, tracks what is done).

    Use :meth:`open` (under the store's lock, see the module docstring); frames are written by
    :func:`write_frame`, in any process that sees the store's folder.

    Attributes:
        path: the store's folder.
        index: absolute input path → frame index.
        wavelengths_nm, frame_size: as in the root attributes.
    """

    def __init__(self, path: Path, lock_fd: int) -> None:
        self.path = path
        self._lock_fd = lock_fd
        self.attrs: dict[str, Any] = {}
        self.meta: dict[str, dict[str, Any]] = {}
        self._var_attrs: dict[str, dict[str, Any]] = {}
        self.index: dict[str, int] = {}
        self.wavelengths_nm: list[float] = []
        self.frame_size: tuple[int, int] = (0, 0)

    # --- opening -------------------------------------------------------------------------
    @classmethod
    @contextlib.contextmanager
    def open(
        cls,
        path: str | os.PathLike,
        sources: Sequence[str | os.PathLike],
        wavelengths_nm: Sequence[float],
        frame_size: tuple[int, int],
        attrs: dict[str, Any] | None = None,
    ) -> Iterator[CubeDataset]:
        """Create the store at ``path`` or open an existing one, make sure every input of
        ``sources`` has a frame (new ones are appended), and hold the store's lock until the
        ``with`` block ends.

        Raises:
            InputError: another run holds the store, or the store was made for another
                wavelength grid or frame size (another bundle).
            FileFormatError: ``path`` exists but is not a store of this layout.
        """
        p = Path(path)
        _refuse_foreign_folder(p)
        p.mkdir(parents=True, exist_ok=True)
        fd = _lock(p)
        try:
            ds = cls(p, fd)
            if (p / ".zgroup").is_file():
                ds._load()
                ds._check(wavelengths_nm, frame_size)
            else:
                ds._create(wavelengths_nm, frame_size, attrs or {})
            ds._add_sources([os.path.abspath(s) for s in sources])
            yield ds
        finally:
            os.close(fd)  # releases the lock

    def _create(
        self, wavelengths_nm: Sequence[float], frame_size: tuple[int, int], attrs: dict[str, Any]
    ) -> None:
        wl = np.asarray(wavelengths_nm, dtype=np.float64)
        h, w = (int(v) for v in frame_size)
        m = int(wl.size)
        self.attrs = {
            "hsi_torch_dataset": DATASET_VERSION,
            "description": "hsi_torch spectral cubes, one frame per input (see 'done')",
            "wavelengths_nm": wl.tolist(),
            "wavelength_units": "nm",
            "frame_size": [h, w],
            **attrs,
        }
        self.meta = {
            "cube": _array_meta([0, m, h, w], [1, m, h, w], "<f4", "NaN", _ZSTD),
            "valid": _array_meta([0, h, w], [1, h, w], "|b1", None, _ZSTD),
            "done": _array_meta([0], [1], "|b1", None),
            "metadata": _array_meta([0], [1], "|O", None, _ZSTD, _VLEN),
            "source": _array_meta([0], [SOURCE_CHUNK], "|O", None, _ZSTD, _VLEN),
            "wavelength": _array_meta([m], [m], "<f8", "NaN"),
            "y": _array_meta([h], [h], "<i8", None),
            "x": _array_meta([w], [w], "<i8", None),
        }
        self._var_attrs = {
            "cube": {"_ARRAY_DIMENSIONS": ["frame", "wavelength", "y", "x"],
                     "long_name": "spectral cube (reflectance relative to the white reference)",
                     "coordinates": "source"},
            "valid": {"_ARRAY_DIMENSIONS": ["frame", "y", "x"],
                      "long_name": "pixel reconstructed (>= min_views views)"},
            "done": {"_ARRAY_DIMENSIONS": ["frame"],
                     "long_name": "frame complete (its cube, valid mask and metadata written)"},
            "metadata": {"_ARRAY_DIMENSIONS": ["frame"],
                         "long_name": "the frame's metadata, JSON"},
            "source": {"_ARRAY_DIMENSIONS": ["frame"], "long_name": "input file"},
            "wavelength": {"_ARRAY_DIMENSIONS": ["wavelength"], "units": "nm",
                           "long_name": "band centre wavelength"},
            "y": {"_ARRAY_DIMENSIONS": ["y"], "units": "pixel",
                  "long_name": "reference-frame row"},
            "x": {"_ARRAY_DIMENSIONS": ["x"], "units": "pixel",
                  "long_name": "reference-frame column"},
        }  # fmt: skip
        for name, meta in self.meta.items():
            (self.path / name).mkdir(exist_ok=True)
            _write_json(self.path / name / ".zarray", meta)
            _write_json(self.path / name / ".zattrs", self._var_attrs[name])
        self._write_chunk("wavelength", 0, wl)
        self._write_chunk("y", 0, np.arange(h, dtype=np.int64))
        self._write_chunk("x", 0, np.arange(w, dtype=np.int64))
        _write_json(self.path / ".zattrs", self.attrs)
        self._write_metadata()
        # written last: a folder without it is not a store (an interrupted creation is redone)
        _write_json(self.path / ".zgroup", {"zarr_format": 2})
        self.wavelengths_nm = wl.tolist()
        self.frame_size = (h, w)

    def _load(self) -> None:
        try:
            self.attrs = _read_json(self.path / ".zattrs")
            self.meta = {n: _read_json(self.path / n / ".zarray") for n in _ARRAYS}
            self._var_attrs = {n: _read_json(self.path / n / ".zattrs") for n in self.meta}
        except (OSError, ValueError) as exc:
            raise FileFormatError(
                f"{self.path}: not a hsi_torch dataset store ({exc}); write into another folder"
            ) from None
        for name, meta in self.meta.items():  # before any chunk is decoded
            check_array_meta(meta, name, self.path)
        self._check_layout()
        if self.attrs.get("hsi_torch_dataset") != DATASET_VERSION:
            raise FileFormatError(
                f"{self.path}: not a hsi_torch dataset store of layout version {DATASET_VERSION} "
                f"(attribute hsi_torch_dataset = {self.attrs.get('hsi_torch_dataset')!r})"
            )
        self.wavelengths_nm = [float(x) for x in self.attrs.get("wavelengths_nm", [])]
        self.frame_size = tuple(int(v) for v in self.attrs.get("frame_size", (0, 0)))  # type: ignore[assignment]
        n = int(self.meta["source"]["shape"][0])
        names: list[str] = []
        for k in range(0, n, SOURCE_CHUNK):
            chunk = self._read_chunk("source", k // SOURCE_CHUNK)
            names += [str(s) for s in chunk[: min(SOURCE_CHUNK, n - k)]]
        self.index = {s: i for i, s in enumerate(names) if s}

    def _check_layout(self) -> None:
        """The arrays' shapes and chunks are this layout's (from the root attributes), before
        any chunk is read."""
        wl, fs = self.attrs.get("wavelengths_nm"), self.attrs.get("frame_size")
        ok = (isinstance(wl, list) and all(isinstance(v, (int, float)) and not isinstance(
            v, bool) for v in wl) and isinstance(fs, list) and len(fs) == 2 and all(
            type(v) is int and v > 0 for v in fs))  # fmt: skip
        if not ok:
            raise FileFormatError(f"{self.path}: root attributes wavelengths_nm / frame_size are "
                                  "not a list of numbers / [h, w]")  # fmt: skip
        m, (h, w) = len(wl), fs
        n = self.meta["done"].get("shape")
        n = n[0] if isinstance(n, list) and len(n) == 1 and type(n[0]) is int else -1
        expect = {
            "cube": ([n, m, h, w], [1, m, h, w]), "valid": ([n, h, w], [1, h, w]),
            "done": ([n], [1]), "metadata": ([n], [1]), "source": ([n], [SOURCE_CHUNK]),
            "wavelength": ([m], [m]), "y": ([h], [h]), "x": ([w], [w]),
        }  # fmt: skip
        for name, (shape, chunks) in expect.items():
            meta = self.meta[name]
            if n < 0 or meta.get("shape") != shape or meta.get("chunks") != chunks:
                raise FileFormatError(
                    f"{self.path}: array {name!r} has shape "
                    f"{short_repr(meta.get('shape'), 60)} and chunks "
                    f"{short_repr(meta.get('chunks'), 60)}, not this layout's {shape} and "
                    f"{chunks} (frames, {m} bands, {h}x{w} frames)")
            if meta.get("order", "C") != "C":
                raise FileFormatError(f"{self.path}: array {name!r} is not in C order")
            dtype, comp, filters = _LAYOUT_CODECS[name]
            got = (meta.get("dtype"), (meta.get("compressor") or {}).get("id"),
                   [f.get("id") for f in meta.get("filters") or []])
            if got != (dtype, comp, filters):
                raise FileFormatError(
                    f"{self.path}: array {name!r} has dtype, compressor and filters "
                    f"{short_repr(got, 60)}, not this layout's {(dtype, comp, filters)}")

    def _check(self, wavelengths_nm: Sequence[float], frame_size: tuple[int, int]) -> None:
        wl = [float(x) for x in wavelengths_nm]
        if len(wl) != len(self.wavelengths_nm) or not np.allclose(wl, self.wavelengths_nm):
            raise InputError(
                f"{self.path}: the store holds cubes of {len(self.wavelengths_nm)} bands "
                f"{_span(self.wavelengths_nm)}, this run's bundle gives {len(wl)} bands "
                f"{_span(wl)}; write into another folder"
            )
        if tuple(int(v) for v in frame_size) != tuple(self.frame_size):
            raise InputError(
                f"{self.path}: the store holds frames of (h, w) = {tuple(self.frame_size)}, this "
                f"run's bundle gives {tuple(frame_size)}; write into another folder"
            )

    def _add_sources(self, sources: Sequence[str]) -> None:
        new = [s for s in dict.fromkeys(sources) if s not in self.index]
        if not new:
            return
        n0 = int(self.meta["source"]["shape"][0])
        n1 = n0 + len(new)
        for i, s in enumerate(new):
            self.index[s] = n0 + i
        names = [""] * n1
        for s, i in self.index.items():
            names[i] = s
        for name in _FRAME_VARS:
            self.meta[name]["shape"][0] = n1
        h, w = self.frame_size
        blank = {"valid": np.zeros((1, h, w), bool), "done": np.zeros(1, bool),
                 "metadata": np.array([""], dtype=object)}  # fmt: skip
        jobs = [(self.path / _chunk_key(name, i, data.ndim), _encode(self.meta[name], data))
                for name, data in blank.items() for i in range(n0, n1)]  # fmt: skip
        with ThreadPoolExecutor(max_workers=8) as pool:  # small files: the waits overlap
            # every chunk exists (see the module docstring)
            list(pool.map(lambda job: _put(*job, fsync=False), jobs))
        for c in range(n0 // SOURCE_CHUNK, (n1 - 1) // SOURCE_CHUNK + 1):  # the chunks touched
            part = names[c * SOURCE_CHUNK: (c + 1) * SOURCE_CHUNK]
            part += [""] * (SOURCE_CHUNK - len(part))
            self._write_chunk("source", c, np.array(part, dtype=object))
        for name in _FRAME_VARS:  # the new shape after the chunks that hold the new names
            _write_json(self.path / name / ".zarray", self.meta[name])
        self._write_metadata()

    # --- bookkeeping -----------------------------------------------------------------------
    def __len__(self) -> int:
        return int(self.meta["done"]["shape"][0])

    def frame_record(self, index: int) -> dict[str, Any] | None:
        """The metadata of a complete frame (``done`` True), else ``None``."""
        try:
            done = bool(self._read_chunk("done", index)[0])
            if not done:
                return None
            rec = json.loads(str(self._read_chunk("metadata", index)[0]))
        except (OSError, ValueError, RuntimeError):
            return None
        return rec if isinstance(rec, dict) else None

    def mark_pending(self, index: int) -> None:
        """The frame is about to be (re)written: not complete until its writer says so."""
        self._write_chunk("done", index, np.zeros(1, bool))

    def clean_frame_temps(self, index: int) -> list[Path]:
        """Remove the temporary files that killed writers of frame ``index`` left (call only
        when no writer of that frame is running)."""
        removed: list[Path] = []
        for name in ("cube", "valid", "metadata", "done"):
            key = Path(_chunk_key(name, index, len(self.meta[name]["shape"])))
            folder = self.path / key.parent
            for p in folder.glob(f".{key.name}.*.tmp"):
                remove_file(p)
                removed.append(p)
        return removed

    # --- low level -------------------------------------------------------------------------
    def _write_chunk(self, name: str, index: int, data: np.ndarray) -> None:
        meta = self.meta[name]
        key = _chunk_key(name, index, len(meta["shape"]))
        with atomic_write(self.path / key, "wb") as f:
            f.write(_encode(meta, data))

    def _read_chunk(self, name: str, index: int) -> np.ndarray:
        meta = self.meta[name]
        p = self.path / _chunk_key(name, index, len(meta["shape"]))
        if not p.is_file():  # (not in a complete store: every chunk is written)
            raise FileNotFoundError(f"{p}: chunk missing")
        try:
            return _decode(meta, p.read_bytes())
        except FileFormatError:
            raise
        except Exception as exc:  # noqa: BLE001 - numcodecs/numpy errors on a damaged chunk
            raise FileFormatError(f"{p}: cannot decode this chunk of array {name!r} "
                                  f"({type(exc).__name__}: {short_repr(str(exc), 120)})") from None

    def _write_metadata(self) -> None:
        """The consolidated metadata (``.zmetadata``), what ``xarray.open_zarr`` reads."""
        md: dict[str, Any] = {".zgroup": {"zarr_format": 2}, ".zattrs": self.attrs}
        for name, meta in self.meta.items():
            md[f"{name}/.zarray"] = meta
            md[f"{name}/.zattrs"] = self._var_attrs[name]
        _write_json(self.path / ".zmetadata", {"zarr_consolidated_format": 1, "metadata": md})


def _span(wl: Sequence[float]) -> str:
    return f"({wl[0]:g}-{wl[-1]:g} nm)" if len(wl) else "()"


def _write_json(path: Path, obj: Any) -> None:
    atomic_write_text(path, json.dumps(obj, indent=2, default=json_default, allow_nan=True))


def _put(path: Path, data: bytes, fsync: bool = True) -> None:
    """Write ``data`` as ``path``: a temporary file then a rename (atomic; ``fsync`` optional)."""
    with atomic_write(path, "wb", fsync=fsync) as f:
        f.write(data)


def _read_json(path: Path) -> dict[str, Any]:
    obj = read_json_bounded(path, "store metadata")  # a regular file, bounded size and depth
    if not isinstance(obj, dict):
        raise ValueError(f"{path}: not a JSON object")
    return obj


#: The entries of a store folder this module writes (the arrays, the group's metadata, the lock).
_STORE_ENTRIES = frozenset({*_ARRAYS, ".zgroup", ".zattrs", ".zmetadata", _LOCK_NAME})


def _refuse_foreign_folder(p: Path) -> None:
    """A folder at ``p`` that is not a store and holds anything a store's creation would not
    have written (the user's own folder that happens to have the store's name) is refused:
    writing the store into it would mix the arrays into their files. A folder left by an
    interrupted creation (only the store's own entries, no ``.zgroup`` yet) is created again."""
    if not p.is_dir() or (p / ".zgroup").is_file():
        return
    foreign = sorted(e.name for e in os.scandir(p) if e.name not in _STORE_ENTRIES
                     and not (e.name.startswith(".") and e.name.endswith(".tmp")))  # fmt: skip
    if foreign:
        shown = ", ".join(foreign[:4]) + (", ..." if len(foreign) > 4 else "")
        raise FileFormatError(
            f"{p} is a folder but not a dataset store (no .zgroup) and holds other files "
            f"({shown}); nothing was written into it: remove or rename it, or choose another "
            "--out")


def _lock(store: Path) -> int:
    """An exclusive ``flock`` on the store's lock file, opened by
    :func:`~hsi_torch.io.atomic.open_own_file` (a symlink or hard link planted at its name is
    refused, never written through; no locking without ``fcntl``)."""
    fd, _created = open_own_file(store / _LOCK_NAME)
    lock_or_refuse(fd, lambda holder: (
        f"the dataset store {store} is being written by another run (process {holder}) "
        "right now; run again when it has finished, or write into another folder"))
    mark_lock_holder(fd)
    return fd


_META_CACHE: dict[str, dict[str, dict[str, Any]]] = {}


def write_frame(
    store: str | os.PathLike,
    index: int,
    cube: Any,
    valid: Any,
    metadata: dict[str, Any],
) -> list[Path]:
    """Write one frame into a store made by :meth:`CubeDataset.open`: the cube (NaN where not
    ``valid``), the mask, the metadata, then ``done`` — each chunk atomically, no lock (the
    frame's chunks are its own files). Any process that sees the store's folder can call it.

    Args:
        store: the store's folder.
        index: the frame (:attr:`CubeDataset.index` of the input).
        cube: ``(M, h, w)`` tensor or array; valid: ``(h, w)`` bool.
        metadata: JSON-serialisable.

    Returns:
        The chunk files written.
    """
    root = Path(store)
    key = os.path.abspath(root)
    metas = _META_CACHE.get(key)
    if metas is None or int(metas["done"]["shape"][0]) <= index:  # a run may have appended
        metas = {n: _read_json(root / n / ".zarray") for n in ("cube", "valid", "metadata",
                                                                 "done")}  # fmt: skip
        for name, meta in metas.items():
            check_array_meta(meta, name, root)
        _META_CACHE[key] = metas
    n = int(metas["done"]["shape"][0])
    if not 0 <= index < n:
        raise IndexError(f"{root}: frame {index} outside the store's {n} frames")
    c = _np(cube).astype(np.float32, copy=False)
    v = _np(valid).astype(bool, copy=False)
    if c.shape != tuple(metas["cube"]["chunks"][1:]) or v.shape != c.shape[1:]:
        raise ValueError(
            f"{root}: frame {index}: cube {tuple(c.shape)} and valid {tuple(v.shape)} do not fit "
            f"the store's frames {tuple(metas['cube']['chunks'][1:])}"
        )
    c = _nan_where_invalid(c, v)
    text = json.dumps(metadata, default=json_default)
    written: list[Path] = []
    for name, data in (("cube", c[None]), ("valid", v[None]),
                       ("metadata", np.array([text], dtype=object)),
                       ("done", np.ones(1, dtype=bool))):  # fmt: skip
        meta = metas[name]
        p = root / _chunk_key(name, index, len(meta["shape"]))
        payload = _encode(meta, data)
        with atomic_write(p, "wb") as f:
            f.write(payload)
        written.append(p)
    return written


def open_dataset(path: str | os.PathLike):
    """The store as an ``xarray.Dataset`` (``xarray.open_zarr``; lazy, chunked per frame)."""
    require_dataset_packages(read=True)
    import xarray as xr  # lazy: optional dependency (the cluster extra)

    p = Path(path)
    if not (p / ".zgroup").is_file():
        raise FileFormatError(f"{p}: not a Zarr store (no .zgroup)")
    check_zarr_codecs(p)
    check_store_files(p)  # every chunk a regular file of bounded size
    return xr.open_zarr(p, consolidated=True)
