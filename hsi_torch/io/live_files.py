"""Files still being written: what a live folder's watcher must not read yet.

The camera's tethering software (or a copy) writes a capture over some time; a reader that opens
it half-way gets a truncated file. :func:`is_temporary_name` tells the names such software gives a
file in progress, :func:`looks_complete` whether a file is whole by its own structure (used with a
stable size and modification time by :class:`hsi_torch.recon.batch.watch.FolderWatcher`).
"""

from __future__ import annotations

import os
from pathlib import Path

from hsi_torch.io.bounded import npy_header
from hsi_torch.io.captures import quiet_tifffile

__all__ = ["is_temporary_name", "looks_complete"]

#: Name endings of files still being written by tethering or copying software.
_TEMP_SUFFIXES = (".tmp", ".temp", ".part", ".partial", ".crdownload", ".download", ".filepart",
                  ".inprogress", ".swp", "~")  # fmt: skip


def is_temporary_name(name: str) -> bool:
    """A name that tethering or copying software gives a file it is still writing (a hidden
    name, ``*.tmp``, ``*.part``, ``*.crdownload``, ...): never a frame."""
    low = name.lower()
    return name.startswith((".", "~$")) or low.endswith(_TEMP_SUFFIXES)


def looks_complete(path: str | os.PathLike) -> bool:
    """Whether a capture file is whole by its own structure (a file still being written is
    not): an NPY holds the bytes its header declares, an NPZ has its ZIP directory (written
    last), a PNG ends with its ``IEND`` chunk, a TIFF (and TIFF-based RAW: DNG, NEF, CR2, ARW,
    ...) holds every strip or tile its pages point to. Other RAW formats: ``True`` (their
    writers are judged by a stable size alone). Never raises: ``False`` when it cannot tell."""
    p = Path(path)
    try:
        size = os.stat(p).st_size
        if size == 0:
            return False
        suffix = p.suffix.lower()
        if suffix == ".npy":
            import numpy as np  # lazy: numpy is loaded by the readers anyway

            with open(p, "rb") as f:
                shape, dtype = npy_header(f)
                need = f.tell() + int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
            return size >= need
        if suffix == ".npz":
            import zipfile

            with zipfile.ZipFile(p):  # its directory, written last, is there
                return True
        if suffix == ".png":
            with open(p, "rb") as f:
                f.seek(max(0, size - 12))
                return b"IEND" in f.read()
        import tifffile  # lazy: TIFF and TIFF-based RAW

        try:
            with quiet_tifffile(), tifffile.TiffFile(p) as tif:
                end = 0
                for page in tif.pages:
                    offs = getattr(page, "dataoffsets", ()) or ()
                    counts = getattr(page, "databytecounts", ()) or ()
                    end = max([end] + [o + c for o, c in zip(offs, counts, strict=False)])
                return end <= size and len(tif.pages) > 0
        except Exception:  # noqa: BLE001 - not readable as a TIFF (yet)
            return suffix not in (
                ".tif",
                ".tiff",
                ".dng",
                ".nef",
                ".cr2",
                ".arw",
                ".pef",
                ".orf",
                ".rw2",
                ".srw",
                ".kdc",
                ".dcr",
                ".3fr",
                ".erf",
            )
    except Exception:  # noqa: BLE001 - a header not written yet, a file removed meanwhile
        return False
