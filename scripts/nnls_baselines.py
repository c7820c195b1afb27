"""Baselines and machine limits for the per-pixel NNLS benchmarks (``bench_pipeline.py``).

Everything here is written independently of :mod:`hsi_torch.recon.nnls` (no call into its
kernels): it is what a skilled user would run instead, and what the machine allows at best.

* :func:`scipy_pool` — the ``scipy.optimize.nnls`` loop on the stacked problems
  ``[A_p[mask_p]; √β D] x ≈ [y_p[mask_p]; 0]`` spread over all cores: a process pool (``spawn``
  start method), the pixels in chunks.
* :func:`fnnls` — a compiled (numba) Lawson–Hanson active-set loop on the same problems, one
  pixel after another, in the ``fnnls`` form (Bro & de Jong 1997): the normal equations
  ``AᵀA = Σ_o a_o a_oᵀ + β DᵀD`` and ``Aᵀy`` of each stacked problem are formed per pixel, the
  passive-set systems are solved by a Cholesky factor extended by one row per added variable
  (refactorised when variables leave). ``num_threads > 1`` spreads the pixels over threads
  (``prange``); each pixel's solve stays serial.
* :func:`solve_inputs`, :func:`read_pass`, :func:`arithmetic_pass` — the per-pixel bytes an
  :class:`~hsi_torch.recon.nnls.NNLSProblem` solve reads, a pass that only reads them, and one
  that does the unavoidable arithmetic (``b = Aᵀ W y`` from the factors, ``x₀ = G⁻¹ b``).

numba is needed for :func:`fnnls` and the compiled passes (``HAVE_NUMBA``); the SciPy pool and
the torch read pass work without it.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import sys
import time
import types
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any

import numpy as np
from nnls_scipy_worker import solve_chunk, worker_info

if TYPE_CHECKING:
    import torch

try:  # optional, as in the package (this script is outside the package's import rules)
    import numba as nb

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - numba absent
    nb = None
    HAVE_NUMBA = False

__all__ = [
    "HAVE_NUMBA",
    "scipy_pool",
    "scipy_serial",
    "fnnls",
    "solve_inputs",
    "nbytes",
    "read_pass",
    "arithmetic_pass",
    "pool_peak_rss_gib",
]


# ---- the SciPy loop -----------------------------------------------------------------------------
def scipy_serial(A: np.ndarray, mask: np.ndarray, y: np.ndarray, sD: np.ndarray,
                 repeats: int = 1) -> tuple[float, np.ndarray]:
    """The SciPy loop in this process: best wall time of ``repeats`` (s) and ``x (n, M)``."""
    best, x = float("inf"), np.empty((A.shape[0], A.shape[2]))
    for _ in range(max(1, repeats)):
        t = time.perf_counter()
        x = solve_chunk((A, mask, y, sD))
        best = min(best, time.perf_counter() - t)
    return best, x


def pool_peak_rss_gib(pids: list[int]) -> float | None:
    """Sum of the peak resident set sizes (``VmHWM``) of processes ``pids`` in GiB (Linux)."""
    total = 0
    for pid in pids:
        try:
            with open(f"/proc/{pid}/status") as f:
                for line in f:
                    if line.startswith("VmHWM:"):
                        total += int(line.split()[1]) * 1024
        except OSError:
            return None
    return total / 2**30


def scipy_pool(A: np.ndarray, mask: np.ndarray, y: np.ndarray, sD: np.ndarray, *,
               workers: int | None = None, chunk: int = 500,
               repeats: int = 1) -> dict[str, Any]:
    """The SciPy loop over all cores: a ``spawn`` process pool, ``chunk`` pixels per task.

    Args:
        A: ``(n, O, M)`` float64 dense sensing matrices; mask: ``(n, O)`` bool; y: ``(n, O)``;
            sD: ``(K, M)`` ``√β D``.
        workers: processes (default: the CPUs this process may run on).
        chunk: pixels per task; repeats: timed passes (the fastest counts).

    Returns:
        ``{"time_s", "x" (n, M), "workers", "chunk", "scipy", "peak_rss_gib"}``: the wall time
        of one pass over the ``n`` pixels (the pool started and warmed up beforehand; the chunks
        are sent to the workers inside the timed pass), the workers' summed peak RSS.
    """
    if workers is None:
        workers = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (
            os.cpu_count() or 1)
    tasks = [(A[s:s + chunk], mask[s:s + chunk], y[s:s + chunk], sD)
             for s in range(0, A.shape[0], chunk)]
    ctx = mp.get_context("spawn")
    best, xs = float("inf"), None
    with _env(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1"), \
            _bare_main():
        pool = ctx.Pool(workers)
    with pool:
        info = pool.map(worker_info, range(workers), chunksize=1)  # start-up, imports
        pool.map(solve_chunk, tasks[:workers], chunksize=1)  # warm-up
        for _ in range(max(1, repeats)):
            t = time.perf_counter()
            out = pool.map(solve_chunk, tasks, chunksize=1)
            dt = time.perf_counter() - t
            if dt < best:
                best, xs = dt, np.concatenate(out)
        pids = sorted({pid for pid, _ in info})
        rss = pool_peak_rss_gib(pids)
    return {"time_s": best, "x": xs, "workers": workers, "chunk": chunk, "scipy": info[0][1],
            "peak_rss_gib": rss}


@contextmanager
def _bare_main() -> Iterator[None]:
    """Hide the calling script from ``spawn``: the workers then import only this module (NumPy,
    SciPy), not the benchmark and torch, as a stand-alone SciPy script's workers would."""
    main = sys.modules.get("__main__")
    sys.modules["__main__"] = types.ModuleType("__main__")
    try:
        yield
    finally:
        if main is not None:
            sys.modules["__main__"] = main


@contextmanager
def _env(**kw: str) -> Iterator[None]:
    old = {k: os.environ.get(k) for k in kw}
    os.environ.update(kw)
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


# ---- compiled Lawson–Hanson (fnnls form) --------------------------------------------------------
if HAVE_NUMBA:

    @nb.njit(cache=True, error_model="numpy")
    def _chol_from_scratch(G, idx, k, L):  # pragma: no cover - compiled
        """Cholesky ``L Lᵀ = G[idx[:k], idx[:k]]`` into ``L[:k, :k]``; False if not SPD."""
        for j in range(k):
            s = G[idx[j], idx[j]]
            for c in range(j):
                s -= L[j, c] * L[j, c]
            if not (s > 0.0):
                return False
            d = np.sqrt(s)
            L[j, j] = d
            for i in range(j + 1, k):
                t = G[idx[i], idx[j]]
                for c in range(j):
                    t -= L[i, c] * L[j, c]
                L[i, j] = t / d
        return True

    @nb.njit(cache=True, error_model="numpy")
    def _chol_solve(L, k, rhs):  # pragma: no cover - compiled
        for i in range(k):
            t = rhs[i]
            for c in range(i):
                t -= L[i, c] * rhs[c]
            rhs[i] = t / L[i, i]
        for i in range(k - 1, -1, -1):
            t = rhs[i]
            for c in range(i + 1, k):
                t -= L[c, i] * rhs[c]
            rhs[i] = t / L[i, i]

    @nb.njit(cache=True, error_model="numpy")
    def _lh_pixel(G, g, x, w, z, passive, banned, idx, L, max_iter):  # pragma: no cover
        """Lawson–Hanson on the normal equations ``G x = g`` (``G = AᵀA``, ``g = Aᵀy``).

        ``x`` receives the answer; returns the number of passive-set solves (negative when
        ``max_iter`` was reached).
        """
        m = g.shape[0]
        gmax = 0.0
        for i in range(m):
            x[i] = 0.0
            passive[i] = False
            banned[i] = False
            for j in range(m):
                a = abs(G[i, j])
                gmax = a if a > gmax else gmax
        gnorm = 0.0
        for i in range(m):
            gnorm = max(gnorm, abs(g[i]))
        eps = 2.220446049250313e-16
        k = 0
        it = 0
        for i in range(m):
            w[i] = g[i]
        while True:
            # the most positive gradient component outside the passive set
            xn = 0.0
            for i in range(m):
                xn += x[i]
            best = 10.0 * m * eps * (gnorm + gmax * xn)  # rounding level of w = g - G x
            j = -1
            for i in range(m):
                if not passive[i] and not banned[i] and w[i] > best:
                    best = w[i]
                    j = i
            if j < 0:
                return it
            # extend the Cholesky factor by the row of variable j
            for a in range(k):
                t = G[idx[a], j]
                for c in range(a):
                    t -= L[a, c] * L[k, c]
                L[k, a] = t / L[a, a]
            d = G[j, j]
            for c in range(k):
                d -= L[k, c] * L[k, c]
            if not (d > 1e-12 * G[j, j]):  # dependent column: skip it this round
                banned[j] = True
                continue
            L[k, k] = np.sqrt(d)
            idx[k] = j
            k += 1
            passive[j] = True
            first = True
            rejected = False
            while True:
                it += 1
                if it > max_iter:
                    return -it
                for a in range(k):
                    z[a] = g[idx[a]]
                _chol_solve(L, k, z)
                feasible = True
                for a in range(k):
                    if z[a] <= 0.0:
                        feasible = False
                if feasible:
                    for a in range(k):
                        x[idx[a]] = z[a]
                    break
                if first and z[k - 1] <= 0.0:  # the new variable would not move: reject it
                    k -= 1
                    passive[j] = False
                    banned[j] = True
                    rejected = True
                    break
                first = False
                alpha = 2.0
                blk = -1
                for a in range(k):
                    if z[a] <= 0.0:
                        xi = x[idx[a]]
                        r = xi / (xi - z[a])
                        if r < alpha:
                            alpha = r
                            blk = a
                for a in range(k):
                    xi = x[idx[a]]
                    x[idx[a]] = xi + alpha * (z[a] - xi)
                x[idx[blk]] = 0.0  # the blocking variable leaves (exactly 0)
                kk = 0
                for a in range(k):  # and every other one that reached 0
                    i = idx[a]
                    if x[i] <= 0.0:
                        x[i] = 0.0
                        passive[i] = False
                    else:
                        idx[kk] = i
                        kk += 1
                k = kk
                _chol_from_scratch(G, idx, k, L)
            if rejected:  # x unchanged; try the next candidate
                continue
            for i in range(m):  # gradient of the new point; the bans last one addition
                banned[i] = False
                v = g[i]
                for c in range(m):
                    v -= G[i, c] * x[c]
                w[i] = v

    @nb.njit(cache=True, error_model="numpy")
    def _lh_range(A, mask, y, DtD, x_out, iters, lo, hi, max_iter):  # pragma: no cover
        """Pixels ``lo … hi-1``: form the normal equations of the stacked problem, solve."""
        n, o, m = A.shape
        G = np.empty((m, m))
        g = np.empty(m)
        x = np.empty(m)
        w = np.empty(m)
        z = np.empty(m)
        passive = np.empty(m, np.bool_)
        banned = np.empty(m, np.bool_)
        idx = np.empty(m, np.int64)
        L = np.empty((m, m))
        for p in range(lo, hi):
            for i in range(m):
                g[i] = 0.0
                for j in range(m):
                    G[i, j] = DtD[i, j]
            for r in range(o):
                if mask[p, r]:
                    yr = y[p, r]
                    for i in range(m):
                        ai = A[p, r, i]
                        g[i] += ai * yr
                        for j in range(i + 1):
                            G[i, j] += ai * A[p, r, j]
            for i in range(m):
                for j in range(i):
                    G[j, i] = G[i, j]
            iters[p] = _lh_pixel(G, g, x, w, z, passive, banned, idx, L, max_iter)
            for i in range(m):
                x_out[p, i] = x[i]

    @nb.njit(cache=True)
    def _lh_serial(A, mask, y, DtD, x_out, iters, max_iter):  # pragma: no cover
        _lh_range(A, mask, y, DtD, x_out, iters, 0, A.shape[0], max_iter)

    @nb.njit(cache=True, parallel=True)
    def _lh_parallel(A, mask, y, DtD, x_out, iters, max_iter, num_chunks):  # pragma: no cover
        n = A.shape[0]
        for c in nb.prange(num_chunks):
            _lh_range(A, mask, y, DtD, x_out, iters, c * n // num_chunks,
                      (c + 1) * n // num_chunks, max_iter)


def fnnls(A: np.ndarray, mask: np.ndarray, y: np.ndarray, sD: np.ndarray, *,
          num_threads: int = 1, max_iter: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Compiled Lawson–Hanson on each stacked problem ``[A_p[mask_p]; sD] x ≈ [y_p[mask_p]; 0]``.

    Args:
        A: ``(n, O, M)`` float64; mask: ``(n, O)`` bool; y: ``(n, O)`` float64; sD: ``(K, M)``
            (``√β D``; its Gram ``sDᵀ sD`` is formed once, the pixels' own parts per pixel).
        num_threads: 1: one pixel after another in this thread; more: the pixels split between
            that many numba threads.
        max_iter: passive-set solves per pixel (default ``30·M``).

    Returns:
        ``x (n, M)`` and ``iterations (n,)`` (negative where ``max_iter`` was reached).
    """
    if not HAVE_NUMBA:
        raise RuntimeError("the compiled Lawson–Hanson baseline needs numba")
    A = np.ascontiguousarray(A, dtype=np.float64)
    y = np.ascontiguousarray(y, dtype=np.float64)
    mask = np.ascontiguousarray(mask, dtype=np.bool_)
    n, o, m = A.shape
    if mask.shape != (n, o) or y.shape != (n, o) or sD.shape[1] != m:
        raise ValueError(f"fnnls: A {A.shape}, mask {mask.shape}, y {y.shape}, sD {sD.shape} "
                         "do not match (n, O, M), (n, O), (n, O), (K, M)")
    DtD = np.ascontiguousarray(sD.T @ sD, dtype=np.float64)
    x = np.empty((n, m))
    iters = np.empty(n, np.int64)
    mi = int(max_iter or 30 * m)
    if num_threads <= 1 or n < 2:
        _lh_serial(A, mask, y, DtD, x, iters, mi)
    else:
        old = nb.get_num_threads()
        nb.set_num_threads(min(int(num_threads), nb.config.NUMBA_NUM_THREADS))
        try:
            _lh_parallel(A, mask, y, DtD, x, iters, mi, min(n, 64 * int(num_threads)))
        finally:
            nb.set_num_threads(old)
    return x, iters


# ---- what the solve reads, and the passes that bound it -----------------------------------------
def solve_inputs(problem: Any, y: torch.Tensor) -> dict[str, torch.Tensor]:
    """The per-pixel tensors an ``NNLSProblem.solve(y)`` reads (active set, compiled kernel).

    The right-hand sides ``b = Aᵀ W y`` read ``y``, the static mask and the sensing factors
    (``transmittance (P, V, M)`` and ``gain (P, V)`` of a ``SensingModel``, or dense
    ``A (P, O, M)``); the compiled pass reads per pixel ``G`` and ``H = G⁻¹`` (``(P, M, M)``
    each), ``diag G``, the ``‖G‖₂`` bound and the singular / no-data flags. Tensors shared by
    all pixels (one row) are left out; so are the outputs (``b``, ``x``, the zero sets, the
    residuals), which are written.
    """
    import torch

    P = y.shape[0]
    cand: dict[str, Any] = {"y": y, "mask": problem.mask}
    sens = problem.sensing
    if hasattr(sens, "transmittance"):
        cand["transmittance"] = sens.transmittance
        cand["gain"] = sens.gain
    else:
        cand["A"] = sens.dense()
    for k in ("gram", "gram_inv", "gram_diag", "gram_norm", "singular", "no_data"):
        cand[k] = getattr(problem, k)
    return {k: t for k, t in cand.items()
            if isinstance(t, torch.Tensor) and t.ndim >= 1 and t.shape[0] == P}


def nbytes(ts: dict[str, torch.Tensor]) -> int:
    """Total bytes of the tensors ``ts``."""
    return int(sum(t.numel() * t.element_size() for t in ts.values()))


if HAVE_NUMBA:

    @nb.njit(cache=True, parallel=True)
    def _rhs_matvec(y, mask, Bt, gain, resp, H, x, num_chunks):  # pragma: no cover - compiled
        """Per pixel ``b = Aᵀ W y`` from the factors and ``x = H b`` (the arithmetic floor),
        each inner loop over the bands (independent accumulators: vectorised), ``H`` read by
        rows (symmetric), the arrays indexed in place (no per-pixel views)."""
        P, V, M = Bt.shape
        C = resp.shape[0]
        for ch in nb.prange(num_chunks):
            w = np.empty(M)
            b = np.empty(M)
            xp = np.empty(M)
            for p in range(ch * P // num_chunks, (ch + 1) * P // num_chunks):
                for m in range(M):
                    b[m] = 0.0
                    xp[m] = 0.0
                for v in range(V):
                    gv = gain[p, v]
                    for m in range(M):
                        w[m] = 0.0
                    for c in range(C):
                        o = v * C + c
                        u = y[p, o] * gv if mask[p, o] else 0.0
                        for m in range(M):
                            w[m] += u * resp[c, m]
                    for m in range(M):
                        b[m] += w[m] * Bt[p, v, m]
                for j in range(M):
                    bj = b[j]
                    for i in range(M):
                        xp[i] += H[p, j, i] * bj
                for i in range(M):
                    x[p, i] = xp[i]


def read_pass(ts: dict[str, torch.Tensor], threads: int, repeats: int = 3) -> dict[str, Any]:
    """A pass that only reads the tensors ``ts`` (a sum over each), best of ``repeats``.

    Two ways, the faster counts: torch's ``sum`` with ``threads`` intra-op threads, and NumPy's
    (CPU only, one thread); booleans are summed as bytes.

    Returns:
        ``{"time_s", "bytes", "gbps", "how"}``.
    """
    import torch

    total = nbytes(ts)
    dev = next(iter(ts.values())).device
    vals = [t.view(torch.uint8) if t.dtype == torch.bool else t for t in ts.values()]
    old = torch.get_num_threads()
    torch.set_num_threads(max(1, threads))
    best, how = float("inf"), "torch"
    try:
        for _ in range(max(1, repeats)):
            if dev.type == "cuda":
                torch.cuda.synchronize(dev)
            t = time.perf_counter()
            float(sum(v.sum().double() for v in vals))
            dt = time.perf_counter() - t
            if dt < best:
                best, how = dt, f"torch sum, {threads} threads"
            if dev.type == "cpu":
                t = time.perf_counter()
                float(sum(float(v.numpy().sum()) for v in vals))
                dt = time.perf_counter() - t
                if dt < best:
                    best, how = dt, "NumPy sum, 1 thread"
    finally:
        torch.set_num_threads(old)
    return {"time_s": best, "bytes": total, "gbps": total / best / 1e9, "how": how}


def arithmetic_pass(problem: Any, y: torch.Tensor, threads: int,
                    repeats: int = 3) -> dict[str, Any] | None:
    """The unavoidable arithmetic of one frame: ``b = Aᵀ W y`` from the sensing factors and the
    unconstrained solution ``x₀ = G⁻¹ b`` per pixel, fused in one compiled pass (numba, float
    arithmetic of the stored dtype, ``threads`` threads), best of ``repeats``.

    Returns ``{"time_s", "bytes", "gbps"}`` (bytes read: ``y``, the mask, the factors, ``H``),
    or ``None`` where it does not apply (no numba, not CPU, not a factored model, no mask, a
    shared ``H``).
    """
    sens = problem.sensing
    if (not HAVE_NUMBA or y.device.type != "cpu" or not hasattr(sens, "transmittance")
            or problem.mask is None or problem.gram_inv.shape[0] != y.shape[0]
            or sens.transmittance.shape[0] != y.shape[0]):
        return None
    yn = y.to(sens.dtype).contiguous().numpy()
    mk = problem.mask.contiguous().numpy()
    Bt = sens.transmittance.contiguous().numpy()
    gn = sens.gain.contiguous().numpy()
    rs = sens.response.contiguous().numpy()
    H = problem.gram_inv.contiguous().numpy()
    x = np.empty((yn.shape[0], H.shape[1]), H.dtype)
    total = yn.nbytes + mk.nbytes + Bt.nbytes + gn.nbytes + H.nbytes
    old = nb.get_num_threads()
    nb.set_num_threads(min(max(1, threads), nb.config.NUMBA_NUM_THREADS))
    try:
        _rhs_matvec(yn[:8], mk[:8], Bt[:8], gn[:8], rs, H[:8], x[:8], 2)  # compile / warm
        best = float("inf")
        for _ in range(max(1, repeats)):
            t = time.perf_counter()
            _rhs_matvec(yn, mk, Bt, gn, rs, H, x, 64 * threads)
            best = min(best, time.perf_counter() - t)
    finally:
        nb.set_num_threads(old)
    return {"time_s": best, "bytes": total, "gbps": total / best / 1e9}
