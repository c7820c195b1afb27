"""Bayer mosaics in torch: CFA patterns and masks, mosaic, demosaic, saturation through a demosaic.

One implementation for the sensor model of the virtual prototype (:mod:`hsi_torch.optics.sensor`)
and the file readers (:mod:`hsi_torch.io.raw`, :mod:`hsi_torch.io.captures`, which re-export these
functions), neither of which owns the other.

Convention:
    - A Bayer mosaic is a tensor ``(..., 1, H, W)``. Its CFA pattern is a 4-letter string giving
      the colours of the top-left 2×2 cell in row-major order, e.g. ``"RGGB"`` means
      ``(row 0, col 0) = R, (0, 1) = G, (1, 0) = G, (1, 1) = B``. The pattern repeats with period 2
      and always refers to the array as given (row 0, column 0 is the first visible pixel).
    - Values are linear (e.g. DN above black); saturation masks are bool mosaics of the same shape.
    - Colour channel order of RGB outputs is R, G, B.

Demosaic options (both differentiable, batched, device/dtype-agnostic):
    - ``"half"``: 2×2 binning to ``(3, H//2, W//2)``: R and B are the cell's R and B samples,
      G the mean of the cell's two G samples (odd trailing rows/columns are dropped). The RGB
      sample of output pixel ``(x, y)`` sits at full-resolution coordinate ``(2x + 0.5, 2y + 0.5)``.
    - ``"bilinear"``: full-resolution bilinear interpolation written as a *normalised convolution*:
      ``rgb_c = conv(x · m_c, k_c) / conv(m_c, k_c)`` with ``m_c`` the CFA mask of colour ``c``,
      ``k_RB = [[1,2,1],[2,4,2],[1,2,1]]/4`` and ``k_G = [[0,1,0],[1,4,1],[0,1,0]]/4``
      (zero padding).
      In the interior this is the textbook bilinear demosaic (measured samples are kept exactly,
      linear ramps are reproduced exactly); at the border the weights renormalise over the
      samples that exist instead of assuming zeros. It is evaluated colour by colour on whole
      rows, band by band, without the products and sums of the masked-out zeros (the same
      values as the masked planes, :func:`demosaic_bilinear`).
"""

from __future__ import annotations

from typing import Literal

import torch
import torch.nn.functional as F

__all__ = [
    "DemosaicMethod",
    "validate_cfa_pattern",
    "cfa_masks",
    "mosaic",
    "bayer_half",
    "demosaic_bilinear",
    "demosaic",
    "demosaic_saturation",
]

DemosaicMethod = Literal["half", "bilinear"]
_CHANNEL = {"R": 0, "G": 1, "B": 2}


def validate_cfa_pattern(pattern: str) -> str:
    """Check and normalise a 2×2 Bayer pattern string (``"RGGB"``, ``"grbg"``, ...).

    Returns:
        The upper-case pattern. Raises ``ValueError`` unless it has exactly one R, one B and two G.
    """
    if not isinstance(pattern, str):
        raise TypeError(f"cfa_pattern must be a str like 'RGGB', got {type(pattern).__name__}")
    p = pattern.upper()
    if len(p) != 4 or sorted(p) != ["B", "G", "G", "R"]:
        raise ValueError(
            f"cfa_pattern must be a 2x2 Bayer pattern such as 'RGGB', 'BGGR', 'GRBG' or 'GBRG' "
            f"(one R, one B, two G), got {pattern!r}")
    return p


def cfa_masks(
    pattern: str,
    height: int,
    width: int,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> torch.Tensor:
    """Colour masks of a Bayer mosaic.

    Returns:
        ``(3, H, W)`` tensor with 1 where the pixel samples R, G, B respectively, 0 elsewhere.
    """
    p = validate_cfa_pattern(pattern)
    cell = torch.zeros(3, 2, 2, device=device, dtype=dtype)
    for i, ch in enumerate(p):
        cell[_CHANNEL[ch], i // 2, i % 2] = 1
    reps_h, reps_w = (height + 1) // 2, (width + 1) // 2
    return cell.repeat(1, reps_h, reps_w)[:, :height, :width]


def _check_mosaic(x: torch.Tensor, name: str = "mosaic") -> None:
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    if x.ndim < 3 or x.shape[-3] != 1:
        raise ValueError(f"{name} must have shape (..., 1, H, W), got {tuple(x.shape)}")


def mosaic(rgb: torch.Tensor, pattern: str) -> torch.Tensor:
    """Sample an RGB image through a Bayer CFA (the forward model of the sensor's colour filter).

    Args:
        rgb: ``(..., 3, H, W)``.
        pattern: CFA pattern string, e.g. ``"RGGB"``.

    Returns:
        ``(..., 1, H, W)`` with each pixel taking the channel its CFA colour selects.
    """
    if not isinstance(rgb, torch.Tensor) or rgb.ndim < 3 or rgb.shape[-3] != 3:
        shape = tuple(rgb.shape) if isinstance(rgb, torch.Tensor) else type(rgb).__name__
        raise ValueError(f"rgb must be a tensor of shape (..., 3, H, W), got {shape}")
    m = cfa_masks(pattern, rgb.shape[-2], rgb.shape[-1], device=rgb.device, dtype=rgb.dtype)
    return (rgb * m).sum(dim=-3, keepdim=True)


def bayer_half(
    x: torch.Tensor, pattern: str, reduce: Literal["mean", "any"] = "mean"
) -> torch.Tensor:
    """2×2 binning of a Bayer mosaic into half-resolution RGB.

    Args:
        x: ``(..., 1, H, W)`` mosaic (float, or bool with ``reduce="any"``).
        pattern: CFA pattern string.
        reduce: ``"mean"`` averages the two greens; ``"any"`` ORs them (for saturation masks).

    Returns:
        ``(..., 3, H // 2, W // 2)``; odd trailing rows/columns are dropped.
    """
    _check_mosaic(x, "x")
    p = validate_cfa_pattern(pattern)
    h2, w2 = x.shape[-2] // 2, x.shape[-1] // 2
    if h2 == 0 or w2 == 0:
        raise ValueError(f"mosaic must be at least 2x2 for half-size binning, got {tuple(x.shape)}")
    x = x[..., 0, : 2 * h2, : 2 * w2]
    subs = [x[..., i // 2 :: 2, i % 2 :: 2] for i in range(4)]
    greens = [s for s, ch in zip(subs, p, strict=True) if ch == "G"]
    r = subs[p.index("R")]
    b = subs[p.index("B")]
    g = (greens[0] | greens[1]) if reduce == "any" else 0.5 * (greens[0] + greens[1])
    return torch.stack([r, g, b], dim=-3)


def _smooth_w(t: torch.Tensor, side: float) -> torch.Tensor:
    """``t + side·(left + right)`` along the last axis, zero padded."""
    p = F.pad(t, (1, 1))
    return p[..., 1:-1] + side * (p[..., :-2] + p[..., 2:])


def _smooth_h(t: torch.Tensor, side: float) -> torch.Tensor:
    """``t + side·(up + down)`` along the second-to-last axis, zero padded."""
    p = F.pad(t, (0, 0, 1, 1))
    return p[..., 1:-1, :] + side * (p[..., :-2, :] + p[..., 2:, :])


def _bilinear_num_den(
    x: torch.Tensor, pattern: str
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Reference numerator ``conv(x·m_c, k_c)`` (N,3,H,W) and denominators (R/B: (2,H,W), G: (H,W)).

    The convolutions are written as shifted sums:
    ``k_RB = ([1,2,1]/2)ᵀ ⊗ ([1,2,1]/2)`` is separable and the R/B masks are products of a row and
    a column indicator, so their normalisers are outer products of 1-D vectors; ``k_G`` is the
    centre plus ¼ of the four neighbours, and on the G checkerboard its normaliser is 1 at G
    pixels and (number of in-image 4-neighbours)/4 elsewhere.
    """
    p = validate_cfa_pattern(pattern)
    n, _, h, w = x.shape
    m = cfa_masks(p, h, w, device=x.device, dtype=x.dtype)
    rb = x * m[[0, 2]]
    num_rb = _smooth_h(_smooth_w(rb, 0.5), 0.5)
    g = x * m[1]
    gp = F.pad(g, (1, 1, 1, 1))
    num_g = g + 0.25 * (gp[..., :-2, 1:-1] + gp[..., 2:, 1:-1] + gp[..., 1:-1, :-2]
                        + gp[..., 1:-1, 2:])  # fmt: skip
    den_rb, den_g = _bilinear_den(p, torch.arange(h, device=x.device),
                                  torch.arange(w, device=x.device), h, w, x.dtype)  # fmt: skip
    num = torch.stack([num_rb[:, 0], num_g[:, 0], num_rb[:, 1]], dim=1)
    return num, den_rb, den_g


def _bilinear_den(
    p: str, rows: torch.Tensor, cols: torch.Tensor, h: int, w: int, dtype: torch.dtype
) -> tuple[torch.Tensor, torch.Tensor]:
    """The normalisers of the bilinear demosaic at the given rows × columns of an ``h × w`` mosaic.

    Args:
        p: validated CFA pattern.
        rows, cols: 1-D integer index tensors (``r`` rows, ``c`` columns).

    Returns:
        R/B ``(2, r, c)`` and G ``(r, c)`` in ``dtype``: the outer product of the smoothed row and
        column indicators of R (B), and 1 at G pixels, (in-image 4-neighbours)/4 elsewhere. Both are
        1 away from the mosaic's first and last row and column.
    """
    all_r = torch.arange(h, device=rows.device)
    all_c = torch.arange(w, device=rows.device)
    dens = []
    for ch in "RB":
        pos = p.index(ch)
        r = (all_r % 2 == pos // 2).to(dtype)
        c = (all_c % 2 == pos % 2).to(dtype)
        dens.append(_smooth_w(r, 0.5)[rows][:, None] * _smooth_w(c, 0.5)[cols][None, :])
    g_pos = [i for i, ch in enumerate(p) if ch == "G"]
    site = (rows % 2 * 2)[:, None] + (cols % 2)[None, :]
    m_g = ((site == g_pos[0]) | (site == g_pos[1])).to(dtype)
    edge_r = (rows == 0).to(dtype) + (rows == h - 1).to(dtype)
    edge_c = (cols == 0).to(dtype) + (cols == w - 1).to(dtype)
    count = 4.0 - edge_r[:, None] - edge_c[None, :]
    return torch.stack(dens), m_g + (1 - m_g) * (count / 4.0)


#: rows of the mosaic demosaiced at a time (bilinear): bounds the temporaries to a band
_BAND_ROWS = 256


def _in_bands(fn, x: torch.Tensor, out_dtype: torch.dtype) -> torch.Tensor:
    """Apply a 3×3-stencil demosaic ``fn`` ((N, 1, h, w) → (N, 3, h, w)) band by band.

    Bands start on even rows (the CFA phase is kept) and carry two rows of context on each side
    that are cropped, so every output row is computed from exactly the rows it would see in one
    pass, with the same arithmetic: the result equals the whole-image one exactly, with
    temporaries of one band instead of the image.
    """
    n, _, h, w = x.shape
    if h <= 2 * _BAND_ROWS:
        return fn(x)
    out = torch.empty((n, 3, h, w), dtype=out_dtype, device=x.device)
    for r0 in range(0, h, _BAND_ROWS):
        r1 = min(h, r0 + _BAND_ROWS)
        a, b = max(0, r0 - 2), min(h, r1 + 2)
        out[:, :, r0:r1] = fn(x[:, :, a:b])[:, :, r0 - a : r0 - a + (r1 - r0)]
    return out


def _bilinear_reference(x: torch.Tensor, pattern: str) -> torch.Tensor:
    """The normalised convolution of the module docstring on whole masked planes, band by band.

    ``x`` is ``(N, 1, H, W)`` floating point; returns ``(N, 3, H, W)``. Slower than the row-wise
    evaluation of :func:`demosaic_bilinear` (it multiplies and adds the masked-out zeros); kept for
    mosaics holding NaN or ±inf, where the masked-out products ``x·0`` are NaN and spread into
    the other colours' neighbourhoods, and for mosaics that require a gradient (no in-place
    writes)."""

    def one(xb: torch.Tensor) -> torch.Tensor:
        num, den_rb, den_g = _bilinear_num_den(xb, pattern)
        return num / torch.stack([den_rb[0], den_g, den_rb[1]])

    return _in_bands(one, x, x.dtype)


def _shifted_means(a: torch.Tensor, b: torch.Tensor, out: torch.Tensor, mask: bool) -> None:
    """``out = 0.5·(a + b)`` (the add, then the product, each rounded: the reference's two
    operations), or ``out = a | b`` for masks. ``out`` may be a view of the result."""
    if mask:
        torch.logical_or(a, b, out=out)
    else:
        torch.add(a, b, out=out)
        out.mul_(0.5)


def _stencil_band(xp: torch.Tensor, out: torch.Tensor, p: str, rows_buf: torch.Tensor) -> None:
    """The bilinear numerators (or, on a bool mask, the saturation flags) of one band of rows.

    Each colour is evaluated on whole rows (contiguous in memory), never multiplying or adding
    the reference's masked-out zeros (``v·1 = v``, ``0 + v = v`` and ``v·0`` dropped from sums
    are exact), the remaining operations in the reference's order:

    * R (B): on its sample rows ``E = 0.5·(left + right)``, its samples copied over at its sample
      columns; on the other rows ``0.5·(E_above + E_below)``;
    * G: ``0.25·(((up + down) + left) + right)`` everywhere, the G samples copied over at G sites.

    A bool mask takes ``|`` for every sum (the flags of the same supports).

    Args:
        xp: ``(N, h+2, w+2)``: the band's mosaic rows (the first on an even mosaic row) with the
            row above and below, zero (False) outside the mosaic.
        out: ``(N, 3, h, w)`` view of the result, written in place.
        p: validated CFA pattern.
        rows_buf: ``(N, ≥ h//2 + 2, w)`` scratch of ``xp``'s dtype.
    """
    h, w = out.shape[-2:]
    mask = xp.dtype == torch.bool
    inner = xp[:, 1 : h + 1, 1 : w + 1]
    pos = {ch: divmod(p.index(ch), 2) for ch in "RB"}
    for c, ch in ((0, "R"), (2, "B")):
        pr, pc = pos[ch]
        qr = 1 - pr
        first = -pr  # the sample row just above the band when the band's first is row 1
        count = (h - first) // 2 + 1  # sample rows first, first + 2, … ≤ h (h: the row below)
        rows = xp[:, 1 + first : 2 + first + 2 * (count - 1) : 2]
        e = rows_buf[:, :count]
        _shifted_means(rows[..., :w], rows[..., 2:], e, mask)
        e[..., pc::2] = rows[..., 1 + pc : w + 1 : 2]
        o = out[:, c]
        own, other = (h - pr + 1) // 2, (h - qr + 1) // 2
        o[:, pr::2] = e[:, pr : pr + own]
        _shifted_means(e[:, :other], e[:, 1 : other + 1], o[:, qr::2], mask)
    g = out[:, 1]
    if mask:
        torch.logical_or(xp[:, :h, 1 : w + 1], xp[:, 2:, 1 : w + 1], out=g)
        g.logical_or_(xp[:, 1 : h + 1, :w]).logical_or_(xp[:, 1 : h + 1, 2:])
    else:
        torch.add(xp[:, :h, 1 : w + 1], xp[:, 2:, 1 : w + 1], out=g)
        g.add_(xp[:, 1 : h + 1, :w]).add_(xp[:, 1 : h + 1, 2:]).mul_(0.25)
    for (i, _), (_, j) in ((pos["R"], pos["B"]), (pos["B"], pos["R"])):  # the G sites
        g[:, i::2, j::2] = inner[:, i::2, j::2]


def _stencil_in_bands(flat: torch.Tensor, p: str) -> torch.Tensor:
    """:func:`_stencil_band` over ``flat`` ``(N, H, W)`` in bands of :data:`_BAND_ROWS` rows.

    Returns ``(N, 3, H, W)`` of ``flat``'s dtype: the numerators (float) or the flags (bool).
    Temporaries: one padded band and half a band, whatever the mosaic's height.
    """
    n, h, w = flat.shape
    out = torch.empty((n, 3, h, w), dtype=flat.dtype, device=flat.device)
    band = min(_BAND_ROWS, h)
    xp = flat.new_zeros((n, band + 2, w + 2))  # the zero columns and first row stay zero
    rows_buf = flat.new_empty((n, band // 2 + 2, w))
    for r0 in range(0, h, band):
        r1 = min(h, r0 + band)
        a, b = max(0, r0 - 1), min(h, r1 + 1)
        xp[:, 1 - (r0 - a) : 1 + (b - r0), 1 : w + 1] = flat[:, a:b]
        if b == r1:  # the band ends at the mosaic's last row: the row below is zero
            xp[:, r1 - r0 + 1].zero_()
        _stencil_band(xp[:, : r1 - r0 + 2], out[:, :, r0:r1], p, rows_buf)
    return out


def _all_finite(x: torch.Tensor) -> bool:
    """Whether ``x`` holds no NaN or ±inf (one reduction: min and max propagate NaN)."""
    lo, hi = torch.aminmax(x)
    return bool(torch.isfinite(lo) & torch.isfinite(hi))


def demosaic_bilinear(x: torch.Tensor, pattern: str) -> torch.Tensor:
    """Bilinear demosaic by normalised convolution (see the module docstring).

    Evaluated colour by colour on whole rows in bands of rows (:func:`_stencil_band`), the
    normalisers applied to the first and last rows and columns only (they are 1 elsewhere): the
    same values as the normalised convolution of whole masked planes (:func:`_bilinear_reference`),
    bit for bit but for the sign of a zero, several times faster and with temporaries of one
    band. Two inputs take the masked-plane evaluation itself: a mosaic holding NaN or ±inf (there
    the products ``NaN·0`` of the masked-out samples spread a non-finite sample into every colour
    of its neighbourhood) and one that requires a gradient (the band evaluation writes in place).

    Args:
        x: ``(..., 1, H, W)`` floating-point mosaic, any device.
        pattern: CFA pattern string.

    Returns:
        ``(..., 3, H, W)`` RGB, same dtype/device; measured samples are reproduced exactly.
    """
    _check_mosaic(x, "x")
    if not x.is_floating_point():
        raise TypeError(f"x must be floating point for bilinear demosaic, got {x.dtype}")
    p = validate_cfa_pattern(pattern)
    lead, (h, w) = x.shape[:-3], x.shape[-2:]
    if h < 2 or w < 2:
        raise ValueError(f"mosaic must be at least 2x2, got {tuple(x.shape)}")
    flat = x.reshape(-1, h, w)
    if flat.shape[0] == 0:
        return x.new_empty((*lead, 3, h, w))
    if (x.requires_grad and torch.is_grad_enabled()) or not _all_finite(flat):
        return _bilinear_reference(flat[:, None], p).reshape(*lead, 3, h, w)
    out = _stencil_in_bands(flat, p)
    # the normalisers differ from 1 only on the first and last rows and columns
    dev = x.device
    ends_r, ends_c = torch.tensor([0, h - 1], device=dev), torch.tensor([0, w - 1], device=dev)
    den_rb, den_g = _bilinear_den(p, ends_r, torch.arange(w, device=dev), h, w, x.dtype)
    den = torch.stack([den_rb[0], den_g, den_rb[1]])  # (3, 2, W)
    out[:, :, 0] /= den[:, 0]
    out[:, :, h - 1] /= den[:, 1]
    den_rb, den_g = _bilinear_den(p, torch.arange(1, h - 1, device=dev), ends_c, h, w, x.dtype)
    den = torch.stack([den_rb[0], den_g, den_rb[1]])  # (3, H - 2, 2)
    out[:, :, 1 : h - 1, 0] /= den[..., 0]
    out[:, :, 1 : h - 1, w - 1] /= den[..., 1]
    return out.reshape(*lead, 3, h, w)


def demosaic(x: torch.Tensor, pattern: str, method: DemosaicMethod = "bilinear") -> torch.Tensor:
    """Dispatch to :func:`bayer_half` (``"half"``) or :func:`demosaic_bilinear` (``"bilinear"``)."""
    if method == "half":
        return bayer_half(x, pattern)
    if method == "bilinear":
        return demosaic_bilinear(x, pattern)
    raise ValueError(f"demosaic method must be 'half' or 'bilinear', got {method!r}")


def demosaic_saturation(
    saturated: torch.Tensor, pattern: str, method: DemosaicMethod = "bilinear"
) -> torch.Tensor:
    """Propagate a mosaic saturation mask through a demosaic.

    An output sample is flagged when *any* mosaic sample it was computed from (with non-zero
    weight) is saturated: the cell's own R/G/B samples for ``"half"``, the kernel support of the
    same colour for ``"bilinear"``.

    Args:
        saturated: ``(..., 1, H, W)`` bool.

    Returns:
        ``(..., 3, H', W')`` bool, matching :func:`demosaic`'s output size.
    """
    _check_mosaic(saturated, "saturated")
    sat = saturated.bool()
    if method == "half":
        return bayer_half(sat, pattern, reduce="any")
    if method != "bilinear":
        raise ValueError(f"demosaic method must be 'half' or 'bilinear', got {method!r}")
    lead, (h, w) = sat.shape[:-3], sat.shape[-2:]
    if h < 2 or w < 2:
        raise ValueError(f"mask must be at least 2x2, got {tuple(sat.shape)}")

    p = validate_cfa_pattern(pattern)
    flat = sat.reshape(-1, h, w)
    if flat.shape[0] == 0 or not bool(flat.any()):
        return torch.zeros((*lead, 3, h, w), dtype=torch.bool, device=sat.device)
    # the stencils of demosaic_bilinear, evaluated with logical OR on bool planes
    return _stencil_in_bands(flat, p).reshape(*lead, 3, h, w)
