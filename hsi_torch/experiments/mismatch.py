"""What each non-ideal effect costs, and what its remedy wins back (``hsi-torch experiment
mismatch``; the protocol, the columns and the remedies are in docs/experiments.md, *What the
reality gap costs*).

For the ideal virtual prototype, each effect of
:data:`~hsi_torch.simulate.mismatch.DOCUMENTED_EFFECTS` alone at its documented magnitude and all
of them together: the capture set is simulated, calibrated with the shipped ``calibrate.yaml``
(plus ``calibrate_set``), and every scored scene reconstructed (per pixel, default ``β``) with
the calibrated bundle and with the oracle bundle. "Lost" is ideal − effect. The ``defaults``
scores use the shipped settings (the findings kept with the scores, summarised by
:func:`decisions`); ``calibrated`` and ``remedy`` apply the remedies exactly as named
(:data:`NO_REMEDY` plus the parts of :data:`ROW_REMEDIES`), a calibration whose automatic
decisions equal the remedies asked for being reused.

**Cost.** Effects that act only after calibration (``drift``, ``brf_temperature``,
``scene_illuminant``) reuse the ideal row's captures and calibration: only their scene captures are
rendered (:func:`~hsi_torch.simulate.rerender.rerender_after_calibration`). Every row's captures,
bundles and scores are kept under ``OUT/rows/<row>/`` and reused by a rerun (delete a row's
folder to redo it). Writes ``mismatch.md`` (the table), ``mismatch.json`` (every score) and
``mismatch.csv``.
"""

from __future__ import annotations

import csv
import gc
import io
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from hsi_torch.calibrate.config import CalibrateConfig
from hsi_torch.calibrate.pipeline import calibrate_capture_set
from hsi_torch.config import load_config, option
from hsi_torch.console import info
from hsi_torch.experiments.metrics import (
    colorchecker_scores,
    erode_px,
    interior_mask,
    spectral_angle_deg_np,
)
from hsi_torch.io.atomic import (
    atomic_write_json,
    atomic_write_text,
    remove_file,
    remove_tree,
    replace_file,
)
from hsi_torch.io.bundle import CalibrationBundle
from hsi_torch.io.capture_set import read_truth_meta
from hsi_torch.metrics import psnr_from_mse
from hsi_torch.recon import Reconstructor
from hsi_torch.recon.pipeline import DEFAULT_BETA
from hsi_torch.recon.sensing import precompute_sensing
from hsi_torch.resources import shipped_config
from hsi_torch.simulate import SimulateConfig, simulate_capture_set
from hsi_torch.simulate.mismatch import DOCUMENTED_EFFECTS
from hsi_torch.simulate.oracle import bundle_from_truth
from hsi_torch.simulate.rerender import rerender_after_calibration, white_mismatch_of

__all__ = ["MismatchConfig", "run_mismatch", "row_keys", "AFTER_CALIBRATION_EFFECTS",
           "REMEDIES", "REMEDY_PARTS", "ROW_REMEDIES", "remedy_parts", "remedy_name",
           "mismatch_table", "decisions", "with_refine", "NO_REMEDY"]

#: effects that act on the scene captures only: their rows reuse the ideal calibration
AFTER_CALIBRATION_EFFECTS = ("drift", "brf_temperature", "scene_illuminant")
#: the parts a remedy can have: calibrate with ``stray_light=subtract`` (the veil, subtracted
#: from every frame, scenes included) and ``defects=mask``, a white reference re-shot under the
#: scene's light (re-rendered, then calibrated), reconstruct with ``refine_registration``
REMEDY_PARTS: dict[str, str] = {
    "stray_light": "veil subtracted",
    "defects": "defects masked",
    "white": "white under the scene's light",
    "refine": "registration refined from the scene",
}
#: which parts each row's remedy has (``ideal``: every part that applies to the ideal device,
#: what the remedies cost a device that needs none; its white already is the scene's light)
ROW_REMEDIES: dict[str, tuple[str, ...]] = {
    "ideal": ("stray_light", "defects", "refine"),
    "stray_light": ("stray_light",),
    "sensor_defects": ("defects",),
    "scene_illuminant": ("white",),
    "drift": ("refine",),
    "all": ("stray_light", "defects", "white", "refine"),
}
#: the remedy of each effect that has one (``remedy`` column)
REMEDIES: dict[str, str] = {k: " + ".join(REMEDY_PARTS[p] for p in v)
                            for k, v in ROW_REMEDIES.items()}


def remedy_parts(name: str) -> tuple[str, ...]:
    """The remedy parts of a row: :data:`ROW_REMEDIES`, and for ``all-<effect>`` the all row's
    but that effect's own (``()``: no remedy)."""
    if name.startswith("all-"):
        drop = ROW_REMEDIES.get(name[4:], ())
        return tuple(p for p in ROW_REMEDIES["all"] if p not in drop)
    return ROW_REMEDIES.get(name, ())


def remedy_name(name: str) -> str | None:
    """The ``remedy`` column's text of a row (``None``: no remedy)."""
    parts = remedy_parts(name)
    return " + ".join(REMEDY_PARTS[p] for p in parts) if parts else None
NO_NOISE = ("sensor.shot_noise=false", "sensor.read_noise_e=0", "sensor.quantize=false")
_SIZES = {"small": "simulate", "full": "simulate_full"}


@dataclass
class MismatchConfig:
    """Settings of ``hsi-torch experiment mismatch`` (see the module docstring)."""

    size: Literal["small", "full"] = option("small", "small: the shipped simulate.yaml (400 x "
                                                     "384 px, ColorChecker); full: "
                                                     "simulate_full.yaml (2896 x 2784 px, "
                                                     "ColorChecker, USAF, CAVE when "
                                                     "$HSI_TORCH_DATA holds it)")
    simulate_config: str | None = option(None, "simulate config (shipped name or YAML path); "
                                               "null: the size's, or the resolved_config.yaml of "
                                               "ideal_captures")
    simulate_set: list[str] = option(text="extra --set overrides of the simulate config",
                                     factory=list)
    effects: list[str] = option(text="rows besides the ideal one: names of DOCUMENTED_EFFECTS, "
                                "'all' (every effect together) and 'all-<effect>' (all but that "
                                "one, with every remedy but its own)",
                                factory=lambda: [*DOCUMENTED_EFFECTS, "all"])
    remedies: bool = option(True, "also score each effect's remedy")
    noise_free: bool = option(False, "no shot/read noise, no quantisation: each effect's own "
                                     "cost without the noise realisations' spread")
    ideal_captures: Path | None = option(None, "an existing ideal capture set (read only; "
                                               "linked, never written) for the ideal row; null: "
                                               "simulate it")
    ideal_bundle: Path | None = option(None, "that set's calibration bundle (with "
                                             "ideal_captures); null: calibrate it")
    calibrate_set: list[str] = option(text="--set overrides of the shipped calibrate.yaml for "
                                      "every row (default: a veil outside the views warns "
                                      "instead of stopping the row)",
                                      factory=lambda: ["pedestal_check=warn"])
    beta: float = option(DEFAULT_BETA, "reconstruction smoothness weight")
    erode_mm: float = option(0.3, "ColorChecker patch interiors: this far inside each patch, mm")
    device: str | None = option(None, "torch device (null: cpu)")

    def __post_init__(self) -> None:
        known = {*DOCUMENTED_EFFECTS, "all", *(f"all-{e}" for e in DOCUMENTED_EFFECTS)}
        bad = sorted(set(self.effects) - known)
        if bad:
            raise ValueError(f"effects: unknown {bad}; known: {sorted(known)}")
        if self.ideal_bundle is not None and self.ideal_captures is None:
            raise ValueError("ideal_bundle needs ideal_captures (the set it calibrates)")
        if self.erode_mm < 0:
            raise ValueError(f"erode_mm must be >= 0, got {self.erode_mm}")


def row_keys(name: str) -> dict[str, Any]:
    """The ``mismatch.*`` keys of a row: ``{}`` (ideal), one effect's, all of them (``all``),
    or all but one effect's (``all-<effect>``)."""
    if name == "ideal":
        return {}
    if name == "all" or name.startswith("all-"):
        every: dict[str, Any] = {}
        for effect, keys in DOCUMENTED_EFFECTS.items():
            if name != f"all-{effect}":
                every.update(keys)
        return every
    return dict(DOCUMENTED_EFFECTS[name])


def _overrides(keys: dict[str, Any]) -> list[str]:
    return [f"mismatch.{k}={json.dumps(list(v) if isinstance(v, tuple) else v)}"
            for k, v in keys.items()]


def _simulate_source(cfg: MismatchConfig) -> Path:
    if cfg.simulate_config is not None:
        p = Path(cfg.simulate_config)
        return p if p.suffix in (".yaml", ".yml") or p.is_file() else shipped_config(str(p))
    if cfg.ideal_captures is not None:
        p = Path(cfg.ideal_captures) / "resolved_config.yaml"
        if not p.is_file():
            raise FileNotFoundError(f"{p} not found: give simulate_config for ideal_captures "
                                    f"{cfg.ideal_captures}")
        return p
    return shipped_config(_SIZES[cfg.size])


def _sim_cfg(cfg: MismatchConfig, keys: dict[str, Any]) -> SimulateConfig:
    extra = [*(NO_NOISE if cfg.noise_free else ()), *cfg.simulate_set]
    return load_config(_simulate_source(cfg), SimulateConfig,
                       ["render.progress=false", "render.figures=false", *extra,
                        *_overrides(keys)])


#: calibrate overrides of the "calibrated" and "remedy" bundles: the remedies exactly as asked
#: (the shipped ``auto`` decides by the data; the "defaults" column keeps it)
NO_REMEDY = ("stray_light=none", "defects=none")


def _cal_cfg(cfg: MismatchConfig, remedy: tuple[str, ...] | None = ()) -> CalibrateConfig:
    """The calibration's config: ``remedy`` ``None`` is the shipped defaults (``auto``), a
    tuple the remedies it names and no other."""
    sets = [] if remedy is None else [*NO_REMEDY, *remedy]
    return load_config(shipped_config("calibrate"), CalibrateConfig,
                       ["progress=false", *cfg.calibrate_set, *sets])


class _Row:
    """One row's folder: captures, bundles and the cached scores."""

    def __init__(self, out: Path, name: str) -> None:
        self.name, self.dir = name, out / "rows" / name
        self.dir.mkdir(parents=True, exist_ok=True)
        self.scores_path = self.dir / "scores.json"
        self.scores: dict[str, Any] = (json.loads(self.scores_path.read_text())
                                       if self.scores_path.is_file() else {})

    def save(self) -> None:
        atomic_write_json(self.scores_path, self.scores)


def _complete(d: Path, make) -> None:
    """Write a capture set with ``make(folder)`` into ``d.partial``, then rename it ``d``: a
    set whose writing was interrupted is never taken for a finished one (a re-rendered set's
    ``manifest.json`` is linked before its scenes are rendered)."""
    tmp = d.with_name(d.name + ".partial")
    for old in (tmp, d):
        if old.exists():
            remove_tree(old)
    make(tmp)
    replace_file(tmp, d)


def _captures(cfg: MismatchConfig, out: Path, name: str, ideal_dir: Path) -> Path:
    """The row's capture set (simulated once, then reused)."""
    d = out / "rows" / name / "captures"
    if (d / "manifest.json").is_file():
        return d
    sim = _sim_cfg(cfg, row_keys(name))
    t0 = time.perf_counter()
    if name in AFTER_CALIBRATION_EFFECTS:
        _complete(d, lambda tmp: rerender_after_calibration(sim, ideal_dir, tmp,
                                                            device=cfg.device,
                                                            log=lambda *a: None))
    else:
        _complete(d, lambda tmp: simulate_capture_set(sim, tmp, device=cfg.device,
                                                      progress=False, log=lambda *a: None))
    how = "(scenes re-rendered) " if name in AFTER_CALIBRATION_EFFECTS else ""
    info(f"  {name}: captures {how}in {time.perf_counter() - t0:.0f} s")
    return d


#: the after-calibration keys a re-shot white reference does not get: it is shot under the
#: scene's light with the calibration, before the sensor drifted and the filter warmed
WHITE_WITHOUT = ("drift_shift_px", "drift_rotation_deg", "brf_delta_t_k")


def _white_captures(cfg: MismatchConfig, out: Path, name: str, caps: Path) -> Path:
    """The row's captures with the white references re-shot under the scene's light
    (re-rendered with the row's effects but :data:`WHITE_WITHOUT`); the scenes and every other
    file are linked from ``caps``."""
    d = out / "rows" / name / "captures_white"
    keys = {k: v for k, v in row_keys(name).items() if k not in WHITE_WITHOUT}
    sim = _sim_cfg(cfg, keys)
    want = white_mismatch_of(sim.mismatch)
    if (d / "manifest.json").is_file():
        got = read_truth_meta(d).get("white_mismatch")
        if got == want:
            return d
        # shot otherwise (an older run, another WHITE_WITHOUT): re-shoot it, and drop the
        # bundles calibrated from it
        info(f"  {name}: {d} was shot with {got}, not {want}: re-shooting it")
        for stale in d.parent.glob("calib_white*.npz"):
            remove_file(stale, missing_ok=False)
    t0 = time.perf_counter()
    _complete(d, lambda tmp: rerender_after_calibration(
        sim, caps, tmp, whites=True, scenes=False, device=cfg.device, log=lambda *a: None))
    info(f"  {name}: white references re-shot under the scene's light in "
         f"{time.perf_counter() - t0:.0f} s")
    return d


def _decided(path: Path) -> tuple[bool, bool]:
    """(veil subtracted, defects masked) of a bundle on disk."""
    b = CalibrationBundle.load(path)
    return b.settings.get("stray_light") == "subtract", "defect_pixels" in b.extras


def _bundle(cfg: MismatchConfig, captures: Path, path: Path,
            remedy: tuple[str, ...] | None = (), defaults: Path | None = None) -> Path:
    """Calibrate ``captures`` into ``path`` once (reused). ``remedy`` ``None``: the shipped
    defaults. ``defaults``: the same captures' defaults bundle, returned instead when its
    decisions are the remedies asked for (the same calibration, bit for bit)."""
    if remedy is not None and defaults is not None and defaults.is_file() \
            and _decided(defaults) == ("stray_light=subtract" in remedy,
                                       "defects=mask" in remedy):
        return defaults
    if not path.is_file():
        t0 = time.perf_counter()
        bundle, _ = calibrate_capture_set(captures, _cal_cfg(cfg, remedy), device=cfg.device,
                                          progress=False)
        bundle.save(path)
        del bundle
        gc.collect()
        tag = " (shipped defaults)" if remedy is None else " (remedy)" if remedy else ""
        info(f"  calibrated {captures.parent.name}{tag} in {time.perf_counter() - t0:.0f} s")
    return path


_TRUTH_KEYS = ("colorchecker_patch_index", "colorchecker_spectra", "scene_colorchecker",
               "diffuser_xy", "scene_cave")


def _truth(captures: Path) -> dict[str, np.ndarray]:
    """The truth arrays the scores need (not ``B``: 0.6 GiB at full size)."""
    with np.load(captures / "ground_truth" / "truth.npz", allow_pickle=False) as z:
        return {k: z[k] for k in _TRUTH_KEYS if k in z.files}


def _pixel_scores(cube: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> dict[str, float]:
    """PSNR (peak 1) of the pooled MSE and mean SAM (true mean reflectance ≥ 0.01) over
    ``mask`` of ``(M, h, w)`` cubes (:func:`~hsi_torch.experiments.metrics.cube_scores`' two
    headline numbers, without its field metrics)."""
    e = cube[:, mask].T
    t = truth[:, mask].T
    bright = t.mean(1) >= 0.01
    sam = spectral_angle_deg_np(e[bright], t[bright])
    return {"psnr_db": psnr_from_mse(float(((e - t) ** 2).mean())),
            "mean_sam_deg": float(sam.mean()) if sam.size else float("nan")}


class _Reconstructors:
    """Reconstructors kept across rows for the bundles many rows share (the ideal calibration,
    the ideal oracle): their factorisation is the costly part at full size."""

    def __init__(self, cfg: MismatchConfig) -> None:
        self.cfg = cfg
        self.kept: dict[str, Reconstructor] = {}

    def get(self, key: str | None, make) -> Reconstructor:
        """A reconstructor of the bundle ``make()`` gives (a path or a bundle), the registration
        never refined (the "calibrated" and "oracle" columns; :func:`with_refine` for others)."""
        if key is not None and key in self.kept:
            return self.kept[key]
        b = make()
        b = CalibrationBundle.load(b) if isinstance(b, Path) else b
        # not in the module's cache: a row's own bundle is freed with its reconstructor
        sens = precompute_sensing(b, beta=self.cfg.beta, device=self.cfg.device, cache=False)
        found = list(b.settings.get("findings") or [])
        del b
        rec = Reconstructor(sens, beta=self.cfg.beta, refine_registration=False)
        rec.bundle_findings = found  # the calibration's decisions, for the scores
        if key is not None:
            self.kept[key] = rec
        return rec


def with_refine(rec: Reconstructor, refine: bool | str) -> Reconstructor:
    """``rec``'s factorisation with ``refine_registration=refine`` (and its bundle's
    findings)."""
    out = Reconstructor(rec.sensing, beta=rec.settings.solve.beta, refine_registration=refine)
    out.bundle_findings = getattr(rec, "bundle_findings", [])
    return out


def score_captures(
    captures: Path, rec: Reconstructor, cfg: MismatchConfig,
    correct: dict[str, bool] | None = None,
) -> dict[str, Any]:
    """Reconstruct the scored scenes of ``captures`` with ``rec`` and score them.

    Args:
        correct: reconstruction remedies the bundle must record, ``{"stray_light": bool,
            "defects": bool}`` (checked; the reconstructor applies what its bundle records).

    Returns:
        ``{"colorchecker": {"means_db", "means_sam", "pixel_db", "pixel_sam"}, "cave": {"pixel_db",
        "pixel_sam"} (when the set holds it), "applied": {"stray_light", "defects" (what the
        bundle records), "refine_registration" (the reconstructor's), "white_mismatch" (the
        after-calibration effects the white references were shot with: ``{}`` the
        calibration's)}, "drift": {scene: {"corrected", "sensor_shift_px", "sensor_rotation_deg",
        "measured_views"}} (the reconstruction's statistics), "seconds"}``.
    """
    t0 = time.perf_counter()
    truth = _truth(captures)
    rad = rec.sensing.radiometry
    want = {"stray_light": rad is not None and rad.veil_index is not None,
            "defects": rad is not None and rad.defect_index is not None}
    for k, v in (correct or {}).items():
        if v and not want[k]:
            raise RuntimeError(f"{captures}: the remedy {k!r} asked for, but the bundle does "
                               "not record it")
    white_mm = read_truth_meta(captures).get("white_mismatch", {})
    refine = rec.settings.registration.refine
    out: dict[str, Any] = {"applied": {**want, "refine_registration": refine,
                                       "white_mismatch": white_mm}, "drift": {},
                           "findings": list(getattr(rec, "bundle_findings", []))}

    def drift_stats(name: str, res) -> None:
        d = res.stats.get("drift")
        if d is not None:
            out["drift"][name] = {k: d.get(k) for k in ("corrected", "sensor_shift_px",
                                                        "sensor_rotation_deg", "measured_views")}
            if d.get("finding"):
                out["findings"].append({**d["finding"], "source": name})
        if res.stats.get("illuminant"):
            out["findings"].append({**res.stats["illuminant"], "source": name})
    pidx = truth["colorchecker_patch_index"]
    spectra = np.asarray(truth["colorchecker_spectra"], np.float64)
    e = erode_px(truth, cfg.erode_mm)
    res = rec.reconstruct_file(captures / "scenes" / "colorchecker.tif")
    cube = res.cube.detach().cpu().double().numpy()
    valid = res.valid.detach().cpu().numpy()
    drift_stats("colorchecker", res)
    inner = valid & (pidx >= 0) & np.logical_or.reduce(
        [interior_mask(pidx == k, e) for k in range(len(spectra))])
    means = colorchecker_scores(cube, valid, pidx, spectra, e)
    px = _pixel_scores(cube, np.asarray(truth["scene_colorchecker"], np.float64), inner)
    out["colorchecker"] = {"means_db": means["mean_psnr_db"], "means_sam": means["mean_sam_deg"],
                           "pixel_db": px["psnr_db"], "pixel_sam": px["mean_sam_deg"]}
    del cube, res
    if "scene_cave" in truth and (captures / "scenes" / "cave.tif").is_file():
        res = rec.reconstruct_file(captures / "scenes" / "cave.tif")
        cube = res.cube.detach().cpu().double().numpy()
        drift_stats("cave", res)
        t = np.asarray(truth["scene_cave"], np.float64)
        m = res.valid.detach().cpu().numpy() & (t.max(0) > 0) & np.isfinite(cube).all(0)
        px = _pixel_scores(cube, t, m)
        out["cave"] = {"pixel_db": px["psnr_db"], "pixel_sam": px["mean_sam_deg"]}
        del cube, res, t
    del truth
    gc.collect()
    out["seconds"] = time.perf_counter() - t0
    return out


def _applied(parts: tuple[str, ...]) -> dict[str, bool]:
    """The ``applied`` flags (of :func:`score_captures`) a remedy of ``parts`` must show."""
    return {"stray_light": "stray_light" in parts, "defects": "defects" in parts,
            "refine_registration": "refine" in parts, "white": "white" in parts}


def _shows(scores: dict[str, Any], parts: tuple[str, ...]) -> bool:
    """Whether cached ``scores`` were made with exactly the remedy ``parts``."""
    a = scores.get("applied")
    if not isinstance(a, dict):
        return False
    got = {k: bool(a.get(k)) for k in ("stray_light", "defects", "refine_registration")}
    got["white"] = bool(a.get("white_mismatch"))
    return got == _applied(parts)


def _score_variant(row: _Row, variant: str, fn, parts: tuple[str, ...] | None = None) -> None:
    """Score ``variant`` of ``row`` with ``fn`` unless cached (a cached remedy made with other
    ``parts`` than the row's remedy now has is redone)."""
    if variant in row.scores and (parts is None or _shows(row.scores[variant], parts)):
        return
    s = fn()
    if parts is not None and not _shows(s, parts):  # never kept: a rerun would trust it
        raise RuntimeError(f"{row.name}: the remedy applied {s['applied']}, not {list(parts)}")
    row.scores[variant] = s
    row.save()
    cave = f", CAVE {s['cave']['pixel_db']:.2f} dB" if "cave" in s else ""
    info(f"  {row.name} / {variant}: ColorChecker means {s['colorchecker']['means_db']:.2f} dB, "
         f"per pixel {s['colorchecker']['pixel_db']:.2f} dB{cave} ({s['seconds']:.0f} s)")


def run_mismatch(cfg: MismatchConfig, out: Path, *, device: str | None = None) -> dict[str, Any]:
    """Run every row (cached under ``out/rows``) and write the table; returns all scores."""
    if device is not None:
        cfg.device = device
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t_all = time.perf_counter()
    # ideal row
    ideal = _Row(out, "ideal")
    if cfg.ideal_captures is not None:
        ideal_dir = Path(cfg.ideal_captures)
        if not (ideal_dir / "manifest.json").is_file():
            raise FileNotFoundError(f"ideal_captures: {ideal_dir}/manifest.json not found")
    else:
        ideal_dir = _captures(cfg, out, "ideal", ideal.dir)
    ideal_defaults = _bundle(cfg, ideal_dir, ideal.dir / "calib_defaults.npz", None)
    ideal_bundle = (Path(cfg.ideal_bundle) if cfg.ideal_bundle is not None
                    else _bundle(cfg, ideal_dir, ideal.dir / "calib.npz",
                                 defaults=ideal_defaults))
    rows: dict[str, _Row] = {"ideal": ideal}
    recs = _Reconstructors(cfg)
    ideal_rec = lambda: recs.get("ideal", lambda: ideal_bundle)  # noqa: E731
    ideal_oracle = lambda: recs.get("oracle", lambda: bundle_from_truth(ideal_dir))  # noqa: E731
    ideal_def = lambda: with_refine(recs.get("ideal_defaults", lambda: ideal_defaults),  # noqa: E731
                                    "auto")
    _score_variant(ideal, "calibrated", lambda: score_captures(ideal_dir, ideal_rec(), cfg))
    _score_variant(ideal, "defaults", lambda: score_captures(ideal_dir, ideal_def(), cfg))
    _score_variant(ideal, "oracle", lambda: score_captures(ideal_dir, ideal_oracle(), cfg))
    calibrated_of: dict[str, Any] = {"ideal": ideal_rec}
    caps_of: dict[str, Path] = {"ideal": ideal_dir}
    for name in cfg.effects:
        row = rows[name] = _Row(out, name)
        info(f"row {name}: mismatch {row_keys(name)}")
        caps = caps_of[name] = _captures(cfg, out, name, ideal_dir)
        if name in AFTER_CALIBRATION_EFFECTS:
            calibrated, defaults = ideal_rec, ideal_def
        else:
            # the shipped defaults first: a calibration whose decisions are the remedies asked
            # for is that bundle (no second calibration)
            defaults = lambda c=caps, r=row: with_refine(recs.get(  # noqa: E731
                None, lambda: _bundle(cfg, c, r.dir / "calib_defaults.npz", None)), "auto")
            calibrated = lambda c=caps, r=row: recs.get(  # noqa: E731
                None, lambda: _bundle(cfg, c, r.dir / "calib.npz",
                                      defaults=r.dir / "calib_defaults.npz"))
        calibrated_of[name] = calibrated
        # the truth (and its oracle) is the ideal device's unless the filter's thickness map,
        # which is in the truth's B, is on
        own_truth = any(k.startswith("brf_thickness") for k in row_keys(name))
        oracle = ((lambda c=caps: recs.get(None, lambda: bundle_from_truth(c))) if own_truth
                  else ideal_oracle)
        _score_variant(row, "defaults", lambda c=caps, f=defaults: score_captures(c, f(), cfg))
        _score_variant(row, "calibrated", lambda c=caps, f=calibrated: score_captures(c, f(), cfg))
        _score_variant(row, "oracle", lambda c=caps, f=oracle: score_captures(c, f(), cfg))
        if cfg.remedies and name in ("stray_light", "sensor_defects", "drift"):
            _score_variant(row, "remedy", lambda n=name: _remedy(cfg, out, n, caps_of[n],
                                                                  calibrated_of[n], recs),
                           remedy_parts(name))
    # the costlier remedies (a whole calibration each) once every row is in
    for name in [n for n in cfg.effects
                 if n in ("scene_illuminant", "all") or n.startswith("all-")] + ["ideal"]:
        if cfg.remedies:
            _score_variant(rows[name], "remedy",
                           lambda n=name: _remedy(cfg, out, n, caps_of[n], calibrated_of[n],
                                                  recs), remedy_parts(name))
    data = {name: {"keys": {k: list(v) if isinstance(v, tuple) else v
                            for k, v in row_keys(name).items()},
                   "remedy_name": remedy_name(name),
                   **r.scores}
            for name, r in rows.items()}
    md, table_rows = mismatch_table(data)
    atomic_write_text(out / "mismatch.md", md + "\n")
    atomic_write_json(out / "mismatch.json", data)
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(list(table_rows[0]))
    w.writerows([list(r.values()) for r in table_rows])
    atomic_write_text(out / "mismatch.csv", buf.getvalue())
    info(md)
    info(f"mismatch experiment: {len(rows)} rows in {time.perf_counter() - t_all:.0f} s")
    return data


def _remedy(cfg: MismatchConfig, out: Path, name: str, caps: Path, calibrated,
            recs: _Reconstructors) -> dict:
    """Score the row's remedy, every part of :func:`remedy_parts` ``(name)`` together: the
    white references re-shot under the scene's light (:func:`_white_captures`), calibrated with
    the veil subtracted and the defects masked, reconstructed with the registration refined
    from each scene. Without a calibration part the row's own calibrated reconstructor is used
    (``calibrated``: a callable that gives it)."""
    parts = remedy_parts(name)
    row_dir = out / "rows" / name
    if "white" in parts:
        caps = _white_captures(cfg, out, name, caps)
    sets = tuple([*(["stray_light=subtract"] if "stray_light" in parts else []),
                  *(["defects=mask"] if "defects" in parts else [])])
    if "white" in parts or sets:
        tag = "_".join(p for p in ("white", "stray_light", "defects") if p in parts)
        own = None if "white" in parts else row_dir / "calib_defaults.npz"
        rec = recs.get(None, lambda: _bundle(cfg, caps, row_dir / f"calib_{tag}.npz", sets,
                                             defaults=own))
    else:
        rec = calibrated()
    if "refine" in parts:
        # the same factorisation; every scene's drift measured and its sampling corrected
        rec = with_refine(rec, True)
    return score_captures(caps, rec, cfg, {"stray_light": "stray_light" in parts,
                                           "defects": "defects" in parts})


def decisions(findings: list[dict[str, Any]]) -> str:
    """What the shipped defaults decided, from a score's findings: the remedies they switched
    on (veil subtracted, defects masked, drift corrected per scene) and every warning."""
    out: list[str] = []
    for f in findings:
        code, sev, msg = f.get("code"), f.get("severity"), str(f.get("message", ""))
        if code == "calibration.stray_light" and sev == "info" and "subtracted from" in msg:
            text = "veil subtracted"
        elif code == "calibration.defects" and sev == "info" and "masked with" in msg:
            text = f"{f.get('measured')} defects masked"
        elif code == "drift.corrected":
            text = f"drift corrected ({f.get('source')})"
        elif code == "capture.illuminant" and sev == "warning":
            text = f"illuminant warning ({f.get('source')}: ratio {f.get('measured')})"
        elif sev in ("warning", "error"):
            text = f"{code} {sev} ({f.get('source')})"
        else:
            continue
        if text not in out:
            out.append(text)
    return "; ".join(out) or "—"


def _fmt(v: float | None, ref: float | None = None) -> str:
    if v is None:
        return "—"
    if ref is None:
        return f"{v:.2f}"
    return f"{v:.2f} ({ref - v:+.2f})"


def mismatch_table(data: dict[str, Any]) -> tuple[str, list[dict[str, str]]]:
    """Markdown table of :func:`run_mismatch`'s scores (``lost`` in brackets, against the
    ideal row's same bundle kind; a remedy against the ideal calibrated row) and its rows as
    dicts (for the CSV)."""
    ideal = data["ideal"]

    def get(r: dict, variant: str, scene: str, key: str) -> float | None:
        v = r.get(variant)
        return v.get(scene, {}).get(key) if isinstance(v, dict) else None

    has_cave = any("cave" in r.get("calibrated", {}) for r in data.values())
    rows: list[dict[str, str]] = []
    for name, r in data.items():
        row = {"effect": name}
        for variant, ref_variant, label in (("calibrated", "calibrated", "calibrated"),
                                            ("defaults", "calibrated", "shipped defaults"),
                                            ("oracle", "oracle", "oracle"),
                                            ("remedy", "calibrated", "remedy")):
            row[f"{label}: CC means dB"] = _fmt(get(r, variant, "colorchecker", "means_db"),
                                                get(ideal, ref_variant, "colorchecker",
                                                    "means_db"))
            if label != "oracle":
                row[f"{label}: CC per pixel dB"] = _fmt(
                    get(r, variant, "colorchecker", "pixel_db"),
                    get(ideal, ref_variant, "colorchecker", "pixel_db"))
                row[f"{label}: CC SAM °"] = _fmt(get(r, variant, "colorchecker", "means_sam"))
            if has_cave:
                row[f"{label}: CAVE dB"] = _fmt(get(r, variant, "cave", "pixel_db"),
                                                get(ideal, ref_variant, "cave", "pixel_db"))
                if label != "oracle":
                    row[f"{label}: CAVE SAM °"] = _fmt(get(r, variant, "cave", "pixel_sam"))
            if label == "shipped defaults":
                row["shipped defaults: decided"] = decisions(
                    (r.get("defaults") or {}).get("findings", []))
        row["remedy"] = r.get("remedy_name") or "—"
        rows.append(row)
    head = list(rows[0])
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    lines += ["| " + " | ".join(r[k] for k in head) + " |" for r in rows]
    return "\n".join(lines), rows
