import math

import pytest
import torch
from torch.testing import assert_close

from hsi_torch.experiments.metrics import psnr, rmse, spectral_angle_deg


def test_psnr_known_value(device, dtype):
    t = torch.zeros(4, 25, device=device, dtype=dtype)
    e = t + 0.1  # MSE = 0.01 → 20 dB
    assert float(psnr(e, t)) == pytest.approx(20.0, abs=1e-4)
    per = psnr(e, t, dim=-1)
    assert per.shape == (4,)
    assert_close(per, torch.full((4,), 20.0, device=device, dtype=dtype), rtol=1e-4, atol=1e-4)
    assert float(rmse(e, t)) == pytest.approx(0.1, rel=1e-4)


def test_spectral_angle(device, dtype):
    a = torch.tensor([[1.0, 0.0], [1.0, 1.0], [2.0, 2.0]], device=device, dtype=dtype)
    b = torch.tensor([[0.0, 1.0], [1.0, 0.0], [1.0, 1.0]], device=device, dtype=dtype)
    assert_close(
        spectral_angle_deg(a, b),
        torch.tensor([90.0, 45.0, 0.0], device=device, dtype=dtype),
        atol=5e-2 if dtype == torch.float32 else 1e-4,
        rtol=0,
    )
    # scale invariance
    assert math.isclose(float(spectral_angle_deg(3 * a[1], b[1])), 45.0, abs_tol=1e-3)


def test_shape_mismatch():
    with pytest.raises(ValueError, match="shape"):
        psnr(torch.zeros(3), torch.zeros(4))


# --------------------------------------------------------------- the field's metrics (public) --

import numpy as np  # noqa: E402

from hsi_torch import metrics as hm  # noqa: E402


def _pair(device, dtype, shape=(6, 32, 28), seed=0):
    g = torch.Generator().manual_seed(seed)
    t = torch.rand(shape, generator=g, dtype=torch.float64) * 0.8 + 0.1
    e = (t + 0.05 * torch.randn(shape, generator=g, dtype=torch.float64)).clamp(0, 1)
    return e.to(device=device, dtype=dtype), t.to(device=device, dtype=dtype)


def test_old_import_path_is_the_public_one():
    from hsi_torch.experiments import metrics as old

    assert old.psnr is hm.psnr and old.spectral_angle_deg is hm.spectral_angle_deg
    assert old.rmse is hm.rmse and old.cube_metrics is hm.cube_metrics


def test_ssim_matches_kornia(device, dtype):
    kornia = pytest.importorskip("kornia")
    e, t = _pair(device, dtype)
    ours = hm.ssim(e, t, per_band=True)
    theirs = kornia.metrics.ssim(e[:, None], t[:, None], 11, max_val=1.0, padding="valid")
    assert_close(ours, theirs.mean((1, 2, 3)), rtol=1e-4, atol=1e-4 if dtype == torch.float32
                 else 1e-10)  # fmt: skip


def test_ssim_matches_skimage():
    skm = pytest.importorskip("skimage.metrics")
    e, t = _pair("cpu", torch.float64, seed=1)
    ref = np.mean([skm.structural_similarity(
        t[b].numpy(), e[b].numpy(), data_range=1.0, gaussian_weights=True, sigma=1.5,
        use_sample_covariance=False) for b in range(e.shape[0])])  # fmt: skip
    assert float(hm.ssim(e, t)) == pytest.approx(ref, abs=1e-8)
    assert float(hm.ssim(t, t)) == pytest.approx(1.0, abs=1e-12)


def _ssim_full_frame(e, t, m, window=11, sigma=1.5):
    """The SSIM of ``ssim`` computed the direct way: the whole frame filtered with ``conv2d``,
    the map averaged over the windows wholly inside the mask."""
    import torch.nn.functional as F

    x = torch.arange(window, dtype=e.dtype) - (window - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    g = g / g.sum()

    def blur(z):
        return F.conv2d(F.conv2d(z, g.view(1, 1, 1, -1)), g.view(1, 1, -1, 1))

    x, y = torch.where(m, e, 0.0)[:, None], torch.where(m, t, 0.0)[:, None]
    inside = blur(m[None, None].to(e.dtype) * 1.0) > 1 - 1e-9  # a normalised box would do
    mx, my = blur(x), blur(y)
    sxx, syy, sxy = blur(x * x) - mx**2, blur(y * y) - my**2, blur(x * y) - mx * my
    c1, c2 = 0.01**2, 0.03**2
    smap = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx**2 + my**2 + c1) * (sxx + syy + c2))
    return (smap[:, 0] * inside[0, 0]).sum((1, 2)) / inside.sum()


def test_ssim_in_a_mask_is_the_full_frame_computation():
    """The CPU path (OpenCV's separable filter, only the rows and columns the mask's windows
    cover) gives the direct full-frame ``conv2d`` computation's numbers."""
    e, t = _pair("cpu", torch.float64, shape=(5, 60, 70), seed=4)
    m = torch.zeros(60, 70, dtype=torch.bool)
    m[7:40, 12:50] = True
    m[45:58, 3:30] = True
    m[20, 30] = False  # a hole: the windows over it do not count
    want = _ssim_full_frame(e, t, m)
    assert_close(hm.ssim(e, t, m, per_band=True), want, rtol=0, atol=1e-12)
    # float32 too, and the whole frame
    assert_close(hm.ssim(e.float(), t.float(), m, per_band=True), want.float(), rtol=0,
                 atol=1e-5)
    full = torch.ones(60, 70, dtype=torch.bool)
    assert_close(hm.ssim(e, t, per_band=True), _ssim_full_frame(e, t, full), rtol=0, atol=1e-12)


def test_ssim_keeps_its_gradient_on_the_cpu():
    """SSIM as a loss: with a tensor that needs a gradient the CPU computation stays in torch
    (differentiable, same value as without one), and the gradient matches finite differences."""
    e, t = _pair("cpu", torch.float64, shape=(2, 20, 22), seed=7)
    m = torch.ones(20, 22, dtype=torch.bool)
    x = e.clone().requires_grad_(True)
    val = hm.ssim(x, t, m)
    assert val.requires_grad
    assert_close(val.detach(), hm.ssim(e, t, m), rtol=0, atol=1e-12)
    (grad,) = torch.autograd.grad(val, x)
    d = torch.zeros_like(e)
    d[1, 9, 11] = 1e-6
    fd = (hm.ssim(e + d, t, m) - hm.ssim(e - d, t, m)) / 2e-6
    assert float(fd) == pytest.approx(float(grad[1, 9, 11]), rel=1e-4, abs=1e-9)
    assert float(grad.abs().sum()) > 0


def test_metrics_match_torchmetrics():
    tmf = pytest.importorskip("torchmetrics.functional.image")
    e, t = _pair("cpu", torch.float64, seed=2)
    ergas_ref = tmf.error_relative_global_dimensionless_synthesis(e[None], t[None], ratio=1)
    assert float(hm.ergas(e, t)) == pytest.approx(float(ergas_ref), rel=1e-10)
    assert float(hm.ergas(e, t, ratio=4)) == pytest.approx(
        float(tmf.error_relative_global_dimensionless_synthesis(e[None], t[None], ratio=4)),
        rel=1e-10)  # fmt: skip
    sam_ref = tmf.spectral_angle_mapper(e[None], t[None])  # radians, mean over pixels
    assert float(hm.sam(e, t)) == pytest.approx(math.degrees(float(sam_ref)), rel=1e-8)
    # torchmetrics' SSIM handles the border slightly differently (skimage and kornia agree with
    # ours to 1e-8 above): same value to 1e-3
    ssim_ref = tmf.structural_similarity_index_measure(e[:, None], t[:, None], data_range=1.0)
    assert float(hm.ssim(e, t)) == pytest.approx(float(ssim_ref), abs=1e-3)


def test_psnr_both_conventions(device, dtype):
    e, t = _pair(device, dtype, seed=3)
    # whole cube, peak 1
    whole = 10 * math.log10(1 / float(((e - t) ** 2).mean()))
    assert float(hm.psnr(e, t)) == pytest.approx(whole, abs=1e-3)
    # per band on 0-255, mean of the bands' dB: an independent per-band loop (skimage when there)
    e8, t8 = e.double().cpu().numpy() * 255, t.double().cpu().numpy() * 255
    per = [10 * math.log10(255**2 / np.mean((e8[b] - t8[b]) ** 2)) for b in range(len(e8))]
    assert float(hm.psnr_bands(e, t)) == pytest.approx(np.mean(per), abs=1e-3)
    try:
        from skimage.metrics import peak_signal_noise_ratio
    except ImportError:
        return
    sk = np.mean([peak_signal_noise_ratio(t8[b], e8[b], data_range=255) for b in range(len(e8))])
    assert float(hm.psnr_bands(e, t)) == pytest.approx(sk, abs=1e-3)
    # the two conventions differ when the error is uneven over the bands
    e2 = t.clone()
    e2[0] += 0.1
    e2[1:] += 0.001
    assert float(hm.psnr_bands(e2, t)) > float(hm.psnr(e2, t)) + 10


def test_rmse_mrae_known_values(device, dtype):
    t = torch.full((3, 12, 12), 0.5, device=device, dtype=dtype)
    e = t * 1.1  # relative error 10 %, absolute 0.05
    assert float(hm.mrae(e, t)) == pytest.approx(0.1, rel=1e-5)
    assert float(hm.rmse(e, t)) == pytest.approx(0.05, rel=1e-5)
    assert float(hm.ergas(e, t)) == pytest.approx(10.0, rel=1e-5)  # 100·sqrt(mean(0.05/0.5)²)
    t2 = t.clone()
    t2[:, 0, 0] = 0  # black truth: left out of the MRAE, not infinite
    e2 = t2 * 1.1
    e2[:, 0, 0] = 0.3
    assert float(hm.mrae(e2, t2)) == pytest.approx(0.1, rel=1e-5)


def test_mask_and_nan_outside_it(device, dtype):
    e, t = _pair(device, dtype, seed=4)
    mask = torch.zeros(e.shape[1:], dtype=torch.bool, device=device)
    mask[4:26, 3:25] = True
    e_nan = e.clone()
    e_nan[:, ~mask] = float("nan")
    got = hm.cube_metrics(e_nan, t, mask)
    sub_e, sub_t = e[:, 4:26, 3:25], t[:, 4:26, 3:25]
    want = hm.cube_metrics(sub_e, sub_t)
    for k in hm.METRIC_NAMES:
        assert got[k] == pytest.approx(want[k], rel=1e-4, abs=1e-6), k
    assert set(got) == set(hm.METRIC_NAMES)
    # pixels outside the mask change nothing, a pixel inside does
    e_bad = e.clone()
    e_bad[:, 0, 0] = 5.0
    assert hm.cube_metrics(e_bad, t, mask)["psnr_db"] == pytest.approx(got["psnr_db"], rel=1e-5)
    e_bad[:, 10, 10] = 5.0
    assert hm.cube_metrics(e_bad, t, mask)["psnr_db"] < got["psnr_db"] - 1


def test_metric_errors_name_the_problem():
    e = torch.zeros(4, 8, 8)
    with pytest.raises(ValueError, match="smaller than the 11x11 window"):
        hm.ssim(e, e)
    with pytest.raises(ValueError, match="mask shape"):
        hm.sam(e, e, torch.ones(3, 3, dtype=torch.bool))
    with pytest.raises(ValueError, match="no pixel"):
        hm.sam(e, e, torch.zeros(8, 8, dtype=torch.bool))
    assert math.isnan(hm.cube_metrics(e + 0.5, e + 0.5)["ssim"])  # no window: NaN, not an error


# ------------------------------------------------- gradients where the estimate is the truth --

#: every differentiable metric as a scalar loss of an (M, h, w) estimate and truth
_LOSSES = {
    "mse": lambda e, t: hm.mse(e, t),
    "rmse": lambda e, t: hm.rmse(e, t),
    "rmse per spectrum": lambda e, t: hm.rmse(e, t, dim=0).mean(),
    "psnr": lambda e, t: hm.psnr(e, t),
    "psnr per spectrum": lambda e, t: hm.psnr(e, t, dim=0).mean(),
    "psnr_bands": lambda e, t: hm.psnr_bands(e, t),
    "spectral_angle_deg": lambda e, t: hm.spectral_angle_deg(e.permute(1, 2, 0),
                                                             t.permute(1, 2, 0)).mean(),
    "sam": lambda e, t: hm.sam(e, t),
    "ergas": lambda e, t: hm.ergas(e, t),
    "mrae": lambda e, t: hm.mrae(e, t),
    "ssim": lambda e, t: hm.ssim(e, t),
}


def _old_values(e, t):
    """The metrics by their formulas before the gradients were made finite (values to match)."""
    m = (e - t).square().mean()
    m_px = (e - t).square().mean(0)
    cos = (e * t).sum(0) / (e.norm(dim=0) * t.norm(dim=0)).clamp_min(1e-12)
    pe, pt = e.flatten(1).T, t.flatten(1).T
    eb, tb = pe.clamp(0, 1) * 255, pt.clamp(0, 1) * 255
    rmse_b = (pe - pt).square().mean(0).sqrt()
    return {
        "rmse": m.sqrt(),
        "rmse per spectrum": m_px.sqrt(),
        "psnr": 10.0 * torch.log10(torch.as_tensor(1.0, dtype=m.dtype) ** 2 / m),
        "psnr per spectrum": 10.0 * torch.log10(torch.as_tensor(1.0, dtype=m.dtype) ** 2 / m_px),
        "psnr_bands": (10.0 * torch.log10(255.0**2 / (eb - tb).square().mean(0))).mean(),
        "spectral_angle_deg": torch.rad2deg(torch.arccos(cos.clamp(-1.0, 1.0))),
        "ergas": 100.0 * ((rmse_b / pt.mean(0)).square().mean()).sqrt(),
    }


def _new_values(e, t):
    return {
        "rmse": hm.rmse(e, t),
        "rmse per spectrum": hm.rmse(e, t, dim=0),
        "psnr": hm.psnr(e, t),
        "psnr per spectrum": hm.psnr(e, t, dim=0),
        "psnr_bands": hm.psnr_bands(e, t),
        "spectral_angle_deg": hm.spectral_angle_deg(e.permute(1, 2, 0), t.permute(1, 2, 0)),
        "ergas": hm.ergas(e, t),
    }


def _half_equal(dtype):
    """A truth ``(4, 12, 12)``, an estimate equal to it in the left half of the pixels (one
    of them a black spectrum, 0 in both), and a black truth pixel."""
    _, t = _pair("cpu", dtype, shape=(4, 12, 12), seed=11)
    e = t.clone()
    e[..., 6:] += 0.01 * torch.randn(4, 12, 6, generator=torch.Generator().manual_seed(1),
                                     dtype=torch.float64).to(dtype)
    e[:, 3, 2] = 0.0
    t[:, 3, 2] = 0.0
    return e, t


def test_metric_gradients_are_finite_where_the_estimate_equals_the_truth(dtype):
    """Each metric as a loss: at an estimate equal to the truth, and where half the pixels are
    (perfect pixels in a batch), the gradient with respect to the estimate and to the truth is
    finite everywhere (it was NaN: sqrt and log of a zero MSE, arccos of a cosine of 1); at
    equality it is 0 for RMSE, PSNR, ERGAS and the angle (their minimum)."""
    e_half, t_half = _half_equal(dtype)
    for name, loss in _LOSSES.items():
        for e0, t0 in ((t_half.clone(), t_half), (e_half, t_half)):
            e = e0.clone().requires_grad_(True)
            t = t0.clone().requires_grad_(True)
            ge, gt = torch.autograd.grad(loss(e, t), (e, t))
            assert bool(torch.isfinite(ge).all()) and bool(torch.isfinite(gt).all()), name
        e = t_half.clone().requires_grad_(True)
        (ge,) = torch.autograd.grad(loss(e, t_half), e)
        if name in ("rmse", "rmse per spectrum", "psnr", "psnr per spectrum", "psnr_bands",
                    "ergas", "mse", "mrae"):
            assert bool((ge == 0).all()), name
        if name in ("sam", "spectral_angle_deg"):  # rounding: cos = 1 − ulp in a few pixels
            assert float(ge.abs().max()) < (1e-4 if dtype == torch.float64 else 1.0), name


def test_metric_values_are_unchanged_by_the_finite_gradients(dtype):
    """The finite gradients change no value: bit for bit the former formulas', with and without
    autograd, at equality (0, +inf dB) and away from it."""
    e_half, t_half = _half_equal(dtype)
    for e, t in ((e_half, t_half), (t_half.clone(), t_half)):
        old = _old_values(e, t)
        for grad in (False, True):
            x = e.clone().requires_grad_(grad)
            new = _new_values(x, t)
            for name, ref in old.items():
                assert torch.equal(new[name].detach(), ref), name
    assert float(hm.psnr(t_half, t_half)) == math.inf and float(hm.rmse(t_half, t_half)) == 0


def test_metric_gradients_near_equality_match_finite_differences():
    """float64, an estimate 1e-3 from the truth (no element closer than 5e-4, so |e − t| and the
    clip of psnr_bands are smooth there): ``torch.autograd.gradcheck`` of every metric. The
    angle is ``arccos`` of a cosine near 1, whose value carries ~1e-16/θ of rounding (θ ≈ 1e-3
    rad here): its central differences are good to ~1e-5 (the gradient is ~1), hence its atol."""
    g = torch.Generator().manual_seed(5)
    _, t = _pair("cpu", torch.float64, shape=(2, 11, 12), seed=13)
    step = 1e-3 * (0.5 + 0.5 * torch.rand(t.shape, generator=g, dtype=torch.float64))
    sign = torch.where(torch.rand(t.shape, generator=g) < 0.5, -1.0, 1.0).to(torch.float64)
    e = (t + sign * step).requires_grad_(True)
    for name, loss in _LOSSES.items():
        atol = 5e-5 if name in ("sam", "spectral_angle_deg") else 1e-6
        assert torch.autograd.gradcheck(lambda x, f=loss: f(x, t), (e,), eps=1e-6, atol=atol,
                                        rtol=1e-4), name
