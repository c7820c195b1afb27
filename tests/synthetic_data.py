"""Test and benchmark helpers (tests/ and scripts/bench_solver.py): realistic random problems with
the camera's structure, and DNG files written the way cameras write them."""

from __future__ import annotations

import os
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from hsi_torch.forward_model import SensingModel
from hsi_torch.refdata import colorchecker_reflectances, illuminant
from hsi_torch.spectral import DEFAULT_GRID, SpectralGrid

__all__ = ["synthetic_brf_problem", "write_dng"]

_CFA_CODES = {"R": 0, "G": 1, "B": 2}


def write_dng(
    path: str | os.PathLike,
    mosaic: Any,
    *,
    cfa_pattern: str = "RGGB",
    black_level: int = 0,
    white_level: int = 65535,
    exposure_s: float | None = None,
    make: str | None = None,
    model: str | None = None,
) -> Path:
    """Write a minimal, uncompressed CFA DNG (what a camera's RAW would be) with tifffile.

    Tags: ``DNGVersion`` 1.4, ``CFARepeatPatternDim`` 2×2, ``CFAPattern``, ``BlackLevel``,
    ``WhiteLevel``, an identity ``ColorMatrix1``, and optionally ``ExposureTime`` (a rational,
    denominator ≤ 10⁶), ``Make``, ``Model``. LibRaw (rawpy) opens it — the mosaic, black and white
    level read back exactly — when the image is at least 22 × 22 px (LibRaw's smallest).

    Args:
        mosaic: ``(H, W)`` or ``(1, H, W)`` stored values (DN, 0…65535), array or tensor.

    Returns:
        The path written (its folder is created when missing).
    """
    import tifffile  # lazy: only the tests and examples write DNG files

    a = mosaic.detach().cpu().numpy() if isinstance(mosaic, torch.Tensor) else np.asarray(mosaic)
    a = np.asarray(np.rint(a), dtype=np.float64).reshape(a.shape[-2:])
    if a.min() < 0 or a.max() > 65535:
        raise ValueError(f"mosaic values must lie in [0, 65535], got [{a.min()}, {a.max()}]")
    pat = cfa_pattern.upper()
    tags: list[tuple[int, str, int, Any]] = [
        (50706, "B", 4, (1, 4, 0, 0)),  # DNGVersion
        (50707, "B", 4, (1, 1, 0, 0)),  # DNGBackwardVersion
        (33421, "H", 2, (2, 2)),  # CFARepeatPatternDim
        (33422, "B", 4, tuple(_CFA_CODES[c] for c in pat)),  # CFAPattern
        (50710, "B", 3, (0, 1, 2)),  # CFAPlaneColor
        (50711, "H", 1, 1),  # CFALayout: rectangular
        (50713, "H", 2, (1, 1)),  # BlackLevelRepeatDim
        (50714, "I", 1, int(black_level)),  # BlackLevel
        (50717, "I", 1, int(white_level)),  # WhiteLevel
        (50721, "2i", 9, (1, 1, 0, 1, 0, 1, 0, 1, 1, 1, 0, 1, 0, 1, 0, 1, 1, 1)),  # ColorMatrix1
        (50778, "H", 1, 21),  # CalibrationIlluminant1: D65
    ]
    if exposure_s is not None:
        t = Fraction(exposure_s).limit_denominator(1_000_000)  # 1/60 s stays 1/60
        tags.append((33434, "2I", 1, (t.numerator, t.denominator)))  # ExposureTime
    for code, text in ((271, make), (272, model)):
        if text:
            tags.append((code, "s", 0, text))
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    tifffile.imwrite(p, a.astype(np.uint16), photometric=32803, extratags=tags, metadata=None)
    return p


def synthetic_brf_problem(
    num_pixels: int,
    *,
    grid: SpectralGrid = DEFAULT_GRID,
    num_views: int = 10,
    opd_range_nm: tuple[float, float] = (1500.0, 6000.0),
    mask_fraction: float = 0.1,
    noise_dn: float = 1.0,
    peak_dn: float = 255.0,
    shared: bool = False,
    spectra: str = "bumps",
    seed: int = 0,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """A realistic random test/benchmark problem with the camera's sensing structure.

    ``A_p[(v, c), m] = g_v(p) · T_v(p, λ_m) · Δλ_m · φ^c(λ_m)`` (the dense matrices of a
    :class:`~hsi_torch.forward_model.SensingModel`) with BRF-like transmittances
    ``T = ½[1 − cos(2π·OPD/λ)]`` (view OPDs spread over ``opd_range_nm``, ±2 % per pixel unless
    ``shared``), smooth Gaussian "RGB" curves ``φ^c`` (peaks 600/540/460 nm), per-pixel gains
    0.6…1 (1 when ``shared``). ``A`` is scaled so that a white reflectance (1 in every band) gives
    at most about ``peak_dn``. Spectra (times a brightness 0.03…1):

    * ``spectra="bumps"`` (hard case): 1–3 Gaussian bumps on a small floor, normalised to peak 1
      — many bands near 0, so ~30 % of the pixels need the active-set correction;
    * ``spectra="reflectance"`` (realistic): random convex mixtures of 2–3 of the 24 ColorChecker
      reflectances (:func:`hsi_torch.refdata.colorchecker_reflectances`) lit by CIE D65,
      normalised to peak 1 — smooth and positive in every band, like real scenes.

    ``y = A x + N(0, noise_dn²)``; ``mask`` drops a random
    ``mask_fraction`` of the observations and every observation above ``peak_dn`` (saturation).
    Generated in float64 in chunks (memory ≈ the outputs), then cast.

    Returns:
        ``A`` ``(P, 3V, M)`` (``(3V, M)`` when ``shared``), ``y (P, 3V)``, ``mask (P, 3V)`` bool,
        ``x_true (P, M)``, in ``dtype`` on ``device``.
    """
    if num_pixels < 1 or num_views < 1:
        raise ValueError(f"need num_pixels >= 1 and num_views >= 1, got {num_pixels}, {num_views}")
    gen = torch.Generator().manual_seed(int(seed))
    f64 = torch.float64
    lam = grid.wavelengths(dtype=f64)
    dl = grid.band_widths(dtype=f64)
    v, P = num_views, num_pixels
    opd = torch.linspace(opd_range_nm[0], opd_range_nm[1], v, dtype=f64)
    opd = opd[torch.randperm(v, generator=gen)].view(1, v, 1)
    centres = torch.tensor([600.0, 540.0, 460.0], dtype=f64).view(3, 1)
    widths = torch.tensor([40.0, 40.0, 30.0], dtype=f64).view(3, 1)
    phi_dl = dl * torch.exp(-0.5 * ((lam - centres) / widths) ** 2)  # (3, M)

    def sensing(n: int, jitter: bool) -> Tensor:
        rnd = torch.rand(n, v, 1, generator=gen, dtype=f64) if jitter else torch.full(
            (n, v, 1), 0.5, dtype=f64)
        trans = 0.5 * (1 - torch.cos(2 * torch.pi * opd * (1 + 0.02 * (2 * rnd - 1)) / lam))
        gain = (0.6 + 0.4 * torch.rand(n, v, generator=gen, dtype=f64) if jitter
                else torch.ones(n, v, dtype=f64))  # fmt: skip
        return SensingModel(trans, gain, phi_dl).dense()

    if spectra not in ("bumps", "reflectance"):
        raise ValueError(f"spectra must be 'bumps' or 'reflectance', got {spectra!r}")
    scale = peak_dn / float(sensing(1, False).sum(2).amax())
    t = (lam - lam[0]) / (lam[-1] - lam[0])
    if spectra == "reflectance":
        refl, _ = colorchecker_reflectances(lam)
        lit = refl.to(f64) * illuminant("D65", lam).to(f64)  # (24, M)
    A_shared = sensing(1, False)[0] * scale if shared else None
    outs: list[list[Tensor]] = [[], [], [], []]
    for s in range(0, P, 16384):
        n = min(P, s + 16384) - s
        a = A_shared.expand(n, -1, -1) if shared else sensing(n, True) * scale
        if spectra == "bumps":
            c = torch.rand(n, 3, 1, generator=gen, dtype=f64) * 1.2 - 0.1
            w = 0.08 + 0.3 * torch.rand(n, 3, 1, generator=gen, dtype=f64)
            h = torch.rand(n, 3, 1, generator=gen, dtype=f64)
            h = h * (torch.rand(n, 3, 1, generator=gen, dtype=f64) < 0.8)
            x = (h * torch.exp(-0.5 * ((t - c) / w) ** 2)).sum(1)
            x = x + 0.05 * torch.rand(n, 1, generator=gen, dtype=f64)
        else:
            pick = torch.randint(0, lit.shape[0], (n, 3), generator=gen)
            wts = -torch.log(torch.rand(n, 3, generator=gen, dtype=f64).clamp_min(1e-12))
            wts = wts * (torch.rand(n, 3, generator=gen, dtype=f64) < 0.8)
            wts[:, 0] += 1e-3  # at least one patch
            x = (wts.unsqueeze(2) * lit[pick]).sum(1) / wts.sum(1, keepdim=True)
        x = x / x.amax(1, keepdim=True).clamp_min(1e-12)
        x = x * (0.03 + 0.97 * torch.rand(n, 1, generator=gen, dtype=f64))
        y = torch.bmm(a, x.unsqueeze(2)).squeeze(2)
        y = y + noise_dn * torch.randn(n, 3 * v, generator=gen, dtype=f64)
        mk = (torch.rand(n, 3 * v, generator=gen, dtype=f64) >= mask_fraction) & (y <= peak_dn)
        for lst, val in zip(outs, (a, y, mk, x), strict=True):
            if not (shared and val is a):
                lst.append(val.to(device=device, dtype=dtype if val.is_floating_point() else None))
    A = A_shared.to(device=device, dtype=dtype) if shared else torch.cat(outs[0])
    return A, torch.cat(outs[1]), torch.cat(outs[2]), torch.cat(outs[3])
