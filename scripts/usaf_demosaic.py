#!/usr/bin/env python
"""USAF 1951 resolution with another demosaic of the HSI captures (a measurement, not a
library option).

``hsi-torch experiment usaf`` demosaics every Bayer capture bilinearly (the library's
``demosaic: bilinear``). This script runs the same experiment with the captures demosaiced by

- ``edge_aware``: OpenCV's edge-aware demosaic (``cv2.COLOR_Bayer..2RGB_EA``). Green at a red or
  blue site is the mean of the two neighbours along the direction (horizontal or vertical) of the
  smaller green difference; red and blue are interpolated bilinearly, as before. OpenCV takes
  8- or 16-bit integers only: each mosaic is mapped onto 0…65535 (offset and scale, rounded;
  for a 14-bit sensor ≈ 0.06 DN steps) and mapped back.
- ``vng``: OpenCV's variable number of gradients (``_VNG``), which accepts 8-bit input only: the
  mosaic is quantised to 256 levels of its range (≈ 64 DN steps at 14 bits) — shown for
  completeness.
- ``mhc``: the gradient-corrected linear demosaic of Malvar, He and Cutler (2004; the one
  MATLAB's ``demosaic`` uses): bilinear plus a fraction of the same pixel's Laplacian in the
  sampled colour (5 × 5 kernels), i.e. red and blue borrow the high frequencies of the other
  planes (it assumes the colour planes share their edges). Linear, in torch.

and, with ``--reference``, the RGB reference too (the yardstick; by default it stays bilinear).
Everything else — config keys, outputs — is the experiment's; give ``--set capture_set=DIR`` to
reconstruct an existing capture set instead of simulating one. ``--experiment spatial`` runs the
spatial experiment instead (ColorChecker, CAVE, USAF: scenes with coloured edges), e.g. on its
own capture set with ``--set captures=DIR``; ``bilinear`` runs either unchanged.

Usage::

    python scripts/usaf_demosaic.py edge_aware --out out/usaf_ea \\
        --set capture_set=out/usaf/capture_set
    python scripts/usaf_demosaic.py mhc --reference --out out/usaf_mhc --set capture_set=...
    python scripts/usaf_demosaic.py mhc --experiment spatial --out out/spatial_mhc \
        --set captures=out/spatial/captures "--set=lams=[1.0]"
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from hsi_torch.bayer import cfa_masks, validate_cfa_pattern

#: OpenCV's legacy Bayer code names by our CFA pattern (OpenCV names the second row's colours)
_CV_CODE = {"RGGB": "BayerBG", "BGGR": "BayerRG", "GRBG": "BayerGB", "GBRG": "BayerGR"}

# Malvar–He–Cutler kernels (× 1/8): green at red/blue; the other colour at green in a row (or
# column) of that colour; the other colour at the opposite colour
_MHC = {
    "g": [[0, 0, -1, 0, 0], [0, 0, 2, 0, 0], [-1, 2, 4, 2, -1], [0, 0, 2, 0, 0],
          [0, 0, -1, 0, 0]],
    "row": [[0, 0, .5, 0, 0], [0, -1, 0, -1, 0], [-1, 4, 5, 4, -1], [0, -1, 0, -1, 0],
            [0, 0, .5, 0, 0]],
    "col": [[0, 0, -1, 0, 0], [0, -1, 4, -1, 0], [.5, 0, 5, 0, .5], [0, -1, 4, -1, 0],
            [0, 0, -1, 0, 0]],
    "diag": [[0, 0, -1.5, 0, 0], [0, 2, 0, 2, 0], [-1.5, 0, 6, 0, -1.5], [0, 2, 0, 2, 0],
             [0, 0, -1.5, 0, 0]],
}


def _opencv(x: torch.Tensor, pattern: str, suffix: str, bits: int) -> torch.Tensor:
    """OpenCV demosaic of ``(..., 1, H, W)`` float mosaics on an integer copy spanning the
    ``bits`` range (offset and scale per image, undone after)."""
    import cv2

    p = validate_cfa_pattern(pattern)
    lead, (h, w) = x.shape[:-3], x.shape[-2:]
    flat = x.reshape(-1, h, w).detach().cpu().double().numpy()
    top = (1 << bits) - 1
    out = np.empty((flat.shape[0], 3, h, w))
    code = getattr(cv2, f"COLOR_{_CV_CODE[p]}2RGB{suffix}")
    for i, im in enumerate(flat):
        lo = float(im.min())
        s = top / max(float(im.max()) - lo, 1e-12)
        q = np.clip(np.rint((im - lo) * s), 0, top).astype(np.uint16 if bits == 16 else np.uint8)
        out[i] = cv2.cvtColor(q, code).astype(np.float64).transpose(2, 0, 1) / s + lo
    return torch.from_numpy(out).to(x).reshape(*lead, 3, h, w)


def demosaic_edge_aware(x: torch.Tensor, pattern: str) -> torch.Tensor:
    """OpenCV edge-aware demosaic ``(..., 1, H, W)`` → ``(..., 3, H, W)`` (16-bit copy)."""
    return _opencv(x, pattern, "_EA", 16)


def demosaic_vng(x: torch.Tensor, pattern: str) -> torch.Tensor:
    """OpenCV VNG demosaic ``(..., 1, H, W)`` → ``(..., 3, H, W)`` (8-bit copy: lossy)."""
    return _opencv(x, pattern, "_VNG", 8)


def demosaic_mhc(x: torch.Tensor, pattern: str) -> torch.Tensor:
    """Malvar–He–Cutler gradient-corrected linear demosaic ``(..., 1, H, W)`` →
    ``(..., 3, H, W)`` (reflect padding, which keeps the CFA phase; measured samples kept)."""
    p = validate_cfa_pattern(pattern)
    lead, (h, w) = x.shape[:-3], x.shape[-2:]
    m = x.reshape(-1, 1, h, w)
    k = torch.tensor([_MHC[n] for n in ("g", "row", "col", "diag")], dtype=m.dtype,
                     device=m.device)[:, None] / 8
    c_g, c_row, c_col, c_diag = F.conv2d(F.pad(m, (2, 2, 2, 2), mode="reflect"), k).unbind(1)
    mk = cfa_masks(p, h, w, device=m.device, dtype=m.dtype).bool()
    r_rows = (torch.arange(h, device=m.device)[:, None] % 2 == p.index("R") // 2).expand(h, w)
    g_r, g_b = mk[1] & r_rows, mk[1] & ~r_rows  # green in a red row / in a blue row
    v = m[:, 0]
    r = torch.where(mk[0], v, torch.where(g_r, c_row, torch.where(g_b, c_col, c_diag)))
    b = torch.where(mk[2], v, torch.where(g_b, c_row, torch.where(g_r, c_col, c_diag)))
    g = torch.where(mk[1], v, c_g)
    return torch.stack([r, g, b], 1).reshape(*lead, 3, h, w)


METHODS = {"edge_aware": demosaic_edge_aware, "vng": demosaic_vng, "mhc": demosaic_mhc}


def install(method: str, reference: bool = False) -> None:
    """Make the capture reader (``read_any``'s bilinear demosaic) use ``method``; with
    ``reference`` also the sensor model's demosaic (the RGB reference)."""
    import hsi_torch.io.captures as captures
    from hsi_torch.bayer import demosaic as library_demosaic
    from hsi_torch.optics.sensor import SensorModel

    fn = METHODS[method]

    def reader_demosaic(x: torch.Tensor, pattern: str, how: str = "bilinear") -> torch.Tensor:
        return fn(x, pattern) if how == "bilinear" else library_demosaic(x, pattern, how)

    captures._demosaic = reader_demosaic
    if reference:
        SensorModel.demosaic = lambda self, raw: fn(raw, self.cfa_pattern)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("method", choices=["bilinear", *sorted(METHODS)],
                    help="bilinear: the library's own (a baseline run the same way)")
    ap.add_argument("--out", required=True, help="output folder: new, empty or this script's own")
    ap.add_argument("--experiment", default="usaf",
                    help="which experiment to run (default usaf; e.g. spatial, whose scenes "
                         "have coloured edges)")
    ap.add_argument("--reference", action="store_true",
                    help="demosaic the RGB reference with the same method")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="experiment config override (repeatable), e.g. capture_set=DIR")
    a = ap.parse_args(argv)
    from hsi_torch.io.paths import claim_out_dir

    claim_out_dir(a.out, ".hsi_torch_usaf_demosaic", "run of usaf_demosaic.py",
                  f"it writes the {a.experiment} experiment's summary.json, tables and figures",
                  script="usaf_demosaic.py")  # fmt: skip
    from hsi_torch.config import load_config
    from hsi_torch.experiments.cli_entry import resolve_experiment
    from hsi_torch.io.atomic import atomic_write_json
    from hsi_torch.resources import shipped_config

    if a.method != "bilinear":
        install(a.method, a.reference)
    schema, run = resolve_experiment(a.experiment)
    try:
        base = shipped_config(a.experiment)
    except FileNotFoundError:
        base = None
    cfg = load_config(base, schema, a.set)
    s = run(cfg, Path(a.out))
    # say in the experiment's summary.json which demosaic made it
    path = Path(a.out) / "summary.json"
    written = json.loads(path.read_text()) if path.is_file() else {}
    written["demosaic"] = {"captures": a.method,
                           "rgb_reference": a.method if a.reference else "bilinear"}
    atomic_write_json(path, written)
    if a.experiment == "usaf":
        st = s["stats"]
        print(json.dumps({"method": a.method, "reference": a.reference,
                          "hsi_median_lp_mm": st["hsi_median_lp_mm"],
                          "rgb_gray_lp_mm": st["rgb_gray_lp_mm"],
                          "bands_within_two_elements": st["bands_within_two_elements"],
                          "psnr_db": s["metrics"]["psnr_db"], "timings_s": s["timings_s"]}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
