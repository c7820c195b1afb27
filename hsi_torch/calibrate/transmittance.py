"""View-channel BRF transmittance B_v(p, λ) from a monochromator scan.

Procedure: one sensor image per wavelength λ_j with the objective removed and the
diffuser evenly lit. Every pixel is divided by the mean of the BRF-free patch of the reference view
at the same λ_j and colour channel; the colour channels are then combined with weights
proportional to their signal (the patch mean to the power ``weight_power``), ignoring saturated
pixels. Pixels that never receive light (between the triangles) are flagged unreliable. The result,
in sensor coordinates, is carried into the reference frame with the view homographies
(:func:`to_reference_frame`, one batched kornia warp; the homographies as
:mod:`hsi_torch.optics.geometry` defines them). Scans are ``(J, 3, H, W)`` (wavelength, colour
R/G/B, row, column), wavelengths in nm.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from hsi_torch.optics.geometry import warp_views

__all__ = [
    "TransmittanceResult",
    "match_wavelengths",
    "brf_transmittance",
    "to_reference_frame",
]


@dataclass
class TransmittanceResult:
    """Output of :func:`brf_transmittance`.

    Attributes:
        transmittance: ``(J, H, W)`` B(p, λ_j) in sensor coordinates (ratio to the BRF-free patch).
        reliable: ``(J, H, W)`` bool: at least one unsaturated channel with signal, pixel lit.
        lit: ``(H, W)`` bool: the pixel receives light at some wavelength (inside a view).
        wavelengths_nm: ``(J,)`` wavelengths of the rows (nm).
        channel_weights: ``(J, 3)`` colour weights used (each row sums to 1).
        patch_mean: ``(J, 3)`` mean of the BRF-free patch (dark-subtracted DN).
    """

    transmittance: torch.Tensor
    reliable: torch.Tensor
    lit: torch.Tensor
    wavelengths_nm: torch.Tensor
    channel_weights: torch.Tensor
    patch_mean: torch.Tensor


def match_wavelengths(
    scan_nm: torch.Tensor | Sequence[float],
    grid_nm: torch.Tensor | Sequence[float],
    tol_nm: float = 0.5,
) -> torch.Tensor:
    """``(M,)`` indices into the scan frames ``scan_nm (J,)`` (nm, any order) of each grid
    wavelength ``grid_nm (M,)``, within ``tol_nm``.

    Raises:
        ValueError: naming the grid wavelengths with no scan frame within ``tol_nm``.
    """
    s = torch.as_tensor(scan_nm, dtype=torch.float64).reshape(-1).cpu()
    g = torch.as_tensor(grid_nm, dtype=torch.float64).reshape(-1).cpu()
    if s.numel() == 0:
        raise ValueError("the monochromator scan has no frames")
    d = (g[:, None] - s[None, :]).abs()
    dmin, idx = d.min(dim=1)
    missing = g[dmin > tol_nm]
    if missing.numel():
        raise ValueError(
            f"monochromator scan is missing wavelengths {missing.tolist()} nm of the grid "
            f"(scan has {sorted(s.tolist())} nm, tolerance {tol_nm} nm)"
        )
    return idx


def brf_transmittance(
    scan: torch.Tensor,
    wavelengths_nm: torch.Tensor | Sequence[float],
    brf_free_mask: torch.Tensor,
    *,
    dark: torch.Tensor | None = None,
    grid_nm: torch.Tensor | Sequence[float] | None = None,
    saturation_level: float | None = None,
    lit_threshold: float = 0.05,
    weight_power: float = 1.0,
    tol_nm: float = 0.5,
) -> TransmittanceResult:
    """Per-pixel BRF transmittance in sensor coordinates from a monochromator scan.

    ``B_c(p, λ_j) = (I_jc(p) − dark) / mean_{q ∈ patch}(I_jc(q) − dark)`` per colour ``c``, then
    ``B(p, λ_j) = Σ_c w_jc u_jc(p) B_c(p, λ_j) / Σ_c w_jc u_jc(p)`` with ``w_jc ∝ patch_mean_jc^
    weight_power`` (dim channels contribute little) and ``u_jc(p) = 0`` where the pixel is
    saturated. A pixel is *lit* when ``max_j B(p, λ_j) ≥ lit_threshold``; ``reliable`` is lit and
    at least one usable channel. With ``saturation_level``, a colour with a saturated sample in
    the patch is not used at that wavelength (the patch mean would be wrong), and saturated
    samples never enter the patch mean.

    Args:
        scan: ``(J, 3, H, W)`` raw-linear images (DN), any float dtype/device.
        wavelengths_nm: ``(J,)`` wavelength of each frame (nm).
        brf_free_mask: ``(H, W)`` bool: the BRF-free patch of the reference view.
        dark: optional dark frame ``(3, H, W)`` or ``(J, 3, H, W)`` subtracted first.
        grid_nm: optional ``(M,)`` wavelengths to return (frames are selected/reordered to match;
            a missing wavelength raises).
        saturation_level: DN at/above which a raw value is treated as saturated (before dark
            subtraction); ``None`` disables the test.
        tol_nm: wavelength matching tolerance (:func:`match_wavelengths`).

    Returns:
        :class:`TransmittanceResult` (rows in grid order when ``grid_nm`` is given).

    Raises:
        ValueError: bad shapes, an empty BRF-free patch, a wavelength at which the patch is dark
            in every channel, or missing grid wavelengths.
    """
    if not isinstance(scan, torch.Tensor) or scan.ndim != 4 or scan.shape[1] != 3:
        shape = tuple(scan.shape) if isinstance(scan, torch.Tensor) else type(scan)
        raise ValueError(f"scan must be a (J, 3, H, W) tensor, got {shape}")
    if not scan.is_floating_point():
        scan = scan.to(torch.get_default_dtype())
    J, _, H, W = scan.shape
    wl = torch.as_tensor(wavelengths_nm, dtype=torch.float64).reshape(-1)
    if wl.numel() != J:
        raise ValueError(f"wavelengths_nm has {wl.numel()} entries but the scan has {J} frames")
    mask = torch.as_tensor(brf_free_mask, device=scan.device)
    if mask.shape != (H, W):
        raise ValueError(f"brf_free_mask must be (H, W) = ({H}, {W}), got {tuple(mask.shape)}")
    mask = mask.to(torch.bool)
    n_patch = int(mask.sum())
    if n_patch == 0:
        raise ValueError("brf_free_mask selects no pixels: the scan has no BRF-free patch")
    if grid_nm is not None:
        idx = match_wavelengths(wl, grid_nm, tol_nm)
        scan = scan[idx.to(scan.device)]
        wl = wl[idx]
        if dark is not None and dark.ndim == 4:
            dark = dark[idx.to(dark.device)]
        J = scan.shape[0]
    if dark is not None:
        dark = torch.as_tensor(dark, device=scan.device, dtype=scan.dtype)
        if dark.shape not in ((3, H, W), (J, 3, H, W)):
            raise ValueError(f"dark must be (3, H, W) or (J, 3, H, W), got {tuple(dark.shape)}")

    def channel(c: int) -> torch.Tensor:  # (J, H, W) dark-subtracted colour c
        xc = scan[:, c]
        if dark is None:
            return xc
        return xc - (dark[c] if dark.ndim == 3 else dark[:, c])

    # one colour at a time: (J, H, W) temporaries, never a second (J, 3, H, W) copy
    if saturation_level is None:
        patch = torch.stack([(channel(c) * mask).sum(dim=(-2, -1)) / n_patch for c in range(3)],
                            1)  # fmt: skip
        patch_sat = torch.zeros_like(patch, dtype=torch.bool)
    else:  # saturated samples never enter the patch mean; such a colour is not used (its
        # patch mean is unknown: the brightest samples are missing)
        ok = [(scan[:, c] < saturation_level) & mask for c in range(3)]
        patch = torch.stack([
            torch.where(ok[c], channel(c), 0.0).sum(dim=(-2, -1))
            / ok[c].sum(dim=(-2, -1)).clamp_min(1) for c in range(3)], 1)  # fmt: skip
        patch_sat = torch.stack([(ok[c] != mask).any(dim=(-2, -1)) for c in range(3)], 1)
        del ok
    bad = (patch <= 0).all(dim=1)
    if bool(bad.any()):
        raise ValueError(
            f"the BRF-free patch is dark in every colour channel at {wl[bad.cpu()].tolist()} nm"
        )
    sat_all = patch_sat.all(dim=1)
    if bool(sat_all.any()):
        raise ValueError(
            f"the BRF-free patch is saturated in every colour channel at "
            f"{wl[sat_all.cpu()].tolist()} nm; reduce the exposure"
        )
    usable_c = (patch > 0) & ~patch_sat  # (J, 3)
    w = torch.where(usable_c, patch.clamp_min(0) ** weight_power, torch.zeros_like(patch))
    w = w / w.sum(dim=1, keepdim=True)
    num = torch.zeros((J, H, W), dtype=scan.dtype, device=scan.device)
    den = torch.zeros_like(num)
    for c in range(3):
        if not bool(usable_c[:, c].any()):
            continue
        wu = torch.where(usable_c[:, c], w[:, c], 0.0).to(scan.dtype)[:, None, None].expand(J, H, W)
        if saturation_level is not None:
            wu = wu * (scan[:, c] < saturation_level)
        ratio = channel(c) / torch.where(usable_c[:, c], patch[:, c], 1.0)[:, None, None]
        num.addcmul_(wu, ratio)
        den.add_(wu)
        del wu, ratio
    B = num.div_(den.clamp_min(torch.finfo(scan.dtype).tiny))
    B = torch.where(den > 0, B, torch.zeros_like(B))
    lit = B.amax(dim=0) >= lit_threshold
    reliable = (den > 0) & lit[None]
    B = torch.where(lit[None], B, torch.zeros_like(B))
    return TransmittanceResult(B, reliable, lit, wl.to(scan.device), w, patch)


def to_reference_frame(
    per_pixel_map: torch.Tensor,
    view_homographies: torch.Tensor,
    triangles: torch.Tensor,
    reference_bbox: Sequence[int] | torch.Tensor,
    *,
    source_mask: torch.Tensor | None = None,
    inset_px: float = 1.0,
    mode: str = "bilinear",
) -> tuple[torch.Tensor, torch.Tensor]:
    """Carry a sensor-coordinate map into the reference frame, once per view (one kornia call).

    For view ``v`` and reference-frame pixel ``q``: ``out[v, …, q] = map(H_v⁻¹(q + (x0, y0)))``
    (bilinear, ``align_corners=True``). The map is expanded (not copied) over the views.

    Args:
        per_pixel_map: ``(…, H, W)`` sensor-coordinate map (e.g. ``(M, H, W)`` transmittance).
        view_homographies, triangles, reference_bbox, inset_px, mode: as
            :func:`~hsi_torch.optics.geometry.warp_views`.
        source_mask: optional ``(H, W)`` bool validity in sensor coordinates (e.g. ``lit`` or
            ``reliable.all(0)``); a warped pixel stays valid only if all its bilinear neighbours
            are valid.

    Returns:
        ``(maps, masks)``: ``maps (V, …, h, w)`` in the map's dtype/device and ``masks (V, h, w)``
        bool (inside view v's triangle, inside the sensor, and valid in ``source_mask``).
    """
    if not isinstance(per_pixel_map, torch.Tensor) or per_pixel_map.ndim < 2:
        raise ValueError("per_pixel_map must be a tensor of shape (..., H, W)")
    m = per_pixel_map if per_pixel_map.is_floating_point() else per_pixel_map.float()
    lead = m.shape[:-2]
    H, W = m.shape[-2:]
    C = 1
    for s in lead:
        C *= int(s)
    extra = 0
    src = m.reshape(C, H, W)
    if source_mask is not None:
        sm = torch.as_tensor(source_mask, device=m.device)
        if sm.shape != (H, W):
            raise ValueError(f"source_mask must be (H, W) = ({H}, {W}), got {tuple(sm.shape)}")
        src = torch.cat([src, sm.to(m.dtype)[None]], dim=0)
        extra = 1
    out, masks = warp_views(src, view_homographies, reference_bbox, triangles, inset_px, mode)
    V, h, w = out.shape[0], out.shape[-2], out.shape[-1]
    if extra:
        masks = masks & (out[:, C] >= 1.0 - 1e-3)
    maps = out[:, :C].reshape(V, *lead, h, w)
    return maps, masks
