"""hsi_torch: snapshot hyperspectral imaging with a birefringent filter and a tapered kaleidoscope.

Sub-packages follow the data flow: ``optics`` and ``simulate`` (the virtual prototype),
``calibrate`` (captures → calibration bundle), ``recon`` (bundle + capture → spectral cube),
``io`` (files), ``experiments`` (evaluations). Heavy sub-modules are imported lazily.
``__version__`` changes with the code: from a git checkout it names the commit
(:func:`hsi_torch.provenance.package_version`).
"""

from __future__ import annotations

import importlib
from typing import Any

_LAZY = {
    "SpectralGrid": "hsi_torch.spectral",
    "DEFAULT_GRID": "hsi_torch.spectral",
    "HSIReconstructor": "hsi_torch.recon.pipeline",
    "Reconstructor": "hsi_torch.recon.pipeline",
    "CalibrationBundle": "hsi_torch.io.bundle",
}

__all__ = ["__version__", *_LAZY]


def __getattr__(name: str) -> Any:
    if name == "__version__":  # from git metadata in a checkout: computed on first use
        return importlib.import_module("hsi_torch.provenance").package_version()
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'hsi_torch' has no attribute {name!r}")
