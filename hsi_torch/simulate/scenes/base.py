"""The scene interface and the sampling of scenes on pixel grids.

A :class:`Scene` is any object with ``extent`` ``(x_min, x_max, y_min, y_max)`` (mm) and
``reflectance(xy_mm (N, 2), wavelengths_nm (M,)) -> (N, M)``; a *linear-mixture* scene also has
``abundances(xy) (N, K)`` and ``endmember_spectra(λ) (K, M)`` (:func:`has_abundances`).
:func:`render_scene_image` and :func:`render_scene_abundances` sample either on a regular pixel
grid (box-filtered supersampling, a band of rows at a time); :func:`pixel_centres_mm` gives the
diffuser coordinates of the pixel centres. The helpers ``_prep`` (check and convert the inputs of
``reflectance``) and ``_constant_spectrum`` are shared by the scene families of this package.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol, runtime_checkable

import numpy as np
import torch
import torch.nn.functional as F

from hsi_torch import refdata
from hsi_torch.spectral import DEFAULT_GRID, SpectralGrid

__all__ = [
    "Scene",
    "Extent",
    "render_scene_image",
    "render_scene_abundances",
    "has_abundances",
    "pixel_centres_mm",
]


Extent = tuple[float, float, float, float]


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


# --- rendering helpers


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
