"""The capture-set manifest's published schema, and the per-file settings it gives calibration.

The schema ships with the package (``capture_set.schema.json`` beside this module, JSON Schema
2020-12; :func:`manifest_schema`), documented key by key in ``docs/calibration.md``. Every key of
a manifest is either

- a **setting** calibration honours: per capture ``file``, ``type``, ``wavelength_nm``, ``name``,
  ``cfa_pattern``, ``black_level``, ``white_level``, ``exposure_s``, ``exposure`` (relative),
  ``camera_make``, ``camera_model``; for the whole set ``captures``, ``files_root``,
  ``nominal_layout``, ``brf_free_mask``, ``sensor_size`` (checked against the layout),
  ``settings_source`` and the same six capture settings as defaults for every capture; or
- **descriptive** (its schema description starts with "descriptive"): recorded, never a setting
  (``seed``, ``pose``, ``generator``, …);

any other key is refused by name (:func:`check_manifest`), so a setting is never silently
ignored. Order of precedence for a capture's settings: the calibration config's
``cfa_pattern``/``black_level``/``white_level`` (the ``--set`` overrides), then the capture's own
entry, then the manifest's set-level key, then the file's own metadata (RAW/DNG/EXIF/JSON), then
the defaults (black 0, white = the integer maximum).
"""

from __future__ import annotations

import difflib
import functools
import json
import math
from collections.abc import Mapping
from importlib import resources
from pathlib import Path
from typing import Any

from hsi_torch.errors import FileFormatError

__all__ = [
    "SCHEMA_FILE",
    "CAPTURE_SETTINGS",
    "manifest_schema",
    "manifest_keys",
    "check_manifest",
    "entry_settings",
]

SCHEMA_FILE = "capture_set.schema.json"
#: The per-capture settings a manifest (entry or set level) or a sheet may give; they go to
#: :func:`hsi_torch.io.read_any` as keyword overrides.
CAPTURE_SETTINGS = ("cfa_pattern", "black_level", "white_level", "exposure_s", "camera_make",
                    "camera_model")  # fmt: skip


@functools.lru_cache(maxsize=1)
def manifest_schema() -> dict[str, Any]:
    """The manifest's JSON Schema (a fresh parse is cached; do not modify the result)."""
    text = resources.files("hsi_torch.io").joinpath(SCHEMA_FILE).read_text(encoding="utf-8")
    return json.loads(text)


def manifest_keys() -> dict[str, dict[str, str]]:
    """``{"set": {key: description}, "entry": {key: description}}`` from the schema."""
    s = manifest_schema()
    entry = s["properties"]["captures"]["items"]["properties"]
    return {"set": {k: v.get("description", "") for k, v in s["properties"].items()},
            "entry": {k: v.get("description", "") for k, v in entry.items()}}  # fmt: skip


def is_descriptive(description: str) -> bool:
    """A schema key whose description starts with "descriptive" is recorded, never a setting."""
    return description.startswith("descriptive")


def _unknown(key: str, known: Mapping[str, str], where: str) -> FileFormatError:
    near = difflib.get_close_matches(key, list(known), n=1)
    hint = f" (did you mean '{near[0]}'?)" if near else ""
    settings = sorted(k for k, d in known.items() if not is_descriptive(d))
    return FileFormatError(
        f"{where}: unknown key '{key}'{hint}; a manifest key is a setting calibration honours "
        f"({', '.join(settings)}) or a descriptive key of the published schema "
        "(docs/calibration.md, 'The manifest'), never ignored")


def _number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _check_setting(key: str, v: Any, where: str) -> None:
    """Type and range of one capture setting (``where`` names the file and key); ``None``
    (JSON null) is "not given"."""
    if v is None and key not in ("file", "type", "files_root"):
        return
    if key == "cfa_pattern":
        ok = isinstance(v, str) and len(v) == 4 and sorted(v.upper()) == ["B", "G", "G", "R"]
        if not ok:
            raise FileFormatError(f"{where}: 'cfa_pattern' must be RGGB, BGGR, GRBG or GBRG, "
                                  f"got {v!r}")  # fmt: skip
    elif key == "black_level":
        vals = v if isinstance(v, list) else [v]
        if not (len(vals) in (1, 3, 4) and all(_number(x) and x >= 0 for x in vals)):
            raise FileFormatError(f"{where}: 'black_level' must be a number >= 0 or a list of 3 "
                                  f"(R, G, B) or 4 (Bayer cell) numbers, got {v!r}")  # fmt: skip
    elif key in ("white_level", "exposure_s", "exposure", "wavelength_nm"):
        if not (_number(v) and v > 0):
            raise FileFormatError(f"{where}: '{key}' must be a number > 0, got {v!r}")
    elif key in ("camera_make", "camera_model", "name", "file", "files_root"):
        if not (isinstance(v, str) and v):
            raise FileFormatError(f"{where}: '{key}' must be a non-empty string, got {v!r}")


def check_manifest(manifest: Mapping[str, Any], path: str | Path) -> None:
    """Refuse, by name, every key the schema does not know and every setting of the wrong type.

    Args:
        manifest: the parsed ``manifest.json`` (a JSON object); path: its file (for messages).

    Raises:
        FileFormatError: naming the file, the entry (``captures[k]``, its file) and the key.
    """
    keys = manifest_keys()
    where = str(path)
    for k, v in manifest.items():
        if k not in keys["set"]:
            raise _unknown(k, keys["set"], where)
        if k in CAPTURE_SETTINGS or k == "files_root":
            _check_setting(k, v, f"{where}: key")
    caps = manifest.get("captures", [])
    if not isinstance(caps, list):
        raise FileFormatError(f"{where}: 'captures' must be a list of entries")
    if "sensor_size" in manifest:
        sz = manifest["sensor_size"]
        if not (isinstance(sz, list) and len(sz) == 2
                and all(isinstance(x, int) and not isinstance(x, bool) and x > 0 for x in sz)):
            raise FileFormatError(f"{where}: 'sensor_size' must be [H, W], got {sz!r}")
    src = manifest.get("settings_source", "manifest")
    if src not in ("manifest", "sheet"):
        raise FileFormatError(f"{where}: 'settings_source' must be 'manifest' or 'sheet', "
                              f"got {src!r}")  # fmt: skip
    for i, e in enumerate(caps):
        if not isinstance(e, dict) or "file" not in e or "type" not in e:
            raise FileFormatError(f"{where}: captures[{i}] needs 'file' and 'type'")
        at = f"{where}: captures[{i}] ({e['file']!r})"
        for k, v in e.items():
            if k not in keys["entry"]:
                raise _unknown(k, keys["entry"], at)
            if not is_descriptive(keys["entry"][k]):
                _check_setting(k, v, at)
        if e["type"] not in ("scan", "white", "grid", "dark", "scene"):
            raise FileFormatError(f"{at}: 'type' must be one of scan, white, grid, dark, scene, "
                                  f"got {e['type']!r}")  # fmt: skip


def entry_settings(manifest: Mapping[str, Any], entry: Mapping[str, Any]) -> dict[str, Any]:
    """The settings of one capture: ``{key: (value, source)}`` for the keys of
    :data:`CAPTURE_SETTINGS` and ``exposure`` that the entry or the set gives (the entry's win);
    ``source`` is ``"sheet"`` or ``"manifest"`` (the manifest's ``settings_source``)."""
    src = str(manifest.get("settings_source", "manifest"))
    out: dict[str, Any] = {}
    for k in CAPTURE_SETTINGS:
        if entry.get(k) is not None:
            out[k] = (entry[k], src)
        elif manifest.get(k) is not None:
            out[k] = (manifest[k], src)
    if entry.get("exposure") is not None:
        out["exposure"] = (entry["exposure"], src)
    return out
