"""The end of a sequence run, shared by ``reconstruct --sequence``
(:mod:`hsi_torch.recon.batch.sequence_run`) and ``watch`` (:mod:`hsi_torch.recon.batch.watch`):
the animated preview of the store, the elapsed time, and an output folder that received nothing
removed again."""

from __future__ import annotations

import time
from pathlib import Path

from hsi_torch.io.sequence_store import write_animated_preview
from hsi_torch.recon.batch.driver import RunSummary
from hsi_torch.recon.batch.run import ReconstructRun

__all__ = ["finish_sequence_run"]


def finish_sequence_run(summary: RunSummary, run: ReconstructRun, store: Path,
                        preview: Path | None, t_start: float) -> RunSummary:  # fmt: skip
    """Write the store's animated preview to ``preview`` (``None``: none, e.g. an empty store)
    and list it with the store in ``summary.outputs``; set ``summary.elapsed_s`` (seconds since
    ``t_start``, a :func:`time.perf_counter` reading); let ``run`` remove an output folder that
    received nothing. Returns ``summary``."""
    if preview is not None:
        gif = write_animated_preview(store, preview)
        if gif is not None:
            summary.outputs[store] = [store, gif]
    summary.elapsed_s = time.perf_counter() - t_start
    run.discard_if_nothing_written(summary)
    return summary
