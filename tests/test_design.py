"""BRF/taper design sweep: condition numbers vs numpy, ranking, best-prototype YAML, CLI."""

from __future__ import annotations

import csv
import importlib

import numpy as np
import pytest
import torch
import yaml

from hsi_torch.config import load_config
from hsi_torch.experiments.cli_entry import EXPERIMENTS, resolve_experiment
from hsi_torch.experiments.design import (
    DesignSweepConfig,
    PSNRSpec,
    condition_sweep,
    geometry_rays,
    rank_designs,
    run_design,
)
from hsi_torch.experiments.systems import brf_sensing_model, phi_matrix
from hsi_torch.optics import DEFAULT_GEOMETRY, BRFConfig, KaleidoscopeGeometry
from hsi_torch.resources import shipped_config
from hsi_torch.spectral import DEFAULT_GRID

SMALL = dict(
    materials={"quartz": [2.5, 3.0], "polymer": [1.0]},
    tilts_deg=[0.0, 40.0, 65.0, 70.0],
    azimuths_deg=[10.0, 40.0],
    a_out_mm=[40.0],
    top_k=2,
    psnr=PSNRSpec(num_seeds=1, betas=[1e2, 1e3]),
    progress=False,
)


@pytest.fixture(scope="module")
def rays():
    return geometry_rays(DEFAULT_GEOMETRY)


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("design")
    summary = run_design(DesignSweepConfig(**SMALL), out)
    return out, summary


def _numpy_cond(rays, brf: BRFConfig) -> np.ndarray:
    phi = phi_matrix(grid=DEFAULT_GRID)
    a = brf_sensing_model(brf, rays.alpha, rays.sigma, rays.throughput, DEFAULT_GRID, phi).dense()
    return np.array([np.linalg.cond(m) for m in a.numpy()])


def test_condition_sweep_matches_numpy(rays):
    assert rays.error is None and rays.alpha.shape == (7, 10)
    tilts, azs = [20.0, 65.0], [10.0, 75.0]
    cond, max_opd = condition_sweep(rays, "quartz", 2.0, tilts, azs, DEFAULT_GRID,
                                    phi_matrix(grid=DEFAULT_GRID))
    assert cond.shape == (2, 2, 7)
    for i, t in enumerate(tilts):
        for j, az in enumerate(azs):
            brf = BRFConfig(thickness_mm=2.0, axis_tilt_deg=t, axis_azimuth_deg=az)
            np.testing.assert_allclose(cond[i, j].numpy(), _numpy_cond(rays, brf), rtol=1e-6)
            opd = brf.opd_nm(rays.alpha, rays.sigma, torch.tensor(430.0, dtype=torch.float64))
            assert float(max_opd[i, j]) == pytest.approx(float(opd.abs().max()), rel=1e-12)


def test_rank_designs_order():
    rows = [
        {"ok": True, "cond_worst": 5.0, "cond_median": 1.0},
        {"ok": False, "cond_worst": 1.0, "cond_median": 1.0},
        {"ok": True, "cond_worst": 2.0, "cond_median": 9.0},
    ]
    by_worst = rank_designs([dict(r) for r in rows], "worst")
    assert [r["cond_worst"] for r in by_worst] == [2.0, 5.0, 1.0]
    assert [r["rank_cond"] for r in by_worst] == [1, 2, 3]
    by_median = rank_designs([dict(r) for r in rows], "median")
    assert [r["cond_median"] for r in by_median] == [1.0, 9.0, 1.0]
    with pytest.raises(ValueError, match="rank_by"):
        rank_designs(rows, "best")


def test_small_sweep_ranking_against_numpy(small_run, rays):
    out, summary = small_run
    rows = list(csv.DictReader(open(out / "ranking.csv")))
    assert len(rows) == 3 * 4 * 2
    lam0_sq = 430.0**2
    worst = []
    for r in rows:
        brf = BRFConfig(material=r["material"], thickness_mm=float(r["thickness_mm"]),
                        axis_tilt_deg=float(r["axis_tilt_deg"]),
                        axis_azimuth_deg=float(r["axis_azimuth_deg"]))
        c = _numpy_cond(rays, brf)
        if c.max() < 1e8:
            assert float(r["cond_worst"]) == pytest.approx(c.max(), rel=1e-6)
            assert float(r["cond_median"]) == pytest.approx(np.median(c), rel=1e-6)
        else:  # round-off dominates: both just have to be (numerically) singular-ish
            assert float(r["cond_worst"]) > 1e7 and float(r["cond_worst"]) == pytest.approx(
                c.max(), rel=0.1)
        ok = float(r["max_opd_nm"]) <= lam0_sq / 30.0
        assert (r["ok"] == "True") == ok
        worst.append((not ok, float(r["cond_worst"])))
    # ranking.csv is sorted: feasible first, then by the worst-case condition number
    assert worst == sorted(worst)
    assert [int(r["rank_cond"]) for r in rows] == list(range(1, len(rows) + 1))
    # untilted quartz plates are infeasible (OPD ~ L·Δn ≈ 19 µm at 430 nm) and last
    assert all(r["ok"] == "False" for r in rows if r["material"] == "quartz"
               and float(r["axis_tilt_deg"]) == 0.0)
    # PSNR stage: top-2 plus the default prototype, ranked by PSNR
    scored = [r for r in rows if r["rank_psnr"]]
    expect = {int(r["rank_cond"]) for r in rows[:2]} | {
        int(r["rank_cond"]) for r in rows if r["is_default"] == "True"}
    assert {int(r["rank_cond"]) for r in scored} == expect
    best = min(scored, key=lambda r: int(r["rank_psnr"]))
    assert float(best["psnr_db"]) == max(float(r["psnr_db"]) for r in scored)
    assert summary["best"]["psnr_db"] == pytest.approx(float(best["psnr_db"]))
    for f in ("ranking.md", "condition_heatmap.png", "best_prototype.yaml", "summary.json"):
        assert (out / f).is_file()


def test_psnr_stage_carries_the_fields_metrics(small_run):
    """The PSNR stage's rows carry the field's metrics of the synthetic protocol: with one seed
    the RMSE is 10^(−PSNR/20) exactly; the per-band PSNR on 0–255 is a different number; SSIM is
    marked not applicable, and the table says why."""
    out, _ = small_run
    scored = [r for r in csv.DictReader(open(out / "ranking.csv")) if r["rank_psnr"]]
    assert scored
    for r in scored:
        assert float(r["rmse"]) == pytest.approx(10 ** (-float(r["psnr_db"]) / 20), rel=1e-9)
        assert float(r["ergas"]) > 0 and float(r["mrae"]) > 0
        assert np.isfinite(float(r["psnr_bands_db"]))
        assert float(r["psnr_bands_db"]) != pytest.approx(float(r["psnr_db"]), abs=1e-6)
        assert r["ssim"] == "n/a"
    md = (out / "ranking.md").read_text()
    for h in ("PSNR dB (per band, 0-255)", "| SSIM |", "SAM °", "ERGAS", "RMSE", "MRAE",
              "SSIM: n/a (the patches are spectra without a spatial layout)"):
        assert h in md, h


def test_best_prototype_yaml(small_run):
    out, summary = small_run
    doc = yaml.safe_load((out / "best_prototype.yaml").read_text())
    b = summary["best"]
    brf = BRFConfig.from_dict(doc["brf"])
    assert (brf.material, brf.thickness_mm, brf.axis_tilt_deg, brf.axis_azimuth_deg) == (
        b["material"], b["thickness_mm"], b["axis_tilt_deg"], b["axis_azimuth_deg"])
    geom = KaleidoscopeGeometry.from_dict(doc["geometry"])
    assert (geom.a_out_mm, geom.length_mm) == (b["a_out_mm"], b["length_mm"])


def test_best_prototype_loads_as_simulator_config(small_run):
    try:
        mod = importlib.import_module("hsi_torch.simulate.config")
    except ModuleNotFoundError:
        pytest.skip("hsi_torch.simulate.config (the simulator's schema) is not available")
    schema = getattr(mod, "SimulateConfig", None)
    if schema is None:
        pytest.skip("hsi_torch.simulate.config has no SimulateConfig")
    out, summary = small_run
    cfg = load_config(out / "best_prototype.yaml", schema)
    b = summary["best"]
    assert cfg.brf.thickness_mm == b["thickness_mm"]
    assert cfg.brf.axis_tilt_deg == b["axis_tilt_deg"]
    assert cfg.geometry.a_out_mm == b["a_out_mm"]


def test_registry_and_unknown_name():
    assert {"synthetic", "design", "opd", "usaf", "spatial"} <= set(EXPERIMENTS)
    schema, run = resolve_experiment("design")
    assert schema is DesignSweepConfig and run is run_design
    with pytest.raises(ValueError,
                       match="available: design, mismatch, opd, spatial, synthetic, usaf"):
        resolve_experiment("nope")


@pytest.mark.parametrize("tilts,azimuths", [("[65, 70]", "[40]"), ("[60]", "[30]")])
def test_cli_dispatch(tmp_path, capsys, tilts, azimuths):
    """The CLI runs the sweep; a sweep that leaves out the default plate's tilt and azimuth gets
    its extra row, which the figure places too (it failed when the default ranked best)."""
    from hsi_torch.cli import main

    out = tmp_path / "cli"
    code = main([
        "experiment", "design", "--config", str(shipped_config("design")), "--out", str(out),
        "--set", "materials={quartz: [2.5]}", "--set", f"tilts_deg={tilts}",
        "--set", f"azimuths_deg={azimuths}", "--set", "a_out_mm=[40]", "--set", "top_k=1",
        "--set", "psnr.num_seeds=1", "--set", "psnr.betas=[1000]", "--set", "progress=false",
    ])  # fmt: skip
    assert code == 0
    assert (out / "condition_heatmap.png").is_file()
    resolved = yaml.safe_load((out / "resolved_config.yaml").read_text())
    assert resolved["tilts_deg"] == yaml.safe_load(tilts)
    assert resolved["psnr"]["betas"] == [1000.0]
    rows = list(csv.DictReader(open(out / "ranking.csv")))
    assert len(rows) == 2
    assert sum(r["is_default"] == "True" for r in rows) == 1
    assert main(["experiment", "nope", "--out", str(tmp_path / "x")]) == 1
    assert "unknown experiment 'nope'" in capsys.readouterr().err
