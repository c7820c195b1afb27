"""Sequences through the reconstruction: frames in (in time order), cubes out, one store.

- :func:`sequence_cubes` — Python: an iterator of ``(frame, result)`` over a
  :class:`~hsi_torch.io.sequence.CaptureSequence` (or any iterable of its frames), one frame
  decoded and reconstructed at a time (for a torch data pipeline).
- :func:`run_sequence` — ``hsi-torch reconstruct --sequence``: the sequence checked (times,
  sizes, duplicates) and the run checked (:func:`~hsi_torch.recon.batch.run.check_run`) before
  anything is written, then every frame appended to ``OUT/sequence.zarr``
  (:mod:`hsi_torch.io.sequence_store`: time axis, timestamps, per-frame findings and valid masks)
  and the animated preview ``OUT/sequence_preview.gif`` written at the end.

Every frame goes through one function, :func:`_reconstruct_sequence` (the reconstructor and the
frames in, ``(frame, result or error)`` out, in order): each frame through the file front door
(:meth:`~hsi_torch.recon.pipeline.Reconstructor.reconstruct_file`), and where the settings'
``sequence`` group asks for it (``warm_start``, ``warm_spatial``, ``temporal``,
``drift_track``: ``--set warm_spatial=true`` …) through a
:class:`~hsi_torch.recon.sequence.SequenceReconstructor` that carries the solver state, the
previous answer and the drift path from one frame to the next.

**Resume** (a store grows forward only; ``--no-resume`` refuses a store with frames):
``docs/sequences_io.md``. A failed frame does not stop the run (the time axis simply has no entry
for it); the exit status is 1 when any failed.
"""

from __future__ import annotations

import os
import time
import traceback
import warnings
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from hsi_torch.console import info, progress_bar, warn
from hsi_torch.errors import HSIError, InputError, NoValidPixelsError
from hsi_torch.findings import Finding, HSIWarning, findings_from_dicts
from hsi_torch.io.dataset import require_dataset_packages
from hsi_torch.io.sequence import CaptureSequence, SequenceFrame, open_sequence
from hsi_torch.io.sequence_store import (
    SEQUENCE_NAME,
    SequenceStore,
    is_sequence_store,
)
from hsi_torch.io.zarr_group import read_json
from hsi_torch.recon.batch.driver import RunFailure, RunSummary
from hsi_torch.recon.batch.run import ReconstructRun, check_run
from hsi_torch.recon.batch.sequence_finish import finish_sequence_run
from hsi_torch.recon.config import ReconstructConfig
from hsi_torch.recon.pipeline import ReconstructionResult, Reconstructor
from hsi_torch.recon.sequence import SequenceReconstructor
from hsi_torch.recon.settings import ReconstructSettings

__all__ = [
    "sequence_cubes",
    "run_sequence",
    "SEQUENCE_PREVIEW",
    "frame_findings",
    "frame_metadata",
    "reconstruct_frame_of_sequence",
    "uses_time",
]

#: The animated sRGB preview of a sequence run (GIF, in the output folder).
SEQUENCE_PREVIEW = "sequence_preview.gif"


# ----------------------------------------------------------------------------------------------
# the one per-frame function


def reconstruct_frame_of_sequence(
    rec: Reconstructor | SequenceReconstructor, frame: SequenceFrame
) -> ReconstructionResult:
    """One frame through the front door, read as ``rec.settings`` say
    (:meth:`Reconstructor.reconstruct_file`, or :meth:`SequenceReconstructor.reconstruct_file`:
    the same front door with the sequence's state; a page of a multi-page TIFF decoded alone).

    Raises:
        NoValidPixelsError: not a single pixel could be reconstructed (the reason named).
    """
    res = rec.reconstruct_file(frame.path, page=frame.page)
    if res.stats.get("num_valid", 0) == 0:
        raise NoValidPixelsError(
            f"{frame.source}: no valid pixel: "
            f"{res.stats.get('no_valid_reason') or 'unknown reason'}"
        )
    return res


def uses_time(settings: ReconstructSettings) -> bool:
    """Whether the settings' ``sequence`` group carries anything from frame to frame (a warm
    start, the temporal prior, the drift path; the spatial warm start, on by default, only with
    the spatial prior)."""
    sq = settings.sequence
    spatial = sq.warm_spatial and settings.prior.kind == "tv"
    return sq.warm_start or spatial or sq.temporal != "none" or sq.drift_track


def _reconstruct_sequence(
    rec: Reconstructor, frames: Iterable[SequenceFrame], quiet: bool = True
) -> Iterator[tuple[SequenceFrame, ReconstructionResult | BaseException]]:
    """THE per-frame function of every sequence (batch, live folder, Python): ``(frame, result)``
    for each frame in order, or ``(frame, error)`` for a frame that could not be read or
    reconstructed (the sequence goes on). ``frames`` may be a lazy iterator (a live folder's
    files as they become complete): each is pulled only when the previous one is done.

    Each frame through the front door (:func:`reconstruct_frame_of_sequence`): independently
    (a cold solve per frame) unless ``rec.settings.sequence`` asks for warm starts, the temporal
    prior or the drift path (:func:`uses_time`): then through one
    :class:`~hsi_torch.recon.sequence.SequenceReconstructor` on ``rec``'s sensing, which carries
    them from frame to frame (a frame that fails in its reading leaves them as they were; one
    refused after its solve has already handed on its solver state — a start only, the next
    solve ends at its own optimum — and its drift measurement, while the temporal prior keeps
    the last good answer). ``quiet``: the findings are not raised as Python warnings (a run
    reports them itself); they are on every result (:attr:`ReconstructionResult.findings`)
    either way.
    """
    one: Reconstructor | SequenceReconstructor = rec
    if uses_time(rec.settings):
        one = SequenceReconstructor(rec.sensing, rec.settings)
    for frame in frames:
        try:
            with warnings.catch_warnings():
                if quiet:  # the run reports them, one line each
                    warnings.simplefilter("ignore", HSIWarning)
                res = reconstruct_frame_of_sequence(one, frame)
        except (HSIError, ValueError, OSError) as exc:  # the frame's fault: reported, go on
            exc.__traceback_text__ = traceback.format_exc()  # type: ignore[attr-defined]
            yield frame, exc
            continue
        yield frame, res


def sequence_cubes(
    reconstructor: Reconstructor,
    frames: CaptureSequence | Iterable[SequenceFrame] | str | os.PathLike | list[Any],
    *,
    time_from: str = "auto",
    frame_interval_s: float | None = None,
) -> Iterator[tuple[SequenceFrame, ReconstructionResult]]:
    """Frames in, cubes out: ``(frame, result)`` for every frame in time order, one decoded and
    reconstructed at a time (``result.cube`` ``(M, h, w)``, ``result.valid`` ``(h, w)``, on the
    reconstructor's device).

    Args:
        reconstructor: the :class:`Reconstructor` (bundle and settings).
        frames: a :class:`~hsi_torch.io.sequence.CaptureSequence`, any iterable of its frames,
            or inputs for :func:`~hsi_torch.io.sequence.open_sequence` (a folder, a sheet, a
            multi-page TIFF, files or patterns; ``time_from`` and ``frame_interval_s`` go to it).

    Raises:
        The first frame's error (unlike the command, which reports it and goes on).

    Example:
        >>> rec = Reconstructor("calib.npz")  # doctest: +SKIP
        >>> for frame, res in sequence_cubes(rec, "shots/"):  # doctest: +SKIP
        ...     print(frame.time_s, res.cube.shape)
    """
    if isinstance(frames, (str, os.PathLike)) or (
        isinstance(frames, list) and frames and not isinstance(frames[0], SequenceFrame)
    ):
        frames = open_sequence(frames, time_from=time_from, frame_interval_s=frame_interval_s)
    for frame, out in _reconstruct_sequence(reconstructor, frames, quiet=False):  # type: ignore[arg-type]
        if isinstance(out, BaseException):
            raise out
        yield frame, out


# ----------------------------------------------------------------------------------------------
# what is stored with each frame

def frame_findings(res: ReconstructionResult, run: ReconstructRun, source: str) -> list[Finding]:
    """The frame's findings: those the front door judged (:attr:`ReconstructionResult.findings`)
    and any a sequence reconstruction adds (``stats["findings"]``, e.g. a drift path's jump)."""
    out = list(res.findings)
    given = res.stats.get("findings")
    if isinstance(given, list):
        out += [f if isinstance(f, Finding) else findings_from_dicts([f], source)[0]
                for f in given]  # fmt: skip
    return out


def frame_metadata(
    res: ReconstructionResult, run: ReconstructRun, frame: SequenceFrame, **extra: Any
) -> dict[str, Any]:
    """The metadata stored with a frame (as a cube file's: source, bundle, configuration,
    statistics, timings; and the frame's time)."""
    stats = dict(res.stats)
    stats.pop("findings", None)
    cap_meta = stats.pop("metadata", {}) or {}
    run_config = run.run_config
    return {
        "source": frame.source, "bundle": os.path.abspath(run.bundle_path),
        "time_s": frame.time_s, "timestamp": frame.timestamp, "time_source": frame.time_source,
        "page": frame.page, "capture_exposure_s": cap_meta.get("exposure_s"),
        "radiometric_scale": stats.get("radiometric_scale"),
        "notes": [f.message for f in res.findings if f.severity == "info"],
        "config": dict(vars(run.cfg)),
        "run_config": run_config.relative_to(run.out_dir).as_posix() if run_config else None,
        "stats": stats, "timings_s": res.timings, **extra,
    }  # fmt: skip


def store_time(store: SequenceStore, frame: SequenceFrame) -> float:
    """The frame's time on the store's axis: seconds since the store's first frame (absolute
    times measured from its ``time_origin``; relative ones as the sequence gives them)."""
    origin = store.attrs.get("time_origin")
    if frame.timestamp and origin:
        import datetime as dt  # lazy: only absolute times

        t, t0 = dt.datetime.fromisoformat(frame.timestamp), dt.datetime.fromisoformat(origin)
        if (t.tzinfo is None) != (t0.tzinfo is None):
            t, t0 = t.replace(tzinfo=None), t0.replace(tzinfo=None)
        return (t - t0).total_seconds()
    return float(frame.time_s)


def begin_store(store: SequenceStore, frame: SequenceFrame) -> None:
    """Record the time origin and source when the store gets its first frame; refuse a frame
    timed otherwise than the store's frames (naming it)."""
    if len(store) == 0 and store.attrs.get("time_source") is None:
        store.set_attrs(time_origin=frame.timestamp, time_source=frame.time_source)
        return
    src = store.attrs.get("time_source")
    if src is not None and src != frame.time_source:
        raise InputError(f"{frame.source}: timed by {frame.time_source}, but the store's frames "
                         f"are timed by {src}; give --time-from {src} or write into another "
                         "folder")  # fmt: skip


# ----------------------------------------------------------------------------------------------
# the command


def run_sequence(
    inputs: Any,
    bundle: str | os.PathLike,
    out_dir: str | os.PathLike,
    cfg: ReconstructConfig,
    *,
    time_from: str = "auto",
    frame_interval_s: float | None = None,
    resume: bool = True,
    progress: bool = True,
    device: str | None = None,
    config_source: str | None = None,
    preview: bool = True,
) -> RunSummary:
    """``hsi-torch reconstruct --sequence`` (module docstring): the sequence and the run checked
    before anything is written, every frame appended to ``OUT/sequence.zarr``, the animated
    preview ``OUT/sequence_preview.gif`` (``preview``) at the end.

    Raises:
        InputError, FileFormatError, ValueError: a bad sequence, bundle, configuration or store
            (before any frame is reconstructed).
    """
    t_start = time.perf_counter()
    if cfg.uncertainty:
        raise ValueError(
            "a sequence store does not hold the uncertainty (config key "
            "'uncertainty'); reconstruct the frames to cube files for it"
        )
    try:
        require_dataset_packages()
    except ModuleNotFoundError as exc:
        raise ValueError(f"--sequence: {exc}") from None
    store_path = Path(out_dir) / SEQUENCE_NAME
    if time_from == "auto" and resume and is_sequence_store(store_path):
        src = read_json(store_path / ".zattrs").get("time_source")
        time_from = src if isinstance(src, str) else "auto"  # the store's frames' rule
    seq = (
        inputs
        if isinstance(inputs, CaptureSequence)
        else open_sequence(inputs, time_from=time_from, frame_interval_s=frame_interval_s)
    )
    files = list(dict.fromkeys(f.path for f in seq))
    run = check_run(files, bundle, out_dir, cfg, device=device, formats=False,
                    config_source=config_source)  # fmt: skip
    info(seq.describe())
    summary = RunSummary()
    out = run.start()
    with SequenceStore.open(out / SEQUENCE_NAME, run.wavelengths_nm, run.frame_size,
                            {"bundle": os.path.abspath(run.bundle_path)}) as store:  # fmt: skip
        summary.store = store.path
        todo = _frames_to_do(seq, store, resume, summary)
        if todo:
            rec = run.reconstructor()
            bar = progress_bar(total=len(todo), enabled=progress, desc="frames", unit="frame")
            try:
                for frame, res in _reconstruct_sequence(rec, todo):
                    _store_frame(store, run, frame, res, summary)
                    bar.update(1)
            finally:
                bar.close()
        n = len(store)
    gif = out / SEQUENCE_PREVIEW if preview and n else None
    return finish_sequence_run(summary, run, store.path, gif, t_start)


def _frames_to_do(
    seq: CaptureSequence, store: SequenceStore, resume: bool, summary: RunSummary
) -> list[SequenceFrame]:
    """The frames after the store's last one; the store's own frames are skipped (resume)."""
    if not len(store):
        return list(seq)
    if not resume:
        raise InputError(f"{store.path} already holds {len(store)} frame(s); --no-resume does "
                         "not overwrite a sequence store: remove it, or write into another "
                         "folder")  # fmt: skip
    where = {f.source: i for i, f in enumerate(seq)}
    last = -1
    for k, src in enumerate(store.sources):
        i = where.get(src)
        if i is None:
            raise InputError(f"{store.path}: its frame {k} ({src}) is not a frame of this "
                             "sequence; a store is resumed with the same sequence (more frames "
                             "may follow): write into another folder")  # fmt: skip
        if i <= last:
            raise InputError(
                f"{store.path}: its frame {k} ({src}) comes before its frame "
                f"{k - 1} in this sequence's order; write into another folder"
            )
        last = i
    stored = set(store.sources)
    for f in seq.frames[: last + 1]:
        if f.source in stored:
            summary.skipped.append(f.path)
        else:
            summary.failed.append(RunFailure(f.path, (
                f"InputError: {f.source} is not in the store (it failed in an earlier run) and "
                "a sequence store only grows forward in time: write into another folder to "
                "include it")))  # fmt: skip
    return seq.frames[last + 1 :]


def _store_frame(
    store: SequenceStore, run: ReconstructRun, frame: SequenceFrame,
    res: ReconstructionResult | BaseException, summary: RunSummary, **extra: Any,
) -> int | None:  # fmt: skip
    """Append a result to the store (or record the failure); the frame's index or ``None``."""
    if not isinstance(res, BaseException):
        try:
            begin_store(store, frame)
            findings = frame_findings(res, run, frame.source)
            meta = frame_metadata(res, run, frame, **extra)
            k = store.append(res.cube, res.valid, time_s=store_time(store, frame),
                             source=frame.source, timestamp=frame.timestamp,
                             findings=findings, metadata=meta)  # fmt: skip
        except (HSIError, ValueError) as exc:
            res = exc
        else:
            for f in findings:
                if f.severity != "info":
                    warn(f"{frame.source}: {f.message}")
            summary.processed.append(frame.path)
            summary.frames[frame.path] = k
            return k
    text = f"{type(res).__name__}: {res}"
    summary.failed.append(RunFailure(frame.path, text,
                                     getattr(res, "__traceback_text__", "")))  # fmt: skip
    return None
