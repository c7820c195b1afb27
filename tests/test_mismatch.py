"""Non-ideal effects of the virtual prototype (``mismatch:``): each does what it says, on the
captures it says, and off changes nothing. Half-size sensor (200 × 192), one ray per pixel."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from hsi_torch.cli import main
from hsi_torch.config import ConfigError, load_config
from hsi_torch.io import read_capture
from hsi_torch.optics import DEFAULT_CAMERA, DEFAULT_GEOMETRY, BRFConfig
from hsi_torch.optics.sensor import SensorModel, cfa_index
from hsi_torch.resources import shipped_config
from hsi_torch.simulate.config import SimulateConfig
from hsi_torch.simulate.mismatch import (
    Mismatch,
    drift_points,
    radial_undistort,
    stray_light_veil,
)
from hsi_torch.simulate.render import CaptureRenderer, CaptureSpec
from hsi_torch.simulate.scenes import ColorCheckerScene

CAM = DEFAULT_CAMERA.scaled(0.5)
_LAYOUTS: dict = {}


def _renderer(device, mismatch: Mismatch | None = None, brf: BRFConfig | None = None,
              **kw) -> CaptureRenderer:
    """A noise-free RGB renderer of the half-size prototype sharing one view layout."""
    sensor = SensorModel(output="rgb", shot_noise=False, read_noise_e=0.0, quantize=False,
                         exposure=0.8)
    key = str(device)
    r = CaptureRenderer(DEFAULT_GEOMETRY, CAM, brf or BRFConfig(), sensor, supersample=1,
                        max_reflections=2, device=device, dtype=torch.float64,
                        layout=_LAYOUTS.get(key), mismatch=mismatch, **kw)
    _LAYOUTS.setdefault(key, r.layout)
    return r


WHITE = CaptureSpec("white", "scene", None)
CC = ColorCheckerScene(width_mm=8.4, center_mm=(0.0, 1.4))


# ------------------------------------------------------------------------------ off = ideal


def test_defaults_are_off_and_keep_the_ideal_render(device):
    m = Mismatch()
    assert not (m.distorted or m.drifted or m.thickness_map or m.after_calibration
                or m.scan_changed) and m.active() == {}
    assert all(v == 0 for k, v in m.sensor_kwargs().items()
               if k not in ("nonlinearity_knee", "hot_pixel_level", "pattern_seed"))
    specs = [WHITE, CaptureSpec("s550", "scan", None, 550.0), CaptureSpec("cc", "scene", CC)]
    r = _renderer(device)
    a = r.render(specs)
    b = r.render(specs[::2], after_calibration=True)  # nothing changes after calibration
    assert torch.equal(a[[0, 2]], b)
    assert a[0].abs().sum() > 0


def test_config_section_loads_and_errors_name_the_key():
    cfg = load_config(shipped_config("simulate"), SimulateConfig,
                      ["mismatch.drift_shift_px=[2, -1]", "mismatch.distortion_k1=-0.1",
                       "mismatch.scene_illuminant=A"])
    assert cfg.mismatch.drift_shift_px == (2.0, -1.0) and cfg.mismatch.after_calibration
    assert cfg.mismatch.active() == {"distortion_k1": -0.1, "drift_shift_px": [2.0, -1.0],
                                     "scene_illuminant": "A"}
    for bad, key in (("mismatch.stray_light_fraction=1.5", "stray_light_fraction"),
                     ("mismatch.drift_shift_px=[1, 2, 3]", "drift_shift_px"),
                     ("mismatch.drift_px=2", "mismatch.drift_px")):
        with pytest.raises((ConfigError, ValueError), match=key):
            load_config(shipped_config("simulate"), SimulateConfig, [bad])


# ------------------------------------------------------------------------------ monochromator


def test_monochromator_offset_and_width_change_only_the_scan(device):
    ideal = _renderer(device)
    m = _renderer(device, Mismatch(scan_wavelength_offset_nm=0.5, scan_fwhm_actual_nm=12.0))
    wide = _renderer(device, scan_fwhm_nm=12.0)  # an ideal device whose line is 12 nm
    specs = [CaptureSpec("s550", "scan", None, 550.0), WHITE]
    got = m.render(specs)
    # the frame labelled 550 nm is the 12 nm line at 550.5 nm, at the nominal line's exposure
    want = wide.render([CaptureSpec("s", "scan", None, 550.5)])[0]
    torch.testing.assert_close(got[0] / m.kappa_scan, want / wide.kappa_scan, rtol=1e-12,
                               atol=1e-15)
    assert not torch.allclose(got[0], ideal.render(specs[:1])[0], rtol=1e-3)
    assert torch.equal(got[1], ideal.render([WHITE])[0])  # objective-on captures untouched


# ------------------------------------------------------------------------------ distortion


def test_radial_undistort_inverts_the_distortion(device):
    p = torch.tensor([[0.0, 0.0], [199.0, 191.0], [30.0, 150.0], [99.5, 95.5]],
                     dtype=torch.float64, device=device)
    f, cx, cy, k1, k2 = CAM.focal_px, float(CAM.cx), float(CAM.cy), -0.1, 0.05
    u = radial_undistort(p, k1, k2, f, cx, cy)
    xu = (u - torch.tensor([cx, cy], dtype=p.dtype, device=device)) / f
    r2 = xu.pow(2).sum(-1, keepdim=True)
    back = xu * (1 + k1 * r2 + k2 * r2 * r2) * f + torch.tensor([cx, cy], dtype=p.dtype,
                                                                device=device)
    torch.testing.assert_close(back, p, rtol=0, atol=1e-9)
    # barrel (k1 < 0): a corner pixel sees a point further out, by ≈ |k1|·r² of its radius
    assert (u[1] - torch.tensor([cx, cy], device=device)).norm() > (
        p[1] - torch.tensor([cx, cy], device=device)).norm()
    torch.testing.assert_close(u[3], p[3])  # the principal point does not move


def test_distortion_warps_every_capture_as_predicted(device):
    k1 = -0.3  # exaggerated: the corners move by 2 px on this half-size sensor
    ideal, m = _renderer(device), _renderer(device, Mismatch(distortion_k1=k1))
    specs = [WHITE, CaptureSpec("s550", "scan", None, 550.0)]
    a, b = ideal.render(specs), m.render(specs)
    h, w = m.sensor_size
    pix = m.camera.pixel_grid(device, torch.float64)
    src = radial_undistort(pix, k1, 0.0, CAM.focal_px, float(CAM.cx), float(CAM.cy))
    assert float((src - pix).norm(dim=1).max()) > 1.5
    grid = torch.stack([src[:, 0] / (w - 1) * 2 - 1, src[:, 1] / (h - 1) * 2 - 1], -1)
    for k in range(2):
        warped = F.grid_sample(a[k][None], grid.reshape(1, h, w, 2).to(a), align_corners=True)[0]
        # compare where the ideal image is smooth around the source point
        lo = -F.max_pool2d(-a[k][None], 5, 1, 2)[0].amin(0)
        hi = F.max_pool2d(a[k][None], 5, 1, 2)[0].amax(0)
        smooth = (lo > 0.6 * hi) & (hi > 0)
        smooth_src = F.grid_sample(smooth[None, None].to(a), grid.reshape(1, h, w, 2).to(a),
                                   align_corners=True)[0, 0] > 0.999
        rel = ((b[k] - warped).abs() / warped.abs().clamp_min(1e-12)).amax(0)[smooth_src]
        assert smooth_src.sum() > 2000
        assert float(rel.median()) < 1e-3
        rel_ideal = ((b[k] - a[k]).abs() / a[k].abs().clamp_min(1e-12)).amax(0)[smooth_src]
        assert float(rel_ideal.median()) > 3 * float(rel.median())


# ------------------------------------------------------------------------------ stray light


def test_stray_light_adds_its_fraction_everywhere(device):
    ideal, m = _renderer(device), _renderer(device, Mismatch(stray_light_fraction=0.02))
    specs = [WHITE, CaptureSpec("s550", "scan", None, 550.0)]
    a, b = ideal.render(specs), m.render(specs)
    veil = b - a
    for k in range(2):
        torch.testing.assert_close(veil[k].mean((1, 2)), 0.02 * a[k].mean((1, 2)))
        dark = a[k].sum(0) == 0  # where no view reaches
        assert int(dark.sum()) > 1000 and bool((veil[k][:, dark] > 0).all())
        # smooth: the veil varies by less than e^(1/(2·0.5²)) ≈ 7.4× across the sensor
        v = veil[k][1]
        assert float(v.max() / v.min()) < math.exp(2.0)


def test_stray_light_veil_per_cfa_colour(device):
    h, w = 8, 10
    cfa = torch.tensor(cfa_index("RGGB"), device=device).reshape(-1)
    cmap = cfa[torch.arange(h, device=device)[:, None] % 2 * 2
               + torch.arange(w, device=device)[None, :] % 2]
    img = torch.zeros(1, h, w, dtype=torch.float64, device=device)
    img[0][cmap == 0] = 3.0  # only red light
    out = stray_light_veil(img, 0.1, 1e6, (4.5, 3.5), cmap)  # flat veil
    torch.testing.assert_close(out[0][cmap == 0], torch.full_like(out[0][cmap == 0], 3.3))
    assert float(out[0][cmap != 0].abs().max()) == 0.0  # no red light leaks into G and B


# ------------------------------------------------------------------------------ filter


def _opd_equivalent(device, factor: float) -> CaptureRenderer:
    """An ideal renderer whose filter is ``factor`` times thicker (OPD ∝ thickness)."""
    base = BRFConfig()
    return _renderer(device, brf=BRFConfig.from_dict({**base.to_dict(),
                                                      "thickness_mm": base.thickness_mm * factor}))


def test_brf_thickness_map_is_in_the_captures_and_the_truth(device):
    g = (0.3, -0.2)  # µm per mm
    m = _renderer(device, Mismatch(brf_thickness_gradient_um_per_mm=g))
    tr = m.ground_truth()
    x = tr["diffuser_xy"].to(torch.float64)
    d = 1.0 + (g[0] * x[..., 0] + g[1] * x[..., 1]) / (1000 * BRFConfig().thickness_mm)
    # one reference pixel: the truth equals an ideal filter of that pixel's thickness
    q = torch.nonzero(tr["valid"] & ~tr["brf_free"])[len(torch.nonzero(tr["valid"])) // 2]
    eq = _opd_equivalent(device, float(d[q[0], q[1]])).ground_truth()
    torch.testing.assert_close(tr["B"][:, :, q[0], q[1]], eq["B"][:, :, q[0], q[1]],
                               rtol=0, atol=2e-7)
    ideal = _renderer(device).ground_truth()
    assert float((tr["B"] - ideal["B"]).abs().max()) > 1e-3
    # the scan (what calibration measures) sees it too
    s = CaptureSpec("s550", "scan", None, 550.0)
    assert not torch.equal(m.render([s])[0], _renderer(device).render([s])[0])


def test_brf_temperature_change_acts_on_scenes_only(device):
    mm = Mismatch(brf_delta_t_k=5.0)
    m = _renderer(device, mm)
    fac = 1.0 + mm.brf_retardance_temp_coeff_per_k * 5.0
    specs = [CaptureSpec("cc", "scene", CC)]
    after = m.render(specs, after_calibration=True)
    torch.testing.assert_close(after, _opd_equivalent(device, fac).render(specs), rtol=1e-9,
                               atol=1e-12)
    ideal = _renderer(device).render(specs)
    assert torch.equal(m.render(specs), ideal)  # calibration captures: the calibrated filter
    assert float((after - ideal).abs().max()) > 1e-3 * float(ideal.max())


# ------------------------------------------------------------------------------ drift


def test_drift_points_shift_and_rotation(device):
    p = torch.tensor([[10.0, 5.0], [2.0, 3.0]], dtype=torch.float64, device=device)
    torch.testing.assert_close(drift_points(p, (2.0, -1.0), 0.0, (0.0, 0.0)),
                               p + torch.tensor([2.0, -1.0], dtype=p.dtype, device=device))
    r = drift_points(p, (0.0, 0.0), 90.0, (2.0, 3.0))
    torch.testing.assert_close(r, torch.tensor([[0.0, 11.0], [2.0, 3.0]], dtype=p.dtype,
                                               device=device))


def test_drift_moves_the_scene_captures_only(device):
    m = _renderer(device, Mismatch(drift_shift_px=(2.0, 0.0)))
    ideal = _renderer(device)
    specs = [CaptureSpec("cc", "scene", CC)]
    a, b = ideal.render(specs)[0], m.render(specs, after_calibration=True)[0]
    # pixel x of the moved sensor sees what pixel x + 2 saw: the image moves 2 px left
    assert torch.equal(b[:, :, :-2], a[:, :, 2:])
    assert not torch.equal(b, a)
    assert torch.equal(m.render(specs)[0], a)  # calibration captures: no drift


# ------------------------------------------------------------------------------ illuminant


def test_scene_illuminant_differs_from_the_white_reference(device):
    m = _renderer(device, Mismatch(scene_illuminant="A"))
    under_a = _renderer(device, illuminant="A")
    ideal = _renderer(device)
    specs = [CaptureSpec("cc", "scene", CC)]
    got = m.render(specs, after_calibration=True)
    # lit by A, exposed as the D65 white reference is (κ of D65)
    torch.testing.assert_close(got / m.kappa, under_a.render(specs) / under_a.kappa,
                               rtol=1e-12, atol=1e-15)
    assert torch.equal(m.render([WHITE])[0], ideal.render([WHITE])[0])
    b_over_r = got[0, 2].sum() / got[0, 0].sum()
    assert b_over_r < 0.7 * ideal.render(specs)[0, 2].sum() / ideal.render(specs)[0, 0].sum()


# ------------------------------------------------------------------------------ sensor


def _flat(level: float, device, h: int = 64, w: int = 64) -> torch.Tensor:
    return torch.full((3, h, w), level, dtype=torch.float64, device=device)


def test_sensor_nonlinearity_bends_near_saturation_only(device):
    kw = dict(output="rgb", shot_noise=False, read_noise_e=0.0, quantize=False, exposure=1.0)
    lin = SensorModel(**kw)
    nl = SensorModel(**kw, nonlinearity=0.05, nonlinearity_knee=0.7)
    levels = torch.tensor([0.2, 0.5, 0.7, 0.85, 1.0], dtype=torch.float64, device=device)
    x = levels[None, :, None].expand(3, 5, 1).contiguous()
    a, b = lin.expose(x).dn, nl.expose(x).dn
    blk = lin.black_level
    rel = (b - blk) / (a - blk)
    torch.testing.assert_close(rel[0, :3, 0], torch.ones(3, dtype=torch.float64, device=device))
    # at 85 %: a quarter of the way in the quadratic; at the full well the stated 5 % is lost
    torch.testing.assert_close(rel[0, 3:, 0], torch.tensor(
        [1 - 0.05 * 0.25 / 0.85, 0.95], dtype=torch.float64, device=device))


def test_sensor_prnu_hot_and_dead_pixels_are_a_fixed_pattern(device):
    kw = dict(output="rgb", shot_noise=False, read_noise_e=0.0, quantize=False, exposure=1.0)
    s = SensorModel(**kw, prnu_sigma=0.01, hot_pixel_fraction=0.01, dead_pixel_fraction=0.01,
                    pattern_seed=3)
    dn = s.expose(_flat(0.4, device)).dn - s.black_level
    ideal = SensorModel(**kw).expose(_flat(0.4, device)).dn - s.black_level
    gain, hot, dead = s.fixed_pattern(64, 64, device)
    assert 10 < int(hot.sum()) < 80 and 10 < int(dead.sum()) < 80
    assert bool((dn[:, dead] == 0).all())
    fw_dn = s.electrons_at_unity / s.gain_e_per_dn
    torch.testing.assert_close(dn[:, hot], (ideal[:, hot] * gain[hot] + 0.2 * fw_dn))
    ok = ~hot & ~dead
    ratio = dn[0][ok] / ideal[0][ok]
    assert abs(float(ratio.std()) - 0.01) < 0.002 and abs(float(ratio.mean()) - 1) < 0.002
    # the same pixels in every exposure (a dark frame shows the hot ones) and on every device
    dark = s.expose(_flat(0.0, device)).dn - s.black_level
    assert torch.equal(dark[0] > 0, hot)
    g_cpu, h_cpu, _ = s.fixed_pattern(64, 64, "cpu")
    assert torch.equal(h_cpu, hot.cpu()) and torch.equal(g_cpu, gain.cpu())


# ------------------------------------------------------------------------------ capture set

TINY = ["camera.scale=0.5", "render.supersample=1", "render.dtype=float32",
        "render.progress=false", "captures.scan_wavelengths_nm=[550]", "captures.white_shots=1",
        "render.figures=false", "captures.grid.poses=[{rotation_deg: 0.0}]"]


def _simulate(out: Path, extra: list[str]) -> dict:
    args = ["simulate", "--config", str(shipped_config("simulate")), "--out", str(out)]
    for o in [*TINY, *extra]:
        args += ["--set", o]
    assert main(args) == 0
    return json.loads((out / "manifest.json").read_text())


def test_capture_set_applies_after_calibration_effects_to_scenes_only(tmp_path):
    ideal = _simulate(tmp_path / "ideal", [])
    late = _simulate(tmp_path / "late", ["mismatch.drift_shift_px=[2, 0]",
                                         "mismatch.brf_delta_t_k=5", "mismatch.scene_illuminant=A"])
    # the manifest holds only what a real camera's would
    assert {k: v for k, v in late.items() if k != "captures"} == {
        k: v for k, v in ideal.items() if k != "captures"}
    tj = [json.loads((tmp_path / n / "ground_truth" / "truth.json").read_text())
          for n in ("ideal", "late")]
    assert tj[0]["mismatch"] == {}
    assert tj[1]["mismatch"] == {"brf_delta_t_k": 5.0, "drift_shift_px": [2.0, 0.0],
                                 "scene_illuminant": "A"}
    for c in ideal["captures"]:
        a, _ = read_capture(tmp_path / "ideal" / c["file"])
        b, _ = read_capture(tmp_path / "late" / c["file"])
        same = np.array_equal(np.asarray(a), np.asarray(b))
        assert same == (c["type"] != "scene"), c["file"]
    ta = np.load(tmp_path / "ideal" / "ground_truth" / "truth.npz")
    tb = np.load(tmp_path / "late" / "ground_truth" / "truth.npz")
    for k in ta.files:  # the truth is the calibrated device's
        np.testing.assert_array_equal(ta[k], tb[k], err_msg=k)


def test_documented_effects_are_valid_keys_and_not_off():
    from hsi_torch.simulate.mismatch import DOCUMENTED_EFFECTS

    everything: dict = {}
    for name, keys in DOCUMENTED_EFFECTS.items():
        m = Mismatch(**keys)
        assert set(m.active()) == set(keys), name
        everything.update(keys)
    assert Mismatch(**everything).after_calibration
    doc = (Path(__file__).resolve().parents[1] / "docs" / "simulate.md").read_text()
    for keys in DOCUMENTED_EFFECTS.values():
        for k in keys:
            assert f"`{k}`" in doc, k
