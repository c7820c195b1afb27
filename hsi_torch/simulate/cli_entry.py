"""``hsi-torch simulate [--config C] --out DIR [--set key=value ...] [--device D]`` (without
``--config``: the shipped ``simulate.yaml``, the README's default prototype)."""

from __future__ import annotations

import argparse
import sys


def run_simulate(args: argparse.Namespace) -> int:
    """Entry point called by :mod:`hsi_torch.cli`: render a capture set with ground truth."""
    from hsi_torch.cli_common import load_args_config
    from hsi_torch.console import info
    from hsi_torch.simulate.capture_sets import simulate_capture_set
    from hsi_torch.simulate.config import SimulateConfig

    cfg = load_args_config(args, SimulateConfig, default="simulate")
    device = getattr(args, "device", None)
    summary = simulate_capture_set(
        cfg, args.out, device=device, log=lambda m: info(m, file=sys.stderr))
    info(summary.report())
    return 0
