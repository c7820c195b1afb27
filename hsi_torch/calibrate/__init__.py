"""Calibration: monochromator scan → B_v(p, λ), white shots → φ^c and g_v(p), circle grids →
view homographies, valid region → the versioned calibration bundle
(:class:`hsi_torch.io.bundle.CalibrationBundle`, the file format reconstruction reads).

All functions are array-in/array-out (torch tensors, numpy for OpenCV detections); the
``hsi-torch calibrate`` command wires them to capture sets.
"""

from hsi_torch.calibrate.registration import (
    BlobDetectorParams,
    GridDetectorConfig,
    RegistrationResult,
    ViewRegistrationReport,
    detect_circle_grid,
    detect_in_views,
    register_views,
)
from hsi_torch.calibrate.response import (
    ResponseResult,
    estimate_response,
    estimate_response_field,
    fit_gain_field,
    solve_gain,
    solve_phi,
)
from hsi_torch.calibrate.transmittance import (
    TransmittanceResult,
    brf_transmittance,
    match_wavelengths,
    to_reference_frame,
)
from hsi_torch.calibrate.validity import ValidRegionSummary, valid_region

__all__ = [
    "BlobDetectorParams",
    "GridDetectorConfig",
    "RegistrationResult",
    "ViewRegistrationReport",
    "detect_circle_grid",
    "detect_in_views",
    "register_views",
    "ResponseResult",
    "estimate_response",
    "estimate_response_field",
    "fit_gain_field",
    "solve_gain",
    "solve_phi",
    "TransmittanceResult",
    "brf_transmittance",
    "match_wavelengths",
    "to_reference_frame",
    "ValidRegionSummary",
    "valid_region",
]
