"""``hsi-torch reconstruct``: captures (files or globs) + a calibration bundle → spectral cubes.

The run itself is :mod:`hsi_torch.recon.run` (outputs, resume, failures, the run's configuration
file): inputs, configuration (``min_views`` against the bundle's views included) and bundle are
all checked before the output folder or the run's configuration file are created. Without
``--scheduler``/``--scheduler-file``/``--format zarr`` the inputs run one after another in this
process (:func:`hsi_torch.recon.run.run_serial`: progress bar, continues past bad files, every
failure reported at the end, exit status 1 when any failed) and Dask is not imported; with them,
:func:`hsi_torch.recon.many.run_many_cli` (the same outputs, on a Dask cluster's workers and/or
into one Zarr dataset store).
"""

from __future__ import annotations

import argparse

from hsi_torch.batch import BatchSummary
from hsi_torch.cli import load_args_config
from hsi_torch.recon.config import ReconstructConfig
from hsi_torch.recon.many import run_many_cli
from hsi_torch.recon.run import check_run, run_serial

__all__ = ["run_reconstruct"]


def run_reconstruct(args: argparse.Namespace) -> BatchSummary:
    """Entry point of ``hsi-torch reconstruct`` (see :mod:`hsi_torch.cli`).

    ``args``: ``bundle``, ``out``, ``inputs``, ``config``, ``overrides``, ``device``, ``resume``,
    ``progress``; for a distributed run or a dataset store also ``scheduler``,
    ``scheduler_file``, ``threads_per_worker``, ``send_bundle``, ``format`` (see
    :func:`hsi_torch.recon.many.run_many_cli`). Returns the
    :class:`hsi_torch.batch.BatchSummary` (a :class:`hsi_torch.recon.many.ManySummary` for a
    distributed or dataset run).
    """
    cfg: ReconstructConfig = load_args_config(args, ReconstructConfig, default="reconstruct")
    output_format = getattr(args, "format", None) or "files"
    scheduler = getattr(args, "scheduler", None)
    scheduler_file = getattr(args, "scheduler_file", None)
    for opt in ("threads_per_worker", "send_bundle", "tls_ca_file", "tls_cert", "tls_key"):
        if getattr(args, opt, None) and not (scheduler or scheduler_file):
            raise ValueError(f"--{opt.replace('_', '-')} needs --scheduler or --scheduler-file")
    run = check_run(
        args.inputs, args.bundle, args.out, cfg, device=getattr(args, "device", None),
        formats=output_format == "files",
        config_source=str(args.config) if getattr(args, "config", None) else None,
        device_here=not (scheduler or scheduler_file),
    )  # fmt: skip
    if scheduler or scheduler_file or output_format != "files":
        return run_many_cli(run, args, output_format=output_format)
    run.start()
    return run_serial(run, resume=getattr(args, "resume", True),
                      progress=getattr(args, "progress", True))  # fmt: skip

