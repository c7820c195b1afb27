#!/usr/bin/env python
"""Benchmark: the full-size bilinear demosaic and saturation propagation against the reference.

``hsi_torch.bayer.demosaic_bilinear`` evaluates the normalised convolution colour by colour on
whole rows; the reference kept here, :func:`reference_bilinear` (and
:func:`reference_saturation`), is the earlier evaluation on whole masked planes (``x·m_c``
smoothed by shifted sums, divided by the smoothed masks) in bands of 256 rows, verbatim. Each
case prints the median wall time of both, their ratio, whether the outputs are equal
(``torch.equal``), and beside them:

* **fresh output**: ``torch.empty((N, 3, H, W)).fill_(1)``, allocating the result and writing it
  once: the floor of any demosaic that returns a new tensor (on Linux most of it is the kernel
  handing out and zeroing the pages);
* **OpenCV**: ``cv2.cvtColor(mosaic, cv2.COLOR_BayerRG2RGB)`` on a ``uint16`` copy, what a
  skilled user would run: it quantises the mosaic to 16-bit integers and treats the border
  differently, so its values are not compared, only its time (the machine's practical limit);
* **peak memory**: the growth of the resident set during one call, in a child process (its
  peak ``VmHWM``, reset just before the call through ``/proc/self/clear_refs``, minus its
  resident set then; Linux), our evaluation and the reference.

Mosaics: uniform random values, and a natural-ish scene (smooth shading, sharp-edged discs and
bars, 1 % noise, 12-bit range) mosaiced through the CFA.

Usage::

    python scripts/bench_demosaic.py                      # full size, 2896 x 2784
    python scripts/bench_demosaic.py --height 1024 --width 1024 --repeat 5 --threads 1
    python scripts/bench_demosaic.py --no-memory          # skip the child processes

Takes about a minute at full size on 2 cores (the reference is the slow part).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from functools import partial

import torch
import torch.nn.functional as F

from hsi_torch.bayer import (
    cfa_masks,
    demosaic_bilinear,
    demosaic_saturation,
    mosaic,
    validate_cfa_pattern,
)

PATTERN = "RGGB"

# --------------------------------------------------------------------------- the reference


def _smooth_w(t: torch.Tensor, side: float) -> torch.Tensor:
    p = F.pad(t, (1, 1))
    return p[..., 1:-1] + side * (p[..., :-2] + p[..., 2:])


def _smooth_h(t: torch.Tensor, side: float) -> torch.Tensor:
    p = F.pad(t, (0, 0, 1, 1))
    return p[..., 1:-1, :] + side * (p[..., :-2, :] + p[..., 2:, :])


def _num_den(x: torch.Tensor, pattern: str) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    p = validate_cfa_pattern(pattern)
    n, _, h, w = x.shape
    m = cfa_masks(p, h, w, device=x.device, dtype=x.dtype)
    rb = x * m[[0, 2]]
    num_rb = _smooth_h(_smooth_w(rb, 0.5), 0.5)
    g = x * m[1]
    gp = F.pad(g, (1, 1, 1, 1))
    num_g = g + 0.25 * (gp[..., :-2, 1:-1] + gp[..., 2:, 1:-1] + gp[..., 1:-1, :-2]
                        + gp[..., 1:-1, 2:])  # fmt: skip
    rows = torch.arange(h, device=x.device)
    cols = torch.arange(w, device=x.device)
    dens = []
    for ch in "RB":
        pos = p.index(ch)
        r = (rows % 2 == pos // 2).to(x.dtype)
        c = (cols % 2 == pos % 2).to(x.dtype)
        dens.append(_smooth_w(r, 0.5)[:, None] * _smooth_w(c, 0.5)[None, :])
    den_rb = torch.stack(dens)
    edge_r = (rows == 0).to(x.dtype) + (rows == h - 1).to(x.dtype)
    edge_c = (cols == 0).to(x.dtype) + (cols == w - 1).to(x.dtype)
    count = 4.0 - edge_r[:, None] - edge_c[None, :]
    den_g = m[1] + (1 - m[1]) * (count / 4.0)
    num = torch.stack([num_rb[:, 0], num_g[:, 0], num_rb[:, 1]], dim=1)
    return num, den_rb, den_g


def _in_bands(fn: Callable, x: torch.Tensor, out_dtype: torch.dtype, band: int) -> torch.Tensor:
    n, _, h, w = x.shape
    if h <= 2 * band:
        return fn(x)
    out = torch.empty((n, 3, h, w), dtype=out_dtype, device=x.device)
    for r0 in range(0, h, band):
        r1 = min(h, r0 + band)
        a, b = max(0, r0 - 2), min(h, r1 + 2)
        out[:, :, r0:r1] = fn(x[:, :, a:b])[:, :, r0 - a : r0 - a + (r1 - r0)]
    return out


def reference_bilinear(x: torch.Tensor, pattern: str, band: int = 256) -> torch.Tensor:
    """The masked-plane bilinear demosaic: ``(..., 1, H, W)`` float → ``(..., 3, H, W)``."""
    lead, (h, w) = x.shape[:-3], x.shape[-2:]

    def one(xb: torch.Tensor) -> torch.Tensor:
        num, den_rb, den_g = _num_den(xb, pattern)
        return num / torch.stack([den_rb[0], den_g, den_rb[1]])

    return _in_bands(one, x.reshape(-1, 1, h, w), x.dtype, band).reshape(*lead, 3, h, w)


def reference_saturation(saturated: torch.Tensor, pattern: str, band: int = 256) -> torch.Tensor:
    """The masked-plane saturation propagation: ``(..., 1, H, W)`` bool → ``(..., 3, H, W)``."""
    sat = saturated.bool()
    lead, (h, w) = sat.shape[:-3], sat.shape[-2:]

    def one(flat: torch.Tensor) -> torch.Tensor:
        hb = flat.shape[-2]
        m = cfa_masks(pattern, hb, w, device=sat.device, dtype=torch.float32).bool()
        rb = flat & m[[0, 2]]
        pw = F.pad(rb, (1, 1))
        rb = pw[..., 1:-1] | pw[..., :-2] | pw[..., 2:]
        ph = F.pad(rb, (0, 0, 1, 1))
        rb = ph[..., 1:-1, :] | ph[..., :-2, :] | ph[..., 2:, :]
        g = flat & m[1]
        gp = F.pad(g, (1, 1, 1, 1))
        g = g | gp[..., :-2, 1:-1] | gp[..., 2:, 1:-1] | gp[..., 1:-1, :-2] | gp[..., 1:-1, 2:]
        return torch.cat([rb[:, :1], g, rb[:, 1:]], dim=1)

    return _in_bands(one, sat.reshape(-1, 1, h, w), torch.bool, band).reshape(*lead, 3, h, w)


# --------------------------------------------------------------------------- mosaics


def natural_mosaic(n: int, h: int, w: int, dtype: torch.dtype, seed: int = 0) -> torch.Tensor:
    """``(n, 1, h, w)``: smooth shading, sharp discs and bars, 1 % noise, 0–4095, mosaiced."""
    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    imgs = []
    for _ in range(n):
        tint = torch.rand(3, 1, 1, generator=g) * 0.6 + 0.4
        rgb = tint * (0.3 + 0.5 * xx * (1 - 0.5 * yy))[None]
        for _ in range(12):
            cy, cx, r = torch.rand(3, generator=g).tolist()
            disc = (yy - cy) ** 2 + (xx - cx) ** 2 < (0.02 + 0.1 * r) ** 2
            rgb = torch.where(disc, torch.rand(3, 1, 1, generator=g), rgb)
        bars = (torch.sin(xx * 200) > 0) & (yy > 0.8)
        rgb = torch.where(bars, rgb * 0.2, rgb)
        rgb = rgb * (1 + 0.01 * torch.randn(rgb.shape, generator=g))
        imgs.append(rgb.clamp(0, 1) * 4095)
    return mosaic(torch.stack(imgs), PATTERN).to(dtype)


# --------------------------------------------------------------------------- timing


def _median_time(fn: Callable[[], object], repeat: int) -> float:
    """Median wall time of ``repeat`` calls after one untimed warm-up call."""
    fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _fresh_output(shape: tuple[int, ...], dtype: torch.dtype) -> torch.Tensor:
    """A new tensor of ``shape`` written once: the floor of returning a fresh result."""
    return torch.empty(shape, dtype=dtype).fill_(1)


def _opencv_time(x: torch.Tensor, repeat: int) -> float | None:
    try:
        import cv2
    except ImportError:
        return None
    cv2.setNumThreads(torch.get_num_threads())
    m16 = x.reshape(-1, *x.shape[-2:]).clamp(0, 65535).round().to(torch.int32).numpy()
    m16 = m16.astype("uint16")
    return _median_time(lambda: [cv2.cvtColor(m, cv2.COLOR_BayerRG2RGB) for m in m16], repeat)


def _child_peak(impl: str, kind: str, n: int, h: int, w: int, dtype: str) -> float:
    """Peak resident-set growth (MiB) of one call, measured in a fresh child process."""
    cmd = [sys.executable, __file__, "--child", impl, kind, str(n), str(h), str(w), dtype,
           "--threads", str(torch.get_num_threads())]  # fmt: skip
    res = subprocess.run(cmd, capture_output=True, text=True, check=True)
    return float(json.loads(res.stdout.strip().splitlines()[-1])["peak_mib"])


def _status_kib(key: str) -> int:
    """A ``kB`` field of ``/proc/self/status`` (Linux)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1])
    raise RuntimeError(f"/proc/self/status has no {key}")


def _run_child(impl: str, kind: str, n: int, h: int, w: int, dtype: str) -> None:
    torch.manual_seed(0)
    if kind == "bilinear":
        x = torch.rand(n, 1, h, w, dtype=getattr(torch, dtype))
        fn = demosaic_bilinear if impl == "ours" else reference_bilinear
    else:
        x = torch.rand(n, 1, h, w) > 0.999
        fn = demosaic_saturation if impl == "ours" else reference_saturation
    fn(x[..., :8, :8], PATTERN)  # warm-up: lazy initialisation is not the call's memory
    with open("/proc/self/clear_refs", "w") as f:  # Linux: resets the peak (VmHWM) to now
        f.write("5")
    rss_before = _status_kib("VmRSS")
    fn(x, PATTERN)
    peak = _status_kib("VmHWM")
    print(json.dumps({"peak_mib": (peak - rss_before) / 1024}))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--height", type=int, default=2896)
    ap.add_argument("--width", type=int, default=2784)
    ap.add_argument("--repeat", type=int, default=3, help="timed calls per case (median)")
    ap.add_argument("--threads", type=int, default=None, help="torch (and OpenCV) threads")
    ap.add_argument("--no-memory", action="store_true", help="skip the peak-memory children")
    ap.add_argument("--child", nargs=6, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.child:
        impl, kind, n, h, w, dtype = args.child
        _run_child(impl, kind, int(n), int(h), int(w), dtype)
        return 0
    h, w = args.height, args.width
    load = os.getloadavg()[0]
    print(f"mosaic {h} x {w}, {PATTERN}, torch {torch.__version__}, "
          f"{torch.get_num_threads()} thread(s), load average {load:.1f}")  # fmt: skip
    print("case | ours s | reference s | ratio | equal | fresh output s | OpenCV uint16 s")
    torch.manual_seed(0)
    cases = [("random", torch.float32, 1), ("random", torch.float64, 1),
             ("random", torch.float32, 3), ("natural", torch.float32, 1),
             ("natural", torch.float64, 1)]  # fmt: skip
    for scene, dtype, n in cases:
        x = (torch.rand(n, 1, h, w, dtype=dtype) * 4095 if scene == "random"
             else natural_mosaic(n, h, w, dtype))  # fmt: skip
        t_new = _median_time(partial(demosaic_bilinear, x, PATTERN), args.repeat)
        t_ref = _median_time(partial(reference_bilinear, x, PATTERN), args.repeat)
        same = torch.equal(demosaic_bilinear(x, PATTERN), reference_bilinear(x, PATTERN))
        floor = _median_time(partial(_fresh_output, (n, 3, h, w), dtype), args.repeat)
        cv = _opencv_time(x, args.repeat)
        cv_txt = f"{cv:.4f}" if cv is not None else "n/a (no cv2)"
        name = f"{scene} {str(dtype).removeprefix('torch.')} N={n}"
        print(f"{name} | {t_new:.4f} | {t_ref:.4f} | {t_ref / t_new:.1f}x | {same} | "
              f"{floor:.4f} | {cv_txt}")  # fmt: skip
    for label, frac in (("saturation, none", 0.0), ("saturation, 0.1 %", 0.001)):
        sat = torch.rand(1, 1, h, w) < frac
        t_new = _median_time(partial(demosaic_saturation, sat, PATTERN), args.repeat)
        t_ref = _median_time(partial(reference_saturation, sat, PATTERN), args.repeat)
        same = torch.equal(demosaic_saturation(sat, PATTERN), reference_saturation(sat, PATTERN))
        print(f"{label} | {t_new:.4f} | {t_ref:.4f} | {t_ref / t_new:.1f}x | {same} | | ")
    if not args.no_memory:
        print("peak resident-set growth of one call (MiB): case | ours | reference | output size")
        for kind, dtype, n in (("bilinear", "float32", 1), ("bilinear", "float64", 1),
                               ("bilinear", "float32", 3), ("saturation", "bool", 1)):  # fmt: skip
            size = n * 3 * h * w * (torch.empty(0, dtype=getattr(torch, dtype)).element_size())
            ours = _child_peak("ours", kind, n, h, w, dtype)
            ref = _child_peak("reference", kind, n, h, w, dtype)
            print(f"{kind} {dtype} N={n} | {ours:.0f} | {ref:.0f} | {size / 2**20:.0f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
