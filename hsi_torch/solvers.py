"""Public alias ``hsi_torch.solvers`` (``solve_nnls`` and friends).

The implementation lives in :mod:`hsi_torch.recon.solvers`.
"""

from hsi_torch.recon.solvers import *  # noqa: F401,F403
from hsi_torch.recon.solvers import __all__  # noqa: F401
