"""``hsi-torch reconstruct``: captures (files or globs) + a calibration bundle → spectral cubes.

The run is :func:`hsi_torch.recon.batch.entry.run_reconstruction` (the same as
``reconstruct_many`` in Python): inputs, configuration (``min_views`` against the bundle's views
included) and bundle are all checked before the output folder or the run's configuration file
are created. Without ``--scheduler``/``--scheduler-file`` the inputs run one after another in
this process (progress bar, continues past bad files, every failure reported at the end, exit
status 1 when any failed) and Dask is not imported; with them, on a Dask cluster's workers (the
same outputs). ``--format zarr`` writes one dataset store instead of files per input.
"""

from __future__ import annotations

import argparse

from hsi_torch.cli_common import load_args_config
from hsi_torch.recon.batch.driver import RunSummary
from hsi_torch.recon.batch.entry import run_reconstruction
from hsi_torch.recon.config import ReconstructConfig

__all__ = ["run_reconstruct"]


def run_reconstruct(args: argparse.Namespace) -> RunSummary:
    """Entry point of ``hsi-torch reconstruct`` (see :mod:`hsi_torch.cli`).

    ``args``: ``bundle``, ``out``, ``inputs``, ``config``, ``overrides``, ``device``, ``resume``,
    ``progress``, ``strict``, ``format``, ``scheduler``, ``scheduler_file``, ``threads_per_worker``,
    ``send_bundle``. Returns the :class:`hsi_torch.recon.batch.driver.RunSummary`.
    """
    cfg: ReconstructConfig = load_args_config(args, ReconstructConfig, default="reconstruct")
    if getattr(args, "strict", False):
        cfg.strict = True  # every warning refuses its frame
    return run_reconstruction(
        args.inputs, args.bundle, args.out, cfg,
        scheduler=getattr(args, "scheduler", None),
        scheduler_file=getattr(args, "scheduler_file", None),
        output_format=getattr(args, "format", None) or "files",
        resume=getattr(args, "resume", True), progress=getattr(args, "progress", True),
        device=getattr(args, "device", None),
        threads_per_worker=getattr(args, "threads_per_worker", None),
        send_bundle=bool(getattr(args, "send_bundle", False)),
        tls=(getattr(args, "tls_ca_file", None), getattr(args, "tls_cert", None),
             getattr(args, "tls_key", None)),
        config_source=str(args.config) if getattr(args, "config", None) else None,
    )  # fmt: skip
