"""Physics of the birefringent filter: dispersion, uniaxial-plate OPD, polarizer transmittance."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from hsi_torch.optics import (
    BRFConfig,
    UniaxialMaterial,
    get_material,
    polarizer_transmittance,
    refractive_indices,
    uniaxial_opd,
    uniaxial_opd_small_angle,
)


def _tol(dtype: torch.dtype) -> dict:
    return (
        {"rtol": 1e-5, "atol": 1e-5} if dtype == torch.float32 else {"rtol": 1e-10, "atol": 1e-10}
    )


# --- dispersion -------------------------------------------------------------------------------


def test_sellmeier_reference_values(device, dtype):
    wl = torch.tensor([550.0, 589.3], device=device, dtype=dtype)
    qo, qe = refractive_indices("quartz", wl)
    co, ce = refractive_indices("calcite", wl)
    assert qo.dtype == dtype and qo.device.type == device.type
    assert abs(float(qe[0] - qo[0]) - 0.00916) < 2e-5
    assert abs(float(co[1]) - 1.6583) < 1e-4
    assert abs(float(ce[1] - co[1]) - (-0.1722)) < 1e-4
    # normal dispersion: indices fall with wavelength
    wl2 = torch.linspace(420, 680, 27, device=device, dtype=dtype)
    for mat in ("quartz", "calcite"):
        n_o, n_e = refractive_indices(mat, wl2)
        assert bool((n_o[1:] < n_o[:-1]).all()) and bool((n_e[1:] < n_e[:-1]).all())


def test_sellmeier_against_direct_formula():
    lam = np.linspace(0.4, 0.7, 7)
    a, b, c, d, e = 1.28604141, 1.07044083, 1.00585997e-2, 1.10202242, 100.0
    ref = np.sqrt(a + b * lam**2 / (lam**2 - c) + d * lam**2 / (lam**2 - e))
    got = refractive_indices("quartz", torch.tensor(lam * 1e3, dtype=torch.float64))[0]
    np.testing.assert_allclose(got.numpy(), ref, rtol=1e-14)


def test_polymer_film_constant_birefringence():
    wl = torch.linspace(400, 700, 5, dtype=torch.float64)
    n_o, n_e = refractive_indices("polymer", wl)
    torch.testing.assert_close(n_e - n_o, torch.full_like(wl, 0.005))
    film = UniaxialMaterial.film(delta_n=0.002, n_o=1.5)
    n_o, n_e = film.indices(wl)
    torch.testing.assert_close(n_e - n_o, torch.full_like(wl, 0.002))
    assert get_material({"name": "f", "n_o": 1.5, "delta_n": 0.002}) == film.__class__(
        name="f", n_o=1.5, delta_n=0.002
    )
    with pytest.raises(ValueError, match="unknown material"):
        get_material("unobtainium")
    with pytest.raises(ValueError):
        UniaxialMaterial("bad", n_o=1.5)


# --- OPD --------------------------------------------------------------------------------------


def _booker_opd(no, ne, alpha, delta, theta, thickness_mm, n=1.0):
    """Independent OPD: forward roots of det(k kᵀ − |k|² I + ε) = 0 (Booker quartic), numpy."""
    c = np.array([math.cos(theta), 0.0, math.sin(theta)])
    eps = no**2 * np.eye(3) + (ne**2 - no**2) * np.outer(c, c)
    kx, ky = n * math.sin(alpha) * math.cos(delta), n * math.sin(alpha) * math.sin(delta)

    def det(q):
        k = np.array([kx, ky, q])
        return np.linalg.det(np.outer(k, k) - (k @ k) * np.eye(3) + eps)

    qs = np.linspace(-3, 3, 5)
    roots = np.roots(np.polyfit(qs, [det(q) for q in qs], 4))
    roots = roots[np.abs(roots.imag) < 1e-7].real
    q_o = math.sqrt(no**2 - kx**2 - ky**2)
    fwd = roots[roots > 0]
    q_e = fwd[np.argmax(np.abs(fwd - q_o))]
    return thickness_mm * 1e6 * (q_e - q_o)


@pytest.mark.parametrize("material", ["quartz", "calcite"])
def test_opd_tilted_axis_matches_booker_quartic(material):
    rng = np.random.default_rng(0)
    no, ne = (
        float(x) for x in refractive_indices(material, torch.tensor(550.0, dtype=torch.float64))
    )
    for _ in range(12):
        alpha, delta = rng.uniform(0, 0.6), rng.uniform(-math.pi, math.pi)
        theta, n = rng.uniform(0.05, 1.5), rng.uniform(1.0, 1.4)
        ref = _booker_opd(no, ne, alpha, delta, theta, 0.7, n)
        got = float(
            uniaxial_opd(no, ne, torch.tensor(alpha, dtype=torch.float64), delta, theta, 0.7, n)
        )
        assert abs(got - ref) < 1e-6 * max(1.0, abs(ref)), (alpha, delta, theta, n, got, ref)


def test_opd_sign_of_first_order_term():
    """Hand-derived: the OPD vanishes where the refracted wave normal lies along the optic axis.

    With δ = 0 the ray leans towards the axis projection; for tilt θ the internal wave normal
    (n sin α, 0, q_o) is parallel to (cos θ, 0, sin θ) when n sin α = n_o cos θ. The opposite
    azimuth (δ = π) leans away and must give a large OPD (a wrong sign would swap the two).
    """
    no, ne = (
        float(x) for x in refractive_indices("quartz", torch.tensor(550.0, dtype=torch.float64))
    )
    theta, n = math.radians(45.0), 1.6
    alpha = math.asin(no * math.cos(theta) / n)
    a = torch.tensor(alpha, dtype=torch.float64)
    assert abs(float(uniaxial_opd(no, ne, a, 0.0, theta, 1.0, n))) < 1e-7
    assert float(uniaxial_opd(no, ne, a, math.pi, theta, 1.0, n)) > 0.5 * 1e6 * (ne - no)
    # first-order slope at normal incidence: dΔ/d(sin α) = L (n_o² − n_e²) sin θ cos θ cos δ / A
    th = math.radians(30.0)
    big_a = no**2 * math.cos(th) ** 2 + ne**2 * math.sin(th) ** 2
    h = 1e-6
    for delta in (0.0, 1.0, 2.5):
        d_opd = float(
            uniaxial_opd(no, ne, torch.tensor([h, -h], dtype=torch.float64), delta, th, 1.0).diff()
        )
        slope = -d_opd / (2 * h)
        ref = 1e6 * (no**2 - ne**2) * math.sin(th) * math.cos(th) * math.cos(delta) / big_a
        assert abs(slope - ref) < 1e-5 * abs(1e6 * (no - ne))
    # normal incidence: L (n_o n_e / sqrt(A) − n_o)
    ref0 = 1e6 * (no * ne / math.sqrt(big_a) - no)
    assert (
        abs(
            float(uniaxial_opd(no, ne, torch.tensor(0.0, dtype=torch.float64), 0.3, th, 1.0)) - ref0
        )
        < 1e-8
    )


def test_first_order_term_vanishes_for_in_plane_axis(device, dtype):
    no, ne = refractive_indices("calcite", torch.tensor(550.0, device=device, dtype=dtype))
    alpha = torch.linspace(0, 0.5, 11, device=device, dtype=dtype)
    for delta in (0.0, 0.7, 2.0):
        plus = uniaxial_opd(no, ne, alpha, delta, 0.0, 0.1)
        minus = uniaxial_opd(no, ne, alpha, delta + math.pi, 0.0, 0.1)
        torch.testing.assert_close(plus, minus, **_tol(dtype))


@pytest.mark.parametrize("material", ["quartz", "calcite"])
def test_opd_small_angle_formula_in_plane_axis(device, dtype, material):
    wl = torch.tensor([450.0, 550.0, 650.0], device=device, dtype=dtype)[:, None, None]
    alpha = torch.linspace(0, 0.2, 9, device=device, dtype=dtype)[None, :, None]
    delta = torch.linspace(-math.pi, math.pi, 13, device=device, dtype=dtype)[None, None, :]
    no, ne = refractive_indices(material, wl)
    exact = uniaxial_opd(no, ne, alpha, delta, 0.0, 1.0)
    approx = uniaxial_opd_small_angle(no, ne, alpha, delta, 1.0)
    assert exact.shape == (3, 9, 13) and exact.dtype == dtype
    # the neglected terms: O(sin⁴α) and O(Δn/n̄ · sin²α) relative to L·Δn; float32 loses ~0.3 nm
    # per mm to the cancellation in q_e − q_o
    dn = (ne - no).abs()
    s2 = torch.sin(alpha) ** 2
    bound = 1e6 * dn * (s2 * s2 + s2 * dn / no) + (1.0 if dtype == torch.float32 else 1e-8)
    assert bool(((exact - approx).abs() <= bound).all())
    # and the second-order coefficient itself is right (tiny α, float64 only)
    if dtype == torch.float64:
        a = torch.tensor(1e-3, device=device, dtype=dtype)
        coef = (uniaxial_opd(no, ne, a, delta, 0.0, 1.0) - 1e6 * (ne - no)) / math.sin(1e-3) ** 2
        nbar = (no + ne) / 2
        ref = -1e6 * (ne - no) * torch.cos(2 * delta) / (2 * nbar**2)
        torch.testing.assert_close(
            coef, ref.expand_as(coef), rtol=0.0, atol=float(1e6 * dn.max() * 0.12)
        )


def test_opd_evanescent_is_nan():
    out = uniaxial_opd(1.55, 1.56, torch.tensor([0.1, 1.4]), 0.0, 0.3, 1.0, n_outside=1.7)
    assert torch.isfinite(out[0]) and torch.isnan(out[1])


def test_opd_gradcheck():
    alpha = torch.tensor([0.1, 0.3], dtype=torch.float64, requires_grad=True)
    delta = torch.tensor([0.2, -1.0], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda a, d: uniaxial_opd(1.54, 1.55, a, d, 0.8, 0.5), (alpha, delta)
    )


# --- transmittance ----------------------------------------------------------------------------


def _jones_transmittance(gamma, psi, chi):
    """|analyser · R(ψ) diag(1, e^{iΓ}) R(−ψ) · x̂|² with numpy complex Jones matrices."""

    def rot(a):
        return np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])

    ret = rot(psi) @ np.diag([1.0, np.exp(1j * gamma)]) @ rot(-psi)
    out = ret @ np.array([1.0, 0.0])
    ana = np.array([math.cos(chi), math.sin(chi)])
    return abs(ana @ out) ** 2


def test_transmittance_identities(device, dtype):
    wl = torch.linspace(430, 670, 25, device=device, dtype=dtype)
    opd = torch.linspace(0, 6000, 7, device=device, dtype=dtype)[:, None]
    crossed = polarizer_transmittance(opd, wl, math.pi / 4, math.pi / 2)
    parallel = polarizer_transmittance(opd, wl, math.pi / 4, 0.0)
    torch.testing.assert_close(crossed + parallel, torch.ones_like(crossed), **_tol(dtype))
    gamma = 2 * math.pi * opd / wl
    torch.testing.assert_close(crossed, 0.5 * (1 - torch.cos(gamma)), **_tol(dtype))
    # aligned polarizers and retarder: everything passes
    torch.testing.assert_close(polarizer_transmittance(opd, wl, 0.0, 0.0), torch.ones_like(crossed))


def test_transmittance_matches_jones_calculus():
    rng = np.random.default_rng(1)
    for _ in range(20):
        gamma, psi, chi = (
            rng.uniform(0, 20),
            rng.uniform(-math.pi, math.pi),
            rng.uniform(-math.pi, math.pi),
        )
        wl = 500.0
        opd = gamma * wl / (2 * math.pi)
        got = float(polarizer_transmittance(torch.tensor(opd, dtype=torch.float64), wl, psi, chi))
        assert abs(got - _jones_transmittance(gamma, psi, chi)) < 1e-12


def test_brfconfig_broadcasting_and_presets(device, dtype):
    brf = BRFConfig(material="quartz", thickness_mm=1.0, axis_tilt_deg=40.0, axis_azimuth_deg=25.0)
    alpha = torch.linspace(0, 0.3, 6, device=device, dtype=dtype)[:, None]
    sigma = torch.linspace(-3, 3, 6, device=device, dtype=dtype)[:, None]
    wl = torch.linspace(430, 670, 25, device=device, dtype=dtype)
    t = brf.transmittance(alpha, sigma, wl)
    assert t.shape == (6, 25) and t.dtype == dtype and t.device.type == device.type
    no, ne = refractive_indices("quartz", wl)
    opd = uniaxial_opd(no, ne, alpha, sigma - math.radians(25.0), math.radians(40.0), 1.0)
    torch.testing.assert_close(brf.opd_nm(alpha, sigma, wl), opd)
    torch.testing.assert_close(t, 0.5 * (1 - torch.cos(2 * math.pi * opd / wl)), **_tol(dtype))
    par = BRFConfig.with_polarizers(
        "parallel", material="quartz", thickness_mm=1.0, axis_tilt_deg=40.0, axis_azimuth_deg=25.0
    )
    torch.testing.assert_close(
        t + par.transmittance(alpha, sigma, wl), torch.ones_like(t), **_tol(dtype)
    )
    assert bool((t >= -1e-6).all() and (t <= 1 + 1e-6).all())


def test_brfconfig_dict_roundtrip():
    brf = BRFConfig(material=UniaxialMaterial.film(0.003), thickness_mm=0.8, axis_tilt_deg=30.0)
    d = brf.to_dict()
    again = BRFConfig.from_dict(d)
    wl = torch.tensor([500.0, 600.0], dtype=torch.float64)
    torch.testing.assert_close(again.opd_nm(0.1, 0.2, wl), brf.opd_nm(0.1, 0.2, wl))
    with pytest.raises(ValueError, match="unknown BRFConfig keys"):
        BRFConfig.from_dict({"thickness": 1.0})
    with pytest.raises(ValueError, match="thickness_mm"):
        BRFConfig(thickness_mm=0.0)
