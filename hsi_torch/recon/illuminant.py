"""Was the scene lit as the white reference was? A check of the reconstructed cube (why, what
it cannot tell and measurements: ``docs/reconstruct.md``, *The scene's light against the white
reference's*).

:func:`illuminant_finding` takes the mean spectrum of the brightest ``top_fraction`` of the valid
pixels and divides its mean at ≥ 620 nm by its mean at ≤ 480 nm (≈ 1 for a near-neutral surface
under the white's light): beyond ``limit`` (default :data:`ILLUMINANT_RATIO_LIMIT`, 3) either way
a ``capture.illuminant`` warning, within it an ``info`` finding recording the ratio.
"""

from __future__ import annotations

import torch
from torch import Tensor

from hsi_torch.findings import Finding

__all__ = ["ILLUMINANT_RATIO_LIMIT", "ILLUMINANT_TOP_FRACTION", "illuminant_ratio",
           "illuminant_finding"]  # fmt: skip

#: the long/short-wavelength ratio of the brightest surfaces beyond which (or below whose
#: inverse) the scene's light is taken to differ from the white reference's
ILLUMINANT_RATIO_LIMIT = 3.0
#: the brightest fraction of the valid pixels whose mean spectrum is tested
ILLUMINANT_TOP_FRACTION = 0.02
_LONG_NM, _SHORT_NM = 620.0, 480.0


def illuminant_ratio(
    cube: Tensor, valid: Tensor, wavelengths_nm: Tensor, top_fraction: float = 0.02
) -> float | None:
    """Mean reflectance at ≥ 620 nm over that at ≤ 480 nm of the brightest valid pixels.

    Args:
        cube: ``(M, h, w)`` reflectance (relative to the white reference).
        valid: ``(h, w)`` bool, the pixels to use (NaN pixels are left out too).
        wavelengths_nm: ``(M,)`` band centres, nm.
        top_fraction: the brightest fraction of the valid pixels (mean over bands) used.

    Returns:
        The ratio, or ``None`` when it cannot be measured (no valid pixel, no band at either
        end, a short end that is not positive).
    """
    if cube.ndim != 3 or valid.shape != cube.shape[1:] or wavelengths_nm.numel() != cube.shape[0]:
        raise ValueError(f"cube (M, h, w), valid (h, w), wavelengths (M,) expected, got "
                         f"{tuple(cube.shape)}, {tuple(valid.shape)}, "
                         f"{tuple(wavelengths_nm.shape)}")  # fmt: skip
    wl = wavelengths_nm.detach().to(device=cube.device, dtype=torch.float64)
    long_, short = wl >= _LONG_NM, wl <= _SHORT_NM
    if not bool(long_.any()) or not bool(short.any()):
        return None
    x = cube.detach().reshape(cube.shape[0], -1)
    bright = x.mean(0)
    ok = valid.reshape(-1).to(x.device) & torch.isfinite(bright)
    count = int(ok.sum())
    if count == 0:
        return None
    n = max(1, int(round(top_fraction * count)))
    idx = torch.topk(torch.where(ok, bright, torch.full_like(bright, -torch.inf)), n).indices
    top = x[:, idx].to(torch.float64).mean(1)
    lo = float(top[short].mean())
    if not lo > 0:
        return None
    return float(top[long_].mean()) / lo


def illuminant_finding(
    cube: Tensor,
    valid: Tensor,
    wavelengths_nm: Tensor,
    *,
    limit: float = ILLUMINANT_RATIO_LIMIT,
    top_fraction: float = ILLUMINANT_TOP_FRACTION,
    source: str | None = None,
) -> Finding | None:
    """The ``capture.illuminant`` finding of a reconstructed frame (module docstring).

    Args:
        cube, valid, wavelengths_nm: as :func:`illuminant_ratio`.
        limit: the ratio (and its inverse) beyond which the light is taken to differ (> 1).

    Returns:
        A ``"warning"`` finding beyond the limit, an ``"info"`` one within it, ``None`` when the
        ratio cannot be measured.
    """
    r = illuminant_ratio(cube, valid, wavelengths_nm, top_fraction)
    if r is None:
        return None
    what = (
        f"the brightest {100 * top_fraction:g} % of the scene reads {r:.2f}× the reflectance "
        f"at ≥ {_LONG_NM:g} nm as at ≤ {_SHORT_NM:g} nm"
    )
    if r > limit or r < 1.0 / limit:
        tint = "redder" if r > 1 else "bluer"
        return Finding(
            "capture.illuminant", "warning",
            f"{what}: if those surfaces are near-neutral (a white card, paper), the scene was "
            f"lit by a {tint} light than the white reference, and every spectrum carries the "
            "two lights' ratio", measured=round(r, 3), limit=limit,
            fix="shoot the white reference under the scene's light and recalibrate (no "
                "software can tell a coloured scene from a coloured light)",
            source=source)  # fmt: skip
    return Finding("capture.illuminant", "info", f"{what}: within the limit (the scene's "
                   "light is consistent with the white reference's)", measured=round(r, 3),
                   limit=limit, source=source)  # fmt: skip
