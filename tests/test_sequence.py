"""Sequences: warm starts give the cold answers, the temporal prior lowers the error of a noisy
still scene and keeps out of a moving part, the drift path tracks a growing drift and flags a
jump, the moving scenes of the simulator move as specified. Tiny bundles (test_pipeline's) and
analytic scenes: fast."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from test_pipeline import make_bundle, render_capture, true_spectra

from hsi_torch.config import ConfigError
from hsi_torch.recon.frame import WarmStart
from hsi_torch.recon.nnls import _compiled as nnls_compiled
from hsi_torch.recon.nnls import nnls_kkt_residual, prepare_nnls
from hsi_torch.recon.pipeline import Reconstructor
from hsi_torch.recon.sequence import DriftPath, SequenceReconstructor
from hsi_torch.recon.settings import ReconstructSettings
from hsi_torch.simulate.motion import Illumination, Layer, LayeredScene, Motion

BACKENDS = ["torch"] + (["compiled"] if nnls_compiled.AVAILABLE else [])


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_warm_started_active_set_ends_at_the_cold_kkt_point(backend):
    """Starting from another frame's zero set changes the rounds, not the answer: the same x as
    the cold solve and the KKT residual within the tolerance on every pixel."""
    g = torch.Generator().manual_seed(0)
    P, O, M = 400, 30, 12
    A = torch.rand(P, O, M, generator=g, dtype=torch.float64)
    s0 = (torch.rand(P, M, generator=g, dtype=torch.float64) - 0.6).clamp_min(0)
    s1 = (s0 + 0.3 * torch.randn(P, M, generator=g, dtype=torch.float64)).clamp_min(0)
    prob = prepare_nnls(A, beta=0.5, diff_order=1)
    y0 = torch.einsum("pom,pm->po", A, s0) + 0.05 * torch.randn(
        P, O, generator=g, dtype=torch.float64
    )
    y1 = torch.einsum("pom,pm->po", A, s1) + 0.05 * torch.randn(
        P, O, generator=g, dtype=torch.float64
    )
    prev = prob.solve(y0, backend=backend).x
    assert int((prev == 0).sum()) > 2 * P  # a real zero set to start from
    cold = prob.solve(y1, backend=backend)
    warm = prob.solve(y1, backend=backend, x0=prev)
    torch.testing.assert_close(warm.x, cold.x, rtol=1e-9, atol=1e-9)
    G = prob.gram
    b = torch.einsum("pom,po->pm", A, y1)
    kkt = nnls_kkt_residual(G, b, warm.x, prob.gram_norm)
    assert bool(warm.converged.all()) and float(kkt.max()) <= 1e-10


def _frames(bundle, n: int, noise: float, seed: int = 0, change=None, growth: float = 0.02):
    """``n`` captures of spectra growing by ``growth`` a frame, with some exact zeros (pivoting
    pixels), Gaussian noise of ``noise`` DN; ``change(t, s)`` edits frame ``t``'s truth."""
    base = true_spectra(zeros=True)
    g = torch.Generator().manual_seed(seed)
    out = []
    for t in range(n):
        s = base * (1 + growth * t)
        if change is not None:
            s = change(t, s)
        img = render_capture(bundle, s)
        img = img + noise * torch.randn(img.shape, generator=g, dtype=img.dtype)
        out.append((s, img))
    return out


@pytest.mark.parametrize("prior", ["none", "tv"])
def test_warm_sequence_matches_cold_frames(prior):
    """The per-pixel warm start gives the cold cubes: the same KKT points, and with the spatial
    prior (its own warm start, on by default, turned off) the same start (this frame's
    per-pixel answer), so the same spatial answer."""
    bundle = make_bundle()
    kw = dict(beta=1e-3, dtype=torch.float64, drift_check=False, prior=prior)
    cold = Reconstructor(bundle, **kw)
    off = {"warm_spatial": False} if prior == "tv" else {}
    seq = SequenceReconstructor(cold.sensing, warm_start=True, **off, **kw)
    for _, img in _frames(bundle, 3, noise=0.5):
        a = cold.reconstruct_frame(img)
        b = seq.reconstruct(img)
        v = a.valid
        assert torch.equal(v, b.valid)
        torch.testing.assert_close(b.cube[:, v], a.cube[:, v], rtol=1e-8, atol=1e-8)
    assert seq.warm is not None and seq.warm.x is not None
    assert b.stats["sequence"]["warm"] and b.stats["sequence"]["frame"] == 2


def test_the_moved_test_reads_the_observations_and_divides_the_light_out():
    """``warm_spatial``: a pixel has moved when its observations changed by more than 4× the
    median change (against its shot noise) after the frame's gain is divided out, or when its
    mask changed; a flicker (every observation 10 % brighter) moves nothing."""
    from hsi_torch.recon.frame import _moved_pixels

    g = torch.Generator().manual_seed(0)
    prev = 10 + 90 * torch.rand(50, 12, generator=g, dtype=torch.float64)
    noise = 0.3 * prev.sqrt() * torch.randn(50, 12, generator=g, dtype=torch.float64)
    y = prev + noise
    y[7] += 40.0  # moved
    mask = torch.ones(50, 12, dtype=torch.bool)
    ok = torch.ones(50, dtype=torch.bool)
    ok[3] = False
    moved, gain = _moved_pixels(y, mask, prev, mask, ok)
    assert gain == pytest.approx(1.0, abs=0.05)  # the light did not change (one pixel moved)
    assert bool(moved[7]) and not bool(moved[3])  # an invalid pixel is never "moved"
    assert int(moved.sum()) <= 5
    flick = 1.1 * (prev + noise)
    moved2, gain2 = _moved_pixels(flick, mask, prev, mask, ok)
    assert gain2 == pytest.approx(1.1, rel=1e-2) and int(moved2.sum()) <= 3
    mask2 = mask.clone()
    mask2[11, 4] = False  # a saturated observation: the pixel's own mask changed
    moved3, _ = _moved_pixels(torch.where(mask2, flick, 0), mask2, prev, mask, ok)
    assert bool(moved3[11])


def test_the_temporal_prior_lowers_the_error_and_stays_out_of_a_moving_part():
    """A noisy still scene: by frame 3 the temporal prior's answer is closer to the truth than
    the independent frame's (the KKT conditions of the temporal problem hold). A patch that
    changes at frame 4 is gated out: its pixels keep their own (independent) answers."""
    bundle = make_bundle()
    kw = dict(beta=1e-3, dtype=torch.float64, drift_check=False)
    ind = Reconstructor(bundle, **kw)
    seq = SequenceReconstructor(ind.sensing, temporal="quadratic", **kw)

    def change(t: int, s: torch.Tensor) -> torch.Tensor:
        if t >= 4:
            s = s.clone()
            s[:, 10:16, 10:16] = s[:, 10:16, 10:16].flip(0) + 0.5
        return s

    frames = _frames(bundle, 6, noise=3.0, seed=2, change=change, growth=0.0)
    for t, (s, img) in enumerate(frames):
        a = ind.reconstruct_frame(img)
        b = seq.reconstruct(img)
        v = a.valid
        if t == 3:  # still scene so far
            ea = float((a.cube[:, v] - s[:, v]).norm())
            eb = float((b.cube[:, v] - s[:, v]).norm())
            assert eb < 0.8 * ea
            assert b.stats["sequence"]["temporal_static_fraction"] > 0.9
            assert b.stats["sequence"]["temporal_max_kkt"] <= 1e-10
        if t == 4:  # the patch changed: gated out
            patch = torch.zeros_like(v)
            patch[10:16, 10:16] = True
            pv = v & patch
            torch.testing.assert_close(b.cube[:, pv], a.cube[:, pv])
            assert b.stats["sequence"]["temporal_static"] <= int((v & ~patch).sum())


def test_temporal_settings_are_validated():
    with pytest.raises(ConfigError, match="temporal"):
        ReconstructSettings.from_flat(temporal="kalman")
    with pytest.raises(ConfigError, match="temporal"):
        ReconstructSettings.from_flat(temporal="quadratic", prior="tv")
    with pytest.raises(ConfigError, match="drift_window"):
        ReconstructSettings.from_flat(drift_window=1)
    with pytest.raises(ConfigError, match="temporal_weight"):
        ReconstructSettings.from_flat(temporal_weight=0)


def test_the_drift_path_tracks_a_growing_drift_and_flags_a_jump():
    """Measurements of a drift growing 0.1 px a frame with 0.05 px noise: the path is closer to
    the truth than the measurements (rms), within 0.1 px on every frame after the third; a 2 px
    jump is a ``drift.jump`` warning and the path restarts from it."""
    rng = np.random.default_rng(0)
    path = DriftPath(window=10, jump_px=0.5)
    err_m, err_p = [], []
    for t in range(30):
        true = np.array([0.1 * t, -0.05 * t, 0.0])
        meas = true + np.r_[rng.normal(0, 0.05, 2), 0.0]
        p, found = path.update(t, meas)
        assert found == []
        err_m.append(float(np.hypot(*(meas - true)[:2])))
        err_p.append(float(np.hypot(*(p - true)[:2])))
        if t >= 3:
            assert err_p[-1] < 0.1
    assert math.sqrt(np.mean(np.square(err_p[3:]))) < math.sqrt(np.mean(np.square(err_m[3:])))
    p, found = path.update(30, np.array([3.0 + 2.0, -1.5, 0.0]))
    assert [f.code for f in found] == ["drift.jump"] and found[0].severity == "warning"
    assert found[0].measured > 1.9 and found[0].limit == 0.5
    np.testing.assert_allclose(p, [5.0, -1.5, 0.0])  # restarted from the jump
    p, found = path.update(31, None)
    assert [f.code for f in found] == ["drift.unmeasured"]
    np.testing.assert_allclose(p, [5.0, -1.5, 0.0])


class _Stripes:
    """Reflectance = a band-independent ramp in x plus a step at y = 0 (analytic)."""

    extent = (-2.0, 2.0, -1.0, 1.0)

    def reflectance(self, xy: torch.Tensor, wl) -> torch.Tensor:
        r = 0.25 + 0.1 * xy[:, 0] + 0.2 * (xy[:, 1] > 0).to(xy.dtype)
        return r.unsqueeze(1).expand(-1, len(wl)).clone()


def test_moving_layers_move_as_specified():
    """Frame t of a layer translated, rotated and scaled shows the still layer at the inverse
    motion; the top layer covers the bottom one inside its moved extent; the illuminant's
    flicker and tilt are as specified."""
    wl = torch.tensor([450.0, 550.0, 650.0], dtype=torch.float64)
    still = _Stripes()
    mo = Motion(
        shift_mm_per_frame=(0.1, -0.05),
        rotation_deg_per_frame=3.0,
        scale_per_frame=0.01,
        centre_mm=(0.0, 0.0),
    )
    g = torch.Generator().manual_seed(0)
    pts = (torch.rand(500, 2, generator=g, dtype=torch.float64) - 0.5) * 1.5
    for t in (0, 4, 10):
        sc = LayeredScene([Layer(still, mo)], t)
        th, s = math.radians(3.0 * t), 1.01**t
        moved = torch.stack(
            [
                s * (math.cos(th) * pts[:, 0] - math.sin(th) * pts[:, 1]),
                s * (math.sin(th) * pts[:, 0] + math.cos(th) * pts[:, 1]),
            ],
            1,
        )
        moved = moved + torch.tensor([0.1 * t, -0.05 * t], dtype=torch.float64)
        torch.testing.assert_close(sc.reflectance(moved, wl), still.reflectance(pts, wl))

    # a top layer (a constant patch) covers the bottom one inside its moved extent only
    class _Patch:
        extent = (-0.2, 0.2, -0.2, 0.2)

        def reflectance(self, xy, w):
            return torch.full((xy.shape[0], len(w)), 0.9, dtype=xy.dtype)

    sc = LayeredScene([Layer(still), Layer(_Patch(), Motion(shift_mm_per_frame=(0.5, 0.0)))], 2)
    q = torch.tensor([[1.0, 0.0], [0.0, 0.5]], dtype=torch.float64)
    r = sc.reflectance(q, wl)
    assert torch.allclose(r[0], torch.full((3,), 0.9, dtype=torch.float64))
    torch.testing.assert_close(r[1], still.reflectance(q[1:], wl)[0])
    assert sc.extent[1] == pytest.approx(2.0)
    ill = Illumination(flicker=0.1, period_frames=4.0, tilt_per_frame=0.01)
    torch.testing.assert_close(ill.spectrum(1, wl), 1.1 * (1 + 0.01 * (wl - 550.0) / 100.0))
    torch.testing.assert_close(ill.spectrum(0, wl), torch.ones(3, dtype=torch.float64))


def test_warm_start_state_is_reset():
    w = WarmStart()
    w.x = torch.zeros(3, 2)
    w.reset()
    assert w.x is None and w.spatial_x is None and w.spatial_dual is None and w.spatial_u is None


@pytest.mark.parametrize("backend", BACKENDS)
def test_the_temporal_problem_solves_every_chunk_of_a_large_frame(backend):
    """The temporal prior's problem over more pixels than one chunk (a full-size frame has
    306 008 pixels, in chunks of 16 384): every chunk gets its own right-hand sides, and the
    answer is the minimiser of ``½sᵀGs − b̃ᵀs`` over ``s ≥ 0`` (KKT) on every pixel, the same as
    solved in one chunk."""
    from hsi_torch.recon.sequence import temporal_problem

    g = torch.Generator().manual_seed(3)
    P, O, M = 300, 30, 12
    A = torch.rand(P, O, M, generator=g, dtype=torch.float64)
    prob = prepare_nnls(A, beta=0.5, diff_order=1)
    s = (torch.rand(P, M, generator=g, dtype=torch.float64) - 0.5).clamp_min(0)
    y = torch.einsum("pom,pm->po", A, s) + 0.05 * torch.randn(P, O, generator=g,
                                                            dtype=torch.float64)
    prev = prob.solve(y, backend=backend).x
    b = torch.einsum("pom,po->pm", A, y)
    bt = (b + prob.gram_apply(prev)) / 2.0  # w = 1
    tp = temporal_problem(prob, P)
    chunked = tp.solve(bt, backend=backend, chunk_size=64)  # 5 chunks, the last one short
    whole = tp.solve(bt, backend=backend, chunk_size=P)
    kkt = nnls_kkt_residual(prob.gram, bt, chunked.x, prob.gram_norm)
    assert bool(chunked.converged.all()) and float(kkt.max()) <= 1e-10
    assert int((chunked.x == 0).sum()) > P  # constraints active: a real NNLS check
    torch.testing.assert_close(chunked.x, whole.x, rtol=1e-9, atol=1e-9)


def test_the_temporal_step_hands_the_sensing_contiguous_rows(monkeypatch):
    """The per-pixel answers and the previous frame's reach the sensing operator as ``(P, M)``
    rows in memory: on a transposed view ``torch.bmm`` runs one BLAS call per pixel on CPU
    (hundreds of seconds a full-size frame on a loaded machine instead of a fraction of one)."""
    from hsi_torch.forward_model import SensingModel

    seen: list[bool] = []
    a_orig = SensingModel.A

    def a_recorded(self, s, idx=None):
        seen.append(s.is_contiguous())
        return a_orig(self, s, idx)

    bundle = make_bundle()
    kw = dict(beta=1e-3, dtype=torch.float64, drift_check=False)
    seq = SequenceReconstructor(bundle, temporal="quadratic", **kw)
    frames = _frames(bundle, 2, noise=3.0, seed=2, growth=0.0)
    seq.reconstruct(frames[0][1])
    monkeypatch.setattr(SensingModel, "A", a_recorded)
    res = seq.reconstruct(frames[1][1])
    assert res.stats["sequence"]["temporal_static"] > 0  # the temporal step ran
    assert len(seen) >= 2 and all(seen)


def test_a_frame_is_demosaiced_once_for_the_solve_and_the_temporal_step(monkeypatch):
    """A Bayer frame of a temporal sequence (the drift path on too) is demosaiced once: the
    front door solves the frame as the sequence prepared it. The answers are those of the same
    frames given demosaiced (RGB), and the front door's per-capture handling of a mosaic holds:
    its demosaic time, and the noise model's Bayer layout (the first frame's standard deviations
    are those of the mosaic reconstructed alone, not of the RGB frame). A bad frame is named."""
    from hsi_torch.io.raw import mosaic
    from hsi_torch.recon import frame as frame_module

    demosaic = frame_module.demosaic_bilinear
    calls: list[int] = []

    def counted(*args):
        calls.append(1)
        return demosaic(*args)

    monkeypatch.setattr(frame_module, "demosaic_bilinear", counted)
    bundle = make_bundle()
    kw = dict(beta=1e-3, dtype=torch.float64, drift_check=False, uncertainty=True)
    seq_kw = dict(temporal="quadratic", drift_track=True, **kw)
    from_bayer = SequenceReconstructor(bundle, **seq_kw)
    from_rgb = SequenceReconstructor(from_bayer.base_sensing, **seq_kw)
    for t, (_, img) in enumerate(_frames(bundle, 2, noise=3.0, seed=2, growth=0.0)):
        bayer = mosaic(img, "RGGB")
        before = len(calls)
        a = from_bayer.reconstruct(bayer, cfa_pattern="RGGB")
        assert len(calls) == before + 1
        b = from_rgb.reconstruct(demosaic(bayer, "RGGB"))
        torch.testing.assert_close(a.cube, b.cube, rtol=0, atol=0, equal_nan=True)
        assert a.stats["sequence"] == b.stats["sequence"]
        assert "demosaic" in a.timings and "demosaic" not in b.timings
        if t == 0:
            alone = Reconstructor(from_bayer.base_sensing, **kw)
            c = alone.reconstruct_frame(bayer, cfa_pattern="RGGB")
            torch.testing.assert_close(a.std, c.std, rtol=0, atol=0, equal_nan=True)
            assert not torch.allclose(a.std.nan_to_num(), b.std.nan_to_num())
    assert a.stats["sequence"]["temporal_static"] > 0  # the temporal step ran
    with pytest.raises(ValueError, match="frame 2: sensor size"):  # named, as by the front door
        from_bayer.reconstruct(bayer[:, :-2], cfa_pattern="RGGB")
    with pytest.raises(ValueError, match=r"cam\.dng: image must be .* got \(40, 40\)"):
        from_bayer.reconstruct(bayer[0], source="cam.dng")
