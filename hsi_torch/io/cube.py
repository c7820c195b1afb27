"""Spectral cubes on disk: multi-page float32 TIFF, ENVI ``.hdr/.img``, NPZ. All writes atomic.

Convention:
    - In memory a cube is ``(M, H, W)`` (band-first, like every image tensor in hsi_torch) with
      wavelengths ``(M,)`` in nm and an optional validity mask ``(H, W)`` bool.
    - **TIFF**: one float32 page per band, in wavelength order. The first page's
      ``ImageDescription`` is JSON: ``{"hsi_torch_cube": 1, "wavelengths_nm": [...],
      "wavelength_units": "nm", ...metadata}``.
    - **ENVI**: ``<stem>.hdr`` + ``<stem>.img``, BSQ, float32 little-endian (``data type = 4``,
      ``byte order = 0``), with ``wavelength = {...}`` and ``wavelength units = nm``, readable by
      ``spectral.envi.open`` and ENVI/QGIS/GDAL. The ``.img`` is written first, then the ``.hdr``.
    - **NPZ**: arrays ``cube (M,H,W) float32``, ``wavelengths_nm (M,) float64``,
      ``valid (H,W) bool``, ``metadata`` (JSON string).
    - TIFF and ENVI have no mask plane: pixels where ``valid`` is False are written as NaN, and on
      loading ``valid`` is "all bands finite". NPZ stores cube values untouched plus the mask.
"""

from __future__ import annotations

import json
import os
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from hsi_torch.errors import FileFormatError, MissingFileError
from hsi_torch.io.atomic import atomic_save_npz, atomic_write, json_default

__all__ = ["Cube", "save_cube", "save_cube_formats", "load_cube", "CubeFormat"]

CubeFormat = Literal["tiff", "envi", "npz"]
CUBE_FORMAT_VERSION = 1
_SUFFIX_FORMAT: dict[str, CubeFormat] = {
    ".tif": "tiff",
    ".tiff": "tiff",
    ".hdr": "envi",
    ".img": "envi",
    ".npz": "npz",
}
_FORMAT_SUFFIX = {"tiff": ".tif", "envi": ".hdr", "npz": ".npz"}


@dataclass
class Cube:
    """A spectral cube loaded from disk.

    Attributes:
        cube: ``(M, H, W)`` float32 (NaN where invalid for TIFF/ENVI files).
        wavelengths: ``(M,)`` float64, nm.
        valid: ``(H, W)`` bool.
        metadata: the stored metadata (TIFF/NPZ JSON; ENVI header fields).
        path: the file read.
    """

    cube: torch.Tensor
    wavelengths: torch.Tensor
    valid: torch.Tensor
    metadata: dict[str, Any] = field(default_factory=dict)
    path: Path | None = None


def _np(x: Any) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy()
    return np.asarray(x)


def _format_of(p: Path, fmt: CubeFormat | None) -> CubeFormat:
    if fmt is not None:
        if fmt not in _FORMAT_SUFFIX:
            raise ValueError(f"fmt must be one of 'tiff', 'envi', 'npz', got {fmt!r}")
        return fmt
    try:
        return _SUFFIX_FORMAT[p.suffix.lower()]
    except KeyError:
        raise ValueError(
            f"{p}: cannot tell the cube format from suffix {p.suffix!r}; use .tif/.tiff, "
            ".hdr/.img (ENVI) or .npz"
        ) from None


def _prepare(
    cube: Any, wavelengths: Any, valid: Any | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    c = _np(cube)
    if c.ndim != 3:
        raise ValueError(f"cube must have shape (M, H, W), got {tuple(c.shape)}")
    if c.dtype.kind not in "uif":
        raise TypeError(f"cube must be numeric, got dtype {c.dtype}")
    wl = _np(wavelengths).astype(np.float64).ravel()
    if wl.shape != (c.shape[0],):
        raise ValueError(
            f"wavelengths must have shape ({c.shape[0]},) to match cube {tuple(c.shape)}, got "
            f"{tuple(_np(wavelengths).shape)}"
        )
    if not np.all(np.isfinite(wl)) or np.any(wl <= 0):
        raise ValueError("wavelengths must be finite and positive (nm)")
    if valid is None:
        v = np.isfinite(c).all(axis=0)
    else:
        v = _np(valid).astype(bool)
        if v.shape != c.shape[1:]:
            raise ValueError(f"valid must have shape {tuple(c.shape[1:])}, got {tuple(v.shape)}")
    return c.astype(np.float32, copy=False), wl, v


def _nan_where_invalid(c: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``c`` with NaN in every band where ``v`` is False; ``c`` itself when it already is
    (e.g. a cube from the reconstruction pipeline), else a copy (``c`` is never modified)."""
    inv = ~v
    if not inv.any():
        return c
    if all(np.isnan(band[inv]).all() for band in c):  # one band at a time: no cube-size temporary
        return c
    return np.where(v[None], c, np.float32(np.nan))


def save_cube(
    path: str | os.PathLike,
    cube: Any,
    wavelengths: Any,
    valid: Any | None = None,
    metadata: dict[str, Any] | None = None,
    fmt: CubeFormat | None = None,
) -> list[Path]:
    """Write a spectral cube atomically as TIFF, ENVI or NPZ (format from the suffix or ``fmt``).

    Args:
        path: ``*.tif``/``*.tiff``, ``*.hdr``/``*.img`` (ENVI pair) or ``*.npz``.
        cube: ``(M, H, W)`` tensor or array (stored as float32).
        wavelengths: ``(M,)`` band centres in nm.
        valid: optional ``(H, W)`` bool mask; default: pixels whose bands are all finite.
        metadata: JSON-serialisable extras (TIFF/NPZ; ENVI keeps only ``description``).
        fmt: force a format.

    Returns:
        The files written (two for ENVI: ``.img`` then ``.hdr``).
    """
    p = Path(path)
    kind = _format_of(p, fmt)
    c, wl, v = _prepare(cube, wavelengths, valid)
    return _save_prepared(p, kind, c, wl, v, metadata)


def _save_prepared(
    p: Path,
    kind: CubeFormat,
    c: np.ndarray,
    wl: np.ndarray,
    v: np.ndarray,
    metadata: dict[str, Any] | None,
    c_nan: np.ndarray | None = None,
) -> list[Path]:
    """:func:`save_cube` after :func:`_prepare`; ``c_nan``: ``c`` with NaN where invalid, if
    already made (TIFF/ENVI)."""
    meta = dict(metadata or {})
    if kind != "npz":
        c = c_nan if c_nan is not None else _nan_where_invalid(c, v)
    if kind == "npz":
        meta_json = json.dumps(
            {"hsi_torch_cube": CUBE_FORMAT_VERSION, **meta}, default=json_default
        )
        atomic_save_npz(
            p, {"cube": c, "wavelengths_nm": wl, "valid": v, "metadata": np.array(meta_json)}
        )
        return [p]
    if kind == "tiff":
        import tifffile

        desc = {
            "hsi_torch_cube": CUBE_FORMAT_VERSION,
            "wavelengths_nm": wl.tolist(),
            "wavelength_units": "nm",
            "shape": list(c.shape),
            **meta,
        }
        text = json.dumps(desc, default=json_default)
        with atomic_write(p, "wb") as f:
            tifffile.imwrite(f, c, photometric="minisblack", description=text, metadata=None)
        return [p]
    return _save_envi(p, c, wl, meta)


def _envi_paths(p: Path) -> tuple[Path, Path]:
    stem = p.with_suffix("")
    return stem.with_suffix(".hdr"), stem.with_suffix(".img")


def _save_envi(p: Path, c: np.ndarray, wl: np.ndarray, meta: dict[str, Any]) -> list[Path]:
    hdr, img = _envi_paths(p)
    m, h, w = c.shape
    desc = (
        str(meta.get("description", "hsi_torch spectral cube")).replace("{", "(").replace("}", ")")
    )
    lines = [
        "ENVI",
        f"description = {{{desc}}}",
        f"samples = {w}",
        f"lines = {h}",
        f"bands = {m}",
        "header offset = 0",
        "file type = ENVI Standard",
        "data type = 4",
        "interleave = bsq",
        "byte order = 0",
        "wavelength units = nm",
        "wavelength = {" + ", ".join(f"{x:.10g}" for x in wl) + "}",
        "band names = {" + ", ".join(f"{x:.10g} nm" for x in wl) + "}",
    ]
    with atomic_write(img, "wb") as f:  # the array's own buffer, no bytes copy
        f.write(memoryview(np.ascontiguousarray(c, dtype="<f4")).cast("B"))
    try:
        with atomic_write(hdr, "w") as f:
            f.write("\n".join(lines) + "\n")
    except BaseException:
        img.unlink(missing_ok=True)  # no data file without its header
        raise
    return [img, hdr]


def save_cube_formats(
    stem: str | os.PathLike,
    cube: Any,
    wavelengths: Any,
    valid: Any | None = None,
    metadata: dict[str, Any] | None = None,
    formats: Sequence[CubeFormat] = ("npz", "tiff", "envi"),
    timings: dict[str, float] | None = None,
) -> list[Path]:
    """Write the cube in several formats: ``<stem>.npz``, ``<stem>.tif``, ``<stem>.hdr/.img``.

    The same files as :func:`save_cube` per format; the cube is converted (and NaN-filled for
    TIFF/ENVI) once. If one format fails, the files already written by this call are removed.
    ``timings``: if given, receives the seconds spent per format (``"prepare"`` for the shared
    conversion).
    """
    s = Path(stem)
    for fmt in formats:
        if fmt not in _FORMAT_SUFFIX:
            raise ValueError(f"formats: unknown cube format {fmt!r} (tiff, envi, npz)")
    t0 = time.perf_counter()
    c, wl, v = _prepare(cube, wavelengths, valid)
    c_nan = _nan_where_invalid(c, v) if any(f != "npz" for f in formats) else None
    tm = timings if timings is not None else {}
    tm["prepare"] = time.perf_counter() - t0
    out: list[Path] = []
    try:
        for fmt in formats:
            t0 = time.perf_counter()
            p = s.with_name(s.name + _FORMAT_SUFFIX[fmt])
            out += _save_prepared(p, fmt, c, wl, v, metadata, c_nan)
            tm[fmt] = time.perf_counter() - t0
    except BaseException:
        for q in out:
            q.unlink(missing_ok=True)
        raise
    return out


def load_cube(
    path: str | os.PathLike,
    wavelengths: Any | None = None,
    device: torch.device | str | None = None,
) -> Cube:
    """Read a cube written by :func:`save_cube` or by other tools (ENVI any interleave/dtype via
    ``spectral``; TIFF stacks ``(M, H, W)``; NPZ with ``cube`` + ``wavelengths_nm``).

    Args:
        path: ``.tif/.tiff``, ``.hdr/.img`` or ``.npz``.
        wavelengths: ``(M,)`` nm, required only for files that do not carry them.
        device: device of the returned tensors.

    Returns:
        :class:`Cube` (float32 cube ``(M, H, W)``, float64 wavelengths in nm, bool valid
        ``(H, W)``).

    Raises:
        MissingFileError (a FileNotFoundError), FileFormatError (unreadable/truncated, no
            wavelengths, shape mismatch).
    """
    p = Path(path)
    kind = _format_of(p, None)
    if kind == "envi":
        hdr, _ = _envi_paths(p)
        if not hdr.exists():
            raise MissingFileError(f"ENVI header not found: {hdr}")
    elif not p.exists():
        raise MissingFileError(f"cube file not found: {p}")
    valid: np.ndarray | None = None
    meta: dict[str, Any] = {}
    wl: np.ndarray | None = None
    try:
        if kind == "npz":
            with np.load(p, allow_pickle=False) as z:
                if "cube" not in z:
                    raise FileFormatError(
                        f"{p}: NPZ has no array 'cube' (found {sorted(z.keys())})"
                    )
                c = z["cube"]
                wl = z["wavelengths_nm"] if "wavelengths_nm" in z else None
                valid = z["valid"].astype(bool) if "valid" in z else None
                meta = json.loads(str(z["metadata"])) if "metadata" in z else {}
        elif kind == "tiff":
            import tifffile

            from hsi_torch.io.captures import quiet_tifffile

            with quiet_tifffile(), tifffile.TiffFile(p) as tif:
                c = tif.asarray()
                desc = tif.pages[0].description if len(tif.pages) else ""
            try:
                parsed = json.loads(desc) if desc else {}
            except json.JSONDecodeError:
                parsed = {}
            meta = parsed if isinstance(parsed, dict) else {}
            if "wavelengths_nm" in meta:
                wl = np.asarray(meta["wavelengths_nm"], dtype=np.float64)
            if c.ndim == 2:
                c = c[None]
        else:
            c, wl, meta = _load_envi(p)
    except FileFormatError:
        raise
    except Exception as exc:
        raise FileFormatError(
            f"{p}: cannot read {kind.upper()} cube ({type(exc).__name__}: {exc}); the file is "
            "corrupt or truncated"
        ) from exc
    if c.ndim != 3:
        raise FileFormatError(f"{p}: cube must be 3-D (M, H, W), got shape {tuple(c.shape)}")
    if wavelengths is not None:
        wl = _np(wavelengths).astype(np.float64).ravel()
    if wl is None:
        raise FileFormatError(f"{p}: the file carries no wavelengths; pass wavelengths=")
    wl = np.asarray(wl, dtype=np.float64).ravel()
    if wl.shape[0] != c.shape[0]:
        raise FileFormatError(
            f"{p}: {wl.shape[0]} wavelengths for a cube with {c.shape[0]} bands {tuple(c.shape)}"
        )
    c = c.astype(np.float32)
    if valid is None:
        valid = np.isfinite(c).all(axis=0)
    elif valid.shape != c.shape[1:]:
        raise FileFormatError(f"{p}: valid mask {valid.shape} does not match cube {c.shape}")
    return Cube(
        cube=torch.from_numpy(np.ascontiguousarray(c)).to(device),
        wavelengths=torch.from_numpy(wl).to(device),
        valid=torch.from_numpy(np.ascontiguousarray(valid)).to(device),
        metadata=meta,
        path=p,
    )


_UNIT_TO_NM = {
    "nm": 1.0,
    "nanometers": 1.0,
    "nanometer": 1.0,
    "um": 1e3,
    "µm": 1e3,
    "micrometers": 1e3,
    "micrometer": 1e3,
    "microns": 1e3,
    "micron": 1e3,
    "mm": 1e6,
    "millimeters": 1e6,
}


def _load_envi(p: Path) -> tuple[np.ndarray, np.ndarray | None, dict[str, Any]]:
    import spectral.io.envi as envi

    hdr, img = _envi_paths(p)
    image = envi.open(str(hdr), str(img) if img.exists() else None)
    h, w, m = image.nrows, image.ncols, image.nbands
    expected = image.offset + h * w * m * np.dtype(image.dtype).itemsize
    actual = Path(image.filename).stat().st_size
    if actual < expected:
        raise FileFormatError(
            f"{image.filename}: ENVI data file is truncated ({actual} bytes, header needs "
            f"{expected})"
        )
    with warnings.catch_warnings():  # NaN marks invalid pixels here; not worth a warning
        warnings.simplefilter("ignore")
        arr = np.asarray(image.load())  # (lines, samples, bands)
    meta = dict(image.metadata)
    wl = None
    centers = image.bands.centers
    if centers:
        unit = (image.bands.band_unit or "nm").strip().lower()
        scale = _UNIT_TO_NM.get(unit)
        if scale is None:
            raise FileFormatError(f"{hdr}: unknown wavelength units {image.bands.band_unit!r}")
        wl = np.asarray(centers, dtype=np.float64) * scale
    return arr.transpose(2, 0, 1), wl, meta
