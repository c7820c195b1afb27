#!/usr/bin/env python
"""Benchmark: one full-size frame through the reconstruction pipeline, stage by stage, against
what a skilled user would run instead and against the machine's limit — in one run.

Synthetic bundle at the original prototype's scale: ten views as ``w × h`` tiles (translations,
some mirrored or rotated by 180°) on a ``2h × 5w`` sensor; the valid region is the equilateral
triangle inscribed in the reference tile (≈ 3.2·10⁵ px for the default 860 × 745 tile); BRF-like
``B = ½[1 − cos(2π·OPD_v(p)/λ)]`` with per-view OPDs 1.5–6 µm varying ±2 % over the frame, smooth
gains 0.7–1.1, Gaussian ``φ`` (peak 255 DN for a white pixel). The capture (uint16 RGB TIFF,
0.1 % of the samples clipped at the white level) is rendered with the exact forward model.

Stages timed (hsi_torch) on ``--frames`` frames: load (``read_any``), warp (one batched kornia
``remap`` of the valid pixels), observations, solve (factorisation reused + exact re-solves of
saturated pixels), assemble, write (NPZ + TIFF + ENVI + preview PNG, concurrently). The best
frame (by total) and the median frame are compared. The one-off per-bundle precomputation is
reported separately, cold (computed from the bundle file; writing its cache entry timed apart)
and cached (a second process: the bundle hashed, the entry checked and memory-mapped; the frames
then run on those factors). β defaults to the reconstruct configuration's (1e4).

Baselines (``scripts/nnls_baselines.py``), each on this frame's stacked problems
``[A_p[mask_p]; √β D] x ≈ [y_p[mask_p]; 0]`` in float64, best of ``--scipy-repeats``, scaled to the
frame's pixels; the other stages are charged at our times:

* ``SciPy loop``: ``scipy.optimize.nnls`` per pixel in this process (``--subset`` pixels);
* ``SciPy pool (N)``: the same loop over all N CPUs — a ``spawn`` process pool, chunks of
  ``--pool-chunk`` pixels (``--pool-subset`` pixels; the pool is started and warmed up first);
* ``compiled LH (1 thr)`` / ``(N thr)``: a compiled (numba) Lawson–Hanson loop in the ``fnnls``
  form, one pixel after another (its answers are checked against SciPy's on the first subset),
  in one thread and with the pixels split between torch's thread count of threads.

The headline is our solve stage against the fastest of them.

The machine's limit: the prepared problem's own solve (``NNLSProblem.solve``, no re-solves)
against a pass that only reads the per-pixel tensors that solve reads (``y``, the static mask,
the factored ``B`` and gains, ``G``, ``G⁻¹``, ``diag G``, the ``‖G‖`` bound, the flags: a torch
or NumPy sum, the faster) and one that does the unavoidable arithmetic (``b = Aᵀ W y`` from the
factors and ``x₀ = G⁻¹ b``, one fused numba pass), with the same threads, interleaved with the
solve so that a busy machine slows all alike; bytes and GB/s are printed.

The spatial-spectral mode (``prior="tv"``, relative weight ``--lam``) is timed on the same frames
beside it (``--spatial-frames``, after one warm-up that factorises ``G + ρI``): its solve stage
(per-pixel warm start + ADMM) and whole frame, and their ratios to the per-pixel ones. Peak RSS
is reported per mode (the per-pixel frames, the TV frames, each baseline; the SciPy pool's is
this process's plus its workers' peaks).

Usage::

    python scripts/bench_pipeline.py                 # full size, float32, cpu
    python scripts/bench_pipeline.py --tile 300 260 --natural skip --frames 2 \
        --spatial-frames 1 --subset 200 --pool-subset 1000     # small quick run
    hsi-torch bench pipeline -- --device cuda
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from hsi_torch.io.bundle import CalibrationBundle
from hsi_torch.profiling import peak_rss_gib
from hsi_torch.recon.checks import exposure_scale
from hsi_torch.recon.frame import observations_from_samples, sample_views
from hsi_torch.recon.pipeline import Reconstructor
from hsi_torch.recon.spatial import DEFAULT_LAM
from hsi_torch.spectral import DEFAULT_GRID, band_widths, difference_matrix

sys.path.insert(0, str(Path(__file__).resolve().parent))  # also when run through runpy
import nnls_baselines  # noqa: E402  (scripts/nnls_baselines.py)
from memory_probes import RssSampler  # noqa: E402


def _sync(dev: torch.device) -> None:
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def timed_reconstructor(
    bundle: CalibrationBundle, args: argparse.Namespace, dev: torch.device, dtype: torch.dtype,
    tmp: Path, name: str,
) -> tuple[Reconstructor, dict[str, float]]:
    """The per-bundle precomputation, cold and cached, as a user meets it: the bundle saved to a
    file, one reconstructor made from it with an empty precomputation cache (computed, then
    written: the write timed apart), then, as a second process would (this process's caches
    cleared), one that loads the entry. The second is returned (its factors memory-mapped)."""
    from hsi_torch.recon import precompute_cache as disk
    from hsi_torch.recon.sensing import clear_sensing_cache

    path = tmp / f"{name}.npz"
    bundle.save(path)
    folder = tmp / f"cache_{name}"
    kw = dict(beta=args.beta, diff_order=args.diff_order, device=dev, dtype=dtype,
              precompute_cache=str(folder))
    spent = {"write": 0.0}
    save = disk.save_entry

    def timed_save(*a, **k):
        t = time.perf_counter()
        try:
            return save(*a, **k)
        finally:
            spent["write"] += time.perf_counter() - t

    disk.save_entry = timed_save
    try:
        t0 = time.perf_counter()
        rec = Reconstructor(path, **kw)
        _sync(dev)
        t_cold = time.perf_counter() - t0
    finally:
        disk.save_entry = save
    del rec
    clear_sensing_cache()
    disk._HASHES.clear()  # a new process hashes the bundle again
    t0 = time.perf_counter()
    rec = Reconstructor(path, **kw)
    _sync(dev)
    t_hit = time.perf_counter() - t0
    size = sum(p.stat().st_size for p in folder.glob("*.hsicache/*"))  # entry folders
    times = {"precompute_s": t_cold - spent["write"], "cache_write_s": spent["write"],
             "cached_s": t_hit, "cache_gib": size / 2**30}
    print(f"  precomputation of {path.name}: cold {times['precompute_s']:.2f} s (+ "
          f"{spent['write']:.2f} s writing the {times['cache_gib']:.2f} GiB cache entry), "
          f"cached (a second process: hash the bundle, check and map the entry) {t_hit:.2f} s")
    return rec, times


def make_bundle(w: int, h: int, seed: int = 0) -> CalibrationBundle:
    """Ten tiles ``w × h`` in a 2 × 5 grid; reference = tile 0 (see the module docstring)."""
    g = np.random.default_rng(seed)
    V = 10
    wl = np.asarray(DEFAULT_GRID.wavelengths_nm, dtype=np.float64)
    M = wl.size
    Hs, tris, par = [], [], []
    for v in range(V):
        r, c = divmod(v, 5)
        ox, oy = c * w, r * h
        kind = v % 3 if v else 0  # 0 translate, 1 mirror x, 2 rotate 180°
        if kind == 0:
            Hv = np.array([[1, 0, -ox], [0, 1, -oy], [0, 0, 1.0]])
        elif kind == 1:
            Hv = np.array([[-1, 0, ox + w - 1], [0, 1, -oy], [0, 0, 1.0]])
        else:
            Hv = np.array([[-1, 0, ox + w - 1], [0, -1, oy + h - 1], [0, 0, 1.0]])
        Hs.append(Hv)
        par.append(-1 if kind == 1 else 1)
        tris.append([[ox, oy + h - 1], [ox + w - 1, oy + h - 1], [ox + (w - 1) / 2, oy]])
    yy, xx = np.meshgrid(np.arange(h, dtype=np.float32), np.arange(w, dtype=np.float32),
                         indexing="ij")
    # equilateral triangle with its base on the bottom row, apex at the top centre
    half = (w - 1) / 2
    valid = np.abs(xx - half) <= (yy / max(h - 1, 1)) * half
    opd = np.linspace(1500.0, 6000.0, V)[g.permutation(V)].astype(np.float32)
    ramp = 1 + 0.02 * ((xx / w - 0.5) + 0.5 * (yy / h - 0.5))
    B = np.empty((V, M, h, w), np.float32)
    for v in range(V):
        B[v] = 0.5 * (1 - np.cos(2 * np.pi * opd[v] * ramp[None] / wl[:, None, None]))
    gain = (0.7 + 0.4 * g.random((V, 1, 1)) * (1 - 0.1 * ((xx / w - 0.5) ** 2)
                                               + 0.05 * (yy / h))).astype(np.float32)
    cen = np.array([600.0, 540.0, 460.0])[:, None]
    phi = np.exp(-0.5 * ((wl[None] - cen) / 40.0) ** 2)
    dl = band_widths(torch.as_tensor(wl)).numpy()
    phi *= 255.0 / float((0.5 * dl * phi).sum(1).max() * 1.1)  # white ≈ 255 DN at most
    vm = np.broadcast_to(valid, (V, h, w)).copy()
    return CalibrationBundle(
        wavelengths_nm=wl, triangles=np.array(tris), parity=np.array(par),
        view_homographies=np.stack(Hs), sensor_size=(2 * h, 5 * w), reference_bbox=(0, 0, w, h),
        B=B, phi=phi, gain=gain, view_mask=vm, modulated=vm, valid=valid,
        settings={"white_exposure_s": 0.01, "synthetic": "bench_pipeline"},
    )  # fmt: skip


def render(rec: Reconstructor, bundle: CalibrationBundle, seed: int = 1) -> np.ndarray:
    """Exact forward model ``y = A s`` for smooth random spectra, placed on the sensor."""
    sens = rec.sensing
    P, O, M = sens.num_pixels, 3 * sens.num_views, sens.num_bands
    h, w = sens.frame_size
    g = torch.Generator().manual_seed(seed)
    lam = torch.linspace(0, 1, M)
    yy, xx = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    centre = (0.5 + 0.4 * torch.sin(6 * xx) * torch.cos(5 * yy)).reshape(-1)[sens.pixel_index]
    amp = (0.2 + 0.75 * torch.rand(P, 1, generator=g)).to(sens.device)
    s = amp * torch.exp(-0.5 * ((lam.view(1, M) - centre.view(-1, 1)) / 0.25) ** 2).to(amp)
    y = sens.model.A(s.to(sens.dtype)).cpu().numpy()  # (P, 3V)
    H, W = sens.sensor_size
    img = np.zeros((3, H, W), np.float64)
    pix = sens.pixel_index.cpu().numpy()
    ref = np.stack([pix % w, pix // w, np.ones_like(pix)]).astype(np.float64)
    for v in range(O // 3):
        q = np.rint(np.linalg.inv(bundle.view_homographies[v]) @ ref).astype(np.int64)
        img[:, q[1], q[0]] = y[:, 3 * v : 3 * v + 3].T
    return img


FRAME_STAGES = ("load", "warp", "observations", "solve", "assemble", "write")


def bench_frame(
    label: str, rec: Reconstructor, cap_path: Path, args: argparse.Namespace, tmp: Path
) -> dict:
    """Time ``args.frames`` reconstructions of one capture, stage by stage, and the SciPy loop on
    ``args.subset`` of the same pixels (observations and masks of the same frame)."""
    from hsi_torch.io import read_any
    from hsi_torch.recon.batch.run import write_outputs
    from hsi_torch.recon.config import ReconstructConfig

    sens = rec.sensing
    dev, dtype = sens.device, sens.dtype
    P = sens.num_pixels
    cfg = ReconstructConfig(beta=args.beta, diff_order=args.diff_order)
    sampler = RssSampler()
    sampler.start()
    t_start = time.perf_counter()
    best: dict[str, float] = {}
    best_w: dict[str, float] = {}
    frames: list[dict[str, float]] = []
    print(f"\n== {label}: {cap_path.name}, {P} valid pixels, sensor {sens.sensor_size}")
    for i in range(args.frames):
        times: dict[str, float] = {}
        t = time.perf_counter()
        cap = read_any(cap_path, expected_size=sens.sensor_size, dtype=dtype, device=dev,
                       default_cfa_pattern=sens.cfa_pattern)
        _sync(dev)
        times["load"] = time.perf_counter() - t
        res = rec.reconstruct_capture(cap)
        for k in ("warp", "observations", "solve", "assemble"):
            times[k] = res.timings[k]
        t = time.perf_counter()
        wt: dict[str, float] = {}
        write_outputs(res, tmp / f"out{i}", cfg, {"bench": True}, timings=wt)
        times["write"] = time.perf_counter() - t
        times["total"] = sum(times.values())
        frames.append(times)
        print(f"  frame {i}: " + ", ".join(f"{k} {v:.3f}" for k, v in times.items()))
        if not best or times["total"] < best["total"]:
            best, best_w = times, wt
    peak = sampler.peak(t_start, time.perf_counter())
    sampler.stop()
    st = res.stats
    print(f"  {st['num_valid']} valid, {st['saturated_observations']} saturated observations, "
          f"{st['num_resolved']} pixels re-solved with their own mask, {st['num_pivoted']} "
          f"active-set corrections ({100 * st['num_pivoted'] / max(1, st['num_valid']):.0f} %), "
          f"{st['num_not_converged']} not converged, max KKT {st['max_kkt']:.1e}, "
          f"fit residual {st['fit_residual']:.3f}")

    # baselines: same stages, solver = what a skilled user would run (timed on pixel subsets of
    # this frame's observations and masks, scaled to the frame)
    with torch.no_grad():
        samples, wsat = sample_views(sens, cap.image.to(dtype)[None], cap.saturated[None])
        y_t, mask_t, _ = observations_from_samples(sens, samples, wsat)
        scale = exposure_scale(cap.metadata.get("exposure_s"), sens.exposure_s)
        y_t = y_t[0] * scale
        mask_t = mask_t[0]
        yc = torch.where(mask_t, y_t, torch.zeros((), dtype=y_t.dtype, device=dev)).to(dtype)
    base_res = bench_baselines(rec, y_t, mask_t, args)
    lim = bench_limit(rec, yc, args)
    ours = res.cube.reshape(sens.num_bands, -1)[:, sens.pixel_index.cpu()].T.cpu()
    ours = ours.double().numpy()[base_res["sub"]]
    xs = base_res["x_scipy"]
    okp = np.isfinite(ours).all(1)
    dev_max = float(np.abs(ours[okp] - xs[okp]).max() / max(np.abs(xs).max(), 1e-30))
    t_scipy = base_res["scipy_s"]
    best_name, t_best = min(base_res["times"].items(), key=lambda kv: kv[1])
    base = {k: best[k] for k in FRAME_STAGES if k != "solve"}
    base["solve"] = t_scipy
    base_total = sum(base.values())
    base_best = dict(base, solve=t_best)
    mid = sorted(frames, key=lambda f: f["total"])[(len(frames) - 1) // 2]
    print(f"  stage times, s (best of {args.frames}; {args.dtype}, {dev}, beta = {args.beta:g}):")
    print(f"    {'stage':<14}{'hsi_torch':>12}{'SciPy loop':>12}{'best baseline':>15}")
    for k in FRAME_STAGES:
        print(f"    {k:<14}{best[k]:>12.3f}{base[k]:>12.3f}{base_best[k]:>15.3f}")
    print(f"    {'total':<14}{best['total']:>12.3f}{base_total:>12.3f}"
          f"{sum(base_best.values()):>15.3f}")
    print("    write: " + ", ".join(f"{k} {v:.3f}" for k, v in best_w.items()))
    print(f"  max |hsi_torch − SciPy| / max|x| on {xs.shape[0]} pixels: {dev_max:.1e} "
          f"({args.dtype} against float64)")
    core = lim["core_s"]
    print(f"  headline: solve {best['solve']:.3f} s (the problem's own solve {core:.3f} s) "
          f"against the best baseline, {best_name} {t_best:.3f} s: "
          f"{t_best / best['solve']:.1f}x")
    out = {
        "label": label, "pixels": P, "pivoted": st["num_pivoted"], "best": best,
        "median": mid, "scipy_solve_s": t_scipy, "whole_ratio": base_total / best["total"],
        "solve_ratio": t_scipy / best["solve"],
        "median_ratio": (mid["total"] - mid["solve"] + t_scipy) / mid["total"],
        "median_solve_ratio": t_scipy / mid["solve"], "peak_rss_gib": peak, "dev_max": dev_max,
        "baseline_s": dict(base_res["times"]), "best_baseline": best_name,
        "best_baseline_s": t_best, "best_ratio": t_best / best["solve"],
        "whole_best_ratio": sum(base_best.values()) / best["total"],
        "baseline_rss_gib": base_res["rss"], **lim,
    }
    out.update(bench_spatial(rec, cap_path, args, best) if args.spatial_frames > 0 else {})
    return out


def bench_baselines(rec: Reconstructor, y: torch.Tensor, mask: torch.Tensor,
                    args: argparse.Namespace) -> dict:
    """What a skilled user would run instead of our solver, on this frame's stacked problems
    ``[A_p[mask_p]; √β D]`` (float64): the SciPy loop in one process (``args.subset`` pixels),
    the SciPy loop over all cores (a ``spawn`` process pool, ``args.pool_subset`` pixels in
    chunks of ``args.pool_chunk``), and the compiled Lawson–Hanson loop (1 thread and all
    threads, ``args.pool_subset`` pixels); each best of ``args.scipy_repeats``, scaled to the
    frame's ``P`` pixels. Returns the times (s), the SciPy answers on the first subset, the peak
    RSS of each (GiB)."""
    import scipy

    sens = rec.sensing
    dev = sens.device
    P = sens.num_pixels
    g = np.random.default_rng(args.seed)
    perm = g.permutation(P)
    n_big = min(max(args.pool_subset, args.subset), P)
    big = perm[:n_big]
    n_sub = min(args.subset, P)
    A_big = sens.model.dense(torch.as_tensor(big, device=dev)).double().cpu().numpy()
    y_big = y.double().cpu().numpy()[big]
    m_big = mask.cpu().numpy()[big]
    D = difference_matrix(sens.num_bands, args.diff_order, dtype=torch.float64).numpy()
    sD = np.sqrt(args.beta) * D
    times: dict[str, float] = {}
    rss: dict[str, float | None] = {}
    sampler = RssSampler()
    sampler.start()
    # SciPy, one process
    t0 = time.perf_counter()
    t_sub, xs = nnls_baselines.scipy_serial(A_big[:n_sub], m_big[:n_sub], y_big[:n_sub], sD,
                                            args.scipy_repeats)
    rss["SciPy loop"] = sampler.peak(t0, time.perf_counter())
    times["SciPy loop"] = t_sub * P / n_sub
    # SciPy over all cores
    t0 = time.perf_counter()
    pool = nnls_baselines.scipy_pool(A_big, m_big, y_big, sD, workers=args.pool_workers,
                                     chunk=args.pool_chunk, repeats=args.scipy_repeats)
    par = sampler.peak(t0, time.perf_counter())
    rss["SciPy pool"] = (None if pool["peak_rss_gib"] is None or par is None
                         else pool["peak_rss_gib"] + par)
    nw = pool["workers"]
    times[f"SciPy pool ({nw})"] = pool["time_s"] * P / n_big
    pool_dev = float(np.abs(pool["x"][:n_sub] - xs).max())
    print(f"  SciPy {scipy.__version__} nnls: one process {1e6 * t_sub / n_sub:.1f} µs/pixel on "
          f"{n_sub} pixels; process pool ({nw} workers, spawn, chunks of {pool['chunk']}) "
          f"{1e6 * pool['time_s'] / n_big:.1f} µs/pixel on {n_big} pixels (best of "
          f"{args.scipy_repeats}; same answers: max diff {pool_dev:.1e}); scaled to P = {P}")
    # compiled Lawson–Hanson, serial per pixel, 1 thread and all threads
    if nnls_baselines.HAVE_NUMBA:
        nthr = torch.get_num_threads()
        nnls_baselines.fnnls(A_big[:8], m_big[:8], y_big[:8], sD)  # compile outside the timing
        nnls_baselines.fnnls(A_big[:8], m_big[:8], y_big[:8], sD, num_threads=2)
        for threads in sorted({1, nthr}):
            t0 = time.perf_counter()
            t_lh = float("inf")
            for _ in range(args.scipy_repeats):
                t = time.perf_counter()
                x_lh, it_lh = nnls_baselines.fnnls(A_big, m_big, y_big, sD, num_threads=threads)
                t_lh = min(t_lh, time.perf_counter() - t)
            name = f"compiled LH ({threads} thr)"
            rss[name] = sampler.peak(t0, time.perf_counter())
            times[name] = t_lh * P / n_big
            lh_dev = float(np.abs(x_lh[:n_sub] - xs).max() / max(np.abs(xs).max(), 1e-30))
            print(f"  compiled Lawson–Hanson (fnnls form, numba, {threads} thread(s)): "
                  f"{1e6 * t_lh / n_big:.2f} µs/pixel on {n_big} pixels, "
                  f"{int((it_lh < 0).sum())} at the iteration cap; max |LH − SciPy| / max|x| "
                  f"{lh_dev:.1e} on {n_sub} pixels")
    else:
        print("  compiled Lawson–Hanson baseline: skipped (numba is not installed)")
    sampler.stop()
    return {"times": times, "scipy_s": times["SciPy loop"], "x_scipy": xs, "sub": big[:n_sub],
            "rss": rss, "workers": nw}


def bench_limit(rec: Reconstructor, yc: torch.Tensor, args: argparse.Namespace) -> dict:
    """The machine's limit for one frame: the problem's own solve (``NNLSProblem.solve`` of the
    prepared factorisation, best of ``args.frames``), a pass that only reads the per-pixel bytes
    that solve reads, and one that does the unavoidable arithmetic (``b = Aᵀ W y``,
    ``x₀ = G⁻¹ b``), with the same threads."""
    prob = rec.sensing.problem
    threads = torch.get_num_threads()
    ins = nnls_baselines.solve_inputs(prob, yc)
    core, rd, ar = float("inf"), None, None
    with torch.no_grad():
        for _ in range(args.frames):  # interleaved: a busy machine slows all three alike
            _sync(yc.device)
            t = time.perf_counter()
            prob.solve(yc)
            _sync(yc.device)
            core = min(core, time.perf_counter() - t)
            r = nnls_baselines.read_pass(ins, threads, repeats=1)
            rd = r if rd is None or r["time_s"] < rd["time_s"] else rd
            a = nnls_baselines.arithmetic_pass(prob, yc, threads, repeats=1)
            ar = a if ar is None or (a is not None and a["time_s"] < ar["time_s"]) else ar
    P = yc.shape[0]
    parts = ", ".join(f"{k} {t.element_size() * t[0].numel()}" for k, t in ins.items())
    print(f"  limit ({threads} threads): the solve reads {rd['bytes'] / P:.0f} B/pixel "
          f"({parts}), {rd['bytes'] / 1e9:.2f} GB a frame")
    print(f"    read-only pass ({rd['how']}; best of {args.frames}, interleaved with the "
          f"solve) {rd['time_s']:.3f} s = {rd['gbps']:.1f} GB/s; "
          f"our solve {core:.3f} s = {rd['bytes'] / core / 1e9:.1f} GB/s, "
          f"{core / rd['time_s']:.1f}x the read-only pass")
    out = {"core_s": core, "read_s": rd["time_s"], "read_bytes": rd["bytes"],
           "read_gbps": rd["gbps"], "core_over_read": core / rd["time_s"]}
    if ar is not None:
        print(f"    arithmetic pass (b = Aᵀ W y, x0 = G⁻¹ b; numba) {ar['time_s']:.3f} s, reads "
              f"{ar['bytes'] / 1e9:.2f} GB = {ar['gbps']:.1f} GB/s; our solve "
              f"{core / ar['time_s']:.1f}x the arithmetic pass")
        out.update(arith_s=ar["time_s"], arith_gbps=ar["gbps"],
                   core_over_arith=core / ar["time_s"])
    return out


def bench_spatial(rec: Reconstructor, cap_path: Path, args: argparse.Namespace,
                  best_pp: dict[str, float]) -> dict:
    """The spatial-spectral mode on the same capture: best of ``args.spatial_frames`` after a
    warm-up (the one-off factorisation of ``G + ρI``), against the per-pixel ``best_pp``."""
    from hsi_torch.recon.spatial import RHO_SCALE

    lam = args.lam if args.lam in ("auto", "discrepancy") else float(args.lam)
    tv = Reconstructor(rec.sensing, prior="tv", lam=lam, spectral_rank=args.spectral_rank)
    sampler = RssSampler()
    sampler.start()
    t0 = time.perf_counter()
    tv.reconstruct_file(cap_path)
    t_warm = time.perf_counter() - t0
    runs = []
    for _ in range(args.spatial_frames):
        t = time.perf_counter()
        r = tv.reconstruct_file(cap_path)
        runs.append((r.timings["solve"], time.perf_counter() - t, r.stats))
    peak = sampler.peak(t0, time.perf_counter())
    sampler.stop()
    solve, frame, st = min(runs, key=lambda v: v[0])
    pp_frame = best_pp["total"] - best_pp["write"]
    print(f"  spatial (TV, lam {st['lam']:.3g}, rho scale {RHO_SCALE:g}, spectral rank "
          f"{st['spectral_rank']}), best of "
          f"{args.spatial_frames} after a warm-up of {t_warm:.1f} s: solve {solve:.3f} s = "
          f"{solve / best_pp['solve']:.1f}x the per-pixel solve ({best_pp['solve']:.3f} s), "
          f"frame without writing {frame:.3f} s = {frame / pp_frame:.1f}x the per-pixel frame "
          f"({pp_frame:.3f} s); {st['spatial_iterations']} ADMM iterations, peak RSS "
          f"{peak or float('nan'):.2f} GiB")
    return {"tv_solve_s": solve, "tv_solve_ratio": solve / best_pp["solve"],
            "tv_frame_ratio": frame / pp_frame, "tv_iterations": st["spatial_iterations"],
            "tv_peak_rss_gib": peak, "tv_warmup_s": t_warm}


def natural_capture_set(args: argparse.Namespace) -> Path:
    """A capture set holding the real CAVE scene through the full-size prototype, with its
    ground truth: ``--captures`` if given, else simulated once into ``--cache`` (reused)."""
    if args.captures is not None:
        p = Path(args.captures)
        if not (p / "scenes" / f"{args.scene}.tif").is_file():
            raise SystemExit(f"--captures {p}: no scenes/{args.scene}.tif")
        return p
    from hsi_torch.resources import real_data_dir, shipped_config

    cave = real_data_dir("cave_stuffed_toys")
    if cave is None or not cave.is_dir():
        raise SystemExit("the natural-scene frame needs the real CAVE scene (set HSI_TORCH_DATA "
                         "or --data-dir) or --captures DIR; --natural skip leaves it out")
    out = Path(args.cache) / "cave_full"
    if (out / "manifest.json").is_file() and (out / "scenes" / "cave.tif").is_file():
        print(f"natural-scene frame: reusing {out}")
        return out
    import json

    from hsi_torch.profiling import run_child

    scenes = [{"kind": "cave", "name": "cave",
               "params": {"folder": str(cave), "width_mm": 7.0, "center_mm": [0.0, 0.9]}}]
    print(f"natural-scene frame: simulating the CAVE scene at full size into {out} (once) ...")
    cmd = [sys.executable, "-m", "hsi_torch", "-q", "simulate", "--config",
           str(shipped_config("simulate_full")), "--out", str(out),
           "--set", "captures.scan_wavelengths_nm=[550]", "--set", "captures.white_shots=0",
           "--set", "captures.dark_frames=0", "--set", "captures.grid.poses=[]",
           "--set", f"captures.scenes={json.dumps(scenes)}", "--set", "render.figures=false"]
    run = run_child(cmd)
    if run.returncode != 0:
        raise SystemExit(f"simulating the natural-scene frame failed (exit {run.returncode})")
    print(f"  {run.wall_s:.0f} s, peak RSS {run.peak_rss_gib:.2f} GiB")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tile", type=int, nargs=2, default=(860, 745), metavar=("W", "H"),
                    help="synthetic frame: reference tile size (valid triangle ≈ W·H/2 px)")
    ap.add_argument("--natural", choices=("run", "skip"), default="run",
                    help="also time the natural-scene frame (the real CAVE scene through the "
                         "full-size prototype, oracle bundle)")
    ap.add_argument("--captures", default=None,
                    help="natural frame: a simulated capture set with scenes/SCENE.tif and its "
                         "ground truth (e.g. a 'demo --full' output's captures/)")
    ap.add_argument("--scene", default="cave", help="natural frame: the scene of --captures")
    ap.add_argument("--cache", default=str(Path.home() / ".cache" / "hsi_torch" / "bench"),
                    help="where the simulated natural-scene capture set is kept between runs")
    ap.add_argument("--subset", type=int, default=2000, help="pixels timed with the SciPy loop")
    ap.add_argument("--scipy-repeats", type=int, default=3,
                    help="times each baseline's subset is solved (the fastest counts)")
    ap.add_argument("--pool-subset", type=int, default=16000,
                    help="pixels timed with the SciPy process pool and the compiled "
                         "Lawson–Hanson loop")
    ap.add_argument("--pool-chunk", type=int, default=500,
                    help="pixels per task of the SciPy process pool")
    ap.add_argument("--pool-workers", type=int, default=None,
                    help="processes of the SciPy pool (default: the CPUs this process may use)")
    from hsi_torch.recon.config import ReconstructConfig

    ap.add_argument("--beta", type=float, default=ReconstructConfig().beta,
                    help="smoothness weight, DN² scale (default: the reconstruct config's)")
    ap.add_argument("--diff-order", type=int, default=1)
    ap.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--frames", type=int, default=5,
                    help="frames timed (the best total is reported, and the median)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--spatial-frames", type=int, default=3,
                    help="frames timed in the spatial-spectral (TV) mode (0: skip it)")
    ap.add_argument("--lam", default=str(DEFAULT_LAM), help="TV mode: relative weight, or auto")
    ap.add_argument("--spectral-rank", type=int, default=None,
                    help="TV mode: the prior on this many leading spectral components "
                         "(spectral_rank; default: all bands)")
    args = ap.parse_args(argv)
    dev = torch.device(args.device)
    dtype = torch.float64 if args.dtype == "float64" else torch.float32
    torch.manual_seed(args.seed)
    from hsi_torch.io import write_capture
    from hsi_torch.profiling import release_freed_memory
    from hsi_torch.recon.sensing import clear_sensing_cache

    results = []
    tmp = Path(tempfile.mkdtemp(prefix="bench_pipeline_"))
    try:
        # ---- synthetic frame ---------------------------------------------------------------
        t0 = time.perf_counter()
        bundle = make_bundle(*args.tile, seed=args.seed)
        t_bundle = time.perf_counter() - t0
        rec, pre = timed_reconstructor(bundle, args, dev, dtype, tmp, "synthetic")
        t_pre = pre["precompute_s"]
        sens = rec.sensing
        print(f"synthetic bundle: {sens.num_views} views, {sens.num_bands} bands, sensor "
              f"{sens.sensor_size}, frame {sens.frame_size}, valid pixels P = "
              f"{sens.num_pixels} (built in {t_bundle:.1f} s); per-bundle precomputation "
              f"(sensing model, masks, factorisation), once: {t_pre:.2f} s "
              f"(cached: {pre['cached_s']:.2f} s), {sens.memory_bytes() / 2**20:.0f} MiB")
        img = render(rec, bundle, seed=args.seed + 1)
        white = 4095
        level = np.quantile(img[img > 0], 0.999)
        img = img * (white * 0.98 / level)  # 0.1 % of the lit samples clip
        stored = np.minimum(np.round(img), white).astype(np.uint16)
        cap_path = tmp / "frame.tif"
        write_capture(cap_path, stored, {"kind": "rgb", "white_level": white, "exposure_s": 0.01})
        results.append(bench_frame("synthetic frame (smooth spectra)", rec, cap_path, args, tmp))
        results[-1].update(pre)
        del rec, sens, bundle, img, stored
        clear_sensing_cache()
        release_freed_memory()

        # ---- natural-scene frame -------------------------------------------------------------
        if args.natural == "run":
            from hsi_torch.simulate.oracle import bundle_from_truth

            cap_dir = natural_capture_set(args)
            nat_bundle = bundle_from_truth(cap_dir)
            rec, pre = timed_reconstructor(nat_bundle, args, dev, dtype, tmp, "natural")
            del nat_bundle
            print(f"natural-scene bundle (oracle of {cap_dir}): precomputation "
                  f"{pre['precompute_s']:.2f} s (cached: {pre['cached_s']:.2f} s), "
                  f"{rec.sensing.memory_bytes() / 2**20:.0f} MiB")
            results.append(bench_frame(f"natural-scene frame ({args.scene}, real data)", rec,
                                       cap_dir / "scenes" / f"{args.scene}.tif", args, tmp))
            results[-1].update(pre)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    nan = float("nan")

    def f(v: float | None, spec: str) -> str:
        return format(nan if v is None else v, spec)

    print(f"\nsummary ({args.dtype}, {dev}, beta = {args.beta:g}, {torch.get_num_threads()} "
          f"threads; baselines on the same frame's stacked problems in float64, same run):")
    print("  speed, s (solve: the pipeline's solve stage; x: the baseline's time / our solve)")
    names = list(dict.fromkeys(k for r in results for k in r.get("baseline_s", {})))
    print(f"    {'frame':<44}{'pixels':>8}{'pivot':>7}{'frame':>8}{'solve':>8}"
          + "".join(f"{k:>22}" for k in names) + f"{'best baseline':>16}")
    for r in results:
        bs = r.get("baseline_s", {})
        print(f"    {r['label']:<44}{r['pixels']:>8}{100 * r['pivoted'] / r['pixels']:>6.0f}%"
              f"{r['best']['total']:>8.3f}{r['best']['solve']:>8.3f}"
              + "".join(f"{f(bs.get(k), '.3f'):>13} "
                        f"{f(bs.get(k, nan) / r['best']['solve'], '.1f'):>7}x" for k in names)
              + f"{r['best_ratio']:>15.1f}x")
    for r in results:
        print(f"  headline, {r['label']}: solve {r['best']['solve']:.3f} s, the best baseline "
              f"({r['best_baseline']}) {r['best_baseline_s']:.3f} s: {r['best_ratio']:.1f}x; "
              f"whole frame {r['whole_best_ratio']:.1f}x")
    print("  the machine's limit (our solve = the prepared problem's solve alone; a pass that "
          "reads its per-pixel bytes; the fused b = AᵀWy, x0 = G⁻¹b pass)")
    print(f"    {'frame':<44}{'B/pixel':>8}{'GB':>6}{'solve':>8}{'GB/s':>6}{'read':>8}{'GB/s':>6}"
          f"{'x read':>8}{'arith':>8}{'x arith':>8}")
    for r in results:
        print(f"    {r['label']:<44}{r['read_bytes'] / r['pixels']:>8.0f}"
              f"{r['read_bytes'] / 1e9:>6.2f}{r['core_s']:>8.3f}"
              f"{r['read_bytes'] / r['core_s'] / 1e9:>6.1f}{r['read_s']:>8.3f}"
              f"{r['read_gbps']:>6.1f}{r['core_over_read']:>7.1f}x"
              f"{f(r.get('arith_s'), '.3f'):>8}{f(r.get('core_over_arith'), '.1f'):>7}x")
    print("  memory and cold start (peak RSS, GiB: per-pixel frames and TV frames of this process; "
          "SciPy pool: this process + its workers' peaks)")
    print(f"    {'frame':<44}{'per-pixel':>10}{'TV':>7}{'SciPy 1p':>9}{'SciPy pool':>11}"
          f"{'LH':>7}{'precomp s':>10}{'cached s':>9}{'TV warm-up':>11}{'TV solve':>9}"
          f"{'TV/pp':>7}"
          f"{'TV/pp frame':>12}")
    for r in results:
        rs = r.get("baseline_rss_gib", {})
        lh = max((v for k, v in rs.items() if k.startswith("compiled") and v is not None),
                 default=None)
        print(f"    {r['label']:<44}{f(r['peak_rss_gib'], '.2f'):>10}"
              f"{f(r.get('tv_peak_rss_gib'), '.2f'):>7}{f(rs.get('SciPy loop'), '.2f'):>9}"
              f"{f(rs.get('SciPy pool'), '.2f'):>11}{f(lh, '.2f'):>7}"
              f"{f(r.get('precompute_s'), '.2f'):>10}{f(r.get('cached_s'), '.2f'):>9}"
              f"{f(r.get('tv_warmup_s'), '.1f'):>11}"
              f"{f(r.get('tv_solve_s'), '.3f'):>9}{f(r.get('tv_solve_ratio'), '.1f'):>6}x"
              f"{f(r.get('tv_frame_ratio'), '.1f'):>11}x")
    print("  targets: solve <= 2x the read-only pass; TV solve <= 2x the per-pixel solve and "
          "<= 3 GiB; precomputation <= 1 s (or cached: the 'cached s' column); the RSS of "
          "hsi-torch reconstruct split into private and file-mapped memory, and runs under a "
          "memory limit: scripts/bench_memory.py")
    print(f"peak RSS of this process {peak_rss_gib():.2f} GiB"
          + (f", CUDA max allocated {torch.cuda.max_memory_allocated(dev) / 2**30:.2f} GiB"
             if dev.type == "cuda" else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
