"""Reconstruction: batched NNLS solvers, per-bundle sensing, the frame pipeline, the nn.Module, the
settings as one object, and runs of many captures (``hsi-torch reconstruct``, ``reconstruct_many``).

Heavy parts are imported lazily (``from hsi_torch.recon import Reconstructor``).
"""

from __future__ import annotations

from hsi_torch.errors import lazy_attributes

__all__, __getattr__ = lazy_attributes(__name__, {
    "hsi_torch.recon.sensing": ("BundleSensing", "precompute_sensing"),
    "hsi_torch.recon.pipeline": ("Reconstructor", "ReconstructionResult", "HSIReconstructor",
                                 "ReconstructionOutput"),
    "hsi_torch.recon.config": ("ReconstructConfig",),
    "hsi_torch.recon.settings": ("ReconstructSettings",),
    "hsi_torch.recon.batch.entry": ("reconstruct_many",),
})  # fmt: skip
