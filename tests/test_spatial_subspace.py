"""The TV prior on a spectral subspace (:mod:`hsi_torch.recon.spatial.subspace`): the basis, the
reduced problem's optimality against an independent primal-dual reference of the full-band
problem it stands for, the exact per-pixel non-negativity step (KKT), and ``λ = 0``."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from hsi_torch.recon.spatial import _compiled, prepare_spatial, solve_spatial
from hsi_torch.recon.spatial.subspace import restore_nonneg, spectral_basis, subspace_problem

pytestmark = pytest.mark.skipif(not _compiled.AVAILABLE, reason="needs numba")


def _scene(h=5, w=6, m=6, o=8, noise=0.05, seed=0, offset=0.0):
    """Two regions, smooth spectra (+ ``offset``), per-pixel random ``A``, noisy ``y``; float64."""
    g = torch.Generator().manual_seed(seed)
    P = h * w
    A = torch.rand(P, o, m, generator=g, dtype=torch.float64)
    lamb = torch.linspace(0, 1, m, dtype=torch.float64)
    s1 = 0.3 + torch.exp(-(((lamb - 0.3) / 0.3) ** 2))
    s2 = offset + 0.5 * torch.exp(-(((lamb - 0.7) / 0.3) ** 2))
    truth = torch.zeros(P, m, dtype=torch.float64)
    cols = torch.arange(P) % w
    truth[cols < w // 2] = s1
    truth[cols >= w // 2] = s2
    y = torch.einsum("pom,pm->po", A, truth) + noise * torch.randn(
        P, o, generator=g, dtype=torch.float64
    )
    G = A.transpose(1, 2) @ A + 0.1 * torch.eye(m, dtype=torch.float64)
    b = torch.einsum("pom,po->pm", A, y)
    return A, y, G, b, truth, (h, w)


def _tv_sub(x, basis, hw, alpha):
    """``Σ ‖K ∇(U Uᵀ x)‖`` on the full grid (reference formula, full-band ``K``)."""
    h, w = hw
    m = x.shape[1]
    c = (x @ basis @ basis.T).T.reshape(m, h, w)
    dx = torch.zeros_like(c)
    dy = torch.zeros_like(c)
    dx[:, :, :-1] = c[:, :, 1:] - c[:, :, :-1]
    dy[:, :-1, :] = c[:, 1:, :] - c[:, :-1, :]
    g = torch.stack([dx, dy])
    g = g - (1 - alpha) * g.mean(1, keepdim=True)
    return float(g.square().sum((0, 1)).sqrt().sum())


def _condat_vu_sub(G, b, basis, lam, hw, iters, alpha):
    """Independent reference (numpy, float64): Condat–Vũ for ``min_x Σ xᵀGx − 2bᵀx + λ TV_α(U
    Uᵀ x)`` without a bound — gradient steps on the quadratic, the TV of the projection onto the
    subspace through its dual ball with the full-band weighting ``K = I − (1 − α)𝟙𝟙ᵀ/M`` (no
    Schur complement, no rotation of the basis, no Cholesky)."""
    h, w = hw
    P, m = b.shape
    proj = basis @ basis.T

    def D(x):  # (P, M) → (2, M, h, w)
        c = (x @ proj).T.reshape(m, h, w)
        dx = np.zeros_like(c)
        dy = np.zeros_like(c)
        dx[:, :, :-1] = c[:, :, 1:] - c[:, :, :-1]
        dy[:, :-1, :] = c[:, 1:, :] - c[:, :-1, :]
        g = np.stack([dx, dy])
        return g - (1 - alpha) * g.mean(1, keepdims=True)

    def DT(p):  # (2, M, h, w) → (P, M)
        p = p - (1 - alpha) * p.mean(1, keepdims=True)
        out = -p[0] - p[1]
        out[:, :, 1:] += p[0][:, :, :-1]
        out[:, 1:, :] += p[1][:, :-1, :]
        return out.reshape(m, -1).T @ proj

    L = 2 * float(np.linalg.eigvalsh(G).max())
    x = np.zeros((P, m))
    yd = np.zeros((2, m, h, w))
    sig = L / 8
    tau = 0.99 / (L / 2 + 8 * sig)
    for _ in range(iters):
        grad = 2 * (np.einsum("pmn,pn->pm", G, x) - b)
        xn = x - tau * (grad + DT(yd))
        yd = yd + sig * D(2 * xn - x)
        yd[0, :, :, -1] = 0
        yd[1, :, -1, :] = 0
        nrm = np.sqrt((yd**2).sum((0, 1), keepdims=True))
        yd = yd / np.maximum(1, nrm / lam)
        x = xn
    return x


def test_basis_is_orthonormal_holds_the_flat_spectrum_and_is_rotated():
    g = torch.Generator().manual_seed(0)
    x = torch.rand(200, 9, generator=g, dtype=torch.float64)
    for k in (1, 3, 9):
        U = spectral_basis(x, k)
        assert U.shape == (9, k)
        torch.testing.assert_close(U.T @ U, torch.eye(k, dtype=torch.float64))
        u = torch.full((9,), 1 / 3.0, dtype=torch.float64)
        torch.testing.assert_close(U.T @ u, torch.full((k,), 1 / math.sqrt(k), dtype=torch.float64))
    # the leading components: spectra in a 3-dim span holding the flat one are reproduced
    span = torch.rand(3, 9, generator=g, dtype=torch.float64)
    span[0] = 1.0
    xs = torch.rand(200, 3, generator=g, dtype=torch.float64) @ span
    U = spectral_basis(xs, 3)
    assert float((xs - xs @ U @ U.T).abs().max()) < 1e-10
    with pytest.raises(ValueError, match="rank"):
        spectral_basis(x, 0)


@pytest.mark.parametrize("alpha", [0.3])
def test_subspace_solve_is_the_minimiser_of_the_subspace_tv_problem(alpha):
    """The reduced ADMM (compiled kernels, no bound) recovers the minimiser of the full-band
    problem with the TV on the projection, against an independent primal-dual run."""
    A, y, G, b, truth, hw = _scene()
    P, m = b.shape
    pix = torch.arange(P)
    sp = prepare_spatial(G, pix, hw, rho=float(G.diagonal(dim1=1, dim2=2).mean()))
    U = spectral_basis(truth + 0.01 * torch.rand(P, m, dtype=torch.float64), 3)
    sub = subspace_problem(sp, torch.linalg.inv(G), b, U)
    lam = 0.5
    res = solve_spatial(
        sub.problem,
        sub.b,
        lam,
        x0=sub.start,
        tol=1e-9,
        max_iter=20000,
        brightness_weight=alpha,
        nonneg=False,
    )
    assert res.converged
    phi = sub.b - (sub.problem.gram @ res.x.unsqueeze(2)).squeeze(2)
    s = torch.linalg.solve(G, (b - phi @ U.T).unsqueeze(2)).squeeze(2)  # full-band minimiser
    ref = torch.from_numpy(_condat_vu_sub(G.numpy(), b.numpy(), U.numpy(), lam, hw, 8000, alpha))

    def f(x):
        return float(torch.einsum("pm,pmn,pn->", x, G, x) - 2 * (b * x).sum()) + lam * _tv_sub(
            x, U, hw, alpha
        )

    x_ls = torch.linalg.solve(G, b.unsqueeze(2)).squeeze(2)
    assert f(s) <= f(ref) + 1e-9 * abs(f(ref))
    assert f(s) < f(x_ls) - 1e-3 * abs(f(x_ls))  # the prior did change the answer
    assert float((s - ref).abs().max()) < 1e-5
    torch.testing.assert_close(res.x, s @ U, atol=1e-8, rtol=0)  # c = Uᵀ s


def test_restore_nonneg_is_exact_per_pixel_and_keeps_nonneg_minimisers():
    """Step 2: every pixel's answer meets the NNLS KKT conditions for ``b − Uφ``; where the
    unconstrained minimiser is already ``≥ 0`` it is returned unchanged."""
    A, y, G, b, truth, hw = _scene(noise=0.1, offset=-0.2, seed=3)  # some bands < 0
    P, m = b.shape
    sp = prepare_spatial(G, torch.arange(P), hw, rho=float(G.diagonal(dim1=1, dim2=2).mean()))
    Ginv = torch.linalg.inv(G)
    U = spectral_basis(truth.clamp_min(0) + 0.05, 3)
    sub = subspace_problem(sp, Ginv, b, U)
    res = solve_spatial(
        sub.problem, sub.b, 2.0, x0=sub.start, tol=1e-6, max_iter=20000, nonneg=False
    )
    diag = G.diagonal(dim1=1, dim2=2).contiguous()
    norm = torch.linalg.matrix_norm(G, 2)
    x, rhs = restore_nonneg(
        sub, res.x, b, G, Ginv, diag, norm, torch.zeros(P, dtype=torch.bool), 1e-12, 16, 2, 1
    )
    assert float(x.min()) >= 0
    grad = (G @ x.unsqueeze(2)).squeeze(2) - rhs
    scale = float(rhs.abs().max())
    assert float(grad[x > 0].abs().max()) < 1e-8 * scale  # stationary on the free bands
    assert float(grad[x == 0].min()) > -1e-8 * scale  # no descent into the bound
    s = torch.linalg.solve(G, rhs.unsqueeze(2)).squeeze(2)
    feasible = (s >= 0).all(1)
    assert 0 < int(feasible.sum()) < P  # both kinds of pixels are tested
    torch.testing.assert_close(x[feasible], s[feasible], atol=1e-9, rtol=1e-9)


def test_lam_zero_gives_the_per_pixel_nnls_answer():
    A, y, G, b, truth, hw = _scene(noise=0.1, offset=-0.2, seed=3)
    P, m = b.shape
    sp = prepare_spatial(G, torch.arange(P), hw, rho=float(G.diagonal(dim1=1, dim2=2).mean()))
    Ginv = torch.linalg.inv(G)
    sub = subspace_problem(sp, Ginv, b, spectral_basis(truth.clamp_min(0) + 0.05, 3))
    res = solve_spatial(sub.problem, sub.b, 0.0, x0=sub.start, tol=1e-8, nonneg=False)
    x, _ = restore_nonneg(
        sub,
        res.x,
        b,
        G,
        Ginv,
        G.diagonal(dim1=1, dim2=2).contiguous(),
        torch.linalg.matrix_norm(G, 2),
        torch.zeros(P, dtype=torch.bool),
        1e-12,
        16,
        2,
        1,
    )
    ref = _nnls_reference(G, b)
    assert float(ref.min()) == 0.0  # some bands are at the bound
    torch.testing.assert_close(x, ref, atol=1e-7, rtol=1e-7)


def _nnls_reference(G: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``min_{x ≥ 0} xᵀGx − 2bᵀx`` per pixel by SciPy's NNLS on ``(R, R⁻ᵀb)``, ``G = RᵀR``."""
    from scipy.optimize import nnls

    out = []
    for Gp, bp in zip(G.numpy(), b.numpy(), strict=True):
        R = np.linalg.cholesky(Gp).T
        out.append(nnls(R, np.linalg.solve(R.T, bp))[0])
    return torch.from_numpy(np.stack(out))


def test_pipeline_option_denoises_and_lam_zero_with_saturation_is_per_pixel():
    """Through the pipeline (``spectral_rank``): on the two-region scene of the pipeline tests
    the subspace prior lowers the per-pixel error and stays ``≥ 0``; with ``λ = 0`` and a
    saturated sample (a pixel with its own Gram matrix) the answer is the per-pixel one."""
    from test_spatial_pipeline import _noisy, _piecewise, make_bundle

    from hsi_torch.recon.pipeline import Reconstructor

    bundle = make_bundle()
    s = _piecewise()
    img = _noisy(bundle, s, sigma=2.0).to(torch.float64)
    kw = dict(beta=1.0, dtype=torch.float64)
    pp = Reconstructor(bundle, **kw).reconstruct_frame(img)
    sub = Reconstructor(bundle, prior="tv", lam=1.0, spectral_rank=3, **kw).reconstruct_frame(img)
    v = pp.valid
    truth = s[:, v]
    err_pp = float((pp.cube[:, v] - truth).square().mean())
    err_sub = float((sub.cube[:, v] - truth).square().mean())
    assert err_sub < 0.7 * err_pp, (err_pp, err_sub)
    assert float(sub.cube[:, v].min()) >= 0
    assert sub.stats["spectral_rank"] == 3 and sub.stats["spatial_iterations"] > 0
    sat = torch.zeros_like(img, dtype=torch.bool)
    sat[0, 5, 7] = True
    img[0, 5, 7] = 1e6  # garbage behind the saturation flag
    pp = Reconstructor(bundle, **kw).reconstruct_frame(img, sat)
    sub0 = Reconstructor(bundle, prior="tv", lam=0.0, spectral_rank=3, **kw)
    out = sub0.reconstruct_frame(img, sat)
    assert pp.stats["num_resolved"] > 0
    assert float((pp.cube[:, v] - out.cube[:, v]).abs().max()) < 1e-6
