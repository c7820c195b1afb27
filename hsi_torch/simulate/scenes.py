"""Resolution-independent scenes on the diffuser plane.

A scene is a spectral reflectance field ``r(X, Y, λ)`` on the diffuser plane ``z = 0``, with
``(X, Y)`` in mm in the optics frame of ``docs/architecture.md`` (image ``x`` = ``+X``, image ``y``
= ``+Y``, so ``Y`` grows *downwards* in a rendered image). Any object with

- ``extent``: ``(x_min, x_max, y_min, y_max)`` in mm (the region worth rendering), and
- ``reflectance(xy_mm (N, 2), wavelengths_nm (M,)) -> (N, M)``

is a :class:`Scene`. Results take the device and floating dtype of ``xy_mm``.

Every scene here is also a *linear mixture*: ``reflectance(xy, λ) = abundances(xy) @
endmember_spectra(λ)`` with ``abundances (N, K)`` and ``endmember_spectra (K, M)`` (a ColorChecker
is 25 one-hot patches, a CAVE cube its 31 bands, the bar/circle targets one flat spectrum). The
renderer samples the ``K`` abundance planes on the diffuser and goes to the 2 nm grid with a
``(K, L)`` matrix afterwards (:func:`render_scene_abundances`, :func:`has_abundances`).

Scenes: :class:`ColorCheckerScene`, :class:`FlatScene`, :class:`USAF1951Scene`,
:class:`CircleGridScene` (OpenCV asymmetric grid), :class:`CubeScene` (any cube, e.g. the CAVE
scene via :func:`load_cave_scene`). :func:`render_scene_image` samples a scene on a pixel grid.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np
import torch
import torch.nn.functional as F

from hsi_torch import refdata
from hsi_torch.resources import DATA_ENV, real_data_dir
from hsi_torch.spectral import DEFAULT_GRID, SpectralGrid, resample_spectra

__all__ = [
    "Scene",
    "ColorCheckerScene",
    "FlatScene",
    "USAF1951Scene",
    "USAFElement",
    "usaf_frequency",
    "CircleGridScene",
    "CubeScene",
    "load_cave_cube",
    "load_cave_scene",
    "render_scene_image",
    "render_scene_abundances",
    "has_abundances",
    "pixel_centres_mm",
    "make_scene",
    "CAVE_WAVELENGTHS_NM",
]

Extent = tuple[float, float, float, float]
CAVE_WAVELENGTHS_NM = tuple(float(w) for w in range(400, 701, 10))


@runtime_checkable
class Scene(Protocol):
    """Spectral reflectance on the diffuser plane (mm)."""

    @property
    def extent(self) -> Extent:
        """``(x_min, x_max, y_min, y_max)`` in mm."""
        ...

    def reflectance(self, xy_mm: torch.Tensor, wavelengths_nm: torch.Tensor) -> torch.Tensor:
        """``(N, 2)`` points (mm), ``(M,)`` wavelengths (nm) → ``(N, M)`` reflectance."""
        ...


def _prep(xy_mm: torch.Tensor, wavelengths_nm) -> tuple[torch.Tensor, torch.Tensor]:
    if not isinstance(xy_mm, torch.Tensor):
        xy_mm = torch.as_tensor(np.asarray(xy_mm, dtype=np.float64))
    if xy_mm.ndim != 2 or xy_mm.shape[1] != 2:
        raise ValueError(f"xy_mm must have shape (N, 2), got {tuple(xy_mm.shape)}")
    if not xy_mm.is_floating_point():
        xy_mm = xy_mm.to(torch.get_default_dtype())
    wl = refdata.as_wavelengths(wavelengths_nm, device=xy_mm.device, dtype=xy_mm.dtype)
    return xy_mm, wl


def _constant_spectrum(value: float, n: int, wl: torch.Tensor) -> torch.Tensor:
    return torch.full((n, wl.numel()), float(value), device=wl.device, dtype=wl.dtype)


# =============================================================================================
# ColorChecker
# =============================================================================================


@dataclass
class ColorCheckerScene:
    """X-Rite ColorChecker: 4 × 6 patches of measured reflectances with black gaps.

    Patch ``k`` (chart order of :func:`hsi_torch.refdata.colorchecker_reflectances`) sits at row
    ``k // 6`` (top = smallest ``Y``), column ``k % 6`` (left = smallest ``X``). The chart covers
    ``width_mm × height_mm`` centred at ``center_mm``; each cell of the 6 × 4 grid has a square-ish
    patch inset by half a gap on every side, so gaps between patches and the outer frame are
    ``gap_fraction · min(cell_w, cell_h)`` and ``gap_fraction/2 · …`` wide.

    Attributes:
        width_mm: chart width (mm).
        height_mm: chart height (mm); ``None`` → ``width_mm · 4/6``.
        center_mm: chart centre ``(X, Y)`` (mm).
        gap_fraction: gap width as a fraction of the smaller cell side.
        gap_reflectance: reflectance (flat) of the gaps and of everything outside the chart.
        name: ColorChecker data set in ``colour.SDS_COLOURCHECKERS``.
    """

    width_mm: float = 12.0
    height_mm: float | None = None
    center_mm: tuple[float, float] = (0.0, 0.0)
    gap_fraction: float = 0.15
    gap_reflectance: float = 0.03
    name: str = refdata.DEFAULT_COLORCHECKER

    def __post_init__(self) -> None:
        if self.height_mm is None:
            self.height_mm = self.width_mm * 4.0 / 6.0
        if self.width_mm <= 0 or self.height_mm <= 0:
            raise ValueError(f"chart size must be positive, got {self.width_mm}x{self.height_mm}")
        if not 0 <= self.gap_fraction < 1:
            raise ValueError(f"gap_fraction must be in [0, 1), got {self.gap_fraction}")
        _, self.patch_names = refdata.colorchecker_reflectances([550.0], self.name)

    @property
    def extent(self) -> Extent:
        cx, cy = self.center_mm
        return (cx - self.width_mm / 2, cx + self.width_mm / 2,
                cy - self.height_mm / 2, cy + self.height_mm / 2)

    @property
    def _gap(self) -> float:
        return self.gap_fraction * min(self.width_mm / 6.0, self.height_mm / 4.0)

    def patch_boxes(self) -> torch.Tensor:
        """``(24, 4)`` float64 boxes ``(x_min, x_max, y_min, y_max)`` of the patches (mm)."""
        x0, _, y0, _ = self.extent
        cw, ch, g = self.width_mm / 6.0, self.height_mm / 4.0, self._gap
        k = torch.arange(24, dtype=torch.float64)
        col, row = k % 6, torch.div(k, 6, rounding_mode="floor")
        return torch.stack([x0 + col * cw + g / 2, x0 + (col + 1) * cw - g / 2,
                            y0 + row * ch + g / 2, y0 + (row + 1) * ch - g / 2], dim=1)

    def patch_centres(self) -> torch.Tensor:
        """``(24, 2)`` float64 patch centres ``(X, Y)`` in mm."""
        b = self.patch_boxes()
        return torch.stack([(b[:, 0] + b[:, 1]) / 2, (b[:, 2] + b[:, 3]) / 2], dim=1)

    def patch_spectra(self, wavelengths_nm, **kw) -> torch.Tensor:
        """``(24, M)`` patch reflectances (see :func:`refdata.colorchecker_reflectances`)."""
        return refdata.colorchecker_reflectances(wavelengths_nm, self.name, **kw)[0]

    def patch_index(self, xy_mm: torch.Tensor) -> torch.Tensor:
        """``(N,)`` long: patch index under each point, −1 in gaps/outside."""
        xy_mm, _ = _prep(xy_mm, [550.0])
        x0, _, y0, _ = self.extent
        cw, ch, g = self.width_mm / 6.0, self.height_mm / 4.0, self._gap
        u = (xy_mm[:, 0] - x0) / cw
        v = (xy_mm[:, 1] - y0) / ch
        col, row = torch.floor(u), torch.floor(v)
        fu, fv = (u - col) * cw, (v - row) * ch  # position inside the cell, mm
        inside = ((col >= 0) & (col < 6) & (row >= 0) & (row < 4)
                  & (fu >= g / 2) & (fu < cw - g / 2) & (fv >= g / 2) & (fv < ch - g / 2))
        idx = (row * 6 + col).long()
        return torch.where(inside, idx, torch.full_like(idx, -1))

    def reflectance(self, xy_mm: torch.Tensor, wavelengths_nm) -> torch.Tensor:
        xy_mm, wl = _prep(xy_mm, wavelengths_nm)
        table = self.endmember_spectra(wl)
        idx = self.patch_index(xy_mm)
        return table[torch.where(idx < 0, torch.full_like(idx, 24), idx)]

    def endmember_spectra(self, wavelengths_nm) -> torch.Tensor:
        """``(25, M)``: the 24 patch spectra, then the flat gap reflectance."""
        wl = refdata.as_wavelengths(wavelengths_nm)
        spectra = self.patch_spectra(wl)  # (24, M)
        return torch.cat([spectra, _constant_spectrum(self.gap_reflectance, 1, wl)], dim=0)

    def abundances(self, xy_mm: torch.Tensor) -> torch.Tensor:
        """``(N, 25)`` one-hot: the patch under each point (column 24: gap or outside)."""
        xy_mm, _ = _prep(xy_mm, [550.0])
        idx = self.patch_index(xy_mm)
        idx = torch.where(idx < 0, torch.full_like(idx, 24), idx)
        return F.one_hot(idx, 25).to(xy_mm.dtype)


# =============================================================================================
# Flat
# =============================================================================================


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


# =============================================================================================
# USAF 1951
# =============================================================================================


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
        groups: groups to draw.
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


# =============================================================================================
# OpenCV asymmetric circle grid
# =============================================================================================


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


# =============================================================================================
# User cube
# =============================================================================================


class CubeScene:
    """A reflectance cube ``(M_s, H, W)`` laid onto the diffuser plane.

    The cube covers ``extent_mm = (x_min, x_max, y_min, y_max)`` edge to edge: pixel column ``c``
    spans ``[x_min + c·dx, x_min + (c+1)·dx]`` with its centre (where its value is exact) in the
    middle; row 0 is at ``y_min``. Between centres the cube is sampled bilinearly, within half a
    pixel of the border it is held constant, outside it is ``outside_value``. Spectra are
    interpolated linearly from ``wavelengths_nm`` to the requested wavelengths.

    With ``endmembers (K, M_s)`` the cube holds ``K`` abundance planes ``(K, H, W)`` instead of
    bands: the spectrum at a point is ``Σ_k a_k · endmembers[k]`` on ``wavelengths_nm`` (a
    low-rank cube; the renderer keeps blurred scenes this way).

    Args:
        cube: ``(M_s, H, W)`` tensor or array (reflectance), or ``(K, H, W)`` abundances.
        wavelengths_nm: ``(M_s,)`` increasing wavelengths of the cube's bands.
        extent_mm: placement; default: ``width_mm`` wide (height from the aspect ratio), centred
            at ``center_mm``.
        width_mm, center_mm: used when ``extent_mm`` is ``None``.
        outside_value: reflectance outside the extent.
        extrapolate: ``'error'`` | ``'zero'`` | ``'edge'`` for wavelengths outside the cube's.
        endmembers: optional ``(K, M_s)`` spectra of the abundance planes.
    """

    def __init__(
        self,
        cube,
        wavelengths_nm,
        extent_mm: Extent | None = None,
        *,
        width_mm: float = 10.0,
        center_mm: tuple[float, float] = (0.0, 0.0),
        outside_value: float = 0.0,
        extrapolate: str = "error",
        endmembers: torch.Tensor | None = None,
    ) -> None:
        cube_t = torch.as_tensor(cube)
        if not cube_t.is_floating_point():
            cube_t = cube_t.to(torch.float32)
        if cube_t.ndim != 3:
            raise ValueError(f"cube must have shape (M_s, H, W), got {tuple(cube_t.shape)}")
        wl = torch.as_tensor(np.asarray(wavelengths_nm, dtype=np.float64)).reshape(-1)
        if endmembers is not None:
            endmembers = torch.as_tensor(endmembers)
            if endmembers.shape != (cube_t.shape[0], wl.numel()):
                raise ValueError(f"endmembers must have shape (K, M_s) = ({cube_t.shape[0]}, "
                                 f"{wl.numel()}) for a cube of {cube_t.shape[0]} abundance planes "
                                 f"and {wl.numel()} wavelengths, got {tuple(endmembers.shape)}")
        elif wl.numel() != cube_t.shape[0]:
            raise ValueError(f"cube has {cube_t.shape[0]} bands but wavelengths_nm has "
                             f"{wl.numel()} values")
        if wl.numel() > 1 and bool((wl[1:] <= wl[:-1]).any()):
            raise ValueError("wavelengths_nm must be strictly increasing")
        if extrapolate not in ("zero", "edge", "error"):
            raise ValueError(f"extrapolate must be 'zero', 'edge' or 'error', got {extrapolate!r}")
        _, h, w = cube_t.shape
        if extent_mm is None:
            if width_mm <= 0:
                raise ValueError(f"width_mm must be > 0, got {width_mm}")
            hh = width_mm * h / w
            cx, cy = center_mm
            extent_mm = (cx - width_mm / 2, cx + width_mm / 2, cy - hh / 2, cy + hh / 2)
        x0, x1, y0, y1 = (float(v) for v in extent_mm)
        if not (x1 > x0 and y1 > y0):
            raise ValueError(f"extent_mm must have x_max > x_min and y_max > y_min: {extent_mm}")
        self.cube = cube_t
        self.wavelengths_nm = wl
        self._extent = (x0, x1, y0, y1)
        self.outside_value = float(outside_value)
        self.extrapolate = extrapolate
        self.endmembers = endmembers
        self._cache: tuple[tuple, torch.Tensor] | None = None

    @property
    def extent(self) -> Extent:
        return self._extent

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.cube.shape)

    def _cube_on(self, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
        key = (str(device), dtype)
        if self._cache is None or self._cache[0] != key:
            self._cache = (key, self.cube.to(device=device, dtype=dtype).unsqueeze(0))
        return self._cache[1]

    def _check_wavelengths(self, wl: torch.Tensor) -> torch.Tensor:
        src = self.wavelengths_nm.to(device=wl.device, dtype=torch.float64)
        if self.extrapolate == "error":
            bad = (wl < src[0] - 1e-9) | (wl > src[-1] + 1e-9)
            if bool(bad.any()):
                raise ValueError(f"cube covers [{float(src[0])}, {float(src[-1])}] nm; requested "
                                 f"{wl[bad].tolist()} nm (set extrapolate='zero' or 'edge')")
        return src

    def _resample(self, vals: torch.Tensor, src: torch.Tensor, wl: torch.Tensor) -> torch.Tensor:
        """``(..., M_s)`` spectra on the cube's wavelengths → ``(..., M)`` on ``wl``."""
        if src.numel() == 1:
            return vals.expand(*vals.shape[:-1], wl.numel()).clone()
        return resample_spectra(vals, src.to(vals.dtype), wl, dim=-1,
                                extrapolate="zero" if self.extrapolate == "error"
                                else self.extrapolate)

    def _sample(self, xy_mm: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Bilinear samples ``(N, C)`` of the stored planes (0 outside the extent) and the
        inside-extent mask ``(N,)``."""
        x0, x1, y0, y1 = self._extent
        _, h, w = self.cube.shape
        cube = self._cube_on(xy_mm.device, xy_mm.dtype)
        # pixel coordinates (centres at integers), then align_corners=True normalisation
        px = (xy_mm[:, 0] - x0) / (x1 - x0) * w - 0.5
        py = (xy_mm[:, 1] - y0) / (y1 - y0) * h - 0.5
        gx = 2 * px / max(w - 1, 1) - 1 if w > 1 else torch.zeros_like(px)
        gy = 2 * py / max(h - 1, 1) - 1 if h > 1 else torch.zeros_like(py)
        grid = torch.stack([gx, gy], dim=-1)
        inside = ((xy_mm[:, 0] >= x0) & (xy_mm[:, 0] <= x1)
                  & (xy_mm[:, 1] >= y0) & (xy_mm[:, 1] <= y1))
        idx = torch.nonzero(inside).squeeze(1)
        if idx.numel() < inside.numel():  # sample only the points inside (outside: 0)
            grid = grid[idx]
        vals = F.grid_sample(cube, grid.view(1, 1, -1, 2), mode="bilinear",
                             padding_mode="border", align_corners=True)[0, :, 0, :].T  # (n, C)
        if idx.numel() < inside.numel():
            full = vals.new_zeros(inside.numel(), vals.shape[1])
            full[idx] = vals
            vals = full
        return vals, inside

    def reflectance(self, xy_mm: torch.Tensor, wavelengths_nm) -> torch.Tensor:
        xy_mm, wl = _prep(xy_mm, wavelengths_nm)
        src = self._check_wavelengths(wl)
        vals, inside = self._sample(xy_mm)
        if self.endmembers is not None:
            vals = vals @ self.endmembers.to(vals)
        out = self._resample(vals, src, wl)
        return torch.where(inside.unsqueeze(1), out, torch.full_like(out, self.outside_value))

    def endmember_spectra(self, wavelengths_nm) -> torch.Tensor:
        """``(K, M)``: the endmembers (or the identity over the bands) resampled to
        ``wavelengths_nm``; one more row ``outside_value`` when that is not 0."""
        wl = refdata.as_wavelengths(wavelengths_nm)
        src = self._check_wavelengths(wl)
        em = (self.endmembers.to(device=wl.device, dtype=wl.dtype) if self.endmembers is not None
              else torch.eye(src.numel(), device=wl.device, dtype=wl.dtype))
        out = self._resample(em, src, wl)
        if self.outside_value != 0.0:
            out = torch.cat([out, _constant_spectrum(self.outside_value, 1, wl)])
        return out

    def abundances(self, xy_mm: torch.Tensor) -> torch.Tensor:
        """``(N, K)``: bilinear samples of the planes inside the extent, 0 outside (plus a last
        column, 1 outside the extent, when ``outside_value`` is not 0)."""
        xy_mm, _ = _prep(xy_mm, [550.0])
        vals, inside = self._sample(xy_mm)
        vals = vals * inside.unsqueeze(1).to(vals.dtype)
        if self.outside_value != 0.0:
            vals = torch.cat([vals, (~inside).to(vals.dtype).unsqueeze(1)], dim=1)
        return vals


# =============================================================================================
# CAVE
# =============================================================================================


def _default_cave_folder() -> Path:
    folder = real_data_dir("cave_stuffed_toys")
    if folder is None:
        raise FileNotFoundError(
            f"the CAVE folder cave_stuffed_toys was not found in the real-data folder ({DATA_ENV} "
            "or ../shared/data/real beside the source checkout); pass folder="
        )
    return folder


def load_cave_cube(
    folder: str | os.PathLike | None = None,
    *,
    normalise: str | None = "white_patch",
    white_search_rows: tuple[int, int] = (256, 512),
    white_search_cols: tuple[int, int] = (100, 356),
    box_px: int = 21,
    colorchecker: str = refdata.DEFAULT_COLORCHECKER,
) -> tuple[torch.Tensor, torch.Tensor, dict]:
    """Load the CAVE ``stuffed_toys`` scene (31 bands, 400–700 nm, 512 × 512, 16-bit PNGs).

    Normalisation ``'white_patch'`` turns the camera counts into reflectance with the
    ColorChecker in the scene: inside the search window (rows × cols) the band-averaged image is
    box-filtered (``box_px`` square); its maximum is the centre of the white patch (the brightest
    flat area of the chart). The per-band median over that box is the measured white ``w(λ)``;
    every band is scaled by ``ρ_white(λ) / w(λ)`` where ``ρ_white`` is the tabulated reflectance of
    the chart's 'white 9.5 (.05 D)' patch (``colorchecker`` data set). No dark frame is available,
    so no offset is subtracted. ``normalise=None`` returns counts / 65535.

    Returns:
        ``(cube (31, 512, 512) float32, wavelengths (31,) float64 nm, info)``; ``info`` holds the
        white patch centre ``(row, col)``, the measured white counts and the scale per band.
    """
    import cv2

    folder = Path(folder) if folder is not None else _default_cave_folder()
    files = sorted(folder.glob("*_ms_[0-9][0-9].png"))
    if len(files) != 31:
        raise FileNotFoundError(f"expected 31 band PNGs '*_ms_01.png'…'_31.png' in {folder}, "
                                f"found {len(files)}")
    bands = []
    for f in files:
        im = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        if im is None:
            raise ValueError(f"cannot read {f}")
        if im.ndim == 3:  # some copies store the band as 3 identical channels
            im = im[..., 0]
        bands.append(im)
    shapes = {b.shape for b in bands}
    if len(shapes) != 1:
        raise ValueError(f"CAVE bands in {folder} have different shapes: {shapes}")
    cube = torch.from_numpy(np.stack(bands).astype(np.float32))
    wl = torch.tensor(CAVE_WAVELENGTHS_NM, dtype=torch.float64)
    info: dict = {"folder": str(folder), "normalise": normalise}
    if normalise is None:
        return cube / 65535.0, wl, info
    if normalise != "white_patch":
        raise ValueError(f"normalise must be 'white_patch' or None, got {normalise!r}")
    r0, r1 = white_search_rows
    c0, c1 = white_search_cols
    region = cube[:, r0:r1, c0:c1]
    if region.numel() == 0 or region.shape[1] < box_px or region.shape[2] < box_px:
        raise ValueError(f"white search window rows {white_search_rows} cols {white_search_cols} "
                         f"is empty or smaller than box_px={box_px}")
    lum = region.mean(dim=0, keepdim=True).unsqueeze(0)
    smooth = F.avg_pool2d(lum, box_px, stride=1)[0, 0]
    k = int(torch.argmax(smooth))
    ry, rx = divmod(k, smooth.shape[1])
    patch = region[:, ry:ry + box_px, rx:rx + box_px].reshape(region.shape[0], -1)
    white_counts = patch.median(dim=1).values.to(torch.float64)
    if bool((white_counts <= 0).any()):
        raise ValueError("white patch has non-positive counts in some band")
    ref, names = refdata.colorchecker_reflectances(wl, colorchecker, dtype=torch.float64)
    white_idx = next(i for i, n in enumerate(names) if n.lower().startswith("white"))
    scale = ref[white_idx] / white_counts
    cube = cube * scale.to(torch.float32).view(-1, 1, 1)
    info.update(white_centre_rc=(r0 + ry + box_px // 2, c0 + rx + box_px // 2),
                white_counts=white_counts.tolist(), scale=scale.tolist(),
                white_reference=ref[white_idx].tolist())
    return cube, wl, info


def load_cave_scene(
    folder: str | os.PathLike | None = None,
    *,
    width_mm: float = 10.0,
    center_mm: tuple[float, float] = (0.0, 0.0),
    extrapolate: str = "error",
    **kwargs,
) -> CubeScene:
    """The CAVE scene as a :class:`CubeScene` ``width_mm`` wide (see :func:`load_cave_cube`)."""
    cube, wl, info = load_cave_cube(folder, **kwargs)
    scene = CubeScene(cube, wl, width_mm=width_mm, center_mm=center_mm, extrapolate=extrapolate)
    scene.info = info  # type: ignore[attr-defined]
    return scene


# =============================================================================================
# rendering helpers
# =============================================================================================


def pixel_centres_mm(
    extent: Extent,
    height: int,
    width: int,
    *,
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
) -> torch.Tensor:
    """``(H, W, 2)`` diffuser ``(X, Y)`` of pixel centres of an image covering ``extent``.

    Pixel ``(x, y)`` covers ``[x_min + x·dx, x_min + (x+1)·dx] × [y_min + y·dy, …]`` with
    ``dx = (x_max − x_min)/W``, ``dy = (y_max − y_min)/H``.
    """
    x0, x1, y0, y1 = (float(v) for v in extent)
    dtype = dtype or torch.get_default_dtype()
    xs = x0 + (torch.arange(width, device=device, dtype=dtype) + 0.5) * ((x1 - x0) / width)
    ys = y0 + (torch.arange(height, device=device, dtype=dtype) + 0.5) * ((y1 - y0) / height)
    yy, xx = torch.meshgrid(ys, xs, indexing="ij")
    return torch.stack([xx, yy], dim=-1)


def has_abundances(scene: object) -> bool:
    """Whether ``scene`` exposes the linear-mixture form (``abundances`` and
    ``endmember_spectra``, see the module docstring)."""
    return callable(getattr(scene, "abundances", None)) and callable(
        getattr(scene, "endmember_spectra", None))


def _raster(
    fn,
    extent: Extent,
    height: int,
    width: int,
    supersample: int,
    device: torch.device | str | None,
    dtype: torch.dtype,
    chunk_points: int,
) -> torch.Tensor:
    """``fn(points (N, 2)) -> (N, C)`` averaged over ``s × s`` samples per pixel → ``(C, H, W)``.

    Evaluated a band of output rows at a time (≈ ``chunk_points`` samples), so memory stays at
    the output image plus one band.
    """
    if height < 1 or width < 1:
        raise ValueError(f"height and width must be >= 1, got {height}x{width}")
    if supersample < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    s = int(supersample)
    pts = pixel_centres_mm(extent, height * s, width * s, device=device, dtype=dtype)
    rows = max(1, chunk_points // (width * s * s))
    out: torch.Tensor | None = None
    for r0 in range(0, height, rows):
        r1 = min(height, r0 + rows)
        band = pts[r0 * s:r1 * s].reshape(-1, 2)
        vals = fn(band)  # (n, C)
        img = vals.T.reshape(vals.shape[1], (r1 - r0) * s, width * s)
        if s > 1:
            img = F.avg_pool2d(img.unsqueeze(0), s)[0]
        if out is None:
            out = torch.empty(vals.shape[1], height, width, device=img.device, dtype=img.dtype)
        out[:, r0:r1] = img
    assert out is not None
    return out


def render_scene_image(
    scene: Scene,
    extent: Extent | None = None,
    height: int = 256,
    width: int = 256,
    wavelengths: SpectralGrid | torch.Tensor | Sequence[float] = DEFAULT_GRID,
    *,
    supersample: int = 1,
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
    chunk_points: int = 1 << 18,
) -> torch.Tensor:
    """Sample a scene on a regular pixel grid.

    Args:
        scene: any :class:`Scene`.
        extent: ``(x_min, x_max, y_min, y_max)`` mm covered edge to edge (default
            ``scene.extent``); row 0 is at ``y_min``.
        height, width: image size in pixels.
        wavelengths: ``(M,)`` nm.
        supersample: ``s``: average ``s × s`` regularly spaced samples per pixel (box filter,
            anti-aliasing).
        device, dtype: of the result (default: of ``wavelengths`` if a tensor, else CPU/default).
        chunk_points: scene evaluations per call (memory bound: one band of rows at a time).

    Returns:
        ``(M, H, W)`` reflectance image.
    """
    if isinstance(wavelengths, torch.Tensor):
        device = device or wavelengths.device
        dtype = dtype or (wavelengths.dtype if wavelengths.is_floating_point() else None)
    wl = refdata.as_wavelengths(wavelengths, device=device, dtype=dtype)
    extent = tuple(float(v) for v in (extent if extent is not None else scene.extent))
    return _raster(lambda p: scene.reflectance(p, wl), extent, height, width, supersample,
                   wl.device, wl.dtype, chunk_points)


def render_scene_abundances(
    scene: Scene,
    extent: Extent | None = None,
    height: int = 256,
    width: int = 256,
    *,
    supersample: int = 1,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float64,
    chunk_points: int = 1 << 18,
) -> torch.Tensor:
    """The ``K`` abundance planes of a linear-mixture scene (:func:`has_abundances`) on a pixel
    grid, ``(K, H, W)``; same sampling as :func:`render_scene_image`, and
    ``render_scene_image(...)[:, y, x] = endmember_spectra(wl).T @ result[:, y, x]``."""
    if not has_abundances(scene):
        raise TypeError(f"{type(scene).__name__} has no abundances()/endmember_spectra()")
    extent = tuple(float(v) for v in (extent if extent is not None else scene.extent))
    return _raster(scene.abundances, extent, height, width, supersample, device, dtype,
                   chunk_points)


def make_scene(kind: str, **kwargs) -> Scene:
    """Build a scene from a config dict (angles in degrees in keys ending ``_deg``).

    ``kind``: ``'colorchecker'``, ``'white'``/``'flat'``, ``'usaf'``, ``'circle_grid'``,
    ``'cave'``. Other keys go to the scene's constructor; ``rotation_deg``, ``tilt_x_deg``,
    ``tilt_y_deg`` are converted to the ``*_rad`` fields.
    """
    kw = dict(kwargs)
    for k in list(kw):
        if k.endswith("_deg"):
            kw[k[:-4] + "_rad"] = math.radians(float(kw.pop(k)))
    for k in ("center_mm", "translation_mm", "pattern_size", "extent_mm"):
        if k in kw and kw[k] is not None:
            kw[k] = tuple(kw[k])
    kinds = {
        "colorchecker": ColorCheckerScene,
        "white": FlatScene,
        "flat": FlatScene,
        "usaf": USAF1951Scene,
        "circle_grid": CircleGridScene,
        "cave": load_cave_scene,
    }
    if kind not in kinds:
        raise ValueError(f"unknown scene kind {kind!r}; choose from {sorted(kinds)}")
    try:
        return kinds[kind](**kw)
    except TypeError as exc:
        raise TypeError(f"bad parameters for scene {kind!r}: {exc}") from exc
