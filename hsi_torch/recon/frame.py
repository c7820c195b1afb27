"""One frame of a reconstruction, all pixels at once: sample the views, build the observations and
masks, solve, assemble (:func:`reconstruct_frame`; no per-pixel Python).

1. **Warp** (:func:`sample_views`): the linear RGB capture ``(3, H, W)`` and its saturation mask
   are stacked into six channels and sampled at the bundle's precomputed sensor positions of every
   valid pixel in every view (:attr:`BundleSensing.sample_grid`, ``(1, V, P, 2)``) by *one*
   batched kornia call (``kornia.geometry.transform.remap``, bilinear, ``align_corners=True``,
   zero padding) → ``(B, 6, V, P)``. This equals the full-frame warp
   (:func:`hsi_torch.optics.geometry.warp_views`, kornia ``warp_perspective``) at the valid pixels,
   without warping the invalid ones (tested). A sample is *saturated* when any saturated sensor
   sample contributes to its bilinear footprint (warped weight ``> sat_threshold``, default
   ``1e-3``: weights that are 0 up to rounding of the homography do not count).
2. **Observations** (:func:`observations_from_samples`): ``y (P, 3V)`` view-major
   (``o = 3v + c``) and the frame mask = static mask (view present and modulated,
   outside-triangle excluded) ∧ not saturated ∧ finite. ``y`` is multiplied by the exposure ratio
   ``t_white / t_capture`` when both are known (the bundle's response was calibrated at the white
   reference's exposure ``t_white``; see :func:`hsi_torch.recon.checks.exposure_scale`).
3. **Solve** (:func:`solve_observations`): the precomputed factorisation
   (:class:`~hsi_torch.recon.sensing.BundleSensing`) solves every pixel for the static mask; pixels
   whose frame mask differs (saturation, non-finite data) are re-solved *exactly* with their own
   mask (``solve_nnls`` on that sub-batch only). Pixels left with fewer than ``min_views`` (3)
   views that still have an observation are invalid: NaN in the cube (or 0 with
   ``nan_invalid=False``) and ``False`` in ``valid``. The frame's fit residual
   ``‖W(A s − y)‖ / ‖W y‖`` (median over a fixed sample of valid pixels) flags a bundle that does
   not belong to the capture.
4. **Assemble**: ``cube (M, h, w)``, ``valid (h, w)``.

Every choice (solver, ``min_views``, prior, ...) comes from one
:class:`~hsi_torch.recon.settings.ReconstructSettings`, passed whole.

Gradients (used by :class:`~hsi_torch.recon.pipeline.HSIReconstructor`): the active-set solver (and
tolerance-driven ADMM) run without autograd; when the input requires grad, the answer is passed
through one differentiable *reduced solve* on its free set ``F = {m : x_m > 0}``:
``x_F = G_FF⁻¹ (Aᵀ W y)_F``, ``x_Z = 0`` — the exact derivative of the NNLS solution wherever the
free set is locally constant. The forward value stays the solver's answer (straight-through
form). Fixed-iteration ADMM (``admm_iters=N``) is differentiated through its iterations.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import torch
from torch import Tensor

from hsi_torch.errors import InputError
from hsi_torch.io.raw import demosaic_bilinear, demosaic_saturation, validate_cfa_pattern
from hsi_torch.recon import _compiled as _frame_compiled
from hsi_torch.recon.nnls import cpu_threads, solve_nnls
from hsi_torch.recon.sensing import BundleSensing, sample_pixels
from hsi_torch.recon.settings import ReconstructSettings
from hsi_torch.recon.spatial import noise as spatial_noise
from hsi_torch.recon.spatial import solve_frame as spatial_solve_frame
from hsi_torch.recon.spatial.admm import CHECK_EVERY as SPATIAL_CHECK_EVERY
from hsi_torch.recon.uncertainty import (
    DEFAULT_ELECTRONS_PER_DN,
    SensorNoise,
    nnls_band_std,
    observation_variance,
)

__all__ = [
    "FrameOutput",
    "WarmStart",
    "reconstruct_frame",
    "sample_views",
    "observations_from_samples",
    "solve_observations",
    "assemble_cube",
    "fit_residual",
    "prepare_input",
    "check_min_views",
    "sensor_noise",
    "FIT_RESIDUAL_SAMPLES",
]

#: Pixels (evenly spaced over the bundle's valid pixels) on which the fit residual is evaluated.
FIT_RESIDUAL_SAMPLES = 4096


@dataclass
class WarmStart:
    """The solver state one frame hands the next (a sequence of captures of one bundle).

    Passed to :func:`solve_observations` / :func:`reconstruct_frame` (one frame at a time), it
    is read as the start of the solves and then overwritten with this frame's state. The
    answers do not depend on it beyond the solvers' tolerances: the active-set method ends at
    the same KKT point from any start, the spatial ADMM at the same optimum to its tolerance.

    Attributes:
        per_pixel: start the active-set solve of the pixels that pivot from the zero set of
            ``x`` (the previous frame's per-pixel solution) instead of the solver's own start.
        spatial: start the spatial prior's ADMM from the previous frame's state on the pixels
            whose observations stayed still (:func:`_moved_pixels`, which also measures the
            frame's gain ``g``): its answer ``spatial_x`` and scaled dual ``spatial_u``, both
            times ``g``; the TV prox from ``spatial_dual``; the stopping rule checked every
            :data:`WARM_CHECK_EVERY` iterations (the same rule and tolerance as cold). The
            per-pixel problem is then solved only where its answer is used: the moved pixels
            (their ADMM start and multiplier), the noise estimate's
            :data:`~hsi_torch.recon.spatial.noise.NOISE_SAMPLES` pixels (so ``σ̂`` and ``λ``
            are the cold solve's) and the pixels whose mask changed.
        reuse_noise: with ``spatial``, a frame whose gain against the previous one
            (:func:`_moved_pixels`) is within :data:`NOISE_REUSE_GAIN` of 1 (the same exposure
            and light) reuses the previous frame's noise level ``σ̂`` and so its ``λ`` instead of
            estimating them again (``stats["noise_sigma_given"]``): the answer is then the
            optimum of the problem with the previous frame's ``λ``, not this frame's own.
        x: ``(P, M)`` the last per-pixel solution, kept with ``per_pixel`` (``None`` before
            the first frame, and after a frame whose per-pixel solve skipped its static
            pixels).
        spatial_x: ``(P, M)`` the last spatial answer; spatial_dual: its TV prox dual;
            spatial_u: ``(P, M)`` its ADMM scaled dual (``None`` where the solve had none).
        y: ``(P, 3V)`` the last frame's observations (DN, 0 where masked) and ``mask`` their
            ``(P, 3V)`` frame mask: with ``spatial``, the next frame tells its moved pixels and
            its gain from them (:func:`_moved_pixels`) and solves the per-pixel problem only on
            the moved pixels, the noise estimate's samples and the pixels whose mask changed.
        workspace: the spatial ADMM's frame-sized buffers, kept from frame to frame
            (:func:`~hsi_torch.recon.spatial.admm.solve_spatial`'s ``workspace``).
    """

    per_pixel: bool = True
    spatial: bool = True
    x: Tensor | None = None
    spatial_x: Tensor | None = None
    spatial_dual: tuple | None = None
    spatial_u: Tensor | None = None
    reuse_noise: bool = False
    spatial_sigma: float | None = None
    sigma_gain: float = 1.0
    y: Tensor | None = None
    mask: Tensor | None = None
    workspace: dict = field(default_factory=dict)

    def reset(self) -> None:
        """Forget the state (the next frame starts cold)."""
        self.x = self.spatial_x = self.spatial_dual = self.spatial_u = None
        self.y = self.mask = None
        self.workspace = {}
        self.spatial_sigma, self.sigma_gain = None, 1.0



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



def sample_views(
    sens: BundleSensing, images: Tensor, saturated: Tensor | None = None
) -> tuple[Tensor, Tensor | None]:
    """Sample every view of ``(B, 3, H, W)`` images (and masks) at the bundle's valid pixels.

    One ``kornia.geometry.transform.remap`` call (bilinear, zero padding, ``align_corners=True``)
    on the stacked image and saturation channels with the per-bundle grid
    :meth:`BundleSensing.grid` ``(1, V, P, 2)``.

    Returns:
        ``(B, 3, V, P)`` values and ``(B, 3, V, P)`` saturation weights in [0, 1] (``None``
        without a mask). Equal to the full-frame warp of every view at ``sens.pixel_index``.
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
        ``saturated (B, P, 3V)`` bool (within the static mask).
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
    x_start: Tensor | None = None,
    select: Callable[[Tensor, Tensor, Tensor], Tensor | None] | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, int]:
    """The per-pixel part of :func:`solve_observations`: the valid and changed pixels, the
    masked ``y``, the prepared problem's solve and the exact re-solves of the changed pixels.
    ``threads``: the solver's CPU threads (torch's own count is lowered to 1 around this call).
    Returns ``ok``, ``changed``, ``yc``, ``x``, ``converged``, ``kkt``, ``iterations``, the
    number re-solved. ``x_start``: the frame solve's warm start (``problem.solve``'s ``x0``).
    ``select(ok, changed, yc)``: the ``(n,)`` pixels to solve (the changed ones among them), or
    ``None`` for all; the others are solved for zero observations, so left at ``x = 0``
    (converged, no pivoting; their answer is not used)."""
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
    rows = None if select is None else select(ok, changed, yc)
    if rows is None:
        res = sens.problem.solve(yc, x0=x_start, **kw)
    else:
        # a subset: the frame's solve with the other pixels' observations zeroed (their answer
        # is 0 at once, without pivoting), not a gathered copy of the subset's stored Gram
        # matrices and factors (on a mapped precomputation cache, gathering them cost more than
        # the whole frame's solve)
        keep = torch.zeros(P, dtype=yc.dtype, device=yc.device).index_fill_(0, rows, 1.0)
        res = sens.problem.solve(yc * keep.unsqueeze(1), **kw)
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



#: The spatial warm start keeps the previous frame's answer on the pixels whose observations
#: changed by at most this many times the frame's median change (the static ones,
#: :func:`_moved_pixels`).
STATIC_CHANGE_FACTOR = 4.0

#: Iterations between two checks of the spatial ADMM's stopping rule when warm-started (cold:
#: :data:`hsi_torch.recon.spatial.admm.CHECK_EVERY`): a start near the optimum meets the rule
#: in a few iterations.
WARM_CHECK_EVERY = 1

#: The spatial ADMM's over-relaxation when warm-started (:func:`~hsi_torch.recon.spatial.
#: solve_spatial`'s ``relax``; cold solves: none). On the full-size moving scene (30 frames) the
#: warm frames met the stopping rule in 5 iterations on every frame (unrelaxed: 6–7) and scored
#: −0.029 … −0.001 dB against their cold solves (1.3: 5–6 iterations, −0.027 … +0.015 dB; 1.5:
#: 4–5 iterations, down to −0.049 dB, at the 0.05 dB bound; 1.8: worse, −0.135 dB).
WARM_RELAX = 1.4

#: ``reuse_noise``: the previous frame's noise level is reused when the frame's gain against it
#: is within this of 1.
NOISE_REUSE_GAIN = 0.1

#: The moved test of :func:`_moved_pixels` takes its medians over at most this many valid pixels
#: (evenly spaced).
START_SAMPLES = 16384


def _moved_pixels(y: Tensor, mask: Tensor, prev_y: Tensor, prev_mask: Tensor,
                  ok: Tensor) -> tuple[Tensor, float]:
    """Which pixels moved since the previous frame, from the observations alone (before any
    solve), and the frame's gain against it.

    The gain ``g = Σy / Σy'`` over the observations used in both frames of up to
    :data:`START_SAMPLES` evenly spaced valid pixels (``y'`` the previous frame's: a change of
    the light or exposure scales every observation by the same factor, and sums average the
    noise out). A pixel's change is ``c_p = ‖y − g y'‖²`` (both 0 where masked); it has *moved*
    when ``c_p`` exceeds :data:`STATIC_CHANGE_FACTOR` × the median change over the valid pixels,
    or when its mask changed. The change is not divided by the pixel's own noise level: the
    bright pixels, whose shot noise is largest, are then mostly "moved" and start from their
    own per-pixel answers (started from the previous answer instead, the bright pixels' answers
    lagged the data: on the full-size moving scene the frames scored 0.02-0.045 dB below their
    cold solves, against +0.03-0.046 dB with this rule).

    Args:
        y, mask: ``(P, 3V)`` this frame's observations (0 where masked) and mask; prev_y,
            prev_mask: the previous frame's; ok: ``(P,)`` this frame's valid pixels.

    Returns:
        ``moved (P,)`` bool (valid pixels only) and ``g``.
    """
    idx = ok.nonzero().squeeze(1)
    if idx.numel() == 0:
        return torch.zeros_like(ok), 1.0
    prev_y = prev_y.to(y)
    # the gain on a sample of the valid pixels (tens of thousands of observations: the noise
    # averages out), over the observations used in both frames
    sample = idx[:: max(1, idx.numel() // START_SAMPLES)]
    both = mask.index_select(0, sample) & prev_mask.index_select(0, sample)
    den = float((prev_y.index_select(0, sample) * both).sum(dtype=torch.float64))
    g = float((y.index_select(0, sample) * both).sum(dtype=torch.float64)) / den if den > 0 else 1.0
    g = g if math.isfinite(g) and g > 0 else 1.0
    # y and y' are 0 where their own masks are False: a pixel whose mask changed is moved anyway
    c = torch.add(y, prev_y, alpha=-g).square_().sum(1)
    moved = ok & ((c > STATIC_CHANGE_FACTOR * c[sample].median()) | (mask != prev_mask).any(1))
    return moved, g


def solve_observations(
    sens: BundleSensing,
    y: Tensor,
    mask: Tensor,
    settings: ReconstructSettings,
    *,
    premasked: bool = False,
    stats: bool = True,
    warm: WarmStart | None = None,
) -> tuple[Tensor, Tensor, dict[str, Any]]:
    """Solve one frame's ``P`` pixels with the precomputed factorisation (+ exact re-solves).

    Args:
        y: ``(P, 3V)`` observations (DN, exposure-corrected); may hold NaN where ``mask`` is False.
        mask: ``(P, 3V)`` bool frame mask.
        settings: the solver (``solve.solver``, ``admm_iters``: fixed ADMM iterations,
            differentiable; ``chunk_size``), ``solve.min_views`` (views with ≥ 1 usable colour a
            pixel needs to stay valid) and the prior (``prior.kind``: ``"none"``, per-pixel
            NNLS, or ``"tv"``: the per-pixel answer warm-starts the spatial-spectral solve,
            :func:`hsi_torch.recon.spatial.solve_frame`, over the valid pixels; ``info`` gains
            its ``lam``, ``lam_abs``, ``noise_sigma``, iterations and residuals, and KKT
            statistics stay those of the per-pixel warm start; ``prior.lam``: the relative TV
            weight; ``prior.spatial_iters``: fixed spatial ADMM iterations, differentiable;
            ``None``: to tolerance, not differentiable).
        premasked: ``y`` is already 0 wherever ``mask`` is False (and in ``sens.dtype``): used
            as is, without a masked copy.
        stats: compute ``info`` (host syncs: counts, KKT statistics, fit residual); ``False``:
            ``info`` is empty and only the solve's own control flow reads the device.
        warm: the previous frame's state (:class:`WarmStart`): read as the solves' start,
            then replaced by this frame's.

    Returns:
        ``x (P, M)`` (0 where invalid), ``ok (P,)`` bool, ``info`` (counts, KKT statistics).
    """
    sv, pr = settings.solve, settings.prior
    solver, admm_iters, min_views = sv.solver, sv.admm_iters, sv.min_views
    P, O = y.shape
    V = O // 3
    zero = torch.zeros((), dtype=y.dtype, device=y.device)
    # the per-pixel solve and its bookkeeping: single-threaded torch kernels on CPU, as in the
    # solver (a multi-threaded element-wise kernel waits at its barrier for a core another
    # process holds; the compiled pass has its own threads)
    threads = torch.get_num_threads()
    M = sens.num_bands
    prior = pr.kind
    grad_in = torch.is_grad_enabled() and y.requires_grad
    # the spatial warm start: the per-pixel solve only where the previous state does not do
    spatial_warm = (
        prior == "tv" and warm is not None and warm.spatial and warm.spatial_x is not None
        and warm.y is not None and warm.mask is not None and not grad_in
        and pr.spatial_iters is None and not isinstance(pr.lam, str)
        and (pr.spectral_rank is None or int(pr.spectral_rank) >= M)
        and warm.y.shape == y.shape and warm.mask.shape == mask.shape
        and warm.spatial_x.shape == (P, M)
    )  # fmt: skip
    moved_gain: list[tuple[Tensor, float, int]] = []
    select = None
    if spatial_warm:
        assert warm is not None and warm.y is not None and warm.mask is not None

        def select(ok: Tensor, changed: Tensor, yc: Tensor) -> Tensor:
            moved, g = _moved_pixels(yc, mask, warm.y, warm.mask, ok)
            moved |= changed
            need = moved.clone()
            samples = sample_pixels(ok, spatial_noise.NOISE_SAMPLES)  # the noise estimate's
            if samples is not None:
                need[samples] = True
            rows = need.nonzero().squeeze(1)
            moved_gain.append((moved, g, int(rows.numel())))
            return rows

    if (warm is not None and warm.per_pixel and warm.x is not None and select is None
            and warm.x.shape == (P, M) and not grad_in):
        x_start = warm.x.to(device=y.device, dtype=sens.dtype)
    else:
        x_start = None
    with cpu_threads(y.device, 1):
        ok, changed, yc, x, conv, kkt, iters, n_changed = _solve_per_pixel(
            sens, y, mask, V, min_views, premasked, solver, admm_iters, sv.chunk_size, threads,
            x_start, select)
    if warm is not None:  # a per-pixel start only where every pixel was solved
        warm.x = x.detach().clone() if warm.per_pixel and not moved_gain else None
    native_grad = solver == "admm" and admm_iters is not None
    grad = torch.is_grad_enabled() and yc.requires_grad
    sinfo: dict[str, Any] = {}
    if prior == "tv":
        if grad and pr.spatial_iters is None:
            raise ValueError("prior='tv' with gradients needs spatial_iters=N (fixed, "
                             "differentiable iterations)")
        start, dual, u0, keep, check, sigma = None, None, None, None, SPATIAL_CHECK_EVERY, None
        relax = 1.0
        if moved_gain:
            assert warm is not None and warm.spatial_x is not None
            moved, gain, n_solved = moved_gain[0]
            keep = ok & ~moved
            start = torch.where(keep.unsqueeze(1), gain * warm.spatial_x.to(x), x)
            dual, check, relax = warm.spatial_dual, WARM_CHECK_EVERY, WARM_RELAX
            if warm.spatial_u is not None and warm.spatial_u.shape == x.shape:
                u0 = gain * warm.spatial_u.to(x)
            if warm.reuse_noise and abs(warm.sigma_gain * gain - 1.0) <= NOISE_REUSE_GAIN:
                sigma = warm.spatial_sigma
        x, sinfo = spatial_solve_frame(sens, yc, mask, ok, changed, x, lam=pr.lam,
                                       iters=pr.spatial_iters, rank=pr.spectral_rank,
                                       start=start, dual=dual, u0=u0,
                                       u0_mask=None if u0 is None else keep, check_every=check,
                                       sigma=sigma, relax=relax,
                                       workspace=(sens.spatial_workspace if warm is None
                                                  else warm.workspace))
        sdual = sinfo.pop("spatial_dual", None)
        su = sinfo.pop("spatial_u", None)
        if warm is None:  # the answer's dual and u are not kept: buffers of the next solve
            _return_buffers(sens.spatial_workspace, sdual, su)
        else:
            warm.spatial_x, warm.spatial_dual, warm.spatial_u = x.detach().clone(), sdual, su
            if warm.spatial and not grad:  # the next frame's moved test
                warm.y, warm.mask = yc.detach().clone(), mask.clone()
            if sigma is None:  # estimated on this frame
                warm.spatial_sigma, warm.sigma_gain = sinfo.get("noise_sigma"), 1.0
            else:
                warm.sigma_gain *= gain
        if start is not None:
            sinfo["spatial_warm_static"] = int(torch.count_nonzero(keep))
            sinfo["spatial_warm_gain"] = gain
            sinfo["per_pixel_solved"] = n_solved
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



def _return_buffers(workspace: dict, dual: tuple | None, u: Tensor | None) -> None:
    """Hand a finished spatial solve's TV dual ``(p, psum)`` and scaled dual ``u`` (the compiled
    backend's band-major arrays; ``u`` as their transposed view) to ``workspace`` as the next
    solve's buffers (the solve takes only those of its layout, shape and dtype)."""
    if dual is not None:
        workspace["p"], workspace["psum"] = dual
    if u is not None and u.device.type == "cpu":
        workspace["u"] = u.detach().numpy().T


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



class FrameOutput(NamedTuple):
    """What :func:`reconstruct_frame` returns for a batch of ``B`` frames.

    Attributes:
        cube: ``(B, M, h, w)`` (NaN or 0 where invalid); valid: ``(B, h, w)`` bool.
        stats: one dict of statistics per frame (empty without ``stats``).
        timings: seconds per stage, summed over the batch (empty without ``stats``).
        std: ``(B, M, h, w)`` standard deviation of every band with ``uncertainty`` on, else
            ``None``.
    """

    cube: Tensor
    valid: Tensor
    stats: list[dict[str, Any]]
    timings: dict[str, float]
    std: Tensor | None = None


def reconstruct_frame(
    sens: BundleSensing,
    images: Tensor,
    settings: ReconstructSettings,
    saturated: Tensor | None = None,
    *,
    scale: Tensor | float | None = None,
    stats: bool = True,
    sampling_factor: Tensor | None = None,
    warm: WarmStart | None = None,
) -> FrameOutput:
    """Frames → cubes: the one frame function of :class:`~hsi_torch.recon.pipeline.Reconstructor`
    and :class:`~hsi_torch.recon.pipeline.HSIReconstructor`.

    Args:
        sens: the bundle's precomputation (β and the difference order are its own).
        images: ``(B, 3, H, W)`` linear RGB on ``sens.device`` (cast to ``sens.dtype``).
        settings: the solve (``solver``, ``admm_iters``, ``chunk_size``, ``min_views``,
            ``nan_invalid``), the prior, ``input.sat_threshold`` and, with
            ``uncertainty.enabled``, the sensor's noise model (:func:`sensor_noise`).
        saturated: ``(B, 3, H, W)`` bool or ``None``.
        scale: scalar or ``(B,)`` factor on the observations (exposure correction).
        stats: per-frame statistics and stage timings (each stage ends with a device sync);
            ``False`` (the ``nn.Module``): no timing, no statistics, no extra sync.
        sampling_factor: with uncertainty, the ``(P, 3V)`` variance factor of the observations
            (:func:`~hsi_torch.recon.uncertainty.sampling_variance_factor`; ``None``: 1).
        warm: the solver state of the previous frame (:class:`WarmStart`, a sequence), read and
            replaced by this frame's; with a batch of several frames they are solved in order,
            each starting from the one before.

    Returns:
        :class:`FrameOutput`.
    """
    sv = settings.solve
    min_views, nan_invalid = sv.min_views, sv.nan_invalid
    noise = sensor_noise(settings) if settings.uncertainty.enabled else None
    dev = sens.device
    if images.device != dev:
        raise ValueError(f"input is on {images.device} but the bundle tensors are on {dev}")
    _check_scale(scale, images.shape[0])
    if images.shape[0] == 0:  # an empty batch: empty outputs of the right shapes
        h, w = sens.frame_size
        cube = images.new_empty((0, sens.num_bands, h, w), dtype=sens.dtype)
        return FrameOutput(cube, torch.zeros((0, h, w), dtype=torch.bool, device=dev), [], {})
    t: dict[str, float] = {}
    clock = _Clock(dev, stats)
    t0 = clock()
    imgs = images.to(sens.dtype)
    if saturated is not None and not bool(saturated.any()):
        saturated = None  # nothing saturated: the mask channels would sample to 0 everywhere
    samples, wsat = sample_views(sens, imgs, saturated)
    t1 = clock()
    t["warp"] = t1 - t0
    y, mask, sat = observations_from_samples(sens, samples, wsat, settings.input.sat_threshold)
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
        x, ok, info = solve_observations(sens, y[i], mask[i], settings, premasked=inplace,
                                         stats=stats, warm=warm)  # fmt: skip
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
        return FrameOutput(cube, valid, infos, t if stats else {})
    std_cube, _ = assemble_cube(sens, torch.stack(stds), torch.stack(oks), nan_invalid)
    return FrameOutput(cube, valid, infos, t if stats else {}, std_cube)



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



def sensor_noise(settings: ReconstructSettings) -> SensorNoise:
    """The noise model of ``settings.uncertainty`` (the simulator's default sensor's gain when
    it is not given)."""
    u = settings.uncertainty
    return SensorNoise(u.electrons_per_dn or DEFAULT_ELECTRONS_PER_DN, u.read_e, u.quantization_dn)
