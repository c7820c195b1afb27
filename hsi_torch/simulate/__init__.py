"""Virtual prototype: scenes, capture renderer, calibration/scene capture sets, ground truth.

See ``docs/simulate.md``. Heavy imports are lazy (``hsi_torch.simulate.render`` etc.).
"""

from hsi_torch.simulate.capture_sets import (
    SimulationSummary,
    build_renderer,
    build_scene,
    simulate_capture_set,
)
from hsi_torch.simulate.config import SimulateConfig
from hsi_torch.simulate.mismatch import DOCUMENTED_EFFECTS, Mismatch
from hsi_torch.simulate.render import CaptureRenderer, CaptureSpec

__all__ = [
    "CaptureRenderer",
    "CaptureSpec",
    "DOCUMENTED_EFFECTS",
    "Mismatch",
    "SimulateConfig",
    "SimulationSummary",
    "build_renderer",
    "build_scene",
    "simulate_capture_set",
]
