"""Oracle calibration: a :class:`~hsi_torch.io.bundle.CalibrationBundle` built from the
simulator's ground truth instead of from calibration captures.

Reconstructing with the oracle bundle isolates the reconstruction (sensing design, solver, noise)
from calibration errors; comparing it with a calibrated bundle measures what calibration costs.
"""

from __future__ import annotations

from pathlib import Path

from hsi_torch.io.bundle import CalibrationBundle
from hsi_torch.io.capture_set import TRUTH_NPZ, read_capture_set, read_truth

__all__ = ["bundle_from_truth"]


def bundle_from_truth(capture_dir: str | Path) -> CalibrationBundle:
    """Calibration bundle made of the true B, φ, g, homographies and masks of a simulated set.

    Args:
        capture_dir: folder written by ``hsi-torch simulate`` (holds ``manifest.json`` and
            ``ground_truth/``; read with :func:`hsi_torch.io.capture_set.read_truth`).

    Returns:
        A bundle whose ``settings`` record ``oracle: True``, the CFA pattern and the white
        reference exposure of the capture set (so exposure scaling matches real calibration).
    """
    root = Path(capture_dir)
    truth, meta = read_truth(root)
    manifest = read_capture_set(root).manifest or {}
    layout = meta.get("layout", {})
    seqs = layout.get("reflection_sequences", [])
    settings = {
        "oracle": True,
        "source": str(root),
        "cfa_pattern": manifest.get("cfa_pattern"),
        "white_exposure_s": manifest.get("exposure", meta.get("exposure")),
        "white_exposure_unit": "relative",  # the simulator's exposure, as its captures carry it
    }
    same = ("wavelengths_nm", "view_homographies", "sensor_size", "reference_bbox", "B", "phi")
    same += ("gain", "view_mask", "modulated", "valid")  # the truth's keys are the bundle's names
    return CalibrationBundle(
        **{k: truth[k] for k in same},
        triangles=truth["layout_triangles"],
        parity=truth["layout_parity"],
        reflection_sequences=[tuple(s) for s in seqs],
        settings=settings,
        provenance={"truth": str(root / TRUTH_NPZ)},
    )
