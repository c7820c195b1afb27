"""Corrections of a frame that the optics and the sensor make outside the forward model: the
veil of stray light, and hot and dead pixels.

**Stray light.** Light scattered inside the kaleidoscope and the objective adds a smooth veil over
the whole sensor, also over the tiles that no view reaches. Those tiles are the only place where
the veil is seen alone, so :func:`estimate_veil` measures it there (the flat indices of
:func:`~hsi_torch.io.radiometry.outside_views_index`): the samples are binned into blocks
(robust mean per block and colour), and a smooth surface is fitted through the blocks and
extrapolated under the views: ``exp`` of a quadratic in the normalised sensor coordinates (a
Gaussian-like glare of any centre, width and tilt), or a constant when the blocks do not hold a
clearly positive veil (too few, or a constant fits them as well). :func:`subtract_veil` removes
it. The veil must be removed from the calibration frames (white, scan, grid) and from the scene
captures alike: calibration does the first (``stray_light: auto``, the default, when the veil
measured on the white is above a threshold; ``subtract`` always) and records it in the bundle, so
reconstruction with that bundle does the second.

**Hot and dead pixels.** :func:`find_defects` flags hot pixels (far above the dark frame's
level) and dead pixels (far below their neighbours in a white frame, where it is lit), dilated by
the demosaic's footprint. Calibration ``defects: auto`` (the default: when any is found) or
``mask`` writes them into the bundle; a
reconstruction with that bundle drops every observation that samples one of them, as it drops
saturated samples.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

__all__ = ["estimate_veil", "subtract_veil", "find_defects", "dilate_mask", "unreached_index",
           "VEIL_BLOCKS"]

#: blocks along the sensor's longer side in which the unreached samples are averaged
VEIL_BLOCKS = 24


def unreached_index(
    white: torch.Tensor, outside_index: Any, *, dark_fraction: float = 0.05, margin_px: float = 8.0
) -> np.ndarray:
    """The samples of ``outside_index`` that no light reaches, judged on a white frame.

    The bundle's views are not every tile the kaleidoscope lights (reflections of higher order
    light tiles around them), so the geometric outside of the views is refined by the white
    frame: a sensor pixel is lit where the white's colour sum reaches ``dark_fraction`` of its
    99th percentile; the lit area is dilated by ``margin_px`` (the diffuser's and the demosaic's
    blur at the tiles' edges) and the samples outside it are kept.

    Args:
        white: ``(C, H, W)`` white frame above black (DN).
        outside_index: ``(K,)`` flat indices outside every view
            (:func:`~hsi_torch.io.radiometry.outside_views_index`).

    Returns:
        ``(K',)`` int64 flat indices (a subset of ``outside_index``).
    """
    if white.ndim != 3:
        raise ValueError(f"white must be (C, H, W), got {tuple(white.shape)}")
    s = torch.nan_to_num(white.to(torch.float32)).sum(0)
    sample = s.reshape(-1)[:: max(1, s.numel() // 1_000_000)]
    lit = s >= dark_fraction * float(torch.quantile(sample, 0.99))
    m = max(0, int(math.ceil(margin_px)))
    if m > 0:  # a square dilation, separable: two 1-D max-pools
        x = F.max_pool2d(lit[None, None].float(), (1, 2 * m + 1), stride=1, padding=(0, m))
        lit = F.max_pool2d(x, (2 * m + 1, 1), stride=1, padding=(m, 0))[0, 0] > 0
    idx = np.asarray(outside_index, dtype=np.int64).ravel()
    dark = ~lit.reshape(-1).cpu().numpy()
    return idx[dark[idx]]


def _robust_mean(x: np.ndarray) -> float:
    med = float(np.median(x))
    mad = float(np.median(np.abs(x - med)))
    keep = np.abs(x - med) <= 5.0 * 1.4826 * mad + 1.0
    return float(x[keep].mean())


def estimate_veil(
    image: torch.Tensor, outside_index: Any, *, blocks: int = VEIL_BLOCKS, min_samples: int = 8
) -> tuple[torch.Tensor, dict[str, Any]]:
    """The smooth veil of each colour of ``image``, measured where no view reaches.

    Args:
        image: ``(C, H, W)`` frame above black (DN; dark-subtracted where available).
        outside_index: ``(K,)`` flat row-major indices of sensor pixels no view reaches
            (:func:`~hsi_torch.io.radiometry.outside_views_index`).
        blocks: blocks along the longer side; a block with fewer than ``min_samples`` samples
            is left out.

    Returns:
        ``(veil, info)``: ``veil`` ``(C, H, W)`` in ``image``'s dtype and device (zeros when the
        index holds fewer than 6 usable blocks); ``info``: per colour ``model``
        (``"exp-quadratic"``, ``"constant"`` or ``"none"``), ``mean_dn`` (the veil's mean over
        the sensor), ``blocks`` used, ``rms_dn`` (fit residual over the blocks) and
        ``shape_gain`` (the constant's squared residual over the shaped fit's, ≥ 1; ≈ 1 for a
        flat offset, whose shaped fit only takes its 5 extra parameters' share of the noise).
    """
    if image.ndim != 3:
        raise ValueError(f"image must be (C, H, W), got {tuple(image.shape)}")
    C, H, W = image.shape
    idx = np.asarray(outside_index, dtype=np.int64).ravel()
    veil = torch.zeros_like(image)
    info: dict[str, Any] = {"model": [], "mean_dn": [], "blocks": [], "rms_dn": [],
                            "shape_gain": []}  # fmt: skip
    if idx.size == 0:
        info["model"] = ["none"] * C
        info["mean_dn"] = [0.0] * C
        return veil, info
    ys, xs = np.divmod(idx, W)
    bs = max(1, math.ceil(max(H, W) / blocks))
    bid = (ys // bs) * (W // bs + 1) + xs // bs
    order = np.argsort(bid, kind="stable")
    bid_s = bid[order]
    starts = np.flatnonzero(np.r_[True, bid_s[1:] != bid_s[:-1]])
    ends = np.r_[starts[1:], bid_s.size]
    sel = [(s, e) for s, e in zip(starts, ends, strict=True) if e - s >= min_samples]
    vals = image.detach().reshape(C, -1)[:, torch.as_tensor(idx, device=image.device)]
    vals = torch.nan_to_num(vals.to(torch.float64)).cpu().numpy()[:, order]
    yy = ys[order].astype(np.float64)
    xx = xs[order].astype(np.float64)
    # block centres in normalised coordinates (-1 … 1)
    cx = np.array([xx[s:e].mean() for s, e in sel]) / max(W - 1, 1) * 2 - 1
    cy = np.array([yy[s:e].mean() for s, e in sel]) / max(H - 1, 1) * 2 - 1
    n = np.array([e - s for s, e in sel], dtype=np.float64)
    design = np.stack([np.ones_like(cx), cx, cy, cx * cx, cx * cy, cy * cy], 1)
    gy = torch.linspace(-1, 1, H, dtype=torch.float64)[:, None]
    gx = torch.linspace(-1, 1, W, dtype=torch.float64)[None, :]
    full = [torch.ones(H, W, dtype=torch.float64), gx.expand(H, W), gy.expand(H, W),
            (gx * gx).expand(H, W), gx * gy, (gy * gy).expand(H, W)]
    for c in range(C):
        if len(sel) < 6:
            info["model"].append("none")
            info["mean_dn"].append(0.0)
            info["blocks"].append(len(sel))
            info["rms_dn"].append(float("nan"))
            info["shape_gain"].append(1.0)
            continue
        m = np.array([_robust_mean(vals[c, s:e]) for s, e in sel])
        const = max(0.0, float((n * m).sum() / n.sum()))
        sse_const = float((n * (m - const) ** 2).sum())
        model, surf, gain = "constant", None, 1.0
        pos = m > 0
        if pos.mean() >= 0.8 and pos.sum() >= 6:
            w = np.sqrt(n[pos] * m[pos])
            coef, *_ = np.linalg.lstsq(design[pos] * w[:, None], np.log(m[pos]) * w, rcond=None)
            pred = np.exp(np.clip(design @ coef, -50, math.log(2.0 * m.max() + 1e-12)))
            sse = float((n * (m - pred) ** 2).sum())
            gain = min(sse_const / sse, 1e6) if sse > 0 else 1e6
            if sse < sse_const:
                model = "exp-quadratic"
                expo = sum(float(k) * f for k, f in zip(coef, full, strict=True))
                surf = torch.exp(expo.clamp(max=math.log(2.0 * m.max() + 1e-12)))
                rms = math.sqrt(sse / n.sum())
        if surf is None:
            surf = torch.full((H, W), const, dtype=torch.float64)
            rms = math.sqrt(sse_const / n.sum())
        veil[c] = surf.to(device=image.device, dtype=image.dtype)
        info["model"].append(model)
        info["mean_dn"].append(float(surf.mean()))
        info["blocks"].append(len(sel))
        info["rms_dn"].append(rms)
        info["shape_gain"].append(gain)
    return veil, info


def subtract_veil(
    image: torch.Tensor, outside_index: Any, **kwargs: Any
) -> tuple[torch.Tensor, dict[str, Any]]:
    """``image − veil`` (:func:`estimate_veil`, same keywords) and the estimate's ``info``.

    A ``(…, 3, H, W)``/``(…, 1, H, W)`` batch is corrected frame by frame; a 1-channel mosaic
    should be demosaiced first (the veil is fitted per channel).
    """
    if image.ndim == 3:
        veil, info = estimate_veil(image, outside_index, **kwargs)
        return image - veil, info
    flat = image.reshape(-1, *image.shape[-3:])
    outs, infos = [], []
    for fr in flat:
        o, i = subtract_veil(fr, outside_index, **kwargs)
        outs.append(o)
        infos.append(i)
    return torch.stack(outs).reshape(image.shape), {"frames": infos}


def _local_kth(x: torch.Tensor, size: int, k: int, rows: int = 128) -> torch.Tensor:
    """``k``-th smallest value (1-based) of the ``size × size`` window around each pixel of
    ``(H, W)`` (edge-replicated), computed in bands of ``rows`` rows."""
    H, W = x.shape
    r = size // 2
    xp = F.pad(x[None, None], (r, r, r, r), mode="replicate")[0, 0]
    out = torch.empty_like(x)
    for r0 in range(0, H, rows):
        r1 = min(H, r0 + rows)
        patches = xp[r0:r1 + 2 * r].unfold(0, size, 1).unfold(1, size, 1)  # (rows, W, s, s)
        out[r0:r1] = patches.reshape(r1 - r0, W, size * size).kthvalue(k, -1).values
    return out


def find_defects(
    dark: torch.Tensor | None,
    white: torch.Tensor | None,
    *,
    hot_sigma: float = 10.0,
    dead_ratio: float = 0.5,
    lit_fraction: float = 0.05,
    dilate_px: int = 1,
) -> torch.Tensor:
    """Hot and dead pixels of a sensor, from its dark and white frames.

    Args:
        dark: ``(C, H, W)`` mean dark frame above black (DN) or ``None``: a pixel is hot where a
            colour reads more than ``median + hot_sigma · σ`` (σ = 1.4826·MAD over the frame,
            at least 1 DN) and is the maximum of its 3 × 3 neighbours.
        white: ``(C, H, W)`` mean white frame above dark (DN) or ``None``: a pixel is dead
            where a colour is the minimum of its 3 × 3 neighbours and reads less than
            ``dead_ratio`` times the lower quartile of its 5 × 5 window, where that quartile is
            at least ``lit_fraction`` of the frame's 99th percentile (tile edges, where half
            the window is dark, are not taken), and whose other 3 × 3 neighbours all read at
            least a quarter of that quartile (a tile's corner, a colour's own edge are not
            taken: their dark samples come in groups).
        dilate_px: the flags are dilated by this many px (a bilinear demosaic spreads one raw
            sample over its 3 × 3 neighbours).

    Returns:
        ``(H, W)`` bool on the frames' device.
    """
    ref = dark if dark is not None else white
    if ref is None:
        raise ValueError("find_defects needs a dark or a white frame")
    if ref.ndim != 3:
        raise ValueError(f"frames must be (C, H, W), got {tuple(ref.shape)}")
    C, H, W = ref.shape
    bad = torch.zeros(H, W, dtype=torch.bool, device=ref.device)
    if dark is not None:
        for c in range(C):
            d = torch.nan_to_num(dark[c].to(torch.float32))
            sample = d.reshape(-1)[:: max(1, d.numel() // 1_000_000)]
            med = sample.median()
            sig = max(1.0, 1.4826 * float((sample - med).abs().median()))
            peak = F.max_pool2d(d[None, None], 3, stride=1, padding=1)[0, 0]
            # the raw sample itself, not the neighbours its demosaic spreads it over
            bad |= (d > med + hot_sigma * sig) & (d >= peak)
    if white is not None:
        if white.shape[-2:] != (H, W):
            raise ValueError(f"white {tuple(white.shape)} and dark {tuple(ref.shape)} differ")
        for c in range(white.shape[0]):
            wv = torch.nan_to_num(white[c].to(torch.float32))
            sample = wv.reshape(-1)[:: max(1, wv.numel() // 1_000_000)]
            top = float(torch.quantile(sample, 0.99))
            # the lower quartile of the 5 x 5 window: high around an isolated dead pixel (whose
            # demosaic darkens only its 3 x 3 neighbours, by at most half), low on the dark side
            # of a tile's edge (half the window dark): edges are not taken for dead pixels
            q = _local_kth(wv, 5, 7)
            trough = -F.max_pool2d(-wv[None, None], 3, stride=1, padding=1)[0, 0]
            # isolated: the demosaic darkens a dead sample's 3 x 3 neighbours by at most half,
            # a tile's corner or a colour's own edge leaves dark neighbours beside it
            second = _local_kth(wv, 3, 2)
            bad |= ((q >= lit_fraction * top) & (q > 0) & (wv < dead_ratio * q) & (wv <= trough)
                    & (second >= 0.25 * q))  # fmt: skip
    return dilate_mask(bad, dilate_px)


def dilate_mask(mask: torch.Tensor, px: int) -> torch.Tensor:
    """``(H, W)`` bool ``mask`` dilated by a ``(2·px + 1)²`` square (``px <= 0``: unchanged)."""
    if px <= 0:
        return mask
    k = 2 * int(px) + 1
    return F.max_pool2d(mask[None, None].float(), k, stride=1, padding=int(px))[0, 0] > 0
