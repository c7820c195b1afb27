"""Sensing designs for the experiments: channel-response builders.

A *sensing design* is a linear map from a reflectance spectrum ``r (M,)`` on a wavelength grid to
``K`` noise-free observations ``y = A r`` (before exposure matching). Row ``k`` of ``A`` is
``T_k(λ_m) · l(λ_m) · Δλ_m``: the channel's spectral response to radiance ``T_k`` times the
illuminant ``l`` times the band width, so observations are radiances of reflectances under ``l``.

Designs:

- **this system** (:func:`this_system_design`): ``A[(v,c), m] = g_v B_v(λ_m) Δλ_m φ^c(λ_m)`` with
  the BRF transmittance ``B_v`` of the ray that sees a scene point in view ``v``, ``φ^c = l f^c``
  and ``g_v = R^n`` (mirror reflectance per bounce); or from a calibration bundle
  (:func:`bundle_design`).
- **3Camera** (:func:`three_camera_design`): nine channels ``T_{q,c} = f_q^c``.
- **Faced Reflectors** (:func:`faced_reflectors_design`): ``T_{i,c} = f^c τ^i``, ``i = 0 … N``.
- **Manakov** (:func:`manakov_design`): the same kaleidoscope with one filter per view and no BRF
  (:class:`~hsi_torch.optics.PrototypeDesign` ``manakov``): ``T_{v,c} = g_v F_v f^c``.
- **Fujimoto** (:func:`fujimoto_design`): the same kaleidoscope with a birefringent thin section
  whose OPD varies over the aperture (``fujimoto``): this system's formula with the OPD times the
  grain factor at the scene point.
- any design from a CSV of channel responses (:func:`csv_design`).

The helpers :func:`scene_points`, :func:`view_rays` and :func:`brf_sensing_model` are shared
with the BRF design sweep (:mod:`hsi_torch.experiments.design`) and ``scripts/optics_report.py``.
All builders return float tensors on the requested ``device``/``dtype``.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from hsi_torch import refdata
from hsi_torch.forward_model import SensingModel
from hsi_torch.io.bundle import CalibrationBundle
from hsi_torch.optics import (
    DEFAULT_CAMERA,
    DEFAULT_GEOMETRY,
    BRFConfig,
    CameraModel,
    KaleidoscopeGeometry,
    PrototypeDesign,
    apply_homography,
    build_view_layout,
    trace_rays,
    trace_sensor,
)
from hsi_torch.optics.birefringence import polarizer_transmittance
from hsi_torch.spectral import DEFAULT_GRID, SpectralGrid, resample_spectra

__all__ = [
    "SensingDesign",
    "DEFAULT_3CAMERA",
    "DEFAULT_FACED_FILTER",
    "DEFAULT_FACED_BOUNCES",
    "phi_matrix",
    "scene_points",
    "view_rays",
    "brf_sensing_model",
    "this_system_design",
    "this_system_matrices",
    "bundle_design",
    "three_camera_design",
    "faced_reflectors_design",
    "manakov_design",
    "fujimoto_design",
    "csv_design",
]

#: Default cameras of the 3Camera baseline (measured sets shipped with colour-science/rawtoaces).
DEFAULT_3CAMERA: tuple[str, str, str] = (
    "Canon EOS 5D Mark II",
    "Nikon 5100 (NPL)",
    "Sigma SDMerill (NPL)",
)
#: Default filter of the Faced Reflectors baseline: Lee 068 Sky Blue (shipped, see refdata).
DEFAULT_FACED_FILTER = "L068"
#: Default highest bounce order N of the Faced Reflectors baseline (channels i = 0 … N).
DEFAULT_FACED_BOUNCES = 4


@dataclass
class SensingDesign:
    """A sensing design on a wavelength grid.

    Attributes:
        name: label used in tables and figures.
        matrix: ``(K, M)`` noise-free observation of a reflectance: ``y = matrix @ r``
            (illuminant and band widths included; arbitrary overall scale).
        channel_names: ``K`` labels (e.g. ``"v3/G"``, ``"Nikon 5100 (NPL)/R"``, ``"i=2/B"``).
        grid: the wavelength grid of ``matrix``.
        info: provenance (kind, cameras, filter, scene point, …) for reports.
    """

    name: str
    matrix: Tensor
    channel_names: list[str]
    grid: SpectralGrid = DEFAULT_GRID
    info: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.matrix.ndim != 2 or self.matrix.shape[1] != self.grid.num_bands:
            raise ValueError(
                f"design {self.name!r}: matrix must have shape (K, {self.grid.num_bands}), "
                f"got {tuple(self.matrix.shape)}"
            )
        if len(self.channel_names) != self.matrix.shape[0]:
            raise ValueError(
                f"design {self.name!r}: {len(self.channel_names)} channel names for "
                f"{self.matrix.shape[0]} channels"
            )
        if not bool(torch.isfinite(self.matrix).all()):
            raise ValueError(f"design {self.name!r}: matrix holds non-finite values")

    @property
    def num_channels(self) -> int:
        return int(self.matrix.shape[0])

    def responses(self) -> Tensor:
        """``(K, M)`` channel responses per nm (``matrix / Δλ``), for plots."""
        dl = self.grid.band_widths(device=self.matrix.device, dtype=self.matrix.dtype)
        return self.matrix / dl


def _rgb(prefix: str) -> list[str]:
    return [f"{prefix}/{c}" for c in "RGB"]


def phi_matrix(
    camera: str | os.PathLike = refdata.DEFAULT_CAMERA,
    illuminant: str | os.PathLike = "D65",
    grid: SpectralGrid = DEFAULT_GRID,
    *,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float64,
) -> Tensor:
    """``(3, M)`` φ^c(λ) = l(λ) f^c(λ): illuminant (1 at 560 nm) × camera sensitivities (``"max"``
    normalisation, so the ratios between R, G, B are kept)."""
    f = refdata.camera_sensitivities(camera, grid, device=device, dtype=dtype)
    l_ = refdata.illuminant(illuminant, grid, device=device, dtype=dtype)
    return f * l_


# --- this system: rays through the kaleidoscope


def scene_points(geometry: Any, dtype: torch.dtype = torch.float64) -> Tensor:
    """``(7, 2)`` diffuser points (mm): the centre, then half-way from it to each entrance vertex
    and to each edge midpoint (vertex k, then edge k→k+1, for k = 0, 1, 2)."""
    v = geometry.entrance_vertices(dtype=dtype)
    c = v.mean(0)
    pts = [c]
    for k in range(3):
        pts.append(c + 0.5 * (v[k] - c))
        pts.append(c + 0.5 * (0.5 * (v[k] + v[(k + 1) % 3]) - c))
    return torch.stack(pts)


def view_rays(
    geometry: Any, camera: Any, layout: Any, points_mm: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """``(α, σ, throughput)``, each ``(P, V)``, of the rays that see ``points_mm (P, 2)`` (mm) in
    each view of ``layout`` (traced through the kaleidoscope; α, σ in rad).

    Raises:
        ValueError: a point is not seen by every view (off the sensor or outside the triangle).
    """
    p, v = points_mm.shape[0], layout.num_views
    hd = layout.diffuser_homographies.to(points_mm)
    px = torch.stack([apply_homography(hd[i], points_mm) for i in range(v)], 1)
    tr = trace_rays(geometry, camera, px.reshape(-1, 2), sequences=layout.reflection_sequences)
    seen = tr.view_index.reshape(p, v) == torch.arange(v, device=tr.view_index.device)
    if not bool(seen.all()):
        bad = (~seen).nonzero()[:, 0].unique().tolist()
        raise ValueError(
            f"scene points {bad} (of points_mm, shape {tuple(points_mm.shape)}) are not seen by "
            "every view of the layout"
        )
    return tr.alpha.reshape(p, v), tr.sigma.reshape(p, v), tr.throughput.reshape(p, v)


def brf_sensing_model(
    brf: Any,
    alpha: Tensor,
    sigma: Tensor,
    throughput: Tensor,
    grid: SpectralGrid,
    phi: Tensor,
) -> SensingModel:
    """The forward model ``A[(v,c), m] = g_v B_v(λ_m) Δλ_m φ^c(λ_m)`` of ``P`` scene points.

    Args:
        brf: a :class:`~hsi_torch.optics.BRFConfig` (``B_v`` its transmittance along each ray).
        alpha, sigma, throughput: ``(P, V)`` rays (rad) and ``g_v`` per scene point and view.
        grid: wavelength grid (``M``); phi: ``(3, M)``.

    Returns:
        :class:`~hsi_torch.forward_model.SensingModel` of ``P`` pixels (``.dense()``:
        ``(P, 3V, M)``, rows view-major ``o = 3v + c``), dtype/device of ``alpha``.
    """
    wl = grid.wavelengths(device=alpha.device, dtype=alpha.dtype)
    dl = grid.band_widths(device=alpha.device, dtype=alpha.dtype)
    t = brf.transmittance(alpha[..., None], sigma[..., None], wl)  # (P, V, M)
    return SensingModel(t, throughput.to(t), dl * phi.to(t))


def _optics(
    geometry: Any | Mapping[str, Any] | None,
    camera: Any | Mapping[str, Any] | None,
    brf: Any | Mapping[str, Any] | None,
) -> tuple[Any, Any, Any]:
    def build(value: Any, default: Any, cls: type, what: str) -> Any:
        if value is None:
            return default
        if isinstance(value, cls):
            return value
        if isinstance(value, Mapping):
            d = dict(default.to_dict()) if hasattr(default, "to_dict") else {}
            d.update(value)
            try:
                return cls.from_dict(d) if hasattr(cls, "from_dict") else cls(**d)
            except TypeError as exc:
                raise ValueError(f"{what}: {exc}") from None
        raise TypeError(f"{what} must be a {cls.__name__} or a mapping, got {type(value).__name__}")

    return (
        build(geometry, DEFAULT_GEOMETRY, KaleidoscopeGeometry, "geometry"),
        build(camera, DEFAULT_CAMERA, CameraModel, "camera"),
        build(brf, BRFConfig(), BRFConfig, "brf"),
    )


def this_system_matrices(
    grid: SpectralGrid = DEFAULT_GRID,
    *,
    geometry: Any | Mapping[str, Any] | None = None,
    camera_model: Any | Mapping[str, Any] | None = None,
    brf: Any | Mapping[str, Any] | None = None,
    camera: str | os.PathLike = refdata.DEFAULT_CAMERA,
    illuminant: str | os.PathLike = "D65",
    points_mm: Tensor | None = None,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float64,
) -> tuple[Tensor, Tensor, Any]:
    """Sensing matrices of the simulated prototype at several scene points.

    Traces the sensor once (``trace_sensor`` + ``build_view_layout``), then the rays seeing each
    point in each view, and evaluates ``g_v B_v(λ) Δλ φ^c(λ)`` with ``g_v = R^n``.

    Args:
        geometry, camera_model, brf: optics (objects or mappings of field overrides on the
            defaults ``DEFAULT_GEOMETRY``, ``DEFAULT_CAMERA``, ``BRFConfig()``).
        camera: camera sensitivities for φ (default Canon EOS 5D Mark II); illuminant: l(λ).
        points_mm: ``(P, 2)`` diffuser points; default :func:`scene_points` (7 points).

    Returns:
        ``(A (P, 3V, M), points_mm (P, 2), layout)``.
    """
    geom, cam, brf_, layout = _traced(geometry, camera_model, brf)
    pts = scene_points(geom) if points_mm is None else points_mm.to("cpu", torch.float64)
    alpha, sigma, thr = view_rays(geom, cam, layout, pts)
    phi = phi_matrix(camera, illuminant, grid)
    a = brf_sensing_model(brf_, alpha, sigma, thr, grid, phi).dense()
    return a.to(device=device, dtype=dtype), pts.to(device=device, dtype=dtype), layout


def this_system_design(
    grid: SpectralGrid = DEFAULT_GRID,
    *,
    geometry: Any | Mapping[str, Any] | None = None,
    camera_model: Any | Mapping[str, Any] | None = None,
    brf: Any | Mapping[str, Any] | None = None,
    camera: str | os.PathLike = refdata.DEFAULT_CAMERA,
    illuminant: str | os.PathLike = "D65",
    scene_point: str | Sequence[float] = "centre",
    name: str = "this system",
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float64,
) -> SensingDesign:
    """The prototype's ``3V`` channels at one scene point.

    Args:
        scene_point: ``"centre"`` (the diffuser centre, i.e. the tube axis), ``"mean"`` (the
            sensing matrices of the 7 :func:`scene_points` averaged) or ``(X, Y)`` in mm.
        other arguments: see :func:`this_system_matrices`.
    """
    pts = _point_xy(scene_point, ("centre", "center", "mean"))
    a, p, layout = this_system_matrices(
        grid, geometry=geometry, camera_model=camera_model, brf=brf, camera=camera,
        illuminant=illuminant, points_mm=pts, device=device, dtype=dtype,
    )  # fmt: skip
    mat = a.mean(0) if scene_point == "mean" else a[0]
    names = [f"v{v}/{c}" for v in range(layout.num_views) for c in "RGB"]
    geom, cam, brf_ = _optics(geometry, camera_model, brf)
    info = {
        "kind": "this_system",
        "scene_point": scene_point if isinstance(scene_point, str) else list(p[0].tolist()),
        "camera": os.fspath(camera),
        "illuminant": os.fspath(illuminant),
        "brf": brf_.to_dict(),
        "geometry": geom.to_dict(),
        "opd_nm_550": layout.opd_nm.tolist(),
    }
    return SensingDesign(name, mat, names, grid, info)


def _point_xy(scene_point: str | Sequence[float], names: tuple[str, ...]) -> Tensor | None:
    """``(1, 2)`` float64 point (mm) of ``(X, Y)``, or None for one of ``names``."""
    if isinstance(scene_point, str):
        if scene_point not in names:
            shown = ", ".join(repr(n) for n in names if n != "center")
            raise ValueError(f"scene_point must be {shown} or (X, Y) mm, got {scene_point!r}")
        return None
    xy = [float(v) for v in scene_point]
    if len(xy) != 2:
        raise ValueError(f"scene_point must be (X, Y) in mm, got {scene_point!r}")
    return torch.tensor([xy], dtype=torch.float64)


def _traced(geometry: Any, camera_model: Any, brf: Any) -> tuple[Any, Any, Any, Any]:
    """``(geometry, camera, brf, layout)``: the optics built by :func:`_optics` and their layout."""
    geom, cam, brf_ = _optics(geometry, camera_model, brf)
    layout = build_view_layout(geom, cam, brf_, trace=trace_sensor(geom, cam, dtype=torch.float64))
    return geom, cam, brf_, layout


def _coded_design(
    design: PrototypeDesign,
    grid: SpectralGrid,
    *,
    geometry: Any | Mapping[str, Any] | None,
    camera_model: Any | Mapping[str, Any] | None,
    brf: Any | Mapping[str, Any] | None,
    camera: str | os.PathLike,
    illuminant: str | os.PathLike,
    scene_point: str | Sequence[float],
    name: str,
    device: torch.device | str | None,
    dtype: torch.dtype,
) -> SensingDesign:
    """``A[(v,c), m] = g_v T_v(λ_m) Δλ_m φ^c(λ_m)`` of a :class:`PrototypeDesign` at one scene
    point: ``T_v`` the view's filter (``manakov``) or the BRF transmittance with the OPD times the
    thin section's grain factor at the point (``fujimoto``)."""
    geom, cam, brf_, layout = _traced(geometry, camera_model, brf)
    pts = _point_xy(scene_point, ("centre", "center"))
    pts = scene_points(geom)[:1] if pts is None else pts
    alpha, sigma, thr = view_rays(geom, cam, layout, pts)  # (1, V)
    wl = grid.wavelengths(dtype=torch.float64)
    info: dict[str, Any] = {"kind": design.kind, "design": design.to_dict(),
                            "scene_point": list(pts[0].tolist()), "camera": os.fspath(camera),
                            "illuminant": os.fspath(illuminant), "geometry": geom.to_dict()}
    if design.kind == "manakov":
        t = design.view_filters(layout.num_views, wl)[None]  # (1, V, M)
    else:
        fac = design.grain_factor(pts)  # (1,)
        opd = brf_.opd_nm(alpha[..., None], sigma[..., None], wl) * fac[:, None, None]
        t = polarizer_transmittance(opd, wl, np.radians(brf_.psi_deg), np.radians(brf_.chi_deg))
        info.update(brf=brf_.to_dict(), grain_factor=float(fac[0]),
                    opd_nm_550=(brf_.opd_nm(alpha, sigma, torch.tensor(550.0, dtype=torch.float64))
                                * fac[:, None])[0].tolist())
    phi = phi_matrix(camera, illuminant, grid)
    dl = grid.band_widths(dtype=torch.float64)
    a = SensingModel(t, thr.to(t), dl * phi).dense()[0]
    names = [f"v{v}/{c}" for v in range(layout.num_views) for c in "RGB"]
    return SensingDesign(name, a.to(device=device, dtype=dtype), names, grid, info)


def manakov_design(
    grid: SpectralGrid = DEFAULT_GRID,
    *,
    design: PrototypeDesign | Mapping[str, Any] | None = None,
    geometry: Any | Mapping[str, Any] | None = None,
    camera_model: Any | Mapping[str, Any] | None = None,
    camera: str | os.PathLike = refdata.DEFAULT_CAMERA,
    illuminant: str | os.PathLike = "D65",
    scene_point: str | Sequence[float] = "centre",
    name: str = "Manakov",
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float64,
) -> SensingDesign:
    """The kaleidoscope with one filter per view (Manakov et al. 2013): ``3V`` channels
    ``g_v F_v(λ) f^c(λ)`` at one scene point, ``F_0 = 1`` (the unfiltered reference view) and
    ``F_1 … F_{V−1}`` the :class:`~hsi_torch.optics.PrototypeDesign` filter set (``design``:
    an object or field overrides of ``PrototypeDesign(kind="manakov")``)."""
    d = _design_of("manakov", design)
    return _coded_design(d, grid, geometry=geometry, camera_model=camera_model, brf=None,
                         camera=camera, illuminant=illuminant, scene_point=scene_point,
                         name=name, device=device, dtype=dtype)


#: The thin section of the ``fujimoto`` design: 30 µm calcite (the standard petrographic
#: thickness), axis as this system's plate (per-grain variation in the grain factor).
FUJIMOTO_BRF: dict[str, Any] = {"material": "calcite", "thickness_mm": 0.03}


def fujimoto_design(
    grid: SpectralGrid = DEFAULT_GRID,
    *,
    design: PrototypeDesign | Mapping[str, Any] | None = None,
    geometry: Any | Mapping[str, Any] | None = None,
    camera_model: Any | Mapping[str, Any] | None = None,
    brf: Any | Mapping[str, Any] | None = None,
    camera: str | os.PathLike = refdata.DEFAULT_CAMERA,
    illuminant: str | os.PathLike = "D65",
    scene_point: str | Sequence[float] = "centre",
    name: str = "Fujimoto",
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float64,
) -> SensingDesign:
    """The kaleidoscope with a birefringent thin section (Fujimoto et al. 2025) at one scene
    point: this system's channels with every view's OPD times the grain factor of the point
    (``brf`` default :data:`FUJIMOTO_BRF`; ``design``: overrides of
    ``PrototypeDesign(kind="fujimoto")``)."""
    d = _design_of("fujimoto", design)
    b = dict(FUJIMOTO_BRF)
    if isinstance(brf, Mapping):
        b.update(brf)
    return _coded_design(d, grid, geometry=geometry, camera_model=camera_model,
                         brf=brf if isinstance(brf, BRFConfig) else b, camera=camera,
                         illuminant=illuminant, scene_point=scene_point, name=name,
                         device=device, dtype=dtype)


def _design_of(kind: str, design: PrototypeDesign | Mapping[str, Any] | None) -> PrototypeDesign:
    if isinstance(design, PrototypeDesign):
        if design.kind != kind:
            raise ValueError(f"design kind {design.kind!r} given to the {kind} builder")
        return design
    d = dict(design or {})
    d.setdefault("kind", kind)
    if d["kind"] != kind:
        raise ValueError(f"design kind {d['kind']!r} given to the {kind} builder")
    try:
        return PrototypeDesign(**d)
    except TypeError as exc:
        raise ValueError(f"design: {exc}") from None


def bundle_design(
    path: str | os.PathLike,
    grid: SpectralGrid = DEFAULT_GRID,
    *,
    pixel: Sequence[int] | None = None,
    name: str = "this system (bundle)",
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float64,
) -> SensingDesign:
    """This system's channels from a calibration bundle (:class:`~hsi_torch.io.CalibrationBundle`).

    ``A_p[(v,c), m] = gain[v,p] B[v,m,p] Δλ_m phi[c,m]`` averaged over the valid pixels where every
    view is present, or at ``pixel = (row, col)`` of the reference frame. ``phi`` is the calibrated
    φ = l·f, so the calibration's illuminant is used as is. The bundle's wavelengths must equal
    ``grid``.
    """
    b = CalibrationBundle.load(path)
    wl = np.asarray(b.wavelengths_nm, dtype=np.float64)
    if wl.shape != (grid.num_bands,) or not np.allclose(wl, grid.wavelengths_nm):
        raise ValueError(
            f"calibration bundle {path}: wavelengths {wl.tolist()} differ from the experiment "
            f"grid {list(grid.wavelengths_nm)}"
        )
    h, w = b.frame_size
    vm = np.asarray(b.view_mask).reshape(b.num_views, -1)
    if pixel is not None:
        r, c = (int(v) for v in pixel)
        if not (0 <= r < h and 0 <= c < w):
            raise ValueError(f"pixel (row {r}, col {c}) lies outside the reference frame ({h} "
                             f"rows, {w} columns) of {path}")  # fmt: skip
        idx = np.array([r * w + c])
        if not vm[:, idx[0]].all():
            raise ValueError(f"pixel (row {r}, col {c}) of {path} is not seen by every view")
    else:
        full = vm.all(0) & np.asarray(b.valid).reshape(-1)
        idx = np.flatnonzero(full)
        if idx.size == 0:
            raise ValueError(f"calibration bundle {path}: no valid pixel is seen by every view")
    a = b.sensing_model(torch.as_tensor(idx), device=device, dtype=torch.float64).dense().mean(0)
    names = [f"v{v}/{c}" for v in range(b.num_views) for c in "RGB"]
    info = {"kind": "bundle", "path": os.fspath(path),
            "pixel": None if pixel is None else [int(v) for v in pixel], "pixels": int(idx.size)}
    return SensingDesign(name, a.to(dtype), names, grid, info)


def three_camera_design(
    cameras: Sequence[str | os.PathLike] = DEFAULT_3CAMERA,
    grid: SpectralGrid = DEFAULT_GRID,
    *,
    illuminant: str | os.PathLike = "D65",
    name: str = "3Camera",
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float64,
) -> SensingDesign:
    """Nine (``3 × len(cameras)``) channels ``T_{q,c} = f_q^c`` (each camera ``"max"``-normalised,
    i.e. its own channel ratios kept), × illuminant × Δλ."""
    if len(cameras) < 1:
        raise ValueError("cameras must name at least one camera")
    dl = grid.band_widths(device=device, dtype=dtype)
    rows, names = [], []
    for cam in cameras:
        rows.append(phi_matrix(cam, illuminant, grid, device=device, dtype=dtype) * dl)
        names += _rgb(Path(os.fspath(cam)).stem if os.fspath(cam).endswith(".json")
                      or os.fspath(cam).endswith(".csv") else os.fspath(cam))
    info = {"kind": "three_camera", "cameras": [os.fspath(c) for c in cameras],
            "illuminant": os.fspath(illuminant)}
    return SensingDesign(name, torch.cat(rows), names, grid, info)


def faced_reflectors_design(
    filter_name: str | os.PathLike = DEFAULT_FACED_FILTER,
    bounces: int = DEFAULT_FACED_BOUNCES,
    grid: SpectralGrid = DEFAULT_GRID,
    *,
    camera: str | os.PathLike = refdata.DEFAULT_CAMERA,
    illuminant: str | os.PathLike = "D65",
    name: str = "Faced Reflectors",
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float64,
) -> SensingDesign:
    """``3(N+1)`` channels ``T_{i,c} = f^c τ^i`` for bounces ``i = 0 … N`` (``N = bounces``),
    τ a filter transmittance (a gel code such as ``'L068'``, see
    :func:`hsi_torch.refdata.filter_transmittance`, or a CSV), × illuminant × Δλ."""
    if int(bounces) < 0:
        raise ValueError(f"bounces must be >= 0, got {bounces}")
    tau = refdata.filter_transmittance(filter_name, grid, device=device, dtype=dtype)
    phi = phi_matrix(camera, illuminant, grid, device=device, dtype=dtype)
    dl = grid.band_widths(device=device, dtype=dtype)
    i = torch.arange(int(bounces) + 1, device=tau.device, dtype=dtype)
    powers = tau[None, :] ** i[:, None]  # (N+1, M)
    mat = (powers[:, None, :] * phi[None] * dl).reshape(-1, grid.num_bands)
    names = [n for k in range(int(bounces) + 1) for n in _rgb(f"i={k}")]
    info = {"kind": "faced_reflectors", "filter": os.fspath(filter_name), "bounces": int(bounces),
            "camera": os.fspath(camera), "illuminant": os.fspath(illuminant)}
    return SensingDesign(name, mat, names, grid, info)


def csv_design(
    path: str | os.PathLike,
    grid: SpectralGrid = DEFAULT_GRID,
    *,
    illuminant: str | os.PathLike = "D65",
    includes_illuminant: bool = False,
    name: str | None = None,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float64,
) -> SensingDesign:
    """Any design from a CSV ``wavelength_nm, ch_1, …, ch_K`` of channel responses T_k(λ).

    Responses are resampled linearly onto ``grid`` (error outside the table), multiplied by the
    illuminant (unless ``includes_illuminant``) and by Δλ. Header names become channel names.
    """
    src, table, cols = refdata.read_spectral_csv(path)
    vals = torch.as_tensor(np.ascontiguousarray(table.T), dtype=torch.float64)

    wl = grid.wavelengths(dtype=torch.float64)
    src_t = torch.as_tensor(np.ascontiguousarray(src, dtype=np.float64))
    if float(wl[0]) < float(src_t[0]) - 1e-9 or float(wl[-1]) > float(src_t[-1]) + 1e-9:
        raise ValueError(
            f"design CSV {path}: table covers {float(src_t[0])}-{float(src_t[-1])} nm but the grid "
            f"needs {float(wl[0])}-{float(wl[-1])} nm"
        )
    t = resample_spectra(vals, src_t, wl).to(device=device, dtype=dtype)
    if not includes_illuminant:
        t = t * refdata.illuminant(illuminant, grid, device=device, dtype=dtype)
    mat = t * grid.band_widths(device=device, dtype=dtype)
    names = list(cols) if cols and len(cols) == mat.shape[0] else [
        f"ch{k}" for k in range(mat.shape[0])
    ]
    info = {"kind": "csv", "path": os.fspath(path), "includes_illuminant": includes_illuminant}
    return SensingDesign(name or Path(path).stem, mat, names, grid, info)
