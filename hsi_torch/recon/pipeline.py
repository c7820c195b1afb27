"""Capture → spectral cube: sample the views, build observations and masks, solve, assemble.

Per frame (all pixels at once, no per-pixel Python):

1. **Warp** (:func:`sample_views`): the linear RGB capture ``(3, H, W)`` and its saturation mask
   are stacked into six channels and sampled at the bundle's precomputed sensor positions of every
   valid pixel in every view (:attr:`BundleSensing.sample_grid`, ``(1, V, P, 2)``) by *one*
   batched kornia call (``kornia.geometry.transform.remap``, bilinear, ``align_corners=True``,
   zero padding) → ``(B, 6, V, P)``. This equals the full-frame warp
   (:func:`warp_capture`: :func:`hsi_torch.optics.geometry.warp_views`, kornia
   ``warp_perspective``) at the valid pixels, without warping the invalid ones. A sample is
   *saturated* when any saturated sensor sample contributes to its bilinear footprint (warped
   weight ``> sat_threshold``, default ``1e-3``: weights that are 0 up to rounding of the
   homography do not count).
2. **Observations** (:func:`observations_from_samples`): ``y (P, 3V)`` view-major
   (``o = 3v + c``) and the frame mask = static mask (view present and modulated,
   outside-triangle excluded) ∧ not saturated ∧ finite. ``y`` is multiplied by the exposure ratio
   ``t_white / t_capture`` when both are known (the bundle's response was calibrated at the white
   reference's exposure ``t_white``; see :func:`exposure_scale`).
3. **Solve** (:func:`solve_observations`): the precomputed factorisation
   (:class:`~hsi_torch.recon.sensing.BundleSensing`) solves every pixel for the static mask; pixels
   whose frame mask differs (saturation, non-finite data) are re-solved *exactly* with their own
   mask (``solve_nnls`` on that sub-batch only). Pixels left with fewer than ``min_views`` (3)
   views that still have an observation are invalid: NaN in the cube (or 0 with
   ``nan_invalid=False``) and ``False`` in ``valid``. The frame's fit residual
   ``‖W(A s − y)‖ / ‖W y‖`` (median over a fixed sample of valid pixels) flags a bundle that does
   not belong to the capture.
4. **Assemble**: ``cube (M, h, w)``, ``valid (h, w)``.

Gradients (used by :class:`~hsi_torch.recon.module.HSIReconstructor`): the active-set solver (and
tolerance-driven ADMM) run without autograd; when the input requires grad, the answer is passed
through one differentiable *reduced solve* on its free set ``F = {m : x_m > 0}``:
``x_F = G_FF⁻¹ (Aᵀ W y)_F``, ``x_Z = 0`` — the exact derivative of the NNLS solution wherever the
free set is locally constant. The forward value stays the solver's answer (straight-through
form). Fixed-iteration ADMM (``admm_iters=N``) is differentiated through its iterations.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from hsi_torch.errors import FileFormatError, InputError
from hsi_torch.io import read_any
from hsi_torch.io.bundle import CalibrationBundle
from hsi_torch.io.cube import cube_to_xarray
from hsi_torch.io.raw import demosaic_bilinear, demosaic_saturation, validate_cfa_pattern
from hsi_torch.io.sensor_corrections import subtract_veil
from hsi_torch.optics.geometry import warp_views
from hsi_torch.recon import _compiled as _frame_compiled
from hsi_torch.recon.checks import BundleRadiometry, exposure_info, prepare_capture
from hsi_torch.recon.drift import DriftError, corrected_sensing, drift_motion_px, estimate_drift
from hsi_torch.recon.nnls import cpu_threads, solve_nnls
from hsi_torch.recon.sensing import (
    BundleSensing,
    precompute_sensing,
    refreshed_sensing,
    sample_pixels,
)
from hsi_torch.recon.settings import (
    DEFAULT_BETA,
    SOLVERS,
    ReconstructSettings,
    dtype_name,
    keyword_defaults,
    settings_or_keywords,
)
from hsi_torch.recon.spatial import DEFAULT_LAM
from hsi_torch.recon.spatial import solve_frame as spatial_solve_frame
from hsi_torch.recon.uncertainty import (
    DEFAULT_ELECTRONS_PER_DN,
    RAW_LAYOUTS,
    SensorNoise,
    nnls_band_std,
    observation_variance,
    sampling_variance_factor,
)

__all__ = [
    "ReconstructionResult",
    "Reconstructor",
    "warp_capture",
    "build_observations",
    "sample_views",
    "observations_from_samples",
    "DEFAULT_BETA",
    "ReconstructSettings",
    "FIT_RESIDUAL_SAMPLES",
    "solve_observations",
    "assemble_cube",
    "exposure_scale",
    "correct_frames",
    "prepare_input",
    "fit_residual",
    "check_min_views",
]

#: Pixels (evenly spaced over the bundle's valid pixels) on which the fit residual is evaluated.
FIT_RESIDUAL_SAMPLES = 4096


@dataclass
class ReconstructionResult:
    """One reconstructed frame.

    Attributes:
        cube: ``(M, h, w)`` spectra on the reference frame (NaN or 0 where ``valid`` is False).
        valid: ``(h, w)`` bool, pixel reconstructed from ≥ ``min_views`` views.
        wavelengths_nm: ``(M,)`` float64, nm.
        stats: counts and solver diagnostics — ``num_valid``, ``num_lost`` (valid in the bundle,
            invalid in this frame), ``num_resolved`` (exact re-solves with a frame mask),
            ``num_pivoted`` (active-set corrections), ``converged_fraction``,
            ``num_not_converged`` (valid pixels whose solve did not reach the KKT tolerance),
            ``max_kkt``, ``fit_residual`` (median over up to :data:`FIT_RESIDUAL_SAMPLES` evenly
            spaced valid pixels of ``‖W(A s − y)‖ / ‖W y‖``, W = the frame mask; ≈ the noise
            level for a matching bundle, large when the bundle belongs to another geometry),
            ``exposure_scale``, ``observations`` (the bundle's static observations),
            ``usable_observations`` (of those: unsaturated and finite in this frame),
            ``saturated_observations``, ``no_valid_reason`` (``None``, or why not a single pixel
            is valid: saturation, non-finite data, ``min_views``).
        timings: seconds per stage (``load`` when read from a file, ``warp``, ``observations``,
            ``solve``, ``uncertainty`` (with ``uncertainty=True``), ``assemble``, ``total``).
        std: ``(M, h, w)`` standard deviation of every band from the sensor noise
            (:mod:`hsi_torch.recon.uncertainty`; 0 on bands at the bound, NaN where ``valid``
            is False), or ``None`` when the reconstructor was made without ``uncertainty=True``.
    """

    cube: Tensor
    valid: Tensor
    wavelengths_nm: Tensor
    stats: dict[str, Any] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)
    std: Tensor | None = None

    def to_xarray(self, metadata: dict[str, Any] | None = None):
        """The cube as an ``xarray.DataArray`` ``(wavelength, y, x)``, wavelength in nm, the
        valid mask as a coordinate (:func:`hsi_torch.io.cube.cube_to_xarray`; needs
        ``pip install 'hsi-torch[formats]'``)."""
        return cube_to_xarray(self.cube.detach().cpu(), self.wavelengths_nm.detach().cpu(),
                              self.valid.detach().cpu(), metadata)  # fmt: skip


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


class _Clock:
    """Stage timer: ``clock()`` syncs the device and returns ``time.perf_counter()``; disabled,
    it returns 0.0 without touching the device."""

    def __init__(self, device: torch.device, enabled: bool) -> None:
        self.device, self.enabled = device, enabled

    def __call__(self) -> float:
        if not self.enabled:
            return 0.0
        _sync(self.device)
        return time.perf_counter()


def exposure_scale(capture_exposure_s: Any, white_exposure_s: float | None) -> float:
    """Factor applied to a capture's observations: ``t_white / t_capture`` (1 when unknown).

    The response ``phi`` (hence ``A``) is calibrated on white-reference shots taken with exposure
    ``t_white``: a white reflector imaged with exposure ``t`` reads ``t / t_white`` times the
    calibrated values. Scaling ``y`` by ``t_white / t`` keeps reconstructed spectra in
    reflectance units relative to the white reference, whatever the capture's exposure.
    """
    if white_exposure_s is None or capture_exposure_s is None:
        return 1.0
    try:
        t = float(capture_exposure_s)
    except (TypeError, ValueError, OverflowError):
        raise InputError(
            f"capture metadata 'exposure_s' is not a number: {capture_exposure_s!r}"
        ) from None
    if not t > 0 or t == float("inf"):
        raise InputError(f"capture metadata 'exposure_s' must be > 0, got {capture_exposure_s!r}")
    return float(white_exposure_s) / t


def _check_scale(scale: Tensor | float | None, batch: int) -> None:
    """``exposure_scale`` must be finite and > 0: a scalar, or one factor per frame."""
    if scale is None:
        return
    if isinstance(scale, Tensor):
        if scale.ndim > 1 or scale.numel() not in (1, batch):
            raise InputError(
                f"exposure_scale must be a scalar or have shape ({batch},) (one factor per "
                f"frame), got shape {tuple(scale.shape)}"
            )
        if scale.is_floating_point() or scale.is_complex():
            bad = not bool((torch.isfinite(scale) & (scale > 0)).all())
        else:
            bad = not bool((scale > 0).all())
        if bad:
            raise InputError(f"exposure_scale must be finite and > 0, got {scale.tolist()}")
        return
    try:
        v = float(scale)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"exposure_scale must be a number, got {scale!r}") from None
    if not (v > 0 and math.isfinite(v)):
        raise InputError(f"exposure_scale must be finite and > 0, got {scale!r}")


def prepare_input(
    image: Tensor, saturated: Tensor | None, cfa_pattern: str | None
) -> tuple[Tensor, Tensor | None]:
    """``(…, 3, H, W)`` RGB passes; ``(…, 1, H, W)`` Bayer is demosaiced (bilinear, full
    resolution, the saturation mask propagated) with ``cfa_pattern``."""
    if not isinstance(image, Tensor):
        raise TypeError(f"image must be a torch.Tensor, got {type(image).__name__}")
    if image.ndim < 3 or image.shape[-3] not in (1, 3):
        raise ValueError(
            f"image must be (…, 3, H, W) linear RGB or (…, 1, H, W) Bayer, got {tuple(image.shape)}"
        )
    if saturated is not None and saturated.shape != image.shape:
        raise ValueError(
            f"saturated must have the image's shape {tuple(image.shape)}, got "
            f"{tuple(saturated.shape)}"
        )
    if image.shape[-3] == 3:
        return image, saturated

    if cfa_pattern is None:
        raise ValueError(
            "a Bayer input (…, 1, H, W) needs a CFA pattern: pass cfa_pattern= or use a bundle "
            "whose settings hold 'cfa_pattern'"
        )
    pattern = validate_cfa_pattern(cfa_pattern)
    rgb = demosaic_bilinear(image, pattern)
    sat = None if saturated is None else demosaic_saturation(saturated.bool(), pattern, "bilinear")
    return rgb, sat


def warp_capture(
    sens: BundleSensing, images: Tensor, saturated: Tensor | None = None
) -> tuple[Tensor, Tensor | None]:
    """Warp all views of ``(B, 3, H, W)`` images (and masks) into the reference frame, one call.

    Returns:
        ``(B, V, 3, h, w)`` warped values and ``(B, V, 3, h, w)`` warped saturation weights
        (float in [0, 1]; ``None`` without a mask).
    """
    x = images
    if saturated is not None:
        x = torch.cat([images, saturated.to(images.dtype)], dim=1)
    warped, _ = warp_views(x, sens.homographies.to(images.device), sens.reference_bbox)
    if saturated is None:
        return warped, None
    return warped[:, :, :3], warped[:, :, 3:]


def build_observations(
    sens: BundleSensing,
    warped: Tensor,
    warped_sat: Tensor | None = None,
    sat_threshold: float = 1e-3,
) -> tuple[Tensor, Tensor, Tensor]:
    """Observations and per-frame masks of the bundle's valid pixels.

    Args:
        warped: ``(B, V, 3, h, w)``; warped_sat: same shape (weights) or ``None``.

    Returns:
        ``y (B, P, 3V)`` (``o = 3v + c``), ``mask (B, P, 3V)`` bool (static ∧ unsaturated ∧ finite),
        ``saturated (B, P, 3V)`` bool (within the static mask).
    """
    B, V, C, h, w = warped.shape
    pix = sens.pixel_index.to(warped.device)
    y = warped.reshape(B, V * C, h * w).index_select(2, pix).transpose(1, 2)
    static = sens.obs_mask.to(warped.device).unsqueeze(0)
    finite = torch.isfinite(y)
    if warped_sat is not None:
        sat = warped_sat.reshape(B, V * C, h * w).index_select(2, pix).transpose(1, 2)
        sat = (sat > sat_threshold) & static
    else:
        sat = torch.zeros_like(finite)
    return y, static & finite & ~sat, sat


def sample_views(
    sens: BundleSensing, images: Tensor, saturated: Tensor | None = None
) -> tuple[Tensor, Tensor | None]:
    """Sample every view of ``(B, 3, H, W)`` images (and masks) at the bundle's valid pixels.

    One ``kornia.geometry.transform.remap`` call (bilinear, zero padding, ``align_corners=True``)
    on the stacked image and saturation channels with the per-bundle grid
    :meth:`BundleSensing.grid` ``(1, V, P, 2)``.

    Returns:
        ``(B, 3, V, P)`` values and ``(B, 3, V, P)`` saturation weights in [0, 1] (``None``
        without a mask). Equal to :func:`warp_capture` at ``sens.pixel_index``.
    """
    grid = sens.grid().to(device=images.device, dtype=images.dtype)
    if saturated is None:
        x = images
    elif torch.is_grad_enabled() and images.requires_grad:
        x = torch.cat([images, saturated.to(images.dtype)], dim=1)
    else:
        # image and mask copied into a staging buffer kept with the bundle (one pass each, no
        # float copy of the mask, no fresh cube-size allocation per frame)
        with sens.staging_lock:
            x = sens.staging((images.shape[0], 6, *images.shape[2:]), images.dtype, images.device)
            x[:, :3].copy_(images)
            x[:, 3:].copy_(saturated)
            return _remap_split(x, grid, 3)
    return _remap_split(x, grid, 3 if saturated is not None else None)


def _remap_split(x: Tensor, grid: Tensor, split: int | None) -> tuple[Tensor, Tensor | None]:
    from kornia.geometry.transform import remap

    out = remap(
        x, grid[..., 0], grid[..., 1], mode="bilinear", padding_mode="zeros", align_corners=True,
        normalized_coordinates=True,
    )  # fmt: skip  # (B, C, V, P)
    if split is None:
        return out, None
    return out[:, :split], out[:, split:]


def observations_from_samples(
    sens: BundleSensing,
    samples: Tensor,
    sat_weights: Tensor | None = None,
    sat_threshold: float = 1e-3,
) -> tuple[Tensor, Tensor, Tensor]:
    """Observations and per-frame masks from :func:`sample_views`' ``(B, 3, V, P)`` output.

    Returns:
        ``y (B, P, 3V)`` (``o = 3v + c``), ``mask (B, P, 3V)`` bool (static ∧ unsaturated ∧ finite),
        ``saturated (B, P, 3V)`` bool (within the static mask) — as :func:`build_observations`.
    """
    B, C, V, P = samples.shape
    y = samples.permute(0, 3, 2, 1).reshape(B, P, V * C)
    static = sens.obs_mask.to(samples.device).unsqueeze(0)
    ok = static & torch.isfinite(y)
    if sens.sample_inside is not None:  # a drift-corrected grid: samples off the sensor dropped
        ok &= sens.sample_inside.to(samples.device).T.repeat_interleave(C, dim=1).unsqueeze(0)
    if sat_weights is not None:
        sat = (sat_weights.permute(0, 3, 2, 1) > sat_threshold).reshape(B, P, V * C) & static
        ok &= ~sat
    else:
        sat = torch.zeros_like(ok)
    return y, ok, sat


def _reduced_resolve(
    sens: BundleSensing, y: Tensor, mask: Tensor, x: Tensor, changed: Tensor
) -> Tensor:
    """Differentiable re-solve on the free set of ``x``; value ``x``, gradient of the reduced
    system ``x_F = G_FF⁻¹ (Aᵀ W y)_F``."""
    model, prob = sens.model, sens.problem
    zero = torch.zeros((), dtype=model.dtype, device=model.device)
    G = prob.gram
    G = G.expand(x.shape[0], -1, -1) if G.shape[0] == 1 else G
    if bool(changed.any()):
        idx = changed.nonzero().squeeze(1)
        G = G.clone()
        G[idx] = model.gram(mask[idx], idx, prob.reg)
    b = model.A_adjoint(torch.where(mask, y, zero))  # (P, M), differentiable in y
    free = x.detach() > 0
    m = x.shape[1]
    eye = torch.eye(m, dtype=model.dtype, device=model.device)
    ff = free.unsqueeze(2) & free.unsqueeze(1)
    Gh = torch.where(ff, G, eye.expand_as(G))
    bh = torch.where(free, b, zero)
    xr = torch.linalg.solve(Gh, bh)
    return x.detach() + (xr - xr.detach())


def _solve_per_pixel(
    sens: BundleSensing, y: Tensor, mask: Tensor, V: int, min_views: int, premasked: bool,
    solver: str, admm_iters: int | None, chunk_size: int | None, threads: int,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, int]:
    """The per-pixel part of :func:`solve_observations`: the valid and changed pixels, the
    masked ``y``, the prepared problem's solve and the exact re-solves of the changed pixels.
    ``threads``: the solver's CPU threads (torch's own count is lowered to 1 around this call).
    Returns ``ok``, ``changed``, ``yc``, ``x``, ``converged``, ``kkt``, ``iterations``, the
    number re-solved."""
    P = y.shape[0]
    static = sens.obs_mask
    if (y.device.type == "cpu" and static.device.type == "cpu" and _frame_compiled.AVAILABLE
            and y.dtype in (torch.float32, torch.float64)
            and not (y.requires_grad and torch.is_grad_enabled())):
        # one compiled pass over the pixels instead of five torch passes over (P, 3V)
        out = _frame_compiled.frame_masks_cpu(
            y.detach().numpy(), mask.numpy(), static.numpy(), 3, int(min_views),
            None if premasked else torch.empty((), dtype=sens.dtype).numpy().dtype, threads)
        ok, changed = torch.from_numpy(out[1]), torch.from_numpy(out[2])
        yc = y if premasked else torch.from_numpy(out[0])
    else:
        zero = torch.zeros((), dtype=y.dtype, device=y.device)
        views_left = mask.view(P, V, 3).any(2).sum(1)
        ok = views_left >= int(min_views)
        changed = ok & (mask != static).any(1)
        yc = y if premasked else torch.where(mask, y, zero).to(sens.dtype)
    kw: dict[str, Any] = dict(solver=solver, chunk_size=chunk_size, num_threads=threads)
    if solver == "admm" and admm_iters is not None:
        kw["admm_iters"] = int(admm_iters)
    res = sens.problem.solve(yc, **kw)
    x, conv, kkt, iters = res.x, res.converged, res.kkt_residual, res.iterations
    n_changed = int(torch.count_nonzero(changed))
    if n_changed:
        idx = changed.nonzero().squeeze(1)
        sub = solve_nnls(
            sens.model.select(idx), yc[idx], mask=mask[idx], beta=sens.beta,
            diff_order=sens.diff_order, **kw,
        )  # fmt: skip
        # the solve's own tensors: overwritten in place (no frame-sized copies), unless x
        # takes part in a graph (the differentiable ADMM mode)
        x = x.index_copy(0, idx, sub.x) if x.requires_grad else x.index_copy_(0, idx, sub.x)
        conv.index_copy_(0, idx, sub.converged)
        kkt = (kkt.index_copy(0, idx, sub.kkt_residual) if kkt.requires_grad
               else kkt.index_copy_(0, idx, sub.kkt_residual))
        iters.index_copy_(0, idx, sub.iterations)
    return ok, changed, yc, x, conv, kkt, iters, n_changed


def solve_observations(
    sens: BundleSensing,
    y: Tensor,
    mask: Tensor,
    *,
    solver: str = "active_set",
    admm_iters: int | None = None,
    chunk_size: int | None = None,
    min_views: int = 3,
    premasked: bool = False,
    stats: bool = True,
    prior: str = "none",
    lam: float | str = DEFAULT_LAM,
    spatial_iters: int | None = None,
) -> tuple[Tensor, Tensor, dict[str, Any]]:
    """Solve one frame's ``P`` pixels with the precomputed factorisation (+ exact re-solves).

    Args:
        y: ``(P, 3V)`` observations (DN, exposure-corrected); may hold NaN where ``mask`` is False.
        mask: ``(P, 3V)`` bool frame mask.
        solver: ``"active_set"`` or ``"admm"``; admm_iters: fixed ADMM iterations (differentiable).
        min_views: views (with ≥ 1 usable colour) a pixel needs to stay valid.
        premasked: ``y`` is already 0 wherever ``mask`` is False (and in ``sens.dtype``): used
            as is, without a masked copy.
        stats: compute ``info`` (host syncs: counts, KKT statistics, fit residual); ``False``:
            ``info`` is empty and only the solve's own control flow reads the device.
        prior: ``"none"`` (per-pixel NNLS) or ``"tv"``: then the per-pixel answer warm-starts
            the spatial-spectral solve (:func:`hsi_torch.recon.spatial.solve_frame`) over the
            valid pixels; ``info`` gains its ``lam``, ``lam_abs``, ``noise_sigma``, iterations
            and residuals, and KKT statistics stay those of the per-pixel warm start.
        lam: relative TV weight (``prior="tv"``); spatial_iters: fixed spatial ADMM iterations
            (differentiable; ``None``: to tolerance, not differentiable).

    Returns:
        ``x (P, M)`` (0 where invalid), ``ok (P,)`` bool, ``info`` (counts, KKT statistics).
    """
    if solver not in SOLVERS:
        raise ValueError(f"solver must be one of {SOLVERS}, got {solver!r}")
    P, O = y.shape
    V = O // 3
    zero = torch.zeros((), dtype=y.dtype, device=y.device)
    # the per-pixel solve and its bookkeeping: single-threaded torch kernels on CPU, as in the
    # solver (a multi-threaded element-wise kernel waits at its barrier for a core another
    # process holds; the compiled pass has its own threads)
    threads = torch.get_num_threads()
    with cpu_threads(y.device, 1):
        ok, changed, yc, x, conv, kkt, iters, n_changed = _solve_per_pixel(
            sens, y, mask, V, min_views, premasked, solver, admm_iters, chunk_size, threads)
    native_grad = solver == "admm" and admm_iters is not None
    grad = torch.is_grad_enabled() and yc.requires_grad
    sinfo: dict[str, Any] = {}
    if prior == "tv":
        if grad and spatial_iters is None:
            raise ValueError("prior='tv' with gradients needs spatial_iters=N (fixed, "
                             "differentiable iterations)")
        x, sinfo = spatial_solve_frame(sens, yc, mask, ok, changed, x, lam=lam,
                                       iters=spatial_iters)
    elif grad and not native_grad:
        x = _reduced_resolve(sens, yc, mask, x, changed)
    if prior != "tv" and x.device.type == "cpu" and not x.requires_grad:
        # the solve's own x: its (usually few) invalid rows zeroed, not a frame-sized select
        x.index_fill_(0, (~ok).nonzero().squeeze(1), 0.0)
    else:
        x = torch.where(ok.unsqueeze(1), x, zero.to(x.dtype))
    if not stats:
        return x, ok, {}
    with cpu_threads(y.device, 1):
        info = _frame_stats(sens, x, yc, mask, ok, conv, kkt, iters, n_changed, solver)
    info.update(sinfo)
    return x, ok, info


def _frame_stats(
    sens: BundleSensing, x: Tensor, yc: Tensor, mask: Tensor, ok: Tensor, conv: Tensor,
    kkt: Tensor, iters: Tensor, n_changed: int, solver: str,
) -> dict[str, Any]:
    """The counts and diagnostics of :func:`solve_observations`' ``info`` (host syncs)."""
    P = x.shape[0]
    zero = torch.zeros((), dtype=kkt.dtype, device=kkt.device)
    okc = conv & ok
    n_ok = int(torch.count_nonzero(ok))
    n_conv = int(torch.count_nonzero(okc))
    return {
        "num_valid": n_ok,
        "num_lost": P - n_ok,
        "num_resolved": n_changed,
        "num_pivoted": (int(torch.count_nonzero((iters > 0) & ok)) if solver == "active_set"
                        else 0),
        "num_not_converged": n_ok - n_conv,
        "converged_fraction": n_conv / max(1, n_ok),
        "max_kkt": float(torch.where(ok, kkt, zero).max()) if n_ok else 0.0,
        "fit_residual": fit_residual(sens, x.detach(), yc.detach(), mask, ok),
    }


def fit_residual(
    sens: BundleSensing,
    x: Tensor,
    y: Tensor,
    mask: Tensor,
    ok: Tensor,
    num_samples: int = FIT_RESIDUAL_SAMPLES,
) -> float:
    """Relative fit residual of a frame on its brighter half: ``sqrt(Σ‖W(A s − y)‖² / Σ‖W y‖²)``.

    Evaluated on up to ``num_samples`` pixels evenly spaced over the bundle's ``P`` valid pixels
    (the same ones every frame; those invalid in this frame are left out), W = the frame mask,
    pooled over the sampled pixels whose signal ``‖W y‖`` is at least the median of the sample.
    Dark pixels are left out because their observations are mostly noise: a dark or shadowed
    scene would otherwise score high with the right bundle. Pooling weights pixels by their
    signal, so the value is the share of the observed signal the model does not explain — about
    the noise-to-signal ratio for the right bundle, large for a bundle of another geometry. NaN
    without valid pixels.

    Args:
        x: ``(P, M)`` solution; y: ``(P, 3V)`` observations (zero where masked); mask, ok: as in
            :func:`solve_observations`.
    """
    idx = sample_pixels(ok, num_samples)
    if idx is None:
        return float("nan")
    model = sens.model
    w = mask.index_select(0, idx).to(model.dtype)
    ys = y.index_select(0, idx).to(model.dtype) * w
    r = model.A(x.index_select(0, idx).to(model.dtype), idx) * w - ys
    num = r.double().square().sum(1)
    den = ys.double().square().sum(1)
    bright = den >= den.median()
    total = float(den[bright].sum())
    return math.sqrt(float(num[bright].sum()) / total) if total > 0 else 0.0


def assemble_cube(
    sens: BundleSensing, x: Tensor, ok: Tensor, nan_invalid: bool = True
) -> tuple[Tensor, Tensor]:
    """Scatter ``x (…, P, M)`` into ``cube (…, M, h, w)``; ``valid (…, h, w)``. Differentiable."""
    h, w = sens.frame_size
    lead = x.shape[:-2]
    P, M = x.shape[-2:]
    pix = sens.pixel_index.to(x.device)
    fill = float("nan") if nan_invalid else 0.0
    cube = torch.full((*lead, M, h * w), fill, dtype=x.dtype, device=x.device)
    cube.index_copy_(cube.ndim - 1, pix, x.transpose(-1, -2))
    valid = torch.zeros((*lead, h * w), dtype=torch.bool, device=x.device)
    valid.index_copy_(valid.ndim - 1, pix, ok)
    lost = sens.valid.to(x.device).reshape(h * w) & ~valid
    if bool(lost.any()):  # bundle pixels invalid in this frame (usually few)
        cube.masked_fill_(lost.unsqueeze(-2), fill)
    return cube.reshape(*lead, M, h, w), valid.reshape(*lead, h, w)


def reconstruct_batch(
    sens: BundleSensing,
    images: Tensor,
    saturated: Tensor | None = None,
    *,
    scale: Tensor | float | None = None,
    solver: str = "active_set",
    admm_iters: int | None = None,
    chunk_size: int | None = None,
    min_views: int = 3,
    nan_invalid: bool = True,
    sat_threshold: float = 1e-3,
    stats: bool = True,
    prior: str = "none",
    lam: float | str = DEFAULT_LAM,
    spatial_iters: int | None = None,
    noise: SensorNoise | None = None,
    sampling_factor: Tensor | None = None,
) -> tuple[Tensor, ...]:
    """Shared core of :class:`Reconstructor` and :class:`~hsi_torch.recon.module.HSIReconstructor`.

    Args:
        images: ``(B, 3, H, W)`` linear RGB on ``sens.device`` (cast to ``sens.dtype``).
        saturated: ``(B, 3, H, W)`` bool or ``None``.
        scale: scalar or ``(B,)`` factor on the observations (exposure correction).
        stats: per-frame statistics and stage timings (each stage ends with a device sync);
            ``False`` (the ``nn.Module``): no timing, no statistics, no extra sync.
        prior, lam, spatial_iters: see :func:`solve_observations`.
        noise: the raw sensor's noise: also return the standard deviation of every band
            (:mod:`hsi_torch.recon.uncertainty`); sampling_factor: ``(P, 3V)`` variance factor
            of the observations (:func:`~hsi_torch.recon.uncertainty.sampling_variance_factor`;
            ``None``: 1).

    Returns:
        ``cube (B, M, h, w)``, ``valid (B, h, w)``, per-frame stats, stage timings (s, summed;
        both empty when ``stats`` is False); with ``noise``, a fifth item ``std (B, M, h, w)``.
    """
    dev = sens.device
    if images.device != dev:
        raise ValueError(f"input is on {images.device} but the bundle tensors are on {dev}")
    _check_scale(scale, images.shape[0])
    if images.shape[0] == 0:  # an empty batch: empty outputs of the right shapes
        h, w = sens.frame_size
        cube = images.new_empty((0, sens.num_bands, h, w), dtype=sens.dtype)
        return cube, torch.zeros((0, h, w), dtype=torch.bool, device=dev), [], {}
    t: dict[str, float] = {}
    clock = _Clock(dev, stats)
    t0 = clock()
    imgs = images.to(sens.dtype)
    if saturated is not None and not bool(saturated.any()):
        saturated = None  # nothing saturated: the mask channels would sample to 0 everywhere
    samples, wsat = sample_views(sens, imgs, saturated)
    t1 = clock()
    t["warp"] = t1 - t0
    y, mask, sat = observations_from_samples(sens, samples, wsat, sat_threshold)
    inplace = not (torch.is_grad_enabled() and y.requires_grad)  # y is this function's own copy
    if scale is not None:
        s = torch.as_tensor(scale, dtype=y.dtype, device=dev)
        s = s.view(-1, 1, 1) if s.ndim == 1 else s
        y = y.mul_(s) if inplace else y * s
    if inplace:
        y.masked_fill_(~mask, 0)  # masked observations are never used (they may be NaN)
    t2 = clock()
    t["observations"] = t2 - t1
    xs, oks, infos = [], [], []
    num_obs = int(torch.count_nonzero(sens.obs_mask)) if stats else 0
    for i in range(y.shape[0]):
        x, ok, info = solve_observations(
            sens, y[i], mask[i], solver=solver, admm_iters=admm_iters, chunk_size=chunk_size,
            min_views=min_views, premasked=inplace, stats=stats, prior=prior, lam=lam,
            spatial_iters=spatial_iters,
        )  # fmt: skip
        if stats:
            info["observations"] = num_obs
            info["usable_observations"] = int(torch.count_nonzero(mask[i]))
            info["saturated_observations"] = int(torch.count_nonzero(sat[i]))
            info["no_valid_reason"] = _no_valid_reason(info, min_views, sens.num_views)
            infos.append(info)
        xs.append(x)
        oks.append(ok)
    t3 = clock()
    t["solve"] = t3 - t2
    stds = []
    if noise is not None:
        ks = torch.ones((), dtype=y.dtype, device=dev) if scale is None else scale
        ks = torch.as_tensor(ks, dtype=y.dtype, device=dev).reshape(-1).expand(y.shape[0])
        for i in range(y.shape[0]):
            var = observation_variance(y[i].detach(), noise, scale=ks[i],
                                       sampling_factor=sampling_factor)  # fmt: skip
            std = nnls_band_std(sens.model, xs[i].detach(), var, mask[i], problem=sens.problem)
            stds.append(torch.where(oks[i].unsqueeze(1), std, torch.zeros((), dtype=std.dtype,
                                                                          device=std.device)))
        t4 = clock()
        t["uncertainty"] = t4 - t3
        t3 = t4
    if len(xs) == 1:  # no stacked copy for a single frame
        cube, valid = assemble_cube(sens, xs[0][None], oks[0][None], nan_invalid)
    else:
        cube, valid = assemble_cube(sens, torch.stack(xs), torch.stack(oks), nan_invalid)
    t["assemble"] = clock() - t3
    if noise is None:
        return cube, valid, infos, (t if stats else {})
    std_cube, _ = assemble_cube(sens, torch.stack(stds), torch.stack(oks), nan_invalid)
    return cube, valid, infos, (t if stats else {}), std_cube


def check_min_views(min_views: int, num_views: int) -> None:
    """``1 <= min_views <= num_views`` (more views than the bundle has: no pixel could be valid)."""
    if not 1 <= int(min_views) <= num_views:
        raise InputError(
            f"min_views must be between 1 and the bundle's {num_views} views, got {min_views}"
        )


def _no_valid_reason(info: dict[str, Any], min_views: int, num_views: int) -> str | None:
    """Why a frame has no valid pixel (``None`` when it has some), from its statistics."""
    if info.get("num_valid", 0) > 0:
        return None
    if min_views > num_views:
        return f"min_views={min_views} exceeds the bundle's {num_views} views"
    total = int(info.get("observations", 0))
    if total == 0:
        return "the calibration bundle has no usable observation"
    sat = int(info.get("saturated_observations", 0))
    usable = int(info.get("usable_observations", 0))
    other = max(0, total - usable - sat)
    parts = []
    if sat:
        parts.append(f"{sat} of {total} observations are saturated (at the white level; reduce "
                     "the exposure or check white_level)")
    if other:
        parts.append(f"{other} of {total} observations are not finite (NaN/inf samples)")
    parts.append(f"no pixel has min_views={min_views} views with a usable observation")
    return "; ".join(parts)


class Reconstructor:
    """Reconstruct frames that share one calibration bundle (all precomputation done once).

    Args:
        bundle: :class:`CalibrationBundle`, its path, or a ready :class:`BundleSensing`.
        beta: smoothness weight on ``‖D s‖²`` on the data's DN² scale (1e-2 … 1e6 are useful;
            default :data:`DEFAULT_BETA` = 1e4, as ``ReconstructConfig``).
        diff_order: 1 (first difference, default), 2, or 0 (Tikhonov).
        solver: ``"active_set"`` (exact) or ``"admm"``; admm_iters: fixed ADMM iterations.
        device, dtype: where the bundle tensors and the solve live.
        chunk_size: pixels per solver chunk (memory bound); ``None``: solver default.
        min_views: views a pixel needs (default 3, as the bundle's valid region).
        nan_invalid: invalid pixels hold NaN (else 0) in the cube.
        exposure_correction: scale observations by ``t_white / t_capture`` when both are known.
        sat_threshold: warped saturation weight above which an observation is saturated.
        prior: ``"none"`` (per-pixel NNLS, the default) or ``"tv"``: spatial-spectral
            reconstruction with a vectorial total-variation prior, warm-started from the
            per-pixel answer (:mod:`hsi_torch.recon.spatial`).
        lam: relative TV weight for ``prior="tv"``: ``λ = lam · σ̂ · sqrt(median trace G)`` with
            ``σ̂`` the frame's noise level estimated from its per-pixel residuals (default
            :data:`~hsi_torch.recon.spatial.DEFAULT_LAM`), or chosen per frame: ``"auto"``
            (minimum of a Monte-Carlo SURE risk estimate) or ``"discrepancy"`` (Morozov); the
            ``lam`` used, the absolute ``λ`` and ``σ̂`` are in the result's ``stats``.
        spatial_iters: fixed iterations of the spatial solve (``None``: to tolerance).
        uncertainty: also compute the standard deviation of every band
            (:attr:`ReconstructionResult.std`, :mod:`hsi_torch.recon.uncertainty`) from
            ``noise`` (default :class:`~hsi_torch.recon.uncertainty.SensorNoise`: the
            simulator's default sensor).
        precompute_cache: for a bundle given as a path, where the per-bundle precomputation
            is cached between processes: ``"auto"`` (the user cache folder, ``$HSI_TORCH_CACHE``
            or ``~/.cache/hsi_torch``), ``"beside"`` (a ``.hsi_torch_cache`` folder beside the
            bundle), ``"off"``, or a folder; a later process with the same bundle content and
            ``(beta, diff_order, dtype, device type)`` loads it instead of factorising
            (:mod:`hsi_torch.recon.precompute_cache`).
        drift_check: measure every frame's sensor drift against the bundle's registration
            (:func:`hsi_torch.recon.drift.estimate_drift`): ``stats["drift"]``.
        refine_registration: correct the measured drift before solving
            (:func:`hsi_torch.recon.drift.corrected_sensing`); implies ``drift_check``. A drift
            the frame cannot support (too few views agree, beyond the measurable range) raises
            :class:`~hsi_torch.recon.drift.DriftError` (``drift_min_views`` in ``settings``).
        settings: all of the above at once, a
            :class:`~hsi_torch.recon.settings.ReconstructSettings` (what a run passes; e.g.
            ``ReconstructConfig(...).settings()``); the keywords are then left at their defaults.
            Either way :attr:`settings` holds them, validated.

    Example:
        >>> rec = Reconstructor("calib.npz", beta=1e4)  # doctest: +SKIP
        >>> res = rec.reconstruct_file("scene.tif")  # doctest: +SKIP
        >>> res.cube.shape, res.valid.sum(), res.timings  # doctest: +SKIP
    """

    def __init__(
        self,
        bundle: CalibrationBundle | BundleSensing | str | os.PathLike,
        *,
        beta: float = DEFAULT_BETA,
        diff_order: int = 1,
        solver: str = "active_set",
        admm_iters: int | None = None,
        device: torch.device | str | None = None,
        dtype: torch.dtype = torch.float32,
        chunk_size: int | None = None,
        min_views: int = 3,
        nan_invalid: bool = True,
        exposure_correction: bool = True,
        sat_threshold: float = 1e-3,
        prior: str = "none",
        lam: float | str = DEFAULT_LAM,
        spatial_iters: int | None = None,
        uncertainty: bool = False,
        noise: SensorNoise | None = None,
        precompute_cache: str = "auto",
        drift_check: bool = True,
        refine_registration: bool = False,
        settings: ReconstructSettings | None = None,
    ) -> None:
        given = dict(beta=beta, diff_order=diff_order, solver=solver, admm_iters=admm_iters,
                     device=device, dtype=dtype, chunk_size=chunk_size, min_views=min_views,
                     nan_invalid=nan_invalid, exposure_correction=exposure_correction,
                     sat_threshold=sat_threshold, prior=prior, lam=lam,
                     spatial_iters=spatial_iters, uncertainty=uncertainty, noise=noise,
                     precompute_cache=precompute_cache, drift_check=drift_check,
                     refine_registration=refine_registration)  # fmt: skip
        flat = {k: v for k, v in given.items() if k not in ("device", "dtype", "noise")}
        flat.update(device=None if device is None else str(device), dtype=dtype_name(dtype))
        if noise is not None:
            flat.update(noise_electrons_per_dn=noise.electrons_per_dn,
                        noise_read_e=noise.read_noise_e,
                        noise_quantization_dn=noise.quantization_dn)  # fmt: skip
        s = settings_or_keywords(settings, given, keyword_defaults(Reconstructor.__init__), flat)
        #: the settings, grouped and frozen (:class:`~hsi_torch.recon.settings.ReconstructSettings`)
        self.settings = s
        sv, pr = s.solve, s.prior
        self.prior, self.lam, self.spatial_iters = pr.kind, pr.lam, pr.spatial_iters
        if isinstance(bundle, BundleSensing):
            self.sensing = bundle.with_regularisation(sv.beta, sv.diff_order)
        else:
            self.sensing = precompute_sensing(
                bundle, beta=sv.beta, diff_order=sv.diff_order, device=sv.device,
                dtype=torch_dtype(sv.dtype), chunk_size=sv.chunk_size,
                disk_cache=sv.precompute_cache,
            )  # fmt: skip
        check_min_views(sv.min_views, self.sensing.num_views)
        self.solver = sv.solver
        self.admm_iters = sv.admm_iters
        self.chunk_size = sv.chunk_size
        self.min_views = int(sv.min_views)
        self.nan_invalid = bool(sv.nan_invalid)
        self.exposure_correction = bool(s.input.exposure_correction)
        self.sat_threshold = float(s.input.sat_threshold)
        self.uncertainty = bool(s.uncertainty.enabled)
        self.noise = sensor_noise(s)
        self.drift_check = bool(s.registration.check or s.registration.refine)
        self.refine_registration = bool(s.registration.refine)
        self._factors: dict[tuple[str, str | None, torch.dtype], Tensor] = {}

    @property
    def wavelengths_nm(self) -> Tensor:
        return self.sensing.wavelengths_nm

    def sampling_factor(self, layout: str, cfa_pattern: str | None = None) -> Tensor:
        """``(P, 3V)`` variance factor of the observations for captures made as ``layout``
        (:func:`~hsi_torch.recon.uncertainty.sampling_variance_factor`); kept per layout."""
        sens = self.sensing
        key = (layout, cfa_pattern if layout == "bayer" else None, sens.dtype)
        if key not in self._factors:
            self._factors[key] = sampling_variance_factor(
                sens.grid(), sens.sensor_size, layout, cfa_pattern)  # type: ignore[arg-type]
        return self._factors[key]

    def reconstruct_frame(
        self,
        image: Tensor,
        saturated: Tensor | None = None,
        *,
        exposure_s: float | None = None,
        cfa_pattern: str | None = None,
        source: str = "capture",
        raw_layout: str | None = None,
        bundle_corrections: bool = True,
    ) -> ReconstructionResult:
        """Reconstruct one capture.

        Args:
            image: ``(3, H, W)`` linear RGB (DN above black) or ``(1, H, W)`` Bayer mosaic
                (demosaiced bilinearly with ``cfa_pattern`` or the bundle's), sensor size.
            saturated: same shape, bool, or ``None``.
            exposure_s: the capture's exposure time (s); see :func:`exposure_scale`.
            source: name used in error messages (the file).
            raw_layout: with ``uncertainty``, how an RGB ``image`` was made from raw samples:
                ``"rgb"`` (independent samples, the default), ``"bayer"`` (bilinear demosaic
                with ``cfa_pattern``) or ``"half"`` (2 × 2 binning); a ``(1, H, W)`` mosaic is
                ``"bayer"``.
            bundle_corrections: apply the corrections the bundle's calibration applied
                (:func:`correct_frames`: veil subtracted, hot and dead pixels masked; reported
                in the statistics); ``False`` for an image already corrected.

        Returns:
            :class:`ReconstructionResult`.
        """
        self.sensing = refreshed_sensing(self.sensing, self.chunk_size)  # cache entry changed?
        sens = self.sensing
        if not isinstance(image, Tensor) or image.ndim != 3:
            raise ValueError(
                f"{source}: image must be a (3, H, W) or (1, H, W) tensor, got "
                f"{tuple(image.shape) if isinstance(image, Tensor) else type(image).__name__}"
            )
        sens.check_capture_size(image.shape, source)
        t0 = time.perf_counter()
        img = image.to(device=sens.device)
        sat = None if saturated is None else saturated.to(device=sens.device)
        pattern = cfa_pattern or sens.cfa_pattern
        img, sat = prepare_input(img, sat, pattern)
        corr: dict[str, Any] = {}
        if bundle_corrections:
            img, sat, corr = correct_frames(img, sat, sens.radiometry)
        scale = exposure_scale(exposure_s, sens.exposure_s) if self.exposure_correction else 1.0
        factor = None
        if self.uncertainty:
            layout = "bayer" if image.shape[0] == 1 else (raw_layout or "rgb")
            if layout not in RAW_LAYOUTS:
                raise ValueError(f"raw_layout must be one of {RAW_LAYOUTS}, got {raw_layout!r}")
            if layout == "bayer" and pattern is None:
                raise ValueError(f"{source}: raw_layout='bayer' needs a CFA pattern")
            factor = self.sampling_factor(layout, pattern)
        _sync(sens.device)
        t_demosaic = time.perf_counter() - t0
        drift = None
        if self.drift_check:
            t1 = time.perf_counter()
            drift = estimate_drift(sens, img, self.settings.registration.min_views)
            motion_px = drift_motion_px(sens, drift)
            if self.refine_registration and drift.refusal is not None:
                raise DriftError(f"{source}: refine_registration: {drift.refusal}")
            if self.refine_registration and drift.sensor_shift_px is not None:
                sens = corrected_sensing(sens, drift.sensor_shift_px,
                                         drift.sensor_rotation_deg or 0.0)
            t_drift = time.perf_counter() - t1
        with torch.no_grad():
            out = reconstruct_batch(
                sens, img.unsqueeze(0), None if sat is None else sat.unsqueeze(0),
                scale=None if scale == 1.0 else scale, solver=self.solver,
                admm_iters=self.admm_iters, chunk_size=self.chunk_size,
                min_views=self.min_views, nan_invalid=self.nan_invalid,
                sat_threshold=self.sat_threshold, prior=self.prior, lam=self.lam,
                spatial_iters=self.spatial_iters,
                noise=self.noise if self.uncertainty else None, sampling_factor=factor,
            )  # fmt: skip
        cube, valid, stats, t = out[:4]
        st = stats[0]
        st["exposure_scale"] = scale
        st.update(corr)
        timings = {"demosaic": t_demosaic, **t} if image.shape[0] == 1 else dict(t)
        if drift is not None:
            st["drift"] = {**drift.to_dict(), "corrected": sens is not self.sensing,
                           "sensor_motion_px": round(motion_px, 3)}
            timings["drift"] = t_drift
        timings["total"] = time.perf_counter() - t0
        std = out[4][0] if self.uncertainty else None
        return ReconstructionResult(cube[0], valid[0], sens.wavelengths_nm, st, timings, std)

    def reconstruct_capture(self, capture: Any) -> ReconstructionResult:
        """Reconstruct a :class:`hsi_torch.io.LinearCapture` (``image``, ``saturated``, the
        exposure from ``metadata``: ``exposure_s``, else the simulator's relative ``exposure``,
        compared with the bundle's white reference in the same unit; the statistics say
        ``radiometric_scale`` and ``exposure_note``, :func:`hsi_torch.recon.checks.exposure_info`).
        """
        src = str(getattr(capture, "path", "capture"))
        corr = apply_bundle_corrections(capture, self.sensing.radiometry)
        meta = capture.metadata
        layout, pattern = "rgb", None
        if meta.get("kind") == "bayer":  # demosaiced by the reader: the noise went through it
            layout = "half" if meta.get("demosaic") == "half" else "bayer"
            pattern = meta.get("cfa_pattern")
        sens = self.sensing
        try:
            t, exp_stats = exposure_info(meta, sens.radiometry, sens.exposure_s,
                                         self.exposure_correction)  # fmt: skip
            res = self.reconstruct_frame(
                capture.image, capture.saturated, exposure_s=t,
                source=src, raw_layout=layout, cfa_pattern=pattern, bundle_corrections=False,
            )  # fmt: skip
            res.stats.update(exp_stats)
            res.stats.update(corr)
            return res
        except InputError as exc:
            if "'exposure_s'" in str(exc) and getattr(capture, "path", None) is not None:
                raise FileFormatError(f"{src}: {exc}") from None  # the file's metadata at fault
            raise

    def reconstruct_file(
        self,
        path: str | os.PathLike,
        demosaic: str = "bilinear",
        *,
        cfa_pattern: str | None = None,
        black_level: float | list[float] | None = None,
        white_level: float | None = None,
        exposure_s: float | None = None,
    ) -> ReconstructionResult:
        """Read a capture (:func:`hsi_torch.io.read_any`) and reconstruct it.

        The file's full-resolution size is checked against the bundle (errors name the file):
        the sensor size, or for Bayer files read with ``demosaic="half"`` (a bundle made at half
        resolution) twice the sensor size. ``cfa_pattern``, ``black_level``, ``white_level``
        override the file's metadata; a Bayer file without a pattern gets the bundle's, a file
        without a black level the calibration's (``settings["black_level_rgb"]``), a file without
        an exposure ``exposure_s`` (s). The statistics also hold the black level used and its
        source, the pedestal outside the views, the camera and its differences from the bundle's
        (:func:`hsi_torch.recon.checks.prepare_capture`); :func:`hsi_torch.recon.checks.
        check_warnings` turns them into warnings. ``timings["load"]`` is the read (and demosaic).
        """
        if demosaic not in ("bilinear", "half"):
            raise ValueError(f"demosaic must be 'bilinear' or 'half', got {demosaic!r}")
        p = Path(path)
        sens = self.sensing
        t0 = time.perf_counter()
        cap = read_any(
            p, expected_size=sens.sensor_size if demosaic == "bilinear" else None,
            demosaic=demosaic, cfa_pattern=cfa_pattern, black_level=black_level,
            white_level=white_level, dtype=sens.dtype, device=sens.device,
            default_cfa_pattern=sens.cfa_pattern,
        )  # fmt: skip
        if demosaic == "half":
            _check_half_size(cap, sens, p)
        apply_bundle_corrections(cap, sens.radiometry)  # before the pedestal is measured
        checks = prepare_capture(cap, sens.radiometry, black_level=black_level,
                                 exposure_s=exposure_s, sensor_size=sens.sensor_size)  # fmt: skip
        _sync(sens.device)
        t_load = time.perf_counter() - t0
        res = self.reconstruct_capture(cap)
        res.timings = {"load": t_load, **res.timings}
        res.timings["total"] += t_load
        res.stats.update(checks)
        res.stats["metadata"] = cap.metadata
        return res


def apply_bundle_corrections(capture: Any, rad: BundleRadiometry | None) -> dict[str, Any]:
    """Correct a :class:`~hsi_torch.io.LinearCapture` in place as its calibration corrected the
    calibration frames (once; repeated calls return the same statistics):

    - ``stray_light: subtract`` bundles: the veil measured on the bundle's unreached sensor
      pixels is subtracted (:func:`~hsi_torch.io.sensor_corrections.subtract_veil`, per colour
      of the ``(3, H, W)`` image; a ``(1, H, W)`` mosaic is left alone);
    - ``defects: mask`` bundles: the hot and dead pixels are marked saturated, so every
      observation that samples one is dropped.

    Returns:
        Statistics: ``stray_light_veil_dn`` (the veil's mean per colour) and
        ``defect_pixels`` (pixels marked), when applied.
    """
    done = getattr(capture, "_bundle_corrections", None)
    if isinstance(done, dict):
        return done
    capture.image, capture.saturated, stats = correct_frames(capture.image, capture.saturated,
                                                             rad)
    capture._bundle_corrections = stats
    return stats


def correct_frames(
    rgb: Tensor, saturated: Tensor | None, rad: BundleRadiometry | None
) -> tuple[Tensor, Tensor | None, dict[str, Any]]:
    """The bundle's sensor corrections on tensors, as :func:`apply_bundle_corrections` does on
    captures: ``stray_light: subtract`` bundles get the veil (fitted per frame and colour on the
    bundle's unreached pixels) subtracted; ``defects: mask`` bundles get their hot and dead
    pixels marked saturated.

    Args:
        rgb: ``(3, H, W)`` or ``(B, 3, H, W)`` linear RGB (demosaiced), sensor size.
        saturated: bool mask of ``rgb``'s shape, or ``None``.
        rad: the bundle's radiometry (``None``: nothing to do).

    Returns:
        ``(rgb, saturated, stats)``: new tensors (the inputs are not modified); ``saturated``
        is created when defects are marked; ``stats`` holds ``stray_light_veil_dn`` (the
        veil's mean per colour, per frame for a batch) and ``defect_pixels``, when applied.
    """
    stats: dict[str, Any] = {}
    if rad is None:
        return rgb, saturated, stats
    if rad.veil_index is not None and rgb.shape[-3] == 3:
        rgb, info = subtract_veil(rgb, rad.veil_index)
        frames = info["frames"] if "frames" in info else [info]
        means = [[round(v, 3) for v in f["mean_dn"]] for f in frames]
        stats["stray_light_veil_dn"] = means[0] if rgb.ndim == 3 else means
    if rad.defect_index is not None and rad.defect_index.size:
        sat = (torch.zeros(rgb.shape, dtype=torch.bool, device=rgb.device) if saturated is None
               else saturated.to(torch.bool))
        H, W = sat.shape[-2:]
        flat = sat.reshape(-1, H * W).clone()
        idx = torch.as_tensor(rad.defect_index, device=sat.device, dtype=torch.long)
        flat[:, idx] = True
        saturated = flat.reshape(sat.shape)
        stats["defect_pixels"] = int(idx.numel())
    return rgb, saturated, stats


def torch_dtype(name: str) -> torch.dtype:
    """``"float32"`` / ``"float64"`` (the settings' ``dtype``) → the torch dtype."""
    return torch.float64 if name == "float64" else torch.float32


def sensor_noise(settings: ReconstructSettings) -> SensorNoise:
    """The noise model of ``settings.uncertainty`` (the simulator's default sensor's gain when
    it is not given)."""
    u = settings.uncertainty
    return SensorNoise(u.electrons_per_dn or DEFAULT_ELECTRONS_PER_DN, u.read_e, u.quantization_dn)


def _check_half_size(cap: Any, sens: BundleSensing, path: Path) -> None:
    """``demosaic="half"``: a Bayer mosaic must be exactly twice the bundle's sensor size (odd
    sizes included, which binning would silently crop); an RGB file is not binned."""
    H, W = sens.sensor_size
    if cap.mosaic is not None:
        full = tuple(int(v) for v in cap.mosaic.shape[-2:])
        if full != (2 * H, 2 * W):
            raise FileFormatError(
                f"{path}: Bayer mosaic size (H, W) = {full} does not match the calibration "
                f"bundle: with demosaic='half' it must be twice the bundle's sensor size "
                f"{(H, W)}, i.e. {(2 * H, 2 * W)}"
            )
    else:
        full = tuple(int(v) for v in cap.image.shape[-2:])
        if full != (H, W):
            raise FileFormatError(
                f"{path}: RGB image size (H, W) = {full} does not match the calibration bundle's "
                f"sensor size {(H, W)} (demosaic='half' bins Bayer mosaics only)"
            )
