"""Spectral reconstruction metrics.

Convention:
    Spectra lie along the last axis ``(..., M)``; metrics reduce that axis (and, for
    :func:`psnr`, every axis unless ``dim`` is given). Reflectance peak is 1 by default.
"""

from __future__ import annotations

import math

import torch

__all__ = ["mse", "psnr", "spectral_angle_deg", "rmse"]


def _check(estimate: torch.Tensor, truth: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    estimate = torch.as_tensor(estimate)
    truth = torch.as_tensor(truth, device=estimate.device)
    if estimate.shape != truth.shape:
        raise ValueError(
            f"estimate shape {tuple(estimate.shape)} != truth shape {tuple(truth.shape)}"
        )
    dtype = torch.promote_types(estimate.dtype, truth.dtype)
    if not dtype.is_floating_point:
        dtype = torch.get_default_dtype()
    return estimate.to(dtype), truth.to(dtype)


def mse(
    estimate: torch.Tensor, truth: torch.Tensor, dim: int | tuple[int, ...] | None = None
) -> torch.Tensor:
    """Mean squared error over ``dim`` (all elements when None)."""
    e, t = _check(estimate, truth)
    d = (e - t).square()
    return d.mean() if dim is None else d.mean(dim=dim)


def rmse(
    estimate: torch.Tensor, truth: torch.Tensor, dim: int | tuple[int, ...] | None = None
) -> torch.Tensor:
    """Root mean squared error over ``dim``."""
    return mse(estimate, truth, dim).sqrt()


def psnr(
    estimate: torch.Tensor,
    truth: torch.Tensor,
    *,
    peak: float = 1.0,
    dim: int | tuple[int, ...] | None = None,
) -> torch.Tensor:
    """PSNR in dB, ``10·log10(peak² / MSE)``; with ``peak = 1`` this is ``10·log10(1/MSE)``.

    Args:
        estimate, truth: same shape.
        peak: signal peak (1 for reflectance).
        dim: axes the MSE averages over (None = all), e.g. ``-1`` for a PSNR per spectrum.
    """
    m = mse(estimate, truth, dim)
    return 10.0 * torch.log10(torch.as_tensor(peak, dtype=m.dtype, device=m.device) ** 2 / m)


def spectral_angle_deg(
    estimate: torch.Tensor, truth: torch.Tensor, eps: float = 1e-12
) -> torch.Tensor:
    """Spectral angle (SAM) in degrees between spectra along the last axis, shape ``(...)``."""
    e, t = _check(estimate, truth)
    cos = (e * t).sum(-1) / (e.norm(dim=-1) * t.norm(dim=-1)).clamp_min(eps)
    return torch.rad2deg(torch.arccos(cos.clamp(-1.0, 1.0)))


def psnr_from_mse(value: float) -> float:
    """PSNR (dB, peak 1) of a scalar MSE."""
    return 10.0 * math.log10(1.0 / value) if value > 0 else math.inf
