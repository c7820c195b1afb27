"""The sensor remedies calibration switches on by what its own frames show (``stray_light: auto``,
``defects: auto``), and the findings that say what was decided.

**Stray light.** The veil is measured on the mean white frame where no light reaches
(:func:`~hsi_torch.io.sensor_corrections.estimate_veil` on the unreached samples of
:func:`~hsi_torch.io.sensor_corrections.unreached_index`). Its level is the veil's mean over the
sensor relative to the white's mean over the sensor, per colour (the simulator's
``stray_light_fraction`` is defined the same way), and the largest colour's is compared with
``stray_light_threshold`` (default :data:`VEIL_THRESHOLD`, 0.2 %): above it the veil is
subtracted from every lit frame (and, through the bundle, from every capture reconstructed with
it), below it nothing is subtracted. An ideal device reads ≈ 0 (the estimate of a veil-free
frame is the robust mean of its noise, clipped at 0); the documented 2 % veil reads ≈ 2 %.
Subtracting a veil that is not there costs nothing measurable (the mismatch experiment's ideal
row), so the threshold sits low, a factor of ten under the documented magnitude.

**Hot and dead pixels.** :func:`~hsi_torch.io.sensor_corrections.find_defects` on the dark
frames' per-pixel mean (hot) and the mean white (dead); under ``defects: auto`` they are masked
when at least ``defect_min_pixels`` raw sensor pixels (before the demosaic's dilation) are found,
else nothing is written. Its thresholds (``defect_hot_sigma`` robust σ, ``defect_dead_ratio``)
keep the noise of a defect-free sensor out: a 10 σ outlier is not expected among 10⁷ Gaussian
samples.

Every decision, automatic or explicit, is a :class:`~hsi_torch.findings.Finding` (codes
``calibration.stray_light``, ``calibration.stray_light_unmeasured``, ``calibration.defects``):
``info`` when the data and the setting agree (a veil measured and subtracted, none measured and
none subtracted; under ``auto``, a veil that cannot be measured: too few unreached samples),
``warning`` when an explicit ``none`` leaves a measured veil or defects in place, or when
``subtract`` cannot measure the veil.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from hsi_torch.findings import Finding

__all__ = [
    "FLAT_VEIL_GAIN",
    "VEIL_THRESHOLD",
    "MIN_UNREACHED",
    "veil_level",
    "stray_light_finding",
    "defects_finding",
]

#: relative veil (veil mean / white mean over the sensor, largest colour) above which
#: ``stray_light: auto`` subtracts it
VEIL_THRESHOLD = 0.002
#: a veil whose shaped (exp-quadratic) fit explains the unreached blocks less than this many
#: times better than a constant is flat: a black pedestal the pedestal check judges, which
#: ``stray_light: auto`` does not subtract (glare falls off across the sensor)
FLAT_VEIL_GAIN = 2.0
#: fewest unreached sensor samples the veil is measured on
MIN_UNREACHED = 64


def veil_level(white: torch.Tensor, veil_mean_dn: list[float]) -> list[float]:
    """The veil relative to the white, per colour: ``veil_mean_dn[c] / mean(white[c])``.

    Args:
        white: ``(C, H, W)`` mean white frame above black and dark (DN).
        veil_mean_dn: ``(C,)`` the veil's mean over the sensor (DN),
            :func:`~hsi_torch.io.sensor_corrections.estimate_veil`'s ``info["mean_dn"]``.

    Returns:
        ``C`` floats (0 where the white's mean is not positive).
    """
    means = torch.nan_to_num(white.to(torch.float64)).mean((1, 2)).cpu().tolist()
    return [float(v) / m if m > 0 else 0.0 for v, m in zip(veil_mean_dn, means, strict=True)]


def stray_light_finding(
    mode: str,
    level: list[float] | None,
    threshold: float,
    samples: int,
    subtract: bool,
    source: str | None = None,
    flat: bool = False,
) -> Finding:
    """The finding of the ``stray_light`` decision (``flat``: the veil fitted as a constant, a
    black pedestal rather than glare, which ``auto`` leaves to the pedestal check).

    Args:
        mode: the setting (``"auto"``, ``"subtract"``, ``"none"``).
        level: the veil relative to the white per colour (:func:`veil_level`), ``None`` when it
            could not be measured (fewer than :data:`MIN_UNREACHED` unreached samples).
        samples: unreached sensor samples the veil was measured on.
    """
    if level is None:  # asked for (subtract): a warning; auto: a fact
        return Finding(
            "calibration.stray_light_unmeasured", "warning" if mode == "subtract" else "info",
            f"the veil of stray light cannot be measured: only {samples} unreached sensor "
            f"samples (the views and their neighbours light the whole sensor); not subtracted "
            f"(stray_light: {mode})", measured=samples, limit=MIN_UNREACHED,
            fix="leave a dark border around the views (a field stop), or remove the veil by "
                "other means", source=source)  # fmt: skip
    top = max(level)
    pct = ", ".join(f"{100 * v:.2f}" for v in level)
    what = f"veil of stray light {pct} % of the white (R, G, B) on {samples} unreached samples"
    if subtract:
        how = (
            "above the threshold: subtracted from every lit frame and, through the bundle, "
            "from every capture"
            if mode == "auto"
            else "subtracted (stray_light: subtract)"
        )
        return Finding(
            "calibration.stray_light",
            "info",
            f"{what}; {how}",
            measured=top,
            limit=threshold,
            source=source,
        )
    if top > threshold and flat and mode == "auto":
        return Finding(
            "calibration.stray_light", "info",
            f"{what}: above the threshold but flat across the sensor, a black pedestal rather "
            "than glare: not subtracted (the pedestal check judges it)", measured=top,
            limit=threshold, fix="--set stray_light=subtract to remove it anyway",
            source=source)  # fmt: skip
    if top > threshold:  # only an explicit none leaves a veil above the threshold
        return Finding(
            "calibration.stray_light",
            "warning",
            f"{what}, above the threshold, but not subtracted (stray_light: none): "
            "the veil biases the transmittance and the response",
            measured=top,
            limit=threshold,
            fix="--set stray_light=auto (or subtract)",
            source=source,
        )
    return Finding(
        "calibration.stray_light",
        "info",
        f"{what}: below the threshold, not subtracted",
        measured=top,
        limit=threshold,
        source=source,
    )


def defects_finding(
    mode: str,
    raw: int,
    masked: int,
    min_pixels: int,
    mask: bool,
    origin: str,
    source: str | None = None,
) -> Finding:
    """The finding of the ``defects`` decision.

    Args:
        mode: the setting (``"auto"``, ``"mask"``, ``"none"``).
        raw: hot and dead sensor pixels found (before the dilation).
        masked: pixels masked (after the demosaic's dilation; 0 when not masked).
        origin: which frames they were looked for in (``"dark and white"``, ``"white only …"``).
    """
    what = f"{raw} hot or dead sensor pixels found ({origin})"
    if mask:
        return Finding(
            "calibration.defects",
            "info",
            f"{what}; {masked} pixels masked with their demosaic neighbours: "
            "reconstruction drops the observations that sample them",
            measured=raw,
            limit=min_pixels,
            source=source,
        )
    if raw >= min_pixels and mode == "none":
        return Finding(
            "calibration.defects",
            "warning",
            f"{what}, not masked (defects: none): their samples bias every spectrum that uses them",
            measured=raw,
            limit=min_pixels,
            fix="--set defects=auto (or mask)",
            source=source,
        )
    return Finding(
        "calibration.defects",
        "info",
        f"{what}: none masked",
        measured=raw,
        limit=min_pixels,
        source=source,
    )


def findings_dicts(findings: list[Finding]) -> list[dict[str, Any]]:
    """The JSON form stored in the bundle's ``settings["findings"]`` and the report."""
    return [f.to_dict() for f in findings]


def flat_indices(mask: torch.Tensor) -> np.ndarray:
    """``(D,)`` int64 flat row-major indices of a ``(H, W)`` bool mask."""
    return mask.reshape(-1).nonzero().squeeze(1).cpu().numpy().astype(np.int64)
