"""The bundle's sensor corrections, repeated on every capture as its calibration applied them to
the calibration frames: the stray-light veil subtracted (``stray_light: subtract``), the hot and
dead pixels masked (``defects: mask``)."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from hsi_torch.io.sensor_corrections import subtract_veil
from hsi_torch.recon.checks import BundleRadiometry

__all__ = ["apply_bundle_corrections", "correct_frames"]


def apply_bundle_corrections(capture: Any, rad: BundleRadiometry | None) -> dict[str, Any]:
    """Correct a :class:`~hsi_torch.io.LinearCapture` in place as its calibration corrected the
    calibration frames (once; repeated calls return the same statistics):

    - ``stray_light: subtract`` bundles: the veil measured on the bundle's unreached sensor
      pixels is subtracted (:func:`~hsi_torch.io.sensor_corrections.subtract_veil`, per colour
      of the ``(3, H, W)`` image; a ``(1, H, W)`` mosaic is left alone);
    - ``defects: mask`` bundles: the hot and dead pixels are marked saturated, so every
      observation that samples one is dropped.

    Returns:
        The statistics of :func:`correct_frames`.
    """
    done = getattr(capture, "_bundle_corrections", None)
    if isinstance(done, dict):
        return done
    capture.image, capture.saturated, stats = correct_frames(capture.image, capture.saturated,
                                                             rad)
    capture._bundle_corrections = stats
    return stats



def correct_frames(
    rgb: Tensor, saturated: Tensor | None, rad: BundleRadiometry | None
) -> tuple[Tensor, Tensor | None, dict[str, Any]]:
    """The bundle's sensor corrections on tensors, as :func:`apply_bundle_corrections` does on
    captures (the veil fitted per frame and colour).

    Args:
        rgb: ``(3, H, W)`` or ``(B, 3, H, W)`` linear RGB (demosaiced), sensor size.
        saturated: bool mask of ``rgb``'s shape, or ``None``.
        rad: the bundle's radiometry (``None``: nothing to do).

    Returns:
        ``(rgb, saturated, stats)``: new tensors (the inputs are not modified); ``saturated``
        is created when defects are marked; ``stats`` holds ``stray_light_veil_dn`` (the
        veil's mean per colour, per frame for a batch) and ``defect_pixels``, when applied.
    """
    stats: dict[str, Any] = {}
    if rad is None:
        return rgb, saturated, stats
    if rad.veil_index is not None and rgb.shape[-3] == 3:
        rgb, info = subtract_veil(rgb, rad.veil_index)
        frames = info["frames"] if "frames" in info else [info]
        means = [[round(v, 3) for v in f["mean_dn"]] for f in frames]
        stats["stray_light_veil_dn"] = means[0] if rgb.ndim == 3 else means
    if rad.defect_index is not None and rad.defect_index.size:
        sat = (torch.zeros(rgb.shape, dtype=torch.bool, device=rgb.device) if saturated is None
               else saturated.to(torch.bool))
        H, W = sat.shape[-2:]
        flat = sat.reshape(-1, H * W).clone()
        idx = torch.as_tensor(rad.defect_index, device=sat.device, dtype=torch.long)
        flat[:, idx] = True
        saturated = flat.reshape(sat.shape)
        stats["defect_pixels"] = int(idx.numel())
    return rgb, saturated, stats

