"""Per-pixel uncertainty of the NNLS reconstruction (hsi_torch.recon.uncertainty).

The formula is checked against an independent numerical derivative of the solver (central finite
differences of ``solve_nnls`` in ``y``, propagated as ``J Σ_y Jᵀ``) and a NumPy closed form; the
sampling factor against the empirical variance of demosaiced, bilinearly sampled noise; and the
whole chain (sensor noise → demosaic → warp → solve → std) by Monte-Carlo coverage on the tiny
4-view bundle of ``test_pipeline`` with sub-pixel homographies: many independent noise
realisations of one flat scene, each reconstructed by the pipeline, and the fraction of
``|ŝ − mean(ŝ)| ≤ kσ`` compared with 68.3 % / 95.4 % on the bands that are free in every
realisation.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from test_pipeline import WL, _tilted, make_bundle, render_capture, true_spectra

from hsi_torch.cli import main
from hsi_torch.config import load_config
from hsi_torch.io import load_cube, write_capture
from hsi_torch.io.raw import bayer_half, demosaic_bilinear, mosaic
from hsi_torch.optics.sensor import SensorModel
from hsi_torch.recon.batch.run import output_paths
from hsi_torch.recon.config import ReconstructConfig
from hsi_torch.recon.nnls import prepare_nnls, smoothness_gram, solve_nnls
from hsi_torch.recon.pipeline import Reconstructor
from hsi_torch.recon.uncertainty import (
    DEFAULT_ELECTRONS_PER_DN,
    DEFAULT_READ_NOISE_E,
    SensorNoise,
    demosaic_tap_covariance,
    nnls_band_std,
    observation_variance,
    relative_std_map,
    sampling_variance_factor,
)


def _problem(P: int = 8, O: int = 12, M: int = 6, seed: int = 0):
    """Random per-pixel problems whose unconstrained solution has negative bands (so the NNLS
    solutions have bound bands), a mask with holes, and random observation variances."""
    g = torch.Generator().manual_seed(seed)
    A = torch.rand(P, O, M, generator=g, dtype=torch.float64) + 0.1
    s = torch.rand(P, M, generator=g, dtype=torch.float64)
    s[:, 2] = -0.6  # pushes band 2 (and sometimes a neighbour) to the bound
    y = torch.einsum("pom,pm->po", A, s) + 0.02 * torch.randn(P, O, generator=g,
                                                               dtype=torch.float64)
    mask = torch.rand(P, O, generator=g) > 0.15
    var = 0.5 + torch.rand(P, O, generator=g, dtype=torch.float64)
    return A, y, mask, var


def test_defaults_are_the_simulator_sensor():
    s = SensorModel()
    assert DEFAULT_ELECTRONS_PER_DN == pytest.approx(s.gain_e_per_dn, rel=1e-12)
    assert DEFAULT_READ_NOISE_E == s.read_noise_e
    with pytest.raises(ValueError, match="electrons_per_dn"):
        SensorNoise(electrons_per_dn=0.0)
    with pytest.raises(ValueError, match="read_noise_e"):
        SensorNoise(read_noise_e=-1.0)


@pytest.mark.parametrize("beta", [0.0, 0.3])
def test_std_matches_finite_differences_of_the_solver(beta, device, dtype):
    A, y, mask, var = _problem()
    M = A.shape[2]
    res = solve_nnls(A, y, mask=mask, beta=beta)
    x = res.x
    free = x > 0
    assert bool((~free).any()) and bool(free.any())  # both kinds of band are exercised
    # independent reference: the solver's Jacobian in y by central differences, J Σ Jᵀ
    h = 1e-6
    J = torch.zeros(A.shape[0], M, A.shape[1], dtype=torch.float64)
    for o in range(A.shape[1]):
        e = torch.zeros_like(y)
        e[:, o] = h
        xp = solve_nnls(A, y + e, mask=mask, beta=beta).x
        xm = solve_nnls(A, y - e, mask=mask, beta=beta).x
        J[:, :, o] = (xp - xm) / (2 * h)
    J = J * mask.unsqueeze(1)  # masked observations do not reach the solution
    ref = torch.einsum("pmo,po,pmo->pm", J, var, J).sqrt()
    reg = smoothness_gram(M, beta, 1, dtype=torch.float64)
    std = nnls_band_std(A.to(device, dtype), x.to(device, dtype), var.to(device, dtype),
                        mask.to(device), reg.to(device, dtype))  # fmt: skip
    assert std.dtype == dtype and std.device.type == device.type
    tol = 1e-6 if dtype == torch.float64 else 1e-4
    torch.testing.assert_close(std.cpu().double(), ref, rtol=tol, atol=tol)
    assert bool((std.cpu()[~free] == 0).all())
    # NumPy closed form on one pixel: G_FF⁻¹ A_Fᵀ W Σ W A_F G_FF⁻¹
    p = 0
    F = free[p].numpy()
    a = A[p].numpy()[mask[p].numpy()][:, F]
    G = a.T @ a + reg.numpy()[np.ix_(F, F)]
    Gi = np.linalg.inv(G)
    cov = Gi @ (a.T * var[p].numpy()[mask[p].numpy()]) @ a @ Gi
    np.testing.assert_allclose(std.cpu().double()[p, torch.from_numpy(F)].numpy(),
                               np.sqrt(np.diag(cov)), rtol=tol)  # fmt: skip


def test_stored_inverse_path_equals_the_factorisation(device, dtype):
    """With ``problem=`` the all-free pixels with the problem's mask reuse its stored G⁻¹; the
    others (bound bands, another mask) are factorised: same numbers either way."""
    A, y, mask, var = _problem(P=40, seed=5)
    A, y, var = (t.to(device, dtype) for t in (A, y, var))
    mask = mask.to(device)
    prob = prepare_nnls(A, mask=mask, beta=0.3)
    x = prob.solve(torch.where(mask, y, 0)).x
    allfree = (x > 0).all(1)
    assert bool(allfree.any()) and bool((~allfree).any())
    frame = mask.clone()
    frame[:5, 0] = ~frame[:5, 0]  # a frame mask that differs from the problem's on 5 pixels
    a = nnls_band_std(A, x, var, frame, problem=prob)
    b = nnls_band_std(A, x, var, frame, prob.reg)
    tol = 1e-9 if dtype == torch.float64 else 2e-4
    torch.testing.assert_close(a, b, rtol=tol, atol=tol)


def test_unit_weight_unregularised_case_is_sigma2_diag_of_inverse_gram():
    g = torch.Generator().manual_seed(3)
    A = torch.rand(5, 9, 4, generator=g, dtype=torch.float64)
    x = torch.rand(5, 4, generator=g, dtype=torch.float64) + 0.1  # all bands free
    sigma2 = 2.5
    std = nnls_band_std(A, x, torch.full((5, 9), sigma2, dtype=torch.float64))
    ref = (sigma2 * torch.linalg.inv(A.transpose(1, 2) @ A).diagonal(dim1=1, dim2=2)).sqrt()
    torch.testing.assert_close(std, ref)


def test_singular_free_set_is_infinite_and_masked_variance_is_ignored():
    A = torch.ones(2, 3, 2, dtype=torch.float64)  # two identical columns: G singular, beta = 0
    x = torch.tensor([[1.0, 1.0], [1.0, 0.0]], dtype=torch.float64)
    var = torch.ones(2, 3, dtype=torch.float64)
    mask = torch.tensor([[True, True, False], [True, True, False]])
    var[:, 2] = float("nan")  # masked: must not leak into the result
    std = nnls_band_std(A, x, var, mask)
    assert bool(torch.isinf(std[0]).all())  # both free, not determined
    assert std[1, 0] == pytest.approx(math.sqrt(1 / 2)) and std[1, 1] == 0


def test_observation_variance_of_the_sensor_model(device, dtype):
    """Empirical variance of SensorModel raw samples = the formula (shot + read + quantisation),
    with the exposure ratio applied afterwards."""
    g, r = 1.7, 4.0
    sensor = SensorModel(output="rgb", input_units="electrons", electrons_per_dn=g,
                         full_well_e=None, read_noise_e=r, black_level=64.0, bit_depth=16,
                         quantize=True, seed=1)  # fmt: skip
    mu_dn = torch.tensor([0.0, 3.0, 40.0, 900.0], dtype=torch.float64)
    e = (mu_dn * g).view(1, 4, 1).expand(3, 4, 20000).to(device)
    dn = sensor.expose(e.unsqueeze(0)).dn[0] - 64.0  # (3, 4, 20000), DN above black
    emp = dn.double().var(dim=(0, 2)).cpu()
    k = 0.5  # exposure ratio applied to the observations
    pred = observation_variance((mu_dn * k).to(device, dtype), SensorNoise(g, r), scale=k)
    torch.testing.assert_close(pred.cpu().double() / k**2, emp, rtol=0.04, atol=0.02)


@pytest.mark.parametrize("layout", ["rgb", "bayer", "half"])
def test_sampling_factor_matches_the_variance_of_sampled_noise(layout):
    """White noise of unit variance through the pipeline's own demosaic/binning and a bilinear
    sample at random sub-pixel positions: its variance is the predicted factor."""
    H = W = 24
    gen = torch.Generator().manual_seed(0)
    K = 4000
    raw = torch.randn(K, 1, 2 * H if layout == "half" else H, 2 * W if layout == "half" else W,
                      generator=gen, dtype=torch.float64)  # fmt: skip
    if layout == "rgb":
        img = torch.randn(K, 3, H, W, generator=gen, dtype=torch.float64)
    elif layout == "bayer":
        img = demosaic_bilinear(raw, "GRBG")
    else:
        img = bayer_half(raw, "GRBG")
    pos = torch.rand(1, 2, 7, 2, generator=gen, dtype=torch.float64) * 0.6 - 0.3  # (1, V, P, 2)
    f = sampling_variance_factor(pos, (H, W), layout, "GRBG")  # (P, 3V)
    samples = torch.nn.functional.grid_sample(
        img, pos.expand(K, -1, -1, -1), mode="bilinear", align_corners=True
    )  # (K, 3, V, P)
    emp = samples.var(0).permute(2, 1, 0).reshape(7, 6)  # (P, 3V), o = 3v + c
    torch.testing.assert_close(f, emp, rtol=0.08, atol=0.0)
    if layout == "bayer":  # the factor is far from 1: leaving it out would be wrong
        assert float(f.min()) < 0.5


def test_demosaic_tap_covariance_is_symmetric_psd():
    K = demosaic_tap_covariance("RGGB")
    torch.testing.assert_close(K, K.transpose(-1, -2))
    assert float(torch.linalg.eigvalsh(K).min()) > -1e-12
    assert K[0, 0, 0, 0] == 1.0  # R at an R site: the raw sample itself
    assert K[0, 0, 3, 3] == pytest.approx(0.25)  # R at a B site: mean of four R samples


def test_relative_std_map():
    cube = torch.tensor([[[1.0, 0.0]], [[3.0, 0.0]]])  # (M=2, h=1, w=2)
    std = torch.tensor([[[0.1, 0.0]], [[0.3, 0.0]]])
    rel = relative_std_map(cube, std, torch.tensor([[True, True]]))
    assert rel[0, 0] == pytest.approx(0.1) and torch.isnan(rel[0, 1])


# ------------------------------------------------------------------ Monte-Carlo coverage
def _flat_scene(t: int) -> torch.Tensor:
    M = WL.size
    lam = torch.linspace(0, 1, M, dtype=torch.float64)
    spec = 0.6 * torch.exp(-0.5 * ((lam - 0.4) / 0.25) ** 2) + 0.05
    return spec.view(M, 1, 1).expand(M, t, t).clone()


@pytest.mark.parametrize("layout", ["rgb", "bayer"])
def test_monte_carlo_coverage(layout, device, dtype):
    """±1σ / ±2σ hold 68.3 % / 95.4 % of the spread over independent noise realisations."""
    t, N, g, r = 16, 100, 1.5, 3.0
    bundle = _tilted(make_bundle(t=t, missing=2, cfa_pattern="RGGB"))
    img = render_capture(bundle, _flat_scene(t))  # noise-free DN
    sensor = SensorModel(output=layout, input_units="electrons", electrons_per_dn=g,
                         full_well_e=None, read_noise_e=r, black_level=0.0, bit_depth=16,
                         quantize=True, seed=7)  # fmt: skip
    x = mosaic(img, "RGGB") if layout == "bayer" else img
    dn = sensor.expose((x * g).unsqueeze(0).expand(N, *x.shape).contiguous()).dn
    rec = Reconstructor(bundle, beta=1e4, device=device, dtype=dtype, uncertainty=True,
                        noise_electrons_per_dn=g, noise_read_e=r)  # fmt: skip
    cubes, stds = [], []
    for i in range(N):  # independent captures of the same scene
        res = rec.reconstruct_frame(dn[i].to(device, dtype))
        cubes.append(res.cube[:, res.valid])
        stds.append(res.std[:, res.valid])
    c = torch.stack(cubes).double().cpu()  # (N, M, P)
    sd = torch.stack(stds).double().cpu()
    free = (c > 0).all(0)  # bands free in every realisation (linearisation holds)
    assert int(free.sum()) > 0.8 * free.numel()
    assert bool((sd[(c == 0)] == 0).all())  # bound bands report 0
    # the spread around the sample mean of N draws is sqrt((N-1)/N) of the spread around the
    # true mean: corrected, so that the ideal coverage is 68.3 % / 95.4 % for any N
    z = ((c - c.mean(0)).abs() / (sd * math.sqrt((N - 1) / N)))[:, free]
    cover1, cover2 = float((z <= 1).double().mean()), float((z <= 2).double().mean())
    assert abs(cover1 - 0.6827) < 0.03, cover1
    assert abs(cover2 - 0.9545) < 0.02, cover2
    ratio = c.std(0)[free] / sd.mean(0)[free]  # empirical / predicted spread per band
    assert 0.95 < float(ratio.median()) < 1.05


def test_exposure_ratio_scales_the_std():
    """A capture taken with twice the white reference's exposure is scaled by k = 1/2: its
    spectra and their standard deviations are half those of the same DN at k = 1."""
    bundle = make_bundle(white_exposure_s=0.01)
    img = render_capture(bundle, true_spectra()).float() + 20.0
    rec = Reconstructor(bundle, beta=1e4, uncertainty=True)
    r1 = rec.reconstruct_frame(img, exposure_s=0.01)
    r2 = rec.reconstruct_frame(img, exposure_s=0.02)
    assert r1.stats["exposure_scale"] == 1.0 and r2.stats["exposure_scale"] == 0.5
    torch.testing.assert_close(r2.std, 0.5 * r1.std, equal_nan=True)
    assert "uncertainty" in r1.timings
    assert Reconstructor(bundle, beta=1e4).reconstruct_frame(img).std is None


def test_reconstruct_cli_writes_the_std(tmp_path):
    bundle = make_bundle(white_exposure_s=0.01)
    bpath = tmp_path / "calib.npz"
    bundle.save(bpath)
    img = np.round(render_capture(bundle, true_spectra()).numpy() + 30).astype(np.uint16)
    write_capture(tmp_path / "c.tif", img, {"kind": "rgb", "exposure_s": 0.02})
    out = tmp_path / "out"
    code = main(["reconstruct", "--bundle", str(bpath), "--out", str(out), "--no-progress",
                 "--set", "uncertainty=true", "--set", "noise_read_e=5", "--set",
                 "formats=[npz, tiff, envi]", str(tmp_path / "c.tif")])  # fmt: skip
    assert code == 0
    written = {p.name for p in out.iterdir() if p.is_file()}
    expected = {p.name for p in output_paths(out / "c", load_config({"uncertainty": True},
                                                                    ReconstructConfig))}
    assert expected <= written
    assert {"c_std.tif", "c_std.vrt", "c_std.hdr", "c_std.img", "c_std.png"} <= written
    with np.load(out / "c.npz") as z:
        std = torch.from_numpy(z["std"])
    cube = load_cube(out / "c.npz")
    assert std.shape == cube.cube.shape and std.dtype == torch.float32
    assert bool(torch.isnan(std[:, ~cube.valid]).all())
    # the same numbers as the Python API with the same settings
    rec = Reconstructor(bpath, uncertainty=True, noise_read_e=5.0)
    ref = rec.reconstruct_file(tmp_path / "c.tif").std
    torch.testing.assert_close(std, ref.float(), equal_nan=True)
    assert bool((std[:, cube.valid] >= 0).all()) and bool((std[:, cube.valid] > 0).any())
    torch.testing.assert_close(load_cube(out / "c_std.tif").cube, std, equal_nan=True)
    torch.testing.assert_close(load_cube(out / "c_std.hdr").cube, std, equal_nan=True)
