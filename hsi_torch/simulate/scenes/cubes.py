"""Reflectance cubes as scenes: any cube laid onto the diffuser (:class:`CubeScene`) and the CAVE
*stuffed toys* scene from the real-data folder (:func:`load_cave_cube`, :func:`load_cave_scene`).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from hsi_torch import refdata
from hsi_torch.resources import DATA_ENV, real_data_dir
from hsi_torch.simulate.scenes.base import Extent, _constant_spectrum, _prep
from hsi_torch.spectral import resample_spectra

__all__ = [
    "CubeScene",
    "CAVE_WAVELENGTHS_NM",
    "load_cave_cube",
    "load_cave_scene",
]


CAVE_WAVELENGTHS_NM = tuple(float(w) for w in range(400, 701, 10))


# --- User cube


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


# --- CAVE


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
