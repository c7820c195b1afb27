"""Benchmark of sequence reconstruction on a simulated moving scene (the CAVE scene panning behind
a rotating ColorChecker, :mod:`hsi_torch.simulate.motion`, forward engine, oracle bundle).

    python scripts/bench_sequence.py [--small] [--frames 30] [--parts warm,temporal,drift,accuracy]

* ``warm``: per mode (per pixel, spatial prior) every frame solved cold and warm-started in the
  same process, alternating (the cold solves keep the ADMM's buffers on the bundle's sensing,
  as the warm ones keep theirs): the solve stage's time per frame, frames/s, the speed-up, each
  frame's PSNR warm vs cold (the difference must stay within 0.05 dB), peak RSS.
* ``temporal``: the same scene at low light (noise ×4): PSNR and SAM per frame with the
  temporal prior vs independent frames, on all valid pixels and on the moving edges alone.
* ``accuracy`` (not run by default: minutes a frame): on the frames ``--accuracy-frames``, each
  iterate's distance to the frame's exact optimum for the cold and the warm spatial solve, and
  the iterations each needs for the same distance (:func:`accuracy_part`).
* ``drift``: drift growing 0.1 px a frame: the tracked path's error per frame and the PSNR of
  the path-corrected frames vs the same frames without drift and vs the frames corrected with
  the true drift (``--drift-prior tv``: every one of them with the spatial prior).

Full size by default; ``--small`` for the 400 × 384 px prototype. ``--cache DIR``: the bundle,
the renderer's ground truth and every part's frames are read from ``DIR``, written there first
if absent (the full-size ground truth takes minutes and a frame up to a minute and a half on a
loaded machine; a second run, or another part on the same frames, reuses them): ``bundle.pt``,
``gt.pt`` (made only when a frame must be simulated), the ``warm`` part's frames
``frame_000.pt`` … (a dict of ``image``, ``saturated``, ``truth``, ``moved``, ``drift_px``,
``drift_deg``), the ``temporal`` part's in ``noise4/`` and the ``drift`` part's in ``drift/``
and, for its reference without drift, ``still/``. ``--drift-flicker 0.05`` gives the ``drift``
part the ``warm`` part's 5 % flicker: its reference without drift is then the ``warm`` part's
frames (same scene, light and noise seeds), not a third simulated sequence.
The spatial mode's warm starts are ``WarmStart(per_pixel=False)`` (the ADMM's state) and the
same with ``reuse_noise=True`` (the noise level, hence ``λ``, of the frame it was last estimated
on); the per-pixel warm start is measured in its own row.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import time
from types import SimpleNamespace

import numpy as np
import torch

from hsi_torch.profiling import peak_rss_gib
from hsi_torch.recon import Reconstructor
from hsi_torch.recon.drift import corrected_sensing
from hsi_torch.recon.frame import WarmStart
from hsi_torch.recon.sequence import SequenceReconstructor
from hsi_torch.simulate.motion import (
    Illumination,
    cave_and_chart,
    oracle_bundle,
    sequence_renderer,
    simulate_sequence,
)


def psnr_sam(
    cube: torch.Tensor, truth: torch.Tensor, valid: torch.Tensor, where: torch.Tensor | None = None
) -> tuple[float, float]:
    """PSNR (dB, peak = the truth's max over the pixels) and mean SAM (deg) over ``valid``
    (∧ ``where``) pixels whose true spectrum is not dark (norm above 1 % of the largest)."""
    v = valid if where is None else valid & where
    norm = truth.double().norm(dim=0)
    v = v & (norm > 0.01 * float(norm.max()))  # SAM needs a spectrum: not the empty background
    if int(v.sum()) == 0:
        return float("nan"), float("nan")
    a, t = cube[:, v].double(), truth[:, v].double()
    mse = float((a - t).square().mean())
    peak = float(t.max())
    cos = (a * t).sum(0) / (a.norm(dim=0) * t.norm(dim=0)).clamp_min(1e-12)
    sam = float(torch.rad2deg(torch.acos(cos.clamp(-1, 1))).mean())
    return 10 * math.log10(peak * peak / mse), sam


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--small", action="store_true", help="the small prototype (400 × 384 px)")
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--parts", default="warm,temporal,drift")
    ap.add_argument("--beta", type=float, default=1e4)
    ap.add_argument("--modes", default="both", choices=["both", "per", "spatial"],
                    help="the warm part's modes: per pixel, spatial prior or both")
    ap.add_argument("--spatial-warm", default="both", choices=["both", "state", "reused"],
                    help="the spatial mode's warm starts: the ADMM state, with the noise level "
                         "reused, or both")
    ap.add_argument("--cache", default=None,
                    help="folder of the bundle, ground truth and every part's simulated frames")
    ap.add_argument("--drift-prior", default="none", choices=["none", "tv"],
                    help="the drift part's prior (every reconstruction of that part)")
    ap.add_argument("--accuracy-frames", default="3,15",
                    help="the accuracy part's frames (each takes minutes: its exact optimum)")
    ap.add_argument("--drift-flicker", type=float, default=0.0,
                    help="the drift part's flicker of the light (0.05: the warm part's, whose "
                         "frames are then its reference without drift)")
    args = ap.parse_args()
    t0 = time.perf_counter()
    size = "small" if args.small else "full"
    parts = set(args.parts.split(","))
    cache = args.cache
    sim: dict[str, object] = {}  # the renderer and its ground truth, made when first needed

    def renderer_and_truth() -> tuple:
        if not sim:
            ts = time.perf_counter()
            sim["renderer"], _ = sequence_renderer(
                size, ["render.supersample=1", "diffuser.blur_sigma_mm=0"]
            )
            gp = None if cache is None else os.path.join(cache, "gt.pt")
            if gp is not None and os.path.exists(gp):
                sim["gt"] = torch.load(gp, weights_only=False)
            else:
                sim["gt"] = sim["renderer"].ground_truth()
                if gp is not None:
                    os.makedirs(cache, exist_ok=True)
                    torch.save(sim["gt"], gp)
            print(f"renderer and ground truth {time.perf_counter() - ts:.1f} s", flush=True)
        return sim["renderer"], sim["gt"]

    bp = None if cache is None else os.path.join(cache, "bundle.pt")
    if bp is not None and os.path.exists(bp):
        bundle = torch.load(bp, weights_only=False)
    else:
        bundle = oracle_bundle(*renderer_and_truth())
        if bp is not None:
            os.makedirs(cache, exist_ok=True)
            torch.save(bundle, bp)
    pp = Reconstructor(bundle, beta=args.beta, drift_check=False)
    sens = pp.sensing
    print(
        f"{size}: sensor {tuple(bundle.sensor_size.tolist())}, {sens.num_pixels} pixels, setup "
        f"{time.perf_counter() - t0:.1f} s; torch threads {torch.get_num_threads()}"
    )
    layers = cave_and_chart()
    n = args.frames

    def frames(tag: str | None = None, **kw):
        """The simulated frames (``simulate_sequence`` keywords ``kw``), read from and written
        to ``--cache``'s folder ``tag`` (``""``: the cache's top level) where given."""
        if cache is None or tag is None:
            yield from simulate_sequence(*_sim_args(), n, truth=renderer_and_truth()[1], **kw)
            return
        folder = os.path.join(cache, tag)
        os.makedirs(folder, exist_ok=True)
        ts = time.perf_counter()
        it = None
        for i in range(n):
            fp = os.path.join(folder, f"frame_{i:03d}.pt")
            if os.path.exists(fp):
                d = torch.load(fp)
            else:
                if it is None:
                    it = iter(simulate_sequence(*_sim_args(), n, truth=renderer_and_truth()[1],
                                                **kw))
                    for _ in range(i):
                        next(it)
                f = next(it)
                d = {k: getattr(f, k) for k in ("image", "saturated", "truth", "moved",
                                                 "drift_px", "drift_deg")}
                torch.save(d, fp)
                print(f"[{tag or 'warm'}] simulated frame {i} ({time.perf_counter() - ts:.0f} s, "
                      f"peak RSS {peak_rss_gib():.2f} GiB)", flush=True)
            d.setdefault("drift_px", (0.0, 0.0))  # caches written before the drift was kept
            d.setdefault("drift_deg", 0.0)
            yield SimpleNamespace(**{**d, "index": i})

    def _sim_args() -> tuple:
        return renderer_and_truth()[0], layers

    def warm_frames():
        """The warm part's frames (5 % flicker), through ``--cache`` where given."""
        return frames("", illumination=Illumination(flicker=0.05))

    if "warm" in parts:
        tv = Reconstructor(sens, prior="tv", drift_check=False)
        # per mode: the reconstructor and its warm starts (each frame solved cold once and
        # warm-started once per warm start, in the same process)
        modes = [m for m in (("per pixel", pp, {"per pixel": WarmStart(spatial=False)}),
                             ("spatial prior", tv, {
                                 k: w for k, w in (
                                     ("state", WarmStart(per_pixel=False)),
                                     ("state + noise reused", WarmStart(per_pixel=False,
                                                                        reuse_noise=True)))
                                 if args.spatial_warm in ("both", k.split()[-1])}))
                 if args.modes in ("both", m[0].split()[0])]
        for name, rec, warms in modes:
            tc: list[float] = []
            tw: dict[str, list[float]] = {k: [] for k in warms}
            dp: dict[str, list[float]] = {k: [] for k in warms}
            its: dict[str, list[int]] = {k: [] for k in warms}
            its_c: list[int] = []
            for f in warm_frames():
                c = rec.reconstruct_frame(f.image, f.saturated)
                pc = psnr_sam(c.cube, f.truth, c.valid)[0]
                line = f"[warm] {name} frame {f.index:2d}: cold {c.timings['solve']:.3f} s"
                if rec is tv:
                    its_c.append(c.stats["spatial_iterations"])
                    line += f" ({its_c[-1]} it)"
                line += f", PSNR {pc:.3f} dB"
                for k, warm in warms.items():
                    w = rec.reconstruct_frame(f.image, f.saturated, warm=warm)
                    pw = psnr_sam(w.cube, f.truth, w.valid)[0]
                    if f.index > 0:  # frame 0 has no previous frame (and compiles)
                        tw[k].append(w.timings["solve"])
                        dp[k].append(pw - pc)
                        if rec is tv:
                            its[k].append(w.stats["spatial_iterations"])
                    line += f"; {k} {w.timings['solve']:.3f} s"
                    if rec is tv:
                        line += (f" ({w.stats['spatial_iterations']} it, per-pixel solved "
                                 f"{w.stats.get('per_pixel_solved')}, static "
                                 f"{w.stats.get('spatial_warm_static')}, gain "
                                 f"{w.stats.get('spatial_warm_gain', 1.0):.3f}, σ given "
                                 f"{w.stats.get('noise_sigma_given')})")
                    line += f" {pw - pc:+.4f} dB"
                if f.index > 0:
                    tc.append(c.timings["solve"])
                print(line, flush=True)
            mc = statistics.median(tc)
            for k in warms:
                mw = statistics.median(tw[k])
                print(
                    f"[warm] {name}, {k}: solve median cold {mc:.3f} s ({1 / mc:.2f} frames/s), "
                    f"warm {mw:.3f} s ({1 / mw:.2f} frames/s), speed-up {mc / mw:.2f}x "
                    f"(sums {sum(tc):.1f} / {sum(tw[k]):.1f} s; per frame cold/warm median "
                    f"{statistics.median(c / w for c, w in zip(tc, tw[k], strict=True)):.2f}x, "
                    f"warm faster on {sum(c > w for c, w in zip(tc, tw[k], strict=True))} of "
                    f"{len(tc)} frames); PSNR warm − cold per frame: "
                    f"min {min(dp[k]):+.4f} max {max(dp[k]):+.4f} dB"
                    + (f"; ADMM iterations median cold {statistics.median(its_c)}, warm "
                       f"{statistics.median(its[k])}" if rec is tv else ""),
                    flush=True,
                )
        print(f"[warm] peak RSS {peak_rss_gib():.2f} GiB")

    if "temporal" in parts:
        seq = SequenceReconstructor(sens, temporal="quadratic", drift_check=False)
        gains, gains_e, sams = [], [], []
        t_ind, t_tem = [], []
        for f in frames("noise4", noise_gain=4.0):
            tc = time.perf_counter()
            ind = pp.reconstruct_frame(f.image, f.saturated)
            tc2 = time.perf_counter()
            tem = seq.reconstruct(f.image, f.saturated)  # its solve, then the temporal step
            t_ind.append(tc2 - tc)
            t_tem.append(time.perf_counter() - tc2)
            a, sa = psnr_sam(ind.cube, f.truth, ind.valid)
            b, sb = psnr_sam(tem.cube, f.truth, tem.valid)
            ae, _ = psnr_sam(ind.cube, f.truth, ind.valid, f.moved)
            be, _ = psnr_sam(tem.cube, f.truth, tem.valid, f.moved)
            st = tem.stats["sequence"].get("temporal_static_fraction", 0.0)
            print(
                f"[temporal] frame {f.index:2d}: PSNR {a:.2f} → {b:.2f} dB, SAM {sa:.2f} → "
                f"{sb:.2f}°, moving edges {ae:.2f} → {be:.2f} dB "
                f"({int(f.moved.sum())} px), static {st:.2f}; frame {t_ind[-1]:.1f} → "
                f"{t_tem[-1]:.1f} s, max KKT {tem.stats['sequence'].get('temporal_max_kkt')}, "
                f"peak RSS {peak_rss_gib():.2f} GiB",
                flush=True,
            )
            if f.index > 0:
                gains.append(b - a)
                sams.append(sb - sa)
                if math.isfinite(ae) and math.isfinite(be):
                    gains_e.append(be - ae)
        print(
            f"[temporal] frames 1–{n - 1}: PSNR gain mean {statistics.mean(gains):+.2f} dB "
            f"(min {min(gains):+.2f}), SAM change mean {statistics.mean(sams):+.2f}°; moving "
            f"edges PSNR change mean {statistics.mean(gains_e):+.2f} dB "
            f"(min {min(gains_e):+.2f}); s/frame median independent "
            f"{statistics.median(t_ind):.2f} s, temporal {statistics.median(t_tem):.2f} s",
            flush=True,
        )

    if "drift" in parts:
        dprior = args.drift_prior
        seq = SequenceReconstructor(sens, drift_track=True, warm_start=False, prior=dprior)
        plain = pp if dprior == "none" else Reconstructor(sens, prior=dprior, drift_check=False)
        errs, dps, dks = [], [], []
        light = Illumination(flicker=args.drift_flicker)
        still = warm_frames() if args.drift_flicker == 0.05 else frames("still", illumination=light)
        drifting = frames("drift", illumination=light, drift_px_per_frame=(0.1, 0.0))
        for f, g in zip(drifting, still, strict=True):
            tc = time.perf_counter()
            r = seq.reconstruct(f.image, f.saturated)  # the drift measured, the path, the solve
            t_frame = time.perf_counter() - tc
            path = r.stats["sequence"]["drift_path"]
            err = (
                math.hypot(path[0] - f.drift_px[0], path[1] - f.drift_px[1])
                if path is not None
                else float("nan")
            )
            ref = plain.reconstruct_frame(g.image, g.saturated)  # the same scene without drift
            known = Reconstructor(
                corrected_sensing(sens, f.drift_px, f.drift_deg), drift_check=False, prior=dprior
            ).reconstruct_frame(f.image, f.saturated)
            both = r.valid & ref.valid & known.valid
            a = psnr_sam(ref.cube, g.truth, both)[0]
            k = psnr_sam(known.cube, f.truth, both)[0]
            b = psnr_sam(r.cube, f.truth, both)[0]
            meas = r.stats["sequence"]["drift_measured"]
            errs.append(err)
            dps.append(b - a)
            dks.append(b - k)
            print(
                f"[drift] frame {f.index:2d}: true {f.drift_px[0]:.2f} px, measured "
                f"{meas[0] if meas else float('nan'):.3f}, path {path[0]:.3f} (error "
                f"{err:.3f} px); PSNR tracked {b:.2f}, true drift corrected {k:.2f}, no drift "
                f"{a:.2f} dB; tracked frame {t_frame:.1f} s, peak RSS {peak_rss_gib():.2f} GiB",
                flush=True,
            )
        print(
            f"[drift] path error max {max(errs):.3f} px; PSNR tracked − no drift "
            f"{min(dps):+.3f} … {max(dps):+.3f} dB, tracked − true drift corrected "
            f"{min(dks):+.3f} … {max(dks):+.3f} dB; findings {[x.code for x in seq.findings]}"
        )
    if "accuracy" in parts:
        at = sorted({int(v) for v in args.accuracy_frames.split(",")})
        accuracy_part(sens, warm_frames(), at)
    print(f"peak RSS {peak_rss_gib():.2f} GiB; total {time.perf_counter() - t0:.0f} s")


def _copied(v: object) -> object:
    """A copy of a recorded argument (tensors, arrays and tuples of them): the solve it was
    recorded from writes into some of them."""
    if isinstance(v, torch.Tensor):
        return v.detach().clone()
    if isinstance(v, np.ndarray):
        return v.copy()
    if isinstance(v, tuple):
        return tuple(_copied(a) for a in v)
    return v


def accuracy_part(sens, frames, at: list[int]) -> None:
    """The ``accuracy`` part: what a warm start buys at equal accuracy. Every frame up to the
    last of ``at`` is solved warm (the spatial prior, ``WarmStart(per_pixel=False)``); on the
    frames ``at`` the spatial solve's arguments are recorded for the cold and the warm solve,
    the frame's exact optimum ``x*`` is computed from the cold start (relative tolerance
    1e-5), and both solves are replayed for 1, 2, … iterations (cold also over-relaxed as
    the warm one is) to give each iterate's distance ``‖x_k − x*‖ / ‖x*‖`` and the iteration
    where the stopping rule, checked every iteration, is first met."""
    import hsi_torch.recon.spatial.frame as spatial_frame

    tv = Reconstructor(sens, prior="tv", drift_check=False)
    warm = WarmStart(per_pixel=False)
    real = spatial_frame.solve_spatial
    calls: list[tuple] = []

    def recording(problem, b, lam, **kw):
        calls.append((problem, b.clone(), lam, {k: _copied(v) for k, v in kw.items()}))
        return real(problem, b, lam, **kw)

    spatial_frame.solve_spatial = recording
    ratios: list[tuple[float, float]] = []
    try:
        for f in frames:
            recorded, its = {}, {}
            for mode, ws in ((("cold", None),) if f.index in at else ()) + (("warm", warm),):
                calls.clear()
                its[mode] = tv.reconstruct_frame(f.image, f.saturated,
                                                 warm=ws).stats["spatial_iterations"]
                recorded[mode] = calls[0]
            if f.index >= at[-1]:
                frames.close()  # no further frame is simulated
            if f.index not in at or f.index == 0:
                continue
            prob, b, lam, kw = recorded["cold"]
            base = {**kw, "workspace": None}
            ts = time.perf_counter()
            ref = real(prob, b, lam, **{**base, "tol": 1e-5, "max_iter": 20000, "check_every": 10})
            star = ref.x.double()
            nstar = float(star.norm())
            print(f"[accuracy] frame {f.index}: optimum in {ref.iterations} iterations "
                  f"({time.perf_counter() - ts:.0f} s, relative residuals {ref.primal_residual:.1e}"
                  f" / {ref.dual_residual:.1e}); the frame's rule: tolerance {kw['tol']}",
                  flush=True)
            rows = {}
            warm_relax = recorded["warm"][3]["relax"]
            n_cold, n_warm = its["cold"], its["warm"]
            for name, (pr, bb, la, k0), n_it, relax in (
                    ("cold", recorded["cold"], max(n_cold, n_warm + 3), None),
                    ("cold, over-relaxed", recorded["cold"], max(n_cold, n_warm + 3), warm_relax),
                    ("warm", recorded["warm"], max(n_cold, n_warm + 3), None)):
                kw_k = {**k0, "workspace": None, "tol": 0.0, "check_every": 1}
                if relax is not None:
                    kw_k["relax"] = relax
                dist, met = [], None
                for k in range(1, n_it + 1):
                    r = real(pr, bb, la, **{**_copied(kw_k), "max_iter": k})
                    dist.append(float((r.x.double() - star).norm()) / nstar)
                    if met is None and max(r.primal_residual, r.dual_residual) <= k0["tol"]:
                        met = k
                rows[name] = (dist, met)
                print(f"[accuracy] frame {f.index} {name} (relax {kw_k.get('relax', 1.0)}): rule "
                      f"met at iteration {met}; distance to the optimum by iteration: "
                      + " ".join(f"{k + 1}:{d:.2e}" for k, d in enumerate(dist)), flush=True)
            cold, wd = rows["cold"][0], rows["warm"][0]
            # the pipeline's answers: the warm solve's iterate n_warm, the cold one's n_cold;
            # the first cold iterate as close as the first, the first warm one as the second
            c_eq = next((k + 1 for k, d in enumerate(cold) if d <= wd[n_warm - 1]), None)
            w_eq = next((k + 1 for k, d in enumerate(wd) if d <= cold[n_cold - 1]), None)
            print(f"[accuracy] frame {f.index}: the pipeline's warm answer ({n_warm} it) is as "
                  f"close as cold iterate {c_eq}; its cold answer ({n_cold} it) is reached warm "
                  f"at iteration {w_eq}", flush=True)
            if c_eq and w_eq:
                ratios.append((c_eq / n_warm, n_cold / w_eq))
    finally:
        spatial_frame.solve_spatial = real
    if ratios:
        print("[accuracy] iterations cold/warm at equal distance to the optimum: at the warm "
              "answer's " + ", ".join(f"{a:.2f}" for a, _ in ratios) + "; at the cold answer's "
              + ", ".join(f"{c:.2f}" for _, c in ratios), flush=True)


if __name__ == "__main__":
    main()
