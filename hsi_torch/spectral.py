"""Wavelength grids, resampling of spectra, and difference operators.

Convention:
    Wavelengths are in nanometres (nm) everywhere; wavenumbers ``k = 1/λ`` are in nm⁻¹.
    Spectral axes are the *last* axis of a tensor unless a function says otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

__all__ = [
    "SpectralGrid",
    "DEFAULT_GRID",
    "band_widths",
    "resample_spectra",
    "difference_matrix",
]


def band_widths(wavelengths: torch.Tensor) -> torch.Tensor:
    """Band widths Δλ_m (nm) of a sorted wavelength grid by the trapezoid/midpoint rule.

    Interior samples get half the distance between their neighbours; the two end samples get the
    distance to their single neighbour (so a uniform grid has Δλ equal to its step everywhere).

    Args:
        wavelengths: ``(M,)`` strictly increasing wavelengths in nm, ``M >= 1``.

    Returns:
        ``(M,)`` band widths in nm, same dtype/device. A single-sample grid gets width 1.
    """
    wl = torch.as_tensor(wavelengths)
    if wl.ndim != 1:
        raise ValueError(f"wavelengths must be 1-D, got shape {tuple(wl.shape)}")
    if wl.numel() == 1:
        return torch.ones_like(
            wl, dtype=torch.get_default_dtype() if not wl.is_floating_point() else wl.dtype)
    wl = wl.to(torch.float64) if not wl.is_floating_point() else wl
    d = wl[1:] - wl[:-1]
    out = torch.empty_like(wl)
    out[0] = d[0]
    out[-1] = d[-1]
    if wl.numel() > 2:
        out[1:-1] = 0.5 * (d[1:] + d[:-1])
    return out


@dataclass(frozen=True)
class SpectralGrid:
    """A sampled wavelength axis.

    Attributes:
        wavelengths_nm: tuple of strictly increasing wavelengths in nm (``M`` samples).

    Example:
        >>> g = SpectralGrid.uniform(430, 670, 10)
        >>> g.num_bands
        25
    """

    wavelengths_nm: tuple[float, ...]

    def __post_init__(self) -> None:
        wl = np.asarray(self.wavelengths_nm, dtype=np.float64)
        if wl.ndim != 1 or wl.size < 1:
            raise ValueError("SpectralGrid needs at least one wavelength")
        if not np.all(np.isfinite(wl)) or np.any(wl <= 0):
            raise ValueError(f"wavelengths must be finite and positive (nm), got {wl}")
        if wl.size > 1 and np.any(np.diff(wl) <= 0):
            raise ValueError("wavelengths must be strictly increasing")

    @classmethod
    def uniform(
        cls, start_nm: float = 430.0, stop_nm: float = 670.0, step_nm: float = 10.0
    ) -> SpectralGrid:
        """Uniform grid ``start, start+step, …, stop`` (inclusive, nm)."""
        if step_nm <= 0:
            raise ValueError(f"step_nm must be positive, got {step_nm}")
        n = int(round((stop_nm - start_nm) / step_nm)) + 1
        if n < 1:
            raise ValueError(f"empty grid: start={start_nm} stop={stop_nm} step={step_nm}")
        return cls(tuple(float(start_nm + i * step_nm) for i in range(n)))

    @property
    def num_bands(self) -> int:
        return len(self.wavelengths_nm)

    def __len__(self) -> int:
        return self.num_bands

    def wavelengths(
        self, device: torch.device | str | None = None, dtype: torch.dtype | None = None
    ) -> torch.Tensor:
        """``(M,)`` wavelengths in nm."""
        return torch.tensor(
            self.wavelengths_nm, device=device, dtype=dtype or torch.get_default_dtype())

    def band_widths(
        self, device: torch.device | str | None = None, dtype: torch.dtype | None = None
    ) -> torch.Tensor:
        """``(M,)`` band widths Δλ_m in nm (see :func:`band_widths`)."""
        return band_widths(self.wavelengths(device, torch.float64)).to(
            dtype or torch.get_default_dtype())

    def wavenumbers(
        self, device: torch.device | str | None = None, dtype: torch.dtype | None = None
    ) -> torch.Tensor:
        """``(M,)`` wavenumbers ``k = 1/λ`` in nm⁻¹ (decreasing)."""
        return 1.0 / self.wavelengths(device, dtype)

    def to_dict(self) -> dict:
        return {"wavelengths_nm": list(self.wavelengths_nm)}


DEFAULT_GRID = SpectralGrid.uniform(430.0, 670.0, 10.0)


def resample_spectra(
    values: torch.Tensor,
    source_nm: torch.Tensor,
    target_nm: torch.Tensor,
    *,
    dim: int = -1,
    extrapolate: str = "zero",
) -> torch.Tensor:
    """Linearly resample spectra from one wavelength grid to another.

    Args:
        values: tensor whose axis ``dim`` has length ``S`` (the source grid).
        source_nm: ``(S,)`` strictly increasing wavelengths (nm) of ``values``.
        target_nm: ``(T,)`` wavelengths (nm) to sample at.
        dim: spectral axis of ``values``.
        extrapolate: ``"zero"`` (0 outside the source range), ``"edge"`` (hold the end values)
            or ``"error"`` (raise when a target lies outside the source range).

    Returns:
        ``values`` with axis ``dim`` replaced by ``T`` samples; dtype/device of ``values``.
    """
    values = torch.as_tensor(values)
    if not values.is_floating_point():
        values = values.to(torch.get_default_dtype())
    src = torch.as_tensor(source_nm, device=values.device, dtype=values.dtype)
    tgt = torch.as_tensor(target_nm, device=values.device, dtype=values.dtype)
    if src.ndim != 1 or tgt.ndim != 1:
        raise ValueError("source_nm and target_nm must be 1-D")
    if values.shape[dim] != src.numel():
        raise ValueError(
            f"values has {values.shape[dim]} samples along dim {dim} "
            f"but source_nm has {src.numel()}")
    if src.numel() > 1 and bool((src[1:] <= src[:-1]).any()):
        raise ValueError("source_nm must be strictly increasing")
    if extrapolate not in ("zero", "edge", "error"):
        raise ValueError(f"extrapolate must be 'zero', 'edge' or 'error', got {extrapolate!r}")
    outside = (tgt < src[0] - 1e-9) | (tgt > src[-1] + 1e-9)
    if extrapolate == "error" and bool(outside.any()):
        raise ValueError(
            f"target wavelengths {tgt[outside].tolist()} nm lie outside the source range "
            f"[{float(src[0])}, {float(src[-1])}] nm")
    v = values.movedim(dim, -1)
    if src.numel() == 1:
        out = v[..., :1].expand(*v.shape[:-1], tgt.numel()).clone()
    else:
        idx = torch.searchsorted(src, tgt.clamp(src[0], src[-1]), right=True).clamp(
            1, src.numel() - 1)
        x0, x1 = src[idx - 1], src[idx]
        t = ((tgt.clamp(src[0], src[-1]) - x0) / (x1 - x0)).clamp(0, 1)
        out = v[..., idx - 1] * (1 - t) + v[..., idx] * t
    if extrapolate == "zero":
        out = torch.where(outside, torch.zeros((), dtype=out.dtype, device=out.device), out)
    return out.movedim(-1, dim)


def difference_matrix(
    num_bands: int,
    order: int = 1,
    *,
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
) -> torch.Tensor:
    """Finite-difference operator ``D`` along wavelength.

    Args:
        num_bands: ``M``.
        order: 1 gives ``(M−1, M)`` with rows ``e_{m+1} − e_m``; 2 gives ``(M−2, M)`` with rows
            ``e_m − 2 e_{m+1} + e_{m+2}``; 0 gives the ``(M, M)`` identity (Tikhonov).

    Returns:
        The dense ``D`` on ``device`` with ``dtype``.
    """
    if order not in (0, 1, 2):
        raise ValueError(f"difference order must be 0, 1 or 2, got {order}")
    if num_bands < order + 1:
        raise ValueError(f"need at least {order + 1} bands for a difference of order {order}")
    dtype = dtype or torch.get_default_dtype()
    eye = torch.eye(num_bands, device=device, dtype=dtype)
    if order == 0:
        return eye
    if order == 1:
        return eye[1:] - eye[:-1]
    return eye[2:] - 2 * eye[1:-1] + eye[:-2]
