"""Many captures, one bundle: the batch run on Dask workers, and into one Zarr dataset store.

:func:`reconstruct_many` (Python) and ``hsi-torch reconstruct --scheduler ... | --format zarr``
(:func:`run_many_cli`) run :func:`run_many`: the same run as the serial one
(:func:`hsi_torch.recon.run.run_serial`) with the frames reconstructed elsewhere — on the workers
of a Dask cluster (:mod:`hsi_torch.recon.distributed`), or in this process when only the output
is the dataset store.

Same semantics as the serial run:

- **The same outputs**: a task reconstructs its input with the code of the serial run
  (:func:`~hsi_torch.recon.run.reconstruct_input`) and writes the same files
  (:func:`~hsi_torch.recon.run.write_outputs`, every file atomic), so the cubes, valid masks and
  previews are the same; the metadata stored with a cube differ as between any two runs
  (``timings_s``, the run's configuration file ``run_config``).
- **Resume, claims, failures**: this process (the *driver*) keeps the bookkeeping of
  :mod:`hsi_torch.batch` — an input is claimed (done-marker ``"started"``, the name lock held)
  before its task is handed out and marked done from the task's result, so resume, the rule that
  outputs belong to one input and stale-file cleaning are those of the serial run. Every failure
  is collected with its input and reason (exit status 1), warnings are printed here, the progress
  bar counts completed inputs.
- **A worker that dies** (killed, out of memory) mid-task: Dask hands its tasks to other workers
  (up to ``distributed.scheduler.allowed-failures`` deaths per task, then the input fails with
  ``KilledWorker``). Outputs are atomic, so the dead worker left at most temporary files; they
  are removed when the input completes (while its name lock is still held, no one else writes
  those names).
- **Ctrl-C**: the tasks not yet started are cancelled, the claims of unfinished inputs are
  released (markers as before the run), a ``local:N`` cluster is shut down, and the
  ``KeyboardInterrupt`` propagates (``hsi-torch`` exits 130). On an existing cluster frames
  already running finish writing their complete files; a rerun redoes those inputs.

**The bundle once per worker.** A task gets the bundle's path (or, with ``send_bundle``, its
bytes: a Dask future replicated once to every worker and kept in a local file); the prepared
:class:`~hsi_torch.recon.pipeline.Reconstructor` is kept in a per-process cache keyed by the
bundle's SHA-256 and the settings that shape it (one prepared bundle per worker; a different
bundle replaces it). A worker checks that its file is the client's (same size and time, else
same SHA-256). Frames run one at a time in a worker process, with ``threads`` torch and numba
threads set in the task's own thread (numba's setting is per thread).

**The dataset store** (``output_format="zarr"``): ``OUT/cubes.zarr``
(:mod:`hsi_torch.io.dataset`), one frame per input, written concurrently by the tasks; resume
skips frames that are complete and were made from the same input file and settings.

Dask is imported only when a cluster is used (inside :mod:`hsi_torch.recon.distributed`).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import glob
import os
import tempfile
import threading
import time
import traceback
import zlib
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numba
import torch

from hsi_torch import __version__
from hsi_torch.batch import (
    BatchFailure,
    BatchSummary,
    OutputClaims,
    clean_run_leftovers,
    input_stamp,
)
from hsi_torch.config import load_config
from hsi_torch.console import progress_bar, warn
from hsi_torch.errors import InputError, MissingFileError
from hsi_torch.io.atomic import atomic_write_bytes, clean_stale_temp_files
from hsi_torch.io.bundle import file_sha256
from hsi_torch.io.cube import remove_output
from hsi_torch.io.dataset import (
    DATASET_NAME,
    CubeDataset,
    require_dataset_packages,
    write_frame,
)
from hsi_torch.profiling import release_freed_memory
from hsi_torch.recon.config import ReconstructConfig
from hsi_torch.recon.distributed import DaskExecutor, connect, in_dask_worker, make_security
from hsi_torch.recon.pipeline import Reconstructor
from hsi_torch.recon.run import (
    ReconstructRun,
    check_run,
    output_paths,
    reconstruct_input,
    run_serial,
    write_outputs,
)
from hsi_torch.resources import shipped_config

__all__ = [
    "reconstruct_many",
    "run_many",
    "run_many_cli",
    "run_on_client",
    "ManySummary",
    "FramePlan",
    "reconstruct_task",
    "InlineExecutor",
    "OUTPUT_FORMATS",
]

#: ``files``: the configured cube files per input (the serial run's outputs); ``zarr``: one
#: dataset store ``OUT/cubes.zarr`` for the whole run.
OUTPUT_FORMATS = ("files", "zarr")


@dataclass
class ManySummary(BatchSummary):
    """:class:`~hsi_torch.batch.BatchSummary` of a run of :func:`run_many`, plus:

    Attributes:
        frames: input → frame index in the dataset store (``output_format="zarr"``).
        workers: input → the worker that reconstructed it (``"local"``: this process).
        prepare_s: worker process → seconds its bundle preparation took (processes that
            prepared it in this run; a restarted worker appears once per process).
        threads: worker → its torch and numba thread counts during its last frame.
        store: the dataset store, if any.
    """

    frames: dict[Path, int] = field(default_factory=dict)
    workers: dict[Path, str] = field(default_factory=dict)
    prepare_s: dict[str, float] = field(default_factory=dict)
    threads: dict[str, dict[str, int]] = field(default_factory=dict)
    store: Path | None = None

    def report(self) -> str:
        text = super().report()
        n = len(set(self.workers.values()))
        if n:
            text += f"\n  frames reconstructed by {n} worker(s)"
        if self.prepare_s:
            secs = ", ".join(f"{s:.1f}" for s in self.prepare_s.values())
            text += f"\n  bundle prepared {len(self.prepare_s)} time(s), once per worker ({secs} s)"
        if self.store is not None:
            text += f"\n  dataset store: {self.store}"
        return text


@dataclass(frozen=True)
class FramePlan:
    """What every task of a run needs (small: sent with each task).

    Attributes:
        run: the checked run (its ``inputs`` left out; paths absolute).
        bundle_key: identifies the bundle's content (SHA-256 for a cluster run).
        bundle_stamp: ``(size, mtime_ns)`` of the bundle file on the driver.
        output_format: ``files`` or ``zarr``.
        store: the dataset store (``zarr``).
        threads: torch/numba threads of a frame (``None``: the worker's Dask thread count, or
            leave as is in this process).
        verify_bundle: check a worker's bundle file against ``bundle_key`` (a cluster run).
    """

    run: ReconstructRun
    bundle_key: str
    bundle_stamp: tuple[int, int]
    output_format: str = "files"
    store: str | None = None
    threads: int | None = None
    verify_bundle: bool = False


# --- the worker side ------------------------------------------------------------------------

_FRAME_LOCK = threading.Lock()  # one frame at a time in a process (one bundle, all its threads)
_PREPARED: dict[tuple[Any, ...], Reconstructor] = {}
#: what this process did: bundles ``prepared``, seconds of each preparation, ``frames``
WORKER_STATS: dict[str, Any] = {"prepared": 0, "prepare_s": [], "frames": 0}


def worker_name() -> str:
    """``"<name> (<address>)"`` of the Dask worker running this, or ``"local"``."""
    w = in_dask_worker()
    return "local" if w is None else f"{w.name} ({w.address})"


def set_threads(n: int | None) -> None:
    """torch's and numba's thread counts for work started from this thread (numba's setting is
    per thread; ``None``: leave both)."""
    if not n:
        return
    # always: torch's OpenMP setting is per thread too, and a task may run in a new thread
    torch.set_num_threads(n)
    numba.set_num_threads(max(1, min(int(n), int(numba.config.NUMBA_NUM_THREADS))))


def thread_counts() -> dict[str, int]:
    """torch's and numba's thread counts in this thread."""
    return {"torch": torch.get_num_threads(), "numba": numba.get_num_threads()}


def worker_device(requested: torch.device | str) -> torch.device:
    """The torch device of a frame in this process: ``cuda`` without an index becomes this
    worker's GPU — ``cuda:0`` when the process sees one GPU (``CUDA_VISIBLE_DEVICES`` set by
    dask-cuda or the batch system), else GPU ``k mod count`` for the worker named ``k`` (the
    workers of ``local:N`` are named 0..N-1; other names are hashed); anything else is used as
    given."""
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
    if bundle_bytes is not None:
        folder = Path(tempfile.gettempdir()) / "hsi_torch_bundles"
        local = folder / f"{plan.bundle_key}.npz"
        if not local.is_file() or local.stat().st_size != len(bundle_bytes):
            atomic_write_bytes(local, bundle_bytes)
        return local
    path = plan.run.bundle_path
    where = f"on worker {worker_name()}"
    try:
        st = path.stat()
    except OSError:
        raise MissingFileError(
            f"calibration bundle {path} not found {where}: the workers do not see the client's "
            "files; use --send-bundle (reconstruct_many(..., send_bundle=True))"
        ) from None
    if not plan.verify_bundle or (st.st_size, st.st_mtime_ns) == tuple(plan.bundle_stamp):
        return path
    if file_sha256(path) != plan.bundle_key:
        raise InputError(
            f"calibration bundle {path} {where} is not the client's file (SHA-256 differs); "
            "use --send-bundle (reconstruct_many(..., send_bundle=True))"
        )
    return path


def prepared_reconstructor(
    plan: FramePlan, bundle_bytes: bytes | None = None
) -> tuple[Reconstructor, float | None]:
    """This process's reconstructor for the plan's bundle and settings, prepared on first use
    and cached (one at a time: another bundle replaces it). Returns it and the seconds its
    preparation took (``None``: it came from the cache)."""
    run = plan.run
    dev = worker_device(run.device)
    cfg = run.cfg
    key = (plan.bundle_key, str(dev), str(run.dtype), cfg.beta, cfg.diff_order, cfg.solver,
           cfg.admm_iters, cfg.chunk_size, cfg.min_views, cfg.nan_invalid,
           cfg.exposure_correction, cfg.prior, cfg.lam, cfg.spatial_iters, cfg.uncertainty,
           cfg.noise_electrons_per_dn, cfg.noise_read_e)  # fmt: skip
    rec = _PREPARED.get(key)
    if rec is not None:
        return rec, None
    if _PREPARED:  # one prepared bundle per process: free the other first
        _PREPARED.clear()
        release_freed_memory()
    t0 = time.perf_counter()
    path = _bundle_file(plan, bundle_bytes)
    rec = dataclasses.replace(run, bundle_path=path, device=dev).reconstructor()
    secs = time.perf_counter() - t0
    _PREPARED[key] = rec
    WORKER_STATS["prepared"] += 1
    WORKER_STATS["prepare_s"].append(secs)
    return rec, secs


def reconstruct_task(
    plan: FramePlan,
    input_path: str,
    frame: int | None = None,
    stamp: list[int] | None = None,
    bundle_bytes: bytes | None = None,
) -> dict[str, Any]:
    """One input, in whatever process runs it (a Dask worker, or this one): reconstruct it and
    write its outputs. Errors are returned, not raised (their text and traceback), so that every
    kind of exception reaches the driver intact.

    Args:
        plan: the run's :class:`FramePlan`.
        input_path: the capture (absolute).
        frame: its frame in the dataset store (``zarr``).
        stamp: the input's ``[size, mtime_ns]`` when it was claimed (stored with the frame).
        bundle_bytes: the bundle's content (``send_bundle``), else ``None``: its path.

    Returns:
        ``{"ok": True, "outputs", "warnings", "worker", "pid", "prepare_s", "seconds",
        "threads"}`` or ``{"ok": False, "error", "traceback", "worker", ...}``.
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
            res, meta, warnings = reconstruct_input(rec, path, run)
            if plan.output_format == "zarr":
                if plan.store is None or frame is None:
                    raise ValueError("a dataset-store task needs the store and its frame")
                meta.update(frame=frame, input_stamp=stamp, fingerprint=run.fingerprint)
                write_frame(plan.store, int(frame), res.cube, res.valid, meta)
                outputs = [str(plan.store)]
            else:
                written = write_outputs(res, run.out_dir / path.stem, run.cfg, meta)
                outputs = [str(p) for p in written]
            del res
        except Exception as exc:  # noqa: BLE001 - reported to the driver with its traceback
            return {**info, "ok": False, "error": f"{type(exc).__name__}: {exc}",
                    "traceback": traceback.format_exc(),
                    "seconds": time.perf_counter() - t0}  # fmt: skip
        finally:
            release_freed_memory()
        WORKER_STATS["frames"] += 1
        return {**info, "ok": True, "outputs": outputs, "warnings": warnings,
                "seconds": time.perf_counter() - t0}  # fmt: skip


# --- the driver side ------------------------------------------------------------------------

Outcome = tuple[Any, "dict[str, Any] | None", "BaseException | None"]


class Executor(Protocol):
    """Where tasks run: :class:`InlineExecutor` (this process) or
    :class:`hsi_torch.recon.distributed.DaskExecutor` (a cluster's workers).

    ``window()``: how many tasks may be in flight; ``submit`` returns a token;
    ``wait_one()`` gives ``(token, result, exception)`` of a completed task; ``cancel`` drops
    tasks not yet finished; ``share(data)`` makes ``data`` available to every task (returns
    what to pass in its place).
    """

    def window(self) -> int: ...
    def submit(self, fn: Callable[..., dict[str, Any]], *args: Any, name: str) -> Any: ...
    def wait_one(self) -> Outcome: ...
    def cancel(self, tokens: Iterable[Any]) -> None: ...
    def share(self, data: bytes) -> Any: ...


class InlineExecutor:
    """Runs each task at once, in this process (the dataset store without a cluster)."""

    def __init__(self) -> None:
        self._done: list[Outcome] = []
        self._n = 0

    def share(self, data: bytes) -> Any:
        return data

    def window(self) -> int:
        return 1

    def submit(self, fn: Callable[..., dict[str, Any]], *args: Any, name: str) -> Any:
        self._n += 1
        self._done.append((self._n, fn(*args), None))
        return self._n

    def wait_one(self) -> Outcome:
        return self._done.pop(0)

    def cancel(self, tokens: Iterable[Any]) -> None:
        self._done.clear()


class _FilesTarget:
    """Cube files per input: the serial run's claims and markers."""

    store: Path | None = None

    def __init__(self, run: ReconstructRun) -> None:
        out, cfg = run.out_dir, run.cfg
        self.out = out
        self.claims = OutputClaims(
            out, run.fingerprint, planned_outputs=lambda p: output_paths(out / p.stem, cfg)
        )

    @contextlib.contextmanager
    def opened(self) -> Iterator[_FilesTarget]:
        yield self

    def cleaned(self) -> list[Path]:
        return clean_run_leftovers(self.out)

    def is_done(self, inp: Path) -> bool:
        return self.claims.is_done(inp)

    def begin(self, inp: Path) -> Any:
        claim = self.claims.claim(inp)
        try:
            claim.begin()
        except BaseException:
            claim.abandon()
            raise
        return claim

    def frame(self, handle: Any) -> int | None:
        return None

    def _clean(self, claim: Any) -> None:
        """Temporary files of a killed attempt at this input's outputs (its name lock is held:
        no one else writes these names)."""
        for p in claim.planned:
            q = Path(p)
            pattern = os.path.join(glob.escape(str(q.parent)), f".{glob.escape(q.name)}.*.tmp")
            for t in glob.glob(pattern):
                remove_output(Path(t))

    def finish(self, handle: Any, outputs: list[str]) -> None:
        self._clean(handle)
        handle.finish([Path(p) for p in outputs])

    def fail(self, handle: Any) -> None:
        with contextlib.suppress(OSError):
            self._clean(handle)
        handle.abandon()


class _StoreTarget:
    """One dataset store: a frame per input, complete when its ``done`` flag is set."""

    def __init__(self, run: ReconstructRun) -> None:
        self.run = run
        self.store: Path | None = run.out_dir / DATASET_NAME
        self.ds: CubeDataset | None = None

    @contextlib.contextmanager
    def opened(self) -> Iterator[_StoreTarget]:
        run = self.run
        attrs = {"bundle": str(run.bundle_path), "hsi_torch_version": __version__}
        with CubeDataset.open(self.store, run.inputs, run.wavelengths_nm, run.frame_size,
                              attrs) as ds:  # fmt: skip
            self.ds = ds
            yield self

    def cleaned(self) -> list[Path]:
        out: list[Path] = []
        for name in ("cube", "valid", "metadata", "done", "source"):
            out += clean_stale_temp_files(self.store / name)
        return out

    def is_done(self, inp: Path) -> bool:
        try:
            stamp = input_stamp(inp)
        except OSError:
            return False
        return self.ds.is_done(inp, stamp, self.run.fingerprint)

    def begin(self, inp: Path) -> Any:
        if not inp.exists():
            raise FileNotFoundError(f"input file not found: {inp}")
        i = self.ds.index[os.path.abspath(inp)]
        self.ds.mark_pending(i)
        return i

    def frame(self, handle: Any) -> int | None:
        return handle

    def finish(self, handle: Any, outputs: list[str]) -> None:
        self.ds.clean_frame_temps(handle)

    def fail(self, handle: Any) -> None:
        with contextlib.suppress(OSError):
            self.ds.clean_frame_temps(handle)


def _failure_text(exc: BaseException) -> str:
    text = f"{type(exc).__name__}: {exc}"
    if type(exc).__name__ == "KilledWorker":
        text += (" (the worker process died each time it ran this input: out of memory? see "
                 "'sizing workers' in docs/cluster.md)")  # fmt: skip
    return text


def run_many(
    run: ReconstructRun,
    executor: Executor,
    *,
    output_format: str = "files",
    resume: bool = True,
    progress: bool = True,
    threads: int | None = None,
    verify_bundle: bool = False,
    send_bundle: bool = False,
) -> ManySummary:
    """Run every input of ``run`` through ``executor`` (see the module docstring).

    Creates the output folder and the run's configuration file (:meth:`ReconstructRun.start`)
    first. ``threads``: torch/numba threads per frame in the workers (``None``: each worker's
    Dask thread count). ``verify_bundle``: workers check their bundle file's SHA-256 (a cluster
    whose workers may not share this file system). ``send_bundle``: the tasks get the bundle's
    bytes (:meth:`Executor.share`) instead of its path.

    Returns:
        :class:`ManySummary`.

    Raises:
        ValueError: unknown ``output_format``, or ``zarr`` without its packages (before anything
            is written).
    """
    if output_format not in OUTPUT_FORMATS:
        raise ValueError(f"output format must be one of {', '.join(OUTPUT_FORMATS)}, got "
                         f"{output_format!r}")  # fmt: skip
    if output_format == "zarr":
        if run.cfg.uncertainty:
            raise ValueError("--format zarr does not store the uncertainty (config key "
                             "'uncertainty'); write cube files for it")
        try:
            require_dataset_packages()
        except ModuleNotFoundError as exc:
            raise ValueError(f"--format zarr: {exc}") from None
    run.start()
    run = dataclasses.replace(
        run, out_dir=Path(os.path.abspath(run.out_dir)),
        run_config=Path(os.path.abspath(run.run_config)) if run.run_config else None,
    )  # fmt: skip
    st = run.bundle_path.stat()
    key = file_sha256(run.bundle_path) if (verify_bundle or send_bundle) else run.fingerprint
    target: Any = _StoreTarget(run) if output_format == "zarr" else _FilesTarget(run)
    summary = ManySummary(store=target.store)
    t0 = time.perf_counter()
    order = {p: k for k, p in enumerate(run.inputs)}
    with target.opened():
        plan = FramePlan(
            run=dataclasses.replace(run, inputs=[]), bundle_key=key,
            bundle_stamp=(int(st.st_size), int(st.st_mtime_ns)), output_format=output_format,
            store=str(target.store) if target.store is not None else None, threads=threads,
            verify_bundle=verify_bundle,
        )  # fmt: skip
        bundle_bytes = executor.share(run.bundle_path.read_bytes()) if send_bundle else None
        summary.cleaned = target.cleaned()
        bar = progress_bar(total=len(run.inputs), enabled=progress, desc="reconstruct",
                           unit="file", leave=True)  # fmt: skip
        pending: dict[Any, tuple[Path, Any]] = {}

        def fail(inp: Path, error: str, tb: str = "") -> None:
            summary.failed.append(BatchFailure(inp, error, tb))
            if progress:
                bar.set_postfix(failed=len(summary.failed))

        def collect() -> None:
            token, result, exc = executor.wait_one()
            inp, handle = pending.pop(token)
            bar.update(1)
            if result is not None:
                summary.threads[result["worker"]] = result["threads"]
                if result.get("prepare_s") is not None:
                    key = f"{result['worker']} pid {result['pid']}"
                    summary.prepare_s[key] = result["prepare_s"]
            if exc is not None or result is None or not result.get("ok"):
                target.fail(handle)
                if exc is not None:
                    fail(inp, _failure_text(exc), "".join(traceback.format_exception(exc)))
                else:
                    fail(inp, str((result or {}).get("error")), (result or {}).get("traceback", ""))
                return
            for msg in result.get("warnings", []):
                warn(f"WARNING {inp}: {msg}")
            try:
                target.finish(handle, result["outputs"])
            except Exception as e:  # noqa: BLE001 - e.g. the done marker cannot be written
                target.fail(handle)
                fail(inp, f"{type(e).__name__}: {e}", traceback.format_exc())
                return
            summary.processed.append(inp)
            summary.outputs[inp] = [Path(p) for p in result["outputs"]]
            summary.workers[inp] = result["worker"]
            frame = target.frame(handle)
            if frame is not None:
                summary.frames[inp] = frame

        try:
            for inp in run.inputs:
                if resume and target.is_done(inp):
                    summary.skipped.append(inp)
                    bar.update(1)
                    continue
                try:
                    handle = target.begin(inp)
                    stamp = input_stamp(inp)
                except Exception as exc:  # noqa: BLE001 - the input's failure
                    fail(inp, f"{type(exc).__name__}: {exc}", traceback.format_exc())
                    bar.update(1)
                    continue
                token = executor.submit(
                    reconstruct_task, plan, os.path.abspath(inp), target.frame(handle), stamp,
                    bundle_bytes, name=f"{inp.stem}-{order[inp]}",
                )  # fmt: skip
                pending[token] = (inp, handle)
                while len(pending) >= executor.window():
                    collect()
            while pending:
                collect()
        except BaseException:
            executor.cancel(list(pending))
            for _, handle in pending.values():
                with contextlib.suppress(Exception):
                    target.fail(handle)
            raise
        finally:
            bar.close()
            summary.elapsed_s = time.perf_counter() - t0
    summary.processed.sort(key=order.__getitem__)
    summary.failed.sort(key=lambda f: order[f.input])
    return summary


def run_on_client(
    run: ReconstructRun,
    client: Any,
    *,
    threads: int | None = None,
    send_bundle: bool = False,
    output_format: str = "files",
    resume: bool = True,
    progress: bool = True,
) -> ManySummary:
    """:func:`run_many` on the workers of ``client`` (a ``distributed.Client``); the workers
    check their bundle file by SHA-256 unless ``send_bundle``."""
    return run_many(run, DaskExecutor(client), output_format=output_format, resume=resume,
                    progress=progress, threads=threads, verify_bundle=not send_bundle,
                    send_bundle=send_bundle)  # fmt: skip


def _load_cfg(config: ReconstructConfig | Mapping[str, Any] | str | os.PathLike | None,
              overrides: list[str] | None) -> ReconstructConfig:  # fmt: skip
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
    output_format: str = "files",
    resume: bool = True,
    progress: bool = True,
    device: str | None = None,
    threads_per_worker: int | None = None,
    send_bundle: bool = False,
    security: Any | None = None,
) -> BatchSummary:
    """Reconstruct many captures with one bundle, on a Dask cluster or in this process.

    Args:
        inputs: capture files and/or glob patterns.
        bundle: the calibration bundle (``.npz``).
        out_dir: output folder (as ``hsi-torch reconstruct --out``).
        client: a ``distributed.Client``, a scheduler spec (``"local:N"``,
            ``"tcp://host:8786"``; see :func:`hsi_torch.recon.distributed.connect`), or
            ``None``: this process (the serial run for ``files``).
        config: a :class:`ReconstructConfig`, a mapping, a YAML file, or ``None`` (the shipped
            ``reconstruct.yaml``); ``overrides``: ``["beta=1e3", ...]`` on top.
        output_format: ``"files"`` (the configured cube formats, previews) or ``"zarr"`` (one
            dataset store ``out_dir/cubes.zarr``).
        resume: skip inputs whose outputs exist (unchanged, same input and settings).
        progress: a progress bar over completed inputs on stderr.
        device: torch device of the frames (``"cuda"``: each worker its GPU).
        threads_per_worker: torch/numba threads per frame on a worker (default: cores / N for
            ``local:N``, else each worker's Dask thread count).
        send_bundle: send the bundle's bytes to the workers (they do not see its file).
        security: for a ``tls://`` scheduler spec, a ``distributed.security.Security``
            (:func:`hsi_torch.recon.distributed.make_security`).

    Returns:
        The summary (a :class:`ManySummary` unless it was the serial run): ``processed``,
        ``skipped``, ``failed`` (input, reason), ``outputs`` per input; ``exit_code`` is 1 when
        any input failed.

    Raises:
        ValueError: a bad option, a glob that matches nothing, a bad bundle or configuration
            (before anything is written).

    Example:
        >>> from distributed import Client                              # doctest: +SKIP
        >>> s = reconstruct_many("shots/*.tif", "calib.npz", "cubes/",  # doctest: +SKIP
        ...                      client=Client("tcp://head:8786"), output_format="zarr")
        >>> s.exit_code, [f.error for f in s.failed]                    # doctest: +SKIP
    """
    cfg = _load_cfg(config, overrides)
    if output_format not in OUTPUT_FORMATS:
        raise ValueError(f"output_format must be one of {', '.join(OUTPUT_FORMATS)}, got "
                         f"{output_format!r}")  # fmt: skip
    if client is None and (threads_per_worker or send_bundle):
        raise ValueError("threads_per_worker and send_bundle need a client (a cluster)")
    run = check_run(inputs, bundle, out_dir, cfg, device=device,
                    formats=output_format == "files", device_here=client is None)  # fmt: skip
    if client is None:
        if output_format == "files":
            run.start()
            return run_serial(run, resume=resume, progress=progress)
        return run_many(run, InlineExecutor(), output_format=output_format, resume=resume,
                        progress=progress)  # fmt: skip
    if isinstance(client, (str, os.PathLike)):
        with connect(str(client), threads_per_worker=threads_per_worker,
                     security=security) as (cl, threads):  # fmt: skip
            return run_on_client(run, cl, threads=threads, send_bundle=send_bundle,
                                 output_format=output_format, resume=resume, progress=progress)
    return run_on_client(run, client, threads=threads_per_worker, send_bundle=send_bundle,
                         output_format=output_format, resume=resume, progress=progress)


def run_many_cli(run: ReconstructRun, args: argparse.Namespace, output_format: str) -> ManySummary:
    """``hsi-torch reconstruct`` with ``--scheduler``, ``--scheduler-file`` or ``--format zarr``
    (called by :func:`hsi_torch.recon.cli_entry.run_reconstruct` after the run was checked)."""
    scheduler = getattr(args, "scheduler", None)
    scheduler_file = getattr(args, "scheduler_file", None)
    threads = getattr(args, "threads_per_worker", None)
    send = bool(getattr(args, "send_bundle", False))
    resume = getattr(args, "resume", True)
    progress = getattr(args, "progress", True)
    if not (scheduler or scheduler_file):
        if threads or send:
            raise ValueError("--threads-per-worker and --send-bundle need --scheduler or "
                             "--scheduler-file")  # fmt: skip
        return run_many(run, InlineExecutor(), output_format=output_format, resume=resume,
                        progress=progress)  # fmt: skip
    security = make_security(getattr(args, "tls_ca_file", None), getattr(args, "tls_cert", None),
                             getattr(args, "tls_key", None))  # fmt: skip
    with connect(scheduler, scheduler_file, threads_per_worker=threads,
                 security=security) as (client, nthreads):  # fmt: skip
        return run_on_client(run, client, threads=nthreads, send_bundle=send,
                             output_format=output_format, resume=resume, progress=progress)
