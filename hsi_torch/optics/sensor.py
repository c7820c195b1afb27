"""Sensor and diffuser radiometry of the virtual prototype.

Signal chain of :meth:`SensorModel.expose` (per pixel, all batched torch):

1. optional Gaussian PSF on the sensor (``psf_sigma_px``, :func:`gaussian_blur`);
2. Bayer mosaic (``output='bayer'``, :func:`mosaic`) or three full planes (``output='rgb'``);
3. mean electrons ``μ = exposure · scale · E`` where ``E`` is the input (``scale`` = full-well
   electrons for ``input_units='relative'``, so ``E·exposure = 1`` fills the well; 1 for
   ``'electrons'``); optional fixed patterns (off by default): ``μ ← μ · (1 + σ_PRNU·z_p)``
   (pixel gain non-uniformity), ``+ hot_pixel_level · full well`` on hot pixels, ``0`` on dead
   pixels — the same map in every exposure (seeded by ``pattern_seed``);
4. photon shot noise ``N_e ~ Poisson(μ)`` (``shot_noise``); optional non-linearity near
   saturation (``nonlinearity``: above ``knee`` of the full well the charge read is
   ``N_e − nonlinearity · FW · ((N_e/FW − knee)/(1 − knee))²``); clipped at the full well;
5. read noise ``+ N(0, σ_read²)`` electrons;
6. conversion to digital numbers ``DN = N_e / (electrons per DN) + black_level``, rounding
   (``quantize``) and clipping to ``[0, white_level]``; pixels at the full well or the white level
   are flagged saturated and read exactly the white level.

Noise is drawn from a ``torch.Generator`` seeded with ``seed`` (one per device, advancing from call
to call; :meth:`SensorModel.reseed` restarts the sequence) or from a generator passed explicitly.

CFA patterns are named by the 2 × 2 tile read row-major from pixel ``(x, y) = (0, 0)``:
``'RGGB'`` means row 0 = R G, row 1 = G B. Channel order of RGB tensors is R, G, B.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import torch

from hsi_torch import bayer as _bayer

__all__ = [
    "CFA_PATTERNS",
    "cfa_index",
    "cfa_masks",
    "cfa_pattern_from_rawpy",
    "mosaic",
    "demosaic_bilinear",
    "bin_bayer",
    "gaussian_blur",
    "diffuser_falloff",
    "DiffuserModel",
    "Exposure",
    "SensorModel",
]

CFA_PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")
_CH = {"R": 0, "G": 1, "B": 2}


def _check_pattern(pattern: str) -> str:
    if not isinstance(pattern, str) or pattern.upper() not in CFA_PATTERNS:
        raise ValueError(f"cfa pattern must be one of {CFA_PATTERNS}, got {pattern!r}")
    return pattern.upper()


def cfa_index(pattern: str = "RGGB") -> list[list[int]]:
    """Channel index (0 = R, 1 = G, 2 = B) of the 2 × 2 CFA tile, ``[row][col]``."""
    p = _check_pattern(pattern)
    return [[_CH[p[0]], _CH[p[1]]], [_CH[p[2]], _CH[p[3]]]]


def cfa_pattern_from_rawpy(raw_pattern, color_desc: bytes | str = b"RGBG") -> str:
    """Pattern name from rawpy's ``raw_pattern`` (2 × 2 indices) and ``color_desc``.

    Example: the Kodak DC50 file has ``raw_pattern = [[1, 0], [2, 3]]``, ``'RGBG'`` → ``'GRBG'``.
    """
    desc = color_desc.decode() if isinstance(color_desc, bytes) else str(color_desc)
    try:
        idx = [int(raw_pattern[r][c]) for r in range(2) for c in range(2)]
        name = "".join(desc[i] for i in idx)
    except (IndexError, TypeError, ValueError) as exc:
        raise ValueError(
            f"raw_pattern {raw_pattern!r} / color_desc {desc!r} is not a 2x2 CFA"
        ) from exc
    return _check_pattern(name)


def cfa_masks(
    pattern: str,
    height: int,
    width: int,
    *,
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
) -> torch.Tensor:
    """One-hot CFA masks ``(3, H, W)``: ``masks[c, y, x] = 1`` where pixel ``(x, y)`` sees ``c``.

    Thin wrapper of :func:`hsi_torch.bayer.cfa_masks` (one CFA implementation for the
    simulator and the loaders).
    """
    return _bayer.cfa_masks(
        _check_pattern(pattern),
        height,
        width,
        device=device,
        dtype=dtype or torch.get_default_dtype(),
    )


def _check_image(x: torch.Tensor, channels: int | None, name: str) -> torch.Tensor:
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    if x.ndim < 3:
        raise ValueError(f"{name} must have shape (..., C, H, W), got {tuple(x.shape)}")
    if channels is not None and x.shape[-3] != channels:
        raise ValueError(f"{name} must have {channels} channel(s) at dim -3, got {tuple(x.shape)}")
    if not x.is_floating_point():
        x = x.to(torch.get_default_dtype())
    return x


def mosaic(rgb: torch.Tensor, pattern: str = "RGGB") -> torch.Tensor:
    """Sample an RGB image ``(..., 3, H, W)`` through a Bayer CFA → ``(..., 1, H, W)``.

    Same as :func:`hsi_torch.bayer.mosaic` with a default pattern.
    """
    return _bayer.mosaic(_check_image(rgb, 3, "rgb"), _check_pattern(pattern))


def demosaic_bilinear(raw: torch.Tensor, pattern: str = "RGGB") -> torch.Tensor:
    """Bilinear demosaic ``(..., 1, H, W)`` → ``(..., 3, H, W)`` by normalised convolution.

    Known samples are kept exactly and borders use only the samples that exist. Delegates to
    :func:`hsi_torch.bayer.demosaic_bilinear`.
    """
    return _bayer.demosaic_bilinear(_check_image(raw, 1, "raw"), _check_pattern(pattern))


def bin_bayer(raw: torch.Tensor, pattern: str = "RGGB") -> torch.Tensor:
    """Half-size RGB ``(..., 3, H // 2, W // 2)`` by 2 × 2 binning (R, mean of the two G, B).

    A trailing odd row/column is dropped; output pixel ``(x, y)`` is centred on raw coordinate
    ``(2x + 0.5, 2y + 0.5)``. Delegates to :func:`hsi_torch.bayer.bayer_half`.
    """
    return _bayer.bayer_half(_check_image(raw, 1, "raw"), _check_pattern(pattern))


def gaussian_blur(image: torch.Tensor, sigma_px: float, border: str = "reflect") -> torch.Tensor:
    """Isotropic Gaussian PSF (``kornia.filters.gaussian_blur2d``), kernel ±3σ.

    Args:
        image: ``(..., C, H, W)``.
        sigma_px: standard deviation in pixels; ``0`` returns the input unchanged.
        border: kornia border mode (``'reflect'``, ``'replicate'``, ``'constant'``, ``'circular'``).
    """
    image = _check_image(image, None, "image")
    if sigma_px < 0:
        raise ValueError(f"sigma_px must be >= 0, got {sigma_px}")
    if sigma_px == 0:
        return image
    import kornia

    half = max(1, int(math.ceil(3.0 * sigma_px)))
    lead, (c, h, w) = image.shape[:-3], image.shape[-3:]
    x = image.reshape(-1, c, h, w)
    if border == "reflect" and (half >= h or half >= w):
        border = "replicate"
    out = kornia.filters.gaussian_blur2d(
        x, (2 * half + 1, 2 * half + 1), (float(sigma_px), float(sigma_px)), border_type=border
    )
    return out.reshape(*lead, c, h, w)


def diffuser_falloff(alpha: torch.Tensor, k: float = 2.0) -> torch.Tensor:
    """Relative radiance of the diffuser towards angle ``alpha`` (rad from the normal): cos^k(α).

    ``k = 0`` is a Lambertian diffuser (constant radiance); larger ``k`` is more forward scattering.
    Angles beyond 90° give 0.
    """
    alpha = torch.as_tensor(alpha)
    if not alpha.is_floating_point():
        alpha = alpha.to(torch.get_default_dtype())
    if k < 0:
        raise ValueError(f"fall-off exponent k must be >= 0, got {k}")
    return torch.cos(alpha).clamp_min(0.0).pow(k)


@dataclass
class DiffuserModel:
    """The diffuser at the objective's image plane.

    Attributes:
        falloff_k: exponent of the angular fall-off ``cos^k(α)`` (see :func:`diffuser_falloff`).
            Default 2: a mildly forward-scattering ground-glass diffuser (an assumed value; the
            calibration absorbs it into the per-view throughput ``g_v``).
        blur_sigma_mm: Gaussian blur of the scene by the diffuser, σ in mm on the diffuser plane
            (default 0.1 mm, the default prototype's ground glass; 0 = none).
    """

    falloff_k: float = 2.0
    blur_sigma_mm: float = 0.1

    def __post_init__(self) -> None:
        if self.falloff_k < 0:
            raise ValueError(f"falloff_k must be >= 0, got {self.falloff_k}")
        if self.blur_sigma_mm < 0:
            raise ValueError(f"blur_sigma_mm must be >= 0, got {self.blur_sigma_mm}")

    def falloff(self, alpha: torch.Tensor) -> torch.Tensor:
        """``cos^k(α)`` for angles ``alpha`` (rad), any shape."""
        return diffuser_falloff(alpha, self.falloff_k)

    def blur(self, image: torch.Tensor, pixel_size_mm: float) -> torch.Tensor:
        """Blur a diffuser-plane image ``(..., C, H, W)`` sampled every ``pixel_size_mm``."""
        if pixel_size_mm <= 0:
            raise ValueError(f"pixel_size_mm must be > 0, got {pixel_size_mm}")
        return gaussian_blur(image, self.blur_sigma_mm / pixel_size_mm)


class Exposure(NamedTuple):
    """Result of :meth:`SensorModel.expose`."""

    dn: torch.Tensor
    """Digital numbers (float tensor holding integers when ``quantize``), ``(..., C, H, W)``."""
    saturated: torch.Tensor
    """Bool mask, same shape: full well reached or DN ≥ white level; these read the white level."""


_OUTPUTS = ("bayer", "rgb")
_UNITS = ("relative", "electrons")


@dataclass
class SensorModel:
    """Raw sensor: CFA, exposure, shot + read noise, black/white level, saturation.

    Attributes:
        output: ``'bayer'`` (one mosaicked plane) or ``'rgb'`` (three full planes, as a
            3-sensor or demosaicked camera without interpolation error).
        cfa_pattern: 2 × 2 CFA tile, one of ``'RGGB'``, ``'BGGR'``, ``'GRBG'``, ``'GBRG'``.
        bit_depth: ADC bits; sets the default ``white_level = 2**bit_depth − 1``.
        white_level: clipping level in DN (``None``: from ``bit_depth``).
        black_level: offset added to every pixel, DN.
        full_well_e: full-well capacity in electrons; electrons are clipped there. ``None``: no
            well clipping (then ``electrons_per_dn`` is required).
        electrons_per_dn: conversion gain; ``None``: ``full_well_e / (white_level − black_level)``
            so a full well reads exactly the white level.
        read_noise_e: read noise σ in electrons (Gaussian).
        shot_noise: draw Poisson photon noise.
        exposure: multiplies the input (exposure time × gain of the optics).
        input_units: ``'relative'``: input × exposure = 1 means a full well (or the white level
            when no full well is set); ``'electrons'``: input × exposure is the mean electron count.
        quantize: round to integer DN.
        psf_sigma_px: Gaussian PSF on the sensor, σ in pixels (0 = none), before the mosaic.
        seed: seed of the noise generator (``None``: nondeterministic).
        nonlinearity: fraction of the charge lost at the full well (0 = linear response);
            ``nonlinearity_knee``: fraction of the full well where the loss starts (quadratic
            from there, so the response and its slope are continuous).
        prnu_sigma: relative σ of the per-pixel gain (photo-response non-uniformity).
        hot_pixel_fraction, hot_pixel_level: pixels with an extra fixed charge of
            ``hot_pixel_level`` full wells (in every exposure, dark frames included).
        dead_pixel_fraction: pixels that collect no photo-charge (they read black + read noise).
        pattern_seed: seed of the fixed patterns (PRNU, hot, dead), drawn on the CPU per sensor
            size so every device and every exposure sees the same pixels.

    Defaults describe a generic 14-bit DSLR raw at low ISO (black 512 DN, 30 000 e⁻ full well,
    3 e⁻ read noise): representative values, not one camera's datasheet.
    """

    output: str = "bayer"
    cfa_pattern: str = "RGGB"
    bit_depth: int = 14
    white_level: float | None = None
    black_level: float = 512.0
    full_well_e: float | None = 30000.0
    electrons_per_dn: float | None = None
    read_noise_e: float = 3.0
    shot_noise: bool = True
    exposure: float = 1.0
    input_units: str = "relative"
    quantize: bool = True
    psf_sigma_px: float = 0.0
    seed: int | None = 0
    nonlinearity: float = 0.0
    nonlinearity_knee: float = 0.7
    prnu_sigma: float = 0.0
    hot_pixel_fraction: float = 0.0
    hot_pixel_level: float = 0.2
    dead_pixel_fraction: float = 0.0
    pattern_seed: int = 1
    _generators: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.output not in _OUTPUTS:
            raise ValueError(f"output must be one of {_OUTPUTS}, got {self.output!r}")
        self.cfa_pattern = _check_pattern(self.cfa_pattern)
        if self.input_units not in _UNITS:
            raise ValueError(f"input_units must be one of {_UNITS}, got {self.input_units!r}")
        if not 1 <= int(self.bit_depth) <= 32:
            raise ValueError(f"bit_depth must be in 1..32, got {self.bit_depth}")
        if not 0 <= self.black_level < self.white:
            raise ValueError(
                f"black_level {self.black_level} must lie in [0, white_level={self.white})"
            )
        if self.full_well_e is None and self.electrons_per_dn is None:
            raise ValueError("give full_well_e or electrons_per_dn")
        if self.full_well_e is not None and self.full_well_e <= 0:
            raise ValueError(f"full_well_e must be > 0, got {self.full_well_e}")
        if self.electrons_per_dn is not None and self.electrons_per_dn <= 0:
            raise ValueError(f"electrons_per_dn must be > 0, got {self.electrons_per_dn}")
        if self.read_noise_e < 0:
            raise ValueError(f"read_noise_e must be >= 0, got {self.read_noise_e}")
        if self.exposure < 0:
            raise ValueError(f"exposure must be >= 0, got {self.exposure}")
        if self.psf_sigma_px < 0:
            raise ValueError(f"psf_sigma_px must be >= 0, got {self.psf_sigma_px}")
        for name in ("nonlinearity", "nonlinearity_knee", "hot_pixel_fraction",
                     "dead_pixel_fraction"):
            if not 0 <= getattr(self, name) < 1:
                raise ValueError(f"{name} must be in [0, 1), got {getattr(self, name)}")
        if self.prnu_sigma < 0 or self.hot_pixel_level <= 0:
            raise ValueError(f"prnu_sigma must be >= 0 and hot_pixel_level > 0, got "
                             f"{self.prnu_sigma}, {self.hot_pixel_level}")

    # ---------------------------------------------------------------- derived quantities
    @property
    def white(self) -> float:
        """White level in DN."""
        if self.white_level is not None:
            return float(self.white_level)
        return float(2 ** int(self.bit_depth) - 1)

    @property
    def gain_e_per_dn(self) -> float:
        """Conversion gain in electrons per DN."""
        if self.electrons_per_dn is not None:
            return float(self.electrons_per_dn)
        return float(self.full_well_e) / (self.white - self.black_level)

    @property
    def electrons_at_unity(self) -> float:
        """Electrons for a relative input × exposure of 1 (the full well, or the white level)."""
        if self.full_well_e is not None:
            return float(self.full_well_e)
        return (self.white - self.black_level) * self.gain_e_per_dn

    # ---------------------------------------------------------------- RNG
    def reseed(self, seed: int | None = None) -> None:
        """Restart the noise sequence (optionally with a new seed) on every device."""
        if seed is not None:
            self.seed = seed
        self._generators.clear()

    def generator(self, device: torch.device | str) -> torch.Generator:
        """The model's generator on ``device`` (created from ``seed`` on first use)."""
        dev = torch.device(device)
        key = str(dev)
        gen = self._generators.get(key)
        if gen is None:
            gen = torch.Generator(device=dev)
            if self.seed is None:
                gen.seed()
            else:
                gen.manual_seed(int(self.seed))
            self._generators[key] = gen
        return gen

    # ---------------------------------------------------------------- imaging
    def mosaic(self, rgb: torch.Tensor) -> torch.Tensor:
        """``(..., 3, H, W)`` → ``(..., 1, H, W)`` with this sensor's CFA."""
        return mosaic(rgb, self.cfa_pattern)

    def demosaic(self, raw: torch.Tensor) -> torch.Tensor:
        """Bilinear demosaic ``(..., 1, H, W)`` → ``(..., 3, H, W)``."""
        return demosaic_bilinear(raw, self.cfa_pattern)

    def bin2x2(self, raw: torch.Tensor) -> torch.Tensor:
        """Half-size binning ``(..., 1, H, W)`` → ``(..., 3, H//2, W//2)``."""
        return bin_bayer(raw, self.cfa_pattern)

    @property
    def has_fixed_pattern(self) -> bool:
        """PRNU, hot or dead pixels are on."""
        return (self.prnu_sigma > 0 or self.hot_pixel_fraction > 0 or self.dead_pixel_fraction > 0)

    def fixed_pattern(
        self, height: int, width: int, device: torch.device | str | None = None,
        dtype: torch.dtype = torch.float64,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(gain, hot, dead)`` maps ``(H, W)``: PRNU gain ``1 + σ z``, hot and dead masks.

        Drawn from a CPU generator seeded with ``pattern_seed`` (same pixels on every device
        and in every exposure); a pixel is not both hot and dead.
        """
        gen = torch.Generator().manual_seed(int(self.pattern_seed))
        z = torch.randn(height, width, generator=gen, dtype=torch.float64)
        u = torch.rand(height, width, generator=gen, dtype=torch.float64)
        gain = (1.0 + self.prnu_sigma * z).clamp_min(0.0)
        hot = u < self.hot_pixel_fraction
        dead = (u >= 1.0 - self.dead_pixel_fraction) & ~hot
        return gain.to(device=device, dtype=dtype), hot.to(device), dead.to(device)

    def mean_electrons(self, irradiance: torch.Tensor) -> torch.Tensor:
        """Noise-free electrons ``exposure · scale · E`` (no mosaic, no clipping)."""
        scale = self.electrons_at_unity if self.input_units == "relative" else 1.0
        return irradiance * (self.exposure * scale)

    def expose(
        self, irradiance: torch.Tensor, generator: torch.Generator | None = None
    ) -> Exposure:
        """Turn irradiance into raw digital numbers.

        Args:
            irradiance: ``(..., 3, H, W)`` per-channel signal (R, G, B; already weighted by the
                camera sensitivities), or ``(..., 1, H, W)`` already mosaicked when
                ``output='bayer'``. Units per ``input_units``; negative values are clipped to 0.
            generator: noise generator on the input's device (default: the model's own, see
                :meth:`generator`).

        Returns:
            :class:`Exposure` ``(dn, saturated)``, ``dn`` of shape ``(..., 1, H, W)`` for
            ``'bayer'`` or ``(..., 3, H, W)`` for ``'rgb'``, in the input's floating dtype.
        """
        x = _check_image(irradiance, None, "irradiance")
        c = x.shape[-3]
        if self.output == "rgb" and c != 3:
            raise ValueError(f"output='rgb' needs 3 input channels, got shape {tuple(x.shape)}")
        if self.output == "bayer" and c not in (1, 3):
            raise ValueError(f"output='bayer' needs 1 or 3 input channels, got {tuple(x.shape)}")
        if self.psf_sigma_px > 0:
            if c != 3 and self.output == "bayer":
                raise ValueError("psf_sigma_px needs the 3-channel irradiance (blur before mosaic)")
            x = gaussian_blur(x, self.psf_sigma_px)
        if self.output == "bayer" and c == 3:
            x = self.mosaic(x)
        gen = generator if generator is not None else self.generator(x.device)
        e = self.mean_electrons(x).clamp_min(0.0)
        fw = self.electrons_at_unity
        if self.has_fixed_pattern:
            gain, hot, dead = self.fixed_pattern(e.shape[-2], e.shape[-1], e.device, e.dtype)
            e = torch.where(dead, 0.0, e * gain + hot.to(e.dtype) * (self.hot_pixel_level * fw))
        if self.shot_noise:
            e = torch.poisson(e, generator=gen)
        if self.nonlinearity > 0:
            k = self.nonlinearity_knee
            over = (e / fw - k).clamp_min(0.0) / (1.0 - k)
            e = e - self.nonlinearity * fw * over * over
        saturated = torch.zeros_like(e, dtype=torch.bool)
        if self.full_well_e is not None:
            saturated = e >= self.full_well_e
            e = e.clamp_max(self.full_well_e)
        if self.read_noise_e > 0:
            noise = torch.randn(e.shape, generator=gen, device=e.device, dtype=e.dtype)
            e = e + self.read_noise_e * noise
        dn = e / self.gain_e_per_dn + self.black_level
        if self.quantize:
            dn = torch.round(dn)
        saturated = saturated | (dn >= self.white)
        dn = torch.where(saturated, torch.full_like(dn, self.white), dn.clamp_min(0.0))
        return Exposure(dn, saturated)

    def to_dict(self) -> dict:
        """Plain-data description (for metadata / configs)."""
        return {
            "output": self.output,
            "cfa_pattern": self.cfa_pattern,
            "bit_depth": int(self.bit_depth),
            "white_level": self.white,
            "black_level": float(self.black_level),
            "full_well_e": None if self.full_well_e is None else float(self.full_well_e),
            "electrons_per_dn": self.gain_e_per_dn,
            "read_noise_e": float(self.read_noise_e),
            "shot_noise": bool(self.shot_noise),
            "exposure": float(self.exposure),
            "input_units": self.input_units,
            "quantize": bool(self.quantize),
            "psf_sigma_px": float(self.psf_sigma_px),
            "seed": self.seed,
            "nonlinearity": float(self.nonlinearity),
            "nonlinearity_knee": float(self.nonlinearity_knee),
            "prnu_sigma": float(self.prnu_sigma),
            "hot_pixel_fraction": float(self.hot_pixel_fraction),
            "hot_pixel_level": float(self.hot_pixel_level),
            "dead_pixel_fraction": float(self.dead_pixel_fraction),
            "pattern_seed": int(self.pattern_seed),
        }
