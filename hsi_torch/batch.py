"""Batch processing of many input files: glob expansion, progress, resume, failures collected.

:func:`run_batch` calls ``process(input_path)`` for every input in order. A failing input is
recorded (exception type and message) and the batch continues; ``KeyboardInterrupt`` stops it.
With ``resume=True`` an input is skipped when its outputs already exist:

- if ``expected_outputs(input)`` is given: when every path it returns exists;
- otherwise: when the *done-marker* written after the input's last success exists and every
  output it lists still exists. Markers live in ``out_dir/.hsi_torch_done/`` (one small JSON per
  input, named ``<stem>-<hash of the absolute input path>.json``, written atomically *after*
  ``process`` returned), so an interrupted or failed input is never mistaken for a finished one.
  The marker also records the input file's size and modification time and the run's
  ``fingerprint`` (e.g. a hash of the configuration and the bundle): an input that changed since,
  or a rerun with different settings, is processed again instead of being skipped.

``process`` should write its files atomically (:func:`hsi_torch.io.atomic.atomic_write`) so a
crash leaves no partial output. Inputs run sequentially in this process; the per-frame work
(torch) is what uses the cores. (Should worker processes ever be added: rawpy/LibRaw with OpenMP
can deadlock under ``fork`` — use the ``spawn`` start method.)
"""

from __future__ import annotations

import glob
import hashlib
import json
import os
import sys
import time
import traceback
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from hsi_torch.io.atomic import atomic_write_json

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
]

DONE_DIR = ".hsi_torch_done"
_GLOB_CHARS = set("*?[")

ProcessFn = Callable[[Path], "Path | str | Sequence[Path | str] | None"]


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
    """

    processed: list[Path] = field(default_factory=list)
    skipped: list[Path] = field(default_factory=list)
    failed: list[BatchFailure] = field(default_factory=list)
    outputs: dict[Path, list[Path]] = field(default_factory=dict)
    elapsed_s: float = 0.0

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


def _input_stamp(inp: Path) -> list[int]:
    st = inp.stat()
    return [int(st.st_size), int(st.st_mtime_ns)]


def _is_done(
    inp: Path,
    out_dir: Path,
    expected_outputs: Callable[[Path], Sequence[Path | str]] | None,
    fingerprint: str | None = None,
) -> bool:
    if expected_outputs is not None:
        paths = [Path(p) for p in expected_outputs(inp)]
        return bool(paths) and all(p.exists() for p in paths)
    marker = _marker_path(out_dir, inp)
    if not marker.is_file():
        return False
    try:
        rec = json.loads(marker.read_text(encoding="utf-8"))
        stamp = _input_stamp(inp)
    except (OSError, json.JSONDecodeError):
        return False
    if rec.get("input_stamp") != stamp:  # the input changed since it was processed
        return False
    if fingerprint is not None and rec.get("fingerprint") != fingerprint:  # other settings
        return False
    return all(Path(p).exists() for p in rec.get("outputs", []))


def _as_paths(result: Any) -> list[Path]:
    if result is None:
        return []
    if isinstance(result, (str, os.PathLike)):
        return [Path(result)]
    return [Path(p) for p in result]


def run_batch(
    inputs: Iterable[str | os.PathLike],
    process: ProcessFn,
    out_dir: str | os.PathLike,
    resume: bool = True,
    progress: bool = True,
    expected_outputs: Callable[[Path], Sequence[Path | str]] | None = None,
    desc: str = "processing",
    fingerprint: str | None = None,
) -> BatchSummary:
    """Run ``process`` over every input, continuing past failures.

    Args:
        inputs: files and/or glob patterns (see :func:`expand_inputs`).
        process: ``process(path) -> output path(s) or None``; raise to signal failure.
        out_dir: output folder (created); holds the resume markers.
        resume: skip inputs whose outputs exist (see the module docstring).
        progress: show a tqdm progress bar on stderr.
        expected_outputs: optional ``input -> output paths`` used to decide resumption.
        desc: progress-bar label.
        fingerprint: identifies the settings of this run (see :func:`fingerprint_of`); with the
            done-markers, an input finished under a different fingerprint is processed again.

    Returns:
        :class:`BatchSummary` (use ``.report()`` / :func:`print_summary` and ``.exit_code``).

    Raises:
        ValueError: a glob matches nothing or an input is a directory (before any processing).
    """
    from hsi_torch.console import progress_bar

    paths = expand_inputs(inputs)
    out = ensure_out_dir(out_dir)
    summary = BatchSummary()
    t0 = time.perf_counter()
    bar = progress_bar(paths, enabled=progress, desc=desc, unit="file", leave=True)
    try:
        for inp in bar:
            if resume and _is_done(inp, out, expected_outputs, fingerprint):
                summary.skipped.append(inp)
                continue
            try:
                if not inp.exists():
                    raise FileNotFoundError(f"input file not found: {inp}")
                stamp = _input_stamp(inp)
                outputs = _as_paths(process(inp))
                if expected_outputs is None:
                    record = {
                        "input": os.path.abspath(inp),
                        "input_stamp": stamp,
                        "fingerprint": fingerprint,
                        "outputs": [os.path.abspath(p) for p in outputs],
                        "finished": time.strftime("%Y-%m-%dT%H:%M:%S"),
                    }
                    atomic_write_json(_marker_path(out, inp), record)
            except Exception as exc:  # noqa: BLE001 - every input failure is collected
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
