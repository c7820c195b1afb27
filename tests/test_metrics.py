import math

import pytest
import torch
from torch.testing import assert_close

from hsi_torch.experiments.metrics import psnr, rmse, spectral_angle_deg


def test_psnr_known_value(device, dtype):
    t = torch.zeros(4, 25, device=device, dtype=dtype)
    e = t + 0.1  # MSE = 0.01 → 20 dB
    assert float(psnr(e, t)) == pytest.approx(20.0, abs=1e-4)
    per = psnr(e, t, dim=-1)
    assert per.shape == (4,)
    assert_close(per, torch.full((4,), 20.0, device=device, dtype=dtype), rtol=1e-4, atol=1e-4)
    assert float(rmse(e, t)) == pytest.approx(0.1, rel=1e-4)


def test_spectral_angle(device, dtype):
    a = torch.tensor([[1.0, 0.0], [1.0, 1.0], [2.0, 2.0]], device=device, dtype=dtype)
    b = torch.tensor([[0.0, 1.0], [1.0, 0.0], [1.0, 1.0]], device=device, dtype=dtype)
    assert_close(
        spectral_angle_deg(a, b),
        torch.tensor([90.0, 45.0, 0.0], device=device, dtype=dtype),
        atol=5e-2 if dtype == torch.float32 else 1e-4,
        rtol=0,
    )
    # scale invariance
    assert math.isclose(float(spectral_angle_deg(3 * a[1], b[1])), 45.0, abs_tol=1e-3)


def test_shape_mismatch():
    with pytest.raises(ValueError, match="shape"):
        psnr(torch.zeros(3), torch.zeros(4))
