"""The calibration diagnostics figure (``hsi-torch calibrate`` writes it beside the bundle).

One PNG, from the bundle alone (plus its report, when given, for the per-view registration
numbers), in reference-frame coordinates:

- rows 1–3: every view's BRF transmittance ``B_v(p, λ)`` at three wavelengths (default the
  grid's nearest to 450, 550 and 650 nm), grey where the view does not reach (one colour scale,
  up to the 99.5th percentile over the BRF-modulated pixels: the BRF-free disk saturates);
- row 4: every view's gain field ``g_v(p)`` (1 = the reference view's mean);
- bottom: the response curves ``φ^c(λ)``; the registration residual vectors ``H_v(x_v) − x_ref``
  of every grid point (magnified, coloured by view; RANSAC outliers as red crosses), from the
  bundle's ``extra_registration_residuals``; the valid region (number of BRF-modulated views
  per pixel, the valid pixels outlined).
"""

from __future__ import annotations

import io
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from hsi_torch.io.atomic import atomic_write_bytes
from hsi_torch.io.bundle import CalibrationBundle

__all__ = ["plot_calibration"]


def plot_calibration(
    bundle: Any,
    path: str | os.PathLike,
    *,
    report: Any | None = None,
    wavelengths_nm: Sequence[float] = (450.0, 550.0, 650.0),
    dpi: int = 80,
) -> Path:
    """Draw the diagnostics figure of a calibration bundle and write it atomically as PNG.

    Args:
        bundle: a :class:`~hsi_torch.calibrate.CalibrationBundle` (or the path of one).
        report: the :class:`~hsi_torch.calibrate.pipeline.CalibrationReport` of the run
            (optional: adds each view's RANSAC inliers and RMS to the residual panel).
        wavelengths_nm: the transmittance maps' wavelengths (nearest grid bands).

    Returns:
        ``path``.
    """
    import matplotlib
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure


    b = bundle if isinstance(bundle, CalibrationBundle) else CalibrationBundle.load(bundle)
    wl = np.asarray(b.wavelengths_nm, dtype=np.float64)
    # the nearest band of each wavelength, each once, in order
    bands = list(dict.fromkeys(int(np.argmin(np.abs(wl - t))) for t in wavelengths_nm))
    # the maps are drawn a few hundred pixels wide: subsample full-size frames (and keep only the
    # drawn bands, in float32) rather than copying the whole (V, M, h, w) transmittance
    fh, fw = (int(v) for v in np.shape(b.valid))
    st = max(1, -(-max(fh, fw) // 320))
    B = np.asarray(b.B)[:, bands, ::st, ::st].astype(np.float32)  # (V, len(bands), h', w')
    gain = np.asarray(b.gain)[:, ::st, ::st].astype(np.float32)  # (V, h', w')
    vmask = np.asarray(b.view_mask, dtype=bool)[:, ::st, ::st]
    V = B.shape[0]
    rows = len(bands) + 1
    fig = Figure(figsize=(1.55 * V + 1.0, 1.45 * rows + 3.6), dpi=dpi)
    FigureCanvasAgg(fig)
    gs = fig.add_gridspec(rows + 1, V, height_ratios=[1.0] * rows + [2.3], hspace=0.35,
                          wspace=0.08)  # fmt: skip
    mod_s = np.asarray(b.modulated, dtype=bool)[:, ::st, ::st]  # scale of the modulation
    b_max = float(np.percentile(B.transpose(1, 0, 2, 3)[:, mod_s], 99.5)) if mod_s.any() else 1.0
    g_in = gain[vmask]
    g_dev = float(np.nanmax(np.abs(g_in - 1.0))) if g_in.size else 0.1
    g_dev = max(g_dev, 1e-3)
    for r, m in enumerate([*range(len(bands)), None]):
        for v in range(V):
            ax = fig.add_subplot(gs[r, v])
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_facecolor("0.85")
            if m is None:
                img = np.where(vmask[v], gain[v], np.nan)
                im_g = ax.imshow(img, cmap="coolwarm", vmin=1 - g_dev, vmax=1 + g_dev)
            else:
                img = np.where(vmask[v], B[v, m], np.nan)
                im_b = ax.imshow(img, cmap="viridis", vmin=0.0, vmax=b_max)
            if r == 0:
                ax.set_title(f"view {v}" + (" (ref)" if v == 0 else ""), fontsize=8)
            if v == 0:
                label = "gain g_v" if m is None else f"B at {wl[bands[m]]:g} nm"
                ax.set_ylabel(label, fontsize=8)
    cax = fig.add_axes((0.915, 0.55, 0.008, 0.3))
    fig.colorbar(im_b, cax=cax).ax.tick_params(labelsize=7)
    cax.set_title("B", fontsize=8)
    gax = fig.add_axes((0.95, 0.55, 0.008, 0.3))
    fig.colorbar(im_g, cax=gax).ax.tick_params(labelsize=7)
    gax.set_title("g", fontsize=8)

    third = max(V // 3, 1)
    mid = slice(third, max(V - third, third + 1))
    # φ^c(λ)
    ax = fig.add_subplot(gs[rows, 0:third])
    phi = np.asarray(b.phi, dtype=np.float64)
    for c, col in enumerate(("tab:red", "tab:green", "tab:blue")):
        ax.plot(wl, phi[c], "-", color=col, lw=1.5, label="RGB"[c])
    ax.set_xlabel("wavelength (nm)", fontsize=8)
    ax.set_title("response φ^c(λ)", fontsize=9)
    ax.tick_params(labelsize=7)
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)

    # registration residuals
    ax = fig.add_subplot(gs[rows, mid])
    x0, y0, w, h = (int(v) for v in np.asarray(b.reference_bbox).reshape(-1))
    valid = np.asarray(b.valid, dtype=bool)
    ax.imshow(valid, cmap="Greys", vmin=0, vmax=4, extent=(-0.5, w - 0.5, h - 0.5, -0.5))
    res = np.asarray(b.extras.get("registration_residuals", np.zeros((0, 6))), np.float64)
    title = "registration residuals"
    if res.size:
        inl = res[:, 5] > 0.5
        mag = np.hypot(res[:, 3], res[:, 4])
        big = float(np.percentile(mag[inl], 95)) if inl.any() else float(mag.max())
        k = 0.08 * max(w, h) / max(big, 1e-6)  # the 95th percentile drawn as 8 % of the frame
        colors = matplotlib.colormaps["tab10"](res[:, 0].astype(int) % 10)
        xs, ys = res[:, 1] - x0, res[:, 2] - y0
        ax.quiver(xs[inl], ys[inl], k * res[inl, 3], k * res[inl, 4], color=colors[inl],
                  angles="xy", scale_units="xy", scale=1.0, width=0.004)  # fmt: skip
        ax.plot(xs[~inl], ys[~inl], "rx", ms=4)
        rms = float(np.sqrt(np.mean(mag[inl] ** 2))) if inl.any() else float("nan")
        title = (f"registration residuals ×{k:.0f} (RMS {rms:.2f} px, {int(inl.sum())} inliers"
                 + (f", {int((~inl).sum())} outliers ×" if (~inl).any() else "") + ")")
    elif report is not None:
        title += " (not stored in this bundle)"
    if report is not None and getattr(report, "registration", None):
        worst = max(report.registration, key=lambda r: r.rms_px)
        title += f"\nworst view {worst.view}: {worst.rms_px:.2f} px RMS"
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.set_title(title, fontsize=9)
    ax.tick_params(labelsize=7)

    # valid region
    ax = fig.add_subplot(gs[rows, mid.stop :])
    nmod = np.asarray(b.modulated, dtype=bool).sum(0)
    im = ax.imshow(nmod, cmap="magma", vmin=0, vmax=max(int(nmod.max()), 1))
    ax.contour(valid.astype(float), levels=[0.5], colors="cyan", linewidths=1.0)
    fig.colorbar(im, ax=ax, fraction=0.04).ax.tick_params(labelsize=7)
    ax.set_title(f"modulated views per pixel; valid (cyan): {int(valid.sum())} px "
                 f"({100 * valid.mean():.0f} %)", fontsize=9)
    ax.tick_params(labelsize=7)

    fig.suptitle(f"calibration bundle: {V} views, {wl.size} bands {wl[0]:g}–{wl[-1]:g} nm, "
                 f"reference frame {w}×{h} px (sensor {int(b.sensor_size[1])}×"
                 f"{int(b.sensor_size[0])})", fontsize=11)  # fmt: skip
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    path = Path(path)
    atomic_write_bytes(path, buf.getvalue())
    return path
