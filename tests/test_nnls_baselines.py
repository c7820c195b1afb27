"""The benchmark's compiled Lawson–Hanson baseline (``scripts/nnls_baselines.py``) solves the
stacked problems exactly: it agrees with ``scipy.optimize.nnls`` and meets the KKT conditions.

A baseline that returned wrong answers fast would flatter nobody but itself; this keeps the
headline ratio of ``scripts/bench_pipeline.py`` honest. NumPy float64 only (no torch tensors).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("numba")
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import nnls_baselines  # noqa: E402

from hsi_torch.spectral import difference_matrix  # noqa: E402


def _problems(n: int, seed: int) -> tuple[np.ndarray, ...]:
    """``n`` stacked problems shaped like the camera's: 30 observations (10 % masked), 25 bands,
    cosine transmittances, spectra with zero runs (so many constraints are active), noise."""
    g = np.random.default_rng(seed)
    O, M = 30, 25
    lam = np.linspace(0, 1, M)
    opd = g.uniform(3, 12, (n, O, 1))
    A = 0.5 * (1 - np.cos(2 * np.pi * opd * (1 + lam))) * g.uniform(0.5, 1.5, (n, O, 1))
    mask = g.random((n, O)) > 0.1
    x = np.maximum(g.normal(0.2, 1.0, (n, M)), 0)
    y = np.einsum("pom,pm->po", A, x) + 0.2 * g.normal(size=(n, O))
    sD = np.sqrt(0.3) * difference_matrix(M, 1).numpy().astype(np.float64)
    return A, mask, y, sD


def test_fnnls_agrees_with_scipy_and_meets_kkt():
    from scipy.optimize import nnls

    A, mask, y, sD = _problems(200, seed=3)
    x, iters = nnls_baselines.fnnls(A, mask, y, sD)
    assert (iters > 0).all()  # none hit the iteration cap
    zeros = np.zeros(sD.shape[0])
    xs = np.stack([nnls(np.vstack([A[j][mask[j]], sD]), np.concatenate([y[j][mask[j]], zeros]))[0]
                   for j in range(A.shape[0])])
    assert (xs == 0).mean() > 0.1  # the constraints matter
    scale = np.abs(xs).max(1, keepdims=True)
    assert np.abs(x - xs).max() / scale.min() < 1e-8
    # KKT of min ½‖[A_m; sD] x − [y_m; 0]‖²: x ≥ 0, gradient g ≥ 0, x·g = 0
    Am = A * mask[:, :, None]
    G = np.einsum("pom,pok->pmk", Am, Am) + sD.T @ sD
    grad = np.einsum("pmk,pk->pm", G, x) - np.einsum("pom,po->pm", Am, y)
    tol = 1e-9 * (np.abs(G).max((1, 2)) * np.abs(x).max(1) + np.abs(y).max(1))[:, None]
    assert (x >= 0).all()
    assert (grad >= -tol).all()
    assert (np.abs(grad[x > 0]) <= np.broadcast_to(tol, x.shape)[x > 0]).all()


def test_fnnls_rejects_mismatched_shapes():
    A, mask, y, sD = _problems(4, seed=0)
    with pytest.raises(ValueError, match="do not match"):
        nnls_baselines.fnnls(A, mask[:, :-1], y, sD)
