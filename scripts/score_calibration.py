"""Score a calibration bundle against the ground truth of a simulated capture set.

    python scripts/score_calibration.py BUNDLE.npz CAPTURES_DIR [--json OUT.json]
    python scripts/score_calibration.py --calibrate CAPTURES_DIR [--set key=value ...]

With ``--calibrate`` the bundle is made first (the shipped ``calibrate.yaml`` + overrides, nothing
written). Prints the calibration targets (B < 2 % RMS, φ correlation > 0.99, g < 2 %,
homography < 0.3 px) with the definitions of
:func:`hsi_torch.experiments.calibration_scores.score_against_truth`; exit status 1 when a target
is missed.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from hsi_torch.experiments.calibration_scores import (
    format_scores,
    score_against_truth,
    targets_met,
)
from hsi_torch.resources import shipped_config


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("bundle", nargs="?", type=Path, help="calibration bundle (.npz)")
    ap.add_argument("captures", nargs="?", type=Path, help="simulated capture set (with truth)")
    ap.add_argument("--calibrate", type=Path, metavar="CAPTURES", help="calibrate this set first")
    ap.add_argument("--config", type=Path, default=None,
                    help="calibration config (default: the shipped calibrate.yaml)")
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    ap.add_argument("--json", type=Path, help="also write the scores as JSON")
    a = ap.parse_args(argv)
    if a.calibrate is not None:
        from hsi_torch.calibrate.config import CalibrateConfig
        from hsi_torch.calibrate.pipeline import calibrate_capture_set
        from hsi_torch.config import load_config

        cfg = load_config(a.config or shipped_config("calibrate"), CalibrateConfig, a.overrides)
        t0 = time.perf_counter()
        bundle, report = calibrate_capture_set(a.calibrate, cfg, progress=False)
        print(report)
        print(f"calibration took {time.perf_counter() - t0:.1f} s")
        captures = a.calibrate
    else:
        if a.bundle is None or a.captures is None:
            ap.error("give BUNDLE and CAPTURES, or --calibrate CAPTURES")
        bundle, captures = a.bundle, a.captures
    scores = score_against_truth(bundle, captures)
    print(format_scores(scores))
    if a.json:
        a.json.write_text(json.dumps(scores, indent=2))
    ok = all(targets_met(scores).values())
    print("all targets met" if ok else "some targets MISSED")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
