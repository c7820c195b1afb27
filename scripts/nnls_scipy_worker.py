"""The SciPy baseline's per-chunk work (``scripts/nnls_baselines.py``), in a module of its own so
that the ``spawn`` pool's workers import only NumPy and SciPy, as a stand-alone SciPy script's
workers would (not torch or numba: their start-up time and memory are not the baseline's)."""

from __future__ import annotations

import os

import numpy as np
from scipy.optimize import nnls

__all__ = ["solve_chunk", "worker_info"]


def solve_chunk(task: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]) -> np.ndarray:
    """Solve one chunk of stacked problems with ``scipy.optimize.nnls``.

    ``task = (A (n, O, M), mask (n, O) bool, y (n, O), sD (K, M))`` → ``x (n, M)``: per pixel
    ``argmin_{x ≥ 0} ‖[A_p[mask_p]; sD] x − [y_p[mask_p]; 0]‖``.
    """
    A, mask, y, sD = task
    zeros = np.zeros(sD.shape[0])
    x = np.empty((A.shape[0], A.shape[2]))
    for j in range(A.shape[0]):
        m = mask[j]
        x[j], _ = nnls(np.vstack([A[j][m], sD]), np.concatenate([y[j][m], zeros]))
    return x


def worker_info(_: int) -> tuple[int, str]:
    """``(pid, SciPy version)`` of the process running it."""
    import scipy

    return os.getpid(), scipy.__version__
