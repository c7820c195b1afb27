"""Oracle calibration: a :class:`~hsi_torch.calibrate.bundle.CalibrationBundle` built from the
simulator's ground truth instead of from calibration captures.

Reconstructing with the oracle bundle isolates the reconstruction (sensing design, solver, noise)
from calibration errors; comparing it with a calibrated bundle measures what calibration costs.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from hsi_torch.calibrate.bundle import CalibrationBundle

__all__ = ["bundle_from_truth", "load_truth"]


def load_truth(capture_dir: str | Path) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Read ``ground_truth/truth.npz`` and ``truth.json`` of a simulated capture set.

    Returns:
        ``(arrays, meta)``: every array of ``truth.npz`` and the parsed ``truth.json``.
    """
    root = Path(capture_dir)
    npz, js = root / "ground_truth" / "truth.npz", root / "ground_truth" / "truth.json"
    for p in (npz, js):
        if not p.is_file():
            raise FileNotFoundError(
                f"{p} not found: {root} is not a simulated capture set with ground truth "
                "(run `hsi-torch simulate` first)"
            )
    with np.load(npz, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    return arrays, json.loads(js.read_text())


def bundle_from_truth(capture_dir: str | Path) -> CalibrationBundle:
    """Calibration bundle made of the true B, φ, g, homographies and masks of a simulated set.

    Args:
        capture_dir: folder written by ``hsi-torch simulate`` (holds ``manifest.json`` and
            ``ground_truth/``).

    Returns:
        A bundle whose ``settings`` record ``oracle: True``, the CFA pattern and the white
        reference exposure of the capture set (so exposure scaling matches real calibration).
    """
    root = Path(capture_dir)
    truth, meta = load_truth(root)
    manifest_path = root / "manifest.json"
    manifest = json.loads(manifest_path.read_text()) if manifest_path.is_file() else {}
    layout = meta.get("layout", {})
    seqs = layout.get("reflection_sequences", [])
    settings = {
        "oracle": True,
        "source": str(root),
        "cfa_pattern": manifest.get("cfa_pattern"),
        "white_exposure_s": manifest.get("exposure", meta.get("exposure")),
    }
    return CalibrationBundle(
        wavelengths_nm=truth["wavelengths_nm"],
        triangles=truth["layout_triangles"],
        parity=truth["layout_parity"],
        view_homographies=truth["view_homographies"],
        sensor_size=truth["sensor_size"],
        reference_bbox=truth["reference_bbox"],
        B=truth["B"],
        phi=truth["phi"],
        gain=truth["gain"],
        view_mask=truth["view_mask"],
        modulated=truth["modulated"],
        valid=truth["valid"],
        reflection_sequences=[tuple(s) for s in seqs],
        settings=settings,
        provenance={"truth": str(root / "ground_truth" / "truth.npz")},
    )
