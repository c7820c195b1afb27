"""How calibration reads its captures: :class:`CaptureReader` (every file through
:func:`hsi_torch.io.read_any` with the manifest's per-file and set-level settings, the config's
overrides winning, the layout's sensor size, the dark frames' mean subtracted; what the files say
about the camera and the black level, and the level of the sensor outside the views after black
subtraction, recorded for :func:`check_pedestal`) and which scan frames it uses
(:func:`group_scan_frames`: every band of the grid its frames — repeated frames averaged —, the
frames near no band listed). The stages that use them are in
:mod:`hsi_torch.calibrate.pipeline`.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from hsi_torch.calibrate.config import CalibrateConfig
from hsi_torch.calibrate.transmittance import match_wavelengths
from hsi_torch.errors import CalibrationError
from hsi_torch.io import read_any, read_capture
from hsi_torch.io.capture_set import CaptureSet, wavelength_from_name
from hsi_torch.io.radiometry import (
    CameraIdentity,
    black_level_rgb,
    pedestal_level,
    pedestal_limit,
)
from hsi_torch.io.sensor_corrections import subtract_veil

__all__ = ["CaptureReader", "check_pedestal", "ScanSelection", "scan_wavelengths",
           "group_scan_frames"]


class CaptureReader:
    """read_any with the per-file settings of the capture set's manifest (``settings``:
    :attr:`CaptureSet.settings`), the config's overrides (which win), the layout's sensor size
    and dark subtraction; it also records what the captures say about the camera and the black
    level, and the pedestal of every frame read after the dark subtraction (:meth:`pedestal`)."""

    def __init__(self, cfg: CalibrateConfig, sensor_size: tuple[int, int], device, dtype,
                 *, settings: dict[Path, dict[str, Any]] | None = None,
                 outside_index: np.ndarray | None = None,
                 roles: dict[Path, str] | None = None):  # fmt: skip
        self.cfg, self.size, self.device, self.dtype = cfg, sensor_size, device, dtype
        self.settings = settings or {}
        #: the role of each capture (``scan``, ``white``, ``grid``, ``dark``): the pedestal is
        #: checked per role as well as per black level (:meth:`pedestal`)
        self.roles = roles or {}
        self.dark: torch.Tensor | None = None
        self.dark_files: list[Path] = []
        #: (file, black level (R, G, B), its source) of each dark frame read
        self.dark_black: list[tuple[str, tuple[float, ...], str]] = []
        #: warnings about repeated scan frames that differ (:meth:`read_mean`), for the report
        self.scan_notes: list[str] = []
        #: a warning about the dark frames (different exposures averaged), for the report
        self.dark_note: str | None = None
        self.cfa_pattern: str | None = None
        #: (file, pattern, source) of the first Bayer frame read: every other must match it
        self._cfa_first: tuple[Path, str, str] | None = None
        self.outside = outside_index
        self.camera: CameraIdentity | None = None
        self.cameras: set[str] = set()
        #: the black level the files were read with (R, G, B) and its source, first capture
        self.black_rgb: list[float] | None = None
        self.black_source: str | None = None
        self.black_sources: set[str] = set()
        #: (file, median (3,), robust sigma (3,), white span) per frame read after the dark
        self.pedestals: list[tuple[Path, list[float], list[float], float | None]] = []
        #: per frame of :attr:`pedestals`: the black level it was read with (R, G, B) and its
        #: source; the frames of one role sharing one are checked together (:meth:`pedestal`)
        self.pedestal_black: dict[Path, tuple[tuple[float, ...], str]] = {}
        self._recording = True
        #: the dark frames' per-pixel mean (whatever ``dark`` mode subtracts), for the defects
        self.dark_pixels: torch.Tensor | None = None
        #: flat indices of unreached sensor pixels: when set, the veil of stray light measured
        #: there is subtracted from every frame read (:func:`~hsi_torch.io.sensor_corrections.
        #: subtract_veil`), and its mean per colour recorded in :attr:`veils`
        self.veil_index: np.ndarray | None = None
        self.veils: list[tuple[str, list[float]]] = []

    def overrides(self, path: Path) -> tuple[dict[str, Any], dict[str, str]]:
        """read_any's keyword overrides for ``path`` and their sources: the manifest's settings
        for the file, then the config's ``cfa_pattern``/``black_level``/``white_level``."""
        given = {k: v for k, v in self.settings.get(path, {}).items() if k != "exposure"}
        for key in ("cfa_pattern", "black_level", "white_level"):
            if getattr(self.cfg, key) is not None:
                given[key] = (getattr(self.cfg, key), "config")
        return {k: v for k, (v, _) in given.items()}, {k: s for k, (_, s) in given.items()}

    def read(self, path: Path) -> tuple[torch.Tensor, torch.Tensor, dict[str, Any]]:
        kw, sources = self.overrides(path)
        cap = read_any(
            path, expected_size=self.size, demosaic=self.cfg.demosaic, dtype=self.dtype,
            device=self.device, sources=sources, **kw,
        )  # fmt: skip
        rel = self.settings.get(path, {}).get("exposure")
        if rel is not None:  # the manifest's relative exposure of the file wins over the file's
            cap.metadata["exposure"] = rel[0]
        meta = cap.metadata
        if meta.get("kind") == "bayer":
            self._check_cfa(path, meta.get("cfa_pattern"), sources.get("cfa_pattern"))
            self.cfa_pattern = meta.get("cfa_pattern")
        src = str(meta["black_level_source"])  # read_any's black_level_rule (no bundle yet)
        self._note_identity(meta, src)
        img = cap.image if self.dark is None else cap.image - self.dark
        if self.veil_index is not None:
            img, vinfo = subtract_veil(img, self.veil_index)
            self.veils.append((path.name, [round(v, 3) for v in vinfo["mean_dn"]]))
        if (self._recording and self.outside is not None and self.outside.size
                and path not in self.pedestal_black):  # a frame read again: the same level
            st = pedestal_level(img, self.outside)
            if st is not None:
                black = black_level_rgb(meta.get("black_level"), meta.get("cfa_pattern")) or [0.0]
                wl = meta.get("white_level")
                span = float(wl) - float(np.mean(black)) if isinstance(wl, (int, float)) else None
                self.pedestals.append((path, st[0], st[1], span))
                self.pedestal_black[path] = (tuple(round(float(b), 3) for b in black), src)
        return img, cap.saturated, meta

    def _check_cfa(self, path: Path, pattern: Any, source: str | None) -> None:
        """Refuse a Bayer frame whose CFA pattern differs from the first Bayer frame's: one
        sensor has one pattern, and a frame demosaiced with another has its colours (and its
        image, by a pixel) swapped."""
        if not isinstance(pattern, str):
            return
        first = self._cfa_first
        if first is None:
            self._cfa_first = (path, pattern, source or "file")
            return
        if pattern.upper() != first[1].upper():
            raise CalibrationError(
                f"{path}: CFA pattern {pattern} ({source or 'file'}) but {first[0]} has "
                f"{first[1]} ({first[2]}): the calibration captures mix Bayer patterns (frames of "
                "another camera, a crop by one pixel, or a wrong cfa_pattern in the sheet or "
                "manifest); give every file of this sensor its right cfa_pattern (one sheet "
                "column or --set cfa_pattern=...) or leave out the other camera's files"
            )

    def _note_identity(self, meta: dict[str, Any], src: str) -> None:
        cam = CameraIdentity.from_metadata(meta, self.size, levels_from_file=src == "file")
        self.camera = cam if self.camera is None else self.camera.merged(cam)
        if cam.name and " ".join(cam.name.lower().split()) not in {
                " ".join(c.lower().split()) for c in self.cameras}:  # fmt: skip
            self.cameras.add(cam.name)
        self.black_sources.add(src)
        if self.black_rgb is None:
            self.black_rgb = black_level_rgb(meta.get("black_level"), meta.get("cfa_pattern"))
            self.black_source = src

    def read_mean(
        self, paths: Path | Sequence[Path]
    ) -> tuple[torch.Tensor, torch.Tensor, dict[str, Any]]:
        """:meth:`read` of one file, or the mean of several (repeated frames of one scan
        wavelength): a sample is saturated when it is in any of them; frames of other exposures
        (``exposure_s``, when every frame has one) are scaled to the first frame's first."""
        if isinstance(paths, Path):
            return self.read(paths)
        img, sat, meta = self.read(paths[0])
        t0 = meta.get("exposure_s")
        first = img
        for p in paths[1:]:
            i2, s2, m2 = self.read(p)
            t = m2.get("exposure_s")
            if t0 is not None and t is not None and float(t) != float(t0):
                i2 = i2 * (float(t0) / float(t))
            d = _pattern_difference(first, i2, sat | s2)
            if d is not None and d > REPEAT_MAX_DIFFERENCE:
                msg = (f"scan: {p.name} differs from {paths[0].name}, the frame of the same "
                       f"wavelength it is averaged with, by {100 * d:.0f} % RMS (8x8 px block "
                       f"means, each frame normalised to its mean; limit "
                       f"{100 * REPEAT_MAX_DIFFERENCE:g} %; frames of one wavelength differ by "
                       "their noise only): is its wavelength right?")  # fmt: skip
                warnings.warn(msg, UserWarning, stacklevel=3)
                self.scan_notes.append(msg)
            img = img + i2
            sat = sat | s2
        return img / len(paths), sat, meta

    def set_dark(self, files: Sequence[Path], mode: str) -> None:
        if mode == "none" or not files:
            return
        acc = None
        self._recording = False  # the dark frames themselves read the pedestal, by definition
        exposures = []
        try:
            for p in files:
                img, _, meta = self.read(p)
                acc = img if acc is None else acc + img
                exposures.append((p.name, meta.get("exposure_s")))
                black = black_level_rgb(meta.get("black_level"), meta.get("cfa_pattern"))
                self.dark_black.append((p.name, tuple(round(float(b), 3) for b in black or [0.0]),
                                        str(meta.get("black_level_source"))))  # fmt: skip
        finally:
            self._recording = True
        known = {float(t) for _, t in exposures if isinstance(t, (int, float))}
        if len(known) > 1:
            listed = ", ".join(f"{n} ({t:g} s)" if isinstance(t, (int, float)) else f"{n} (?)"
                               for n, t in exposures)  # fmt: skip
            self.dark_note = (
                f"dark frames of different exposures averaged ({listed}): one dark level is "
                "subtracted from every frame (scan, white and grid alike), though the dark "
                "current grows with the exposure; calibrate with the dark frames of one "
                "exposure (the scan's or the white's), or check the black level it gives"
            )
            warnings.warn(self.dark_note, UserWarning, stacklevel=3)
        d = acc / len(files)
        self.dark_pixels = d
        self.dark = d.mean(dim=(-2, -1), keepdim=True).expand_as(d) if mode == "mean" else d
        self.dark_files = list(files)

    def black_level_record(self) -> dict[str, Any]:
        """What a capture without a black level of its own must have subtracted to match the
        calibration: ``black_level_rgb`` (the files' black level plus the dark frames' mean, per
        colour, DN), ``black_level_source`` (a sentence), ``dark_level_rgb`` (the dark frames'
        mean above the black level, or ``None``) and ``files_black_level_source``."""
        base = self.black_rgb if self.black_rgb is not None else [0.0, 0.0, 0.0]
        src = self.black_source or "default"
        if len(self.black_sources) > 1:
            src = "mixed (" + ", ".join(sorted(self.black_sources)) + ")"
        what = {"file": "the files' metadata", "config": "the black_level setting",
                "default": "none given: 0", "bundle": "the bundle"}.get(src, src)  # fmt: skip
        dark = None
        total = list(base)
        text = f"black level {_levels_text(base)} DN ({what})"
        if self.dark is not None:
            dark = [float(v) for v in self.dark.mean(dim=(-2, -1)).double().cpu()]
            total = [a + b for a, b in zip(base, dark, strict=True)]
            names = ", ".join(p.name for p in self.dark_files)
            text += (f" + dark frame mean {_levels_text(dark)} DN ({names}; "
                     f"dark: {self.cfg.dark})")  # fmt: skip
        return {"black_level_rgb": total, "black_level_source": text,
                "dark_level_rgb": dark, "files_black_level_source": src}  # fmt: skip

    def pedestal(self) -> dict[str, Any] | None:
        """The pedestal of the captures: per colour, the frame level closest to 0 over the frames
        read with one black level from one source (stray light only adds to it; a black level
        missed or wrong for a file is in every frame read with it), its limit
        (:func:`~hsi_torch.io.radiometry.pedestal_limit`), and ``ok``. With frames read with
        different black levels (a lab's TIFFs without one beside DNGs with theirs), each such
        group is checked on its own and the worst one is returned, ``group`` naming its black
        level, source, role (when its frames share one) and files.

        When every such group passes, the frames of each role (:attr:`roles`: scan, white,
        grid) within it are checked on their own as well — a pedestal in one role's frames only
        (DNG scan frames whose BlackLevel tag misses it, beside white shots whose tag is right)
        is otherwise hidden by the other roles' frames that read 0 — and the worst failing one is
        returned, ``group`` naming its role (``group["by"] == "role"``). ``by_group`` lists
        every role and black level's frame count, level and limit (when there is more than
        one). ``None`` when no frame had sensor pixels outside the views."""
        if not self.pedestals:
            return None
        by_black: dict[Any, list] = {}
        by_role: dict[Any, list] = {}
        for r in self.pedestals:
            black = self.pedestal_black.get(r[0])
            by_black.setdefault(black, []).append(r)
            by_role.setdefault((black, self.roles.get(r[0])), []).append(r)
        role_groups = _measure_groups(by_role)  # measured once: the check and the report
        worst = max(_measure_groups(by_black), key=lambda m: m[0])
        by = "black level"
        if worst[0] <= 1.0 and len(by_role) > len(by_black):  # every black level passes
            role_worst = max(role_groups, key=lambda m: m[0])  # the first of equals
            if role_worst[0] > 1.0:
                worst, by = role_worst, "role"
        _, key, frames, level, limit = worst
        ok = all(abs(v) <= lim for v, lim in zip(level, limit, strict=True))
        n_out = 0 if self.outside is None else int(self.outside.size)
        out = {"pedestal_dn": level, "pedestal_limit_dn": limit, "ok": ok,
               "frames": len(frames), "outside_pixels": n_out}  # fmt: skip
        black = key[0] if by == "role" else key
        roles = {self.roles.get(r[0]) for r in frames}
        if (by == "role" or len(by_black) > 1) and black is not None:
            out["group"] = {"black_level_rgb": list(black[0]), "black_level_source": black[1],
                            "role": roles.pop() if len(roles) == 1 else None, "by": by,
                            "files": [str(r[0].name) for r in frames],
                            "groups": len(by_black)}  # fmt: skip
        if len(by_role) > 1:
            out["by_group"] = [
                {"role": k[1], "black_level_rgb": None if k[0] is None else list(k[0][0]),
                 "black_level_source": None if k[0] is None else k[0][1], "frames": len(fr),
                 "pedestal_dn": [round(v, 3) for v in lv],
                 "pedestal_limit_dn": [round(v, 3) for v in lim]}
                for _, k, fr, lv, lim in role_groups
            ]  # fmt: skip
        return out


def _measure_groups(groups: dict[Any, list]) -> list[tuple[float, Any, list, list, list]]:
    """Per group of :attr:`CaptureReader.pedestals` records: ``(badness, key, frames, level,
    limit)``: per colour the level closest to 0 of its frames and that frame's limit; badness
    is the largest level / limit."""
    out = []
    for key, frames in groups.items():
        level, limit = [], []
        for c in range(3):
            f = min(frames, key=lambda r, c=c: abs(r[1][c]))
            level.append(f[1][c])
            limit.append(pedestal_limit(f[3], f[2][c]))
        badness = max(abs(v) / lim for v, lim in zip(level, limit, strict=True))
        out.append((badness, key, frames, level, limit))
    return out


#: Largest RMS difference between repeated scan frames of one wavelength (8x8 px block means,
#: each frame normalised to its mean) taken as noise; adjacent 10 nm bands differ by ~30 %.
REPEAT_MAX_DIFFERENCE = 0.05


def _pattern_difference(a: torch.Tensor, b: torch.Tensor, sat: torch.Tensor) -> float | None:
    """RMS difference of two ``(C, H, W)`` frames' 8x8 px block means, each normalised to its
    mean over the blocks brighter than 10 % of the first's brightest (no saturated sample);
    ``None`` when fewer than 16 such blocks."""
    if a.shape != b.shape or a.shape[-1] < 8 or a.shape[-2] < 8:
        return None
    pool = torch.nn.functional.avg_pool2d
    x = pool(a.sum(0)[None].double(), 8)[0]
    y = pool(b.sum(0)[None].double(), 8)[0]
    ok = pool(sat.any(0)[None].double(), 8)[0] == 0
    m = ok & (x > 0.1 * float(x.max()))
    if int(m.sum()) < 16:
        return None
    xm, ym = x[m] / x[m].mean(), y[m] / y[m].mean()
    return float(((xm - ym) ** 2).mean().sqrt())


def _other_groups_text(by_group: list[dict[str, Any]], group: dict[str, Any], c: int) -> str:
    """``; the other frames read 2.0 DN (white, 3 frames), …`` in colour ``c``: the level of every
    group but ``group`` (its black level named when it differs from ``group``'s)."""
    parts = []
    for g in by_group:
        same = (g["black_level_rgb"] == group["black_level_rgb"]
                and g["black_level_source"] == group["black_level_source"])  # fmt: skip
        if same and g["role"] == group["role"]:
            continue
        text = f"{g['pedestal_dn'][c]:.1f} DN ({g['role'] or 'other'}, {g['frames']} frames"
        if not same:
            text += (f", black level {_levels_text(g['black_level_rgb'] or [0.0])} DN, source: "
                     f"{g['black_level_source']}")  # fmt: skip
        parts.append(text + ")")
    return "; the other frames read " + ", ".join(parts) if parts else ""


def _levels_text(v: Sequence[float]) -> str:
    if max(v) - min(v) < 0.05:
        return f"{v[0]:.4g}"
    return "[" + ", ".join(f"{x:.4g}" for x in v) + "]"


def check_pedestal(reader: CaptureReader, mode: str, notes: list[str]) -> dict[str, Any] | None:
    """Refuse (``mode="error"``) or warn (``"warn"``) when the sensor outside every view reads
    more than the limit after black subtraction in every frame of one role read with one black
    level (all of them, or one group: :meth:`CaptureReader.pedestal`): those captures carry a
    black pedestal the black level did not remove (or too much was subtracted). The message
    names the group's role, black level and files, and the other groups' levels. Returns the
    measurement (:meth:`CaptureReader.pedestal`).

    Raises:
        CalibrationError: naming the level measured and the fix.
    """
    ped = reader.pedestal()
    if mode == "off" or ped is None:
        if ped is None:
            notes.append("pedestal not checked: every sensor pixel is within the margin of a view")
        return ped
    if ped["ok"]:
        return ped
    c = max(range(3), key=lambda i: abs(ped["pedestal_dn"][i]) / ped["pedestal_limit_dn"][i])
    lvl, lim = ped["pedestal_dn"][c], ped["pedestal_limit_dn"][c]
    rec = reader.black_level_record()
    sub = rec["black_level_rgb"][c]
    which = f"the frame closest to 0 of {ped['frames']}"
    group = ped.get("group")
    if group:  # frames of other roles or black levels: name the group at fault
        dark = rec["dark_level_rgb"]
        black = group["black_level_rgb"][c]
        sub = black + (dark[c] if dark else 0.0)
        files = group["files"]
        names = ", ".join(files[:3]) + (f", … ({len(files)} files)" if len(files) > 3 else "")
        role = f" {group['role']} frames" if group.get("role") else ""
        which = (f"the frame closest to 0 of the {len(files)}{role} read with black level "
                 f"{_levels_text(group['black_level_rgb'])} DN (source: "
                 f"{group['black_level_source']}): {names}")  # fmt: skip
        if group.get("by") != "role" and group["groups"] > 1:
            which += f"; the captures were read with {group['groups']} different black levels"
        if group.get("role"):
            which += _other_groups_text(ped.get("by_group", []), group, c)
    if lvl > 0 and group and group["black_level_source"] == "file":  # the files' own level
        what = (f"these captures carry a black pedestal of ~{lvl:.0f} DN that their files' "
                f"black level ({black:.0f} DN) does not include: correct the files' black level "
                f"(a DNG's BlackLevel tag) or give their black_level in the sheet or manifest "
                f"(e.g. {black + lvl:.0f})")  # fmt: skip
    elif lvl > 0 and group:
        what = (f"these captures carry a black pedestal of ~{lvl:.0f} DN; give their "
                f"black_level in the sheet or manifest (e.g. {black + lvl:.0f})")  # fmt: skip
    elif lvl > 0:
        what = (f"the captures carry a black pedestal of ~{lvl:.0f} DN; give black_level in the "
                f"sheet/manifest/--set (e.g. --set black_level={sub + lvl:.0f}) or add a dark "
                "frame")  # fmt: skip
    elif group:
        what = (f"the black level subtracted from these captures ({sub:.0f} DN) is ~{-lvl:.0f} "
                f"DN too high; give their right black_level in the sheet or manifest (e.g. "
                f"{sub + lvl:.0f})")  # fmt: skip
    else:
        what = (f"the black level subtracted ({sub:.0f} DN) is ~{-lvl:.0f} DN too high; give the "
                "right black_level in the sheet/manifest/--set (e.g. --set "
                f"black_level={sub + lvl:.0f})")  # fmt: skip
    dark_mean = rec["dark_level_rgb"][c] if rec["dark_level_rgb"] else 0.0
    if lvl < 0 and reader.dark_black and dark_mean > 0.5 * -lvl:  # the dark frame may be why
        n, b, src = reader.dark_black[0]
        what += (f"; or the dark frame {n} (read with black level {_levels_text(b)} DN, source: "
                 f"{src}; its mean, {dark_mean:.0f} DN above that, is subtracted from every "
                 "frame) carries a pedestal the other captures do not: give its black_level in "
                 "the sheet or manifest, or take a dark frame with the same settings")
    per_colour = ", ".join(f"{k} {v:.1f}" for k, v in zip("RGB", ped["pedestal_dn"],
                                                           strict=True))  # fmt: skip
    msg = (f"the sensor outside the views reads {lvl:.1f} DN after black subtraction "
           f"({'RGB'[c]} channel; {per_colour} DN; {which}; limit {lim:.3g} DN): "
           f"{what}")  # fmt: skip
    if mode == "error":
        raise CalibrationError(msg + " (pedestal_check=warn only warns)")
    warnings.warn(msg, UserWarning, stacklevel=3)
    notes.append(msg)
    return ped


# --- which scan frames


@dataclass
class ScanSelection:
    """The scan frames calibration uses (:func:`group_scan_frames`).

    Attributes:
        frames: per band of the grid, ``(files, band wavelength nm)``: one file, or the
            repeated frames of that wavelength (averaged when read).
        outside: ``(file, wavelength nm)`` of the frames no band uses (outside the grid or
            between its bands by more than the tolerance).
        repeated: ``(band wavelength nm, files)`` of the bands with more than one frame.
    """

    frames: list[tuple[tuple[Path, ...], float]]
    outside: list[tuple[Path, float]]
    repeated: list[tuple[float, tuple[Path, ...]]]

    @property
    def num_files(self) -> int:
        return sum(len(f) for f, _ in self.frames)

    def notes(self, grid_text: str) -> list[str]:
        """One line each for the averaged bands and the frames left out (for the report)."""
        out = []
        if self.repeated:
            out.append(
                "scan: repeated frames averaged: " + "; ".join(
                    f"{lam:g} nm: {len(fs)} frames ({', '.join(p.name for p in fs)})"
                    for lam, fs in self.repeated
                )
            )  # fmt: skip
        if self.outside:
            out.append(
                f"scan: {len(self.outside)} frame(s) not used (no band of the grid {grid_text} "
                "within the wavelength tolerance): "
                + ", ".join(f"{p.name} ({lam:g} nm)" for p, lam in self.outside)
            )
        return out


def scan_wavelengths(cs: CaptureSet) -> list[tuple[Path, float]]:
    """Every scan frame with its wavelength: its manifest entry's, else the ``<number>nm`` in its
    name, else the ``wavelength_nm`` of its TIFF/NPY/NPZ metadata.

    Raises:
        ValueError: a frame's wavelength is unknown (naming the file).
    """
    scan = list(cs.scan)
    for i, (p, lam) in enumerate(scan):
        if lam is None:
            lam = wavelength_from_name(p.name)
            if lam is None and p.suffix.lower() in (".tif", ".tiff", ".npy", ".npz"):
                _, meta = read_capture(p)
                lam = meta.get("wavelength_nm")
            if lam is None:
                raise ValueError(
                    f"scan frame {p}: wavelength unknown (no 'wavelength_nm' in its manifest "
                    "entry or metadata, and no '<number>nm' in the file name, e.g. scan_550nm.tif)"
                )
            scan[i] = (p, float(lam))
    return scan  # type: ignore[return-value]


def group_scan_frames(
    cs: CaptureSet, wavelengths_nm: torch.Tensor | Sequence[float], tol_nm: float
) -> ScanSelection:
    """Every band's scan frames (checked before any image is read): each frame goes to the band
    within ``tol_nm`` of its wavelength (:func:`scan_wavelengths`); a band with several frames
    averages them; frames near no band are listed in ``outside``, never silently dropped.

    Raises:
        ValueError: a frame's wavelength is unknown, or a band has no frame within ``tol_nm``
            (naming the missing wavelengths).
    """
    scan = scan_wavelengths(cs)
    grid = [float(v) for v in torch.as_tensor(wavelengths_nm).reshape(-1).cpu().tolist()]
    try:
        match_wavelengths([lam for _, lam in scan], grid, tol_nm)  # names missing bands
    except ValueError as exc:
        raise ValueError(f"captures {cs.root}: {exc}") from exc
    groups: list[list[Path]] = [[] for _ in grid]
    outside = []
    for p, lam in scan:
        d = [abs(lam - g) for g in grid]
        j = min(range(len(grid)), key=d.__getitem__)
        if d[j] <= tol_nm:
            groups[j].append(p)
        else:
            outside.append((p, lam))
    frames = [(tuple(g), lam) for g, lam in zip(groups, grid, strict=True)]
    repeated = [(lam, fs) for fs, lam in frames if len(fs) > 1]
    return ScanSelection(frames, outside, repeated)
