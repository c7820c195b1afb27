"""The loop of every batch run: the inputs, an output target, an executor — serial or Dask.

:func:`drive` runs one cycle per input, the same whether the work runs in this process
(:class:`InlineExecutor`: each task at once, in order) or on a cluster's workers
(:class:`hsi_torch.recon.distributed.DaskExecutor`: a bounded number in flight, taken as they
complete):

check the input's name → **skip** it when the target says it is done (``resume``) → **claim** it
(:meth:`OutputTarget.begin <hsi_torch.recon.batch.targets.OutputTarget.begin>`) → **hand out** its
task (``task(*args(input, frame))``, which returns ``{"ok": True, "outputs": [...], "warnings":
[...], ...}`` or ``{"ok": False, "error", "traceback"}`` instead of raising) → **collect** it
(notes and warnings printed, findings kept in :attr:`RunSummary.findings`) → **finish** or
**abandon** (the earlier marker back, the failure recorded); ``docs/architecture.md``, *A
reconstruction run, end to end*.

A skipped input's findings are those stored with its outputs
(:meth:`OutputTarget.stored_findings <hsi_torch.recon.batch.targets.FilesTarget.stored_findings>`,
read from the cube's metadata only): printed again and kept in the summary, so a rerun reports
what the first run found.

A failure at any step fails that input alone (its reason and traceback in
:attr:`RunSummary.failed`); the others run. ``KeyboardInterrupt`` (and any other
``BaseException``) cancels the tasks not yet started, releases the claims of unfinished inputs
and propagates. The summary lists processed, skipped and failed inputs in input order; its
``exit_code`` is 1 when any input failed.
"""

from __future__ import annotations

import contextlib
import sys
import time
import traceback
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Protocol

from hsi_torch.console import info, progress_bar, warn
from hsi_torch.findings import Finding, findings_from_dicts, findings_summary
from hsi_torch.io.paths import check_input_name, shown_path
from hsi_torch.provenance import provenance
from hsi_torch.recon.batch.targets import OutputTarget

__all__ = [
    "drive",
    "Executor",
    "InlineExecutor",
    "RunSummary",
    "RunFailure",
    "print_summary",
]

#: ``(token, result, exception)`` of a completed task
Outcome = tuple[Any, "dict[str, Any] | None", "BaseException | None"]


@dataclass
class RunFailure:
    """One failed input: ``error`` is ``"ExceptionType: message"``; ``traceback`` the full text."""

    input: Path
    error: str
    traceback: str = field(default="", repr=False)


@dataclass
class RunSummary:
    """Outcome of a run.

    Attributes:
        processed: inputs processed successfully in this run (input order).
        skipped: inputs skipped because their outputs existed (resume).
        failed: the failures, in input order.
        outputs: input → output paths its task reported (processed inputs only).
        elapsed_s: wall time of the run in seconds.
        cleaned: stale temporary files removed: those of killed runs at the start, and those of
            this run's writers killed mid-file (a cluster worker) once every task has ended.
        frames: input → frame index in the dataset store (a store target).
        workers: input → the cluster worker that reconstructed it (runs on a cluster).
        prepare_s: worker process → seconds its bundle preparation took (processes that
            prepared it in this run; a restarted worker appears once per process).
        threads: worker → its torch and numba thread counts during its last frame.
        store: the dataset store, if any.
        provenance: the command line, package version, git commit and the torch / NumPy /
            Python versions of the run (:func:`hsi_torch.provenance.provenance`).
        findings: input → its findings (:class:`~hsi_torch.findings.Finding`): those its task
            reported (processed, and failed ones that carried any) or those stored with its
            outputs (skipped).
        findings_report: the run's JSON report of them, once written
            (:func:`hsi_torch.recon.batch.report.write_findings_report`).
    """

    processed: list[Path] = field(default_factory=list)
    skipped: list[Path] = field(default_factory=list)
    failed: list[RunFailure] = field(default_factory=list)
    outputs: dict[Path, list[Path]] = field(default_factory=dict)
    elapsed_s: float = 0.0
    cleaned: list[Path] = field(default_factory=list)
    frames: dict[Path, int] = field(default_factory=dict)
    workers: dict[Path, str] = field(default_factory=dict)
    prepare_s: dict[str, float] = field(default_factory=dict)
    threads: dict[str, dict[str, int]] = field(default_factory=dict)
    store: Path | None = None
    provenance: dict[str, Any] = field(default_factory=provenance)
    findings: dict[Path, list[Finding]] = field(default_factory=dict)
    findings_report: Path | None = None

    @property
    def total(self) -> int:
        return len(self.processed) + len(self.skipped) + len(self.failed)

    @property
    def ok(self) -> bool:
        return not self.failed

    @property
    def exit_code(self) -> int:
        """0 when nothing failed, else 1 (the CLI's exit status)."""
        return 0 if self.ok else 1

    def report(self) -> str:
        """Multi-line text: one line of counts, then one line per failure (and, for a cluster
        or a store, the workers, the bundle preparations and the store)."""
        head = (
            f"{self.total} input(s): {len(self.processed)} processed, {len(self.skipped)} skipped "
            f"(outputs exist), {len(self.failed)} failed in {self.elapsed_s:.1f} s"
        )
        lines = [head]
        every = [f for fs in self.findings.values() for f in fs]
        if every or self.findings_report is not None:
            where = f" (report: {shown_path(self.findings_report)})" if self.findings_report else ""
            lines.append(f"  findings: {findings_summary(every)}{where}")
        if self.cleaned:
            lines.append(f"  removed {len(self.cleaned)} stale temporary file(s) of an "
                         "interrupted run or a killed worker")
        lines += [f"  FAILED {shown_path(f.input)}: {f.error}" for f in self.failed]
        n = len(set(self.workers.values()))
        if n:
            lines.append(f"  frames reconstructed by {n} worker(s)")
        if self.prepare_s:
            secs = ", ".join(f"{s:.1f}" for s in self.prepare_s.values())
            lines.append(f"  bundle prepared {len(self.prepare_s)} time(s), once per worker "
                         f"({secs} s)")  # fmt: skip
        if self.store is not None:
            lines.append(f"  dataset store: {self.store}")
        return "\n".join(lines)


def print_summary(summary: RunSummary, file: IO[str] | None = None) -> None:
    """Print :meth:`RunSummary.report` (counts, then every failure) to ``file`` (stderr)."""
    print(summary.report(), file=file if file is not None else sys.stderr)


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
    """Runs each task at once, in this process, in input order (the serial run)."""

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


def _failure_text(exc: BaseException) -> str:
    text = f"{type(exc).__name__}: {exc}"
    if type(exc).__name__ == "KilledWorker":
        text += (" (the worker process died each time it ran this input: out of memory? see "
                 "'sizing workers' in docs/cluster.md)")  # fmt: skip
    return text


def _task_findings(inp: Path, result: dict[str, Any] | None) -> list[Finding]:
    """The findings a task's result carries (``"findings"``: a list of dicts); an unreadable
    entry becomes a ``run.findings_unreadable`` warning instead of failing the input."""
    try:
        return findings_from_dicts((result or {}).get("findings"), source=f"task of {inp}")
    except ValueError as exc:
        return [Finding("run.findings_unreadable", "warning", str(exc), source=str(inp))]


def _stored_findings(target: OutputTarget, inp: Path) -> list[Finding]:
    """The findings stored with a skipped input's outputs, printed as the run's own are (notes
    as info, the rest as warnings); an unreadable store of them is itself a warning."""
    read = getattr(target, "stored_findings", None)
    try:
        found = list(read(inp)) if read is not None else []
    except (OSError, ValueError) as exc:  # FileFormatError, InputError: the message names it
        found = [Finding("run.findings_unreadable", "warning",
                         f"the findings stored with the skipped input's outputs cannot be read: "
                         f"{exc}", source=str(inp))]  # fmt: skip
    name = shown_path(inp)
    for f in found:
        if f.severity == "info":
            info(f"{Path(name).name} (skipped, stored): {f.text()}")
        else:
            warn(f"WARNING {name} (skipped; stored with its outputs): {f.text()}")
    return found


def drive(
    inputs: Sequence[Path],
    target: OutputTarget,
    executor: Executor,
    task: Callable[..., dict[str, Any]],
    args: Callable[[Path, int | None], tuple[Any, ...]],
    *,
    resume: bool = True,
    progress: bool = True,
    desc: str = "reconstruct",
) -> RunSummary:
    """Run every input through ``executor`` into ``target`` (see the module docstring).

    Args:
        inputs: the inputs, in order (expanded: see :func:`hsi_torch.io.paths.expand_inputs`).
        target: where the outputs go (resume, claims).
        executor: where the tasks run.
        task: the function a task runs; args: ``(input, frame) -> task's arguments``.
        resume: skip inputs the target says are done.
        progress: a progress bar over completed inputs on stderr; desc: its label.

    Returns:
        :class:`RunSummary`.
    """
    summary = RunSummary(store=target.store)
    t0 = time.perf_counter()
    order = {p: k for k, p in enumerate(inputs)}
    with target.opened():
        summary.cleaned = target.cleaned()
        bar = progress_bar(total=len(inputs), enabled=progress, desc=desc, unit="file",
                           leave=True)  # fmt: skip
        pending: dict[Any, tuple[Path, Any]] = {}

        def fail(inp: Path, error: str, tb: str = "") -> None:
            summary.failed.append(RunFailure(inp, error, tb))
            if progress:
                bar.set_postfix(failed=len(summary.failed))

        def collect() -> None:
            token, result, exc = executor.wait_one()
            inp, handle = pending.pop(token)
            bar.update(1)
            worker = (result or {}).get("worker", "local")
            if worker != "local":
                summary.threads[worker] = result["threads"]
                if result.get("prepare_s") is not None:
                    summary.prepare_s[f"{worker} pid {result['pid']}"] = result["prepare_s"]
            summary.findings[inp] = _task_findings(inp, result)
            if exc is not None or result is None or not result.get("ok"):
                target.fail(handle)
                if exc is not None:
                    fail(inp, _failure_text(exc), "".join(traceback.format_exception(exc)))
                else:
                    fail(inp, str((result or {}).get("error")), (result or {}).get("traceback", ""))
                return
            for msg in result.get("notes", []):  # what was assumed (black level, exposure)
                info(f"{Path(shown_path(inp)).name}: {msg}")
            for msg in result.get("warnings", []):
                warn(f"WARNING {shown_path(inp)}: {msg}")
            try:
                stale = target.finish(handle, result["outputs"])
            except Exception as e:  # noqa: BLE001 - e.g. the done marker cannot be written
                target.fail(handle)
                fail(inp, f"{type(e).__name__}: {e}", traceback.format_exc())
                return
            for p in stale or []:
                info(f"{Path(shown_path(inp)).name}: removed {Path(p).name}, an earlier run's "
                     "output this run does not make (it described the earlier cube)")
            summary.processed.append(inp)
            summary.outputs[inp] = [Path(p) for p in result["outputs"]]
            if worker != "local":
                summary.workers[inp] = worker
            frame = target.frame(handle)
            if frame is not None:
                summary.frames[inp] = frame

        try:
            for inp in inputs:
                handle = None
                try:
                    check_input_name(inp)
                    if resume and target.is_done(inp):
                        summary.skipped.append(inp)
                        summary.findings[inp] = _stored_findings(target, inp)
                        bar.update(1)
                        continue
                    handle = target.begin(inp)
                    call = args(inp, target.frame(handle))
                except Exception as exc:  # noqa: BLE001 - the input's failure
                    tb = traceback.format_exc()
                    if handle is not None:
                        with contextlib.suppress(Exception):
                            target.fail(handle)
                    fail(inp, f"{type(exc).__name__}: {exc}", tb)
                    bar.update(1)
                    continue
                try:
                    token = executor.submit(task, *call, name=f"{inp.stem}-{order[inp]}")
                except BaseException:  # (an inline task interrupted: its claim released)
                    target.fail(handle)
                    raise
                pending[token] = (inp, handle)
                while len(pending) >= executor.window():
                    collect()
            while pending:
                collect()
            # a worker killed mid-file (its task retried elsewhere) left its temporary file:
            # every task has ended, so none of this run's writers is still writing
            summary.cleaned += target.cleaned()
        except BaseException:
            executor.cancel(list(pending))
            for _, held in pending.values():
                with contextlib.suppress(Exception):  # the others are released all the same
                    target.fail(held)
            raise
        finally:
            bar.close()
            summary.elapsed_s = time.perf_counter() - t0
    summary.processed.sort(key=order.__getitem__)
    summary.failed.sort(key=lambda f: order[f.input])
    summary.findings = dict(sorted(summary.findings.items(), key=lambda kv: order[kv[0]]))
    return summary
