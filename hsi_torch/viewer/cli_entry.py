"""``hsi-torch view FILE…``: open cube files in napari with the spectrum widget docked."""

from __future__ import annotations

import argparse

from hsi_torch.errors import InputError

__all__ = ["run_view"]

_HINT = "pip install 'hsi-torch[viewer]'"


def _point(text: str) -> tuple[float, float]:
    try:
        r, c = (float(v) for v in text.split(","))
    except ValueError:
        raise InputError(f"--point {text!r}: expected ROW,COL (pixels), e.g. 40,52") from None
    return r, c


def run_view(args: argparse.Namespace) -> int:
    """Open ``args.files`` (``--screenshot PNG`` writes the window and exits)."""
    if args.screenshot is not None:  # never over a cube being viewed (before napari starts)
        from hsi_torch.io.atomic import check_not_input

        check_not_input(args.screenshot, args.files)
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
