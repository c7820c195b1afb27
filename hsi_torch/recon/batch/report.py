"""The findings report of a reconstruction run: every run that processed or skipped an input
writes ``OUT/runs/<run>.findings.json`` beside its configuration file ``OUT/runs/<run>.yaml``
(its keys, an example and when it is written: ``docs/reconstruct.md``, *Findings*).
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from hsi_torch.findings import findings_summary
from hsi_torch.io.atomic import atomic_write_new, json_default
from hsi_torch.recon.batch.driver import RunSummary

__all__ = ["REPORT_VERSION", "REPORT_SUFFIX", "findings_report", "write_findings_report"]

#: Layout version of the report (key ``hsi_torch_findings_report``).
REPORT_VERSION = 1
#: The report's name is the run configuration file's stem plus this.
REPORT_SUFFIX = ".findings.json"


def findings_report(
    summary: RunSummary,
    out_dir: str | os.PathLike,
    run_config: str | os.PathLike | None = None,
    skipped_outputs: Callable[[Path], Sequence[str | os.PathLike]] | None = None,
) -> dict[str, Any]:
    """The report of a run (the layout of ``docs/reconstruct.md``, *Findings*) as a JSON-able
    dict.

    Args:
        summary: the run's summary.
        out_dir: its output folder.
        run_config: its configuration file (recorded relative to ``out_dir``).
        skipped_outputs: ``input -> its outputs`` for skipped inputs (default: none listed).
    """
    out = Path(os.path.abspath(out_dir))
    failures = {f.input: f.error for f in summary.failed}
    rows = []
    for status, inputs in (("processed", summary.processed), ("skipped", summary.skipped),
                           ("failed", [f.input for f in summary.failed])):  # fmt: skip
        for inp in inputs:
            if status == "processed":
                outputs = summary.outputs.get(inp, [])
            elif status == "skipped" and skipped_outputs is not None:
                outputs = list(skipped_outputs(inp))
            else:
                outputs = []
            rows.append({
                "input": os.path.abspath(inp),
                "status": status,
                "outputs": [os.path.abspath(q) for q in outputs],
                "findings": [f.to_dict() for f in summary.findings.get(inp, [])],
                "error": failures.get(inp),
            })  # fmt: skip
    every = [f for fs in summary.findings.values() for f in fs]
    cfg = None
    if run_config is not None:
        rc = Path(os.path.abspath(run_config))
        cfg = rc.relative_to(out).as_posix() if rc.is_relative_to(out) else str(rc)
    return {
        "hsi_torch_findings_report": REPORT_VERSION,
        "run_config": cfg,
        "out": str(out),
        "store": str(summary.store) if summary.store is not None else None,
        "elapsed_s": round(summary.elapsed_s, 3),
        "counts": {
            "processed": len(summary.processed),
            "skipped": len(summary.skipped),
            "failed": len(summary.failed),
        },  # fmt: skip
        "findings_summary": findings_summary(every),
        "provenance": summary.provenance,
        "inputs": rows,
    }


def write_findings_report(
    summary: RunSummary,
    out_dir: str | os.PathLike,
    run_config: str | os.PathLike,
    skipped_outputs: Callable[[Path], Sequence[str | os.PathLike]] | None = None,
) -> Path:
    """Write :func:`findings_report` as ``<run_config's folder>/<its stem>.findings.json``, a
    new file (never an earlier run's: ``-2``, ``-3``, ... if the name is taken), atomically;
    sets ``summary.findings_report`` and returns the path."""
    rc = Path(run_config)
    doc = findings_report(summary, out_dir, rc, skipped_outputs)
    data = json.dumps(doc, indent=2, default=json_default).encode("utf-8") + b"\n"
    names = (f"{rc.stem}{REPORT_SUFFIX}" if i == 1 else f"{rc.stem}-{i}{REPORT_SUFFIX}"
             for i in range(1, 10_000))  # fmt: skip
    path = atomic_write_new(rc.parent, names, data)
    summary.findings_report = path
    return path
