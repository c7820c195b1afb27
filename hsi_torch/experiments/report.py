"""Report writers shared by the experiments: CSV, Markdown tables, figures, progress bars.

Every writer is atomic (a temporary file in the same folder, then ``os.replace``), so an
interrupted run never leaves a half-written table or PNG behind.
"""

from __future__ import annotations

import csv
import io
import math
import os
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

import torch

from hsi_torch.console import progress_bar, progress_enabled
from hsi_torch.devices import torch_dtype
from hsi_torch.io.atomic import atomic_write_bytes, atomic_write_text

__all__ = [
    "format_value",
    "write_csv",
    "markdown_table",
    "write_markdown",
    "new_figure",
    "save_figure",
    "progress",
    "start_run",
]

T = TypeVar("T")


def format_value(value: Any, fmt: str | Callable[[Any], str] | None = None) -> str:
    """Readable text for a table cell: floats with 4 significant digits (or ``fmt``), ``None``
    → empty, ``inf``/``nan`` as such."""
    if callable(fmt):
        return fmt(value)
    if value is None:
        return ""
    if isinstance(value, bool):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value) or math.isinf(value):
            return str(value)
        return format(value, fmt) if fmt else f"{value:.4g}"
    if fmt and isinstance(value, int):
        return format(value, fmt)
    return str(value)


def write_csv(
    path: str | os.PathLike,
    rows: Sequence[Mapping[str, Any]],
    fieldnames: Sequence[str] | None = None,
) -> Path:
    """Write ``rows`` (dicts) as CSV, atomically. Columns: ``fieldnames`` or the union of the
    rows' keys in first-seen order. Floats are written with full precision (``repr``)."""
    if fieldnames is None:
        seen: dict[str, None] = {}
        for r in rows:
            for k in r:
                seen.setdefault(k, None)
        fieldnames = list(seen)
    buf = io.StringIO()
    wr = csv.DictWriter(
        buf, fieldnames=list(fieldnames), extrasaction="ignore", lineterminator="\n"
    )
    wr.writeheader()
    for r in rows:
        wr.writerow({k: ("" if r.get(k) is None else r.get(k)) for k in fieldnames})
    return atomic_write_text(path, buf.getvalue())


def markdown_table(
    rows: Sequence[Mapping[str, Any]],
    columns: Sequence[str] | Mapping[str, str],
    formats: Mapping[str, str | Callable[[Any], str]] | None = None,
    bold: Callable[[Mapping[str, Any]], bool] | None = None,
) -> str:
    """A GitHub-flavoured Markdown table.

    Args:
        columns: keys to show, or ``{key: header}``.
        formats: per-key format spec (``".2f"``) or callable.
        bold: rows for which this returns True are set in bold.
    """
    cols = dict(columns) if isinstance(columns, Mapping) else {c: c for c in columns}
    formats = formats or {}
    lines = ["| " + " | ".join(cols.values()) + " |", "| " + " | ".join("---" for _ in cols) + " |"]
    for r in rows:
        cells = [format_value(r.get(k), formats.get(k)).replace("|", "\\|") for k in cols]
        if bold is not None and bold(r):
            cells = [f"**{c}**" if c else c for c in cells]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def write_markdown(path: str | os.PathLike, text: str) -> Path:
    """Write Markdown text atomically (a trailing newline is added when missing)."""
    return atomic_write_text(path, text if text.endswith("\n") else text + "\n")


def new_figure(*args: Any, **kwargs: Any) -> tuple[Any, Any]:
    """``plt.subplots`` on the non-interactive Agg backend (safe on headless machines)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt.subplots(*args, **kwargs)


def save_figure(fig: Any, path: str | os.PathLike, dpi: int = 110, tight: bool = True) -> Path:
    """Save a Matplotlib figure as PNG atomically and close it (``tight``: crop to its contents)."""
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, **({"bbox_inches": "tight"} if tight else {}))
    plt.close(fig)
    return atomic_write_bytes(path, buf.getvalue())


def progress(
    iterable: Iterable[T], *, desc: str = "", total: int | None = None, enable: bool = True
) -> Iterable[T]:
    """A tqdm progress bar on stderr (:func:`hsi_torch.console.progress_bar`: plain iteration
    when ``enable`` is False, ``--no-progress``/``--quiet`` is given or stderr is no terminal)."""
    if not progress_enabled(enable):
        return iterable
    return progress_bar(iterable, desc=desc, total=total)


def start_run(out: str | os.PathLike, cfg: Any, device: str | None
              ) -> tuple[float, Path, torch.device, torch.dtype]:
    """The start of an experiment's run: ``(t0, out, device, dtype)`` — the start time
    (``time.perf_counter``), ``out`` as a created folder, the torch device (``device``, else
    ``cfg.device``, else the CPU) and the torch dtype of ``cfg.dtype``."""
    t0 = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    return t0, out, torch.device(device or cfg.device or "cpu"), torch_dtype(cfg.dtype)
