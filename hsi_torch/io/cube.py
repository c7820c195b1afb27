"""Spectral cubes on disk, in files that the usual tools open. All writes atomic.

The format table, with each tool that opens them: docs/io_config_cli.md. In memory a cube is
``(M, H, W)`` (band-first) with wavelengths ``(M,)`` in nm and an optional validity mask
``(H, W)`` bool. On disk:

- **TIFF** (``tiff``): ``<stem>.tif``, an OME-TIFF of one float32 page per band in wavelength
  order, each an OME ``Channel`` named ``"550 nm"`` with ``EmissionWavelength`` in nm; the OME
  ``Image/Description`` holds our JSON (``{"hsi_torch_cube": 1, "wavelengths_nm": [...],
  "wavelength_units": "nm", ...metadata}``). Beside it ``<stem>.vrt`` lets GDAL/QGIS/rasterio
  open the pages as bands named by wavelength (one file cannot be both an OME-TIFF and 25 GDAL
  bands: GDAL maps a multi-page TIFF's pages to sub-datasets). Older files whose first page's
  description is our JSON are still read.
- **ENVI** (``envi``): ``<stem>.hdr`` + ``<stem>.img``, BSQ float32 little-endian, with
  ``wavelength``, ``wavelength units = nm``, ``band names`` and ``data ignore value = nan``; the
  ``.img`` is written first, then the ``.hdr``.
- **NPZ** (``npz``): ``cube (M,H,W) float32``, ``wavelengths_nm (M,) float64``, ``valid (H,W)
  bool``, ``metadata`` (JSON string).
- **NetCDF** (``<stem>.nc``) and **Zarr** (the folder ``<stem>.zarr``): the
  :func:`cube_to_xarray` DataArray ``cube (wavelength, y, x)``, ``valid`` as a coordinate; they
  need the optional extra ``pip install 'hsi-torch[formats]'``, imported only when used.

TIFF, ENVI, NetCDF and Zarr hold NaN where ``valid`` is False (NetCDF/Zarr also keep ``valid``);
on loading ``valid`` is "all bands finite" (or the stored mask). NPZ stores the values untouched
plus the mask. **Findings** (:class:`hsi_torch.findings.Finding`) are stored in every format as
the metadata key ``"findings"``, a JSON list of :meth:`~hsi_torch.findings.Finding.to_dict`
(ENVI, whose header keeps no other metadata: the header field ``hsi_torch findings = [...]`` on
one line); :func:`load_cube` gives them back as :attr:`Cube.findings`, :func:`read_cube_findings`
(and :func:`read_cube_metadata`) read them without decoding the cube.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
import time
import uuid
import warnings
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal
from xml.sax.saxutils import escape as _xml_escape

import numpy as np
import torch

from hsi_torch.devices import to_numpy
from hsi_torch.errors import FileFormatError, InputError, MissingFileError, require_packages
from hsi_torch.findings import Finding, findings_from_dicts
from hsi_torch.io.atomic import (
    atomic_save_npz,
    atomic_write,
    atomic_write_text,
    json_default,
    remove_file,
    remove_tree,
    replace_file,
)
from hsi_torch.io.bounded import (
    MAX_JSON_BYTES,
    check_declared,
    check_store_files,
    npz_declared,
    require_npz,
)
from hsi_torch.io.captures import quiet_tifffile
from hsi_torch.io.safety import require_regular_file, unreadable_as_format_error
from hsi_torch.io.zarr_codecs import SAFE_CODECS, check_zarr_codecs

__all__ = [
    "Cube",
    "save_cube",
    "save_cube_formats",
    "load_cube",
    "read_cube_metadata",
    "read_cube_findings",
    "cube_to_xarray",
    "require_format",
    "remove_output",
    "CubeFormat",
    "CUBE_FORMATS",
    "OPTIONAL_FORMATS",
]

CubeFormat = Literal["tiff", "envi", "npz", "netcdf", "zarr"]
CUBE_FORMAT_VERSION = 1
_SUFFIX_FORMAT: dict[str, CubeFormat] = {
    ".tif": "tiff",
    ".tiff": "tiff",
    ".hdr": "envi",
    ".img": "envi",
    ".npz": "npz",
    ".nc": "netcdf",
    ".zarr": "zarr",
}
_FORMAT_SUFFIX = {"tiff": ".tif", "envi": ".hdr", "npz": ".npz", "netcdf": ".nc", "zarr": ".zarr"}
#: Every cube format, in the order of :data:`CubeFormat`.
CUBE_FORMATS: tuple[str, ...] = tuple(_FORMAT_SUFFIX)
#: Formats that need the optional extra ``hsi-torch[formats]``: format → the modules they import.
OPTIONAL_FORMATS: dict[str, tuple[str, ...]] = {
    "netcdf": ("xarray", "netCDF4"),
    "zarr": ("xarray", "zarr"),
}
_EXTRA_HINT = "pip install 'hsi-torch[formats]'"


def remove_output(path: Path) -> None:
    """Remove a written cube file (or a Zarr folder); absent is fine."""
    if path.is_dir() and not path.is_symlink():
        remove_tree(path)
    else:
        remove_file(path)


def require_format(fmt: str) -> None:
    """Check that the optional packages of a cube format are installed (before any work).

    Raises:
        ValueError: unknown format.
        ModuleNotFoundError: a package is missing (the message says what to install).
    """
    if fmt not in _FORMAT_SUFFIX:
        raise ValueError(f"unknown cube format {fmt!r}; one of {', '.join(CUBE_FORMATS)}")
    require_packages(OPTIONAL_FORMATS.get(fmt, ()), f"the cube format {fmt!r}", _EXTRA_HINT)


def _import_xarray(what: str):
    require_packages(("xarray",), what, _EXTRA_HINT)
    import xarray as xr

    return xr


@dataclass
class Cube:
    """A spectral cube loaded from disk.

    Attributes:
        cube: ``(M, H, W)`` float32 (NaN where invalid for TIFF/ENVI files).
        wavelengths: ``(M,)`` float64, nm.
        valid: ``(H, W)`` bool.
        metadata: the stored metadata (TIFF/NPZ/NetCDF/Zarr JSON; ENVI header fields); the
            stored findings, if any, as a list of dicts under ``"findings"``.
        path: the file read.
        findings: the findings stored with the cube, decoded (``[]`` when none were stored).
    """

    cube: torch.Tensor
    wavelengths: torch.Tensor
    valid: torch.Tensor
    metadata: dict[str, Any] = field(default_factory=dict)
    path: Path | None = None
    findings: list[Finding] = field(default_factory=list)

    def to_xarray(self):
        """This cube as an ``xarray.DataArray`` (see :func:`cube_to_xarray`)."""
        return cube_to_xarray(self.cube, self.wavelengths, self.valid, self.metadata)


def _format_of(p: Path, fmt: CubeFormat | None) -> CubeFormat:
    if fmt is not None:
        if fmt not in _FORMAT_SUFFIX:
            raise ValueError(f"fmt must be one of {', '.join(CUBE_FORMATS)}, got {fmt!r}")
        return fmt
    try:
        return _SUFFIX_FORMAT[p.suffix.lower()]
    except KeyError:
        raise ValueError(
            f"{p}: cannot tell the cube format from suffix {p.suffix!r}; use .tif/.tiff, "
            ".hdr/.img (ENVI), .npz, .nc (NetCDF) or .zarr"
        ) from None


def _prepare(
    cube: Any, wavelengths: Any, valid: Any | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    c = to_numpy(cube)
    if c.ndim != 3:
        raise ValueError(f"cube must have shape (M, H, W), got {tuple(c.shape)}")
    if c.dtype.kind not in "uif":
        raise TypeError(f"cube must be numeric, got dtype {c.dtype}")
    wl = to_numpy(wavelengths).astype(np.float64).ravel()
    if wl.shape != (c.shape[0],):
        raise ValueError(
            f"wavelengths must have shape ({c.shape[0]},) to match cube {tuple(c.shape)}, got "
            f"{tuple(to_numpy(wavelengths).shape)}")
    if not np.all(np.isfinite(wl)) or np.any(wl <= 0):
        raise ValueError("wavelengths must be finite and positive (nm)")
    if valid is None:
        v = np.isfinite(c).all(axis=0)
    else:
        v = to_numpy(valid).astype(bool)
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
    findings: Iterable[Finding] | None = None,
) -> list[Path]:
    """Write a spectral cube atomically as OME-TIFF (+ GDAL ``.vrt``), ENVI, NPZ, NetCDF or Zarr
    (format from the suffix or ``fmt``; see the module docstring).

    Args:
        path: ``*.tif``/``*.tiff``, ``*.hdr``/``*.img`` (ENVI pair), ``*.npz``, ``*.nc`` or
            ``*.zarr`` (a folder).
        cube: ``(M, H, W)`` tensor or array (stored as float32).
        wavelengths: ``(M,)`` band centres in nm.
        valid: optional ``(H, W)`` bool mask; default: pixels whose bands are all finite.
        metadata: JSON-serialisable extras (TIFF/NPZ/NetCDF/Zarr; ENVI keeps only
            ``description``).
        findings: stored as the metadata key ``"findings"`` (every format, ENVI included;
            replaces a ``"findings"`` key of ``metadata``).

    Returns:
        The files written (two for TIFF: ``.tif`` then ``.vrt``; two for ENVI: ``.img`` then
        ``.hdr``).

    Raises:
        ModuleNotFoundError: NetCDF/Zarr without the optional packages (``hsi-torch[formats]``).
    """
    p = Path(path)
    kind = _format_of(p, fmt)
    c, wl, v = _prepare(cube, wavelengths, valid)
    return _save_prepared(p, kind, c, wl, v, _with_findings(metadata, findings))


def _with_findings(
    metadata: dict[str, Any] | None, findings: Iterable[Finding] | None
) -> dict[str, Any] | None:
    """``metadata`` with ``findings`` (or Finding objects already under ``"findings"``) as
    the list of their dicts."""
    items = findings if findings is not None else (metadata or {}).get("findings")
    if items is None:
        return metadata
    if not isinstance(items, (list, tuple)) and findings is None:
        raise InputError(f"metadata 'findings' must be a list of findings, got "
                         f"{type(items).__name__}")  # fmt: skip
    dicts = [f.to_dict() if isinstance(f, Finding) else f for f in items]
    for d in dicts:  # checked before anything is written
        Finding.from_dict(d)
    return {**(metadata or {}), "findings": dicts}


def _save_prepared(
    p: Path,
    kind: CubeFormat,
    c: np.ndarray,
    wl: np.ndarray,
    v: np.ndarray,
    metadata: dict[str, Any] | None,
    c_nan: np.ndarray | None = None,
    extra_arrays: dict[str, np.ndarray] | None = None,
) -> list[Path]:
    """:func:`save_cube` after :func:`_prepare`; ``c_nan``: ``c`` with NaN where invalid, if
    already made (TIFF/ENVI); ``extra_arrays``: more arrays stored in an NPZ (other formats
    ignore them)."""
    meta = dict(metadata or {})
    if kind != "npz":
        c = c_nan if c_nan is not None else _nan_where_invalid(c, v)
    if kind in OPTIONAL_FORMATS:
        return _save_xarray(p, kind, c, wl, v, meta)
    if kind == "npz":
        meta_json = json.dumps(
            {"hsi_torch_cube": CUBE_FORMAT_VERSION, **meta}, default=json_default)
        atomic_save_npz(
            p, {"cube": c, "wavelengths_nm": wl, "valid": v, "metadata": np.array(meta_json),
                **(extra_arrays or {})})  # fmt: skip
        return [p]
    if kind == "tiff":
        return _save_tiff(p, c, wl, meta)
    return _save_envi(p, c, wl, meta)


def _band_name(w: float) -> str:
    return f"{w:.10g} nm"


def _save_tiff(p: Path, c: np.ndarray, wl: np.ndarray, meta: dict[str, Any]) -> list[Path]:
    """OME-TIFF (one named channel per band) + the GDAL ``.vrt`` beside it."""
    import tifffile

    desc = {
        "hsi_torch_cube": CUBE_FORMAT_VERSION,
        "wavelengths_nm": wl.tolist(),
        "wavelength_units": "nm",
        "shape": list(c.shape),
        **meta,
    }
    text = json.dumps(desc, default=json_default)
    # a UUID derived from the content description: the same cube and metadata give the same bytes
    file_uuid = uuid.uuid5(uuid.NAMESPACE_URL, f"hsi_torch_cube:{text}:{c.dtype}")
    ome = {
        "axes": "CYX",
        "UUID": f"urn:uuid:{file_uuid}",
        "Creator": "hsi_torch",
        "Description": text,
        "Channel": {
            "Name": [_band_name(w) for w in wl],
            "EmissionWavelength": [float(w) for w in wl],
            "EmissionWavelengthUnit": ["nm"] * len(wl),
        },
    }
    if meta.get("scene"):
        ome["Name"] = str(meta["scene"])
    with atomic_write(p, "wb") as f:
        tifffile.imwrite(f, c, ome=True, photometric="minisblack", metadata=ome)
    try:
        vrt = _save_vrt(p, c.shape, wl)
    except BaseException:
        remove_file(p)  # no TIFF without its VRT
        raise
    return [p, vrt]


def _vrt_path(tif: Path) -> Path:
    """``<stem>.vrt`` beside ``<stem>.tif`` (``.tiff``, ``.ome.tif``, ``.ome.tiff``)."""
    for suffix in (".ome.tiff", ".ome.tif", ".tiff", ".tif"):
        if tif.name.lower().endswith(suffix):
            return tif.with_name(tif.name[: -len(suffix)] + ".vrt")
    return tif.with_name(tif.stem + ".vrt")


def _save_vrt(tif: Path, shape: tuple[int, ...], wl: np.ndarray) -> Path:
    """GDAL virtual dataset: the TIFF's pages (``GTIFF_DIR:k:``) as bands named by wavelength."""
    m, h, w = shape
    src = _xml_escape(tif.name)
    bands = [
        f'  <VRTRasterBand dataType="Float32" band="{k + 1}">\n'
        f"    <Description>{_band_name(lam)}</Description>\n"
        "    <NoDataValue>nan</NoDataValue>\n"
        f'    <Metadata><MDI key="wavelength">{lam:.10g}</MDI>'
        '<MDI key="wavelength_units">nm</MDI></Metadata>\n'
        f'    <Metadata domain="IMAGERY"><MDI key="CENTRAL_WAVELENGTH_UM">{lam / 1000:.10g}'
        "</MDI></Metadata>\n"
        "    <SimpleSource>\n"
        f'      <SourceFilename relativeToVRT="1">GTIFF_DIR:{k + 1}:{src}</SourceFilename>\n'
        "      <SourceBand>1</SourceBand>\n"
        f'      <SourceProperties RasterXSize="{w}" RasterYSize="{h}" DataType="Float32" '
        f'BlockXSize="{w}" BlockYSize="1"/>\n'
        "    </SimpleSource>\n"
        "  </VRTRasterBand>" for k, lam in enumerate(wl)]
    text = (
        f'<VRTDataset rasterXSize="{w}" rasterYSize="{h}">\n'
        "  <!-- hsi_torch spectral cube: the bands are the pages of the OME-TIFF beside this "
        "file -->\n" + "\n".join(bands) + "\n</VRTDataset>\n"
    )
    return atomic_write_text(_vrt_path(tif), text)


def cube_to_xarray(
    cube: Any, wavelengths: Any, valid: Any | None = None, metadata: dict[str, Any] | None = None
):
    """A cube as an ``xarray.DataArray`` named ``cube`` with dims ``(wavelength, y, x)``.

    Coordinates: ``wavelength`` (nm, float64, ``units: nm``), ``y``/``x`` (pixel indices of the
    reference frame) and ``valid`` ``(y, x)`` bool. Values are float32, NaN where invalid. The
    metadata go, as JSON, to the attribute ``hsi_torch_metadata``. Needs ``xarray``
    (``pip install 'hsi-torch[formats]'``).

    Example:
        >>> da = cube_to_xarray(cube, wl, valid)              # doctest: +SKIP
        >>> da.sel(wavelength=550).plot()                     # doctest: +SKIP
    """
    c, wl, v = _prepare(cube, wavelengths, valid)
    return _xarray_of(_nan_where_invalid(c, v), wl, v, dict(metadata or {}))


def _xarray_of(c: np.ndarray, wl: np.ndarray, v: np.ndarray, meta: dict[str, Any]):
    xr = _import_xarray("the xarray export")
    m, h, w = c.shape
    return xr.DataArray(
        c,
        dims=("wavelength", "y", "x"),
        coords={
            "wavelength": ("wavelength", wl, {"units": "nm",
                                              "long_name": "band centre wavelength"}),
            "y": ("y", np.arange(h), {"long_name": "reference-frame row", "units": "pixel"}),
            "x": ("x", np.arange(w), {"long_name": "reference-frame column", "units": "pixel"}),
            "valid": (("y", "x"), v, {"long_name": "pixel reconstructed (>= min_views views)"}),
        },
        name="cube",
        attrs={
            "long_name": "spectral cube (reflectance relative to the white reference)",
            "hsi_torch_cube": CUBE_FORMAT_VERSION,
            "hsi_torch_metadata": json.dumps(meta, default=json_default),
        })


@contextlib.contextmanager
def _atomic_dir(dest: Path):
    """A temporary folder beside ``dest``, renamed onto it on success (an old ``dest`` is
    replaced; a reader never sees a half-written folder under ``dest``)."""
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{dest.name}.", suffix=".tmp", dir=dest.parent))
    try:
        yield tmp
        if dest.exists():
            old = dest.with_name(f".{dest.name}.{uuid.uuid4().hex}.old")
            replace_file(dest, old)
            replace_file(tmp, dest)
            remove_tree(old)
        else:
            replace_file(tmp, dest)
    except BaseException:
        remove_tree(tmp)
        raise


def _save_xarray(
    p: Path, kind: str, c: np.ndarray, wl: np.ndarray, v: np.ndarray, meta: dict[str, Any]
) -> list[Path]:
    require_format(kind)
    da = _xarray_of(c, wl, v, meta)
    if kind == "netcdf":
        with atomic_write(p, "wb") as f:  # netCDF4 writes by file name: the temporary one
            da.to_netcdf(f.name, engine="netcdf4")
        return [p]
    import zarr

    # Zarr format 2 (with consolidated metadata): what every Zarr reader opens
    kw = {"zarr_format": 2} if int(zarr.__version__.split(".")[0]) >= 3 else {}
    with _atomic_dir(p) as tmp:
        da.to_dataset().to_zarr(tmp, mode="w", **kw)
    return [p]


def _envi_paths(p: Path) -> tuple[Path, Path]:
    stem = p.with_suffix("")
    return stem.with_suffix(".hdr"), stem.with_suffix(".img")


def _envi_header(hdr: Path) -> Path:
    """``hdr``, refused unless a regular file of at most :data:`MAX_JSON_BYTES`."""
    require_regular_file(hdr, "ENVI header")
    if hdr.stat().st_size > MAX_JSON_BYTES:
        raise FileFormatError(f"{hdr}: an ENVI header of {hdr.stat().st_size} bytes (at most "
                              f"{MAX_JSON_BYTES // 2**20} MiB is read)")  # fmt: skip
    return hdr


#: The ENVI header field that holds the findings (a JSON list on one line).
_ENVI_FINDINGS = "hsi_torch findings"


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
        "band names = {" + ", ".join(_band_name(x) for x in wl) + "}",
        "data ignore value = nan",
    ]
    if meta.get("findings") is not None:  # one line, not in braces: ENVI readers keep it whole
        lines.append(f"{_ENVI_FINDINGS} = " + json.dumps(meta["findings"], default=json_default,
                                                          ensure_ascii=True))  # fmt: skip
    with atomic_write(img, "wb") as f:  # the array's own buffer, no bytes copy
        f.write(memoryview(np.ascontiguousarray(c, dtype="<f4")).cast("B"))
    try:
        atomic_write_text(hdr, "\n".join(lines) + "\n")
    except BaseException:
        remove_file(img)  # no data file without its header
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
    npz_arrays: dict[str, Any] | None = None,
    findings: Iterable[Finding] | None = None,
) -> list[Path]:
    """Write the cube in several formats: ``<stem>.npz``, ``<stem>.tif`` (+ ``.vrt``),
    ``<stem>.hdr/.img``, ``<stem>.nc``, ``<stem>.zarr``.

    The same files as :func:`save_cube` per format; the cube is converted (and NaN-filled for
    TIFF/ENVI) once. If one format fails, the files already written by this call are removed.
    ``timings``: if given, receives the seconds spent per format (``"prepare"`` for the shared
    conversion). ``npz_arrays``: more arrays (tensors or arrays, by key; not the cube's own keys)
    stored in the NPZ, e.g. the reconstruction's per-band standard deviation ``"std"``.
    ``findings``: stored with the cube in every format (as :func:`save_cube`'s).
    """
    s = Path(stem)
    metadata = _with_findings(metadata, findings)
    for fmt in formats:
        if fmt not in _FORMAT_SUFFIX:
            raise ValueError(f"formats: unknown cube format {fmt!r} ({', '.join(CUBE_FORMATS)})")
        require_format(fmt)  # a missing optional package fails before anything is written
    t0 = time.perf_counter()
    c, wl, v = _prepare(cube, wavelengths, valid)
    c_nan = _nan_where_invalid(c, v) if any(f != "npz" for f in formats) else None
    extra = {k: to_numpy(a) for k, a in (npz_arrays or {}).items()}
    taken = {"cube", "wavelengths_nm", "valid", "metadata"} & set(extra)
    if taken:
        raise ValueError(f"npz_arrays: {sorted(taken)} are the cube's own keys")
    tm = timings if timings is not None else {}
    tm["prepare"] = time.perf_counter() - t0
    out: list[Path] = []
    try:
        for fmt in formats:
            t0 = time.perf_counter()
            p = s.with_name(s.name + _FORMAT_SUFFIX[fmt])
            out += _save_prepared(p, fmt, c, wl, v, metadata, c_nan, extra)
            tm[fmt] = time.perf_counter() - t0
    except BaseException:
        for q in out:
            remove_output(q)
        raise
    return out


def load_cube(
    path: str | os.PathLike,
    wavelengths: Any | None = None,
    device: torch.device | str | None = None,
    max_bytes: int | None = None,
) -> Cube:
    """Read a cube written by :func:`save_cube` or by other tools (ENVI any interleave/dtype via
    ``spectral``; TIFF stacks ``(M, H, W)``; NPZ with ``cube`` + ``wavelengths_nm``).

    The size the file declares (NPZ member headers, TIFF series, ENVI header, Zarr/NetCDF
    variable) is checked before anything is decoded (:mod:`hsi_torch.io.bounded`).

    Args:
        path: ``.tif/.tiff``, ``.hdr/.img`` or ``.npz``.
        wavelengths: ``(M,)`` nm, required only for files that do not carry them.
        max_bytes: the largest decoded cube accepted (default
            :func:`~hsi_torch.io.bounded.max_cube_bytes`: ``$HSI_TORCH_MAX_CUBE_GB``, 1 GiB).

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
    if kind in OPTIONAL_FORMATS:
        require_format(kind)
    valid: np.ndarray | None = None
    meta: dict[str, Any] = {}
    wl: np.ndarray | None = None
    with unreadable_as_format_error(p, f"{kind.upper()} cube"):
        if kind == "npz":
            require_npz(p)
            with np.load(p, allow_pickle=False) as z:
                for name, (shape, dtype) in npz_declared(z).items():  # before decoding
                    check_declared(p, shape, dtype, max_bytes, f"cube array {name!r}")
                if "cube" not in z:
                    raise FileFormatError(
                        f"{p}: NPZ has no array 'cube' (found {sorted(z.keys())})")
                c = z["cube"]
                wl = z["wavelengths_nm"] if "wavelengths_nm" in z else None
                valid = z["valid"].astype(bool) if "valid" in z else None
                meta = json.loads(str(z["metadata"])) if "metadata" in z else {}
        elif kind == "tiff":
            c, wl, meta = _load_tiff(p, max_bytes)
        elif kind in OPTIONAL_FORMATS:
            c, wl, valid, meta = _load_xarray(p, kind, max_bytes)
        else:
            c, wl, meta = _load_envi(p, max_bytes)
    if c.ndim != 3:
        raise FileFormatError(f"{p}: cube must be 3-D (M, H, W), got shape {tuple(c.shape)}")
    if wavelengths is not None:
        wl = to_numpy(wavelengths).astype(np.float64).ravel()
    if wl is None:
        raise FileFormatError(f"{p}: the file carries no wavelengths; pass wavelengths=")
    wl = np.asarray(wl, dtype=np.float64).ravel()
    if wl.shape[0] != c.shape[0]:
        raise FileFormatError(
            f"{p}: {wl.shape[0]} wavelengths for a cube with {c.shape[0]} bands {tuple(c.shape)}")
    c = c.astype(np.float32)
    if valid is None:
        valid = np.isfinite(c).all(axis=0)
    elif valid.shape != c.shape[1:]:
        raise FileFormatError(f"{p}: valid mask {valid.shape} does not match cube {c.shape}")
    findings = _decode_findings(p, meta)
    return Cube(
        cube=torch.from_numpy(np.ascontiguousarray(c)).to(device),
        wavelengths=torch.from_numpy(wl).to(device),
        valid=torch.from_numpy(np.ascontiguousarray(valid)).to(device),
        metadata=meta,
        path=p,
        findings=findings)


def _decode_findings(p: Path, meta: dict[str, Any]) -> list[Finding]:
    """The findings stored in ``meta`` (an ENVI header's field is parsed into ``"findings"``
    first, in place).

    Raises:
        FileFormatError: the stored findings are not a list of findings (naming ``p``).
    """
    raw = meta.pop(_ENVI_FINDINGS, None)
    if isinstance(raw, str):
        try:
            meta["findings"] = json.loads(raw)
        except json.JSONDecodeError as exc:
            raise FileFormatError(f"{p}: the header field '{_ENVI_FINDINGS}' is not JSON "
                                  f"({exc})") from None  # fmt: skip
    try:
        return findings_from_dicts(meta.get("findings"), source=f"{p}: metadata")
    except InputError as exc:
        msg = str(exc)
        raise FileFormatError(msg if msg.startswith(str(p)) else
                              f"{p}: metadata 'findings': {msg}") from None  # fmt: skip


def read_cube_metadata(path: str | os.PathLike) -> dict[str, Any]:
    """A cube file's stored metadata, without decoding the cube (the NPZ's ``metadata`` member,
    the OME-TIFF's description, the ENVI header, the NetCDF/Zarr attributes): cheap whatever
    the cube's size. The stored findings, if any, are under ``"findings"`` (a list of dicts;
    the ENVI header's field is parsed into it).

    Raises:
        MissingFileError, FileFormatError: as :func:`load_cube`.
    """
    p = Path(path)
    kind = _format_of(p, None)
    target = _envi_paths(p)[0] if kind == "envi" else p
    if not target.exists():
        raise MissingFileError(f"cube file not found: {target}")
    if kind in OPTIONAL_FORMATS:
        require_format(kind)
    try:
        if kind == "npz":
            require_npz(p)
            with np.load(p, allow_pickle=False) as z:
                declared = npz_declared(z)
                if "metadata" not in declared:
                    return {}
                shape, dtype = declared["metadata"]
                check_declared(p, shape, dtype, MAX_JSON_BYTES, "cube array 'metadata'")
                meta = _json_dict(str(z["metadata"]))
        elif kind == "tiff":
            import tifffile

            require_regular_file(p, "cube file")
            with quiet_tifffile(), tifffile.TiffFile(p) as tif:
                meta = _tiff_meta(tif)[0]
        elif kind == "envi":
            import spectral.io.envi as envi

            meta = dict(envi.read_envi_header(str(_envi_header(target))))
        else:
            with _open_xarray(p, kind, None) as da:  # lazy: the cube's chunks are not read
                meta = _json_dict(da.attrs.get("hsi_torch_metadata"))
    except FileFormatError:
        raise
    except Exception as exc:
        raise FileFormatError(f"{p}: cannot read the metadata of a {kind.upper()} cube "
                              f"({type(exc).__name__}: {exc})") from exc  # fmt: skip
    _decode_findings(p, meta)  # checked (and the ENVI field parsed)
    return meta


def read_cube_findings(path: str | os.PathLike) -> list[Finding]:
    """The findings stored with a cube file (``[]`` when it has none), read from its metadata
    only (:func:`read_cube_metadata`).

    Raises:
        MissingFileError, FileFormatError: the file is missing or unreadable, or a stored
            finding is malformed (the message names the file).
    """
    return _decode_findings(Path(path), read_cube_metadata(path))


def _json_dict(text: str | None) -> dict[str, Any]:
    try:
        parsed = json.loads(text) if text else {}
    except json.JSONDecodeError:
        return {}
    return parsed if isinstance(parsed, dict) else {}


def _load_tiff(
    p: Path, max_bytes: int | None = None
) -> tuple[np.ndarray, np.ndarray | None, dict[str, Any]]:
    """Our OME-TIFF (JSON in the OME Image Description), any OME-TIFF whose channels carry
    emission wavelengths or ``"<λ> nm"`` names, or an older file with JSON in the page
    description; other TIFF stacks ``(M, H, W)`` without wavelengths."""
    import tifffile


    require_regular_file(p, "cube file")
    with quiet_tifffile(), tifffile.TiffFile(p) as tif:
        if not tif.series:
            raise FileFormatError(f"{p}: TIFF file has no image data")
        check_declared(p, tif.series[0].shape, tif.series[0].dtype, max_bytes)
        c = tif.asarray()
        meta, wl = _tiff_meta(tif)
    if c.ndim == 2:
        c = c[None]
    return c, wl, meta


def _tiff_meta(tif: Any) -> tuple[dict[str, Any], np.ndarray | None]:
    """The metadata and wavelengths of an open ``tifffile.TiffFile`` (no pixel decoded)."""
    import tifffile

    ome = tif.ome_metadata if tif.is_ome else None
    desc = tif.pages[0].description if len(tif.pages) else ""
    meta: dict[str, Any] = {}
    wl = None
    if ome:
        image = tifffile.xml2dict(ome).get("OME", {}).get("Image", {})
        image = image[0] if isinstance(image, list) else image
        meta = _json_dict(image.get("Description"))
        if "wavelengths_nm" not in meta:
            chans = image.get("Pixels", {}).get("Channel", [])
            chans = chans if isinstance(chans, list) else [chans]
            wl = _ome_channel_wavelengths(chans)
    else:
        meta = _json_dict(desc)
    if "wavelengths_nm" in meta:
        wl = np.asarray(meta["wavelengths_nm"], dtype=np.float64)
    return meta, wl


def _ome_channel_wavelengths(chans: list[dict[str, Any]]) -> np.ndarray | None:
    out = []
    for ch in chans:
        if "EmissionWavelength" in ch:
            scale = _UNIT_TO_NM.get(str(ch.get("EmissionWavelengthUnit", "nm")).lower())
            if scale is None:
                return None
            out.append(float(ch["EmissionWavelength"]) * scale)
        else:
            name = str(ch.get("Name", "")).strip()
            if not name.endswith("nm"):
                return None
            try:
                out.append(float(name[:-2]))
            except ValueError:
                return None
    return np.asarray(out, dtype=np.float64) if out else None


@contextlib.contextmanager
def _open_xarray(p: Path, kind: str, max_bytes: int | None) -> Iterator[Any]:
    """The ``cube`` variable of a NetCDF or Zarr cube file, opened lazily (nothing decoded)."""
    xr = _import_xarray(f"reading {p}")
    if kind == "zarr":  # before xarray decodes anything: no codec that runs code (pickle)
        check_zarr_codecs(p, SAFE_CODECS)
        check_store_files(p, max_bytes)  # no FIFO, device or huge chunk
    else:
        require_regular_file(p, "cube file")
    opener = xr.open_dataset if kind == "netcdf" else xr.open_zarr
    with opener(p) as ds:
        if "cube" not in ds:
            raise FileFormatError(f"{p}: no variable 'cube' (found {sorted(ds.data_vars)})")
        yield ds["cube"]


def _load_xarray(p: Path, kind: str, max_bytes: int | None = None):
    with _open_xarray(p, kind, max_bytes) as cube:
        da = cube.transpose("wavelength", ...)
        check_declared(p, da.shape, da.dtype, max_bytes)  # (lazy until .values)
        c = np.asarray(da.values)
        wl = np.asarray(da["wavelength"].values, dtype=np.float64)
        scale = _UNIT_TO_NM.get(str(da["wavelength"].attrs.get("units", "nm")).lower())
        if scale is None:
            raise FileFormatError(f"{p}: unknown wavelength units "
                                  f"{da['wavelength'].attrs.get('units')!r}")  # fmt: skip
        valid = np.asarray(da["valid"].values, dtype=bool) if "valid" in da.coords else None
        meta = _json_dict(da.attrs.get("hsi_torch_metadata"))
    return c, wl * scale, valid, meta


_UNIT_TO_NM = {"nm": 1.0, "nanometers": 1.0, "nanometer": 1.0, "um": 1e3, "µm": 1e3,
               "micrometers": 1e3, "micrometer": 1e3, "microns": 1e3, "micron": 1e3, "mm": 1e6,
               "millimeters": 1e6}  # fmt: skip


def _load_envi(
    p: Path, max_bytes: int | None = None
) -> tuple[np.ndarray, np.ndarray | None, dict[str, Any]]:
    """An ENVI cube whose data file holds exactly what its header declares (lines × samples ×
    bands × the data type's size after the header offset; a file of another size means the
    header describes another cube: refused, naming both sizes)."""
    import spectral.io.envi as envi

    hdr, img = _envi_paths(p)
    _envi_header(hdr)
    if img.exists():
        require_regular_file(img, "ENVI data file")
    image = envi.open(str(hdr), str(img) if img.exists() else None)
    require_regular_file(image.filename, "ENVI data file")
    h, w, m = image.nrows, image.ncols, image.nbands
    dtype = np.dtype(image.dtype)
    check_declared(hdr, (m, h, w), dtype, max_bytes)
    expected = image.offset + h * w * m * dtype.itemsize
    actual = Path(image.filename).stat().st_size
    if actual != expected:
        raise FileFormatError(
            f"{image.filename}: the ENVI data file holds {actual} bytes but its header {hdr.name} "
            f"declares {expected} ({h} lines x {w} samples x {m} bands of {dtype}"
            + (f" after a {image.offset}-byte offset" if image.offset else "")
            + "): " + ("truncated" if actual < expected else "the header describes another "
                       "cube (bands, samples, lines or data type)"))
    centers = image.bands.centers
    for key, values in (("wavelength", centers), ("band names", image.metadata.get(
            "band names"))):
        if values and len(values) != m:
            raise FileFormatError(f"{hdr}: the header lists {len(values)} values of "
                                  f"'{key}' for {m} bands")  # fmt: skip
    with warnings.catch_warnings():  # NaN marks invalid pixels here; not worth a warning
        warnings.simplefilter("ignore")
        arr = np.asarray(image.load())  # (lines, samples, bands)
    meta = dict(image.metadata)
    wl = None
    if centers:
        unit = (image.bands.band_unit or "nm").strip().lower()
        scale = _UNIT_TO_NM.get(unit)
        if scale is None:
            raise FileFormatError(f"{hdr}: unknown wavelength units {image.bands.band_unit!r}")
        wl = np.asarray(centers, dtype=np.float64) * scale
    return arr.transpose(2, 0, 1), wl, meta
