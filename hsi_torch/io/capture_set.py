"""Capture sets: the folder of captures a calibration (and an experiment) starts from.

One reader and one writer for the whole package: the simulator writes capture sets with
:func:`write_capture_set_index` and :func:`write_truth`; calibration, the experiments and the
oracle bundle read them with :func:`read_capture_set` and :func:`read_truth`.

Folder format (manifest schema version :data:`CAPTURE_SET_SCHEMA_VERSION` = 1)::

    ROOT/manifest.json          {"schema_version": 1, "captures": [{"file", "type", ...}], ...}
    ROOT/nominal_layout.json    what is known before calibration: sensor_size (H, W),
                                triangles_px (V, 3, 2), parity (V,), reference_bbox (x0, y0, w, h),
                                reflection_sequences, brf_free_patch {polygon_px, usable_mask, ...}
    ROOT/brf_free_mask.png      (H, W) 8-bit, 255 = usable BRF-free pixel of the reference view
    ROOT/scan/ white/ grid/ dark/ scenes/   the captures (any file :func:`hsi_torch.io.read_any`
                                reads)
    ROOT/ground_truth/truth.npz + truth.json   simulated sets only

A capture entry's ``type`` is ``scan`` (with ``wavelength_nm``), ``white``, ``grid``, ``dark`` or
``scene`` (with ``name``); the manifest's keys are published as a JSON Schema
(:mod:`hsi_torch.io.capture_manifest`; the table of keys is in ``docs/calibration.md``, *The
manifest*). A folder without ``manifest.json`` (a real device) is read from its sub-folders; a
scan frame's wavelength then comes from its name (``scan_550nm.tif``, ``mono_552p5nm.dng``) or its
metadata. Every path a manifest names must resolve (``..`` and symlinks followed) to a file inside
``ROOT`` (or ``files_root``) unless the manifest says ``"allow_files_outside": true``.

The BRF-free mask is a PNG; OpenCV, which decodes and encodes it, is imported only where that
happens, so reading a bundle or a capture never loads it.
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hsi_torch.devices import to_numpy
from hsi_torch.errors import FileFormatError, MissingFileError
from hsi_torch.io.atomic import atomic_save_npz, atomic_write_bytes, atomic_write_json
from hsi_torch.io.capture_manifest import check_manifest, entry_settings
from hsi_torch.io.captures import SUPPORTED_SUFFIXES, read_any
from hsi_torch.io.safety import file_sha256, short_repr

__all__ = [
    "CAPTURE_SET_SCHEMA_VERSION",
    "ALLOW_OUTSIDE_KEY",
    "CAPTURE_SUFFIXES",
    "CAPTURE_TYPES",
    "ROLE_FOLDERS",
    "MANIFEST",
    "NOMINAL_LAYOUT",
    "BRF_FREE_MASK",
    "TRUTH_NPZ",
    "TRUTH_JSON",
    "NominalLayout",
    "CaptureSet",
    "read_capture_set",
    "read_nominal_layout",
    "read_mask_png",
    "read_truth",
    "read_truth_meta",
    "wavelength_from_name",
    "duplicate_uses",
    "scan_label",
    "write_capture_set_index",
    "write_truth",
    "encode_mask_png",
]

#: Version of ``manifest.json`` (and ``truth.json``) this software reads and writes.
CAPTURE_SET_SCHEMA_VERSION = 1
MANIFEST = "manifest.json"
NOMINAL_LAYOUT = "nominal_layout.json"
BRF_FREE_MASK = "brf_free_mask.png"
TRUTH_NPZ = "ground_truth/truth.npz"
TRUTH_JSON = "ground_truth/truth.json"
CAPTURE_TYPES = ("scan", "white", "grid", "dark", "scene")
#: File suffixes of captures found in the sub-folders of a folder without a manifest.
CAPTURE_SUFFIXES = SUPPORTED_SUFFIXES  # every file read_any reads
_WL_RE = re.compile(r"(\d+(?:[.p]\d+)?)\s*nm", re.IGNORECASE)
#: The sub-folder of each capture type (a folder without a manifest; ``captures import --copy``).
ROLE_FOLDERS = {"scan": "scan", "white": "white", "grid": "grid", "dark": "dark", "scene": "scenes"}


def wavelength_from_name(name: str) -> float | None:
    """Wavelength (nm) in a file name such as ``scan_550nm.tif`` or ``mono_552p5nm.dng``."""
    m = _WL_RE.findall(Path(name).stem)
    if not m:
        return None
    return float(m[-1].replace("p", "."))


class _DuplicateKey(ValueError):
    pass


def _no_duplicate_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """``json.loads``'s ``object_pairs_hook``: a key given twice in one object is refused (JSON
    readers keep the later value in silence; a hand-edited manifest or layout with
    ``"black_level"`` twice would be read with the one its author may not have meant)."""
    out: dict[str, Any] = {}
    for k, v in pairs:
        if k in out:
            raise _DuplicateKey(k)
        out[k] = v
    return out


def _read_json(path: Path, what: str) -> Any:
    try:
        return json.loads(path.read_text(), object_pairs_hook=_no_duplicate_keys)
    except json.JSONDecodeError as exc:
        raise FileFormatError(f"{path}: not valid JSON ({exc})") from exc
    except _DuplicateKey as exc:
        raise FileFormatError(
            f"{what} {path}: key {str(exc)!r} is given twice in one JSON object; JSON readers "
            "keep the later value in silence: keep one of them"
        ) from None
    except OSError as exc:
        raise MissingFileError(f"{what} {path} cannot be read ({exc})") from exc


def _read_json_object(path: Path, what: str, missing: str | None = None) -> dict[str, Any]:
    """A JSON object file; ``missing``: the message when the file is absent (default: the
    file's name and kind)."""
    if not path.is_file():
        raise MissingFileError(missing or f"{what} {path} not found")
    d = _read_json(path, what)
    if not isinstance(d, dict):
        raise FileFormatError(f"{what} {path}: must be a JSON object")
    return d


@dataclass
class NominalLayout:
    """The view layout known before calibration (``nominal_layout.json``), checked.

    Attributes:
        path: the file.
        sensor_size: ``(H, W)``; triangles: ``(V, 3, 2)`` float64 sensor px; parity: ``(V,)``
            int64 ±1; reference_bbox: ``(x0, y0, w, h)``; reflection_sequences: per view (may
            be empty when unknown); brf_free_patch: the patch description (``polygon_px``,
            ``usable_mask``, …) or ``{}``; data: the whole parsed object.
    """

    path: Path
    sensor_size: tuple[int, int]
    triangles: np.ndarray
    parity: np.ndarray
    reference_bbox: tuple[int, int, int, int]
    reflection_sequences: list[tuple[int, ...]]
    brf_free_patch: dict[str, Any]
    data: dict[str, Any] = field(repr=False)

    @property
    def num_views(self) -> int:
        return int(self.triangles.shape[0])

    def brf_free_polygon(self) -> np.ndarray | None:
        """``(K, 2)`` float64 sensor px of the BRF-free disk's outline, or ``None``."""
        poly = self.brf_free_patch.get("polygon_px")
        return np.asarray(poly, np.float64) if poly else None


def read_nominal_layout(path: str | Path) -> NominalLayout:
    """Read and check ``nominal_layout.json``; errors name the file and the key at fault."""
    p = Path(path)
    d = _read_json_object(
        p, "nominal layout",
        missing=f"nominal layout {p} not found: calibration needs the view triangles, parity, "
        "reference_bbox and BRF-free patch (see docs/calibration.md)")  # fmt: skip
    for key in ("sensor_size", "triangles_px", "parity", "reference_bbox"):
        if key not in d:
            raise FileFormatError(f"nominal layout {p}: missing key '{key}'")
    tri = np.asarray(d["triangles_px"], dtype=np.float64)
    par = np.asarray(d["parity"], dtype=np.int64).reshape(-1)
    bbox = [int(v) for v in d["reference_bbox"]]
    size = tuple(int(v) for v in d["sensor_size"])
    if tri.ndim != 3 or tri.shape[1:] != (3, 2):
        raise FileFormatError(f"nominal layout {p}: triangles_px must be (V, 3, 2), got "
                              f"{tri.shape}")  # fmt: skip
    if par.shape != (tri.shape[0],) or not np.all(np.isin(par, (-1, 1))):
        raise FileFormatError(f"nominal layout {p}: parity must be {tri.shape[0]} values of ±1")
    if len(bbox) != 4 or bbox[2] <= 0 or bbox[3] <= 0:
        raise FileFormatError(f"nominal layout {p}: reference_bbox must be (x0, y0, w, h)")
    if len(size) != 2:
        raise FileFormatError(f"nominal layout {p}: sensor_size must be (H, W)")
    ref = int(d.get("reference_view", 0))
    if ref != 0:
        raise FileFormatError(f"nominal layout {p}: reference_view must be 0 (got {ref})")
    seqs = [tuple(int(i) for i in s) for s in d.get("reflection_sequences", [])]
    patch = d.get("brf_free_patch") or {}
    return NominalLayout(p, (size[0], size[1]), tri, par, (bbox[0], bbox[1], bbox[2], bbox[3]),
                         seqs, dict(patch), d)  # fmt: skip


@dataclass
class CaptureSet:
    """The files of one capture set (see the module docstring).

    Attributes:
        root: the folder.
        scan: ``[(file, wavelength_nm or None)]`` monochromator frames, in manifest (or name)
            order; ``None`` when neither the manifest nor the name tells the wavelength.
        white, grid, dark: files of the white-reference shots, circle-grid shots, dark frames.
        scenes: ``{name: file}`` scene captures.
        manifest: the parsed ``manifest.json`` or ``None`` (a folder without one).
        layout_path: the nominal layout to use (it may not exist: see :meth:`layout`).
        brf_free_mask_path: the PNG of usable BRF-free pixels, or ``None``.
        settings: per capture file, the manifest's settings for it (entry, else set level):
            ``{file: {key: (value, source)}}`` with keys of
            :data:`hsi_torch.io.capture_manifest.CAPTURE_SETTINGS` and ``exposure``, source
            ``"manifest"`` or ``"sheet"`` (:func:`~hsi_torch.io.capture_manifest.entry_settings`);
            empty for a folder without a manifest.
    """

    root: Path
    scan: list[tuple[Path, float | None]] = field(default_factory=list)
    white: list[Path] = field(default_factory=list)
    grid: list[Path] = field(default_factory=list)
    dark: list[Path] = field(default_factory=list)
    scenes: dict[str, Path] = field(default_factory=dict)
    manifest: dict[str, Any] | None = None
    layout_path: Path | None = None
    brf_free_mask_path: Path | None = None
    settings: dict[Path, dict[str, Any]] = field(default_factory=dict)

    def layout(self) -> NominalLayout:
        """The nominal layout (:func:`read_nominal_layout`)."""
        if self.layout_path is None:
            raise MissingFileError(f"capture set {self.root}: no nominal layout")
        return read_nominal_layout(self.layout_path)

    def require_calibration_captures(self) -> None:
        """Raise naming what is missing when there is no scan, white or grid capture, and
        naming both uses when one file (or a byte-identical copy) is used in two roles or at
        two wavelengths (:meth:`duplicate_files`)."""
        where = f"{MANIFEST}" if self.manifest is not None else "folders scan/, white/, grid/"
        for name, lst in (("monochromator scan", self.scan), ("white-reference", self.white),
                          ("circle-grid", self.grid)):  # fmt: skip
            if not lst:
                raise FileFormatError(
                    f"captures folder {self.root}: no {name} captures (looked in {where})")
        dups = self.duplicate_files()
        if dups:
            raise FileFormatError(f"captures folder {self.root}: " + "; ".join(dups))

    def uses(self, scenes: bool = False) -> list[tuple[Path, str]]:
        """Every calibration capture (and with ``scenes``, every scene) with what it is used
        as: ``(file, "scan frame at 550 nm" | "white" | "grid" | "dark" | "scene 'name'")``."""
        out = [(p, scan_label(lam if lam is not None else wavelength_from_name(p.name)))
               for p, lam in self.scan]  # fmt: skip
        for role in ("white", "grid", "dark"):
            out += [(p, role) for p in getattr(self, role)]
        return out + ([(p, f"scene {n!r}") for n, p in self.scenes.items()] if scenes else [])

    def duplicate_files(self, scenes: bool = False) -> list[str]:
        """One calibration capture used as two things — two roles, or scan frames at two
        wavelengths — found by resolved path and by the bytes (a copy counts): one message per
        file, naming both uses (:func:`duplicate_uses`); ``scenes``: the scenes too. Empty when
        there is none."""
        return duplicate_uses(self.uses(scenes))

    def read(self, path: str | Path, **kwargs: Any) -> Any:
        """:func:`hsi_torch.io.read_any` of one of the set's captures with the manifest's settings
        for it (:attr:`settings`, their sources labelled); keyword arguments given here win (and
        count as ``"config"`` unless ``sources`` says otherwise). Returns the
        :class:`~hsi_torch.io.captures.LinearCapture` (the manifest's relative ``exposure`` is
        put into its metadata)."""
        p = Path(path)
        given = self.settings.get(p, {})
        kw = {k: v for k, (v, _) in given.items() if k != "exposure"}
        sources = {k: src for k, (_, src) in given.items() if k != "exposure"}
        for k in kwargs:
            sources.pop(k, None)
        sources.update(kwargs.pop("sources", None) or {})
        kw.update(kwargs)
        cap = read_any(p, sources=sources, **kw)
        if "exposure" in given:
            cap.metadata["exposure"] = given["exposure"][0]
        return cap

    def scene(self, name: str) -> Path:
        """The capture of scene ``name``."""
        if name not in self.scenes:
            raise MissingFileError(
                f"capture set {self.root}: no scene {name!r} (it has {sorted(self.scenes)})")
        return self.scenes[name]

    def read_brf_free_mask(self, size: tuple[int, int] | None = None) -> np.ndarray:
        """The usable BRF-free pixels, ``(H, W)`` bool (:func:`read_mask_png`)."""
        if self.brf_free_mask_path is None:
            raise MissingFileError(f"capture set {self.root}: no BRF-free mask ({BRF_FREE_MASK})")
        return read_mask_png(self.brf_free_mask_path, size)

    def files(self) -> dict[str, Path]:
        """Every calibration input file, labelled by its path relative to the folder (for
        provenance): scan, white, grid and dark captures, the layout and the BRF-free mask."""
        out: dict[str, Path] = {}
        paths = [p for p, _ in self.scan] + self.white + self.grid + self.dark
        paths += [p for p in (self.layout_path, self.brf_free_mask_path) if p is not None]
        for p in paths:
            try:
                key = str(p.resolve().relative_to(self.root.resolve()))
            except ValueError:
                key = str(p)
            out[key] = p
        return out


def scan_label(lam: float | None) -> str:
    return "scan frame at " + (f"{lam:g} nm" if lam is not None else "an unknown wavelength")


def _digest(p: Path, head: int | None = None) -> str:
    """SHA-256 of the file's bytes (its first ``head`` bytes when given)."""
    if head is None:
        return file_sha256(p)
    with open(p, "rb") as f:
        return file_sha256(f.read(head))


def duplicate_uses(uses: Sequence[tuple[Path, str]]) -> list[str]:
    """Files used under two different labels (``"white"``, ``"scan frame at 550 nm"``, …): the
    same file by resolved path, or another file with the same bytes (a copy). The same file
    twice under one label is reported too (it would count twice); byte-identical copies under one
    label are not (repeated frames of a noiseless simulation can be).

    Returns:
        One message per duplicated file, naming each file and its uses. The bytes are compared
        by size, then the SHA-256 of the first MiB, then of the whole file, so distinct frames
        cost one MiB read each.
    """
    by_path: dict[Path, list[tuple[Path, str]]] = {}
    for p, label in uses:
        try:
            key = p.resolve()
        except (OSError, RuntimeError):
            key = p
        by_path.setdefault(key, []).append((p, label))
    groups: dict[Any, list[Path]] = {}
    for key in by_path:
        try:
            groups.setdefault(key.stat().st_size, []).append(key)
        except OSError:
            continue  # a missing file is reported by its reader
    same: list[list[Path]] = []
    for keys in groups.values():
        for stage in (1 << 20, None):
            if len(keys) < 2:
                break
            sub: dict[str, list[Path]] = {}
            for k in keys:
                sub.setdefault(_digest(k, stage), []).append(k)
            keys = [k for ks in sub.values() if len(ks) > 1 for k in ks]
            if stage is None:
                same += [ks for ks in sub.values() if len(ks) > 1]
        # (keys left with one member each are unique)
    merged = [[k] for k in by_path if not any(k in ks for ks in same)] + same
    out = []
    for keys in merged:
        entries = [e for k in keys for e in by_path[k]]
        labels = list(dict.fromkeys(label for _, label in entries))
        if len(labels) < 2:
            if len(by_path[keys[0]]) > 1 and len(keys) == 1:  # one file listed again
                out.append(f"{entries[0][0]} is listed {len(entries)} times as {labels[0]}: "
                           "a frame counts once; delete the repeated entry")  # fmt: skip
            continue
        names = list(dict.fromkeys(str(p) for p, _ in entries))
        what = (f"{names[0]} is used as " if len(names) == 1 else
                f"{', '.join(names)} hold the same bytes and are used as ")  # fmt: skip
        out.append(what + " and as ".join(labels) + ": one frame cannot be both (a copied line of "
                   "the sheet or manifest?); give each use its own capture")  # fmt: skip
    return out


def _folder_files(folder: Path) -> list[Path]:
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir()
                  if p.is_file() and p.suffix.lower() in CAPTURE_SUFFIXES)  # fmt: skip


def _check_version(d: Mapping[str, Any], path: Path) -> None:
    ver = d.get("schema_version", CAPTURE_SET_SCHEMA_VERSION)
    if type(ver) is not int or ver != CAPTURE_SET_SCHEMA_VERSION:
        raise FileFormatError(
            f"{path}: schema_version {ver!r} is not supported (this software reads version "
            f"{CAPTURE_SET_SCHEMA_VERSION})")


#: Manifest key by which its author lets entries name files outside the set's folder.
ALLOW_OUTSIDE_KEY = "allow_files_outside"


def _inside(root: Path, value: str) -> bool:
    """``root / value`` is a relative path that resolves (``..`` and symlinks followed) inside
    ``root``."""
    try:
        return not Path(value).is_absolute() and (root / value).resolve().is_relative_to(
            root.resolve())
    except (OSError, RuntimeError, ValueError):  # a symlink loop, ...
        return False


def _manifest_path(root: Path, value: Any, mpath: Path, key: str, outside_ok: bool) -> Path:
    """The file a manifest entry names: a relative path string that resolves (symlinks
    followed) inside ``root`` (the set's folder, or the manifest's ``files_root``), unless
    ``outside_ok``; errors name the manifest and ``key``."""
    if not isinstance(value, str) or not value.strip() or "\0" in value:
        raise FileFormatError(
            f"{mpath}: {key} must be a file name (a non-empty string relative to the folder), "
            f"got {type(value).__name__} {short_repr(value, 80)}")
    p = root / value
    if outside_ok:
        return p
    if not _inside(root, value):
        raise FileFormatError(
            f"{mpath}: {key} {short_repr(value, 120)} points outside the capture set's folder "
            f"{root} (absolute, '..' or a symlink out of it); only files inside it are read "
            f"unless the manifest says \"{ALLOW_OUTSIDE_KEY}\": true")
    return p


def read_capture_set(
    root: str | Path, *, layout: str | Path | None = None, brf_free_mask: str | Path | None = None
) -> CaptureSet:
    """Find the files of a capture set (manifest, or the sub-folders of a real device's folder).

    Args:
        layout: a nominal layout to use instead of the set's (``manifest["nominal_layout"]``,
            else ``ROOT/nominal_layout.json``).
        brf_free_mask: a BRF-free mask PNG to use instead of the set's (the layout's
            ``brf_free_patch.usable_mask``, the manifest's ``brf_free_mask``, else
            ``ROOT/brf_free_mask.png``; ``None`` when none exists).

    Raises:
        MissingFileError: the folder, a listed capture or the given ``brf_free_mask`` is missing.
        FileFormatError: the manifest is not valid JSON, has another schema version or an entry
            without ``file``/``type``.
    """
    root = Path(root)
    if not root.is_dir():
        raise MissingFileError(f"captures folder {root} does not exist")
    cs = CaptureSet(root)
    mpath = root / MANIFEST
    outside_ok = False
    if mpath.is_file():
        manifest = _read_json_object(mpath, "manifest")
        _check_version(manifest, mpath)
        cs.manifest = manifest
        check_manifest(manifest, mpath)
        outside_ok = manifest.get(ALLOW_OUTSIDE_KEY, False)
        if not isinstance(outside_ok, bool):
            raise FileFormatError(f"{mpath}: {ALLOW_OUTSIDE_KEY} must be true or false, got "
                                  f"{short_repr(outside_ok, 80)}")  # fmt: skip
        # files_root: the folder the manifest's author names for its files (captures import
        # writes it to reference a lab's files in place) — the entries stay inside it
        files_root = root
        if manifest.get("files_root") is not None:
            fr = manifest["files_root"]
            if not isinstance(fr, str) or not fr.strip() or "\0" in fr:
                raise FileFormatError(f"{mpath}: files_root must be a folder name, got "
                                      f"{short_repr(fr, 80)}")  # fmt: skip
            files_root = root / fr
            if not outside_ok and not _inside(root, fr):
                raise FileFormatError(
                    f"{mpath}: files_root {short_repr(fr, 120)} points outside the capture set's "
                    f"folder {root} (absolute, '..' or a symlink out of it); the captures are "
                    f"read from inside it unless the manifest says \"{ALLOW_OUTSIDE_KEY}\": true")
            if not files_root.is_dir():
                raise MissingFileError(f"{mpath}: files_root {files_root} is not a folder")
        # (check_manifest has checked the entries' form, types and settings)
        for k, e in enumerate(manifest.get("captures", [])):
            p = _manifest_path(files_root, e["file"], mpath, f"captures[{k}].file", outside_ok)
            cs.settings[p] = entry_settings(manifest, e)
            if not p.is_file():
                raise MissingFileError(f"{mpath}: captures[{k}] file {p} does not exist")
            t = e["type"]
            if t == "scan":
                wl = e.get("wavelength_nm")
                cs.scan.append((p, None if wl is None else float(wl)))
            elif t == "scene":
                name = e.get("name", p.stem)
                if not isinstance(name, str):
                    raise FileFormatError(f"{mpath}: captures[{k}].name must be a string, got "
                                          f"{short_repr(name, 80)}")  # fmt: skip
                cs.scenes[name] = p
            elif t in ("white", "grid", "dark"):
                getattr(cs, t).append(p)
    else:
        found = {t: _folder_files(root / sub) for t, sub in ROLE_FOLDERS.items()}
        cs.scan = [(p, wavelength_from_name(p.name)) for p in found["scan"]]
        cs.white, cs.grid, cs.dark = found["white"], found["grid"], found["dark"]
        cs.scenes = {p.stem: p for p in found["scene"]}
    if layout is not None:
        cs.layout_path = Path(layout)
    elif cs.manifest is not None and cs.manifest.get("nominal_layout"):
        cs.layout_path = _manifest_path(root, cs.manifest["nominal_layout"], mpath,
                                        "nominal_layout", outside_ok)  # fmt: skip
    else:
        cs.layout_path = root / NOMINAL_LAYOUT
    if brf_free_mask is not None:
        cs.brf_free_mask_path = Path(brf_free_mask)
        if not cs.brf_free_mask_path.is_file():
            raise MissingFileError(f"BRF-free mask {cs.brf_free_mask_path} not found")
    else:
        cands = []
        if cs.layout_path.is_file():  # the layout is checked where it is used (CaptureSet.layout)
            d = _read_json(cs.layout_path, "nominal layout")
            patch = d.get("brf_free_patch") if isinstance(d, dict) else None
            if isinstance(patch, dict) and patch.get("usable_mask"):
                mask_val = patch["usable_mask"]
                if layout is not None or outside_ok:  # the caller's own layout, or opted in
                    cands.append(cs.layout_path.parent / str(mask_val))
                else:  # the set's layout (inside the folder): its mask must be inside too
                    rel = cs.layout_path.parent.relative_to(root)
                    cands.append(_manifest_path(
                        root, str(rel / mask_val) if isinstance(mask_val, str) else mask_val,
                        cs.layout_path, "brf_free_patch.usable_mask", outside_ok))
        if cs.manifest is not None and cs.manifest.get("brf_free_mask"):
            cands.append(_manifest_path(root, cs.manifest["brf_free_mask"], mpath,
                                        "brf_free_mask", outside_ok))  # fmt: skip
        cands.append(root / BRF_FREE_MASK)
        cs.brf_free_mask_path = next((c for c in cands if c.is_file()), None)
    return cs


def read_mask_png(path: str | Path, size: tuple[int, int] | None = None) -> np.ndarray:
    """``(H, W)`` bool of an 8-bit mask PNG (pixels > 127); ``size`` checks ``(H, W)``."""
    import cv2  # lazy: OpenCV only where a PNG mask is decoded (see the module docstring)

    p = Path(path)
    m = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
    if m is None:
        raise FileFormatError(f"BRF-free mask {p}: not a readable image")
    if size is not None and m.shape != tuple(size):
        raise FileFormatError(
            f"BRF-free mask {p}: size {m.shape} does not match the sensor size {tuple(size)}")
    return m > 127


def encode_mask_png(mask: Any) -> bytes:
    """PNG bytes of a bool ``(H, W)`` mask (tensor or array): 255 where True."""
    import cv2  # lazy: OpenCV only where a PNG mask is encoded (see the module docstring)

    ok, buf = cv2.imencode(".png", to_numpy(mask, np.uint8) * 255)
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()


def write_capture_set_index(
    root: str | Path,
    *,
    captures: list[dict[str, Any]],
    nominal_layout: Mapping[str, Any],
    brf_free_mask: Any,
    **manifest_fields: Any,
) -> Path:
    """Write ``manifest.json``, ``nominal_layout.json`` and ``brf_free_mask.png`` of a capture
    set whose captures are already written (atomically, each file).

    Args:
        captures: manifest entries (``file`` relative to ``root``, ``type``, …).
        nominal_layout: the layout object (``schema_version`` is added).
        brf_free_mask: ``(H, W)`` bool usable BRF-free pixels.
        **manifest_fields: further manifest keys (``sensor_size``, ``cfa_pattern``, …).

    Returns:
        The manifest's path.
    """
    root = Path(root)
    for k, e in enumerate(captures):
        if e.get("type") not in CAPTURE_TYPES:
            raise ValueError(f"captures[{k}]: type {e.get('type')!r} is not one of "
                             f"{CAPTURE_TYPES}")  # fmt: skip
    atomic_write_bytes(root / BRF_FREE_MASK, encode_mask_png(brf_free_mask))
    atomic_write_json(root / NOMINAL_LAYOUT,
                      {"schema_version": CAPTURE_SET_SCHEMA_VERSION, **nominal_layout})
    manifest = {
        "schema_version": CAPTURE_SET_SCHEMA_VERSION,
        **manifest_fields,
        "nominal_layout": NOMINAL_LAYOUT,
        "brf_free_mask": BRF_FREE_MASK,
        "ground_truth": TRUTH_NPZ if (root / TRUTH_NPZ).is_file() else None,
        "captures": captures,
    }
    return atomic_write_json(root / MANIFEST, manifest)


def write_truth(root: str | Path, arrays: Mapping[str, Any], meta: Mapping[str, Any]) -> Path:
    """Write a simulated set's ground truth: ``truth.npz`` (arrays) and ``truth.json`` (``meta``
    with ``schema_version``). Returns the NPZ's path."""
    root = Path(root)
    npz = atomic_save_npz(root / TRUTH_NPZ, dict(arrays))
    atomic_write_json(root / TRUTH_JSON, {"schema_version": CAPTURE_SET_SCHEMA_VERSION, **meta})
    return npz


def read_truth_meta(root: str | Path) -> dict[str, Any]:
    """The parsed ``ground_truth/truth.json`` of a simulated capture set, ``{}`` when the set
    has none (the records of what was rendered: ``mismatch``, ``white_mismatch``, …)."""
    js = Path(root) / TRUTH_JSON
    return _read_json_object(js, "ground truth") if js.is_file() else {}


def read_truth(root: str | Path) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Read ``ground_truth/truth.npz`` and ``truth.json`` of a simulated capture set.

    Returns:
        ``(arrays, meta)``: every array of ``truth.npz`` and the parsed ``truth.json``.
    """
    root = Path(root)
    npz, js = root / TRUTH_NPZ, root / TRUTH_JSON
    hint = "is not a simulated capture set with ground truth (run `hsi-torch simulate` first)"
    if not npz.is_file():
        raise MissingFileError(f"{npz} not found: {root} {hint}")
    meta = _read_json_object(js, "ground truth", missing=f"{js} not found: {root} {hint}")
    _check_version(meta, js)
    with np.load(npz, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    return arrays, meta
