"""``hsi-torch view FILE…``: open cube files in napari with the spectrum widget docked."""

from __future__ import annotations

import argparse
import glob
import os
from collections.abc import Sequence
from pathlib import Path

from hsi_torch.errors import InputError

__all__ = ["run_view", "check_screenshot"]

#: The PNG ``Software`` text of our screenshots (the same as the plugin's; not imported from it:
#: the plugin imports napari).
SCREENSHOT_SOFTWARE = "hsi-torch view"

_HINT = "pip install 'hsi-torch[viewer]'"


def _point(text: str) -> tuple[float, float]:
    try:
        r, c = (float(v) for v in text.split(","))
    except ValueError:
        raise InputError(f"--point {text!r}: expected ROW,COL (pixels), e.g. 40,52") from None
    return r, c


def _cube_members(files: Sequence[str | os.PathLike]) -> list[Path]:
    """Every file that the viewed cubes consist of or bring along: each file, the files beside
    it of the same stem (ENVI ``c.hdr`` with ``c.img``, ``c.dat``, ``c.raw`` or ``c``; a TIFF's
    ``.vrt``), its ``_std`` companion's, and everything below a folder (a Zarr store)."""
    out: list[Path] = []
    for f in files:
        p = Path(f)
        out.append(p)
        if p.is_dir():
            continue
        stem = p.name.split(".")[0] if p.name.split(".")[0] else p.stem
        for pattern in (f"{glob.escape(stem)}.*", f"{glob.escape(stem)}_std.*"):
            out += p.parent.glob(pattern)
        out += [q for q in (p.parent / stem, p.parent / f"{stem}_std") if q.exists()]
    return out


def check_screenshot(path: str | os.PathLike, files: Sequence[str | os.PathLike],
                     overwrite: bool = False) -> None:  # fmt: skip
    """Refuse a ``--screenshot`` destination that would destroy data: any file the viewed cubes
    consist of (whatever its name or link; even with ``overwrite``), or an existing file that
    is not a screenshot this command wrote (its PNG ``Software`` tag) unless ``overwrite``.

    Raises:
        InputError: naming the file and why.
    """
    from hsi_torch.io.atomic import InputFiles, check_not_input, read_file_head

    check_not_input(path, InputFiles(_cube_members(files)))
    p = Path(path)
    if not os.path.lexists(p) or overwrite:
        return
    head = read_file_head(p, 1 << 16)
    ours = (head is not None and head.startswith(b"\x89PNG\r\n\x1a\n")
            and b"tEXtSoftware\x00" + SCREENSHOT_SOFTWARE.encode() in head)  # fmt: skip
    if not ours:
        raise InputError(f"--screenshot {p}: that file exists and is not a screenshot written "
                         "by hsi-torch view; nothing was written. Choose another name, or pass "
                         "--overwrite to replace it")  # fmt: skip


def run_view(args: argparse.Namespace) -> int:
    """Open ``args.files`` (``--screenshot PNG`` writes the window and exits)."""
    if args.screenshot is not None:  # never over a cube being viewed (before napari starts)
        check_screenshot(args.screenshot, args.files, bool(getattr(args, "overwrite", False)))
    try:
        from hsi_torch.viewer import plugin
    except ImportError as exc:
        raise InputError(f"'hsi-torch view' needs napari and a Qt binding ({exc}): {_HINT}") \
            from None
    points = [_point(p) for p in (args.point or [])]
    plugin.view(args.files, screenshot=args.screenshot, points=points, band_nm=args.band)
    if args.screenshot is not None:
        print(f"wrote {args.screenshot}")
    return 0
