"""Synthetic comparison of sensing designs under one reconstruction model.

Protocol, for every design (a ``(O, M)`` matrix ``A``, see :mod:`hsi_torch.experiments.systems`):

1. **Spectra**: ``K`` reflectances ``R (K, M)`` on the grid (default: the 24 ColorChecker N Ohta
   patches of colour-science).
2. **Exposure matching**: ``A`` is scaled by ``peak_dn / max_{k,o} (R Aᵀ)_{k,o}``, so the largest
   noise-free observation over all patches and channels is ``peak_dn`` (255 DN).
3. **Noise**: for seed ``s`` a standard normal ``ε_s (K, O)`` is drawn from
   ``torch.Generator("cpu").manual_seed(s)`` (``torch.randn``, float64); the observation at noise
   level σ is ``y = R Aᵀ + σ ε_s`` (the same ε_s for every σ: common random numbers).
4. **Reconstruction**: ``x = argmin_{x≥0} ||A x − y||² + β ||D x||²`` (first difference by
   default) with :func:`hsi_torch.recon.nnls.solve_nnls`, for every β of
   ``{0} ∪ logspace(−2, 6, 17)``. All patches × seeds × σ × β are *one* batch per design: β
   enters through the stacked matrix ``[A; √β D]`` with observations ``[y; 0]``.
5. **Scores**: PSNR = 10·log10(1/MSE) on reflectance over all patches and bands, per seed
   (:func:`hsi_torch.experiments.metrics.psnr`), and the spectral angle
   (:func:`~hsi_torch.experiments.metrics.spectral_angle_deg`, mean over patches). Per design and
   σ the best β maximises the PSNR averaged over seeds; the table reports that mean, its standard
   deviation over seeds and the mean spectral angle at that β, and, at that β, the field's other
   metrics (:func:`hsi_torch.metrics.cube_metrics` of each seed's ``K`` patches as a ``1 × K``
   image, mean over seeds): PSNR per band on 0–255 averaged over bands, ERGAS, RMSE, MRAE.
   SSIM does not apply (the patches are spectra without a spatial layout): ``n/a``.

Command: ``hsi-torch experiment synthetic --out DIR`` (the shipped ``synthetic.yaml``).
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
    NOT_APPLICABLE,
    cube_metrics,
    metric_columns,
    metrics_note,
    psnr,
    spectral_angle_deg,
)
from hsi_torch.experiments.systems import (
    DEFAULT_3CAMERA,
    DEFAULT_FACED_BOUNCES,
    DEFAULT_FACED_FILTER,
    SensingDesign,
    bundle_design,
    csv_design,
    faced_reflectors_design,
    fujimoto_design,
    manakov_design,
    this_system_design,
    three_camera_design,
)
from hsi_torch.io.atomic import atomic_write_json
from hsi_torch.recon.nnls import solve_nnls
from hsi_torch.spectral import SpectralGrid, difference_matrix

__all__ = [
    "GridSpec",
    "DesignSpec",
    "SyntheticConfig",
    "DesignEvaluation",
    "default_betas",
    "peak_matching_gain",
    "noise_realisation",
    "evaluate_design",
    "build_design",
    "run_synthetic",
]


def default_betas() -> list[float]:
    """``[0] + logspace(−2, 6, 17)``: the β sweep of the protocol."""
    return [0.0] + [float(v) for v in np.logspace(-2, 6, 17)]


# --- configuration


@dataclass
class GridSpec:
    """Uniform wavelength grid ``start_nm, start_nm + step_nm, …, stop_nm`` (nm)."""

    start_nm: float = 430.0
    stop_nm: float = 670.0
    step_nm: float = 10.0

    def grid(self) -> SpectralGrid:
        return SpectralGrid.uniform(self.start_nm, self.stop_nm, self.step_nm)


@dataclass
class DesignSpec:
    """One sensing design of the comparison.

    ``kind``: ``this_system`` (simulator default optics, overridable by ``geometry``/``brf``
    fields), ``bundle`` (calibration bundle at ``path``), ``three_camera`` (``cameras``),
    ``faced_reflectors`` (``filter``, ``bounces``, ``camera``), ``csv`` (channel responses at
    ``path``), ``manakov`` (one filter per view, ``design`` overrides) or ``fujimoto`` (a
    birefringent thin section, ``design`` and ``brf`` overrides).
    """

    kind: Literal["this_system", "bundle", "three_camera", "faced_reflectors", "csv", "manakov",
                  "fujimoto"]
    name: str | None = option(None, "label (default from the kind)")
    camera: str = option(refdata.DEFAULT_CAMERA, "camera sensitivities (name, CSV or JSON) for "
                                                 "this_system/faced")
    cameras: list[str] = field(
        default_factory=lambda: list(DEFAULT_3CAMERA),
        metadata={"help": "three_camera: camera names or CSV/JSON files"},
    )
    filter: str = option(DEFAULT_FACED_FILTER, "faced_reflectors: Lee code or CSV")
    bounces: int = option(DEFAULT_FACED_BOUNCES, "faced: N (i = 0…N)")
    path: Path | None = option(None, "bundle .npz or design CSV")
    pixel: list[int] | None = option(None, "bundle: [row, col] reference-frame pixel; None = mean")
    scene_point: str = option("centre", "this_system: 'centre' or 'mean' (of 7 points)")
    scene_point_mm: list[float] | None = option(None, "this_system: (X, Y) diffuser point in mm "
                                                      "(overrides)")
    includes_illuminant: bool = option(False, "csv: responses already include the illuminant")
    geometry: dict[str, Any] = option(text="this_system: KaleidoscopeGeometry overrides",
                                      factory=dict)
    brf: dict[str, Any] = option(text="this_system/fujimoto: BRFConfig overrides", factory=dict)
    design: dict[str, Any] = option(text="manakov/fujimoto: PrototypeDesign overrides (filters, "
                                         "grains)", factory=dict)

    def __post_init__(self) -> None:
        if self.kind in ("bundle", "csv") and self.path is None:
            raise ValueError(f"kind {self.kind!r} needs 'path'")
        if self.bounces < 0:
            raise ValueError(f"bounces must be >= 0, got {self.bounces}")
        if self.scene_point not in ("centre", "center", "mean"):
            raise ValueError(f"scene_point must be 'centre' or 'mean', got {self.scene_point!r}")


def _default_designs() -> list[DesignSpec]:
    return [
        DesignSpec(kind="this_system"),
        DesignSpec(kind="three_camera"),
        DesignSpec(kind="faced_reflectors"),
    ]


@dataclass
class SyntheticConfig:
    """Configuration of ``hsi-torch experiment synthetic``."""

    wavelengths: GridSpec = field(default_factory=GridSpec)
    illuminant: str = option("D65", "CIE name or CSV, for every design")
    reflectances: str = option("ColorChecker N Ohta", "ColorChecker name, '190 patches' or a CSV "
                                                      "wavelength,r1..rK")
    noise_sigmas: list[float] = option(text="Gaussian noise σ (DN)",
                                       factory=lambda: [0.5, 1.0, 2.0, 4.0])
    num_seeds: int = option(5, "noise realisations per σ")
    seed: int = option(0, "first seed (seeds are seed … seed+n−1)")
    betas: list[float] | None = option(None, "β sweep; None = [0] + logspace(-2, 6, 17)")
    peak_dn: float = option(255.0, "exposure matching target (DN)")
    diff_order: int = option(1, "smoothness operator order (1 or 2)")
    dtype: Literal["float32", "float64"] = "float64"
    device: str | None = option(None, "torch device (None = cpu)")
    reference: str = option("3Camera", "design the margins are measured against")
    spectra_patches: list[int] = field(
        default_factory=lambda: [0, 2, 7, 11, 13, 15],
        metadata={"help": "patches drawn in spectra.png"},
    )
    spectra_sigma: float = option(1.0, "σ of spectra.png")
    progress: bool = True
    designs: list[DesignSpec] = field(default_factory=_default_designs)

    def __post_init__(self) -> None:
        if self.num_seeds < 1:
            raise ValueError(f"num_seeds must be >= 1, got {self.num_seeds}")
        if not self.noise_sigmas or any(s < 0 for s in self.noise_sigmas):
            raise ValueError(f"noise_sigmas must be non-empty and >= 0, got {self.noise_sigmas}")
        if self.betas is not None and (not self.betas or any(b < 0 for b in self.betas)):
            raise ValueError(f"betas must be non-empty and >= 0, got {self.betas}")
        if not self.peak_dn > 0:
            raise ValueError(f"peak_dn must be > 0, got {self.peak_dn}")
        if self.diff_order not in (0, 1, 2):
            raise ValueError(f"diff_order must be 0, 1 or 2, got {self.diff_order}")
        if not self.designs:
            raise ValueError("designs must list at least one design")


_DEFAULT_NAMES = {
    "this_system": "this system",
    "bundle": "this system (bundle)",
    "three_camera": "3Camera",
    "faced_reflectors": "Faced Reflectors",
    "manakov": "Manakov",
    "fujimoto": "Fujimoto",
}


def build_design(
    spec: DesignSpec,
    grid: SpectralGrid,
    illuminant: str = "D65",
    *,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float64,
) -> SensingDesign:
    """The :class:`SensingDesign` described by ``spec`` (responses include ``illuminant``)."""
    kw: dict[str, Any] = dict(device=device, dtype=dtype)
    name = spec.name or _DEFAULT_NAMES.get(spec.kind)
    if spec.kind == "this_system":
        point = spec.scene_point_mm if spec.scene_point_mm is not None else spec.scene_point
        return this_system_design(
            grid, geometry=spec.geometry or None, brf=spec.brf or None, camera=spec.camera,
            illuminant=illuminant, scene_point=point, name=name, **kw,
        )  # fmt: skip
    if spec.kind == "bundle":
        return bundle_design(spec.path, grid, pixel=spec.pixel, name=name, **kw)
    if spec.kind == "three_camera":
        return three_camera_design(spec.cameras, grid, illuminant=illuminant, name=name, **kw)
    if spec.kind == "faced_reflectors":
        return faced_reflectors_design(
            spec.filter, spec.bounces, grid, camera=spec.camera, illuminant=illuminant,
            name=name, **kw,
        )  # fmt: skip
    if spec.kind in ("manakov", "fujimoto"):
        point = spec.scene_point_mm if spec.scene_point_mm is not None else spec.scene_point
        if point == "mean":
            raise ValueError(f"design {name!r}: scene_point 'mean' is not defined for kind "
                             f"{spec.kind!r} (use 'centre' or scene_point_mm)")
        extra = {"brf": spec.brf or None} if spec.kind == "fujimoto" else {}
        build = manakov_design if spec.kind == "manakov" else fujimoto_design
        return build(grid, design=spec.design or None, geometry=spec.geometry or None,
                     camera=spec.camera, illuminant=illuminant, scene_point=point, name=name,
                     **extra, **kw)
    if spec.kind == "csv":
        return csv_design(
            spec.path, grid, illuminant=illuminant, includes_illuminant=spec.includes_illuminant,
            name=name, **kw,
        )  # fmt: skip
    raise ValueError(f"unknown design kind {spec.kind!r}")


# --- the experiment's machinery


def peak_matching_gain(matrix: Tensor, reflectances: Tensor, peak_dn: float = 255.0) -> Tensor:
    """Scalar factor so that ``max(reflectances @ (factor·matrix)ᵀ) = peak_dn``.

    Args:
        matrix: ``(O, M)``; reflectances: ``(K, M)``.
    """
    top = (reflectances.to(matrix) @ matrix.T).max()
    if not bool(top > 0):
        raise ValueError("exposure matching: the design observes nothing (max observation <= 0)")
    return peak_dn / top


def noise_realisation(
    num_patches: int,
    num_channels: int,
    seed: int,
    *,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float64,
) -> Tensor:
    """``(K, O)`` standard normal noise of seed ``seed`` (drawn on the CPU in float64 with
    ``torch.Generator().manual_seed(seed)``, so every device/dtype sees the same numbers)."""
    g = torch.Generator(device="cpu").manual_seed(int(seed))
    eps = torch.randn((num_patches, num_channels), generator=g, dtype=torch.float64)
    return eps.to(device=device, dtype=dtype)


@dataclass
class DesignEvaluation:
    """Scores of one design over σ × seeds × β.

    Attributes:
        name: design name; scale: exposure-matching factor applied to its matrix.
        sigmas ``(S,)``, seeds ``(N,)``, betas ``(B,)``: the sweep.
        psnr_db: ``(S, N, B)`` PSNR over all patches and bands per seed.
        sam_deg: ``(S, N, B)`` mean spectral angle over patches.
        best_index: ``(S,)`` index of the best β (max of the seed-mean PSNR).
        estimates: ``(S, N, K, M)`` reconstructions at the best β (None unless requested).
        converged: fraction of the ``S·N·B·K`` problems whose solver reported convergence.
        metrics: at the best β, ``{key: (S, N)}`` of :func:`hsi_torch.metrics.cube_metrics` of
            each seed's patches as a ``(M, 1, K)`` cube (``ssim`` NaN: no spatial layout).
    """

    name: str
    scale: float
    sigmas: list[float]
    seeds: list[int]
    betas: list[float]
    psnr_db: Tensor
    sam_deg: Tensor
    best_index: Tensor
    estimates: Tensor | None
    converged: float
    metrics: dict[str, Tensor] = field(default_factory=dict)

    def summary_rows(self) -> list[dict[str, Any]]:
        """One row per σ: ``method, noise_sigma, best_beta, psnr_db, psnr_std_db, sam_deg, …``."""
        rows = []
        n = len(self.seeds)
        for i, s in enumerate(self.sigmas):
            b = int(self.best_index[i])
            p = self.psnr_db[i, :, b]
            a = self.sam_deg[i, :, b]
            rows.append({
                "method": self.name,
                "noise_sigma": float(s),
                "best_beta": float(self.betas[b]),
                "psnr_db": float(p.mean()),
                "psnr_std_db": float(p.std()) if n > 1 else 0.0,
                "sam_deg": float(a.mean()),
                "sam_std_deg": float(a.std()) if n > 1 else 0.0,
                "num_seeds": n,
            })  # fmt: skip
            for k in METRIC_NAMES:  # the field's other metrics at the best β, mean over seeds
                if k in ("psnr_db", "sam_deg"):
                    continue
                if k == "ssim":
                    rows[-1][k] = NOT_APPLICABLE  # spectra without a spatial layout
                elif k in self.metrics:
                    rows[-1][k] = float(self.metrics[k][i].mean())
        return rows

    def sweep_rows(self) -> list[dict[str, Any]]:
        """One row per (σ, β): the seed-mean PSNR and SAM (the whole sweep)."""
        rows = []
        mp, ma = self.psnr_db.mean(1), self.sam_deg.mean(1)
        # the spread over seeds (none with one seed: no std of a single value)
        sp = self.psnr_db.std(1) if len(self.seeds) > 1 else torch.zeros_like(mp)
        for i, s in enumerate(self.sigmas):
            for j, b in enumerate(self.betas):
                rows.append({
                    "method": self.name, "noise_sigma": float(s), "beta": float(b),
                    "psnr_db": float(mp[i, j]),
                    "psnr_std_db": float(sp[i, j]) if len(self.seeds) > 1 else 0.0,
                    "sam_deg": float(ma[i, j]),
                })  # fmt: skip
        return rows


def evaluate_design(
    matrix: Tensor,
    reflectances: Tensor,
    sigmas: list[float],
    seeds: list[int],
    betas: list[float] | None = None,
    *,
    peak_dn: float = 255.0,
    diff_order: int = 1,
    name: str = "design",
    keep_estimates: bool = False,
) -> DesignEvaluation:
    """Exposure-match, add noise, reconstruct for every β and score one design.

    Args:
        matrix: ``(O, M)`` design matrix (any scale, float32/float64, any device).
        reflectances: ``(K, M)`` true spectra (moved to ``matrix``'s device/dtype).
        sigmas: noise levels (DN); seeds: noise seeds (:func:`noise_realisation`).
        betas: smoothness weights (default :func:`default_betas`).
        peak_dn: exposure-matching target; diff_order: order of ``D``.

    Returns:
        :class:`DesignEvaluation`. One :func:`~hsi_torch.recon.nnls.solve_nnls` call solves
        all ``S·N·B·K`` problems (stacked ``[A; √β D]`` per β, ``beta=0`` in the solver).
    """
    if matrix.ndim != 2:
        raise ValueError(f"matrix must have shape (O, M), got {tuple(matrix.shape)}")
    o, m = matrix.shape
    r = reflectances.to(matrix)
    if r.ndim != 2 or r.shape[1] != m:
        raise ValueError(f"reflectances must have shape (K, {m}), got {tuple(r.shape)}")
    betas = default_betas() if betas is None else [float(b) for b in betas]
    dev, dt = matrix.device, matrix.dtype
    k = r.shape[0]
    S, N, B = len(sigmas), len(seeds), len(betas)

    scale = peak_matching_gain(matrix, r, peak_dn)
    a = matrix * scale  # (O, M)
    y0 = r @ a.T  # (K, O)
    eps = torch.stack([noise_realisation(k, o, s, device=dev, dtype=dt) for s in seeds])  # N,K,O
    sig = torch.as_tensor(sigmas, device=dev, dtype=dt)
    y = y0 + sig[:, None, None, None] * eps  # (S, N, K, O)

    d = difference_matrix(m, diff_order, device=dev, dtype=dt)  # (M-d, M)
    bt = torch.as_tensor(betas, device=dev, dtype=dt)
    a_aug = torch.cat([a.expand(B, o, m), bt.sqrt()[:, None, None] * d], 1)  # (B, O+R, M)
    rows = a_aug.shape[1]
    # problem order (S, N, B, K)
    a_p = a_aug[None, None, :, None].expand(S, N, B, k, rows, m).reshape(-1, rows, m)
    y_aug = torch.cat([y, torch.zeros(S, N, k, d.shape[0], device=dev, dtype=dt)], -1)
    y_p = y_aug[:, :, None].expand(S, N, B, k, rows).reshape(-1, rows)
    res = solve_nnls(a_p, y_p, beta=0.0)
    x = res.x.reshape(S, N, B, k, m)
    truth = r.expand_as(x)
    p = psnr(x, truth, dim=(-2, -1))  # (S, N, B)
    sam = spectral_angle_deg(x, truth).mean(-1)  # (S, N, B)
    best = p.mean(1).argmax(1)  # (S,)
    idx = best[:, None, None, None, None].expand(S, N, 1, k, m)
    x_best = x.gather(2, idx).squeeze(2)  # (S, N, K, M)
    est = x_best if keep_estimates else None
    # the field's metrics at the best β: each seed's K patches as a 1 × K image (M, 1, K)
    per = [[cube_metrics(x_best[i, j].T[:, None], r.T[:, None]) for j in range(N)]
           for i in range(S)]  # fmt: skip
    fm = {key: torch.tensor([[per[i][j][key] for j in range(N)] for i in range(S)],
                            dtype=torch.float64) for key in METRIC_NAMES}  # fmt: skip
    return DesignEvaluation(
        name=name, scale=float(scale), sigmas=[float(s) for s in sigmas],
        seeds=[int(s) for s in seeds], betas=betas, psnr_db=p, sam_deg=sam,
        best_index=best, estimates=est, converged=float(res.converged.to(dt).mean()),
        metrics=fm,
    )  # fmt: skip


# --- figures


def _plot_psnr(out: Path, rows: list[dict[str, Any]], names: list[str]) -> None:
    fig, ax = report.new_figure(figsize=(6, 4.2))
    for n in names:
        rr = sorted((r for r in rows if r["method"] == n), key=lambda r: r["noise_sigma"])
        ax.errorbar([r["noise_sigma"] for r in rr], [r["psnr_db"] for r in rr],
                    yerr=[r["psnr_std_db"] for r in rr], marker="o", capsize=3, label=n)
    ax.set_xscale("log", base=2)
    ax.set_xlabel("noise σ (DN, exposure matched to 255 DN peak)")
    ax.set_ylabel("PSNR (dB), best β")
    ax.set_title("Reflectance PSNR vs noise (mean ± std over seeds)", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    report.save_figure(fig, out / "psnr_vs_sigma.png")


def _plot_spectra(
    out: Path, evals: list[DesignEvaluation], r: Tensor, names: list[str], grid: SpectralGrid,
    patches: list[int], sigma_index: int,
) -> None:  # fmt: skip
    wl = np.asarray(grid.wavelengths_nm)
    n = len(patches)
    ncol = min(3, n)
    nrow = math.ceil(n / ncol)
    fig, axes = report.new_figure(nrow, ncol, figsize=(4.2 * ncol, 3.2 * nrow), squeeze=False)
    for i, ax in enumerate(axes.ravel()):
        if i >= n:
            ax.axis("off")
            continue
        pk = patches[i]
        ax.plot(wl, r[pk].cpu().numpy(), "k-", lw=2.2, label="true")
        for ev in evals:
            x = ev.estimates[sigma_index, 0, pk].cpu().numpy()
            ax.plot(wl, x, "-", lw=1.2, label=ev.name)
        ax.set_title(names[pk] if pk < len(names) else f"patch {pk}", fontsize=9)
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
        if i % ncol == 0:
            ax.set_ylabel("reflectance")
        if i >= n - ncol:
            ax.set_xlabel("λ (nm)")
    axes.ravel()[0].legend(fontsize=7)
    s = evals[0].sigmas[sigma_index]
    fig.suptitle(f"reconstructed vs true reflectance, σ = {s:g} DN, seed {evals[0].seeds[0]}, "
                 "best β per design", fontsize=10)
    report.save_figure(fig, out / "spectra.png")


def _plot_responses(out: Path, designs: list[SensingDesign], scales: list[float]) -> None:
    n = len(designs)
    fig, axes = report.new_figure(1, n, figsize=(4.6 * n, 3.6), squeeze=False)
    colours = {"R": "tab:red", "G": "tab:green", "B": "tab:blue"}
    for ax, d, s in zip(axes.ravel(), designs, scales, strict=True):
        wl = np.asarray(d.grid.wavelengths_nm)
        resp = (d.responses() * s).cpu().numpy()
        order = list(dict.fromkeys(c.rsplit("/", 1)[0] for c in d.channel_names))
        for k, cname in enumerate(d.channel_names):
            g, c = (cname.rsplit("/", 1) + [""])[:2]
            shade = 0.35 + 0.65 * (1 - order.index(g) / max(1, len(order) - 1))
            ax.plot(wl, resp[k], color=colours.get(c, "0.3"), alpha=shade, lw=1)
        ax.set_title(f"{d.name}: {d.num_channels} channels", fontsize=10)
        ax.set_xlabel("λ (nm)")
        ax.grid(alpha=0.3)
    axes.ravel()[0].set_ylabel("response × illuminant (DN per unit reflectance per nm)")
    fig.suptitle("channel responses after exposure matching (colour = camera channel, "
                 "shade = view / camera / bounce)", fontsize=10)
    report.save_figure(fig, out / "responses.png")


# --- the command


def run_synthetic(
    cfg: SyntheticConfig, out: str | Path, *, device: str | None = None
) -> dict[str, Any]:
    """Run the comparison and write ``results.csv``, ``results.md``, ``sweep.csv``,
    ``summary.json``, ``psnr_vs_sigma.png``, ``spectra.png`` and ``responses.png`` to ``out``.

    Returns:
        The summary dict (also written as ``summary.json``): per design and σ the rows of
        ``results.csv``, the margin of every design over ``cfg.reference`` per σ, timings.
    """
    t0, out, dev, dt = report.start_run(out, cfg, device)
    grid = cfg.wavelengths.grid()
    refl, patch_names = refdata.reflectance_set(cfg.reflectances, grid, device=dev, dtype=dt)
    seeds = list(range(cfg.seed, cfg.seed + cfg.num_seeds))
    betas = default_betas() if cfg.betas is None else list(cfg.betas)
    sigmas = [float(s) for s in cfg.noise_sigmas]

    designs, evals, rows, sweep = [], [], [], []
    it = report.progress(cfg.designs, desc="synthetic: designs", enable=cfg.progress)
    for spec in it:
        d = build_design(spec, grid, cfg.illuminant, device=dev, dtype=dt)
        if any(d.name == e.name for e in designs):
            raise ValueError(f"two designs are named {d.name!r}; give them distinct 'name's")
        ev = evaluate_design(d.matrix, refl, sigmas, seeds, betas, peak_dn=cfg.peak_dn,
                             diff_order=cfg.diff_order, name=d.name, keep_estimates=True)
        designs.append(d)
        evals.append(ev)
        for r in ev.summary_rows():
            r.update(kind=d.info.get("kind", ""), num_channels=d.num_channels,
                     peak_gain=ev.scale, converged=ev.converged)
            rows.append(r)
        sweep += ev.sweep_rows()

    names = [d.name for d in designs]
    margins: dict[str, dict[str, float]] = {}
    if cfg.reference in names:
        ref = {r["noise_sigma"]: r["psnr_db"] for r in rows if r["method"] == cfg.reference}
        for n in names:
            if n != cfg.reference:
                margins[n] = {f"{s:g}": r["psnr_db"] - ref[s] for r in rows
                              if r["method"] == n for s in [r["noise_sigma"]]}
        for r in rows:
            r[f"margin_vs_{cfg.reference}_db"] = r["psnr_db"] - ref[r["noise_sigma"]]

    cols = ["method", "kind", "num_channels", "noise_sigma", "best_beta", "psnr_db",
            "psnr_std_db", "sam_deg", "sam_std_deg", "psnr_bands_db", "ssim", "ergas", "rmse",
            "mrae", "num_seeds", "peak_gain", "converged"]
    if margins:
        cols.append(f"margin_vs_{cfg.reference}_db")
    report.write_csv(out / "results.csv", rows, cols)
    report.write_csv(out / "sweep.csv", sweep)

    wide = []
    for s in sigmas:
        w: dict[str, Any] = {"noise_sigma": s}
        for r in rows:
            if r["noise_sigma"] == s:
                w[r["method"]] = f"{r['psnr_db']:.2f} ± {r['psnr_std_db']:.2f}"
        wide.append(w)
    md = [
        "# Synthetic comparison of sensing designs\n",
        f"{len(refl)} reflectances ({cfg.reflectances}) on {grid.num_bands} bands "
        f"{grid.wavelengths_nm[0]:g}–{grid.wavelengths_nm[-1]:g} nm, illuminant "
        f"{cfg.illuminant}, exposure matched to {cfg.peak_dn:g} DN, {len(seeds)} noise seeds, "
        f"β ∈ {{{', '.join(f'{b:g}' for b in betas)}}}, NNLS + first-difference smoothness "
        f"(order {cfg.diff_order}). PSNR = 10·log10(1/MSE) on reflectance, mean ± std over "
        "seeds at the best β.\n",
        metrics_note({"ssim": "the patches are spectra without a spatial layout"})
        + " Each seed's patches are scored as one 1 × K image at the best β, mean over "
        "seeds.\n",
        "## PSNR (dB)\n",
        report.markdown_table(wide, {"noise_sigma": "σ (DN)", **{n: n for n in names}},
                              {"noise_sigma": "g"}),
        "\n## Per design and noise level\n",
        report.markdown_table(
            rows,
            {"method": "method", "noise_sigma": "σ (DN)", "best_beta": "best β",
             **{k: h for k, h in metric_columns().items() if k == "psnr_db"},
             "psnr_std_db": "± (dB)",
             **{k: h for k, h in metric_columns().items() if k != "psnr_db"},
             "num_channels": "channels",
             **({f"margin_vs_{cfg.reference}_db": f"Δ vs {cfg.reference} (dB)"}
                if margins else {})},
            {"noise_sigma": "g", "best_beta": ".3g", **METRIC_FORMATS, "psnr_std_db": ".2f",
             f"margin_vs_{cfg.reference}_db": "+.2f"},
        ),
    ]  # fmt: skip
    report.write_markdown(out / "results.md", "\n".join(md))

    si = min(range(len(sigmas)), key=lambda i: abs(sigmas[i] - cfg.spectra_sigma))
    patches = [p for p in cfg.spectra_patches if 0 <= p < len(refl)] or [0]
    _plot_psnr(out, rows, names)
    _plot_spectra(out, evals, refl, patch_names, grid, patches, si)
    _plot_responses(out, designs, [e.scale for e in evals])

    summary = {
        "rows": rows,
        "margins_db": margins,
        "reference": cfg.reference,
        "designs": {d.name: d.info for d in designs},
        "elapsed_s": time.perf_counter() - t0,
        "device": str(dev),
    }
    atomic_write_json(out / "summary.json", summary)
    return summary
