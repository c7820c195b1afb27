"""The one writer of this package's Zarr stores: a Zarr (format 2, consolidated metadata) group of
spectral cubes along one axis, written without a Zarr library.

Both stores use it: the run's dataset store (:mod:`hsi_torch.io.dataset`, axis ``frame``) and
the sequence store (:mod:`hsi_torch.io.sequence_store`, axis ``time``). Each chunk is encoded by
the Zarr v2 rules with ``numcodecs`` (C order, the filters in turn, then the compressor), only
with the codecs of :data:`~hsi_torch.io.zarr_codecs.STORE_CODECS`, and every file is written
atomically (:mod:`hsi_torch.io.atomic`). :class:`ZarrGroup` holds what the stores share: the
store's lock, the refusal of a foreign folder, the creation of the group (every array's
``.zarray`` and ``.zattrs``, the coordinates, the root attributes, the consolidated
``.zmetadata``, ``.zgroup`` last: a folder without it is not a store, an interrupted creation is
redone), one chunk written or read, and the checks of a loaded store against the layout.
"""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from hsi_torch.errors import FileFormatError, InputError
from hsi_torch.io.atomic import (
    atomic_write,
    atomic_write_text,
    json_default,
    lock_or_refuse,
    mark_lock_holder,
    open_own_file,
)
from hsi_torch.io.bounded import read_json_bounded
from hsi_torch.io.safety import short_repr
from hsi_torch.io.zarr_codecs import STORE_CODECS

__all__ = [
    "ZarrGroup", "array_meta", "axis_array", "chunk_key", "decode_chunk", "encode_chunk",
    "put", "read_json", "write_json", "ZSTD", "VLEN", "LOCK_NAME",
]  # fmt: skip

#: The lock file of a store (one writer at a time).
LOCK_NAME = ".hsi_torch.lock"
#: The compressor of every compressed array (Zstandard, level 1).
ZSTD = {"id": "zstd", "level": 1}
#: The filters of a string array.
VLEN = [{"id": "vlen-utf8"}]


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


def encode_chunk(meta: dict[str, Any], data: np.ndarray) -> bytes:
    """One chunk's bytes by the Zarr v2 rules: C order, the filters in turn, the compressor.

    Args:
        meta: the array's ``.zarray``; data: one chunk, shape ``meta["chunks"]``.
    """
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


def decode_chunk(meta: dict[str, Any], raw: bytes) -> np.ndarray:
    """The chunk of shape ``meta["chunks"]`` that :func:`encode_chunk` made ``raw`` from."""
    comp = _codec(meta.get("compressor"))
    buf: Any = comp.decode(raw) if comp is not None else raw
    for f in reversed(meta.get("filters") or []):
        buf = _codec(f).decode(buf)
    if meta["dtype"] == "|O":
        return np.asarray(buf, dtype=object).reshape(meta["chunks"])
    return np.frombuffer(buf, dtype=np.dtype(meta["dtype"])).reshape(meta["chunks"])


def chunk_key(name: str, index: int, ndim: int) -> str:
    """The file of chunk ``index`` (along the first axis) of array ``name`` in the store."""
    return f"{name}/" + ".".join([str(index)] + ["0"] * (ndim - 1))


def array_meta(
    shape: Sequence[int], chunks: Sequence[int], dtype: str, fill: Any,
    compressor: dict[str, Any] | None = None, filters: list[dict[str, Any]] | None = None,
) -> dict[str, Any]:  # fmt: skip
    """An array's ``.zarray`` (Zarr format 2, C order, ``.`` separated chunk keys)."""
    return {
        "zarr_format": 2, "shape": list(shape), "chunks": list(chunks), "dtype": dtype,
        "fill_value": fill, "order": "C", "filters": filters, "compressor": compressor,
        "dimension_separator": ".",
    }  # fmt: skip


def axis_array(axis: str, dtype: str, long_name: str, chunk: int = 1,
               **attrs: Any) -> tuple[dict[str, Any], dict[str, Any]]:  # fmt: skip
    """``.zarray`` and ``.zattrs`` of an empty 1-D array along ``axis`` (strings ``"|O"``:
    Zstandard and ``vlen-utf8``; ``"<f8"``: fill NaN, uncompressed; others uncompressed)."""
    if dtype == "|O":
        meta = array_meta([0], [chunk], dtype, None, ZSTD, VLEN)
    else:
        meta = array_meta([0], [chunk], dtype, "NaN" if dtype == "<f8" else None)
    return meta, {"_ARRAY_DIMENSIONS": [axis], **attrs, "long_name": long_name}


def write_json(path: Path, obj: Any) -> None:
    """``obj`` as indented JSON at ``path``, atomically."""
    atomic_write_text(path, json.dumps(obj, indent=2, default=json_default, allow_nan=True))


def put(path: Path, data: bytes, fsync: bool = True) -> None:
    """Write ``data`` as ``path``: a temporary file then a rename (atomic; ``fsync`` optional)."""
    with atomic_write(path, "wb", fsync=fsync) as f:
        f.write(data)


def read_json(path: Path) -> dict[str, Any]:
    """A store's JSON object (a regular file, bounded size and depth).

    Raises:
        ValueError: not a JSON object (OSError: not readable).
    """
    obj = read_json_bounded(path, "store metadata")
    if not isinstance(obj, dict):
        raise ValueError(f"{path}: not a JSON object")
    return obj


def _span(wl: Sequence[float]) -> str:
    return f"({wl[0]:g}-{wl[-1]:g} nm)" if len(wl) else "()"


class ZarrGroup:
    """A store of spectral cubes along one axis (``AXIS``), as its writer holds it.

    A subclass names its arrays (``AXIS_ARRAYS``, ``ARRAYS``), what it is called in
    messages (``KIND``) and each array's (dtype, compressor id, filter ids) (``LAYOUT``), and
    builds its own axis arrays in its ``_create``.

    Attributes:
        path: the store's folder.
        attrs: the root attributes; meta: every array's ``.zarray``.
        wavelengths_nm, frame_size: as in the root attributes.
    """

    KIND = "store"
    AXIS = "frame"
    #: the arrays along the axis (one chunk per entry), then every array of the store
    AXIS_ARRAYS: tuple[str, ...] = ()
    ARRAYS: tuple[str, ...] = ()
    LAYOUT: dict[str, tuple[str, str | None, list[str]]] = {}

    def __init__(self, path: Path) -> None:
        self.path = path
        self.attrs: dict[str, Any] = {}
        self.meta: dict[str, dict[str, Any]] = {}
        self._var_attrs: dict[str, dict[str, Any]] = {}
        self.wavelengths_nm: list[float] = []
        self.frame_size: tuple[int, int] = (0, 0)

    # --- opening -------------------------------------------------------------------------
    @classmethod
    @contextlib.contextmanager
    def _locked(cls, path: str | os.PathLike) -> Iterator[tuple[Path, int]]:
        """``(folder, lock fd)``: the store's folder (made; refused if foreign) and its lock
        held until the ``with`` block ends."""
        p = Path(path)
        cls._refuse_foreign_folder(p)
        p.mkdir(parents=True, exist_ok=True)
        fd = cls._lock(p)
        try:
            yield p, fd
        finally:
            os.close(fd)  # releases the lock

    def _open_or_create(self, wavelengths_nm: Sequence[float], frame_size: tuple[int, int],
                        attrs: dict[str, Any] | None) -> None:  # fmt: skip
        if (self.path / ".zgroup").is_file():
            self._load()
            self._check(wavelengths_nm, frame_size)
        else:
            self._create(wavelengths_nm, frame_size, attrs or {})

    def _load(self) -> None:
        raise NotImplementedError

    def _create(self, wavelengths_nm: Sequence[float], frame_size: tuple[int, int],
                attrs: dict[str, Any]) -> None:  # fmt: skip
        raise NotImplementedError

    @classmethod
    def _refuse_foreign_folder(cls, p: Path) -> None:
        """A folder at ``p`` that is not a store and holds anything a store's creation would
        not have written (the user's own folder that happens to have the store's name) is
        refused: writing the store into it would mix the arrays into their files. A folder left
        by an interrupted creation (only the store's own entries, no ``.zgroup`` yet) is created
        again."""
        if not p.is_dir() or (p / ".zgroup").is_file():
            return
        own = {*cls.ARRAYS, ".zgroup", ".zattrs", ".zmetadata", LOCK_NAME}
        foreign = sorted(e.name for e in os.scandir(p) if e.name not in own
                         and not (e.name.startswith(".") and e.name.endswith(".tmp")))  # fmt: skip
        if foreign:
            shown = ", ".join(foreign[:4]) + (", ..." if len(foreign) > 4 else "")
            raise FileFormatError(
                f"{p} is a folder but not a {cls.KIND} (no .zgroup) and holds other files "
                f"({shown}); nothing was written into it: remove or rename it, or choose another "
                "--out")

    @classmethod
    def _lock(cls, store: Path) -> int:
        """An exclusive ``flock`` on the store's lock file, opened by
        :func:`~hsi_torch.io.atomic.open_own_file` (a symlink or hard link planted at its name
        is refused, never written through; no locking without ``fcntl``)."""
        fd, _created = open_own_file(store / LOCK_NAME)
        lock_or_refuse(fd, lambda holder: (
            f"the {cls.KIND} {store} is being written by another run (process {holder}) "
            "right now; run again when it has finished, or write into another folder"))
        mark_lock_holder(fd)
        return fd

    # --- creation --------------------------------------------------------------------------
    def _create_group(self, attrs: dict[str, Any], cube_coordinates: str,
                      arrays: dict[str, tuple[dict[str, Any], dict[str, Any]]],
                      ) -> None:  # fmt: skip
        """Write a new store: the cube ``(axis, M, h, w)`` and mask ``(axis, h, w)`` (one chunk
        per entry, Zstandard), ``arrays`` (name → ``.zarray``, ``.zattrs``, in order), the
        coordinates ``wavelength`` (nm), ``y``, ``x`` (pixels), the root ``attrs`` (holding
        ``wavelengths_nm`` and ``frame_size`` ``[h, w]``), the consolidated metadata, and
        ``.zgroup`` last."""
        wl = np.asarray(attrs["wavelengths_nm"], dtype=np.float64)
        h, w = (int(v) for v in attrs["frame_size"])
        m, ax = int(wl.size), self.AXIS
        coord = {"units": "pixel", "long_name": "reference-frame row"}
        specs = {
            "cube": (array_meta([0, m, h, w], [1, m, h, w], "<f4", "NaN", ZSTD),
                     {"_ARRAY_DIMENSIONS": [ax, "wavelength", "y", "x"],
                      "long_name": "spectral cube (reflectance relative to the white reference)",
                      "coordinates": cube_coordinates}),
            "valid": (array_meta([0, h, w], [1, h, w], "|b1", None, ZSTD),
                      {"_ARRAY_DIMENSIONS": [ax, "y", "x"],
                       "long_name": "pixel reconstructed (>= min_views views)"}),
            **arrays,
            "wavelength": (array_meta([m], [m], "<f8", "NaN"),
                           {"_ARRAY_DIMENSIONS": ["wavelength"], "units": "nm",
                            "long_name": "band centre wavelength"}),
            "y": (array_meta([h], [h], "<i8", None), {"_ARRAY_DIMENSIONS": ["y"], **coord}),
            "x": (array_meta([w], [w], "<i8", None),
                  {"_ARRAY_DIMENSIONS": ["x"], **coord, "long_name": "reference-frame column"}),
        }  # fmt: skip
        self.attrs = attrs
        self.meta = {name: meta for name, (meta, _) in specs.items()}
        self._var_attrs = {name: va for name, (_, va) in specs.items()}
        for name, meta in self.meta.items():
            (self.path / name).mkdir(exist_ok=True)
            write_json(self.path / name / ".zarray", meta)
            write_json(self.path / name / ".zattrs", self._var_attrs[name])
        self._write_chunk("wavelength", 0, wl)
        self._write_chunk("y", 0, np.arange(h, dtype=np.int64))
        self._write_chunk("x", 0, np.arange(w, dtype=np.int64))
        write_json(self.path / ".zattrs", self.attrs)
        self._write_consolidated()
        # written last: a folder without it is not a store (an interrupted creation is redone)
        write_json(self.path / ".zgroup", {"zarr_format": 2})
        self.wavelengths_nm = wl.tolist()
        self.frame_size = (h, w)

    # --- loading ---------------------------------------------------------------------------
    def _read_metadata(self) -> None:
        """The root attributes and every array's ``.zarray`` and ``.zattrs``.

        Raises:
            FileFormatError: one is missing or not a JSON object.
        """
        try:
            self.attrs = read_json(self.path / ".zattrs")
            self.meta = {n: read_json(self.path / n / ".zarray") for n in self.ARRAYS}
            self._var_attrs = {n: read_json(self.path / n / ".zattrs") for n in self.ARRAYS}
        except (OSError, ValueError) as exc:
            raise FileFormatError(f"{self.path}: not a hsi_torch {self.KIND} ({exc}); write "
                                  "into another folder") from None  # fmt: skip

    def _check_codecs(self, name: str) -> None:
        """Array ``name``'s dtype, compressor and filters are this layout's (``LAYOUT``)."""
        meta = self.meta[name]
        got = (meta.get("dtype"), (meta.get("compressor") or {}).get("id"),
               [f.get("id") for f in meta.get("filters") or []])  # fmt: skip
        if got != tuple(self.LAYOUT[name]):
            raise FileFormatError(
                f"{self.path}: array {name!r} has dtype, compressor and filters "
                f"{short_repr(got, 60)}, not this layout's {tuple(self.LAYOUT[name])}")

    def _check(self, wavelengths_nm: Sequence[float], frame_size: tuple[int, int]) -> None:
        """The store was made for this wavelength grid and frame size.

        Raises:
            InputError: another grid or size (another bundle), naming the store.
        """
        wl = [float(x) for x in wavelengths_nm]
        if len(wl) != len(self.wavelengths_nm) or not np.allclose(wl, self.wavelengths_nm):
            raise InputError(
                f"{self.path}: the store holds cubes of {len(self.wavelengths_nm)} bands "
                f"{_span(self.wavelengths_nm)}, this run's bundle gives {len(wl)} bands "
                f"{_span(wl)}; write into another folder")
        if tuple(int(v) for v in frame_size) != tuple(self.frame_size):
            raise InputError(
                f"{self.path}: the store holds frames of (h, w) = {tuple(self.frame_size)}, this "
                f"run's bundle gives {tuple(frame_size)}; write into another folder")

    def _set_length(self, n: int) -> None:
        """Every array along the axis has ``n`` entries (their ``.zarray``, then ``.zmetadata``)."""
        for name in self.AXIS_ARRAYS:
            self.meta[name]["shape"][0] = n
            write_json(self.path / name / ".zarray", self.meta[name])
        self._write_consolidated()

    # --- low level -------------------------------------------------------------------------
    def _chunk_path(self, name: str, index: int) -> Path:
        return self.path / chunk_key(name, index, len(self.meta[name]["shape"]))

    def _write_chunk(self, name: str, index: int, data: np.ndarray) -> None:
        put(self._chunk_path(name, index), encode_chunk(self.meta[name], data))

    def _read_chunk(self, name: str, index: int) -> np.ndarray:
        """Chunk ``index`` of array ``name``, decoded.

        Raises:
            FileFormatError: the chunk is missing, unreadable or cannot be decoded (naming it).
        """
        p = self._chunk_path(name, index)
        try:
            return decode_chunk(self.meta[name], p.read_bytes())
        except OSError as exc:
            raise FileFormatError(f"{p}: chunk of array {name!r} missing or unreadable "
                                  f"({exc})") from None  # fmt: skip
        except FileFormatError:
            raise
        except Exception as exc:  # noqa: BLE001 - numcodecs/numpy errors on a damaged chunk
            raise FileFormatError(f"{p}: cannot decode this chunk of array {name!r} "
                                  f"({type(exc).__name__}: {short_repr(str(exc), 120)})") from None

    def _write_consolidated(self) -> None:
        """The consolidated metadata (``.zmetadata``), what ``xarray.open_zarr`` reads."""
        md: dict[str, Any] = {".zgroup": {"zarr_format": 2}, ".zattrs": self.attrs}
        for name, meta in self.meta.items():
            md[f"{name}/.zarray"] = meta
            md[f"{name}/.zattrs"] = self._var_attrs[name]
        write_json(self.path / ".zmetadata", {"zarr_consolidated_format": 1, "metadata": md})
