"""Spectrally flat targets: a uniform field, the USAF 1951 bar target and the OpenCV asymmetric
circle grid (the calibration's registration target), each one endmember whose abundance is the
reflectance.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from hsi_torch import refdata
from hsi_torch.simulate.scenes.base import Extent, _constant_spectrum, _prep
from hsi_torch.spectral import resample_spectra

__all__ = [
    "FlatScene",
    "USAF1951Scene",
    "USAFElement",
    "usaf_frequency",
    "CircleGridScene",
]


# --- Flat


@dataclass
class FlatScene:
    """Uniform target: reflectance ``value`` at every wavelength, or a tabulated spectrum.

    Attributes:
        value: flat reflectance (used when ``spectrum_nm`` is ``None``).
        spectrum_nm, spectrum_values: optional tabulated reflectance (linearly interpolated; zero
            outside its range).
        extent_mm: nominal extent (the scene is infinite).
    """

    value: float = 1.0
    spectrum_nm: Sequence[float] | None = None
    spectrum_values: Sequence[float] | None = None
    extent_mm: Extent = (-50.0, 50.0, -50.0, 50.0)

    def __post_init__(self) -> None:
        if (self.spectrum_nm is None) != (self.spectrum_values is None):
            raise ValueError("give both spectrum_nm and spectrum_values, or neither")
        if self.spectrum_nm is not None:
            a = np.asarray(self.spectrum_nm, np.float64)
            b = np.asarray(self.spectrum_values, np.float64)
            if a.ndim != 1 or a.shape != b.shape or a.size < 2:
                raise ValueError(f"spectrum_nm {a.shape} and spectrum_values {b.shape} must be "
                                 "1-D of equal length >= 2")

    @property
    def extent(self) -> Extent:
        return tuple(float(v) for v in self.extent_mm)

    def reflectance(self, xy_mm: torch.Tensor, wavelengths_nm) -> torch.Tensor:
        xy_mm, wl = _prep(xy_mm, wavelengths_nm)
        return self.endmember_spectra(wl).expand(xy_mm.shape[0], -1).clone()

    def endmember_spectra(self, wavelengths_nm) -> torch.Tensor:
        """``(1, M)``: the flat value or the tabulated spectrum."""
        wl = refdata.as_wavelengths(wavelengths_nm)
        if self.spectrum_nm is None:
            return _constant_spectrum(self.value, 1, wl)
        src = torch.as_tensor(np.asarray(self.spectrum_nm, np.float64), device=wl.device)
        val = torch.as_tensor(np.asarray(self.spectrum_values, np.float64), device=wl.device)
        return resample_spectra(val, src, wl.to(torch.float64)).to(wl.dtype)[None]

    def abundances(self, xy_mm: torch.Tensor) -> torch.Tensor:
        """``(N, 1)`` ones."""
        xy_mm, _ = _prep(xy_mm, [550.0])
        return torch.ones(xy_mm.shape[0], 1, device=xy_mm.device, dtype=xy_mm.dtype)


# --- USAF 1951


def usaf_frequency(group: int | float, element: int | float) -> float:
    """Spatial frequency of a USAF 1951 element in line pairs per mm: ``2^(G + (E − 1)/6)``."""
    return float(2.0 ** (group + (element - 1) / 6.0))


class _FlatTarget:
    """A spectrally flat target (one endmember of ones; its abundance is the reflectance)."""

    def reflectance(self, xy_mm: torch.Tensor, wavelengths_nm) -> torch.Tensor:
        raise NotImplementedError

    def endmember_spectra(self, wavelengths_nm) -> torch.Tensor:
        """``(1, M)`` ones (the target is spectrally flat)."""
        return _constant_spectrum(1.0, 1, refdata.as_wavelengths(wavelengths_nm))

    def abundances(self, xy_mm: torch.Tensor) -> torch.Tensor:
        """``(N, 1)``: the target's reflectance under each point."""
        xy_mm, _ = _prep(xy_mm, [550.0])
        return self.reflectance(xy_mm, torch.tensor([550.0], dtype=xy_mm.dtype,
                                                    device=xy_mm.device))


def _two_level(mask: torch.Tensor, inside: float, outside: float, wl: torch.Tensor) -> torch.Tensor:
    """``(N, M)`` flat spectra: ``inside`` where ``mask (N,)`` holds, else ``outside``."""
    r = torch.where(mask, torch.tensor(inside, dtype=wl.dtype, device=wl.device),
                    torch.tensor(outside, dtype=wl.dtype, device=wl.device))
    return r.unsqueeze(1).expand(-1, wl.numel()).clone()


@dataclass(frozen=True)
class USAFElement:
    """Geometry of one bar triplet of the USAF target, in diffuser-plane mm.

    ``orientation='horizontal'``: bars run along ``X`` (intensity varies along ``Y``);
    ``'vertical'``: bars run along ``Y`` (varies along ``X``).
    """

    group: int
    element: int
    orientation: str
    lp_per_mm_target: float
    lp_per_mm: float
    bar_width_mm: float
    bar_length_mm: float
    bbox_mm: Extent
    bars_mm: tuple[Extent, Extent, Extent]


@dataclass
class USAF1951Scene(_FlatTarget):
    """Analytic USAF 1951 resolution target.

    Element ``(G, E)`` has ``r = 2^(G + (E−1)/6)`` line pairs per target mm; on the diffuser the
    frequency is ``r / magnification`` (``magnification`` = diffuser mm per target mm). Each element
    is two triplets of bars of width ``w = 1/(2r)`` and length ``5w`` separated by ``w``: one
    horizontal, one vertical (the standard bar geometry). The arrangement is simplified: each group
    is a column (coarsest group on the left), elements 1…6 top to bottom, the horizontal triplet
    left of the vertical one; columns are separated by twice the group's largest bar width.

    Attributes:
        magnification: diffuser mm per target mm.
        center_mm: centre of the pattern's bounding box (mm).
        bar_reflectance, background_reflectance: flat reflectances.
    """

    groups: Sequence[int] = (0, 1, 2, 3)
    magnification: float = 1.0
    center_mm: tuple[float, float] = (0.0, 0.0)
    bar_reflectance: float = 0.9
    background_reflectance: float = 0.05
    _elements: list[USAFElement] = field(default_factory=list, init=False, repr=False)
    _boxes: torch.Tensor | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        if self.magnification <= 0:
            raise ValueError(f"magnification must be > 0, got {self.magnification}")
        if len(self.groups) == 0:
            raise ValueError("groups must not be empty")
        self.groups = tuple(int(g) for g in self.groups)
        self._layout()

    def _layout(self) -> None:
        m = self.magnification
        raw: list[tuple] = []  # (G, E, orient, lp_t, w, x0, y0) before centring, diffuser mm
        x_cursor = 0.0
        for g in sorted(self.groups):
            w_max = m / (2.0 * usaf_frequency(g, 1))
            y_cursor = 0.0
            for e in range(1, 7):
                lp_t = usaf_frequency(g, e)
                w = m / (2.0 * lp_t)
                raw.append((g, e, "horizontal", lp_t, w, x_cursor, y_cursor))
                raw.append((g, e, "vertical", lp_t, w, x_cursor + 6.0 * w, y_cursor))
                y_cursor += 7.0 * w
            x_cursor += 11.0 * w_max + 2.0 * w_max
        xs = [r[5] + 5 * r[4] for r in raw]
        ys = [r[6] + 5 * r[4] for r in raw]
        width, height = max(xs), max(ys)
        ox = self.center_mm[0] - width / 2
        oy = self.center_mm[1] - height / 2
        self._size = (width, height)
        elements, boxes = [], []
        for g, e, orient, lp_t, w, x0, y0 in raw:
            x0, y0 = x0 + ox, y0 + oy
            bars = []
            for b in range(3):
                if orient == "horizontal":
                    bars.append((x0, x0 + 5 * w, y0 + 2 * b * w, y0 + (2 * b + 1) * w))
                else:
                    bars.append((x0 + 2 * b * w, x0 + (2 * b + 1) * w, y0, y0 + 5 * w))
            boxes.extend(bars)
            elements.append(USAFElement(
                group=g, element=e, orientation=orient, lp_per_mm_target=lp_t,
                lp_per_mm=lp_t / self.magnification, bar_width_mm=w, bar_length_mm=5 * w,
                bbox_mm=(x0, x0 + 5 * w, y0, y0 + 5 * w), bars_mm=tuple(bars),
            ))
        self._elements = elements
        self._boxes = torch.tensor(boxes, dtype=torch.float64)

    def elements(self) -> list[USAFElement]:
        """All bar triplets (2 per element), in layout order."""
        return list(self._elements)

    @property
    def extent(self) -> Extent:
        cx, cy = self.center_mm
        w, h = self._size
        mx = 0.05 * max(w, h)
        return (cx - w / 2 - mx, cx + w / 2 + mx, cy - h / 2 - mx, cy + h / 2 + mx)

    def bar_mask(self, xy_mm: torch.Tensor, chunk: int = 65536) -> torch.Tensor:
        """``(N,)`` bool: point lies on a bar."""
        xy_mm, _ = _prep(xy_mm, [550.0])
        boxes = self._boxes.to(device=xy_mm.device, dtype=xy_mm.dtype)
        out = torch.empty(xy_mm.shape[0], dtype=torch.bool, device=xy_mm.device)
        for s in range(0, xy_mm.shape[0], chunk):
            p = xy_mm[s:s + chunk]
            x, y = p[:, :1], p[:, 1:]
            inside = ((x >= boxes[:, 0]) & (x < boxes[:, 1])
                      & (y >= boxes[:, 2]) & (y < boxes[:, 3]))
            out[s:s + chunk] = inside.any(dim=1)
        return out

    def reflectance(self, xy_mm: torch.Tensor, wavelengths_nm) -> torch.Tensor:
        xy_mm, wl = _prep(xy_mm, wavelengths_nm)
        return _two_level(self.bar_mask(xy_mm), self.bar_reflectance,
                          self.background_reflectance, wl)  # fmt: skip


# --- OpenCV asymmetric circle grid


@dataclass
class CircleGridScene(_FlatTarget):
    """OpenCV asymmetric circle grid placed on the diffuser with a planar pose.

    Pattern coordinates follow OpenCV's calibration sample for ``ASYMMETRIC_CIRCLES_GRID`` with
    ``pattern_size = (cols, rows)`` (the ``patternSize`` passed to ``cv2.findCirclesGrid``):
    circle ``k = i·cols + j`` (row ``i < rows``, column ``j < cols``) is at
    ``((2j + i mod 2)·s, i·s)`` with ``s = spacing_mm`` (OpenCV's ``squareSize``: rows are ``s``
    apart, circles within a row ``2s``). :meth:`object_points` returns these points.

    Pose (pattern → diffuser): the pattern, centred on its centroid, is rotated in 3-D by
    ``R = Rz(rotation) · Ry(tilt_y) · Rx(tilt_x)``, placed ``view_distance_mm`` in front of a
    pinhole of focal length ``view_distance_mm`` (so an untilted pattern keeps its size), projected
    and shifted by ``translation_mm``. Tilts give a true perspective (homography) distortion.

    Attributes:
        pattern_size: ``(cols, rows)``; default ``(4, 5)``.
        spacing_mm: ``s`` above.
        radius_mm: circle radius; must be ``< s·√2/2`` (circles must not touch).
        rotation_rad, tilt_x_rad, tilt_y_rad: pose angles (rad).
        translation_mm: ``(X, Y)`` of the projected centroid.
        view_distance_mm: sets the strength of the perspective for a given tilt.
        circle_reflectance, background_reflectance: flat reflectances (dark circles on white, as
            ``cv2.findCirclesGrid``'s default blob detector expects).
    """

    pattern_size: tuple[int, int] = (4, 5)
    spacing_mm: float = 1.0
    radius_mm: float = 0.3
    rotation_rad: float = 0.0
    translation_mm: tuple[float, float] = (0.0, 0.0)
    tilt_x_rad: float = 0.0
    tilt_y_rad: float = 0.0
    view_distance_mm: float = 100.0
    circle_reflectance: float = 0.05
    background_reflectance: float = 0.9

    def __post_init__(self) -> None:
        cols, rows = (int(v) for v in self.pattern_size)
        if cols < 1 or rows < 2:
            raise ValueError(
                f"pattern_size (cols, rows) must be >= (1, 2), got {self.pattern_size}"
            )
        self.pattern_size = (cols, rows)
        if self.spacing_mm <= 0:
            raise ValueError(f"spacing_mm must be > 0, got {self.spacing_mm}")
        if not 0 < self.radius_mm < self.spacing_mm * math.sqrt(0.5):
            raise ValueError(f"radius_mm must be in (0, spacing·√2/2 = "
                             f"{self.spacing_mm * math.sqrt(0.5):.4g}), got {self.radius_mm}")
        if self.view_distance_mm <= 0:
            raise ValueError(f"view_distance_mm must be > 0, got {self.view_distance_mm}")
        h = self.homography()
        hinv = torch.linalg.inv(h)
        self._h, self._hinv = h, hinv / hinv[2, 2]

    def object_points(self) -> torch.Tensor:
        """``(rows·cols, 3)`` float64 pattern coordinates (mm, ``z = 0``) in OpenCV order."""
        cols, rows = self.pattern_size
        i = torch.arange(rows, dtype=torch.float64).repeat_interleave(cols)
        j = torch.arange(cols, dtype=torch.float64).repeat(rows)
        s = self.spacing_mm
        return torch.stack([(2 * j + i % 2) * s, i * s, torch.zeros_like(i)], dim=1)

    def homography(self) -> torch.Tensor:
        """``(3, 3)`` float64 homography: pattern mm ``(u, v, 1)`` → diffuser mm ``(X, Y, 1)``."""
        obj = self.object_points()[:, :2]
        c = obj.mean(dim=0)
        t_c = torch.tensor([[1.0, 0, -c[0]], [0, 1.0, -c[1]], [0, 0, 1.0]], dtype=torch.float64)
        cz, sz = math.cos(self.rotation_rad), math.sin(self.rotation_rad)
        cy, sy = math.cos(self.tilt_y_rad), math.sin(self.tilt_y_rad)
        cx, sx = math.cos(self.tilt_x_rad), math.sin(self.tilt_x_rad)
        rz = torch.tensor([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]], dtype=torch.float64)
        ry = torch.tensor([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]], dtype=torch.float64)
        rx = torch.tensor([[1, 0, 0], [0, cx, -sx], [0, sx, cx]], dtype=torch.float64)
        r = rz @ ry @ rx
        d = self.view_distance_mm
        tx, ty = self.translation_mm
        k = torch.tensor([[d, 0, tx], [0, d, ty], [0, 0, 1.0]], dtype=torch.float64)
        rt = torch.stack([r[:, 0], r[:, 1], torch.tensor([0.0, 0.0, d], dtype=torch.float64)], 1)
        h = k @ rt @ t_c
        return h / h[2, 2]

    def true_centres(self) -> torch.Tensor:
        """``(rows·cols, 2)`` float64 circle centres on the diffuser (mm), OpenCV's order.

        These are the projections of the circle centres (what a homography fit assumes); under a
        tilt the centre of the projected ellipse differs from it at second order.
        """
        p = self.object_points().clone()
        p[:, 2] = 1.0
        q = p @ self._h.T
        return q[:, :2] / q[:, 2:3]

    @property
    def extent(self) -> Extent:
        c = self.true_centres()
        m = 2.0 * self.spacing_mm
        return (float(c[:, 0].min()) - m, float(c[:, 0].max()) + m,
                float(c[:, 1].min()) - m, float(c[:, 1].max()) + m)

    def circle_mask(self, xy_mm: torch.Tensor) -> torch.Tensor:
        """``(N,)`` bool: point lies inside a circle (tested in pattern coordinates)."""
        xy_mm, _ = _prep(xy_mm, [550.0])
        hinv = self._hinv.to(device=xy_mm.device, dtype=xy_mm.dtype)
        q = xy_mm @ hinv[:2, :2].T + hinv[:2, 2]
        w = xy_mm @ hinv[2, :2] + hinv[2, 2]
        uv = q / w.unsqueeze(1)
        s = self.spacing_mm
        cols, rows = self.pattern_size
        u, v = uv[:, 0] / s, uv[:, 1] / s
        best = torch.full_like(u, float("inf"))
        i0 = torch.floor(v)
        for di in (0.0, 1.0):
            i = (i0 + di).clamp(0, rows - 1)
            par = torch.remainder(i, 2.0)
            j = torch.round((u - par) / 2.0).clamp(0, cols - 1)
            d2 = (u - (2 * j + par)) ** 2 + (v - i) ** 2
            best = torch.minimum(best, d2)
        inside = best * s * s < self.radius_mm**2
        return inside & (w > 0)

    def reflectance(self, xy_mm: torch.Tensor, wavelengths_nm) -> torch.Tensor:
        xy_mm, wl = _prep(xy_mm, wavelengths_nm)
        return _two_level(self.circle_mask(xy_mm), self.circle_reflectance,
                          self.background_reflectance, wl)  # fmt: skip
