"""``hsi-torch reconstruct`` and ``hsi-torch watch``: captures + a calibration bundle → cubes.

A batch is :func:`hsi_torch.recon.batch.entry.run_reconstruction` (the same as
``reconstruct_many`` in Python: everything checked before the output folder is created; this
process, or a Dask cluster with ``--scheduler``/``--scheduler-file``); ``--sequence`` (or one
folder, sheet ``.csv`` or multi-page TIFF as the input, which is said) is
:func:`hsi_torch.recon.batch.sequence_run.run_sequence` into ``OUT/sequence.zarr``; ``watch`` is
:func:`hsi_torch.recon.batch.watch.watch_folder` into the same store.
"""

from __future__ import annotations

import argparse

from hsi_torch.cli_common import load_args_config
from hsi_torch.console import info
from hsi_torch.io.sequence import is_sequence_input
from hsi_torch.recon.batch.driver import RunSummary
from hsi_torch.recon.batch.entry import run_reconstruction
from hsi_torch.recon.batch.sequence_run import run_sequence
from hsi_torch.recon.batch.watch import watch_folder
from hsi_torch.recon.config import ReconstructConfig

__all__ = ["run_reconstruct", "run_watch"]


def run_reconstruct(args: argparse.Namespace) -> RunSummary:
    """Entry point of ``hsi-torch reconstruct`` (see :mod:`hsi_torch.cli`).

    ``args``: ``bundle``, ``out``, ``inputs``, ``config``, ``overrides``, ``device``, ``resume``,
    ``progress``, ``strict``, ``format``, ``scheduler``, ``scheduler_file``, ``threads_per_worker``,
    ``send_bundle``. Returns the :class:`hsi_torch.recon.batch.driver.RunSummary`.
    """
    cfg: ReconstructConfig = load_args_config(args, ReconstructConfig, default="reconstruct")
    if getattr(args, "strict", False):
        cfg.strict = True  # every warning refuses its frame
    common = dict(resume=getattr(args, "resume", True), progress=getattr(args, "progress", True),
                  device=getattr(args, "device", None), config_source=_config_source(args))
    sequence = bool(getattr(args, "sequence", False))
    if not sequence and is_sequence_input(args.inputs):
        info(f"{args.inputs[0]}: a folder, a sheet or a multi-page TIFF: reconstructed as a "
             "sequence (--sequence) into OUT/sequence.zarr")  # fmt: skip
        sequence = True
    if sequence:
        _refuse_with_sequence(args)
        return run_sequence(
            args.inputs, args.bundle, args.out, cfg,
            time_from=getattr(args, "time_from", "auto"),
            frame_interval_s=getattr(args, "frame_interval", None), **common,
        )  # fmt: skip
    return run_reconstruction(
        args.inputs, args.bundle, args.out, cfg,
        scheduler=getattr(args, "scheduler", None),
        scheduler_file=getattr(args, "scheduler_file", None),
        output_format=getattr(args, "format", None) or "files",
        threads_per_worker=getattr(args, "threads_per_worker", None),
        send_bundle=bool(getattr(args, "send_bundle", False)),
        tls=(getattr(args, "tls_ca_file", None), getattr(args, "tls_cert", None),
             getattr(args, "tls_key", None)), **common,
    )  # fmt: skip


def _refuse_with_sequence(args: argparse.Namespace) -> None:
    """The options a sequence run does not take (it runs in this process, into its own store)."""
    for opt in ("scheduler", "scheduler_file", "threads_per_worker", "send_bundle"):
        if getattr(args, opt, None):
            raise ValueError(f"--{opt.replace('_', '-')}: a sequence runs in this process, frame "
                             "after frame (--sequence)")  # fmt: skip
    if (getattr(args, "format", None) or "files") != "files":
        raise ValueError("--format: a sequence is written to OUT/sequence.zarr (--sequence)")


def _config_source(args: argparse.Namespace) -> str | None:
    return str(args.config) if getattr(args, "config", None) else None


def run_watch(args: argparse.Namespace) -> RunSummary:
    """Entry point of ``hsi-torch watch`` (see :mod:`hsi_torch.recon.batch.watch`).

    ``args``: ``bundle``, ``out``, ``folder``, ``config``, ``overrides``, ``device``,
    ``time_from``, ``max_frames``, ``idle_timeout``, ``settle``.
    """
    cfg: ReconstructConfig = load_args_config(args, ReconstructConfig, default="reconstruct")
    return watch_folder(
        args.folder, args.bundle, args.out, cfg, time_from=args.time_from,
        max_frames=args.max_frames, idle_timeout_s=args.idle_timeout, settle_s=args.settle,
        device=getattr(args, "device", None), config_source=_config_source(args),
    )  # fmt: skip
