"""One Zarr store for a whole run: every frame's cube in one chunked dataset.

``hsi-torch reconstruct --format zarr`` writes ``OUT/cubes.zarr`` instead of files per input: a
Zarr (format 2, consolidated metadata) group that ``xarray.open_zarr`` opens as a Dataset (the
layout table and reading examples: docs/cluster.md). Variables, one chunk per frame:
``cube (frame, wavelength, y, x)`` float32, NaN where invalid or not (yet) reconstructed;
``valid (frame, y, x)`` bool; ``done (frame,)`` bool, the frame is complete; ``metadata
(frame,)`` str, the frame's metadata (JSON, as in a cube file: its ``"findings"`` are the
frame's findings); coordinates ``source (frame,)`` (the input's absolute path, chunks of 4096),
``wavelength`` (float64, nm), ``y``, ``x`` (int64 reference-frame pixel indices). ``cube`` is
compressed with Zstandard (level 1: 0.1–0.2 s and 27–43 % of the raw 61 MiB for the full-size
demo's three scenes). The root attributes hold ``hsi_torch_dataset`` (layout version),
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

from hsi_torch.devices import to_numpy
from hsi_torch.errors import FileFormatError, require_packages
from hsi_torch.io.atomic import json_default, remove_file
from hsi_torch.io.bounded import check_store_files
from hsi_torch.io.cube import _nan_where_invalid
from hsi_torch.io.safety import short_repr
from hsi_torch.io.zarr_codecs import (
    SAFE_CODECS,
    STORE_CODECS,
    check_array_meta,
    check_zarr_codecs,
)
from hsi_torch.io.zarr_group import (
    ZarrGroup,
    axis_array,
    chunk_key,
    encode_chunk,
    put,
)
from hsi_torch.io.zarr_group import read_json as _read_json

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


#: each array's dtype, compressor id and filter ids in this layout
_LAYOUT_CODECS: dict[str, tuple[str, str | None, list[str]]] = {
    "cube": ("<f4", "zstd", []), "valid": ("|b1", "zstd", []), "done": ("|b1", None, []),
    "metadata": ("|O", "zstd", ["vlen-utf8"]), "source": ("|O", "zstd", ["vlen-utf8"]),
    "wavelength": ("<f8", None, []), "y": ("<i8", None, []), "x": ("<i8", None, []),
}  # fmt: skip


class CubeDataset(ZarrGroup):
    """The run driver's handle on a store (creates it, adds frames, tracks what is done).

    Use :meth:`open` (under the store's lock, see the module docstring); frames are written by
    :func:`write_frame`, in any process that sees the store's folder.

    Attributes:
        path: the store's folder.
        index: absolute input path → frame index.
        wavelengths_nm, frame_size: as in the root attributes.
    """

    KIND = "dataset store"
    AXIS = "frame"
    AXIS_ARRAYS = _FRAME_VARS
    ARRAYS = _ARRAYS
    LAYOUT = _LAYOUT_CODECS

    def __init__(self, path: Path, lock_fd: int) -> None:
        super().__init__(path)
        self._lock_fd = lock_fd
        self.index: dict[str, int] = {}

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
        with cls._locked(path) as (p, fd):
            ds = cls(p, fd)
            ds._open_or_create(wavelengths_nm, frame_size, attrs)
            ds._add_sources([os.path.abspath(s) for s in sources])
            yield ds

    def _create(
        self, wavelengths_nm: Sequence[float], frame_size: tuple[int, int], attrs: dict[str, Any]
    ) -> None:
        attrs = {
            "hsi_torch_dataset": DATASET_VERSION,
            "description": "hsi_torch spectral cubes, one frame per input (see 'done')",
            "wavelengths_nm": [float(v) for v in wavelengths_nm],
            "wavelength_units": "nm",
            "frame_size": [int(v) for v in frame_size],
            **attrs,
        }
        self._create_group(attrs, "source", {
            "done": axis_array("frame", "|b1", "frame complete (its cube, valid mask and "
                               "metadata written)"),
            "metadata": axis_array("frame", "|O", "the frame's metadata, JSON"),
            "source": axis_array("frame", "|O", "input file", chunk=SOURCE_CHUNK),
        })

    def _load(self) -> None:
        self._read_metadata()
        for name, meta in self.meta.items():  # before any chunk is decoded
            check_array_meta(meta, name, self.path)
        self._check_layout()
        if self.attrs.get("hsi_torch_dataset") != DATASET_VERSION:
            raise FileFormatError(
                f"{self.path}: not a hsi_torch dataset store of layout version {DATASET_VERSION} "
                f"(attribute hsi_torch_dataset = {self.attrs.get('hsi_torch_dataset')!r})")
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
            self._check_codecs(name)

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
        jobs = [(self.path / chunk_key(name, i, data.ndim), encode_chunk(self.meta[name], data))
                for name, data in blank.items() for i in range(n0, n1)]  # fmt: skip
        with ThreadPoolExecutor(max_workers=8) as pool:  # small files: the waits overlap
            # every chunk exists (see the module docstring)
            list(pool.map(lambda job: put(*job, fsync=False), jobs))
        for c in range(n0 // SOURCE_CHUNK, (n1 - 1) // SOURCE_CHUNK + 1):  # the chunks touched
            part = names[c * SOURCE_CHUNK: (c + 1) * SOURCE_CHUNK]
            part += [""] * (SOURCE_CHUNK - len(part))
            self._write_chunk("source", c, np.array(part, dtype=object))
        self._set_length(n1)  # the new shape after the chunks that hold the new names

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
            key = Path(chunk_key(name, index, len(self.meta[name]["shape"])))
            folder = self.path / key.parent
            for p in folder.glob(f".{key.name}.*.tmp"):
                remove_file(p)
                removed.append(p)
        return removed

_META_CACHE: dict[str, dict[str, dict[str, Any]]] = {}


def write_frame(
    store: str | os.PathLike, index: int, cube: Any, valid: Any, metadata: dict[str, Any]
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
    c = to_numpy(cube, np.float32)
    v = to_numpy(valid, bool)
    if c.shape != tuple(metas["cube"]["chunks"][1:]) or v.shape != c.shape[1:]:
        raise ValueError(
            f"{root}: frame {index}: cube {tuple(c.shape)} and valid {tuple(v.shape)} do not fit "
            f"the store's frames {tuple(metas['cube']['chunks'][1:])}")
    c = _nan_where_invalid(c, v)
    text = json.dumps(metadata, default=json_default)
    written: list[Path] = []
    for name, data in (("cube", c[None]), ("valid", v[None]),
                       ("metadata", np.array([text], dtype=object)),
                       ("done", np.ones(1, dtype=bool))):  # fmt: skip
        p = root / chunk_key(name, index, len(metas[name]["shape"]))
        put(p, encode_chunk(metas[name], data))
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
