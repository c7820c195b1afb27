"""The calibration bundle: everything reconstruction needs, in one versioned NPZ file.

File format (schema version 2): an uncompressed ``.npz`` with the arrays below and ``meta``, a
0-d unicode array holding a JSON object ``{schema_version, software_version, settings,
provenance, reflection_sequences}``. Loading needs no pickle.

Version 2 adds entries to ``settings`` (the arrays are those of version 1, which still loads;
its bundles simply lack these, and reconstruction then assumes nothing about them):

=========================  ==================================================================
settings key               meaning
=========================  ==================================================================
black_level_rgb            ``[R, G, B]`` DN the calibration subtracted (black level + dark
                           frames' mean): what a capture without a black level of its own gets
black_level_source         how it was found (a sentence: files' metadata, setting, dark frames)
dark_level_rgb             the dark frames' mean above the black level, or null
files_black_level_source   ``file`` / ``config`` / ``default`` / ``manifest`` / ``sheet`` / mixed
white_exposure_unit        ``s`` (``exposure_s``) or ``relative`` (the simulator's ``exposure``)
white_exposure_source      where the white shots' exposure came from (``file``, ``manifest``, …)
white_level_dn             the white level the white shots were read with (DN, whatever its
                           source: the file, sheet, manifest, setting or the integer type's
                           maximum), or null: the scale of the data the bundle expects
white_level_source         ``file`` / ``sheet`` / ``manifest`` / ``config`` / ``default``
camera                     ``{make, model, cfa_pattern, sensor_size, black_level, white_level}``
                           (:class:`~hsi_torch.io.radiometry.CameraIdentity`; null = unknown)
pedestal                   ``{pedestal_dn, pedestal_limit_dn, ok, frames, outside_pixels}``: the
                           sensor outside every view after black subtraction, or null
=========================  ==================================================================

=========================  =================  ==================================================
key                        shape, dtype       meaning
=========================  =================  ==================================================
wavelengths_nm             (M,) float64       reconstruction grid (nm)
layout_triangles           (V, 3, 2) float64  view triangles, sensor px (x, y)
layout_parity              (V,) int64         ±1 (−1: odd number of reflections)
layout_view_homographies   (V, 3, 3) float64  view-v sensor px → reference sensor px, H_0 = I
layout_sensor_size         (2,) int64         (H, W) of the sensor the bundle was made for
layout_reference_bbox      (4,) int64         (x0, y0, w, h): reference frame = sensor crop
B                          (V, M, h, w) float BRF transmittance B_v(p, λ_m), reference frame
phi                        (3, M) float       φ^c(λ_m)
gain                       (V, h, w) float    g_v(p) (mean 1 over the reference view)
view_mask                  (V, h, w) bool     view present and BRF-modulated at p
modulated                  (V, h, w) bool     view BRF-modulated at p (False on the BRF-free patch)
valid                      (h, w) bool        ≥ 3 modulated views
extra_<name>               any                optional diagnostics
=========================  =================  ==================================================

Sensing matrix of reference-frame pixel ``p = i·w + j`` (row-major):
``A_p[3v + c, m] = gain[v, p] · B[v, m, p] · Δλ_m · phi[c, m]`` (view-major observations).
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import io
import json
import os
import zipfile
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from hsi_torch.devices import to_numpy
from hsi_torch.errors import FileFormatError, MissingFileError
from hsi_torch.forward_model import SensingModel
from hsi_torch.io.atomic import atomic_save_npz, json_default
from hsi_torch.io.bounded import npy_header
from hsi_torch.io.radiometry import CameraIdentity
from hsi_torch.io.safety import file_sha256, require_regular_file, short_repr
from hsi_torch.provenance import package_version, provenance
from hsi_torch.spectral import band_widths

__all__ = [
    "READABLE_SCHEMA_VERSIONS",
    "SCHEMA_VERSION",
    "CalibrationBundle",
    "ReferenceFrame",
    "file_sha256",
    "make_provenance",
]

SCHEMA_VERSION = 2
#: Schema versions this software loads (version 1: no radiometric settings, see the docstring).
READABLE_SCHEMA_VERSIONS = (1, 2)

_FLOAT_KEYS = ("wavelengths_nm", "triangles", "view_homographies", "B", "phi", "gain")
_INT_KEYS = ("parity", "sensor_size", "reference_bbox")
_BOOL_KEYS = ("view_mask", "modulated", "valid")
#: Members a bundle file may hold besides the required ones of ``_FILE_KEYS`` and ``meta``:
#: name -> a function of ``(V, M, h, w)`` giving the most elements the member may declare. To add
#: an optional array member, add it here (and write it in :meth:`CalibrationBundle.save`);
#: ``extra_<name>`` members (listed in meta ``extras``) are bounded by :data:`_MAX_EXTRA`.
OPTIONAL_MEMBERS: dict[str, Any] = {}
#: Largest ``meta`` JSON text (bytes) and number of members of a bundle file.
MAX_META_BYTES = 64 << 20
MAX_MEMBERS = 256


def _max_elements(key: str, V: int, M: int, h: int, w: int) -> int:
    """The most elements the required member ``key`` may declare for a bundle of ``V`` views,
    ``M`` bands and an ``h × w`` reference frame (the exact shapes are checked by
    :meth:`CalibrationBundle.validate` after reading)."""
    return {
        "wavelengths_nm": M, "layout_triangles": 6 * V, "layout_parity": V,
        "layout_view_homographies": 9 * V, "layout_sensor_size": 2, "layout_reference_bbox": 4,
        "B": V * M * h * w, "phi": 3 * M, "gain": V * h * w, "view_mask": V * h * w,
        "modulated": V * h * w, "valid": h * w,
    }[key]  # fmt: skip


def _max_extra(V: int, M: int, h: int, w: int) -> int:
    """The most elements an ``extra_<name>`` member (and all of them together) may declare."""
    return max(V * M * h * w, 1 << 20)


_FILE_KEYS = {
    "wavelengths_nm": "wavelengths_nm",
    "triangles": "layout_triangles",
    "parity": "layout_parity",
    "view_homographies": "layout_view_homographies",
    "sensor_size": "layout_sensor_size",
    "reference_bbox": "layout_reference_bbox",
    "B": "B",
    "phi": "phi",
    "gain": "gain",
    "view_mask": "view_mask",
    "modulated": "modulated",
    "valid": "valid",
}


def make_provenance(
    inputs: Mapping[str, str | os.PathLike] | Iterable[str | os.PathLike] = (), **extra: Any
) -> dict[str, Any]:
    """Provenance record: SHA-256 of each input file, UTC creation time, the run (``run``:
    command line, package version, git commit, torch / NumPy / Python versions, see
    :func:`hsi_torch.provenance.provenance`), plus ``extra`` items.

    Args:
        inputs: files (``{label: path}`` or a list of paths; a list is labelled by file name).
        **extra: further JSON-serialisable entries (e.g. ``simulator_seed=0``).
    """
    items = inputs.items() if isinstance(inputs, Mapping) else ((Path(p).name, p) for p in inputs)
    hashes = {str(k): file_sha256(p) for k, p in items}
    return {
        "inputs_sha256": hashes,
        "created_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "run": provenance(),
        **extra,
    }


def _is_num(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and bool(np.isfinite(v))


def _check_radiometry_settings(settings: Any, fail: Any) -> None:
    """The version-2 settings, where present: ``black_level_rgb`` / ``dark_level_rgb`` 3 finite
    numbers or null, ``camera`` / ``pedestal`` objects or null, the texts strings or null."""
    if not isinstance(settings, dict):
        return
    for key in ("black_level_rgb", "dark_level_rgb"):
        v = settings.get(key)
        if v is not None and not (isinstance(v, list) and len(v) == 3 and all(map(_is_num, v))):
            fail(f"settings.{key}", f"must be 3 finite numbers (R, G, B DN) or null, got {v!r}")
    v = settings.get("white_level_dn")
    if v is not None and not (_is_num(v) and v > 0):
        fail("settings.white_level_dn", f"must be a finite number > 0 (DN) or null, got {v!r}")
    for key in ("camera", "pedestal"):
        v = settings.get(key)
        if v is not None and not isinstance(v, dict):
            fail(f"settings.{key}", f"must be a JSON object or null, got {type(v).__name__}")
    for key in ("black_level_source", "white_exposure_unit", "white_exposure_source",
                "files_black_level_source", "white_level_source"):  # fmt: skip
        v = settings.get(key)
        if v is not None and not isinstance(v, str):
            fail(f"settings.{key}", f"must be a string or null, got {type(v).__name__}")


class ReferenceFrame:
    """``frame_size``, ``(h, w)`` of the reference frame, from the ``reference_bbox``
    ``(x0, y0, w, h)`` of a bundle or of what is built from it."""

    @property
    def frame_size(self) -> tuple[int, int]:
        return int(self.reference_bbox[3]), int(self.reference_bbox[2])  # type: ignore[attr-defined]
@dataclass
class CalibrationBundle(ReferenceFrame):
    """Calibration products in reference-frame coordinates (see the module docstring for shapes).

    Array fields accept numpy arrays or tensors and are stored as numpy arrays. Construction
    validates shapes and dtypes (``ValueError`` naming the field).

    Example:
        >>> bundle = CalibrationBundle.load("calib.npz")  # doctest: +SKIP
        >>> bundle.check_compatible(capture.shape)  # doctest: +SKIP
        >>> A = bundle.sensing_model(device="cuda").dense()  # (h*w, 3V, M)  # doctest: +SKIP
    """

    wavelengths_nm: np.ndarray
    triangles: np.ndarray
    parity: np.ndarray
    view_homographies: np.ndarray
    sensor_size: np.ndarray  # (H, W), any int sequence accepted
    reference_bbox: np.ndarray  # (x0, y0, w, h), any int sequence accepted
    B: np.ndarray
    phi: np.ndarray
    gain: np.ndarray
    view_mask: np.ndarray
    modulated: np.ndarray
    valid: np.ndarray
    reflection_sequences: list[tuple[int, ...]] = field(default_factory=list)
    settings: dict[str, Any] = field(default_factory=dict)
    provenance: dict[str, Any] = field(default_factory=dict)
    software_version: str = field(default_factory=package_version)
    schema_version: int = SCHEMA_VERSION
    extras: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for k in (*_FLOAT_KEYS, *_INT_KEYS, *_BOOL_KEYS):
            setattr(self, k, to_numpy(getattr(self, k)))
        self.extras = {str(k): to_numpy(v) for k, v in self.extras.items()}
        self.reflection_sequences = [tuple(int(i) for i in s) for s in self.reflection_sequences]
        self.validate()

    # ---------------------------------------------------------------- shapes
    @property
    def num_views(self) -> int:
        return int(self.triangles.shape[0])

    @property
    def num_bands(self) -> int:
        return int(self.wavelengths_nm.shape[0])

    def validate(self, source: str = "<in memory>") -> None:
        """Check dtypes and the consistency of all shapes; raise naming the key and ``source``."""

        def fail(key: str, msg: str) -> None:
            raise FileFormatError(f"calibration bundle {source}: '{key}' {msg}")

        for k in _FLOAT_KEYS:
            a = getattr(self, k)
            if a.dtype.kind != "f":
                fail(k, f"must be floating point, got dtype {a.dtype}")
            if not np.all(np.isfinite(a)):
                fail(k, "contains NaN or inf")
        for k in _INT_KEYS:
            a = getattr(self, k)
            if a.dtype.kind not in "iu":
                fail(k, f"must be integer, got dtype {a.dtype}")
        for k in _BOOL_KEYS:
            a = getattr(self, k)
            if a.dtype != np.bool_:
                fail(k, f"must be bool, got dtype {a.dtype}")
        if self.wavelengths_nm.ndim != 1 or self.wavelengths_nm.size < 1:
            fail("wavelengths_nm", f"must be (M,), got {self.wavelengths_nm.shape}")
        if np.any(np.diff(self.wavelengths_nm) <= 0):
            fail("wavelengths_nm", "must be strictly increasing")
        M = self.num_bands
        if self.triangles.ndim != 3 or self.triangles.shape[1:] != (3, 2):
            fail("triangles", f"must be (V, 3, 2), got {self.triangles.shape}")
        V = self.num_views
        if self.parity.shape != (V,) or not np.all(np.isin(self.parity, (-1, 1))):
            fail("parity", f"must be (V,) = ({V},) of ±1, got {self.parity.tolist()}")
        if self.view_homographies.shape != (V, 3, 3):
            fail("view_homographies", f"must be ({V}, 3, 3), got {self.view_homographies.shape}")
        if self.sensor_size.shape != (2,) or np.any(self.sensor_size <= 0):
            fail("sensor_size", f"must be (H, W) > 0, got {self.sensor_size.tolist()}")
        if self.reference_bbox.shape != (4,) or np.any(self.reference_bbox[2:] <= 0):
            fail("reference_bbox", f"must be (x0, y0, w, h), got {self.reference_bbox.tolist()}")
        x0, y0, bw, bh = (int(v) for v in self.reference_bbox)
        H, W = (int(v) for v in self.sensor_size)
        if x0 < 0 or y0 < 0 or x0 + bw > W or y0 + bh > H:
            fail("reference_bbox", f"{[x0, y0, bw, bh]} (x0, y0, w, h) is not inside the "
                                   f"{H}x{W} sensor")  # fmt: skip
        if V < 1:
            fail("triangles", "holds no view (V = 0)")
        with np.errstate(all="ignore"):
            det = np.linalg.det(self.view_homographies.astype(np.float64))
        if not np.all(np.isfinite(det)) or np.any(np.abs(det) < 1e-12):
            fail("view_homographies", "must be invertible (a view's homography is singular)")
        h, w = self.frame_size
        expect = {"B": (V, M, h, w), "phi": (3, M), "gain": (V, h, w), "view_mask": (V, h, w),
                  "modulated": (V, h, w), "valid": (h, w)}  # fmt: skip
        for k, shp in expect.items():
            if getattr(self, k).shape != shp:
                fail(k, f"has shape {getattr(self, k).shape}, expected {shp} (V={V}, M={M}, "
                        f"reference frame {h}x{w})")  # fmt: skip
        if self.reflection_sequences and len(self.reflection_sequences) != V:
            fail("reflection_sequences", f"has {len(self.reflection_sequences)} entries, not {V}")
        if int(self.schema_version) not in READABLE_SCHEMA_VERSIONS:
            fail("schema_version", f"is {self.schema_version}; this software reads "
                                   f"{list(READABLE_SCHEMA_VERSIONS)}")  # fmt: skip
        _check_radiometry_settings(self.settings, fail)

    # ---------------------------------------------------------------- I/O
    def meta(self) -> dict[str, Any]:
        """The JSON metadata object stored under ``meta``."""
        return {
            "schema_version": int(self.schema_version),
            "software_version": self.software_version,
            "settings": self.settings,
            "provenance": self.provenance,
            "reflection_sequences": [list(s) for s in self.reflection_sequences],
            "extras": sorted(self.extras),
        }

    def save(self, path: str | os.PathLike) -> Path:
        """Write the bundle atomically (temporary file + ``os.replace``); returns the path."""
        self.validate()
        meta = json.dumps(self.meta(), default=json_default)  # fails before touching the file
        arrays: dict[str, Any] = {fk: getattr(self, k) for k, fk in _FILE_KEYS.items()}
        arrays["meta"] = np.array(meta)
        for k, v in self.extras.items():
            arrays[f"extra_{k}"] = v
        return atomic_save_npz(path, arrays)

    @classmethod
    def load_hashed(cls, path: str | os.PathLike) -> tuple[CalibrationBundle, str]:
        """Read the file once: the bundle (:meth:`load`) and its SHA-256
        (:func:`~hsi_torch.io.safety.file_sha256`), both from the same bytes. The members are
        checked from the zip directory first, and a file larger than its members is refused
        before it is read whole."""
        p = Path(path)
        bound = cls._checked_path(p)
        size = p.stat().st_size
        if size > bound:
            raise FileFormatError(
                f"calibration bundle {p}: {size} bytes, more than its members hold ({bound}); "
                "refusing to read it")
        raw = p.read_bytes()
        return cls.load(p, raw=raw), file_sha256(raw)

    @staticmethod
    def _checked_path(p: Path, raw: bytes | None = None) -> int:
        """The checks before a bundle is decompressed (a folder, a missing or irregular file, not
        a zip archive, :func:`_check_members`); ``raw``: the file's bytes, already read. Returns
        the bytes its zip directory accounts for."""
        if raw is None:
            if p.is_dir():
                raise FileFormatError(
                    f"calibration bundle {p} is a folder, not a bundle file (give the .npz "
                    "written by 'hsi-torch calibrate')")
            if not p.exists():
                raise MissingFileError(f"calibration bundle {p} does not exist")
            require_regular_file(p, "calibration bundle")  # a FIFO would block the reader
        if not zipfile.is_zipfile(p if raw is None else io.BytesIO(raw)):  # np.load would guess
            raise FileFormatError(  # .npy/pickle: say it here
                f"calibration bundle {p}: not a readable NPZ file (not a zip archive: corrupt, "
                "truncated or another format)")
        try:
            return _check_members(p, raw)  # known members, sizes bounded: before decompressing
        except FileFormatError:
            raise
        except Exception as exc:  # zipfile/format errors
            raise FileFormatError(
                f"calibration bundle {p}: not a readable NPZ file ({exc})"
            ) from exc

    @classmethod
    def load(cls, path: str | os.PathLike, *, raw: bytes | None = None) -> CalibrationBundle:
        """Read and validate a bundle; errors name the file and the offending key. ``raw``: the
        file's bytes, already read (:meth:`load_hashed`)."""
        p = Path(path)
        cls._checked_path(p, raw)  # 'meta' and every array member present
        try:
            with np.load(p if raw is None else io.BytesIO(raw), allow_pickle=False) as z:
                data = {k: z[k] for k in z.files}
        except Exception as exc:  # zipfile/format errors
            raise FileFormatError(
                f"calibration bundle {p}: not a readable NPZ file ({exc})"
            ) from exc
        for k, v in data.items():  # np.load gives the raw bytes of a member that is no array
            if not isinstance(v, np.ndarray):
                raise FileFormatError(f"calibration bundle {p}: member '{k}' is not an array")
        raw_meta = data["meta"]
        if raw_meta.ndim != 0 or raw_meta.dtype.kind != "U":
            raise FileFormatError(
                f"calibration bundle {p}: 'meta' must be a JSON string (0-d str array), got a "
                f"{raw_meta.dtype} array of shape {raw_meta.shape}")
        try:
            meta = json.loads(str(raw_meta))
        except (json.JSONDecodeError, RecursionError) as exc:
            raise FileFormatError(
                f"calibration bundle {p}: 'meta' is not valid JSON ({exc})"
            ) from exc
        if not isinstance(meta, dict):
            raise FileFormatError(
                f"calibration bundle {p}: 'meta' must be a JSON object, got {type(meta).__name__}")
        ver = meta.get("schema_version")
        if type(ver) is not int or ver not in READABLE_SCHEMA_VERSIONS:
            raise FileFormatError(
                f"calibration bundle {p}: schema_version {ver!r} is not supported "
                f"(this software reads versions {', '.join(map(str, READABLE_SCHEMA_VERSIONS))})")
        kw = {k: data[fk] for k, fk in _FILE_KEYS.items()}
        extras = {k[len("extra_") :]: v for k, v in data.items() if k.startswith("extra_")}
        bundle = cls.__new__(cls)  # bypass __post_init__ so errors can name the file
        for k, v in kw.items():
            setattr(bundle, k, v)
        seqs = meta.get("reflection_sequences", [])
        ok = isinstance(seqs, list) and all(
            isinstance(q, list) and all(type(i) is int for i in q) for q in seqs)
        if not ok:
            raise FileFormatError(
                f"calibration bundle {p}: meta 'reflection_sequences' must be a list of lists of "
                "mirror indices (integers)")
        bundle.reflection_sequences = [tuple(q) for q in seqs]
        for key in ("settings", "provenance"):
            if not isinstance(meta.get(key, {}), dict):
                raise FileFormatError(
                    f"calibration bundle {p}: meta '{key}' must be a JSON object, got "
                    f"{type(meta[key]).__name__}")
        bundle.settings = meta.get("settings", {})
        bundle.provenance = meta.get("provenance", {})
        bundle.software_version = str(meta.get("software_version", "unknown"))
        bundle.schema_version = int(ver)
        bundle.extras = extras
        bundle.validate(source=str(p))
        return bundle

    # ---------------------------------------------------------------- use
    @property
    def black_level_rgb(self) -> list[float] | None:
        """``[R, G, B]`` DN the calibration subtracted (``settings["black_level_rgb"]``), or
        ``None`` (a version-1 bundle)."""
        v = self.settings.get("black_level_rgb") if isinstance(self.settings, dict) else None
        return [float(x) for x in v] if isinstance(v, list) else None

    @property
    def camera(self) -> CameraIdentity | None:
        """The camera the bundle was calibrated with (``settings["camera"]``), or ``None``."""
        s = self.settings if isinstance(self.settings, dict) else {}
        return CameraIdentity.from_dict(s.get("camera"))

    def check_compatible(self, image_shape: Sequence[int] | torch.Size) -> None:
        """Refuse a capture whose sensor size differs from the bundle's.

        Args:
            image_shape: ``(H, W)``, ``(C, H, W)`` or ``(B, C, H, W)``.

        Raises:
            ValueError: naming both sizes.
        """
        shp = tuple(int(s) for s in image_shape)
        if len(shp) < 2:
            raise ValueError(f"image_shape must end with (H, W), got {shp}")
        H, W = int(self.sensor_size[0]), int(self.sensor_size[1])
        if shp[-2:] != (H, W):
            raise ValueError(
                f"capture sensor size {shp[-2]}x{shp[-1]} (HxW) does not match the calibration "
                f"bundle's {H}x{W}: the bundle was made for another camera/geometry or crop")
        if len(shp) >= 3 and shp[-3] != 3:
            raise ValueError(f"capture must have 3 colour channels, got shape {shp}")

    def sensing_model(
        self,
        pixel_index: torch.Tensor | None = None,
        *,
        device: torch.device | str | None = None,
        dtype: torch.dtype = torch.float32,
    ) -> SensingModel:
        """The forward model of reference-frame pixels ``pixel_index`` (flat row-major, long;
        default every pixel, ``P = h·w``): a :class:`~hsi_torch.forward_model.SensingModel` with
        ``A_p[3v + c, m] = gain[v, p] · B[v, m, p] · Δλ_m · phi[c, m]`` (``Δλ`` from the
        wavelengths; ``Δλ·φ`` formed in float64, then cast). Dense ``(P, 3V, M)`` matrices:
        ``.dense()``.
        """
        wl = torch.as_tensor(self.wavelengths_nm, dtype=torch.float64)
        idx = None if pixel_index is None else torch.as_tensor(pixel_index).cpu()
        return SensingModel.from_factors(
            torch.as_tensor(self.B), torch.as_tensor(self.gain), torch.as_tensor(self.phi),
            band_widths(wl), pixel_index=idx, device=device, dtype=dtype)  # fmt: skip

    def observation_mask(
        self, device: torch.device | str | None = None, pixel_index: torch.Tensor | None = None
    ) -> torch.Tensor:
        """``(P, 3V)`` bool: observation ``3v + c`` of pixel p is usable (``view_mask[v, p]``)."""
        vm = torch.as_tensor(self.view_mask, device=device).reshape(self.num_views, -1)
        if pixel_index is not None:
            vm = vm[:, torch.as_tensor(pixel_index, device=vm.device, dtype=torch.long)]
        return vm.T.repeat_interleave(3, dim=1)

    def summary(self) -> str:
        """A few readable lines (sizes, valid-region size, provenance)."""
        h, w = self.frame_size
        nv = int(self.valid.sum())
        return (
            f"calibration bundle v{self.schema_version} (hsi_torch {self.software_version}): "
            f"{self.num_views} views, {self.num_bands} bands "
            f"{self.wavelengths_nm[0]:g}-{self.wavelengths_nm[-1]:g} nm, sensor "
            f"{int(self.sensor_size[0])}x{int(self.sensor_size[1])}, reference frame {h}x{w} at "
            f"({int(self.reference_bbox[0])}, {int(self.reference_bbox[1])}), valid {nv} px "
            f"({100 * nv / (h * w):.1f} %)"
        )


def _npy_header(zf: zipfile.ZipFile, info: zipfile.ZipInfo) -> tuple[tuple[int, ...], np.dtype]:
    """Shape and dtype from a member's ``.npy`` header (a few hundred bytes decompressed)."""
    with zf.open(info) as f:
        return npy_header(f)


def _check_members(p: Path, raw: bytes | None = None) -> int:
    """Refuse a bundle file with a member this software does not know, or one whose size (from
    the zip directory and its ``.npy`` header) exceeds what the bundle's own layout implies —
    before any member but the small ``meta`` and ``layout_reference_bbox`` is decompressed.

    Known members: the arrays of ``_FILE_KEYS``, ``meta``, :data:`OPTIONAL_MEMBERS` and the
    ``extra_<name>`` arrays that ``meta`` lists under ``extras``. Bounds: ``V``, ``M`` from the
    headers of ``layout_triangles`` and ``wavelengths_nm``, ``h × w`` from the reference box
    (inside the sensor), then :func:`_max_elements` per member (``B``: ``V·M·h·w``). Returns the
    bytes the zip directory accounts for (members, their names and headers)."""
    where = f"calibration bundle {p}"
    with zipfile.ZipFile(p if raw is None else io.BytesIO(raw)) as zf:
        infos = zf.infolist()
        if len(infos) > MAX_MEMBERS:
            raise FileFormatError(f"{where}: {len(infos)} members, more than a bundle has")
        by_name: dict[str, zipfile.ZipInfo] = {}
        for info in infos:
            name = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
            if name in by_name:
                raise FileFormatError(f"{where}: member {short_repr(name)} appears twice")
            by_name[name] = info
        known = {*_FILE_KEYS.values(), "meta", *OPTIONAL_MEMBERS}
        extras_named: list[Any] | None = None
        meta_info = by_name.get("meta")
        if meta_info is None:
            raise FileFormatError(f"{where}: missing key 'meta' (not a bundle written by "
                                  "'hsi-torch calibrate')")  # fmt: skip
        if not meta_info.filename.endswith(".npy"):
            raise FileFormatError(f"{where}: member 'meta' is not an array")
        missing = [fk for fk in _FILE_KEYS.values() if fk not in by_name]
        if missing:
            raise FileFormatError(f"{where}: missing key(s) {missing}")
        if meta_info.file_size > MAX_META_BYTES:
            raise FileFormatError(
                f"{where}: member 'meta' is {meta_info.file_size} bytes, more than "
                f"{MAX_META_BYTES >> 20} MiB of metadata; refusing to decompress it")
        shape, dtype = _npy_header(zf, meta_info)
        if shape == () and dtype.kind == "U":
            with zf.open(meta_info) as f:
                raw = np.lib.format.read_array(f, allow_pickle=False)
            meta: Any = None
            with contextlib.suppress(ValueError, RecursionError):
                meta = json.loads(str(raw))
            if isinstance(meta, dict):
                ver = meta.get("schema_version")
                if type(ver) is not int or ver not in READABLE_SCHEMA_VERSIONS:  # (a newer
                    raise FileFormatError(  # layout's members)
                        f"{where}: schema_version {short_repr(ver)} is not supported (this "
                        f"software reads versions "
                        f"{', '.join(map(str, READABLE_SCHEMA_VERSIONS))})")
                if isinstance(meta.get("extras"), list):
                    extras_named = meta["extras"]
        for name, info in by_name.items():
            if name in known:
                continue
            ok = (
                name.startswith("extra_")
                and info.filename.endswith(".npy")
                and (extras_named is None or name[len("extra_") :] in extras_named)
            )
            if not ok:
                raise FileFormatError(
                    f"{where}: unknown member {short_repr(info.filename)} (a bundle holds "
                    f"meta, {', '.join(_FILE_KEYS.values())} and the extra_<name> arrays its "
                    "meta lists); refusing the file")
        headers = {}
        for name, info in by_name.items():
            if name == "meta":
                continue
            if not info.filename.endswith(".npy"):
                raise FileFormatError(f"{where}: member '{name}' is not an array")
            headers[name] = _npy_header(zf, info)

        def dim(key: str, axis: int, cap: int) -> int:
            shape = headers.get(key, ((),))[0]
            n = int(shape[axis]) if len(shape) > axis else 1
            if not 0 <= n <= cap:
                raise FileFormatError(f"{where}: '{key}' declares shape {shape}: {n} is out of "
                                      f"range (at most {cap})")  # fmt: skip
            return n

        V = dim("layout_triangles", 0, 4096)
        M = dim("wavelengths_nm", 0, 100_000)
        h = w = 1
        bbox_info = by_name.get("layout_reference_bbox")
        if bbox_info is not None and headers["layout_reference_bbox"][0] == (4,):
            with zf.open(bbox_info) as f:
                bbox = np.lib.format.read_array(f, allow_pickle=False)
            if bbox.dtype.kind in "iu":
                h, w = (int(v) for v in bbox[[3, 2]])
        size_shape = headers.get("layout_sensor_size", ((),))[0]
        size_info = by_name.get("layout_sensor_size")
        if size_info is not None and size_shape == (2,):
            with zf.open(size_info) as f:
                sensor = np.lib.format.read_array(f, allow_pickle=False)
            if sensor.dtype.kind in "iu":
                H, W = (int(v) for v in sensor)
                h, w = min(max(h, 1), max(H, 1)), min(max(w, 1), max(W, 1))
        h, w = min(max(h, 1), 1 << 16), min(max(w, 1), 1 << 16)
        extra_total = 0
        for name, (shape, dtype) in headers.items():
            n = int(np.prod(shape, dtype=np.float64)) if shape else 1
            counted = n
            if name in _FILE_KEYS.values():
                cap = _max_elements(name, V, M, h, w)
            elif name in OPTIONAL_MEMBERS:
                cap = int(OPTIONAL_MEMBERS[name](V, M, h, w))
            else:  # the extras together
                cap = _max_extra(V, M, h, w)
                extra_total += n
                counted = extra_total
            if counted > cap or dtype.itemsize > 16:
                raise FileFormatError(
                    f"{where}: member '{name}' declares shape {short_repr(shape)} ({dtype}), "
                    f"more than the bundle's layout allows (V={V} views, M={M} bands, reference "
                    f"frame {h}x{w}: at most {cap} elements); refusing to decompress it")
            declared = by_name[name].file_size
            if declared > n * dtype.itemsize + 65536:
                raise FileFormatError(
                    f"{where}: member '{name}' holds {declared} bytes, far more than its header's "
                    f"{short_repr(shape)} {dtype}; refusing to decompress it")
    return sum(i.compress_size + 2 * len(i.filename) + 256 for i in infos) + 65536
