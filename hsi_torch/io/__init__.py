"""File I/O: camera RAW (linear, via rawpy), capture TIFF/NPY/NPZ, spectral cubes, the calibration
bundle, atomic writes.

See :mod:`hsi_torch.io.raw`, :mod:`hsi_torch.io.captures`, :mod:`hsi_torch.io.cube`,
:mod:`hsi_torch.io.bundle` and :mod:`hsi_torch.io.atomic` for the file formats and conventions;
:mod:`hsi_torch.io.capture_set` (capture-set folders), :mod:`hsi_torch.io.capture_manifest` (the
manifest's published schema) and :mod:`hsi_torch.io.capture_import` (a lab's folder → a capture
set: ``hsi-torch captures import|check``).
"""

from hsi_torch.io.atomic import (
    FileFormatError,
    atomic_save_npz,
    atomic_write,
    atomic_write_bytes,
    atomic_write_json,
    atomic_write_text,
)
from hsi_torch.io.bundle import CalibrationBundle, file_sha256, make_provenance
from hsi_torch.io.captures import LinearCapture, read_any, read_capture, write_capture
from hsi_torch.io.cube import (
    Cube,
    load_cube,
    read_cube_findings,
    save_cube,
    save_cube_formats,
)
from hsi_torch.io.raw import (
    RawImage,
    bayer_half,
    cfa_masks,
    demosaic,
    demosaic_bilinear,
    demosaic_saturation,
    load_raw,
    mosaic,
    validate_cfa_pattern,
)

__all__ = [  # one line per module above
    "FileFormatError", "atomic_write", "atomic_write_bytes", "atomic_write_text",
    "atomic_write_json", "atomic_save_npz",
    "CalibrationBundle", "file_sha256", "make_provenance",
    "LinearCapture", "read_any", "read_capture", "write_capture",
    "Cube", "load_cube", "read_cube_findings", "save_cube", "save_cube_formats",
    "RawImage", "load_raw", "bayer_half", "cfa_masks", "demosaic", "demosaic_bilinear",
    "demosaic_saturation", "mosaic", "validate_cfa_pattern",
]  # fmt: skip
