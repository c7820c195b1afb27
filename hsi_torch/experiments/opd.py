"""OPD validation: the optical path difference of every view-channel estimated from its
transmittance spectrum (:mod:`hsi_torch.experiments.opd_estimate`), matched to the ray tracer's
predicted views on the image plane (:mod:`hsi_torch.experiments.opd_points`).

Experiment (:func:`run_opd`, ``hsi-torch experiment opd``): inputs are a simulated capture set's
ground truth ``B`` (reference frame), calibration bundles (oracle, calibrated, or any file), the
monochromator scan itself (``B`` in sensor coordinates via
:func:`hsi_torch.calibrate.brf_transmittance`) or a CSV of measured spectra at image-plane
positions. Every measured point (``x, y`` sensor px) is matched to the ray tracer's predicted view
whose triangle contains it (else the nearest view centroid), and the ray through that point gives
``(α, σ)`` and the predicted OPD.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from torch import Tensor

from hsi_torch.calibrate import brf_transmittance
from hsi_torch.calibrate.config import CalibrateConfig
from hsi_torch.calibrate.pipeline import calibrate_capture_set
from hsi_torch.config import load_config, option
from hsi_torch.experiments import report
from hsi_torch.experiments.opd_estimate import (
    OPDEstimate,
    band_centre_nm,
    estimate_opd,
    group_opd_nm,
)
from hsi_torch.experiments.opd_points import (
    MeasuredPoints,
    PredictedViews,
    match_points,
    points_from_reference_frame,
    points_from_sensor_map,
    predicted_views,
    read_points_csv,
)
from hsi_torch.io import read_any
from hsi_torch.io.atomic import atomic_write_json
from hsi_torch.io.bundle import CalibrationBundle
from hsi_torch.io.capture_set import read_capture_set, read_truth
from hsi_torch.resources import shipped_config
from hsi_torch.simulate.capture_sets import build_renderer, simulate_capture_set
from hsi_torch.simulate.config import SimulateConfig
from hsi_torch.simulate.oracle import bundle_from_truth

__all__ = [
    "calibrated_bundle",
    "OPDInputSpec",
    "OPDPointsSpec",
    "OPDEstimatorSpec",
    "OPDConfig",
    "run_opd",
]


# --- inputs


@dataclass
class OPDInputSpec:
    """One source of measured transmittances.

    ``kind``:
      - ``truth``: the simulator's ground-truth ``B`` (reference frame; the capture set's
        ``truth.npz``, or computed in memory when no capture set is used);
      - ``oracle``: :func:`hsi_torch.simulate.oracle.bundle_from_truth` of the capture set;
      - ``calibrated``: :func:`calibrated_bundle` of the capture set;
      - ``scan``: ``B`` in sensor coordinates from the capture set's monochromator scan with
        :func:`hsi_torch.calibrate.brf_transmittance` (ratio to the BRF-free patch), sampled in
        the *nominal* triangles (no homographies needed);
      - ``bundle``: any calibration bundle file (``path``);
      - ``csv``: measured spectra at image-plane points (``path``, :func:`read_points_csv`).
    """

    kind: Literal["truth", "oracle", "calibrated", "scan", "bundle", "csv"]
    name: str | None = option(None, "label (default: the kind)")
    path: Path | None = option(None, "bundle .npz or CSV file")


@dataclass
class OPDPointsSpec:
    """Sample points per view (reference-frame inputs use the reference triangle, sensor inputs
    every nominal triangle): the centroid plus ``num_ring`` (0, 3 or 6) points
    ``ring_fraction`` of the way to the vertices (and edge midpoints)."""

    num_ring: int = 6
    ring_fraction: float = option(0.35, "0.35 keeps the ring clear of the BRF-free disk")
    min_modulation: float = option(0.2, "fitted amplitude/offset below this: 'unmodulated', left "
                                        "out of the error statistics")


@dataclass
class OPDEstimatorSpec:
    """Parameters of :func:`estimate_opd`."""

    num_k: int | None = None
    window: Literal["hann", "none"] = "hann"
    pad_factor: int = 32
    search_bins: float = 1.0
    search_points: int = 41
    iters: int = 20


#: Why the tables of this experiment carry none of the field's reconstruction metrics.
OPD_METRICS_NOTE = ("The field's reconstruction metrics (hsi_torch.metrics: PSNR in both "
                    "conventions, SSIM, SAM, ERGAS, RMSE, MRAE) do not apply here: this "
                    "experiment reconstructs no reflectance cube, it compares optical path "
                    "differences (nm) with the ray tracer's.")


@dataclass
class OPDConfig:
    """``hsi-torch experiment opd`` configuration (see docs/experiments.md)."""

    prototype: Path | None = option(None, "SimulateConfig YAML of the design (null: the shipped "
                                          "simulate.yaml, the default prototype)")
    prototype_overrides: list[str] = field(
        default_factory=list, metadata={"help": "key=value overrides of the prototype config"})
    capture_set: Path | None = option(None, "existing simulated capture set; null: simulate one "
                                            "into OUT/capture_set when an input needs it")
    inputs: list[OPDInputSpec] = field(default_factory=lambda: [OPDInputSpec("truth")])
    points: OPDPointsSpec = field(default_factory=OPDPointsSpec)
    estimator: OPDEstimatorSpec = field(default_factory=OPDEstimatorSpec)
    prediction_wavelength_nm: float = option(550.0, "wavelength of the listed phase OPD")
    calibrate_config: Path | None = option(None, "calibration config for kind 'calibrated'")
    dtype: Literal["float32", "float64"] = "float64"
    device: str | None = None
    progress: bool = True


def _load_prototype(cfg: OPDConfig):
    return load_config(cfg.prototype or shipped_config("simulate"), SimulateConfig,
                       list(cfg.prototype_overrides))


def _bundle_points(bundle, pts: OPDPointsSpec) -> MeasuredPoints:
    keys = ("B", "wavelengths_nm", "view_homographies", "triangles", "reference_bbox", "modulated")
    return _truth_points({k: getattr(bundle, k) for k in keys}, pts)


def calibrated_bundle(capture_set: str | Path, calibrate_config: str | Path | None = None, *,
                      device: str | None = None, progress: bool = False,
                      save_to: str | Path | None = None) -> tuple[CalibrationBundle, str]:
    """``(bundle, note)``: :func:`hsi_torch.calibrate.pipeline.calibrate_capture_set` on a
    capture set (``calibrate_config``: a ``CalibrateConfig`` YAML, else the shipped
    ``calibrate.yaml``); ``note`` says how it was made. ``save_to`` writes the bundle."""
    ccfg = load_config(calibrate_config or shipped_config("calibrate"), CalibrateConfig)
    bundle, rep = calibrate_capture_set(capture_set, ccfg, device=device, progress=progress)
    if save_to is not None:
        bundle.save(save_to)
    return bundle, ("calibrated with hsi_torch.calibrate.pipeline.calibrate_capture_set "
                    f"({calibrate_config or 'the shipped calibrate.yaml'}; "
                    f"{rep.valid.num_valid} valid pixels)")


def _scan_points(capture_set: Path, pts: OPDPointsSpec, device: torch.device,
                 progress: bool = False) -> MeasuredPoints:
    """``B`` in sensor coordinates from the capture set's monochromator scan
    (:func:`hsi_torch.calibrate.brf_transmittance`, dark frame subtracted, the usable BRF-free
    mask of the reference view), sampled in the *nominal* triangles."""
    cs = read_capture_set(capture_set)
    scans = cs.scan
    if len(scans) < 4:
        raise ValueError(f"{cs.root}: needs >= 4 monochromator scan frames, found {len(scans)}")
    unknown = [p.name for p, lam in scans if lam is None]
    if unknown:
        raise ValueError(f"{cs.root}: scan frame(s) {unknown} without a wavelength")
    it = report.progress(scans, desc="opd: reading scan", enable=progress)
    frames = [read_any(p, dtype=torch.float64, device=device).image for p, _ in it]
    wl = [float(lam) for _, lam in scans]
    dark = None
    if cs.dark:
        dark = read_any(cs.dark[0], dtype=torch.float64, device=device).image
    mask = cs.read_brf_free_mask()
    res = brf_transmittance(torch.stack(frames), wl, torch.from_numpy(mask).to(device),
                            dark=dark, grid_nm=sorted(wl))
    tris = torch.from_numpy(cs.layout().triangles)
    return points_from_sensor_map(res.transmittance, res.wavelengths_nm, tris, res.lit,
                                  num_ring=pts.num_ring, ring_fraction=pts.ring_fraction)


def _truth_points(truth: dict[str, Any], pts: OPDPointsSpec) -> MeasuredPoints:
    return points_from_reference_frame(
        torch.as_tensor(truth["B"]), torch.as_tensor(truth["wavelengths_nm"]),
        torch.as_tensor(truth["view_homographies"]),
        torch.as_tensor(truth["layout_triangles"] if "layout_triangles" in truth
                        else truth["triangles"]),
        tuple(int(v) for v in truth["reference_bbox"]), torch.as_tensor(truth["modulated"]),
        num_ring=pts.num_ring, ring_fraction=pts.ring_fraction)


def _memory_truth(renderer: Any, progress: bool) -> dict[str, Any]:
    """Ground truth computed in memory (no capture set), with the layout arrays."""
    bar = None
    if progress:
        def bar(it, **kw):
            return report.progress(it, desc=kw.get("desc", ""), enable=True)
    gt = renderer.ground_truth(bar)
    lay = renderer.layout
    return {"B": gt["B"], "wavelengths_nm": gt["wavelengths_nm"], "modulated": gt["modulated"],
            "view_homographies": lay.view_homographies, "layout_triangles": lay.triangles,
            "reference_bbox": torch.tensor(lay.reference_bbox)}


# --- the experiment


def _rows_for(name: str, mp: MeasuredPoints, est: OPDEstimate, match: dict[str, Tensor],
              min_mod: float) -> list[dict[str, Any]]:
    rows = []
    c = {k: v.detach().cpu().to(torch.float64) for k, v in
         (("coarse", est.coarse_nm), ("fft", est.fft_nm), ("fit", est.fit_nm),
          ("mod", est.modulation), ("rms", est.rms), ("amp", est.amplitude),
          ("off", est.offset))}
    for i in range(mp.xy.shape[0]):
        g = float(match["opd_group_nm"][i])
        fit = float(c["fit"][i])
        rows.append({
            "input": name, "label": mp.label[i], "input_view": int(mp.view[i]),
            "x_px": float(mp.xy[i, 0]), "y_px": float(mp.xy[i, 1]),
            "view": int(match["view"][i]), "inside": bool(match["inside"][i]),
            "traced": bool(match["traced"][i]),
            "distance_px": float(match["distance_px"][i]),
            "alpha_deg": math.degrees(float(match["alpha"][i])),
            "sigma_deg": math.degrees(float(match["sigma"][i])),
            "pred_phase_nm": float(match["opd_phase_nm"][i]), "pred_group_nm": g,
            "view_pred_group_nm": float(match["view_opd_group_nm"][i]),
            "coarse_nm": float(c["coarse"][i]), "fft_nm": float(c["fft"][i]), "fit_nm": fit,
            "err_coarse_nm": float(c["coarse"][i]) - abs(g),
            "err_fft_nm": float(c["fft"][i]) - abs(g), "err_fit_nm": fit - abs(g),
            "rel_err_fit": (fit - abs(g)) / max(abs(g), 1e-9),
            "err_fit_vs_phase_nm": fit - abs(float(match["opd_phase_nm"][i])),
            "modulation": float(c["mod"][i]), "fit_rms": float(c["rms"][i]),
            "modulated": bool(float(c["mod"][i]) >= min_mod),
            "view_ok": bool(int(mp.view[i]) < 0 or int(mp.view[i]) == int(match["view"][i])),
        })
    return rows


def _stats(rows: list[dict[str, Any]], bin_nm: float) -> dict[str, Any]:
    use = [r for r in rows if r["modulated"]]
    out: dict[str, Any] = {"points": len(rows), "modulated_points": len(use),
                           "views_matched_correctly": sum(r["view_ok"] for r in rows),
                           "bin_nm": bin_nm}
    if not use:
        return out
    for key in ("coarse", "fft", "fit"):
        e = np.array([r[f"err_{key}_nm"] for r in use])
        rel = e / np.maximum(np.abs([r["pred_group_nm"] for r in use]), 1e-9)
        out[f"{key}_max_abs_nm"] = float(np.abs(e).max())
        out[f"{key}_rms_nm"] = float(np.sqrt((e**2).mean()))
        out[f"{key}_median_abs_nm"] = float(np.median(np.abs(e)))
        out[f"{key}_max_rel"] = float(np.abs(rel).max())
        out[f"{key}_median_rel"] = float(np.median(np.abs(rel)))
    ph = np.array([r["err_fit_vs_phase_nm"] for r in use])
    out["fit_vs_phase_median_rel"] = float(np.median(np.abs(ph) / np.maximum(
        np.abs([r["pred_phase_nm"] for r in use]), 1e-9)))
    out["coarse_within_one_bin"] = bool(out["coarse_max_abs_nm"] <= bin_nm)
    return out


def _per_view(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    out = []
    names = list(dict.fromkeys(r["input"] for r in rows))
    for n in names:
        rs = [r for r in rows if r["input"] == n and r["modulated"]]
        for v in sorted({r["view"] for r in rs}):
            rv = [r for r in rs if r["view"] == v]
            fit = np.array([r["fit_nm"] for r in rv])
            g = np.array([r["pred_group_nm"] for r in rv])
            out.append({"input": n, "view": v, "points": len(rv),
                        "pred_phase_550_nm": float(np.mean([r["pred_phase_nm"] for r in rv])),
                        "pred_group_nm": float(g.mean()), "fit_nm": float(fit.mean()),
                        "fft_nm": float(np.mean([r["fft_nm"] for r in rv])),
                        "coarse_nm": float(np.mean([r["coarse_nm"] for r in rv])),
                        "max_abs_err_fit_nm": float(np.abs(fit - np.abs(g)).max()),
                        "max_rel_err_fit": float((np.abs(fit - np.abs(g)) / np.abs(g)).max())})
    return out


def _examples(rows: list[dict[str, Any]]) -> list[int]:
    idx = [i for i, r in enumerate(rows) if r["modulated"]]
    if not idx:
        return []
    idx.sort(key=lambda i: rows[i]["fit_nm"])
    picks = [idx[0], idx[len(idx) // 2], idx[-1]]
    return list(dict.fromkeys(picks))


def _plot_correspondence(path: Path, pred: PredictedViews, rows: list[dict[str, Any]],
                         ex: list[int], title: str) -> None:
    import matplotlib.pyplot as plt

    fig, ax = report.new_figure(figsize=(7.5, 7.2))
    lay = pred.layout
    tris = lay.triangles.numpy()
    cen = pred.centres.numpy()
    vals = [r["fit_nm"] for r in rows]
    norm = plt.Normalize(min(vals + list(lay.opd_nm.numpy())), max(vals + list(lay.opd_nm
                                                                              .numpy())))
    cmap = plt.get_cmap("viridis")
    for v in range(lay.num_views):
        t = np.vstack([tris[v], tris[v][:1]])
        ax.plot(t[:, 0], t[:, 1], "-", color="0.6", lw=0.8)
        ax.annotate(f"v{v}", cen[v] + np.array([6, -6]), fontsize=8, color="0.3")
    for r in rows:
        c = cen[r["view"]]
        ax.plot([r["x_px"], c[0]], [r["y_px"], c[1]], "-", color="0.4", lw=0.6, zorder=1)
    ax.scatter(cen[:, 0], cen[:, 1], s=90, facecolors="none", edgecolors="k", lw=1.2,
               zorder=3, label="predicted view centres (ray tracer)")
    sc = ax.scatter([r["x_px"] for r in rows], [r["y_px"] for r in rows], c=vals, cmap=cmap,
                    norm=norm, marker="s", s=28, edgecolors="k", lw=0.4, zorder=4,
                    label="measured points (colour: fitted OPD)")
    for tag, i in zip("SML", ex, strict=False):
        ax.add_patch(plt.Circle((rows[i]["x_px"], rows[i]["y_px"]), 12, fill=False, ls="--",
                                ec="red", lw=1.2, zorder=5))
        ax.annotate(tag, (rows[i]["x_px"] + 13, rows[i]["y_px"] - 13), color="red",
                    fontsize=10, weight="bold")
    h, w = lay.sensor_size
    ax.set_xlim(0, w)
    ax.set_ylim(h, 0)
    ax.set_aspect("equal")
    ax.set_xlabel("x (sensor px)")
    ax.set_ylabel("y (sensor px)")
    ax.legend(loc="lower center", fontsize=7, bbox_to_anchor=(0.5, -0.2), ncol=2)
    fig.colorbar(sc, ax=ax, shrink=0.75, label="OPD (nm)")
    ax.set_title(f"(a) image-plane correspondence — {title}", fontsize=10)
    report.save_figure(fig, path)


def _plot_polar(path: Path, pred: PredictedViews, rows: list[dict[str, Any]], ex: list[int],
                view_group: np.ndarray, title: str) -> None:
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(7.2, 6.4))
    ax = fig.add_subplot(111, projection="polar")
    ax.set_theta_direction(-1)  # σ from +X towards +Y (image y points down)
    lay = pred.layout
    ma, ms = np.degrees(lay.mean_alpha.numpy()), lay.mean_sigma.numpy()
    vals = [r["fit_nm"] for r in rows]
    norm = plt.Normalize(min(vals + list(view_group)), max(vals + list(view_group)))
    cmap = plt.get_cmap("viridis")
    for r in rows:
        ax.plot([math.radians(r["sigma_deg"]), ms[r["view"]]], [r["alpha_deg"], ma[r["view"]]],
                "-", color="0.5", lw=0.6, zorder=1)
    ax.scatter(ms, ma, s=260, facecolors="none", edgecolors=cmap(norm(view_group)), lw=2.2,
               zorder=3, label="predicted views (outline: ray-traced group OPD)")
    for v in range(lay.num_views):
        ax.annotate(f"v{v}", (ms[v], ma[v]), xytext=(8, 8), textcoords="offset points", fontsize=8)
    sc = ax.scatter([math.radians(r["sigma_deg"]) for r in rows],
                    [r["alpha_deg"] for r in rows], c=vals, cmap=cmap, norm=norm, marker="s",
                    s=24, edgecolors="k", lw=0.3, zorder=4, label="estimated (fit)")
    for tag, i in zip("SML", ex, strict=False):
        ax.scatter([math.radians(rows[i]["sigma_deg"])], [rows[i]["alpha_deg"]], s=240,
                   facecolors="none", edgecolors="red", linestyles="--", zorder=5)
        ax.annotate(tag, (math.radians(rows[i]["sigma_deg"]), rows[i]["alpha_deg"]),
                    xytext=(-14, 6), textcoords="offset points", color="red", weight="bold")
    ax.set_rlabel_position(100)
    ax.set_title(f"(b) OPD over (α, σ): r = α (deg), θ = σ — {title}", fontsize=10)
    fig.colorbar(sc, ax=ax, shrink=0.7, pad=0.1, label="OPD (nm)")
    ax.legend(loc="lower center", fontsize=7, bbox_to_anchor=(0.5, -0.18), ncol=1)
    report.save_figure(fig, path)


def _plot_spectra(path: Path, mp: MeasuredPoints, est: OPDEstimate, rows: list[dict[str, Any]],
                  ex: list[int], title: str) -> None:
    fig, axes = report.new_figure(1, max(1, len(ex)), figsize=(4.2 * max(1, len(ex)), 3.4),
                                  squeeze=False)
    wl = mp.wavelengths_nm
    fine = torch.linspace(float(wl[0]), float(wl[-1]), 400, dtype=torch.float64)
    model = est.model(fine.to(est.fit_nm)).detach().cpu().to(torch.float64)
    for ax, tag, i in zip(axes[0], "SML", ex, strict=False):
        r = rows[i]
        scale = float(est.offset[i] + est.amplitude[i])
        scale = scale if scale > 0 else 1.0
        ax.plot(wl.numpy(), (mp.T[i] / scale).numpy(), "o", ms=4, label="measured T (norm.)")
        ax.plot(fine.numpy(), (model[i] / scale).numpy(), "-", lw=1.2, label="fitted cosine")
        ax.set_title(f"{tag}: {r['label']} → v{r['view']}\n"
                     f"fit {r['fit_nm']:.0f} nm, FFT {r['fft_nm']:.0f}, coarse "
                     f"{r['coarse_nm']:.0f}\npred. (group, k₀) {r['pred_group_nm']:.0f} nm",
                     fontsize=8)
        ax.set_xlabel("wavelength (nm)")
        ax.set_ylim(-0.05, 1.1)
    axes[0][0].set_ylabel("normalised transmittance")
    axes[0][0].legend(fontsize=7, loc="lower left")
    fig.suptitle(f"(c) transmittance at small / medium / large OPD — {title}", fontsize=10)
    report.save_figure(fig, path)


def _slug(name: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in name)


def run_opd(cfg: OPDConfig, out: str | Path, *, device: str | None = None) -> dict[str, Any]:
    """Estimate per-view OPDs of every input, match them to the ray tracer's views and write
    ``matched_pairs.csv/.md``, ``per_view.csv``, ``summary.md``, ``summary.json`` and per input
    ``correspondence_<name>.png``, ``opd_polar_<name>.png``, ``spectra_<name>.png`` to ``out``.

    Returns:
        The summary dict (statistics per input, notes, timings).
    """
    t_all, out, dev, dt = report.start_run(out, cfg, device)
    if not cfg.inputs:
        raise ValueError("opd: `inputs` is empty")
    names = [i.name or i.kind for i in cfg.inputs]
    if len(set(names)) != len(names):
        raise ValueError(f"opd: input names must be unique, got {names}")
    proto = _load_prototype(cfg)
    timings: dict[str, float] = {}
    notes: list[str] = []
    capture_set = cfg.capture_set
    if any(i.kind in ("oracle", "calibrated", "scan") for i in cfg.inputs) and capture_set is None:
        capture_set = out / "capture_set"
        if not (capture_set / "ground_truth" / "truth.npz").is_file():
            t0 = time.perf_counter()
            simulate_capture_set(proto, capture_set, device=str(dev), progress=cfg.progress,
                                 log=lambda *a: None)
            timings["simulate"] = time.perf_counter() - t0
        notes.append(f"capture set simulated into {capture_set}")
    t0 = time.perf_counter()
    renderer = build_renderer(proto, device="cpu")
    pred = predicted_views(renderer.geometry, renderer.camera, renderer.brf, renderer.layout)
    timings["prediction"] = time.perf_counter() - t0

    rows: list[dict[str, Any]] = []
    stats: dict[str, Any] = {}
    per_input: list[tuple[str, MeasuredPoints, OPDEstimate, list[dict[str, Any]]]] = []
    es = cfg.estimator
    it = report.progress(list(zip(names, cfg.inputs, strict=True)), desc="opd: inputs",
                         enable=cfg.progress)
    for name, spec in it:
        t0 = time.perf_counter()
        if spec.kind in ("bundle", "csv") and spec.path is None:
            raise ValueError(f"opd input {name!r}: kind {spec.kind!r} needs `path`")
        if spec.kind == "truth":
            if capture_set is not None:
                arrays, _ = read_truth(capture_set)
                mp = _truth_points(arrays, cfg.points)
            else:
                mp = _truth_points(_memory_truth(renderer, cfg.progress), cfg.points)
        elif spec.kind == "oracle":
            mp = _bundle_points(bundle_from_truth(capture_set), cfg.points)
        elif spec.kind == "calibrated":
            bundle, note = calibrated_bundle(capture_set, cfg.calibrate_config,
                                             device=str(dev), progress=cfg.progress,
                                             save_to=out / f"bundle_{_slug(name)}.npz")
            notes.append(f"{name}: {note}")
            mp = _bundle_points(bundle, cfg.points)
        elif spec.kind == "scan":
            mp = _scan_points(Path(capture_set), cfg.points, dev, cfg.progress)
        elif spec.kind == "bundle":
            mp = _bundle_points(CalibrationBundle.load(spec.path), cfg.points)
        else:
            mp = read_points_csv(spec.path)
        wl = mp.wavelengths_nm
        k0 = band_centre_nm(wl)
        est = estimate_opd(mp.T.to(dev, dt), wl.to(dev, dt), num_k=es.num_k, window=es.window,
                           pad_factor=es.pad_factor, search_bins=es.search_bins,
                           search_points=es.search_points, iters=es.iters)
        match = match_points(pred, mp.xy, cfg.prediction_wavelength_nm, k0)
        r_in = _rows_for(name, mp, est, match, cfg.points.min_modulation)
        st = _stats(r_in, est.bin_nm)
        st.update(kind=spec.kind, band_centre_nm=k0, seconds=time.perf_counter() - t0)
        stats[name] = st
        rows += r_in
        per_input.append((name, mp, est, r_in))

    cols = ["input", "label", "input_view", "view", "x_px", "y_px", "inside", "distance_px",
            "alpha_deg", "sigma_deg", "pred_phase_nm", "pred_group_nm", "coarse_nm", "fft_nm",
            "fit_nm", "err_coarse_nm", "err_fft_nm", "err_fit_nm", "rel_err_fit",
            "err_fit_vs_phase_nm", "modulation", "fit_rms", "modulated", "view_ok", "traced"]
    report.write_csv(out / "matched_pairs.csv", rows, cols)
    pv = _per_view(rows)
    report.write_csv(out / "per_view.csv", pv)
    fmt = {"x_px": ".1f", "y_px": ".1f", "distance_px": ".1f", "alpha_deg": ".2f",
           "sigma_deg": ".1f", "pred_phase_nm": ".0f", "pred_group_nm": ".0f",
           "coarse_nm": ".0f", "fft_nm": ".0f", "fit_nm": ".0f", "err_coarse_nm": "+.0f",
           "err_fft_nm": "+.1f", "err_fit_nm": "+.1f", "rel_err_fit": "+.2%",
           "modulation": ".2f"}
    md_pairs = report.markdown_table(
        rows, {"input": "input", "label": "point", "view": "view", "x_px": "x", "y_px": "y",
               "alpha_deg": "α (°)", "sigma_deg": "σ (°)", "pred_phase_nm": "pred. Δ(550)",
               "pred_group_nm": "pred. Δ_g(k₀)", "coarse_nm": "coarse", "fft_nm": "FFT",
               "fit_nm": "fit", "err_fft_nm": "FFT − pred", "err_fit_nm": "fit − pred",
               "rel_err_fit": "rel.", "modulation": "mod."}, fmt)
    report.write_markdown(out / "matched_pairs.md", "# OPD: matched pairs (nm)\n\n" + md_pairs)
    srows = [{"input": n, **s} for n, s in stats.items()]
    k0 = band_centre_nm(per_input[0][1].wavelengths_nm)
    md = [
        "# OPD validation\n",
        f"Predicted views: ray tracer of the prototype "
        f"({cfg.prototype or 'the shipped simulate.yaml'}). "
        f"Prediction compared: **group OPD Δ_g = Δ − λ dΔ/dλ at the band-centre wavenumber "
        f"(λ₀ = {k0:.1f} nm)** of the ray through each measured point (a single-frequency fit "
        f"over the band measures this, not the phase OPD); the phase OPD at "
        f"{cfg.prediction_wavelength_nm:g} nm is listed for reference. Points with fitted "
        f"modulation < {cfg.points.min_modulation:g} are left out of the statistics. "
        f"{OPD_METRICS_NOTE}\n",
        report.markdown_table(
            srows, {"input": "input", "points": "points", "modulated_points": "modulated",
                    "views_matched_correctly": "view match ok", "bin_nm": "bin (nm)",
                    "coarse_max_abs_nm": "coarse max|err|", "fft_max_abs_nm": "FFT max|err|",
                    "fft_max_rel": "FFT max rel", "fit_max_abs_nm": "fit max|err|",
                    "fit_rms_nm": "fit rms", "fit_max_rel": "fit max rel",
                    "fit_vs_phase_median_rel": "fit vs Δ(550) median rel"},
            {"bin_nm": ".0f", "coarse_max_abs_nm": ".0f", "fft_max_abs_nm": ".1f",
             "fft_max_rel": ".2%", "fit_max_abs_nm": ".1f", "fit_rms_nm": ".1f",
             "fit_max_rel": ".2%", "fit_vs_phase_median_rel": ".2%"}),
        "\n## Per view (mean over the view's modulated points, nm)\n",
        report.markdown_table(
            pv, {"input": "input", "view": "view", "points": "points",
                 "pred_phase_550_nm": "pred. Δ(550)", "pred_group_nm": "pred. Δ_g(k₀)",
                 "coarse_nm": "coarse", "fft_nm": "FFT", "fit_nm": "fit",
                 "max_abs_err_fit_nm": "fit max|err|", "max_rel_err_fit": "fit max rel"},
            {"pred_phase_550_nm": ".0f", "pred_group_nm": ".0f", "coarse_nm": ".0f",
             "fft_nm": ".0f", "fit_nm": ".0f", "max_abs_err_fit_nm": ".1f",
             "max_rel_err_fit": ".2%"}),
    ]
    if notes:
        md.append("\nNotes:\n\n" + "\n".join(f"- {n}" for n in notes) + "\n")
    report.write_markdown(out / "summary.md", "\n".join(md))

    t0 = time.perf_counter()
    v_group = group_opd_nm(pred.brf, pred.layout.mean_alpha, pred.layout.mean_sigma, k0).numpy()
    for name, mp, est, r_in in per_input:
        ex = _examples(r_in)
        s = _slug(name)
        _plot_correspondence(out / f"correspondence_{s}.png", pred, r_in, ex, name)
        _plot_polar(out / f"opd_polar_{s}.png", pred, r_in, ex, np.abs(v_group), name)
        if ex:
            _plot_spectra(out / f"spectra_{s}.png", mp, est, r_in, ex, name)
    timings["figures"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_all
    summary = {"inputs": stats, "notes": notes, "band_centre_nm": k0,
               "capture_set": str(capture_set) if capture_set else None,
               "timings_s": timings, "device": str(dev)}
    atomic_write_json(out / "summary.json", summary)
    return summary
