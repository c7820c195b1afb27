"""One Zarr store for a sequence: the cubes of a moving scene along a time axis, appended frame
by frame.

``hsi-torch reconstruct --sequence`` and ``hsi-torch watch`` write ``OUT/sequence.zarr``, a Zarr
(format 2, consolidated metadata) group that ``xarray.open_zarr`` opens as a Dataset and the
napari reader shows with a time slider (the layout table and reading examples:
docs/sequences_io.md). Along ``time``, one chunk per frame: ``cube (time, wavelength, y, x)``
float32, NaN where not valid; ``valid (time, y, x)`` bool; ``time`` (coordinate, float64,
seconds since the first frame); ``timestamp`` (str, the frame's ISO 8601 date and time or
``""`` when not absolute); ``source`` (str, the input's absolute path, ``#page=N`` for a TIFF
page); ``findings`` (str, a JSON list of :meth:`hsi_torch.findings.Finding.to_dict`);
``metadata`` (str, JSON as in a cube file); coordinates ``wavelength`` (float64, nm), ``y``,
``x`` (int64 reference-frame pixel indices). The root attributes hold ``hsi_torch_sequence``
(layout version), ``wavelengths_nm``, ``frame_size``, ``time_origin`` (the first frame's date
and time, or ``None``), ``time_source`` and ``bundle``. ``cube`` is compressed with Zstandard
(level 1), as in the run's store (:mod:`hsi_torch.io.dataset`); both are written by
:mod:`hsi_torch.io.zarr_group` (chunk encoding, codec checks, the lock).

**Appended, resumable.** Every frame is one chunk of each time-axis array, written atomically
(temporary file + rename, :mod:`hsi_torch.io.atomic`); only then is the time axis lengthened (the
arrays' ``.zarray`` and the consolidated ``.zmetadata``). The store's length is therefore the
number of complete frames: a run killed while writing frame ``k`` leaves ``k`` frames and stray
chunks past the end, which the next run overwrites — a rerun continues after the last complete
frame. A store whose arrays disagree on the length (killed between two ``.zarray`` updates) is
cut back to the shortest when opened. One writer at a time (the store's lock file,
``.hsi_torch.lock``).

**Read lazily.** :func:`open_sequence_store` checks the codecs (only those this module writes are
decoded) and that every file is a regular file of bounded size, then opens the store lazily
(``xarray.open_zarr``: one frame is decoded when it is asked for); :func:`iter_store_frames`
yields one frame at a time, each checked against the cube size cap
(``$HSI_TORCH_MAX_CUBE_GB``, :mod:`hsi_torch.io.bounded`) — a sequence is never loaded whole.
"""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from hsi_torch.colour import cube_to_srgb, cube_to_xyz
from hsi_torch.devices import to_numpy
from hsi_torch.errors import FileFormatError, InputError
from hsi_torch.findings import Finding
from hsi_torch.io.atomic import atomic_write, json_default
from hsi_torch.io.bounded import check_declared, check_store_files
from hsi_torch.io.cube import _nan_where_invalid
from hsi_torch.io.dataset import require_dataset_packages
from hsi_torch.io.safety import short_repr
from hsi_torch.io.zarr_codecs import check_array_meta, check_zarr_codecs
from hsi_torch.io.zarr_group import ZarrGroup, axis_array, read_json, write_json

__all__ = [
    "SEQUENCE_NAME",
    "SEQUENCE_VERSION",
    "SequenceStore",
    "open_sequence_store",
    "iter_store_frames",
    "is_sequence_store",
    "write_animated_preview",
]

#: The store's name inside an output folder.
SEQUENCE_NAME = "sequence.zarr"
#: Layout version (root attribute ``hsi_torch_sequence``).
SEQUENCE_VERSION = 1
#: The arrays along the time axis (one chunk per frame each).
_TIME_VARS = ("cube", "valid", "time", "timestamp", "source", "findings", "metadata")
_ARRAYS = (*_TIME_VARS, "wavelength", "y", "x")
#: each array's dtype, compressor id, filter ids
_LAYOUT: dict[str, tuple[str, str | None, list[str]]] = {
    "cube": ("<f4", "zstd", []), "valid": ("|b1", "zstd", []), "time": ("<f8", None, []),
    "timestamp": ("|O", "zstd", ["vlen-utf8"]), "source": ("|O", "zstd", ["vlen-utf8"]),
    "findings": ("|O", "zstd", ["vlen-utf8"]), "metadata": ("|O", "zstd", ["vlen-utf8"]),
    "wavelength": ("<f8", None, []), "y": ("<i8", None, []), "x": ("<i8", None, []),
}  # fmt: skip


def is_sequence_store(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a folder holding a sequence store (its root attributes say so)."""
    p = Path(path)
    if not (p / ".zgroup").is_file() or not (p / ".zattrs").is_file():
        return False
    try:
        return read_json(p / ".zattrs").get("hsi_torch_sequence") is not None
    except (OSError, ValueError):
        return False


class SequenceStore(ZarrGroup):
    """The writer's handle on a sequence store (:meth:`open`; appends with :meth:`append`).

    Attributes:
        path: the store's folder.
        sources: the inputs of the complete frames, in order (``len`` = frames in the store).
        times_s: their times (seconds since the first frame).
        wavelengths_nm, frame_size: as in the root attributes.
        attrs: the root attributes.
    """

    KIND = "sequence store"
    AXIS = "time"
    AXIS_ARRAYS = _TIME_VARS
    ARRAYS = _ARRAYS
    LAYOUT = _LAYOUT

    def __init__(self, path: Path) -> None:
        super().__init__(path)
        self.sources: list[str] = []
        self.times_s: list[float] = []

    @classmethod
    @contextlib.contextmanager
    def open(
        cls,
        path: str | os.PathLike,
        wavelengths_nm: Sequence[float],
        frame_size: tuple[int, int],
        attrs: dict[str, Any] | None = None,
    ) -> Iterator[SequenceStore]:
        """Create the store at ``path`` or open an existing one (for the same wavelength grid
        and frame size), holding its lock until the ``with`` block ends.

        Raises:
            InputError: another process writes the store, or it was made for another bundle
                (wavelengths, frame size).
            FileFormatError: ``path`` is a folder that is not a sequence store.
        """
        require_dataset_packages()
        with cls._locked(path) as (p, _fd):
            st = cls(p)
            st._open_or_create(wavelengths_nm, frame_size, attrs)
            yield st

    def __len__(self) -> int:
        return len(self.sources)

    # --- creation and loading ------------------------------------------------------------
    def _create(self, wavelengths_nm: Sequence[float], frame_size: tuple[int, int],
                attrs: dict[str, Any]) -> None:  # fmt: skip
        attrs = {
            "hsi_torch_sequence": SEQUENCE_VERSION,
            "description": "hsi_torch spectral cubes of a sequence, one per frame along 'time'",
            "wavelengths_nm": [float(v) for v in wavelengths_nm], "wavelength_units": "nm",
            "frame_size": [int(v) for v in frame_size],
            "time_origin": None, "time_source": None, **attrs,
        }  # fmt: skip
        self._create_group(attrs, "source timestamp", {
            "time": axis_array("time", "<f8", "seconds since the first frame", units="s"),
            "timestamp": axis_array("time", "|O", "the frame's date and time, ISO 8601 ('' if "
                                    "unknown)"),
            "source": axis_array("time", "|O", "input file"),
            "findings": axis_array("time", "|O", "the frame's findings, JSON list"),
            "metadata": axis_array("time", "|O", "the frame's metadata, JSON"),
        })

    def _load(self) -> None:
        self._read_metadata()
        if self.attrs.get("hsi_torch_sequence") != SEQUENCE_VERSION:
            raise FileFormatError(
                f"{self.path}: not a hsi_torch sequence store of layout version "
                f"{SEQUENCE_VERSION} (attribute hsi_torch_sequence = "
                f"{short_repr(self.attrs.get('hsi_torch_sequence'), 40)}); write into another "
                "folder")  # fmt: skip
        for name, meta in self.meta.items():  # before any chunk is decoded
            check_array_meta(meta, name, self.path)
            self._check_codecs(name)
        self.wavelengths_nm = [float(v) for v in self.attrs.get("wavelengths_nm", [])]
        self.frame_size = tuple(int(v) for v in self.attrs.get("frame_size", (0, 0)))  # type: ignore[assignment]
        h, w = self.frame_size
        m = len(self.wavelengths_nm)
        lengths = {n: int(self.meta[n]["shape"][0]) for n in _TIME_VARS}
        n = min(lengths.values())
        if self.meta["cube"]["chunks"] != [1, m, h, w] or self.meta["valid"]["chunks"] != [1, h, w]:
            raise FileFormatError(f"{self.path}: the cube's chunks "
                                  f"{short_repr(self.meta['cube']['chunks'], 40)} do not fit "
                                  f"{m} bands of {h}x{w} frames")  # fmt: skip
        if len(set(lengths.values())) > 1:  # killed between two .zarray updates: cut back
            self._set_length(n)
        self.sources = [str(self._read_chunk("source", k)[0]) for k in range(n)]
        self.times_s = [float(self._read_chunk("time", k)[0]) for k in range(n)]

    def set_attrs(self, **attrs: Any) -> None:
        """Update root attributes (e.g. ``time_origin`` when the first frame is appended)."""
        self.attrs.update(attrs)
        write_json(self.path / ".zattrs", self.attrs)
        self._write_consolidated()

    # --- appending -----------------------------------------------------------------------
    def append(
        self,
        cube: Any,
        valid: Any,
        *,
        time_s: float,
        source: str,
        timestamp: str | None = None,
        findings: Iterable[Finding | dict[str, Any]] = (),
        metadata: dict[str, Any] | None = None,
    ) -> int:
        """Append one frame; returns its index. The frame is in the store once this returns
        (all its chunks written, then the time axis lengthened).

        Args:
            cube: ``(M, h, w)`` tensor or array (NaN is written where not ``valid``).
            valid: ``(h, w)`` bool.
            time_s: seconds since the first frame; must exceed the last frame's.
            source: the input (its name in the store).
            timestamp: ISO 8601 date and time, or ``None``.
            findings: the frame's findings (:class:`~hsi_torch.findings.Finding` or their dicts).
            metadata: JSON-serialisable.

        Raises:
            InputError: a time not after the last frame's, naming the source; ValueError: a
                cube or mask of another shape.
        """
        k = len(self.sources)
        t = float(time_s)
        if not np.isfinite(t):
            raise InputError(f"{source}: time {time_s!r} is not a finite number of seconds")
        if k and t <= self.times_s[-1]:
            raise InputError(
                f"{source}: its time ({t:g} s) is not after the store's last frame "
                f"({self.times_s[-1]:g} s, {self.sources[-1]}); a sequence store only grows "
                "forward in time: write into another folder")
        c = to_numpy(cube, np.float32)
        v = to_numpy(valid, bool)
        want = tuple(self.meta["cube"]["chunks"][1:])
        if c.shape != want or v.shape != want[1:]:
            raise ValueError(f"{self.path}: frame {k} ({source}): cube {tuple(c.shape)} and "
                             f"valid {tuple(v.shape)} do not fit the store's {want}")  # fmt: skip
        c = _nan_where_invalid(c, v)
        fd = [f.to_dict() if isinstance(f, Finding) else dict(f) for f in findings]
        data = {
            "cube": c[None], "valid": v[None], "time": np.array([t]),
            "timestamp": np.array([timestamp or ""], dtype=object),
            "source": np.array([source], dtype=object),
            "findings": np.array([json.dumps(fd, default=json_default)], dtype=object),
            "metadata": np.array([json.dumps(metadata or {}, default=json_default)],
                                 dtype=object),
        }  # fmt: skip
        for name, arr in data.items():
            self._write_chunk(name, k, arr)
        self._set_length(k + 1)
        self.sources.append(source)
        self.times_s.append(t)
        return k



def _checked(path: str | os.PathLike) -> Path:
    p = Path(path)
    if not is_sequence_store(p):
        raise FileFormatError(f"{p}: not a hsi_torch sequence store (no .zgroup, or its "
                              ".zattrs has no hsi_torch_sequence)")  # fmt: skip
    check_zarr_codecs(p)  # only the codecs this module writes are ever decoded
    check_store_files(p)  # every file regular, of bounded size
    return p


def open_sequence_store(path: str | os.PathLike):
    """The store as an ``xarray.Dataset`` (``xarray.open_zarr``: lazy, one chunk per frame),
    after its codecs and files are checked (module docstring).

    Raises:
        FileFormatError: not a sequence store, a foreign codec, a non-regular or oversized file.
    """
    require_dataset_packages(read=True)
    import xarray as xr  # lazy: optional dependency (the cluster or formats extra)

    return xr.open_zarr(_checked(path), consolidated=True)


def iter_store_frames(
    path: str | os.PathLike, indices: Iterable[int] | None = None,
    max_bytes: int | None = None,
) -> Iterator[tuple[int, float, np.ndarray, np.ndarray]]:  # fmt: skip
    """``(index, time_s, cube (M, h, w) float32, valid (h, w) bool)`` of the store's frames, one
    decoded at a time (no xarray needed), each checked against the cube size cap first
    (``max_bytes``, default ``$HSI_TORCH_MAX_CUBE_GB``)."""
    p = _checked(path)
    st = SequenceStore(p)
    st._load()
    n = len(st.sources)
    check_declared(p, st.meta["cube"]["chunks"], np.float32, max_bytes, "frame")
    for k in range(n) if indices is None else indices:
        if not 0 <= k < n:
            raise IndexError(f"{p}: frame {k} outside the store's {n} frames")
        yield (
            k,
            st.times_s[k],
            np.array(st._read_chunk("cube", k)[0], np.float32),
            np.array(st._read_chunk("valid", k)[0], bool),
        )  # fmt: skip (writable copies)


def write_animated_preview(
    store: str | os.PathLike,
    path: str | os.PathLike,
    *,
    fps: float = 5.0,
    max_frames: int = 300,
    max_side: int = 480,
    percentile: float = 99.5,
) -> Path | None:
    """An animated sRGB GIF of the store's frames (Pillow; written atomically), one frame
    decoded at a time.

    All frames share one white (the ``percentile``-th luminance of the middle frame's valid
    pixels, of those shown), so that a brightening scene is seen to brighten (per-frame
    normalisation would hide it). At most ``max_frames`` frames are shown (every k-th frame of a
    longer sequence) and each is shrunk (nearest neighbour) to at most ``max_side`` px on its
    longer side; the GIF's frame duration is ``1 / fps`` (the times themselves are in the store).

    Returns:
        ``path``, or ``None`` when the store has no frame.
    """
    from PIL import Image  # lazy: Pillow (a dependency of matplotlib) only for the GIF

    p = _checked(store)
    st = SequenceStore(p)
    st._load()
    n = len(st.sources)
    if n == 0:
        return None
    wl = torch.tensor(st.wavelengths_nm, dtype=torch.float64)
    stride = max(1, -(-n // max(1, int(max_frames))))
    idx = list(range(0, n, stride))
    h, w = st.frame_size
    step = max(1, -(-max(h, w) // max(1, int(max_side))))
    _, _, mid, mid_valid = next(iter_store_frames(p, [idx[len(idx) // 2]]))
    mid = np.nan_to_num(mid[:, ::step, ::step])  # the white from the pixels shown
    y = cube_to_xyz(torch.from_numpy(mid).double(), wl)[1]
    vals = y[torch.from_numpy(np.ascontiguousarray(mid_valid[::step, ::step]))]
    ref = float(torch.quantile(vals, percentile / 100.0)) if vals.numel() else 1.0
    ref = ref if ref > 0 else 1.0
    images = []
    for _, _, cube, valid in iter_store_frames(p, idx):
        c = torch.from_numpy(np.nan_to_num(cube[:, ::step, ::step])).double()
        rgb = cube_to_srgb(
            c,
            wl,
            normalise=None,
            exposure=1.0 / ref,
            valid=torch.from_numpy(np.ascontiguousarray(valid[::step, ::step])))
        u8 = (rgb.clamp(0, 1) * 255).round().to(torch.uint8).permute(1, 2, 0).numpy()
        images.append(Image.fromarray(np.ascontiguousarray(u8), "RGB").quantize(colors=255))
    out = Path(path)
    with atomic_write(out, "wb") as f:
        images[0].save(f, format="GIF", save_all=True, append_images=images[1:],
                       duration=max(20, int(round(1000.0 / fps))), loop=0)  # fmt: skip
    return out
