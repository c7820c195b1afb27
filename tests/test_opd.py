"""OPD estimator (synthetic cosines, chirped spectra) and the OPD validation on the default
prototype's ground truth."""

from __future__ import annotations

import math

import pytest
import torch

from hsi_torch.experiments.opd import OPDConfig, run_opd
from hsi_torch.experiments.opd_estimate import band_centre_nm, estimate_opd, group_opd_nm
from hsi_torch.experiments.opd_points import match_points, predicted_views, read_points_csv

WL = torch.arange(430.0, 671.0, 10.0, dtype=torch.float64)
OPDS = [2000.0, 2600.0, 3300.0, 4100.0, 4800.0, 5500.0]


def _cosines(opds, phases, device, dtype, offset=0.3, amp=0.25):
    k = 1.0 / WL
    o = torch.tensor(opds, dtype=torch.float64)[:, None]
    p = torch.tensor(phases, dtype=torch.float64)[:, None]
    t = offset + amp * torch.cos(2 * math.pi * o * k[None] + p)
    return t.to(device, dtype), WL.to(device, dtype)


@pytest.mark.parametrize("phase", [0.0, 1.3, math.pi])
def test_recovers_synthetic_cosines(device, dtype, phase):
    t, wl = _cosines(OPDS, [phase] * len(OPDS), device, dtype)
    est = estimate_opd(t, wl)
    truth = torch.tensor(OPDS, dtype=torch.float64)
    assert est.fit_nm.device.type == device.type and est.fit_nm.dtype == dtype
    # coarse: within one FFT bin (≈ 1.15 µm over 430–670 nm on 25 k samples)
    assert 1100 < est.bin_nm < 1250
    assert ((est.coarse_nm.double().cpu() - truth).abs() <= est.bin_nm).all()
    # refined: zero-padded parabolic FFT peak within 1 % from 2.5 µm (>= 2 fringes in the band;
    # below, the negative-frequency image biases it: up to 5 % at 2 µm), cosine fit everywhere
    rel_fft = (est.fft_nm.double().cpu() - truth).abs() / truth
    rel_fit = (est.fit_nm.double().cpu() - truth).abs() / truth
    assert rel_fft[truth >= 2500].max() < 0.01, rel_fft
    assert rel_fft.max() < 0.06, rel_fft
    assert rel_fit.max() < (1e-3 if dtype == torch.float32 else 1e-6), rel_fit
    torch.testing.assert_close(est.amplitude.double().cpu(), torch.full((len(OPDS),), 0.25,
                               dtype=torch.float64), rtol=1e-3, atol=1e-3)
    # the fitted model reproduces the spectra
    torch.testing.assert_close(est.model(wl), t, rtol=0, atol=2e-3 if dtype == torch.float32
                               else 1e-8)


def test_fit_handles_low_opd_and_noise():
    g = torch.Generator().manual_seed(0)
    t, wl = _cosines([1100.0, 1600.0, 3000.0], [0.4, 2.0, -1.0], "cpu", torch.float64)
    est = estimate_opd(t, wl)
    torch.testing.assert_close(est.fit_nm, torch.tensor([1100.0, 1600.0, 3000.0],
                               dtype=torch.float64), rtol=1e-6, atol=0)
    noisy = t + 0.005 * torch.randn(t.shape, generator=g, dtype=torch.float64)  # 2 % of b
    est = estimate_opd(noisy, wl)
    rel = (est.fit_nm - torch.tensor([1100.0, 1600.0, 3000.0], dtype=torch.float64)).abs()
    assert (rel / torch.tensor([1100.0, 1600.0, 3000.0], dtype=torch.float64)).max() < 0.01


def test_chirped_spectrum_measures_group_opd():
    """A dispersive plate: the fit measures Δ_g(k₀) = Δ − λ dΔ/dλ, not the phase OPD."""
    from hsi_torch.optics import BRFConfig

    brf = BRFConfig(material="quartz", thickness_mm=2.5, axis_tilt_deg=70, axis_azimuth_deg=40)
    alpha = torch.tensor([0.02, 0.12, 0.2, 0.24], dtype=torch.float64)
    sigma = torch.tensor([0.3, 2.0, -1.0, 1.0], dtype=torch.float64)
    t = brf.transmittance(alpha[:, None], sigma[:, None], WL)
    est = estimate_opd(t, WL)
    k0 = band_centre_nm(WL)
    assert abs(k0 - 2 / (1 / 430 + 1 / 670)) < 1e-9
    g = group_opd_nm(brf, alpha, sigma, k0)
    ph = brf.opd_nm(alpha, sigma, torch.tensor(k0, dtype=torch.float64)).abs()
    rel = (est.fit_nm - g.abs()).abs() / g.abs()
    assert rel.max() < 0.01, rel
    # the phase OPD is ≈ 10 % off: dispersion matters
    assert ((est.fit_nm - ph).abs() / ph).min() > 0.05
    # Δ_g by its definition d(Δ k)/dk, independently by a wide central difference in k
    h = 1e-7
    kk = torch.tensor([1 / k0 - h, 1 / k0 + h], dtype=torch.float64)
    dk = brf.opd_nm(alpha[:, None], sigma[:, None], 1 / kk) * kk
    torch.testing.assert_close(g, (dk[:, 1] - dk[:, 0]) / (2 * h), rtol=1e-4, atol=0)


def test_errors():
    with pytest.raises(ValueError, match="samples"):
        estimate_opd(torch.ones(3, 10, dtype=torch.float64), WL)
    with pytest.raises(ValueError, match="increasing"):
        estimate_opd(torch.ones(2, 25, dtype=torch.float64), WL.flip(0))
    with pytest.raises(ValueError, match="window"):
        estimate_opd(torch.rand(2, 25, dtype=torch.float64), WL, window="kaiser")


def test_csv_points(tmp_path):
    t, _ = _cosines([3000.0, 4000.0], [0.0, 1.0], "cpu", torch.float64)
    head = "label,x_px,y_px," + ",".join(f"{w:g}" for w in WL.tolist())
    rows = [f"a,200.0,190.0,{','.join(map(str, t[0].tolist()))}",
            f"b,258.0,157.0,{','.join(map(str, t[1].tolist()))}"]
    p = tmp_path / "pts.csv"
    p.write_text("\n".join([head, *rows]) + "\n")
    mp = read_points_csv(p)
    assert mp.label == ["a", "b"] and mp.T.shape == (2, 25)
    torch.testing.assert_close(mp.xy, torch.tensor([[200.0, 190.0], [258.0, 157.0]],
                                                   dtype=torch.float64))
    (tmp_path / "bad.csv").write_text("x_px,foo\n1,2\n")
    with pytest.raises(ValueError, match="y_px"):
        read_points_csv(tmp_path / "bad.csv")


@pytest.fixture(scope="module")
def default_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("opd")
    cfg = OPDConfig(progress=False)  # the default prototype's ground truth, in memory
    return run_opd(cfg, out), out


def test_default_truth_views_within_stated_error(default_run):
    """Every sample point of all 10 views of the default prototype's truth B: the cosine fit
    is within 1 % (stated error) of the ray tracer's group OPD at k₀; coarse within a bin."""
    summary, out = default_run
    st = summary["inputs"]["truth"]
    assert st["points"] == 70 and st["modulated_points"] == 70
    assert st["views_matched_correctly"] == 70
    assert st["fit_max_rel"] < 0.01
    assert st["coarse_within_one_bin"]
    for f in ("matched_pairs.csv", "matched_pairs.md", "per_view.csv", "summary.md",
              "correspondence_truth.png", "opd_polar_truth.png", "spectra_truth.png"):
        assert (out / f).is_file(), f
    # no reflectance cube here: the table says the field's metrics do not apply, and why
    assert "reconstruction metrics (hsi_torch.metrics" in (out / "summary.md").read_text()
    assert "do not apply here" in (out / "summary.md").read_text()


def test_match_points_nearest_view():
    from hsi_torch.optics import DEFAULT_CAMERA, DEFAULT_GEOMETRY, BRFConfig

    pred = predicted_views(DEFAULT_GEOMETRY, DEFAULT_CAMERA, BRFConfig())
    c = pred.centres
    xy = torch.cat([c + 0.5, torch.tensor([[-50.0, -50.0]], dtype=torch.float64)])
    m = match_points(pred, xy, 550.0, band_centre_nm(WL))
    assert m["view"][:-1].tolist() == list(range(c.shape[0]))
    assert bool(m["inside"][:-1].all()) and not bool(m["inside"][-1])
    assert int(m["view"][-1]) == int(torch.cdist(xy[-1:], c).argmin())
    # the traced prediction at a centre is close to the view's mean OPD
    torch.testing.assert_close(m["opd_phase_nm"][:-1].abs(), pred.layout.opd_nm.abs(),
                               rtol=0.05, atol=60.0)
