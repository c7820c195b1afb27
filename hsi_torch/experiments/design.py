"""BRF and taper design sweep: rank configurations by the conditioning of the sensing matrix
(docs/experiments.md, *BRF / taper design sweep*, gives the default sweep and its results).

For every kaleidoscope geometry (``a_out_mm`` × ``length_mm``) the sensor is traced once and the
rays that see :func:`~hsi_torch.experiments.systems.scene_points` in each of the ``V`` views give
``(α, σ, g_v)``. For every filter (material × thickness × tilt θ × azimuth) the ``3V × M`` matrix
``A[(v,c), m] = g_v B_v(λ_m) Δλ_m φ^c(λ_m)`` is formed at each point and its 2-norm condition
number computed (batched over tilts × azimuths × points); a design's score is the **worst** over
the points (``rank_by: median``: the median). Designs whose modulation period
``λ²/max|OPD| < min_period_nm`` at the shortest wavelength are flagged ``ok = False`` (the grid
would alias them) and ranked last.

The ``top_k`` feasible designs plus the default prototype are then scored by simulated PSNR
(:func:`hsi_torch.experiments.synthetic.evaluate_design`, σ = 1 DN, sensing matrix at the diffuser
centre); the best is written as the simulator config ``best_prototype.yaml``.

Command: ``hsi-torch experiment design --out DIR`` (the shipped ``design.yaml``).
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

from hsi_torch import refdata
from hsi_torch.config import option
from hsi_torch.experiments import report
from hsi_torch.experiments.metrics import (
    METRIC_FORMATS,
    METRIC_NAMES,
    metric_columns,
    metrics_note,
)
from hsi_torch.experiments.synthetic import GridSpec, default_betas, evaluate_design
from hsi_torch.experiments.systems import (
    brf_sensing_model,
    phi_matrix,
    scene_points,
    view_rays,
)
from hsi_torch.forward_model import SensingModel
from hsi_torch.io.atomic import atomic_write_json, atomic_write_text
from hsi_torch.optics import (
    DEFAULT_CAMERA,
    DEFAULT_GEOMETRY,
    BRFConfig,
    KaleidoscopeGeometry,
    build_view_layout,
    get_material,
    polarizer_transmittance,
    trace_sensor,
    uniaxial_opd,
)
from hsi_torch.spectral import SpectralGrid

__all__ = [
    "PSNRSpec",
    "DesignSweepConfig",
    "GeometryRays",
    "geometry_rays",
    "condition_sweep",
    "rank_designs",
    "run_design",
]


@dataclass
class PSNRSpec:
    """Simulated-PSNR stage of the design sweep (synthetic protocol at one noise level)."""

    noise_sigma: float = option(1.0, "σ (DN)")
    num_seeds: int = 5
    seed: int = 0
    betas: list[float] | None = option(None, "None = [0] + logspace(-2, 6, 17)")
    reflectances: str = "ColorChecker N Ohta"
    peak_dn: float = 255.0
    diff_order: int = 1


def _default_materials() -> dict[str, list[float]]:
    return {
        "quartz": [0.5, 1.0, 1.5, 2.0, 2.5, 3.0],
        "calcite": [0.05, 0.1, 0.15, 0.2],
        "polymer": [0.5, 1.0, 1.5],
    }


@dataclass
class DesignSweepConfig:
    """Configuration of ``hsi-torch experiment design``."""

    materials: dict[str, list[float]] = option(text="material -> plate thicknesses (mm); "
                                               "'quartz', 'calcite', 'polymer'",
                                               factory=_default_materials)
    tilts_deg: list[float] = field(default_factory=lambda: [float(v) for v in range(0, 90, 5)],
                                   metadata={"help": "optic-axis tilt out of the plate (deg)"})
    azimuths_deg: list[float] = option(text="projected optic-axis azimuth (deg); the tube is "
                                       "3-fold symmetric",
                                       factory=lambda: [float(v) for v in range(0, 120, 10)])
    a_out_mm: list[float] = option(text="kaleidoscope exit side (taper; a_in from the default "
                                        "geometry)", factory=lambda: [16.0, 22.0, 28.0, 34.0, 40.0])
    length_mm: list[float] = option(text="kaleidoscope tube lengths", factory=lambda: [160.0])
    geometry: dict[str, Any] = option(text="other KaleidoscopeGeometry overrides", factory=dict)
    camera: str = option(refdata.DEFAULT_CAMERA, "camera for φ")
    illuminant: str = "D65"
    wavelengths: GridSpec = field(default_factory=GridSpec)
    min_period_nm: float = option(30.0, "min modulation period λ²/|OPD| at the first band")
    rank_by: Literal["worst", "median"] = option("worst", "condition number over the 7 scene "
                                                          "points")
    top_k: int = option(8, "designs scored by simulated PSNR")
    psnr: PSNRSpec = field(default_factory=PSNRSpec)
    progress: bool = True

    def __post_init__(self) -> None:
        for key in ("tilts_deg", "azimuths_deg", "a_out_mm", "length_mm"):
            if not getattr(self, key):
                raise ValueError(f"{key} must not be empty")
        if not self.materials or any(not v for v in self.materials.values()):
            raise ValueError("materials must map each material to a non-empty thickness list")
        if any(t <= 0 for v in self.materials.values() for t in v):
            raise ValueError("thicknesses must be > 0 mm")
        if self.top_k < 0:
            raise ValueError(f"top_k must be >= 0, got {self.top_k}")


# --- condition numbers


@dataclass
class GeometryRays:
    """Rays of one kaleidoscope geometry at the scene points.

    Attributes:
        geometry: the :class:`~hsi_torch.optics.KaleidoscopeGeometry`.
        alpha, sigma, throughput: ``(P, V)`` (rad, rad, g_v = R^n).
        points_mm: ``(P, 2)``; ref_view_px: pixels of the reference view on the sensor.
        error: why the geometry is unusable (a point not seen by every view), else None.
    """

    geometry: Any
    alpha: Tensor | None
    sigma: Tensor | None
    throughput: Tensor | None
    points_mm: Tensor
    ref_view_px: int
    num_views: int
    error: str | None = None


def geometry_rays(geometry: Any, camera: Any | None = None) -> GeometryRays:
    """Trace ``geometry`` and return the rays seeing the 7 scene points in every view."""
    cam = camera or DEFAULT_CAMERA
    pts = scene_points(geometry)
    trace = trace_sensor(geometry, cam, dtype=torch.float64)
    layout = build_view_layout(geometry, cam, trace=trace)
    ref_px = int(layout.pixel_count[0])
    try:
        a, s, t = view_rays(geometry, cam, layout, pts)
    except ValueError as exc:
        return GeometryRays(geometry, None, None, None, pts, ref_px, layout.num_views, str(exc))
    return GeometryRays(geometry, a, s, t, pts, ref_px, layout.num_views)


def condition_sweep(
    rays: GeometryRays,
    material: str,
    thickness_mm: float,
    tilts_deg: list[float],
    azimuths_deg: list[float],
    grid: SpectralGrid,
    phi: Tensor,
    *,
    psi_deg: float = 45.0,
    chi_deg: float = 90.0,
) -> tuple[Tensor, Tensor]:
    """Condition numbers of all tilts × azimuths for one plate, batched.

    Returns:
        ``cond (T, A, P)`` (2-norm condition number of the ``(3V, M)`` matrix at each scene
        point) and ``max_opd_nm (T, A)`` (largest |OPD| over points and views at the first
        wavelength of ``grid``).
    """
    alpha, sigma, thr = rays.alpha, rays.sigma, rays.throughput
    dev, dt = alpha.device, alpha.dtype
    wl = grid.wavelengths(device=dev, dtype=dt)
    dl = grid.band_widths(device=dev, dtype=dt)
    n_o, n_e = get_material(material).indices(wl)
    tilt = torch.deg2rad(torch.as_tensor(tilts_deg, device=dev, dtype=dt)).view(-1, 1, 1, 1, 1)
    az = torch.deg2rad(torch.as_tensor(azimuths_deg, device=dev, dtype=dt)).view(1, -1, 1, 1, 1)
    delta = sigma[None, None, :, :, None] - az
    opd = uniaxial_opd(n_o, n_e, alpha[None, None, :, :, None], delta, tilt, thickness_mm)
    t = polarizer_transmittance(opd, wl, math.radians(psi_deg), math.radians(chi_deg))
    lead, (V, M) = t.shape[:3], t.shape[3:]  # t: (T, A, P, V, M)
    model = SensingModel(t.reshape(-1, V, M), thr.to(t).expand(*lead, V).reshape(-1, V),
                         dl * phi.to(t))  # fmt: skip
    a = model.dense().reshape(*lead, 3 * V, M)
    cond = torch.linalg.cond(a)
    cond = torch.where(torch.isfinite(cond), cond, torch.full_like(cond, math.inf))
    max_opd = opd[..., 0].abs().amax((-1, -2))
    return cond, max_opd


def rank_designs(rows: list[dict[str, Any]], rank_by: str = "worst") -> list[dict[str, Any]]:
    """Sort sweep rows: feasible (``ok``) first, then by ``cond_worst`` (or ``cond_median``)
    ascending; sets ``rank_cond`` (1 = best) on every row and returns the sorted list."""
    key = {"worst": "cond_worst", "median": "cond_median"}.get(rank_by)
    if key is None:
        raise ValueError(f"rank_by must be 'worst' or 'median', got {rank_by!r}")
    out = sorted(rows, key=lambda r: (not r["ok"], r[key], r["cond_median"]))
    for i, r in enumerate(out):
        r["rank_cond"] = i + 1
    return out


# --- the command


def _brf_of(r: dict[str, Any]) -> Any:
    return BRFConfig(material=r["material"], thickness_mm=r["thickness_mm"],
                     axis_tilt_deg=r["axis_tilt_deg"], axis_azimuth_deg=r["axis_azimuth_deg"])


def _cond_row(common: dict[str, Any], tilt: float, azimuth: float, cond: Tensor, max_opd: Tensor,
              max_opd_allowed: float, ref_view_px: int) -> dict[str, Any]:
    """One design's row: ``cond`` its condition numbers at the scene points (centre first)."""
    return {**common, "axis_tilt_deg": tilt, "axis_azimuth_deg": azimuth,
            "cond_worst": float(cond.max()), "cond_median": float(cond.median()),
            "cond_centre": float(cond[0]), "max_opd_nm": float(max_opd),
            "ok": bool(max_opd <= max_opd_allowed), "ref_view_px": ref_view_px}


def _plot(out: Path, rows: list[dict[str, Any]], best: dict[str, Any], cfg: DesignSweepConfig,
          key: str) -> None:
    # the axes of the rows themselves: the default plate's extra row may lie outside the sweep
    tilts = sorted({r["axis_tilt_deg"] for r in rows})
    azs = sorted({r["axis_azimuth_deg"] for r in rows})
    sel = {(r["axis_tilt_deg"], r["axis_azimuth_deg"]): r for r in rows
           if (r["a_out_mm"], r["length_mm"], r["material"], r["thickness_mm"])
           == (best["a_out_mm"], best["length_mm"], best["material"], best["thickness_mm"])}
    heat = np.array([[math.log10(sel[(t, a)][key]) if (t, a) in sel and sel[(t, a)]["ok"]
                      else np.nan for a in azs] for t in tilts])
    ths = sorted({r["thickness_mm"] for r in rows if r["material"] == best["material"]})
    heat2 = np.full((len(tilts), len(ths)), np.nan)
    for r in rows:
        if (r["a_out_mm"], r["length_mm"], r["material"]) == (
                best["a_out_mm"], best["length_mm"], best["material"]) and r["ok"]:
            i, j = tilts.index(r["axis_tilt_deg"]), ths.index(r["thickness_mm"])
            v = math.log10(r[key])
            heat2[i, j] = v if np.isnan(heat2[i, j]) else min(heat2[i, j], v)
    fig, axes = report.new_figure(1, 3, figsize=(16, 4.6))
    ext = [azs[0] - 5, azs[-1] + 5, tilts[-1] + 2.5, tilts[0] - 2.5]
    im = axes[0].imshow(heat, aspect="auto", extent=ext, cmap="viridis_r")
    axes[0].plot(best["axis_azimuth_deg"], best["axis_tilt_deg"], "r*", ms=12)
    axes[0].set_xlabel("optic-axis azimuth (deg)")
    axes[0].set_ylabel("optic-axis tilt θ (deg)")
    axes[0].set_title(f"log10 cond ({cfg.rank_by}) — {best['material']} "
                      f"{best['thickness_mm']:g} mm, a_out {best['a_out_mm']:g} mm "
                      "(white: OPD too large)",
                      fontsize=9)
    fig.colorbar(im, ax=axes[0])
    im2 = axes[1].imshow(heat2, aspect="auto", cmap="viridis_r",
                         extent=[-0.5, len(ths) - 0.5, tilts[-1] + 2.5, tilts[0] - 2.5])
    axes[1].set_xticks(range(len(ths)), [f"{t:g}" for t in ths])
    axes[1].set_xlabel(f"{best['material']} thickness (mm)")
    axes[1].set_ylabel("optic-axis tilt θ (deg)")
    axes[1].set_title("log10 cond, best azimuth (feasible designs only)", fontsize=9)
    axes[1].plot(ths.index(best["thickness_mm"]), best["axis_tilt_deg"], "r*", ms=12)
    fig.colorbar(im2, ax=axes[1])
    for mat in cfg.materials:
        xs, ys = [], []
        for a_out in sorted(cfg.a_out_mm):
            c = [r[key] for r in rows if r["ok"] and r["material"] == mat
                 and r["a_out_mm"] == a_out and r["length_mm"] == best["length_mm"]]
            if c:
                xs.append(a_out)
                ys.append(min(c))
        axes[2].semilogy(xs, ys, "o-", label=mat)
    axes[2].set_xlabel(f"exit side a_out (mm), a_in = {best['a_in_mm']:g} mm, "
                       f"L = {best['length_mm']:g} mm")
    axes[2].set_ylabel(f"best cond ({cfg.rank_by})")
    axes[2].set_title("taper: best feasible design per material", fontsize=9)
    axes[2].grid(alpha=0.3)
    axes[2].legend(fontsize=8)
    report.save_figure(fig, out / "condition_heatmap.png")


def run_design(
    cfg: DesignSweepConfig, out: str | Path, *, device: str | None = None
) -> dict[str, Any]:
    """Run the sweep; writes ``ranking.csv``, ``ranking.md``, ``condition_heatmap.png``,
    ``best_prototype.yaml`` and ``summary.json`` to ``out``. Returns the summary dict.

    The sweep runs on the CPU in float64 (condition numbers up to ~1e14 need it); ``device`` is
    accepted for the CLI and used for the PSNR stage.
    """
    import yaml


    t0 = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    grid = cfg.wavelengths.grid()
    phi = phi_matrix(cfg.camera, cfg.illuminant, grid)
    base = dict(DEFAULT_GEOMETRY.to_dict())
    base.update(cfg.geometry)
    lam0 = float(grid.wavelengths_nm[0])
    max_opd_allowed = lam0**2 / cfg.min_period_nm
    key = "cond_worst" if cfg.rank_by == "worst" else "cond_median"
    default_brf = BRFConfig()

    geoms = [(a, L) for L in cfg.length_mm for a in cfg.a_out_mm]
    if (DEFAULT_GEOMETRY.a_out_mm, DEFAULT_GEOMETRY.length_mm) not in geoms and not cfg.geometry:
        geoms.append((DEFAULT_GEOMETRY.a_out_mm, DEFAULT_GEOMETRY.length_mm))
    rows: list[dict[str, Any]] = []
    skipped: list[dict[str, Any]] = []
    rays_of: dict[tuple[float, float], GeometryRays] = {}
    jobs = [(g, m, th) for g in geoms for m, ths in cfg.materials.items() for th in ths]
    for (a_out, length), mat, th in report.progress(jobs, desc="design: cond sweep",
                                                    enable=cfg.progress):
        if (a_out, length) not in rays_of:
            geom = KaleidoscopeGeometry.from_dict({**base, "a_out_mm": a_out, "length_mm": length})
            rays_of[(a_out, length)] = geometry_rays(geom)
            if rays_of[(a_out, length)].error:
                skipped.append({"a_out_mm": a_out, "length_mm": length,
                                "reason": rays_of[(a_out, length)].error})
        rays = rays_of[(a_out, length)]
        if rays.error:
            continue
        tilts, azs = list(cfg.tilts_deg), list(cfg.azimuths_deg)
        extra = (mat == default_brf.material and th == default_brf.thickness_mm
                 and (default_brf.axis_tilt_deg not in tilts
                      or default_brf.axis_azimuth_deg not in azs))
        cond, max_opd = condition_sweep(rays, mat, th, tilts, azs, grid, phi)
        common = {"a_in_mm": base["a_in_mm"], "a_out_mm": a_out, "length_mm": length,
                  "material": mat, "thickness_mm": th}
        for i, t in enumerate(tilts):
            for j, az in enumerate(azs):
                rows.append(_cond_row(common, t, az, cond[i, j], max_opd[i, j], max_opd_allowed,
                                      rays.ref_view_px))
        if extra:
            t, az = default_brf.axis_tilt_deg, default_brf.axis_azimuth_deg
            c1, m1 = condition_sweep(rays, mat, th, [t], [az], grid, phi)
            rows.append(_cond_row(common, t, az, c1[0, 0], m1[0, 0], max_opd_allowed,
                                  rays.ref_view_px))
    if not rows:
        raise ValueError(f"design sweep: no usable geometry ({skipped})")
    t_cond = time.perf_counter() - t0

    def_key = (DEFAULT_GEOMETRY.a_out_mm, DEFAULT_GEOMETRY.length_mm, default_brf.material,
               default_brf.thickness_mm, default_brf.axis_tilt_deg, default_brf.axis_azimuth_deg)
    keys = ("a_out_mm", "length_mm", "material", "thickness_mm", "axis_tilt_deg",
            "axis_azimuth_deg")
    for r in rows:
        r["is_default"] = tuple(r[k] for k in keys) == def_key and not cfg.geometry
    ranked = rank_designs(rows, cfg.rank_by)

    # simulated PSNR of the top-K (+ the default prototype)
    ps = cfg.psnr
    refl, _ = refdata.reflectance_set(ps.reflectances, grid, dtype=torch.float64)
    dev = torch.device(device or "cpu")
    seeds = list(range(ps.seed, ps.seed + ps.num_seeds))
    betas = default_betas() if ps.betas is None else list(ps.betas)
    cand = [r for r in ranked if r["ok"]][: cfg.top_k]
    cand += [r for r in ranked if r["is_default"] and r not in cand]
    for r in report.progress(cand, desc="design: PSNR of top-K", enable=cfg.progress):
        rays = rays_of[(r["a_out_mm"], r["length_mm"])]
        a = brf_sensing_model(_brf_of(r), rays.alpha[:1], rays.sigma[:1],
                              rays.throughput[:1], grid, phi).dense()[0]
        ev = evaluate_design(a.to(dev), refl.to(dev), [ps.noise_sigma], seeds, betas,
                             peak_dn=ps.peak_dn, diff_order=ps.diff_order)
        row = ev.summary_rows()[0]
        r["psnr_db"], r["psnr_std_db"] = row["psnr_db"], row["psnr_std_db"]
        r["best_beta"], r["sam_deg"] = row["best_beta"], row["sam_deg"]
        for k in METRIC_NAMES:  # the field's metrics at the best β (SSIM n/a: no spatial layout)
            r[k] = row[k]
    scored = sorted(cand, key=lambda r: -r["psnr_db"])
    for i, r in enumerate(scored):
        r["rank_psnr"] = i + 1
    best = scored[0] if scored else ranked[0]
    default_row = next((r for r in ranked if r["is_default"]), None)

    cols = ["rank_cond", "rank_psnr", "is_default", "ok", "material", "thickness_mm",
            "axis_tilt_deg", "axis_azimuth_deg", "a_in_mm", "a_out_mm", "length_mm",
            "cond_worst", "cond_median", "cond_centre", "max_opd_nm", "ref_view_px", "psnr_db",
            "psnr_std_db", "best_beta", "sam_deg", "psnr_bands_db", "ssim", "ergas", "rmse",
            "mrae"]
    report.write_csv(out / "ranking.csv", ranked, cols)

    fmt = {"cond_worst": ".3g", "cond_median": ".3g", "cond_centre": ".3g",
           "max_opd_nm": ".0f", "psnr_db": ".2f", "psnr_std_db": ".2f", "best_beta": ".3g",
           "sam_deg": ".2f", "thickness_mm": "g", "axis_tilt_deg": "g",
           "axis_azimuth_deg": "g", "a_out_mm": "g", "length_mm": "g",
           **{k: v for k, v in METRIC_FORMATS.items() if k not in ("psnr_db", "sam_deg")}}
    show = {"rank_cond": "rank (cond)", "material": "material", "thickness_mm": "L (mm)",
            "axis_tilt_deg": "tilt (°)", "axis_azimuth_deg": "azimuth (°)",
            "a_out_mm": "a_out (mm)", "length_mm": "tube (mm)", "cond_worst": "cond worst",
            "cond_median": "cond median", "max_opd_nm": f"max OPD@{lam0:g} (nm)",
            "ref_view_px": "ref. view px"}
    show_psnr = {"rank_psnr": "rank (PSNR)", **show, "psnr_db": "PSNR σ=1 (dB)",
                 "psnr_std_db": "± (dB)", "best_beta": "best β",
                 **{k: h for k, h in metric_columns().items() if k != "psnr_db"}}
    n_ok = sum(r["ok"] for r in rows)
    md = [
        "# BRF / taper design sweep\n",
        f"{len(rows)} designs ({n_ok} with modulation period ≥ {cfg.min_period_nm:g} nm at "
        f"{lam0:g} nm), {len(geoms) - len(skipped)} kaleidoscope geometries; condition number of "
        f"the stacked {3 * 10}×{grid.num_bands} sensing matrix at 7 scene points, ranked by the "
        f"{cfg.rank_by} over the points. φ = {cfg.illuminant} × {cfg.camera}.\n",
        "## Top 15 by condition number\n",
        report.markdown_table(ranked[:15], show, fmt, bold=lambda r: r["is_default"]),
        f"\n## Simulated PSNR (σ = {ps.noise_sigma:g} DN, {len(seeds)} seeds, best β, "
        "diffuser centre) of the top designs and the default (bold)\n",
        metrics_note({"ssim": "the patches are spectra without a spatial layout"})
        + " Each seed's patches are scored as one 1 × K image, mean over seeds.\n",
        report.markdown_table(scored, show_psnr, fmt, bold=lambda r: r["is_default"]),
    ]
    if skipped:
        md.append("\nGeometries skipped: " + "; ".join(
            f"a_out {s['a_out_mm']:g} mm, L {s['length_mm']:g} mm ({s['reason']})"
            for s in skipped))
    report.write_markdown(out / "ranking.md", "\n".join(md))
    _plot(out, rows, best, cfg, key)

    geom_best = KaleidoscopeGeometry.from_dict(
        {**base, "a_out_mm": best["a_out_mm"], "length_mm": best["length_mm"]})
    doc = {"geometry": geom_best.to_dict(), "brf": _brf_of(best).to_dict(),
           "illuminant": cfg.illuminant, "camera_sensitivity": cfg.camera}
    header = (
        "best prototype of the design sweep (hsi-torch experiment design)\n"
        f"cond worst/median over 7 points: {best['cond_worst']:.4g} / {best['cond_median']:.4g}; "
        f"simulated PSNR at σ = {ps.noise_sigma:g} DN: {best.get('psnr_db', float('nan')):.2f} dB"
    )
    text = "".join(f"# {ln}\n" for ln in header.splitlines())
    text += yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=100)
    atomic_write_text(out / "best_prototype.yaml", text)

    summary = {
        "num_designs": len(rows),
        "num_feasible": n_ok,
        "rank_by": cfg.rank_by,
        "best": best,
        "default": default_row,
        "best_is_default": bool(best.get("is_default")),
        "top_by_cond": ranked[:10],
        "by_psnr": scored,
        "skipped_geometries": skipped,
        "elapsed_cond_s": t_cond,
        "elapsed_s": time.perf_counter() - t0,
    }
    atomic_write_json(out / "summary.json", summary)
    return summary
