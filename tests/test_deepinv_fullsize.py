"""scripts/deepinv_fullsize.py: its crop of a bundle reconstructs a window of the full-size capture
exactly as the whole bundle does (so the crop's scores are the whole frame's on those pixels)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import torch
from test_pipeline import make_bundle, render_capture, true_spectra

from hsi_torch.recon import Reconstructor
from hsi_torch.recon.camera import CameraOperator

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "deepinv_fullsize.py"


def _script():
    spec = importlib.util.spec_from_file_location("deepinv_fullsize", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)  # imports neither deepinv nor torchvision until main() runs
    return mod


def test_cropped_bundle_reconstructs_the_window_of_the_whole_frame():
    full = make_bundle(t=24)
    img = render_capture(full, true_spectra(t=24))
    y0, x0, n = 7, 3, 12  # off the origin: the reference bbox moves with the window
    crop = _script().crop_bundle(full, y0, x0, n)
    assert tuple(crop.reference_bbox) == (x0, y0, n, n) and crop.valid.shape == (n, n)
    whole = Reconstructor(full, dtype="float64", precompute_cache="off").reconstruct_frame(img)
    part = Reconstructor(crop, dtype="float64", precompute_cache="off").reconstruct_frame(img)
    win = (slice(y0, y0 + n), slice(x0, x0 + n))
    assert torch.equal(part.valid, whole.valid[win])
    assert int(part.valid.sum()) > n * n // 2  # the window holds the invalid corner's edge too
    v = part.valid
    np.testing.assert_allclose(part.cube[:, v].numpy(), whole.cube[(slice(None), *win)][:, v],
                               rtol=1e-9, atol=1e-12)  # fmt: skip
    # the physics deepinv runs on: the crop's observations are the whole frame's window
    y_full, ok_full = CameraOperator(full, dtype=torch.float64).observe(img[None])
    y_crop, ok_crop = CameraOperator(crop, dtype=torch.float64).observe(img[None])
    assert torch.equal(ok_crop, ok_full[(..., *win)])
    torch.testing.assert_close(y_crop, y_full[(..., *win)], rtol=1e-12, atol=1e-12)
