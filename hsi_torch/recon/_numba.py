"""numba, the optional CPU accelerator of the solvers: availability, the opt-out switch, threads.

The compiled kernels (:mod:`hsi_torch.recon.nnls._compiled`,
:mod:`hsi_torch.recon.spatial._compiled`) import numba through this module only. Without numba,
or with the environment variable ``HSI_TORCH_NO_NUMBA`` set to anything but ``""``/``"0"``,
:data:`AVAILABLE` is False and the solvers run their torch kernels (same iterations, answers to
rounding).

numba's thread count is a per-thread setting (as torch's OpenMP one is): :func:`threads` sets it
for a block of kernels, :func:`set_threads` sets torch's and numba's for work started from the
calling thread (a Dask task's thread), :func:`thread_counts` reads both back.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import torch

__all__ = ["AVAILABLE", "DISABLE_ENV", "nb", "threads", "set_threads", "thread_counts"]

#: the environment variable that turns the compiled kernels off (any value but "" or "0")
DISABLE_ENV = "HSI_TORCH_NO_NUMBA"

nb: Any
try:  # optional accelerator
    if os.environ.get(DISABLE_ENV, "") not in ("", "0"):
        raise ImportError(f"disabled by {DISABLE_ENV}")
    import numba as nb

    AVAILABLE = True
except ImportError:  # pragma: no cover - exercised when numba is absent
    nb = None
    AVAILABLE = False


def _clamp(num: int) -> int:
    """``num`` within numba's thread pool: ``1 … NUMBA_NUM_THREADS``."""
    return max(1, min(int(num), int(nb.config.NUMBA_NUM_THREADS)))


@contextmanager
def threads(num: int) -> Iterator[None]:
    """numba's thread count for the kernels run in the block, restored afterwards (clamped to
    ``1 … NUMBA_NUM_THREADS``; a no-op without numba)."""
    if not AVAILABLE:
        yield
        return
    old = nb.get_num_threads()
    nb.set_num_threads(_clamp(num))
    try:
        yield
    finally:
        nb.set_num_threads(old)


def set_threads(num: int | None) -> None:
    """torch's and numba's thread counts for work started from this thread (both settings are
    per thread; ``None`` or 0: leave both)."""
    if not num:
        return
    # always: torch's OpenMP setting is per thread too, and a task may run in a new thread
    torch.set_num_threads(int(num))
    if AVAILABLE:
        nb.set_num_threads(_clamp(num))


def thread_counts() -> dict[str, int | None]:
    """torch's and numba's thread counts in this thread (``"numba"``: ``None`` without it)."""
    return {"torch": torch.get_num_threads(),
            "numba": nb.get_num_threads() if AVAILABLE else None}
