"""Design kinds of the virtual prototype (``design.kind``): Manakov's per-view filters and
Fujimoto's birefringent thin section, rendered, calibrated and reconstructed by the same chain,
and as rows of the synthetic comparison."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import pytest
import torch

from hsi_torch.config import load_config
from hsi_torch.experiments.synthetic import DesignSpec, SyntheticConfig, build_design, run_synthetic
from hsi_torch.experiments.systems import (
    fujimoto_design,
    manakov_design,
    phi_matrix,
    this_system_design,
)
from hsi_torch.optics import DEFAULT_CAMERA, DEFAULT_GEOMETRY, BRFConfig, PrototypeDesign
from hsi_torch.optics.sensor import SensorModel
from hsi_torch.resources import shipped_config
from hsi_torch.simulate.config import SimulateConfig
from hsi_torch.simulate.mismatch import Mismatch
from hsi_torch.simulate.render import CaptureRenderer, CaptureSpec
from hsi_torch.simulate.scenes import ColorCheckerScene
from hsi_torch.spectral import DEFAULT_GRID

CAM = DEFAULT_CAMERA.scaled(0.5)
THIN = BRFConfig(material="calcite", thickness_mm=0.03)
_LAYOUTS: dict = {}
WHITE = CaptureSpec("white", "scene", None)
CC = CaptureSpec("cc", "scene", ColorCheckerScene(width_mm=8.4, center_mm=(0.0, 1.4)))
SCAN = CaptureSpec("s550", "scan", None, 550.0)


def _renderer(device, design: PrototypeDesign | None = None, brf: BRFConfig | None = None,
              **kw) -> CaptureRenderer:
    """A noise-free RGB renderer of the half-size prototype sharing one view layout."""
    sensor = SensorModel(output="rgb", shot_noise=False, read_noise_e=0.0, quantize=False,
                         exposure=0.8)
    key = str(device)
    r = CaptureRenderer(DEFAULT_GEOMETRY, CAM, brf or BRFConfig(), sensor, supersample=1,
                        max_reflections=2, device=device, dtype=torch.float64,
                        layout=_LAYOUTS.get(key), design=design, **kw)
    _LAYOUTS.setdefault(key, r.layout)
    return r


# ------------------------------------------------------------------------------ the designs


def test_design_validation_names_the_key():
    for kw, key in (({"kind": "prism"}, "kind"), ({"filter_fwhm_nm": 0}, "filter_fwhm_nm"),
                    ({"filter_peak": 1.5}, "filter_peak"), ({"grain_size_mm": -1}, "grain_size"),
                    ({"grain_opd_factor": (2.0, 1.0)}, "grain_opd_factor"),
                    ({"filter_span_nm": (600.0, 500.0)}, "filter_span_nm")):
        with pytest.raises(ValueError, match=key):
            PrototypeDesign(**kw)
    with pytest.raises(ValueError, match="9 filtered views"):
        PrototypeDesign("manakov", filter_centers_nm=(500.0, 600.0)).view_filters(
            10, torch.linspace(430, 670, 25))
    with pytest.raises(ValueError, match="no per-view filters"):
        PrototypeDesign("fujimoto").view_filters(10, torch.linspace(430, 670, 25))


def test_manakov_filters_are_the_stated_band_passes():
    wl = torch.arange(420.0, 680.0, 0.5, dtype=torch.float64)
    d = PrototypeDesign("manakov")
    f = d.view_filters(10, wl)
    assert f.shape == (10, wl.numel()) and bool((f[0] == 1).all())  # unfiltered reference view
    centres = torch.linspace(440.0, 660.0, 9, dtype=torch.float64)
    assert torch.allclose(wl[f[1:].argmax(1)], centres, atol=0.5)
    assert torch.allclose(f[1:].max(1).values, torch.full((9,), 0.9, dtype=torch.float64))
    # half maximum at centre ± FWHM / 2
    half = d.view_filters(10, torch.stack([centres - 15.0, centres + 15.0], 1).reshape(-1))
    # rows are views, columns the 18 probe wavelengths: view k+1 at its own two probes
    probes = torch.stack([half[k + 1, 2 * k:2 * k + 2] for k in range(9)])
    assert torch.allclose(probes, torch.full_like(probes, 0.45), atol=1e-12)
    # measured curves replace the band-passes
    curves = tuple(([400.0, 700.0], [0.1 * k, 0.1 * k]) for k in range(1, 10))
    g = PrototypeDesign("manakov", filter_curves=curves).view_filters(10, wl)
    assert torch.allclose(g[3], torch.full_like(wl, 0.3))
    with pytest.raises(ValueError, match="covers"):
        PrototypeDesign("manakov", filter_curves=(([500.0, 700.0], [0.5, 0.5]),) * 9
                        ).view_filters(10, wl)


def test_fujimoto_grain_map_is_piecewise_constant_and_seeded():
    d = PrototypeDesign("fujimoto", grain_size_mm=1.0, grain_opd_factor=(0.5, 6.0))
    ax = torch.linspace(-6.0, 6.0, 241, dtype=torch.float64)
    xy = torch.stack(torch.meshgrid(ax, ax, indexing="xy"), -1).reshape(-1, 2)
    f = d.grain_factor(xy)
    assert bool(((f >= 0.5) & (f <= 6.0)).all())
    assert torch.equal(f, d.grain_factor(xy))  # deterministic
    grains = f.unique().numel()
    assert 100 < grains < 200, grains  # ≈ (12 mm / 1 mm)² = 144 grains
    fm = f.reshape(241, 241)
    same = (fm[:, 1:] == fm[:, :-1]).float().mean()  # neighbours 0.05 mm apart: mostly one grain
    assert same > 0.9
    other = PrototypeDesign("fujimoto", grain_size_mm=1.0, grain_seed=1).grain_factor(xy)
    assert not torch.equal(f, other)


# ------------------------------------------------------------------------------ the renderer


def test_fujimoto_with_unit_grains_is_this_system_bit_identical(device):
    specs = [WHITE, SCAN, CC]
    plate = _renderer(device, brf=THIN).render(specs)
    unit = _renderer(device, PrototypeDesign("fujimoto", grain_opd_factor=(1.0, 1.0)),
                     brf=THIN).render(specs)
    assert torch.equal(plate, unit)
    grains = _renderer(device, PrototypeDesign("fujimoto"), brf=THIN).render(specs)
    assert (grains - plate).abs().max() > 0.05 * plate.abs().max()


@pytest.mark.parametrize("kind", ["manakov", "fujimoto"])
def test_truth_forward_model_reproduces_the_render(device, kind):
    """The truth (B, phi, gain) of each design predicts its noise-free white capture (as
    closely as for this system: the 10 nm grid's discretisation, grain edges)."""
    r = _renderer(device, PrototypeDesign(kind), brf=THIN if kind == "fujimoto" else None)
    img = r.render([WHITE])[0]
    truth = r.ground_truth()
    y = r.forward_model(truth, torch.ones(25, *truth["valid"].shape, device=device))
    ys = r.sample_views(r.noise_free_dn(img, r.scene_exposure))
    m = (truth["valid"][None] & truth["view_mask"])[:, None].expand_as(y)
    rel = ((y - ys).abs() / y.abs().clamp_min(1e-9))[m]
    strong = y[m] > 0.2 * y[m].max()  # (weak: a band-pass's far tail, where the grid's
    # quadrature error is relatively large; this system measures 0.4 % here)
    assert float(rel[strong].median()) < 0.01, float(rel[strong].median())


def test_manakov_truth_is_the_view_filter(device):
    r = _renderer(device, PrototypeDesign("manakov"))
    truth = r.ground_truth()
    valid = truth["valid"] & truth["view_mask"].all(0)
    y, x = (int(v[0]) for v in torch.nonzero(valid, as_tuple=True))
    b = truth["B"][:, :, y, x].double()  # (V, M)
    thr = truth["throughput"][:, y, x].double()
    assert torch.allclose(b[0], thr[0].expand(25), rtol=1e-6)  # the clear reference view
    wl = truth["wavelengths_nm"].double().cpu()
    centres = torch.linspace(440.0, 660.0, 9, dtype=torch.float64)
    peak = wl[b[1:].cpu().argmax(1)]
    assert bool(((peak - centres).abs() <= 5.0).all()), peak
    # no polarizers: a filter (peak 0.9, seen through the 10 nm scan line) transmits more than
    # the ½·η·T_BRF ≤ 0.45 of a BRF stack
    assert float((b[1:].max(1).values / thr[1:]).min()) > 0.6


def test_manakov_rejects_brf_mismatch_keys(device):
    with pytest.raises(ValueError, match="no birefringent filter"):
        _renderer(device, PrototypeDesign("manakov"), mismatch=Mismatch(brf_delta_t_k=5.0))


def test_shipped_design_configs_load():
    m = load_config(shipped_config("simulate_manakov"), SimulateConfig)
    f = load_config(shipped_config("simulate_fujimoto"), SimulateConfig)
    base = load_config(shipped_config("simulate"), SimulateConfig)
    assert base.design.kind == "this_system"
    assert m.design.kind == "manakov" and f.design.kind == "fujimoto"
    assert f.brf.material == "calcite" and f.brf.thickness_mm == 0.03
    assert m.camera == base.camera and m.geometry == base.geometry


# ------------------------------------------------------------------------------ the chain


def _chain(tmp_path: Path, name: str, calibrate_overrides: str = "") -> dict:
    from hsi_torch.experiments.demo import DemoConfig, demo

    cal = None
    if calibrate_overrides:
        text = shipped_config("calibrate").read_text()
        cal = tmp_path / "calibrate.yaml"
        cal.write_text(text.replace("max_patch_ratio: 0.8", calibrate_overrides))
        assert cal.read_text() != text
    cfg = DemoConfig(simulate_config=shipped_config(name), calibrate_config=cal, cave=False,
                     progress=False)
    return demo(tmp_path / "demo", cfg, quick=True, log=lambda *a, **k: None)


def test_manakov_simulates_calibrates_and_reconstructs(tmp_path):
    # the unfiltered reference view is as bright as its BRF-free patch: relax the patch check
    s = _chain(tmp_path, "simulate_manakov", "max_patch_ratio: 1.05")
    cc = s["scenes"]["colorchecker"]
    # measured (quick, seed 0): calibrated 32.6 dB / 4.60 deg, oracle 33.0 dB
    assert cc["calibrated"]["patches"] == 24
    assert cc["calibrated"]["mean_psnr_db"] >= 29.0, cc["calibrated"]["mean_psnr_db"]
    assert cc["calibrated"]["mean_sam_deg"] <= 6.0
    assert cc["oracle"]["mean_psnr_db"] >= 29.0


def test_fujimoto_simulates_calibrates_and_reconstructs(tmp_path):
    s = _chain(tmp_path, "simulate_fujimoto")
    cc = s["scenes"]["colorchecker"]
    # measured (quick, seed 0): calibrated 31.9 dB / 3.79 deg, oracle 31.8 dB
    assert cc["calibrated"]["patches"] == 24
    assert cc["calibrated"]["mean_psnr_db"] >= 29.0, cc["calibrated"]["mean_psnr_db"]
    assert cc["calibrated"]["mean_sam_deg"] <= 6.0


# ------------------------------------------------------------------------------ synthetic rows


def test_design_builders_follow_the_renderer_physics():
    grid = DEFAULT_GRID
    ours = this_system_design(grid)
    man = manakov_design(grid)
    assert man.matrix.shape == ours.matrix.shape == (30, 25)
    # view 0 is unfiltered: its rows are the camera's φ·Δλ (× g_0 = 1)
    dl = grid.band_widths(dtype=torch.float64)
    assert torch.allclose(man.matrix[:3], phi_matrix(grid=grid) * dl, rtol=1e-12)
    k = int(man.matrix[4].argmax())  # view 1, G: peaks within its 440 nm band-pass region
    assert abs(float(grid.wavelengths(dtype=torch.float64)[k]) - 440.0) <= 20.0
    unit = fujimoto_design(grid, design={"grain_opd_factor": (1.0, 1.0)})
    plate = this_system_design(grid, brf={"material": "calcite", "thickness_mm": 0.03})
    assert torch.allclose(unit.matrix, plate.matrix, rtol=1e-10, atol=0)
    fuj = fujimoto_design(grid)
    fac = fuj.info["grain_factor"]
    assert 0.5 <= fac <= 6.0 and not torch.allclose(fuj.matrix, plate.matrix)


def test_synthetic_rows_for_the_designs(tmp_path):
    cfg = load_config(shipped_config("synthetic"), SyntheticConfig)
    assert {"manakov", "fujimoto"} <= {d.kind for d in cfg.designs}
    cfg = SyntheticConfig(
        noise_sigmas=[1.0], num_seeds=1, betas=[1e2, 1e3], progress=False,
        designs=[DesignSpec(kind="three_camera"), DesignSpec(kind="manakov"),
                 DesignSpec(kind="fujimoto")],
    )  # fmt: skip
    run_synthetic(cfg, tmp_path)
    rows = {r["method"]: r for r in csv.DictReader(open(tmp_path / "results.csv"))}
    assert {"3Camera", "Manakov", "Fujimoto"} <= set(rows)
    for name in ("Manakov", "Fujimoto"):
        psnr = float(rows[name]["psnr_db"])
        assert math.isfinite(psnr) and psnr > 25.0, (name, psnr)
    with pytest.raises(ValueError, match="mean"):
        build_design(DesignSpec(kind="fujimoto", scene_point="mean"), DEFAULT_GRID)
