"""``hsi-torch demo --full --out DIR``: the whole chain at the original prototype's size.

The reference run for every claim about quality, speed and memory: the full-size prototype
(``simulate_full.yaml``: 2896 × 2784 sensor, 3.8 µm pixels, ≈ 3.06·10⁵ valid reference-frame
pixels) with the ColorChecker, the USAF 1951 target and the real CAVE scene (or, without the
real data, the built-in synthetic cube). Each stage runs as its own ``hsi-torch`` command in a
child process, so its wall time, CPU time and **peak resident memory** are its own (``os.wait4``):

1. ``simulate`` the capture set with ground truth → ``OUT/captures``;
2. ``calibrate`` it with the shipped defaults → ``OUT/calib/calib.npz``;
3. ``calibrate --oracle``: the bundle of the truth → ``OUT/oracle/oracle.npz``;
4. ``reconstruct`` the scenes with each bundle → ``OUT/cubes_calibrated``, ``OUT/cubes_oracle``;
5. score in this process (calibration against the truth; every scene with both bundles:
   ColorChecker patch-interior means, whole patches and per pixel in the interiors; the other
   scenes per pixel on all valid pixels and on the brighter half; PSNR and spectral angle),
   write ``summary.json``, the labelled previews and panels, and the spectra plots.

The small default demo (``hsi-torch demo``) is the quick, in-process version of the same chain.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from hsi_torch.experiments.calibration_scores import (
    format_scores,
    score_against_truth,
    targets_met,
)
from hsi_torch.experiments.demo import _previews, _scene_specs, metrics_lines, score_scene
from hsi_torch.experiments.metrics import erode_px
from hsi_torch.io import load_cube
from hsi_torch.io.atomic import atomic_write_json
from hsi_torch.io.capture_set import read_truth
from hsi_torch.profiling import run_child
from hsi_torch.resources import shipped_config

__all__ = ["demo_full", "score_full"]


def _hsi(*args: str) -> list[str]:
    return [sys.executable, "-m", "hsi_torch", "-q", *args]


def _full_scenes(cfg: Any, out: Path, log) -> list[dict[str, Any]]:
    """The scene specs of the full-size run: the demo's (ColorChecker, CAVE or the synthetic
    cube) with the USAF target second."""
    grid_wl = np.arange(430.0, 670.0 + 1e-9, 10.0)
    scenes = _scene_specs(cfg, out, grid_wl, log)
    scenes.insert(1, {"kind": "usaf", "name": "usaf",
                      "params": {"groups": [2, 3, 4], "magnification": 1.0,
                                 "center_mm": [0.0, 1.0]}})  # fmt: skip
    return scenes


def score_full(out: str | Path, cfg: Any, scenes: list[dict[str, Any]] | None = None, *,
               log=print) -> dict[str, Any]:
    """The scoring stage alone: score a full-size run's outputs in ``out`` (``captures``, ``calib``,
    ``cubes_calibrated``, ``cubes_oracle``) against the truth and write its previews, panels
    and spectra plots into ``out`` (the folders may be links to another run's).

    Returns:
        ``{"calibration", "scenes", "sensor_size", "valid_pixels_true"}`` as in
        ``summary.json``.
    """
    out = Path(out)
    cap_dir, cal_dir = out / "captures", out / "calib"
    scenes = _full_scenes(cfg, out, log) if scenes is None else scenes
    truth, _ = read_truth(cap_dir)  # once, for the calibration and the scenes
    cal_scores = score_against_truth(cal_dir / "calib.npz", cap_dir, truth)
    log("      calibration vs truth:\n      " + format_scores(cal_scores).replace("\n", "\n      "))
    wl = np.asarray(truth["wavelengths_nm"], np.float64)
    results: dict[str, Any] = {}
    for spec in scenes:
        name = spec["name"]
        files = {k: out / f"cubes_{k}" / f"{name}.npz" for k in ("calibrated", "oracle")}
        if not all(f.is_file() for f in files.values()):
            log(f"      scene {name}: no cube (not simulated)")
            continue
        cubes, valids, timings = {}, {}, {}
        for key, f in files.items():
            c = load_cube(f)
            cubes[key] = np.asarray(c.cube, np.float64)
            valids[key] = np.asarray(c.valid, bool)
            timings[key] = c.metadata.get("timings_s", {})
        entry, both, true_cube = score_scene(spec, cubes, valids, truth, out,
                                             erode_px(truth, cfg.erode_mm), log)
        entry["reconstruct_timings_s"] = timings
        _previews(out, name, wl, true_cube * both[None], cubes, entry, cfg.beta)
        results[name] = entry
        del cubes
    return {"calibration": cal_scores, "scenes": results,
            "sensor_size": [int(v) for v in truth["sensor_size"]],
            "valid_pixels_true": int(truth["valid"].sum())}


def demo_full(out: str | Path, cfg: Any, *, log=print) -> dict[str, Any]:
    """Run the full-size chain (module docstring); returns the summary written to
    ``OUT/summary.json``.

    Args:
        out: output folder (created).
        cfg: :class:`hsi_torch.experiments.demo.DemoConfig` (``beta``, ``diff_order``,
            ``erode_mm``, ``cave``, ``seed``, ``device``, ``simulate_config``/``calibrate_config``:
            default the shipped ``simulate_full.yaml`` and ``calibrate.yaml``).
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t_all = time.perf_counter()
    scenes = _full_scenes(cfg, out, log)
    stages: dict[str, dict[str, float]] = {}

    def stage(key: str, title: str, cmd: list[str]) -> None:
        log(f"[{len(stages) + 1}/6] {title} ...")
        run = run_child(cmd)
        if run.returncode != 0:
            raise RuntimeError(f"{title} failed (exit code {run.returncode}): {' '.join(cmd)}")
        stages[key] = {"wall_s": run.wall_s, "cpu_s": run.cpu_s, "peak_rss_gib": run.peak_rss_gib}
        log(f"      {run.wall_s:.1f} s wall, {run.cpu_s:.1f} s CPU, peak RSS "
            f"{run.peak_rss_gib:.2f} GiB")

    cap_dir, cal_dir = out / "captures", out / "calib"
    sim_cfg = str(cfg.simulate_config or shipped_config("simulate_full"))
    stage("simulate", f"simulating the full-size prototype into {cap_dir}",
          _hsi("simulate", "--config", sim_cfg, "--out", str(cap_dir), "--overwrite",
               "--set", f"captures.scenes={json.dumps(scenes)}",
               "--set", f"render.seed={cfg.seed}", "--set", "render.progress=false"))
    cal_cmd = ["calibrate", "--captures", str(cap_dir), "--out", str(cal_dir), "--no-progress"]
    if cfg.calibrate_config:
        cal_cmd += ["--config", str(cfg.calibrate_config)]
    if cfg.device != "cpu":
        cal_cmd += ["--device", cfg.device]
    stage("calibrate", f"calibrating from {cap_dir} (shipped defaults)", _hsi(*cal_cmd))
    oracle = out / "oracle" / "oracle.npz"
    stage("oracle", "building the oracle bundle from the truth",
          _hsi("calibrate", "--oracle", "--captures", str(cap_dir), "--out", str(oracle)))
    shots = sorted(str(p) for p in (cap_dir / "scenes").glob("*.tif"))
    rec_set = ["--set", f"beta={cfg.beta}", "--set", f"diff_order={cfg.diff_order}",
               "--set", "formats=[npz]", "--set", "preview=false", "--no-progress",
               "--device", cfg.device]  # fmt: skip
    for key, bundle in (("calibrated", cal_dir / "calib.npz"), ("oracle", oracle)):
        stage(f"reconstruct_{key}", f"reconstructing {len(shots)} scenes with the {key} bundle",
              _hsi("reconstruct", "--bundle", str(bundle), "--out", str(out / f"cubes_{key}"),
                   *rec_set, *shots))

    # ---- score --------------------------------------------------------------------------------
    log("[6/6] scoring against the truth ...")
    t0 = time.perf_counter()
    scored = score_full(out, cfg, scenes, log=log)
    cal_scores, results = scored["calibration"], scored["scenes"]
    stages["score"] = {"wall_s": time.perf_counter() - t0}
    summary = {
        "prototype": "full size (simulate_full.yaml)",
        "beta": cfg.beta,
        "sensor_size": scored["sensor_size"],
        "valid_pixels_true": scored["valid_pixels_true"],
        "calibration": cal_scores,
        "calibration_targets_met": targets_met(cal_scores),
        "scenes": results,
        "stages": stages,
        "total_s": time.perf_counter() - t_all,
        "torch_threads": torch.get_num_threads(),
    }
    atomic_write_json(out / "summary.json", summary)
    log(report_lines(summary, out))
    return summary


def report_lines(s: dict[str, Any], out: Path) -> str:
    """The readable summary of a full-size run (``summary.json``'s content)."""
    lines = ["results (reflectance, PSNR = 10 log10(1/MSE) in dB, spectral angle in degrees):"]
    for name, e in s["scenes"].items():
        c, o = e["calibrated"], e["oracle"]
        if "mean_psnr_db" in c:
            pc, po = e["per_pixel_interiors"]["calibrated"], e["per_pixel_interiors"]["oracle"]
            lines.append(
                f"  {name}: patch-interior means calibrated {c['mean_psnr_db']:.1f} dB / "
                f"{c['mean_sam_deg']:.2f} deg, oracle {o['mean_psnr_db']:.1f} dB / "
                f"{o['mean_sam_deg']:.2f} deg; per pixel in the interiors calibrated "
                f"{pc['psnr_db']:.1f} dB / {pc['mean_sam_deg']:.2f} deg, oracle "
                f"{po['psnr_db']:.1f} dB / {po['mean_sam_deg']:.2f} deg; whole patches "
                f"calibrated {e['whole_patch']['calibrated']['mean_psnr_db']:.1f} dB"
            )
        else:
            nan = {"psnr_db": float("nan"), "median_sam_deg": float("nan")}
            bc, bo = c.get("bright_half", nan), o.get("bright_half", nan)
            lines.append(
                f"  {name}: per pixel, all {c['pixels']} px: calibrated {c['psnr_db']:.1f} dB "
                f"(median SAM {c['median_sam_deg']:.1f} deg), oracle {o['psnr_db']:.1f} dB "
                f"({o['median_sam_deg']:.1f} deg); brighter half: calibrated "
                f"{bc['psnr_db']:.1f} dB ({bc['median_sam_deg']:.1f} deg), oracle "
                f"{bo['psnr_db']:.1f} dB ({bo['median_sam_deg']:.1f} deg)"
            )
        lines.extend(metrics_lines(e))
    st = s["stages"]
    lines.append("  stages: " + ", ".join(
        f"{k} {v['wall_s']:.0f} s" + (f" / {v['peak_rss_gib']:.2f} GiB" if "peak_rss_gib" in v
                                      else "") for k, v in st.items()))  # fmt: skip
    lines.append(f"  total {s['total_s']:.0f} s; outputs in {out}")
    return "\n".join(lines)
