"""Time the sequence store (hsi_torch.io.sequence_store) at the full frame size: appending a
frame, opening the store in xarray, decoding one frame, the animated preview.

The cubes are synthetic (smooth spectra varying over the frame plus 0.1 % noise, the valid mask
of an irregular region): the store's cost does not depend on how they were made, only on their
size and how well they compress. Prints one line per measurement.

    python scripts/bench_sequence_store.py --frames 4 --size 1536 1640
"""

from __future__ import annotations

import argparse
import resource
import tempfile
import time
from pathlib import Path

import numpy as np

from hsi_torch.io.sequence_store import (
    SequenceStore,
    iter_store_frames,
    open_sequence_store,
    write_animated_preview,
)


def _cube(k: int, m: int, h: int, w: int, rng: np.random.Generator) -> np.ndarray:
    lam = np.linspace(0, 1, m, dtype=np.float32)[:, None, None]
    yy = np.linspace(0, 1, h, dtype=np.float32)[None, :, None]
    xx = np.linspace(0, 1, w, dtype=np.float32)[None, None, :]
    c = 0.2 + 0.6 * ((xx + 0.05 * k) % 1.0)  # a scene panning by 5 % a frame
    s = 0.1 + 0.8 * np.exp(-0.5 * ((lam - c) / (0.2 + 0.1 * yy)) ** 2)
    return (s + 0.001 * rng.standard_normal((m, h, w), dtype=np.float32)).astype(np.float32)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=4)
    ap.add_argument("--size", type=int, nargs=2, default=(1536, 1640), metavar=("H", "W"))
    ap.add_argument("--bands", type=int, default=25)
    a = ap.parse_args()
    h, w = a.size
    m = a.bands
    rng = np.random.default_rng(0)
    wl = np.linspace(430, 670, m)
    yy, xx = np.mgrid[:h, :w]
    valid = (yy - h / 2) ** 2 / (0.45 * h) ** 2 + (xx - w / 2) ** 2 / (0.45 * w) ** 2 < 1
    raw_mib = m * h * w * 4 / 2**20
    with tempfile.TemporaryDirectory() as d:
        store = Path(d) / "sequence.zarr"
        times = []
        with SequenceStore.open(store, wl, (h, w)) as st:
            for k in range(a.frames):
                cube = _cube(k, m, h, w, rng)
                t0 = time.perf_counter()
                st.append(cube, valid, time_s=0.04 * k, source=f"frame{k}")
                times.append(time.perf_counter() - t0)
        on_disk = sum(p.stat().st_size for p in (store / "cube").iterdir()) / 2**20
        print(f"frame {m}x{h}x{w} float32 = {raw_mib:.0f} MiB; append {np.median(times):.2f} s "
              f"a frame (median of {a.frames}); cube on disk {on_disk / a.frames:.0f} MiB a "
              "frame (zstd 1)")  # fmt: skip
        t0 = time.perf_counter()
        ds = open_sequence_store(store)
        t_open = time.perf_counter() - t0
        t0 = time.perf_counter()
        one = ds.cube.isel(time=a.frames - 1).values
        t_one = time.perf_counter() - t0
        print(f"xarray open {t_open:.2f} s; one frame decoded {t_one:.2f} s ({one.shape})")
        t0 = time.perf_counter()
        for _ in iter_store_frames(store):
            pass
        print(f"iter_store_frames: {(time.perf_counter() - t0) / a.frames:.2f} s a frame")
        t0 = time.perf_counter()
        write_animated_preview(store, Path(d) / "p.gif")
        print(f"animated preview: {time.perf_counter() - t0:.2f} s for {a.frames} frames")
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    print(f"peak RSS {rss:.2f} GiB")


if __name__ == "__main__":
    main()
