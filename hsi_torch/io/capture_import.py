"""A lab's own folder of photos → a capture set (``hsi-torch captures import``), and the check of
a set (``hsi-torch captures check``); the sheet, the patterns and both commands' output are
described in ``docs/calibration.md``, *Your own photos*.

The roles, wavelengths and per-file settings come from a **sheet** (:func:`read_sheet`: a CSV file
with a header ``file,role,...`` of :data:`SHEET_COLUMNS`; ``file`` relative to the sheet's folder;
an empty cell means "not given", a ``file`` starting with ``#`` is a comment) or from **name
patterns** (:func:`rows_from_patterns`: ``{nm}`` in a scan pattern is the wavelength).
:func:`import_captures` writes ``OUT/manifest.json`` referencing the files where they are
(``files_root``; ``copy=True`` copies them into ``OUT/<role>/``) with the sheet's settings per
file, the nominal layout, and a report per band of the calibration grid.
:func:`check_capture_set` reads every capture as calibration will and lists what it will use.
"""

from __future__ import annotations

import difflib
import filecmp
import glob
import json
import math
import os
import re
import shutil
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hsi_torch.console import info, warn
from hsi_torch.errors import FileFormatError, HSIError, InputError, MissingFileError
from hsi_torch.io.atomic import atomic_write, atomic_write_json
from hsi_torch.io.bounded import (
    MAX_JSON_BYTES,
    csv_header,
    csv_lines,
    declared_image_size,
    npz_declared,
    read_json_bounded,
    require_npz,
)
from hsi_torch.io.capture_manifest import CAPTURE_SETTINGS
from hsi_torch.io.capture_set import (
    ALLOW_OUTSIDE_KEY,
    CAPTURE_SET_SCHEMA_VERSION,
    CAPTURE_TYPES,
    MANIFEST,
    NOMINAL_LAYOUT,
    ROLE_FOLDERS,
    duplicate_uses,
    read_capture_set,
    read_nominal_layout,
    scan_label,
    wavelength_from_name,
)
from hsi_torch.io.captures import SUPPORTED_SUFFIXES
from hsi_torch.io.safety import short_text

__all__ = [
    "SHEET_COLUMNS",
    "SheetRow",
    "ImportReport",
    "read_sheet",
    "rows_from_patterns",
    "import_captures",
    "check_capture_set",
    "run_captures",
]

#: The sheet's columns: ``file`` and ``role`` required, the rest optional.
SHEET_COLUMNS = ("file", "role", "wavelength_nm", "exposure_s", "black_level", "white_level",
                 "cfa_pattern", "name", "camera_make", "camera_model")  # fmt: skip
_NUMERIC = ("wavelength_nm", "exposure_s", "white_level")
#: the calibration grid the import report is made for (calibrate.yaml's defaults)
DEFAULT_GRID_NM = (430.0, 670.0, 10.0)


@dataclass
class SheetRow:
    """One capture of a sheet (or of a name pattern).

    Attributes:
        file: the capture file (absolute).
        role: ``scan``, ``white``, ``grid``, ``dark`` or ``scene``.
        where: ``sheet.csv:line`` or the pattern, for messages.
        wavelength_nm: scan frames: the wavelength (sheet, else the file name, else metadata).
        name: scene captures: the scene's name.
        settings: the given per-file settings (keys of :data:`CAPTURE_SETTINGS`).
    """

    file: Path
    role: str
    where: str
    wavelength_nm: float | None = None
    name: str | None = None
    settings: dict[str, Any] = field(default_factory=dict)


def _did_you_mean(word: str, choices: Sequence[str]) -> str:
    near = difflib.get_close_matches(word, list(choices), n=1)
    return f" (did you mean '{near[0]}'?)" if near else ""


def _check_file(p: Path, where: str) -> None:
    if not p.exists():
        raise MissingFileError(f"{where}: file {p} does not exist")
    if not p.is_file():
        raise FileFormatError(f"{where}: {p} is not a regular file")
    if p.suffix.lower() not in SUPPORTED_SUFFIXES:
        raise FileFormatError(
            f"{where}: {p.name}: unsupported file type {p.suffix!r}; captures are camera RAW "
            "(.dng, .cr2, .nef, ...), 8/16-bit TIFF or PNG, NPY or NPZ")


def _cell_value(column: str, text: str, where: str) -> Any:
    """A sheet cell as its setting's value (numbers, a list of numbers for black_level)."""
    if column in _NUMERIC:
        try:
            v = float(text)
        except ValueError:
            raise FileFormatError(f"{where}: column '{column}': {text!r} is not a number") from None
        if not (math.isfinite(v) and v > 0):
            raise FileFormatError(f"{where}: column '{column}' must be > 0, got {text!r}")
        return v
    if column == "black_level":
        parts = [t for t in re.split(r"[\s;/|\[\],]+", text) if t]
        try:
            vals = [float(t) for t in parts]
        except ValueError:
            raise FileFormatError(
                f"{where}: column 'black_level': {text!r} is not a number or a list of 3 (R G B) "
                "or 4 (Bayer cell, row-major) numbers separated by spaces or ';'"
            ) from None
        if len(vals) not in (1, 3, 4) or not all(math.isfinite(v) and v >= 0 for v in vals):
            raise FileFormatError(
                f"{where}: column 'black_level' must be one number >= 0, or 3 (R G B) or 4 "
                f"(Bayer cell) of them, got {text!r}")
        return vals[0] if len(vals) == 1 else vals
    if column == "cfa_pattern":
        v = text.upper()
        if len(v) != 4 or sorted(v) != ["B", "G", "G", "R"]:
            raise FileFormatError(f"{where}: column 'cfa_pattern' must be RGGB, BGGR, GRBG or "
                                  f"GBRG, got {text!r}")  # fmt: skip
        return v
    return text


def read_sheet(path: str | os.PathLike) -> list[SheetRow]:
    """Read and check a capture sheet (see the module docstring).

    Returns:
        One :class:`SheetRow` per capture line, files resolved against the sheet's folder.

    Raises:
        MissingFileError: the sheet or a file it names does not exist.
        FileFormatError: no header, a missing ``file``/``role`` column, an unknown column or role,
            a bad value — each naming the sheet, the line and the column.
    """
    sheet = Path(path)
    if not sheet.is_file():
        raise MissingFileError(f"capture sheet {sheet} not found")
    reader, header = csv_header(sheet, "capture sheet")
    if not header or not any(h.strip() for h in header):
        raise FileFormatError(f"capture sheet {sheet}: empty; the first line is the header "
                              f"({','.join(SHEET_COLUMNS[:3])},...)")  # fmt: skip
    cols = [h.strip().lower() for h in header]
    if len(cols) == 1:
        sep = next((c for c in ";\t|" if c in header[0]), None)
        if sep is not None:
            name = {";": "semicolons (';')", "\t": "tabs", "|": "'|'"}[sep]
            raise FileFormatError(
                f"capture sheet {sheet}: the header {short_text(header[0], 80)!r} is separated by "
                f"{name}; a capture sheet is comma-separated: save it as CSV with ',' between "
                "the cells (spreadsheets in some locales write ';')")
    for c in cols:
        if c not in SHEET_COLUMNS:
            raise FileFormatError(
                f"capture sheet {sheet}: unknown column '{c}'{_did_you_mean(c, SHEET_COLUMNS)}; "
                f"the columns are {', '.join(SHEET_COLUMNS)}")
    for c in ("file", "role"):
        if c not in cols:
            raise FileFormatError(f"capture sheet {sheet}: no '{c}' column (header: "
                                  f"{','.join(cols)})")  # fmt: skip
    if len(set(cols)) != len(cols):
        raise FileFormatError(f"capture sheet {sheet}: a column appears twice ({','.join(cols)})")
    rows: list[SheetRow] = []
    seen: dict[tuple[str, ...], str] = {}  # a line's cells -> where it was first
    for where, cells in csv_lines(reader, sheet):
        key = tuple(c.strip() for c in cells[:len(cols)])
        if key in seen:
            raise FileFormatError(f"{where}: the same line as {seen[key]} (an exact duplicate "
                                  "row would count the capture twice); delete one")  # fmt: skip
        seen[key] = where
        if len(cells) > len(cols) and any(c.strip() for c in cells[len(cols):]):
            raise FileFormatError(f"{where}: {len(cells)} cells but the header has {len(cols)} "
                                  "columns")  # fmt: skip
        vals = {c: (cells[i].strip() if i < len(cells) else "") for i, c in enumerate(cols)}
        if not vals["file"]:
            raise FileFormatError(f"{where}: empty 'file' cell")
        role = vals["role"].lower()
        if role not in CAPTURE_TYPES:
            raise FileFormatError(
                f"{where}: role {vals['role']!r} is not one of {', '.join(CAPTURE_TYPES)}"
                f"{_did_you_mean(role, CAPTURE_TYPES)}")
        f = sheet.parent / vals["file"]
        _check_file(f, where)
        given = {c: _cell_value(c, v, where) for c, v in vals.items()
                 if c not in ("file", "role") and v}  # fmt: skip
        row = SheetRow(f, role, where, settings={k: given[k] for k in CAPTURE_SETTINGS
                                                 if k in given})  # fmt: skip
        if "wavelength_nm" in given:
            if role != "scan":
                raise FileFormatError(f"{where}: 'wavelength_nm' is given for a {role} capture; "
                                      "only scan frames have one")  # fmt: skip
            row.wavelength_nm = given["wavelength_nm"]
        if "name" in given:
            if role != "scene":
                raise FileFormatError(f"{where}: 'name' is given for a {role} capture; only "
                                      "scenes have one")  # fmt: skip
            row.name = given["name"]
        rows.append(row)
    if not rows:
        raise FileFormatError(f"capture sheet {sheet}: no capture lines below the header")
    return rows


def _nm_regex(pattern: str) -> re.Pattern[str]:
    """The regex of a file-name pattern with one ``{nm}`` (the wavelength) and glob wildcards."""
    out = []
    for part in re.split(r"(\{nm\}|\*|\?)", Path(pattern).name):
        if part == "{nm}":
            out.append(r"(?P<nm>\d+(?:[.p]\d+)?)")
        elif part == "*":
            out.append(r".*?")
        elif part == "?":
            out.append(r".")
        else:
            out.append(re.escape(part))
    return re.compile("^" + "".join(out) + "$")


def rows_from_patterns(
    patterns: Mapping[str, Sequence[str]], base: str | os.PathLike = "."
) -> list[SheetRow]:
    """Captures from file-name patterns, by role (``{"scan": ["mono/*_{nm}nm.dng"], ...}``).

    A scan pattern may hold ``{nm}`` in its file name where the wavelength is (else it comes
    from a ``<number>nm`` in the name or the file's metadata); scenes are named by the file's
    stem. Patterns are relative to ``base``.

    Raises:
        InputError: an unknown role, or a pattern matching no file (naming it).
    """
    rows: list[SheetRow] = []
    base = Path(base)
    for role, pats in patterns.items():
        if role not in CAPTURE_TYPES:
            raise InputError(f"unknown role {role!r}; roles are {', '.join(CAPTURE_TYPES)}")
        for pat in pats:
            rx = _nm_regex(pat) if "{nm}" in pat else None
            pat_path = pat if Path(pat).is_absolute() else str(base / pat)
            matches = sorted(glob.glob(pat_path.replace("{nm}", "*")))
            matches = [m for m in matches if rx is None or rx.match(Path(m).name)]
            if not matches:
                raise InputError(f"--{role} {pat!r} matches no file")
            for m in matches:
                f = Path(m)
                where = f"--{role} {pat!r}"
                _check_file(f, where)
                row = SheetRow(f, role, where)
                if rx is not None:
                    row.wavelength_nm = float(rx.match(f.name)["nm"].replace("p", "."))
                if role == "scene":
                    row.name = f.stem
                rows.append(row)
    if not rows:
        raise InputError("no captures given (a --sheet, or --scan/--white/--grid/... patterns)")
    return rows


def _stored_metadata(p: Path) -> dict[str, Any]:
    """The JSON metadata a TIFF/NPY/NPZ capture carries (the TIFF's description, the NPY's
    ``.json`` sidecar, the NPZ's ``metadata`` member), read without decoding a pixel: an import
    never inflates an image (a small compressed file may hold gigabytes)."""
    suffix = p.suffix.lower()
    try:
        if suffix in (".tif", ".tiff"):
            import tifffile  # lazy: only TIFF metadata needs it

            with tifffile.TiffFile(p) as tif:
                text = tif.pages[0].description if len(tif.pages) else ""
        elif suffix == ".npy":
            side = p.with_name(p.name + ".json")
            meta = read_json_bounded(side, "metadata sidecar") if side.exists() else {}
            return meta if isinstance(meta, dict) else {}
        elif suffix == ".npz":
            require_npz(p)
            with np.load(p, allow_pickle=False) as z:
                shape, dtype = npz_declared(z).get("metadata", ((1,), np.dtype(np.uint8)))
                if shape != () or dtype.kind not in "US" or dtype.itemsize > MAX_JSON_BYTES:
                    return {}
                text = str(z["metadata"])
        else:
            return {}
        meta = json.loads(text) if text else {}
    except FileFormatError:
        raise
    except (ValueError, RecursionError):
        return {}  # a foreign description: no metadata
    except Exception as exc:  # noqa: BLE001 - tifffile/zipfile errors on a damaged file
        raise FileFormatError(f"{p}: cannot read the file's metadata ({type(exc).__name__}: "
                              f"{exc})") from None  # fmt: skip
    return meta if isinstance(meta, dict) else {}


def _scan_wavelength(row: SheetRow) -> float | None:
    if row.wavelength_nm is not None:
        return row.wavelength_nm
    lam = wavelength_from_name(row.file.name)
    if lam is None:
        lam = _stored_metadata(row.file).get("wavelength_nm")
    try:
        return None if lam is None else float(lam)
    except (TypeError, ValueError):
        raise FileFormatError(f"{row.file}: its metadata's wavelength_nm {lam!r} is not a "
                              "number") from None  # fmt: skip


@dataclass
class ImportReport:
    """What :func:`import_captures` wrote and found.

    Attributes:
        manifest: the manifest written.
        counts: captures per role.
        bands: per band of the grid, the scan files (``{wavelength_nm: [names]}``).
        repeated: bands with several frames (averaged by calibration).
        outside: ``(name, wavelength_nm)`` of scan frames near no band (not used).
        missing: bands without a frame (calibration will refuse the set).
        warnings: things the lab should fix before calibrating.
    """

    manifest: Path
    counts: dict[str, int]
    bands: dict[float, list[str]]
    repeated: dict[float, list[str]]
    outside: list[tuple[str, float]]
    missing: list[float]
    warnings: list[str]

    def __str__(self) -> str:
        c = self.counts
        lines = [f"wrote {self.manifest}: " + ", ".join(f"{c.get(r, 0)} {r}"
                                                        for r in CAPTURE_TYPES)]  # fmt: skip
        lines.append(f"scan: {len(self.bands) - len(self.missing)} of {len(self.bands)} bands "
                     "of the grid have a frame")  # fmt: skip
        for lam, names in self.repeated.items():
            lines.append(f"  {lam:g} nm: {len(names)} frames, averaged by calibration "
                         f"({', '.join(names)})")  # fmt: skip
        if self.outside:
            lines.append(f"  {len(self.outside)} frame(s) near no band (not used): "
                         + ", ".join(f"{n} ({lam:g} nm)" for n, lam in self.outside))
        return "\n".join(lines)


def _set_value(v: Any) -> str:
    return "[" + ",".join(f"{x:g}" for x in v) + "]" if isinstance(v, list) else (
        f"{v:g}" if isinstance(v, float) else str(v))


def _grid(grid_nm: tuple[float, float, float]) -> list[float]:
    start, stop, step = grid_nm
    n = int(round((stop - start) / step)) + 1
    return [start + k * step for k in range(n)]


def _band_of(grid: list[float], lam: float, tol_nm: float) -> float | None:
    """The band of ``grid`` nearest to ``lam`` (nm), ``None`` when none is within ``tol_nm``."""
    j = min(range(len(grid)), key=lambda k: abs(grid[k] - float(lam)))
    return grid[j] if abs(grid[j] - float(lam)) <= tol_nm else None


def import_captures(
    rows: Sequence[SheetRow],
    out: str | os.PathLike,
    *,
    layout: str | os.PathLike | None = None,
    copy: bool = False,
    grid_nm: tuple[float, float, float] = DEFAULT_GRID_NM,
    tol_nm: float = 0.5,
    source: str = "sheet",
    origin: str | None = None,
) -> ImportReport:
    """Write the capture set ``out`` (``manifest.json``, the layout) for ``rows``.

    Args:
        rows: from :func:`read_sheet` or :func:`rows_from_patterns`.
        out: the capture-set folder (created; a folder with a manifest is refused).
        layout: the nominal layout JSON (copied into the set with its BRF-free mask).
        copy: copy the files into ``out/<role>/`` instead of referencing them where they are.
        grid_nm, tol_nm: the calibration grid ``(start, stop, step)`` and wavelength tolerance the
            report is made for (``calibrate``'s ``grid_*_nm``, ``transmittance.wavelength_tol_nm``).
        source: ``"sheet"`` or ``"manifest"``: how calibration labels the settings' source.
        origin: the sheet or patterns, recorded in the manifest.

    Raises:
        InputError: ``out`` already holds a manifest, a scan frame's wavelength is unknown, two
            scenes share a name.
    """
    out = Path(out)
    if (out / MANIFEST).exists():
        raise InputError(f"{out / MANIFEST} exists; import into a new folder (a capture set "
                         "is never overwritten)")  # fmt: skip
    if out.exists() and not out.is_dir():
        raise InputError(f"output folder {out} exists and is not a folder")
    grid = _grid(grid_nm)
    entries, warnings = [], []
    bands: dict[float, list[str]] = {g: [] for g in grid}
    outside: list[tuple[str, float]] = []
    scenes: dict[str, str] = {}
    for r in rows:
        e: dict[str, Any] = {"type": r.role}
        if r.role == "scan":
            lam = _scan_wavelength(r)
            if lam is None:
                raise InputError(f"{r.where}: scan frame {r.file.name}: wavelength unknown; give "
                                 "it in the sheet's wavelength_nm column, as '<number>nm' in the "
                                 "file name, or with {nm} in the --scan pattern")  # fmt: skip
            named = wavelength_from_name(r.file.name)
            if r.wavelength_nm is not None and named is not None and abs(named - lam) > tol_nm:
                raise InputError(
                    f"{r.where}: scan frame {r.file.name}: the sheet says {lam:g} nm but the file "
                    f"name says {named:g} nm; correct the sheet's wavelength_nm cell (an empty "
                    "cell takes the name's) or the file name")
            e["wavelength_nm"] = lam
            band = _band_of(grid, lam, tol_nm)
            if band is not None:
                bands[band].append(r.file.name)
            else:
                outside.append((r.file.name, lam))
        if r.role == "scene":
            name = r.name or r.file.stem
            if name in scenes:
                raise InputError(f"{r.where}: scene name {name!r} is also {scenes[name]}; give "
                                 "each scene its own name")  # fmt: skip
            scenes[name] = r.where
            e["name"] = name
        e.update(r.settings)
        e["sheet_row"] = r.where
        entries.append((r, e))
    uses = [(r.file, scan_label(e.get("wavelength_nm")) if r.role == "scan"
             else f"scene {e['name']!r}" if r.role == "scene" else r.role)
            for r, e in entries]  # fmt: skip
    dups = duplicate_uses([u for u in uses if not u[1].startswith("scene ")])
    if dups:  # one frame as two wavelengths or roles: before anything is written
        raise InputError("; ".join(dups))
    warnings += [d for d in duplicate_uses(uses) if d not in dups]  # a scene that is a shot
    missing = [g for g, names in bands.items() if not names]
    repeated = {g: names for g, names in bands.items() if len(names) > 1}
    counts = {t: sum(1 for r in rows if r.role == t) for t in CAPTURE_TYPES}
    if missing:
        warnings.append("no scan frame for " + ", ".join(f"{g:g}" for g in missing) + " nm: "
                        "calibration will refuse this set until every band has one")
    for role in ("white", "grid"):
        if not counts[role]:
            warnings.append(f"no {role} captures: calibration needs them")
    if not counts["dark"]:
        warnings.append("no dark frame: calibration subtracts the black level only (check it)")
    for r in rows:
        if r.role == "scene" and r.settings:
            sets = " ".join(f"--set {k}={_set_value(v)}" for k, v in r.settings.items()
                            if k in ("cfa_pattern", "black_level", "white_level"))  # fmt: skip
            warnings.append(
                f"scene {r.file.name}: its settings ({', '.join(r.settings)}) apply when it is "
                "read through the capture set (CaptureSet.read, captures check); 'hsi-torch "
                "reconstruct' reads the file alone" + (f": give them there with {sets}" if sets
                                                       else "")  # fmt: skip
            )

    lay_src = Path(layout) if layout is not None else None
    if lay_src is not None:
        lay = read_nominal_layout(lay_src)  # checked before anything is written
    else:
        lay = None
        warnings.append("no nominal layout (--layout): calibration needs one; write "
                        f"{out / NOMINAL_LAYOUT} or pass calibrate --set layout=...")

    # the files copied into OUT: none may replace a file the user has there (an identical copy,
    # left by an interrupted import of the same files, is fine)
    shots: list[tuple[Path, Path]] = []  # (the capture, its copy in OUT) with --copy
    if copy:
        used: set[str] = set()
        for r, e in entries:
            rel = f"{ROLE_FOLDERS[r.role]}/{r.file.name}"
            k = 1
            while rel in used:
                rel = f"{ROLE_FOLDERS[r.role]}/{r.file.stem}_{k}{r.file.suffix}"
                k += 1
            used.add(rel)
            shots.append((r.file, out / rel))
            e["file"] = rel
    layout_files: list[tuple[Path, Path]] = []  # the nominal layout and its mask
    if lay is not None:
        layout_files.append((lay_src, out / NOMINAL_LAYOUT))
        mask = lay.brf_free_patch.get("usable_mask")
        if mask and (lay_src.parent / mask).is_file():
            layout_files.append((lay_src.parent / mask, out / mask))
    _refuse_users_files(shots + layout_files, out)

    out.mkdir(parents=True, exist_ok=True)
    manifest: dict[str, Any] = {"schema_version": CAPTURE_SET_SCHEMA_VERSION,
                                "generator": "hsi-torch captures import",
                                "settings_source": source}  # fmt: skip
    if copy:
        for src, dst in shots:
            dst.parent.mkdir(parents=True, exist_ok=True)
            if not _same_content(src, dst):
                _atomic_copy(src, dst, stat=True)
    else:
        common = Path(os.path.commonpath([str(r.file.resolve().parent) for r, _ in entries]))
        try:
            root_ref = os.path.relpath(common, out.resolve())
        except ValueError:  # another drive (Windows)
            root_ref = str(common)
        manifest["files_root"] = Path(root_ref).as_posix()
        if Path(root_ref).is_absolute() or root_ref.split(os.sep)[0] == os.pardir:
            manifest[ALLOW_OUTSIDE_KEY] = True  # the lab's files, referenced where they are
        for r, e in entries:
            e["file"] = r.file.resolve().relative_to(common).as_posix()
    for src, dst in layout_files:
        dst.parent.mkdir(parents=True, exist_ok=True)
        if not _same_content(src, dst):  # a set imported into the folder of its layout keeps it
            _atomic_copy(src, dst)
    if lay is not None:
        manifest["nominal_layout"] = NOMINAL_LAYOUT
        manifest["sensor_size"] = list(lay.sensor_size)
    manifest["import"] = {
        "from": origin, "copied": bool(copy),
        "grid_nm": list(grid_nm), "wavelength_tol_nm": tol_nm,
        "repeated_scan_frames": {f"{g:g}": n for g, n in repeated.items()},
        "scan_frames_near_no_band": [{"file": n, "wavelength_nm": lam} for n, lam in outside],
        "bands_without_a_frame": missing,
    }  # fmt: skip
    manifest["captures"] = [e for _, e in entries]
    mpath = atomic_write_json(out / MANIFEST, manifest)
    read_capture_set(out)  # the set reads back (every file found, every key known)
    return ImportReport(mpath, counts, bands, repeated, outside, missing, warnings)


def _atomic_copy(src: Path, dst: Path, stat: bool = False) -> None:
    """Copy ``src`` to ``dst`` whole or not at all (an interrupted import leaves no partial
    file, so that its rerun finds only complete copies); ``stat``: also the times and mode."""
    with open(src, "rb") as fin, atomic_write(dst, "wb") as fout:
        shutil.copyfileobj(fin, fout, 1 << 20)
    if stat:
        shutil.copystat(src, dst)


def _same_content(src: Path, dst: Path) -> bool:
    """``dst`` is ``src`` (the same file) or a byte-identical copy of it."""
    if not dst.is_file():
        return False
    try:
        return os.path.samefile(src, dst) or filecmp.cmp(src, dst, shallow=False)
    except OSError:
        return False


def _refuse_users_files(copies: list[tuple[Path, Path]], out: Path) -> None:
    """Refuse, before anything is written, copies into ``out`` whose destination exists and is
    not already the same file or a byte-identical copy (the user's own file of that name)."""
    theirs = [dst for src, dst in copies
              if (dst.exists() or dst.is_symlink()) and not _same_content(src, dst)]  # fmt: skip
    if theirs:
        names = [d.relative_to(out).as_posix() for d in theirs]
        shown = ", ".join(names[:5]) + (", ..." if len(names) > 5 else "")
        raise InputError(
            f"refusing to import into {out}: it holds files of the names the import would write "
            f"({shown}) that are not copies of the files imported; choose a new folder, or move "
            "them away")


def check_capture_set(
    root: str | os.PathLike, layout: str | os.PathLike | None = None,
    grid_nm: tuple[float, float, float] = DEFAULT_GRID_NM, tol_nm: float = 0.5,
) -> tuple[list[dict[str, Any]], list[str]]:
    """Read every capture of a set as calibration will (its manifest's settings applied) and
    list what it will use.

    Returns:
        ``(rows, problems)``: per capture ``{"file", "role", "band_nm", "kind", "size",
        "cfa_pattern", "black_level", "black_level_source", "white_level", "exposure_s",
        "exposure_source", "camera", "error"}`` — every file, a file that cannot be read as
        calibration will (wrong size, bad metadata, …) with its ``"error"``; ``problems``:
        ``(level, text)`` with level ``"error"`` (calibration will refuse the set: no layout, a
        band without a frame, no white or grid shots, a file refused, calibration captures of
        mixed Bayer patterns, one file in two roles or at two wavelengths) or ``"note"``
        (repeated frames, frames near no band, mixed cameras, black levels that are the default
        0, captures without a known exposure when others have one).

    Raises:
        HSIError: the set cannot be read (naming the file and key).
    """
    cs = read_capture_set(root, layout=layout)
    grid = _grid(grid_nm)
    problems: list[tuple[str, str]] = []
    size = None
    if cs.layout_path is not None and cs.layout_path.is_file():
        size = read_nominal_layout(cs.layout_path).sensor_size
    else:
        problems.append(("error", f"no nominal layout ({cs.layout_path}): calibration needs one"))
    for role in ("white", "grid"):
        if not getattr(cs, role):
            problems.append(("error", f"no {role} captures: calibration needs them"))
    files: list[tuple[Path, str, float | None]] = []
    for p, lam in cs.scan:
        files.append((p, "scan", lam if lam is not None else wavelength_from_name(p.name)))
    for role in ("white", "grid", "dark"):
        files += [(p, role, None) for p in getattr(cs, role)]
    files += [(p, f"scene {n}", None) for n, p in cs.scenes.items()]
    rows = []
    seen_bands: dict[float, int] = {}
    for p, role, lam in files:
        try:  # every file is listed: a bad one is an error of its row, the others still read
            cap = cs.read(p, expected_size=size)
        except HSIError as exc:
            try:
                hw = declared_image_size(p)
            except HSIError:
                hw = None
            problems.append(("error", str(exc)))
            band = _band_of(grid, lam, tol_nm) if role == "scan" and lam is not None else None
            if band is not None:  # (the band has a frame: this one is refused by name)
                seen_bands[band] = seen_bands.get(band, 0) + 1
            rows.append({"file": str(p), "role": role, "wavelength_nm": lam, "band_nm": band,
                         "size": list(hw) if hw else None, "error": str(exc),
                         **dict.fromkeys(_CHECK_KEYS)})  # fmt: skip
            continue
        m = cap.metadata
        band = None
        if role == "scan":
            if lam is None:
                lam = m.get("wavelength_nm")
            if lam is not None:
                band = _band_of(grid, lam, tol_nm)
                if band is not None:
                    seen_bands[band] = seen_bands.get(band, 0) + 1
        make = " ".join(x for x in (m.get("camera_make"), m.get("camera_model")) if x) or None
        exposure = m.get("exposure_s")
        rows.append({
            "file": str(p), "role": role, "wavelength_nm": lam, "band_nm": band,
            "kind": m["kind"], "size": list(cap.image.shape[-2:]),
            "cfa_pattern": m.get("cfa_pattern"), "black_level": m.get("black_level"),
            "black_level_source": m.get("black_level_source"), "white_level": m.get("white_level"),
            "exposure_s": exposure, "exposure_source": m.get("exposure_source"),
            "relative_exposure": m.get("exposure"),
            "camera": make, "error": None,
        })  # fmt: skip
    # what calibrate refuses besides: one sensor has one Bayer pattern; one frame is one thing
    patterns: dict[str, list[str]] = {}
    for r in rows:
        if r["role"] in ("scan", "white", "grid", "dark") and r["kind"] == "bayer":
            patterns.setdefault(str(r["cfa_pattern"]), []).append(Path(r["file"]).name)
    if len(patterns) > 1:
        problems.append(("error", "the calibration captures mix Bayer patterns: " + "; ".join(
            f"{pat} in {', '.join(names[:4])}" + (" ..." if len(names) > 4 else "")
            for pat, names in patterns.items()) + " (calibrate refuses them: frames of another "
            "camera, a crop by one pixel, or a wrong cfa_pattern in the sheet or manifest)"))
    dups = cs.duplicate_files()
    problems += [("error", d) for d in dups]
    problems += [("note", d) for d in cs.duplicate_files(scenes=True) if d not in dups]
    missing = [g for g in grid if g not in seen_bands]
    if missing:
        problems.append(("error", "no scan frame for " + ", ".join(f"{g:g}" for g in missing)
                         + " nm (calibration refuses the set)"))
    for g, n in seen_bands.items():
        if n > 1:
            problems.append(("note", f"{n} scan frames at {g:g} nm: calibration averages them"))
    off = [r for r in rows if r["role"] == "scan" and r["band_nm"] is None
           and r["wavelength_nm"] is not None]  # fmt: skip
    if off:
        problems.append(("note", "scan frames near no band (not used): " + ", ".join(
            f"{Path(r['file']).name} ({r['wavelength_nm']:g} nm)" for r in off)))
    cams = {r["camera"] for r in rows if r["camera"]}
    if len(cams) > 1:
        problems.append(("note", f"captures of {len(cams)} cameras: {sorted(cams)}"))
    defaults = [Path(r["file"]).name for r in rows if r["black_level_source"] == "default"]
    if defaults:
        problems.append(("note", f"{len(defaults)} capture(s) with no black level given or in "
                         f"the file (0 subtracted): {', '.join(defaults[:5])}"
                         + (" ..." if len(defaults) > 5 else "")))
    known = [r for r in rows if r["exposure_s"] is not None]
    if known and len(known) < len(rows):
        unk = [Path(r["file"]).name for r in rows if r["exposure_s"] is None]
        problems.append(("note", f"exposure unknown for {len(unk)} capture(s) "
                         f"({', '.join(unk[:5])}" + (" ..." if len(unk) > 5 else "")
                         + "): no exposure ratio for them"))
    return rows, problems


#: the per-file keys of check_capture_set's rows that an unreadable file leaves empty
_CHECK_KEYS = ("kind", "cfa_pattern", "black_level", "black_level_source", "white_level",
               "exposure_s", "exposure_source", "relative_exposure", "camera")  # fmt: skip


def _format_check(rows: list[dict[str, Any]], problems: list[tuple[str, str]]) -> str:
    def lv(v: Any) -> str:
        if v is None:
            return "-"
        if isinstance(v, list):
            return "/".join(f"{x:g}" for x in v) if len(set(v)) > 1 else f"{v[0]:g}"
        return f"{v:g}"

    lines = ["role         file                                 band   size       black (source)"
             "        white   CFA   exposure (source)      camera"]
    for r in rows:
        band = f"{r['band_nm']:g}" if r["band_nm"] is not None else "-"
        hw = "x".join(map(str, r["size"])) if r.get("size") else "?"
        if r.get("error"):
            lines.append(f"{r['role'][:12]:<12} {Path(r['file']).name[-36:]:<36} {band:>5}  "
                         f"{hw:<10} REFUSED (see the errors)")  # fmt: skip
            continue
        exp = (f"{r['exposure_s']:g} s ({r['exposure_source']})" if r["exposure_s"] is not None
               else "unknown")  # fmt: skip
        lines.append(
            f"{r['role'][:12]:<12} {Path(r['file']).name[-36:]:<36} {band:>5}  {hw:<10} "
            f"{lv(r['black_level']) + ' (' + str(r['black_level_source']) + ')':<21} "
            f"{lv(r['white_level']):>7} {r['cfa_pattern'] or 'RGB':<5} {exp:<22} "
            f"{r['camera'] or '-'}")
    lines += [f"{level}: {text}" for level, text in problems]
    return "\n".join(lines)


def run_captures(args: Any) -> int:
    """``hsi-torch captures import|check`` (see :mod:`hsi_torch.cli`)."""
    if args.action == "import":
        pats = {role: getattr(args, role) for role in CAPTURE_TYPES if getattr(args, role)}
        if args.sheet is not None and pats:
            raise InputError("give a --sheet or name patterns (--scan, --white, ...), not both")
        if args.sheet is not None:
            rows = read_sheet(args.sheet)
            origin, source = str(args.sheet), "sheet"
            layout = args.layout
            if layout is None and (Path(args.sheet).parent / NOMINAL_LAYOUT).is_file():
                layout = Path(args.sheet).parent / NOMINAL_LAYOUT
        else:
            rows = rows_from_patterns(pats)
            origin = " ".join(f"--{k} {p!r}" for k, ps in pats.items() for p in ps)
            source, layout = "manifest", args.layout
        rep = import_captures(rows, args.out, layout=layout, copy=args.copy, source=source,
                              origin=origin)  # fmt: skip
        info(str(rep))
        for w in rep.warnings:
            warn(f"hsi-torch: warning: {w}")
        return 0
    rows, problems = check_capture_set(args.dir, layout=args.layout)
    info(_format_check(rows, [p for p in problems if p[0] == "note"]))
    for level, text in problems:
        if level == "error":
            warn(f"hsi-torch: error: {text}")
    return 1 if any(level == "error" for level, _ in problems) else 0
