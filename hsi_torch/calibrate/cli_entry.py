"""``hsi-torch calibrate [--config C] --captures DIR --out BUNDLE.npz [--set k=v] [--device D]``.

Writes, only after the whole calibration succeeded (each file atomically):

- ``BUNDLE.npz`` — the :class:`~hsi_torch.calibrate.CalibrationBundle`;
- ``BUNDLE.report.json`` — the per-view registration report, valid-region statistics, timings;
- ``BUNDLE.resolved_config.yaml`` — the configuration (rerun with ``--config``); named after the
  bundle so that several bundles can share a folder without overwriting each other's record.

On any error nothing is written (an existing bundle is left untouched).
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

__all__ = ["run_calibrate", "output_paths"]

_PACKAGE_DIR = str(Path(__file__).resolve().parents[1])


def output_paths(out: str | Path) -> tuple[Path, Path, Path]:
    """``(bundle, report_json, resolved_config)`` for ``--out`` (``.npz`` added if missing)."""
    p = Path(out)
    if p.suffix.lower() != ".npz":
        p = p.with_name(p.name + ".npz")
    return p, p.with_name(p.stem + ".report.json"), p.with_name(p.stem + ".resolved_config.yaml")


def run_calibrate(args: argparse.Namespace) -> int:
    """Entry point called by :mod:`hsi_torch.cli`: calibrate a capture folder into a bundle."""
    from hsi_torch.calibrate.config import CalibrateConfig
    from hsi_torch.calibrate.pipeline import calibrate_capture_set
    from hsi_torch.cli import load_args_config
    from hsi_torch.config import write_resolved_config
    from hsi_torch.io.atomic import atomic_write_json

    cfg = load_args_config(args, CalibrateConfig)
    device = getattr(args, "device", None)
    if Path(args.out).is_dir():  # checked before '.npz' is appended (DIR would become DIR.npz)
        raise ValueError(
            f"--out {args.out} is a folder; give the bundle's file name, e.g. "
            f"{Path(args.out) / 'calib.npz'}"
        )
    bundle_path, report_path, config_path = output_paths(args.out)
    if bundle_path.is_dir():
        raise ValueError(f"--out {bundle_path} is a folder; give the bundle's file name")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("default")
        bundle, report = calibrate_capture_set(args.captures, cfg, device=device)
    for w in caught:  # ours as one plain line each (e.g. a saturated white shot dropped)
        if str(Path(w.filename).resolve()).startswith(_PACKAGE_DIR):
            print(f"hsi-torch: warning: {w.message}", file=sys.stderr)
        else:
            warnings.showwarning(w.message, w.category, w.filename, w.lineno)
    bundle_path.parent.mkdir(parents=True, exist_ok=True)
    bundle.save(bundle_path)
    atomic_write_json(report_path, report.to_dict())
    write_resolved_config(cfg, config_path.parent, name=config_path.name)
    print(report)
    print(bundle.summary())
    print(f"wrote {bundle_path} (+ {report_path.name}, {config_path.name})")
    return 0
