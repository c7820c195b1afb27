"""Spatial-spectral (TV) reconstruction: optimality against an independent primal-dual reference,
λ = 0 is per-pixel NNLS, non-negativity, TV decreasing in λ, the TV operator's adjoint, the
noise/λ scale, and gradients of the fixed-iteration mode."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hsi_torch.recon.nnls import solve_nnls
from hsi_torch.recon.spatial import (
    effective_dof,
    estimate_noise,
    grid_edges,
    grid_gradient,
    grid_gradient_adjoint,
    guide_weights,
    lam_scale,
    prepare_spatial,
    prox_tv_nonneg,
    solve_spatial,
    total_variation,
)


def _tiny(device, dtype, h=5, w=6, m=4, o=6, noise=0.05, seed=0, holes=True):
    """Two-region piecewise-constant scene, per-pixel random A, noisy y; a few inactive pixels."""
    g = torch.Generator().manual_seed(seed)
    P = h * w
    A = torch.rand(P, o, m, generator=g, dtype=torch.float64)
    truth = torch.zeros(m, h, w, dtype=torch.float64)
    truth[:, :, : w // 2] = torch.rand(m, 1, 1, generator=g, dtype=torch.float64)
    truth[:, :, w // 2:] = torch.rand(m, 1, 1, generator=g, dtype=torch.float64)
    y = torch.einsum("pom,pm->po", A, truth.reshape(m, -1).T)
    y = y + noise * torch.randn(P, o, generator=g, dtype=torch.float64)
    active = torch.ones(P, dtype=torch.bool)
    if holes:
        active[[0, 7, 20]] = False
    A, y, active = A.to(device, dtype), y.to(device, dtype), active.to(device)
    G = A.transpose(1, 2) @ A
    b = torch.einsum("pom,po->pm", A, y)
    return A, y, G, b, active, (h, w)


def _objective(G, b, x, lam, cube_active, to_cube, alpha=1.0):
    quad = torch.einsum("pm,pmn,pn->", x, G, x) - 2 * (b * x).sum()
    return float(quad + lam * total_variation(to_cube(x), cube_active, alpha))


def _condat_vu(G, b, lam, active_grid, iters, alpha=1.0):
    """Independent reference (numpy, float64): Condat–Vũ primal-dual splitting for
    ``min_{x≥0} Σ ½xᵀGx − bᵀx + (λ/2) TV(x)`` — gradient steps on the quadratic, projection for
    ``x ≥ 0``, the TV through its dual ball; no Cholesky, no prox of TV. ``alpha``: the
    brightness weight, ``K = I − (1 − α)𝟙𝟙ᵀ/M`` applied to every band vector of the gradient."""
    P, m = b.shape
    h, w = active_grid.shape
    ex = np.zeros((h, w), bool)
    ey = np.zeros((h, w), bool)
    ex[:, :-1] = active_grid[:, :-1] & active_grid[:, 1:]
    ey[:-1, :] = active_grid[:-1, :] & active_grid[1:, :]

    def D(c):
        dx = np.zeros_like(c)
        dy = np.zeros_like(c)
        dx[:, :, :-1] = c[:, :, 1:] - c[:, :, :-1]
        dy[:, :-1, :] = c[:, 1:, :] - c[:, :-1, :]
        g = np.stack([dx * ex, dy * ey])
        return g - (1 - alpha) * g.mean(1, keepdims=True)

    def DT(p):
        p = p - (1 - alpha) * p.mean(1, keepdims=True)
        px, py = p[0] * ex, p[1] * ey
        out = -px - py
        out[:, :, 1:] += px[:, :, :-1]
        out[:, 1:, :] += py[:, :-1, :]
        return out

    L = float(np.linalg.eigvalsh(G).max())
    tv = lam / 2
    x = np.zeros((P, m))
    yd = np.zeros((2, m, h, w))
    sig = L / 8
    tau = 0.99 / (L / 2 + 8 * sig)
    for _ in range(iters):
        grad = np.einsum("pmn,pn->pm", G, x) - b
        xn = np.maximum(x - tau * (grad + DT(yd).reshape(m, -1).T), 0)
        yd = yd + sig * D((2 * xn - x).T.reshape(m, h, w))
        nrm = np.sqrt((yd**2).sum((0, 1), keepdims=True))
        yd = yd / np.maximum(1, nrm / tv)
        x = xn
    return x


def test_gradient_adjoint(device, dtype):
    """<D c, p> = <c, Dᵀ p> on a grid with holes."""
    g = torch.Generator().manual_seed(1)
    active = torch.rand(7, 9, generator=g) > 0.25
    ex, ey = grid_edges(active.to(device))
    c = torch.randn(3, 7, 9, generator=g, dtype=torch.float64).to(device, dtype)
    p = torch.randn(2, 3, 7, 9, generator=g, dtype=torch.float64).to(device, dtype)
    lhs = float((grid_gradient(c, ex, ey) * p).sum())
    rhs = float((c * grid_gradient_adjoint(p, ex, ey)).sum())
    tol = 1e-4 if dtype == torch.float32 else 1e-12
    assert abs(lhs - rhs) <= tol * max(1.0, abs(lhs))
    # no edge touches an inactive pixel: changing it leaves the gradient unchanged
    c2 = c.clone()
    c2[:, ~active.to(device)] = 123.0
    assert torch.equal(grid_gradient(c, ex, ey), grid_gradient(c2, ex, ey))


def test_prox_matches_brute_force(device):
    """The TV prox (with z ≥ 0) agrees with the Condat–Vũ reference for G = I."""
    dtype = torch.float64
    g = torch.Generator().manual_seed(2)
    h, w, m = 4, 5, 3
    v = torch.randn(m, h, w, generator=g, dtype=dtype)
    active = np.ones((h, w), bool)
    ex, ey = grid_edges(torch.from_numpy(active).to(device))
    z, _ = prox_tv_nonneg(v.to(device), 0.3, ex, ey, 3000)
    G = np.broadcast_to(np.eye(m), (h * w, m, m)).copy()
    ref = _condat_vu(G, v.reshape(m, -1).T.numpy(), 0.6, active, 6000)
    assert float(z.min()) >= 0
    np.testing.assert_allclose(z.cpu().reshape(m, -1).T.numpy(), ref, atol=1e-6)


@pytest.mark.parametrize("alpha", [1.0, 0.3])
def test_admm_matches_independent_reference(device, alpha):
    """The ADMM answer is the minimiser: same point and objective as a long primal-dual run
    (plain vectorial TV and the brightness-weighted one)."""
    dtype = torch.float64
    A, y, G, b, active, (h, w) = _tiny(device, dtype)
    pix = torch.arange(h * w, device=device)
    prob = prepare_spatial(G, pix, (h, w), active)
    x0 = solve_nnls(A, y).x
    lam = 0.5
    res = solve_spatial(prob, b, lam, x0=x0, tol=1e-9, max_iter=20000, brightness_weight=alpha)
    assert res.converged
    grid = active.view(h, w).cpu().numpy()
    ref = _condat_vu(G.cpu().numpy(), b.cpu().numpy(), lam, grid, 30000, alpha)
    ref_t = torch.from_numpy(ref).to(device, dtype)
    cube_active = active.view(h, w)
    f_admm = _objective(G, b, res.x, lam, cube_active, prob.to_cube, alpha)
    f_ref = _objective(G, b, ref_t, lam, cube_active, prob.to_cube, alpha)
    f_pp = _objective(G, b, x0, lam, cube_active, prob.to_cube, alpha)
    assert f_admm <= f_ref + 1e-9 * abs(f_ref)
    assert f_admm < f_pp - 1e-3 * abs(f_pp)  # TV did change the answer
    assert float((res.x - ref_t).abs().max()) < 1e-5
    assert float(res.x.min()) >= 0


def test_lam_zero_is_per_pixel_nnls(device, dtype):
    A, y, G, b, active, (h, w) = _tiny(device, dtype, seed=3)
    pix = torch.arange(h * w, device=device)
    prob = prepare_spatial(G, pix, (h, w), active)
    ref = solve_nnls(A.double(), y.double()).x
    res = solve_spatial(prob, b, 0.0, tol=1e-6 if dtype == torch.float32 else 1e-10,
                        max_iter=20000)
    tol = 2e-3 if dtype == torch.float32 else 1e-6
    assert float((res.x.double() - ref).abs().max()) <= tol * max(1.0, float(ref.abs().max()))
    # and started at the per-pixel answer it stays there
    res0 = solve_spatial(prob, b, 0.0, x0=ref.to(dtype), iters=20)
    assert float((res0.x.double() - ref).abs().max()) <= tol * max(1.0, float(ref.abs().max()))


def test_larger_lam_lowers_tv_and_stays_nonneg(device, dtype):
    A, y, G, b, active, (h, w) = _tiny(device, dtype, noise=0.2, seed=4)
    pix = torch.arange(h * w, device=device)
    prob = prepare_spatial(G, pix, (h, w), active)
    x0 = solve_nnls(A, y).x
    grid = active.view(h, w)
    tvs = []
    for lam in (0.0, 0.3, 1.0, 3.0):
        res = solve_spatial(prob, b, lam, x0=x0, tol=1e-5, max_iter=5000)
        assert float(res.x.min()) >= 0
        assert torch.isfinite(res.x).all()
        tvs.append(float(total_variation(prob.to_cube(res.x), grid)))
    assert all(a > b_ for a, b_ in zip(tvs, tvs[1:], strict=False)), tvs
    assert tvs[-1] < 0.5 * tvs[0]


def test_inactive_pixels_are_solved_alone(device):
    """A pixel outside the TV graph gets its own NNLS answer, whatever λ."""
    dtype = torch.float64
    A, y, G, b, active, (h, w) = _tiny(device, dtype, seed=5)
    pix = torch.arange(h * w, device=device)
    prob = prepare_spatial(G, pix, (h, w), active)
    res = solve_spatial(prob, b, 5.0, tol=1e-9, max_iter=20000)
    ref = solve_nnls(A, y).x
    off = ~active
    assert float((res.x[off] - ref[off]).abs().max()) < 1e-5  # ADMM's accuracy at tol 1e-9


def test_fixed_iterations_gradcheck(device):
    dtype = torch.float64
    A, y, G, b, active, (h, w) = _tiny(device, dtype, h=3, w=3, m=3, o=4, holes=False, seed=6)
    pix = torch.arange(h * w, device=device)
    prob = prepare_spatial(G, pix, (h, w))
    x0 = solve_nnls(A, y).x.detach()
    lam = torch.tensor(0.3, dtype=dtype, device=device, requires_grad=True)
    bb = b.clone().requires_grad_(True)

    def f(bv, lv):
        return solve_spatial(prob, bv, lv, x0=x0, iters=8, inner_iters=4).x

    assert torch.autograd.gradcheck(f, (bb, lam), eps=1e-6, atol=1e-5)


def test_noise_estimate_and_scale(device):
    """σ̂ from the residuals with the effective dof recovers the simulated noise level (a truth
    that β does not bias, so the residual is noise only)."""
    dtype = torch.float64
    g = torch.Generator().manual_seed(7)
    P, o, m, sigma = 4000, 12, 5, 0.3
    A = torch.rand(P, o, m, generator=g, dtype=dtype)
    x = (torch.rand(P, 1, generator=g, dtype=dtype) + 0.5).expand(P, m)  # D x = 0: no bias
    y = torch.einsum("pom,pm->po", A, x) + sigma * torch.randn(P, o, generator=g, dtype=dtype)
    A, y = A.to(device), y.to(device)
    beta = 2.0
    res = solve_nnls(A, y, beta=beta)
    D = torch.diff(torch.eye(m, dtype=dtype, device=device), dim=0)
    R = beta * D.T @ D
    G = A.transpose(1, 2) @ A + R
    dof = effective_dof(G, R, res.x)
    assert float(dof.min()) > 0 and float(dof.max()) <= m + 1e-9
    assert float(dof.mean()) < m - 0.05  # β shrinks the fit
    r2 = (torch.einsum("pom,pm->po", A, res.x) - y).square().sum(1)
    s = estimate_noise(r2, torch.full((P,), o, device=device), dof)
    assert abs(s - sigma) < 0.03 * sigma
    # λ's scale: σ · sqrt(median trace G), exactly
    tr = G.diagonal(dim1=1, dim2=2).sum(1)
    assert lam_scale(s, G) == pytest.approx(s * float(tr.median()) ** 0.5)


def test_bad_inputs(device):
    G = torch.eye(3, device=device).expand(4, 3, 3).contiguous()
    pix = torch.arange(4, device=device)
    with pytest.raises(ValueError, match="pixel_index"):
        prepare_spatial(G, torch.arange(5, device=device), (2, 2))
    with pytest.raises(ValueError, match="out of range"):
        prepare_spatial(G, pix + 1, (2, 2))
    prob = prepare_spatial(G, pix, (2, 2))
    with pytest.raises(ValueError, match="b must be"):
        solve_spatial(prob, torch.zeros(4, 2, device=device), 1.0)
    with pytest.raises(ValueError, match="lam"):
        solve_spatial(prob, torch.zeros(4, 3, device=device), -1.0)
    for relax in (0.0, 2.0):
        with pytest.raises(ValueError, match="relax must be in"):
            solve_spatial(prob, torch.zeros(4, 3, device=device), 1.0, relax=relax)


def test_inplace_and_differentiable_paths_agree(device, dtype):
    """The tolerance-driven solve (in-place prox) and the fixed-iteration one (out of place) run
    the same iterations."""
    A, y, G, b, active, (h, w) = _tiny(device, dtype, seed=8)
    pix = torch.arange(h * w, device=device)
    prob = prepare_spatial(G, pix, (h, w), active)
    x0 = solve_nnls(A, y).x
    a = solve_spatial(prob, b, 0.7, x0=x0, tol=1e-30, max_iter=20, inner_iters=5)
    f = solve_spatial(prob, b, 0.7, x0=x0, iters=20, inner_iters=5)
    assert a.iterations == 20 and not a.converged
    tol = 1e-4 if dtype == torch.float32 else 1e-10
    assert float((a.x - f.x).abs().max()) <= tol * float(f.x.abs().max())


def test_edge_weights(device):
    """Float edge weights of ones are the plain TV; the guide's weights are ~1 within the noise
    and small across a colour edge of the reference view."""
    dtype = torch.float64
    A, y, G, b, active, (h, w) = _tiny(device, dtype, seed=9)
    pix = torch.arange(h * w, device=device)
    prob = prepare_spatial(G, pix, (h, w), active)
    ones = torch.ones(h, w, dtype=dtype, device=device)
    wprob = prob.for_frame(active, weights=(ones, ones))
    assert wprob.ex.dtype == dtype
    a = solve_spatial(prob, b, 0.7, tol=1e-30, max_iter=20)
    c = solve_spatial(wprob, b, 0.7, tol=1e-30, max_iter=20)
    f = solve_spatial(wprob, b, 0.7, iters=20)
    assert float((a.x - c.x).abs().max()) < 1e-10 and float((a.x - f.x).abs().max()) < 1e-10
    # guide: a left/right colour step in the reference view (observations 0..2)
    yy = torch.full((h * w, 6), 100.0, dtype=dtype, device=device)
    cols = pix % w
    yy[cols >= w // 2, :3] = 300.0
    mask = torch.ones_like(yy, dtype=torch.bool)
    wx, wy = guide_weights(prob, yy, mask, sigma=1.0)
    j = w // 2 - 1
    assert float(wx[:, j].max()) < 0.01  # across the edge
    assert float(wx[:, :j].min()) == 1.0 and float(wy.min()) == 1.0
    # a smaller weight across the edge lets the solution keep a larger jump there
    wprob2 = prob.for_frame(torch.ones_like(active), weights=(wx, wy))
    plain = prob.for_frame(torch.ones_like(active))
    g = solve_spatial(wprob2, b, 5.0, tol=1e-8, max_iter=5000)
    p = solve_spatial(plain, b, 5.0, tol=1e-8, max_iter=5000)
    jump = lambda x: float((plain.to_cube(x)[:, :, j + 1] - plain.to_cube(x)[:, :, j]).norm())  # noqa: E731
    assert jump(g.x) > jump(p.x)


@pytest.mark.parametrize("weighted,alpha,relax",
                         [(False, 1.0, 1.0), (True, 1.0, 1.0), (True, 0.3, 1.0), (True, 0.3, 1.3)])
def test_compiled_and_torch_backends_agree(dtype, weighted, alpha, relax):
    """The compiled CPU kernels run the torch path's iterations: same answer to rounding, with
    inactive pixels, edge weights and pixels with their own Gram matrix in this frame (and
    over-relaxed: the same relaxed iterations, the primal residual of ``x``, not ``x̂``)."""
    from hsi_torch.recon.spatial import _compiled as _spatial_compiled

    if not _spatial_compiled.AVAILABLE:
        pytest.skip("numba not installed")
    A, y, G, b, active, (h, w) = _tiny("cpu", dtype, h=7, w=9, seed=11)
    pix = torch.arange(h * w)
    base = prepare_spatial(G, pix, (h, w), active)
    g = torch.Generator().manual_seed(3)
    weights = None
    if weighted:
        weights = tuple(torch.rand(h, w, generator=g, dtype=torch.float64) for _ in range(2))
    rows = torch.tensor([4, 30, 50])
    row_gram = G[rows] * 1.5  # a frame mask changed these pixels' data terms
    prob = base.for_frame(active, rows, row_gram, weights)
    assert prob.compiled_inputs() is not None
    x0 = solve_nnls(A, y).x
    kw = dict(x0=x0, tol=1e-30, max_iter=30, inner_iters=4, brightness_weight=alpha,
              relax=relax)
    a = solve_spatial(prob, b, 0.7, backend="compiled", **kw)
    t = solve_spatial(prob, b, 0.7, backend="torch", **kw)
    f = solve_spatial(prob, b, 0.7, x0=x0, iters=30, inner_iters=4, brightness_weight=alpha,
                      relax=relax)
    torch.testing.assert_close(f.x, t.x, atol=1e-5 if dtype == torch.float32 else 1e-11, rtol=0)
    assert a.iterations == t.iterations == 30
    torch.testing.assert_close(a.x, t.x, atol=1e-5 if dtype == torch.float32 else 1e-11,
                               rtol=0)
    assert a.primal_residual == pytest.approx(t.primal_residual, rel=1e-3)
    assert float(a.x.min()) >= 0


def test_compiled_backend_refuses_what_it_cannot_run():
    """Pixels out of row-major order (or no numba): a clear error for backend='compiled',
    the torch path for 'auto'."""
    A, y, G, b, active, (h, w) = _tiny("cpu", torch.float64, seed=12, holes=False)
    perm = torch.randperm(h * w, generator=torch.Generator().manual_seed(0))
    prob = prepare_spatial(G[perm], perm, (h, w))
    assert prob.compiled_inputs() is None
    with pytest.raises(ValueError, match="row-major"):
        solve_spatial(prob, b[perm], 0.5, backend="compiled")
    with pytest.raises(ValueError, match="backend"):
        solve_spatial(prob, b[perm], 0.5, backend="numba")
    auto = solve_spatial(prob, b[perm], 0.5, tol=1e-30, max_iter=20)
    ref = prepare_spatial(G, torch.arange(h * w), (h, w))
    sorted_ = solve_spatial(ref, b, 0.5, tol=1e-30, max_iter=20)
    torch.testing.assert_close(auto.x, sorted_.x[perm], atol=1e-10, rtol=0)


def test_brightness_weighting_is_symmetric_and_weights_only_the_flat_spectrum(dtype):
    """``K`` is symmetric, scales the flat spectrum by α and keeps zero-mean spectra; the
    weighted TV charges a brightness step α times a shape step of the same size."""
    from hsi_torch.recon.spatial import brightness_weighted

    g = torch.Generator().manual_seed(5)
    a = torch.randn(2, 6, 3, 4, generator=g, dtype=torch.float64).to(dtype=dtype)
    c = torch.randn(2, 6, 3, 4, generator=g, dtype=torch.float64).to(dtype=dtype)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    lhs = float((brightness_weighted(a, 0.3) * c).sum())
    rhs = float((a * brightness_weighted(c, 0.3)).sum())
    assert abs(lhs - rhs) <= tol * max(1.0, abs(lhs))
    flat = torch.ones(2, 6, 3, 4, dtype=dtype)
    torch.testing.assert_close(brightness_weighted(flat, 0.3), 0.3 * flat)
    shape = a - a.mean(1, keepdim=True)
    torch.testing.assert_close(brightness_weighted(shape, 0.3), shape)
    active = torch.ones(2, 2, dtype=torch.bool)
    step_b = torch.zeros(6, 2, 2, dtype=dtype)
    step_b[:, :, 1] = 1.0  # a brightness step, norm sqrt(6) per edge
    step_s = torch.zeros(6, 2, 2, dtype=dtype)
    step_s[:3, :, 1], step_s[3:, :, 1] = 1.0, -1.0  # a shape step of the same norm
    tb = float(total_variation(step_b, active, 0.3))
    ts = float(total_variation(step_s, active, 0.3))
    assert tb == pytest.approx(0.3 * ts, rel=1e-5)
    with pytest.raises(ValueError, match="brightness_weight"):
        solve_spatial(prepare_spatial(torch.eye(2, dtype=dtype)[None], torch.arange(1), (1, 1)),
                      torch.zeros(1, 2, dtype=dtype), 1.0, brightness_weight=0.0)


def test_factor_is_built_in_chunks(device, dtype, monkeypatch):
    """``(G + ρI)⁻¹`` factorised a few pixels at a time equals the whole-batch inverse (per-pixel
    and shared ``G``), and a Gram matrix that is not positive semi-definite is still refused."""
    from hsi_torch.recon.spatial import problem as spatial_problem

    monkeypatch.setattr(spatial_problem, "FACTOR_CHUNK", 7)  # 30 pixels: 5 chunks, a short last
    A, y, G, b, active, (h, w) = _tiny(device, dtype, seed=21)
    pix = torch.arange(h * w, device=device)
    prob = prepare_spatial(G, pix, (h, w), active)
    eye = torch.eye(G.shape[-1], dtype=dtype, device=device)
    tol = 1e-4 if dtype == torch.float32 else 1e-10
    ref = torch.linalg.inv(G.double() + prob.rho * eye.double())
    assert prob.inv.shape == G.shape and prob.inv.is_contiguous()
    assert float((prob.inv.double() - ref).abs().max()) <= tol * float(ref.abs().max())
    shared = prepare_spatial(G[:1], pix, (h, w), rho=0.5)
    torch.testing.assert_close(shared.inv.double(), torch.linalg.inv(G[:1].double() + 0.5 * eye),
                               atol=tol * 10, rtol=tol)
    bad = G.clone()
    bad[12] = -eye * 10  # negative definite in the third chunk
    with pytest.raises(ValueError, match="positive definite"):  # formed on first use
        _ = prepare_spatial(bad, pix, (h, w)).inv
    if device == "cpu" and prob.compiled_inputs() is not None:  # the packed form, the same
        with pytest.raises(ValueError, match="positive definite"):
            prepare_spatial(bad, pix, (h, w)).compiled_inputs()


@pytest.mark.parametrize("shared", [False, True])
def test_compiled_products(dtype, shared):
    """The compiled ``S x`` (columns of a symmetric ``S`` read as axpy's) equals the plain
    product; the fused pass's x-update from the packed inverse (a frame with a hole, rows longer
    than one packed run, pixels with their own factor) equals ``(G + ρI)⁻¹(b + ρ(z − u))``, with
    ``u ← u + x − z`` first or not, and with ``λ = 0`` its ``z`` is the projection of ``x + u``."""
    from hsi_torch.recon.spatial import _compiled as sc

    if not sc.AVAILABLE:
        pytest.skip("numba not installed")
    rng = np.random.default_rng(5)
    P, m = 1000, 25
    dtype_np = np.float32 if dtype == torch.float32 else np.float64
    B = rng.standard_normal((1 if shared else P, m, m))
    S = np.ascontiguousarray((B + B.transpose(0, 2, 1)).astype(dtype_np))
    x = rng.standard_normal((P, m)).astype(dtype_np)
    out = np.empty_like(x)
    sc.sym_apply(S, x, out)
    ref = np.einsum("pij,pj->pi", np.broadcast_to(S, (P, m, m)).astype(np.float64), x)
    tol = 1e-4 if dtype == torch.float32 else 1e-12
    assert np.abs(out - ref).max() <= tol * np.abs(ref).max()
    # the fused x-update on a 9 x 150 frame (rows of 150 > 64 pixels) with one hole
    h, w = 9, 150
    keep = np.ones(h * w, bool)
    keep[3 * w + 70] = False
    pix = torch.from_numpy(np.flatnonzero(keep))
    n = pix.numel()
    A = torch.from_numpy(rng.standard_normal((1 if shared else n, 30, m))).to(dtype)
    G = A.transpose(1, 2) @ A + torch.eye(m, dtype=dtype)
    prob = prepare_spatial(G, pix, (h, w), rho=0.3)
    rows = torch.tensor([5, 300, 301, n - 1])
    row_gram = G.expand(n, m, m)[rows] * 1.5
    fp = prob.for_frame(torch.ones(n, dtype=torch.bool), rows, row_gram)
    inv_rows, _ = fp.compiled_inputs()
    dense = fp.inv.expand(n, m, m).clone().double()
    dense[rows] = fp.row_inv.double()
    step = _CompiledStepInputs(fp, dtype_np, rng)
    for update_u in (False, True):
        st = step.fresh()
        sc.fgp_block(inv_rows, st.row_slot, st.row_inv, st.has_slot, st.b, st.x, st.u, st.z,
                     st.x2, st.u2, 0.3, update_u, 0.0, 0.0, np.zeros(0, dtype_np), st.p, st.ps,
                     st.p2, st.ps2, st.z2, fp.fgp_grid(), sc.fgp_blocks(fp.fgp_grid()[0], 3))
        u1 = st.u.astype(np.float64) + ((st.x - st.z) if update_u else 0)
        rhs = st.b + 0.3 * (st.z - u1)
        xr = np.einsum("pij,jp->ip", dense.numpy(), rhs)
        assert np.abs(st.u2 - u1).max() <= tol * np.abs(u1).max()
        assert np.abs(st.x2 - xr).max() <= tol * np.abs(xr).max()
        assert np.abs(st.z2 - np.maximum(xr + u1, 0)).max() <= tol * np.abs(xr + u1).max()


class _CompiledStepInputs:
    """Random band-major state for one call of the fused pass (:func:`test_compiled_products`)."""

    def __init__(self, prob, dtype_np, rng) -> None:
        self.prob, self.dt, self.rng = prob, dtype_np, rng

    def fresh(self):
        n, m = self.prob.num_pixels, self.prob.num_bands
        st = type("State", (), {})()
        st.b, st.x, st.u, st.z = (self.rng.standard_normal((m, n)).astype(self.dt)
                                  for _ in range(4))
        st.x2, st.u2, st.z2 = (np.full((m, n), np.nan, self.dt) for _ in range(3))
        st.p, st.p2 = np.zeros((2, m, n), self.dt), np.zeros((2, m, n), self.dt)
        st.ps, st.ps2 = np.zeros((2, n), self.dt), np.zeros((2, n), self.dt)
        st.row_slot = np.full(n, -1, np.int64)
        rows = self.prob.row_index.numpy()
        st.row_slot[rows] = np.arange(rows.size)
        row_ptr = self.prob.fgp_grid()[0]
        st.has_slot = np.zeros(row_ptr.size - 1, bool)
        st.has_slot[np.searchsorted(row_ptr, rows, side="right") - 1] = True
        st.row_inv = np.ascontiguousarray(self.prob.row_inv.numpy())
        return st


def test_total_variation_gradient_is_finite_on_flat_patches():
    """TV's sqrt has an infinite derivative at 0: a flat patch (equal neighbours) gave NaN
    gradients, e.g. through CameraOperator.objective; it now contributes the subgradient 0, and
    elsewhere the gradient is unchanged (gradcheck)."""
    active = torch.ones(4, 5, dtype=torch.bool)
    active[0, 0] = False
    g = torch.Generator().manual_seed(0)
    x = torch.rand(3, 4, 5, generator=g, dtype=torch.float64)
    x[:, 1:3, 1:4] = 0.5  # a flat patch
    x.requires_grad_(True)
    for alpha in (1.0, 0.3):
        (grad,) = torch.autograd.grad(total_variation(x, active, alpha), x)
        assert bool(torch.isfinite(grad).all())
    flat = torch.zeros(2, 3, 4, 5, dtype=torch.float64, requires_grad=True)
    (grad,) = torch.autograd.grad(total_variation(flat, active).sum(), flat)
    assert bool((grad == 0).all())
    smooth = torch.rand(3, 4, 5, generator=g, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda c: total_variation(c, active, 0.3), (smooth,))
    with pytest.raises(ValueError, match=r"active must be \(h, w\) = \(4, 5\)"):
        total_variation(smooth, torch.ones(5, 4, dtype=torch.bool))
