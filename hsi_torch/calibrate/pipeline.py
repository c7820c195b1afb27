"""Calibration captures → :class:`~hsi_torch.io.bundle.CalibrationBundle`: the work behind
``hsi-torch calibrate``, one function per stage, all on the device/dtype of the config (the
procedure, step by step, is in ``docs/calibration.md``).

1. **Inputs**: the capture set (:func:`hsi_torch.io.capture_set.read_capture_set`), every band's
   scan frames (:func:`~hsi_torch.calibrate.reading.group_scan_frames`), the BRF-free patch
   (:func:`brf_free_patch`); every capture read linearly by
   :class:`~hsi_torch.calibrate.reading.CaptureReader` (the manifest's settings, the config's
   overrides winning; **bilinear demosaic**; the dark frames' mean subtracted).
2. **Registration** (:func:`register_grid_shots`) from the circle-grid shots, flat-fielded by the
   white shots.
3. **BRF transmittance** (:func:`calibrate_transmittance`) from the scan, carried into the
   reference frame.
4. **Response** φ^c and the gain field g_v(p) (:func:`calibrate_response`) from the white shots;
   then the **pedestal check** (:func:`~hsi_torch.calibrate.reading.check_pedestal`).
5. **Valid region** (≥ ``min_views`` BRF-modulated views) and the bundle with settings and
   provenance (:func:`assemble_bundle`).

:func:`calibrate_capture_set` runs the stages in order. Scoring a bundle against a simulated
set's ground truth is :mod:`hsi_torch.experiments.calibration_scores`.
"""

from __future__ import annotations

import json
import math
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from hsi_torch import refdata
from hsi_torch.calibrate.config import CalibrateConfig
from hsi_torch.calibrate.reading import (
    CaptureReader,
    ScanSelection,
    check_pedestal,
    group_scan_frames,
    scan_wavelengths,
)
from hsi_torch.calibrate.registration import (
    GridDetectorConfig,
    RegistrationResult,
    ViewRegistrationReport,
    check_registration,
    register_views,
)
from hsi_torch.calibrate.remedies import (
    FLAT_VEIL_GAIN,
    MIN_UNREACHED,
    defects_finding,
    findings_dicts,
    flat_indices,
    stray_light_finding,
    veil_level,
)
from hsi_torch.calibrate.response import ResponseResult, estimate_response_field
from hsi_torch.calibrate.transmittance import (
    brf_transmittance,
    to_reference_frame,
)
from hsi_torch.calibrate.validity import ValidRegionSummary, valid_region
from hsi_torch.config import to_dict
from hsi_torch.console import progress_bar, progress_enabled
from hsi_torch.devices import torch_dtype
from hsi_torch.errors import CalibrationError, FileFormatError
from hsi_torch.findings import findings_from_dicts, warn_findings
from hsi_torch.io.bundle import CalibrationBundle, make_provenance
from hsi_torch.io.capture_set import (
    CaptureSet,
    NominalLayout,
    read_capture_set,
    read_mask_png,
)
from hsi_torch.io.radiometry import (
    capture_exposure,
    default_margin_px,
    outside_views_index,
)
from hsi_torch.io.sensor_corrections import (
    dilate_mask,
    estimate_veil,
    find_defects,
    unreached_index,
)
from hsi_torch.optics.geometry import warp_views
from hsi_torch.spectral import SpectralGrid, band_widths

__all__ = [
    "CalibrationReport",
    "PatchMasks",
    "TransmittanceStage",
    "ResponseStage",
    "ScanSelection",
    "scan_wavelengths",
    "group_scan_frames",
    "check_sensor_size",
    "brf_free_patch",
    "register_grid_shots",
    "calibrate_transmittance",
    "calibrate_response",
    "assemble_bundle",
    "calibrate_capture_set",
]

#: Saturated samples are replaced by this value before :func:`brf_transmittance` (which then
#: excludes them through ``saturation_level``); it never enters a mean.
_SAT_SENTINEL = 1e20

Tick = Callable[..., None]


def _no_tick(n: int = 1, stage: str | None = None) -> None:
    """A progress callback that does nothing."""


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
    black_level: str = ""
    pedestal: dict[str, Any] | None = None
    camera: str | None = None
    #: the remedies' decisions (:mod:`hsi_torch.calibrate.remedies`), as
    #: :meth:`hsi_torch.findings.Finding.to_dict`; also in the bundle's ``settings["findings"]``
    findings: list[dict[str, Any]] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
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
        if self.black_level:
            lines.append(f"black: {self.black_level}; camera {self.camera or 'unknown'}")
        if self.pedestal is not None:
            lines.append(
                "outside the views (after black subtraction): "
                + ", ".join(f"{c} {v:.1f}" for c, v in zip("RGB", self.pedestal["pedestal_dn"],
                                                            strict=True))
                + f" DN (limit {max(self.pedestal['pedestal_limit_dn']):.3g} DN, "
                f"{self.pedestal['outside_pixels']} px sampled per frame)"
            )
            for g in self.pedestal.get("by_group", []):  # each role / black level on its own
                lines.append(
                    f"  {g['role'] or 'frames'} ({g['frames']} frames, black level "
                    f"{g['black_level_rgb'][0]:.0f} DN, {g['black_level_source']}): "
                    + ", ".join(f"{c} {v:.1f}" for c, v in zip("RGB", g["pedestal_dn"],
                                                                strict=True))
                    + f" DN (limit {max(g['pedestal_limit_dn']):.3g} DN)"
                )  # fmt: skip
        for f in findings_from_dicts(self.findings, "report"):
            lines.append(f"finding: {f.text()}")
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


# --- helpers


def _polygon_mask(poly: np.ndarray, size: tuple[int, int], offset_px: float) -> np.ndarray:
    """``(H, W)`` bool: pixel centres inside the polygon by more than ``offset_px`` (negative:
    dilated by ``−offset_px``).

    Erosion (``offset_px > 0``) of a convex polygon (the BRF-free disk's outline) uses the
    exact distance of each pixel centre to the polygon's edges, so the usable BRF-free pixels
    are those whose centre lies ``offset_px`` inside the disk, as in the simulator's mask;
    otherwise the polygon is rasterised and the distance transform of the raster is used (it
    measures between pixel centres: it erodes by up to a pixel less, and dilates by up to a
    pixel more, a safe margin for the dilated disk)."""
    H, W = size
    poly = np.asarray(poly, np.float64).reshape(-1, 2)
    e = np.roll(poly, -1, axis=0) - poly
    cross = e[:, 0] * np.roll(e[:, 1], -1) - e[:, 1] * np.roll(e[:, 0], -1)
    convex = len(poly) >= 3 and (np.all(cross > 0) or np.all(cross < 0))
    if offset_px > 0 and convex:
        sign = 1.0 if cross[0] > 0 else -1.0  # inward normal of edge (p -> q): sign*(-e_y, e_x)
        nrm = sign * np.stack([-e[:, 1], e[:, 0]], 1) / np.linalg.norm(e, axis=1)[:, None]
        pad = 2
        x0 = int(max(0, np.floor(poly[:, 0].min() - pad)))
        x1 = int(min(W - 1, np.ceil(poly[:, 0].max() + pad)))
        y0 = int(max(0, np.floor(poly[:, 1].min() - pad)))
        y1 = int(min(H - 1, np.ceil(poly[:, 1].max() + pad)))
        out = np.zeros((H, W), bool)
        if x1 < x0 or y1 < y0:
            return out
        ys, xs = np.mgrid[y0 : y1 + 1, x0 : x1 + 1].astype(np.float64)
        d = np.full(xs.shape, np.inf)
        for p, n in zip(poly, nrm, strict=True):
            d = np.minimum(d, (xs - p[0]) * n[0] + (ys - p[1]) * n[1])
        out[y0 : y1 + 1, x0 : x1 + 1] = d > offset_px
        return out
    inside = np.zeros((H, W), np.uint8)
    cv2.fillPoly(inside, [np.round(poly * 16).astype(np.int32)], 1, lineType=cv2.LINE_8, shift=4)
    if offset_px == 0:
        return inside.astype(bool)
    if offset_px > 0:
        dist = cv2.distanceTransform(inside, cv2.DIST_L2, 5)
        return dist > offset_px
    dist = cv2.distanceTransform(1 - inside, cv2.DIST_L2, 5)
    return dist <= -offset_px


def _camera_prior(name: str, wl: torch.Tensor) -> torch.Tensor:
    if name.lower() == "flat":
        return torch.ones(3, wl.numel(), dtype=wl.dtype, device=wl.device)
    try:
        f = refdata.camera_sensitivities(name, wl.cpu().to(torch.float64), extrapolate="edge")
    except (FileNotFoundError, ValueError) as exc:  # name the configuration key at fault
        raise type(exc)(f"config key 'response.camera_sensitivity': {exc}") from None
    return torch.as_tensor(f, dtype=wl.dtype).to(wl.device)


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
            warnings.warn(msg, UserWarning, stacklevel=4)  # the caller of calibrate_capture_set
            notes.append(msg)
    keep = torch.tensor([not x for x in bad], device=white_ref.device)
    return white_ref[keep], sat_ref[keep], text


def _names(p: Path | Sequence[Path]) -> str:
    """A file's name, or the names of a band's repeated frames joined by '+'."""
    return p.name if isinstance(p, Path) else "+".join(q.name for q in p)


def _polygon_mask_from_mask(mask: np.ndarray, dilate_px: float) -> np.ndarray:
    """Dilate a bool mask by ``dilate_px`` (Euclidean)."""
    dist = cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, 5)
    return dist <= dilate_px


# --- the stages


def check_sensor_size(cs: CaptureSet, lay: NominalLayout) -> None:
    """The manifest's ``sensor_size`` (when it has one) must be the layout's.

    Raises:
        FileFormatError: naming both sizes and files."""
    size = (cs.manifest or {}).get("sensor_size")
    if size is not None and tuple(size) != tuple(lay.sensor_size):
        raise FileFormatError(
            f"{cs.root / 'manifest.json'}: sensor_size {list(size)} (H, W) does not match the "
            f"nominal layout {lay.path}'s {list(lay.sensor_size)}"
        )


@dataclass
class PatchMasks:
    """The BRF-free patch in sensor and reference-frame coordinates.

    Attributes:
        usable: ``(H, W)`` bool numpy, usable BRF-free pixels (the ratio's denominator).
        source: where ``usable`` came from (a file, or the layout's polygon), for messages.
        disk: ``(H, W)`` bool numpy, the whole disk dilated by the margin (not BRF-modulated).
        reference_triangle: ``(H, W)`` bool numpy, the reference view's triangle.
        usable_t: ``usable`` as a tensor on the device; disk_reference: ``(h, w)`` bool tensor,
            ``disk`` cropped to the reference frame.
    """

    usable: np.ndarray
    source: str
    disk: np.ndarray
    reference_triangle: np.ndarray
    usable_t: torch.Tensor
    disk_reference: torch.Tensor


def brf_free_patch(
    cs: CaptureSet, lay: NominalLayout, cfg: CalibrateConfig, device: torch.device
) -> PatchMasks:
    """The BRF-free patch: the capture set's mask PNG, else the layout's disk polygon eroded by
    ``transmittance.brf_free_erode_px``; checked to lie in the reference view.

    Raises:
        ValueError: no patch, an empty one, or one mostly outside the reference triangle.
    """
    size = lay.sensor_size
    x0, y0, w, h = lay.reference_bbox
    tcfg = cfg.transmittance
    poly = lay.brf_free_polygon()
    if cs.brf_free_mask_path is not None:
        patch_mask_np = read_mask_png(cs.brf_free_mask_path, size)
        mask_src = str(cs.brf_free_mask_path)
    elif poly is not None:
        patch_mask_np = _polygon_mask(poly, size, tcfg.brf_free_erode_px)
        mask_src = f"{lay.path}: brf_free_patch.polygon_px eroded by " \
                   f"{tcfg.brf_free_erode_px} px"  # fmt: skip
    else:
        raise ValueError(
            f"captures {cs.root}: no BRF-free patch: neither a mask (brf_free_mask.png, config "
            f"brf_free_mask) nor brf_free_patch.polygon_px in {lay.path}; B is the ratio to "
            "that patch and cannot be calibrated without it"
        )
    if not patch_mask_np.any():
        raise ValueError(f"BRF-free mask ({mask_src}) selects no pixels: the scan has no BRF-free "
                         "patch")  # fmt: skip
    # the whole disk (dilated) in the reference frame: not BRF-modulated
    if poly is not None:
        disk_np = _polygon_mask(poly, size, -tcfg.brf_free_margin_px)
    else:
        disk_np = _polygon_mask_from_mask(patch_mask_np, tcfg.brf_free_erode_px
                                          + tcfg.brf_free_margin_px)
    ref_tri_mask = _polygon_mask(lay.triangles[0], size, 0.0)
    outside = patch_mask_np & ~ref_tri_mask
    if outside.sum() > 0.05 * patch_mask_np.sum():
        raise ValueError(
            f"BRF-free mask ({mask_src}): {int(outside.sum())} of {int(patch_mask_np.sum())} "
            "pixels lie outside the reference view's triangle; the patch must be in view 0"
        )
    return PatchMasks(
        patch_mask_np, mask_src, disk_np, ref_tri_mask, torch.from_numpy(patch_mask_np).to(device),
        torch.from_numpy(disk_np[y0 : y0 + h, x0 : x0 + w].copy()).to(device),
    )  # fmt: skip


def register_grid_shots(
    cs: CaptureSet, reader: CaptureReader, lay: NominalLayout, cfg: CalibrateConfig,
    notes: list[str], tick: Tick = _no_tick,
) -> RegistrationResult:
    """View homographies from the circle-grid shots (:func:`register_views`), each shot divided
    by the mean white shot first when ``registration.flat_field`` (the target's own reflectance,
    free of the views' transmittance fringes, vignetting and fall-off, which otherwise bias
    circle centres by a few tenths of a pixel at full sensor size).

    Raises:
        ValueError: the grid was found in no shot for some view (naming the files).
    """
    det_cfg = GridDetectorConfig.from_dict(cfg.detector_dict())
    flat = None
    if cfg.registration.flat_field and cs.white:
        # saturated samples left out of the mean, shot by shot
        count = None
        for p in cs.white:
            img, sat, _ = reader.read(p)
            ok = (~sat).to(img.dtype)
            flat = img.mul_(ok) if flat is None else flat.addcmul_(img, ok)
            count = ok if count is None else count.add_(ok)
        lost = float((count == 0).float().mean())
        flat = flat.div_(count.clamp_min_(1))
        del count
        lim = 0.02 * float(torch.quantile(flat.flatten()[:: max(1, flat.numel() // 200_000)], 0.99))
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
        reg = register_views(grid_imgs, lay.triangles, lay.parity, det_cfg)
    except ValueError as exc:
        names = ", ".join(p.name for p in cs.grid)
        raise ValueError(f"registration from {len(cs.grid)} grid image(s) ({names}): {exc}") \
            from exc  # fmt: skip
    try:
        check_registration(reg, lay.triangles, lay.parity,
                           cfg.registration.min_inlier_fraction, str(lay.path))  # fmt: skip
    except ValueError as exc:
        raise CalibrationError(f"registration: {exc}") from exc
    return reg


@dataclass
class TransmittanceStage:
    """Output of :func:`calibrate_transmittance`.

    Attributes:
        B: ``(V, M, h, w)`` BRF transmittance in the reference frame (0 outside ``view_mask``).
        view_mask: ``(V, h, w)`` bool, view present (registered, inside its triangle, reliably
            lit).
        patch_mean: ``(M, 3)`` mean signal of the BRF-free patch per frame and colour (DN).
    """

    B: torch.Tensor
    view_mask: torch.Tensor
    patch_mean: torch.Tensor


def calibrate_transmittance(
    scan: Sequence[tuple[Path | Sequence[Path], float]], reader: CaptureReader, lay: NominalLayout,
    homographies: torch.Tensor, patch: PatchMasks, wavelengths_nm: torch.Tensor,
    cfg: CalibrateConfig, tick: Tick = _no_tick,
) -> TransmittanceStage:
    """B_v(p, λ) from the scan frames (one per band), in the reference frame.

    Frames are read a chunk at a time; each chunk's ratio to the BRF-free patch is carried into
    the reference frame at once (the warp is linear per wavelength), so no full-sensor
    ``(M, H, W)`` stack is ever held. What needs every wavelength — the "lit" test (max over λ),
    the reliable mask (all λ), the BRF-free plausibility check — is accumulated per sensor pixel
    and applied through the warped mask at the end.

    Raises:
        ValueError: the patch is saturated in every channel of a frame, or is not BRF-free.
    """
    wl, Hs = wavelengths_nm, homographies
    dev, dt = wl.device, wl.dtype
    size = lay.sensor_size
    bbox = list(lay.reference_bbox)
    V, M = lay.num_views, wl.numel()
    _, _, w, h = bbox
    tcfg = cfg.transmittance
    patch_mask, mask_src = patch.usable_t, patch.source
    tri_t = torch.as_tensor(lay.triangles, device=dev, dtype=dt)
    B_ref = torch.empty((V, M, h, w), dtype=dt, device=dev)
    patch_means = []
    b_max = torch.full(size, -math.inf, dtype=dt, device=dev)
    rel_all = torch.ones(size, dtype=torch.bool, device=dev)
    ref_view = torch.from_numpy(patch.reference_triangle & ~patch.disk).to(dev)
    ref_sum = torch.zeros(int(ref_view.sum()), dtype=torch.float64, device=dev)
    chunk = tcfg.frames_per_chunk
    for s in range(0, M, chunk):
        frames = []
        for p, _ in scan[s : s + chunk]:  # a band's repeated frames are averaged
            img, sat, _ = reader.read_mean(p)
            frames.append(torch.where(sat, torch.full_like(img, _SAT_SENTINEL), img))
            del img, sat
            tick(1, "scan")
        x = torch.stack(frames)
        del frames
        psat = (x >= _SAT_SENTINEL)[:, :, patch_mask].any(-1)  # (J, 3)
        if bool(psat.all(dim=1).any()):
            bad = [_names(scan[s + int(j)][0]) for j in torch.nonzero(psat.all(1)).flatten()]
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
    return TransmittanceStage(B_ref, vmask, patch_mean)


@dataclass
class ResponseStage:
    """Output of :func:`calibrate_response`.

    Attributes:
        response: the fitted φ, gain field and diagnostics
            (:class:`~hsi_torch.calibrate.response.ResponseResult`).
        white_exposure_s: the white shots' exposure (s), or ``None`` when unknown.
        white_signal_dn: mean white signal over the fitted samples (DN).
        white_exposure_unit: ``"s"`` (metadata ``exposure_s``), ``"relative"`` (the
            simulator's ``exposure``) or ``None``.
        white_exposure_source: where the first shot's exposure came from (``"file"``,
            ``"manifest"``, ...), or ``None``.
        white_level_dn: the white level the first shot was read with (DN: the file's, the
            sheet's or manifest's, the setting, or the integer type's maximum), ``None`` when it
            had none (a float file) or one per cell; white_level_source: where it came from
            (``"file"``, ``"sheet"``, ``"manifest"``, ``"config"``, ``"default"``: the integer
            type's maximum).
    """

    response: ResponseResult
    white_exposure_s: float | None
    white_signal_dn: float
    white_exposure_unit: str | None = None
    white_exposure_source: str | None = None
    white_level_dn: float | None = None
    white_level_source: str | None = None


def calibrate_response(
    white: Sequence[Path], reader: CaptureReader, homographies: torch.Tensor,
    reference_bbox: Sequence[int], trans: TransmittanceStage, wavelengths_nm: torch.Tensor,
    cfg: CalibrateConfig, notes: list[str], tick: Tick = _no_tick,
) -> ResponseStage:
    """φ^c(λ) and g_v(p) from the white-reference shots, registered into the reference frame.

    Shots of different exposures are scaled to the first one's; shots saturated over more than
    ``response.max_saturated_fraction`` of the view pixels are dropped while another one is
    below (:func:`_drop_saturated_whites`).

    Raises:
        CalibrationError: every shot is saturated, or a view has no unsaturated sample.
    """
    wl, Hs = wavelengths_nm, homographies
    dt = wl.dtype
    bbox = list(reference_bbox)
    vmask, B_ref = trans.view_mask, trans.B
    V, _, h, w = B_ref.shape
    whites, wsats, w_exp, units, sources = [], [], [], set(), []
    white_level, white_level_source = None, None
    for p in white:
        img, sat, meta = reader.read(p)
        if not whites:
            wl0 = meta.get("white_level")
            if isinstance(wl0, (int, float)) and not isinstance(wl0, bool) \
                    and math.isfinite(wl0):  # fmt: skip
                white_level = float(wl0)
                white_level_source = meta.get("white_level_source")
        whites.append(img)
        wsats.append(sat)
        # seconds (file, sheet, manifest), else the simulator's relative exposure
        t, unit, src = capture_exposure(meta)
        w_exp.append(t)
        units.add(unit)
        sources.append(src)
        tick(1, "white")
    # one unit for all (seconds, or the simulator's relative exposure), else unknown
    exp_known = all(e is not None for e in w_exp) and len(units) == 1
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
        white_ref, sat_ref, vmask, white, rc.saturation_margin, rc.max_saturated_fraction,
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
    return ResponseStage(resp, white_exposure, white_signal,
                         units.pop() if exp_known else None,
                         sources[0] if exp_known else None, white_level,
                         white_level_source)  # fmt: skip


def assemble_bundle(
    cs: CaptureSet, lay: NominalLayout, grid: SpectralGrid, wavelengths_nm: torch.Tensor,
    reg: RegistrationResult, trans: TransmittanceStage, resp: ResponseStage, patch: PatchMasks,
    reader: CaptureReader, dark_mode: str, cfg: CalibrateConfig,
    pedestal: dict[str, Any] | None = None,
) -> tuple[CalibrationBundle, torch.Tensor, ValidRegionSummary]:
    """The valid region (≥ ``min_views`` BRF-modulated views) and the bundle with its settings and
    provenance; returns ``(bundle, modulated (V, h, w), valid-region summary)``.

    Besides the grid, β's and detector settings, ``settings`` record the white shots' exposure
    (``white_exposure_s``, ``white_exposure_unit``, ``white_exposure_source``), the black level
    a capture without its own must get (``black_level_rgb``, ``black_level_source``,
    ``dark_level_rgb``, :meth:`~hsi_torch.calibrate.reading.CaptureReader.black_level_record`),
    the camera's identity (``camera``: :class:`~hsi_torch.io.radiometry.CameraIdentity`) and the
    pedestal measured (``pedestal``).

    Raises:
        ValueError: no pixel has ``min_views`` modulated views.
    """
    wl, vmask = wavelengths_nm, trans.view_mask
    V = lay.num_views
    rc, tcfg, r = cfg.response, cfg.transmittance, resp.response
    modulated = vmask & ~patch.disk_reference[None]
    valid, vsum = valid_region(vmask, modulated, cfg.min_views)
    if vsum.num_valid == 0:
        raise ValueError(
            f"no reference-frame pixel has >= {cfg.min_views} BRF-modulated registered views"
        )
    det_cfg = GridDetectorConfig.from_dict(cfg.detector_dict())
    settings = {
        "grid": grid.to_dict(),
        "wavelengths_nm": wl.cpu().tolist(),
        "white_exposure_s": resp.white_exposure_s,
        "white_exposure_note": "the white shots' metadata 'exposure_s' (s), else their "
                               "relative 'exposure' (simulator)",
        "white_exposure_unit": resp.white_exposure_unit,
        "white_exposure_source": resp.white_exposure_source,
        "white_level_dn": resp.white_level_dn,
        "white_level_source": resp.white_level_source,
        "cfa_pattern": reader.cfa_pattern,
        "demosaic": cfg.demosaic,
        "dark": dark_mode,
        **reader.black_level_record(),
        "camera": None if reader.camera is None else reader.camera.to_dict(),
        "pedestal": pedestal,
        "brf_free_mask": patch.source,
        "detector": det_cfg.to_dict(),
        "beta_phi": rc.beta_phi,
        "gamma_h": rc.gamma_h,
        "beta_phi_effective": r.beta_phi_effective,
        "gamma_h_effective": r.gamma_h_effective,
        "response": {**to_dict(rc), "alpha": r.alpha.cpu().tolist()},
        "transmittance": to_dict(tcfg),
        "min_views": cfg.min_views,
        "config": json.loads(json.dumps(to_dict(cfg), default=str)),
    }
    prov = make_provenance(cs.files(), captures_dir=str(cs.root.resolve()),
                           generator="hsi-torch calibrate")  # fmt: skip
    seqs = lay.reflection_sequences
    bundle = CalibrationBundle(
        wavelengths_nm=wl.cpu().to(torch.float64),
        triangles=lay.triangles,
        parity=lay.parity,
        view_homographies=reg.view_homographies.cpu().numpy(),
        sensor_size=np.asarray(lay.sensor_size, np.int64),
        reference_bbox=np.asarray(lay.reference_bbox, np.int64),
        B=trans.B.to(torch.float32).cpu(),
        phi=r.phi.to(torch.float64).cpu(),
        gain=r.gain.to(torch.float32).cpu(),
        view_mask=vmask.cpu(),
        modulated=modulated.cpu(),
        valid=valid.cpu(),
        reflection_sequences=seqs if len(seqs) == V else [],
        settings=settings,
        provenance=prov,
        extras={"gain_coefficients": r.coefficients.cpu().numpy(),
                "patch_mean_dn": trans.patch_mean.cpu().numpy(),
                "registration_residuals": reg.residuals},  # fmt: skip
    )
    return bundle, modulated, vsum


# --- the calibration


def sensor_corrections(
    cs: CaptureSet, reader: CaptureReader, outside: np.ndarray, cfg: CalibrateConfig,
    notes: list[str],
) -> dict[str, Any]:
    """Decide and set up the ``stray_light`` and ``defects`` remedies (after the dark frames are
    read; :mod:`hsi_torch.calibrate.remedies`).

    The veil is measured on the mean white frame at the unreached sensor samples (the
    geometric outside of the views where the mean white frame is dark,
    :func:`~hsi_torch.io.sensor_corrections.unreached_index`, margin twice the pedestal
    check's); ``stray_light: auto`` subtracts it when its level relative to the white is above
    ``stray_light_threshold``, ``subtract`` always, ``none`` never (the reader then subtracts
    it from every frame it reads). Hot pixels come from the dark frames' per-pixel mean, dead
    pixels from the mean white frame (:func:`~hsi_torch.io.sensor_corrections.find_defects`);
    ``defects: auto`` masks them when at least ``defect_min_pixels`` are found, ``mask``
    always, ``none`` never. Each decision is a finding (also when the setting is explicit).

    Returns:
        ``{"settings": {...}, "extras": {...}, "findings": [Finding, ...]}`` for the bundle:
        ``settings["stray_light"]`` (``"subtract"`` when subtracted), ``settings["defects"]``
        (counts, when masked), ``extras["unreached_index"]`` ``(K,)`` int64 and
        ``extras["defect_pixels"]`` ``(D,)`` int64 flat sensor indices.
    """
    out: dict[str, Any] = {"settings": {}, "extras": {}, "findings": []}
    if not cs.white:
        if cfg.stray_light == "subtract" or cfg.defects == "mask":
            raise ValueError("stray_light: subtract and defects: mask need white frames")
        return out  # auto: nothing to decide from
    was = reader._recording
    reader._recording = False  # a pre-read: the pedestal is recorded when the frames are used
    try:
        white, _, _ = reader.read_mean(list(cs.white))
    finally:
        reader._recording = was
    idx = unreached_index(white, outside, margin_px=2.0 * default_margin_px(reader.size))
    level = None
    if idx.size >= MIN_UNREACHED:
        _, info = estimate_veil(white, idx)
        level = veil_level(white, info["mean_dn"])
    # auto subtracts a glare (a veil shaped across the sensor), not a flat offset: that is a
    # black pedestal the pedestal check must judge, not stray light
    flat = level is not None and max(info.get("shape_gain") or [1.0]) < FLAT_VEIL_GAIN
    subtract = level is not None and (
        cfg.stray_light == "subtract"
        or (cfg.stray_light == "auto" and max(level) > cfg.stray_light_threshold and not flat))
    f = stray_light_finding(cfg.stray_light, level, cfg.stray_light_threshold, int(idx.size),
                            subtract, source="white frames", flat=flat)
    out["findings"].append(f)
    if level is not None:
        out["settings"]["stray_light_level"] = [round(v, 6) for v in level]
    if subtract:
        reader.veil_index = idx
        out["settings"]["stray_light"] = "subtract"
        out["settings"]["stray_light_white_veil_dn"] = [round(v, 3) for v in info["mean_dn"]]
        out["extras"]["unreached_index"] = idx

    origin = ("dark and white" if reader.dark_pixels is not None
              else "white only (no dark frames: hot pixels not found)")
    raw = find_defects(reader.dark_pixels, white, hot_sigma=cfg.defect_hot_sigma,
                       dead_ratio=cfg.defect_dead_ratio, dilate_px=0)
    n_raw = int(raw.sum())
    mask = cfg.defects == "mask" or (cfg.defects == "auto" and n_raw >= cfg.defect_min_pixels)
    pix = flat_indices(dilate_mask(raw, 1)) if mask else np.zeros(0, np.int64)
    f = defects_finding(cfg.defects, n_raw, int(pix.size), cfg.defect_min_pixels, mask, origin,
                        source="dark and white frames")
    out["findings"].append(f)
    if mask:
        out["settings"]["defects"] = {"pixels": int(pix.size), "raw_pixels": n_raw, "from": origin}
        out["extras"]["defect_pixels"] = pix
    return out


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
    cfg = cfg or CalibrateConfig()
    t_all = time.perf_counter()
    tm: dict[str, float] = {}
    notes: list[str] = []
    dev = torch.device(device or cfg.device)
    dt = torch_dtype(cfg.dtype)
    cs = read_capture_set(captures_dir, layout=cfg.layout, brf_free_mask=cfg.brf_free_mask)
    cs.require_calibration_captures()
    lay = cs.layout()
    grid = SpectralGrid.uniform(cfg.grid_start_nm, cfg.grid_stop_nm, cfg.grid_step_nm)
    wl = grid.wavelengths(device=dev, dtype=dt)
    check_sensor_size(cs, lay)
    scan_groups = group_scan_frames(cs, wl, cfg.transmittance.wavelength_tol_nm)
    scan_sel = scan_groups.frames
    notes += scan_groups.notes(f"{cfg.grid_start_nm:g}-{cfg.grid_stop_nm:g} nm every "
                               f"{cfg.grid_step_nm:g} nm")  # fmt: skip
    patch = brf_free_patch(cs, lay, cfg, dev)

    files_total = len(cs.dark) + len(cs.grid) + len(scan_sel) + len(cs.white) + 3  # + 3 fits
    bar = (progress_bar(total=files_total, desc="calibrating", unit="step", leave=False)
           if progress_enabled(cfg.progress if progress is None else progress) else None)

    def tick(n: int = 1, stage: str | None = None) -> None:
        if bar is not None:
            if stage:
                bar.set_postfix_str(stage)
            bar.update(n)

    outside = outside_views_index(lay.triangles, lay.sensor_size)
    roles = {p: "scan" for p, _ in cs.scan}
    roles.update({p: role for role in ("white", "grid", "dark") for p in getattr(cs, role)})
    reader = CaptureReader(cfg, lay.sensor_size, dev, dt, settings=cs.settings,
                           outside_index=outside, roles=roles)
    try:
        t0 = time.perf_counter()
        reader.set_dark(cs.dark, cfg.dark)
        if reader.dark_note:
            notes.append(reader.dark_note)
        tick(len(cs.dark), "dark")
        dark_mode = cfg.dark if cs.dark else "none (no dark frames; black level only)"
        tm["dark"] = time.perf_counter() - t0
        corrections = sensor_corrections(cs, reader, outside, cfg, notes)
        warn_findings(corrections["findings"], stacklevel=2)

        t0 = time.perf_counter()
        reg = register_grid_shots(cs, reader, lay, cfg, notes, tick)
        Hs = reg.view_homographies.to(device=dev, dtype=dt)
        tick(1, "registered")
        tm["registration"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        trans = calibrate_transmittance(scan_sel, reader, lay, Hs, patch, wl, cfg, tick)
        notes.extend(reader.scan_notes)
        tm["transmittance"] = time.perf_counter() - t0
        if len(reader.cameras) > 1:
            msg = ("the captures name more than one camera (" + ", ".join(sorted(reader.cameras))
                   + "); the bundle records the first one's")  # fmt: skip
            warnings.warn(msg, UserWarning, stacklevel=2)
            notes.append(msg)

        t0 = time.perf_counter()
        resp = calibrate_response(cs.white, reader, Hs, lay.reference_bbox, trans, wl, cfg,
                                  notes, tick)  # fmt: skip
        tm["response"] = time.perf_counter() - t0
        # every role's frames read (the white's here, when the grid is not flat-fielded)
        pedestal = check_pedestal(reader, cfg.pedestal_check, notes)

        t0 = time.perf_counter()
        bundle, modulated, vsum = assemble_bundle(cs, lay, grid, wl, reg, trans, resp, patch,
                                                  reader, dark_mode, cfg, pedestal)  # fmt: skip
        bundle.settings.update(corrections["settings"])
        bundle.extras.update(corrections["extras"])
        bundle.settings["findings"] = findings_dicts(corrections["findings"])
        tm["bundle"] = time.perf_counter() - t0
        tick(1, "bundle")
    finally:
        if bar is not None:
            bar.close()
    tm["total"] = time.perf_counter() - t_all
    vmask = trans.view_mask
    report = CalibrationReport(
        captures_dir=str(cs.root),
        counts={"scan": scan_groups.num_files, "white": len(cs.white), "grid": len(cs.grid),
                "dark": len(cs.dark)},  # fmt: skip
        registration=reg.reports,
        valid=vsum,
        view_pixels=[int(n) for n in vmask.sum((1, 2)).cpu()],
        modulated_pixels=[int(n) for n in modulated.sum((1, 2)).cpu()],
        patch_pixels=int(patch.usable.sum()),
        patch_mean_dn=trans.patch_mean.cpu().tolist(),
        response_residual_rms=[float(r) for r in resp.response.residual_rms],
        white_signal_dn=resp.white_signal_dn,
        white_exposure_s=resp.white_exposure_s,
        dark=dark_mode,
        cfa_pattern=reader.cfa_pattern,
        timings_s=tm,
        notes=notes,
        black_level=bundle.settings["black_level_source"],
        pedestal=pedestal,
        camera=None if reader.camera is None else reader.camera.name,
        findings=findings_dicts(corrections["findings"]),
    )
    return bundle, report
