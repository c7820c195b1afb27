"""Bounded readers: what a file's header declares is checked before anything is decoded.

A cube, a capture or a store declares its size in a header (NPY/NPZ member headers, TIFF
pages, the ENVI ``.hdr``, Zarr ``.zarray``): a 1 MB compressed file may declare gigabytes. The
readers check the declared size against a cap first, so a small file cannot make them allocate
more than the cap, and every file they open is a regular file (a FIFO would block forever,
``/dev/zero`` never ends).

- :func:`max_cube_bytes`: the cap on one decoded cube, ``$HSI_TORCH_MAX_CUBE_GB`` GiB (default
  :data:`DEFAULT_MAX_CUBE_GB`); raise it to open a larger cube on purpose.
- :func:`check_declared`: refuse a declared ``shape × dtype`` above the cap, naming the file.
- :func:`require_npz` / :func:`npz_declared`: a ``.npz`` is a ZIP archive (else "not an NPZ
  file", never numpy's pickle hint) and the sizes its members declare.
- :func:`read_json_bounded`: a JSON file that is a regular file of bounded size and depth.
- :func:`check_store_files`: every file of a Zarr store is a regular file of bounded size.
- :func:`declared_image_size`: a capture's ``(H, W)`` from its header (TIFF, PNG, NPY, NPZ,
  camera RAW), before any pixel is decoded: checked against the sensor size first.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import stat
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from hsi_torch.errors import FileFormatError
from hsi_torch.io.safety import png_header, require_regular_file, short_text

__all__ = [
    "MAX_CUBE_GB_ENV",
    "DEFAULT_MAX_CUBE_GB",
    "MAX_JSON_BYTES",
    "max_cube_bytes",
    "check_declared",
    "require_npz",
    "npz_declared",
    "npy_header",
    "read_json_bounded",
    "check_store_files",
    "declared_image_size",
    "image_hw",
    "csv_header",
    "csv_lines",
]

#: Environment variable: the largest decoded cube a reader accepts (GiB).
MAX_CUBE_GB_ENV = "HSI_TORCH_MAX_CUBE_GB"
#: Default of :data:`MAX_CUBE_GB_ENV`: twice a full-size 25-band float32 cube (0.47 GiB); the
#: viewer holds about 4.5 times the cube at its peak (the band stack, the sRGB composite).
DEFAULT_MAX_CUBE_GB = 1.0
#: Largest metadata JSON file read (``.zmetadata``, ``.zattrs``, sidecars), bytes.
MAX_JSON_BYTES = 64 << 20
_ZIP_MAGIC = (b"PK\x03\x04", b"PK\x05\x06")


def max_cube_bytes(limit: int | None = None) -> int:
    """The cap on a decoded cube (bytes): ``limit`` when given, else ``$HSI_TORCH_MAX_CUBE_GB``
    GiB, else :data:`DEFAULT_MAX_CUBE_GB` GiB.

    Raises:
        ValueError: the variable is not a finite positive number (naming it).
    """
    if limit is not None:
        return int(limit)
    raw = os.environ.get(MAX_CUBE_GB_ENV, "").strip()
    if not raw:
        return int(DEFAULT_MAX_CUBE_GB * 2**30)
    try:
        gb = float(raw)
    except ValueError:
        gb = math.nan
    if not (math.isfinite(gb) and 0 < gb <= 2**20):
        raise ValueError(f"${MAX_CUBE_GB_ENV}={short_text(raw, 40)!r} must be a number of GiB "
                         "between 0 and 1048576")  # fmt: skip
    return int(gb * 2**30)


def check_declared(
    path: str | os.PathLike, shape: Any, dtype: Any, limit: int | None = None,
    what: str = "cube",
) -> int:  # fmt: skip
    """Refuse a declared array of ``shape`` and ``dtype`` above the cap, before decoding it.

    Returns:
        The declared size in bytes.

    Raises:
        FileFormatError: naming the file, the shape, the size and how to raise the cap.
    """
    shape = tuple(int(v) for v in shape)
    nbytes = math.prod(shape) * max(1, np.dtype(dtype).itemsize)
    cap = max_cube_bytes(limit)
    if nbytes > cap:
        raise FileFormatError(
            f"{path}: the header declares a {what} of shape {shape} {np.dtype(dtype)} "
            f"({nbytes / 2**30:.2f} GiB), more than the {cap / 2**30:.2f} GiB a reader decodes "
            f"(refused before decoding; set ${MAX_CUBE_GB_ENV} to open a larger one on purpose)")
    return nbytes


def require_npz(path: str | os.PathLike) -> Path:
    """Refuse ``path`` unless it is a regular file that starts as a ZIP archive (an NPZ).

    Raises:
        FileFormatError: a FIFO, a device, or a file of another kind named ``.npz``.
    """
    p = require_regular_file(path, "NPZ file")
    with open(p, "rb") as f:
        head = f.read(4)
    if head not in _ZIP_MAGIC:
        what = "an NPY array" if head.startswith(b"\x93NUM") else f"it starts with {head!r}"
        raise FileFormatError(f"{p}: not an NPZ file (an NPZ is a ZIP archive of .npy arrays; "
                              f"{what})")  # fmt: skip
    return p


def npz_declared(z: Any) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
    """``{name: (shape, dtype)}`` of an open :class:`numpy.lib.npyio.NpzFile`'s members, read
    from their ``.npy`` headers (nothing decompressed beyond them)."""
    out = {}
    for name in z.files:
        with z.zip.open(name + ".npy") as f:
            out[name] = npy_header(f)
    return out


def npy_header(f: Any, max_header_size: int = 10_000,
               c_order: bool = False) -> tuple[tuple[int, ...], np.dtype]:  # fmt: skip
    """``(shape, dtype)`` from the header of the ``.npy`` stream ``f`` (positioned at its start;
    left at the first data byte): the one reader of ``.npy`` headers in the package.
    ``max_header_size``: the largest header accepted (bytes); ``c_order``: refuse an array of
    two or more axes stored in Fortran order.

    Raises:
        ValueError: not an ``.npy`` header (NumPy's own message), or Fortran order refused.
    """
    version = np.lib.format.read_magic(f)
    read = (np.lib.format.read_array_header_1_0 if version == (1, 0)
            else np.lib.format.read_array_header_2_0)  # fmt: skip
    shape, fortran, dtype = read(f, max_header_size=max_header_size)
    if c_order and fortran and len(shape) > 1:
        raise ValueError(f"a {tuple(shape)} array in Fortran order (C order expected)")
    return tuple(int(v) for v in shape), np.dtype(dtype)


def read_json_bounded(
    path: str | os.PathLike, what: str = "metadata", max_bytes: int = MAX_JSON_BYTES
) -> Any:
    """Parse a JSON file that is a regular file of at most ``max_bytes``.

    Raises:
        FileFormatError: not a regular file, too large, not UTF-8 JSON or nested too deeply
            (the message names the file).
    """
    p = require_regular_file(path, what)
    size = p.stat().st_size
    if size > max_bytes:
        raise FileFormatError(f"{p}: the {what} holds {size} bytes, more than "
                              f"{max_bytes // 2**20} MiB")  # fmt: skip
    try:
        with open(p, "rb") as f:
            text = f.read(max_bytes + 1).decode("utf-8")
        return json.loads(text)
    except RecursionError:
        raise FileFormatError(f"{p}: the {what} is nested too deeply to be JSON metadata") from None
    except (OSError, ValueError) as exc:
        raise FileFormatError(f"{p}: the {what} is not readable JSON "
                              f"({short_text(str(exc), 120)})") from None  # fmt: skip


def check_store_files(root: str | os.PathLike, max_bytes: int | None = None) -> None:
    """Every file of the store folder ``root`` (its chunks and metadata, any depth; symlinks
    followed to what they name) must be a regular file of at most ``max_bytes`` (default
    :func:`max_cube_bytes`): a FIFO chunk would block the reader forever, a device or a huge
    chunk exhaust memory.

    Raises:
        FileFormatError: naming the file.
    """
    cap = max_cube_bytes(max_bytes)
    for dirpath, dirnames, filenames in os.walk(root):
        for name in filenames + [d for d in dirnames if os.path.islink(os.path.join(dirpath, d))]:
            f = os.path.join(dirpath, name)
            try:
                st = os.stat(f)
            except OSError:
                continue  # a dangling link: the reader reports the missing chunk
            if stat.S_ISDIR(st.st_mode):
                continue
            if not stat.S_ISREG(st.st_mode):
                require_regular_file(f, "store file")  # raises, naming the kind
            if st.st_size > cap:
                raise FileFormatError(
                    f"{f}: a store file of {st.st_size / 2**30:.2f} GiB, more than the "
                    f"{cap / 2**30:.2f} GiB a reader decodes (${MAX_CUBE_GB_ENV})")


def declared_image_size(path: str | os.PathLike) -> tuple[int, int] | None:
    """``(H, W)`` of a capture file from its header, nothing decoded: TIFF (the first series),
    PNG (``IHDR``), NPY/NPZ (the array's ``.npy`` header: ``(H, W)``, ``(C, H, W)`` or
    ``(H, W, C)`` with C 1 or 3), camera RAW (LibRaw's visible size, before unpacking);
    ``None`` for a file whose header gives no such shape (the reader then says why).

    Raises:
        FileFormatError: not a regular file, or a header that cannot be read (naming the file).
    """
    from hsi_torch.io.raw import RAW_SUFFIXES  # lazy: raw imports torch

    p = require_regular_file(path, "capture file")
    suffix = p.suffix.lower()
    shape: tuple[int, ...] | None = None
    try:
        if suffix in (".tif", ".tiff"):
            import tifffile  # lazy: only TIFF headers need it

            with tifffile.TiffFile(p) as tif:
                shape = tuple(tif.series[0].shape) if tif.series else None
        elif suffix == ".png":
            (h, w, c), _ = png_header(p)
            shape = (h, w) if c == 1 else (h, w, c)
        elif suffix == ".npy":
            with open(p, "rb") as f:
                shape = npy_header(f)[0]
        elif suffix == ".npz":
            require_npz(p)
            with np.load(p, allow_pickle=False) as z:
                members = {k: v for k, v in npz_declared(z).items() if k != "metadata"}
                key = "image" if "image" in members else (next(iter(members))
                                                          if len(members) == 1 else None)
                shape = members[key][0] if key is not None else None
        elif suffix in RAW_SUFFIXES:
            import rawpy  # lazy: LibRaw

            with rawpy.RawPy() as r:
                r.open_file(str(p))  # the header only: unpack() would decode the pixels
                shape = (int(r.sizes.height), int(r.sizes.width))
    except FileFormatError:
        raise
    except Exception as exc:  # noqa: BLE001 - each library raises its own types
        raise FileFormatError(f"{p}: cannot read the image header ({type(exc).__name__}: "
                              f"{short_text(str(exc), 120)})") from None  # fmt: skip
    return None if shape is None else image_hw(shape)


def image_hw(shape: tuple[int, ...]) -> tuple[int, int] | None:
    """``(H, W)`` of a capture's array shape: ``(H, W)``, ``(C, H, W)`` or ``(H, W, C)`` with C
    1 or 3 (channels first when both fit); ``None`` for any other shape."""
    if len(shape) == 2 or (len(shape) == 3 and shape[0] in (1, 3)):
        return int(shape[-2]), int(shape[-1])
    return (int(shape[0]), int(shape[1])) if len(shape) == 3 and shape[-1] in (1, 3) else None


def csv_header(path: Path, what: str) -> tuple[Any, list[str] | None]:
    """A sheet's ``csv.reader`` (UTF-8, an optional BOM) and its header row (``None``: an empty
    file); errors name ``what`` and the file."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise FileFormatError(f"{what} {path}: cannot read it as UTF-8 text ({exc})") from None
    reader = csv.reader(io.StringIO(text, newline=""))  # a quoted cell keeps its line breaks
    try:
        return reader, next(reader, None)
    except csv.Error as exc:
        raise FileFormatError(f"{what} {path}: not a CSV file ({exc})") from None


def csv_lines(reader: Any, name: Any) -> Iterator[tuple[str, list[str]]]:
    """The data lines of a sheet's ``csv.reader`` after its header: ``(where, cells)``, ``where``
    being ``"<name>:<line>"`` (the line a row starts on); blank lines and lines whose first cell
    starts with ``#`` (comments) are skipped.

    Raises:
        FileFormatError: a line the CSV rules cannot parse, naming ``name`` and the line.
    """
    line_no = reader.line_num + 1
    while True:
        try:
            cells = next(reader, None)
        except csv.Error as exc:
            raise FileFormatError(f"{name}:{line_no}: not a CSV line ({exc})") from None
        if cells is None:
            return
        where, line_no = f"{name}:{line_no}", reader.line_num + 1
        if any(c.strip() for c in cells) and not cells[0].strip().startswith("#"):
            yield where, cells
