"""Figures of a simulated capture set (written by ``hsi-torch simulate`` into ``OUT/figures``).

- ``capture_views.png``: a scene capture as the camera sees it (demosaiced, white-balanced to the
  illuminant, sRGB gamma) with every view triangle outlined and labelled with its index, mirror
  sequence and OPD at 550 nm;
- ``transmittance.png``: the true per-view transmittance ``B_v(λ)`` at one reference pixel (10 nm
  grid, markers) over the fine-grid ``t·Tstack(λ)`` (line);
- ``scene_<name>_srgb.png``: each scene's true reflectance cube in the reference frame as sRGB.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import numpy as np
import torch

from hsi_torch.colour import cube_to_srgb, srgb_encode
from hsi_torch.io import atomic_write_bytes
from hsi_torch.optics.sensor import demosaic_bilinear

__all__ = ["camera_preview", "plot_capture_views", "plot_view_transmittances",
           "plot_scene_srgb", "write_figures"]


def _save(fig, path: Path) -> Path:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=fig.dpi, bbox_inches="tight")
    return atomic_write_bytes(path, buf.getvalue())


def camera_preview(
    dn: torch.Tensor, renderer, percentile: float = 99.5, max_side: int | None = None
) -> np.ndarray:
    """``(H, W, 3)`` display image of a raw capture ``dn (C, H, W)``: black subtracted,
    demosaiced (bilinear), white-balanced with the true ``φ`` channel sums, scaled so the
    ``percentile`` of the brightest channel is 1, sRGB-encoded. Computed in float32 (a display
    image); with ``max_side`` it is box-averaged by the smallest integer factor that brings
    its longer side to at most ``max_side`` (the last partial block is averaged as it is)."""
    s = renderer.sensor
    x = dn.to(torch.float32) - s.black_level
    if x.shape[0] == 1:
        x = demosaic_bilinear(x, s.cfa_pattern)
    if max_side is not None and max(x.shape[-2:]) > max_side:
        k = -(-max(x.shape[-2:]) // max_side)
        x = torch.nn.functional.avg_pool2d(x[None], k, ceil_mode=True)[0]
    wb = renderer.phi_true().sum(1)
    x = x / (wb / wb.max()).to(x)[:, None, None]
    ref = torch.quantile(x.amax(0).reshape(-1)[:: max(1, x[0].numel() // 1_000_000)],
                         percentile / 100.0).clamp_min(1e-9)
    return srgb_encode((x / ref).clamp(0, 1)).permute(1, 2, 0).cpu().numpy()


def plot_capture_views(
    dn: torch.Tensor, renderer, path: Path, title: str = "", max_side: int = 1600
) -> Path:
    """Scene capture with the view triangles outlined and labelled (index, sequence, OPD).

    The image is shown at most ``max_side`` pixels a side (box-averaged; axes stay in sensor
    pixels), which keeps a full-size capture's preview small in memory.
    """
    from matplotlib.figure import Figure

    lay = renderer.layout
    img = camera_preview(dn, renderer, max_side=max_side)
    h, w = dn.shape[-2:]
    fig = Figure(figsize=(9, 9 * h / w + 0.4), dpi=110)
    ax = fig.add_subplot(111)
    ax.imshow(img, interpolation="nearest", extent=(-0.5, w - 0.5, h - 0.5, -0.5))
    tris = lay.triangles.cpu().numpy()
    for v in range(lay.num_views):
        t = np.vstack([tris[v], tris[v][:1]])
        ax.plot(t[:, 0], t[:, 1], "-", color="yellow" if v == 0 else "cyan", lw=0.8)
        c = tris[v].mean(0)
        seq = "".join(str(m) for m in lay.reflection_sequences[v]) or "-"
        ax.text(c[0], c[1], f"v{v} ({seq})\nOPD {float(lay.opd_nm[v]):.0f} nm",
                color="white", ha="center", va="center", fontsize=7,
                bbox={"facecolor": "black", "alpha": 0.45, "pad": 1, "lw": 0})
    x0, y0, bw, bh = lay.reference_bbox
    ax.add_patch(__import__("matplotlib.patches", fromlist=["Rectangle"]).Rectangle(
        (x0 - 0.5, y0 - 0.5), bw, bh, fill=False, ec="red", ls="--", lw=0.8))
    ax.set_title(title or "simulated capture (demosaiced, white-balanced)", fontsize=9)
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")
    return _save(fig, path)


def _central_valid_pixel(truth: dict[str, torch.Tensor]) -> tuple[int, int]:
    valid = truth["valid"]
    ys, xs = torch.nonzero(valid, as_tuple=True)
    if ys.numel() == 0:
        h, w = valid.shape
        return h // 2, w // 2
    cy, cx = ys.double().median(), xs.double().median()
    k = int(((ys - cy) ** 2 + (xs - cx) ** 2).argmin())
    return int(ys[k]), int(xs[k])


def plot_view_transmittances(renderer, truth: dict[str, torch.Tensor], path: Path) -> Path:
    """Small multiples of ``B_v(λ)`` at a central valid reference pixel, one panel per view."""
    from matplotlib.figure import Figure

    lay = renderer.layout
    y, x = _central_valid_pixel(truth)
    wl = truth["wavelengths_nm"].cpu().numpy()
    fine = renderer.fine
    V = lay.num_views
    ncol = 5
    nrow = (V + ncol - 1) // ncol
    fig = Figure(figsize=(3.0 * ncol, 2.3 * nrow), dpi=100)
    free = truth["brf_free"][y, x].reshape(1)
    for v in range(V):
        ax = fig.add_subplot(nrow, ncol, v + 1)
        if bool(truth["view_mask"][v, y, x]):
            a = truth["alpha"][v, y, x].to(torch.float64).reshape(1)
            s = truth["sigma"][v, y, x].to(torch.float64).reshape(1)
            t = truth["throughput"][v, y, x].to(torch.float64)
            design = getattr(renderer, "design", None)
            seq = "".join(str(m) for m in lay.reflection_sequences[v]) or "-"
            if design is not None and not design.has_brf:  # one filter per view
                view = torch.tensor([v], device=fine.device)
                tf = (t * renderer.stack_transmittance(a.to(fine), s.to(fine), free, fine,
                                                       view=view))[0]
                title = f"v{v} ({seq}) filter"
            else:
                tf = (t * renderer.stack_transmittance(a.to(fine), s.to(fine), free, fine))[0]
                opd = float(renderer.brf.opd_nm(a, s, torch.tensor([550.0]).to(a))[0])
                title = f"v{v} ({seq}) OPD {opd:.0f} nm"
                if design is not None and design.kind == "fujimoto":  # the grain's factor
                    xy = truth["diffuser_xy"][y, x].to(torch.float64).reshape(1, 2)
                    g = design.grain_factor(xy).to(fine)
                    ca, cb = renderer.stack_cosine_form()
                    cos = renderer.retardance_cosine(a.to(fine), s.to(fine), free, g)
                    tf = (t * torch.where(free[:, None], 1.0, ca + cb * cos))[0]
                    title = f"v{v} ({seq}) OPD {opd * float(g[0]):.0f} nm"
            ax.plot(fine.cpu().numpy(), tf.cpu().numpy(), "-", color="0.6", lw=0.8)
            ax.plot(wl, truth["B"][v, :, y, x].cpu().numpy(), "o-", ms=2.5, lw=1.0)
            ax.set_title(title, fontsize=8)
        else:
            ax.set_title(f"v{v}: absent at this pixel", fontsize=8)
        top = 0.5 * renderer.polarizer_efficiency
        if getattr(renderer, "design", None) is not None and not renderer.design.has_brf:
            top = 1.0  # manakov: no polarizers
        ax.set_ylim(0, top * 1.05)
        ax.tick_params(labelsize=7)
        if v % ncol == 0:
            ax.set_ylabel("B_v(λ)", fontsize=8)
        if v >= V - ncol:
            ax.set_xlabel("λ (nm)", fontsize=8)
    fig.suptitle(f"true view transmittances at reference pixel (x={x}, y={y}); markers: "
                 f"10 nm grid (line-averaged), grey: fine grid", fontsize=9)
    fig.tight_layout()
    return _save(fig, path)


def plot_scene_srgb(cube: torch.Tensor, wavelengths: torch.Tensor, path: Path,
                    title: str = "", illuminant: str = "D65") -> Path:
    """A reflectance cube ``(M, h, w)`` as sRGB (absolute: reflectance 1 = white)."""
    from matplotlib.figure import Figure

    rgb = cube_to_srgb(cube.to(torch.float64), wavelengths.to(torch.float64), illuminant)
    img = rgb.permute(1, 2, 0).cpu().numpy()
    h, w = img.shape[:2]
    fig = Figure(figsize=(6, 6 * h / w + 0.4), dpi=110)
    ax = fig.add_subplot(111)
    ax.imshow(img, interpolation="nearest")
    ax.set_title(title, fontsize=9)
    ax.set_axis_off()
    return _save(fig, path)


def write_figures(
    fig_dir: Path,
    renderer,
    truth: dict[str, torch.Tensor],
    scene_capture: tuple[Any, torch.Tensor] | None,
    scene_cubes: dict[str, torch.Tensor],
) -> list[Path]:
    """Write all figures; returns their paths."""
    fig_dir = Path(fig_dir)
    fig_dir.mkdir(parents=True, exist_ok=True)
    out: list[Path] = []
    if scene_capture is not None:
        pc, dn = scene_capture
        out.append(plot_capture_views(dn, renderer, fig_dir / "capture_views.png",
                                      f"simulated capture '{pc.spec.name}' "
                                      "(demosaiced, white-balanced; red: reference frame)"))
    out.append(plot_view_transmittances(renderer, truth, fig_dir / "transmittance.png"))
    for name, cube in scene_cubes.items():
        out.append(plot_scene_srgb(cube, truth["wavelengths_nm"], fig_dir /
                                   f"scene_{name}_srgb.png",
                                   f"scene '{name}': true reflectance, reference frame, sRGB"))
    return out
