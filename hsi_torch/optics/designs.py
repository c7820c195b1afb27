"""Design kinds of the virtual prototype: what codes the spectrum behind the kaleidoscope
(:class:`PrototypeDesign`, the ``design:`` section of the simulate config; docs/simulate.md,
*Design kinds*, gives the models' sources and defaults).

- ``this_system`` (default): a birefringent filter (BRF) between polarizers directly behind the
  diffuser; each view crosses it at its own angle and sees its own OPD.
- ``manakov`` (after Manakov et al., ACM TOG 32(4) 2013): no BRF and no polarizers; view
  ``v ≥ 1`` carries filter ``v − 1`` of a set (default: Gaussian band-passes tiling the band,
  :func:`gaussian_bandpass`; or measured curves), the reference view none; higher-order tiles
  are masked.
- ``fujimoto`` (after Fujimoto et al. 2025): a birefringent thin section, modelled as the ``brf``
  plate whose OPD every ray multiplies by the factor of the grain it crosses
  (:meth:`PrototypeDesign.grain_factor`: cells of a jittered-grid Voronoi tessellation with mean
  size ``grain_size_mm``, factors drawn uniformly from ``grain_opd_factor``; a grain tilted by
  ``θ`` has birefringence ``Δn cos²θ``).

Deterministic physics on tensors (no I/O): filter curves read from files are handed in as arrays
(``filter_curves``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import torch

__all__ = ["DESIGN_KINDS", "PrototypeDesign", "gaussian_bandpass"]

#: The design kinds of the virtual prototype.
DESIGN_KINDS: tuple[str, ...] = ("this_system", "manakov", "fujimoto")

_FWHM_TO_SIGMA = 1.0 / (2.0 * math.sqrt(2.0 * math.log(2.0)))


def gaussian_bandpass(
    wavelengths_nm: torch.Tensor, centers_nm: Sequence[float], fwhm_nm: float, peak: float
) -> torch.Tensor:
    """``(F, L)`` Gaussian band-pass transmittances ``peak · exp(−(λ − c)² / 2σ²)``,
    ``σ = FWHM / (2 √(2 ln 2))``, at ``wavelengths_nm (L,)`` (nm)."""
    c = torch.as_tensor(list(centers_nm), dtype=wavelengths_nm.dtype, device=wavelengths_nm.device)
    sig = float(fwhm_nm) * _FWHM_TO_SIGMA
    return float(peak) * torch.exp(-0.5 * ((wavelengths_nm[None, :] - c[:, None]) / sig) ** 2)


def _hash_uniform(i: torch.Tensor, j: torch.Tensor, seed: int, salt: int) -> torch.Tensor:
    """Deterministic uniforms in ``[0, 1)`` of integer cells ``(i, j)`` (same shape, int64)."""
    m = 0xFFFFFFFF
    h = (i * 73856093) ^ (j * 19349663) ^ (seed * 83492791 + salt * 2654435761)
    h = h & m
    for _ in range(3):  # xorshift-multiply rounds (Wang-style 32-bit mix)
        h = ((h ^ (h >> 16)) * 0x45D9F3B) & m
    h = h ^ (h >> 16)
    return h.to(torch.float64) / 4294967296.0


@dataclass
class PrototypeDesign:
    """What codes the spectrum in the virtual prototype (see the module docstring).

    Attributes:
        kind: ``"this_system"`` | ``"manakov"`` | ``"fujimoto"``.
        filter_centers_nm: ``manakov``: centres of the Gaussian band-pass filters of views
            ``1 … V−1`` in order (nm); ``None`` = ``V − 1`` centres evenly spaced from
            ``filter_span_nm[0]`` to ``filter_span_nm[1]``.
        filter_span_nm: ``manakov``: first and last default centre (nm).
        filter_fwhm_nm: ``manakov``: FWHM of the band-pass filters (nm).
        filter_peak: ``manakov``: peak transmittance of the band-pass filters (0…1).
        filter_curves: ``manakov``: measured curves replacing the band-pass set, one per
            filtered view: ``(wavelengths_nm, transmittance)`` pairs (0…1), e.g. from CSV files.
        grain_size_mm: ``fujimoto``: mean grain size of the thin section (mm on the diffuser).
        grain_opd_factor: ``fujimoto``: range of the per-grain factor on the plate's OPD.
        grain_seed: ``fujimoto``: seed of the grain map.
    """

    kind: str = "this_system"
    filter_centers_nm: tuple[float, ...] | None = None
    filter_span_nm: tuple[float, float] = (440.0, 660.0)
    filter_fwhm_nm: float = 30.0
    filter_peak: float = 0.9
    filter_curves: tuple[tuple[Any, Any], ...] | None = field(default=None, repr=False)
    grain_size_mm: float = 3.0
    grain_opd_factor: tuple[float, float] = (0.5, 6.0)
    grain_seed: int = 0

    def __post_init__(self) -> None:
        if self.kind not in DESIGN_KINDS:
            raise ValueError(f"design kind must be one of {list(DESIGN_KINDS)}, got {self.kind!r}")
        if self.filter_centers_nm is not None:
            self.filter_centers_nm = tuple(float(c) for c in self.filter_centers_nm)
        self.filter_span_nm = tuple(float(v) for v in self.filter_span_nm)  # type: ignore
        self.grain_opd_factor = tuple(float(v) for v in self.grain_opd_factor)  # type: ignore
        if len(self.filter_span_nm) != 2 or self.filter_span_nm[1] < self.filter_span_nm[0]:
            raise ValueError(f"design.filter_span_nm must be (first, last) with first <= last, "
                             f"got {self.filter_span_nm}")
        if not self.filter_fwhm_nm > 0:
            raise ValueError(f"design.filter_fwhm_nm must be > 0, got {self.filter_fwhm_nm}")
        if not 0 < self.filter_peak <= 1:
            raise ValueError(f"design.filter_peak must be in (0, 1], got {self.filter_peak}")
        if not self.grain_size_mm > 0:
            raise ValueError(f"design.grain_size_mm must be > 0, got {self.grain_size_mm}")
        lo, hi = self.grain_opd_factor if len(self.grain_opd_factor) == 2 else (-1.0, -1.0)
        if not 0 < lo <= hi:
            raise ValueError(f"design.grain_opd_factor must be (low, high) with 0 < low <= high, "
                             f"got {self.grain_opd_factor}")

    @property
    def has_brf(self) -> bool:
        """Whether the spectral coder is a birefringent filter between polarizers."""
        return self.kind != "manakov"

    # ------------------------------------------------------------------ manakov
    def view_filters(self, num_views: int, wavelengths_nm: torch.Tensor) -> torch.Tensor:
        """``(V, L)`` transmittance of each view's filter at ``wavelengths_nm (L,)``: row 0 (the
        reference view) is 1, rows ``1 … V−1`` the filter set (``manakov`` only).

        Raises:
            ValueError: the set does not hold ``V − 1`` filters, or the kind is not ``manakov``.
        """
        if self.kind != "manakov":
            raise ValueError(f"view_filters: design kind {self.kind!r} has no per-view filters")
        wl = wavelengths_nm
        n = num_views - 1
        if self.filter_curves is not None:
            if len(self.filter_curves) != n:
                raise ValueError(f"design.filters: {len(self.filter_curves)} curves for {n} "
                                 f"filtered views (views 1..{n})")
            rows = []
            for src, val in self.filter_curves:
                s = torch.as_tensor(src, dtype=torch.float64, device=wl.device)
                v = torch.as_tensor(val, dtype=torch.float64, device=wl.device)
                rows.append(_interp(wl.to(torch.float64), s, v))
            filt = torch.stack(rows).to(wl.dtype)
        else:
            centres = self.filter_centers_nm
            if centres is None:
                a, b = self.filter_span_nm
                centres = tuple(a + (b - a) * k / max(n - 1, 1) for k in range(n))
            if len(centres) != n:
                raise ValueError(f"design.filter_centers_nm: {len(centres)} centres for {n} "
                                 f"filtered views (views 1..{n})")
            filt = gaussian_bandpass(wl, centres, self.filter_fwhm_nm, self.filter_peak)
        if bool((filt < 0).any()) or bool((filt > 1 + 1e-9).any()):
            raise ValueError("design filters: transmittance must lie in [0, 1]")
        return torch.cat([torch.ones_like(wl)[None], filt], 0)

    # ------------------------------------------------------------------ fujimoto
    def grain_factor(self, xy_mm: torch.Tensor) -> torch.Tensor:
        """``(N,)`` factor on the OPD of rays crossing the thin section at ``xy_mm (N, 2)`` (mm).

        Grains: one seed per cell of a square grid of pitch ``grain_size_mm``, placed uniformly
        at random in its cell (deterministic in ``grain_seed`` and the cell); a point belongs to
        the nearest seed among the 3 × 3 cells around it. Each grain's factor is uniform in
        ``grain_opd_factor``. Float64 inside; the result has the dtype of ``xy_mm``.
        """
        g = float(self.grain_size_mm)
        x = xy_mm.to(torch.float64) / g
        cell = torch.floor(x).to(torch.int64)  # (N, 2)
        best = torch.full(x.shape[:1], float("inf"), dtype=torch.float64, device=x.device)
        fac = torch.zeros_like(best)
        lo, hi = self.grain_opd_factor
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                ci, cj = cell[:, 0] + di, cell[:, 1] + dj
                sx = ci.to(torch.float64) + _hash_uniform(ci, cj, self.grain_seed, 1)
                sy = cj.to(torch.float64) + _hash_uniform(ci, cj, self.grain_seed, 2)
                d = (x[:, 0] - sx) ** 2 + (x[:, 1] - sy) ** 2
                f = lo + (hi - lo) * _hash_uniform(ci, cj, self.grain_seed, 3)
                closer = d < best
                best = torch.where(closer, d, best)
                fac = torch.where(closer, f, fac)
        return fac.to(xy_mm.dtype)

    def to_dict(self) -> dict[str, Any]:
        """JSON-able fields (``filter_curves`` as the number of curves)."""
        return {"kind": self.kind,
                "filter_centers_nm": (None if self.filter_centers_nm is None
                                      else list(self.filter_centers_nm)),
                "filter_span_nm": list(self.filter_span_nm), "filter_fwhm_nm": self.filter_fwhm_nm,
                "filter_peak": self.filter_peak,
                "filter_curves": None if self.filter_curves is None else len(self.filter_curves),
                "grain_size_mm": self.grain_size_mm,
                "grain_opd_factor": list(self.grain_opd_factor), "grain_seed": self.grain_seed}


def _interp(x: torch.Tensor, xp: torch.Tensor, fp: torch.Tensor) -> torch.Tensor:
    """Linear interpolation of ``fp(xp)`` at ``x`` (``xp`` increasing); error outside ``xp``."""
    if float(x.min()) < float(xp[0]) - 1e-9 or float(x.max()) > float(xp[-1]) + 1e-9:
        raise ValueError(f"design filter curve covers {float(xp[0]):g}-{float(xp[-1]):g} nm, "
                         f"the band needs {float(x.min()):g}-{float(x.max()):g} nm")
    idx = torch.searchsorted(xp, x.clamp(xp[0], xp[-1])).clamp(1, xp.numel() - 1)
    x0, x1 = xp[idx - 1], xp[idx]
    t = (x - x0) / (x1 - x0)
    return fp[idx - 1] + t * (fp[idx] - fp[idx - 1])
