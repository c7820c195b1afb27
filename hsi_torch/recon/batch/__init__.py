"""Batch runs: many captures, one bundle → cubes, in this process or on a Dask cluster (the path
from the command line to a solved frame: ``docs/architecture.md``, *A reconstruction run, end to
end*).

Modules: :mod:`~hsi_torch.recon.batch.entry` (:func:`run_reconstruction`,
:func:`reconstruct_many`), :mod:`~hsi_torch.recon.batch.driver` (the loop, executors, the
summary), :mod:`~hsi_torch.recon.batch.targets` (output targets),
:mod:`~hsi_torch.recon.batch.tasks` (the worker side), :mod:`~hsi_torch.recon.batch.run` (the
checked run, one input's reconstruction and files), :mod:`~hsi_torch.recon.batch.report` (the
run's findings report). Dask is imported only inside :mod:`hsi_torch.recon.distributed`, and only
when a cluster is used. The names below are imported lazily.
"""

from __future__ import annotations

from hsi_torch.errors import lazy_attributes

__all__, __getattr__ = lazy_attributes(__name__, {
    "hsi_torch.recon.batch.entry": ("run_reconstruction", "reconstruct_many"),
    "hsi_torch.recon.batch.driver": ("RunSummary", "RunFailure", "print_summary"),
    "hsi_torch.recon.batch.run": ("ReconstructRun", "check_run"),
})  # fmt: skip
