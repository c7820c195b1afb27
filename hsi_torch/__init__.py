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

from hsi_torch.errors import lazy_attributes

_NAMES, _lazy = lazy_attributes("hsi_torch", {
    "hsi_torch.spectral": ("SpectralGrid", "DEFAULT_GRID"),
    "hsi_torch.recon.pipeline": ("HSIReconstructor", "Reconstructor"),
    "hsi_torch.io.bundle": ("CalibrationBundle",),
})
__all__ = ["__version__", *_NAMES]


def __getattr__(name: str) -> Any:
    if name == "__version__":  # from git metadata in a checkout: computed on first use
        return importlib.import_module("hsi_torch.provenance").package_version()
    return _lazy(name)
