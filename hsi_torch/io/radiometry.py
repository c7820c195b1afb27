"""Radiometric facts shared by calibration and reconstruction: the black level a capture was read
with and where it came from, the exposure, the camera's identity, and the *pedestal* — what the
sensor reads, after black subtraction, where no view of the kaleidoscope reaches.

Conventions:
    - Black levels are DN of the stored values. :func:`black_level_rgb` turns any form a file or
      setting gives (a scalar, 4 values of the Bayer cell in row-major order, 3 values for R, G, B)
      into one value per colour ``[R, G, B]``; that is what a calibration bundle records.
    - A capture's exposure is its metadata's ``exposure_s`` (seconds), else the simulator's
      relative ``exposure`` (a unitless multiplier); :func:`capture_exposure` says which.
    - The pedestal of a capture is the per-colour median of the linear image (stored − black)
      over sensor pixels farther than a margin from every view triangle
      (:func:`outside_views_index`); it is ≈ 0 when the black level is right (stray light
      aside), and the black level that was missed when it is not.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch

from hsi_torch.io.raw import validate_cfa_pattern

__all__ = [
    "PEDESTAL_FRACTION",
    "PEDESTAL_SIGMAS",
    "CameraIdentity",
    "black_level_rgb",
    "camera_mismatches",
    "capture_exposure",
    "default_margin_px",
    "outside_views_index",
    "pedestal_level",
    "pedestal_limit",
]

#: The pedestal limit's share of the white level's span above black (0.25 %: 41 DN of 14-bit
#: data, 10 DN of 12-bit data, 164 DN of 16-bit data).
PEDESTAL_FRACTION = 0.0025
#: The pedestal limit in robust standard deviations of the outside pixels (their noise).
PEDESTAL_SIGMAS = 5.0
#: At most this many outside pixels are looked at per frame (a regular sample).
PEDESTAL_MAX_SAMPLES = 65_536


# ----------------------------------------------------------------------------------- levels


def black_level_rgb(level: Any, cfa_pattern: str | None = None) -> list[float] | None:
    """A black level as one value per colour ``[R, G, B]`` (DN).

    Args:
        level: a number, 3 values (R, G, B) or 4 values of the Bayer cell (row-major; needs
            ``cfa_pattern``, the two greens are averaged).
        cfa_pattern: the mosaic's pattern (``"RGGB"``, ...), for 4 values.

    Returns:
        ``[R, G, B]`` floats, or ``None`` for ``None`` or a form that cannot be read so (4 values
        without a pattern, non-numbers).
    """
    if level is None:
        return None
    try:
        v = np.atleast_1d(np.asarray(level, dtype=np.float64)).ravel()
    except (TypeError, ValueError, OverflowError):
        return None
    if not np.all(np.isfinite(v)):
        return None
    if v.size == 1:
        return [float(v[0])] * 3
    if v.size == 3:
        return [float(x) for x in v]
    if v.size == 4 and cfa_pattern:
        try:
            colours = ["RGB".index(ch) for ch in validate_cfa_pattern(cfa_pattern)]
        except (TypeError, ValueError):
            return None
        return [float(np.mean([v[i] for i in range(4) if colours[i] == c])) for c in range(3)]
    return None


def capture_exposure(metadata: Mapping[str, Any]) -> tuple[Any, str | None, str | None]:
    """A capture's exposure from its metadata: ``(value, unit, source)``.

    ``exposure_s`` gives ``unit = "s"`` (its source: the metadata's ``exposure_source``, else
    ``"file"``); the simulator's relative ``exposure`` gives ``unit = "relative"``; neither gives
    ``(None, None, None)``. The value is returned as stored (checked by the caller).
    """
    v = metadata.get("exposure_s")
    if v is not None:
        return v, "s", str(metadata.get("exposure_source") or "file")
    v = metadata.get("exposure")
    if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0:
        return float(v), "relative", "metadata 'exposure' (relative)"
    return None, None, None


# ----------------------------------------------------------------------------------- pedestal


def default_margin_px(sensor_size: Sequence[int]) -> float:
    """Distance from every view triangle beyond which the sensor is taken as unlit: 1 % of the
    sensor's shorter side, at least 4 px (the edges of the views are blurred by the diffuser, the
    optics and the demosaic)."""
    return max(4.0, 0.01 * min(int(sensor_size[0]), int(sensor_size[1])))


def outside_views_index(
    triangles: Any,
    sensor_size: Sequence[int],
    margin_px: float | None = None,
    max_samples: int = PEDESTAL_MAX_SAMPLES,
) -> np.ndarray:
    """Flat (row-major) indices of sensor pixels that no view reaches: farther than ``margin_px``
    from every triangle's edge lines, on a regular grid of at most about ``max_samples`` pixels.

    Args:
        triangles: ``(V, 3, 2)`` view triangles, sensor px ``(x, y)``.
        sensor_size: ``(H, W)``.
        margin_px: default :func:`default_margin_px`.

    Returns:
        ``(K,)`` int64 indices into ``H·W`` (empty when the views cover the sensor).
    """
    H, W = (int(v) for v in sensor_size)
    m = default_margin_px((H, W)) if margin_px is None else float(margin_px)
    tri = np.asarray(triangles, dtype=np.float64).reshape(-1, 3, 2)
    stride = max(1, math.ceil(math.sqrt(H * W / max(1, 4 * max_samples))))
    stride += stride % 2 == 0 and stride > 1  # odd: every colour site of a mosaic is sampled
    ys, xs = np.mgrid[0:H:stride, 0:W:stride]
    px, py = xs.ravel().astype(np.float64), ys.ravel().astype(np.float64)
    out = np.ones(px.shape, dtype=bool)
    for t in tri:
        # signed distance to each edge line, positive outside (either winding)
        area = (t[1, 0] - t[0, 0]) * (t[2, 1] - t[0, 1]) - (t[1, 1] - t[0, 1]) * (t[2, 0] - t[0, 0])
        sgn = -1.0 if area > 0 else 1.0
        dmax = np.full(px.shape, -np.inf)
        for i in range(3):
            a, b = t[i], t[(i + 1) % 3]
            ex, ey = b[0] - a[0], b[1] - a[1]
            n = math.hypot(ex, ey) or 1.0
            d = sgn * (ex * (py - a[1]) - ey * (px - a[0])) / n
            dmax = np.maximum(dmax, d)
        out &= dmax > m  # outside this triangle by more than the margin
    idx = (py[out].astype(np.int64) * W + px[out].astype(np.int64))
    if idx.size > max_samples:
        idx = idx[np.linspace(0, idx.size - 1, max_samples).round().astype(np.int64)]
    return idx


def pedestal_level(image: torch.Tensor, index: Any) -> tuple[list[float], list[float]] | None:
    """Per-colour median and robust standard deviation (1.4826 · MAD) of ``image (C, H, W)`` at
    the flat pixel indices ``index``; ``None`` when there are fewer than 16 of them."""
    idx = torch.as_tensor(np.asarray(index, dtype=np.int64), device=image.device)
    if idx.numel() < 16:
        return None
    x = image.detach().reshape(image.shape[0], -1).index_select(1, idx).to(torch.float64)
    x = torch.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0)
    med = x.median(dim=1).values
    mad = (x - med[:, None]).abs().median(dim=1).values
    return [float(v) for v in med.cpu()], [float(1.4826 * v) for v in mad.cpu()]


def pedestal_limit(white_span: float | None, sigma: float) -> float:
    """The largest pedestal taken as 0: ``max(PEDESTAL_FRACTION · white span,
    PEDESTAL_SIGMAS · σ)``, at least 1 DN (the span: white level − black level, DN; ``None``
    when unknown)."""
    parts = [PEDESTAL_SIGMAS * float(sigma), 1.0]
    if white_span is not None and math.isfinite(white_span) and white_span > 0:
        parts.append(PEDESTAL_FRACTION * float(white_span))
    return max(parts)


# ----------------------------------------------------------------------------------- identity


def _text(v: Any) -> str | None:
    if v is None:
        return None
    s = " ".join(str(v).split())
    return s or None


def _number(v: Any) -> float | None:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        return None
    return float(v)


@dataclass(frozen=True)
class CameraIdentity:
    """What identifies the camera a capture (or a calibration) was made with; ``None`` = unknown.

    Attributes:
        make, model: from the file (RAW/DNG/EXIF) or the capture set's sheet/manifest.
        cfa_pattern: Bayer pattern of the mosaic (``None`` for RGB captures).
        sensor_size: ``(H, W)`` px.
        black_level, white_level: the levels the file itself states (``[R, G, B]`` DN and DN);
            ``None`` when they were not the file's own (a setting, a default).
    """

    make: str | None = None
    model: str | None = None
    cfa_pattern: str | None = None
    sensor_size: tuple[int, int] | None = None
    black_level: tuple[float, float, float] | None = None
    white_level: float | None = None

    @classmethod
    def from_metadata(
        cls, metadata: Mapping[str, Any], sensor_size: Sequence[int] | None = None,
        levels_from_file: bool | None = None,
    ) -> CameraIdentity:
        """From a :class:`~hsi_torch.io.LinearCapture`'s metadata (keys ``camera_make``,
        ``camera_model`` (also ``make``/``model``), ``cfa_pattern``, ``black_level``,
        ``white_level``, ``black_level_source``). The levels count only when they are the file's
        own: ``levels_from_file``, else ``black_level_source == "file"``."""
        own = levels_from_file
        if own is None:
            own = metadata.get("black_level_source") == "file"
        pattern = metadata.get("cfa_pattern") if metadata.get("kind", "bayer") == "bayer" else None
        black = black_level_rgb(metadata.get("black_level"), pattern) if own else None
        return cls(
            make=_text(metadata.get("camera_make", metadata.get("make"))),
            model=_text(metadata.get("camera_model", metadata.get("model"))),
            cfa_pattern=_text(pattern).upper() if _text(pattern) else None,
            sensor_size=None if sensor_size is None else (int(sensor_size[0]),
                                                          int(sensor_size[1])),
            black_level=None if black is None else (black[0], black[1], black[2]),
            white_level=_number(metadata.get("white_level")) if own else None)  # fmt: skip

    @classmethod
    def from_dict(cls, d: Any) -> CameraIdentity | None:
        """From :meth:`to_dict`'s form (a bundle's ``settings["camera"]``); ``None`` for anything
        that is not a dict. Unreadable entries become ``None``."""
        if not isinstance(d, Mapping):
            return None
        size = d.get("sensor_size")
        ok_size = isinstance(size, (list, tuple)) and len(size) == 2 and all(
            isinstance(v, int) and not isinstance(v, bool) for v in size)  # fmt: skip
        black = black_level_rgb(d.get("black_level"))
        return cls(
            make=_text(d.get("make")), model=_text(d.get("model")),
            cfa_pattern=_text(d.get("cfa_pattern")),
            sensor_size=(int(size[0]), int(size[1])) if ok_size else None,
            black_level=None if black is None else (black[0], black[1], black[2]),
            white_level=_number(d.get("white_level")))  # fmt: skip

    def to_dict(self) -> dict[str, Any]:
        """A JSON-able dict (lists for tuples)."""
        d = asdict(self)
        for k in ("sensor_size", "black_level"):
            if d[k] is not None:
                d[k] = list(d[k])
        return d

    @property
    def name(self) -> str | None:
        """``"make model"`` (the make left out when the model starts with it), or ``None``."""
        if self.model and self.make and not self.model.lower().startswith(self.make.lower()):
            return f"{self.make} {self.model}"
        return self.model or self.make

    def merged(self, other: CameraIdentity) -> CameraIdentity:
        """This identity with its unknown fields taken from ``other``."""
        return CameraIdentity(**{k: (v if v is not None else getattr(other, k))
                                 for k, v in asdict(self).items()})  # fmt: skip


def camera_mismatches(bundle: CameraIdentity | None, capture: CameraIdentity) -> list[str]:
    """How a capture's camera differs from the one the bundle was calibrated with: one sentence
    per difference, only where both sides know the field (make/model, CFA pattern, sensor size,
    the file's own black and white levels)."""
    if bundle is None:
        return []
    out: list[str] = []

    def norm(s: str | None) -> str:
        return " ".join((s or "").lower().split())

    if bundle.name and capture.name and norm(bundle.name) != norm(capture.name):
        b_mod, c_mod = norm(bundle.model), norm(capture.model)
        b_make, c_make = norm(bundle.make), norm(capture.make)
        differs = (b_mod and c_mod and b_mod != c_mod) or (b_make and c_make and b_make != c_make)
        if differs:
            out.append(f"the capture was taken with a {capture.name} but the bundle was "
                       f"calibrated with a {bundle.name}")  # fmt: skip
    if bundle.cfa_pattern and capture.cfa_pattern and bundle.cfa_pattern != capture.cfa_pattern:
        out.append(f"the capture's CFA pattern is {capture.cfa_pattern}, the bundle's "
                   f"{bundle.cfa_pattern}")  # fmt: skip
    if bundle.sensor_size and capture.sensor_size and bundle.sensor_size != capture.sensor_size:
        out.append(f"the capture's sensor is {capture.sensor_size[0]}x{capture.sensor_size[1]}, "
                   f"the bundle's {bundle.sensor_size[0]}x{bundle.sensor_size[1]}")
    if bundle.white_level is not None and capture.white_level is not None and \
            abs(bundle.white_level - capture.white_level) > 0.5:  # fmt: skip
        out.append(f"the capture's white level is {capture.white_level:g} DN, the bundle's "
                   f"{bundle.white_level:g} DN")  # fmt: skip
    if bundle.black_level is not None and capture.black_level is not None:
        diff = max(abs(a - b) for a, b in zip(bundle.black_level, capture.black_level,
                                             strict=True))  # fmt: skip
        if diff > max(2.0, 0.02 * max(abs(v) for v in bundle.black_level)):
            out.append("the capture's black level is "
                       f"{_levels(capture.black_level)} DN, the bundle's "
                       f"{_levels(bundle.black_level)} DN")  # fmt: skip
    return out


def _levels(v: Sequence[float]) -> str:
    if max(v) - min(v) < 0.05:
        return f"{v[0]:g}"
    return "[" + ", ".join(f"{x:g}" for x in v) + "]"
