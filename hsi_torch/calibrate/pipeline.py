"""Calibration captures → :class:`CalibrationBundle`: the work behind ``hsi-torch calibrate``.

Steps (DESIGN §2, issue 4), all on the device/dtype of the config:

1. **Inputs.** A capture folder with ``manifest.json`` (as written by ``hsi-torch simulate``) or,
   for a real device, the folders ``scan/``, ``white/``, ``grid/`` and optionally ``dark/`` (scan
   wavelengths from the file's metadata key ``wavelength_nm`` or its name, e.g.
   ``scan_550nm.tif``, ``scan_552p5nm.dng``). Always needed: ``nominal_layout.json`` (view
   triangles, parity, reference bbox, BRF-free patch) and the BRF-free mask (``brf_free_mask.png``
   or the layout's disk polygon, eroded). Every capture is read linearly with
   :func:`hsi_torch.io.read_any` (black level subtracted, Bayer → **bilinear demosaic**,
   saturation mask) and checked against the layout's sensor size; the dark frames' mean is then
   subtracted (``dark: per_pixel | mean | none``).
2. **Registration** from the circle-grid shots (:func:`register_views`), per-view report.
3. **BRF transmittance** from the scan (:func:`brf_transmittance`, chunked over frames), carried
   into the reference frame (:func:`to_reference_frame`, one kornia call) with its masks.
4. **Response** φ^c and the gain field g_v(p) from the white shots, registered with
   :func:`warp_views` (:func:`estimate_response_field`).
5. **Valid region** (≥ ``min_views`` BRF-modulated views) and the bundle with settings and
   provenance (SHA-256 of every input, software version).

:func:`score_against_truth` compares a bundle with a simulated set's ground truth.
"""

from __future__ import annotations

import json
import math
import re
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from hsi_torch.calibrate.bundle import CalibrationBundle, make_provenance
from hsi_torch.calibrate.config import CalibrateConfig
from hsi_torch.calibrate.registration import (
    GridDetectorConfig,
    ViewRegistrationReport,
    register_views,
)
from hsi_torch.calibrate.response import estimate_response_field
from hsi_torch.calibrate.transmittance import (
    brf_transmittance,
    match_wavelengths,
    to_reference_frame,
)
from hsi_torch.calibrate.validity import ValidRegionSummary, valid_region
from hsi_torch.errors import CalibrationError
from hsi_torch.optics.geometry import apply_homography, warp_views
from hsi_torch.spectral import SpectralGrid, band_widths

__all__ = [
    "CaptureSet",
    "CalibrationReport",
    "find_captures",
    "wavelength_from_name",
    "calibrate_capture_set",
    "score_against_truth",
    "format_scores",
    "targets_met",
]

_DTYPES = {"float32": torch.float32, "float64": torch.float64}
_SUFFIXES = (
    ".tif", ".tiff", ".npy", ".npz", ".dng", ".cr2", ".cr3", ".nef", ".arw", ".kdc", ".raf",
    ".orf", ".rw2", ".pef", ".srw", ".raw", ".3fr", ".iiq", ".erf", ".mrw", ".nrw", ".x3f",
)  # fmt: skip
_WL_RE = re.compile(r"(\d+(?:[.p]\d+)?)\s*nm", re.IGNORECASE)
#: Saturated samples are replaced by this value before :func:`brf_transmittance` (which then
#: excludes them through ``saturation_level``); it never enters a mean.
_SAT_SENTINEL = 1e20


# =============================================================================================
# inputs
# =============================================================================================


@dataclass
class CaptureSet:
    """The files of one calibration capture set.

    Attributes:
        root: the captures folder.
        scan: ``[(file, wavelength_nm or None)]`` monochromator frames.
        white, grid, dark: files of the white-reference shots, circle-grid shots, dark frames.
        layout: the parsed nominal layout; ``layout_path`` its file.
        brf_free_mask_path: PNG of usable BRF-free pixels, or ``None`` (use the layout polygon).
        manifest: the parsed ``manifest.json`` or ``None`` (plain folders).
    """

    root: Path
    scan: list[tuple[Path, float | None]]
    white: list[Path]
    grid: list[Path]
    dark: list[Path]
    layout: dict[str, Any]
    layout_path: Path
    brf_free_mask_path: Path | None
    manifest: dict[str, Any] | None = None

    def files(self) -> dict[str, Path]:
        """Every input file, labelled by its path relative to the folder (for provenance)."""
        out: dict[str, Path] = {}
        paths = [p for p, _ in self.scan] + self.white + self.grid + self.dark + [self.layout_path]
        if self.brf_free_mask_path is not None:
            paths.append(self.brf_free_mask_path)
        for p in paths:
            try:
                key = str(p.resolve().relative_to(self.root.resolve()))
            except ValueError:
                key = str(p)
            out[key] = p
        return out


def wavelength_from_name(name: str) -> float | None:
    """Wavelength (nm) in a file name such as ``scan_550nm.tif`` or ``mono_552p5nm.dng``."""
    m = _WL_RE.findall(Path(name).stem)
    if not m:
        return None
    return float(m[-1].replace("p", "."))


def _folder_files(folder: Path) -> list[Path]:
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in _SUFFIXES)


def find_captures(captures_dir: str | Path, cfg: CalibrateConfig | None = None) -> CaptureSet:
    """Locate the calibration inputs of a capture folder (manifest or plain folders).

    Raises:
        FileNotFoundError: the folder, the layout or a listed capture is missing.
        ValueError: no scan / white / grid captures (naming what is missing).
    """
    cfg = cfg or CalibrateConfig()
    root = Path(captures_dir)
    if not root.is_dir():
        raise FileNotFoundError(f"captures folder {root} does not exist")
    manifest = None
    mpath = root / "manifest.json"
    scan: list[tuple[Path, float | None]] = []
    white: list[Path] = []
    grid: list[Path] = []
    dark: list[Path] = []
    if mpath.is_file():
        try:
            manifest = json.loads(mpath.read_text())
        except json.JSONDecodeError as exc:
            raise ValueError(f"{mpath}: not valid JSON ({exc})") from exc
        for k, e in enumerate(manifest.get("captures", [])):
            if "file" not in e or "type" not in e:
                raise ValueError(f"{mpath}: captures[{k}] needs 'file' and 'type'")
            p = root / e["file"]
            if not p.is_file():
                raise FileNotFoundError(f"{mpath}: captures[{k}] file {p} does not exist")
            t = e["type"]
            if t == "scan":
                wl = e.get("wavelength_nm")
                scan.append((p, None if wl is None else float(wl)))
            elif t == "white":
                white.append(p)
            elif t == "grid":
                grid.append(p)
            elif t == "dark":
                dark.append(p)
    else:
        scan = [(p, wavelength_from_name(p.name)) for p in _folder_files(root / "scan")]
        white = _folder_files(root / "white")
        grid = _folder_files(root / "grid")
        dark = _folder_files(root / "dark")
    where = "manifest.json" if manifest is not None else "folders scan/, white/, grid/"
    for name, lst in (("monochromator scan", scan), ("white-reference", white),
                      ("circle-grid", grid)):  # fmt: skip
        if not lst:
            raise ValueError(f"captures folder {root}: no {name} captures (looked in {where})")

    lpath = Path(cfg.layout) if cfg.layout is not None else root / "nominal_layout.json"
    if manifest is not None and cfg.layout is None and manifest.get("nominal_layout"):
        lpath = root / manifest["nominal_layout"]
    if not lpath.is_file():
        raise FileNotFoundError(
            f"nominal layout {lpath} not found: calibration needs the view triangles, parity, "
            "reference_bbox and BRF-free patch (see docs/calibration.md)"
        )
    try:
        layout = json.loads(lpath.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{lpath}: not valid JSON ({exc})") from exc
    for key in ("sensor_size", "triangles_px", "parity", "reference_bbox"):
        if key not in layout:
            raise ValueError(f"nominal layout {lpath}: missing key '{key}'")

    mask_path: Path | None = None
    if cfg.brf_free_mask is not None:
        mask_path = Path(cfg.brf_free_mask)
        if not mask_path.is_file():
            raise FileNotFoundError(f"BRF-free mask {mask_path} (config brf_free_mask) not found")
    else:
        patch = layout.get("brf_free_patch") or {}
        cands = []
        if patch.get("usable_mask"):
            cands.append(lpath.parent / patch["usable_mask"])
        if manifest is not None and manifest.get("brf_free_mask"):
            cands.append(root / manifest["brf_free_mask"])
        cands.append(root / "brf_free_mask.png")
        mask_path = next((c for c in cands if c.is_file()), None)
    return CaptureSet(root, scan, white, grid, dark, layout, lpath, mask_path, manifest)


class _Reader:
    """read_any with the config's overrides, the layout's sensor size and dark subtraction."""

    def __init__(self, cfg: CalibrateConfig, sensor_size: tuple[int, int], device, dtype):
        self.cfg, self.size, self.device, self.dtype = cfg, sensor_size, device, dtype
        self.dark: torch.Tensor | None = None
        self.cfa_pattern: str | None = None

    def read(self, path: Path) -> tuple[torch.Tensor, torch.Tensor, dict[str, Any]]:
        from hsi_torch.io import read_any

        cap = read_any(
            path, expected_size=self.size, demosaic=self.cfg.demosaic,
            cfa_pattern=self.cfg.cfa_pattern, black_level=self.cfg.black_level,
            white_level=self.cfg.white_level, dtype=self.dtype, device=self.device,
        )  # fmt: skip
        if cap.metadata.get("kind") == "bayer":
            self.cfa_pattern = cap.metadata.get("cfa_pattern")
        img = cap.image if self.dark is None else cap.image - self.dark
        return img, cap.saturated, cap.metadata

    def set_dark(self, files: Sequence[Path], mode: str) -> None:
        if mode == "none" or not files:
            return
        acc = None
        for p in files:
            img, _, _ = self.read(p)
            acc = img if acc is None else acc + img
        d = acc / len(files)
        self.dark = d.mean(dim=(-2, -1), keepdim=True).expand_as(d) if mode == "mean" else d


# =============================================================================================
# report
# =============================================================================================


@dataclass
class CalibrationReport:
    """What :func:`calibrate_capture_set` did and measured (printable, JSON-able)."""

    captures_dir: str
    counts: dict[str, int]
    registration: list[ViewRegistrationReport]
    valid: ValidRegionSummary
    view_pixels: list[int]
    modulated_pixels: list[int]
    patch_pixels: int
    patch_mean_dn: list[list[float]]
    response_residual_rms: list[float]
    white_signal_dn: float
    white_exposure_s: float | None
    dark: str
    cfa_pattern: str | None
    timings_s: dict[str, float] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        from dataclasses import asdict

        d = asdict(self)
        d["valid"] = asdict(self.valid)
        return d

    def __str__(self) -> str:
        c = self.counts
        lines = [
            f"calibrated from {self.captures_dir}: {c.get('scan', 0)} scan frames, "
            f"{c.get('white', 0)} white, {c.get('grid', 0)} grid, {c.get('dark', 0)} dark "
            f"(dark: {self.dark}, demosaic: bilinear, CFA {self.cfa_pattern or 'none (RGB)'})",
            "registration (per view: grid images, RANSAC inliers / correspondences, RMS):",
        ]
        lines += ["  " + str(r) for r in self.registration]
        lines.append(
            f"BRF-free patch: {self.patch_pixels} px; scan signal there "
            f"{min(max(r) for r in self.patch_mean_dn):.0f}-"
            f"{max(max(r) for r in self.patch_mean_dn):.0f} DN (brightest channel per frame)"
        )
        lines.append(
            "view pixels in the reference frame: "
            + ", ".join(f"v{v}:{n}" for v, n in enumerate(self.view_pixels))
        )
        lines.append(
            f"response: mean white signal {self.white_signal_dn:.0f} DN, residual RMS "
            + " -> ".join(f"{r:.2f}" for r in self.response_residual_rms)
            + " DN"
        )
        lines.append(str(self.valid))
        for n in self.notes:
            lines.append(f"note: {n}")
        if self.timings_s:
            t = self.timings_s
            lines.append(
                f"time {t.get('total', 0.0):.1f} s ("
                + ", ".join(f"{k} {v:.1f} s" for k, v in t.items() if k != "total")
                + ")"
            )
        return "\n".join(lines)


# =============================================================================================
# helpers
# =============================================================================================


def _layout_arrays(layout: dict[str, Any], path: Path):
    tri = np.asarray(layout["triangles_px"], dtype=np.float64)
    par = np.asarray(layout["parity"], dtype=np.int64).reshape(-1)
    bbox = [int(v) for v in layout["reference_bbox"]]
    size = tuple(int(v) for v in layout["sensor_size"])
    if tri.ndim != 3 or tri.shape[1:] != (3, 2):
        raise ValueError(f"nominal layout {path}: triangles_px must be (V, 3, 2), got {tri.shape}")
    if par.shape != (tri.shape[0],) or not np.all(np.isin(par, (-1, 1))):
        raise ValueError(f"nominal layout {path}: parity must be {tri.shape[0]} values of ±1")
    if len(bbox) != 4 or bbox[2] <= 0 or bbox[3] <= 0:
        raise ValueError(f"nominal layout {path}: reference_bbox must be (x0, y0, w, h)")
    if len(size) != 2:
        raise ValueError(f"nominal layout {path}: sensor_size must be (H, W)")
    ref = int(layout.get("reference_view", 0))
    if ref != 0:
        raise ValueError(f"nominal layout {path}: reference_view must be 0 (got {ref})")
    seqs = [tuple(int(i) for i in s) for s in layout.get("reflection_sequences", [])]
    return tri, par, bbox, size, seqs


def _polygon_mask(poly: np.ndarray, size: tuple[int, int], offset_px: float) -> np.ndarray:
    """``(H, W)`` bool: pixel centres inside the polygon by at least ``offset_px`` (negative:
    dilated by ``−offset_px``)."""
    import cv2

    H, W = size
    inside = np.zeros((H, W), np.uint8)
    cv2.fillPoly(inside, [np.round(poly * 16).astype(np.int32)], 1, lineType=cv2.LINE_8, shift=4)
    if offset_px == 0:
        return inside.astype(bool)
    if offset_px > 0:
        dist = cv2.distanceTransform(inside, cv2.DIST_L2, 5)
        return dist > offset_px
    dist = cv2.distanceTransform(1 - inside, cv2.DIST_L2, 5)
    return dist <= -offset_px


def _read_mask_png(path: Path, size: tuple[int, int]) -> np.ndarray:
    import cv2

    m = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if m is None:
        raise ValueError(f"BRF-free mask {path}: not a readable image")
    if m.shape != tuple(size):
        raise ValueError(
            f"BRF-free mask {path}: size {m.shape} does not match the sensor size {tuple(size)}"
        )
    return m > 127


def _camera_prior(name: str, wl: torch.Tensor) -> torch.Tensor:
    if name.lower() == "flat":
        return torch.ones(3, wl.numel(), dtype=wl.dtype, device=wl.device)
    from hsi_torch import refdata

    f = refdata.camera_sensitivities(name, wl.cpu().to(torch.float64), extrapolate="edge")
    return torch.as_tensor(f, dtype=wl.dtype).to(wl.device)


def _progress(enabled: bool, total: int):
    from hsi_torch.console import progress_bar, progress_enabled

    if not progress_enabled(enabled):
        return None
    return progress_bar(total=total, desc="calibrating", unit="step", leave=False)


# =============================================================================================
# the calibration
# =============================================================================================


def calibrate_capture_set(
    captures_dir: str | Path,
    cfg: CalibrateConfig | None = None,
    *,
    device: str | None = None,
    progress: bool | None = None,
) -> tuple[CalibrationBundle, CalibrationReport]:
    """Calibrate from a capture folder (see the module docstring); writes nothing.

    Args:
        captures_dir: folder with ``manifest.json`` or ``scan/``, ``white/``, ``grid/`` folders,
            plus ``nominal_layout.json`` (or ``cfg.layout``).
        cfg: settings (:class:`CalibrateConfig`; defaults when ``None``).
        device: overrides ``cfg.device``.
        progress: overrides ``cfg.progress`` (tqdm bar on stderr, one step per file read).

    Returns:
        ``(bundle, report)``: the :class:`CalibrationBundle` (``settings`` hold the grid, β's,
        ``white_exposure_s``, ``cfa_pattern``, detector parameters; ``provenance`` the SHA-256 of
        every input) and a :class:`CalibrationReport`.

    Raises:
        ValueError / FileNotFoundError naming the file, wavelength, view or key at fault: missing
        grid wavelengths, no BRF-free patch (or one that is not BRF-free), a grid found in no
        image for some view, captures of another sensor size, unreadable files.
    """
    from hsi_torch.config import to_dict

    cfg = cfg or CalibrateConfig()
    t_all = time.perf_counter()
    tm: dict[str, float] = {}
    notes: list[str] = []
    dev = torch.device(device or cfg.device)
    dt = _DTYPES[cfg.dtype]
    cs = find_captures(captures_dir, cfg)
    tri, par, bbox, size, seqs = _layout_arrays(cs.layout, cs.layout_path)
    V = tri.shape[0]
    x0, y0, w, h = bbox
    grid = SpectralGrid.uniform(cfg.grid_start_nm, cfg.grid_stop_nm, cfg.grid_step_nm)
    wl = grid.wavelengths(device=dev, dtype=dt)
    M = wl.numel()

    # ---- scan wavelengths (checked before any image is read) --------------------------------
    scan = list(cs.scan)
    for i, (p, lam) in enumerate(scan):
        if lam is None:
            from hsi_torch.io import read_capture

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
    scan_nm = [float(lam) for _, lam in scan]  # type: ignore[arg-type]
    try:
        idx = match_wavelengths(scan_nm, wl.cpu(), cfg.transmittance.wavelength_tol_nm)
    except ValueError as exc:
        raise ValueError(f"captures {cs.root}: {exc}") from exc
    scan_sel = [scan[int(i)] for i in idx]

    # ---- BRF-free patch -----------------------------------------------------------------------
    patch_info = cs.layout.get("brf_free_patch") or {}
    poly_list = patch_info.get("polygon_px")
    poly = np.asarray(poly_list, np.float64) if poly_list else None
    if cs.brf_free_mask_path is not None:
        patch_mask_np = _read_mask_png(cs.brf_free_mask_path, size)
        mask_src = str(cs.brf_free_mask_path)
    elif poly is not None:
        patch_mask_np = _polygon_mask(poly, size, cfg.transmittance.brf_free_erode_px)
        mask_src = f"{cs.layout_path}: brf_free_patch.polygon_px eroded by " \
                   f"{cfg.transmittance.brf_free_erode_px} px"  # fmt: skip
    else:
        raise ValueError(
            f"captures {cs.root}: no BRF-free patch: neither a mask (brf_free_mask.png, config "
            f"brf_free_mask) nor brf_free_patch.polygon_px in {cs.layout_path}; B is the ratio to "
            "that patch and cannot be calibrated without it"
        )
    if not patch_mask_np.any():
        raise ValueError(f"BRF-free mask ({mask_src}) selects no pixels: the scan has no BRF-free "
                         "patch")  # fmt: skip
    # the whole disk (dilated) in the reference frame: not BRF-modulated
    if poly is not None:
        disk_np = _polygon_mask(poly, size, -cfg.transmittance.brf_free_margin_px)
    else:
        disk_np = _polygon_mask_from_mask(patch_mask_np, cfg.transmittance.brf_free_erode_px
                                          + cfg.transmittance.brf_free_margin_px)
    ref_tri_mask = _polygon_mask(tri[0], size, 0.0)
    outside = patch_mask_np & ~ref_tri_mask
    if outside.sum() > 0.05 * patch_mask_np.sum():
        raise ValueError(
            f"BRF-free mask ({mask_src}): {int(outside.sum())} of {int(patch_mask_np.sum())} "
            "pixels lie outside the reference view's triangle; the patch must be in view 0"
        )
    patch_mask = torch.from_numpy(patch_mask_np).to(dev)
    disk_ref = torch.from_numpy(disk_np[y0 : y0 + h, x0 : x0 + w].copy()).to(dev)

    files_total = len(cs.dark) + len(cs.grid) + len(scan_sel) + len(cs.white) + 3  # + 3 fits
    bar = _progress(cfg.progress if progress is None else progress, files_total)

    def tick(n: int = 1, stage: str | None = None) -> None:
        if bar is not None:
            if stage:
                bar.set_postfix_str(stage)
            bar.update(n)

    reader = _Reader(cfg, size, dev, dt)
    try:
        # ---- dark ---------------------------------------------------------------------------
        t0 = time.perf_counter()
        reader.set_dark(cs.dark, cfg.dark)
        tick(len(cs.dark), "dark")
        dark_mode = cfg.dark if cs.dark else "none (no dark frames; black level only)"
        tm["dark"] = time.perf_counter() - t0

        # ---- registration -------------------------------------------------------------------
        t0 = time.perf_counter()
        det_cfg = GridDetectorConfig.from_dict(cfg.detector_dict())
        flat = None
        if cfg.registration.flat_field and cs.white:
            # the grid shots divided by the mean white shot: the target's own reflectance, free
            # of the views' transmittance fringes, vignetting and fall-off (which otherwise bias
            # circle centres by a few tenths of a pixel at full sensor size)
            # (saturated samples left out of the mean, shot by shot)
            count = None
            for p in cs.white:
                img, sat, _ = reader.read(p)
                ok = (~sat).to(img.dtype)
                flat = img.mul_(ok) if flat is None else flat.addcmul_(img, ok)
                count = ok if count is None else count.add_(ok)
            lost = float((count == 0).float().mean())
            flat = flat.div_(count.clamp_min_(1))
            del count
            lim = 0.02 * float(torch.quantile(flat.flatten()[:: max(1, flat.numel() // 200_000)],
                                              0.99))
            if lost > cfg.response.max_saturated_fraction or not lim > 0:
                # saturated white shots are reported (or dropped) by the response stage; the
                # grid shots are then registered as they are
                notes.append(f"grid shots not flat-fielded: {100 * lost:.1f} % of the white "
                             "samples saturated in every shot")
                flat = None
            else:
                flat = torch.where(flat > lim, flat.reciprocal(), torch.zeros_like(flat))
        grid_imgs = []
        for p in cs.grid:
            img, _, _ = reader.read(p)
            grid_imgs.append(img if flat is None else img.mul_(flat))
            tick(1, "grid")
        del flat
        try:
            reg = register_views(grid_imgs, tri, par, det_cfg)
        except ValueError as exc:
            names = ", ".join(p.name for p in cs.grid)
            raise ValueError(f"registration from {len(cs.grid)} grid image(s) ({names}): {exc}") \
                from exc  # fmt: skip
        Hs = reg.view_homographies.to(device=dev, dtype=dt)
        del grid_imgs
        tick(1, "registered")
        tm["registration"] = time.perf_counter() - t0

        # ---- BRF transmittance --------------------------------------------------------------
        # Frames are read a chunk at a time; each chunk's ratio to the BRF-free patch is carried
        # into the reference frame at once (the warp is linear per wavelength), so no
        # full-sensor (M, H, W) stack is ever held. What needs every wavelength — the "lit" test
        # (max over λ), the reliable mask (all λ), the BRF-free plausibility check — is
        # accumulated per sensor pixel and applied through the warped mask at the end.
        t0 = time.perf_counter()
        tcfg = cfg.transmittance
        tri_t = torch.as_tensor(tri, device=dev, dtype=dt)
        B_ref = torch.empty((V, M, h, w), dtype=dt, device=dev)
        patch_means = []
        b_max = torch.full(size, -math.inf, dtype=dt, device=dev)
        rel_all = torch.ones(size, dtype=torch.bool, device=dev)
        ref_view = torch.from_numpy(ref_tri_mask & ~disk_np).to(dev)
        ref_sum = torch.zeros(int(ref_view.sum()), dtype=torch.float64, device=dev)
        chunk = tcfg.frames_per_chunk
        for s in range(0, M, chunk):
            frames = []
            for p, _ in scan_sel[s : s + chunk]:
                img, sat, _ = reader.read(p)
                frames.append(torch.where(sat, torch.full_like(img, _SAT_SENTINEL), img))
                del img, sat
                tick(1, "scan")
            x = torch.stack(frames)
            del frames
            psat = (x >= _SAT_SENTINEL)[:, :, patch_mask].any(-1)  # (J, 3)
            if bool(psat.all(dim=1).any()):
                bad = [scan_sel[s + int(j)][0].name for j in torch.nonzero(psat.all(1)).flatten()]
                raise ValueError(f"scan frame(s) {bad}: the BRF-free patch is saturated in every "
                                 "colour channel; reduce the exposure")  # fmt: skip
            try:
                tr = brf_transmittance(
                    x, wl[s : s + chunk], patch_mask, saturation_level=_SAT_SENTINEL,
                    lit_threshold=-math.inf, weight_power=tcfg.weight_power,
                )  # fmt: skip
            except ValueError as exc:
                raise ValueError(f"monochromator scan ({mask_src}): {exc}") from exc
            del x
            torch.maximum(b_max, tr.transmittance.amax(0), out=b_max)
            rel_all &= tr.reliable.all(0)
            ref_sum += tr.transmittance[:, ref_view].sum(0, dtype=torch.float64)
            patch_means.append(tr.patch_mean)
            B_ref[:, s : s + chunk] = to_reference_frame(
                tr.transmittance, Hs, tri_t, bbox, inset_px=cfg.registration.inset_px,
            )[0]  # fmt: skip
            del tr
        lit = b_max >= tcfg.lit_threshold
        reliable = rel_all & lit
        patch_mean = torch.cat(patch_means)
        # the patch must be BRF-free: elsewhere in the reference view the filter stack (two
        # polarizers) passes at most ~half of it
        lit_ref = lit[ref_view]
        if bool(lit_ref.any()):
            level = float((ref_sum[lit_ref] / M).median())
            if level > tcfg.max_patch_ratio:
                raise ValueError(
                    f"BRF-free mask ({mask_src}) does not mark a BRF-free patch: the rest of the "
                    f"reference view transmits {level:.2f} of it on average (a patch without the "
                    f"filter stack is ~2x brighter; limit transmittance.max_patch_ratio = "
                    f"{tcfg.max_patch_ratio})"
                )
        _, vmask = to_reference_frame(
            reliable[None].to(dt), Hs, tri_t, bbox, source_mask=reliable,
            inset_px=cfg.registration.inset_px,
        )  # fmt: skip
        B_ref.clamp_min_(0).mul_(vmask[:, None])
        tm["transmittance"] = time.perf_counter() - t0

        # ---- response φ and gain field ------------------------------------------------------
        t0 = time.perf_counter()
        whites, wsats, w_exp = [], [], []
        for p in cs.white:
            img, sat, meta = reader.read(p)
            whites.append(img)
            wsats.append(sat)
            w_exp.append(meta.get("exposure_s", meta.get("exposure")))
            tick(1, "white")
        exp_known = all(e is not None for e in w_exp)
        white_exposure = float(w_exp[0]) if exp_known else None
        if exp_known and any(abs(float(e) / float(w_exp[0]) - 1) > 1e-6 for e in w_exp):
            t_ref = float(w_exp[0])
            whites = [im * (t_ref / float(e)) for im, e in zip(whites, w_exp, strict=True)]
            notes.append(f"white shots scaled to the exposure of the first ({w_exp[0]})")
        # each shot warped on its own (image + saturation as 6 channels): no (S, 6, H, W) stack
        both = torch.cat([
            warp_views(torch.cat([im, sm.to(dt)])[None], Hs, bbox)[0]
            for im, sm in zip(whites, wsats, strict=True)
        ])  # (S, V, 6, h, w)  # fmt: skip
        del whites, wsats
        white_ref, sat_ref = both[:, :, :3], both[:, :, 3:]
        rc = cfg.response
        white_ref, sat_ref, sat_text = _drop_saturated_whites(
            white_ref, sat_ref, vmask, cs.white, rc.saturation_margin, rc.max_saturated_fraction,
            notes,
        )  # fmt: skip
        ok = (sat_ref <= rc.saturation_margin).all(2).all(0)  # (V, h, w)
        obs_mask = vmask & ok
        empty = [v for v in range(V) if bool(vmask[v].any()) and not bool(obs_mask[v].any())]
        if empty:
            raise CalibrationError(
                f"white-reference shots: no unsaturated sample left in view(s) {empty} "
                f"({sat_text}); reduce the exposure of the white shots"
            )
        del ok
        f_prior = _camera_prior(rc.camera_sensitivity, wl)
        resp = estimate_response_field(
            white_ref, B_ref, f_prior, obs_mask, band_widths_nm=band_widths(wl),
            beta_phi=rc.beta_phi, gamma_h=rc.gamma_h,
            normalise=rc.normalise, max_pixels=rc.max_pixels,
            n_iter=rc.n_iter, degree=rc.degree, smoothness=rc.smoothness,
            diff_order=rc.diff_order, refine_steps=rc.refine_steps,
        )  # fmt: skip
        tick(1, "response")
        white_signal = float(white_ref.mean(0)[obs_mask[:, None].expand(V, 3, h, w)].mean())
        tm["response"] = time.perf_counter() - t0

        # ---- valid region and bundle --------------------------------------------------------
        t0 = time.perf_counter()
        modulated = vmask & ~disk_ref[None]
        valid, vsum = valid_region(vmask, modulated, cfg.min_views)
        if vsum.num_valid == 0:
            raise ValueError(
                f"no reference-frame pixel has >= {cfg.min_views} BRF-modulated registered views"
            )
        settings = {
            "grid": grid.to_dict(),
            "wavelengths_nm": wl.cpu().tolist(),
            "white_exposure_s": white_exposure,
            "white_exposure_note": "the white shots' metadata 'exposure_s' (s), else their "
                                   "relative 'exposure' (simulator)",
            "cfa_pattern": reader.cfa_pattern,
            "demosaic": cfg.demosaic,
            "dark": dark_mode,
            "brf_free_mask": mask_src,
            "detector": det_cfg.to_dict(),
            "beta_phi": rc.beta_phi,
            "gamma_h": rc.gamma_h,
            "beta_phi_effective": resp.beta_phi_effective,
            "gamma_h_effective": resp.gamma_h_effective,
            "response": {**to_dict(rc), "alpha": resp.alpha.cpu().tolist()},
            "transmittance": to_dict(tcfg),
            "min_views": cfg.min_views,
            "config": json.loads(json.dumps(to_dict(cfg), default=str)),
        }
        prov = make_provenance(cs.files(), captures_dir=str(cs.root.resolve()),
                               generator="hsi-torch calibrate")  # fmt: skip
        bundle = CalibrationBundle(
            wavelengths_nm=wl.cpu().to(torch.float64),
            triangles=tri,
            parity=par,
            view_homographies=reg.view_homographies.cpu().numpy(),
            sensor_size=np.asarray(size, np.int64),
            reference_bbox=np.asarray(bbox, np.int64),
            B=B_ref.to(torch.float32).cpu(),
            phi=resp.phi.to(torch.float64).cpu(),
            gain=resp.gain.to(torch.float32).cpu(),
            view_mask=vmask.cpu(),
            modulated=modulated.cpu(),
            valid=valid.cpu(),
            reflection_sequences=seqs if len(seqs) == V else [],
            settings=settings,
            provenance=prov,
            extras={"gain_coefficients": resp.coefficients.cpu().numpy(),
                    "patch_mean_dn": patch_mean.cpu().numpy(),
                    "registration_residuals": reg.residuals},  # fmt: skip
        )
        tm["bundle"] = time.perf_counter() - t0
        tick(1, "bundle")
    finally:
        if bar is not None:
            bar.close()
    tm["total"] = time.perf_counter() - t_all
    report = CalibrationReport(
        captures_dir=str(cs.root),
        counts={"scan": len(scan_sel), "white": len(cs.white), "grid": len(cs.grid),
                "dark": len(cs.dark)},  # fmt: skip
        registration=reg.reports,
        valid=vsum,
        view_pixels=[int(n) for n in vmask.sum((1, 2)).cpu()],
        modulated_pixels=[int(n) for n in modulated.sum((1, 2)).cpu()],
        patch_pixels=int(patch_mask_np.sum()),
        patch_mean_dn=patch_mean.cpu().tolist(),
        response_residual_rms=[float(r) for r in resp.residual_rms],
        white_signal_dn=white_signal,
        white_exposure_s=white_exposure,
        dark=dark_mode,
        cfa_pattern=reader.cfa_pattern,
        timings_s=tm,
        notes=notes,
    )
    return bundle, report


def _drop_saturated_whites(
    white_ref: torch.Tensor,
    sat_ref: torch.Tensor,
    vmask: torch.Tensor,
    files: Sequence[Path],
    margin: float,
    max_fraction: float,
    notes: list[str],
) -> tuple[torch.Tensor, torch.Tensor, str]:
    """Leave out the white shots with more than ``max_fraction`` of their registered view pixels
    saturated, as long as another shot is below (a warning and a note name each one dropped).

    Args:
        white_ref, sat_ref: ``(S, V, 3, h, w)`` warped shots and saturation weights.
        vmask: ``(V, h, w)`` registered view pixels.

    Returns:
        The kept shots and weights, and a text of every shot's saturated fraction (for errors).

    Raises:
        CalibrationError: every shot is above the limit (naming them and their fractions).
    """
    n_px = max(1, int(vmask.sum()))
    frac = [float(((s > margin).any(1) & vmask).sum()) / n_px for s in sat_ref]
    text = ", ".join(f"{p.name} {100 * f:.1f} % saturated" for p, f in zip(files, frac,
                                                                          strict=True))
    bad = [f > max_fraction for f in frac]
    if all(bad):
        raise CalibrationError(
            f"all {len(files)} white-reference shot(s) are saturated ({text} of the registered "
            f"view pixels; limit response.max_saturated_fraction = {max_fraction:g}); reduce the "
            "exposure of the white shots"
        )
    if not any(bad):
        return white_ref, sat_ref, text
    kept = sum(1 for x in bad if not x)
    for p, f, x in zip(files, frac, bad, strict=True):
        if x:
            msg = (f"white-reference shot {p} dropped: {100 * f:.1f} % of its registered view "
                   f"pixels are saturated (limit response.max_saturated_fraction = "
                   f"{max_fraction:g}); the other {kept} shot(s) are used")  # fmt: skip
            warnings.warn(msg, UserWarning, stacklevel=3)
            notes.append(msg)
    keep = torch.tensor([not x for x in bad], device=white_ref.device)
    return white_ref[keep], sat_ref[keep], text


def _polygon_mask_from_mask(mask: np.ndarray, dilate_px: float) -> np.ndarray:
    """Dilate a bool mask by ``dilate_px`` (Euclidean)."""
    import cv2

    dist = cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, 5)
    return dist <= dilate_px


# =============================================================================================
# scoring against the simulator's truth
# =============================================================================================


def score_against_truth(
    bundle: CalibrationBundle | str | Path, capture_dir: str | Path
) -> dict[str, Any]:
    """Compare a calibration bundle with the ground truth of a simulated capture set.

    Definitions (all over the **common valid region** ``Q = valid_true ∧ valid_est`` unless
    stated):

    - ``B_rel_rms``: ``RMS(B_est − B_true) / RMS(B_true)`` over every band and every (view,
      pixel) with ``q ∈ Q`` and the view present in both bundles; per view too.
    - ``phi_corr``: Pearson correlation of ``φ^c_est`` and ``φ^c_true`` per colour (shape).
    - gauge: ``(g, φ)`` and ``(s·g, φ/s)`` are equivalent, so both sides are normalised the same
      way: ``g ← g / mean_{q ∈ Q, v=0}(g_0)``, ``φ ← φ · that mean``. Then ``gain_rel_rms[v]`` =
      ``RMS((g_est − g_true)/g_true)`` over ``q ∈ Q`` where view v is present in both,
      ``gain_max_rel_rms`` their maximum, and ``phi_rel_rms`` = ``RMS(φ_est−φ_true)/RMS(φ_true)``
      (scale included: the product ``g·φ`` is what reconstruction uses).
    - ``homography_rms_px`` / ``homography_max_px`` per view: ``|H_est(p) − q|`` in reference
      px for ``p = H_true⁻¹(q)`` over the reference-frame pixels where the view is truly present.
    - valid-region sizes and their intersection over union.
    """
    from hsi_torch.simulate.oracle import load_truth

    b = bundle if isinstance(bundle, CalibrationBundle) else CalibrationBundle.load(bundle)
    t, _ = load_truth(capture_dir)
    if tuple(t["B"].shape) != tuple(b.B.shape):
        raise ValueError(
            f"bundle B {tuple(b.B.shape)} and truth B {tuple(t['B'].shape)} differ in shape: "
            "the bundle was not made from this capture set's geometry"
        )
    Q = t["valid"] & b.valid
    both = t["view_mask"] & b.view_mask & Q[None]  # (V, h, w)
    V = b.num_views
    Bt = t["B"].astype(np.float64)
    Be = b.B.astype(np.float64)
    d = (Be - Bt).transpose(1, 0, 2, 3)[:, both]  # (M, n)
    ref = Bt.transpose(1, 0, 2, 3)[:, both]
    out: dict[str, Any] = {
        "B_rel_rms": float(np.sqrt((d**2).mean()) / np.sqrt((ref**2).mean())),
        "B_rel_rms_per_view": [
            float(np.sqrt(((Be[v] - Bt[v])[:, both[v]] ** 2).mean())
                  / np.sqrt((Bt[v][:, both[v]] ** 2).mean()))
            if both[v].any() else float("nan")
            for v in range(V)
        ],  # fmt: skip
        "B_abs_rms": float(np.sqrt((d**2).mean())),
    }
    pe, pt = b.phi.astype(np.float64), t["phi"].astype(np.float64)
    out["phi_corr"] = [float(np.corrcoef(pe[c], pt[c])[0, 1]) for c in range(3)]
    m0 = both[0]
    if not m0.any():
        m0 = b.view_mask[0] & t["view_mask"][0]
    se = float(b.gain[0][m0].mean())
    st = float(t["gain"][0][m0].mean())
    ge, gt = b.gain / se, t["gain"] / st
    pe, pt = pe * se, pt * st
    out["phi_rel_rms"] = float(np.sqrt(((pe - pt) ** 2).mean()) / np.sqrt((pt**2).mean()))
    rel = []
    for v in range(V):
        m = both[v] & (gt[v] > 0)
        r = (ge[v][m] - gt[v][m]) / gt[v][m]
        rel.append(float(np.sqrt((r**2).mean())) if m.any() else float("nan"))
    out["gain_rel_rms_per_view"] = rel
    out["gain_max_rel_rms"] = float(np.nanmax(rel))
    # homographies
    x0, y0, w, h = (int(v) for v in b.reference_bbox)
    ys, xs = np.mgrid[0:h, 0:w]
    He, Ht = b.view_homographies, t["view_homographies"]
    rms, mx = [], []
    for v in range(V):
        m = t["view_mask"][v]
        q = np.stack([xs[m] + x0, ys[m] + y0], 1).astype(np.float64)
        if not len(q):
            rms.append(float("nan"))
            mx.append(float("nan"))
            continue
        p = apply_homography(np.linalg.inv(Ht[v]), q)
        e = np.linalg.norm(apply_homography(He[v], p) - q, axis=1)
        rms.append(float(np.sqrt((e**2).mean())))
        mx.append(float(e.max()))
    out["homography_rms_px"] = rms
    out["homography_max_px"] = mx
    out["homography_worst_rms_px"] = float(np.nanmax(rms))
    nv_t, nv_e = int(t["valid"].sum()), int(b.valid.sum())
    union = int((t["valid"] | b.valid).sum())
    out["valid_true"] = nv_t
    out["valid_est"] = nv_e
    out["valid_iou"] = float(Q.sum() / union) if union else 0.0
    out["pixels_scored"] = int(Q.sum())
    return out


def targets_met(s: dict[str, Any]) -> dict[str, bool]:
    """The issue's targets on :func:`score_against_truth`'s result: ``{"B", "phi", "gain",
    "homography"} → met`` (B < 2 % RMS, φ correlation > 0.99, g < 2 %, homography < 0.3 px)."""
    return {
        "B": s["B_rel_rms"] < 0.02,
        "phi": min(s["phi_corr"]) > 0.99,
        "gain": s["gain_max_rel_rms"] < 0.02,
        "homography": s["homography_worst_rms_px"] < 0.3,
    }


def format_scores(s: dict[str, Any], targets: bool = True) -> str:
    """Readable lines of :func:`score_against_truth`'s result (with the issue's targets)."""
    met = targets_met(s)

    def ok(key: str) -> str:
        return (" ok" if met[key] else " MISSED") if targets else ""

    lines = [
        f"B: RMS(B_est - B_true)/RMS(B_true) = {100 * s['B_rel_rms']:.2f} % over the common valid "
        f"region (target < 2 %){ok('B')}",
        "   per view: " + ", ".join(f"{100 * x:.2f}" for x in s["B_rel_rms_per_view"]) + " %",
        "phi shape correlation R/G/B: " + ", ".join(f"{x:.5f}" for x in s["phi_corr"])
        + f" (target > 0.99){ok('phi')}",
        f"phi (same gauge) RMS rel. error {100 * s['phi_rel_rms']:.2f} %",
        f"gain (same gauge) worst view RMS rel. error {100 * s['gain_max_rel_rms']:.2f} % "
        f"(target < 2 %){ok('gain')}",
        "   per view: " + ", ".join(f"{100 * x:.2f}" for x in s["gain_rel_rms_per_view"]) + " %",
        f"homography vs true mapping: worst view RMS {s['homography_worst_rms_px']:.3f} px "
        f"(target < 0.3 px){ok('homography')}",
        "   RMS per view: " + ", ".join(f"{x:.3f}" for x in s["homography_rms_px"]) + " px",
        "   max per view: " + ", ".join(f"{x:.3f}" for x in s["homography_max_px"]) + " px",
        f"valid region: {s['valid_est']} px calibrated vs {s['valid_true']} px true "
        f"(IoU {s['valid_iou']:.3f}); {s['pixels_scored']} px scored",
    ]
    return "\n".join(lines)

