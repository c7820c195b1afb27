"""The paths of a batch run: inputs (files and globs), the output folder, the outputs' names.

:func:`expand_inputs` turns files and glob patterns into the inputs of a run,
:func:`check_input_name` refuses a name that cannot name outputs (not valid UTF-8),
:func:`check_out_dir` / :func:`ensure_out_dir` check and create the output folder,
:func:`claim_out_dir` refuses an output folder holding files of something else (a script's
``--out``), and
:func:`output_paths` names the files a reconstruction writes for one input (``DIR/<stem>.tif``,
``<stem>_preview.png``, ...), and :func:`file_states` tells which files of an output folder a
rerun wrote. Every command that takes inputs or an output folder uses these.
"""

from __future__ import annotations

import glob
import os
from collections.abc import Iterable, Sequence
from pathlib import Path

from hsi_torch.errors import HSIError, InputError

__all__ = [
    "expand_inputs",
    "check_input_name",
    "shown_path",
    "check_out_dir",
    "ensure_out_dir",
    "output_paths",
    "file_states",
    "out_entries",
    "refuse_not_empty",
    "claim_out_dir",
    "CUBE_SUFFIXES",
]

_GLOB_CHARS = set("*?[")

#: the files of each cube format (:func:`hsi_torch.io.cube.save_cube_formats`)
CUBE_SUFFIXES: dict[str, tuple[str, ...]] = {
    "tiff": (".tif", ".vrt"), "envi": (".hdr", ".img"), "npz": (".npz",), "netcdf": (".nc",),
    "zarr": (".zarr",),
}  # fmt: skip


def expand_inputs(inputs: Iterable[str | os.PathLike] | str | os.PathLike) -> list[Path]:
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
                    f"'{Path(text) / '*.tif'}'")
            paths = [p]
        for p in paths:
            key = os.path.abspath(p)
            if key not in seen:
                seen.add(key)
                out.append(p)
    return out


def shown_path(path: str | os.PathLike) -> str:
    """``path`` as printable text: bytes that are not UTF-8 as ``\\xNN`` escapes."""
    return os.fsencode(path).decode("utf-8", "backslashreplace")


def check_input_name(path: str | os.PathLike) -> None:
    """Refuse an input whose name is not valid UTF-8: its outputs, resume markers and stored
    metadata are named after it.

    Raises:
        InputError: naming the file (undecodable bytes shown as ``\\xNN``).
    """
    try:
        os.fspath(path).encode("utf-8")
    except UnicodeEncodeError:
        raise InputError(
            f"{shown_path(path)}: the file name is not valid UTF-8 (its outputs and metadata are "
            "named after it); rename the file"
        ) from None


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


def output_paths(
    stem: str | os.PathLike,
    formats: Sequence[str],
    *,
    uncertainty: bool = False,
    preview: bool = True,
    spectra: bool = False,
) -> list[Path]:
    """The files a reconstruction writes for ``stem`` (``DIR/<input stem>``): the cube in
    ``formats`` (:data:`CUBE_SUFFIXES`), with ``uncertainty`` the standard deviation as
    ``<stem>_std.*`` (every format but NPZ, which holds it as a key) and ``<stem>_std.png``
    beside the preview, ``<stem>_preview.png``, and with ``spectra`` ``<stem>_spectra.png``."""
    s = Path(stem)

    def named(suffix: str) -> Path:
        return s.with_name(s.name + suffix)

    out = [named(x) for f in formats for x in CUBE_SUFFIXES[f]]
    if uncertainty:
        out += [named("_std" + x) for f in formats if f != "npz" for x in CUBE_SUFFIXES[f]]
    if preview:
        out.append(named("_preview.png"))
        if uncertainty:
            out.append(named("_std.png"))
    if spectra:
        out.append(named("_spectra.png"))
    return out


def file_states(folder: str | os.PathLike) -> dict[str, tuple[int, int, int]]:
    """Every file below ``folder`` (recursively; symlinks not followed into folders): relative
    path (``/``-separated) → ``(size, modification time in ns, inode)``. Taken before and after
    a run, a path whose state is unchanged was not written by the run (an atomic write makes a
    new inode). A missing folder gives ``{}``; this package's temporary files are left out."""
    from hsi_torch.io.atomic import TEMP_FILE_RE  # lazy: atomic imports numpy

    root = Path(folder)
    states: dict[str, tuple[int, int, int]] = {}
    for dirpath, _dirs, files in os.walk(root):
        for name in files:
            if TEMP_FILE_RE.match(name):
                continue
            p = Path(dirpath) / name
            try:
                st = p.stat()
            except OSError:
                continue
            states[p.relative_to(root).as_posix()] = (st.st_size, st.st_mtime_ns, st.st_ino)
    return states


def out_entries(out: str | os.PathLike) -> list[str]:
    """The sorted names in the folder ``out`` (none when it is not a folder)."""
    p = Path(out)
    return sorted(q.name for q in p.iterdir()) if p.is_dir() else []


def refuse_not_empty(out: str | os.PathLike, names: Sequence[str], earlier: str,
                     writes: str) -> None:  # fmt: skip
    """Refuse the ``--out`` folder ``out`` that holds ``names`` but no earlier ``earlier``
    (e.g. ``"demo run"``) whose run ``writes`` files there (e.g. ``"it writes a capture set"``).

    Raises:
        InputError: always; it names the folder and a few of ``names``.
    """
    shown = ", ".join(names[:5]) + (", ..." if len(names) > 5 else "")
    raise InputError(
        f"--out {out} is not empty ({shown}) and holds no earlier {earlier}; {writes} there "
        "and would replace files of those names: choose a new or empty folder")


def claim_out_dir(
    out: str | os.PathLike, marker: str, earlier: str, writes: str, *, script: str | None = None,
    earlier_names: Sequence[str] = (),
) -> Path:
    """Take the output folder ``out`` of a command or script that writes into it in place.

    ``out`` must be new, empty, or hold ``marker`` (a hidden file naming the folder's writer,
    left by an earlier or interrupted run of the same writer); a folder holding anything else is
    refused before anything is written, naming a few of its files (:func:`refuse_not_empty`,
    the refusal of ``hsi-torch demo`` and ``experiment``). Then the folder is created and
    ``marker`` written first, so the writer's own folder is accepted the next time.

    Args:
        marker: the marker's file name in ``out`` (e.g. ``.hsi_torch_bench_simulate``).
        earlier: what an earlier run is called in the message (``"run of drift_small.py"``).
        writes: what the run writes there, for the message (``"it writes drift_small.json"``).
        script: a script's name: errors are raised as ``SystemExit("SCRIPT: error: …")``
            (exit status 1), for a script's ``main``.
        earlier_names: names in ``out`` that only the writer makes (e.g. its result file): a
            folder holding one is an earlier run from before the writer wrote ``marker``, and
            is accepted too (as ``demo`` accepts a demo's ``summary.json``). Never a generic
            name (``rows``, ``ideal``): a user's folder holding one would be written into.

    Returns:
        ``out`` as a :class:`~pathlib.Path`.

    Raises:
        InputError: ``out`` holds files but not ``marker``.
        ValueError: ``out`` exists and is not a folder.
        OSError: it cannot be created or the marker written (names the folder).
    """
    from hsi_torch.io.atomic import atomic_write_text  # lazy: atomic imports numpy

    try:
        p = check_out_dir(out)
        names = out_entries(p)
        if names and marker not in names and not set(earlier_names) & set(names):
            refuse_not_empty(p, names, earlier, writes)
        ensure_out_dir(p)
        atomic_write_text(p / marker, f"a folder written by {script or earlier}\n")
    except (HSIError, ValueError, OSError) as exc:
        if script is None:
            raise
        raise SystemExit(f"{script}: error: {exc}") from None
    return p
