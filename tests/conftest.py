"""Shared pytest fixtures: devices (cpu, plus cuda when present), dtypes, real-data location."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from hsi_torch.resources import DATA_ENV, real_data_dir

REPO_ROOT = Path(__file__).resolve().parents[1]
#: the real-data folder: HSI_TORCH_DATA, else ../shared/data/real beside the checkout (or None)
REAL_DATA = real_data_dir()

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.fixture(params=DEVICES)
def device(request) -> torch.device:
    return torch.device(request.param)


@pytest.fixture(params=[torch.float32, torch.float64], ids=["f32", "f64"])
def dtype(request) -> torch.dtype:
    return request.param


@pytest.fixture
def real_data() -> Path:
    """The folder of real data (``HSI_TORCH_DATA`` or ``../shared/data/real`` beside the project);
    skips the test when there is none."""
    if REAL_DATA is None:
        pytest.skip(f"no real-data folder ({DATA_ENV} unset and ../shared/data/real absent)")
    return REAL_DATA
