"""Calibration and scene capture sets of the virtual prototype, written with their ground truth.

Folder format (:mod:`hsi_torch.io.capture_set` writes and reads it; see ``docs/simulate.md``)::

    OUT/manifest.json            schema version, sensor, levels, exposures, list of captures
    OUT/nominal_layout.json      what a user knows before calibration (no homographies)
    OUT/brf_free_mask.png        (H, W) 8-bit: 255 = usable BRF-free pixels of the reference view
    OUT/scan/scan_430nm.tif …    monochromator scan (objective removed)
    OUT/white/white_00.tif …     white reference (objective on)
    OUT/grid/grid_00.tif …       circle-grid poses
    OUT/scenes/<name>.tif        scene captures
    OUT/dark/dark_00.tif         dark frames
    OUT/ground_truth/truth.npz + truth.json
    OUT/figures/*.png
    OUT/resolved_config.yaml

Every file is written atomically (temp file + ``os.replace``).
"""

from __future__ import annotations

import functools
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from hsi_torch.config import to_dict, write_resolved_config
from hsi_torch.console import progress_bar, progress_enabled
from hsi_torch.devices import torch_dtype
from hsi_torch.io import load_cube, write_capture
from hsi_torch.io.capture_set import write_capture_set_index, write_truth
from hsi_torch.optics import BRFConfig, CameraModel, KaleidoscopeGeometry
from hsi_torch.optics.geometry import apply_homography
from hsi_torch.optics.sensor import DiffuserModel, SensorModel
from hsi_torch.provenance import provenance
from hsi_torch.refdata import filter_transmittance, read_spectral_csv
from hsi_torch.resources import DATA_ENV, real_data_dir
from hsi_torch.simulate import figures
from hsi_torch.simulate.config import SceneSpec, SimulateConfig
from hsi_torch.simulate.render import (
    CaptureRenderer,
    CaptureSpec,
    fine_wavelengths,
    subpixel_offsets,
)
from hsi_torch.simulate.scenes import CircleGridScene, ColorCheckerScene, CubeScene, make_scene
from hsi_torch.spectral import SpectralGrid

__all__ = [
    "PlannedCapture",
    "SimulationSummary",
    "build_renderer",
    "build_scene",
    "plan_captures",
    "nominal_layout",
    "brf_free_patch_mask",
    "simulate_capture_set",
]


# --- building blocks from the config


def design_optics(cfg: SimulateConfig) -> tuple[KaleidoscopeGeometry, CameraModel]:
    """The kaleidoscope geometry and the camera (``scale`` applied) of a simulate config: the
    device's design, as the renderer and ``hsi-torch layout`` trace it."""
    g = to_dict(cfg.geometry)
    if g["vertices_in"] is not None:
        g["vertices_in"] = tuple(tuple(p) for p in g["vertices_in"])
    geometry = KaleidoscopeGeometry.from_dict(g)
    cam_d = to_dict(cfg.camera)
    scale = cam_d.pop("scale")
    camera = CameraModel.from_dict(cam_d)
    return geometry, (camera.scaled(scale) if scale != 1.0 else camera)


def build_renderer(cfg: SimulateConfig, device: str | None = None) -> CaptureRenderer:
    """A :class:`CaptureRenderer` for a :class:`SimulateConfig` (``device`` overrides it)."""
    geometry, camera = design_optics(cfg)
    brf_d = to_dict(cfg.brf)
    eff = brf_d.pop("polarizer_efficiency")
    brf = BRFConfig.from_dict(brf_d)
    sensor = SensorModel(**to_dict(cfg.sensor), input_units="relative", seed=cfg.render.seed,
                         **cfg.mismatch.sensor_kwargs())
    if sensor.white > 65535:
        raise ValueError(f"sensor white level {sensor.white} does not fit a 16-bit capture "
                         "(sensor.bit_depth <= 16)")
    tau: Any = cfg.objective.transmission
    if cfg.objective.transmission_csv:
        src, table, _ = read_spectral_csv(cfg.objective.transmission_csv)
        tau = (src, table[:, 0])
    r = cfg.render
    grid = SpectralGrid.uniform(r.grid_start_nm, r.grid_stop_nm, r.grid_step_nm)
    curves = None
    if cfg.design.kind == "manakov" and cfg.design.filters:
        fine, _ = fine_wavelengths(grid.wavelengths(dtype=torch.float64), r.fine_step_nm)
        curves = []
        for f in cfg.design.filters:
            try:
                t = filter_transmittance(f, fine, extrapolate="edge", dtype=torch.float64)
            except (FileNotFoundError, ValueError, ModuleNotFoundError) as exc:
                raise type(exc)(f"config key 'design.filters': {exc}") from None
            curves.append((fine.numpy(), t.numpy()))
        curves = tuple(curves)
    return CaptureRenderer(
        geometry, camera, brf, sensor,
        diffuser=DiffuserModel(cfg.diffuser.falloff_k, cfg.diffuser.blur_sigma_mm),
        grid=grid, fine_step_nm=r.fine_step_nm, polarizer_efficiency=eff,
        vignetting=cfg.objective.vignetting, objective_transmission=tau,
        illuminant=cfg.illuminant, camera_sensitivity=cfg.camera_sensitivity,
        supersample=r.supersample, max_reflections=r.max_reflections,
        scan_fwhm_nm=cfg.captures.scan_fwhm_nm, scan_line=cfg.captures.scan_line,
        scan_exposure=cfg.captures.scan_exposure, chunk=r.chunk,
        device=device or r.device, dtype=torch_dtype(r.dtype), view_inset_px=r.view_inset_px,
        mismatch=cfg.mismatch, design=cfg.design.to_design(curves),
    )


def build_scene(spec: SceneSpec) -> Any | None:
    """The scene of a :class:`SceneSpec`; ``None`` when it is optional and its data is missing.

    ``cave`` reads ``cave_stuffed_toys`` in the real-data folder
    (:func:`hsi_torch.resources.real_data_dir`: ``HSI_TORCH_DATA``, else ``../shared/data/real``
    beside a source checkout) unless ``params.folder`` is given.
    """
    params = dict(spec.params)
    if spec.kind == "cube":
        if spec.path is None:
            raise ValueError(f"scene {spec.name or spec.kind!r}: kind 'cube' needs `path`")
        if not Path(spec.path).exists():
            if spec.optional:
                return None
            raise FileNotFoundError(f"scene {spec.name or 'cube'!r}: cube file not found: "
                                    f"{spec.path}")

        c = load_cube(spec.path)
        cube = torch.nan_to_num(torch.as_tensor(c.cube), nan=0.0)
        return CubeScene(cube, c.wavelengths, width_mm=float(params.get("width_mm", 7.0)),
                         center_mm=tuple(params.get("center_mm", (0.0, 0.9))),
                         extrapolate=params.get("extrapolate", "edge"))
    if spec.kind == "cave":
        given = params.pop("folder", None)
        folder = Path(given) if given is not None else real_data_dir("cave_stuffed_toys")
        if folder is None or not folder.is_dir():
            if spec.optional:
                return None
            where = folder if folder is not None else (
                f"cave_stuffed_toys in the real-data folder (none found: set {DATA_ENV} or "
                "params.folder)")
            raise FileNotFoundError(f"scene {spec.name or 'cave'!r}: CAVE folder not found: "
                                    f"{where}")
        params.setdefault("width_mm", 7.0)
        params.setdefault("center_mm", (0.0, 0.9))
        params.setdefault("extrapolate", "edge")
        return make_scene("cave", folder=folder, **params)
    return make_scene(spec.kind, **params)


@dataclass
class PlannedCapture:
    """A capture of the set: what to render, where to write it and its manifest entry."""

    spec: CaptureSpec
    file: str
    type: str
    render_key: int
    seed: int
    entry: dict[str, Any] = field(default_factory=dict)


def plan_captures(
    cfg: SimulateConfig, renderer: CaptureRenderer, log=print
) -> tuple[list[CaptureSpec], list[PlannedCapture], dict[str, Any]]:
    """Noise-free renders to compute, the captures to write, and the scenes by name."""
    specs: list[CaptureSpec] = []
    planned: list[PlannedCapture] = []
    scenes: dict[str, Any] = {}
    seed0 = int(cfg.render.seed)
    cap = cfg.captures

    def add(spec: CaptureSpec, files: list[tuple[str, str, dict]]) -> None:
        specs.append(spec)
        for f, t, extra in files:
            planned.append(PlannedCapture(spec, f, t, len(specs) - 1, seed0 + len(planned), extra))

    wl_scan = (cap.scan_wavelengths_nm if cap.scan_wavelengths_nm is not None
               else renderer.wavelengths.tolist())
    for lam in wl_scan:
        tag = f"{lam:g}".replace(".", "p")
        add(CaptureSpec(f"scan_{tag}nm", "scan", None, float(lam)),
            [(f"scan/scan_{tag}nm.tif", "scan",
              {"wavelength_nm": float(lam), "fwhm_nm": cap.scan_fwhm_nm,
               "line": cap.scan_line})])
    if cap.white_shots > 0:
        add(CaptureSpec("white", "scene", None),
            [(f"white/white_{k:02d}.tif", "white", {"shot": k}) for k in range(cap.white_shots)])
    gc = cap.grid
    for k, pose in enumerate(gc.poses):
        sc = CircleGridScene(pattern_size=tuple(gc.pattern_size), spacing_mm=gc.spacing_mm,
                             radius_mm=gc.radius_mm, rotation_rad=math.radians(pose.rotation_deg),
                             translation_mm=tuple(pose.translation_mm),
                             tilt_x_rad=math.radians(pose.tilt_x_deg),
                             tilt_y_rad=math.radians(pose.tilt_y_deg))
        scenes[f"grid_{k:02d}"] = sc
        add(CaptureSpec(f"grid_{k:02d}", "scene", sc),
            [(f"grid/grid_{k:02d}.tif", "grid",
              {"pose": to_dict(pose), "pattern_size": list(gc.pattern_size),
               "spacing_mm": gc.spacing_mm, "radius_mm": gc.radius_mm})])
    for s in cap.scenes:
        name = s.name or s.kind
        sc = build_scene(s)
        if sc is None:
            log(f"scene {name!r} skipped: its data is not available (optional)")
            continue
        scenes[name] = sc
        add(CaptureSpec(name, "scene", sc),
            [(f"scenes/{name}.tif", "scene", {"name": name, "scene_kind": s.kind})])
    for k in range(cap.dark_frames):
        add(CaptureSpec(f"dark_{k:02d}", "dark"), [(f"dark/dark_{k:02d}.tif", "dark", {})])
    return specs, planned, scenes


# --- nominal layout and BRF-free patch


def brf_free_patch_mask(renderer: CaptureRenderer, margin_px: float = 1.5) -> torch.Tensor:
    """``(H, W)`` bool: reference-view pixels whose footprint lies inside the BRF-free disk.

    A pixel is kept when its centre's diffuser point is at least ``margin_px`` (in reference-view
    pixels) inside the disk, so neither its sub-pixel area nor a bilinear neighbour is filtered.
    """
    lay = renderer.layout
    h, w = renderer.sensor_size
    hd = lay.diffuser_homographies[0]
    mm_per_px = 1.0 / float(torch.linalg.det(hd[:2, :2] / hd[2, 2]).abs().sqrt())
    r = lay.brf_free_radius_mm - margin_px * mm_per_px
    if r <= 0:
        raise ValueError(f"the BRF-free disk ({lay.brf_free_radius_mm} mm) is smaller than the "
                         f"margin of {margin_px} px")
    pix = renderer.camera.pixel_grid(renderer.device, torch.float64)
    xy = lay.sensor_to_diffuser(0, pix)
    c = torch.tensor(lay.brf_free_center_mm, dtype=torch.float64, device=xy.device)
    inside = ((xy - c) ** 2).sum(-1) <= r * r
    return inside.reshape(h, w) & lay.triangle_mask(0, renderer.device)


def nominal_layout(renderer: CaptureRenderer, patch_mask: torch.Tensor) -> dict[str, Any]:
    """What a user of a real device knows before calibration (JSON-able): view triangles on
    the sensor, parities, reflection sequences, reference bbox, sensor size and the BRF-free
    patch of the reference view (disk + polygon in sensor px). No homographies."""
    lay = renderer.layout
    hd = lay.diffuser_homographies[0].to(torch.float64)
    c = torch.tensor(lay.brf_free_center_mm, dtype=torch.float64, device=hd.device)
    ang = torch.linspace(0, 2 * math.pi, 65, dtype=torch.float64, device=hd.device)[:-1]
    circ = c + lay.brf_free_radius_mm * torch.stack([ang.cos(), ang.sin()], -1)
    poly = apply_homography(hd, circ)
    centre = apply_homography(hd, c[None])[0]
    r_px = float((poly - centre).norm(dim=1).mean())
    ys, xs = torch.nonzero(patch_mask, as_tuple=True)
    return {
        "sensor_size": list(lay.sensor_size),
        "num_views": lay.num_views,
        "reflection_sequences": [list(s) for s in lay.reflection_sequences],
        "triangles_px": lay.triangles.cpu().tolist(),
        "parity": lay.parity.cpu().tolist(),
        "reference_view": 0,
        "reference_bbox": list(lay.reference_bbox),
        "brf_free_patch": {
            "view": 0,
            "center_px": centre.cpu().tolist(),
            "radius_px": r_px,
            "polygon_px": poly.cpu().tolist(),
            "usable_mask": "brf_free_mask.png",
            "usable_pixels": int(patch_mask.sum()),
            "usable_bbox": ([int(xs.min()), int(ys.min()), int(xs.max()), int(ys.max())]
                            if xs.numel() else None),
            "note": "brf_free_mask.png keeps pixels >= 1.5 px inside the disk",
        },
        "conventions": "pixel (x, y) = (column, row), centres at integers; triangle vertices "
                       "are the images of entrance vertices P0, P1, P2",
    }


# --- the command's work


@dataclass
class SimulationSummary:
    """What ``simulate_capture_set`` did."""

    out_dir: Path
    files: list[str]
    num_views: int
    valid_pixels: int
    reference_bbox: tuple[int, int, int, int]
    sensor_size: tuple[int, int]
    timings_s: dict[str, float]
    rays: int

    def report(self) -> str:
        t = self.timings_s
        parts = ", ".join(f"{k} {v:.1f} s" for k, v in t.items() if k != "total")
        return (f"simulated {len(self.files)} captures into {self.out_dir}\n"
                f"  sensor {self.sensor_size[1]}x{self.sensor_size[0]} px, {self.num_views} "
                f"views, reference frame {self.reference_bbox[2]}x{self.reference_bbox[3]} px, "
                f"{self.valid_pixels} valid pixels (>= 3 modulated views), {self.rays} rays\n"
                f"  time {t.get('total', 0.0):.1f} s ({parts})")


def _camera_name(sensitivity: str) -> str:
    """A camera sensitivity's name: itself for a reference-data name, a file's stem."""
    p = Path(sensitivity)
    return p.stem if p.suffix.lower() in (".csv", ".json") else sensitivity


def _capture_metadata(renderer: CaptureRenderer, pc: PlannedCapture, exposure: float) -> dict:
    s = renderer.sensor
    meta = {
        "kind": s.output,
        "black_level": float(s.black_level),
        "white_level": float(s.white),
        "exposure": float(exposure),
        "type": pc.type,
        "seed": pc.seed,
        "source": "hsi_torch virtual prototype",
        # the camera's identity, as RAW/EXIF metadata would give it: the sensitivity's name
        # (the file's stem for a CSV/JSON file), compared by reconstruction with the bundle's
        "camera_model": _camera_name(renderer.camera_sensitivity),
        **pc.entry,
    }
    if s.output == "bayer":
        meta["cfa_pattern"] = s.cfa_pattern
    return meta


def _render_all(
    renderer: CaptureRenderer, specs: list[CaptureSpec], planned: list[PlannedCapture], bar
) -> list[torch.Tensor | None]:
    """Every spec's noise-free image. When the mismatch changes the device after calibration
    (drift, filter temperature, scene illuminant), the scene captures (``type: scene``) are
    rendered in a second pass with those effects; scan, white, grid and dark frames are not."""
    if not renderer.mismatch.after_calibration:
        return renderer.render_captures(specs, bar)
    late = sorted({pc.render_key for pc in planned if pc.type == "scene"})
    early = [i for i in range(len(specs)) if i not in set(late)]
    irr: list[torch.Tensor | None] = [None] * len(specs)
    rays = 0
    for keys, after in ((early, False), (late, True)):
        if keys:
            imgs = renderer.render_captures([specs[i] for i in keys], bar, after_calibration=after)
            rays += renderer.num_rays
            for i, im in zip(keys, imgs, strict=True):
                irr[i] = im
    renderer.num_rays = rays  # both passes' rays
    return irr


def simulate_capture_set(
    cfg: SimulateConfig,
    out_dir: str | Path,
    *,
    device: str | None = None,
    progress: bool | None = None,
    log=print,
) -> SimulationSummary:
    """Render every capture of ``cfg`` with its ground truth into ``out_dir``."""
    t_all = time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    show = cfg.render.progress if progress is None else progress
    bar = functools.partial(progress_bar, leave=False) if progress_enabled(show) else None
    tm: dict[str, float] = {}

    t0 = time.perf_counter()
    renderer = build_renderer(cfg, device)
    specs, planned, scenes = plan_captures(cfg, renderer, log)
    tm["setup"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    irr = _render_all(renderer, specs, planned, bar)
    tm["trace+render"] = time.perf_counter() - t0

    # expose and write each capture, and free its irradiance after its last shot
    t0 = time.perf_counter()
    files: list[str] = []
    entries: list[dict[str, Any]] = []
    last_use = {pc.render_key: k for k, pc in enumerate(planned)}
    it = planned if bar is None else bar(planned, desc="sensor + write", unit="capture")
    first_scene = None
    h, w = renderer.sensor_size
    for k, pc in enumerate(it):
        exposure = renderer.exposure_of(pc.spec)
        img = irr[pc.render_key]
        if img is None:  # dark: no light
            img = torch.zeros(1 if renderer.mosaic_early else 3, h, w,
                              device=renderer.device, dtype=renderer.dtype)
        dn, sat = renderer.expose(img, exposure, pc.seed)
        del img
        if last_use[pc.render_key] == k:
            irr[pc.render_key] = None
        meta = _capture_metadata(renderer, pc, exposure)
        meta["saturated_pixels"] = int(sat.sum())
        write_capture(out / pc.file, dn, meta)
        files.append(pc.file)
        entries.append({"file": pc.file, "type": pc.type, "exposure": exposure,
                        "seed": pc.seed, "saturated_pixels": int(sat.sum()), **pc.entry})
        if pc.type == "scene" and first_scene is None:
            first_scene = (pc, dn)
    del irr
    tm["sensor+write"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    truth = renderer.ground_truth(bar)
    patch = brf_free_patch_mask(renderer)
    arrays: dict[str, Any] = {k: v for k, v in truth.items()}
    lay = renderer.layout
    layout_arrays = lay.to_dict(arrays=True)
    for k, v in layout_arrays.items():
        if k != "reflection_sequences":
            arrays[f"layout_{k}"] = np.asarray(v)
    arrays["view_homographies"] = lay.view_homographies
    arrays["opd_nm"] = lay.opd_nm
    arrays["mean_alpha"] = lay.mean_alpha
    arrays["mean_sigma"] = lay.mean_sigma
    arrays["reference_bbox"] = np.asarray(lay.reference_bbox)
    arrays["sensor_size"] = np.asarray(lay.sensor_size)
    arrays["brf_free_mask_sensor"] = patch
    scene_names = []
    for name, sc in scenes.items():
        if name.startswith("grid_"):
            c = renderer.diffuser_to_reference(sc.true_centres().to(renderer.device))
            arrays[f"{name}_centres_ref_px"] = c
            continue
        arrays[f"scene_{name}"] = renderer.scene_truth(sc)
        scene_names.append(name)
        if isinstance(sc, ColorCheckerScene):
            xy = renderer.reference_diffuser_points(1)[:, 0]
            x0, y0, w, h = lay.reference_bbox
            arrays[f"{name}_patch_index"] = sc.patch_index(xy).reshape(h, w).to(torch.int16)
            arrays[f"{name}_spectra"] = sc.patch_spectra(renderer.wavelengths)
    write_truth(out, arrays, _truth_json(cfg, renderer, truth, scene_names, arrays))
    renderer.release_scenes()  # the blurred scene rasters are no longer needed
    tm["truth"] = time.perf_counter() - t0

    s = renderer.sensor
    manifest = {
        "generator": "hsi-torch simulate",
        "sensor_size": list(renderer.sensor_size),
        "output": s.output,
        "cfa_pattern": s.cfa_pattern if s.output == "bayer" else None,
        "black_level": float(s.black_level),
        "white_level": float(s.white),
        "exposure": renderer.scene_exposure,
        "scan_exposure": renderer.scan_exposure,
        "wavelengths_nm": renderer.wavelengths.tolist(),
        "scan_fwhm_nm": renderer.scan_fwhm_nm,
        "scan_line": renderer.scan_line,
    }

    if cfg.render.figures:
        t0 = time.perf_counter()

        figs = figures.write_figures(out / "figures", renderer, truth, first_scene,
                                     {n: arrays[f"scene_{n}"] for n in scene_names})
        manifest["figures"] = [str(Path(f).relative_to(out)) for f in figs]
        tm["figures"] = time.perf_counter() - t0
    write_capture_set_index(out, captures=entries, nominal_layout=nominal_layout(renderer, patch),
                            brf_free_mask=patch, **manifest)  # manifest.json written last
    write_resolved_config(cfg, out)
    tm["total"] = time.perf_counter() - t_all
    return SimulationSummary(
        out_dir=out, files=files, num_views=lay.num_views,
        valid_pixels=int(truth["valid"].sum()), reference_bbox=lay.reference_bbox,
        sensor_size=renderer.sensor_size, timings_s=tm,
        rays=renderer.num_rays)


_TRUTH_DOC = {
    "wavelengths_nm": "(M,) reconstruction grid, nm",
    "band_widths_nm": "(M,) Δλ_m, nm",
    "B": "(V,M,h,w) float32 t·Tstack/Tstack_free averaged over the scan line at λ_m "
         "(what the monochromator-scan ratio to the reference BRF-free patch measures); 0 where "
         "the view is absent",
    "phi": "(3,M) float64 exposure-scaled l·f·τ_obj in DN per nm per unit reflectance "
           "(hat-averaged on the grid)",
    "gain": "(V,h,w) D(α_v(q))·V_obj(X(q)) (diffuser fall-off × objective vignetting)",
    "view_mask": "(V,h,w) bool: view v sees reference pixel q fully inside its triangle",
    "modulated": "(V,h,w) bool: view_mask and X(q) outside the BRF-free disk",
    "valid": "(h,w) bool: >= 3 modulated views",
    "alpha": "(V,h,w) incidence angle at the filter, rad (NaN where absent)",
    "sigma": "(V,h,w) azimuth at the filter, rad",
    "throughput": "(V,h,w) mirror throughput R^n",
    "diffuser_xy": "(h,w,2) diffuser point X(q) of each reference pixel, mm",
    "brf_free": "(h,w) bool: X(q) inside the BRF-free disk",
    "brf_free_mask_sensor": "(H,W) bool: usable BRF-free pixels (= brf_free_mask.png)",
    "view_homographies": "(V,3,3) sensor px of view v -> sensor px of view 0 (true)",
    "opd_nm": "(V,) mean OPD per view at 550 nm",
    "mean_alpha": "(V,) rad", "mean_sigma": "(V,) rad",
    "reference_bbox": "(4,) x0, y0, w, h", "sensor_size": "(2,) H, W",
    "layout_*": "ViewLayout.to_dict(arrays=True) arrays",
    "scene_<name>": "(M,h,w) float32 reflectance in the reference frame (pixel-footprint mean)",
    "<colorchecker>_patch_index": "(h,w) int16 patch under each reference pixel, -1 off-patch",
    "<colorchecker>_spectra": "(24,M) true patch reflectances",
    "grid_<k>_centres_ref_px": "(rows·cols,2) true circle centres in reference-frame px "
                               "(OpenCV order)",
}


def _truth_json(cfg, renderer: CaptureRenderer, truth, scene_names, arrays) -> dict[str, Any]:
    lay = renderer.layout
    return {
        "forward_model": "y[v,c,q] = gain[v,q] * sum_m B[v,m,q] * band_widths_nm[m] * phi[c,m] "
                         "* s[m,q]  (DN above black, reference frame = sensor crop "
                         "reference_bbox)",
        "arrays": {k: _TRUTH_DOC.get(k, "") for k in arrays},
        "shapes": {k: list(np.shape(v)) for k, v in arrays.items()},
        "layout": lay.to_dict(),
        "valid_pixels": int(truth["valid"].sum()),
        "kappa": renderer.kappa,
        "kappa_scan": renderer.kappa_scan,
        "dn_per_unit": renderer.dn_per_unit,
        "exposure": renderer.scene_exposure,
        "scan_exposure": renderer.scan_exposure,
        "polarizer_efficiency": renderer.polarizer_efficiency,
        "fine_wavelengths_nm": [float(renderer.fine[0]), float(renderer.fine[-1]),
                                float(renderer.fine_widths[0])],
        "scenes": scene_names,
        # the non-ideal effects that are on (docs/simulate.md); {} for the ideal device
        "mismatch": cfg.mismatch.active(),
        # the spectral coder (this_system, manakov, fujimoto; docs/simulate.md)
        "design": renderer.design.to_dict(),
        "config": json.loads(json.dumps(to_dict(cfg), default=str)),
        "supersample_offsets_px": subpixel_offsets(renderer.supersample).tolist(),
        # the command line, package version, git commit, torch / NumPy / Python versions
        "provenance": provenance(),
    }
