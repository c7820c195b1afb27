"""``hsi-torch demo [--out DIR] [--quick] [--set key=value ...]``: the README's main command
(the command line is :func:`hsi_torch.experiments.cli_entry.run_demo`).

End to end on the virtual prototype (docs/demo.md tells what it writes): **simulate** the
default prototype (the shipped ``simulate.yaml``) into ``OUT/captures`` with the ColorChecker and
the real CAVE cube when the real-data folder holds it (else a built-in synthetic cube: smooth
blends of ColorChecker spectra); **calibrate** from those captures only → ``OUT/calib.npz``;
**reconstruct** every scene with the calibrated bundle, the *oracle* bundle (the simulator's true
B, φ, g and homographies: the cost of calibration) and, calibrated, the TV prior at its default
weight (scores under ``tv``); **score** against the ground truth into ``OUT/summary.json``.

Metrics (reflectance, peak 1; :mod:`hsi_torch.experiments.metrics`, shared with the
experiments): PSNR = 10·log10(1/MSE), spectral angle (SAM) in degrees.
ColorChecker: per patch, the mean reconstructed spectrum over the patch **interior** (pixels at
least ``erode_mm`` = 0.3 mm inside the patch on the diffuser — 3 σ of the diffuser's 0.1 mm blur,
which mixes neighbouring patches near their edges; 2.2 px on the small sensor, 16 px at full
size) against the patch's true spectrum; reported as the mean over the 24 patches (whole-patch
means are reported too). Other scenes: per pixel, over the valid pixels that lie on the scene
(SAM only where the true mean reflectance is ≥ 0.01).

β rule: a fixed default ``beta = 1e4`` (DN² scale of the default prototype's observations; the
useful range is 1e-2…1e6). It is the value measured best for the oracle bundle on this
set (interiors 39.2 dB at 1e4 vs 33.9 dB at 1e3) and the solver is fast there; override with
``--set beta=...``.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from hsi_torch.calibrate.config import CalibrateConfig
from hsi_torch.calibrate.figures import plot_calibration
from hsi_torch.calibrate.pipeline import calibrate_capture_set
from hsi_torch.colour import cube_to_srgb, cube_to_xyz, save_labelled_png, save_preview_panel
from hsi_torch.config import load_config, option
from hsi_torch.experiments.calibration_scores import format_scores, score_against_truth
from hsi_torch.experiments.metrics import (
    colorchecker_scores,
    cube_scores,
    erode_px,
    format_metrics,
    interior_mask,
)
from hsi_torch.experiments.report import new_figure, save_figure
from hsi_torch.io import save_cube, save_cube_formats
from hsi_torch.io.atomic import atomic_write_json
from hsi_torch.io.capture_set import read_truth
from hsi_torch.io.run_record import DEMO_RUN_RECORD, INCOMPLETE_FILE
from hsi_torch.recon import Reconstructor
from hsi_torch.refdata import colorchecker_reflectances
from hsi_torch.resources import DATA_ENV, real_data_dir, shipped_config
from hsi_torch.simulate import SimulateConfig, simulate_capture_set
from hsi_torch.simulate.capture_sets import build_scene
from hsi_torch.simulate.config import SceneSpec
from hsi_torch.simulate.oracle import bundle_from_truth

__all__ = ["DemoConfig", "demo", "score_scene"]



@dataclass
class DemoConfig:
    """Settings of ``hsi-torch demo`` (``--set key=value`` overrides any of them)."""

    simulate_config: Path | None = option(None, "simulator config; null: the shipped simulate.yaml")
    calibrate_config: Path | None = option(None, "calibration config; null: the shipped "
                                                 "calibrate.yaml")
    beta: float = option(1e4, "reconstruction smoothness weight (DN^2)")
    diff_order: int = option(1, "order of the difference operator")
    erode_mm: float = option(0.3, "ColorChecker: score pixels at least this far inside a patch, "
                                  "mm on the diffuser (3 sigma of the 0.1 mm diffuser blur)")
    cave: bool = option(True, "add the real CAVE scene when the real-data folder has it")
    quick_scale: float = option(0.75, "--quick: camera.scale of the simulated sensor")
    device: str = option("cpu", "torch device of calibration/reconstruction")
    seed: int = option(0, "simulator noise seed")
    progress: bool = option(True, "progress bars on stderr")


# --- scenes


def _synthetic_cube(wavelengths_nm: np.ndarray, size: int = 96) -> np.ndarray:
    """A built-in test cube ``(M, size, size)``: smooth blends of six ColorChecker spectra plus
    four flat-spectrum discs (so both smooth and sharp structures appear)."""
    refl_t, _ = colorchecker_reflectances(torch.as_tensor(wavelengths_nm, dtype=torch.float64),
                                          extrapolate="edge")
    refl = refl_t.detach().cpu().numpy()
    base = refl[[14, 13, 12, 11, 2, 18]]  # red, green, blue, yellow-green, blue sky, white
    y, x = np.mgrid[0:size, 0:size] / (size - 1)
    w = np.stack([
        np.exp(-((x - 0.2) ** 2 + (y - 0.25) ** 2) / 0.05),
        np.exp(-((x - 0.8) ** 2 + (y - 0.3) ** 2) / 0.05),
        np.exp(-((x - 0.5) ** 2 + (y - 0.8) ** 2) / 0.06),
        0.5 + 0.5 * np.sin(6 * x) * np.cos(4 * y),
        0.3 * np.ones_like(x),
    ])  # fmt: skip
    w = w / w.sum(0, keepdims=True)
    cube = np.einsum("kyx,km->myx", w, base[:5])
    for (cx, cy), k in zip(((0.3, 0.6), (0.7, 0.65), (0.5, 0.35), (0.15, 0.85)),
                           (5, 1, 16, 7), strict=True):  # fmt: skip
        disc = (x - cx) ** 2 + (y - cy) ** 2 < 0.01
        cube[:, disc] = refl[k][:, None]
    return cube.astype(np.float32)


def _scene_specs(cfg: DemoConfig, out: Path, wl: np.ndarray, log) -> list[dict[str, Any]]:
    specs: list[dict[str, Any]] = [
        {"kind": "colorchecker", "name": "colorchecker",
         "params": {"width_mm": 8.4, "center_mm": [0.0, 1.4]}},
    ]  # fmt: skip
    cave_dir = real_data_dir("cave_stuffed_toys")
    if cfg.cave and cave_dir is not None and cave_dir.is_dir():
        specs.append({"kind": "cave", "name": "cave", "optional": True,
                      "params": {"folder": str(cave_dir), "width_mm": 7.0,
                                 "center_mm": [0.0, 0.9]}})  # fmt: skip
    else:
        why = ("disabled (cave=false)" if not cfg.cave else
               f"not found (no cave_stuffed_toys in the real-data folder; set {DATA_ENV})")
        log(f"CAVE scene {why}: using the built-in synthetic cube instead")
        path = out / "synthetic_scene.npz"
        save_cube(path, _synthetic_cube(wl), wl)
        specs.append({"kind": "cube", "name": "synthetic", "path": str(path),
                      "params": {"width_mm": 7.0, "center_mm": [0.0, 0.9]}})  # fmt: skip
    return specs


# --- plots


def _plot_colorchecker(path: Path, wl, truth, est_cal, est_orc, scores_cal, scores_orc) -> None:
    fig, axes = new_figure(4, 6, figsize=(15, 9), sharex=True, sharey=True)
    for k, ax in enumerate(axes.flat):
        ax.plot(wl, truth[k], "k-", lw=2, label="truth")
        ax.plot(wl, est_cal[k], "r-", lw=1.3, label="calibrated")
        ax.plot(wl, est_orc[k], "b--", lw=1.0, label="oracle")
        p_k, s_k = scores_cal["psnr_db"][k], scores_cal["sam_deg"][k]
        ax.set_title(f"{k + 1}: {p_k:.1f} dB / {s_k:.1f}°", fontsize=8)
        ax.set_ylim(0, 1.0)
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(
        f"ColorChecker patch interiors: calibrated {scores_cal['mean_psnr_db']:.1f} dB / "
        f"{scores_cal['mean_sam_deg']:.2f}°, oracle {scores_orc['mean_psnr_db']:.1f} dB / "
        f"{scores_orc['mean_sam_deg']:.2f}° (reflectance vs wavelength, nm)"
    )
    fig.tight_layout()
    save_figure(fig, path, dpi=90, tight=False)


def _plot_pixels(path: Path, wl, truth, cal, orc, mask, name: str, n: int = 6) -> None:
    ys, xs = np.nonzero(mask)
    if not len(ys):
        return
    rng = np.random.default_rng(0)
    pick = rng.choice(len(ys), size=min(n, len(ys)), replace=False)
    fig, axes = new_figure(1, len(pick), figsize=(3 * len(pick), 3), sharey=True)
    for ax, i in zip(np.atleast_1d(axes), pick, strict=False):
        y, x = ys[i], xs[i]
        ax.plot(wl, truth[:, y, x], "k-", lw=2, label="truth")
        ax.plot(wl, cal[:, y, x], "r-", lw=1.3, label="calibrated")
        ax.plot(wl, orc[:, y, x], "b--", lw=1.0, label="oracle")
        ax.set_title(f"{name} pixel (x={x}, y={y})", fontsize=8)
        ax.grid(alpha=0.3)
    np.atleast_1d(axes)[0].legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path, dpi=90, tight=False)


def _score_text(e: dict[str, Any], key: str) -> str:
    s = e[key]
    if "mean_psnr_db" in s:
        return f"{s['mean_psnr_db']:.1f} dB / {s['mean_sam_deg']:.2f} deg"
    return f"{s['psnr_db']:.1f} dB / {s['mean_sam_deg']:.2f} deg"


def _previews(out: Path, name: str, wl, truth: np.ndarray, cubes: dict[str, np.ndarray],
              entry: dict[str, Any], beta: float) -> None:
    """``<name>_preview.png`` (calibrated), ``<name>_oracle_preview.png``,
    ``<name>_truth_preview.png`` (enlarged, captioned) and ``<name>_panel.png`` (the three side by
    side). All three are rendered on one exposure (the
    truth's 99.5th-percentile luminance is white), so that they compare."""
    t = torch.from_numpy(np.asarray(truth, np.float64))
    ref = float(np.percentile(cube_to_xyz(t, wl)[1].numpy(), 99.5))
    exposure = 1.0 / ref if ref > 0 else 1.0
    rgbs = {
        "truth": cube_to_srgb(t, wl, exposure=exposure),
        "calibrated": cube_to_srgb(torch.from_numpy(np.nan_to_num(cubes["calibrated"])), wl,
                                   exposure=exposure),  # fmt: skip
        "oracle": cube_to_srgb(torch.from_numpy(np.nan_to_num(cubes["oracle"])), wl,
                               exposure=exposure),  # fmt: skip
    }
    files = {"calibrated": f"{name}_preview.png", "oracle": f"{name}_oracle_preview.png",
             "truth": f"{name}_truth_preview.png"}  # fmt: skip
    for key, rgb in rgbs.items():
        what = {"truth": "ground truth", "calibrated": "calibrated bundle (calib.npz)",
                "oracle": "oracle bundle (true B, phi, g)"}[key]  # fmt: skip
        cap = f"{name} | {what}" + ("" if key == "truth" else
                                    f" | beta {beta:g} | {_score_text(entry, key)}")
        save_labelled_png(rgb, out / files[key], caption=cap, min_size=512)
    save_preview_panel(
        [("truth", rgbs["truth"]),
         (f"calibrated: {_score_text(entry, 'calibrated')}", rgbs["calibrated"]),
         (f"oracle: {_score_text(entry, 'oracle')}", rgbs["oracle"])],
        out / f"{name}_panel.png",
        caption=f"{name}: truth | reconstruction with the calibrated bundle | with the oracle "
                f"bundle; beta {beta:g}, sRGB D65, one exposure for all three",
    )  # fmt: skip


def score_scene(
    spec: dict[str, Any], cubes: dict[str, np.ndarray], valids: dict[str, np.ndarray],
    truth: dict[str, np.ndarray], out: Path, erode_px: float, log,
) -> tuple[dict[str, Any], np.ndarray, np.ndarray]:
    """Score one scene's ``calibrated`` and ``oracle`` cubes against the simulator's truth.

    ColorChecker: the per-patch mean spectrum over the patch interiors (≥ ``erode_px`` inside,
    see :func:`erode_px`)
    and over whole patches, per pixel over the interiors and over every valid pixel
    (``per_pixel_valid``); other scenes: per pixel over the valid pixels on the scene, and on its
    brighter half (:func:`cube_scores`, which adds the field's metrics under ``metrics``). Writes
    the spectra plot ``<name>_spectra.png``.

    Returns:
        ``(entry, both, true_cube)``: the scores, the pixels valid in both cubes, the truth.
    """
    name = spec["name"]
    wl = np.asarray(truth["wavelengths_nm"], np.float64)
    both = valids["calibrated"] & valids["oracle"]
    true_cube = np.asarray(truth[f"scene_{name}"], np.float64)
    entry: dict[str, Any] = {"valid_pixels": int(both.sum())}
    if spec["kind"] == "colorchecker":
        pidx = truth[f"{name}_patch_index"]
        spectra = np.asarray(truth[f"{name}_spectra"], np.float64)
        sc = {k: colorchecker_scores(cubes[k], both, pidx, spectra, erode_px)
              for k in cubes}  # fmt: skip
        whole = {k: colorchecker_scores(cubes[k], both, pidx, spectra, 0.0) for k in cubes}
        inner = both & (pidx >= 0)
        inner &= np.logical_or.reduce([interior_mask(pidx == k, erode_px)
                                       for k in range(len(spectra))])  # fmt: skip
        per_pixel = {k: cube_scores(cubes[k], true_cube, inner) for k in cubes}
        # the field's metrics need whole images (SSIM windows): every valid pixel of the frame
        per_pixel_valid = {k: cube_scores(cubes[k], true_cube, both) for k in cubes}
        entry.update(
            metric="per-patch mean spectrum over patch interiors "
                   f"(>= {erode_px:.1f} px inside), mean over patches",
            calibrated=sc["calibrated"], oracle=sc["oracle"],
            **({"tv": sc["tv"]} if "tv" in sc else {}),
            whole_patch={k: {"mean_psnr_db": v["mean_psnr_db"],
                             "mean_sam_deg": v["mean_sam_deg"]} for k, v in whole.items()},
            per_pixel_interiors=per_pixel,
            per_pixel_valid=per_pixel_valid,
        )  # fmt: skip
        _plot_colorchecker(out / f"{name}_spectra.png", wl, spectra,
                           np.asarray(sc["calibrated"]["estimated_spectra"]),
                           np.asarray(sc["oracle"]["estimated_spectra"]),
                           sc["calibrated"], sc["oracle"])  # fmt: skip
    else:
        on_scene = both.copy()
        try:
            sobj = build_scene(SceneSpec(kind=spec["kind"], name=name, path=spec.get("path"),
                                         params=dict(spec.get("params", {}))))
            x_min, x_max, y_min, y_max = sobj.extent
            xy = truth["diffuser_xy"]
            on_scene &= ((xy[..., 0] >= x_min) & (xy[..., 0] <= x_max)
                         & (xy[..., 1] >= y_min) & (xy[..., 1] <= y_max))  # fmt: skip
        except Exception as exc:  # noqa: BLE001 - the extent only narrows the scored pixels
            log(f"      scene {name}: extent unknown ({exc}); scoring every valid pixel")
        entry.update(
            metric="per pixel over valid pixels on the scene (SAM where mean truth >= 0.01)",
            calibrated=cube_scores(cubes["calibrated"], true_cube, on_scene),
            oracle=cube_scores(cubes["oracle"], true_cube, on_scene),
            **({"tv": cube_scores(cubes["tv"], true_cube, on_scene)} if "tv" in cubes else {}),
        )
        _plot_pixels(out / f"{name}_spectra.png", wl, true_cube, cubes["calibrated"],
                     cubes["oracle"], on_scene & (true_cube.mean(0) > 0.05), name)  # fmt: skip
    return entry, both, true_cube


def metrics_lines(entry: dict[str, Any]) -> list[str]:
    """The field's metrics of one scored scene (:func:`score_scene`'s entry), one line per
    bundle: per pixel over every valid pixel (ColorChecker) or the valid pixels on the scene."""
    src = entry.get("per_pixel_valid", entry)
    where = "every valid pixel" if "per_pixel_valid" in entry else "valid pixels on the scene"
    out = [f"    the field's metrics, per pixel over {where}:"]
    for k in ("calibrated", "oracle", "tv"):
        if "metrics" in src.get(k, {}):
            out.append(f"      {k}: {format_metrics(src[k]['metrics'])}")
    return out


# --- the demo


def demo(
    out: str | Path, cfg: DemoConfig | None = None, *, quick: bool = False, log=print
) -> dict[str, Any]:
    """Simulate → calibrate → reconstruct → score (see the module docstring).

    Args:
        out: output folder (created).
        cfg: :class:`DemoConfig` (defaults when ``None``).
        quick: smaller sensor (``quick_scale``), float32 rendering, no figures.

    Returns:
        The summary dict written to ``OUT/summary.json``.
    """
    cfg = cfg or DemoConfig()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    tm: dict[str, float] = {}
    t_all = time.perf_counter()

    # ---- 1. simulate -------------------------------------------------------------------------
    t0 = time.perf_counter()
    sim_path = cfg.simulate_config or shipped_config("simulate")
    if not Path(sim_path).is_file():
        raise FileNotFoundError(f"simulator config {sim_path} not found (set simulate_config)")
    grid_wl = np.arange(430.0, 670.0 + 1e-9, 10.0)
    scenes = _scene_specs(cfg, out, grid_wl, log)
    overrides = [f"captures.scenes={json.dumps(scenes)}", f"render.seed={cfg.seed}",
                 f"render.progress={'true' if cfg.progress else 'false'}"]  # fmt: skip
    if quick:
        overrides += [f"camera.scale={cfg.quick_scale}", "render.dtype=float32",
                      "render.figures=false"]  # fmt: skip
    scfg = load_config(sim_path, SimulateConfig, overrides)
    cap_dir = out / "captures"
    if quick:
        what = f"smaller sensor (camera.scale {cfg.quick_scale:g}), float32 rendering, no figures"
        log(f"[quick] a smoke run: the demo's chain on a {what}; its scores are not the demo's")
    log(f"[1/4] simulating the prototype into {cap_dir} ...")
    summary = simulate_capture_set(scfg, cap_dir, log=log)
    log("      " + summary.report().replace("\n", "\n      "))
    tm["simulate"] = time.perf_counter() - t0

    # ---- 2. calibrate ------------------------------------------------------------------------
    t0 = time.perf_counter()
    cal_path = cfg.calibrate_config or shipped_config("calibrate")
    ccfg = load_config(cal_path, CalibrateConfig,
                       [f"progress={'true' if cfg.progress else 'false'}"])  # fmt: skip
    log(f"[2/4] calibrating from {cap_dir} ...")
    bundle, report = calibrate_capture_set(cap_dir, ccfg, device=cfg.device)
    bundle_path = out / "calib.npz"
    bundle.save(bundle_path)
    atomic_write_json(out / "calib.report.json", report.to_dict())
    plot_calibration(bundle, out / "calib_diagnostics.png", report=report)
    log("      " + str(report).replace("\n", "\n      "))
    cal_scores = score_against_truth(bundle, cap_dir)
    scores = format_scores(cal_scores, targets=not quick)
    if quick:  # the targets are set for the demo's sensor, not this smaller one
        scores += "\n(--quick: a smoke run on a smaller sensor; the calibration targets are judged "
        scores += "at the demo's size only, and these scores are not the demo's)"
    log("      calibration vs truth:\n      " + scores.replace("\n", "\n      "))
    tm["calibrate"] = time.perf_counter() - t0

    # ---- 3./4. reconstruct and score ---------------------------------------------------------
    t0 = time.perf_counter()
    truth, tmeta = read_truth(cap_dir)
    oracle = bundle_from_truth(cap_dir)
    recs = {
        "calibrated": Reconstructor(bundle, beta=cfg.beta, diff_order=cfg.diff_order,
                                    device=cfg.device),
        "oracle": Reconstructor(oracle, beta=cfg.beta, diff_order=cfg.diff_order,
                                device=cfg.device),
    }  # fmt: skip
    # the calibrated bundle with the spatial (TV) prior at its default weight, beside per-pixel
    recs["tv"] = Reconstructor(recs["calibrated"].sensing, prior="tv")
    wl = np.asarray(truth["wavelengths_nm"], np.float64)
    results: dict[str, Any] = {}
    log(f"[3/4] reconstructing {', '.join(s['name'] for s in scenes)} (beta = {cfg.beta:g}) ...")
    for spec in scenes:
        name = spec["name"]
        cap = cap_dir / "scenes" / f"{name}.tif"
        if not cap.is_file():
            log(f"      scene {name}: no capture (skipped by the simulator)")
            continue
        cubes, valids, tims = {}, {}, {}
        for key, rec in recs.items():
            res = rec.reconstruct_file(cap)
            cubes[key] = res.cube.detach().cpu().double().numpy()
            valids[key] = res.valid.detach().cpu().numpy()
            tims[key] = res.timings.get("total", float("nan"))
        entry, both, true_cube = score_scene(spec, cubes, valids, truth, out,
                                             erode_px(truth, cfg.erode_mm), log)
        entry.update(capture=str(cap), reconstruct_s=tims)
        cube_t = torch.from_numpy(cubes["calibrated"]).float()
        save_cube_formats(out / name, cube_t, wl, torch.from_numpy(valids["calibrated"]),
                          metadata={"scene": name, "bundle": str(bundle_path), "beta": cfg.beta},
                          formats=("npz", "tiff"))  # fmt: skip
        _previews(out, name, wl, true_cube * both[None], cubes, entry, cfg.beta)
        results[name] = entry
    tm["reconstruct+score"] = time.perf_counter() - t0
    tm["total"] = time.perf_counter() - t_all

    summary_d = {
        "beta": cfg.beta,
        "beta_rule": "fixed default of DemoConfig.beta (1e4, DN^2 scale); --set beta=... to change",
        "quick": quick,
        "sensor_size": list(summary.sensor_size),
        "valid_pixels_true": int(truth["valid"].sum()),
        "calibration": {k: v for k, v in cal_scores.items()},
        "scenes": results,
        "timings_s": tm,
        "files": sorted(p.name for p in out.iterdir()
                        if p.is_file() and p.name not in (INCOMPLETE_FILE, DEMO_RUN_RECORD)),
    }
    atomic_write_json(out / "summary.json", summary_d)

    # ---- report ------------------------------------------------------------------------------
    lines = ["[4/4] results (reflectance, PSNR = 10 log10(1/MSE), SAM in degrees):"]
    for name, e in results.items():
        c, o = e["calibrated"], e["oracle"]
        if "mean_psnr_db" in c:
            lines.append(
                f"  {name}: {c['patches']} patches, interiors: calibrated "
                f"{c['mean_psnr_db']:.1f} dB / {c['mean_sam_deg']:.2f} deg, oracle "
                f"{o['mean_psnr_db']:.1f} dB / {o['mean_sam_deg']:.2f} deg; whole patches: "
                f"calibrated {e['whole_patch']['calibrated']['mean_psnr_db']:.1f} dB / "
                f"{e['whole_patch']['calibrated']['mean_sam_deg']:.2f} deg"
            )
            if "tv" in e:
                pv, pc = e["per_pixel_valid"], e["per_pixel_valid"]["calibrated"]
                lines.append(
                    f"    per pixel over every valid pixel: calibrated "
                    f"{pc['psnr_db']:.1f} dB / {pc['median_sam_deg']:.2f}"
                    f" deg median, TV prior {pv['tv']['psnr_db']:.1f} dB / "
                    f"{pv['tv']['median_sam_deg']:.2f} deg median (patch interiors: TV "
                    f"{e['tv']['mean_psnr_db']:.1f} dB)"
                )
        else:
            lines.append(
                f"  {name}: {c['pixels']} px, calibrated {c['psnr_db']:.1f} dB / "
                f"{c['mean_sam_deg']:.2f} deg, oracle {o['psnr_db']:.1f} dB / "
                f"{o['mean_sam_deg']:.2f} deg"
                + (f", TV prior (calibrated) {e['tv']['psnr_db']:.1f} dB / "
                   f"{e['tv']['mean_sam_deg']:.2f} deg" if "tv" in e else "")
            )
        lines.extend(metrics_lines(e))
    lines.append(
        "  time " + ", ".join(f"{k} {v:.1f} s" for k, v in tm.items()) + f"; outputs in {out}"
    )
    log("\n".join(lines))
    return summary_d
