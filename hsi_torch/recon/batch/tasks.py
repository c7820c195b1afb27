"""The worker side of a reconstruction run: one task = one input, in whatever process runs it.

:func:`reconstruct_task` reconstructs one input
(:func:`~hsi_torch.recon.batch.run.reconstruct_input`) and writes its outputs — the cube files
(:func:`~hsi_torch.recon.batch.run.write_outputs`, every file atomic) or its frame of the dataset
store (:func:`hsi_torch.io.dataset.write_frame`). It runs in this process for a serial run
(:class:`~hsi_torch.recon.batch.driver.InlineExecutor`) and on the workers of a Dask cluster
otherwise, so both write the same files. Errors are returned, not raised, so that every kind of
exception reaches the driver intact.

**The bundle once per process** (``docs/cluster.md``, *How work is spread*): the prepared
:class:`~hsi_torch.recon.pipeline.Reconstructor` is kept per process, keyed by the bundle's
SHA-256 and :meth:`~hsi_torch.recon.settings.ReconstructSettings.key`; ``threads`` torch and
numba threads are set in the task's own thread (numba's setting is per thread).
"""

from __future__ import annotations

import os
import tempfile
import threading
import time
import traceback
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from hsi_torch.errors import InputError, MissingFileError
from hsi_torch.findings import RefusedError
from hsi_torch.io.atomic import atomic_write_bytes
from hsi_torch.io.dataset import write_frame
from hsi_torch.profiling import release_freed_memory
from hsi_torch.recon._numba import set_threads, thread_counts
from hsi_torch.recon.batch.run import (
    ReconstructRun,
    finding_line,
    reconstruct_input,
    write_outputs,
)
from hsi_torch.recon.distributed import in_dask_worker
from hsi_torch.recon.pipeline import Reconstructor
from hsi_torch.recon.precompute_cache import content_sha256

__all__ = [
    "FramePlan",
    "reconstruct_task",
    "prepared_reconstructor",
    "forget_prepared",
    "worker_device",
    "WORKER_STATS",
]


@dataclass(frozen=True)
class FramePlan:
    """What every task of a run needs (small: sent with each task).

    Attributes:
        run: the checked run (its ``inputs`` left out; paths absolute); its ``settings`` are
            what the reconstructor is built from.
        output_format: ``files`` or ``zarr``.
        store: the dataset store (``zarr``).
        threads: torch/numba threads of a frame (``None``: the worker's Dask thread count, or
            leave as is in this process).
        verify_bundle: check a worker's bundle file against the run's SHA-256 (a cluster run).
    """

    run: ReconstructRun
    output_format: str = "files"
    store: str | None = None
    threads: int | None = None
    verify_bundle: bool = False


_FRAME_LOCK = threading.Lock()  # one frame at a time in a process (one bundle, all its threads)
_PREPARED: dict[tuple[str, str], Reconstructor] = {}
#: what this process did: bundles ``prepared``, seconds of each preparation, ``frames``
WORKER_STATS: dict[str, Any] = {"prepared": 0, "prepare_s": [], "frames": 0}


def worker_name() -> str:
    """``"<name> (<address>)"`` of the Dask worker running this, or ``"local"``."""
    w = in_dask_worker()
    return "local" if w is None else f"{w.name} ({w.address})"


def worker_device(requested: torch.device | str | None) -> torch.device | None:
    """The torch device of a frame in this process: ``cuda`` without an index becomes this
    worker's GPU — ``cuda:0`` when the process sees one GPU (``CUDA_VISIBLE_DEVICES`` set by
    dask-cuda or the batch system), else GPU ``k mod count`` for the worker named ``k`` (the
    workers of ``local:N`` are named 0..N-1; other names are hashed); anything else is used as
    given (``None``: the bundle's)."""
    if requested is None:
        return None
    dev = torch.device(requested)
    if dev.type != "cuda" or dev.index is not None:
        return dev
    n = torch.cuda.device_count()
    w = in_dask_worker()
    if n <= 1 or w is None:
        return torch.device("cuda", 0)
    try:
        k = int(w.name)
    except (TypeError, ValueError):
        k = zlib.crc32(str(w.name).encode())
    return torch.device("cuda", k % n)


def _bundle_file(plan: FramePlan, bundle_bytes: bytes | None) -> Path:
    """The bundle file this process reads: the client's path (checked to be the same file), or
    a local copy of the bytes sent."""
    run = plan.run
    if bundle_bytes is not None:
        folder = Path(tempfile.gettempdir()) / "hsi_torch_bundles"
        local = folder / f"{run.bundle_sha256}.npz"
        if not local.is_file() or local.stat().st_size != len(bundle_bytes):
            atomic_write_bytes(local, bundle_bytes)
        return local
    path = run.bundle_path
    where = f"on worker {worker_name()}"
    try:
        st = path.stat()
    except OSError:
        raise MissingFileError(
            f"calibration bundle {path} not found {where}: the workers do not see the client's "
            "files; use --send-bundle (reconstruct_many(..., send_bundle=True))"
        ) from None
    if not plan.verify_bundle or (st.st_size, st.st_mtime_ns) == tuple(run.bundle_stamp):
        return path
    if content_sha256(path) != run.bundle_sha256:  # the run's own hash function
        raise InputError(
            f"calibration bundle {path} {where} is not the client's file (SHA-256 differs); "
            "use --send-bundle (reconstruct_many(..., send_bundle=True))"
        )
    return path


def prepared_reconstructor(
    plan: FramePlan, bundle_bytes: bytes | None = None
) -> tuple[Reconstructor, float | None]:
    """This process's reconstructor for the plan's bundle and settings, prepared on first use
    and cached under ``(bundle SHA-256, settings key)`` (one at a time: another bundle or other
    settings replace it). Returns it and the seconds its preparation took (``None``: it came
    from the cache)."""
    run = plan.run
    settings = run.settings
    dev = worker_device(settings.solve.device)
    if dev is not None and str(dev) != settings.solve.device:  # "cuda" → this worker's GPU
        settings = settings.replace(device=str(dev))
    key = (run.bundle_sha256, settings.key())
    rec = _PREPARED.get(key)
    if rec is not None:
        return rec, None
    forget_prepared()  # one prepared bundle per process: free the other first
    t0 = time.perf_counter()
    rec = Reconstructor(_bundle_file(plan, bundle_bytes), settings=settings)
    secs = time.perf_counter() - t0
    _PREPARED[key] = rec
    WORKER_STATS["prepared"] += 1
    WORKER_STATS["prepare_s"].append(secs)
    return rec, secs


def forget_prepared() -> None:
    """Drop this process's prepared reconstructor (its memory handed back)."""
    if _PREPARED:
        _PREPARED.clear()
        release_freed_memory()


def reconstruct_task(
    plan: FramePlan,
    input_path: str,
    frame: int | None = None,
    stamp: list[int] | None = None,
    bundle_bytes: bytes | None = None,
) -> dict[str, Any]:
    """One input, in whatever process runs it (see the module docstring).

    Args:
        plan: the run's :class:`FramePlan`.
        input_path: the capture (absolute).
        frame: its frame in the dataset store (``zarr``).
        stamp: the input's ``[size, mtime_ns]`` when it was claimed (stored with the frame).
        bundle_bytes: the bundle's content (``send_bundle``), else ``None``: its path.

    Returns:
        ``{"ok": True, "outputs", "warnings", "notes", "findings", "worker", "pid",
        "prepare_s", "seconds", "threads"}`` or ``{"ok": False, "error", "traceback",
        "findings", "worker", ...}``: ``warnings`` and ``notes`` the lines the run prints (the
        warning and info findings), ``findings`` every finding as
        :meth:`~hsi_torch.findings.Finding.to_dict` (a refused frame's with its errors).
    """
    with _FRAME_LOCK:
        t0 = time.perf_counter()
        w = in_dask_worker()
        set_threads(plan.threads or (w.state.nthreads if w is not None else None))
        info: dict[str, Any] = {"worker": worker_name(), "pid": os.getpid(), "prepare_s": None,
                                "threads": thread_counts()}  # fmt: skip
        try:
            rec, info["prepare_s"] = prepared_reconstructor(plan, bundle_bytes)
            run = plan.run
            path = Path(input_path)
            res, meta, findings = reconstruct_input(rec, path, run)
            if plan.output_format == "zarr":
                if plan.store is None or frame is None:
                    raise ValueError("a dataset-store task needs the store and its frame")
                meta.update(frame=frame, input_stamp=stamp, fingerprint=run.fingerprint)
                write_frame(plan.store, int(frame), res.cube, res.valid, meta)
                outputs = [str(plan.store)]
            else:
                written = write_outputs(res, run.out_dir / path.stem, run.settings, meta,
                                        inputs=[path, run.bundle_path])
                outputs = [str(p) for p in written]
            del res
        except Exception as exc:  # noqa: BLE001 - reported to the driver with its traceback
            refused = getattr(exc, "findings", None) if isinstance(exc, RefusedError) else None
            return {**info, "ok": False, "error": f"{type(exc).__name__}: {exc}",
                    "traceback": traceback.format_exc(),
                    "findings": [f.to_dict() for f in refused or []],
                    "seconds": time.perf_counter() - t0}  # fmt: skip
        finally:
            release_freed_memory()
        WORKER_STATS["frames"] += 1
        return {**info, "ok": True, "outputs": outputs,
                "warnings": [finding_line(f) for f in findings if f.severity == "warning"],
                "notes": [finding_line(f) for f in findings if f.severity == "info"],
                "findings": [f.to_dict() for f in findings],
                "seconds": time.perf_counter() - t0}  # fmt: skip
