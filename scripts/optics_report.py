#!/usr/bin/env python
"""Optics report: view layout, white-field capture, per-view BRF spectra, condition numbers.

Writes to ``--out``:
    view_map.png            simulated white-field capture (left) and view-index map (right), each
                            view outlined and labelled with its index, mirror sequence and OPD
    transmittance.png       per-view BRF transmittance B_v(λ) of the ray seeing the diffuser centre
    opd_polar.png           mean (α, σ) of the views on a polar plot, coloured by OPD
    layout.json             the ViewLayout (to_dict)
and prints the layout table and the condition numbers of the stacked 30 × 25 sensing matrix
``A[(v, c), m] = g_v B_v(λ_m) Δλ_m φ^c(λ_m)`` (φ^c = the default camera's sensitivities ×
CIE D65) for the chosen BRF and for plain RGB repeated ten times.

Usage:
    python scripts/optics_report.py --out /tmp/optics [--full]

The BRF/taper design sweep is the ``design`` experiment (``hsi-torch experiment design``).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from hsi_torch.experiments.systems import (  # noqa: E402
    brf_sensing_model,
    phi_matrix,
    scene_points,
    view_rays,
)
from hsi_torch.io.paths import claim_out_dir  # noqa: E402
from hsi_torch.optics import (  # noqa: E402
    DEFAULT_CAMERA,
    DEFAULT_GEOMETRY,
    FULL_CAMERA,
    BRFConfig,
    CameraModel,
    KaleidoscopeGeometry,
    ViewLayout,
    apply_homography,
    build_view_layout,
    trace_sensor,
)
from hsi_torch.spectral import DEFAULT_GRID, SpectralGrid  # noqa: E402


def white_field_rgb(
    geometry: KaleidoscopeGeometry,
    camera: CameraModel,
    brf: BRFConfig,
    trace,
    polarizer: float = 0.5,
) -> np.ndarray:
    """``(H, W, 3)`` display RGB of an evenly lit white diffuser seen through the add-on.

    Per pixel: throughput · T(α, σ, λ) · polarizer (1 on the BRF-free patch), integrated against
    φ^c on a 5 nm grid; white-balanced on the BRF-free patch; sRGB-like gamma. For the picture only.
    """
    wl = torch.arange(420.0, 681.0, 5.0, dtype=torch.float64)
    phi = phi_matrix(grid=SpectralGrid(tuple(wl.tolist())))
    phi = phi / phi.max()
    ok = trace.view_index >= 0
    t = brf.transmittance(trace.alpha[..., None], trace.sigma[..., None], wl) * polarizer
    free = geometry.brf_free_mask(trace.hit_xy) & ok
    t = torch.where(free[..., None], torch.ones_like(t), t)
    t = torch.where(ok[..., None], t * trace.throughput[..., None], torch.zeros_like(t))
    rgb = torch.einsum("hwm,cm->hwc", torch.nan_to_num(t), phi)
    white = rgb[free].mean(0) if bool(free.any()) else rgb[ok].amax(0)
    rgb = (rgb / white).clamp(0, 1)
    return (rgb ** (1 / 2.2)).numpy()


def plot_view_map(out: Path, layout: ViewLayout, rgb: np.ndarray, view_index: np.ndarray) -> None:
    fig, axes = plt.subplots(1, 2, figsize=(14, 7))
    cmap = plt.get_cmap("tab10")
    vis = np.zeros(view_index.shape + (3,))
    for v in range(layout.num_views):
        vis[view_index == v] = cmap(v % 10)[:3]
    titles = ["simulated white-field capture (crossed polarizers)", "view-index map"]
    for ax, img, title in zip(axes, [rgb, vis], titles, strict=True):
        ax.imshow(img, interpolation="nearest")
        ax.set_title(title)
        for v in range(layout.num_views):
            tri = layout.triangles[v].cpu().numpy()
            ax.plot(*np.vstack([tri, tri[:1]]).T, color="w" if img is rgb else "k", lw=0.8)
            cx, cy = tri.mean(0)
            seq = "".join(map(str, layout.reflection_sequences[v])) or "-"
            ax.text(
                cx,
                cy,
                f"v{v} [{seq}]\n{float(layout.opd_nm[v]):.0f} nm",
                ha="center",
                va="center",
                fontsize=8,
                color="k",
                bbox=dict(facecolor="w", alpha=0.7, lw=0, pad=1),
            )
        x0, y0, w, h = layout.reference_bbox
        ax.add_patch(plt.Rectangle((x0 - 0.5, y0 - 0.5), w, h, fill=False, ec="r", ls="--", lw=0.8))
        c = apply_homography(
            layout.diffuser_homographies[0], torch.tensor([layout.brf_free_center_mm])
        )[0]
        r_px = layout.brf_free_radius_mm * float(layout.diffuser_homographies[0][0, 0])
        ax.add_patch(plt.Circle((float(c[0]), float(c[1])), r_px, fill=False, ec="m", lw=1.0))
        ax.set_xlabel("x (px)")
        ax.set_ylabel("y (px)")
    fig.suptitle(
        "sensor: 10 kaleidoscope views (label: index [mirror sequence], OPD at 550 nm); "
        "red dashed = reference bbox, magenta = BRF-free patch",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(out / "view_map.png", dpi=110)
    plt.close(fig)


def plot_spectra(
    out: Path, layout: ViewLayout, brf: BRFConfig, alpha, sigma, grid: SpectralGrid
) -> None:
    wl_f = torch.arange(420.0, 680.5, 0.5, dtype=torch.float64)
    wl_g = grid.wavelengths(dtype=torch.float64)
    t_f = brf.transmittance(alpha[:, None], sigma[:, None], wl_f).numpy()
    t_g = brf.transmittance(alpha[:, None], sigma[:, None], wl_g).numpy()
    opd = brf.opd_nm(alpha, sigma, torch.tensor(550.0, dtype=torch.float64)).numpy()
    v = layout.num_views
    ncol = 5
    fig, axes = plt.subplots(math.ceil(v / ncol), ncol, figsize=(15, 5.5), sharex=True, sharey=True)
    for i, ax in enumerate(np.ravel(axes)):
        if i >= v:
            ax.axis("off")
            continue
        ax.plot(wl_f, t_f[i], lw=1, color="0.5")
        ax.plot(wl_g, t_g[i], "o-", ms=3, lw=1, color=plt.get_cmap("tab10")(i % 10))
        seq = "".join(map(str, layout.reflection_sequences[i])) or "-"
        ax.set_title(
            f"v{i} [{seq}] OPD {opd[i]:.0f} nm\nα={math.degrees(float(alpha[i])):.1f}° "
            f"σ={math.degrees(float(sigma[i])):.0f}°",
            fontsize=9,
        )
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
    for ax in np.ravel(axes)[-ncol:]:
        ax.set_xlabel("λ (nm)")
    fig.suptitle(
        f"BRF transmittance per view at the diffuser centre ({brf.material}, "
        f"{brf.thickness_mm} mm, tilt {brf.axis_tilt_deg}°, azimuth {brf.axis_azimuth_deg}°, "
        "crossed polarizers); dots: 10 nm grid",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(out / "transmittance.png", dpi=110)
    plt.close(fig)


def plot_polar(out: Path, layout: ViewLayout) -> None:
    fig = plt.figure(figsize=(5.5, 5))
    ax = fig.add_subplot(projection="polar")
    sc = ax.scatter(
        layout.mean_sigma.numpy(),
        np.degrees(layout.mean_alpha.numpy()),
        c=layout.opd_nm.numpy(),
        cmap="viridis",
        s=80,
    )
    for v in range(layout.num_views):
        ax.annotate(
            f"v{v}",
            (float(layout.mean_sigma[v]), math.degrees(float(layout.mean_alpha[v]))),
            fontsize=8,
            xytext=(4, 4),
            textcoords="offset points",
        )
    fig.colorbar(sc, label="mean OPD at 550 nm (nm)", pad=0.1)
    ax.set_title("views at the filter: σ (angle), α in degrees (radius)", fontsize=10)
    fig.tight_layout()
    fig.savefig(out / "opd_polar.png", dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--out", type=Path, required=True,
                    help="output folder for the PNGs: new, empty or this script's own")
    ap.add_argument("--full", action="store_true", help="also trace the full-size camera preset")
    args = ap.parse_args(argv)
    claim_out_dir(args.out, ".hsi_torch_optics_report", "run of optics_report.py",
                  "it writes view_map.png, transmittance.png, opd_polar.png and layout.json",
                  script="optics_report.py")  # fmt: skip
    torch.set_printoptions(precision=4)

    geom, cam, brf, grid = DEFAULT_GEOMETRY, DEFAULT_CAMERA, BRFConfig(), DEFAULT_GRID
    print(f"geometry: {geom.to_dict()}")
    print(f"camera:   {cam.to_dict()}")
    print(f"BRF:      {brf.to_dict()}")
    t0 = time.perf_counter()
    trace = trace_sensor(geom, cam, dtype=torch.float64)
    layout = build_view_layout(geom, cam, brf, trace=trace)
    print(f"traced {cam.width_px}x{cam.height_px} px + layout in {time.perf_counter() - t0:.2f} s")
    (args.out / "layout.json").write_text(json.dumps(layout.to_dict()))
    print("view  seq     parity  pixels  mean_alpha  mean_sigma  OPD550   H-resid(px)")
    for v in range(layout.num_views):
        print(
            f"{v:4d}  {str(layout.reflection_sequences[v]):7s} {int(layout.parity[v]):+d}  "
            f"{int(layout.pixel_count[v]):7d}  {math.degrees(float(layout.mean_alpha[v])):8.2f}°  "
            f"{math.degrees(float(layout.mean_sigma[v])):9.1f}°  {float(layout.opd_nm[v]):7.0f}  "
            f"{float(layout.homography_residual_px[v]):.2e}"
        )
    print(
        f"reference bbox (x0, y0, w, h) = {layout.reference_bbox}, BRF-free patch: centre "
        f"{layout.brf_free_center_mm} mm, radius {layout.brf_free_radius_mm} mm, "
        f"{int(layout.brf_free_mask_sensor(0).sum())} px in the reference view"
    )

    phi = phi_matrix(grid=grid)
    pts = scene_points(geom)
    alpha, sigma, thr = view_rays(geom, cam, layout, pts)
    a_design = brf_sensing_model(brf, alpha, sigma, thr, grid, phi).dense()
    cond_design = torch.linalg.cond(a_design)
    rgb10 = (grid.band_widths(dtype=torch.float64) * phi).repeat(layout.num_views, 1)
    sv = torch.linalg.svdvals(rgb10)
    rank = int(torch.linalg.matrix_rank(rgb10))
    cond_rgb = math.inf if rank < min(rgb10.shape) else float(sv[0] / sv[-1])
    print(
        f"stacked sensing matrix {tuple(a_design.shape[1:])}: condition number at the diffuser "
        f"centre {float(cond_design[0]):.3e}; over {pts.shape[0]} scene points median "
        f"{float(cond_design.median()):.3e}, max {float(cond_design.max()):.3e}"
    )
    print(
        f"RGB repeated {layout.num_views}x {tuple(rgb10.shape)}: condition number {cond_rgb:.3e} "
        f"(rank {rank}; sigma_1/sigma_{rank + 1} = {float(sv[0] / sv[rank]):.1e} is round-off; "
        f"sigma_1/sigma_3 = {float(sv[0] / sv[2]):.2f})"
    )

    rgb = white_field_rgb(geom, cam, brf, trace)
    plot_view_map(args.out, layout, rgb, trace.view_index.numpy())
    plot_spectra(args.out, layout, brf, alpha[0], sigma[0], grid)
    plot_polar(args.out, layout)
    print(f"wrote {sorted(p.name for p in args.out.glob('*.png'))} to {args.out}")

    print(
        "BRF/taper design sweep (ranked by condition number and simulated PSNR): "
        "hsi-torch experiment design --out DIR"
    )

    if args.full:
        t0 = time.perf_counter()
        tr_full = trace_sensor(geom, FULL_CAMERA, dtype=torch.float64)
        lay_full = build_view_layout(geom, FULL_CAMERA, brf, trace=tr_full)
        print(
            f"full preset {FULL_CAMERA.width_px}x{FULL_CAMERA.height_px}: traced + layout in "
            f"{time.perf_counter() - t0:.1f} s; pixels per view {lay_full.pixel_count.tolist()}; "
            f"reference bbox {lay_full.reference_bbox}; max H residual "
            f"{float(lay_full.homography_residual_px.max()):.2e} px"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
