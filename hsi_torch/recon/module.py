"""``HSIReconstructor``, the reconstruction as a ``torch.nn.Module``: defined, with the file methods
of the same object, in :mod:`hsi_torch.recon.pipeline` (the one reconstructor class); this module
keeps the import path."""

from __future__ import annotations

from hsi_torch.recon.pipeline import OUTPUTS, HSIReconstructor, ReconstructionOutput

__all__ = ["HSIReconstructor", "ReconstructionOutput", "OUTPUTS"]
