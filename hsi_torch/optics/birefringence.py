"""Birefringent filter (BRF): dispersion, exact OPD of a uniaxial plate, polarizer transmittance.

Convention:
    Wavelengths in nm, OPD in nm, plate thickness in mm, angles in radians (degrees only in the
    ``*_deg`` fields of :class:`BRFConfig`). The plate lies in the ``(x, y)`` plane with its normal
    along ``+z``; light crosses it travelling towards ``+z`` (from the diffuser towards the camera).
    The optic axis is ``c = (cos θ cos φ_c, cos θ sin φ_c, sin θ)``: ``θ`` is its tilt *out of the
    plate plane* (``θ = 0``: an a-cut plate, axis in the plane; ``θ = 90°``: a c-cut plate) and
    ``φ_c`` the azimuth of its projection. A ray has incidence angle ``α`` (in the outside medium of
    index ``n``) and azimuth ``σ`` of its transverse direction; ``δ = σ − φ_c``.

    The signed OPD is ``Δ = L (q_e − q_o)`` where ``q = k_z / k_0`` are the normal wave-vector
    components of the extraordinary and ordinary waves refracted from the same incident plane wave
    (both share the tangential component ``n sin α (cos δ, sin δ)``), i.e.

    ``Δ/L = [(n_o² − n_e²) sin θ cos θ · n sin α cos δ
             + n_o √(n_e² A − n² sin²α (n_e² − (n_e² − n_o²) cos²θ sin²δ))] / A
            − √(n_o² − n² sin²α)``,  ``A = n_o² cos²θ + n_e² sin²θ``

    (Veiras, Perez & Garea, Appl. Opt. 49(15), 2010, eq. 12, rewritten with the tilt measured from
    the plate plane). The first-order term is negative for a positive crystal when the ray leans
    towards the optic axis (``cos δ > 0`` with ``θ > 0``): the OPD falls to zero when the refracted
    wave normal lies along the axis. At normal incidence ``Δ = L (n_o n_e / √A − n_o)``; for
    ``θ = 0``, ``Δ ≈ L Δn [1 − n² sin²α cos 2δ / (2 n̄²)]``.

    Between a polarizer (axis 0), the retarder (fast/slow axes at ``ψ``) and an analyser at ``χ``:
    ``T = cos²χ − sin 2ψ · sin 2(ψ − χ) · sin²(Γ/2)``, ``Γ = 2π Δ / λ`` (ideal polarizers, the
    transmittance of polarized light; the 1/2 of an unpolarized source is a sensor-side factor).

    Precision: ``q_e − q_o`` is a difference of two numbers ≈ 1.5, so float32 loses ≈ 0.3 nm of OPD
    per mm of plate (a phase error < 0.01 rad at 430 nm for the default 2 mm plate); use float64 for
    calibration-grade OPDs.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields
from typing import Any

import torch

__all__ = [
    "UniaxialMaterial",
    "MATERIALS",
    "get_material",
    "sellmeier_index",
    "refractive_indices",
    "uniaxial_opd",
    "uniaxial_opd_small_angle",
    "polarizer_transmittance",
    "POLARIZER_PRESETS",
    "BRFConfig",
]

TensorLike = torch.Tensor | float | int


def _float_dtype(*xs: Any) -> tuple[torch.device, torch.dtype]:
    """Device and floating dtype shared by the tensor arguments (default dtype otherwise)."""
    tensors = [x for x in xs if isinstance(x, torch.Tensor)]
    device = tensors[0].device if tensors else torch.device("cpu")
    dtype = None
    for t in tensors:
        if t.is_floating_point():
            dtype = t.dtype if dtype is None else torch.promote_types(dtype, t.dtype)
    return device, dtype or torch.get_default_dtype()


def _t(x: TensorLike, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    return torch.as_tensor(x, device=device, dtype=dtype)


def sellmeier_index(coeffs: tuple[float, ...], wavelength_nm: torch.Tensor) -> torch.Tensor:
    """Refractive index from Ghosh's (1999) Sellmeier form, λ in µm inside the formula.

    ``n² = A + B λ²/(λ² − C) + D λ²/(λ² − E)``.

    Args:
        coeffs: ``(A, B, C, D, E)`` with C and E in µm².
        wavelength_nm: any-shape tensor of wavelengths in nm.

    Returns:
        Tensor of refractive indices, same shape/device/dtype as ``wavelength_nm``.
    """
    if len(coeffs) != 5:
        raise ValueError(f"Sellmeier coefficients must be (A, B, C, D, E), got {coeffs!r}")
    a, b, c, d, e = coeffs
    lam2 = (wavelength_nm * 1e-3) ** 2
    return torch.sqrt(a + b * lam2 / (lam2 - c) + d * lam2 / (lam2 - e))


@dataclass(frozen=True)
class UniaxialMaterial:
    """A uniaxial birefringent material: Sellmeier dispersion or constant indices.

    Attributes:
        sellmeier_o, sellmeier_e: Ghosh ``(A, B, C, D, E)`` for the ordinary/extraordinary index.
        n_o, delta_n: constant ordinary index and birefringence ``n_e − n_o`` (used when the
            Sellmeier coefficients are ``None``, e.g. a polymer retarder film).
    """

    name: str
    sellmeier_o: tuple[float, ...] | None = None
    sellmeier_e: tuple[float, ...] | None = None
    n_o: float | None = None
    delta_n: float | None = None

    def __post_init__(self) -> None:
        has_s = self.sellmeier_o is not None and self.sellmeier_e is not None
        has_c = self.n_o is not None and self.delta_n is not None
        if has_s == has_c:
            raise ValueError(
                f"material {self.name!r}: give either sellmeier_o and sellmeier_e, "
                "or n_o and delta_n"
            )

    @classmethod
    def film(cls, delta_n: float, n_o: float = 1.58, name: str = "polymer") -> UniaxialMaterial:
        """A constant-Δn retarder film (no dispersion)."""
        return cls(name=name, n_o=float(n_o), delta_n=float(delta_n))

    def indices(self, wavelength_nm: TensorLike) -> tuple[torch.Tensor, torch.Tensor]:
        """``(n_o, n_e)`` at ``wavelength_nm`` (any shape, nm), same device/dtype."""
        device, dtype = _float_dtype(wavelength_nm)
        wl = _t(wavelength_nm, device, dtype)
        if bool((wl <= 0).any()):
            raise ValueError("wavelength_nm must be positive (nm)")
        if self.sellmeier_o is not None and self.sellmeier_e is not None:
            return sellmeier_index(self.sellmeier_o, wl), sellmeier_index(self.sellmeier_e, wl)
        n_o = torch.full_like(wl, float(self.n_o))  # type: ignore[arg-type]
        return n_o, n_o + float(self.delta_n)  # type: ignore[arg-type]

    def to_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}


MATERIALS: dict[str, UniaxialMaterial] = {
    "quartz": UniaxialMaterial(
        "quartz",
        sellmeier_o=(1.28604141, 1.07044083, 1.00585997e-2, 1.10202242, 100.0),
        sellmeier_e=(1.28851804, 1.09509924, 1.02101864e-2, 1.15662475, 100.0),
    ),
    "calcite": UniaxialMaterial(
        "calcite",
        sellmeier_o=(1.73358749, 0.96464345, 1.94325203e-2, 1.82831454, 120.0),
        sellmeier_e=(1.35859695, 0.82427830, 1.06689543e-2, 0.14429128, 120.0),
    ),
    # a stretched-polycarbonate-like retarder film: n ≈ 1.58, constant Δn
    "polymer": UniaxialMaterial.film(delta_n=0.005, n_o=1.58, name="polymer"),
}


def get_material(material: str | UniaxialMaterial | Mapping[str, Any]) -> UniaxialMaterial:
    """Resolve a material given by name (``quartz``, ``calcite``, ``polymer``), object or dict.

    A dict is passed to :class:`UniaxialMaterial` (e.g. ``{"name": "film", "n_o": 1.5,
    "delta_n": 0.003}``).
    """
    if isinstance(material, UniaxialMaterial):
        return material
    if isinstance(material, str):
        key = material.strip().lower()
        if key not in MATERIALS:
            raise ValueError(f"unknown material {material!r}; known: {sorted(MATERIALS)}")
        return MATERIALS[key]
    if isinstance(material, Mapping):
        d = dict(material)
        for k in ("sellmeier_o", "sellmeier_e"):
            if d.get(k) is not None:
                d[k] = tuple(float(v) for v in d[k])
        d.setdefault("name", "custom")
        return UniaxialMaterial(**d)
    raise TypeError(f"material must be a name, UniaxialMaterial or dict, got {type(material)}")


def refractive_indices(
    material: str | UniaxialMaterial | Mapping[str, Any], wavelength_nm: TensorLike
) -> tuple[torch.Tensor, torch.Tensor]:
    """Ordinary and extraordinary indices ``(n_o, n_e)`` of ``material`` at ``wavelength_nm``."""
    return get_material(material).indices(wavelength_nm)


def uniaxial_opd(
    n_o: TensorLike,
    n_e: TensorLike,
    alpha: TensorLike,
    delta: TensorLike,
    theta: TensorLike,
    thickness_mm: TensorLike,
    n_outside: TensorLike = 1.0,
) -> torch.Tensor:
    """Exact signed OPD ``L (q_e − q_o)`` (nm) of a uniaxial plate (module docstring formula).

    All arguments broadcast against each other.

    Args:
        n_o, n_e: ordinary/extraordinary indices.
        alpha: incidence angle in the outside medium (rad).
        delta: azimuth of the plane of incidence relative to the projected optic axis (rad).
        theta: optic-axis tilt out of the plate plane (rad).
        thickness_mm: plate thickness ``L`` (mm).
        n_outside: index of the medium the angle ``alpha`` is measured in.

    Returns:
        OPD in nm (broadcast shape). NaN where no propagating wave exists inside the plate.
    """
    device, dtype = _float_dtype(n_o, n_e, alpha, delta, theta, thickness_mm, n_outside)
    n_o, n_e, alpha, delta, theta, thick, n = (
        _t(x, device, dtype) for x in (n_o, n_e, alpha, delta, theta, thickness_mm, n_outside)
    )
    kt = n * torch.sin(alpha)  # tangential wave-vector / k0
    kt2 = kt * kt
    st, ct = torch.sin(theta), torch.cos(theta)
    no2, ne2 = n_o * n_o, n_e * n_e
    a = no2 * ct * ct + ne2 * st * st
    cd, sd = torch.cos(delta), torch.sin(delta)
    root_e = ne2 * a - kt2 * (ne2 - (ne2 - no2) * ct * ct * sd * sd)
    root_o = no2 - kt2
    nan = torch.full((), float("nan"), device=device, dtype=dtype)
    q_e = ((no2 - ne2) * st * ct * kt * cd + n_o * torch.sqrt(root_e.clamp_min(0))) / a
    q_o = torch.sqrt(root_o.clamp_min(0))
    opd = thick * 1e6 * (q_e - q_o)
    return torch.where((root_e >= 0) & (root_o >= 0), opd, nan)


def uniaxial_opd_small_angle(
    n_o: TensorLike,
    n_e: TensorLike,
    alpha: TensorLike,
    delta: TensorLike,
    thickness_mm: TensorLike,
    n_outside: TensorLike = 1.0,
) -> torch.Tensor:
    """Second-order approximation for an in-plane axis (θ = 0), in nm.

    ``Δ ≈ L Δn [1 − n² sin²α cos 2δ / (2 n̄²)]`` with ``n̄ = (n_o + n_e)/2``.
    """
    device, dtype = _float_dtype(n_o, n_e, alpha, delta, thickness_mm, n_outside)
    n_o, n_e, alpha, delta, thick, n = (
        _t(x, device, dtype) for x in (n_o, n_e, alpha, delta, thickness_mm, n_outside)
    )
    nbar = 0.5 * (n_o + n_e)
    s2 = (n * torch.sin(alpha)) ** 2
    return thick * 1e6 * (n_e - n_o) * (1 - s2 * torch.cos(2 * delta) / (2 * nbar * nbar))


def polarizer_transmittance(
    opd_nm: TensorLike,
    wavelength_nm: TensorLike,
    psi: TensorLike = math.pi / 4,
    chi: TensorLike = math.pi / 2,
) -> torch.Tensor:
    """Transmittance of polarizer → retarder (axis ψ) → analyser (axis χ), angles in rad.

    ``T = cos²χ − sin 2ψ · sin 2(ψ − χ) · sin²(π·OPD/λ)``. Crossed (ψ = 45°, χ = 90°):
    ``½[1 − cos Γ]``; parallel (ψ = 45°, χ = 0): ``½[1 + cos Γ]``. Inputs broadcast.
    """
    device, dtype = _float_dtype(opd_nm, wavelength_nm, psi, chi)
    opd, wl, psi_t, chi_t = (_t(x, device, dtype) for x in (opd_nm, wavelength_nm, psi, chi))
    half_gamma = math.pi * opd / wl
    return (
        torch.cos(chi_t) ** 2
        - torch.sin(2 * psi_t) * torch.sin(2 * (psi_t - chi_t)) * torch.sin(half_gamma) ** 2
    )


POLARIZER_PRESETS: dict[str, tuple[float, float]] = {
    "crossed": (45.0, 90.0),
    "parallel": (45.0, 0.0),
}


@dataclass
class BRFConfig:
    """A birefringent filter between polarizers, directly behind the diffuser.

    The defaults are the design picked by the condition-number sweep of
    ``scripts/optics_report.py`` for the default kaleidoscope (see ``docs/optics.md``).

    Attributes:
        material: ``"quartz"``, ``"calcite"``, ``"polymer"`` (constant-Δn film), a
            :class:`UniaxialMaterial` or a dict of its fields.
        thickness_mm: plate thickness (mm).
        axis_tilt_deg: optic-axis tilt out of the plate plane θ (deg).
        axis_azimuth_deg: azimuth φ_c of the projected optic axis in the diffuser frame (deg,
            from ``+X`` towards ``+Y``).
        psi_deg: retarder axis relative to the polarizer (deg).
        chi_deg: analyser axis relative to the polarizer (deg); 90 = crossed, 0 = parallel.
        outside_index: index of the medium the incidence angle is measured in (1 = air).
    """

    material: str | UniaxialMaterial | dict = "quartz"
    thickness_mm: float = 2.5
    axis_tilt_deg: float = 70.0
    axis_azimuth_deg: float = 40.0
    psi_deg: float = 45.0
    chi_deg: float = 90.0
    outside_index: float = 1.0
    _mat: UniaxialMaterial = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        self._mat = get_material(self.material)
        if not self.thickness_mm > 0:
            raise ValueError(f"thickness_mm must be positive, got {self.thickness_mm}")
        if not self.outside_index > 0:
            raise ValueError(f"outside_index must be positive, got {self.outside_index}")

    @classmethod
    def with_polarizers(cls, preset: str, **kwargs: Any) -> BRFConfig:
        """Config with ``psi_deg``/``chi_deg`` from a preset: ``"crossed"`` or ``"parallel"``."""
        if preset not in POLARIZER_PRESETS:
            raise ValueError(
                f"unknown polarizer preset {preset!r}; known: {list(POLARIZER_PRESETS)}"
            )
        psi, chi = POLARIZER_PRESETS[preset]
        return cls(psi_deg=psi, chi_deg=chi, **kwargs)

    def indices(self, wavelength_nm: TensorLike) -> tuple[torch.Tensor, torch.Tensor]:
        """``(n_o, n_e)`` at ``wavelength_nm``."""
        return self._mat.indices(wavelength_nm)

    def opd_nm(
        self, alpha: TensorLike, sigma: TensorLike, wavelength_nm: TensorLike
    ) -> torch.Tensor:
        """Signed OPD (nm) for rays at incidence ``alpha`` and azimuth ``sigma`` (rad).

        ``alpha``, ``sigma`` and ``wavelength_nm`` broadcast (e.g. ``(N, 1)`` angles against an
        ``(M,)`` grid give ``(N, M)``).
        """
        device, dtype = _float_dtype(alpha, sigma, wavelength_nm)
        n_o, n_e = self._mat.indices(_t(wavelength_nm, device, dtype))
        delta = _t(sigma, device, dtype) - math.radians(self.axis_azimuth_deg)
        return uniaxial_opd(
            n_o,
            n_e,
            _t(alpha, device, dtype),
            delta,
            math.radians(self.axis_tilt_deg),
            self.thickness_mm,
            self.outside_index,
        )

    def transmittance(
        self, alpha: TensorLike, sigma: TensorLike, wavelength_nm: TensorLike
    ) -> torch.Tensor:
        """Polarizer–BRF–analyser transmittance (0…1) for rays (α, σ) at ``wavelength_nm``."""
        device, dtype = _float_dtype(alpha, sigma, wavelength_nm)
        wl = _t(wavelength_nm, device, dtype)
        opd = self.opd_nm(alpha, sigma, wl)
        return polarizer_transmittance(
            opd, wl, math.radians(self.psi_deg), math.radians(self.chi_deg)
        )

    def to_dict(self) -> dict:
        mat = self.material
        if isinstance(mat, UniaxialMaterial):
            mat = mat.to_dict()
        d = {f.name: getattr(self, f.name) for f in fields(self) if f.init}
        d["material"] = mat
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> BRFConfig:
        known = {f.name for f in fields(cls) if f.init}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown BRFConfig keys {sorted(unknown)}; known: {sorted(known)}")
        return cls(**dict(d))
