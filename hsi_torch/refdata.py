"""Reference spectra: illuminants, camera sensitivities, reflectances, CIE CMFs, gel filters.

Every loader returns torch tensors sampled at the requested wavelengths (nm), obtained by linear
interpolation of the tabulated data (:func:`hsi_torch.spectral.resample_spectra`). Wavelengths may
be given as a :class:`~hsi_torch.spectral.SpectralGrid`, a 1-D tensor (its device and dtype are
used for the result) or a sequence of floats. Requests outside the tabulated range raise
``ValueError`` unless ``extrapolate="zero"`` or ``"edge"`` is passed.

Sources (all real, measured data shipped in PyPI packages or in this package):

- illuminants ``'D65'``, ``'A'``: CIE tables in ``colour.SDS_ILLUMINANTS``;
- cameras: ``colour.MSDS_CAMERA_SENSITIVITIES`` (``'Nikon 5100 (NPL)'``, ``'Sigma SDMerill
  (NPL)'``) and the rawtoaces measurement of the Canon EOS 5D Mark II
  (``CANON_EOS_5DMark_II_RGB_Sensitivities.csv`` under
  ``colour.characterisation.aces_it.ROOT_RESOURCES_RAWTOACES``); the default camera of the
  simulator is :data:`DEFAULT_CAMERA` = ``'Canon EOS 5D Mark II'`` (a DSLR like the original
  prototype's, and unlike the NPL sets its channels are not normalised separately, so the R:G:B
  gains of a real raw sensor are kept);
- reflectances: ``colour.SDS_COLOURCHECKERS`` (default ``'ColorChecker N Ohta'``) and the 190
  training patches ``190_Patches.csv`` of rawtoaces;
- CIE 1931 2° colour matching functions: ``colour.MSDS_CMFS``;
- gel filter transmittances: Lee 068 *Sky Blue* (``'L068'``, the Faced Reflectors baseline's
  filter) ships with this package (``hsi_torch/data/lee_068_sky_blue.csv``, the manufacturer's
  curve as compiled in the MIT-licensed PyPI package ``lighting_filters`` 0.1.1; source and
  licence in ``hsi_torch/data/README.md``). Other brands' codes are read from
  ``lighting_filters`` when it is installed (optional, not a dependency); any CSV file works.
"""

from __future__ import annotations

import functools
import json
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from hsi_torch.errors import MissingFileError
from hsi_torch.resources import real_data_dir, shipped_data
from hsi_torch.spectral import SpectralGrid, resample_spectra

__all__ = [
    "DEFAULT_CAMERA",
    "DEFAULT_ILLUMINANT",
    "DEFAULT_COLORCHECKER",
    "as_wavelengths",
    "illuminant",
    "list_illuminants",
    "camera_sensitivities",
    "list_cameras",
    "resolve_camera",
    "colorchecker_reflectances",
    "reflectance_set",
    "cie_1931_cmfs",
    "filter_transmittance",
    "list_filters",
    "read_spectral_csv",
]

DEFAULT_CAMERA = "Canon EOS 5D Mark II"
DEFAULT_ILLUMINANT = "D65"
DEFAULT_COLORCHECKER = "ColorChecker N Ohta"

_CANON_CSV = "CANON_EOS_5DMark_II_RGB_Sensitivities.csv"
_PATCHES_190_CSV = "190_Patches.csv"
_BUILTIN_CAMERA_CSV = {DEFAULT_CAMERA: _CANON_CSV}
_REFLECTANCE_SET_ALIASES = ("190 patches", "190_patches", "rawtoaces 190")

WavelengthsLike = SpectralGrid | torch.Tensor | Sequence[float] | np.ndarray


# -------------------------------------------------------------------------------------- helpers --


def as_wavelengths(
    wavelengths: WavelengthsLike,
    *,
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
) -> torch.Tensor:
    """Return wavelengths (nm) as a 1-D floating tensor.

    A tensor keeps its device and (floating) dtype unless ``device``/``dtype`` are given; a grid or
    a sequence is created on ``device`` with ``dtype`` (default: ``torch.get_default_dtype()``).
    """
    if isinstance(wavelengths, SpectralGrid):
        wl = wavelengths.wavelengths(device=device, dtype=dtype)
    elif isinstance(wavelengths, torch.Tensor):
        wl = wavelengths
        if not wl.is_floating_point():
            wl = wl.to(dtype or torch.get_default_dtype())
        wl = wl.to(device=device or wl.device, dtype=dtype or wl.dtype)
    else:
        try:
            arr = np.asarray(wavelengths, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise TypeError(
                "wavelengths must be a SpectralGrid, a tensor or a sequence of numbers, "
                f"got {type(wavelengths).__name__}"
            ) from exc
        wl = torch.as_tensor(arr, device=device, dtype=dtype or torch.get_default_dtype())
    if wl.ndim != 1 or wl.numel() < 1:
        raise ValueError(f"wavelengths must be a non-empty 1-D array, got shape {tuple(wl.shape)}")
    if not bool(torch.isfinite(wl).all()) or bool((wl <= 0).any()):
        raise ValueError("wavelengths must be finite and positive (nm)")
    return wl


def _resample(
    src_nm: np.ndarray,
    values: np.ndarray,
    wavelengths: WavelengthsLike,
    extrapolate: str,
    what: str,
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
) -> torch.Tensor:
    """Resample ``values (..., S)`` tabulated at ``src_nm (S,)`` onto ``wavelengths`` (float64)."""
    wl = as_wavelengths(wavelengths, device=device, dtype=dtype)
    if extrapolate not in ("zero", "edge", "error"):
        raise ValueError(f"extrapolate must be 'zero', 'edge' or 'error', got {extrapolate!r}")
    src = torch.as_tensor(np.ascontiguousarray(src_nm, dtype=np.float64), device=wl.device)
    val = torch.as_tensor(np.ascontiguousarray(values, dtype=np.float64), device=wl.device)
    tgt = wl.to(torch.float64)
    if extrapolate == "error":
        outside = (tgt < src[0] - 1e-9) | (tgt > src[-1] + 1e-9)
        if bool(outside.any()):
            raise ValueError(
                f"{what}: requested wavelengths {tgt[outside].tolist()} nm lie outside the "
                f"tabulated range [{float(src[0])}, {float(src[-1])}] nm; pass "
                "extrapolate='zero' or 'edge' to allow this")
    out = resample_spectra(val, src, tgt, dim=-1, extrapolate=extrapolate)
    return out.to(wl.dtype)


def read_spectral_csv(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Read a spectral table: first column wavelength (nm), further columns values.

    Accepts comma, semicolon, tab or whitespace delimiters, an optional header row (column names)
    and ``#`` comment lines. Rows are sorted by wavelength.

    Returns:
        ``(wavelengths (S,), values (S, K), column_names)``; names are ``col1…colK`` when the file
        has no header.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"spectral CSV file not found: {path}")
    lines = [
        ln.strip()
        for ln in path.read_text(encoding="utf-8-sig").splitlines()
        if ln.strip() and not ln.lstrip().startswith("#")
    ]
    if not lines:
        raise ValueError(f"{path}: empty spectral table")

    def split(line: str) -> list[str]:
        for sep in (",", ";", "\t"):
            if sep in line:
                return [t.strip() for t in line.split(sep)]
        return line.split()

    rows = [split(ln) for ln in lines]
    names: list[str] | None = None
    try:
        [float(t) for t in rows[0]]
    except ValueError:
        names = rows[0][1:]
        rows = rows[1:]
    if not rows:
        raise ValueError(f"{path}: no numeric rows after the header")
    ncol = len(rows[0])
    if ncol < 2:
        raise ValueError(f"{path}: need at least 2 columns (wavelength, value), got {ncol}")
    data = np.empty((len(rows), ncol), dtype=np.float64)
    for i, r in enumerate(rows):
        if len(r) != ncol:
            raise ValueError(f"{path}: row {i + 1} has {len(r)} columns, expected {ncol}")
        try:
            data[i] = [float(t) for t in r]
        except ValueError as exc:
            raise ValueError(f"{path}: non-numeric value in data row {i + 1}: {r}") from exc
    if not np.all(np.isfinite(data)):
        raise ValueError(f"{path}: non-finite values in the table")
    order = np.argsort(data[:, 0], kind="stable")
    data = data[order]
    if np.any(np.diff(data[:, 0]) <= 0):
        raise ValueError(f"{path}: duplicate wavelengths in the first column")
    if names is None or len(names) != ncol - 1:
        names = [f"col{k + 1}" for k in range(ncol - 1)]
    return data[:, 0], data[:, 1:], names


#: suffixes of the spectral table files the loaders read (a camera may also be rawtoaces JSON)
_TABLE_SUFFIXES = (".csv", ".txt", ".tsv")


def _is_table_file(name: str) -> bool:
    """Whether a loader argument names a spectral table file (CSV/TXT/TSV suffix or a file)."""
    return Path(name).suffix.lower() in _TABLE_SUFFIXES or Path(name).is_file()


def _rawtoaces_root() -> Path:
    from colour.characterisation.aces_it import ROOT_RESOURCES_RAWTOACES

    return Path(ROOT_RESOURCES_RAWTOACES)


def _normalise(values: np.ndarray, src_nm: np.ndarray, mode: str | None, what: str) -> np.ndarray:
    """Normalise tabulated spectra (``(..., S)``) on their native grid."""
    if mode is None or mode == "none":
        return values
    if mode == "max":
        peak = np.max(values)
    elif mode == "560":
        if not (src_nm[0] <= 560.0 <= src_nm[-1]):
            raise ValueError(f"{what}: cannot normalise at 560 nm, table covers "
                             f"[{src_nm[0]}, {src_nm[-1]}] nm; use normalise='max'")
        peak = np.interp(560.0, src_nm, values.reshape(-1, values.shape[-1])[0])
    elif mode == "channel":
        peak = np.max(values, axis=-1, keepdims=True)
    else:
        raise ValueError(f"{what}: unknown normalise={mode!r}")
    if np.any(np.asarray(peak) <= 0):
        raise ValueError(f"{what}: cannot normalise, reference value is not positive")
    return values / peak


# ---------------------------------------------------------------------------------- illuminants --


def list_illuminants() -> list[str]:
    """Names accepted by :func:`illuminant` besides CSV paths (CIE tables of colour-science)."""
    import colour

    return sorted(colour.SDS_ILLUMINANTS.keys())


def illuminant(
    name_or_path: str | os.PathLike = DEFAULT_ILLUMINANT,
    wavelengths: WavelengthsLike = (),
    *,
    normalise: str | None = "560",
    extrapolate: str = "error",
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
) -> torch.Tensor:
    """Relative spectral power distribution of an illuminant.

    Args:
        name_or_path: a name of ``colour.SDS_ILLUMINANTS`` (e.g. ``'D65'``, ``'A'``) or a CSV file
            with columns ``wavelength_nm, value``.
        wavelengths: ``(M,)`` target wavelengths in nm (grid, tensor or sequence).
        normalise: ``'560'`` (default): value 1 at 560 nm, the CIE convention (the CIE tables are
            100 at 560 nm); ``'max'``: peak of the table = 1; ``None``: as tabulated.
            Normalisation uses the table, before resampling.
        extrapolate: ``'error'`` | ``'zero'`` | ``'edge'`` outside the tabulated range.

    Returns:
        ``(M,)`` relative power, dtype/device of ``wavelengths`` (or ``dtype``/``device``).
    """
    name = os.fspath(name_or_path)
    import colour

    if name in colour.SDS_ILLUMINANTS:
        sd = colour.SDS_ILLUMINANTS[name]
        src, val, what = np.asarray(sd.wavelengths), np.asarray(sd.values), f"illuminant {name!r}"
    elif _is_table_file(name):
        src, table, _ = read_spectral_csv(name)
        if table.shape[1] != 1:
            raise ValueError(f"illuminant CSV {name}: expected 2 columns, got {table.shape[1] + 1}")
        val, what = table[:, 0], f"illuminant CSV {name}"
    else:
        raise ValueError(
            f"unknown illuminant {name!r}: not a CSV file and not in colour.SDS_ILLUMINANTS "
            f"(e.g. 'D65', 'A'; see list_illuminants())")
    src = np.asarray(src, np.float64)
    val = _normalise(np.asarray(val, dtype=np.float64), src, normalise, what)
    return _resample(src, val, wavelengths, extrapolate, what, device, dtype)


# ------------------------------------------------------------------------- camera sensitivities --


def _real_data_cameras() -> dict[str, Path]:
    """Cameras measured in the real-data folder (``camera_sensitivities/*.json``, rawtoaces
    format, named ``Make_Model_380_780_5.json``), by name (``'Nikon D850'``); empty when the
    folder is absent."""
    folder = real_data_dir("camera_sensitivities")
    if folder is None:
        return {}
    out: dict[str, Path] = {}
    for f in sorted(folder.glob("*.json")):
        parts = f.stem.split("_")
        while parts and parts[-1].isdigit():  # the range and step of the file name
            parts.pop()
        if parts:
            out[" ".join(parts)] = f
    return out


def list_cameras() -> list[str]:
    """Built-in cameras: colour-science's measured sets, rawtoaces' Canon EOS 5D Mark II and,
    when the real-data folder is present, the cameras measured there (by name)."""
    import colour

    return sorted(set(colour.MSDS_CAMERA_SENSITIVITIES.keys()) | set(_BUILTIN_CAMERA_CSV)
                  | set(_real_data_cameras()))


def resolve_camera(name_or_path: str | os.PathLike) -> str:
    """The camera a name or path means: a name of :func:`list_cameras` matched without regard to
    case, spaces or ``-``/``_`` (``'nikon d850'``, ``'NIKON_D850'``; a real-data camera resolves
    to its JSON file's path), or a CSV/JSON path returned as given.

    Raises:
        MissingFileError: a CSV/JSON path that does not exist (the message names it).
        ValueError: neither a known name nor a table file (the message lists the names).
    """
    import colour

    name = os.fspath(name_or_path)
    if name in colour.MSDS_CAMERA_SENSITIVITIES or name in _BUILTIN_CAMERA_CSV:
        return name

    def key(text: str) -> str:
        return "".join(ch for ch in text.lower() if ch.isalnum())

    # the built-in measurements win over a real-data file of the same camera
    known = {key(n): os.fspath(p) for n, p in _real_data_cameras().items()}
    known.update({key(n): n for n in [*colour.MSDS_CAMERA_SENSITIVITIES.keys(),
                                      *_BUILTIN_CAMERA_CSV]})
    if Path(name).suffix.lower() in (".json", *_TABLE_SUFFIXES):  # a file, by its name
        if not Path(name).is_file():
            raise MissingFileError(f"camera sensitivity file not found: {name}")
        return name
    if key(name) in known:
        return known[key(name)]
    if Path(name).is_file():
        return name
    raise ValueError(
        f"unknown camera {name!r}: not a CSV/JSON file and not one of {list_cameras()} "
        "(names match without regard to case)")


def _read_camera_json(path: Path) -> tuple[np.ndarray, np.ndarray]:
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise ValueError(f"camera JSON {path}: not valid JSON ({exc})") from exc
    try:
        main = doc["spectral_data"]["data"]["main"]
    except (KeyError, TypeError) as exc:
        raise ValueError(
            f"camera JSON {path}: expected values under spectral_data.data.main "
            "as {wavelength: [R, G, B]}"
        ) from exc
    index = doc.get("spectral_data", {}).get("index", {}).get("main")
    if index is not None and [str(s).upper() for s in index] != ["R", "G", "B"]:
        raise ValueError(f"camera JSON {path}: spectral_data.index.main is {index}, expected R,G,B")
    try:
        items = sorted((float(k), [float(x) for x in v]) for k, v in main.items())
    except (TypeError, ValueError, AttributeError) as exc:
        raise ValueError(f"camera JSON {path}: malformed spectral_data.data.main") from exc
    if not items or any(len(v) != 3 for _, v in items):
        raise ValueError(f"camera JSON {path}: every entry must hold 3 values [R, G, B]")
    src = np.array([k for k, _ in items])
    vals = np.array([v for _, v in items]).T
    return src, vals


def camera_sensitivities(
    name_or_path: str | os.PathLike = DEFAULT_CAMERA,
    wavelengths: WavelengthsLike = (),
    *,
    normalise: str | None = "max",
    extrapolate: str = "error",
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
) -> torch.Tensor:
    """Camera RGB spectral sensitivities ``f^c(λ)``.

    Args:
        name_or_path: a name from :func:`list_cameras` (``colour.MSDS_CAMERA_SENSITIVITIES`` keys,
            ``'Canon EOS 5D Mark II'``, the real-data folder's cameras such as ``'Nikon D850'``;
            matched without regard to case, see :func:`resolve_camera`), a CSV file
            ``wavelength,R,G,B`` or a JSON file in the rawtoaces format
            (``spectral_data.data.main = {wavelength: [R, G, B]}``).
        wavelengths: ``(M,)`` target wavelengths in nm.
        normalise: ``'max'`` (default): the largest value over all channels is 1 (keeps the ratios
            between channels); ``'channel'``: each channel's peak is 1; ``None``: as stored.
            Note the NPL sets in colour-science are already normalised per channel.
        extrapolate: ``'error'`` | ``'zero'`` | ``'edge'``.

    Returns:
        ``(3, M)`` rows R, G, B.
    """
    import colour

    if normalise not in ("max", "channel", None, "none"):
        raise ValueError(f"normalise must be 'max', 'channel' or None, got {normalise!r}")
    name = resolve_camera(name_or_path)
    if name in colour.MSDS_CAMERA_SENSITIVITIES:
        msds = colour.MSDS_CAMERA_SENSITIVITIES[name]
        src, vals = np.asarray(msds.wavelengths), np.asarray(msds.values).T
    elif name in _BUILTIN_CAMERA_CSV:
        src, vals, _ = read_spectral_csv(_rawtoaces_root() / _BUILTIN_CAMERA_CSV[name])
        vals = vals.T
    elif Path(name).suffix.lower() == ".json":
        src, vals = _read_camera_json(Path(name))
    elif _is_table_file(name):
        src, table, _ = read_spectral_csv(name)
        if table.shape[1] != 3:
            raise ValueError(
                f"camera CSV {name}: expected 4 columns (wavelength,R,G,B), "
                f"got {table.shape[1] + 1}")
        vals = table.T
    else:
        raise ValueError(
            f"unknown camera {name!r}: not a CSV/JSON file and not one of {list_cameras()}")
    what = f"camera {name!r}"
    vals = _normalise(np.asarray(vals, np.float64), np.asarray(src, np.float64), normalise, what)
    return _resample(src, vals, wavelengths, extrapolate, what, device, dtype)


# --------------------------------------------------------------------------------- reflectances --


@functools.lru_cache(maxsize=8)
def _colorchecker_table(name: str) -> tuple[np.ndarray, np.ndarray, tuple[str, ...]]:
    import colour

    if name not in colour.SDS_COLOURCHECKERS:
        raise ValueError(
            f"unknown ColorChecker {name!r}; available: {sorted(colour.SDS_COLOURCHECKERS)}")
    sds = colour.SDS_COLOURCHECKERS[name]
    names = tuple(sds.keys())
    src = np.asarray(next(iter(sds.values())).wavelengths, dtype=np.float64)
    vals = np.stack([np.interp(src, sd.wavelengths, sd.values) for sd in sds.values()])
    return src, vals, names


def colorchecker_reflectances(
    wavelengths: WavelengthsLike,
    name: str = DEFAULT_COLORCHECKER,
    *,
    extrapolate: str = "error",
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
) -> tuple[torch.Tensor, list[str]]:
    """The 24 measured reflectances of an X-Rite ColorChecker (``colour.SDS_COLOURCHECKERS``).

    Patches are in chart order, row-major over the 4 × 6 chart: row 0 is 'dark skin' …
    'bluish green', row 3 is 'white 9.5 (.05 D)' … 'black 2 (1.5 D)'.

    Returns:
        ``(reflectance (24, M), patch_names)``, reflectance in [0, 1].
    """
    src, vals, names = _colorchecker_table(name)
    return _resample(src, vals, wavelengths, extrapolate, f"ColorChecker {name!r}", device,
                     dtype), list(names)


def reflectance_set(
    name_or_path: str | os.PathLike,
    wavelengths: WavelengthsLike,
    *,
    extrapolate: str = "error",
    clip_negative: bool = True,
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
) -> tuple[torch.Tensor, list[str]]:
    """A set of reflectance spectra.

    Args:
        name_or_path: ``'190 patches'`` (the rawtoaces training set ``190_Patches.csv``, K = 190),
            a ColorChecker name of ``colour.SDS_COLOURCHECKERS`` (K = 24) or a CSV file
            ``wavelength, r_1, …, r_K`` (header row optional; its names are returned).
        clip_negative: clip tiny negative values (the 190-patch table has ~−1e-16 entries) to 0.

    Returns:
        ``(reflectance (K, M), names)``.
    """
    import colour

    name = os.fspath(name_or_path)
    if name.lower() in _REFLECTANCE_SET_ALIASES:
        src, table, names = read_spectral_csv(_rawtoaces_root() / _PATCHES_190_CSV)
        vals, what = table.T, "190 patches"
    elif name in colour.SDS_COLOURCHECKERS:
        src, vals, nm = _colorchecker_table(name)
        names, what = list(nm), f"ColorChecker {name!r}"
    elif _is_table_file(name):
        src, table, names = read_spectral_csv(name)
        vals, what = table.T, f"reflectance CSV {name}"
    else:
        raise ValueError(
            f"unknown reflectance set {name!r}: use '190 patches', a ColorChecker name "
            f"{sorted(colour.SDS_COLOURCHECKERS)} or a CSV file")
    if clip_negative:
        vals = np.clip(vals, 0.0, None)
    return _resample(src, vals, wavelengths, extrapolate, what, device, dtype), list(names)


# ---------------------------------------------------------------- CIE colour matching functions --


def cie_1931_cmfs(
    wavelengths: WavelengthsLike,
    *,
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
) -> torch.Tensor:
    """CIE 1931 2° standard observer ``x̄, ȳ, z̄`` (colour-science, 1 nm table 360–830 nm).

    Returns:
        ``(3, M)``; zero outside 360–830 nm (where the CMFs are negligible).
    """
    import colour

    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    return _resample(np.asarray(cmfs.wavelengths), np.asarray(cmfs.values).T, wavelengths,
                     "zero", "CIE 1931 CMFs", device, dtype)


# ---------------------------------------------------------------------------------- gel filters --


#: Gel filters shipped in ``hsi_torch/data`` (code → (file, brand, name)).
SHIPPED_FILTERS: dict[str, tuple[str, str, str]] = {
    "L068": ("lee_068_sky_blue.csv", "Lee", "Sky Blue"),
}


@functools.lru_cache(maxsize=1)
def _lighting_filters_table() -> dict:
    try:
        import importlib.metadata as md

        files = md.files("lighting_filters") or []
    except Exception as exc:  # PackageNotFoundError and friends
        raise ModuleNotFoundError(
            "the optional package 'lighting_filters' is not installed "
            "(pip install lighting_filters); pass a CSV file instead"
        ) from exc
    hits = [f for f in files if f.name == "filters.json" and f.parent.name == "dataset"]
    if not hits:
        raise FileNotFoundError("lighting_filters is installed but dataset/filters.json is missing")
    doc = json.loads(Path(hits[0].locate()).read_text(encoding="utf-8"))
    return doc["filters"]


def list_filters(brand: str | None = None) -> list[str]:
    """Codes of the gel filters with a measured spectrum: the shipped ones (``'L068'``), plus
    those of ``lighting_filters`` when that optional package is installed."""
    codes = {k for k, (_, b, _) in SHIPPED_FILTERS.items() if brand is None or b == brand}
    try:
        table = _lighting_filters_table()
    except (ModuleNotFoundError, FileNotFoundError):
        table = {}
    codes |= {k for k, v in table.items()
              if v.get("sd") and (brand is None or v.get("brand") == brand)}  # fmt: skip
    return sorted(codes)


def filter_transmittance(
    name_or_path: str | os.PathLike,
    wavelengths: WavelengthsLike,
    *,
    extrapolate: str = "error",
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
) -> torch.Tensor:
    """Spectral transmittance (0…1) of a colour filter.

    Args:
        name_or_path: a CSV file ``wavelength_nm, transmittance`` (transmittance in 0…1, or in
            percent if any value exceeds 1.5), or a filter code: ``'L068'`` = Lee 068 Sky Blue
            (shipped, measured 405–700 nm every 5 nm), or any code of the optional
            ``lighting_filters`` package when it is installed.

    Returns:
        ``(M,)`` transmittance.
    """
    name = os.fspath(name_or_path)
    if name in SHIPPED_FILTERS and not _is_table_file(name):
        fname, brand, title = SHIPPED_FILTERS[name]
        src, table, _ = read_spectral_csv(shipped_data(fname))
        return _resample(src, table[:, 0], wavelengths, extrapolate,
                         f"filter {name!r} ({brand} {title})", device, dtype)
    if _is_table_file(name):
        src, table, _ = read_spectral_csv(name)
        if table.shape[1] != 1:
            raise ValueError(f"filter CSV {name}: expected 2 columns, got {table.shape[1] + 1}")
        vals, what = table[:, 0], f"filter CSV {name}"
        if vals.max() > 1.5:
            vals = vals / 100.0
    else:
        try:
            table = _lighting_filters_table()
        except ModuleNotFoundError:
            raise ValueError(
                f"unknown filter {name!r}: not a CSV file and not a shipped filter "
                f"({', '.join(SHIPPED_FILTERS)}); other gel codes need the optional package "
                "lighting_filters (pip install lighting_filters)") from None
        entry = table.get(name)
        if entry is None:
            raise ValueError(f"unknown filter {name!r}: not a CSV file, not a shipped filter "
                             f"({', '.join(SHIPPED_FILTERS)}) and not a code in "
                             "lighting_filters (see list_filters())")
        if not entry.get("sd"):
            raise ValueError(f"filter {name!r} ({entry.get('brand')} {entry.get('name')}) has no "
                             "measured spectrum in lighting_filters")
        items = sorted((float(k), float(v)) for k, v in entry["sd"].items())
        src = np.array([k for k, _ in items])
        vals = np.array([v for _, v in items])
        what = f"filter {name!r} ({entry.get('brand')} {entry.get('name')})"
    return _resample(src, vals, wavelengths, extrapolate, what, device, dtype)
