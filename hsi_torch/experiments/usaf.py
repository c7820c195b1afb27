"""Spatial resolution with a USAF 1951 target: the finest resolvable group/element
per reconstructed band, compared with an RGB reference imaged without the add-on
(docs/experiments.md, *USAF 1951 resolution*, describes the set-up, the ablations and the results).

**Scale.** ``magnification`` is diffuser mm per target mm, so ``r(G, E) = 2^{G+(E−1)/6}`` lp/mm
is in *target* units and the diffuser sees ``r / magnification``; a reference frame sampling the
diffuser at ``p`` mm per pixel has its Nyquist limit at ``magnification/(2p)`` lp/mm on the target.

**HSI**: the capture rendered through the prototype and reconstructed from the oracle or a
calibrated bundle. **RGB reference** (:func:`rgb_reference`): the same scene sampled at the
reference frame's diffuser points, weighted by ``φ`` and vignetting only, then the same sensor
model and bilinear demosaic; channels white-balanced, ``gray`` their mean.

**Contrast criterion.** Per bar triplet, Michelson contrast ``C = (min bars − max gaps) /
(min bars + max gaps)`` of a profile sampled at the bar and gap centres; an element is
*resolved* when ``C ≥ threshold``, and the limit is the finest element before the first
unresolved one (elements not wholly inside the valid region are skipped).

The reconstructed cube is also scored against the true reflectance with
:func:`hsi_torch.metrics.cube_metrics` (not the RGB reference: it has no spectrum).
``capture_set`` reuses a previous run's capture set after :func:`check_reusable_capture_set`.
Command: ``hsi-torch experiment usaf --out DIR`` (the shipped ``usaf.yaml``).
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from hsi_torch.config import load_config, option, to_dict
from hsi_torch.experiments import report
from hsi_torch.experiments.metrics import (
    METRIC_FORMATS,
    cube_metrics,
    metric_cells,
    metric_columns,
    metrics_note,
)
from hsi_torch.experiments.opd import calibrated_bundle
from hsi_torch.io.atomic import atomic_write_json
from hsi_torch.io.bundle import CalibrationBundle
from hsi_torch.io.capture_set import read_truth
from hsi_torch.recon import Reconstructor
from hsi_torch.recon.frame import assemble_cube, solve_observations
from hsi_torch.recon.pipeline import ReconstructionResult
from hsi_torch.recon.spatial import DEFAULT_LAM
from hsi_torch.resources import shipped_config
from hsi_torch.simulate.capture_sets import build_renderer, build_scene, simulate_capture_set
from hsi_torch.simulate.config import SceneSpec, SimulateConfig
from hsi_torch.simulate.oracle import bundle_from_truth

__all__ = [
    "michelson_bar_contrast",
    "triplet_sample_points",
    "element_contrasts",
    "resolution_limit",
    "elements_below",
    "rgb_reference",
    "USAFTargetSpec",
    "USAFConfig",
    "ABLATIONS",
    "ideal_observations",
    "check_reusable_capture_set",
    "run_usaf",
]

#: factors the ``ablate`` key can switch off (see :class:`USAFConfig` and docs/experiments.md)
ABLATIONS = ("diffuser", "warp", "demosaic", "noise", "beta")


# --- contrast criterion


def michelson_bar_contrast(bars: Tensor, gaps: Tensor) -> Tensor:
    """Michelson contrast of a bar triplet: ``(min bars − max gaps) / (min bars + max gaps)``.

    Args:
        bars: ``(..., 3)`` intensities at the three bar centres (bright bars).
        gaps: ``(..., 2)`` intensities at the two gap centres.

    Returns:
        ``(...)`` contrast (negative when some gap is brighter than some bar; NaN propagates).
    """
    if bars.shape[-1] != 3 or gaps.shape[-1] != 2 or bars.shape[:-1] != gaps.shape[:-1]:
        raise ValueError(f"bars must be (..., 3) and gaps (..., 2) with equal leading dims, got "
                         f"{tuple(bars.shape)} and {tuple(gaps.shape)}")
    lo = bars.amin(-1)
    hi = gaps.amax(-1)
    # amin/amax ignore NaN ordering rules: propagate explicitly
    nan = torch.isnan(bars).any(-1) | torch.isnan(gaps).any(-1)
    den = lo + hi
    c = (lo - hi) / torch.where(den == 0, torch.ones_like(den), den)
    return torch.where(nan, torch.full_like(c, float("nan")), c)


def triplet_sample_points(element: Any, length_fraction: float = 0.6, n_along: int = 7) -> Tensor:
    """``(5, n_along, 2)`` diffuser points (mm) of a bar triplet: rows 0, 2, 4 = bar centres,
    rows 1, 3 = gap centres, each at ``n_along`` positions along the central ``length_fraction``
    of the bars. ``element``: a :class:`~hsi_torch.simulate.scenes.USAFElement`."""
    w = float(element.bar_width_mm)
    x0, x1, y0, y1 = (float(v) for v in element.bbox_mm)
    across = torch.tensor([(j + 0.5) * w for j in range(5)], dtype=torch.float64)
    half = 0.5 * length_fraction * 5 * w
    along = torch.linspace(-half, half, n_along, dtype=torch.float64)
    if element.orientation == "vertical":  # bars run along Y, profile along X
        xs = x0 + across[:, None].expand(5, n_along)
        ys = 0.5 * (y0 + y1) + along[None].expand(5, n_along)
    else:
        ys = y0 + across[:, None].expand(5, n_along)
        xs = 0.5 * (x0 + x1) + along[None].expand(5, n_along)
    return torch.stack([xs, ys], -1)


def element_contrasts(images: Tensor, points_px: Tensor) -> Tensor:
    """Contrast of every triplet in every image channel.

    Args:
        images: ``(C, h, w)`` (NaN = invalid pixels, which make the contrast NaN).
        points_px: ``(E, 5, n, 2)`` sample points in image px ``(x, y)`` (triplets × bars/gaps
            × along), from :func:`triplet_sample_points` mapped to the image.

    Returns:
        ``(C, E)`` Michelson contrasts (:func:`michelson_bar_contrast` of the along-averages).
    """
    C, h, w = images.shape
    E = points_px.shape[0]
    p = points_px.to(images)
    g = torch.stack([2 * p[..., 0] / (w - 1) - 1, 2 * p[..., 1] / (h - 1) - 1], -1)
    g = g.reshape(1, E * 5, -1, 2).expand(C, -1, -1, -1)
    out = F.grid_sample(images[:, None].expand(C, 1, h, w).reshape(C, 1, h, w), g,
                        mode="bilinear", padding_mode="border", align_corners=True)
    out = out[:, 0].reshape(C, E, 5, -1).mean(-1)  # (C, E, 5), NaN propagates
    outside = (g[0].abs() > 1).any(-1).any(-1).reshape(E, 5).any(-1)  # (E,)
    c = michelson_bar_contrast(out[..., [0, 2, 4]], out[..., [1, 3]])
    return c.masked_fill(outside[None], float("nan"))


def resolution_limit(contrast: Tensor, frequency: Tensor, threshold: float,
                     usable: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Finest resolved element per row: walk the usable elements from coarse to fine and stop
    at the first with ``contrast < threshold`` (or NaN).

    Args:
        contrast: ``(C, E)``; frequency: ``(E,)`` lp/mm (any order); usable: ``(E,)`` bool
            (default all).

    Returns:
        ``(index (C,) long, lp_per_mm (C,))``: index into ``E`` of the finest resolved element
        (−1 and 0 lp/mm when even the coarsest usable one fails).
    """
    C, E = contrast.shape
    usable = torch.ones(E, dtype=torch.bool) if usable is None else usable.to(torch.bool).cpu()
    order = [i for i in torch.argsort(frequency.cpu(), stable=True).tolist() if bool(usable[i])]
    idx = torch.full((C,), -1, dtype=torch.long)
    c = contrast.detach().cpu()
    for row in range(C):
        for i in order:
            v = float(c[row, i])
            if not (v >= threshold):
                break
            idx[row] = i
    f = torch.where(idx >= 0, frequency.cpu().to(torch.float64)[idx.clamp_min(0)],
                    torch.zeros(C, dtype=torch.float64))
    return idx, f


def elements_below(lp_mm: Tensor, reference_lp_mm: float) -> list[int | None]:
    """USAF elements (steps of ``2^(1/6)``) each limit lies below ``reference_lp_mm``:
    ``round(6 · log2(reference / limit))`` (negative: finer than the reference; ``None`` where
    a limit is 0, i.e. nothing resolved, or the reference resolved nothing)."""
    out: list[int | None] = []
    for v in lp_mm.tolist():
        if v > 0 and reference_lp_mm > 0:
            out.append(int(round(6.0 * math.log2(reference_lp_mm / v))))
        else:
            out.append(None)
    return out


# --- RGB reference (no add-on)


def rgb_reference(renderer: Any, scene: Any, *, seed: int = 0, supersample: int | None = None,
                  chunk: int = 1 << 16, sensor: Any | None = None) -> tuple[Tensor, Tensor]:
    """The scene imaged directly on a sensor with the reference frame's image-plane scale.

    ``E_c(q) = κ · mean_sub-samples[ V(X) · Σ_λ Δλ_f φ^c(λ) S(X, λ) ]`` at the diffuser points
    ``X`` of reference pixel ``q`` (the renderer's illuminant × camera × objective ``φ``, κ and
    vignetting; no kaleidoscope, diffuser fall-off, polarizers or BRF), then the renderer's
    :class:`~hsi_torch.optics.sensor.SensorModel` (mosaic, noise, same exposure, generator seeded
    with ``seed``; ``sensor`` replaces it, e.g. the un-ablated one) and its bilinear demosaic.

    Returns:
        ``(rgb (3, h, w), white (3,))``: demosaiced DN above black, and the noise-free DN of a
        white (reflectance 1) reflector per channel at the frame centre's vignetting — divide by
        it to white-balance.
    """
    s = int(supersample or renderer.supersample)
    x0, y0, w, h = renderer.layout.reference_bbox
    pts = renderer.reference_diffuser_points(s)  # (n, s², 2) float64
    n = pts.shape[0]
    flat = pts.reshape(-1, 2)
    fine = renderer.fine.to(torch.float64)
    phi_w = (renderer.phi_fine * renderer.fine_widths * renderer.kappa).to(torch.float64)  # (3,L)
    sig = torch.empty(flat.shape[0], 3, dtype=torch.float64, device=flat.device)
    for a in range(0, flat.shape[0], chunk):
        p = flat[a:a + chunk]
        refl = scene.reflectance(p, fine).to(torch.float64)  # (N, L)
        sig[a:a + chunk] = (refl @ phi_w.T) * renderer.vignetting_factor(p)[:, None]
    irr = sig.reshape(n, s * s, 3).mean(1).T.reshape(3, h, w)
    gen = torch.Generator(device=irr.device)
    gen.manual_seed(int(seed))
    sensor = renderer.sensor if sensor is None else sensor
    dn, _ = sensor.expose(irr[None], generator=gen)
    raw = dn - sensor.black_level
    rgb = sensor.demosaic(raw)[0] if raw.shape[-3] == 1 else raw[0]
    unit = sensor.electrons_at_unity / sensor.gain_e_per_dn * sensor.exposure
    white = phi_w.sum(1) * unit
    return rgb, white


def ideal_observations(rec: Reconstructor, renderer: Any, scene: Any, *, noise: bool = True,
                       seed: int = 0) -> tuple[Tensor, Tensor, dict[str, Any]]:
    """Reconstruct from *ideally registered* observations: no view sampling, warp or demosaic.

    Every view observes exactly the reference pixel's footprint: ``y_p = A_p s̄_p`` with ``A_p``
    the reconstructor's (bundle's) sensing matrix and ``s̄_p`` the scene's reflectance averaged
    over the reference pixel's ``s × s`` sub-samples on the (diffuser-blurred) diffuser plane
    (:meth:`CaptureRenderer.scene_truth`), in DN above black at the scene exposure. With
    ``noise`` the observations go through the renderer's sensor as full RGB planes (shot and
    read noise, quantisation, saturation: ``SensorModel(output='rgb')``, generator seeded with
    ``seed``). Then the reconstructor's own solve (its ``prior``, ``lam``, ``min_views``).

    Returns:
        ``(cube (M, h, w), valid (h, w), stats)`` as :class:`ReconstructionResult` holds them.
    """
    sens = rec.sensing
    M = sens.wavelengths_nm.numel()
    truth = renderer.scene_truth(scene).to(torch.float64)  # (M, h, w)
    if tuple(truth.shape[1:]) != tuple(sens.frame_size):
        raise ValueError(f"renderer frame {tuple(truth.shape[1:])} != the bundle's reference "
                         f"frame {tuple(sens.frame_size)}")
    pix = sens.pixel_index.to(truth.device)
    x = truth.reshape(M, -1).index_select(1, pix).T.to(device=sens.device, dtype=sens.dtype)
    y = sens.model.A(x).to(torch.float64)  # (P, 3V) noise-free DN above black
    P, O = y.shape
    V = O // 3
    sat = torch.zeros_like(y, dtype=torch.bool)
    if noise:
        sensor = dataclasses.replace(renderer.sensor, output="rgb")
        unit = sensor.electrons_at_unity / sensor.gain_e_per_dn * sensor.exposure
        irr = (y / unit).reshape(P, V, 3).permute(1, 2, 0).unsqueeze(2)  # (V, 3, 1, P)
        gen = torch.Generator(device=irr.device)
        gen.manual_seed(int(seed))
        dn, s_ = sensor.expose(irr, generator=gen)
        y = (dn - sensor.black_level).squeeze(2).permute(2, 0, 1).reshape(P, O)
        sat = s_.squeeze(2).permute(2, 0, 1).reshape(P, O)
    y = y.to(sens.dtype)
    mask = sens.obs_mask.to(y.device) & torch.isfinite(y) & ~sat.to(y.device)
    xs, ok, info = solve_observations(sens, y, mask, rec.settings)
    cube, valid = assemble_cube(sens, xs, ok, nan_invalid=True)
    return cube, valid, info


# --- config and run


@dataclass
class USAFTargetSpec:
    """The USAF 1951 scene (:class:`~hsi_torch.simulate.scenes.USAF1951Scene` parameters)."""

    groups: list[int] = field(default_factory=lambda: [-2, -1, 0, 1])
    magnification: float = option(0.0625, "diffuser mm per target mm (r(G,E) in target lp/mm); "
                                          "1/16 puts the full-size RGB reference's limit at G0 "
                                          "E2 = 1.12 lp/mm")
    center_mm: list[float] = field(default_factory=lambda: [0.0, 0.3])
    bar_reflectance: float = 0.9
    background_reflectance: float = 0.05


@dataclass
class USAFConfig:
    """``hsi-torch experiment usaf`` configuration (see docs/experiments.md)."""

    prototype: Path | None = option(None, "SimulateConfig YAML of the prototype (null: the "
                                          "shipped simulate_full.yaml, the full-size prototype)")
    prototype_overrides: list[str] = field(
        default_factory=lambda: ["diffuser.blur_sigma_mm=0.01"],
        metadata={"help": "overrides of the prototype config (default: a fine ground-glass "
                          "diffuser, σ = 10 µm; docs/experiments.md says why)"})
    target: USAFTargetSpec = field(default_factory=USAFTargetSpec)
    bundle: str = option("oracle", "oracle | calibrated | path to a bundle .npz")
    calibrate_config: Path | None = None
    capture_set: Path | None = option(None, "reuse this capture set (a previous run's "
                                            "OUT/capture_set) instead of simulating one; refused "
                                            "unless it was simulated with the very prototype, "
                                            "target and ablations this run would simulate")
    beta: float = option(1000.0, "smoothness weight (DN² scale)")
    diff_order: int = 1
    prior: Literal["none", "tv"] = option("none", "none: per-pixel NNLS; tv: spatial-spectral (TV)")
    lam: float | Literal["auto", "discrepancy"] = option(
        DEFAULT_LAM, "prior=tv: relative TV weight (see the reconstruct config), auto (SURE) or "
                     "discrepancy")
    ablate: list[str] = option(text="factors switched off (ablation): diffuser (no diffuser "
                               "blur), warp (ideally registered observations: no view sampling, "
                               "warp or demosaic), demosaic (full-RGB sensor), noise (no "
                               "shot/read noise, no quantisation), beta (beta = 0)",
                               factory=list)
    threshold: float = option(0.1, "Michelson contrast to resolve")
    orientation: Literal["both", "horizontal", "vertical", "either"] = "both"
    length_fraction: float = 0.6
    n_along: int = 7
    figure_band_nm: float = 600.0
    seed: int = 0
    dtype: Literal["float32", "float64"] = "float32"
    device: str | None = None
    progress: bool = True

    def __post_init__(self) -> None:
        if isinstance(self.ablate, str):
            self.ablate = [self.ablate]
        bad = [a for a in self.ablate if a not in ABLATIONS]
        if bad:
            raise ValueError(f"ablate: unknown factor(s) {bad}; choose from {list(ABLATIONS)}")
        if len(set(self.ablate)) != len(self.ablate):
            raise ValueError(f"ablate: {self.ablate} names a factor twice")
        if self.beta < 0:
            raise ValueError(f"beta must be >= 0, got {self.beta}")


def _apply_ablations(proto: SimulateConfig, ablate: list[str]) -> None:
    """Switch the prototype's factors named in ``ablate`` off (in place)."""
    if "diffuser" in ablate:
        proto.diffuser.blur_sigma_mm = 0.0
    if "demosaic" in ablate:
        proto.sensor.output = "rgb"
    if "noise" in ablate:
        proto.sensor.shot_noise, proto.sensor.read_noise_e = False, 0.0
        proto.sensor.quantize = False


def _sim_config(cfg: USAFConfig, calibrated: bool, ablate: bool = True):
    proto = load_config(cfg.prototype or shipped_config("simulate_full"), SimulateConfig,
                        list(cfg.prototype_overrides))
    t = cfg.target
    scene = SceneSpec("usaf", "usaf", params={
        "groups": list(t.groups), "magnification": t.magnification,
        "center_mm": list(t.center_mm), "bar_reflectance": t.bar_reflectance,
        "background_reflectance": t.background_reflectance})
    cap = proto.captures
    if calibrated:
        cap.scenes = [scene]
    else:  # the oracle bundle needs only the ground truth
        cap.scenes, cap.scan_wavelengths_nm = [scene], []
        cap.white_shots, cap.dark_frames, cap.grid.poses = 0, 0, []
    proto.render.figures = False
    proto.render.seed = int(cfg.seed)
    if ablate:
        _apply_ablations(proto, list(cfg.ablate))
    return proto


#: keys of the resolved simulate config that do not change a rendered capture
_NO_EFFECT_KEYS = (("render", "progress"), ("render", "figures"))


def check_reusable_capture_set(path: Path, expected: list[SimulateConfig]) -> None:
    """Refuse to reuse the capture set at ``path`` unless it is complete (``manifest.json``,
    ground truth) and its ``resolved_config.yaml`` equals one of the ``expected`` simulate
    configs (all keys but :data:`_NO_EFFECT_KEYS`): the same prototype, target, ablations of
    the capture (diffuser, demosaic, noise) and seed. Raises ``ValueError`` naming the keys
    that differ."""
    path = Path(path)
    for need in ("manifest.json", "resolved_config.yaml", "ground_truth/truth.npz"):
        if not (path / need).is_file():
            raise ValueError(f"capture_set: {path} is not a complete capture set ({need} missing)")

    def flat(d: Any, pre: tuple = ()) -> dict[tuple, Any]:
        if isinstance(d, dict):
            out: dict[tuple, Any] = {}
            for k, v in d.items():
                out.update(flat(v, pre + (k,)))
            return out
        return {} if pre in _NO_EFFECT_KEYS else {pre: d}

    have = flat(to_dict(load_config(path / "resolved_config.yaml", SimulateConfig)))
    diffs = []
    for exp in expected:
        want = flat(to_dict(exp))
        d = sorted(".".join(map(str, k)) for k in set(have) | set(want)
                   if have.get(k) != want.get(k))
        if not d:
            return
        diffs.append(d)
    best = min(diffs, key=len)
    raise ValueError(f"capture_set: {path} was simulated with another configuration than "
                     f"this run would simulate (differs in {', '.join(best[:8])}"
                     f"{', ...' if len(best) > 8 else ''}); it can only be reused for rows "
                     f"that change the reconstruction, not the capture (beta, prior, lam, "
                     f"threshold, ...)")


def _combine(contrast: Tensor, elements: list[Any], mode: str) -> tuple[Tensor, list[tuple]]:
    """Per (G, E): combine the two orientations' contrasts (min for 'both', max for 'either')."""
    keys = list(dict.fromkeys((e.group, e.element) for e in elements))
    cols = []
    for k in keys:
        ii = [i for i, e in enumerate(elements) if (e.group, e.element) == k]
        sel = {elements[i].orientation: contrast[:, i] for i in ii}
        if mode in ("horizontal", "vertical"):
            cols.append(sel[mode])
        else:
            st = torch.stack(list(sel.values()), -1)
            nan = torch.isnan(st).any(-1)
            v = st.amin(-1) if mode == "both" else st.amax(-1)
            cols.append(torch.where(nan, torch.full_like(v, float("nan")), v))
    return torch.stack(cols, -1), keys


def run_usaf(cfg: USAFConfig, out: str | Path, *, device: str | None = None) -> dict[str, Any]:
    """Render, reconstruct and score the USAF target; write ``resolution.csv/.md``,
    ``contrast.csv``, ``summary.json``, ``usaf_600nm_vs_rgb.png``, ``resolution_vs_wavelength.png``
    into ``out``.

    Returns:
        The summary dict (limits per band and for the RGB reference, scale, timings).
    """
    t_all, out, dev, dt = report.start_run(out, cfg, device)
    dev = str(dev)
    cfg.__post_init__()  # the ablation list and beta may have been edited after construction
    ablate = list(cfg.ablate)
    ideal = "warp" in ablate
    if ideal and cfg.bundle != "oracle":
        raise ValueError(f"ablate: 'warp' needs bundle: oracle (the ideal observations are "
                         f"made with the bundle's sensing matrix), got bundle {cfg.bundle!r}")
    beta = 0.0 if "beta" in ablate else float(cfg.beta)
    tm: dict[str, float] = {}
    calibrated = cfg.bundle == "calibrated"
    sim = _sim_config(cfg, calibrated)
    cs = out / "capture_set"
    t0 = time.perf_counter()
    if ideal:  # the oracle bundle needs only the ground truth: no capture to render
        sim_cs = dataclasses.replace(sim, captures=dataclasses.replace(sim.captures, scenes=[]))
    else:
        sim_cs = sim
    if cfg.capture_set is not None:  # reuse: only when the capture would be the same
        cs = Path(cfg.capture_set)
        check_reusable_capture_set(cs, [sim_cs, sim] if ideal else [sim_cs])
    else:
        simulate_capture_set(sim_cs, cs, device=dev, progress=cfg.progress, log=lambda *a: None)
    tm["simulate"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    if cfg.bundle == "oracle":
        bundle, note = bundle_from_truth(cs), "oracle bundle (simulator truth)"
    elif calibrated:
        bundle, note = calibrated_bundle(cs, cfg.calibrate_config, device=dev,
                                         progress=cfg.progress, save_to=out / "bundle.npz")
    else:
        bundle, note = CalibrationBundle.load(cfg.bundle), f"bundle {cfg.bundle}"
    tm["bundle"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    rec = Reconstructor(bundle, beta=beta, diff_order=cfg.diff_order, device=dev, dtype=dt,
                        prior=cfg.prior, lam=cfg.lam)
    renderer = build_renderer(sim, device="cpu")
    scene = build_scene(sim.captures.scenes[0])
    if ideal:
        cube_i, valid_i, st_i = ideal_observations(rec, renderer, scene,
                                                   noise="noise" not in ablate, seed=cfg.seed)
        res = ReconstructionResult(cube_i, valid_i, rec.sensing.wavelengths_nm, st_i, {})
    else:
        res = rec.reconstruct_file(cs / "scenes" / "usaf.tif")
    tm["reconstruct"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    # the RGB reference is always the un-ablated camera (Bayer, noise): the fixed yardstick
    ref_sensor = build_renderer(_sim_config(cfg, calibrated, ablate=False), device="cpu").sensor \
        if {"demosaic", "noise"} & set(ablate) else None
    rgb, white = rgb_reference(renderer, scene, seed=cfg.seed + 1000, sensor=ref_sensor)
    rgb_wb = rgb / white[:, None, None].to(rgb)
    ref_imgs = torch.cat([rgb_wb, rgb_wb.mean(0, keepdim=True)])
    tm["rgb_reference"] = time.perf_counter() - t0

    # geometry of the triplets in reference-frame px
    elements = scene.elements()
    pts_mm = torch.stack([triplet_sample_points(e, cfg.length_fraction, cfg.n_along)
                          for e in elements])  # (T, 5, n, 2)
    pts_px = renderer.diffuser_to_reference(pts_mm.reshape(-1, 2)).reshape(pts_mm.shape)
    valid = res.valid.cpu()
    h, w = valid.shape
    box_ok = []
    for e in elements:
        bx = renderer.diffuser_to_reference(torch.tensor(
            [[e.bbox_mm[0], e.bbox_mm[2]], [e.bbox_mm[1], e.bbox_mm[3]]], dtype=torch.float64))
        xa, ya = [int(math.floor(v)) for v in bx[0].tolist()]
        xb, yb = [int(math.ceil(v)) for v in bx[1].tolist()]
        ok = 0 <= xa and 0 <= ya and xb < w and yb < h and bool(valid[ya:yb + 1, xa:xb + 1].all())
        box_ok.append(ok)
    cube = res.cube.detach().to("cpu", torch.float64)
    c_hsi = element_contrasts(cube, pts_px)  # (M, T)
    c_rgb = element_contrasts(ref_imgs.to("cpu", torch.float64), pts_px)  # (4, T)
    # the field's metrics against the simulator's true reflectance, over the valid pixels
    # (a warp row's capture set holds no rendered scene, hence no scene_usaf: the renderer's
    # own truth, which is what the simulator writes there)
    truth_arrays = read_truth(cs)[0]
    true_cube = (torch.from_numpy(np.asarray(truth_arrays["scene_usaf"], np.float64))
                 if "scene_usaf" in truth_arrays
                 else renderer.scene_truth(scene).to("cpu", torch.float64))
    metrics = cube_metrics(cube, true_cube, valid & (true_cube.amax(0) > 0))
    usable_t = torch.tensor(box_ok)
    c_hsi = c_hsi.masked_fill(~usable_t[None], float("nan"))
    c_rgb_u = c_rgb.masked_fill(~usable_t[None], float("nan"))
    cb_hsi, keys = _combine(c_hsi, elements, cfg.orientation)
    cb_rgb, _ = _combine(c_rgb_u, elements, cfg.orientation)
    freq = torch.tensor([2.0 ** (g + (e - 1) / 6.0) for g, e in keys], dtype=torch.float64)
    usable_k = torch.tensor([all(box_ok[i] for i, el in enumerate(elements)
                                 if (el.group, el.element) == k) for k in keys])
    idx_h, f_h = resolution_limit(cb_hsi, freq, cfg.threshold, usable_k)
    idx_r, f_r = resolution_limit(cb_rgb, freq, cfg.threshold, usable_k)
    orient = {}
    for o in ("horizontal", "vertical"):
        cbo, _ = _combine(c_hsi, elements, o)
        orient[o] = resolution_limit(cbo, freq, cfg.threshold, usable_k)

    m = float(cfg.target.magnification)
    hd = renderer.layout.diffuser_homographies[0]
    px_mm = 1.0 / float(torch.linalg.det(hd[:2, :2] / hd[2, 2]).abs().sqrt())
    nyq_diff = 1.0 / (2.0 * px_mm)
    wl = res.wavelengths_nm.cpu().tolist()

    def ge(i: int) -> str:
        return "–" if i < 0 else f"G{keys[i][0]} E{keys[i][1]}"

    steps = elements_below(f_h, float(f_r[3]))
    rows = []
    for mi, lam in enumerate(wl):
        rows.append({"image": f"HSI {lam:g} nm", "wavelength_nm": lam,
                     "finest": ge(int(idx_h[mi])), "lp_per_mm_target": float(f_h[mi]),
                     "lp_per_mm_diffuser": float(f_h[mi]) / m,
                     "horizontal": ge(int(orient["horizontal"][0][mi])),
                     "vertical": ge(int(orient["vertical"][0][mi])),
                     "elements_below_rgb": steps[mi]})
    rnames = ["RGB reference (R)", "RGB reference (G)", "RGB reference (B)", "RGB reference (gray)"]
    for ci, nm in enumerate(rnames):
        rows.append({"image": nm, "wavelength_nm": None, "finest": ge(int(idx_r[ci])),
                     "lp_per_mm_target": float(f_r[ci]),
                     "lp_per_mm_diffuser": float(f_r[ci]) / m})
    report.write_csv(out / "resolution.csv", rows)
    crow = []
    for ti, e in enumerate(elements):
        base = {"group": e.group, "element": e.element, "orientation": e.orientation,
                "lp_per_mm_target": e.lp_per_mm_target, "lp_per_mm_diffuser": e.lp_per_mm,
                "in_valid_region": box_ok[ti]}
        for mi, lam in enumerate(wl):
            crow.append({**base, "image": f"HSI {lam:g} nm", "contrast": float(c_hsi[mi, ti])})
        for ci, nm in enumerate(rnames):
            crow.append({**base, "image": nm, "contrast": float(c_rgb[ci, ti])})
    report.write_csv(out / "contrast.csv", crow)

    hsi_f = f_h.numpy()
    stats = {"hsi_median_lp_mm": float(np.median(hsi_f)), "hsi_min_lp_mm": float(hsi_f.min()),
             "hsi_max_lp_mm": float(hsi_f.max()), "rgb_gray_lp_mm": float(f_r[3]),
             "rgb_channels_lp_mm": [float(v) for v in f_r[:3]],
             "rgb_at_least_as_fine_as_hsi_max": bool(float(f_r[3]) >= hsi_f.max()),
             "elements_below_rgb": steps,
             "bands_within_two_elements": sum(1 for d in steps if d is not None and d <= 2),
             "bands": len(steps)}
    md = [
        "# USAF 1951 resolution\n",
        f"Target groups {list(cfg.target.groups)}, magnification {m:g} diffuser mm per target "
        f"mm: r(G, E) = 2^(G+(E−1)/6) lp/mm on the target, r/{m:g} on the diffuser. Reference "
        f"frame: {px_mm:.4f} mm per px on the diffuser → Nyquist {nyq_diff:.2f} lp/mm "
        f"(diffuser) = {nyq_diff * m:.3f} lp/mm (target). {note}; β = {beta:g}; prior "
        f"{cfg.prior}; diffuser blur σ = {sim.diffuser.blur_sigma_mm:g} mm; ablated: "
        f"{', '.join(ablate) or 'nothing'}. "
        f"Criterion: Michelson contrast (min bars − max gaps)/(min bars + max gaps) ≥ "
        f"{cfg.threshold:g}, orientation '{cfg.orientation}', finest element before the first "
        f"failure (coarse → fine); {sum(usable_k.tolist())}/{len(keys)} elements lie wholly "
        "in the valid region.\n",
        report.markdown_table(
            rows, {"image": "image", "finest": "finest G/E",
                   "lp_per_mm_target": "lp/mm (target)",
                   "lp_per_mm_diffuser": "lp/mm (diffuser)", "horizontal": "horizontal bars",
                   "vertical": "vertical bars", "elements_below_rgb": "elements below RGB"},
            {"lp_per_mm_target": ".3f", "lp_per_mm_diffuser": ".2f"}),
        f"\nHSI bands: median {stats['hsi_median_lp_mm']:.3f} lp/mm (range "
        f"{stats['hsi_min_lp_mm']:.3f}–{stats['hsi_max_lp_mm']:.3f}); RGB reference (gray) "
        f"{stats['rgb_gray_lp_mm']:.3f} lp/mm; {stats['bands_within_two_elements']} of "
        f"{len(steps)} bands within two elements of it.\n",
        "\n## Reconstruction against the truth\n",
        f"The HSI cube against the simulator's true reflectance of the target over the "
        f"{int(valid.sum())} valid pixels. "
        + metrics_note()
        + " Not applicable to the RGB reference (three colour channels, no spectrum).\n",
        report.markdown_table([{"image": "HSI cube", **metric_cells(metrics)}],
                              {"image": "image", **metric_columns()}, METRIC_FORMATS),
    ]
    report.write_markdown(out / "resolution.md", "\n".join(md))

    t0 = time.perf_counter()
    band = int(np.argmin(np.abs(np.asarray(wl) - cfg.figure_band_nm)))
    _plot_side_by_side(out / "usaf_600nm_vs_rgb.png", cube[band], ref_imgs[:3], renderer,
                       elements, keys, int(idx_h[band]), int(idx_r[3]), wl[band])
    _plot_vs_wavelength(out / "resolution_vs_wavelength.png", wl, f_h.numpy(),
                        {o: orient[o][1].numpy() for o in orient}, f_r.numpy(), rnames,
                        nyq_diff * m, m)
    tm["figures"] = time.perf_counter() - t0
    tm["total"] = time.perf_counter() - t_all
    summary = {"rows": rows, "stats": stats, "bundle": note, "magnification": m,
               "ablate": ablate, "beta": beta, "prior": cfg.prior,
               "capture_set": str(cs), "capture_set_reused": cfg.capture_set is not None,
               "diffuser_blur_sigma_mm": float(sim.diffuser.blur_sigma_mm),
               "diffuser_mm_per_px": px_mm, "nyquist_lp_mm_diffuser": nyq_diff,
               "nyquist_lp_mm_target": nyq_diff * m, "threshold": cfg.threshold,
               "orientation": cfg.orientation, "usable_elements": int(usable_k.sum()),
               "elements": len(keys), "metrics": metrics,
               "recon_stats": {k: v for k, v in res.stats.items()
                               if isinstance(v, (int, float))},
               "timings_s": tm, "device": dev}
    atomic_write_json(out / "summary.json", summary)
    return summary


def _element_box_px(renderer: Any, elements: list[Any], key: tuple) -> list[tuple]:
    boxes = []
    for e in elements:
        if (e.group, e.element) != key:
            continue
        b = renderer.diffuser_to_reference(torch.tensor(
            [[e.bbox_mm[0], e.bbox_mm[2]], [e.bbox_mm[1], e.bbox_mm[3]]], dtype=torch.float64))
        boxes.append((float(b[0, 0]), float(b[0, 1]), float(b[1, 0] - b[0, 0]),
                      float(b[1, 1] - b[0, 1])))
    return boxes


def _plot_side_by_side(path: Path, band_img: Tensor, rgb: Tensor, renderer: Any,
                       elements: list[Any], keys: list[tuple], i_hsi: int, i_rgb: int,
                       lam: float) -> None:
    import matplotlib.patches as mpatches

    fig, axes = report.new_figure(1, 2, figsize=(11, 5.2))
    img = band_img.numpy()
    finite = img[np.isfinite(img)]
    hi = float(np.percentile(finite, 99.5)) if finite.size else 1.0
    axes[0].imshow(np.ma.masked_invalid(img), cmap="gray", vmin=0, vmax=hi, interpolation="nearest")
    disp = (rgb / rgb.amax().clamp_min(1e-9)).clamp(0, 1).permute(1, 2, 0).numpy() ** (1 / 2.2)
    axes[1].imshow(disp, interpolation="nearest")
    for ax, i, title in ((axes[0], i_hsi, f"HSI reconstruction, {lam:g} nm band"),
                         (axes[1], i_rgb, "RGB reference (no add-on, same image-plane scale)")):
        for j, col, tag in ((i, "lime", "finest resolved"), (i + 1, "red", "first failed")):
            if 0 <= j < len(keys):
                for (x, y, bw, bh) in _element_box_px(renderer, elements, keys[j]):
                    ax.add_patch(mpatches.Rectangle((x - 0.5, y - 0.5), bw, bh, fill=False,
                                                    ec=col, lw=1.3))
                g, e = keys[j]
                ax.plot([], [], color=col, lw=2, label=f"{tag}: G{g} E{e} "
                        f"({2.0 ** (g + (e - 1) / 6):.3f} lp/mm)")
        ax.set_title(title, fontsize=10)
        ax.legend(loc="lower left", fontsize=7, framealpha=0.8)
        ax.set_xlabel("x (reference-frame px)")
    axes[0].set_ylabel("y (px)")
    report.save_figure(fig, path)


def _plot_vs_wavelength(path: Path, wl: list[float], both: np.ndarray,
                        per_orient: dict[str, np.ndarray], rgb: np.ndarray, rnames: list[str],
                        nyq_target: float, m: float) -> None:
    fig, ax = report.new_figure(figsize=(7.5, 4.2))
    ax.plot(wl, both, "o-", color="k", label="HSI, both orientations")
    ax.plot(wl, per_orient["horizontal"], "v--", color="tab:blue", ms=4, lw=0.8,
            label="HSI, horizontal bars")
    ax.plot(wl, per_orient["vertical"], "^--", color="tab:orange", ms=4, lw=0.8,
            label="HSI, vertical bars")
    for v, nm, col in zip(rgb, rnames, ("red", "green", "blue", "gray"), strict=True):
        ax.axhline(v, color=col, ls=":", lw=1.2, label=nm)
    ax.axhline(nyq_target, color="purple", ls="-.", lw=0.8, label="Nyquist of the frame")
    ax.set_xlabel("wavelength (nm)")
    ax.set_ylabel("finest resolved (lp/mm, target)")
    sec = ax.secondary_yaxis("right", functions=(lambda y: y / m, lambda y: y * m))
    sec.set_ylabel("lp/mm on the diffuser")
    ax.legend(fontsize=7, ncol=2, loc="lower right")
    ax.set_title("USAF 1951: resolvable spatial frequency per band", fontsize=10)
    report.save_figure(fig, path)
