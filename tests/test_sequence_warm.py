"""Warm starts of the spatial prior across frames (the ADMM's whole state carried: ``z``, the
scaled dual ``u``, the TV prox's dual) reach the cold optimum, and ``reconstruct --sequence``
uses the settings' ``sequence`` group (warm starts, temporal prior, drift path) end to end.
Tiny problems and test_pipeline's 4-view bundle: fast."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from test_pipeline import make_bundle, render_capture, true_spectra
from test_spatial import _condat_vu, _objective, _tiny

from hsi_torch.cli import main
from hsi_torch.recon.nnls import solve_nnls
from hsi_torch.recon.pipeline import Reconstructor
from hsi_torch.recon.sequence import SequenceReconstructor
from hsi_torch.recon.settings import ReconstructSettings
from hsi_torch.recon.spatial import _compiled as spatial_compiled
from hsi_torch.recon.spatial import prepare_spatial, solve_spatial

BACKENDS = ["torch"] + (["compiled"] if spatial_compiled.AVAILABLE else [])


def _two_frames(seed: int = 0):
    """A tiny spatial problem and a second frame of it: the same scene 3 % brighter with new
    noise (``b`` of both)."""
    A, y, G, b, active, (h, w) = _tiny("cpu", torch.float64, h=6, w=7, seed=seed)
    g = torch.Generator().manual_seed(seed + 100)
    y1 = 1.03 * (y - 0.0) + 0.05 * torch.randn(y.shape, generator=g, dtype=torch.float64)
    b1 = torch.einsum("pom,po->pm", A, y1)
    prob = prepare_spatial(G, torch.arange(h * w), (h, w), active)
    return A, y, y1, G, b, b1, active, prob, (h, w)


@pytest.mark.parametrize("relax", [1.0, 1.3, 1.7])
@pytest.mark.parametrize("backend", BACKENDS[-1:])  # compiled where numba is (torch: slow here;
def test_the_warm_state_reaches_the_cold_optimum(backend, relax):  # the masked test ties them)
    """Frame 1 solved from frame 0's final state (``z``, ``u``, TV dual; the rule checked every
    iteration; over-relaxed or not) ends at the same minimiser as its cold solve and as an
    independent primal-dual reference, to the solver's tolerance."""
    A, y, y1, G, b, b1, active, prob, (h, w) = _two_frames()
    # the torch backend's iterations are Python-bound: a looser tolerance keeps the test fast
    lam, (tol, close, fclose) = 0.5, ((1e-8, 1e-5, 1e-8) if backend == "compiled"
                                      else (1e-5, 1e-3, 1e-5))
    kw = dict(tol=tol, max_iter=20000, backend=backend)
    prev = solve_spatial(prob, b, lam, x0=solve_nnls(A, y).x, **kw)
    assert prev.u is not None and prev.u.shape == b.shape
    cold = solve_spatial(prob, b1, lam, x0=solve_nnls(A, y1).x, **kw)
    warm = solve_spatial(prob, b1, lam, x0=prev.x, u0=prev.u, dual0=prev.dual, check_every=1,
                         relax=relax, **kw)  # fmt: skip
    assert cold.converged and warm.converged
    assert float((warm.x - cold.x).abs().max()) < close
    ref = torch.from_numpy(_condat_vu(G.numpy(), b1.numpy(), lam, active.view(h, w).numpy(),
                                      20000))  # fmt: skip
    f_warm = _objective(G, b1, warm.x, lam, active.view(h, w), prob.to_cube)
    f_ref = _objective(G, b1, ref, lam, active.view(h, w), prob.to_cube)
    assert f_warm <= f_ref + fclose * abs(f_ref)
    assert float((warm.x - ref).abs().max()) < 10 * close
    assert float(warm.x.min()) >= 0


def test_the_whole_state_is_carried():
    """Restarted from its own final state, a solve of the same data is already converged: one
    iteration meets the rule (``x``, ``z``, ``u`` and the TV dual all carried; the compiled
    backend, the one that carries the TV dual). Started from the same ``z`` with the
    multiplier recomputed and a zero TV dual it is not."""
    if not spatial_compiled.AVAILABLE:
        pytest.skip("numba not installed")
    backend = "compiled"
    A, y, _, G, b, _, active, prob, _ = _two_frames(seed=1)
    kw = dict(tol=1e-3, max_iter=5000, backend=backend)
    first = solve_spatial(prob, b, 0.5, x0=solve_nnls(A, y).x, **kw)
    again = solve_spatial(prob, b, 0.5, x0=first.x, u0=first.u, dual0=first.dual,
                          check_every=1, **kw)  # fmt: skip
    assert again.converged and again.iterations == 1
    torch.testing.assert_close(again.x, first.x, atol=1e-3 * float(first.x.abs().max()), rtol=0)
    fresh = solve_spatial(prob, b, 0.5, x0=first.x, check_every=1, **kw)
    assert fresh.iterations > 1


@pytest.mark.parametrize("relax", [1.0, 1.3])
def test_the_masked_dual_start_is_the_same_on_both_backends(relax):
    """``u0`` on the masked rows, ``(b − G z)/ρ`` elsewhere: the torch and compiled backends run
    the same iterations from it (fixed count, same answer and final ``u`` to rounding; over-
    relaxed too, where the carried ``u`` is that of ``x̂``)."""
    if not spatial_compiled.AVAILABLE:
        pytest.skip("numba not installed")
    A, y, y1, G, b, b1, active, prob, _ = _two_frames(seed=2)
    prev = solve_spatial(prob, b, 0.7, x0=solve_nnls(A, y).x, tol=1e-4, max_iter=5000)
    mask = torch.zeros(b.shape[0], dtype=torch.bool)
    mask[::2] = True
    kw = dict(x0=prev.x, u0=prev.u, u0_mask=mask, tol=1e-30, max_iter=20, check_every=4,
              relax=relax)
    a = solve_spatial(prob, b1, 0.7, backend="compiled", **kw)
    t = solve_spatial(prob, b1, 0.7, backend="torch", **kw)
    assert a.iterations == t.iterations == 20
    torch.testing.assert_close(a.x, t.x, atol=1e-11, rtol=0)
    torch.testing.assert_close(a.u, t.u, atol=1e-9, rtol=0)


def test_a_kept_workspace_gives_the_same_iterations():
    """The ADMM's buffers kept between solves (a sequence's ``workspace``) hold the last solve's
    values; every one is written before it is read, so a solve with them runs the same
    iterations as with fresh buffers (the same answer, to the last bit)."""
    if not spatial_compiled.AVAILABLE:
        pytest.skip("numba not installed")
    A, y, y1, G, b, b1, active, prob, _ = _two_frames(seed=4)
    ws: dict = {}
    kw = dict(tol=1e-30, max_iter=12, backend="compiled")
    first = solve_spatial(prob, b, 0.6, x0=solve_nnls(A, y).x, workspace=ws, **kw)
    assert {"x", "p2", "b", "z"} <= set(ws) and "p" not in ws  # the dual is the answer's
    for dual in (None, first.dual):
        fresh = solve_spatial(prob, b1, 0.6, x0=first.x, u0=first.u, dual0=dual, **kw)
        kept = solve_spatial(prob, b1, 0.6, x0=first.x, u0=first.u, dual0=dual, workspace=ws,
                             **kw)  # fmt: skip
        assert torch.equal(kept.x, fresh.x) and torch.equal(kept.u, fresh.u)
        assert all(np.array_equal(k, f) for k, f in zip(kept.dual, fresh.dual, strict=True))


def test_the_start_state_and_the_norms_kernels():
    """The compiled start state takes the given scaled dual on the masked pixels (their ``G`` not
    read) and ``(b − G z)/ρ`` elsewhere, into kept buffers; the fused norms equal numpy's."""
    if not spatial_compiled.AVAILABLE:
        pytest.skip("numba not installed")
    rng = np.random.default_rng(0)
    P, m, rho = 301, 5, 0.7
    R = rng.normal(size=(P, m, m))
    G = np.ascontiguousarray(R @ R.transpose(0, 2, 1))
    b, z0 = rng.normal(size=(P, m)), rng.normal(size=(P, m))
    u0 = rng.normal(size=(m, P))
    use = rng.random(P) < 0.6
    slot = np.full(P, -1, np.int64)
    none = np.zeros((1, m, m))
    bT, zT, uT = spatial_compiled.start_state(b, z0, G, slot, none, rho)
    z = np.maximum(z0, 0)
    np.testing.assert_allclose(uT.T, (b - np.einsum("pij,pj->pi", G, z)) / rho, atol=1e-12)
    np.testing.assert_array_equal(zT, z.T)
    out = tuple(np.full((m, P), np.nan) for _ in range(3))
    bT2, zT2, uT2 = spatial_compiled.start_state(b, z0, G, slot, none, rho, True, u0, use, out)
    assert bT2 is out[0] and uT2 is out[2]
    np.testing.assert_array_equal(uT2[:, use], u0[:, use])
    np.testing.assert_array_equal(uT2[:, ~use], uT[:, ~use])
    np.testing.assert_array_equal(bT2, b.T)
    x, zp = rng.normal(size=(m, P)), rng.normal(size=(m, P))
    got = spatial_compiled.norms3(zT, x, zp)
    want = (np.linalg.norm(zT), np.linalg.norm(x - zT), np.linalg.norm(zT - zp))
    np.testing.assert_allclose(got, want, rtol=1e-12)


def test_the_subset_solve_skips_the_zeroed_pixels():
    """A warm frame's per-pixel subset is the frame's compiled solve with the other pixels'
    observations zeroed: those answer ``x = 0`` at once (their KKT point: ``b = 0``), the subset
    exactly as in the whole frame's solve, which meets the KKT conditions."""
    from hsi_torch.forward_model import SensingModel
    from hsi_torch.recon.nnls import _compiled as nnls_compiled
    from hsi_torch.recon.nnls import prepare_nnls

    if not nnls_compiled.AVAILABLE:
        pytest.skip("numba not installed")
    g = torch.Generator().manual_seed(5)
    P, V, C, M = 500, 6, 3, 25
    B = torch.rand(P, V, M, generator=g, dtype=torch.float64)
    model = SensingModel(B, 0.7 + 0.4 * torch.rand(P, V, generator=g, dtype=torch.float64),
                         torch.rand(C, M, generator=g, dtype=torch.float64) * 20)
    s = torch.rand(P, M, generator=g, dtype=torch.float64)
    y = torch.einsum("pom,pm->po", model.dense(), s)
    y = y + 0.5 * torch.randn(y.shape, generator=g, dtype=torch.float64)
    prob = prepare_nnls(model, beta=10.0)
    whole = prob.solve(y, backend="compiled")
    assert float(whole.kkt_residual.max()) < 1e-9
    sub = torch.rand(P, generator=g) < 0.35
    part = prob.solve(y * sub.unsqueeze(1).to(y.dtype), backend="compiled")
    torch.testing.assert_close(part.x[sub], whole.x[sub], rtol=0, atol=1e-12)
    assert bool((part.x[~sub] == 0).all()) and bool((part.kkt_residual[~sub] == 0).all())
    assert bool(part.converged.all()) and bool((part.iterations[~sub] == 0).all())
    assert float((whole.x[~sub] > 0).float().mean()) > 0.5  # they had answers of their own


def test_the_kept_frame_constants_follow_the_valid_pixels(monkeypatch):
    """A sequence's workspace keeps the frame's TV graph and ``λ``'s data scale with the valid
    pixels they were made for: a frame with other valid pixels (e.g. some saturated) makes
    them again, and every frame's answer and ``λ`` are those of a solve without the
    workspace."""
    import hsi_torch.recon.frame as frame_mod
    from hsi_torch.recon.spatial.frame import solve_frame

    args: dict = {}
    real = frame_mod.spatial_solve_frame

    def spy(*a, **k):
        args["a"] = a
        return real(*a, **k)

    monkeypatch.setattr(frame_mod, "spatial_solve_frame", spy)
    bundle = make_bundle()
    rec = Reconstructor(bundle, beta=1e-3, dtype=torch.float64, drift_check=False, prior="tv")
    rec.reconstruct_frame(render_capture(bundle, true_spectra()))
    sens, y, mask, ok, changed, x0 = args["a"]
    fewer = ok.clone()
    fewer[ok.nonzero()[::3, 0]] = False
    ws: dict = {}
    lams, consts = [], []
    for valid in (ok, ok, fewer, ok):
        kept_x, kept = solve_frame(sens, y, mask, valid, changed, x0, workspace=ws)
        fresh_x, fresh = solve_frame(sens, y, mask, valid, changed, x0)
        assert kept["lam_abs"] == fresh["lam_abs"]
        assert torch.equal(kept_x, fresh_x)
        assert torch.equal(ws["frame_constants"][1], valid)
        lams.append(kept["lam_abs"])
        consts.append(ws["frame_constants"])
    assert lams[0] == lams[1] == lams[3] != lams[2]
    assert consts[0] is consts[1] and consts[2] is not consts[1] and consts[3] is not consts[2]


def test_frames_without_a_warm_start_reuse_the_bundles_buffers():
    """Frames solved one after another without a warm start keep the ADMM's buffers and frame
    constants on the bundle's sensing (``spatial_workspace``): each cube is, to the last bit,
    that of a reconstructor that solves only that frame."""
    if not spatial_compiled.AVAILABLE:
        pytest.skip("numba not installed")
    bundle = make_bundle()
    kw = dict(beta=1e-3, dtype=torch.float64, drift_check=False, prior="tv")
    rec = Reconstructor(bundle, **kw)
    g = torch.Generator().manual_seed(3)
    for t in range(3):
        img = render_capture(bundle, true_spectra(seed=t))
        img = img + 0.3 * torch.randn(img.shape, generator=g, dtype=img.dtype)
        kept = rec.reconstruct_frame(img)
        # the iteration buffers, and the answer's dual and scaled dual handed back
        assert {"x", "z", "b", "u", "p", "psum", "frame_constants"} <= set(
            rec.sensing.spatial_workspace)
        fresh = Reconstructor(bundle, **kw).reconstruct_frame(img)
        torch.testing.assert_close(kept.cube, fresh.cube, rtol=0, atol=0, equal_nan=True)
        assert torch.equal(kept.valid, fresh.valid)
        assert kept.stats["spatial_iterations"] == fresh.stats["spatial_iterations"]
    import pickle

    assert pickle.loads(pickle.dumps(rec.sensing)).spatial_workspace == {}


def test_threads_sharing_the_bundles_buffers_get_their_own_answers():
    """Frames of one reconstructor solved from two threads at once: a solve takes each kept
    buffer out of ``spatial_workspace`` while it uses it, so every cube is still the one its
    own frame gives alone."""
    import threading

    bundle = make_bundle()
    kw = dict(beta=1e-3, dtype=torch.float64, drift_check=False, prior="tv")
    rec = Reconstructor(bundle, **kw)
    images = [render_capture(bundle, true_spectra(seed=s)) for s in (5, 6)]
    alone = [Reconstructor(bundle, **kw).reconstruct_frame(img).cube for img in images]
    start = threading.Barrier(2)
    bad: list[str] = []

    def run(k: int) -> None:
        start.wait()
        for _ in range(3):
            cube = rec.reconstruct_frame(images[k]).cube
            if not torch.allclose(cube, alone[k], rtol=0, atol=0, equal_nan=True):
                bad.append(f"thread {k}")

    threads = [threading.Thread(target=run, args=(k,)) for k in (0, 1)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert bad == []


def test_bad_warm_states_are_named():
    A, y, _, G, b, _, active, prob, _ = _two_frames()
    with pytest.raises(ValueError, match="check_every"):
        solve_spatial(prob, b, 0.5, check_every=0)
    with pytest.raises(ValueError, match="u0 must be"):
        solve_spatial(prob, b, 0.5, u0=torch.zeros(3, 4, dtype=b.dtype))
    with pytest.raises(ValueError, match="u0_mask must be"):
        solve_spatial(prob, b, 0.5, u0=torch.zeros_like(b), u0_mask=torch.ones(2, dtype=bool))


def test_warm_spatial_frames_stay_at_the_cold_answers():
    """A sequence with ``warm_spatial``: every frame after the first is warm-started (its static
    pixels counted, the gain measured) and its cube agrees with the cold solve of the same
    frame to the spatial solve's tolerance."""
    bundle = make_bundle()
    kw = dict(beta=1e-3, dtype=torch.float64, drift_check=False, prior="tv")
    cold = Reconstructor(bundle, **kw)
    seq = SequenceReconstructor(cold.sensing, warm_spatial=True, **kw)
    base = true_spectra()
    g = torch.Generator().manual_seed(0)
    for t in range(3):
        img = render_capture(bundle, base * (1 + 0.02 * t))
        img = img + 0.3 * torch.randn(img.shape, generator=g, dtype=img.dtype)
        a = cold.reconstruct_frame(img)
        r = seq.reconstruct(img)
        v = a.valid & r.valid
        err = float((r.cube[:, v] - a.cube[:, v]).norm() / a.cube[:, v].norm())
        assert err < 2e-2, (t, err)  # the ADMM's relative tolerance (1e-2) on both
        if t:
            assert r.stats["spatial_warm_static"] > 0
            assert r.stats["spatial_warm_gain"] == pytest.approx(1.02, abs=0.02)
    assert seq.warm is not None and seq.warm.spatial_u is not None


def test_a_warm_frame_solves_per_pixel_only_where_its_answer_is_used(monkeypatch):
    """``warm_spatial`` with a noise estimate on 8 sampled pixels: on a warm frame the per-pixel
    problem is solved on the moved pixels, the samples and nothing else; a patch that changes
    is moved, starts the ADMM from its own per-pixel answer (the cold solve's, exactly), and
    every frame's cube and ``λ`` agree with its cold solve (the same noise estimate, the ADMM's
    tolerance)."""
    import hsi_torch.recon.frame as frame_mod
    import hsi_torch.recon.spatial.noise as noise_mod

    monkeypatch.setattr(noise_mod, "NOISE_SAMPLES", 8)
    seen: dict = {}
    real_moved, real_spatial = frame_mod._moved_pixels, frame_mod.spatial_solve_frame

    def spy_moved(*a, **k):
        seen["moved"], seen["gain"] = real_moved(*a, **k)
        return seen["moved"], seen["gain"]

    def spy_spatial(*a, **k):
        seen["start"] = k.get("start")
        return real_spatial(*a, **k)

    monkeypatch.setattr(frame_mod, "_moved_pixels", spy_moved)
    monkeypatch.setattr(frame_mod, "spatial_solve_frame", spy_spatial)
    bundle = make_bundle()
    kw = dict(beta=1e-3, dtype=torch.float64, drift_check=False, prior="tv")
    cold = Reconstructor(bundle, **kw)
    per_pixel = Reconstructor(cold.sensing, **{**kw, "prior": "none"})
    seq = SequenceReconstructor(cold.sensing, warm_spatial=True, **kw)
    sens = cold.sensing
    h, w = sens.frame_size
    pix = sens.pixel_index
    base = true_spectra()
    g = torch.Generator().manual_seed(3)
    for t in range(3):
        s = base * (1 + 0.03 * t)
        if t == 2:  # a patch changes its spectrum
            s = s.clone()
            s[:, 10:15, 10:15] = s[:, 10:15, 10:15].flip(0) * 1.5
        img = render_capture(bundle, s)
        img = img + 0.3 * torch.randn(img.shape, generator=g, dtype=img.dtype)
        a = cold.reconstruct_frame(img)
        seen.clear()
        r = seq.reconstruct(img)
        v = a.valid & r.valid
        err = float((r.cube[:, v] - a.cube[:, v]).norm() / a.cube[:, v].norm())
        assert err < 2e-2, (t, err)
        assert r.stats["lam_abs"] == pytest.approx(a.stats["lam_abs"], rel=1e-9)
        if t == 0:
            assert "moved" not in seen and "per_pixel_solved" not in r.stats
            continue
        moved = seen["moved"]
        n_valid = r.stats["num_valid"]
        assert r.stats["per_pixel_solved"] <= int(moved.sum()) + 8 < n_valid
        assert r.stats["spatial_warm_gain"] == pytest.approx(1 + 0.03 * t, rel=0.03, abs=0.02)
        patch = torch.zeros(h, w, dtype=torch.bool)
        patch[10:15, 10:15] = True
        in_patch = patch.reshape(-1)[pix] & r.valid.reshape(-1)[pix]
        if t == 1:
            assert int(moved.sum()) < n_valid // 4  # a flicker is not motion
        else:
            assert bool(moved[in_patch].all())
            own = per_pixel.reconstruct_frame(img).cube.reshape(sens.num_bands, -1)[:, pix].T
            torch.testing.assert_close(seen["start"][in_patch], own[in_patch], rtol=1e-9,
                                       atol=1e-9)


def test_warm_noise_reuses_the_noise_level_while_the_light_holds():
    """``warm_noise``: frames within 10 % of the light of the frame whose noise level was
    estimated reuse it (and its ``λ``), said in the statistics; a frame 30 % brighter
    estimates its own again."""
    bundle = make_bundle()
    kw = dict(beta=1e-3, dtype=torch.float64, drift_check=False, prior="tv")
    seq = SequenceReconstructor(bundle, warm_spatial=True, warm_noise=True, **kw)
    base = true_spectra()
    g = torch.Generator().manual_seed(1)
    stats = []
    for gain in (1.0, 1.03, 1.05, 1.4):
        img = render_capture(bundle, base * gain)
        img = img + 0.3 * torch.randn(img.shape, generator=g, dtype=img.dtype)
        stats.append(seq.reconstruct(img).stats)
    assert [s["noise_sigma_given"] for s in stats] == [False, True, True, False]
    assert stats[1]["lam_abs"] == stats[2]["lam_abs"] == stats[0]["lam_abs"]
    assert stats[3]["lam_abs"] != stats[0]["lam_abs"]


# ---------------------------------------------------------------------------------------------
# reconstruct --sequence with the sequence group


def test_the_sequence_settings_are_yaml_keys():
    from hsi_torch.recon.config import ReconstructConfig

    cfg = ReconstructConfig(warm_spatial=False, prior="tv", drift_track=True)
    s = cfg.settings()
    assert not s.sequence.warm_spatial and s.sequence.drift_track
    assert ReconstructSettings().sequence.warm_spatial  # on by default
    msgs = ReconstructSettings.from_flat({"warm_noise": True}).inert()
    assert any("warm_noise" in m for m in msgs)


def test_reconstruct_sequence_uses_the_sequence_group(tmp_path: Path):
    """``--set temporal=quadratic --set warm_start=true --set drift_track=true``: the CLI's
    store holds what :class:`SequenceReconstructor` gives the same files in Python (the
    temporal prior acting from the second frame on), and each frame's metadata says it."""
    pytest.importorskip("zarr")
    pytest.importorskip("xarray")
    from hsi_torch.io.sequence_store import open_sequence_store

    bundle_path = tmp_path / "calib.npz"
    make_bundle(white_exposure_s=0.01, cfa_pattern="RGGB").save(bundle_path)
    bundle = make_bundle()
    shots = tmp_path / "shots"
    shots.mkdir()
    g = torch.Generator().manual_seed(0)
    for k in range(3):
        img = render_capture(bundle, true_spectra(seed=10))
        img = img + 0.5 * torch.randn(img.shape, generator=g, dtype=img.dtype)
        np.save(shots / f"s_t={0.5 * k}s.npy", img.numpy())
    keys = {"temporal": "quadratic", "warm_start": True, "drift_track": True}
    sets = ["--set", "dtype=float64", "--set", "beta=0.001"]
    for k, v in keys.items():
        sets += ["--set", f"{k}={str(v).lower()}"]
    out = tmp_path / "out"
    assert main(["reconstruct", "--bundle", str(bundle_path), "--out", str(out),
                 "--no-progress", *sets, "--sequence", str(shots / "*.npy")]) == 0  # fmt: skip
    ds = open_sequence_store(out / "sequence.zarr")
    assert ds.sizes["time"] == 3
    seq = SequenceReconstructor(bundle_path, dtype=torch.float64, beta=1e-3, **keys)
    plain = Reconstructor(bundle_path, dtype=torch.float64, beta=1e-3)
    for k in range(3):
        src = shots / f"s_t={0.5 * k}s.npy"
        ref = seq.reconstruct_file(src)
        cube = ds.cube.isel(time=k).values
        want = torch.where(ref.valid, ref.cube, torch.nan).numpy()
        assert np.allclose(cube, want, rtol=1e-6, atol=1e-8, equal_nan=True)
        meta = json.loads(ds.metadata[k].values.item())
        st = meta["stats"]["sequence"]
        assert st["frame"] == k and "drift_measured" in st  # the path was asked for
        if k:
            assert st["temporal_static"] > 0
            ind = plain.reconstruct_file(src)  # the temporal prior changed the answer
            assert not np.allclose(cube, torch.where(ind.valid, ind.cube, torch.nan).numpy(),
                                   rtol=1e-6, atol=1e-8, equal_nan=True)  # fmt: skip
