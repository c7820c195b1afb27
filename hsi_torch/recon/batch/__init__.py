"""Batch runs: many captures, one bundle → cubes, in this process or on a Dask cluster.

One path from the command line (or Python) to a solved frame::

    hsi-torch reconstruct ─┐                        (recon/cli_entry.py)
    reconstruct_many() ────┴─► entry.run_reconstruction   the one decision: this process or a
                                 │                        cluster; files or a dataset store
                                 ├─ run.check_run          config → ReconstructSettings (once),
                                 │                         inputs, bundle (read once), device
                                 └─ entry.execute
                                      ├─ targets.FilesTarget | targets.StoreTarget   (resume,
                                      │                      claims, markers, the store)
                                      ├─ driver.InlineExecutor | distributed.DaskExecutor
                                      └─ driver.drive          the loop: check → skip → claim →
                                           │                   hand out → finish / abandon
                                           ▼
                                      tasks.reconstruct_task   (this process or a worker)
                                           prepared Reconstructor (cached by bundle SHA-256 and
                                           settings key) → run.reconstruct_input →
                                           run.write_outputs | io.dataset.write_frame

Modules: :mod:`~hsi_torch.recon.batch.entry` (:func:`run_reconstruction`,
:func:`reconstruct_many`), :mod:`~hsi_torch.recon.batch.driver` (the loop, executors, the
summary), :mod:`~hsi_torch.recon.batch.targets` (output targets),
:mod:`~hsi_torch.recon.batch.tasks` (the worker side), :mod:`~hsi_torch.recon.batch.run` (the
checked run, one input's reconstruction and files), :mod:`~hsi_torch.recon.batch.report` (the
run's findings report). Dask is imported only inside
:mod:`hsi_torch.recon.distributed`, and only when a cluster is used. The names below are imported
lazily.
"""

from __future__ import annotations

from hsi_torch.errors import lazy_attributes

__all__, __getattr__ = lazy_attributes(__name__, {
    "hsi_torch.recon.batch.entry": ("run_reconstruction", "reconstruct_many"),
    "hsi_torch.recon.batch.driver": ("RunSummary", "RunFailure", "print_summary"),
    "hsi_torch.recon.batch.run": ("ReconstructRun", "check_run"),
})  # fmt: skip
