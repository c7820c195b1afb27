"""Former location of the batched NNLS solver; it now lives in :mod:`hsi_torch.recon.nnls`."""

from hsi_torch.recon.nnls import *  # noqa: F401,F403
from hsi_torch.recon.nnls import __all__ as _nnls_all
from hsi_torch.testing import synthetic_brf_problem  # noqa: F401

__all__ = [*_nnls_all, "synthetic_brf_problem"]
