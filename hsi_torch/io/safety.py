"""Small guards for files and values that come from outside: regular files only, bounded text.

- :func:`require_regular_file`: an input must be a regular file (a symlink to one is fine)
  before it is opened; a FIFO, a device or a socket is refused by name (opening a FIFO blocks
  until a writer appears: a batch would hang forever).
- :func:`file_kind`: what a file that is not a regular one is (a FIFO, a device, ...), the
  one wording of every such refusal.
- :func:`file_sha256`: the one content hash of a file (bundles, inputs, provenance, the
  precomputation cache's key), or of the bytes already read from it.
- :func:`short_repr`: ``repr`` of a value cut to a bounded length, for error messages about
  values read from a file (a YAML alias bomb expands to gigabytes when printed whole).
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import reprlib
import stat
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from hsi_torch.errors import FileFormatError, MissingFileError

__all__ = [
    "require_regular_file",
    "file_sha256",
    "short_repr",
    "short_text",
    "png_header",
    "unreadable_as_format_error",
    "MAX_REPR",
]

#: Longest ``repr`` of a value put into an error message (characters).
MAX_REPR = 200

_KINDS = (
    (stat.S_ISDIR, "a folder"),
    (stat.S_ISFIFO, "a FIFO (named pipe)"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
    (stat.S_ISLNK, "a symbolic link"),
)


def file_kind(mode: int) -> str:
    """What a file that is not a regular one is, from its ``st_mode``, for error messages."""
    return next((name for test, name in _KINDS if test(mode)), "not a regular file")


def require_regular_file(path: str | os.PathLike, what: str = "input file") -> Path:
    """Refuse ``path`` unless it is a regular file (symlinks followed), without opening it.

    Raises:
        MissingFileError: it does not exist.
        FileFormatError: it is a folder, a FIFO, a device or a socket (the message names it).
    """
    p = Path(path)
    try:
        mode = os.stat(p).st_mode
    except FileNotFoundError:
        raise MissingFileError(f"{what} not found: {p}") from None
    except (OSError, ValueError) as exc:
        raise FileFormatError(f"{p}: cannot read the {what} ({exc})") from None
    if not stat.S_ISREG(mode):
        raise FileFormatError(
            f"{p}: is {file_kind(mode)}, not a regular file; a {what} must be a file")
    return p


@contextlib.contextmanager
def unreadable_as_format_error(p: str | os.PathLike, kind: str) -> Iterator[None]:
    """Any error but a :class:`FileFormatError` inside the block (the file libraries raise many
    types for corrupt or truncated data) raised as a ``FileFormatError`` naming ``p``: ``"<p>:
    cannot read <kind> (<type>: <error>); the file is corrupt or truncated"``."""
    try:
        yield
    except FileFormatError:
        raise
    except Exception as exc:
        raise FileFormatError(f"{p}: cannot read {kind} ({type(exc).__name__}: {exc}); the file "
                              "is corrupt or truncated") from exc


_REPR = reprlib.Repr()
_REPR.maxstring = MAX_REPR
_REPR.maxother = MAX_REPR
_REPR.maxlist = _REPR.maxtuple = _REPR.maxdict = _REPR.maxset = 8
_REPR.maxlevel = 3


def file_sha256(source: str | os.PathLike | bytes | memoryview, chunk: int = 1 << 22) -> str:
    """Hex SHA-256 of a file's content, read in ``chunk``-byte blocks, or of ``source`` itself
    when it is the bytes already read from a file."""
    h = hashlib.sha256()
    if isinstance(source, (bytes, memoryview)):
        h.update(source)
        return h.hexdigest()
    with open(source, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def short_repr(value: Any, limit: int = MAX_REPR) -> str:
    """``repr(value)`` of bounded length (at most ``limit`` characters, ``...`` where cut).

    Nested containers are abbreviated level by level (:mod:`reprlib`: 8 items, 3 levels), so
    the cost is bounded too: a list that refers to itself a billion times over (a YAML alias
    bomb) is never expanded.
    """
    try:
        text = _REPR.repr(value)
    except Exception:  # noqa: BLE001 - a broken __repr__
        text = f"<{type(value).__name__}>"
    return text if len(text) <= limit else text[: max(0, limit - 3)] + "..."


def short_text(text: str, limit: int = 2 * MAX_REPR) -> str:
    """``text`` cut to at most ``limit`` characters (``...`` where cut)."""
    return text if len(text) <= limit else text[: max(0, limit - 3)] + "..."


_PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}  # colour type -> samples per pixel


def png_header(path: str | os.PathLike) -> tuple[tuple[int, int, int], int]:
    """``((H, W, C), bit_depth)`` of a PNG from its IHDR chunk (the first 33 bytes), before any
    pixel is decompressed: a reader checks the decoded size (``H·W·C·bit_depth/8``) against the
    expected sensor size with it, so a small file that inflates to gigabytes is refused first.

    Raises:
        FileFormatError: not a PNG, or a damaged header (the message names the file).
    """
    p = Path(path)
    with open(p, "rb") as f:
        head = f.read(33)
    if len(head) < 33 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        raise FileFormatError(f"{p}: not a PNG file (no PNG signature and IHDR header)")
    w, h = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    depth, ctype = head[24], head[25]
    if ctype not in _PNG_CHANNELS or depth not in (1, 2, 4, 8, 16) or w < 1 or h < 1:
        raise FileFormatError(f"{p}: damaged PNG header (size {w}x{h}, bit depth {depth}, "
                              f"colour type {ctype})")  # fmt: skip
    return (h, w, _PNG_CHANNELS[ctype]), depth
