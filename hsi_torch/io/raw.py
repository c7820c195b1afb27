"""Camera RAW files as *linear* sensor data (rawpy/LibRaw, never ``postprocess``: no white
balance, colour conversion, gamma, flips or LibRaw demosaic; ``docs/io_config_cli.md``, *Camera
RAW*).

Values are ``raw_image_visible − black`` (DN, float, per CFA position from
``black_level_per_channel``; not clipped), or divided by ``white − black`` with
``normalize=True``; saturated where the raw value is ``>= white_level``. The Bayer utilities live
in :mod:`hsi_torch.bayer` and are re-exported here.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from hsi_torch.bayer import (  # re-exported
    DemosaicMethod,
    bayer_half,
    demosaic_bilinear,
    demosaic_saturation,
    validate_cfa_pattern,
)
from hsi_torch.bayer import __all__ as bayer_names
from hsi_torch.bayer import cfa_masks as cfa_masks
from hsi_torch.bayer import demosaic as demosaic
from hsi_torch.bayer import mosaic as mosaic
from hsi_torch.errors import FileFormatError, MissingFileError

__all__ = ["RawImage", "load_raw", *bayer_names]

RAW_SUFFIXES = (
    ".kdc", ".dng", ".cr2", ".cr3", ".nef", ".nrw", ".arw", ".srf", ".sr2", ".orf", ".rw2",
    ".raf", ".pef", ".srw", ".3fr", ".erf", ".mef", ".mos", ".mrw", ".raw", ".rwl", ".iiq",
    ".x3f", ".dcr", ".k25", ".crw",
)  # fmt: skip


@dataclass
class RawImage:
    """Linear sensor data from a camera RAW file.

    Attributes:
        mosaic: ``(1, H, W)`` float Bayer mosaic, DN above black (or normalised, see
            ``normalized``).
        saturated: ``(1, H, W)`` bool, raw value ``>= white_level``.
        cfa_pattern: e.g. ``"GRBG"`` (top-left 2×2 cell, row-major).
        black_level: black level (DN) of the four CFA cell positions, row-major like
            ``cfa_pattern``.
        white_level: raw saturation level (DN).
        normalized: ``True`` when values were divided by ``white_level − black``.
        path: source file.
        rgb: ``(3, H', W')`` demosaiced linear RGB when a method was requested, else ``None``.
        rgb_saturated: ``(3, H', W')`` bool saturation of ``rgb`` (see :func:`demosaic_saturation`).
        demosaic: the method used for ``rgb`` (``None`` if not demosaiced).
        metadata: extra facts from LibRaw (sizes, camera white balance — informational only, never
            applied).
    """

    mosaic: torch.Tensor
    saturated: torch.Tensor
    cfa_pattern: str
    black_level: tuple[float, float, float, float]
    white_level: float
    normalized: bool
    path: Path
    rgb: torch.Tensor | None = None
    rgb_saturated: torch.Tensor | None = None
    demosaic: str | None = None
    metadata: dict[str, Any] = field(default_factory=dict)


def _decode(msg: Any) -> str:
    if isinstance(msg, bytes):
        return msg.decode("utf-8", "replace")
    return str(msg)


def load_raw(
    path: str | os.PathLike,
    demosaic: DemosaicMethod | None = None,
    normalize: bool = False,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> RawImage:
    """Read a camera RAW file as linear sensor data (no ``postprocess``).

    Args:
        path: RAW file (any format LibRaw reads: DNG, CR2, NEF, ARW, KDC, ...).
        demosaic: ``None`` (mosaic only), ``"half"`` or ``"bilinear"`` to also fill ``rgb``.
        normalize: divide by ``white − black`` per pixel so that saturation is 1.0.
        dtype, device: of the outputs (a floating dtype).

    Returns:
        :class:`RawImage`.

    Raises:
        MissingFileError: ``path`` does not exist (a ``FileNotFoundError``).
        FileFormatError: the file is not a readable RAW (corrupt, truncated, unsupported), or its
            sensor is not a 2×2 R/G/B Bayer sensor (X-Trans, Foveon and CMYG are not supported).
    """
    import rawpy  # lazy: LibRaw is only needed for RAW files

    p = Path(path)
    if not p.exists():
        raise MissingFileError(f"RAW file not found: {p}")
    if p.is_dir():
        raise FileFormatError(f"{p}: is a directory, expected a camera RAW file")
    if demosaic not in (None, "half", "bilinear"):
        raise ValueError(f"demosaic must be None, 'half' or 'bilinear', got {demosaic!r}")
    if not dtype.is_floating_point:
        raise TypeError(f"dtype must be a floating dtype, got {dtype}")
    try:
        with rawpy.imread(str(p)) as r:
            raw = np.array(r.raw_image_visible, dtype=np.uint16, copy=True)
            colors = np.array(r.raw_colors_visible[:6, :6], copy=True)
            desc = _decode(r.color_desc)
            black_pc = [float(b) for b in r.black_level_per_channel]
            white = float(r.white_level)
            wb = [float(v) for v in r.camera_whitebalance]
            sizes = r.sizes._asdict()
    except rawpy.LibRawError as exc:
        raise FileFormatError(
            f"{p}: cannot read as a camera RAW file ({type(exc).__name__}: {_decode(exc)}); "
            "it is corrupt, truncated or not a format LibRaw supports"
        ) from exc
    if raw.ndim != 2:
        raise FileFormatError(
            f"{p}: RAW data has shape {raw.shape}; only single-plane Bayer sensors are supported")
    h, w = raw.shape
    if h < 2 or w < 2:
        raise FileFormatError(f"{p}: RAW image is too small ({h}x{w})")
    cell = colors[:2, :2]
    periodic = np.array_equal(np.tile(cell, (3, 3))[: colors.shape[0], : colors.shape[1]], colors)
    try:
        pattern = "".join(desc[int(i)] for i in cell.ravel())
        pattern = validate_cfa_pattern(pattern)
    except (IndexError, ValueError):
        pattern = ""
    if not periodic or not pattern:
        raise FileFormatError(
            f"{p}: unsupported colour filter array (colour description {desc!r}, top-left cell "
            f"{cell.tolist()}); only 2x2 R/G/B Bayer sensors are supported")
    black_cell = tuple(black_pc[int(i)] for i in cell.ravel())

    data = torch.from_numpy(raw.astype(np.float32)).to(device=device)
    sat = (data >= white)[None]
    black_map = torch.tensor(black_cell, dtype=torch.float32, device=data.device).reshape(2, 2)
    black_map = black_map.repeat((h + 1) // 2, (w + 1) // 2)[:h, :w]
    lin = data - black_map
    if normalize:
        span = white - black_map
        if bool((span <= 0).any()):
            raise FileFormatError(f"{p}: white level {white} is not above black level {black_cell}")
        lin = lin / span
    lin = lin.to(dtype)[None]

    out = RawImage(
        mosaic=lin,
        saturated=sat,
        cfa_pattern=pattern,
        black_level=black_cell,  # type: ignore[arg-type]
        white_level=white,
        normalized=normalize,
        path=p,
        metadata={"sizes": sizes, "color_desc": desc, "camera_whitebalance": wb})
    if demosaic is not None:
        half = demosaic == "half"
        out.rgb = bayer_half(lin, pattern) if half else demosaic_bilinear(lin, pattern)
        out.rgb_saturated = demosaic_saturation(sat, pattern, demosaic)
        out.demosaic = demosaic
    return out
