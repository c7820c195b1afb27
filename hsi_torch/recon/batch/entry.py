"""The one entry point of a reconstruction run, for the command line and for Python.

:func:`run_reconstruction` is what ``hsi-torch reconstruct`` (:mod:`hsi_torch.recon.cli_entry`)
and :func:`reconstruct_many` (Python) call. It decides, in one place, where the frames run — in
this process (:class:`~hsi_torch.recon.batch.driver.InlineExecutor`; Dask is not imported) or on
a Dask cluster (``scheduler`` / ``scheduler_file`` / ``client``:
:class:`hsi_torch.recon.distributed.DaskExecutor`) — and where the outputs go (files per input,
or one dataset store), checks the options that only a cluster takes (``threads_per_worker``,
``send_bundle``), checks the run (:func:`~hsi_torch.recon.batch.run.check_run`: nothing is written
when anything is wrong) and runs it (:func:`execute`: the driver loop of
:mod:`hsi_torch.recon.batch.driver`).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from hsi_torch import __version__
from hsi_torch.config import load_config
from hsi_torch.console import warn
from hsi_torch.io.atomic import InputFiles
from hsi_torch.io.dataset import DATASET_NAME, require_dataset_packages
from hsi_torch.provenance import provenance
from hsi_torch.recon.batch.driver import Executor, InlineExecutor, RunSummary, drive
from hsi_torch.recon.batch.report import write_findings_report
from hsi_torch.recon.batch.run import ReconstructRun, check_run, output_paths
from hsi_torch.recon.batch.targets import FilesTarget, OutputTarget, StoreTarget, input_stamp
from hsi_torch.recon.batch.tasks import FramePlan, forget_prepared, reconstruct_task
from hsi_torch.recon.config import ReconstructConfig
from hsi_torch.recon.distributed import DaskExecutor, connect, make_security
from hsi_torch.resources import shipped_config

__all__ = ["run_reconstruction", "reconstruct_many", "execute", "OUTPUT_FORMATS", "load_run_config"]

#: ``files``: the configured cube files per input; ``zarr``: one dataset store
#: ``OUT/cubes.zarr`` for the whole run.
OUTPUT_FORMATS = ("files", "zarr")


def run_reconstruction(
    inputs: str | os.PathLike | Iterable[str | os.PathLike],
    bundle: str | os.PathLike,
    out_dir: str | os.PathLike,
    cfg: ReconstructConfig,
    *,
    scheduler: str | None = None,
    scheduler_file: str | os.PathLike | None = None,
    client: Any = None,
    output_format: str = "files",
    resume: bool = True,
    progress: bool = True,
    device: str | None = None,
    threads_per_worker: int | None = None,
    send_bundle: bool = False,
    security: Any | None = None,
    tls: tuple[Any, Any, Any] | None = None,
    config_source: str | None = None,
) -> RunSummary:
    """Check and run a reconstruction (see the module docstring).

    Args:
        inputs: capture files and/or glob patterns; bundle: the calibration bundle; out_dir:
            the output folder; cfg: the configuration.
        scheduler: ``"local:N"`` or a scheduler address (``"tcp://host:8786"``);
            scheduler_file: the file a scheduler wrote; client: a ``distributed.Client`` — any
            of the three runs the frames on that cluster, none of them in this process.
        output_format: ``"files"`` or ``"zarr"`` (:data:`OUTPUT_FORMATS`).
        resume: skip inputs whose outputs exist (unchanged, same input, settings and bundle).
        progress: a progress bar over completed inputs on stderr.
        device: overrides the configuration's ``device``.
        threads_per_worker: torch/numba threads per frame on a worker (a cluster only).
        send_bundle: send the bundle's bytes to the workers (a cluster only).
        security: a ``distributed.security.Security`` for a ``tls://`` scheduler (a cluster
            only; :func:`hsi_torch.recon.distributed.make_security`).
        tls: ``(ca_file, cert, key)`` to build ``security`` from (the CLI's ``--tls-ca-file``,
            ``--tls-cert``, ``--tls-key``; a cluster only).
        config_source: the configuration's file, named in errors.

    Returns:
        :class:`~hsi_torch.recon.batch.driver.RunSummary`.

    Raises:
        ValueError: a bad option, a glob that matches nothing, a bad bundle or configuration
            (before anything is written).
    """
    if output_format not in OUTPUT_FORMATS:
        raise ValueError(f"output format (--format) must be one of {', '.join(OUTPUT_FORMATS)}, "
                         f"got {output_format!r}")  # fmt: skip
    on_cluster = bool(scheduler or scheduler_file) or client is not None
    if not on_cluster:
        ca, cert, key = tls or (None, None, None)
        for name, value in (("threads_per_worker", threads_per_worker),
                            ("send_bundle", send_bundle), ("security", security),
                            ("tls_ca_file", ca), ("tls_cert", cert),
                            ("tls_key", key)):  # fmt: skip
            if value:
                raise ValueError(f"--{name.replace('_', '-')} ({name}) needs a cluster: "
                                 "--scheduler or --scheduler-file (reconstruct_many(..., "
                                 "client=...))")  # fmt: skip
    if output_format == "zarr":
        if cfg.uncertainty:
            raise ValueError("--format zarr does not store the uncertainty (config key "
                             "'uncertainty'); write cube files for it")
        try:
            require_dataset_packages()
        except ModuleNotFoundError as exc:
            raise ValueError(f"--format zarr: {exc}") from None
    run = check_run(inputs, bundle, out_dir, cfg, device=device,
                    formats=output_format == "files", config_source=config_source,
                    device_here=not on_cluster)  # fmt: skip
    opts: dict[str, Any] = {"output_format": output_format, "resume": resume,
                            "progress": progress}  # fmt: skip
    if not on_cluster:
        try:
            return execute(run, InlineExecutor(), **opts)
        finally:
            forget_prepared()  # the run's reconstructor is not kept in this process
    cluster = {"verify_bundle": not send_bundle, "send_bundle": send_bundle}
    if client is not None:
        return execute(run, DaskExecutor(client), threads=threads_per_worker, **cluster, **opts)
    if security is None and tls is not None and any(tls):
        security = make_security(*tls)
    with connect(scheduler, scheduler_file, threads_per_worker=threads_per_worker,
                 security=security) as (cl, n):  # fmt: skip
        return execute(run, DaskExecutor(cl), threads=n, **cluster, **opts)


def execute(
    run: ReconstructRun,
    executor: Executor,
    *,
    output_format: str = "files",
    resume: bool = True,
    progress: bool = True,
    threads: int | None = None,
    verify_bundle: bool = False,
    send_bundle: bool = False,
) -> RunSummary:
    """Run a checked ``run`` through ``executor``: creates the output folder and the run's
    configuration file (:meth:`ReconstructRun.start`), then drives every input
    (:func:`~hsi_torch.recon.batch.driver.drive`) into its output target.

    ``threads``: torch/numba threads per frame in the workers (``None``: each worker's Dask
    thread count; in this process: unchanged). ``verify_bundle``: workers check their bundle
    file's SHA-256 (a cluster whose workers may not share this file system). ``send_bundle``:
    the tasks get the bundle's bytes (:meth:`Executor.share`) instead of its path.
    A run that wrote anything ends with its findings report, ``OUT/runs/<run>.findings.json``
    (:mod:`hsi_torch.recon.batch.report`; ``summary.findings_report``).
    """
    for msg in run.settings.inert():  # once per run, not once per frame
        warn(f"WARNING: {msg}")
    run.start()
    out = Path(os.path.abspath(run.out_dir))
    run = dataclasses.replace(
        run, out_dir=out,
        run_config=Path(os.path.abspath(run.run_config)) if run.run_config else None,
    )  # fmt: skip
    target: OutputTarget
    if output_format == "zarr":
        attrs = {"bundle": str(run.bundle_path), "hsi_torch_version": __version__,
                 "provenance": provenance()}
        target = StoreTarget(out / DATASET_NAME, run.inputs, run.wavelengths_nm, run.frame_size,
                             attrs, run.fingerprint)  # fmt: skip
    else:
        settings = run.settings
        target = FilesTarget(out, run.fingerprint,
                             planned_outputs=lambda p: output_paths(out / p.stem, settings),
                             protected=InputFiles([*run.inputs, run.bundle_path]))
    plan = FramePlan(
        run=dataclasses.replace(run, inputs=[]), output_format=output_format,
        store=str(target.store) if target.store is not None else None, threads=threads,
        verify_bundle=verify_bundle,
    )  # fmt: skip
    bundle_bytes = executor.share(run.bundle_path.read_bytes()) if send_bundle else None

    def task_args(inp: Path, frame: int | None) -> tuple[Any, ...]:
        return plan, os.path.abspath(inp), frame, input_stamp(inp), bundle_bytes

    summary = drive(run.inputs, target, executor, reconstruct_task, task_args, resume=resume,
                    progress=progress)  # fmt: skip
    run.discard_if_nothing_written(summary)
    if run.run_config is not None and run.run_config.exists():  # not when it made nothing
        store = target.store
        skipped = ((lambda p: [store]) if store is not None
                   else (lambda p: output_paths(out / p.stem, run.settings)))  # fmt: skip
        write_findings_report(summary, out, run.run_config, skipped)
    return summary


def load_run_config(
    config: ReconstructConfig | Mapping[str, Any] | str | os.PathLike | None,
    overrides: list[str] | None = None,
) -> ReconstructConfig:
    """A :class:`ReconstructConfig` from an instance (copied), a mapping, a YAML file or
    ``None`` (the shipped ``reconstruct.yaml``), with ``overrides`` (``["beta=1e3", ...]``)."""
    if isinstance(config, ReconstructConfig):
        if overrides:
            return load_config(dataclasses.asdict(config), ReconstructConfig, overrides)
        return dataclasses.replace(config)
    source = shipped_config("reconstruct") if config is None else config
    return load_config(source, ReconstructConfig, overrides or [])


def reconstruct_many(
    inputs: str | os.PathLike | Iterable[str | os.PathLike],
    bundle: str | os.PathLike,
    out_dir: str | os.PathLike,
    client: Any = None,
    *,
    config: ReconstructConfig | Mapping[str, Any] | str | os.PathLike | None = None,
    overrides: list[str] | None = None,
    **options: Any,
) -> RunSummary:
    """Reconstruct many captures with one bundle, on a Dask cluster or in this process
    (:func:`run_reconstruction` from Python).

    Args:
        inputs, bundle, out_dir: as :func:`run_reconstruction`.
        client: a ``distributed.Client``, a scheduler spec (``"local:N"``,
            ``"tcp://host:8786"``; see :func:`hsi_torch.recon.distributed.connect`), or
            ``None``: this process.
        config: a :class:`ReconstructConfig`, a mapping, a YAML file, or ``None`` (the shipped
            ``reconstruct.yaml``); ``overrides``: ``["beta=1e3", ...]`` on top.
        options: :func:`run_reconstruction`'s keywords (``output_format``, ``resume``,
            ``progress``, ``device``, ``threads_per_worker``, ``send_bundle``, ``security``).

    Returns and raises as :func:`run_reconstruction`.

    Example:
        >>> from distributed import Client                              # doctest: +SKIP
        >>> s = reconstruct_many("shots/*.tif", "calib.npz", "cubes/",  # doctest: +SKIP
        ...                      client=Client("tcp://head:8786"), output_format="zarr")
        >>> s.exit_code, [f.error for f in s.failed]                    # doctest: +SKIP
    """
    cfg = load_run_config(config, overrides)
    spec = str(client) if isinstance(client, (str, os.PathLike)) else None
    return run_reconstruction(inputs, bundle, out_dir, cfg, scheduler=spec,
                              client=None if spec else client, **options)  # fmt: skip
