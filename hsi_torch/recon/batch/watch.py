"""``hsi-torch watch``: a live folder — each capture reconstructed as the camera's tethering
software writes it, into the sequence store a batch run can resume (the user's rules: when a file
is complete, given up, skipped; what is printed and written: ``docs/sequences_io.md``).

:class:`FolderWatcher` polls the folder (every ``poll_s`` seconds; no file-system events) and
hands out complete capture files only (unchanged for ``settle_s`` seconds *and* whole by
:func:`~hsi_torch.io.sequence.looks_complete`), in natural name order; one incomplete and
unchanged for ``stale_s`` seconds is given up. Each frame goes through the sequences' one
per-frame function (:func:`hsi_torch.recon.batch.sequence_run._reconstruct_sequence`) and is
appended to ``OUT/sequence.zarr``.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import torch

from hsi_torch.colour import save_preview_png
from hsi_torch.console import info, warn
from hsi_torch.errors import HSIError, InputError
from hsi_torch.io.captures import SUPPORTED_SUFFIXES
from hsi_torch.io.sequence import (
    SequenceFrame,
    frame_time,
    is_temporary_name,
    looks_complete,
    natural_key,
)
from hsi_torch.io.sequence_store import SEQUENCE_NAME, SequenceStore
from hsi_torch.recon.batch.driver import RunFailure, RunSummary
from hsi_torch.recon.batch.run import check_run
from hsi_torch.recon.batch.sequence_finish import finish_sequence_run
from hsi_torch.recon.batch.sequence_run import (
    SEQUENCE_PREVIEW,
    _reconstruct_sequence,
    _store_frame,
)
from hsi_torch.recon.config import ReconstructConfig

__all__ = ["FolderWatcher", "watch_folder", "LATEST_PREVIEW"]

#: The latest frame's sRGB preview (replaced after every frame).
LATEST_PREVIEW = "latest_preview.png"


class FolderWatcher:
    """Complete capture files of a folder as they appear (module docstring).

    Args:
        folder: the folder the camera's software writes into.
        settle_s: how long size and modification time must stay unchanged.
        poll_s: seconds between scans.
        stale_s: an incomplete file unchanged this long is given up (default
            ``max(30, 20 × settle_s)``).
        idle_timeout_s: stop when no file arrived or changed for this long (``None``: never).
        max_frames: stop after handing out this many files (``None``: never).
        known: files to skip (already in the store), absolute paths.
        stop: an event that stops the watch when set (another thread's Ctrl-C).
        clock: the time source (seconds; tests may pass their own).
    """

    def __init__(
        self, folder: str | os.PathLike, *, settle_s: float = 1.0, poll_s: float = 0.25,
        stale_s: float | None = None, idle_timeout_s: float | None = None,
        max_frames: int | None = None, known: set[str] | None = None,
        stop: threading.Event | None = None, clock: Callable[[], float] = time.monotonic,
    ) -> None:  # fmt: skip
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise InputError(f"{self.folder}: not a folder (hsi-torch watch watches the folder "
                             "the camera's software writes into)")  # fmt: skip
        for name, v in (("settle_s", settle_s), ("poll_s", poll_s)):
            if not v > 0:
                raise InputError(f"{name} must be > 0 seconds, got {v!r}")
        self.settle_s = float(settle_s)
        self.poll_s = float(poll_s)
        self.stale_s = max(30.0, 20 * self.settle_s) if stale_s is None else float(stale_s)
        self.idle_timeout_s = idle_timeout_s
        self.max_frames = max_frames
        self.done: set[str] = set(known or ())
        self.given_up: list[tuple[Path, str]] = []
        self.handed_out = 0
        self.stop_reason: str | None = None
        self._stop = stop or threading.Event()
        self._clock = clock
        #: path -> (size, mtime_ns, since when unchanged)
        self._seen: dict[str, tuple[int, int, float]] = {}
        #: path -> (size, mtime_ns) at which it was found whole
        self._whole: dict[str, tuple[int, int]] = {}
        self._last_activity = clock()

    def stop(self) -> None:
        """Stop after the current frame."""
        self._stop.set()

    def _candidates(self) -> list[Path]:
        try:
            entries = list(os.scandir(self.folder))
        except OSError:
            return []
        out = [Path(e.path) for e in entries
               if not is_temporary_name(e.name) and Path(e.name).suffix.lower()
               in SUPPORTED_SUFFIXES and os.path.abspath(e.path) not in self.done
               and e.is_file()]  # fmt: skip
        return sorted(out, key=lambda q: natural_key(q.name))

    def scan(self) -> tuple[list[Path], list[Path]]:
        """``(ready, pending)``: complete files not yet handed out, and files still being
        written, both in natural name order (a ready file after a pending one waits)."""
        now = self._clock()
        ready: list[Path] = []
        pending: list[Path] = []
        for p in self._candidates():
            key = os.path.abspath(p)
            try:
                st = os.stat(p)
            except OSError:
                continue
            sig = (int(st.st_size), int(st.st_mtime_ns))
            old = self._seen.get(key)
            if old is None or old[:2] != sig:
                self._seen[key] = (*sig, now)
                self._last_activity = now
                pending.append(p)
                continue
            steady = now - old[2]
            if steady >= self.settle_s and (self._whole.get(key) == sig or looks_complete(p)):
                self._whole[key] = sig  # (not parsed again while unchanged)
                ready.append(p)
            elif steady >= self.stale_s:
                self.done.add(key)
                self.given_up.append(
                    (
                        p,
                        f"still incomplete after {steady:.0f} s without a "
                        "change (a write that was abandoned); skipped",
                    )
                )
            else:
                pending.append(p)
        if pending and ready:  # keep the time order: nothing after a file still being written
            first = natural_key(pending[0].name)
            ready = [p for p in ready if natural_key(p.name) < first]
        return ready, pending

    def backlog(self) -> tuple[int, float]:
        """``(files complete and waiting, seconds since the oldest of them was written)``."""
        ready, _ = self.scan()
        if not ready:
            return 0, 0.0
        oldest = min(os.stat(p).st_mtime for p in ready if p.exists())
        return len(ready), max(0.0, time.time() - oldest)

    def files(self) -> Iterator[Path]:
        """Complete files as they become complete, until stopped (``stop_reason`` says why)."""
        while True:
            if self._stop.is_set():
                self.stop_reason = "stopped"
                return
            if self.max_frames is not None and self.handed_out >= self.max_frames:
                self.stop_reason = f"{self.max_frames} frame(s) done (--max-frames)"
                return
            ready, _ = self.scan()
            if ready:
                p = ready[0]
                self.done.add(os.path.abspath(p))
                self.handed_out += 1
                self._last_activity = self._clock()
                yield p
                continue
            idle = self._clock() - self._last_activity
            if self.idle_timeout_s is not None and idle >= self.idle_timeout_s:
                self.stop_reason = f"nothing new for {idle:.1f} s (--idle-timeout)"
                return
            self._stop.wait(self.poll_s)


def watch_folder(
    folder: str | os.PathLike,
    bundle: str | os.PathLike,
    out_dir: str | os.PathLike,
    cfg: ReconstructConfig,
    *,
    time_from: str = "auto",
    max_frames: int | None = None,
    idle_timeout_s: float | None = None,
    settle_s: float = 1.0,
    poll_s: float = 0.25,
    device: str | None = None,
    config_source: str | None = None,
    preview: bool = True,
    stop: threading.Event | None = None,
) -> RunSummary:
    """``hsi-torch watch`` (module docstring): reconstruct each complete capture of ``folder``
    into ``out_dir/sequence.zarr`` until stopped.

    Args:
        folder: the watched folder; bundle, out_dir, cfg: as for ``reconstruct``.
        time_from: ``"auto"`` (name, EXIF, modification time), ``"name"``, ``"exif"`` or
            ``"mtime"``.
        max_frames, idle_timeout_s, settle_s, poll_s: see :class:`FolderWatcher`.
        stop: set it (from another thread) to stop after the current frame.

    Returns:
        The :class:`~hsi_torch.recon.batch.driver.RunSummary` (Ctrl-C ends the watch normally).
    """
    t_start = time.perf_counter()
    if cfg.uncertainty:
        raise ValueError("a sequence store does not hold the uncertainty (config key "
                         "'uncertainty')")  # fmt: skip
    if time_from not in ("auto", "name", "exif", "mtime"):
        raise InputError(f"--time-from {time_from!r}: a live folder's frames are timed by "
                         "auto, name, exif or mtime")  # fmt: skip
    run = check_run([], bundle, out_dir, cfg, device=device, formats=False,
                    config_source=config_source)  # fmt: skip
    out = run.start()
    summary = RunSummary()
    with SequenceStore.open(out / SEQUENCE_NAME, run.wavelengths_nm, run.frame_size,
                            {"bundle": os.path.abspath(run.bundle_path)}) as store:  # fmt: skip
        summary.store = store.path
        known = {s.split("#page=")[0] for s in store.sources}
        watcher = FolderWatcher(folder, settle_s=settle_s, poll_s=poll_s,
                                idle_timeout_s=idle_timeout_s, max_frames=max_frames,
                                known=known, stop=stop)  # fmt: skip
        if store.sources:
            info(f"{store.path}: {len(store)} frame(s) already; their files are skipped")
        rec = run.reconstructor()
        wl = torch.as_tensor(run.wavelengths_nm, dtype=torch.float64)
        info(f"watching {watcher.folder} (Ctrl-C stops)")

        def frames() -> Iterator[SequenceFrame]:
            for p in watcher.files():
                src = time_from
                if src == "auto" and store.attrs.get("time_source") in ("name", "exif", "mtime"):
                    src = str(store.attrs["time_source"])  # the store's frames' source
                try:
                    how, secs, stamp = frame_time(p, src)
                except (HSIError, ValueError, OSError) as exc:
                    summary.failed.append(RunFailure(p, f"{type(exc).__name__}: {exc}"))
                    warn(f"{p}: {exc}")
                    continue
                yield SequenceFrame(len(store), p, None, float(secs or 0.0),
                                    stamp.isoformat(timespec="microseconds") if stamp else None,
                                    how)  # fmt: skip

        t_frame = time.perf_counter()
        try:
            for frame, res in _reconstruct_sequence(rec, frames()):
                waiting, behind = watcher.backlog()
                k = _store_frame(store, run, frame, res, summary,
                                 watch={"waiting": waiting, "behind_s": behind})  # fmt: skip
                took = time.perf_counter() - t_frame
                if k is not None and not isinstance(res, BaseException):
                    if preview:
                        save_preview_png(res.cube.detach().cpu(), wl, out / LATEST_PREVIEW,
                                         valid=res.valid.detach().cpu(), min_size=256,
                                         caption=f"frame {k}: {frame.path.name}, "
                                                 f"t = {store.times_s[-1]:.3f} s")  # fmt: skip
                    pace = (
                        "keeping up"
                        if waiting == 0
                        else f"{waiting} file(s) waiting, {behind:.1f} s behind"
                    )
                    info(f"frame {k}: {frame.path.name} (t = {store.times_s[-1]:.3f} s) in "
                         f"{took:.2f} s; {pace}")  # fmt: skip
                elif isinstance(res, BaseException) or k is None:
                    warn(f"{frame.path}: failed: {summary.failed[-1].error}")
                t_frame = time.perf_counter()
        except KeyboardInterrupt:
            watcher.stop_reason = "stopped (Ctrl-C)"
        for p, why in watcher.given_up:
            summary.failed.append(RunFailure(p, f"IncompleteFile: {why}"))
        n = len(store)
    info(f"watch ended: {watcher.stop_reason or 'stopped'}; {n} frame(s) in {store.path}")
    gif = out / SEQUENCE_PREVIEW if preview and n else None
    return finish_sequence_run(summary, run, store.path, gif, t_start)
