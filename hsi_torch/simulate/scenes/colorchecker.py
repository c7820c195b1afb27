"""The ColorChecker chart as a scene: 4 × 6 patches of measured reflectances with black gaps.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from hsi_torch import refdata
from hsi_torch.simulate.scenes.base import Extent, _constant_spectrum, _prep

__all__ = [
    "ColorCheckerScene",
]


# --- ColorChecker


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
