"""Batch processing of many input files: glob expansion, progress, resume, failures collected.

:func:`run_batch` calls ``process(input_path)`` for every input in order. A failing input is
recorded (exception type and message) and the batch continues; ``KeyboardInterrupt`` stops it.
With ``resume=True`` an input is skipped when its outputs already exist:

- if ``expected_outputs(input)`` is given: when every path it returns is a non-empty file;
- otherwise: when the input's *done-marker* says it finished and every output it lists is still
  the file that was written (same size and modification time: an emptied, truncated or replaced
  output is not "done"). Markers live in ``out_dir/.hsi_torch_done/`` (one small JSON per input,
  named ``<stem>-<hash of the absolute input path>.json``). Before ``process`` runs, the marker is
  written as a *claim* (``"status": "started"``, the planned outputs); after ``process`` returned,
  atomically, as ``"status": "done"`` with the outputs and their sizes and times — so an
  interrupted or failed input is never mistaken for a finished one. The marker also records the
  input file's size and modification time and the run's ``fingerprint`` (e.g. a hash of the
  configuration and the bundle): an input that changed since, or a rerun with different
  settings, is processed again instead of being skipped.

**Outputs belong to one input.** With ``planned_outputs(input)`` (the files ``process`` will
write), an input whose outputs were claimed by *another* input — e.g. ``A/x.tif`` and
``B/x.tif`` both writing ``out/x.*`` — fails with an error naming both inputs, in the same run or
a later one, instead of overwriting the other's files. The claim lapses once none of the other
input's outputs exists any more (delete them to hand the names over).

**Leftovers of killed runs.** At the start of a run the temporary files that killed writers left
in ``out_dir`` and the marker folder (:func:`hsi_torch.io.atomic.clean_stale_temp_files`: only
this package's own ``.<name>.<pid>-<random>.tmp`` files whose process is gone) are deleted;
:attr:`BatchSummary.cleaned` lists them.

``process`` should write its files atomically (:func:`hsi_torch.io.atomic.atomic_write`) so a
crash leaves no partial output. Inputs run sequentially in this process; the per-frame work
(torch) is what uses the cores. (Should worker processes ever be added: rawpy/LibRaw with OpenMP
can deadlock under ``fork`` — use the ``spawn`` start method.)
"""

from __future__ import annotations

import contextlib
import glob
import hashlib
import json
import os
import sys
import time
import traceback
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from hsi_torch.console import progress_bar
from hsi_torch.errors import InputError
from hsi_torch.io.atomic import (
    atomic_write_json,
    clean_stale_temp_files,
    lock_or_refuse,
    mark_lock_holder,
)

__all__ = [
    "BatchFailure",
    "BatchSummary",
    "expand_inputs",
    "run_batch",
    "print_summary",
    "DONE_DIR",
    "check_out_dir",
    "ensure_out_dir",
    "fingerprint_of",
    "OutputClaims",
    "InputClaim",
    "clean_run_leftovers",
    "input_stamp",
]

DONE_DIR = ".hsi_torch_done"
_GLOB_CHARS = set("*?[")

ProcessFn = Callable[[Path], "Path | str | Sequence[Path | str] | None"]
PathsFn = Callable[[Path], Sequence["Path | str"]]


@dataclass
class BatchFailure:
    """One failed input: ``error`` is ``"ExceptionType: message"``; ``traceback`` the full text."""

    input: Path
    error: str
    traceback: str = field(default="", repr=False)


@dataclass
class BatchSummary:
    """Outcome of :func:`run_batch`.

    Attributes:
        processed: inputs processed successfully in this run.
        skipped: inputs skipped because their outputs existed (resume).
        failed: the failures, in input order.
        outputs: input → output paths reported by ``process`` (processed inputs only).
        elapsed_s: wall time of the batch in seconds.
        cleaned: stale temporary files of killed runs removed at the start.
    """

    processed: list[Path] = field(default_factory=list)
    skipped: list[Path] = field(default_factory=list)
    failed: list[BatchFailure] = field(default_factory=list)
    outputs: dict[Path, list[Path]] = field(default_factory=dict)
    elapsed_s: float = 0.0
    cleaned: list[Path] = field(default_factory=list)

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
        """Multi-line text: one line of counts, then one line per failure."""
        head = (
            f"{self.total} input(s): {len(self.processed)} processed, {len(self.skipped)} skipped "
            f"(outputs exist), {len(self.failed)} failed in {self.elapsed_s:.1f} s"
        )
        lines = [head]
        if self.cleaned:
            lines.append(f"  removed {len(self.cleaned)} stale temporary file(s) of an "
                         "interrupted run")
        lines += [f"  FAILED {f.input}: {f.error}" for f in self.failed]
        return "\n".join(lines)


def expand_inputs(inputs: Iterable[str | os.PathLike]) -> list[Path]:
    """Expand files and glob patterns (``*``, ``?``, ``[...]``, recursive ``**``) into paths.

    Patterns expand to their matches in sorted order; plain paths are kept as given (a missing
    plain file becomes a per-input failure later, not an error here). Duplicates are dropped,
    first occurrence kept.

    Raises:
        ValueError: a pattern matches nothing, or an input is a directory.
    """
    if isinstance(inputs, (str, os.PathLike)):
        inputs = [inputs]
    out: list[Path] = []
    seen: set[str] = set()
    for item in inputs:
        text = os.fspath(item)
        if _GLOB_CHARS & set(text) and not os.path.exists(os.path.expanduser(text)):
            matches = sorted(m for m in glob.glob(os.path.expanduser(text), recursive=True))
            matches = [m for m in matches if not os.path.isdir(m)]
            if not matches:
                raise ValueError(f"input pattern {text!r} matches no files")
            paths = [Path(m) for m in matches]
        else:
            p = Path(os.path.expanduser(text))
            if p.is_dir():
                raise ValueError(
                    f"input {text!r} is a directory; pass files or a pattern such as "
                    f"'{Path(text) / '*.tif'}'"
                )
            paths = [p]
        for p in paths:
            key = os.path.abspath(p)
            if key not in seen:
                seen.add(key)
                out.append(p)
    return out


def _marker_path(out_dir: Path, inp: Path) -> Path:
    digest = hashlib.sha1(os.path.abspath(inp).encode("utf-8")).hexdigest()[:10]
    return out_dir / DONE_DIR / f"{inp.stem}-{digest}.json"


def check_out_dir(path: str | os.PathLike) -> Path:
    """Refuse an output folder ``path`` that exists as something else (creates nothing).

    Raises:
        ValueError: ``path`` exists and is not a folder.
    """
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise ValueError(f"output folder {p} exists and is not a folder")
    return p


def ensure_out_dir(path: str | os.PathLike) -> Path:
    """Create the output folder ``path`` (and its parents); errors name the folder.

    Raises:
        ValueError: ``path`` exists and is not a folder.
        OSError: it cannot be created (the message names the folder and the reason).
    """
    p = check_out_dir(path)
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OSError(f"cannot create output folder {p}: {exc.strerror or exc}") from None
    return p


def fingerprint_of(obj: Any) -> str:
    """A short stable hash of a JSON-serialisable ``obj`` (keys sorted), for ``run_batch``."""
    text = json.dumps(obj, sort_keys=True, default=str)
    return hashlib.sha1(text.encode("utf-8")).hexdigest()


def input_stamp(inp: Path) -> list[int]:
    """``[size, mtime_ns]`` of an input file (how resume tells that it changed).

    Raises:
        OSError: it cannot be read (missing, ...).
    """
    st = inp.stat()
    return [int(st.st_size), int(st.st_mtime_ns)]


def _file_stamp(path: str | os.PathLike) -> list[int] | None:
    """``[size, mtime_ns]`` of a regular file, ``None`` when it is missing or not a file."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    if not os.path.isfile(path):
        return None
    return [int(st.st_size), int(st.st_mtime_ns)]


def _read_marker(path: Path) -> dict[str, Any] | None:
    try:
        rec = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    return rec if isinstance(rec, dict) else None


def _outputs_intact(rec: dict[str, Any]) -> bool:
    """Every output the marker lists is still the (non-empty) file that was written."""
    outputs = rec.get("outputs")
    if not isinstance(outputs, list):
        return False
    stamps = rec.get("output_stamps")
    for p in outputs:
        now = _file_stamp(p)
        if now is None or now[0] == 0:
            return False
        if isinstance(stamps, dict) and stamps.get(str(p)) != now:  # truncated or replaced
            return False
    return True


def _is_done(
    inp: Path,
    out_dir: Path,
    expected_outputs: PathsFn | None,
    fingerprint: str | None = None,
) -> bool:
    if expected_outputs is not None:
        paths = [Path(p) for p in expected_outputs(inp)]
        return bool(paths) and all((_file_stamp(p) or [0])[0] > 0 for p in paths)
    rec = _read_marker(_marker_path(out_dir, inp))
    if rec is None or rec.get("status", "done") != "done":  # none, unreadable, or interrupted
        return False
    try:
        stamp = input_stamp(inp)
    except OSError:
        return False
    if rec.get("input_stamp") != stamp:  # the input changed since it was processed
        return False
    if fingerprint is not None and rec.get("fingerprint") != fingerprint:  # other settings
        return False
    return _outputs_intact(rec)


class _Owners:
    """Which input each output path of ``out_dir`` belongs to, from the markers."""

    def __init__(self, out_dir: Path) -> None:
        self.by_output: dict[str, tuple[str, Path]] = {}
        self.outputs_of: dict[Path, list[str]] = {}
        folder = out_dir / DONE_DIR
        markers = sorted(folder.glob("*.json")) if folder.is_dir() else []
        for m in markers:
            rec = _read_marker(m)
            if rec is None or not isinstance(rec.get("input"), str):
                continue
            outs = [str(p) for p in rec.get("outputs", []) if isinstance(p, str)]
            self.claim(m, rec["input"], outs)

    def refresh(self, out_dir: Path, stem: str) -> None:
        """Re-read the markers of inputs named ``stem`` (another run may have written some)."""
        for m in (out_dir / DONE_DIR).glob(f"{glob.escape(stem)}-*.json"):
            rec = _read_marker(m)
            if rec is not None and isinstance(rec.get("input"), str):
                outs = [str(p) for p in rec.get("outputs", []) if isinstance(p, str)]
                self.claim(m, rec["input"], outs)

    def claim(self, marker: Path, inp: str, outputs: Sequence[str]) -> None:
        self.outputs_of[marker] = list(outputs)
        for p in outputs:
            self.by_output[p] = (inp, marker)

    def conflict(self, inp: str, outputs: Sequence[str]) -> tuple[str, list[str]] | None:
        """The other input that holds some of ``outputs`` (one of its outputs still exists),
        and the outputs in question; lapsed claims are dropped (their marker deleted)."""
        for p in outputs:
            owner = self.by_output.get(p)
            if owner is None or owner[0] == inp:
                continue
            other, marker = owner
            held = self.outputs_of.get(marker, [])
            if any(os.path.lexists(q) for q in held):
                return other, [q for q in outputs if self.by_output.get(q, ("",))[0] == other]
            for q in held:  # nothing of it is left: the names are free again
                if self.by_output.get(q, ("",))[0] == other:
                    del self.by_output[q]
            self.outputs_of.pop(marker, None)
            marker.unlink(missing_ok=True)
        return None


@contextlib.contextmanager
def _name_lock(out_dir: Path, stem: str) -> Iterator[None]:
    """Hold ``out_dir/.hsi_torch_done/<stem>.lock`` (an exclusive ``flock``) while the outputs
    named ``stem`` are written; another run holding it makes this input fail at once, naming
    that run's process id. (No locking where ``fcntl`` does not exist.)"""
    if os.name != "posix":  # no fcntl
        yield
        return
    folder = out_dir / DONE_DIR
    folder.mkdir(exist_ok=True)
    path = folder / f"{stem}.lock"
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        lock_or_refuse(fd, lambda holder: (
            f"outputs named '{stem}' in {out_dir} are being written by another run (process "
            f"{holder}) right now; run again when it has finished"))
        try:  # still the file at that name? (its holder removes it when done)
            same = os.stat(path).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    try:
        mark_lock_holder(fd)
        yield
    finally:
        with contextlib.suppress(OSError):
            os.unlink(path)  # while still held: a waiting run re-checks the name (above)
        os.close(fd)  # releases the lock


def _release_claim(
    owners: _Owners | None, marker: Path, inp: str, previous: dict[str, Any] | None
) -> None:
    """After a failed input: its earlier marker back (its earlier outputs, if any are left,
    are still its own), or no marker at all."""
    try:
        if previous is not None:
            atomic_write_json(marker, previous)
            if owners is not None:
                outs = [str(p) for p in previous.get("outputs", []) if isinstance(p, str)]
                owners.claim(marker, inp, outs)
        else:
            marker.unlink(missing_ok=True)
            if owners is not None:
                owners.outputs_of.pop(marker, None)
    except OSError:
        pass  # the claim stays: the input is redone next time, never skipped


def _as_paths(result: Any) -> list[Path]:
    if result is None:
        return []
    if isinstance(result, (str, os.PathLike)):
        return [Path(result)]
    return [Path(p) for p in result]


class InputClaim:
    """What :func:`run_batch` does around one input, in steps, for drivers that run the input
    elsewhere (the distributed run of :mod:`hsi_torch.recon.many`): :meth:`begin` before the
    work (input exists; with markers: the name lock, the ownership check, the ``"started"``
    claim), :meth:`finish` after it (the ``"done"`` marker with the outputs' stamps) or
    :meth:`abandon` when it failed or was interrupted (the earlier marker back, the lock freed).
    Made by :meth:`OutputClaims.claim`."""

    def __init__(self, claims: OutputClaims, inp: Path) -> None:
        self.claims = claims
        self.input = inp
        self.key = os.path.abspath(inp)
        self.marker = _marker_path(claims.out, inp)
        self.planned: list[str] = []
        self._record: dict[str, Any] = {}
        self._previous: dict[str, Any] | None = None
        self._claimed = False
        self._lock = contextlib.ExitStack()

    def begin(self) -> None:
        """Check the input and claim its planned outputs (see :func:`run_batch`).

        Raises:
            FileNotFoundError: the input is missing.
            InputError: another input owns the outputs, or another run writes them right now.
        """
        inp, out, owners = self.input, self.claims.out, self.claims.owners
        if not inp.exists():
            raise FileNotFoundError(f"input file not found: {inp}")
        stamp = input_stamp(inp)
        if owners is None:
            return
        # one run at a time writes the outputs of a name into this folder
        self._lock.enter_context(_name_lock(out, inp.stem))
        owners.refresh(out, inp.stem)  # claims a concurrent run made meanwhile
        planned_fn = self.claims.planned_outputs
        self.planned = [os.path.abspath(p) for p in planned_fn(inp)] \
            if planned_fn is not None else []  # fmt: skip
        clash = owners.conflict(self.key, self.planned)
        if clash is not None:
            other, names = clash
            shown = ", ".join(Path(n).name for n in names[:4])
            raise InputError(
                f"{inp}: its outputs ({shown}) in {out} already belong to another "
                f"input, {other}; rename one of the two, write into another folder, "
                "or delete those outputs first"
            )
        self._record = {
            "status": "started",
            "input": self.key,
            "input_stamp": stamp,
            "fingerprint": self.claims.fingerprint,
            "outputs": self.planned,
            "started": time.strftime("%Y-%m-%dT%H:%M:%S"),
        }
        self._previous = _read_marker(self.marker)
        atomic_write_json(self.marker, self._record)  # the claim, before any output exists
        self._claimed = True
        owners.claim(self.marker, self.key, self.planned)

    def finish(self, outputs: Sequence[Path]) -> None:
        """The input's outputs are written: mark it done (then the lock is freed)."""
        owners = self.claims.owners
        try:
            if owners is not None:
                done = [os.path.abspath(p) for p in outputs]
                self._record.update(
                    status="done", outputs=done,
                    output_stamps={p: _file_stamp(p) for p in done},
                    finished=time.strftime("%Y-%m-%dT%H:%M:%S"),
                )  # fmt: skip
                atomic_write_json(self.marker, self._record)
                owners.claim(self.marker, self.key, sorted(set(done) | set(self.planned)))
        finally:
            self._lock.close()

    def abandon(self) -> None:
        """The input failed or was interrupted: no claim of an unfinished input is left."""
        if self._claimed:
            _release_claim(self.claims.owners, self.marker, self.key, self._previous)
            self._claimed = False
        self._lock.close()
        with contextlib.suppress(OSError):  # the marker folder, if nothing is in it
            (self.claims.out / DONE_DIR).rmdir()


class OutputClaims:
    """The resume and ownership bookkeeping of one output folder (see the module docstring):
    :meth:`is_done` decides resumption, :meth:`claim` makes an :class:`InputClaim`. Arguments
    as :func:`run_batch`'s."""

    def __init__(
        self,
        out: Path,
        fingerprint: str | None = None,
        planned_outputs: PathsFn | None = None,
        expected_outputs: PathsFn | None = None,
    ) -> None:
        self.out = out
        self.fingerprint = fingerprint
        self.planned_outputs = planned_outputs
        self.expected_outputs = expected_outputs
        self.owners = _Owners(out) if expected_outputs is None else None

    def is_done(self, inp: Path) -> bool:
        return _is_done(inp, self.out, self.expected_outputs, self.fingerprint)

    def claim(self, inp: Path) -> InputClaim:
        return InputClaim(self, inp)


def clean_run_leftovers(out: Path) -> list[Path]:
    """Remove the temporary files of killed runs from ``out`` and its marker folder."""
    return clean_stale_temp_files(out) + clean_stale_temp_files(out / DONE_DIR)


def run_batch(
    inputs: Iterable[str | os.PathLike],
    process: ProcessFn,
    out_dir: str | os.PathLike,
    resume: bool = True,
    progress: bool = True,
    expected_outputs: PathsFn | None = None,
    desc: str = "processing",
    fingerprint: str | None = None,
    planned_outputs: PathsFn | None = None,
) -> BatchSummary:
    """Run ``process`` over every input, continuing past failures.

    Args:
        inputs: files and/or glob patterns (see :func:`expand_inputs`).
        process: ``process(path) -> output path(s) or None``; raise to signal failure.
        out_dir: output folder (created); holds the resume markers.
        resume: skip inputs whose outputs exist (see the module docstring).
        progress: show a tqdm progress bar on stderr.
        expected_outputs: optional ``input -> output paths`` used to decide resumption (no
            markers, no ownership check).
        desc: progress-bar label.
        fingerprint: identifies the settings of this run (see :func:`fingerprint_of`); with the
            done-markers, an input finished under a different fingerprint is processed again.
        planned_outputs: optional ``input -> output paths`` that ``process`` will write; an input
            whose planned outputs belong to another input (a claim by its marker, one of its
            outputs still on disk) fails with an error naming both, before ``process`` runs.

    Returns:
        :class:`BatchSummary` (use ``.report()`` / :func:`print_summary` and ``.exit_code``).

    Raises:
        ValueError: a glob matches nothing or an input is a directory (before any processing).
    """
    paths = expand_inputs(inputs)
    out = ensure_out_dir(out_dir)
    summary = BatchSummary()
    summary.cleaned = clean_run_leftovers(out)
    claims = OutputClaims(out, fingerprint, planned_outputs, expected_outputs)
    t0 = time.perf_counter()
    bar = progress_bar(paths, enabled=progress, desc=desc, unit="file", leave=True)
    try:
        for inp in bar:
            if resume and claims.is_done(inp):
                summary.skipped.append(inp)
                continue
            claim = claims.claim(inp)
            try:
                claim.begin()
                outputs = _as_paths(process(inp))
                claim.finish(outputs)
            except BaseException as exc:
                claim.abandon()  # failed or interrupted (Ctrl-C)
                if not isinstance(exc, Exception):
                    raise
                summary.failed.append(
                    BatchFailure(inp, f"{type(exc).__name__}: {exc}", traceback.format_exc())
                )
                if progress:
                    bar.set_postfix(failed=len(summary.failed))
                continue
            summary.processed.append(inp)
            summary.outputs[inp] = outputs
    finally:
        bar.close()
        summary.elapsed_s = time.perf_counter() - t0
    return summary


def print_summary(summary: BatchSummary, file: IO[str] | None = None) -> None:
    """Print :meth:`BatchSummary.report` (counts, then every failure) to ``file`` (stderr)."""
    print(summary.report(), file=file if file is not None else sys.stderr)
