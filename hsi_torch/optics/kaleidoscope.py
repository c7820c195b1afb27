"""Tapered triangular kaleidoscope: geometry, pinhole camera and a batched backward ray tracer.

Convention (see ``docs/architecture.md``):
    Diffuser plane ``z = 0``, tube axis ``+z`` (diffuser → camera), lengths in mm, origin on the
    tube axis. The entrance triangle (vertices ``P_i``, counter-clockwise in ``(X, Y)``) lies at
    ``z = 0``; the exit triangle is its copy scaled by ``a_out/a_in`` about the axis at
    ``z = L_k``. Mirror ``i`` is the planar face through the entrance edge ``P_i → P_{i+1}`` and
    the corresponding exit edge (tilted by the taper). The pinhole pupil sits at
    ``(0, 0, L_k + pupil_distance)``; pixel ``(x, y)`` (column, row; centres at integers) looks
    along ``((x − cx)·pitch, (y − cy)·pitch, −f)``.

    A traced ray ends on ``z = 0`` at ``hit_xy`` with unit direction ``d`` (``d_z < 0``). At the
    filter: ``α = arccos|d_z|`` and ``σ = atan2(−d_y, −d_x)`` (azimuth of the light travelling
    from the diffuser towards the camera).

    Views are named by their mirror sequence in the order the *backward* ray meets the mirrors
    (first = the mirror nearest the camera). The default enumeration of views is by number of
    reflections, then lexicographic: ``(), (0,), (1,), (2,), (0, 1), (0, 2), (1, 0), …``; view 0 is
    the direct (reference) view. For an equilateral tube and ≤ 2 reflections this gives 1 + 3 + 6
    = 10 views.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, fields
from typing import Any

import torch

from .geometry import pixel_centres, points_in_triangle

__all__ = [
    "KaleidoscopeGeometry",
    "CameraModel",
    "RayTrace",
    "enumerate_sequences",
    "sequence_codes",
    "trace_rays",
    "trace_sensor",
    "mirror_planes",
    "reflection_isometry",
    "diffuser_to_sensor_homography",
    "DEFAULT_GEOMETRY",
    "DEFAULT_CAMERA",
    "FULL_CAMERA",
]


@dataclass(frozen=True)
class KaleidoscopeGeometry:
    """A triangular mirror tube between the diffuser (``z = 0``) and the camera.

    Attributes:
        a_in_mm: entrance side length at the diffuser (equilateral), mm.
        a_out_mm: exit side length at ``z = length_mm`` (mm). ``a_out > a_in`` widens the tube
            towards the camera; each reflection then tilts the ray by about ``2τ`` further from the
            axis (τ the mirror tilt), spreading the views' angles at the filter.
        length_mm: tube length ``L_k`` (mm).
        pupil_distance_mm: distance of the camera pupil beyond the exit plane (mm).
        mirror_reflectance: reflectance per bounce (wavelength independent).
        max_reflections: rays needing more reflections are not a view (``view_index = −1``).
        vertices_in: optional ``((X0, Y0), (X1, Y1), (X2, Y2))`` entrance vertices (mm) for a
            non-equilateral tube, counter-clockwise; ``a_in_mm`` then only sets the taper ratio
            ``a_out/a_in`` about the origin (the tube axis).
        brf_free_center_mm: centre ``(X, Y)`` of the BRF-free disk on the diffuser (mm); ``None``
            puts it 60 % of the way from the axis to entrance vertex 0.
        brf_free_radius_mm: radius of the BRF-free disk (mm); 0 disables it.
    """

    a_in_mm: float = 16.0
    a_out_mm: float = 40.0
    length_mm: float = 160.0
    pupil_distance_mm: float = 12.0
    mirror_reflectance: float = 0.92
    max_reflections: int = 2
    vertices_in: tuple[tuple[float, float], ...] | None = None
    brf_free_center_mm: tuple[float, float] | None = None
    brf_free_radius_mm: float = 1.0

    def __post_init__(self) -> None:
        for name in ("a_in_mm", "a_out_mm", "length_mm", "pupil_distance_mm"):
            if not getattr(self, name) > 0:
                raise ValueError(
                    f"KaleidoscopeGeometry.{name} must be positive, got {getattr(self, name)}"
                )
        if not 0 <= self.mirror_reflectance <= 1:
            raise ValueError(
                f"mirror_reflectance must lie in [0, 1], got {self.mirror_reflectance}"
            )
        if int(self.max_reflections) != self.max_reflections or self.max_reflections < 0:
            raise ValueError(
                f"max_reflections must be a non-negative int, got {self.max_reflections}"
            )
        if self.brf_free_radius_mm < 0:
            raise ValueError(f"brf_free_radius_mm must be >= 0, got {self.brf_free_radius_mm}")
        if self.vertices_in is not None:
            v = torch.as_tensor(self.vertices_in, dtype=torch.float64)
            if v.shape != (3, 2):
                raise ValueError(f"vertices_in must have shape (3, 2), got {tuple(v.shape)}")
            e1, e2 = v[1] - v[0], v[2] - v[0]
            if float(e1[0] * e2[1] - e1[1] * e2[0]) <= 0:
                raise ValueError("vertices_in must be counter-clockwise and non-degenerate")
            object.__setattr__(self, "vertices_in", tuple(tuple(map(float, p)) for p in v.tolist()))
        if self.brf_free_center_mm is not None:
            object.__setattr__(
                self, "brf_free_center_mm", tuple(map(float, self.brf_free_center_mm))
            )

    @property
    def taper_ratio(self) -> float:
        return self.a_out_mm / self.a_in_mm

    @property
    def pupil_z(self) -> float:
        return self.length_mm + self.pupil_distance_mm

    def entrance_vertices(
        self, device: torch.device | str | None = None, dtype: torch.dtype | None = None
    ) -> torch.Tensor:
        """``(3, 2)`` entrance vertices (mm). Equilateral default: vertex 0 at ``−Y`` (top)."""
        dtype = dtype or torch.get_default_dtype()
        if self.vertices_in is not None:
            return torch.tensor(self.vertices_in, device=device, dtype=dtype)
        r = self.a_in_mm / math.sqrt(3.0)
        ang = [-math.pi / 2 + k * 2 * math.pi / 3 for k in range(3)]
        return torch.tensor(
            [[r * math.cos(a), r * math.sin(a)] for a in ang], device=device, dtype=dtype
        )

    def exit_vertices(
        self, device: torch.device | str | None = None, dtype: torch.dtype | None = None
    ) -> torch.Tensor:
        """``(3, 2)`` exit vertices (mm) at ``z = length_mm``."""
        return self.entrance_vertices(device, dtype) * self.taper_ratio

    def brf_free_center(self) -> tuple[float, float]:
        """Centre of the BRF-free disk (mm)."""
        if self.brf_free_center_mm is not None:
            return self.brf_free_center_mm  # type: ignore[return-value]
        v0 = self.entrance_vertices(dtype=torch.float64)
        c = v0.mean(0) + 0.6 * (v0[0] - v0.mean(0))
        return float(c[0]), float(c[1])

    def brf_free_mask(self, hit_xy: torch.Tensor) -> torch.Tensor:
        """Bool mask of diffuser points ``hit_xy (..., 2)`` (mm) inside the BRF-free disk."""
        if hit_xy.shape[-1] != 2:
            raise ValueError(f"hit_xy must have a last dimension of 2, got {tuple(hit_xy.shape)}")
        c = torch.tensor(self.brf_free_center(), device=hit_xy.device, dtype=hit_xy.dtype)
        return ((hit_xy - c) ** 2).sum(-1) <= self.brf_free_radius_mm**2

    def to_dict(self) -> dict:
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        if d["vertices_in"] is not None:
            d["vertices_in"] = [list(p) for p in d["vertices_in"]]
        if d["brf_free_center_mm"] is not None:
            d["brf_free_center_mm"] = list(d["brf_free_center_mm"])
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> KaleidoscopeGeometry:
        known = {f.name for f in fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise ValueError(
                f"unknown KaleidoscopeGeometry keys {sorted(unknown)}; known: {sorted(known)}"
            )
        d = dict(d)
        if d.get("vertices_in") is not None:
            d["vertices_in"] = tuple(tuple(p) for p in d["vertices_in"])
        if d.get("brf_free_center_mm") is not None:
            d["brf_free_center_mm"] = tuple(d["brf_free_center_mm"])
        return cls(**d)


@dataclass(frozen=True)
class CameraModel:
    """Pinhole camera on the tube axis looking along ``−z``.

    Attributes:
        width_px, height_px: sensor size (pixels).
        pixel_pitch_mm: pixel pitch (mm).
        focal_length_mm: focal length (mm).
        cx, cy: principal point (px); ``None`` = sensor centre ``((W − 1)/2, (H − 1)/2)``.
    """

    width_px: int = 400
    height_px: int = 384
    pixel_pitch_mm: float = 0.0275
    focal_length_mm: float = 35.0
    cx: float | None = None
    cy: float | None = None

    def __post_init__(self) -> None:
        for name in ("width_px", "height_px"):
            v = getattr(self, name)
            if int(v) != v or v < 1:
                raise ValueError(f"CameraModel.{name} must be a positive int, got {v}")
        for name in ("pixel_pitch_mm", "focal_length_mm"):
            if not getattr(self, name) > 0:
                raise ValueError(f"CameraModel.{name} must be positive, got {getattr(self, name)}")
        if self.cx is None:
            object.__setattr__(self, "cx", (self.width_px - 1) / 2.0)
        if self.cy is None:
            object.__setattr__(self, "cy", (self.height_px - 1) / 2.0)

    @property
    def focal_px(self) -> float:
        return self.focal_length_mm / self.pixel_pitch_mm

    def intrinsics(
        self, device: torch.device | str | None = None, dtype: torch.dtype | None = None
    ) -> torch.Tensor:
        """``(3, 3)`` intrinsic matrix ``K`` (focal length in px, principal point)."""
        f = self.focal_px
        return torch.tensor(
            [[f, 0.0, self.cx], [0.0, f, self.cy], [0.0, 0.0, 1.0]],
            device=device,
            dtype=dtype or torch.get_default_dtype(),
        )

    def pixel_grid(
        self, device: torch.device | str | None = None, dtype: torch.dtype | None = None
    ) -> torch.Tensor:
        """``(H·W, 2)`` pixel-centre coordinates ``(x, y)``, row-major."""
        return pixel_centres(self.height_px, self.width_px, device=device,
                             dtype=dtype or torch.get_default_dtype()).reshape(-1, 2)

    def scaled(self, factor: float) -> CameraModel:
        """Same optics with the sensor resampled by ``factor`` (pitch / factor, size × factor)."""
        return CameraModel(
            width_px=int(round(self.width_px * factor)),
            height_px=int(round(self.height_px * factor)),
            pixel_pitch_mm=self.pixel_pitch_mm / factor,
            focal_length_mm=self.focal_length_mm,
        )

    def to_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> CameraModel:
        known = {f.name for f in fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown CameraModel keys {sorted(unknown)}; known: {sorted(known)}")
        return cls(**d)


DEFAULT_GEOMETRY = KaleidoscopeGeometry()
#: Small default sensor 400 × 384 (27.5 µm ≈ 7× binned pixels): reference triangle ≈ 118 px on a
#: side (≈ 6.0·10³ px), the ten views span ≈ 353 × 306 px.
DEFAULT_CAMERA = CameraModel()
#: Full-size preset 2896 × 2784 (3.8 µm pixels, f = 35 mm): reference triangle ≈ 857 px on a side,
#: ≈ 3.18·10⁵ px.
FULL_CAMERA = CameraModel(
    width_px=2896, height_px=2784, pixel_pitch_mm=0.0038, focal_length_mm=35.0
)


@dataclass
class RayTrace:
    """Result of :func:`trace_rays` (shape ``S`` = ``(N,)``) or :func:`trace_sensor` (``(H, W)``).

    Attributes:
        view_index: ``S`` long, index into ``sequences``; −1 = no view (missed the exit aperture,
            left the tube, or needed more than ``max_reflections`` / an unlisted sequence).
        sequence_code: ``S`` long, reflection sequence code (see :func:`sequence_codes`); −1 when
            the ray did not reach the diffuser.
        n_reflections: ``S`` long.
        parity: ``S`` long, ``(−1)^n_reflections`` (``0`` where ``view_index = −1``).
        hit_xy: ``S + (2,)`` diffuser hit point (mm); NaN where the ray did not reach it.
        direction: ``S + (3,)`` unit direction of the backward ray at the diffuser (``d_z < 0``).
        alpha, sigma: ``S`` incidence angle and azimuth at the filter (rad).
        throughput: ``S`` ``mirror_reflectance ** n_reflections`` (0 where no view).
        sequences: the view list ``view_index`` refers to.
    """

    view_index: torch.Tensor
    sequence_code: torch.Tensor
    n_reflections: torch.Tensor
    parity: torch.Tensor
    hit_xy: torch.Tensor
    direction: torch.Tensor
    alpha: torch.Tensor
    sigma: torch.Tensor
    throughput: torch.Tensor
    sequences: list[tuple[int, ...]]

    _FIELDS = (
        "view_index",
        "sequence_code",
        "n_reflections",
        "parity",
        "hit_xy",
        "direction",
        "alpha",
        "sigma",
        "throughput",
    )

    @property
    def valid(self) -> torch.Tensor:
        return self.view_index >= 0

    def reshape(self, *shape: int) -> RayTrace:
        """Reshape the per-ray leading dimension(s) (vector fields keep their last axis)."""
        out = {}
        for name in self._FIELDS:
            t = getattr(self, name)
            out[name] = (
                t.reshape(*shape, t.shape[-1])
                if name in ("hit_xy", "direction")
                else t.reshape(*shape)
            )
        return RayTrace(**out, sequences=self.sequences)


def enumerate_sequences(max_reflections: int, n_mirrors: int = 3) -> list[tuple[int, ...]]:
    """All mirror sequences with ≤ ``max_reflections`` bounces, no mirror twice in a row.

    Ordered by length, then lexicographically; ``()`` first.
    """
    out: list[tuple[int, ...]] = [()]
    level: list[tuple[int, ...]] = [()]
    for _ in range(max_reflections):
        level = [s + (m,) for s in level for m in range(n_mirrors) if not s or s[-1] != m]
        out.extend(level)
    return out


def sequence_codes(sequences: Sequence[Sequence[int]]) -> list[int]:
    """Integer code ``Σ_k (m_k + 1)·4^k`` of each sequence (``()`` → 0)."""
    codes = []
    for s in sequences:
        if any(m not in (0, 1, 2) for m in s):
            raise ValueError(f"mirror indices must be 0, 1 or 2, got sequence {tuple(s)}")
        codes.append(sum((m + 1) * 4**k for k, m in enumerate(s)))
    return codes


def mirror_planes(
    geometry: KaleidoscopeGeometry,
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit inward normals ``(3, 3)`` and offsets ``(3,)`` of the mirror planes.

    A point ``X`` is inside the tube when ``n_i · X ≥ h_i`` for all ``i``; mirror ``i`` passes
    through entrance vertices ``i``, ``i+1`` and exit vertex ``i``.
    """
    dtype = dtype or torch.get_default_dtype()
    vin = geometry.entrance_vertices(device, torch.float64)
    vout = geometry.exit_vertices(device, torch.float64)
    z0 = torch.zeros(3, 1, device=device, dtype=torch.float64)
    p_in = torch.cat([vin, z0], 1)
    p_out = torch.cat([vout, z0 + geometry.length_mm], 1)
    a, b = p_in, p_in.roll(-1, 0)
    n = torch.linalg.cross(b - a, p_out - a)
    n = n / n.norm(dim=1, keepdim=True)
    h = (n * a).sum(1)
    centre = torch.tensor([0.0, 0.0, 0.0], device=device, dtype=torch.float64)
    inside_ref = torch.cat([vin.mean(0), centre[:1]])
    sign = torch.where((n * inside_ref).sum(1) >= h, 1.0, -1.0)
    return (n * sign[:, None]).to(dtype), (h * sign).to(dtype)


def reflection_isometry(
    geometry: KaleidoscopeGeometry,
    sequence: Sequence[int],
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Unfolding isometry ``X ↦ R X + t`` of a view: ``S_{m1} ∘ S_{m2} ∘ … ∘ S_{mn}``.

    It maps a diffuser point to its virtual image seen straight from the pupil through the mirror
    sequence ``(m1, …, mn)`` (``m1`` nearest the camera). Returns ``R (3, 3)``, ``t (3,)``.
    """
    n, h = mirror_planes(geometry, device, torch.float64)
    r = torch.eye(3, device=device, dtype=torch.float64)
    t = torch.zeros(3, device=device, dtype=torch.float64)
    for m in reversed(tuple(sequence)):
        nm = n[m]
        s = torch.eye(3, device=device, dtype=torch.float64) - 2 * torch.outer(nm, nm)
        r, t = s @ r, s @ t + 2 * h[m] * nm
    dtype = dtype or torch.get_default_dtype()
    return r.to(dtype), t.to(dtype)


def diffuser_to_sensor_homography(
    geometry: KaleidoscopeGeometry,
    camera: CameraModel,
    sequence: Sequence[int] = (),
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
) -> torch.Tensor:
    """Exact ``(3, 3)`` homography diffuser ``(X, Y, 1)`` mm → sensor ``(x, y, 1)`` px of a view.

    The view's virtual image of the diffuser plane is ``R (X, Y, 0) + t`` (planar mirrors), seen
    by the pinhole: ``H = K · diag(1, 1, −1) · [r₁ r₂ (t − O)]``, ``O`` the pupil. Normalised so
    ``H[2, 2] = 1``. The image is mirrored (``det < 0`` in the affine part) for odd sequences.
    """
    r, t = reflection_isometry(geometry, sequence, device, torch.float64)
    o = torch.tensor([0.0, 0.0, geometry.pupil_z], device=device, dtype=torch.float64)
    m = torch.stack([r[:, 0], r[:, 1], t - o], dim=1)
    flip = torch.diag(torch.tensor([1.0, 1.0, -1.0], device=device, dtype=torch.float64))
    hmat = camera.intrinsics(device, torch.float64) @ flip @ m
    hmat = hmat / hmat[2, 2]
    return hmat.to(dtype or torch.get_default_dtype())


def _trace_chunk(
    geometry: KaleidoscopeGeometry,
    camera: CameraModel,
    pix: torch.Tensor,
    normals: torch.Tensor,
    offsets: torch.Tensor,
    exit_tri: torch.Tensor,
    codes_sorted: torch.Tensor,
    code_to_view: torch.Tensor,
) -> dict[str, torch.Tensor]:
    device, dtype = pix.device, pix.dtype
    n = pix.shape[0]
    pitch, f = camera.pixel_pitch_mm, camera.focal_length_mm
    d = torch.stack(
        [
            (pix[:, 0] - camera.cx) * pitch,
            (pix[:, 1] - camera.cy) * pitch,
            torch.full_like(pix[:, 0], -f),
        ],
        dim=1,
    )
    d = d / d.norm(dim=1, keepdim=True)
    # pupil → exit plane
    t_exit = -geometry.pupil_distance_mm / d[:, 2]
    p = torch.zeros(n, 3, device=device, dtype=dtype)
    p[:, 2] = geometry.pupil_z
    p = p + t_exit[:, None] * d
    active = points_in_triangle(p[:, :2], exit_tri)
    done = torch.zeros(n, dtype=torch.bool, device=device)
    code = torch.zeros(n, dtype=torch.long, device=device)
    nref = torch.zeros(n, dtype=torch.long, device=device)
    inf = torch.full((), float("inf"), device=device, dtype=dtype)
    for r in range(geometry.max_reflections + 1):
        # exit parameter of each face the ray moves outwards through (convex frustum)
        dn = d @ normals.T  # (n, 3)
        t_m = torch.where(dn < 0, (offsets - p @ normals.T) / dn.clamp_max(-1e-300), inf)
        t_bot = torch.where(d[:, 2] < 0, -p[:, 2] / d[:, 2].clamp_max(-1e-300), inf)
        t_top = torch.where(
            d[:, 2] > 0, (geometry.length_mm - p[:, 2]) / d[:, 2].clamp_min(1e-300), inf
        )
        t_all = torch.cat([t_m, t_bot[:, None], t_top[:, None]], dim=1)
        t_min, face = t_all.min(dim=1)
        hit_bottom = active & (face == 3)
        hit_mirror = active & (face < 3)
        p = torch.where(
            (hit_bottom | hit_mirror)[:, None], p + t_min.clamp_max(1e12)[:, None] * d, p
        )
        done |= hit_bottom
        if r == geometry.max_reflections:
            break
        active = hit_mirror
        nm = normals[face.clamp_max(2)]
        d_ref = d - 2 * (d * nm).sum(1, keepdim=True) * nm
        d = torch.where(hit_mirror[:, None], d_ref, d)
        code = torch.where(hit_mirror, code + (face + 1) * (4**r), code)
        nref = nref + hit_mirror.long()
    # map codes → view index
    pos = torch.searchsorted(codes_sorted, code).clamp_max(codes_sorted.numel() - 1)
    found = done & (codes_sorted[pos] == code)
    view = torch.where(found, code_to_view[pos], torch.full_like(code, -1))
    nan = torch.full((), float("nan"), device=device, dtype=dtype)
    hit = torch.where(done[:, None], p[:, :2], nan)
    alpha = torch.atan2(d[:, :2].norm(dim=1), d[:, 2].abs())
    sigma = torch.atan2(-d[:, 1], -d[:, 0])
    ok = view >= 0
    parity = torch.where(ok, 1 - 2 * (nref % 2), torch.zeros_like(nref))
    refl = torch.as_tensor(geometry.mirror_reflectance, device=device, dtype=dtype)
    thr = torch.where(ok, refl ** nref.to(dtype), torch.zeros((), device=device, dtype=dtype))
    return {
        "view_index": view,
        "sequence_code": torch.where(done, code, torch.full_like(code, -1)),
        "n_reflections": nref,
        "parity": parity,
        "hit_xy": hit,
        "direction": d,
        "alpha": torch.where(done, alpha, nan),
        "sigma": torch.where(done, sigma, nan),
        "throughput": thr,
    }


def trace_rays(
    geometry: KaleidoscopeGeometry,
    camera: CameraModel,
    pixel_xy: torch.Tensor,
    *,
    sequences: Sequence[Sequence[int]] | None = None,
    chunk: int = 1 << 18,
) -> RayTrace:
    """Trace one backward ray per (sub-)pixel coordinate through the kaleidoscope.

    Batched over rays and chunked over ``chunk`` rays; the only Python loop is over the
    reflection count. Any float dtype/device; ``float64`` recommended for calibration-grade work.

    Args:
        pixel_xy: ``(N, 2)`` sensor coordinates ``(x, y)`` in px (any real values).
        sequences: the view list (view ``i`` = ``sequences[i]``); default
            :func:`enumerate_sequences` ``(geometry.max_reflections)``. Rays with another sequence
            get ``view_index = −1`` (but keep their hit point and angles).

    Returns:
        :class:`RayTrace` with ``(N,)`` fields.
    """
    if not isinstance(pixel_xy, torch.Tensor):
        raise TypeError(f"pixel_xy must be a torch.Tensor, got {type(pixel_xy)}")
    if pixel_xy.ndim != 2 or pixel_xy.shape[1] != 2:
        raise ValueError(f"pixel_xy must have shape (N, 2), got {tuple(pixel_xy.shape)}")
    if chunk < 1:
        raise ValueError(f"chunk must be >= 1, got {chunk}")
    pix = pixel_xy if pixel_xy.is_floating_point() else pixel_xy.to(torch.get_default_dtype())
    device, dtype = pix.device, pix.dtype
    seqs = [
        tuple(s)
        for s in (
            sequences if sequences is not None else enumerate_sequences(geometry.max_reflections)
        )
    ]
    if any(len(s) > geometry.max_reflections for s in seqs):
        raise ValueError("a sequence in `sequences` is longer than geometry.max_reflections")
    codes = torch.tensor(sequence_codes(seqs), device=device, dtype=torch.long)
    if codes.unique().numel() != codes.numel():
        raise ValueError("duplicate sequences in `sequences`")
    codes_sorted, order = codes.sort()
    normals, offsets = mirror_planes(geometry, device, dtype)
    exit_tri = geometry.exit_vertices(device, dtype)
    parts = [
        _trace_chunk(
            geometry, camera, pix[i : i + chunk], normals, offsets, exit_tri, codes_sorted, order
        )
        for i in range(0, pix.shape[0], chunk)
    ]
    if not parts:
        parts = [
            _trace_chunk(geometry, camera, pix, normals, offsets, exit_tri, codes_sorted, order)
        ]
    merged = {k: torch.cat([p[k] for p in parts]) for k in parts[0]}
    return RayTrace(**merged, sequences=seqs)


def trace_sensor(
    geometry: KaleidoscopeGeometry,
    camera: CameraModel,
    *,
    sequences: Sequence[Sequence[int]] | None = None,
    chunk: int = 1 << 18,
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
) -> RayTrace:
    """Trace every pixel centre of the sensor; fields have shape ``(H, W)`` (``(H, W, 2|3)``)."""
    pix = camera.pixel_grid(device, dtype or torch.float64)
    tr = trace_rays(geometry, camera, pix, sequences=sequences, chunk=chunk)
    return tr.reshape(camera.height_px, camera.width_px)
