"""The spatial-spectral option through the pipeline, the nn.Module and the command line, on the
tiny 4-view bundle of test_pipeline (exact forward model)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from test_pipeline import make_bundle, render_capture

from hsi_torch.cli import main
from hsi_torch.recon.config import ReconstructConfig
from hsi_torch.recon.module import HSIReconstructor
from hsi_torch.recon.pipeline import Reconstructor
from hsi_torch.recon.spatial import DEFAULT_LAM, SURE_LAMS, total_variation

WL_M = 8


def _piecewise(t: int = 20) -> torch.Tensor:
    """Two flat spectra split by a vertical edge (float64, ``(M, t, t)``)."""
    lam = torch.linspace(0, 1, WL_M, dtype=torch.float64).view(WL_M, 1, 1)
    a = 0.2 + 0.6 * torch.exp(-0.5 * ((lam - 0.3) / 0.2) ** 2)
    b = 0.1 + 0.5 * torch.exp(-0.5 * ((lam - 0.7) / 0.25) ** 2)
    s = a.expand(WL_M, t, t).clone()
    s[:, :, t // 2:] = b.expand(WL_M, t, t - t // 2)
    return s


def _noisy(bundle, s, sigma, seed=0):
    img = render_capture(bundle, s)
    g = torch.Generator().manual_seed(seed)
    return img + sigma * torch.randn(img.shape, generator=g, dtype=img.dtype)


def test_tv_option_reduces_error_on_a_piecewise_scene(device):
    bundle = make_bundle()
    s = _piecewise()
    img = _noisy(bundle, s, sigma=2.0).to(device, torch.float64)
    kw = dict(beta=1.0, device=device, dtype=torch.float64)
    pp = Reconstructor(bundle, **kw).reconstruct_frame(img)
    tv = Reconstructor(bundle, prior="tv", lam=1.0, **kw).reconstruct_frame(img)
    v = pp.valid
    assert torch.equal(v, tv.valid)
    truth = s.to(device)[:, v]
    err_pp = float((pp.cube[:, v] - truth).square().mean())
    err_tv = float((tv.cube[:, v] - truth).square().mean())
    assert err_tv < 0.5 * err_pp, (err_pp, err_tv)
    assert float(tv.cube[:, v].min()) >= 0
    st = tv.stats
    assert st["prior"] == "tv" and st["lam"] == 1.0 and st["lam_rule"] == "fixed"
    assert st["spatial_converged"] and st["spatial_iterations"] > 0
    # the noise estimate recovers the simulated σ (exact model: the residual is noise only)
    assert st["noise_sigma"] == pytest.approx(2.0, rel=0.15)
    assert st["lam_abs"] > 0
    assert "prior" not in pp.stats
    assert float(total_variation(tv.cube, v)) < float(total_variation(pp.cube, v))


def test_lam_zero_and_noise_free_equal_per_pixel(device):
    """λ = 0: the spatial answer is the per-pixel answer."""
    bundle = make_bundle()
    s = _piecewise()
    img = _noisy(bundle, s, sigma=1.0).to(device, torch.float64)
    kw = dict(beta=1.0, device=device, dtype=torch.float64)
    pp = Reconstructor(bundle, **kw).reconstruct_frame(img)
    tv0 = Reconstructor(bundle, prior="tv", lam=0.0, **kw).reconstruct_frame(img)
    v = pp.valid
    assert float((pp.cube[:, v] - tv0.cube[:, v]).abs().max()) < 1e-6


def test_saturated_pixels_use_their_own_gram(device):
    """A saturated observation is excluded in the spatial solve too: with λ = 0 the answer is
    the per-pixel re-solve with the frame mask."""
    bundle = make_bundle()
    s = _piecewise()
    img = _noisy(bundle, s, sigma=1.0).to(device, torch.float64)
    sat = torch.zeros_like(img, dtype=torch.bool)
    sat[0, 5, 7] = True
    img[0, 5, 7] = 1e6  # garbage behind the saturation flag
    kw = dict(beta=1.0, device=device, dtype=torch.float64)
    pp = Reconstructor(bundle, **kw).reconstruct_frame(img, sat)
    tv0 = Reconstructor(bundle, prior="tv", lam=0.0, **kw).reconstruct_frame(img, sat)
    v = pp.valid
    assert pp.stats["num_resolved"] > 0
    assert float((pp.cube[:, v] - tv0.cube[:, v]).abs().max()) < 1e-6
    tv = Reconstructor(bundle, prior="tv", lam=1.0, **kw).reconstruct_frame(img, sat)
    assert float(tv.cube[:, v].max()) < 2.0  # the garbage value never entered


def test_auto_lam_sure_tracks_the_prediction_risk(device):
    """lam="auto": the SURE values match the true prediction risk ``‖W A (s_λ − s_true)‖²/N``
    at every weight evaluated (to 0.15 σ²), and the chosen weight's true risk is within 1.5× of
    the best one's; the spectra beat per-pixel by far."""
    bundle = make_bundle()
    s = _piecewise()
    sigma = 10.0
    img = _noisy(bundle, s, sigma=sigma).to(device, torch.float64)
    kw = dict(beta=1.0, device=device, dtype=torch.float64)
    rec = Reconstructor(bundle, prior="tv", lam="auto", **kw)
    res = rec.reconstruct_frame(img)
    st = res.stats
    assert st["lam_rule"] == "sure" and len(st["sure_curve"]) == len(SURE_LAMS)
    sens = rec.sensing
    pix = sens.pixel_index
    ok = res.valid.reshape(-1)[pix]
    w = (sens.obs_mask & ok[:, None]).double()
    m = s.shape[0]
    pred_true = sens.model.A(s.to(device).reshape(m, -1)[:, pix].T) * w

    def risk(cube):
        x = torch.nan_to_num(cube.reshape(m, -1)[:, pix].T)
        return float(((sens.model.A(x) * w - pred_true) ** 2).sum() / w.sum())

    risks = []
    for lam, sure in st["sure_curve"]:
        r = risk(Reconstructor(sens, prior="tv", lam=lam).reconstruct_frame(img).cube)
        assert abs(sure - r) <= 0.15 * sigma**2, (lam, sure, r)
        risks.append(r)
    assert risk(res.cube) <= 1.5 * min(risks)
    v = res.valid
    truth = s.to(device)[:, v]
    per_pixel = Reconstructor(sens).reconstruct_frame(img).cube[:, v]
    assert float((res.cube[:, v] - truth).square().mean()) < 0.2 * float(
        (per_pixel - truth).square().mean())


def test_discrepancy_lam_meets_the_discrepancy(device):
    bundle = make_bundle()
    s = _piecewise()
    img = _noisy(bundle, s, sigma=2.0).to(device, torch.float64)
    rec = Reconstructor(bundle, beta=1.0, prior="tv", lam="discrepancy", device=device,
                        dtype=torch.float64)
    st = rec.reconstruct_frame(img).stats
    assert st["lam_rule"] == "discrepancy" and st["lam"] > 0
    # the chosen λ's residual per observation is σ̂² (to the bisection's resolution)
    assert st["mean_square_residual"] == pytest.approx(st["discrepancy_target"], rel=0.1)
    assert len(st["discrepancy_search"]) >= 5


def test_module_fixed_iterations_are_differentiable(device):
    bundle = make_bundle(t=12, missing=2)
    s = _piecewise(12)
    img = _noisy(bundle, s, sigma=1.0).to(device, torch.float64)
    mod = HSIReconstructor.from_bundle(bundle, beta=1.0, device=device, dtype=torch.float64,
                                       prior="tv", lam=0.5, spatial_iters=5)
    x = img.unsqueeze(0).clone().requires_grad_(True)
    cube, valid = mod(x)
    loss = cube[valid.unsqueeze(1).expand_as(cube)].square().sum()
    loss.backward()
    assert x.grad is not None and torch.isfinite(x.grad).all() and float(x.grad.abs().sum()) > 0
    assert "prior='tv'" in repr(mod)
    # without fixed iterations a gradient cannot be had: a clear error
    mod2 = HSIReconstructor.from_bundle(bundle, beta=1.0, device=device, dtype=torch.float64,
                                        prior="tv", lam=0.5)
    with pytest.raises(ValueError, match="spatial_iters"):
        mod2(img.unsqueeze(0).clone().requires_grad_(True))


def test_bad_options():
    bundle = make_bundle()
    with pytest.raises(ValueError, match="prior"):
        Reconstructor(bundle, prior="l1")
    with pytest.raises(ValueError, match="lam"):
        Reconstructor(bundle, prior="tv", lam=-1.0)
    with pytest.raises(ValueError, match="lam"):
        Reconstructor(bundle, prior="tv", lam="gcv")
    with pytest.raises(ValueError, match="spatial_iters"):
        Reconstructor(bundle, prior="tv", spatial_iters=0)
    with pytest.raises(ValueError, match="uncertainty"):
        Reconstructor(bundle, prior="tv", uncertainty=True)
    with pytest.raises(ValueError, match="uncertainty"):
        ReconstructConfig(prior="tv", uncertainty=True)


def test_config_default_is_the_api_default():
    cfg = ReconstructConfig()
    assert cfg.prior == "none" and cfg.lam == DEFAULT_LAM
    with pytest.raises(ValueError, match="lam"):
        ReconstructConfig(lam=-1.0)


def test_cli_reconstruct_with_tv(tmp_path, capsys):
    bundle = make_bundle()
    bpath = tmp_path / "b.npz"
    bundle.save(bpath)
    img = _noisy(bundle, _piecewise(), sigma=1.0).numpy().astype(np.float32)
    cap = tmp_path / "cap.npz"
    np.savez(cap, image=img)
    out = tmp_path / "out"
    rc = main(["reconstruct", "--bundle", str(bpath), "--out", str(out), "--set", "prior=tv",
               "--set", "lam=discrepancy", "--set", "formats=[npz]", "--set", "preview=false",
               "--set", "beta=1.0", str(cap)])  # fmt: skip
    assert rc == 0, capsys.readouterr().err
    with np.load(out / "cap.npz", allow_pickle=False) as z:
        keys = list(z.keys())
        meta = json.loads(str(z["metadata"])) if "metadata" in keys else None
    assert "cube" in keys
    if meta is not None:
        assert meta["stats"]["prior"] == "tv" and meta["stats"]["lam_rule"] == "discrepancy"


def test_experiment_registered_and_scores(tmp_path):
    from hsi_torch.experiments.cli_entry import resolve_experiment
    from hsi_torch.experiments.spatial import SpatialConfig, scene_scores

    schema, run = resolve_experiment("spatial")
    assert schema is SpatialConfig and callable(run)
    assert SpatialConfig().lams == [DEFAULT_LAM, "auto"]
    # scores: a perfect cube scores inf dB / 0°, a biased one finite; patch metrics present
    g = np.random.default_rng(0)
    truth_cube = 0.1 + 0.8 * g.random((5, 8, 10))
    truth_cube[:, :, :2] = 0.0  # off the scene
    pidx = np.full((8, 10), -1)
    pidx[:, 2:6], pidx[:, 6:] = 0, 1
    spectra = np.stack([truth_cube[:, 0, 3], truth_cube[:, 0, 8]])
    truth_cube[:, :, 2:6] = spectra[0][:, None, None]
    truth_cube[:, :, 6:] = spectra[1][:, None, None]
    truth = {"scene_cc": truth_cube, "cc_patch_index": pidx, "cc_spectra": spectra}
    valid = np.ones((8, 10), bool)
    sc = scene_scores("cc", truth_cube.copy(), valid, truth, 0.0)
    assert sc["footprint"]["pixels"] == 8 * 8 and sc["footprint"]["median_sam_deg"] < 1e-6
    assert sc["whole_patch_means"]["mean_sam_deg"] < 1e-6
    worse = scene_scores("cc", truth_cube * 1.1, valid, truth, 0.0)
    assert np.isfinite(worse["footprint"]["psnr_db"])
    assert worse["whole_patches_per_pixel"]["psnr_db"] < 60


def test_experiment_table_carries_the_fields_metrics(tmp_path):
    """table.md / table.csv hold hsi_torch.metrics of the footprint (both PSNR conventions,
    SSIM, mean SAM, ERGAS, RMSE, MRAE) of a known cube."""
    import csv

    import torch

    from hsi_torch.experiments.spatial import _row, _write_tables, scene_scores
    from hsi_torch.metrics import cube_metrics

    g = np.random.default_rng(1)
    truth_cube = 0.1 + 0.8 * g.random((5, 20, 24))
    truth_cube[:, :, :2] = 0.0  # off the scene: outside the footprint
    cube = truth_cube + g.normal(0.0, 0.03, truth_cube.shape)
    valid = np.ones((20, 24), bool)
    sc = scene_scores("s", cube, valid, {"scene_s": truth_cube}, 0.0)
    foot = torch.from_numpy(valid & (truth_cube.max(0) > 0))
    want = cube_metrics(torch.from_numpy(cube), torch.from_numpy(truth_cube), foot)
    row = _row("s", "per-pixel", sc, {})
    md = _write_tables(tmp_path, [row])
    got = next(csv.DictReader(open(tmp_path / "table.csv")))
    assert float(got["psnr_db"]) == pytest.approx(want["psnr_db"], rel=1e-12)
    for k in ("psnr_bands_db", "ssim", "sam_deg", "ergas", "rmse", "mrae"):
        assert float(got[k]) == pytest.approx(want[k], rel=1e-12), k
    for text in ("PSNR/band 0-255", "SSIM", "ERGAS", "MRAE", f"{want['ssim']:.4f}",
                 f"{want['psnr_bands_db']:.2f}", f"{want['ergas']:.2f}"):
        assert text in md, text


def test_frame_tolerance_scores_like_the_converged_answer(device, monkeypatch):
    """The pipeline stops ADMM at the frame tolerance: on a noisy frame its answer keeps at least
    95 % of the converged minimiser's error reduction over per-pixel NNLS (the converged one
    takes many more iterations); the distance between the two is under a tenth of per-pixel's
    error."""
    import hsi_torch.recon.frame as pipeline

    bundle = make_bundle()
    s = _piecewise()
    img = _noisy(bundle, s, sigma=10.0).to(device, torch.float64)
    kw = dict(beta=1.0, device=device, dtype=torch.float64)
    fast = Reconstructor(bundle, prior="tv", **kw).reconstruct_frame(img)
    solve = pipeline.spatial_solve_frame
    monkeypatch.setattr(pipeline, "spatial_solve_frame",
                        lambda *a, **k: solve(*a, **{**k, "tol": 1e-10, "max_iter": 100000}))
    conv = Reconstructor(bundle, prior="tv", **kw).reconstruct_frame(img)
    per_pixel = Reconstructor(bundle, **kw).reconstruct_frame(img)
    assert conv.stats["spatial_converged"]
    assert conv.stats["spatial_iterations"] > 2 * fast.stats["spatial_iterations"]
    v = fast.valid
    truth = s.to(device)[:, v]
    err = lambda c: float((c[:, v] - truth).square().mean())  # noqa: E731
    gain_fast = err(per_pixel.cube) - err(fast.cube)
    gain_conv = err(per_pixel.cube) - err(conv.cube)
    assert gain_conv > 0.9 * err(per_pixel.cube)  # TV removes most of the error here
    assert gain_fast >= 0.95 * gain_conv, (err(per_pixel.cube), err(fast.cube), err(conv.cube))
    gap = float((fast.cube[:, v] - conv.cube[:, v]).square().mean())
    assert gap < 0.1 * err(per_pixel.cube), (gap, err(per_pixel.cube))
