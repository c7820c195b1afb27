#!/usr/bin/env python
"""The small-prototype mismatch table, with its noise floor: a thin wrapper of
``hsi-torch experiment mismatch`` (:mod:`hsi_torch.experiments.mismatch`).

Runs the experiment (each documented effect alone and all together, calibrated vs oracle, the
remedies) on the shipped small prototype into ``OUT``, and with ``--noise-seeds N`` the ideal
device again with N other noise seeds (``OUT/seed<k>``, ideal row only): the spread of their
ideal rows is the noise floor below which a "lost" is not significant.

Usage::

    OMP_NUM_THREADS=1 python scripts/mismatch_small.py --out /tmp/mismatch
    python scripts/mismatch_small.py --out /tmp/mismatch --effects drift distortion
    python scripts/mismatch_small.py --out /tmp/mismatch_nf --noise-free --noise-seeds 3

Rows are cached under ``OUT/rows`` (a rerun reuses them).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from hsi_torch.experiments.mismatch import MismatchConfig, run_mismatch
from hsi_torch.io.paths import claim_out_dir
from hsi_torch.simulate.mismatch import DOCUMENTED_EFFECTS


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True,
                    help="output folder: new, empty or this script's own")
    ap.add_argument("--effects", nargs="*", default=None,
                    help=f"subset of {sorted(DOCUMENTED_EFFECTS)} and 'all' (default: every one)")
    ap.add_argument("--noise-seeds", type=int, default=0,
                    help="also render the ideal device with this many other noise seeds")
    ap.add_argument("--noise-free", action="store_true",
                    help="no shot/read noise, no quantisation")
    ap.add_argument("--no-remedies", action="store_true", help="skip the remedy column")
    args = ap.parse_args(argv)
    claim_out_dir(args.out, ".hsi_torch_mismatch_small", "run of mismatch_small.py",
                  "it writes the mismatch experiment's tables, figures and rows/ (and seed<k>/)",
                  script="mismatch_small.py", earlier_names=("mismatch.json",))  # fmt: skip
    kw = {"noise_free": args.noise_free, "remedies": not args.no_remedies}
    if args.effects is not None:
        kw["effects"] = list(args.effects)
    run_mismatch(MismatchConfig(**kw), args.out)
    for k in range(1, args.noise_seeds + 1):
        d = run_mismatch(MismatchConfig(effects=[], remedies=False, noise_free=args.noise_free,
                                        simulate_set=[f"render.seed={1000 * k}"]),
                         args.out / f"seed{k}")
        c = d["ideal"]["calibrated"]["colorchecker"]
        o = d["ideal"]["oracle"]["colorchecker"]
        print(f"ideal, noise seed {1000 * k}: calibrated {c['means_db']:.2f} / "
              f"{c['pixel_db']:.2f} dB, oracle {o['means_db']:.2f} / {o['pixel_db']:.2f} dB "
              "(means / per pixel)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
