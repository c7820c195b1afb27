"""Scoring a calibration bundle against the ground truth of a simulated capture set.

The simulator writes the true ``B``, φ, g, homographies and masks of every capture set
(:func:`hsi_torch.io.capture_set.read_truth`); :func:`score_against_truth` compares a bundle
with them, :func:`targets_met` applies the calibration targets (B < 2 % RMS, φ shape correlation
> 0.99, g < 2 %, homographies < 0.3 px) and :func:`format_scores` prints the result. Used by the
demo, ``scripts/score_calibration.py`` and the calibration tests.
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import numpy as np

from hsi_torch.io.bundle import CalibrationBundle
from hsi_torch.io.capture_set import read_truth
from hsi_torch.optics.geometry import apply_homography

__all__ = ["score_against_truth", "targets_met", "format_scores"]


def score_against_truth(
    bundle: CalibrationBundle | str | Path, capture_dir: str | Path,
    truth: dict[str, np.ndarray] | None = None,
) -> dict[str, Any]:
    """Compare a calibration bundle with the ground truth of a simulated capture set.

    Definitions (all over the **common valid region** ``Q = valid_true ∧ valid_est`` unless
    stated):

    - ``B_rel_rms``: ``RMS(B_est − B_true) / RMS(B_true)`` over every band and every (view,
      pixel) with ``q ∈ Q`` and the view present in both bundles; per view too.
    - ``phi_corr``: Pearson correlation of ``φ^c_est`` and ``φ^c_true`` per colour (shape).
    - gauge: ``(g, φ)`` and ``(s·g, φ/s)`` are equivalent, so both sides are normalised the same
      way: ``g ← g / mean_{q ∈ Q, v=0}(g_0)``, ``φ ← φ · that mean``. Then ``gain_rel_rms[v]`` =
      ``RMS((g_est − g_true)/g_true)`` over ``q ∈ Q`` where view v is present in both,
      ``gain_max_rel_rms`` their maximum, and ``phi_rel_rms`` = ``RMS(φ_est−φ_true)/RMS(φ_true)``
      (scale included: the product ``g·φ`` is what reconstruction uses).
    - ``homography_rms_px`` / ``homography_max_px`` per view: ``|H_est(p) − q|`` in reference
      px for ``p = H_true⁻¹(q)`` over the reference-frame pixels where the view is truly present.
    - valid-region sizes and their intersection over union.

    ``truth``: the arrays of :func:`~hsi_torch.io.capture_set.read_truth` of ``capture_dir``,
    when the caller has them already (not read again).
    """
    b = bundle if isinstance(bundle, CalibrationBundle) else CalibrationBundle.load(bundle)
    t = truth if truth is not None else read_truth(capture_dir)[0]
    if tuple(t["B"].shape[:2]) != tuple(b.B.shape[:2]) or (
            "reference_bbox" not in t and tuple(t["B"].shape) != tuple(b.B.shape)):
        raise ValueError(
            f"bundle B {tuple(b.B.shape)} and truth B {tuple(t['B'].shape)} differ in shape: "
            "the bundle was not made from this capture set's geometry"
        )
    if "reference_bbox" in t:
        b, t = _common_frame(b, t)
    Q = t["valid"] & b.valid
    both = t["view_mask"] & b.view_mask & Q[None]  # (V, h, w)
    V = b.num_views
    # each view's common pixels gathered first, then in float64: (M, n_v) differences and truth
    ref_v = [t["B"][v][:, both[v]].astype(np.float64) for v in range(V)]
    d_v = [b.B[v][:, both[v]].astype(np.float64) - r for v, r in enumerate(ref_v)]
    d = np.concatenate(d_v, axis=1)  # (M, n), the pixels in (view, row, column) order
    ref = np.concatenate(ref_v, axis=1)
    out: dict[str, Any] = {
        "B_rel_rms": float(np.sqrt((d**2).mean()) / np.sqrt((ref**2).mean())),
        "B_rel_rms_per_view": [
            float(np.sqrt((d_v[v] ** 2).mean()) / np.sqrt((ref_v[v] ** 2).mean()))
            if both[v].any() else float("nan")
            for v in range(V)
        ],  # fmt: skip
        "B_abs_rms": float(np.sqrt((d**2).mean())),
    }
    del d, ref, d_v, ref_v
    pe, pt = b.phi.astype(np.float64), t["phi"].astype(np.float64)
    out["phi_corr"] = [float(np.corrcoef(pe[c], pt[c])[0, 1]) for c in range(3)]
    m0 = both[0]
    if not m0.any():
        m0 = b.view_mask[0] & t["view_mask"][0]
    se = float(b.gain[0][m0].mean())
    st = float(t["gain"][0][m0].mean())
    ge, gt = b.gain / se, t["gain"] / st
    pe, pt = pe * se, pt * st
    out["phi_rel_rms"] = float(np.sqrt(((pe - pt) ** 2).mean()) / np.sqrt((pt**2).mean()))
    rel = []
    for v in range(V):
        m = both[v] & (gt[v] > 0)
        r = (ge[v][m] - gt[v][m]) / gt[v][m]
        rel.append(float(np.sqrt((r**2).mean())) if m.any() else float("nan"))
    out["gain_rel_rms_per_view"] = rel
    out["gain_max_rel_rms"] = float(np.nanmax(rel))
    # homographies
    x0, y0, w, h = (int(v) for v in b.reference_bbox)
    ys, xs = np.mgrid[0:h, 0:w]
    He, Ht = b.view_homographies, t["view_homographies"]
    rms, mx = [], []
    for v in range(V):
        m = t["view_mask"][v]
        q = np.stack([xs[m] + x0, ys[m] + y0], 1).astype(np.float64)
        if not len(q):
            rms.append(float("nan"))
            mx.append(float("nan"))
            continue
        p = apply_homography(np.linalg.inv(Ht[v]), q)
        e = np.linalg.norm(apply_homography(He[v], p) - q, axis=1)
        rms.append(float(np.sqrt((e**2).mean())))
        mx.append(float(e.max()))
    out["homography_rms_px"] = rms
    out["homography_max_px"] = mx
    out["homography_worst_rms_px"] = float(np.nanmax(rms))
    nv_t, nv_e = int(t["valid"].sum()), int(b.valid.sum())
    union = int((t["valid"] | b.valid).sum())
    out["valid_true"] = nv_t
    out["valid_est"] = nv_e
    out["valid_iou"] = float(Q.sum() / union) if union else 0.0
    out["pixels_scored"] = int(Q.sum())
    return out


def _common_frame(
    b: CalibrationBundle, t: dict[str, np.ndarray]
) -> tuple[CalibrationBundle, dict[str, np.ndarray]]:
    """Bundle and truth cropped to the overlap of their reference frames (a bundle calibrated
    with a fitted layout may choose its reference frame a pixel off the simulator's; both are
    crops of the same reference-view sensor pixels). The homographies map to sensor px and
    need no change."""
    bx, by, bw, bh = (int(v) for v in b.reference_bbox)
    tx, ty, tw, th = (int(v) for v in t["reference_bbox"])
    x0, y0 = max(bx, tx), max(by, ty)
    x1, y1 = min(bx + bw, tx + tw), min(by + bh, ty + th)
    if (bx, by, bw, bh) == (tx, ty, tw, th):
        return b, t
    if x1 - x0 < 8 or y1 - y0 < 8:
        raise ValueError(f"bundle reference frame {[bx, by, bw, bh]} and the truth's "
                         f"{[tx, ty, tw, th]} hardly overlap")  # fmt: skip

    def crop(a: np.ndarray, ox: int, oy: int) -> np.ndarray:
        return a[..., y0 - oy : y1 - oy, x0 - ox : x1 - ox]

    t = dict(t)
    for k in ("B", "gain", "view_mask", "valid"):
        t[k] = crop(t[k], tx, ty)
    t["reference_bbox"] = np.asarray([x0, y0, x1 - x0, y1 - y0])
    b = copy.copy(b)
    for k in ("B", "gain", "view_mask", "modulated", "valid"):
        setattr(b, k, crop(np.asarray(getattr(b, k)), bx, by))
    b.reference_bbox = np.asarray([x0, y0, x1 - x0, y1 - y0])
    return b, t


def targets_met(s: dict[str, Any]) -> dict[str, bool]:
    """The calibration targets on :func:`score_against_truth`'s result: ``{"B", "phi", "gain",
    "homography"} → met`` (B < 2 % RMS, φ correlation > 0.99, g < 2 %, homography < 0.3 px)."""
    return {
        "B": s["B_rel_rms"] < 0.02,
        "phi": min(s["phi_corr"]) > 0.99,
        "gain": s["gain_max_rel_rms"] < 0.02,
        "homography": s["homography_worst_rms_px"] < 0.3,
    }


def format_scores(s: dict[str, Any], targets: bool = True) -> str:
    """Readable lines of :func:`score_against_truth`'s result (with the calibration targets)."""
    met = targets_met(s)

    def ok(key: str) -> str:
        return (" ok" if met[key] else " MISSED") if targets else ""

    lines = [
        f"B: RMS(B_est - B_true)/RMS(B_true) = {100 * s['B_rel_rms']:.2f} % over the common valid "
        f"region (target < 2 %){ok('B')}",
        "   per view: " + ", ".join(f"{100 * x:.2f}" for x in s["B_rel_rms_per_view"]) + " %",
        "phi shape correlation R/G/B: " + ", ".join(f"{x:.5f}" for x in s["phi_corr"])
        + f" (target > 0.99){ok('phi')}",
        f"phi (same gauge) RMS rel. error {100 * s['phi_rel_rms']:.2f} %",
        f"gain (same gauge) worst view RMS rel. error {100 * s['gain_max_rel_rms']:.2f} % "
        f"(target < 2 %){ok('gain')}",
        "   per view: " + ", ".join(f"{100 * x:.2f}" for x in s["gain_rel_rms_per_view"]) + " %",
        f"homography vs true mapping: worst view RMS {s['homography_worst_rms_px']:.3f} px "
        f"(target < 0.3 px){ok('homography')}",
        "   RMS per view: " + ", ".join(f"{x:.3f}" for x in s["homography_rms_px"]) + " px",
        "   max per view: " + ", ".join(f"{x:.3f}" for x in s["homography_max_px"]) + " px",
        f"valid region: {s['valid_est']} px calibrated vs {s['valid_true']} px true "
        f"(IoU {s['valid_iou']:.3f}); {s['pixels_scored']} px scored",
    ]
    return "\n".join(lines)
