"""Per-pixel vs spatial-spectral reconstruction (``hsi-torch experiment spatial``; the outputs,
method and measured numbers are in docs/experiments.md, *Per-pixel vs spatial-spectral*, and
docs/spatial.md).

Every scene of a simulated capture set with ground truth (``captures``, or a fresh simulation of
``prototype`` when null) is reconstructed from one bundle (``oracle`` or a ``.npz`` path) and
``β`` with the per-pixel NNLS solver and with the TV prior (:mod:`hsi_torch.recon.spatial`) at
each ``lams`` entry, and scored against the truth (:mod:`hsi_torch.experiments.metrics`,
reflectance, PSNR = 10·log10(1/MSE), SAM in degrees) per pixel over the scene's footprint (valid
pixels where the truth is non-zero) and its brighter half (true mean reflectance ≥ the median);
the ColorChecker also over whole patches and as per-patch mean spectra (whole patches and
interiors, ``erode_mm`` inside). ``solve s`` in the table is the frame's solve stage, per-pixel
NNLS included for the TV rows.
"""

from __future__ import annotations

import csv
import io
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from hsi_torch.config import load_config, option
from hsi_torch.console import info as log
from hsi_torch.experiments.metrics import (
    METRIC_FORMATS,
    colorchecker_scores,
    cube_scores,
    erode_px,
)
from hsi_torch.experiments.report import new_figure, save_figure, start_run
from hsi_torch.io.atomic import atomic_write_json, atomic_write_text
from hsi_torch.io.bundle import CalibrationBundle
from hsi_torch.io.capture_set import read_truth
from hsi_torch.recon import Reconstructor
from hsi_torch.recon.spatial import DEFAULT_LAM
from hsi_torch.resources import real_data_dir, shipped_config
from hsi_torch.simulate.capture_sets import simulate_capture_set
from hsi_torch.simulate.config import SceneSpec, SimulateConfig
from hsi_torch.simulate.oracle import bundle_from_truth

__all__ = ["SpatialConfig", "run_spatial", "scene_scores"]


def _h(text: str) -> dict[str, str]:
    return {"help": text}


@dataclass
class SpatialConfig:
    """``hsi-torch experiment spatial`` configuration (see the module docstring)."""

    captures: Path | None = option(None, "simulated capture set with ground truth (e.g. a demo's "
                                         "captures folder); null: simulate one into OUT/captures")
    prototype: Path | None = option(None, "when simulating: SimulateConfig YAML (null: the "
                                          "shipped simulate.yaml, the small default prototype)")
    prototype_overrides: list[str] = option(text="when simulating: overrides of the prototype "
                                                 "config", factory=list)
    bundle: str = option("oracle", "oracle | path to a bundle .npz")
    beta: float = option(1e4, "spectral smoothness weight (DN^2)")
    diff_order: int = 1
    lams: list[float | Literal["auto", "discrepancy"]] = field(
        default_factory=lambda: [DEFAULT_LAM, "auto"],
        metadata=_h("TV weights to compare with per-pixel: relative lam values, auto (SURE), "
                   "discrepancy"))
    ranks: list[int] = option(text="also the TV on k leading spectral components "
                                   "(spectral_rank), at the first numeric lams entry (default "
                                   "lam if none), for each k listed", factory=list)
    erode_mm: float = option(0.3, "ColorChecker interiors: mm inside a patch on the diffuser")
    scenes: list[str] = field(
        default_factory=list, metadata=_h("scene names to score (empty: every scene with truth)"))
    seed: int = 0
    dtype: Literal["float32", "float64"] = "float32"
    device: str | None = None
    progress: bool = True


def _simulate(cfg: SpatialConfig, out: Path, dev: str, oracle: bool) -> Path:
    proto = load_config(cfg.prototype or shipped_config("simulate"), SimulateConfig,
                        list(cfg.prototype_overrides))
    scenes = [SceneSpec("colorchecker", "colorchecker",
                        params={"width_mm": 8.4, "center_mm": [0.0, 1.4]})]
    cave = real_data_dir("cave_stuffed_toys")
    if cave is not None and cave.is_dir():
        scenes.append(SceneSpec("cave", "cave", params={"folder": str(cave), "width_mm": 7.0,
                                                        "center_mm": [0.0, 0.9]}))
    scenes.append(SceneSpec("usaf", "usaf", params={"groups": [2, 3, 4], "magnification": 1.0,
                                                    "center_mm": [0.0, 1.0]}))
    cap = proto.captures
    cap.scenes = scenes
    if oracle:  # the oracle bundle needs only the ground truth
        cap.scan_wavelengths_nm = []
        cap.white_shots, cap.dark_frames, cap.grid.poses = 0, 0, []
    proto.render.figures = False
    proto.render.seed = int(cfg.seed)
    cs = out / "captures"
    simulate_capture_set(proto, cs, device=dev, progress=cfg.progress, log=lambda *a: None)
    return cs


def scene_scores(
    name: str, cube: np.ndarray, valid: np.ndarray, truth: dict[str, np.ndarray], erode: float
) -> dict[str, Any]:
    """Scores of one reconstructed ``cube (M, h, w)`` of scene ``name`` (see the module
    docstring): ``footprint`` (per pixel, with ``bright_half``), and for a ColorChecker
    ``whole_patches_per_pixel``, ``whole_patch_means``, ``interior_means``."""
    t = np.asarray(truth[f"scene_{name}"], np.float64)
    foot = valid & (t.max(0) > 0)
    out: dict[str, Any] = {"footprint": cube_scores(cube, t, foot)}
    if f"{name}_patch_index" in truth:
        pidx = truth[f"{name}_patch_index"]
        spectra = np.asarray(truth[f"{name}_spectra"], np.float64)
        out["whole_patches_per_pixel"] = cube_scores(cube, t, valid & (pidx >= 0))
        for key, e in (("whole_patch_means", 0.0), ("interior_means", erode)):
            sc = colorchecker_scores(cube, valid, pidx, spectra, e)
            out[key] = {"mean_psnr_db": sc["mean_psnr_db"], "mean_sam_deg": sc["mean_sam_deg"]}
    return out


def _row(scene: str, method: str, sc: dict[str, Any], info: dict[str, Any]) -> dict[str, Any]:
    f, b = sc["footprint"], sc["footprint"].get("bright_half", {})
    row = {
        "scene": scene, "method": method,
        "lam": info.get("lam", ""), "noise_sigma_dn": info.get("noise_sigma", ""),
        "psnr_db": f["psnr_db"], "median_sam_deg": f["median_sam_deg"],
        "bright_psnr_db": b.get("psnr_db", float("nan")),
        "bright_median_sam_deg": b.get("median_sam_deg", float("nan")),
        "patches_pp_psnr_db": "", "patch_means_psnr_db": "", "interior_means_psnr_db": "",
        "solve_seconds": info.get("solve_seconds", float("nan")),
    }  # fmt: skip
    m = f.get("metrics", {})  # the field's metrics over the footprint (hsi_torch.metrics)
    for k in ("psnr_bands_db", "ssim", "sam_deg", "ergas", "rmse", "mrae"):
        row[k] = m.get(k, float("nan"))
    if "whole_patches_per_pixel" in sc:
        row["patches_pp_psnr_db"] = sc["whole_patches_per_pixel"]["psnr_db"]
        row["patch_means_psnr_db"] = sc["whole_patch_means"]["mean_psnr_db"]
        row["interior_means_psnr_db"] = sc["interior_means"]["mean_psnr_db"]
    return row


_COLUMNS = [
    ("scene", "scene"), ("method", "method"), ("lam", "lam"), ("noise_sigma_dn", "σ̂ DN"),
    ("psnr_db", "PSNR dB"), ("median_sam_deg", "med SAM°"),
    ("bright_psnr_db", "bright PSNR"), ("bright_median_sam_deg", "bright med SAM°"),
    ("patches_pp_psnr_db", "patches px PSNR"), ("patch_means_psnr_db", "patch means PSNR"),
    ("interior_means_psnr_db", "interiors PSNR"),
    ("psnr_bands_db", "PSNR/band 0-255"), ("ssim", "SSIM"), ("sam_deg", "mean SAM°"),
    ("ergas", "ERGAS"), ("rmse", "RMSE"), ("mrae", "MRAE"), ("solve_seconds", "solve s"),
]


def _fmt(v: Any, key: str = "") -> str:
    if isinstance(v, float) and key in METRIC_FORMATS and key != "psnr_db":
        return format(v, METRIC_FORMATS[key])  # the field's metrics, as in the other tables
    if isinstance(v, float):
        return f"{v:.3g}" if abs(v) < 0.1 or abs(v) >= 1e4 else f"{v:.2f}"
    return str(v)


def _write_tables(out: Path, rows: list[dict[str, Any]]) -> str:
    lines = ["| " + " | ".join(h for _, h in _COLUMNS) + " |", "|" + "---|" * len(_COLUMNS)]
    for r in rows:
        lines.append("| " + " | ".join(_fmt(r[k], k) for k, _ in _COLUMNS) + " |")
    md = "\n".join(lines) + "\n"
    atomic_write_text(out / "table.md", md)
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=[k for k, _ in _COLUMNS])
    w.writeheader()
    w.writerows(rows)
    atomic_write_text(out / "table.csv", buf.getvalue())
    return md


def _plot_errors(path: Path, name: str, truth: np.ndarray, cubes: dict[str, np.ndarray],
                 valid: np.ndarray) -> None:
    errs = {k: np.where(valid, np.sqrt(np.mean((c - truth) ** 2, 0)), np.nan)
            for k, c in cubes.items()}  # fmt: skip
    vmax = float(np.nanpercentile(np.concatenate([e[valid] for e in errs.values()]), 99))
    keys = list(errs)
    fig, axes = new_figure(1, len(keys) + 1, figsize=(3.6 * (len(keys) + 1), 3.4))
    for ax, k in zip(axes, keys, strict=False):
        im = ax.imshow(errs[k], vmin=0, vmax=vmax, cmap="magma")
        ax.set_title(f"{name}: {k}\nRMS error over bands", fontsize=8)
        ax.axis("off")
    fig.colorbar(im, ax=axes[len(keys) - 1], fraction=0.046)
    ref = keys[0]
    d = errs[keys[-1]] - errs[ref]
    lim = float(np.nanpercentile(np.abs(d[valid]), 99)) or 1.0
    im2 = axes[-1].imshow(d, vmin=-lim, vmax=lim, cmap="coolwarm")
    axes[-1].set_title(f"{keys[-1]} − {ref}\n(blue: spatial better)", fontsize=8)
    axes[-1].axis("off")
    fig.colorbar(im2, ax=axes[-1], fraction=0.046)
    fig.tight_layout()
    save_figure(fig, path, dpi=90, tight=False)


def _plot_spectra(path: Path, name: str, wl: np.ndarray, truth: np.ndarray,
                  cubes: dict[str, np.ndarray], valid: np.ndarray, n: int = 6) -> None:
    level = truth.mean(0)
    gy, gx = np.gradient(level)
    edge = np.hypot(gx, gy)
    cand = valid & (level > 0.05)
    ys, xs = np.nonzero(cand)
    if not len(ys):
        return
    order = np.argsort(edge[ys, xs])
    pick = list(order[-(n // 2):]) + list(order[np.linspace(0, len(order) // 2, n - n // 2,
                                                            dtype=int)])  # fmt: skip
    fig, axes = new_figure(1, len(pick), figsize=(3 * len(pick), 3), sharey=True)
    for ax, i in zip(np.atleast_1d(axes), pick, strict=False):
        y, x = ys[i], xs[i]
        ax.plot(wl, truth[:, y, x], "k-", lw=2, label="truth")
        for k, c in cubes.items():
            ax.plot(wl, c[:, y, x], lw=1.1, label=k)
        where = "edge" if edge[y, x] >= np.median(edge[cand]) else "flat"
        ax.set_title(f"{name} ({where}) x={x}, y={y}", fontsize=8)
        ax.grid(alpha=0.3)
    np.atleast_1d(axes)[0].legend(fontsize=6)
    fig.tight_layout()
    save_figure(fig, path, dpi=90, tight=False)


def run_spatial(cfg: SpatialConfig, out: str | Path, *, device: str | None = None
                ) -> dict[str, Any]:
    """Run the comparison (see the module docstring); returns the summary written to
    ``out/summary.json``."""
    t_all, out, dev, dt = start_run(out, cfg, device)
    dev = str(dev)
    oracle = cfg.bundle == "oracle"
    cs = Path(cfg.captures) if cfg.captures is not None else _simulate(cfg, out, dev, oracle)
    truth, _ = read_truth(cs)
    bundle = bundle_from_truth(cs) if oracle else CalibrationBundle.load(cfg.bundle)
    wl = np.asarray(truth["wavelengths_nm"], np.float64)
    ep = erode_px(truth, cfg.erode_mm)
    names = [p.stem for p in sorted((cs / "scenes").glob("*.tif"))
             if f"scene_{p.stem}" in truth]  # fmt: skip
    if cfg.scenes:
        missing = [s for s in cfg.scenes if s not in names]
        if missing:
            raise ValueError(f"config key 'scenes': no capture with truth for {missing} in "
                             f"{cs} (available: {names})")
        names = list(cfg.scenes)
    methods: list[tuple[str, dict[str, Any]]] = [("per-pixel", {"prior": "none"})]
    methods += [(f"tv lam={lam}", {"prior": "tv", "lam": lam}) for lam in cfg.lams]
    lam_k = next((v for v in cfg.lams if not isinstance(v, str)), DEFAULT_LAM)
    methods += [(f"tv lam={lam_k} k={k}", {"prior": "tv", "lam": lam_k, "spectral_rank": int(k)})
                for k in cfg.ranks]
    recs = {m: Reconstructor(bundle, beta=cfg.beta, diff_order=cfg.diff_order, device=dev,
                             dtype=dt, **kw) for m, kw in methods}  # fmt: skip
    rows: list[dict[str, Any]] = []
    results: dict[str, Any] = {}
    for name in names:
        t_cube = np.asarray(truth[f"scene_{name}"], np.float64)
        cubes: dict[str, np.ndarray] = {}
        entry: dict[str, Any] = {}
        valid_all = None
        for m, rec in recs.items():
            t0 = time.perf_counter()
            res = rec.reconstruct_file(cs / "scenes" / f"{name}.tif")
            secs = time.perf_counter() - t0
            cube = res.cube.detach().cpu().double().numpy()
            valid = res.valid.detach().cpu().numpy()
            valid_all = valid if valid_all is None else valid_all & valid
            info = {k: res.stats[k] for k in ("lam", "lam_abs", "lam_rule", "noise_sigma",
                                              "spatial_iterations", "spatial_converged")
                    if k in res.stats}  # fmt: skip
            info["seconds"] = secs
            info["solve_seconds"] = res.timings.get("solve", float("nan"))
            sc = scene_scores(name, cube, valid, truth, ep)
            entry[m] = {"scores": sc, **info}
            rows.append(_row(name, m, sc, info))
            cubes[m] = np.where(valid[None], cube, np.nan)
        results[name] = entry
        assert valid_all is not None
        _plot_errors(out / f"{name}_error.png", name, t_cube, cubes, valid_all)
        _plot_spectra(out / f"{name}_spectra.png", name, wl, t_cube, cubes, valid_all)
    md = _write_tables(out, rows)
    summary = {
        "captures": str(cs), "bundle": "oracle (simulator truth)" if oracle else cfg.bundle,
        "beta": cfg.beta, "lams": list(cfg.lams), "scenes": results, "table": rows,
        "total_s": time.perf_counter() - t_all,
    }  # fmt: skip
    atomic_write_json(out / "summary.json", json.loads(json.dumps(summary, default=float)))
    log(md)
    return summary
