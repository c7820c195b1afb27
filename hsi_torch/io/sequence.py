"""Sequences of captures: an ordered set of frames of a moving scene, each with its time.

:func:`open_sequence` turns the inputs into a :class:`CaptureSequence` without decoding a pixel
(only headers are read: the sizes, the EXIF tags); its frames are read one at a time
(:meth:`CaptureSequence.read`), so a sequence of any length needs the memory of one capture.

**Inputs** (the table with examples: docs/sequences_io.md): a folder (every capture file in it,
hidden and temporary names such as ``*.tmp``, ``*.part``, ``*.crdownload`` skipped, in natural
name order: ``frame_2`` before ``frame_10``), files and glob patterns (natural name order), one
multi-page TIFF (one frame per page, in page order; a page's JSON ``ImageDescription`` may give
its ``time_s``) or a sheet (``.csv``: columns ``file``, required, relative to the sheet's folder;
``time_s`` in seconds or ``timestamp`` in ISO 8601; optionally ``page``; ``#`` starts a comment).

**Each frame's time** (``time_from``, default ``"auto"``: the first that every frame has):
``"sheet"`` (its ``time_s`` / ``timestamp``), ``"name"`` (an elapsed ``t=12.5s``, ``t12.5s``,
``t_0012.500s``, ``t=250ms`` — unit ``s`` when absent — or an absolute ``20261207-130500.250`` /
``20261207T130500_250``), ``"exif"`` (``DateTimeOriginal`` + ``SubSecTimeOriginal`` through
``exifread``, ``DateTime`` when the original is absent; absolute) or ``"index"`` (frame ``k`` at
``k × frame_interval_s``, default 1 s: only the order). ``"mtime"`` (the file's modification
time, absolute) only when asked for (``hsi-torch watch`` falls back to it). Times (``time_s``)
are seconds since the first frame where absolute (its date and time is
:attr:`CaptureSequence.origin`, each frame's :attr:`SequenceFrame.timestamp` its ISO 8601 date
and time in the camera's local time; EXIF's ``OffsetTimeOriginal`` is kept when present), as
given where relative.

**Checked before any frame is read**, each error naming the file at fault: a file listed twice,
two frames at the same time, times that go backwards in the frames' order (the name order or the
sheet's: the order is never silently changed), captures of different sizes (from their headers),
a folder or pattern with no capture.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
import re
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hsi_torch.errors import FileFormatError, InputError, MissingFileError
from hsi_torch.io.bounded import csv_header, csv_lines, declared_image_size
from hsi_torch.io.captures import (
    SUPPORTED_SUFFIXES,
    LinearCapture,
    exif_tags,
    quiet_tifffile,
    read_any,
)
from hsi_torch.io.live_files import is_temporary_name, looks_complete
from hsi_torch.io.paths import expand_inputs
from hsi_torch.io.safety import require_regular_file, short_text

__all__ = [
    "SequenceFrame",
    "CaptureSequence",
    "open_sequence",
    "TIME_SOURCES",
    "is_temporary_name",
    "time_from_name",
    "exif_time",
    "natural_key",
    "is_sequence_input",
    "frame_time",
    "file_mtime",
    "looks_complete",
]

#: Where a frame's time comes from (``time_from``; ``"auto"`` picks the first every frame has).
TIME_SOURCES = ("sheet", "name", "exif", "index", "mtime")
#: Largest sheet read (bytes).
_MAX_SHEET_BYTES = 16 << 20
_ELAPSED = re.compile(
    r"(?<![A-Za-z0-9])t[=_-]?(?P<v>\d+(?:\.\d+)?)(?P<u>ms|s)?(?![A-Za-z0-9])", re.IGNORECASE)
_STAMP = re.compile(r"(?<!\d)(?P<d>\d{8})[T_-](?P<t>\d{6})(?:[._](?P<f>\d{1,6}))?(?!\d)")


@dataclass(frozen=True)
class SequenceFrame:
    """One frame of a sequence (nothing decoded).

    Attributes:
        index: position in the sequence (0 first).
        path: the capture file.
        page: the page of a multi-page TIFF, else ``None``.
        time_s: the frame's time in seconds: since the first frame for absolute times (EXIF,
            dated names, sheet timestamps), as given for relative ones (a sheet's ``time_s``,
            ``t=12.5s`` names, a page's ``time_s``), ``index × frame_interval_s`` otherwise.
        timestamp: the frame's date and time (ISO 8601) when absolute times are known, else
            ``None``.
        time_source: ``"sheet"``, ``"name"``, ``"exif"`` or ``"index"`` (:data:`TIME_SOURCES`).
    """

    index: int
    path: Path
    page: int | None
    time_s: float
    timestamp: str | None
    time_source: str

    @property
    def source(self) -> str:
        """The frame's name in stores and messages: the absolute path (``#page=N`` for a page)."""
        base = os.path.abspath(self.path)
        return base if self.page is None else f"{base}#page={self.page}"


class CaptureSequence(Sequence[SequenceFrame]):
    """An ordered set of frames (:func:`open_sequence`); a ``Sequence`` of
    :class:`SequenceFrame`. Frames are decoded only by :meth:`read` / :meth:`captures`.

    Attributes:
        frames: the frames, in time order.
        origin: the first frame's date and time (ISO 8601) when absolute, else ``None``.
        frame_size: ``(H, W)`` of every capture (from the headers), or ``None`` when a header
            does not say (camera RAW without LibRaw's size, ...).
        kind: what the inputs were: ``"folder"``, ``"files"``, ``"multipage"`` or ``"sheet"``.
    """

    def __init__(self, frames: list[SequenceFrame], origin: str | None,
                 frame_size: tuple[int, int] | None, kind: str) -> None:  # fmt: skip
        self.frames = frames
        self.origin = origin
        self.frame_size = frame_size
        self.kind = kind

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, i):  # type: ignore[override]
        return self.frames[i]

    def __iter__(self) -> Iterator[SequenceFrame]:
        return iter(self.frames)

    @property
    def time_source(self) -> str:
        """Where the times came from (every frame's is the same)."""
        return self.frames[0].time_source if self.frames else "index"

    def read(self, frame: SequenceFrame | int, **read_kw: Any) -> LinearCapture:
        """Decode one frame (:func:`hsi_torch.io.read_any`; ``read_kw`` its keyword arguments;
        a page of a multi-page TIFF is decoded alone)."""
        f = self.frames[frame] if isinstance(frame, int) else frame
        return read_any(f.path, page=f.page, **read_kw)

    def captures(self, **read_kw: Any) -> Iterator[tuple[SequenceFrame, LinearCapture]]:
        """``(frame, capture)`` for every frame in order, one decoded at a time."""
        for f in self.frames:
            yield f, self.read(f, **read_kw)

    def describe(self) -> str:
        """One line: how many frames, from what, their times."""
        n = len(self.frames)
        span = self.frames[-1].time_s if n else 0.0
        where = {"folder": "a folder", "files": "files", "multipage": "a multi-page TIFF",
                 "sheet": "a sheet"}[self.kind]  # fmt: skip
        return (
            f"sequence of {n} frame(s) from {where}, times from {self.time_source}"
            f" ({span:g} s from first to last"
            + (f", starting {self.origin}" if self.origin else "")
            + ")"
        )


# ----------------------------------------------------------------------------------------------
# names and times


def natural_key(name: str) -> list[Any]:
    """Sort key of a file name with runs of digits compared as numbers (``f2`` < ``f10``)."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def time_from_name(name: str) -> tuple[float | None, _dt.datetime | None]:
    """The time a file name gives: ``(elapsed seconds, None)`` for ``t=12.5s``-style names,
    ``(None, datetime)`` for ``20261207-130500.250``-style names, ``(None, None)`` otherwise
    (see the module docstring)."""
    stem = name
    m = _STAMP.search(stem)
    if m is not None:
        frac = m["f"] or "0"
        try:
            t = _dt.datetime.strptime(m["d"] + m["t"], "%Y%m%d%H%M%S")
        except ValueError:
            t = None
        if t is not None:
            return None, t + _dt.timedelta(microseconds=int(frac.ljust(6, "0")))
    matches = list(_ELAPSED.finditer(Path(stem).stem if "." in stem else stem))
    if len(matches) == 1:
        v = float(matches[0]["v"])
        return (v / 1000.0 if (matches[0]["u"] or "s").lower() == "ms" else v), None
    return None, None


def _parse_exif_datetime(text: str, subsec: str | None, offset: str | None) -> _dt.datetime:
    t = _dt.datetime.strptime(text.strip().strip("\x00").strip(), "%Y:%m:%d %H:%M:%S")
    digits = re.sub(r"\D", "", subsec or "")[:6]
    if digits:
        t += _dt.timedelta(microseconds=int(digits.ljust(6, "0")))
    off = (offset or "").strip().strip("\x00")
    m = re.fullmatch(r"([+-])(\d{2}):?(\d{2})", off)
    if m:
        sign = 1 if m[1] == "+" else -1
        t = t.replace(tzinfo=_dt.timezone(sign * _dt.timedelta(hours=int(m[2]), minutes=int(m[3]))))
    return t


def exif_time(path: str | os.PathLike) -> _dt.datetime | None:
    """The capture time of a TIFF or camera RAW/DNG from its EXIF tags (``exifread``):
    ``DateTimeOriginal`` + ``SubSecTimeOriginal`` (+ ``OffsetTimeOriginal`` when written),
    else ``DateTime`` + ``SubSecTime``; ``None`` when the file has none (or no EXIF at all).

    Raises:
        FileFormatError: a date tag that is not ``YYYY:MM:DD HH:MM:SS`` (naming the file).
    """
    p = require_regular_file(path, "capture file")
    tags = exif_tags(p)

    def tag(*names: str) -> str | None:
        for n in names:
            v = tags.get(n)
            if v is not None and str(v.printable).strip().strip("\x00").strip():
                return str(v.printable)
        return None

    for base, sub, off in (("DateTimeOriginal", "SubSecTimeOriginal", "OffsetTimeOriginal"),
                           ("DateTime", "SubSecTime", "OffsetTime")):  # fmt: skip
        text = tag(f"EXIF {base}", f"Image {base}")
        if text is None:
            continue
        try:
            return _parse_exif_datetime(text, tag(f"EXIF {sub}", f"Image {sub}"),
                                        tag(f"EXIF {off}", f"Image {off}"))  # fmt: skip
        except ValueError:
            raise FileFormatError(f"{p}: EXIF {base} {short_text(text, 40)!r} is not a date and "
                                  "time (YYYY:MM:DD HH:MM:SS)") from None  # fmt: skip
    return None


def file_mtime(path: str | os.PathLike) -> _dt.datetime:
    """A file's modification time as a local date and time (no zone)."""
    return _dt.datetime.fromtimestamp(os.stat(path).st_mtime)


def frame_time(
    path: str | os.PathLike, time_from: str = "auto"
) -> tuple[str, float | None, _dt.datetime | None]:
    """One file's time, on its own (a live folder's frames arrive one by one): ``(source,
    elapsed s or None, datetime or None)``; ``"auto"`` tries the name, EXIF, then the
    modification time.

    Raises:
        InputError: the asked source gives no time for this file (naming it).
    """
    p = Path(path)
    order = ["name", "exif", "mtime"] if time_from == "auto" else [time_from]
    for src in order:
        if src == "name":
            v, t = time_from_name(p.name)
            if v is not None or t is not None:
                return src, v, t
        elif src == "exif":
            t = exif_time(p) if p.suffix.lower() not in (".png", ".npy", ".npz") else None
            if t is not None:
                return src, None, t
        elif src == "mtime":
            return src, None, file_mtime(p)
        else:
            raise InputError(f"{p}: a file arriving on its own cannot be timed by {src!r} "
                             "(use name, exif or mtime)")  # fmt: skip
    raise InputError(f"{p}: no time from {time_from} for this file")


def _iso(t: _dt.datetime) -> str:
    return t.isoformat(timespec="microseconds")


# ----------------------------------------------------------------------------------------------
# opening


def is_sequence_input(inputs: str | os.PathLike | Iterable[str | os.PathLike]) -> bool:
    """Whether ``inputs`` can only be a sequence: one folder, one ``.csv`` sheet, or one TIFF
    with more than one page (what ``hsi-torch reconstruct`` detects, and says)."""
    items = [inputs] if isinstance(inputs, (str, os.PathLike)) else list(inputs)
    if len(items) != 1:
        return False
    p = Path(os.path.expanduser(os.fspath(items[0])))
    if p.is_dir() or (p.suffix.lower() == ".csv" and p.is_file()):
        return True
    return p.suffix.lower() in (".tif", ".tiff") and p.is_file() and _tiff_pages(p) > 1


def _tiff_pages(p: Path) -> int:
    import tifffile  # lazy: only TIFF inputs

    try:
        with quiet_tifffile(), tifffile.TiffFile(p) as tif:
            return len(tif.pages)
    except Exception:  # noqa: BLE001 - not a readable TIFF: the reader will say why
        return 0


def _folder_files(folder: Path) -> list[Path]:
    files = [Path(e.path) for e in os.scandir(folder)
             if e.is_file() and not is_temporary_name(e.name)
             and Path(e.name).suffix.lower() in SUPPORTED_SUFFIXES]  # fmt: skip
    if not files:
        raise InputError(f"{folder}: no capture file in this folder (looked for "
                         f"{', '.join(SUPPORTED_SUFFIXES[:5])}, camera RAW)")  # fmt: skip
    return sorted(files, key=lambda q: natural_key(q.name))


def open_sequence(
    inputs: str | os.PathLike | Iterable[str | os.PathLike],
    *,
    time_from: str = "auto",
    frame_interval_s: float | None = None,
    check_sizes: bool = True,
) -> CaptureSequence:
    """The sequence the inputs describe (see the module docstring); nothing decoded.

    Args:
        inputs: a folder, a sheet (``.csv``), a multi-page TIFF, or capture files and glob
            patterns (a ``str``/path or a list of them).
        time_from: ``"auto"`` or one of :data:`TIME_SOURCES` (a source some frame lacks is an
            error naming that frame).
        frame_interval_s: seconds between frames for ``"index"`` times (default 1).
        check_sizes: compare every capture's size from its header (a file whose header gives
            none is checked when it is read).

    Raises:
        InputError: no frame, a duplicate file or time, times going backwards, mixed sizes, an
            unknown ``time_from`` — naming the file.
        MissingFileError: a listed file does not exist.
    """
    if time_from != "auto" and time_from not in TIME_SOURCES:
        raise InputError(f"time_from must be 'auto' or one of {', '.join(TIME_SOURCES)}, got "
                         f"{time_from!r}")  # fmt: skip
    step = 1.0 if frame_interval_s is None else float(frame_interval_s)
    if not (math.isfinite(step) and step > 0):
        raise InputError(f"frame_interval_s must be a number > 0 (seconds), got "
                         f"{frame_interval_s!r}")  # fmt: skip
    items = [inputs] if isinstance(inputs, (str, os.PathLike)) else list(inputs)
    if not items:
        raise InputError("a sequence needs at least one input (a folder, a sheet, a multi-page "
                         "TIFF or capture files)")  # fmt: skip
    sheet_times: list[tuple[float | None, _dt.datetime | None]] | None = None
    single = Path(os.path.expanduser(os.fspath(items[0]))) if len(items) == 1 else None
    if single is not None and single.is_dir():
        kind, entries = "folder", [(p, None) for p in _folder_files(single)]
    elif single is not None and single.suffix.lower() == ".csv":
        kind = "sheet"
        entries, sheet_times = _read_sequence_sheet(single)
    elif (
        single is not None
        and single.suffix.lower() in (".tif", ".tiff")
        and single.is_file()
        and _tiff_pages(single) > 1
    ):
        kind = "multipage"
        entries = [(single, k) for k in range(_tiff_pages(single))]
    else:
        kind = "files"
        plain = [Path(os.path.expanduser(os.fspath(i))) for i in items
                 if not set(os.fspath(i)) & set("*?[")]  # fmt: skip
        _check_duplicates([(p, None) for p in plain])  # (expand_inputs drops repeats)
        files = [p for p in expand_inputs(items) if not is_temporary_name(p.name)]
        if any(Path(os.path.expanduser(os.fspath(i))).is_dir() for i in items):
            raise InputError("a sequence is one folder, or files and patterns: not several "
                             "folders (pass 'FOLDER/*.tif')")  # fmt: skip
        has_glob = any(set(os.fspath(i)) & set("*?[") for i in items)
        if has_glob:  # patterns: natural name order over all of them
            files = sorted(files, key=lambda q: natural_key(q.name))
        entries = [(p, None) for p in files]
    _check_duplicates(entries)
    for p, _ in entries:
        if not p.exists():
            raise MissingFileError(f"sequence frame not found: {p}")
    times = _frame_times(entries, kind, time_from, sheet_times, step)
    size = _check_sizes(entries) if check_sizes else None
    return _build(entries, times, kind, size)


def _check_duplicates(entries: list[tuple[Path, int | None]]) -> None:
    seen: dict[tuple[str, int | None], int] = {}
    for i, (p, page) in enumerate(entries):
        key = (os.path.realpath(p), page)
        if key in seen:
            raise InputError(f"{_name((p, page))} is listed twice in the sequence (frames "
                             f"{seen[key]} and {i}); each capture is one frame")  # fmt: skip
        seen[key] = i


def _frame_times(
    entries: list[tuple[Path, int | None]], kind: str, time_from: str,
    sheet_times: list[tuple[float | None, _dt.datetime | None]] | None, step: float,
) -> tuple[str, list[tuple[float | None, _dt.datetime | None]]]:  # fmt: skip
    """``(source, [(elapsed s or None, datetime or None)])`` for every frame."""
    order = [time_from] if time_from != "auto" else ["sheet", "name", "exif", "index"]
    for src in order:
        if src == "mtime":
            return src, [(None, file_mtime(p)) for p, _ in entries]
        if src == "sheet":
            if sheet_times is None:
                if time_from == "sheet":
                    raise InputError("time_from='sheet' needs a sheet (.csv) as the input")
                continue
            return src, sheet_times
        if src == "name":
            if kind == "multipage":
                got = _page_times(entries[0][0], len(entries))
            else:
                got = [time_from_name(p.name) for p, _ in entries]
            missing = [entries[i] for i, t in enumerate(got) if t == (None, None)]
            kinds = {t[0] is None for t in got if t != (None, None)}
            if not missing and len(kinds) == 1:
                return src, got
            if time_from == "name":
                if missing:
                    raise InputError(_name(missing[0]) + ": no time in the name (e.g. 't=12.5s', "
                                     "'t0012.5s', '20261207-130500.250')")  # fmt: skip
                raise InputError("the file names mix elapsed times (t=…s) and dates: give one "
                                 "kind of time")  # fmt: skip
            continue
        if src == "exif":
            if kind == "multipage":
                if time_from == "exif":
                    raise InputError(
                        f"{entries[0][0]}: the pages of a multi-page TIFF carry "
                        "no EXIF time each; use a sheet or the pages' time_s")
                continue
            got_dt: list[tuple[float | None, _dt.datetime | None]] = []
            for p, _ in entries:
                t = exif_time(p) if p.suffix.lower() not in (".png", ".npy", ".npz") else None
                if t is None:
                    if time_from == "exif":
                        raise InputError(f"{p}: no EXIF DateTimeOriginal (nor DateTime) to "
                                         "time this frame by")  # fmt: skip
                    break
                got_dt.append((None, t))
            else:
                aware = {t[1].tzinfo is not None for t in got_dt if t[1] is not None}
                if len(aware) > 1:  # some with an offset, some without: compare as written
                    got_dt = [(None, t.replace(tzinfo=None)) for _, t in got_dt if t]
                return src, got_dt
            continue
        return "index", [(k * step, None) for k in range(len(entries))]
    raise AssertionError("unreachable")  # pragma: no cover


def _page_times(p: Path, n: int) -> list[tuple[float | None, _dt.datetime | None]]:
    """The ``time_s`` of each page's JSON description (``(None, None)`` where absent)."""
    import tifffile  # lazy: only TIFF inputs

    out: list[tuple[float | None, _dt.datetime | None]] = []
    with quiet_tifffile(), tifffile.TiffFile(p) as tif:
        for k in range(n):
            try:
                d = json.loads(tif.pages[k].description or "")
            except (ValueError, RecursionError, IndexError):
                d = None
            v = d.get("time_s") if isinstance(d, dict) else None
            ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
            out.append((float(v), None) if ok else (None, None))
    return out


def _build(
    entries: list[tuple[Path, int | None]],
    timed: tuple[str, list[tuple[float | None, _dt.datetime | None]]],
    kind: str, size: tuple[int, int] | None,
) -> CaptureSequence:  # fmt: skip
    source, times = timed
    absolute = times[0][1] is not None
    if absolute:
        t0 = times[0][1]
        assert t0 is not None
        secs = [(t - t0).total_seconds() for _, t in times]  # type: ignore[operator]
        stamps: list[str | None] = [_iso(t) for _, t in times]  # type: ignore[arg-type]
        origin: str | None = _iso(t0)
    else:  # relative times as given (a sheet's time_s, t=12.5s names, the index)
        secs = [float(v) for v, _ in times]  # type: ignore[arg-type]
        stamps, origin = [None] * len(times), None
    for i in range(1, len(entries)):
        if secs[i] <= secs[i - 1]:
            what = "at the same time as" if secs[i] == secs[i - 1] else "earlier than"
            cur, prev = _name(entries[i]), _name(entries[i - 1])
            order = (
                "the sheet's order"
                if kind == "sheet"
                else ("the page order" if kind == "multipage" else "the name order")
            )
            raise InputError(
                f"{cur}: its time ({source}: {_when(stamps[i], secs[i])}) is {what} the frame "
                f"before it in {order}, {prev} ({_when(stamps[i - 1], secs[i - 1])}); a "
                "sequence's times increase frame by frame: fix the times, or rename the files "
                "(or reorder the sheet) so that the order is the time order")  # fmt: skip
    frames = [SequenceFrame(i, p, page, secs[i], stamps[i], source)
              for i, (p, page) in enumerate(entries)]  # fmt: skip
    return CaptureSequence(frames, origin, size, kind)


def _name(entry: tuple[Path, int | None]) -> str:
    p, page = entry
    return f"{p}" + (f" page {page}" if page is not None else "")


def _when(stamp: str | None, secs: float) -> str:
    return stamp if stamp else f"t = {secs:g} s"


def _check_sizes(entries: list[tuple[Path, int | None]]) -> tuple[int, int] | None:
    if entries and entries[0][1] is not None:  # a multi-page TIFF: every page's shape
        return _page_sizes(entries[0][0])
    first: tuple[Path, tuple[int, int]] | None = None
    for p, _ in entries:
        hw = declared_image_size(p)
        if hw is None:
            continue
        if first is None:
            first = (p, hw)
        elif hw != first[1]:
            raise InputError(f"{p}: a capture of (H, W) = {hw}, but {first[0]} (an earlier "
                             f"frame) is {first[1]}: every frame of a sequence has the same "
                             "size")  # fmt: skip
    return None if first is None else first[1]


def _page_sizes(p: Path) -> tuple[int, int]:
    import tifffile  # lazy: only TIFF inputs

    with quiet_tifffile(), tifffile.TiffFile(p) as tif:
        shapes = [tuple(int(v) for v in pg.shape) for pg in tif.pages]
    hw = [s[:2] if len(s) == 3 and s[-1] in (1, 3) else s[-2:] for s in shapes]
    for k, s in enumerate(hw):
        if s != hw[0]:
            raise InputError(f"{p}: page {k} is (H, W) = {s}, page 0 is {hw[0]}: every frame "
                             "of a sequence has the same size")  # fmt: skip
    return hw[0]  # type: ignore[return-value]


def _read_sequence_sheet(
    sheet: Path,
) -> tuple[list[tuple[Path, int | None]], list[tuple[float | None, _dt.datetime | None]]]:
    p = require_regular_file(sheet, "sequence sheet")
    if p.stat().st_size > _MAX_SHEET_BYTES:
        raise FileFormatError(f"{p}: a sequence sheet larger than {_MAX_SHEET_BYTES >> 20} MiB")
    reader, header = csv_header(p, "sequence sheet")
    cols = [h.strip().lower() for h in header or []]
    known = ("file", "time_s", "timestamp", "page")
    for c in cols:
        if c not in known:
            raise FileFormatError(f"sequence sheet {p}: unknown column {c!r}; the columns are "
                                  f"{', '.join(known)}")  # fmt: skip
    if "file" not in cols or not ({"time_s", "timestamp"} & set(cols)):
        raise FileFormatError(
            f"sequence sheet {p}: the header needs a 'file' column and a "
            f"'time_s' or 'timestamp' column (got {','.join(cols) or 'none'})")
    entries: list[tuple[Path, int | None]] = []
    times: list[tuple[float | None, _dt.datetime | None]] = []
    for where, cells in csv_lines(reader, p):
        row = dict(zip(cols, (c.strip() for c in cells), strict=False))
        if not row.get("file"):
            raise FileFormatError(f"{where}: no file")
        f = Path(row["file"])
        f = f if f.is_absolute() else p.parent / f
        page: int | None = None
        if row.get("page"):
            try:
                page = int(row["page"])
            except ValueError:
                raise FileFormatError(
                    f"{where}: page {row['page']!r} is not a whole number"
                ) from None
            if page < 0:
                raise FileFormatError(f"{where}: page {page} is negative")
        if row.get("time_s"):
            try:
                v = float(row["time_s"])
            except ValueError:
                v = math.nan
            if not math.isfinite(v):
                raise FileFormatError(f"{where}: time_s {row['time_s']!r} is not a number of "
                                      "seconds")  # fmt: skip
            times.append((v, None))
        elif row.get("timestamp"):
            try:
                t = _dt.datetime.fromisoformat(row["timestamp"].replace("Z", "+00:00"))
            except ValueError:
                raise FileFormatError(
                    f"{where}: timestamp {row['timestamp']!r} is not an ISO "
                    "8601 date and time (2026-12-07T13:05:00.250)"
                ) from None
            times.append((None, t))
        else:
            raise FileFormatError(f"{where}: no time (column time_s or timestamp)")
        entries.append((f, page))
    if not entries:
        raise InputError(f"sequence sheet {p}: no frame listed")
    if len({t[0] is None for t in times}) > 1:
        raise FileFormatError(f"sequence sheet {p}: some lines give time_s, others timestamp: "
                              "give one kind of time")  # fmt: skip
    if times[0][1] is not None and len({t[1].tzinfo is None for t in times if t[1]}) > 1:
        raise FileFormatError(f"sequence sheet {p}: some timestamps have a time zone, others "
                              "not")  # fmt: skip
    return entries, times
