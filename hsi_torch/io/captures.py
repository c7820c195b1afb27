"""Capture files: 16-bit TIFF with JSON metadata, PNG, NPY/NPZ, camera RAW — one linear reader.

:func:`write_capture` writes (and :func:`read_capture` reads back) a single-page uncompressed
**uint16 TIFF**: a Bayer mosaic as a grey ``H×W`` page (``kind = "bayer"``) or an ``H×W×3`` RGB
page (``kind = "rgb"``); its ``ImageDescription`` is a JSON object with ``"hsi_torch_capture": 1``
(format version), ``"kind"``, ``"cfa_pattern"`` (required for Bayer), ``"black_level"`` (scalar,
4 values for the Bayer cell positions in row-major order, or 3 for R, G, B), ``"white_level"``
(DN), ``"exposure_s"``, ``"wavelength_nm"``, ... (any JSON-serialisable keys are kept).

:func:`read_any` turns any supported file into *linear* RGB ``(3, H, W)`` (value = stored − black,
float, DN; or normalised to the white level), a saturation mask and the metadata; the suffixes,
the value convention and the metadata contract are in ``docs/io_config_cli.md``, *Captures in*.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from hsi_torch.devices import to_numpy
from hsi_torch.errors import FileFormatError, MissingFileError
from hsi_torch.io.atomic import atomic_write, json_default
from hsi_torch.io.bounded import declared_image_size, image_hw, npy_header, require_npz
from hsi_torch.io.radiometry import capture_exposure
from hsi_torch.io.raw import (
    RAW_SUFFIXES,
    DemosaicMethod,
    demosaic_saturation,
    load_raw,
    validate_cfa_pattern,
)
from hsi_torch.io.raw import demosaic as _demosaic  # read_any's argument shadows the name
from hsi_torch.io.safety import require_regular_file, unreadable_as_format_error

__all__ = [
    "CAPTURE_FORMAT_VERSION",
    "LinearCapture",
    "write_capture",
    "read_capture",
    "read_any",
    "SUPPORTED_SUFFIXES",
    "SETTING_SOURCES",
    "CaptureDefaults",
    "black_level_rule",
]

CAPTURE_FORMAT_VERSION = 1
_TIFF_SUFFIXES = (".tif", ".tiff")
_PNG_SUFFIXES = (".png",)
SUPPORTED_SUFFIXES = (*_TIFF_SUFFIXES, *_PNG_SUFFIXES, ".npy", ".npz", *RAW_SUFFIXES)
#: Where a setting in a capture's metadata came from (``exposure_source``, ``black_level_source``):
#: the file itself, a capture sheet, a capture-set manifest, the command's configuration, or the
#: reader's default.
SETTING_SOURCES = ("file", "sheet", "manifest", "config", "default")


@dataclass(frozen=True)
class CaptureDefaults:
    """What a capture file that does not say it gets from its calibration (and the run's
    settings): :func:`read_any` applies these, once, where it reads the file.

    Attributes:
        black_level_rgb: ``(R, G, B)`` DN the calibration subtracted from its own captures (the
            files' black level plus the dark frames' mean; source ``"bundle"``), for a file
            without a black level of its own (:func:`black_level_rule`).
        cfa_pattern: the pattern of a Bayer file that names none (e.g. the bundle's).
        exposure_s: the exposure time (s) of a file whose metadata has none (source
            ``"config"``).
    """

    black_level_rgb: tuple[float, float, float] | None = None
    cfa_pattern: str | None = None
    exposure_s: float | None = None


def black_level_rule(
    given: Any, given_source: str, file_level: Any, default_rgb: Any = None
) -> tuple[Any, str]:
    """Which black level applies to a capture, and its source — the one rule, for calibration
    and reconstruction alike: the level given (a setting, a sheet or manifest: ``given_source``),
    else the file's own (``"file"``), else the calibration's ``(R, G, B)`` (``"bundle"``; only
    when not all zero), else 0 (``"default"``)."""
    if given is not None:
        return given, given_source
    if file_level is not None:
        return file_level, "file"
    if default_rgb is not None and any(float(v) != 0 for v in default_rgb):
        return [float(v) for v in default_rgb], "bundle"
    return 0.0, "default"


def _rgb_as_cell(rgb: list[float], pattern: str) -> list[float]:
    """An ``(R, G, B)`` level as the 4 values of the Bayer cell of ``pattern`` (row-major):
    subtracting it from the mosaic equals subtracting ``rgb`` from either demosaic (both form a
    colour from its own sites with weights summing to one)."""
    return [rgb["RGB".index(c)] for c in pattern]


@dataclass
class LinearCapture:
    """A capture converted to linear RGB.

    Attributes:
        image: ``(3, H', W')`` float linear RGB (stored value − black level, DN; or normalised).
        saturated: ``(3, H', W')`` bool, the stored value reached the white level (propagated
            through the demosaic for Bayer inputs).
        metadata: the file's metadata plus the resolved ``kind``, ``black_level``, ``white_level``,
            ``cfa_pattern`` (Bayer), ``demosaic`` (Bayer), ``source`` (path as str).
        path: source file.
        mosaic: ``(1, H, W)`` linear mosaic for Bayer inputs (before demosaic), else ``None``.
    """

    image: torch.Tensor
    saturated: torch.Tensor
    metadata: dict[str, Any]
    path: Path
    mosaic: torch.Tensor | None = None
    mosaic_saturated: torch.Tensor | None = field(default=None, repr=False)


# ----------------------------------------------------------------------------------------------
# writing


def write_capture(
    path: str | os.PathLike, image: Any, metadata: dict[str, Any] | None = None
) -> Path:
    """Write a capture as a 16-bit TIFF with JSON metadata, atomically.

    Args:
        path: destination (``.tif`` or ``.tiff``).
        image: ``(1, H, W)`` or ``(H, W)`` Bayer mosaic, or ``(3, H, W)`` RGB; tensor or array of
            stored DN. Integer data must lie in [0, 65535]; floating data must be finite and in
            [0, 65535] and is rounded to the nearest integer.
        metadata: JSON-serialisable dict (see module docstring). ``kind`` is inferred from the
            channel count when absent; a Bayer capture needs ``cfa_pattern``.

    Returns:
        The path written.
    """
    import tifffile

    p = Path(path)
    if p.suffix.lower() not in _TIFF_SUFFIXES:
        raise ValueError(f"capture path must end in .tif or .tiff, got {p}")
    arr = to_numpy(image)
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3 or arr.shape[0] not in (1, 3):
        raise ValueError(
            f"image must have shape (1, H, W) (Bayer) or (3, H, W) (RGB), got {tuple(arr.shape)}")
    if arr.dtype.kind not in "uif":
        raise TypeError(f"image must be integer or floating point, got dtype {arr.dtype}")
    if arr.dtype.kind == "f":
        if not np.isfinite(arr).all():
            raise ValueError(f"image has {int((~np.isfinite(arr)).sum())} non-finite values")
        arr = np.rint(arr)
    if arr.size and (arr.min() < 0 or arr.max() > 65535):
        raise ValueError(
            f"image values must lie in [0, 65535] for a 16-bit capture, got "
            f"[{arr.min()}, {arr.max()}]")
    arr = arr.astype(np.uint16)
    meta = dict(metadata or {})
    kind = meta.get("kind", "bayer" if arr.shape[0] == 1 else "rgb")
    if kind not in ("bayer", "rgb") or (kind == "bayer") != (arr.shape[0] == 1):
        raise ValueError(
            f"metadata kind {kind!r} does not match an image with {arr.shape[0]} channel(s)")
    if kind == "bayer":
        if "cfa_pattern" not in meta:
            raise ValueError("a Bayer capture needs metadata['cfa_pattern'] (e.g. 'RGGB')")
        meta["cfa_pattern"] = validate_cfa_pattern(meta["cfa_pattern"])
    meta["kind"] = kind
    meta["hsi_torch_capture"] = CAPTURE_FORMAT_VERSION
    description = json.dumps(meta, default=json_default)
    with atomic_write(p, "wb") as f:
        if kind == "bayer":
            tifffile.imwrite(f, arr[0], photometric="minisblack", description=description,
                             metadata=None)  # fmt: skip
        else:
            tifffile.imwrite(f, np.ascontiguousarray(arr.transpose(1, 2, 0)), photometric="rgb",
                             description=description, metadata=None)  # fmt: skip
    return p


# ----------------------------------------------------------------------------------------------
# reading (storage level)


def _check_exists(p: Path) -> None:
    """A capture must be a regular file (a symlink to one is fine), checked before it is
    opened: a folder, a FIFO (which would block the reader forever), a device or a socket is
    refused by name."""
    if not p.exists() and not p.is_symlink():
        raise MissingFileError(f"capture file not found: {p}")
    if p.is_dir():
        raise FileFormatError(f"{p}: is a directory, expected a capture file")
    require_regular_file(p, "capture file")


def _as_chw(arr: np.ndarray, p: Path, meta: dict[str, Any]) -> tuple[np.ndarray, str]:
    """Bring a stored array to (C, H, W) with C in {1, 3}; returns it and the kind."""
    kind = meta.get("kind")
    if arr.ndim == 2:
        arr = arr[None]
    elif arr.ndim == 3 and arr.shape[0] in (1, 3):
        pass
    elif arr.ndim == 3 and arr.shape[-1] in (1, 3):
        arr = arr.transpose(2, 0, 1)
    else:
        raise FileFormatError(
            f"{p}: image has shape {tuple(arr.shape)}; expected (H, W) or (1, H, W) for a Bayer "
            "mosaic, or (3, H, W) / (H, W, 3) for RGB")
    if min(arr.shape) == 0:
        raise FileFormatError(f"{p}: the image is empty (shape {tuple(arr.shape)})")
    inferred = "bayer" if arr.shape[0] == 1 else "rgb"
    if kind is not None and kind != inferred:
        raise FileFormatError(
            f"{p}: metadata says kind={kind!r} but the image has {arr.shape[0]} channel(s)")
    return arr, inferred


def _check_dtype(arr: np.ndarray, p: Path) -> None:
    if arr.dtype.kind not in "uif" or arr.dtype.itemsize > 8:
        raise FileFormatError(
            f"{p}: unsupported pixel dtype {arr.dtype}; expected unsigned/signed integers or floats"
        )
    if arr.dtype.kind == "f":
        bad = ~np.isfinite(arr)
        if bad.any():
            raise FileFormatError(f"{p}: image contains {int(bad.sum())} NaN/inf values")
    if arr.dtype.kind == "f" or arr.dtype.itemsize > 4:  # 64-bit integers too (< 2^32 else)
        top = max(abs(float(arr.max())), abs(float(arr.min()))) if arr.size else 0.0
        if top > MAX_SAMPLE_VALUE:
            raise FileFormatError(
                f"{p}: image values reach {top:.3g}, beyond any sensor's range (at most "
                f"{MAX_SAMPLE_VALUE:.3g} = 2^50 is accepted: the reconstruction works in float32, "
                "whose squares overflow near 1.8e19); rescale the capture to sensor counts (DN)")
    if arr.dtype.kind in "if" and arr.size and arr.min() < 0:
        raise FileFormatError(f"{p}: image contains negative stored values (min {arr.min()})")


#: Largest decoded capture accepted (bytes); a header asking for more is refused before reading.
MAX_CAPTURE_BYTES = 8 << 30
#: Largest magnitude of a stored sample accepted (float files): 2^50, far above any sensor's count.
MAX_SAMPLE_VALUE = float(2**50)
#: Largest metadata text of an NPZ capture (bytes, from its header, before it is decoded).
_MAX_META_BYTES = 16 << 20


def _check_header(
    p: Path, shape: tuple[int, ...], dtype: np.dtype, expected_size: tuple[int, int] | None,
    available: int | None = None,
) -> None:
    """Size checks from a file's header, before any pixel is decoded: a usable image shape
    (``(H, W)``, ``(C, H, W)`` or ``(H, W, C)`` with ``C`` 1 or 3: anything else is refused
    here, so that a compressed file cannot make the reader decode more than one sensor image),
    the expected sensor size, a sane byte count, and (uncompressed data) no more bytes than the
    file holds. The decoded size is therefore bounded by ``H·W·3`` samples of the expected
    sensor size before decoding starts, whatever the compression."""
    shape = tuple(int(v) for v in shape)
    hw = image_hw(shape)
    if hw is None:
        raise FileFormatError(
            f"{p}: the header describes an image of shape {shape} ({dtype}); expected (H, W) or "
            "(1, H, W) for a Bayer mosaic, or (3, H, W) / (H, W, 3) for RGB (refused before "
            "decoding)")
    if min(shape) < 1:
        raise FileFormatError(f"{p}: the image is empty (shape {shape})")
    _check_size(p, hw, expected_size)
    nbytes = int(np.prod(shape, dtype=np.float64) * max(1, dtype.itemsize))
    if nbytes > MAX_CAPTURE_BYTES:
        raise FileFormatError(
            f"{p}: the header describes a {'x'.join(map(str, shape))} {dtype} image "
            f"({nbytes / 2**30:.1f} GiB), more than a capture can be "
            f"({MAX_CAPTURE_BYTES / 2**30:.0f} GiB)")
    if available is not None and nbytes > available:
        raise FileFormatError(
            f"{p}: the header describes a {'x'.join(map(str, shape))} {dtype} image "
            f"({nbytes} bytes) but the file holds only {available} bytes of data: truncated")


@contextlib.contextmanager
def _quiet(logger: str) -> Iterator[None]:
    """Silence a library's log messages while it reads a file (unnamed lines such as
    "incorrect StripOffsets count", a foreign file's odd EXIF tags): our own error names the
    file instead."""
    log = logging.getLogger(logger)
    level = log.level
    log.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        log.setLevel(level)


def quiet_tifffile() -> contextlib.AbstractContextManager[None]:
    """Silence tifffile's log messages about a damaged file while reading (:func:`_quiet`)."""
    return _quiet("tifffile")


def exif_tags(p: str | os.PathLike) -> dict[str, Any]:
    """The EXIF tags of a TIFF or camera RAW/DNG (``exifread``, its messages silenced), ``{}``
    when it has no readable EXIF."""
    import exifread  # lazy: only TIFF and RAW files have EXIF to read

    try:
        with _quiet("exifread"), open(p, "rb") as f:
            return exifread.process_file(f, details=False)
    except Exception:  # noqa: BLE001 - EXIF is optional information; the pixels are read elsewhere
        return {}


def _read_tiff(
    p: Path, expected_size: tuple[int, int] | None = None, page: int | None = None
) -> tuple[np.ndarray, dict[str, Any]]:
    import tifffile

    with unreadable_as_format_error(p, "TIFF"):
        with quiet_tifffile(), tifffile.TiffFile(p) as tif:
            if page is not None:  # one page of a multi-page TIFF (a sequence's frame)
                return _read_tiff_page(p, tif, page, expected_size)
            if not tif.series:
                raise FileFormatError(f"{p}: TIFF file has no image data")
            if len(tif.series) > 1:
                raise FileFormatError(
                    f"{p}: TIFF holds {len(tif.series)} image series; a capture has exactly one")
            desc = tif.pages[0].description if len(tif.pages) else ""
            series = tif.series[0]
            page = series.pages[0] if len(series.pages) else None
            raw = None
            if page is not None and getattr(page, "compression", None) == 1:  # uncompressed
                end = max((o + c for o, c in zip(page.dataoffsets, page.databytecounts,
                                                 strict=False)), default=0)  # fmt: skip
                raw = min(p.stat().st_size, end) - min(page.dataoffsets, default=0)
                raw = max(0, raw) * max(1, len(series.pages))
            _check_header(p, series.shape, np.dtype(series.dtype), expected_size, raw)
            arr = series.asarray()
    return arr, _description_metadata(desc)


def _description_metadata(desc: str | None) -> dict[str, Any]:
    """Our JSON metadata in a TIFF page's description; a foreign description is ignored."""
    try:
        parsed = json.loads(desc or "")
    except (json.JSONDecodeError, RecursionError):
        return {}
    return parsed if isinstance(parsed, dict) else {}


def _read_tiff_page(
    p: Path, tif: Any, page: int, expected_size: tuple[int, int] | None
) -> tuple[np.ndarray, dict[str, Any]]:
    """Page ``page`` of an open multi-page TIFF, checked from its header before decoding."""
    n = len(tif.pages)
    if not 0 <= page < n:
        raise FileFormatError(f"{p}: no page {page} (the TIFF has {n} page(s))")
    pg = tif.pages[page]
    _check_header(p, tuple(pg.shape), np.dtype(pg.dtype), expected_size)
    return pg.asarray(), {**_description_metadata(pg.description), "page": page}


def _parse_metadata(text: str, where: str) -> dict[str, Any]:
    """Our JSON metadata (an object); errors name ``where`` (file and key)."""
    try:
        meta = json.loads(text)
    except (json.JSONDecodeError, RecursionError) as exc:
        raise FileFormatError(f"{where} is not valid JSON ({exc})") from None
    if not isinstance(meta, dict):
        raise FileFormatError(f"{where} must be a JSON object, got {type(meta).__name__}")
    return meta


def _read_npy(
    p: Path, expected_size: tuple[int, int] | None = None
) -> tuple[np.ndarray, dict[str, Any]]:
    with unreadable_as_format_error(p, "NPY"):
        with open(p, "rb") as f:
            shape, dtype = npy_header(f)
            available = p.stat().st_size - f.tell()
        _check_header(p, shape, dtype, expected_size, available)
        arr = np.load(p, allow_pickle=False)
    meta: dict[str, Any] = {}
    side = p.with_name(p.name + ".json")
    if side.exists() or side.is_symlink():
        require_regular_file(side, "metadata sidecar")  # a FIFO would block, /dev/zero fill RAM
        if side.stat().st_size > _MAX_META_BYTES:
            raise FileFormatError(f"{side}: the metadata sidecar holds {side.stat().st_size} "
                                  f"bytes, more than {_MAX_META_BYTES // 2**20} MiB")  # fmt: skip
        try:
            text = side.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise FileFormatError(f"{side}: cannot read the metadata sidecar ({exc})") from None
        meta = _parse_metadata(text, f"{side}: the metadata sidecar")
    return arr, meta


def _read_npz(
    p: Path, expected_size: tuple[int, int] | None = None
) -> tuple[np.ndarray, dict[str, Any]]:
    require_npz(p)  # else numpy's hint about allow_pickle, for a file that is no NPZ
    with unreadable_as_format_error(p, "NPZ"):
        with np.load(p, allow_pickle=False) as z:
            keys = list(z.keys())
            if "image" in keys:
                key = "image"
            elif len([k for k in keys if k != "metadata"]) == 1:
                key = next(k for k in keys if k != "metadata")
            else:
                raise FileFormatError(
                    f"{p}: NPZ must hold an array named 'image' (found {sorted(keys)})")
            info = z.zip.getinfo(key + ".npy")
            with z.zip.open(info) as f:
                shape, dtype = npy_header(f)
                header_len = f.tell()
            raw = info.file_size - header_len if info.compress_type == 0 else None
            _check_header(p, shape, dtype, expected_size, raw)
            if "metadata" in keys:  # a text: its header too, before it is decoded
                with z.zip.open(z.zip.getinfo("metadata.npy")) as f:
                    mshape, mdtype = npy_header(f)
                if mshape != () or mdtype.kind not in "US" or mdtype.itemsize > _MAX_META_BYTES:
                    raise FileFormatError(
                        f"{p}: 'metadata' must be a JSON string (0-d str array) of at most "
                        f"{_MAX_META_BYTES // 2**20} MiB, the header says a {mdtype} array of "
                        f"shape {mshape}")
            arr = z[key]
            meta_text = None
            if "metadata" in keys:  # a 0-d str array (its header was checked)
                item = z["metadata"].item()
                meta_text = item.decode("utf-8") if isinstance(item, bytes) else str(item)
    meta = _parse_metadata(meta_text, f"{p}: 'metadata'") if meta_text else {}
    return arr, meta


_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
#: PNG colour types: 0 grey, 2 RGB, 3 palette, 4 grey + alpha, 6 RGB + alpha
_PNG_CHANNELS = {0: 1, 2: 3}


def _read_png(
    p: Path, expected_size: tuple[int, int] | None = None
) -> tuple[np.ndarray, dict[str, Any]]:
    """An 8- or 16-bit grey (Bayer mosaic) or RGB PNG as ``(H, W)`` / ``(H, W, 3)`` R, G, B.

    The header (``IHDR``) is checked before the pixels are decoded (sensor size, byte count);
    palette and alpha PNGs are refused (a capture is raw sensor data). PNGs carry no metadata
    here: black level, CFA pattern and exposure come from the caller (sheet, manifest, config)."""
    try:
        with open(p, "rb") as f:
            head = f.read(33)
    except OSError as exc:
        raise FileFormatError(f"{p}: cannot read PNG ({exc})") from None
    if len(head) < 33 or head[:8] != _PNG_MAGIC or head[12:16] != b"IHDR":
        raise FileFormatError(f"{p}: not a PNG file (no PNG signature and IHDR header)")
    width, height = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    depth, ctype = head[24], head[25]
    if ctype not in _PNG_CHANNELS or depth not in (8, 16):
        raise FileFormatError(
            f"{p}: PNG of colour type {ctype}, bit depth {depth} is not a capture; expected an "
            "8- or 16-bit grey (Bayer mosaic) or RGB PNG without alpha or palette")
    nch = _PNG_CHANNELS[ctype]
    shape = (height, width) if nch == 1 else (height, width, 3)
    _check_header(p, shape, np.dtype(np.uint16 if depth == 16 else np.uint8), expected_size)
    import cv2  # lazy: OpenCV decodes PNG captures only

    try:
        arr = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:
        raise FileFormatError(f"{p}: cannot decode PNG ({exc}); the file is corrupt") from None
    if arr is None or arr.shape[:2] != (height, width):
        raise FileFormatError(f"{p}: cannot decode PNG; the file is corrupt or truncated")
    if arr.ndim == 3:
        arr = np.ascontiguousarray(arr[..., ::-1])  # OpenCV's B, G, R -> R, G, B
    return arr, {}


def _read_stored(
    p: Path, expected_size: tuple[int, int] | None = None, page: int | None = None
) -> tuple[np.ndarray, dict[str, Any]]:
    """Stored array as (C, H, W) numpy (file dtype) and metadata with ``kind`` filled in.

    ``expected_size``: the ``(H, W)`` the image must have, checked from the file's header before
    the pixels are read (and again after reading)."""
    _check_exists(p)
    suffix = p.suffix.lower()
    if page is not None and suffix not in _TIFF_SUFFIXES:
        raise FileFormatError(f"{p}: page {page} asked of a file that is not a TIFF")
    if suffix in _TIFF_SUFFIXES:
        arr, meta = _read_tiff(p, expected_size, page)
    elif suffix in _PNG_SUFFIXES:
        arr, meta = _read_png(p, expected_size)
    elif suffix == ".npy":
        arr, meta = _read_npy(p, expected_size)
    elif suffix == ".npz":
        arr, meta = _read_npz(p, expected_size)
    else:
        raise FileFormatError(f"{p}: unsupported capture suffix {p.suffix!r} for read_capture")
    _check_dtype(arr, p)
    arr, kind = _as_chw(arr, p, meta)
    meta = dict(meta)
    meta["kind"] = kind
    return arr, meta


def read_capture(path: str | os.PathLike) -> tuple[torch.Tensor, dict[str, Any]]:
    """Read a TIFF/NPY/NPZ capture at storage level (no black subtraction, no demosaic).

    Args:
        path: ``.tif``, ``.tiff``, ``.npy`` or ``.npz`` file.

    Returns:
        ``(image, metadata)``: ``image`` is ``(1, H, W)`` (Bayer) or ``(3, H, W)`` (RGB) float32
        stored values (float64 for float64 files; exact for 16-bit data); ``metadata`` is the
        stored JSON (``{}`` for a file without it) with ``kind`` filled in.

    Raises:
        MissingFileError (a FileNotFoundError), FileFormatError (corrupt/truncated file, wrong
        shape or dtype, NaNs, bad metadata).
    """
    arr, meta = _read_stored(Path(path))
    out_dtype = np.float64 if arr.dtype == np.float64 else np.float32
    return torch.from_numpy(np.ascontiguousarray(arr, dtype=out_dtype)), meta


# ----------------------------------------------------------------------------------------------
# linear reader


def _level_map(value: Any, kind: str, shape: tuple[int, int], p: Path, name: str) -> torch.Tensor:
    """A black/white level (scalar, 4 per Bayer cell position, or 3 per RGB channel) as (C,H,W)."""
    try:
        vals = np.atleast_1d(np.asarray(value, dtype=np.float64)).ravel()
    except (TypeError, ValueError, OverflowError):
        raise FileFormatError(
            f"{p}: {name} {value!r} is not a number or a list of numbers (metadata key "
            f"'{name}', or the {name} setting)"
        ) from None
    if not np.all(np.isfinite(vals)):
        raise FileFormatError(f"{p}: {name} must be finite, got {vals.tolist()}")
    h, w = shape
    if vals.size == 1:
        return torch.full((1, 1, 1), float(vals[0]), dtype=torch.float64)
    if kind == "bayer" and vals.size == 4:
        cell = torch.from_numpy(vals.reshape(2, 2))
        return cell.repeat((h + 1) // 2, (w + 1) // 2)[None, :h, :w]
    if kind == "rgb" and vals.size == 3:
        return torch.from_numpy(vals).reshape(3, 1, 1)
    raise FileFormatError(
        f"{p}: {name} must be a scalar, 4 values (Bayer cell, row-major) or 3 values (RGB); "
        f"got {vals.tolist()} for a {kind} capture")


def read_any(
    path: str | os.PathLike,
    expected_size: tuple[int, int] | None = None,
    demosaic: DemosaicMethod = "bilinear",
    cfa_pattern: str | None = None,
    black_level: float | list[float] | None = None,
    white_level: float | None = None,
    normalize: bool = False,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
    default_cfa_pattern: str | None = None,
    exposure_s: float | None = None,
    camera_make: str | None = None,
    camera_model: str | None = None,
    sources: Mapping[str, str] | None = None,
    defaults: CaptureDefaults | None = None,
    page: int | None = None,
) -> LinearCapture:
    """Read any supported capture (TIFF, PNG, NPY, NPZ, camera RAW) as linear RGB.

    Args:
        path: the capture file; the reader is chosen by suffix (case-insensitive).
        expected_size: ``(H, W)`` the *sensor* (full-resolution, before ``"half"`` binning) image
            must have, e.g. the calibration bundle's sensor size; a mismatch raises a
            ``FileFormatError`` naming the file and both shapes.
        demosaic: ``"bilinear"`` (full resolution) or ``"half"`` for Bayer inputs.
        cfa_pattern, black_level, white_level: override (or supply, for files without metadata)
            the CFA pattern, black level and white level. Defaults: metadata, else black 0 and the
            integer dtype's maximum as white level (floating files without a white level get no
            saturation mask).
        normalize: divide by ``white − black`` (1.0 = saturation).
        dtype, device: of the returned tensors.
        default_cfa_pattern: CFA pattern of a Bayer file that has none in its metadata (when
            ``cfa_pattern`` is not given), e.g. the pattern the calibration bundle was made with.
        exposure_s, camera_make, camera_model: override (or supply) the exposure time (s) and
            the camera identity; by default they come from the file (our JSON metadata, else the
            EXIF ``ExposureTime``/``Make``/``Model`` tags of a TIFF or camera RAW/DNG, read with
            ``exifread``).
        sources: where each keyword override came from, by name (``{"black_level": "sheet",
            "exposure_s": "manifest"}``): one of :data:`SETTING_SOURCES`; an override not named
            here counts as ``"config"``.
        defaults: what a file that does not say gets from its calibration
            (:class:`CaptureDefaults`: black level, CFA pattern, exposure time); its
            ``cfa_pattern`` is used when ``default_cfa_pattern`` is not given.
        page: read only this page of a multi-page TIFF (a frame of a sequence,
            :mod:`hsi_torch.io.sequence`; its JSON description is its metadata, ``page`` added).

    Returns:
        :class:`LinearCapture` with ``image`` ``(3, H', W')`` = stored − black (float), saturation
        mask ``(3, H', W')`` and metadata: the file's own keys plus ``kind``, ``source`` (the
        path), ``demosaic`` (Bayer), ``cfa_pattern``, ``black_level`` (DN subtracted) and
        ``black_level_source`` (:func:`black_level_rule`), ``white_level`` and
        ``white_level_source``, ``exposure_s`` and ``exposure_source``, ``camera_make``,
        ``camera_model``: the metadata contract of ``docs/io_config_cli.md``, *Captures in*.

    Raises:
        MissingFileError (a ``FileNotFoundError``), FileFormatError (``ValueError``) for unreadable,
        truncated, NaN-holding, wrongly shaped/typed or wrong-size files and bad metadata.
    """
    p = Path(path)
    _check_exists(p)
    if not dtype.is_floating_point:
        raise TypeError(f"dtype must be floating point, got {dtype}")
    if demosaic not in ("half", "bilinear"):
        raise ValueError(f"demosaic must be 'half' or 'bilinear', got {demosaic!r}")
    suffix = p.suffix.lower()
    if suffix not in SUPPORTED_SUFFIXES:
        raise FileFormatError(
            f"{p}: unsupported file type {p.suffix!r}; expected one of .tif, .tiff, .png, .npy, "
            ".npz or a camera RAW suffix (.dng, .cr2, .nef, .arw, .kdc, ...)")
    srcs = dict(sources or {})
    for key, src in srcs.items():
        if src not in SETTING_SOURCES:
            raise ValueError(f"sources[{key!r}] = {src!r} is not one of {SETTING_SOURCES}")

    if suffix in RAW_SUFFIXES:
        if page is not None:
            raise FileFormatError(f"{p}: page {page} asked of a camera RAW file")
        if expected_size is not None:  # LibRaw's size from the header, before unpacking
            _check_size(p, declared_image_size(p) or (), expected_size)
        raw = load_raw(p, demosaic=None, dtype=torch.float64)
        shape = (raw.mosaic.shape[-2], raw.mosaic.shape[-1])
        stored = raw.mosaic + _level_map(raw.black_level, "bayer", shape, p, "black_level")
        meta = {
            "kind": "bayer",
            "cfa_pattern": raw.cfa_pattern,
            "black_level": list(raw.black_level),
            "white_level": raw.white_level,
            **raw.metadata,
        }
        stored_dtype = "uint16"
    else:
        arr, meta = _read_stored(p, expected_size, page)
        stored_dtype = str(arr.dtype)
        stored = None
    kind = meta["kind"]
    h, w = (stored if stored is not None else arr).shape[-2:]
    _check_size(p, (h, w), expected_size)
    dflt = defaults or CaptureDefaults()
    pattern = None
    if kind == "bayer":
        pattern = cfa_pattern or meta.get("cfa_pattern") or default_cfa_pattern or dflt.cfa_pattern
        if not pattern:
            raise FileFormatError(
                f"{p}: Bayer mosaic without a CFA pattern in its metadata; pass cfa_pattern="
                "('RGGB', 'BGGR', 'GRBG' or 'GBRG'; on the command line: --set cfa_pattern=RGGB; "
                "in a capture sheet or manifest: its cfa_pattern)")
        try:
            pattern = validate_cfa_pattern(pattern)
        except (TypeError, ValueError) as exc:
            raise FileFormatError(f"{p}: {exc}") from exc

    bl, bl_source = black_level_rule(black_level, srcs.get("black_level", "config"),
                                     meta.get("black_level"), dflt.black_level_rgb)  # fmt: skip
    bl_map = _rgb_as_cell(bl, pattern) if bl_source == "bundle" and kind == "bayer" else bl
    wl = white_level if white_level is not None else meta.get("white_level")
    wl_source = (srcs.get("white_level", "config") if white_level is not None
                 else "file" if wl is not None else None)  # fmt: skip
    if wl is None and np.dtype(stored_dtype).kind in "ui":
        wl = float(np.iinfo(np.dtype(stored_dtype)).max)
        wl_source = "default"
    black = _level_map(bl_map, kind, (h, w), p, "black_level")
    white = _level_map(wl, kind, (h, w), p, "white_level") if wl is not None else None
    if stored is None and not normalize and _exact_in(arr, black, white, dtype):
        # integer data and integral levels: stored − black is exact in ``dtype``, so it is
        # computed there directly (same values as the float64 route below, a fraction of the time)
        lin = torch.empty(arr.shape, dtype=dtype)
        lin.copy_(torch.from_numpy(arr))
        lin = lin.sub_(black.to(dtype)).to(device)
        if white is not None:
            # stored >= white  <=>  stored − black >= white − black, exact on integers
            sat = torch.ge(lin, (white - black).to(device=device, dtype=dtype))
        else:
            sat = torch.zeros(arr.shape, dtype=torch.bool, device=device)
    else:
        if stored is None:
            stored = torch.from_numpy(np.ascontiguousarray(arr, dtype=np.float64))
        lin = stored - black
        if white is not None:
            sat = (stored >= white).expand(stored.shape)
            if normalize:
                span = white - black
                if bool((span <= 0).any()):
                    raise FileFormatError(f"{p}: white level {wl} is not above black level {bl}")
                lin = lin / span
        else:
            if normalize:
                raise FileFormatError(
                    f"{p}: normalize=True needs a white level (none in metadata)")
            sat = torch.zeros(stored.shape, dtype=torch.bool)
        lin = lin.to(device=device, dtype=dtype)
        sat = sat.to(device=device)

    out_meta = dict(meta)
    out_meta.update(kind=kind, black_level=_jsonable(bl), white_level=_jsonable(wl),
                    white_level_source=wl_source, source=str(p))  # fmt: skip
    out_meta.update(_contract_metadata(
        p, meta, black_source=bl_source, sources=srcs, exposure_s=exposure_s,
        camera_make=camera_make, camera_model=camera_model,
        exif=_file_exif(p) if suffix in RAW_SUFFIXES or (
            suffix in _TIFF_SUFFIXES and "hsi_torch_capture" not in meta) else {},
    ))  # fmt: skip
    if dflt.exposure_s is not None and capture_exposure(out_meta)[0] is None:
        out_meta.update(exposure_s=float(dflt.exposure_s), exposure_source="config")
    out_meta.setdefault("cfa_pattern", None)
    if kind == "bayer":
        out_meta.update(cfa_pattern=pattern, demosaic=demosaic)
        try:
            rgb = _demosaic(lin, pattern, demosaic)
            rgb_sat = demosaic_saturation(sat, pattern, demosaic)
        except ValueError as exc:  # e.g. a mosaic too small for 2x2 binning
            raise FileFormatError(f"{p}: cannot demosaic the {h}x{w} mosaic ({exc})") from None
        return LinearCapture(rgb, rgb_sat, out_meta, p, lin, sat)
    return LinearCapture(lin, sat, out_meta, p)


def _file_exif(p: Path) -> dict[str, Any]:
    """``exposure_s``, ``camera_make``, ``camera_model`` from a TIFF's or camera RAW's EXIF tags
    (``exifread``); keys absent when the file has no such tag or no readable EXIF at all.
    (Our own capture TIFFs, written by :func:`write_capture`, hold no EXIF and are not parsed:
    ~30 ms for a full-size TIFF's tags.)"""
    tags = exif_tags(p)
    out: dict[str, Any] = {}
    for name in ("EXIF ExposureTime", "Image ExposureTime"):
        tag = tags.get(name)
        if tag is None or not getattr(tag, "values", None):
            continue
        v = tag.values[0]
        try:
            t = float(v.num) / float(v.den) if hasattr(v, "num") else float(v)
        except (TypeError, ValueError, ZeroDivisionError):
            continue
        if np.isfinite(t) and t > 0:
            out["exposure_s"] = t
            break
    for name, key in (("Image Make", "camera_make"), ("Image Model", "camera_model")):
        tag = tags.get(name)
        text = str(tag.printable).strip().strip("\x00").strip() if tag is not None else ""
        if text:
            out[key] = text
    return out


def _contract_metadata(
    p: Path, meta: Mapping[str, Any], *, black_source: str, sources: Mapping[str, str],
    exposure_s: float | None, camera_make: str | None, camera_model: str | None,
    exif: Mapping[str, Any],
) -> dict[str, Any]:
    """The metadata keys every :class:`LinearCapture` carries (see :func:`read_any`)."""
    out: dict[str, Any] = {"black_level_source": black_source}
    if exposure_s is not None:
        try:
            t = float(exposure_s)
        except (TypeError, ValueError):
            t = math.nan
        if not (math.isfinite(t) and t > 0):
            raise FileFormatError(f"{p}: exposure_s must be a number > 0 (seconds), got "
                                  f"{exposure_s!r}")  # fmt: skip
        out.update(exposure_s=t, exposure_source=sources.get("exposure_s", "config"))
    elif meta.get("exposure_s") is not None:
        out.update(exposure_s=meta["exposure_s"], exposure_source="file")
    elif exif.get("exposure_s") is not None:
        out.update(exposure_s=exif["exposure_s"], exposure_source="file")
    else:
        out.update(exposure_s=None, exposure_source=None)
    for key, given in (("camera_make", camera_make), ("camera_model", camera_model)):
        if given is not None:
            out[key] = str(given)
        elif isinstance(meta.get(key), str) and meta[key]:
            out[key] = meta[key]
        else:
            out[key] = exif.get(key)
    return out


def _exact_in(
    arr: np.ndarray, black: torch.Tensor, white: torch.Tensor | None, dtype: torch.dtype
) -> bool:
    """Whether ``stored − black`` (and the saturation test) are exact without float64: 8/16-bit
    integer data, integral levels below 2**20, a float32/float64 result (integers < 2**24 exact)."""
    if arr.dtype.kind not in "ui" or arr.dtype.itemsize > 2:
        return False
    if dtype not in (torch.float32, torch.float64):
        return False
    for lv in [black] if white is None else [black, white]:
        if not bool(torch.isfinite(lv).all()) or not bool((lv == lv.round()).all()):
            return False
        if float(lv.abs().max()) > 2**20:
            return False
    return True


def _jsonable(v: Any) -> Any:
    if v is None:
        return None
    a = np.asarray(v, dtype=np.float64)
    return float(a) if a.ndim == 0 else a.tolist()


def _check_size(p: Path, actual: tuple[int, ...], expected: tuple[int, int] | None) -> None:
    if expected is None:
        return
    exp = tuple(int(v) for v in expected)
    if len(exp) != 2:
        raise ValueError(f"expected_size must be (H, W), got {expected!r}")
    if tuple(actual) != exp:
        raise FileFormatError(
            f"{p}: image size (H, W) = {tuple(actual)} does not match the expected sensor size "
            f"{exp} (e.g. of the calibration bundle)")
