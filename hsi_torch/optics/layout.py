"""View layout of the kaleidoscope on the sensor, derived from a ray trace.

Convention: that of :mod:`hsi_torch.optics.geometry`; homographies are normalised to
``H[2, 2] = 1``, and ``diffuser_homographies[v]`` maps diffuser mm ``(X, Y, 1)`` to sensor px of
view ``v``. Both kinds are fitted by a normalised DLT on traced (hit point, pixel) pairs; for planar
mirrors the mapping is exactly projective, so the fit residual measures only numerical error.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import torch

from .birefringence import BRFConfig
from .geometry import apply_homography, pixel_centres, points_in_triangle
from .kaleidoscope import CameraModel, KaleidoscopeGeometry, RayTrace, trace_sensor

__all__ = [
    "ViewLayout",
    "build_view_layout",
    "fit_homography_dlt",
    "brf_free_mask",
]


def _normaliser(p: torch.Tensor) -> torch.Tensor:
    c = p.mean(0)
    s = math.sqrt(2.0) / (p - c).norm(dim=1).mean().clamp_min(1e-300)
    t = torch.eye(3, dtype=p.dtype, device=p.device)
    t[0, 0] = t[1, 1] = s
    t[:2, 2] = -s * c
    return t


def fit_homography_dlt(src: torch.Tensor, dst: torch.Tensor) -> torch.Tensor:
    """Least-squares homography ``dst ~ H src`` by the normalised DLT (Hartley), in float64.

    Args:
        src, dst: ``(N, 2)`` corresponding points, ``N >= 4``.

    Returns:
        ``(3, 3)`` float64 homography on ``src``'s device, ``H[2, 2] = 1``.
    """
    if src.ndim != 2 or src.shape[1] != 2 or dst.shape != src.shape:
        raise ValueError(
            f"src and dst must both be (N, 2), got {tuple(src.shape)} and {tuple(dst.shape)}"
        )
    if src.shape[0] < 4:
        raise ValueError(f"need at least 4 correspondences, got {src.shape[0]}")
    s, d = src.to(torch.float64), dst.to(device=src.device, dtype=torch.float64)
    ts, td = _normaliser(s), _normaliser(d)
    sn = s @ ts[:2, :2].T + ts[:2, 2]
    dn = d @ td[:2, :2].T + td[:2, 2]
    x, y = sn[:, 0:1], sn[:, 1:2]
    u, v = dn[:, 0:1], dn[:, 1:2]
    one, zero = torch.ones_like(x), torch.zeros_like(x)
    rows1 = torch.cat([-x, -y, -one, zero, zero, zero, u * x, u * y, u], 1)
    rows2 = torch.cat([zero, zero, zero, -x, -y, -one, v * x, v * y, v], 1)
    a = torch.cat([rows1, rows2], 0)
    _, _, vh = torch.linalg.svd(a, full_matrices=False)
    hn = vh[-1].reshape(3, 3)
    h = torch.linalg.solve(td, hn @ ts)
    return h / h[2, 2]


def brf_free_mask(geometry: KaleidoscopeGeometry, hit_xy: torch.Tensor) -> torch.Tensor:
    """Bool mask: diffuser points ``hit_xy (..., 2)`` (mm) with no filter stack (BRF-free disk).

    NaN hit points (rays that never reached the diffuser) give ``False``.
    """
    return geometry.brf_free_mask(hit_xy)


@dataclass
class ViewLayout:
    """Per-view geometry on the sensor (``V`` views; view 0 = reference, zero reflections).

    Attributes:
        reflection_sequences: view ``v``'s mirror sequence (``()`` for ``v = 0``).
        triangles: ``(V, 3, 2)`` images of the entrance vertices ``P_0, P_1, P_2`` (sensor px).
        parity: ``(V,)`` long, ``+1`` upright, ``−1`` mirrored (odd reflection count).
        view_homographies: ``(V, 3, 3)`` sensor px of view ``v`` → sensor px of view 0.
        diffuser_homographies: ``(V, 3, 3)`` diffuser mm → sensor px of view ``v``.
        mean_alpha, mean_sigma: ``(V,)`` mean incidence angle and (circular) mean azimuth at the
            filter over the view's pixels (rad).
        opd_nm: ``(V,)`` mean OPD over the view's pixels at ``opd_wavelength_nm`` (nm).
        pixel_count: ``(V,)`` number of sensor pixels of the view.
        homography_residual_px: ``(V,)`` max error (px) of ``view_homographies[v]`` over all
            traced pixels of the view (against the reference pixel of the same diffuser point).
        sensor_size: ``(H, W)``.
        reference_bbox: ``(x0, y0, w, h)`` integer px: the reference frame is the sensor crop
            ``x0 ≤ x < x0 + w, y0 ≤ y < y0 + h`` around view 0's triangle.
        brf_free_center_mm, brf_free_radius_mm: the BRF-free disk on the diffuser.
        opd_wavelength_nm: wavelength of ``opd_nm``.
    """

    reflection_sequences: list[tuple[int, ...]]
    triangles: torch.Tensor
    parity: torch.Tensor
    view_homographies: torch.Tensor
    diffuser_homographies: torch.Tensor
    mean_alpha: torch.Tensor
    mean_sigma: torch.Tensor
    opd_nm: torch.Tensor
    pixel_count: torch.Tensor
    homography_residual_px: torch.Tensor
    sensor_size: tuple[int, int]
    reference_bbox: tuple[int, int, int, int]
    brf_free_center_mm: tuple[float, float] = (0.0, 0.0)
    brf_free_radius_mm: float = 0.0
    opd_wavelength_nm: float = 550.0
    _TENSORS: ClassVar[tuple[str, ...]] = (
        "triangles",
        "parity",
        "view_homographies",
        "diffuser_homographies",
        "mean_alpha",
        "mean_sigma",
        "opd_nm",
        "pixel_count",
        "homography_residual_px",
    )

    @property
    def num_views(self) -> int:
        return len(self.reflection_sequences)

    @property
    def reference_triangle(self) -> torch.Tensor:
        return self.triangles[0]

    def to(
        self, device: torch.device | str | None = None, dtype: torch.dtype | None = None
    ) -> ViewLayout:
        """Copy with float tensors on ``device``/``dtype`` (integer tensors keep their dtype)."""
        kw = {}
        for name in self._TENSORS:
            t = getattr(self, name)
            kw[name] = t.to(
                device=device, dtype=dtype if (dtype and t.is_floating_point()) else t.dtype
            )
        return ViewLayout(
            reflection_sequences=list(self.reflection_sequences),
            sensor_size=self.sensor_size,
            reference_bbox=self.reference_bbox,
            brf_free_center_mm=self.brf_free_center_mm,
            brf_free_radius_mm=self.brf_free_radius_mm,
            opd_wavelength_nm=self.opd_wavelength_nm,
            **kw,
        )

    def sensor_to_diffuser(self, view: int, pixel_xy: torch.Tensor) -> torch.Tensor:
        """Diffuser point (mm) seen at sensor ``pixel_xy (..., 2)`` through view ``view``."""
        return apply_homography(
            torch.linalg.inv(self.diffuser_homographies[view].double()), pixel_xy
        )

    def reference_to_view(self, view: int, pixel_xy: torch.Tensor) -> torch.Tensor:
        """Sensor px of view ``view`` showing the scene point at reference-view px ``pixel_xy``."""
        return apply_homography(torch.linalg.inv(self.view_homographies[view].double()), pixel_xy)

    def triangle_mask(self, view: int, device: torch.device | str | None = None) -> torch.Tensor:
        """``(H, W)`` bool: pixel centres inside view ``view``'s triangle."""
        h, w = self.sensor_size
        tri = self.triangles[view].to(device=device, dtype=torch.float64)
        return points_in_triangle(pixel_centres(h, w, device=device).reshape(-1, 2),
                                  tri).reshape(h, w)

    def brf_free_mask_sensor(
        self, view: int = 0, device: torch.device | str | None = None
    ) -> torch.Tensor:
        """``(H, W)`` bool: pixels of view ``view`` whose diffuser point is in the BRF-free disk."""
        xy = self.sensor_to_diffuser(view, pixel_centres(*self.sensor_size, device=device))
        c = torch.tensor(self.brf_free_center_mm, device=device, dtype=torch.float64)
        inside = ((xy - c) ** 2).sum(-1) <= self.brf_free_radius_mm**2
        return inside & self.triangle_mask(view, device)

    def to_dict(self, arrays: bool = False) -> dict[str, Any]:
        """Plain dict: nested lists (JSON-able) or, with ``arrays=True``, numpy arrays (NPZ)."""
        d: dict[str, Any] = {
            "reflection_sequences": [list(s) for s in self.reflection_sequences],
            "sensor_size": list(self.sensor_size),
            "reference_bbox": list(self.reference_bbox),
            "brf_free_center_mm": list(self.brf_free_center_mm),
            "brf_free_radius_mm": float(self.brf_free_radius_mm),
            "opd_wavelength_nm": float(self.opd_wavelength_nm),
        }
        for name in self._TENSORS:
            a = getattr(self, name).detach().cpu().numpy()
            d[name] = a if arrays else a.tolist()
        return d

    @classmethod
    def from_dict(
        cls,
        d: Mapping[str, Any],
        device: torch.device | str | None = None,
        dtype: torch.dtype | None = None,
    ) -> ViewLayout:
        """Inverse of :meth:`to_dict` (lists or arrays); float tensors get ``dtype`` (float64)."""
        required = ("reflection_sequences", "sensor_size", "reference_bbox", *cls._TENSORS)
        missing = [k for k in required if k not in d]
        if missing:
            raise ValueError(f"ViewLayout dict is missing keys {missing}")
        fdt = dtype or torch.float64
        kw: dict[str, Any] = {}
        for name in cls._TENSORS:  # type: ignore[attr-defined]
            arr = np.asarray(d[name])
            t_dtype = torch.long if name in ("parity", "pixel_count") else fdt
            kw[name] = torch.as_tensor(arr, device=device).to(t_dtype)
        v = len(d["reflection_sequences"])
        if kw["triangles"].shape != (v, 3, 2) or kw["view_homographies"].shape != (v, 3, 3):
            raise ValueError(
                f"ViewLayout dict: triangles {tuple(kw['triangles'].shape)} / view_homographies "
                f"{tuple(kw['view_homographies'].shape)} do not match {v} views"
            )
        seqs = [tuple(int(m) for m in np.asarray(s).reshape(-1)) for s in d["reflection_sequences"]]
        return cls(
            reflection_sequences=seqs,
            sensor_size=tuple(int(x) for x in np.asarray(d["sensor_size"]).reshape(-1)),  # type: ignore[arg-type]
            reference_bbox=tuple(int(x) for x in np.asarray(d["reference_bbox"]).reshape(-1)),  # type: ignore[arg-type]
            brf_free_center_mm=tuple(
                float(x) for x in np.asarray(d.get("brf_free_center_mm", (0, 0))).reshape(-1)
            ),  # type: ignore[arg-type]
            brf_free_radius_mm=float(np.asarray(d.get("brf_free_radius_mm", 0.0))),
            opd_wavelength_nm=float(np.asarray(d.get("opd_wavelength_nm", 550.0))),
            **kw,
        )


def build_view_layout(
    geometry: KaleidoscopeGeometry,
    camera: CameraModel,
    brf: BRFConfig | None = None,
    *,
    trace: RayTrace | None = None,
    min_pixels: int = 50,
    fit_points: int = 4000,
    opd_wavelength_nm: float = 550.0,
    device: torch.device | str | None = None,
) -> ViewLayout:
    """Derive the :class:`ViewLayout` from a full-sensor trace.

    Args:
        brf: filter used for ``opd_nm`` (default :class:`BRFConfig` ``()``).
        trace: an ``(H, W)`` :func:`trace_sensor` result to reuse (traced in float64 otherwise).
        min_pixels: views with fewer pixels on the sensor are left out (sequences kept in order).
        fit_points: correspondences per view for the DLT fit (evenly strided subset).
        opd_wavelength_nm: wavelength for ``opd_nm``.
        device: where to trace when ``trace`` is None.

    Returns:
        The layout (float64 tensors on the trace's device).

    Raises:
        ValueError: if the reference view (zero reflections) is not on the sensor.
    """
    brf = brf if brf is not None else BRFConfig()
    if trace is None:
        trace = trace_sensor(geometry, camera, device=device, dtype=torch.float64)
    h, w = camera.height_px, camera.width_px
    if tuple(trace.view_index.shape) != (h, w):
        raise ValueError(
            f"trace must be an (H, W) = {(h, w)} sensor trace, got {tuple(trace.view_index.shape)}"
        )
    dev = trace.view_index.device
    pix = camera.pixel_grid(dev, torch.float64)
    vidx = trace.view_index.reshape(-1)
    hit = trace.hit_xy.reshape(-1, 2).to(torch.float64)
    alpha = trace.alpha.reshape(-1).to(torch.float64)
    sigma = trace.sigma.reshape(-1).to(torch.float64)
    counts = torch.bincount(vidx[vidx >= 0], minlength=len(trace.sequences)).cpu()

    keep = [i for i, n in enumerate(counts.tolist()) if n >= max(min_pixels, 8)]
    if not keep or trace.sequences[keep[0]] != ():
        raise ValueError("the reference view (no reflection) is not visible on the sensor")
    seqs, tris, par, hd, ma, ms, opd, npx = [], [], [], [], [], [], [], []
    verts = geometry.entrance_vertices(dev, torch.float64)
    members = []
    for i in keep:
        sel = torch.nonzero(vidx == i).squeeze(1)
        members.append(sel)
        stride = max(1, sel.numel() // fit_points)
        sub = sel[::stride]
        hmat = fit_homography_dlt(hit[sub], pix[sub])
        seqs.append(tuple(trace.sequences[i]))
        hd.append(hmat)
        tris.append(apply_homography(hmat, verts))
        par.append(1 - 2 * (len(trace.sequences[i]) % 2))
        ma.append(alpha[sel].mean())
        ms.append(torch.atan2(torch.sin(sigma[sel]).mean(), torch.cos(sigma[sel]).mean()))
        wl = torch.tensor(opd_wavelength_nm, device=dev, dtype=torch.float64)
        opd.append(brf.opd_nm(alpha[sel], sigma[sel], wl).mean())
        npx.append(sel.numel())
    hd_t = torch.stack(hd)
    h0 = hd_t[0]
    hv = torch.linalg.solve(hd_t.transpose(1, 2), h0.T.expand_as(hd_t)).transpose(
        1, 2
    )  # h0 @ inv(hd)
    hv = hv / hv[:, 2:3, 2:3]
    hv[0] = torch.eye(3, device=dev, dtype=torch.float64)
    resid = []
    for k, sel in enumerate(members):
        ref_px = apply_homography(h0, hit[sel])
        resid.append((apply_homography(hv[k], pix[sel]) - ref_px).norm(dim=1).max())
    tri0 = tris[0]
    x0 = int(max(0, math.floor(float(tri0[:, 0].min()))))
    y0 = int(max(0, math.floor(float(tri0[:, 1].min()))))
    x1 = int(min(w - 1, math.ceil(float(tri0[:, 0].max()))))
    y1 = int(min(h - 1, math.ceil(float(tri0[:, 1].max()))))
    return ViewLayout(
        reflection_sequences=seqs,
        triangles=torch.stack(tris),
        parity=torch.tensor(par, device=dev, dtype=torch.long),
        view_homographies=hv,
        diffuser_homographies=hd_t,
        mean_alpha=torch.stack(ma),
        mean_sigma=torch.stack(ms),
        opd_nm=torch.stack(opd),
        pixel_count=torch.tensor(npx, device=dev, dtype=torch.long),
        homography_residual_px=torch.stack(resid),
        sensor_size=(h, w),
        reference_bbox=(x0, y0, x1 - x0 + 1, y1 - y0 + 1),
        brf_free_center_mm=geometry.brf_free_center(),
        brf_free_radius_mm=float(geometry.brf_free_radius_mm),
        opd_wavelength_nm=float(opd_wavelength_nm),
    )
