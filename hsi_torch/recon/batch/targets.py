"""Where a run's outputs go: an :class:`OutputTarget` decides resumption and keeps the claims.

Two targets: :class:`FilesTarget` (files per input in a folder: the cube formats, previews) and
:class:`StoreTarget` (one Zarr dataset store for the run, a frame per input). The run's driver
(:func:`hsi_torch.recon.batch.driver.drive`) calls, per input, :meth:`~OutputTarget.is_done`
(resume), :meth:`~OutputTarget.begin` before the work is handed out, then
:meth:`~OutputTarget.finish` with the outputs or :meth:`~OutputTarget.fail`. The user-facing rules
(resume, outputs belonging to one input, never over a file the folder's runs did not write, stale
outputs removed) are in ``docs/reconstruct.md`` and ``docs/io_config_cli.md``.

**Done-markers** (files target): ``out/.hsi_torch_done/<stem>-<hash of the absolute input
path>.json``, written as a claim (``"status": "started"``, the planned outputs) before the work
and atomically as ``"status": "done"`` (outputs with size and mtime, ``owned``: every output of
the input's runs that still exists) after it; they record the input's ``[size, mtime_ns]``, the
run's ``fingerprint`` and ``out``'s identity (device, inode). A marker is data: its paths are
relative to ``out`` and confined to it, and one written in another folder (a copy) is void, so
nothing is ever deleted outside ``out``. The name lock ``out/.hsi_torch_done/<stem>.lock`` is
held while an input's outputs are written. A skipped input's findings are read from the
metadata of its cube (the first of ``.npz``, ``.tif``, ``.nc``, ``.hdr``, ``.zarr``) or of its
frame in the store; a store's frame is done when its ``done`` flag is set and its metadata name
the same input (size, time) and fingerprint (:mod:`hsi_torch.io.dataset`).
:meth:`OutputTarget.cleaned` removes the temporary files killed writers left
(:func:`hsi_torch.io.atomic.clean_stale_temp_files`).
"""

from __future__ import annotations

import contextlib
import glob
import hashlib
import os
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any, Protocol

from hsi_torch.errors import InputError
from hsi_torch.findings import Finding, findings_from_dicts
from hsi_torch.io.atomic import (
    InputFiles,
    atomic_write_json,
    check_not_input,
    clean_stale_temp_files,
    clean_stale_temp_files_of,
    confined,
    folder_identity,
    hold_lock,
    read_own_json,
    relative_to_root,
    remove_confined,
    remove_empty_folder,
    remove_file,
)
from hsi_torch.io.cube import read_cube_findings
from hsi_torch.io.dataset import CubeDataset

__all__ = ["OutputTarget", "FilesTarget", "StoreTarget", "DONE_DIR", "input_stamp"]

DONE_DIR = ".hsi_torch_done"

PathsFn = Callable[[Path], Sequence["Path | str"]]


class OutputTarget(Protocol):
    """Where a run writes (see the module docstring). ``store``: the dataset store, if any.

    ``opened()``: a context for the run (the store is opened and locked in it);
    ``cleaned()``: the stale temporary files removed; ``is_done(input)``: resume skips it;
    ``begin(input)``: claim it before its work is handed out (raises to fail the input), returns
    a handle; ``frame(handle)``: its frame in the store (``None`` for files);
    ``finish(handle, outputs)``: its outputs are written (returns the earlier run's outputs it
    removed as stale); ``fail(handle)``: it failed or was
    interrupted (nothing of the claim is left); ``stored_findings(input)``: the findings stored
    with a done input's outputs (optional: the driver reports none for a target without it)."""

    store: Path | None

    def opened(self) -> contextlib.AbstractContextManager[Any]: ...
    def cleaned(self) -> list[Path]: ...
    def is_done(self, inp: Path) -> bool: ...
    def begin(self, inp: Path) -> Any: ...
    def frame(self, handle: Any) -> int | None: ...
    def finish(self, handle: Any, outputs: Sequence[str]) -> list[str]: ...
    def fail(self, handle: Any) -> None: ...
    def stored_findings(self, inp: Path) -> list[Finding]: ...


#: The cube files whose metadata a skipped input's findings are read from, cheapest first.
_FINDINGS_FROM = (".npz", ".tif", ".nc", ".hdr", ".zarr")


def input_stamp(inp: Path) -> list[int]:
    """``[size, mtime_ns]`` of an input file (how resume tells that it changed).

    Raises:
        OSError: it cannot be read (missing, ...).
    """
    st = inp.stat()
    return [int(st.st_size), int(st.st_mtime_ns)]


def _require_input(inp: Path) -> None:
    if not inp.exists():
        raise FileNotFoundError(f"input file not found: {inp}")


# --- files per input -------------------------------------------------------------------------


def _marker_path(out_dir: Path, inp: Path) -> Path:
    digest = hashlib.sha1(os.fsencode(os.path.abspath(inp))).hexdigest()[:10]
    return out_dir / DONE_DIR / f"{inp.stem}-{digest}.json"


def _file_stamp(path: str | os.PathLike) -> list[int] | None:
    """``[size, mtime_ns]`` of a regular file, ``None`` when it is missing or not a file."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    if not os.path.isfile(path):
        return None
    return [int(st.st_size), int(st.st_mtime_ns)]


#: Largest done-marker read (bytes): one input's outputs, a few hundred bytes each.
MAX_MARKER = 1 << 20


def _read_marker(path: Path) -> dict[str, Any] | None:
    """A done-marker of the folder ``path.parent.parent`` with its output paths made absolute,
    or ``None`` when it is not one of this folder's own markers: unreadable, not a regular file
    (a FIFO is refused without blocking), too large, written into another folder (a copy of
    the folder: ``out_id``, the folder's device and inode, differs) or naming a path that does
    not stay inside the folder (absolute, ``..``, a symlinked folder). A marker is data: what
    it says never reaches outside the output folder."""
    rec = read_own_json(path, MAX_MARKER)
    out_dir = path.parent.parent
    if not isinstance(rec, dict) or rec.get("out_id") != folder_identity(out_dir):
        return None
    try:
        return _map_paths(rec, lambda q: os.path.abspath(confined(out_dir, q)))
    except (InputError, TypeError):
        return None


def _write_marker(path: Path, rec: dict[str, Any]) -> None:
    """Write a done-marker (atomically) with its output paths relative to the output folder
    and the folder's identity (``out_id``)."""
    out_dir = path.parent.parent
    doc = _map_paths(dict(rec), lambda q: relative_to_root(out_dir, q))
    doc["out_id"] = folder_identity(out_dir)
    atomic_write_json(path, doc)


def _map_paths(rec: dict[str, Any], fn: Callable[[str], str]) -> dict[str, Any]:
    """``rec`` (changed in place) with ``fn`` applied to its output paths: the ``outputs`` and
    ``owned`` lists and the keys of ``output_stamps``."""
    for key in ("outputs", "owned"):
        if key in rec:
            rec[key] = [fn(q) for q in rec[key]]
    if isinstance(rec.get("output_stamps"), dict):
        rec["output_stamps"] = {fn(k): v for k, v in rec["output_stamps"].items()}
    return rec


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


def _owned(rec: dict[str, Any]) -> list[str]:
    """The output paths a marker gives to its input: its ``outputs`` and ``owned`` lists."""
    out: list[str] = []
    for key in ("outputs", "owned"):
        v = rec.get(key)
        out += [str(p) for p in v if isinstance(p, str)] if isinstance(v, list) else []
    return sorted(set(out))


class _Owners:
    """Which input each output path of ``out_dir`` belongs to, from the markers."""

    def __init__(self, out_dir: Path) -> None:
        self.by_output: dict[str, tuple[str, Path]] = {}
        self.outputs_of: dict[Path, list[str]] = {}
        folder = out_dir / DONE_DIR
        self._read(sorted(folder.glob("*.json")) if folder.is_dir() else [])

    def refresh(self, out_dir: Path, stem: str) -> None:
        """Re-read the markers of inputs named ``stem`` (another run may have written some)."""
        self._read((out_dir / DONE_DIR).glob(f"{glob.escape(stem)}-*.json"))

    def _read(self, markers: Iterable[Path]) -> None:
        for m in markers:
            rec = _read_marker(m)
            if rec is not None and isinstance(rec.get("input"), str):
                self.claim(m, rec["input"], _owned(rec))

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
            remove_file(marker)
        return None


@contextlib.contextmanager
def _name_lock(out_dir: Path, stem: str) -> Iterator[None]:
    """Hold ``out_dir/.hsi_torch_done/<stem>.lock`` (an exclusive ``flock``,
    :func:`~hsi_torch.io.atomic.hold_lock`: never through a symlink or a hard link planted
    there) while the outputs named ``stem`` are written; another run holding it makes this
    input fail at once, naming that run's process id."""
    folder = out_dir / DONE_DIR
    folder.mkdir(exist_ok=True)
    with hold_lock(folder / f"{stem}.lock", lambda holder: (
            f"outputs named '{stem}' in {out_dir} are being written by another run (process "
            f"{holder}) right now; run again when it has finished")):  # fmt: skip
        yield


class _Claim:
    """One input's claim on its outputs (the handle of :class:`FilesTarget`): the name lock, the
    ``"started"`` marker, and the marker it replaced (put back if the input fails)."""

    def __init__(self, target: FilesTarget, inp: Path) -> None:
        self.target = target
        self.input = inp
        self.key = os.path.abspath(inp)
        self.marker = _marker_path(target.out, inp)
        self.planned: list[str] = []
        self.record: dict[str, Any] = {}
        self.previous: dict[str, Any] | None = None
        self.claimed = False
        self.lock = contextlib.ExitStack()

    def begin(self) -> None:
        inp, out, owners = self.input, self.target.out, self.target.owners
        _require_input(inp)
        stamp = input_stamp(inp)
        # one run at a time writes the outputs of a name into this folder
        self.lock.enter_context(_name_lock(out, inp.stem))
        owners.refresh(out, inp.stem)  # claims a concurrent run made meanwhile
        planned_fn = self.target.planned_outputs
        self.planned = [os.path.abspath(p) for p in planned_fn(inp)] if planned_fn else []
        for p in self.planned:  # never an input (or the bundle): refused before any work
            check_not_input(p, self.target.protected)
        clash = owners.conflict(self.key, self.planned)
        if clash is not None:
            other, names = clash
            shown = ", ".join(Path(n).name for n in names[:4])
            raise InputError(
                f"{inp}: its outputs ({shown}) in {out} already belong to another "
                f"input, {other}; rename one of the two, write into another folder, "
                "or delete those outputs first"
            )
        foreign = [p for p in self.planned
                   if os.path.lexists(p) and owners.by_output.get(p, ("",))[0] != self.key]
        if foreign:
            shown = ", ".join(Path(n).name for n in foreign[:4])
            raise InputError(
                f"{inp}: refusing to write over {shown} in {out}: "
                f"{'that file was' if len(foreign) == 1 else 'those files were'} not written "
                "there by hsi-torch reconstruct for this input (it may be your own data, e.g. "
                "a capture of the same name); move it away or write into another folder"
            )
        self.previous = _read_marker(self.marker)
        kept = [q for q in (_owned(self.previous) if self.previous else []) if os.path.lexists(q)]
        self.record = {
            "status": "started",
            "input": self.key,
            "input_stamp": stamp,
            "fingerprint": self.target.fingerprint,
            "outputs": self.planned,
            "owned": sorted(set(kept) | set(self.planned)),
            "started": time.strftime("%Y-%m-%dT%H:%M:%S"),
        }
        _write_marker(self.marker, self.record)  # the claim, before any output exists
        self.claimed = True
        owners.claim(self.marker, self.key, self.record["owned"])

    def finish(self, outputs: Sequence[str]) -> list[str]:
        """Record the input as done with ``outputs``; then remove the outputs of its earlier
        run that this run did not make (e.g. the ``_std`` files of a run with ``uncertainty``,
        which would no longer match the new cube), but only those still exactly as that run
        wrote them (size and time). Returns the paths removed."""
        try:
            done = [os.path.abspath(p) for p in outputs]
            owned = sorted(set(done) | {q for q in self.record.get("owned", [])
                                        if os.path.lexists(q)})  # fmt: skip
            self.record.update(
                status="done", outputs=done, output_stamps={p: _file_stamp(p) for p in done},
                owned=owned, finished=time.strftime("%Y-%m-%dT%H:%M:%S"),
            )  # fmt: skip
            _write_marker(self.marker, self.record)
            self.target.owners.claim(self.marker, self.key, sorted(set(owned) | set(self.planned)))
            return self._remove_stale(set(done))
        finally:
            self.lock.close()

    def _remove_stale(self, done: set[str]) -> list[str]:
        prev = self.previous or {}
        stamps = prev.get("output_stamps")
        if prev.get("status") != "done" or not isinstance(stamps, dict):
            return []
        removed = []
        for p in prev.get("outputs", []) if isinstance(prev.get("outputs"), list) else []:
            p = str(p)
            if p in done or stamps.get(p) is None or _file_stamp(p) != stamps.get(p):
                continue  # this run's own, or changed since that run wrote it: kept
            if remove_confined(self.target.out, p):  # never outside the output folder
                removed.append(p)
        return removed

    def abandon(self) -> None:
        """No claim of an unfinished input is left: its earlier marker back (its earlier
        outputs, if any are left, are still its own), or no marker at all."""
        owners = self.target.owners
        if self.claimed:
            self.claimed = False
            try:
                if self.previous is not None:
                    _write_marker(self.marker, self.previous)
                    owners.claim(self.marker, self.key, _owned(self.previous))
                else:
                    remove_file(self.marker)
                    owners.outputs_of.pop(self.marker, None)
            except OSError:
                pass  # the claim stays: the input is redone next time, never skipped
        self.lock.close()
        remove_empty_folder(self.target.out / DONE_DIR)  # the marker folder, if nothing is in it

    def clean_temps(self) -> None:
        """Temporary files of a killed attempt at this input's outputs (e.g. a worker that
        died; its writer process is gone)."""
        for p in self.planned:
            clean_stale_temp_files_of(p)


class FilesTarget:
    """Files per input in the folder ``out`` (see the module docstring).

    Args:
        out: the output folder (must exist); holds the markers.
        fingerprint: identifies the settings and bundle of the run (resume redoes inputs made
            under another one).
        planned_outputs: ``input -> the paths its work will write`` (the ownership check).
        protected: files no output may be (the run's inputs and its bundle, by identity: an
            output that *is* one of them — whatever its folder or name — fails that input before
            its work starts, and nothing is written over it).
    """

    store: Path | None = None

    def __init__(
        self,
        out: Path,
        fingerprint: str | None = None,
        planned_outputs: PathsFn | None = None,
        protected: InputFiles | None = None,
    ) -> None:
        self.out = Path(out)
        self.fingerprint = fingerprint
        self.planned_outputs = planned_outputs
        self.protected = protected if protected is not None else InputFiles()
        self.owners = _Owners(self.out)

    @contextlib.contextmanager
    def opened(self) -> Iterator[FilesTarget]:
        yield self

    def cleaned(self) -> list[Path]:
        return clean_stale_temp_files(self.out) + clean_stale_temp_files(self.out / DONE_DIR)

    def is_done(self, inp: Path) -> bool:
        rec = _read_marker(_marker_path(self.out, inp))
        if rec is None or rec.get("status", "done") != "done":  # none, unreadable, interrupted
            return False
        try:
            stamp = input_stamp(inp)
        except OSError:
            return False
        if rec.get("input_stamp") != stamp:  # the input changed since it was processed
            return False
        if self.fingerprint is not None and rec.get("fingerprint") != self.fingerprint:
            return False  # other settings, or another bundle
        return _outputs_intact(rec)

    def stored_findings(self, inp: Path) -> list[Finding]:
        """The findings stored with a done input's cube (its first output among ``.npz``,
        ``.tif``, ``.nc``, ``.hdr``, ``.zarr`` named ``<stem>.<suffix>``; metadata only).

        Raises:
            FileFormatError: that file's stored findings are malformed (naming it).
        """
        rec = _read_marker(_marker_path(self.out, inp))
        outputs = rec.get("outputs") if rec is not None else None
        if not isinstance(outputs, list):
            return []
        by_name = {Path(q).name: Path(q) for q in outputs if isinstance(q, str)}
        for suffix in _FINDINGS_FROM:
            cube = by_name.get(inp.stem + suffix)
            if cube is not None:
                return read_cube_findings(cube)
        return []

    def begin(self, inp: Path) -> _Claim:
        claim = _Claim(self, inp)
        try:
            claim.begin()
        except BaseException:
            claim.abandon()
            raise
        return claim

    def frame(self, handle: _Claim) -> int | None:
        return None

    def finish(self, handle: _Claim, outputs: Sequence[str]) -> list[str]:
        handle.clean_temps()
        return handle.finish(outputs)

    def fail(self, handle: _Claim) -> None:
        with contextlib.suppress(OSError):
            handle.clean_temps()
        handle.abandon()


# --- one dataset store -----------------------------------------------------------------------


class StoreTarget:
    """One dataset store (:class:`~hsi_torch.io.dataset.CubeDataset`): a frame per input,
    complete when its ``done`` flag is set.

    Args:
        store: the store's folder; inputs: every input of the run (frames are given to them
            when the store is opened); wavelengths_nm, frame_size: the cubes' bands and
            ``(h, w)``; attrs: root attributes; fingerprint: as :class:`FilesTarget`'s.
    """

    def __init__(
        self,
        store: Path,
        inputs: Sequence[Path],
        wavelengths_nm: Sequence[float],
        frame_size: tuple[int, int],
        attrs: dict[str, Any],
        fingerprint: str | None,
    ) -> None:
        self.store: Path | None = Path(store)
        self.inputs = list(inputs)
        self.wavelengths_nm = list(wavelengths_nm)
        self.frame_size = frame_size
        self.attrs = attrs
        self.fingerprint = fingerprint
        self.ds: CubeDataset | None = None

    @contextlib.contextmanager
    def opened(self) -> Iterator[StoreTarget]:
        with CubeDataset.open(self.store, self.inputs, self.wavelengths_nm, self.frame_size,
                              self.attrs) as ds:  # fmt: skip
            self.ds = ds
            try:
                yield self
            finally:
                self.ds = None

    def _ds(self) -> CubeDataset:
        if self.ds is None:
            raise RuntimeError(f"dataset store {self.store}: use the target inside opened()")
        return self.ds

    def cleaned(self) -> list[Path]:
        out: list[Path] = []
        for name in ("cube", "valid", "metadata", "done", "source"):
            out += clean_stale_temp_files(self.store / name)
        return out

    def _record(self, inp: Path) -> tuple[int | None, dict[str, Any] | None]:
        """The frame of ``inp`` and its record (``None``: no frame, or not complete)."""
        ds = self._ds()
        i = ds.index.get(os.path.abspath(inp))
        return i, None if i is None else ds.frame_record(i)

    def is_done(self, inp: Path) -> bool:
        _i, rec = self._record(inp)
        if rec is None:
            return False
        try:
            stamp = input_stamp(inp)
        except OSError:
            return False
        return rec.get("input_stamp") == stamp and rec.get("fingerprint") == self.fingerprint

    def stored_findings(self, inp: Path) -> list[Finding]:
        """The findings stored in a done input's frame metadata.

        Raises:
            InputError: they are malformed (naming the store and the frame).
        """
        i, rec = self._record(inp)
        if rec is None:
            return []
        where = f"{self.store}: frame {i}'s metadata"
        try:
            return findings_from_dicts(rec.get("findings"), source=where)
        except InputError as exc:
            msg = str(exc)
            raise InputError(msg if msg.startswith(where) else f"{where}: {msg}") from None

    def begin(self, inp: Path) -> int:
        _require_input(inp)
        ds = self._ds()
        i = ds.index[os.path.abspath(inp)]
        ds.mark_pending(i)
        return i

    def frame(self, handle: int) -> int | None:
        return handle

    def finish(self, handle: int, outputs: Sequence[str]) -> list[str]:
        self._ds().clean_frame_temps(handle)
        return []

    def fail(self, handle: int) -> None:
        with contextlib.suppress(OSError):
            self._ds().clean_frame_temps(handle)
