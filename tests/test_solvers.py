"""Tests of the batched NNLS solver against scipy.optimize.nnls and the KKT conditions."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.optimize import nnls
from synthetic_data import synthetic_brf_problem

from hsi_torch.recon.nnls import NNLSResult, prepare_nnls, solve_nnls
from hsi_torch.spectral import difference_matrix

# relative (per-pixel L2) agreement with SciPy on well-conditioned problems
RTOL = {torch.float64: 1e-8, torch.float32: 1e-4}


# ------------------------------------------------------------------------------------------------
# references


def scipy_reference(A, y, beta, mask=None, diff_order=1):
    """Per-pixel scipy.optimize.nnls on the stacked system [A_p[mask]; sqrt(beta) D] (float64)."""
    A = A.detach().double().cpu()
    y = y.detach().double().cpu().numpy()
    P = y.shape[0]
    A = (A.unsqueeze(0).expand(P, -1, -1) if A.ndim == 2 else A).numpy()
    M = A.shape[2]
    m = np.ones(y.shape, bool) if mask is None else mask.cpu().numpy()
    D = np.sqrt(beta) * difference_matrix(M, diff_order, dtype=torch.float64).numpy()
    X = np.zeros((P, M))
    for p in range(P):
        a = np.vstack([A[p][m[p]], D])
        b = np.concatenate([y[p][m[p]], np.zeros(D.shape[0])])
        X[p] = nnls(a, b, maxiter=50 * M)[0]
    return torch.from_numpy(X)


def kkt_violation(A, y, x, beta, mask=None, diff_order=1):
    """Independent KKT check from (A, y, mask): returns per-pixel scaled violations.

    g = Aᵀ W (A x − y) + β DᵀD x. Violations: max(−x), max over x=0 of max(−g, 0), and
    |min(G_mm x_m, g_m)| (covers |g| at x > 0), all divided by the scale ‖AᵀWy‖∞ + ‖diag(G) x‖∞.
    """
    A = A.double()
    y = y.double()
    x = x.double()
    P, M = x.shape
    A3 = A.unsqueeze(0).expand(P, -1, -1) if A.ndim == 2 else A
    w = torch.ones_like(y) if mask is None else mask.double()
    y = torch.where(w > 0, y, torch.zeros_like(y))
    D = difference_matrix(M, diff_order, dtype=torch.float64, device=x.device)
    r = torch.einsum("pom,pm->po", A3, x) - y
    g = torch.einsum("pom,po->pm", A3, w * r) + beta * x @ (D.T @ D)
    gdiag = torch.einsum("pom,po->pm", A3 * A3, w) + beta * torch.diagonal(D.T @ D)
    b = torch.einsum("pom,po->pm", A3, w * y)
    scale = (b.abs().amax(1) + (gdiag * x).abs().amax(1)).clamp_min(1e-300)
    neg_x = (-x).clamp_min(0).amax(1) * gdiag.amax(1)
    neg_g = torch.where(x <= 0, (-g).clamp_min(0), torch.zeros_like(g)).amax(1)
    comp = torch.minimum(gdiag * x, g).abs().amax(1)
    return torch.stack([neg_x, neg_g, comp]).amax(0) / scale


def rel_err(x, ref):
    x = x.detach().double().cpu()
    return (x - ref).norm(dim=1) / ref.norm(dim=1).clamp_min(1e-30)


def random_problem(P, O=30, M=25, *, seed=0, shared=False, masked=False, noise=0.5):
    g = torch.Generator().manual_seed(seed)
    A = torch.rand((O, M) if shared else (P, O, M), generator=g, dtype=torch.float64)
    xt = torch.randn(P, M, generator=g, dtype=torch.float64).clamp_min(0)
    A3 = A.expand(P, -1, -1) if shared else A
    y = torch.einsum("pom,pm->po", A3, xt) + noise * torch.randn(P, O, generator=g,
                                                                 dtype=torch.float64)
    mask = (torch.rand(P, O, generator=g) > 0.25) if masked else None
    return A, y, mask


# ------------------------------------------------------------------------------------------------
# agreement with SciPy


@pytest.mark.parametrize("shared", [False, True])
@pytest.mark.parametrize("masked", [False, True])
def test_random_matches_scipy(device, dtype, shared, masked):
    P, beta = 500, 1.0
    A, y, mask = random_problem(P, seed=1 + 2 * shared + masked, shared=shared, masked=masked)
    A, y = A.to(device, dtype), y.to(device, dtype)
    mask = None if mask is None else mask.to(device)
    res = solve_nnls(A, y, beta=beta, mask=mask)
    assert isinstance(res, NNLSResult)
    assert res.x.shape == (P, 25) and res.x.dtype == dtype and res.x.device.type == device.type
    ref = scipy_reference(A, y, beta, mask)
    err = rel_err(res.x, ref)
    assert err.max() < RTOL[dtype] * (5 if dtype == torch.float32 else 1), err.max()
    assert bool(res.converged.all())
    assert bool((res.x >= 0).all())
    assert kkt_violation(A, y, res.x, beta, mask).max() < (1e-10 if dtype == torch.float64
                                                            else 1e-4)


@pytest.mark.parametrize("shared", [False, True])
def test_realistic_brf_matches_scipy(device, dtype, shared):
    """BRF-like cosine transmittances × smooth RGB curves, 30 obs × 25 bands, DN scale."""
    A, y, mask, _ = synthetic_brf_problem(800, shared=shared, seed=3, dtype=torch.float64)
    beta = 1e2
    ref = scipy_reference(A, y, beta, mask)
    res = solve_nnls(A.to(device, dtype), y.to(device, dtype), beta=beta, mask=mask.to(device))
    err = rel_err(res.x, ref)
    # per-pixel relative L2; float32 is limited by cond(G)·eps (cond up to ~700 here)
    assert err.max() < (1e-8 if dtype == torch.float64 else 5e-4), err.max()
    assert err.median() < RTOL[dtype], err.median()
    assert bool(res.converged.all())
    # some pixels really need the active set (the unconstrained solution is negative there)
    assert 0.05 < float((res.iterations > 0).double().mean()) < 0.9
    tol = 1e-10 if dtype == torch.float64 else 1e-4
    assert kkt_violation(A.to(device), y.to(device), res.x, beta, mask.to(device)).max() < tol


@pytest.mark.parametrize("diff_order", [0, 2])
def test_other_difference_orders(diff_order):
    A, y, mask = random_problem(300, seed=7, masked=True)
    res = solve_nnls(A, y, beta=3.0, mask=mask, diff_order=diff_order)
    ref = scipy_reference(A, y, 3.0, mask, diff_order)
    assert rel_err(res.x, ref).max() < 1e-8


def test_beta_zero_full_rank_and_masked_rank_deficient():
    """beta = 0: unique solutions match SciPy; < M used rows (rank deficient) still satisfy KKT."""
    A, y, mask = random_problem(600, seed=11, masked=True)  # ~22 of 30 rows used < 25 bands
    res = solve_nnls(A, y, beta=0.0, mask=mask)
    assert bool(res.converged.all())
    assert kkt_violation(A, y, res.x, 0.0, mask).max() < 1e-10
    ref = scipy_reference(A, y, 0.0, mask)
    # same optimal objective as SciPy (the minimiser need not be unique)
    A_np, y_np, m_np = A.numpy(), y.numpy(), mask.numpy()
    for p in range(0, 600, 7):
        a, b = A_np[p][m_np[p]], y_np[p][m_np[p]]
        f_ours = np.sum((a @ res.x[p].numpy() - b) ** 2)
        f_ref = np.sum((a @ ref[p].numpy() - b) ** 2)
        assert f_ours <= f_ref * (1 + 1e-9) + 1e-12


def test_beta_zero_rank_deficient_A(device, dtype):
    """A = B C with rank 8 < 25 bands: Lawson–Hanson fallback, KKT holds, objective = SciPy's."""
    g = torch.Generator().manual_seed(5)
    P = 400
    A = torch.rand(P, 30, 8, generator=g, dtype=torch.float64) @ torch.rand(
        P, 8, 25, generator=g, dtype=torch.float64)
    y = 10 * torch.rand(P, 30, generator=g, dtype=torch.float64)
    res = solve_nnls(A.to(device, dtype), y.to(device, dtype), beta=0.0)
    assert torch.isfinite(res.x).all() and bool((res.x >= 0).all())
    viol = kkt_violation(A.to(device), y.to(device), res.x, 0.0)
    if dtype == torch.float64:
        assert viol.max() < 1e-10
        assert bool(res.converged.all())
    else:
        assert viol.median() < 1e-5 and viol.max() < 5e-3
    ref = scipy_reference(A, y, 0.0)
    r_ours = torch.einsum("pom,pm->po", A, res.x.double().cpu()) - y
    r_ref = torch.einsum("pom,pm->po", A, ref) - y
    f_ours, f_ref = r_ours.square().sum(1), r_ref.square().sum(1)
    tol = 1e-10 if dtype == torch.float64 else 1e-3
    assert ((f_ours - f_ref) / f_ref).max() < tol


# ------------------------------------------------------------------------------------------------
# edge cases


def test_all_masked_pixel_returns_zero_and_is_flagged(device, dtype):
    A, y, mask = random_problem(50, seed=2, masked=True)
    mask[3] = False
    mask[17] = False
    y[3] = float("nan")  # ignored where masked
    y[10, ~mask[10]] = float("inf")
    A, y, mask = A.to(device, dtype), y.to(device, dtype), mask.to(device)
    for beta in (0.0, 2.0):
        for solver in ("active_set", "admm"):
            res = solve_nnls(A, y, beta=beta, mask=mask, solver=solver, max_iter=300)
            assert torch.isfinite(res.x).all()
            assert res.no_data.tolist() == [i in (3, 17) for i in range(50)]
            assert (res.x[[3, 17]] == 0).all()
            assert res.converged[[3, 17]].all()
            if beta > 0 and solver == "active_set":  # the other pixels are unaffected
                ref = scipy_reference(A[8:12], torch.nan_to_num(y[8:12], posinf=0.0), beta,
                                      mask[8:12])
                assert rel_err(res.x[8:12], ref).max() < RTOL[dtype] * 5


@pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_used_observation_is_an_error_naming_it(dtype, value):
    """NaN or ±inf in ``y`` where the mask uses it is a ``ValueError`` (an ``InputError``) that
    counts the observations and pixels and names the first (pixel, observation): per-pixel dense
    and factored ``A``, shared ``A`` with and without a mask, both kernels (compiled "auto" and
    "torch"), both solvers, and through ``solve_nnls``' outer chunks (whole-frame indices).
    Before the fix the pixel came back as x = 0 (ADMM: NaN), unconverged, or, for -inf,
    "converged", with no error. The same values where the mask is False are still ignored."""
    from hsi_torch.errors import InputError
    from hsi_torch.forward_model import SensingModel

    g = torch.Generator().manual_seed(31)
    P, V, M = 40, 10, 25
    model = SensingModel(0.2 + 0.8 * torch.rand(P, V, M, generator=g, dtype=torch.float64),
                         0.7 + 0.4 * torch.rand(P, V, generator=g, dtype=torch.float64),
                         torch.rand(3, M, generator=g, dtype=torch.float64) * 20).to(dtype=dtype)
    A = model.dense()
    y = torch.bmm(A, torch.rand(P, M, 1, generator=g, dtype=dtype)).squeeze(2)
    mask = torch.rand(P, 3 * V, generator=g) > 0.2
    mask[[7, 23], [4, 11]] = True
    bad = y.clone()
    bad[7, 4] = value
    bad[23, 11] = value
    bad[23, 12] = value
    mask[23, 12] = False  # not used: not counted
    bad[30, ~mask[30]] = value  # not used anywhere in the pixel
    msg = (r"2 used observation\(s\) of 2 pixel\(s\), the first at pixel 7, observation 4 "
           r"\(y\[7, 4\] = " + str(value).replace("-", "\\-") + r"\).*mask them out")
    unmasked = y.clone()  # without a mask every observation is used
    unmasked[[7, 23], [4, 11]] = value
    cases = [(model, mask, bad), (A, mask, bad), (A[0], mask, bad), (A[0], None, unmasked),
             (A, None, unmasked)]
    for a, mk, yb in cases:
        for solver in ("active_set", "admm"):
            for backend in ("auto", "torch"):
                kw = dict(beta=1.0, mask=mk, solver=solver, backend=backend)
                with pytest.raises(InputError, match=msg):
                    solve_nnls(a, yb, **kw)
                with pytest.raises(ValueError, match=msg):
                    prepare_nnls(a, mask=mk, beta=1.0).solve(yb, solver=solver, backend=backend)
                # masked out, the same values are ignored: the answer of the frame with zeros
                mk0 = torch.ones_like(mask) if mk is None else mk.clone()
                mk0[[7, 23], [4, 11]] = False
                ok = solve_nnls(a, yb, **{**kw, "mask": mk0})
                ref = solve_nnls(a, torch.where(mk0, yb, torch.zeros((), dtype=dtype)),
                                 **{**kw, "mask": mk0})
                assert torch.equal(ok.x, ref.x) and bool(torch.isfinite(ok.x).all())
                assert solver == "admm" or bool(ok.converged.all())
    # outer chunks of solve_nnls: the pixel index and the counts are the whole frame's
    with pytest.raises(ValueError, match=msg):
        solve_nnls(A, bad, beta=1.0, mask=mask, chunk_size=5)
    late = y.clone()
    late[37, 2] = value
    with pytest.raises(ValueError, match=r"1 used observation\(s\) of 1 pixel\(s\), the first "
                                         r"at pixel 37, observation 2"):
        solve_nnls(A, late, beta=1.0, chunk_size=5)


def test_observations_overflowing_the_problems_dtype_are_an_error_naming_them():
    """Finite observations too large for the problem's dtype (1e38 in a float32 frame: b = AᵀWy
    overflows) passed the NaN/inf check, which looks at y, and the pixel silently came back as
    x = 0. Now an ``InputError`` names the first pixel and says the values overflow the dtype
    (either solver, either kernel, whole-frame indices through ``solve_nnls``' outer chunks);
    a float64 y whose cast to a float32 problem makes inf says the cast did it."""
    from hsi_torch.errors import InputError

    g = torch.Generator().manual_seed(5)
    P, O, M = 12, 30, 25
    A = torch.rand(P, O, M, generator=g)
    y = torch.bmm(A, torch.rand(P, M, 1, generator=g)).squeeze(2)
    big = y.clone()
    big[9] = 1e38  # finite in float32; b = Aᵀ W y is not
    msg = (r"b = A\^T W y overflows float32 in 1 pixel\(s\)( \(of the pixels \d+ to \d+\))? "
           r"whose used observations are finite, the first at pixel 9 .*overflow the problem's "
           r"dtype.*scale the data.*float64")
    for solver in ("active_set", "admm"):
        for backend in ("auto", "torch"):
            with pytest.raises(InputError, match=msg):
                prepare_nnls(A, beta=1.0).solve(big, solver=solver, backend=backend)
            with pytest.raises(InputError, match=msg):
                solve_nnls(A, big, beta=1.0, solver=solver, backend=backend,
                           mask=torch.ones(P, O, dtype=torch.bool), chunk_size=4)  # fmt: skip
    with pytest.raises(InputError, match=msg):  # ADMM's own chunks: the whole frame's index
        prepare_nnls(A, beta=1.0).solve(big, solver="admm", chunk_size=4)
    # the same data in float64 solves, and scaled down in float32 too
    assert bool(solve_nnls(A.double(), big.double(), beta=1.0).converged.all())
    assert bool(torch.isfinite(solve_nnls(A, big / 1e30, beta=1.0).x).all())
    # a float64 y cast to a float32 problem: the cast made the inf, and the message says so
    y64 = y.double()
    y64[6, 13] = 1e39
    cast = (r"y is float64 and the problem float32: casting y to float32 made 1 used "
            r"observation\(s\) of 1 pixel\(s\) inf, the first at pixel 6, observation 13 "
            r"\(y\[6, 13\] = 1e\+39.*overflow the problem's dtype.*float64")
    for solver in ("active_set", "admm"):
        with pytest.raises(InputError, match=cast):
            prepare_nnls(A, beta=1.0).solve(y64, solver=solver)
        with pytest.raises(InputError, match=cast):
            solve_nnls(A, y64, beta=1.0, solver=solver,
                       mask=torch.ones(P, O, dtype=torch.bool), chunk_size=4)  # fmt: skip
    # masked out, the value is not used: no error
    mask = torch.ones(P, O, dtype=torch.bool)
    mask[6, 13] = False
    assert bool(torch.isfinite(prepare_nnls(A, mask=mask, beta=1.0).solve(y64).x).all())



def test_an_overflow_count_found_in_one_chunk_says_which_pixels_it_counted():
    """With chunks (ADMM's own, ``solve_nnls``' outer ones) the overflow is found in the first
    chunk holding one: its count is that chunk's, and the message said "in 1 pixel(s)" of a
    frame where 2 overflow. It now names the pixels counted."""
    from hsi_torch.errors import InputError

    g = torch.Generator().manual_seed(5)
    P, O, M = 12, 30, 25
    A = torch.rand(P, O, M, generator=g)
    big = torch.bmm(A, torch.rand(P, M, 1, generator=g)).squeeze(2)
    big[5] = 1e38
    big[9] = 1e38
    whole = (r"overflows float32 in 2 pixel\(s\) whose used observations are finite, the first "
             r"at pixel 5")
    part = (r"overflows float32 in 1 pixel\(s\) \(of the pixels 4 to 7\) whose used observations "
            r"are finite, the first at pixel 5")
    with pytest.raises(InputError, match=whole):
        prepare_nnls(A, beta=1.0).solve(big, solver="admm")
    with pytest.raises(InputError, match=part):
        prepare_nnls(A, beta=1.0).solve(big, solver="admm", chunk_size=4)
    with pytest.raises(InputError, match=part):
        solve_nnls(A, big, beta=1.0, chunk_size=4)

def test_exact_zeros():
    # y = 0 -> x = 0 exactly
    A, _, _ = random_problem(20, seed=4)
    res = solve_nnls(A, torch.zeros(20, 30, dtype=torch.float64), beta=1.0)
    assert (res.x == 0).all() and bool(res.converged.all())
    # noise-free data from a sparse non-negative x with exact zeros, beta = 0, full rank
    g = torch.Generator().manual_seed(9)
    xt = torch.rand(200, 25, generator=g, dtype=torch.float64)
    xt[torch.rand(200, 25, generator=g) < 0.4] = 0.0
    A, _, _ = random_problem(200, seed=9)
    y = torch.einsum("pom,pm->po", A, xt)
    res = solve_nnls(A, y, beta=0.0)
    torch.testing.assert_close(res.x, xt, rtol=0, atol=1e-9)
    # a band no observation sees (zero column) with beta = 0 stays 0, and KKT holds
    A2 = A.clone()
    A2[:, :, 5] = 0.0
    res = solve_nnls(A2, y, beta=0.0)
    assert (res.x[:, 5] == 0).all()
    assert kkt_violation(A2, y, res.x, 0.0).max() < 1e-10


def test_single_pixel(device):
    A, y, mask = random_problem(1, seed=21, masked=True)
    res = solve_nnls(A.to(device), y.to(device), beta=0.5, mask=mask.to(device))
    assert res.x.shape == (1, 25)
    assert rel_err(res.x, scipy_reference(A, y, 0.5, mask)).max() < 1e-8
    res2 = solve_nnls(A[0].to(device), y.to(device), beta=0.5)  # shared A, P = 1
    assert rel_err(res2.x, scipy_reference(A[0], y, 0.5)).max() < 1e-8


def test_prepared_reuse_equals_fresh_solve(device, dtype):
    A, y, mask, _ = synthetic_brf_problem(400, seed=8, dtype=dtype, device=device)
    prob = prepare_nnls(A, mask=mask, beta=50.0)
    g = torch.Generator().manual_seed(0)
    for f in range(2):  # several frames, same calibration
        yf = y + torch.randn(y.shape, generator=g, dtype=torch.float64).to(device, dtype)
        fresh = solve_nnls(A, yf, beta=50.0, mask=mask)
        reused = prob.solve(yf)
        torch.testing.assert_close(reused.x, fresh.x, rtol=0, atol=0 if f == 0 else 1e-12)
        assert torch.equal(reused.iterations, fresh.iterations)


def test_chunking_gives_identical_results(device):
    A, y, mask, _ = synthetic_brf_problem(600, seed=12, device=device)
    full = solve_nnls(A, y, beta=1e2, mask=mask, chunk_size=600)
    for kw in (dict(chunk_size=61), dict(max_memory=300_000)):
        part = solve_nnls(A, y, beta=1e2, mask=mask, **kw)
        torch.testing.assert_close(part.x, full.x, rtol=1e-12, atol=1e-12)
        assert torch.equal(part.converged, full.converged)
        prob = prepare_nnls(A, mask=mask, beta=1e2, **kw)
        torch.testing.assert_close(prob.solve(y, **kw).x, full.x, rtol=1e-12, atol=1e-12)


def test_shared_A_with_mask_equals_per_pixel_A():
    A, y, mask = random_problem(300, seed=13, shared=True, masked=True)
    a = solve_nnls(A, y, beta=2.0, mask=mask)
    b = solve_nnls(A.expand(300, -1, -1).contiguous(), y, beta=2.0, mask=mask)
    torch.testing.assert_close(a.x, b.x, rtol=1e-10, atol=1e-12)


# ------------------------------------------------------------------------------------------------
# ADMM


def test_admm_converges_to_active_set(device):
    A, y, mask, _ = synthetic_brf_problem(400, seed=14, device=device)
    exact = solve_nnls(A, y, beta=1e2, mask=mask)
    res = solve_nnls(A, y, beta=1e2, mask=mask, solver="admm", tol=1e-11, max_iter=20000)
    assert bool(res.converged.all())
    torch.testing.assert_close(res.x, exact.x, rtol=0, atol=1e-7 * float(exact.x.abs().max()))
    # warm start from the exact answer: ADMM is at its fixed point and stops at the first check
    warm = solve_nnls(A, y, beta=1e2, mask=mask, solver="admm", x0=exact.x, tol=1e-11)
    assert int(warm.iterations.max()) <= 10
    torch.testing.assert_close(warm.x, exact.x, rtol=0, atol=1e-9 * float(exact.x.abs().max()))
    # fixed-iteration mode gets close too
    fixed = solve_nnls(A, y, beta=1e2, mask=mask, solver="admm", admm_iters=300)
    assert (fixed.iterations == 300).all()
    assert float((fixed.x - exact.x).abs().max()) < 1e-3 * float(exact.x.abs().max())


def test_admm_fixed_iterations_gradcheck():
    g = torch.Generator().manual_seed(0)
    A = torch.rand(2, 6, 4, generator=g, dtype=torch.float64)
    x_true = torch.rand(2, 4, generator=g, dtype=torch.float64)
    y0 = torch.einsum("pom,pm->po", A, x_true) + 0.05 * torch.randn(2, 6, generator=g,
                                                                    dtype=torch.float64)
    prob = prepare_nnls(A, beta=0.5)

    def f(y):
        return prob.solve(y, solver="admm", admm_iters=25).x

    y = y0.clone().requires_grad_(True)
    assert f(y).requires_grad
    assert torch.autograd.gradcheck(f, (y,), eps=1e-6, atol=1e-6)
    # and through solve_nnls directly
    out = solve_nnls(A, y, beta=0.5, solver="admm", admm_iters=25).x.sum()
    (grad,) = torch.autograd.grad(out, y)
    assert torch.isfinite(grad).all() and grad.abs().sum() > 0


# ------------------------------------------------------------------------------------------------
# API and errors


def test_errors():
    A, y, mask = random_problem(10, seed=1)
    with pytest.raises(ValueError, match="y"):
        solve_nnls(A, y[:, :5])
    with pytest.raises(ValueError, match="pixels"):
        solve_nnls(A, y[:7])
    with pytest.raises(ValueError, match="mask"):
        solve_nnls(A, y, mask=torch.ones(10, 4, dtype=torch.bool))
    with pytest.raises(TypeError, match="float32 or float64"):
        solve_nnls(A.long(), y)
    with pytest.raises(ValueError, match="beta"):
        solve_nnls(A, y, beta=-1.0)
    with pytest.raises(ValueError, match="solver"):
        solve_nnls(A, y, solver="lbfgs")
    with pytest.raises(ValueError, match="diff_order"):
        solve_nnls(A, y, diff_order=3)
    with pytest.raises(ValueError, match="chunk_size"):
        solve_nnls(A, y, chunk_size=0)
    prob = prepare_nnls(A)
    with pytest.raises(ValueError, match="pixels"):
        prob.solve(y[:3])


# ------------------------------------------------------------------------------------------------
# per-frame fast path: conditioning, realistic spectra, threads, residual definition


def test_ill_conditioned_float64_no_spurious_fallback():
    """beta = 1 on the DN scale (cond(G) ~ 1e4–1e5): well-solved pixels count as converged,
    only pixels whose unconstrained solution is negative pivot, answers match SciPy."""
    A, y, mask, _ = synthetic_brf_problem(600, seed=21, dtype=torch.float64)
    G = prepare_nnls(A, mask=mask, beta=1.0).gram_matrices()
    ev = torch.linalg.eigvalsh(G)
    assert float((ev[:, -1] / ev[:, 0]).median()) > 1e3
    res = solve_nnls(A, y, beta=1.0, mask=mask)
    assert bool(res.converged.all())
    assert float(res.kkt_residual.max()) < 25 * torch.finfo(torch.float64).eps
    ref = scipy_reference(A, y, 1.0, mask)
    # exactly the pixels with a negative unconstrained solution needed the active set
    x_unc = torch.linalg.solve(G, prepare_nnls(A, mask=mask, beta=1.0).rhs(y, slice(None)))
    assert torch.equal(res.iterations > 0, (x_unc < -1e-9 * x_unc.abs().amax(1,
                                                                             keepdim=True)).any(1))
    assert rel_err(res.x, ref).max() < 1e-8
    assert kkt_violation(A, y, res.x, 1.0, mask).max() < 1e-10


def test_realistic_reflectance_spectra(dtype):
    """ColorChecker × D65 spectra: positive in every band, few pixels need the correction."""
    A, y, mask, xt = synthetic_brf_problem(600, spectra="reflectance", seed=4)
    assert bool((xt > 0).all())
    res = solve_nnls(A.to(dtype), y.to(dtype), beta=1e2, mask=mask)
    ref = scipy_reference(A, y, 1e2, mask)
    assert rel_err(res.x, ref).max() < (1e-8 if dtype == torch.float64 else 5e-4)
    Ah, yh, mh, _ = synthetic_brf_problem(600, seed=4)  # the hard (Gaussian-bump) spectra
    hard = solve_nnls(Ah, yh, beta=1e2, mask=mh)
    assert float((res.iterations > 0).double().mean()) < float(
        (hard.iterations > 0).double().mean())
    assert bool(res.converged.all())
    with pytest.raises(ValueError, match="spectra"):
        synthetic_brf_problem(5, spectra="flat")


def test_worker_threads_identical_and_restored():
    A, y, mask, _ = synthetic_brf_problem(5000, seed=6, dtype=torch.float32)
    n0 = torch.get_num_threads()
    prob = prepare_nnls(A, mask=mask, beta=1e2, num_threads=1)
    one = prob.solve(y, num_threads=1, chunk_size=512)
    two = prob.solve(y, num_threads=2, chunk_size=512)
    assert torch.get_num_threads() == n0
    assert torch.equal(one.x, two.x) and torch.equal(one.iterations, two.iterations)
    prob2 = prepare_nnls(A, mask=mask, beta=1e2, num_threads=2, chunk_size=512)
    assert torch.equal(prob2.gram_inv, prob.gram_inv)
    with pytest.raises(ValueError, match="num_threads"):
        prob.solve(y, num_threads=0)


def test_kkt_residual_is_a_backward_error():
    """The residual is ~eps at SciPy's answers, large for a wrong answer; ‖G‖₂ bound is below
    the largest eigenvalue."""
    from hsi_torch.recon.nnls import nnls_kkt_residual

    A, y, mask, _ = synthetic_brf_problem(300, seed=2)
    prob = prepare_nnls(A, mask=mask, beta=1.0)
    b = prob.rhs(y, slice(None))
    G = prob.gram_matrices()
    lam = torch.linalg.eigvalsh(G)[:, -1]
    assert bool((prob.gram_norm <= lam * (1 + 1e-12)).all())
    assert float((prob.gram_norm / lam).min()) > 0.5
    ref = scipy_reference(A, y, 1.0, mask)
    r = nnls_kkt_residual(G, b, ref)
    assert float(r.max()) < 1e-12
    bad = ref.clone()
    bad[:, 3] += 0.01 * ref.abs().amax(1)
    assert float(nnls_kkt_residual(G, b, bad).min()) > 1e-6


def test_small_beta_stacked_sweep_converges():
    """The experiments' sweep: stacked [A; √β D] with tiny β and beta = 0 in the solver."""
    A, y, mask, _ = synthetic_brf_problem(400, seed=9, shared=True, mask_fraction=0.0)
    D = difference_matrix(25, 1, dtype=torch.float64)
    a = torch.cat([A, 0.1 * D])  # beta = 0.01
    yy = torch.cat([y, torch.zeros(400, D.shape[0], dtype=torch.float64)], 1)
    res = solve_nnls(a, yy, beta=0.0)
    assert bool(res.converged.all())
    ref = scipy_reference(a, yy, 0.0)
    # same optimal objective as SciPy (cond is huge: compare objectives, not x)
    f_ours = (yy - res.x @ a.T).square().sum(1)
    f_ref = (yy - ref @ a.T).square().sum(1)
    assert float(((f_ours - f_ref) / f_ref).max()) < 1e-9
    assert kkt_violation(a, yy, res.x, 0.0).max() < 1e-9


# ------------------------------------------------------------------------------------------------
# dark pixels (most bands at zero) and the two kernels of the active-set correction


def dark_scene_problem(P, seed, dtype):
    """Camera-structured problem whose spectra are mostly noise (shadows): the unconstrained
    solution is negative in ~half the bands and the answer has 15–25 zeros."""
    A, y, mask, _ = synthetic_brf_problem(P, seed=seed, dtype=torch.float64, spectra="bumps",
                                          noise_dn=2.0, mask_fraction=0.05)
    g = torch.Generator().manual_seed(seed + 100)
    dark = torch.rand(P, generator=g, dtype=torch.float64) < 0.7
    A3 = A
    clean = torch.bmm(A3, (0.01 * torch.rand(P, 25, generator=g, dtype=torch.float64))
                      .unsqueeze(2)).squeeze(2)
    y = torch.where(dark.unsqueeze(1), clean + 2.0 * torch.randn(y.shape, generator=g,
                                                                 dtype=torch.float64), y)
    return A.to(dtype), y.to(dtype), mask


@pytest.mark.parametrize("backend", ["torch", "compiled"])
def test_dark_pixels_both_kernels_match_scipy_and_kkt(dtype, backend):
    from hsi_torch.recon.nnls import _compiled

    if backend == "compiled" and not _compiled.AVAILABLE:
        pytest.skip("numba not installed")
    A, y, mask = dark_scene_problem(1500, seed=5, dtype=dtype)
    beta = 1e2
    res = solve_nnls(A, y, beta=beta, mask=mask, backend=backend)
    zeros = (res.x == 0).sum(1)
    assert float((res.iterations > 0).float().mean()) > 0.5  # most pixels pivot
    assert int((zeros >= 15).sum()) > 300  # many with mostly zero bands (free-set solves)
    assert bool(res.converged.all())
    ref = scipy_reference(A, y, beta, mask)
    scale = ref.abs().amax().item()
    tol = 1e-9 if dtype == torch.float64 else 2e-4
    assert float((res.x.double() - ref).abs().max()) < tol * scale
    assert float(kkt_violation(A.double(), y.double(), res.x.double(), beta, mask).max()) < (
        1e-10 if dtype == torch.float64 else 1e-4)


def test_compiled_and_torch_kernels_agree(monkeypatch):
    """Same method, same exchange rules, same answers to rounding. The compiled kernel starts
    from the zero set of a few coordinate-descent sweeps (fewer rounds); started as the torch
    kernels start (the negative entries of x0) it takes the same rounds."""
    from hsi_torch.recon.nnls import _compiled

    if not _compiled.AVAILABLE:
        pytest.skip("numba not installed")
    A, y, mask = dark_scene_problem(2000, seed=8, dtype=torch.float64)
    prob = prepare_nnls(A, mask=mask, beta=10.0)
    a = prob.solve(y, backend="torch")
    b = prob.solve(y, backend="compiled")
    assert torch.equal(a.x == 0, b.x == 0)
    torch.testing.assert_close(a.x, b.x, rtol=1e-9, atol=1e-9 * float(a.x.abs().max()))
    piv = a.iterations > 0
    assert torch.equal(piv, b.iterations > 0)  # the same pixels pivot
    assert int(piv.sum()) > 1000
    assert float(b.iterations[piv].double().mean()) < 0.8 * float(a.iterations[piv].double().mean())
    monkeypatch.setattr(_compiled, "START_SWEEPS", 0)
    c = prob.solve(y, backend="compiled")
    assert torch.equal(a.iterations, c.iterations)
    assert torch.equal(a.x == 0, c.x == 0)
    torch.testing.assert_close(a.x, c.x, rtol=1e-9, atol=1e-9 * float(a.x.abs().max()))
    with pytest.raises(ValueError, match="backend"):
        prob.solve(y, backend="numba")


@pytest.mark.parametrize("channels", [3, 2])
def test_factored_model_compiled_pass_forms_rhs_itself(dtype, channels):
    """With the camera's factored ``A`` (per-pixel ``B`` and gains) the compiled pass forms
    ``b = Aᵀ W y`` itself (masked observations NaN, ignored): same answers and zero sets as the
    torch kernels, SciPy's answers, and the KKT conditions (RGB and a generic channel count)."""
    from hsi_torch.forward_model import SensingModel
    from hsi_torch.recon.nnls import _compiled

    if not _compiled.AVAILABLE:
        pytest.skip("numba not installed")
    g = torch.Generator().manual_seed(11 + channels)
    P, V, M = 1200, 10, 25
    B = 0.5 * (1 - torch.cos(2 * torch.pi * (1.5 + 4.5 * torch.rand(P, V, 1, generator=g,
                                                                   dtype=torch.float64))
                             / torch.linspace(0.43, 0.67, M, dtype=torch.float64)))
    gain = 0.7 + 0.4 * torch.rand(P, V, generator=g, dtype=torch.float64)
    resp = torch.rand(channels, M, generator=g, dtype=torch.float64) * 20
    model = SensingModel(B, gain, resp)
    A = model.dense()
    s = torch.rand(P, M, generator=g, dtype=torch.float64)
    dark = torch.rand(P, generator=g) < 0.6  # shadows: mostly noise, many bands at zero
    s = torch.where(dark.unsqueeze(1), 0.01 * s, s)
    y = torch.bmm(A, s.unsqueeze(2)).squeeze(2) + 0.5 * torch.randn(P, V * channels, generator=g,
                                                                     dtype=torch.float64)
    mask = torch.rand(P, V * channels, generator=g) > 0.05
    y = torch.where(mask, y, torch.full_like(y, float("nan")))
    beta = 10.0
    prob = prepare_nnls(model.to(dtype=dtype), mask=mask, beta=beta)
    a = prob.solve(y.to(dtype), backend="torch")
    b = prob.solve(y.to(dtype), backend="compiled")
    assert float((b.iterations > 0).float().mean()) > 0.4
    assert bool(b.converged.all()) and bool(a.converged.all())
    assert not bool(torch.isnan(b.x).any())
    if dtype == torch.float64:
        assert torch.equal(a.x == 0, b.x == 0)
    scale = float(a.x.abs().max())
    # float32: forward error up to cond(G)·eps, cond(G) up to 6e3 here (two channels): 4e-4
    tol = 1e-9 if dtype == torch.float64 else 5e-4
    assert float((a.x.double() - b.x.double()).abs().max()) < tol * scale
    ref = scipy_reference(A, torch.nan_to_num(y), beta, mask)
    assert float((b.x.double() - ref).abs().max()) < tol * float(ref.abs().max())
    assert float(kkt_violation(A, torch.nan_to_num(y), b.x.double(), beta, mask).max()) < (
        1e-10 if dtype == torch.float64 else 1e-4)


@pytest.mark.parametrize("masked", [True, False])
def test_compiled_factorisation_flags_non_finite_data(masked, monkeypatch):
    """A NaN or inf in a pixel's transmittance makes it singular on both paths (compiled and
    torch), with or without a mask (the compiled kernel's unmasked branch), and leaves every
    other pixel's flags, ``G`` and ``H`` as the torch path has them."""
    from hsi_torch.forward_model import SensingModel
    from hsi_torch.recon.nnls import _compiled

    if not _compiled.AVAILABLE:
        pytest.skip("numba not installed")
    g = torch.Generator().manual_seed(5)
    P, V, M = 12, 10, 25
    B = 0.2 + 0.8 * torch.rand(P, V, M, generator=g, dtype=torch.float64)
    B[1, 2, 5] = float("nan")  # a NaN pivot after the first row
    B[2, 0, 0] = float("nan")
    B[7, 4, 20] = float("inf")
    model = SensingModel(B, 0.7 + 0.4 * torch.rand(P, V, generator=g, dtype=torch.float64),
                         torch.rand(3, M, generator=g, dtype=torch.float64) * 20)
    mask = torch.ones(P, 3 * V, dtype=torch.bool) if masked else None
    fast = prepare_nnls(model, mask=mask, beta=1e2)
    monkeypatch.setattr(_compiled, "AVAILABLE", False)
    ref = prepare_nnls(model, mask=mask, beta=1e2)
    bad = torch.zeros(P, dtype=torch.bool)
    bad[[1, 2, 7]] = True
    assert torch.equal(fast.singular, bad) and torch.equal(ref.singular, bad)
    assert bool((fast.gram_inv[bad] == 0).all())
    ok = ~bad
    torch.testing.assert_close(fast.gram[ok], ref.gram[ok], rtol=1e-12, atol=1e-9)
    torch.testing.assert_close(fast.gram_inv[ok], ref.gram_inv[ok], rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("beta", [10.0, 0.0])
def test_compiled_factorisation_matches_torch(dtype, beta, monkeypatch):
    """``prepare_nnls`` of the camera's factored ``A`` on the CPU runs one compiled pass (float64
    arithmetic): the same ``G`` (to rounding, exactly symmetric), ``diag G``, ``‖G‖₂`` bound,
    singular and no-data flags, and ``H = G⁻¹`` to ``cond(G)·eps``, as the torch factorisation —
    for whole-view masks (the factored form), masks that split views, a pixel without data and,
    at beta = 0, pixels with fewer observations than bands (singular)."""
    from hsi_torch.forward_model import SensingModel
    from hsi_torch.recon.nnls import _compiled

    if not _compiled.AVAILABLE:
        pytest.skip("numba not installed")
    g = torch.Generator().manual_seed(21)
    P, V, M = 400, 10, 25
    B = 0.5 * (1 - torch.cos(2 * torch.pi * (1.5 + 4.5 * torch.rand(P, V, 1, generator=g,
                                                                   dtype=torch.float64))
                             / torch.linspace(0.43, 0.67, M, dtype=torch.float64)))
    gain = 0.7 + 0.4 * torch.rand(P, V, generator=g, dtype=torch.float64)
    resp = torch.rand(3, M, generator=g, dtype=torch.float64) * 20
    model = SensingModel(B, gain, resp).to(dtype=dtype)
    mask = torch.rand(P, 3 * V, generator=g) > 0.05  # split views
    whole = (torch.rand(P // 2, V, 1, generator=g) > 0.1).expand(-1, -1, 3)
    mask[: P // 2] = whole.reshape(-1, 3 * V)  # whole views
    mask[3] = False  # no data
    mask[4, 3 * 8:] = False  # 8 whole views: 24 observations < 25 bands (singular at beta = 0)
    mask[5] = False
    mask[5, :20] = True  # 6 whole views and two of the seventh's colours
    fast = prepare_nnls(model, mask=mask, beta=beta)
    monkeypatch.setattr(_compiled, "AVAILABLE", False)
    ref = prepare_nnls(model, mask=mask, beta=beta)
    eps = torch.finfo(dtype).eps
    assert torch.equal(fast.gram, fast.gram.transpose(1, 2))
    assert torch.equal(fast.gram_inv, fast.gram_inv.transpose(1, 2))
    torch.testing.assert_close(fast.gram, ref.gram, rtol=8 * eps, atol=8 * eps * float(
        ref.gram.abs().max()))
    torch.testing.assert_close(fast.gram_diag, ref.gram_diag, rtol=8 * eps, atol=0)
    torch.testing.assert_close(fast.gram_norm, ref.gram_norm, rtol=64 * eps, atol=0)
    assert torch.equal(fast.no_data, ref.no_data) and bool(fast.no_data[3])
    assert bool(fast.singular[3]) and (beta > 0 or bool(fast.singular[4] & fast.singular[5]))
    # the same singularity test on differently rounded pivots: only numerically singular pixels
    # (at beta = 0, fewer observations than bands or nearly so) may be flagged by one path only
    differ = fast.singular != ref.singular
    ev = torch.linalg.eigvalsh(fast.gram[differ].double())
    assert bool((ev[:, 0] < 2000 * M * eps * ev[:, -1]).all())
    assert int(differ.sum()) <= (0 if beta > 0 else 10)
    ok = ~fast.singular & ~ref.singular
    assert int(ok.sum()) > P // 2
    Gd = fast.gram[ok].double()
    cond = torch.linalg.cond(Gd)
    err = (fast.gram_inv[ok].double() - ref.gram_inv[ok].double()).abs().amax((1, 2))
    assert bool((err <= 50 * eps * cond * ref.gram_inv[ok].double().abs().amax((1, 2))).all())
    eye = torch.eye(M, dtype=torch.float64)
    resid = (torch.bmm(fast.gram_inv[ok].double(), Gd) - eye).abs().amax((1, 2))
    assert bool((resid <= 50 * eps * cond).all())
    assert bool((fast.gram_inv[fast.singular] == 0).all())


def test_solve_nnls_takes_the_problems_options_and_refuses_others():
    """``solve_nnls`` takes exactly :meth:`NNLSProblem.solve`'s options (one list of them)."""
    import inspect

    from hsi_torch.recon.nnls import NNLSProblem, SolveOptions

    params = inspect.signature(NNLSProblem.solve).parameters
    assert set(SolveOptions.__annotations__) == set(params) - {"self", "y"}
    A = torch.rand(4, 6, 3, dtype=torch.float64)
    y = torch.rand(4, 6, dtype=torch.float64)
    with pytest.raises(TypeError, match=r"\['method'\]"):
        solve_nnls(A, y, method="admm")
    res = solve_nnls(A, y, beta=0.1, solver="admm", admm_iters=5)
    assert res.solver == "admm" and res.x.shape == (4, 3)


def test_numba_helper_switch_and_threads():
    """One place for numba: ``HSI_TORCH_NO_NUMBA`` turns every compiled kernel off (both
    solvers fall back to torch), and the thread helpers set and read torch's and numba's
    per-thread counts."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    from hsi_torch.recon import _numba

    code = ("from hsi_torch.recon import _numba\n"
            "from hsi_torch.recon.nnls import _compiled as a\n"
            "from hsi_torch.recon.spatial import _compiled as b\n"
            "print(_numba.AVAILABLE, a.AVAILABLE, b.AVAILABLE, _numba.thread_counts()['numba'])")
    env = {**os.environ, "HSI_TORCH_NO_NUMBA": "1",
           "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         timeout=120, check=True)
    assert out.stdout.split() == ["False", "False", "False", "None"]
    n0 = torch.get_num_threads()
    try:
        _numba.set_threads(1)
        counts = _numba.thread_counts()
        assert counts["torch"] == 1
        assert counts["numba"] == (1 if _numba.AVAILABLE else None)
        _numba.set_threads(None)  # leaves both
        assert _numba.thread_counts() == counts
    finally:
        torch.set_num_threads(n0)


def test_a_requiring_grad_is_refused():
    """The factorisations are constants for autograd: a gradient with respect to A would see A only
    through AᵀWy (wrong), so an A that requires grad is refused while autograd is on."""
    g = torch.Generator().manual_seed(0)
    A = torch.rand(2, 6, 4, generator=g, dtype=torch.float64).requires_grad_(True)
    y = torch.rand(2, 6, generator=g, dtype=torch.float64)
    with pytest.raises(ValueError, match="A requires grad"):
        solve_nnls(A, y, beta=0.1, solver="admm", admm_iters=10)
    with pytest.raises(ValueError, match="A requires grad"):
        prepare_nnls(A[0], beta=0.1)
    from hsi_torch.forward_model import SensingModel

    model = SensingModel(torch.rand(2, 2, 4, dtype=torch.float64, requires_grad=True),
                         torch.ones(2, 2, dtype=torch.float64),
                         torch.rand(3, 4, dtype=torch.float64))  # fmt: skip
    with pytest.raises(ValueError, match="A requires grad"):
        solve_nnls(model, y, beta=0.1)
    # detached, or without autograd, it solves
    x = solve_nnls(A.detach(), y, beta=0.1, solver="admm", admm_iters=10).x
    with torch.no_grad():
        torch.testing.assert_close(solve_nnls(A, y, beta=0.1, solver="admm", admm_iters=10).x, x)


def test_a_mask_of_weights_is_refused():
    """mask is used / not used: float weights were read as True wherever they were non-zero (an
    unweighted solve in silence); 0/1 masks of any dtype still work."""
    A, y, mask = random_problem(10, seed=1, masked=True)
    w = mask.to(A.dtype) * 0.5
    with pytest.raises(TypeError, match="mask must be bool"):
        solve_nnls(A, y, beta=1.0, mask=w)
    with pytest.raises(TypeError, match="mask must be bool"):
        prepare_nnls(A, mask=w, beta=1.0)
    ref = solve_nnls(A, y, beta=1.0, mask=mask).x
    for m in (mask.to(A.dtype), mask.to(torch.uint8)):
        torch.testing.assert_close(solve_nnls(A, y, beta=1.0, mask=m).x, ref, rtol=0, atol=0)
