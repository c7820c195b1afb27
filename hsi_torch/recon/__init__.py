"""Reconstruction: batched NNLS solvers, per-bundle sensing, the frame pipeline, the nn.Module, the
settings as one object, and runs of many captures (``hsi-torch reconstruct``, ``reconstruct_many``).

Heavy parts are imported lazily (``from hsi_torch.recon import Reconstructor``).
"""

from __future__ import annotations

from hsi_torch.errors import lazy_attributes

_LAZY = {
    "BundleSensing": "hsi_torch.recon.sensing",
    "precompute_sensing": "hsi_torch.recon.sensing",
    "Reconstructor": "hsi_torch.recon.pipeline",
    "ReconstructionResult": "hsi_torch.recon.pipeline",
    "HSIReconstructor": "hsi_torch.recon.pipeline",
    "ReconstructionOutput": "hsi_torch.recon.pipeline",
    "ReconstructConfig": "hsi_torch.recon.config",
    "ReconstructSettings": "hsi_torch.recon.settings",
    "reconstruct_many": "hsi_torch.recon.batch.entry",
}

__all__ = list(_LAZY)


__getattr__ = lazy_attributes(__name__, _LAZY)
