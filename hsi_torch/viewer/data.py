"""What the viewer shows, without napari: cubes read into layer data, spectra at points.

:func:`read_layers` turns any cube file this package writes (OME-TIFF ``.tif``, ENVI
``.hdr/.img``, ``.npz``, NetCDF ``.nc``, a Zarr cube ``.zarr``, the run's Zarr store
``cubes.zarr`` with its frame axis and a sequence store ``sequence.zarr`` with its time axis) into
napari layer-data tuples ``(data, kwargs, "image")``:

* the **band stack** ``(M, h, w)`` (``(F, M, h, w)`` for the run store), float32, NaN where not
  valid; its band axis is scaled to nanometres when the grid is uniform (``scale`` = step,
  ``translate`` = first band: the viewer's band coordinate *is* the wavelength) and the layer's
  ``metadata`` holds ``wavelengths_nm``, ``valid``, ``std`` (when the ``_std`` companion or the
  NPZ key ``std`` exists), the file and the ``findings`` stored with the cube
  (:class:`~hsi_torch.findings.Finding` list; a cube file's, not a run store's); a cube with
  warnings or errors says so in its layers' names (``"scene (bands) (!) 2 warnings"``);
* the **sRGB composite** ``(h, w, 3)`` (``(F, h, w, 3)``; CIE 1931, D65, 99.5th percentile of
  luminance as white, :func:`~hsi_torch.colour.cube_to_srgb`), black where not valid.

A sequence store is read lazily (Dask arrays, one frame decoded when napari shows it, its sRGB
composite computed then; the viewer's slider moves along ``time``), so a sequence of any length
opens: only one frame must fit ``$HSI_TORCH_MAX_CUBE_GB``. The layers' ``metadata`` also hold
``frames`` (the inputs) and ``times_s``.

A file is decoded only after the size it declares is checked against
``$HSI_TORCH_MAX_CUBE_GB`` (:mod:`hsi_torch.io.bounded`; a run store's files must also be regular
files, its metadata bounded), so a small compressed file cannot make the viewer allocate
gigabytes.

:func:`spectrum_at` returns the spectrum (and σ) under a point, refusing points outside the valid
mask. The napari side (reader, dock widget) is :mod:`hsi_torch.viewer.plugin`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from hsi_torch.colour import cube_to_srgb
from hsi_torch.errors import FileFormatError
from hsi_torch.findings import Finding, findings_summary
from hsi_torch.io.bounded import check_declared, read_json_bounded
from hsi_torch.io.cube import load_cube
from hsi_torch.io.sequence_store import is_sequence_store, open_sequence_store

__all__ = [
    "CUBE_SUFFIXES",
    "is_cube_path",
    "std_companion",
    "read_layers",
    "Spectrum",
    "spectrum_at",
    "band_axis",
    "LazyFrames",
]

#: File suffixes the reader accepts (a ``.zarr`` folder is a cube or the run store).
CUBE_SUFFIXES = (".tif", ".tiff", ".hdr", ".img", ".npz", ".nc", ".zarr")

LayerData = tuple[Any, dict[str, Any], str]


def is_cube_path(path: str | os.PathLike) -> bool:
    """True when the path has a cube suffix and is not itself a ``_std`` companion."""
    p = Path(path)
    return p.suffix.lower() in CUBE_SUFFIXES and not _stem(p).endswith("_std")


def _stem(p: Path) -> str:
    name = p.name
    for s in (".ome.tif", ".ome.tiff"):
        if name.lower().endswith(s):
            return name[: -len(s)]
    return p.stem


def std_companion(path: str | os.PathLike) -> Path | None:
    """``<stem>_std.<suffix>`` beside a cube file (the reconstruction's per-band σ), if any."""
    p = Path(path)
    cand = p.with_name(_stem(p) + "_std" + p.suffix)
    if p.suffix.lower() == ".img":
        cand = cand.with_suffix(".hdr")
    if cand.suffix.lower() == ".hdr":
        return cand if cand.exists() and cand.with_suffix(".img").exists() else None
    return cand if cand.exists() else None


def _is_run_store(p: Path) -> bool:
    attrs = p / ".zattrs"
    if not (p.is_dir() and attrs.exists()):
        return False
    meta = read_json_bounded(attrs, "store attributes")  # a FIFO or a bomb refused by name
    return isinstance(meta, dict) and "hsi_torch_dataset" in meta


def band_axis(wavelengths_nm: np.ndarray) -> tuple[float, float] | None:
    """``(translate, scale)`` mapping band index to nm, or None when the grid is not uniform."""
    wl = np.asarray(wavelengths_nm, np.float64)
    if wl.size < 2:
        return (float(wl[0]) if wl.size else 0.0), 1.0
    step = np.diff(wl)
    if np.allclose(step, step[0], rtol=1e-6, atol=1e-9) and step[0] > 0:
        return float(wl[0]), float(step[0])
    return None


def _srgb(cube: np.ndarray, wl: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """``(..., M, h, w)`` → ``(..., h, w, 3)`` float32 sRGB in [0, 1], black where not valid."""
    rgb = cube_to_srgb(torch.from_numpy(np.ascontiguousarray(cube, np.float32)),
                       torch.from_numpy(np.array(wl, np.float64)), normalise="percentile",
                       valid=torch.from_numpy(valid))  # fmt: skip
    return np.moveaxis(rgb.numpy(), -3, -1).astype(np.float32)


def _contrast(cube: np.ndarray) -> list[float]:
    finite = cube[np.isfinite(cube)]
    if finite.size == 0:
        return [0.0, 1.0]
    lo, hi = np.percentile(finite, [0.5, 99.5])
    return [float(lo), float(hi if hi > lo else lo + 1e-6)]


def _layers(
    name: str,
    cube: np.ndarray,
    wl: np.ndarray,
    valid: np.ndarray,
    std: np.ndarray | None,
    path: Path,
    frames: list[str] | None = None,
    findings: list[Finding] | None = None,
) -> list[LayerData]:
    ax = band_axis(wl)
    lead = cube.ndim - 3  # 1 with a frame axis
    meta = {"hsi_torch": True, "wavelengths_nm": wl, "valid": valid, "std": std,
            "path": str(path), "frames": frames, "findings": list(findings or [])}  # fmt: skip
    bad = [f for f in findings or [] if f.severity != "info"]
    flag = f" (!) {findings_summary(bad)}" if bad else ""
    kw: dict[str, Any] = {"name": f"{name} (bands){flag}", "metadata": meta,
                          "contrast_limits": _contrast(cube), "colormap": "gray"}  # fmt: skip
    if ax is not None:
        kw["scale"] = [1.0] * lead + [ax[1], 1.0, 1.0]
        kw["translate"] = [0.0] * lead + [ax[0], 0.0, 0.0]
        kw["units"] = ["pixel"] * lead + ["nm", "pixel", "pixel"]
    kw["axis_labels"] = (["frame"] if lead else []) + ["wavelength", "y", "x"]
    rgb_kw: dict[str, Any] = {"name": f"{name} (sRGB){flag}", "rgb": True,
                              "metadata": {"hsi_torch_srgb": True, "path": str(path)}}  # fmt: skip
    rgb_kw["axis_labels"] = (["frame"] if lead else []) + ["y", "x"]
    return [(cube, kw, "image"), (_srgb(cube, wl, valid), rgb_kw, "image")]


def read_layers(path: str | os.PathLike, max_bytes: int | None = None) -> list[LayerData]:
    """Layer-data tuples (band stack, sRGB composite) of a cube file or run store (module
    docstring). The cube's declared size is checked before it is decoded: at most
    ``max_bytes`` (default ``$HSI_TORCH_MAX_CUBE_GB`` GiB, :mod:`hsi_torch.io.bounded`).

    Raises:
        MissingFileError, FileFormatError: as :func:`~hsi_torch.io.cube.load_cube`.
    """
    p = Path(path)
    if p.suffix.lower() == ".zarr" and _is_run_store(p):
        return _read_run_store(p, max_bytes)
    if p.suffix.lower() == ".zarr" and is_sequence_store(p):
        return _read_sequence_store(p, max_bytes)
    c = load_cube(p, max_bytes=max_bytes)
    cube = c.cube.numpy()
    wl = c.wavelengths.numpy()
    valid = c.valid.numpy()
    std = None
    if p.suffix.lower() == ".npz":
        with np.load(p, allow_pickle=False) as z:
            if "std" in z:
                std = np.asarray(z["std"], np.float32)
    else:
        comp = std_companion(p)
        if comp is not None:
            std = load_cube(comp, max_bytes=max_bytes).cube.numpy()
    if std is not None and std.shape != cube.shape:
        raise FileFormatError(f"{p}: standard deviation {std.shape} does not match the cube "
                              f"{cube.shape}")  # fmt: skip
    cube = np.where(valid[None], cube, np.nan).astype(np.float32)
    return _layers(_stem(p), cube, wl, valid, std, p, findings=c.findings)


def _read_run_store(p: Path, max_bytes: int | None = None) -> list[LayerData]:
    from hsi_torch.io.dataset import open_dataset  # lazy: needs xarray + zarr (optional)

    ds = open_dataset(p)  # codecs, metadata and chunk files checked before any decoding
    done = np.asarray(ds["done"].values, bool)
    if not done.any():
        raise FileFormatError(f"{p}: the run store has no complete frame yet")
    idx = np.flatnonzero(done)
    check_declared(p, (idx.size, *ds["cube"].shape[1:]), ds["cube"].dtype, max_bytes,
                   f"set of {idx.size} complete frames")  # fmt: skip
    cube = np.asarray(ds["cube"].values[idx], np.float32)  # (F, M, h, w)
    valid = np.asarray(ds["valid"].values[idx], bool)
    wl = np.asarray(ds["wavelength"].values, np.float64)
    frames = [str(s) for s in np.asarray(ds["source"].values)[idx]]
    cube = np.where(valid[:, None], cube, np.nan).astype(np.float32)
    return _layers(_stem(p), cube, wl, valid, None, p, frames)


class LazyFrames:
    """A read-only ``(T, ...)`` array whose frame ``k`` is ``frame(k)``, computed only when
    indexed (what napari asks for: the frame shown); ``np.asarray`` of the whole computes every
    frame. Enough of the array protocol for napari's image layers (``shape``, ``dtype``,
    ``ndim``, ``__getitem__``, ``__array__``)."""

    def __init__(self, frame: Any, n: int, frame_shape: tuple[int, ...], dtype: Any) -> None:
        self._frame = frame
        self.shape = (int(n), *(int(v) for v in frame_shape))
        self.dtype = np.dtype(dtype)
        self.ndim = len(self.shape)
        self.size = int(np.prod(self.shape))

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, key: Any) -> np.ndarray:
        key = key if isinstance(key, tuple) else (key,)
        first, rest = key[0], key[1:]
        if isinstance(first, (int, np.integer)):
            k = int(first) + (self.shape[0] if int(first) < 0 else 0)
            if not 0 <= k < self.shape[0]:
                raise IndexError(f"frame {int(first)} outside {self.shape[0]} frames")
            return np.asarray(self._frame(k), self.dtype)[rest]
        ks = np.arange(self.shape[0])[first]
        stack = [np.asarray(self._frame(int(k)), self.dtype) for k in np.atleast_1d(ks)]
        out = np.stack(stack) if stack else np.empty((0, *self.shape[1:]), self.dtype)
        return out[(slice(None), *rest)]

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        out = self[:]
        return out if dtype is None else out.astype(dtype)


def _read_sequence_store(p: Path, max_bytes: int | None = None) -> list[LayerData]:
    """The band stack ``(T, M, h, w)`` and sRGB ``(T, h, w, 3)`` of a sequence store as
    :class:`LazyFrames` (one frame decoded at a time; the frame size checked first)."""
    ds = open_sequence_store(p)  # codecs, metadata and chunk files checked before decoding
    n = int(ds.sizes["time"])
    if n == 0:
        raise FileFormatError(f"{p}: the sequence store has no frame yet")
    m, h, w = (int(v) for v in ds["cube"].shape[1:])
    check_declared(p, (m, h, w), np.float32, max_bytes, "frame")
    wl = np.asarray(ds["wavelength"].values, np.float64)

    def cube_at(k: int) -> np.ndarray:
        return np.asarray(ds["cube"][k].values, np.float32)

    def valid_at(k: int) -> np.ndarray:
        return np.asarray(ds["valid"][k].values, bool)

    def rgb_at(k: int) -> np.ndarray:
        return _srgb(cube_at(k), wl, valid_at(k))

    cube = LazyFrames(cube_at, n, (m, h, w), np.float32)
    valid = LazyFrames(valid_at, n, (h, w), bool)
    (_, kw, _), (_, rgb_kw, _) = _layers(_stem(p), cube[0], wl, valid[0], None, p)
    for key, lead in (("scale", 1.0), ("translate", 0.0), ("units", "pixel")):
        if key in kw:
            kw[key] = [lead, *kw[key]]
    kw["axis_labels"] = ["time", *kw["axis_labels"]]
    rgb_kw["axis_labels"] = ["time", "y", "x"]
    kw["metadata"].update(valid=valid, frames=[str(s) for s in ds["source"].values],
                          times_s=np.asarray(ds["time"].values, np.float64))  # fmt: skip
    return [(cube, kw, "image"), (LazyFrames(rgb_at, n, (h, w, 3), np.float32), rgb_kw, "image")]


@dataclass
class Spectrum:
    """The spectrum under one pixel.

    Attributes:
        row, col: the pixel (integers); frame: the frame index (run store) or None.
        wavelengths_nm: ``(M,)``; values: ``(M,)``; std: ``(M,)`` or None.
    """

    row: int
    col: int
    wavelengths_nm: np.ndarray
    values: np.ndarray
    std: np.ndarray | None = None
    frame: int | None = None


def spectrum_at(
    data: np.ndarray, metadata: dict[str, Any], row: float, col: float, frame: int | None = None
) -> Spectrum | None:
    """The spectrum of a band-stack layer (``read_layers``' first tuple) at pixel ``(row, col)``
    (rounded to the nearest pixel); None outside the image or the valid mask."""
    r, c = int(round(float(row))), int(round(float(col)))
    valid = metadata["valid"]  # (a sequence's is lazy: only the frame shown is decoded)
    if data.ndim == 4:
        f = int(frame or 0)
        if not 0 <= f < data.shape[0]:
            return None
        stack, v = data[f], np.asarray(valid[f])
    else:
        f, stack, v = None, data, np.asarray(valid)
    h, w = v.shape
    if not (0 <= r < h and 0 <= c < w) or not bool(v[r, c]):
        return None
    std = metadata.get("std")
    sd = None
    if std is not None:
        sd = np.asarray(std[f] if data.ndim == 4 else std)[:, r, c].astype(np.float64)
    return Spectrum(row=r, col=c, wavelengths_nm=np.asarray(metadata["wavelengths_nm"]),
                    values=np.asarray(stack[:, r, c], np.float64), std=sd, frame=f)  # fmt: skip
