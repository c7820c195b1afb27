"""The banded renderer against the renderer's physics written the direct way.

The reference below traces every sub-pixel ray of a tiny sensor at once, evaluates the filter
stack ``Tstack(α, σ, λ)`` on the 2 nm grid per ray (``stack_transmittance``), rasterises every
scene on the 2 nm grid before blurring it, and integrates ``Σ_λ Tstack · S · φ`` per ray and
capture. ``CaptureRenderer.render`` instead works band by band, shares ``cos(2π OPD/λ)`` between
captures, keeps scenes as abundance planes × endmember spectra and crops their rasters: the
same sums in another order, so the two agree to rounding.
"""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from hsi_torch.optics import (
    DEFAULT_CAMERA,
    DEFAULT_GEOMETRY,
    BRFConfig,
    enumerate_sequences,
    trace_rays,
)
from hsi_torch.optics.sensor import DiffuserModel, SensorModel, cfa_index
from hsi_torch.simulate import render as render_module
from hsi_torch.simulate.render import CaptureRenderer, CaptureSpec, line_profile, subpixel_offsets
from hsi_torch.simulate.scenes import (
    CircleGridScene,
    ColorCheckerScene,
    CubeScene,
    FlatScene,
    USAF1951Scene,
    render_scene_image,
)


class _StripesScene:
    """A scene with only ``reflectance`` (no linear-mixture form): spectral stripes."""

    extent = (-10.0, 10.0, -10.0, 10.0)

    def reflectance(self, xy_mm: torch.Tensor, wavelengths_nm: torch.Tensor) -> torch.Tensor:
        wl = wavelengths_nm.to(xy_mm)
        return 0.5 + 0.4 * torch.sin(2.0 * xy_mm[:, :1] + wl[None] / 40.0)


def _scenes() -> list[CaptureSpec]:
    g = torch.Generator().manual_seed(3)
    cube = CubeScene(torch.rand(6, 9, 11, generator=g, dtype=torch.float64),
                     [420.0, 470.0, 520.0, 570.0, 620.0, 690.0], width_mm=6.0,
                     center_mm=(0.5, 1.0), extrapolate="edge")
    return [
        CaptureSpec("scan_450", "scan", None, 450.0),
        CaptureSpec("white", "scene", None),
        CaptureSpec("dark", "dark"),
        CaptureSpec("cc", "scene", ColorCheckerScene(width_mm=8.4, center_mm=(0.0, 1.4))),
        CaptureSpec("scan_610", "scan", None, 610.0),
        CaptureSpec("usaf", "scene", USAF1951Scene(groups=(0, 1), center_mm=(0.0, 1.0))),
        CaptureSpec("grid", "scene", CircleGridScene(radius_mm=0.38, rotation_rad=0.1,
                                                     translation_mm=(0.0, 0.9))),
        CaptureSpec("cube", "scene", cube),
        CaptureSpec("flat", "scene", FlatScene(spectrum_nm=[400, 550, 700],
                                               spectrum_values=[0.2, 0.8, 0.4])),
        CaptureSpec("stripes", "scene", _StripesScene()),
    ]


def _reference_blurred(r: CaptureRenderer, scene) -> CubeScene:
    """The scene on the fine grid, rasterised (2× supersampled) and blurred in float64."""
    sig = r.diffuser.blur_sigma_mm
    v = r.geometry.entrance_vertices(dtype=torch.float64)
    ext = (float(v[:, 0].min()) - 4 * sig, float(v[:, 0].max()) + 4 * sig,
           float(v[:, 1].min()) - 4 * sig, float(v[:, 1].max()) + 4 * sig)
    hd = r.layout.diffuser_homographies[0]
    spacing = 0.5 / float(torch.linalg.det(hd[:2, :2] / hd[2, 2]).abs().sqrt())
    w = int(min(1024, max(8, math.ceil((ext[1] - ext[0]) / spacing))))
    h = int(min(1024, max(8, math.ceil((ext[3] - ext[2]) / spacing))))
    fine = r.fine.to(torch.float64).cpu()
    img = render_scene_image(scene, ext, h, w, fine, supersample=2)
    img = DiffuserModel(blur_sigma_mm=sig).blur(img, min((ext[1] - ext[0]) / w,
                                                         (ext[3] - ext[2]) / h))
    return CubeScene(img, fine, extent_mm=ext, extrapolate="edge")


def _reference_render(r: CaptureRenderer, specs: list[CaptureSpec]) -> torch.Tensor:
    dev, dt = r.device, r.dtype
    h, w = r.sensor_size
    s = r.supersample
    ys, xs = torch.meshgrid(torch.arange(h, device=dev), torch.arange(w, device=dev),
                            indexing="ij")
    base = torch.stack([xs.reshape(-1), ys.reshape(-1)], -1).to(torch.float64)
    pts = (base[:, None] + subpixel_offsets(s, dev, torch.float64)[None]).reshape(-1, 2)
    geom = dataclasses.replace(r.geometry, max_reflections=r.max_reflections)
    tr = trace_rays(geom, r.camera, pts.to(dt), sequences=enumerate_sequences(r.max_reflections))
    keep = tr.view_index >= 0
    pix = (ys.reshape(-1) * w + xs.reshape(-1)).repeat_interleave(s * s)[keep]
    alpha, sigma, hit, t = tr.alpha[keep], tr.sigma[keep], tr.hit_xy[keep], tr.throughput[keep]
    fine = r.fine.to(dt)
    tst = r.stack_transmittance(alpha, sigma, r.geometry.brf_free_mask(hit), fine, exact=False)
    phi_w = (r.phi_fine * r.fine_widths * r.kappa).T.to(dt)  # (L, 3)
    g_obj = t * r.diffuser.falloff(alpha) * r.vignetting_factor(hit)
    out = torch.zeros(len(specs), 3, h * w, device=dev, dtype=dt)
    for k, sp in enumerate(specs):
        if sp.kind == "dark":
            continue
        if sp.kind == "scan":
            line = line_profile(torch.tensor([sp.wavelength_nm], device=dev), r.fine,
                                r.scan_fwhm_nm, r.scan_line)[0]
            wts = (line * r.fine_widths * r.kappa_scan)[:, None] * r.camera_sens.T
            e = (tst @ wts.to(dt)) * t[:, None]
        else:
            refl = (torch.ones_like(tst) if sp.scene is None
                    else _reference_blurred(r, sp.scene).reflectance(hit, fine).to(dt))
            e = ((tst * refl) @ phi_w) * g_obj[:, None]
        out[k].index_add_(1, pix, e.T / (s * s))
    return out.reshape(len(specs), 3, h, w)


def _renderer(device, dtype, output: str, chunk: int = 4096) -> CaptureRenderer:
    sensor = SensorModel(output=output, shot_noise=False, read_noise_e=0.0, quantize=False)
    # chunk: a few sensor rows per band, so the banded path really runs over many bands
    return CaptureRenderer(DEFAULT_GEOMETRY, DEFAULT_CAMERA.scaled(0.25), BRFConfig(), sensor,
                           diffuser=DiffuserModel(blur_sigma_mm=0.1), max_reflections=3,
                           dtype=dtype, device=device, chunk=chunk)


@pytest.fixture(scope="module")
def reference():
    """``get(dtype) -> (specs, (K, 3, H, W))``: the direct RGB rendering on the CPU (cached)."""
    specs = _scenes()
    cache: dict[torch.dtype, torch.Tensor] = {}

    def get(dtype: torch.dtype) -> tuple[list[CaptureSpec], torch.Tensor]:
        if dtype not in cache:
            cache[dtype] = _reference_render(_renderer("cpu", dtype, "rgb"), specs)
        return specs, cache[dtype].to(torch.float64)

    return get


@pytest.mark.parametrize("output", ["bayer", "rgb"])
def test_banded_render_equals_direct_reference(device, dtype, output, reference, monkeypatch):
    specs, ref = reference(dtype)
    r = _renderer(device, dtype, output)
    # small shading batches: several per band, some inside the cube scene, some outside it
    monkeypatch.setattr(render_module, "_SHADE_BATCH", 700)
    new = r.render(specs).cpu().to(torch.float64)
    if output == "bayer":  # each pixel keeps its CFA colour
        cfa = torch.tensor(cfa_index(r.sensor.cfa_pattern))
        ch = cfa.repeat(48, 50)
        ref = ref.gather(1, ch.expand(len(specs), 1, 96, 100))
    assert new.shape == ref.shape == (len(specs), 1 if output == "bayer" else 3, 96, 100)
    assert r.num_rays > 0.5 * 96 * 100 * 4
    assert not bool(new[2].any())  # dark
    # the same sums in another order; in float32 also the phase 2π·OPD/λ (≈ 250 rad) rounded
    # once instead of twice and float32 scene rasters
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    for k, sp in enumerate(specs):
        peak = float(ref[k].abs().max())
        assert sp.kind == "dark" or peak > 0.01, sp.name
        err = float((new[k] - ref[k]).abs().max())
        assert err <= tol * max(peak, 1e-30), (sp.name, err, peak)


def test_ground_truth_equals_direct_reference():
    """Scene truth and B of the banded renderer (cosine form, abundance rasters) against the
    direct formulas: float32 truth arrays agree to float32 rounding."""
    r = _renderer("cpu", torch.float64, "rgb")
    truth = r.ground_truth()
    lay = r.layout
    q = r.reference_pixels()
    x_ref = lay.sensor_to_diffuser(0, q)
    free = r.geometry.brf_free_mask(x_ref)
    lw = r.scan_line_weights(r.wavelengths)
    n_checked = 0
    for v in range(lay.num_views):
        p = lay.reference_to_view(v, q)
        tr = trace_rays(r.geometry, r.camera, p, sequences=lay.reflection_sequences)
        m = truth["view_mask"][v].reshape(-1)
        tst = r.stack_transmittance(tr.alpha[m], tr.sigma[m], free[m], r.fine, exact=False)
        b_ref = (tr.throughput[m, None] * (tst @ lw.T)).T.to(torch.float32)
        torch.testing.assert_close(truth["B"][v].reshape(len(lw), -1)[:, m], b_ref,
                                   rtol=0, atol=1e-7)
        n_checked += int(m.sum())
    assert n_checked > 500
    for sp in _scenes():
        if sp.kind != "scene" or sp.scene is None:
            continue
        pts = r.reference_diffuser_points(r.supersample)
        ref = _reference_blurred(r, sp.scene).reflectance(pts.reshape(-1, 2), r.wavelengths)
        ref = ref.reshape(pts.shape[0], pts.shape[1], -1).mean(1).T.reshape(truth["B"].shape[1:])
        torch.testing.assert_close(r.scene_truth(sp.scene), ref.to(torch.float32), rtol=0,
                                   atol=1e-7, msg=sp.name)


def test_cosine_form_equals_stack_transmittance():
    g = torch.Generator().manual_seed(1)
    a = torch.rand(500, generator=g, dtype=torch.float64) * 0.3
    s = (torch.rand(500, generator=g, dtype=torch.float64) - 0.5) * 2 * math.pi
    free = torch.rand(500, generator=g) < 0.2
    for brf in (BRFConfig(), BRFConfig(psi_deg=30.0, chi_deg=10.0)):
        r = CaptureRenderer(DEFAULT_GEOMETRY, DEFAULT_CAMERA.scaled(0.25), brf, SensorModel(),
                            max_reflections=2, polarizer_efficiency=0.8)
        ca, cb = r.stack_cosine_form()
        cos = r.retardance_cosine(a, s, free)
        t = torch.where(free[:, None], 1.0, ca + cb * cos)
        ref = r.stack_transmittance(a, s, free, r.fine, exact=False)
        torch.testing.assert_close(t, ref, rtol=0, atol=1e-12)
        assert float(ref[~free].max() - ref[~free].min()) > 0.15  # fringes
