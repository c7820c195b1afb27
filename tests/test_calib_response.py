"""Response φ^c(λ) and throughput g_v estimation against known synthetic truth and SciPy."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.linalg
import torch

from hsi_torch.calibrate.response import (
    estimate_response,
    estimate_response_field,
    fit_gain_field,
    legendre_basis_2d,
    solve_gain,
    solve_phi,
)
from hsi_torch.spectral import difference_matrix


def _truth(h=16, w=16, V=8, M=25, S=3, noise=0.0, seed=0, dtype=torch.float64):
    """BRF-like per-pixel transmittances, a smooth φ that differs from the prior f̃ by an
    illumination factor, and smooth per-view gain fields (reference mean ≠ 1)."""
    gen = torch.Generator().manual_seed(seed)
    wl = torch.linspace(430, 670, M, dtype=dtype)
    yy, xx = torch.meshgrid(torch.linspace(-1, 1, h, dtype=dtype),
                            torch.linspace(-1, 1, w, dtype=dtype), indexing="ij")
    opd = 1800 + 900 * torch.arange(V, dtype=dtype)
    opd_p = opd[:, None, None] * (1 + 0.08 * xx + 0.05 * yy)[None]
    B = 0.45 * (1 - 0.9 * torch.cos(2 * math.pi * opd_p[:, None] / wl[None, :, None, None])) + 0.03
    b = B * 10.0
    centres = torch.tensor([600.0, 540.0, 460.0], dtype=dtype)
    widths = torch.tensor([40.0, 45.0, 35.0], dtype=dtype)
    f = torch.exp(-0.5 * ((wl[None] - centres[:, None]) / widths[:, None]) ** 2)
    illum = 0.6 + 0.8 * (wl - 430) / 240 + 0.1 * torch.sin(wl / 30)
    phi = 1200.0 * f * illum[None]
    gv = 0.7 + 0.6 * torch.rand(V, generator=gen, dtype=dtype)
    tilt = torch.linspace(-1, 1, V, dtype=dtype)[:, None, None]
    gfield = gv[:, None, None] * (1 + 0.05 * xx[None] * tilt - 0.03 * yy[None] ** 2)
    mask = torch.ones(V, h, w, dtype=torch.bool)
    mask[:, :2] = False
    clean = gfield[:, None] * torch.einsum("vmhw,cm->vchw", b, phi)
    white = clean[None].expand(S, *clean.shape).clone()
    if noise:
        white += noise * clean.mean() * torch.randn(white.shape, generator=gen, dtype=dtype)
    s = gfield[0][mask[0]].mean()
    return dict(b=b, f=f, phi=phi * s, gain=gfield / s, mask=mask, white=white)


def _tol(dtype):
    return {"atol": 1e-3, "rtol": 1e-3} if dtype == torch.float32 else {"atol": 1e-8, "rtol": 1e-8}


def test_solve_phi_matches_scipy_stacked_lstsq(device, dtype):
    rng = np.random.default_rng(0)
    N, V, M = 5, 6, 12
    b = rng.uniform(0, 10, (N, V, M))
    g = rng.uniform(0.5, 1.5, (N, V))
    w = rng.uniform(0.5, 2.0, (N, V))
    f = rng.uniform(0.1, 1.0, (3, M))
    I = rng.uniform(100, 500, (N, V, 3))
    beta, gamma = 3.0, 7.0
    t = lambda a: torch.as_tensor(a, device=device, dtype=dtype)  # noqa: E731
    phi, alpha = solve_phi(t(I), t(b), t(g), t(f), weights=t(w), beta_phi=beta, gamma_h=gamma)
    D = difference_matrix(M, 1, dtype=torch.float64).numpy()
    rows = (np.sqrt(w) * g)[..., None] * b
    A_data = rows.reshape(-1, M)
    for c in range(3):
        A = np.block([
            [A_data, np.zeros((N * V, 1))],
            [np.sqrt(beta) * D, np.zeros((M - 1, 1))],
            [np.sqrt(gamma) * np.eye(M), -np.sqrt(gamma) * f[c][:, None]],
        ])
        y = np.concatenate([(np.sqrt(w) * I[..., c]).reshape(-1), np.zeros(2 * M - 1)])
        x = scipy.linalg.lstsq(A, y)[0]
        torch.testing.assert_close(phi[c].cpu().double(), torch.from_numpy(x[:M]), **_tol(dtype))
        torch.testing.assert_close(alpha[c].cpu().double(), torch.tensor(x[M]), **_tol(dtype))


def test_solve_phi_without_prior_and_solve_gain_closed_form():
    rng = np.random.default_rng(1)
    N, V, M = 40, 5, 10
    b = torch.from_numpy(rng.uniform(0, 10, (N, V, M)))
    phi_true = torch.from_numpy(rng.uniform(1, 2, (3, M)))
    g_true = torch.from_numpy(rng.uniform(0.8, 1.2, V))
    I = g_true[None, :, None] * torch.einsum("nvm,cm->nvc", b, phi_true)
    phi, alpha = solve_phi(I, b, g_true, torch.ones(3, M, dtype=torch.float64),
                           beta_phi=0.0, gamma_h=0.0)
    torch.testing.assert_close(phi, phi_true)
    torch.testing.assert_close(alpha, phi_true.mean(1))
    g = solve_gain(I, b, phi_true, reg=0.0)
    torch.testing.assert_close(g, g_true)
    # ridge towards 1: g = (Σ a I + λ) / (Σ a² + λ) with λ = reg Σ a²
    a = torch.einsum("nvm,cm->nvc", b, phi_true)
    saa = (a * a).sum((0, 2))
    expect = ((a * I).sum((0, 2)) + 0.1 * saa) / (1.1 * saa)
    torch.testing.assert_close(solve_gain(I, b, phi_true, reg=0.1), expect)


def test_estimate_response_scalar_gains_noise_free():
    d = _truth()
    V = d["b"].shape[0]
    g_scalar = d["gain"].mean((1, 2))
    clean = g_scalar[:, None, None, None] * torch.einsum("vmhw,cm->vchw", d["b"], d["phi"])
    I = clean.permute(2, 3, 0, 1).reshape(-1, V, 3)
    b = d["b"].permute(2, 3, 0, 1).reshape(-1, V, 25)
    res = estimate_response(I, b, d["f"], beta_phi=1e-3, gamma_h=1e-3, normalise=False,
                            gain_reg=0.0)
    gt = g_scalar / g_scalar[0]
    assert res.gain[0] == 1.0
    torch.testing.assert_close(res.gain, gt, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(res.phi, d["phi"] * g_scalar[0], rtol=1e-3, atol=1.0)  # max ~1500
    assert res.residual_rms[-1] < 1e-4 * float(I.mean())
    # the plain 3-step alternation (refine_steps=0) is much further from the truth
    plain = estimate_response(I, b, d["f"], beta_phi=1e-3, gamma_h=1e-3, normalise=False,
                              gain_reg=0.0, refine_steps=0)
    assert float((plain.gain - gt).abs().max()) > 10 * float((res.gain - gt).abs().max())


def test_fit_gain_field_exact_for_polynomial_gain():
    d = _truth()
    gain, coef = fit_gain_field(d["white"], d["b"], d["phi"], d["mask"], degree=2,
                                smoothness=0.0)
    torch.testing.assert_close(gain, d["gain"], rtol=1e-9, atol=1e-9)
    L, deg = legendre_basis_2d(16, 16, 2, dtype=torch.float64)
    assert L.shape == (6, 16, 16) and deg.tolist() == [0, 1, 1, 2, 2, 2]
    torch.testing.assert_close(L[0], torch.ones(16, 16, dtype=torch.float64))
    # Legendre polynomials are orthogonal on the symmetric grid for odd x-degree
    assert abs(float((L[1] * L[0]).sum())) < 1e-9


def test_estimate_response_field_noisy_meets_targets():
    d = _truth(noise=0.01, h=20, w=20)
    res = estimate_response_field(d["white"], d["b"], d["f"], d["mask"], beta_phi=1.0,
                                  gamma_h=1.0, normalise=False, degree=2, smoothness=1e-3)
    m = d["mask"]
    gerr = ((res.gain - d["gain"]).abs() / d["gain"])[m]
    assert float(gerr.max()) < 0.02, float(gerr.max())
    for c in range(3):
        r = torch.corrcoef(torch.stack([res.phi[c], d["phi"][c]]))[0, 1]
        assert float(r) > 0.99
    torch.testing.assert_close(res.gain[0][m[0]].mean(), torch.tensor(1.0, dtype=torch.float64))
    # φ absorbs the scale: the product g·φ is what the data see
    torch.testing.assert_close(res.phi.sum(), d["phi"].sum(), rtol=0.02, atol=0)


@pytest.mark.parametrize("bad", ["I", "b", "f", "mask"])
def test_shape_errors(bad):
    d = _truth(h=6, w=6, V=4, M=9)
    I = torch.ones(4, 3, dtype=torch.float64)
    b = torch.ones(4, 9, dtype=torch.float64)
    f = torch.ones(3, 9, dtype=torch.float64)
    with pytest.raises(ValueError):
        if bad == "I":
            solve_phi(torch.ones(4, 2, dtype=torch.float64), b, torch.ones(4), f)
        elif bad == "b":
            solve_phi(I, torch.ones(5, 9, dtype=torch.float64), torch.ones(4), f)
        elif bad == "f":
            solve_phi(I, b, torch.ones(4), torch.ones(3, 8, dtype=torch.float64))
        else:
            estimate_response_field(d["white"], d["b"], d["f"], d["mask"][:, :-1])


def test_normalised_weights_do_not_depend_on_the_number_of_observations():
    """The same white data seen 4x (a 4x larger sensor of the same scene) gives the same φ and g
    with normalised weights; absolute weights then weaken the prior 4x and the answer moves."""
    from hsi_torch.calibrate.response import data_scale

    d = _truth(noise=0.02, h=12, w=12)
    V = d["b"].shape[0]
    I = d["white"].mean(0).permute(2, 3, 0, 1).reshape(-1, V, 3)
    b = d["b"].permute(2, 3, 0, 1).reshape(-1, V, 25)
    I4, b4 = I.repeat(4, 1, 1), b.repeat(4, 1, 1)
    assert data_scale(b4) == pytest.approx(4 * data_scale(b), rel=1e-12)
    kw = dict(beta_phi=0.05, gamma_h=0.05, refine_steps=5)
    one = estimate_response(I, b, d["f"], **kw)
    four = estimate_response(I4, b4, d["f"], **kw)
    torch.testing.assert_close(four.phi, one.phi, rtol=1e-7, atol=1e-7 * float(one.phi.abs().max()))
    torch.testing.assert_close(four.gain, one.gain, rtol=1e-7, atol=1e-9)
    assert four.beta_phi_effective == pytest.approx(4 * one.beta_phi_effective, rel=1e-12)
    absolute = dict(kw, beta_phi=one.beta_phi_effective, gamma_h=one.gamma_h_effective,
                    normalise=False)
    same = estimate_response(I, b, d["f"], **absolute)
    torch.testing.assert_close(same.phi, one.phi, rtol=1e-9, atol=1e-9 * float(one.phi.abs().max()))
    weaker = estimate_response(I4, b4, d["f"], **absolute)
    assert float((weaker.phi - one.phi).abs().max()) > 1e-4 * float(one.phi.abs().max())
