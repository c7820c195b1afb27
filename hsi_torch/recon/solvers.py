"""Batched non-negative, smoothness-regularised least squares: one small problem per pixel.

Every pixel ``p`` solves

.. math::

    x_p = \\arg\\min_{x \\ge 0} \\sum_o w_{po} (A_p x - y_p)_o^2 + \\beta \\lVert D x \\rVert^2

with ``A_p`` of shape ``(O, M)`` (``O`` observations, ``M`` bands), a 0/1 observation mask ``w``
and ``D`` the difference operator of :func:`hsi_torch.spectral.difference_matrix`. In
normal-equation form this is the convex quadratic programme ``min ½ xᵀGx − bᵀx, x ≥ 0`` with
``G = Aᵀ W A + β DᵀD`` and ``b = Aᵀ W y``; its KKT conditions are ``x ≥ 0``, ``g = Gx − b ≥ 0`` and
``x ⊙ g = 0``.

Method (``method="active_set"``, exact, finite termination):

1. Per calibration (:func:`prepare_nnls`, done once when ``A``, mask and ``beta`` are fixed):
   the Gram matrices ``G_p``, their explicit inverses ``H_p = G_p⁻¹`` (batched Cholesky) and a
   lower bound of ``‖G_p‖₂``. A frame then costs, streamed over cache-sized pixel chunks,
   ``b = Aᵀ W y`` and ``x = H b`` (two batched row-vector products).
2. Pixels whose ``x`` has a negative entry are gathered into one compacted sub-batch and run
   *block principal pivoting* (Júdice & Pires; Kim & Park's NNLS variant) on the zero set ``Z``,
   starting from ``Z`` = the negative entries (usually already the answer). The solution with
   ``x_Z = 0`` is ``x = x₀ − H[:, Z] H_ZZ⁻¹ x₀_Z`` and its multipliers ``λ_Z = −H_ZZ⁻¹ x₀_Z``
   (the gradient on ``Z``), so a round reads ``|Z|`` rows of ``H`` and factorises a
   ``|Z| × |Z|`` system per pixel (pixels bucketed by ``|Z|``, padded within a bucket). Infeasible
   variables (``x_F < 0`` or ``λ_Z < 0``) are exchanged; after three rounds without progress
   only the largest one (Murty's rule: finite termination for positive definite ``G``). Pixels
   leave the working set as they finish; those not settled after 16 rounds (badly conditioned
   ``G`` cycling through single pivots) continue with Lawson–Hanson (3.).
3. An independent KKT check with the exact ``G`` and ``b`` for every pixel (streamed), as a
   normwise backward error (:func:`nnls_kkt_residual`); pixels above ``tol`` (default ``M·eps``)
   get up to ``refine`` steps of iterative refinement on their zero set. Pixels whose ``G`` is
   singular or numerically so (``beta = 0`` with rank-deficient ``A``, few observations), or that
   still fail, use the Lawson–Hanson active-set method on a principal-pivot tableau of ``G``
   starting from ``x = 0``; a variable only enters the free set while its reduced pivot is safely
   positive, so the free columns stay independent and the KKT conditions hold at the end.

On CPU every kernel runs single-threaded and the pixels are split between ``num_threads`` Python
threads instead (default ``torch.get_num_threads()``): thousands of small multi-threaded kernels
stall at their barriers whenever another process holds a core (see :func:`_workers`).

``method="admm"``: ADMM on ``x = z, z ≥ 0`` with per-pixel ``(G + ρI)⁻¹`` precomputed, warm started
from the clamped unconstrained solution (or a given ``x0``). With ``admm_iters=N`` it runs exactly
``N`` iterations with out-of-place torch ops only, so the result is differentiable w.r.t. ``y``.

Convention:
    ``A``: ``(O, M)`` shared by all pixels or ``(P, O, M)`` one per pixel; ``y``: ``(P, O)``;
    ``mask``: ``(P, O)`` bool, ``True`` = observation used. ``y`` may hold non-finite values where
    the mask is ``False``; ``A`` must be finite. Observation index ``o = 3·v + c`` (view-major)
    as in the rest of the package, but the solver itself is agnostic of it. No per-pixel Python
    loops: all loops run over iterations or pivots of a whole (sub-)batch; memory is bounded by
    chunking over pixels.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass

import torch
from torch import Tensor

from hsi_torch.spectral import DEFAULT_GRID, SpectralGrid, difference_matrix

__all__ = [
    "NNLSResult",
    "NNLSProblem",
    "prepare_nnls",
    "solve_nnls",
    "nnls_kkt_residual",
    "smoothness_gram",
    "masked_gram",
    "synthetic_brf_problem",
    "cpu_threads",
]

_METHODS = ("active_set", "admm")


@dataclass
class NNLSResult:
    """Output of :func:`solve_nnls` / :meth:`NNLSProblem.solve`.

    Attributes:
        x: ``(P, M)`` solution, ``≥ 0``, never NaN (0 for pixels without data).
        converged: ``(P,)`` bool, the method terminated and the relative KKT residual is ``≤ tol``.
        iterations: ``(P,)`` int64; active set: exchange rounds plus Lawson–Hanson iterations of
            the fallback (0 when the unconstrained solution was already non-negative); ADMM:
            iterations run.
        kkt_residual: ``(P,)`` KKT residual as a normwise backward error,
            ``‖min(diag(G) ⊙ x, g)‖₂ / (‖G‖₂ ‖x‖₂ + ‖b‖₂)`` with ``g = Gx − b`` (see
            :func:`nnls_kkt_residual`; 0 for an exact solution, O(eps) for a well-solved one).
        no_data: ``(P,)`` bool, pixel had no usable observation (all masked): ``x = 0``.
        method: the method used.
    """

    x: Tensor
    converged: Tensor
    iterations: Tensor
    kkt_residual: Tensor
    no_data: Tensor
    method: str = "active_set"


# ----------------------------------------------------------------------------------------------
# small helpers


def _rowvec(
    v: Tensor, mat: Tensor, *, out: Tensor | None = None, sub: Tensor | None = None
) -> Tensor:
    """``v[p] @ mat[p]`` (minus ``sub[p]``) for ``v (n, K)``, ``mat (n|1, K, L)`` -> ``(n, L)``.

    The row-vector form of a batched mat-vec is the fast one on CPU (a symmetric ``mat`` gives
    ``mat @ v``). ``out``: contiguous ``(n, L)`` to write into; ``sub``: ``(n, L)`` subtracted in
    the same kernel.
    """
    if mat.shape[0] == 1 and v.shape[0] != 1:
        if sub is not None:
            return torch.addmm(sub, v, mat[0], beta=-1, out=out)
        return torch.mm(v, mat[0], out=out)
    o3 = None if out is None else out.unsqueeze(1)
    if sub is not None:
        r = torch.baddbmm(sub.unsqueeze(1), v.unsqueeze(1), mat, beta=-1, out=o3)
    else:
        r = torch.bmm(v.unsqueeze(1), mat, out=o3)
    return r.squeeze(1) if out is None else out


@contextmanager
def cpu_threads(device: torch.device | str, num_threads: int | None) -> Iterator[None]:
    """Temporarily lower torch's intra-op thread count for CPU work (no-op elsewhere).

    ``num_threads=None`` keeps torch's setting. The setting is process-wide while the block runs.
    """
    dev = torch.device(device)
    if num_threads is not None and int(num_threads) < 1:
        raise ValueError(f"num_threads must be >= 1 or None, got {num_threads}")
    old = torch.get_num_threads()
    if dev.type != "cpu" or num_threads is None or int(num_threads) >= old:
        yield
        return
    torch.set_num_threads(int(num_threads))
    try:
        yield
    finally:
        torch.set_num_threads(old)


def _workers(device: torch.device, num_threads: int | None) -> int:
    """Worker threads of the CPU solver: ``num_threads`` or torch's intra-op thread count.

    The solver runs thousands of small batched kernels. On a small machine shared with other
    processes every multi-threaded kernel waits at its barrier for a thread the OS has not
    scheduled: measured on the 2-core development machine under load, one frame took 3.6–9 s
    with torch's 2 intra-op threads and 0.6–1.1 s with one. So the solver runs single-threaded
    kernels and instead splits the pixels between ``num_threads`` Python threads (torch releases
    the GIL inside kernels), which never wait for each other within a kernel.
    """
    if num_threads is not None and int(num_threads) < 1:
        raise ValueError(f"num_threads must be >= 1 or None, got {num_threads}")
    if device.type != "cpu":
        return 1
    return int(num_threads) if num_threads is not None else torch.get_num_threads()


_POOLS: dict[int, ThreadPoolExecutor] = {}


def _for_chunks(fn: Callable[[slice], None], num: int, n: int, workers: int) -> None:
    """Call ``fn(slice)`` for consecutive chunks of ``n`` of ``range(num)``.

    With ``workers > 1`` the chunks are split into ``workers`` contiguous blocks run by that many
    threads (``fn`` must write disjoint outputs). Each thread runs single-threaded kernels, so no
    kernel waits at a thread barrier for a core that another process holds.
    """
    chunks = [slice(s, min(num, s + n)) for s in range(0, num, max(1, n))]
    if workers <= 1 or len(chunks) <= 1:
        for sl in chunks:
            fn(sl)
        return
    workers = min(workers, len(chunks))
    per = -(-len(chunks) // workers)
    blocks = [chunks[i:i + per] for i in range(0, len(chunks), per)]
    pool = _POOLS.get(workers)
    if pool is None:
        pool = _POOLS[workers] = ThreadPoolExecutor(workers, thread_name_prefix="hsi_nnls")

    def run(block: list[slice]) -> None:
        for sl in block:
            fn(sl)

    for f in [pool.submit(run, blk) for blk in blocks]:
        f.result()


def _take(t: Tensor | None, sl: slice) -> Tensor | None:
    """Slice a per-pixel tensor, pass shared (leading dim 1) and ``None`` through."""
    if t is None or t.shape[0] == 1:
        return t
    return t[sl]


def _expand_rows(t: Tensor, n: int) -> Tensor:
    return t.expand(n, *t.shape[1:]) if t.shape[0] == 1 and n != 1 else t


def _default_tol(dtype: torch.dtype, num_bands: int) -> float:
    return float(num_bands * torch.finfo(dtype).eps)


def _admm_tol(dtype: torch.dtype) -> float:
    return float(torch.finfo(dtype).eps) ** 0.5


def _default_chunk(device: torch.device) -> int:
    # Measured on the 2-core CPU: chunks of a few thousand pixels keep the batched 25×25 LAPACK
    # calls in cache and are ~2× faster than one huge batch. GPUs prefer large batches.
    return 8192 if device.type == "cpu" else 262144


def _default_stream_chunk(device: torch.device) -> int:
    # per-frame solve, streamed stages (b = AᵀWy, x = Hb, KKT check): on the 2-core CPU chunks of
    # ~16k pixels keep the (n, M) temporaries in cache (measured ~3x faster than one full-frame
    # batch with 2 threads); GPUs prefer one large batch
    return 16384 if device.type == "cpu" else 1 << 20


def _default_solve_chunk(device: torch.device) -> int:
    # correction sub-batch: as large as memory comfortably allows (fewer Python-level rounds)
    return 131072 if device.type == "cpu" else 1 << 20


def _chunk_len(
    num: int, per_pixel_bytes: int, chunk_size: int | None, max_memory: int | None,
    device: torch.device, default: int | None = None,
) -> int:
    if chunk_size is not None:
        if int(chunk_size) < 1:
            raise ValueError(f"chunk_size must be >= 1, got {chunk_size}")
        n = int(chunk_size)
    elif max_memory is not None:
        if int(max_memory) < 1:
            raise ValueError(f"max_memory must be >= 1 byte, got {max_memory}")
        n = max(1, int(max_memory) // max(1, per_pixel_bytes))
    else:
        n = _default_chunk(device) if default is None else default
    return max(1, min(n, max(num, 1)))


def smoothness_gram(
    num_bands: int, beta: float, diff_order: int, *, device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
) -> Tensor:
    """The regulariser's Gram matrix ``β DᵀD`` ``(M, M)`` (zeros for ``β = 0``), ``D`` from
    :func:`hsi_torch.spectral.difference_matrix`."""
    if beta > 0:
        D = difference_matrix(num_bands, diff_order, device=device, dtype=dtype)
        return beta * (D.T @ D)
    return torch.zeros((num_bands, num_bands), dtype=dtype, device=device)


def masked_gram(
    A: Tensor, mask: Tensor | None, reg: Tensor | None = None, *, out: Tensor | None = None
) -> Tensor:
    """Per-pixel Gram matrices ``G = Aᵀ W A (+ reg)``.

    Args:
        A: ``(n, O, M)`` finite sensing matrices; mask: ``(n, O)`` bool (``W``) or ``None``.
        reg: optional ``(M, M)`` added, e.g. :func:`smoothness_gram`.
        out: optional ``(n, M, M)`` to write into.

    Returns:
        ``(n, M, M)``, exactly symmetric (the same products in the same order on both sides).
    """
    aw = A if mask is None else A * mask.unsqueeze(2)  # A finite: 0/1 weights by product
    G = torch.bmm(A.transpose(1, 2), aw, out=out)
    return G if reg is None else G.add_(reg)


def _gram_norm(G: Tensor) -> Tensor:
    """Lower bound of ``‖G‖₂`` (largest eigenvalue of the PSD ``G``): ``(P|1, M, M)`` -> ``(P|1,)``.

    The larger of ``max_m G_mm`` and the Rayleigh quotient after three power-iteration steps from
    the all-ones vector (close to the Perron vector of the non-negative Gram matrices of this
    camera). Both never exceed ``‖G‖₂``, so the KKT residual built on it is never underestimated.
    """
    tiny = torch.finfo(G.dtype).tiny
    v = torch.ones(G.shape[:2], dtype=G.dtype, device=G.device)
    for _ in range(3):
        v = _rowvec(v, G)
        v = v / v.square().sum(1, keepdim=True).sqrt().clamp_min(tiny)
    rq = (_rowvec(v, G) * v).sum(1)
    return torch.maximum(rq, G.diagonal(dim1=1, dim2=2).amax(1)).clamp_min(0)


def _norm2(v: Tensor) -> Tensor:
    """Row 2-norms of ``(n, K)`` (a sum of squares: the fast reduction on CPU)."""
    return (v * v).sum(1).sqrt()


def nnls_kkt_residual(G: Tensor, b: Tensor, x: Tensor, gram_norm: Tensor | None = None) -> Tensor:
    """Relative KKT residual (a normwise backward error) of ``min ½xᵀGx − bᵀx, x ≥ 0`` per pixel.

    Args:
        G: ``(P|1, M, M)`` symmetric positive semi-definite Gram matrices.
        b: ``(P, M)`` right-hand sides.
        x: ``(P, M)`` candidate solutions.
        gram_norm: ``(P|1,)`` a lower bound of ``‖G‖₂`` if already known (default: computed as
            in :class:`NNLSProblem`).

    Returns:
        ``(P,)`` ``‖min(diag(G) ⊙ x, g)‖₂ / (‖G‖₂ ‖x‖₂ + ‖b‖₂)`` with ``g = Gx − b`` (0 where the
        denominator is 0). The numerator vanishes exactly when ``x ≥ 0``, ``g ≥ 0`` and
        ``x ⊙ g = 0``; dividing by ``‖G‖₂‖x‖₂ + ‖b‖₂`` (the size of the terms that make up ``g``)
        makes it the relative perturbation of ``(G, b)`` the answer is exact for (Rigal–Gaches),
        so a well-solved pixel scores ``O(eps)`` whatever ``cond(G)``.
    """
    g = _rowvec(x, G) - b
    gn = _gram_norm(G) if gram_norm is None else gram_norm
    return _kkt_ratio(g, x, G.diagonal(dim1=-2, dim2=-1), gn, _norm2(b))


def _kkt_ratio(g: Tensor, x: Tensor, gd: Tensor, gn: Tensor, bnorm: Tensor) -> Tensor:
    """:func:`nnls_kkt_residual` from ``g``, ``diag(G)``, the ``‖G‖₂`` bound and ``‖b‖₂``.

    The denominator is 0 only where ``x = 0`` and ``b = 0``; then ``g = 0`` and the ratio is 0.
    """
    t = gd * x
    torch.minimum(t, g, out=t)
    return _norm2(t) / (gn * _norm2(x) + bnorm).clamp_min(torch.finfo(x.dtype).tiny)


# ----------------------------------------------------------------------------------------------
# tableau (principal pivot transform) machinery


def _pivot(T: Tensor, c: Tensor, k: Tensor, has: Tensor | None = None) -> Tensor:
    """One principal pivot on index ``k[i]`` of every tableau ``T[i]``, in place.

    The tableau represents ``v = T u + c`` with ``v = (x_F, g_Z)`` and ``u = (g_F, x_Z)`` for the
    free set ``F`` and the active (zero) set ``Z``; pivoting on ``k`` moves ``k`` between the two
    sets. ``c`` then holds ``x_F`` and ``g_Z`` of the equality-constrained solution. Rows with
    ``has[i] = False`` are left unchanged (masked rank-1 update, no gather/scatter of ``T``).

    Returns:
        ``(n,)`` bool: the pivot was positive and finite (otherwise ``T`` of that row is invalid).
    """
    n, m = c.shape
    kk = k.view(n, 1, 1)
    col = T.gather(2, kk.expand(n, m, 1))  # T[:, :, k]
    row = T.gather(1, kk.expand(n, 1, m))  # T[:, k, :]
    p0 = col.gather(1, kk)  # (n, 1, 1)
    ok = (p0 > 0) & torch.isfinite(p0)
    use = ok if has is None else ok & has.view(n, 1, 1)
    p = torch.where(use, p0, torch.ones((), dtype=p0.dtype, device=p0.device))
    colp = torch.where(use, col / p, torch.zeros((), dtype=p.dtype, device=p.device))
    ck = c.gather(1, k.view(n, 1))
    # entries off row/column k get the rank-1 update; row k, column k and (k, k) are written
    # explicitly (no cancellation whatever the scale of p)
    T.addcmul_(colp, row, value=-1.0)
    T.scatter_(1, kk.expand(n, 1, m), torch.where(use, -row / p, row))
    T.scatter_(2, kk.expand(n, m, 1), torch.where(use, colp, col))
    T.view(n, m * m).scatter_(1, (k * (m + 1)).view(n, 1), torch.where(use, 1.0 / p, p0).view(n, 1))
    c.addcmul_(colp.squeeze(2), ck, value=-1.0)
    c.scatter_(1, k.view(n, 1), torch.where(use.view(n, 1), -ck / p.view(n, 1), ck))
    return ok.view(n)


def _pivot_rows(T: Tensor, c: Tensor, free: Tensor, k: Tensor, has: Tensor | None) -> Tensor:
    """Masked pivot (see :func:`_pivot`) that also toggles ``free[i, k[i]]``; returns ok."""
    ok = _pivot(T, c, k, has)
    flip = ok if has is None else ok & has
    fk = free.gather(1, k.view(-1, 1))
    free.scatter_(1, k.view(-1, 1), fk ^ flip.view(-1, 1))
    return ok


def _refine(T: Tensor, c: Tensor, free: Tensor, G: Tensor, b: Tensor) -> Tensor:
    """One step of iterative refinement of the equality-constrained solution; returns new ``c``.

    Uses the exact ``G`` for the gradient and the tableau block ``T_FF = G_FF⁻¹`` as the
    (approximate) inverse; ``c`` becomes ``(x_F, g_Z)`` recomputed from the refined ``x``.
    """
    zero = torch.zeros((), dtype=c.dtype, device=c.device)
    x = torch.where(free, c, zero)
    g = _rowvec(x, G) - b
    d = torch.bmm(T, torch.where(free, g, zero).unsqueeze(2)).squeeze(2)
    x = torch.where(free, x - d, zero)
    g = _rowvec(x, G) - b
    return torch.where(free, x, g)


def _zero_set_solve(
    H: Tensor, idx: Tensor, Z: Tensor, v: Tensor, k: int
) -> tuple[Tensor, Tensor, Tensor, Tensor | None]:
    """Equality-constrained solve through the precomputed inverse ``H = G⁻¹``.

    For every row: ``λ = −H_ZZ⁻¹ v_Z``, ``x = v + H[:, Z] λ`` (so ``x_Z = 0``). With ``v = G⁻¹ b``
    this is the minimiser of ``½xᵀGx − bᵀx`` subject to ``x_Z = 0`` and ``λ = (Gx − b)_Z`` its
    gradient (the multipliers) on ``Z``. Only ``|Z|`` rows of ``H`` are read and only a
    ``k × k`` system (``k = max |Z|``, padded with identity rows) is factorised per pixel.

    Args:
        H: ``(P|1, M, M)`` symmetric inverses (all pixels); idx: ``(n,)`` rows of ``H`` to use.
        Z: ``(n, M)`` bool zero set; v: ``(n, M)``; k: ``max |Z|`` over the rows (host int).

    Returns:
        ``x (n, M)`` with exact zeros on ``Z``; ``lam (n, M)`` (0 off ``Z``); ``ok (n,)`` the
        ``k × k`` Cholesky succeeded; the Cholesky data ``(zi, R, L)`` packed for reuse (or None
        when ``k = 0``).
    """
    n, m = v.shape
    if k == 0:
        return v.clone(), torch.zeros_like(v), torch.ones((n,), dtype=torch.bool,
                                                           device=v.device), None
    zero = torch.zeros((), dtype=v.dtype, device=v.device)
    # indices of Z first (ascending), then free ones as padding (their λ comes out exactly 0)
    zi = torch.argsort((~Z).to(torch.uint8), dim=1, stable=True)[:, :k]
    zv = Z.gather(1, zi)  # (n, k) valid entries
    # rows H[Z, :] (n, k, M): one contiguous row copy each (H symmetric: also the columns)
    rows = zi if H.shape[0] == 1 else idx.unsqueeze(1) * m + zi
    R = H.view(-1, m).index_select(0, rows.reshape(-1)).view(n, k, m)
    Hzz = R.gather(2, zi.unsqueeze(1).expand(n, k, k))
    eye = torch.eye(k, dtype=v.dtype, device=v.device)
    Hzz = torch.where(zv.unsqueeze(2) & zv.unsqueeze(1), Hzz, eye)
    L, info = torch.linalg.cholesky_ex(Hzz)
    ok = info == 0
    L = torch.where(ok.view(n, 1, 1), L, eye)
    rhs = torch.where(zv, v.gather(1, zi), zero).unsqueeze(2)
    t = torch.linalg.solve_triangular(L, rhs, upper=False)
    lam_k = -torch.linalg.solve_triangular(L.transpose(1, 2), t, upper=True).squeeze(2)
    x = (v + _rowvec(lam_k, R)).masked_fill(Z, 0.0)
    lam = torch.zeros_like(v).scatter_(1, zi, lam_k)
    return x, lam, ok, (zi, R, L)


def _bucketed_solve(
    H: Tensor, gi: Tensor, Z: Tensor, v: Tensor, edge_list: list[int], bounds: list[int]
) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`_zero_set_solve` for rows sorted by ``|Z|``, one padded size per bucket.

    ``bounds[i]`` = number of rows with ``|Z| ≤ edge_list[i]`` (rows ``bounds[i-1]:bounds[i]``
    are solved with ``k = edge_list[i]``).
    """
    x = torch.empty_like(v)
    lam = torch.empty_like(v)
    ok = torch.empty((v.shape[0],), dtype=torch.bool, device=v.device)
    start = 0
    for k, stop in zip(edge_list, bounds, strict=True):
        if stop > start:
            sl = slice(start, stop)
            x[sl], lam[sl], ok[sl], _ = _zero_set_solve(H, gi[sl], Z[sl], v[sl], k)
            start = stop
    return x, lam, ok


def _zero_set_solve_any(H: Tensor, gi: Tensor, Z: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`_zero_set_solve` for rows in any order (sorted into ``|Z|`` buckets inside).

    Returns ``x`` and ``ok`` in the input order.
    """
    m = v.shape[1]
    edges = torch.tensor([e for e in _K_EDGES if e < m] + [m], device=v.device)
    cnt = Z.sum(1)
    order = torch.argsort(cnt, stable=True)
    bounds = torch.searchsorted(cnt[order], edges, right=True).tolist()
    xs, _, oks = _bucketed_solve(H, gi[order], Z[order], v[order], edges.tolist(), bounds)
    x = torch.empty_like(v)
    ok = torch.empty_like(oks)
    x[order] = xs
    ok[order] = oks
    return x, ok


#: exchange rounds after which a pixel leaves block principal pivoting for Lawson–Hanson: well
#: conditioned pixels settle in 1–6 rounds; badly conditioned ones (cond(G) ~ 1e5) can cycle
#: through dozens of Murty single pivots, each a round for the whole (tiny) remaining batch
_BPP_ROUNDS = 16

#: bucket bounds on |Z| for the padded zero-set solves (pixels with |Z| in (e_i, e_{i+1}] share
#: one k = e_{i+1} system size)
_K_EDGES = (0, 1, 2, 3, 4, 5, 6, 8, 10, 13, 17)


def _bpp(
    H: Tensor, idx: Tensor, x0: Tensor, gd: Tensor, thr: Tensor, max_iter: int
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Block principal pivoting on the zero set, through ``H = G⁻¹`` (Júdice–Pires, Kim–Park).

    Starts with the zero set ``Z`` = the negative entries of the unconstrained solution ``x0``
    (usually already the answer). Each round solves the equality-constrained problem for the
    current ``Z`` (:func:`_zero_set_solve`, a ``|Z| × |Z|`` system per pixel) and exchanges the
    infeasible set (``x_F < 0`` or ``λ_Z < 0``); after three rounds without fewer infeasible
    variables only the largest infeasible index is exchanged (Murty's rule, which guarantees
    finite termination for positive definite ``G``). Finished pixels leave the working set, so
    every round works on the still-active rows only.

    Args:
        H: ``(P|1, M, M)`` inverses; idx: ``(n,)`` global pixel indices into ``H``.
        x0: ``(n, M)`` unconstrained solutions ``H b``; gd: ``(n, M)`` ``diag(G)``.
        thr: ``(n, 1)`` infeasibility threshold in gradient units (``x_m G_mm`` and ``λ_m``).
        max_iter: maximum number of exchange rounds.

    Returns:
        ``x (n, M)``, ``Z (n, M)`` final zero sets, ``done (n,)``, ``failed (n,)`` (Cholesky of
        ``H_ZZ`` failed: re-solve another way), ``iterations (n,)``.
    """
    n, m = x0.shape
    dev = x0.device
    x_out = torch.zeros_like(x0)
    z_out = torch.zeros((n, m), dtype=torch.bool, device=dev)
    done = torch.zeros((n,), dtype=torch.bool, device=dev)
    failed = torch.zeros((n,), dtype=torch.bool, device=dev)
    iters = torch.zeros((n,), dtype=torch.long, device=dev)
    edges = torch.tensor([e for e in _K_EDGES if e < m] + [m], device=dev)
    edge_list = edges.tolist()
    Z = x0 * gd < -thr
    z0_empty = ~Z.any(1)  # candidates without a clearly negative entry: 0 rounds if done at once
    # working set, kept sorted by |Z| so that each bucket of similar |Z| is a contiguous slice
    key = Z.sum(1)
    order = torch.argsort(key, stable=True)
    w = order  # local row (into the outputs) of each working pixel
    gi, v, gdw, tw, Z = idx[order], x0[order], gd[order], thr[order], Z[order]
    best = torch.full((n,), m + 1, dtype=torch.long, device=dev)
    backup = torch.full((n,), 3, dtype=torch.long, device=dev)
    bounds = torch.searchsorted(key[order], edges, right=True).tolist()
    for rnd in range(1, max_iter + 1):
        x, lam, ok = _bucketed_solve(H, gi, Z, v, edge_list, bounds)
        infeas = torch.where(Z, lam < -tw, x * gdw < -tw)
        nv = infeas.sum(1)
        fin = (nv == 0) | ~ok
        if rnd == max_iter:
            fin = torch.ones_like(fin)
        iters[w] = rnd
        x_out[w] = x
        z_out[w] = Z
        done[w] = (nv == 0) & ok
        failed[w] = ~ok
        improved = nv < best
        full_block = improved | (backup >= 1)
        backup = torch.where(improved, torch.full_like(backup, 3), (backup - 1).clamp_min(0))
        best = torch.where(improved, nv, best)
        last = (m - 1) - infeas.flip(1).to(torch.uint8).argmax(1)  # Murty: largest index
        single = torch.zeros_like(infeas).scatter_(1, last.view(-1, 1), True)
        Z = Z ^ torch.where(full_block.view(-1, 1), infeas, single)
        # compact (finished rows sort last) and re-sort by the new |Z|: one host sync a round
        key = torch.where(fin, m + 1, Z.sum(1))
        order = torch.argsort(key, stable=True)
        bounds = torch.searchsorted(key[order], edges, right=True).tolist()
        n_keep = bounds[-1]
        if n_keep == 0:
            break
        order = order[:n_keep]
        w, gi, v, gdw, tw = w[order], gi[order], v[order], gdw[order], tw[order]
        Z, best, backup = Z[order], best[order], backup[order]
    return x_out.clamp_min(0), z_out, done, failed, iters - z0_empty.long()


def _lawson_hanson(
    G: Tensor, b: Tensor, thr: Tensor, piv_tol: float, max_iter: int
) -> tuple[Tensor, Tensor, Tensor]:
    """Lawson–Hanson active set on the tableau, for singular or ill-conditioned ``G``.

    Starts from ``x = 0`` (``T = G``, ``c = −b``). Outer step: the most negative gradient among
    the active variables whose reduced pivot ``T_kk > piv_tol · G_kk`` enters the free set. Inner
    step: while the equality-constrained solution ``z`` has a non-positive free entry, move ``x``
    towards ``z`` up to the first blocking bound and drop that variable. One pivot per pixel per
    loop iteration.

    Returns:
        ``x (n, M)``, ``done (n,)``, ``iterations (n,)``.
    """
    n, m = b.shape
    dev, dt = b.device, b.dtype
    Gn = _expand_rows(G, n)
    gd = Gn.diagonal(dim1=1, dim2=2)
    T = Gn.clone()
    c = -b.clone()
    free = torch.zeros((n, m), dtype=torch.bool, device=dev)
    x = torch.zeros((n, m), dtype=dt, device=dev)
    iters = torch.zeros((n,), dtype=torch.long, device=dev)
    done = torch.zeros((n,), dtype=torch.bool, device=dev)
    zero = torch.zeros((), dtype=dt, device=dev)
    inf = torch.full((), float("inf"), dtype=dt, device=dev)
    refined = False
    refinements = 0
    for _ in range(max_iter + 3):
        nonpos = free & (c <= 0)
        inner = nonpos.any(1)
        diag_t = T.diagonal(dim1=1, dim2=2)
        cand = ~free & (c < -thr) & (diag_t > piv_tol * gd)
        outer = ~inner & cand.any(1)
        act = inner | outer
        finished = ~act
        x = torch.where(finished.view(-1, 1), torch.where(free, c, zero), x)
        if not bool(act.any()):
            if refined or refinements >= 3:
                done = torch.ones_like(done)
                break
            c = _refine(T, c, free, G, b)
            refined = True
            refinements += 1
            continue
        if int(iters.max()) >= max_iter:
            done = finished
            break
        refined = False
        z = torch.where(free, c, zero)
        # outer: x = z, k = most negative admissible gradient
        k_out = torch.where(cand, c, inf).argmin(1)
        # inner: step to the first blocking bound
        ratio = torch.where(nonpos, x / (x - z).clamp_min(torch.finfo(dt).tiny), inf)
        alpha, k_in = ratio.min(1)
        alpha = torch.where(inner, alpha, torch.zeros_like(alpha)).clamp(0, 1).view(-1, 1)
        x_in = torch.where(free, x + alpha * (z - x), zero).clamp_min(0)
        x_in = x_in.scatter(1, k_in.view(-1, 1), zero.expand(n, 1))
        x = torch.where(inner.view(-1, 1), x_in, torch.where(outer.view(-1, 1), z, x))
        k = torch.where(inner, k_in, k_out)
        _pivot_rows(T, c, free, k, act)
        iters += act.long()
    return x.clamp_min(0), done, iters


# ----------------------------------------------------------------------------------------------
# the problem object


def _check_inputs(
    A: Tensor, mask: Tensor | None, beta: float, diff_order: int
) -> tuple[Tensor, Tensor | None, float]:
    if not isinstance(A, Tensor):
        raise TypeError(f"A must be a torch.Tensor, got {type(A).__name__}")
    if A.dtype not in (torch.float32, torch.float64):
        raise TypeError(f"A must be float32 or float64, got {A.dtype}")
    if A.ndim not in (2, 3):
        raise ValueError(f"A must have shape (O, M) or (P, O, M), got {tuple(A.shape)}")
    o, m = A.shape[-2:]
    if o < 1 or m < 1:
        raise ValueError(f"A needs at least one observation and one band, got {tuple(A.shape)}")
    if diff_order not in (0, 1, 2):
        raise ValueError(f"diff_order must be 0, 1 or 2, got {diff_order}")
    beta = float(beta)
    if not (beta >= 0.0) or beta == float("inf"):
        raise ValueError(f"beta must be finite and >= 0, got {beta}")
    if beta > 0 and m < diff_order + 1:
        raise ValueError(f"diff_order={diff_order} needs at least {diff_order + 1} bands, got {m}")
    if mask is not None:
        if not isinstance(mask, Tensor):
            raise TypeError(f"mask must be a torch.Tensor or None, got {type(mask).__name__}")
        if mask.ndim != 2 or mask.shape[1] != o:
            raise ValueError(f"mask must have shape (P, {o}) to match A, got {tuple(mask.shape)}")
        if A.ndim == 3 and mask.shape[0] != A.shape[0]:
            raise ValueError(
                f"mask has {mask.shape[0]} pixels but A has {A.shape[0]} (shape {tuple(A.shape)})"
            )
        if mask.device != A.device:
            raise ValueError(f"mask is on {mask.device} but A is on {A.device}")
        mask = mask.to(torch.bool)
    return A, mask, beta


class NNLSProblem:
    """Precomputed per-pixel factorisations of one sensing configuration; reuse for every frame.

    Build with :func:`prepare_nnls`. Holds ``A`` (a reference, not a copy), the mask, the Gram
    matrices ``G = Aᵀ W A + β DᵀD`` and their inverses, each ``(P, M, M)`` (or ``(1, M, M)`` when
    ``A`` is shared and there is no mask). Memory: ``2·P·M²`` floats (≈ 1.6 GB in float32 for
    324 000 pixels × 25 bands).

    Attributes:
        A: ``(1|P, O, M)``; mask: ``(P, O)`` bool or ``None``; beta; diff_order.
        gram, gram_inv: ``(1|P, M, M)``; ``gram_inv`` is 0 where ``singular``.
        singular: ``(1|P,)`` bool, ``G`` is (numerically) singular: those pixels use
            Lawson–Hanson. no_data: ``(1|P,)`` bool, all observations masked.
        gram_norm: ``(1|P,)`` lower bound of ``‖G‖₂`` (computed here, for the KKT residual);
            gram_diag_max: ``(1|P,)`` ``max_m G_mm``.

    The constructor signature is stable (``HSIReconstructor`` builds it from its buffers).
    """

    def __init__(
        self,
        A: Tensor,
        mask: Tensor | None,
        beta: float,
        diff_order: int,
        gram: Tensor,
        gram_inv: Tensor,
        singular: Tensor,
        no_data: Tensor,
    ) -> None:
        self.A = A
        self.mask = mask
        self.beta = beta
        self.diff_order = diff_order
        self.gram = gram
        self.gram_inv = gram_inv
        self.singular = singular
        self.no_data = no_data
        self._admm_cache: dict[str, tuple[Tensor, Tensor]] = {}
        with torch.no_grad():  # ‖G‖₂ bound per pixel, the KKT residual's scale (chunked temps)
            n = 65536
            self.gram_norm = torch.cat(
                [_gram_norm(gram[s:s + n]) for s in range(0, gram.shape[0], n)]
            )
            self.gram_diag_max = gram.diagonal(dim1=1, dim2=2).amax(1)

    # -- shapes -----------------------------------------------------------------------------
    @property
    def num_pixels(self) -> int | None:
        """``P``, or ``None`` when ``A`` is shared and unmasked (any ``P`` is accepted)."""
        if self.mask is not None:
            return self.mask.shape[0]
        return self.A.shape[0] if self.A.shape[0] > 1 else None

    @property
    def num_obs(self) -> int:
        return self.A.shape[1]

    @property
    def num_bands(self) -> int:
        return self.A.shape[2]

    @property
    def dtype(self) -> torch.dtype:
        return self.A.dtype

    @property
    def device(self) -> torch.device:
        return self.A.device

    def _check_y(self, y: Tensor) -> Tensor:
        if not isinstance(y, Tensor):
            raise TypeError(f"y must be a torch.Tensor, got {type(y).__name__}")
        if y.ndim != 2 or y.shape[1] != self.num_obs:
            raise ValueError(f"y must have shape (P, {self.num_obs}), got {tuple(y.shape)}")
        p = self.num_pixels
        if p is not None and y.shape[0] != p:
            raise ValueError(f"y has {y.shape[0]} pixels but the problem has {p}")
        if y.device != self.device:
            raise ValueError(f"y is on {y.device} but A is on {self.device}")
        if not y.is_floating_point():
            raise TypeError(f"y must be floating point, got {y.dtype}")
        return y.to(self.dtype)

    def _masked_y(self, y: Tensor, sl: slice) -> Tensor:
        """``y`` of the pixels ``sl`` with 0 where the mask is False (NaN-safe)."""
        yc = y[sl]
        w = _take(self.mask, sl)
        if w is not None:
            yc = torch.where(w, yc, torch.zeros((), dtype=yc.dtype, device=yc.device))
        return yc

    def _rhs(self, y: Tensor, sl: slice) -> Tensor:
        """``b = Aᵀ W y`` for the pixels ``sl`` -> ``(n, M)``."""
        return _rowvec(self._masked_y(y, sl), _take(self.A, sl))

    # -- solve ------------------------------------------------------------------------------
    def solve(
        self,
        y: Tensor,
        *,
        method: str = "active_set",
        tol: float | None = None,
        max_iter: int | None = None,
        refine: int | None = None,
        chunk_size: int | None = None,
        max_memory: int | None = None,
        x0: Tensor | None = None,
        admm_iters: int | None = None,
        rho: float | None = None,
        num_threads: int | None = None,
    ) -> NNLSResult:
        """Solve all pixels for observations ``y``.

        Args:
            y: ``(P, O)`` observations (same device as ``A``; cast to ``A``'s dtype).
            method: ``"active_set"`` (exact) or ``"admm"``.
            tol: active set: tolerance on the KKT residual (a backward error, see
                :class:`NNLSResult`), default ``M·eps(dtype)``; ADMM: relative primal/dual
                residual tolerance (``‖x − z‖∞`` and ``‖z − z_prev‖∞`` over ``‖z‖∞``), default
                ``sqrt(eps)``.
            max_iter: active set: exchange rounds (at most 16, then Lawson–Hanson) and
                Lawson–Hanson iterations (default ``10·M``); ADMM: iterations in the
                tolerance-driven mode (default 5000).
            refine: at most this many steps of iterative refinement (on the final zero set), only
                for pixels whose KKT residual exceeds ``tol`` (default 2).
            chunk_size / max_memory: pixels per chunk, or a working-memory budget in bytes.
            x0: ``(P, M)`` ADMM warm start (e.g. the previous frame's solution).
            admm_iters: run exactly this many ADMM iterations (no data-dependent stopping,
                differentiable w.r.t. ``y``). Ignored by the active-set method.
            rho: ADMM penalty; default per pixel ``trace(G)/M``.
            num_threads: CPU threads (default ``torch.get_num_threads()``); each runs
                single-threaded kernels on its share of the pixels, so no kernel waits at a
                thread barrier for a core another process holds (see :func:`_workers`).

        Returns:
            :class:`NNLSResult`. Gradients flow only in the fixed-iteration ADMM mode.
        """
        workers = _workers(self.device, num_threads)
        with cpu_threads(self.device, 1):
            return self._solve(y, method, tol, max_iter, refine, chunk_size, max_memory, x0,
                               admm_iters, rho, workers)

    def _solve(
        self, y: Tensor, method: str, tol: float | None, max_iter: int | None,
        refine: int | None, chunk_size: int | None, max_memory: int | None, x0: Tensor | None,
        admm_iters: int | None, rho: float | None, workers: int,
    ) -> NNLSResult:
        if method not in _METHODS:
            raise ValueError(f"method must be one of {_METHODS}, got {method!r}")
        y = self._check_y(y)
        P, m = y.shape[0], self.num_bands
        if P == 0:
            return _empty_result(m, self.dtype, self.device, method)
        if tol is None:
            tol = _default_tol(self.dtype, m) if method == "active_set" else _admm_tol(self.dtype)
        tol = float(tol)
        if not tol > 0:
            raise ValueError(f"tol must be > 0, got {tol}")
        if refine is None:
            refine = 2
        if int(refine) < 0:
            raise ValueError(f"refine must be >= 0, got {refine}")
        if x0 is not None and (x0.shape != (P, m) or x0.device != self.device):
            raise ValueError(f"x0 must have shape ({P}, {m}) on {self.device}, got "
                             f"{tuple(x0.shape)} on {x0.device}")
        if admm_iters is not None and int(admm_iters) < 0:
            raise ValueError(f"admm_iters must be >= 0, got {admm_iters}")
        item = torch.finfo(self.dtype).bits // 8
        if method == "active_set":
            per_px = item * (2 * self.num_obs + 16 * m + 3 * m * m)
            n = _chunk_len(P, per_px, chunk_size, max_memory, self.device,
                           default=_default_stream_chunk(self.device))
            n_corr = _chunk_len(P, per_px, chunk_size, max_memory, self.device,
                                default=_default_solve_chunk(self.device))
            with torch.no_grad():
                out = self._solve_as(y, tol, max_iter or 10 * m, int(refine), n, n_corr,
                                     workers)
            return NNLSResult(*out, method)
        per_px = item * (2 * self.num_obs + 16 * m + 4 * m * m)
        n = _chunk_len(P, per_px, chunk_size, max_memory, self.device)
        outs = []
        for s in range(0, P, n):
            sl = slice(s, min(P, s + n))
            fixed = admm_iters is not None
            with torch.set_grad_enabled(fixed and torch.is_grad_enabled()):
                outs.append(self._solve_chunk_admm(
                    y, sl, tol, max_iter or 5000, admm_iters, rho,
                    None if x0 is None else x0[sl]))
        cat = [torch.cat([o[i] for o in outs]) for i in range(5)]
        return NNLSResult(cat[0], cat[1], cat[2], cat[3], cat[4], method)

    def _chunk_parts(self, sl: slice, n: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        G = _take(self.gram, sl)
        Gi = _take(self.gram_inv, sl)
        sing = _expand_rows(_take(self.singular, sl), n)
        nod = _expand_rows(_take(self.no_data, sl), n)
        return G, Gi, sing, nod

    def _finish(
        self, G: Tensor, b: Tensor, x: Tensor, nod: Tensor, done: Tensor, tol: float
    ) -> tuple[Tensor, Tensor, Tensor]:
        zero = torch.zeros((), dtype=x.dtype, device=x.device)
        x = torch.where(nod.view(-1, 1), zero, x)
        with torch.no_grad():
            r = nnls_kkt_residual(G, b, x.detach())
            r = torch.where(nod, zero, r)
            r = torch.where(torch.isfinite(r), r, torch.full_like(r, float("inf")))
        return x, done & (r <= tol), r

    def _solve_as(
        self, y: Tensor, tol: float, max_iter: int, refine: int, n: int, n_corr: int,
        workers: int,
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """Active-set solve of the whole frame (see the module docstring).

        ``n``: pixels per chunk of the streamed stages; ``n_corr``: pixels per correction batch;
        ``workers``: CPU threads sharing the chunks (1 elsewhere).
        """
        P, m = y.shape[0], self.num_bands
        dev, dt = y.device, self.dtype
        G, H = self.gram, self.gram_inv
        tiny = torch.finfo(dt).tiny
        zero = torch.zeros((), dtype=dt, device=dev)
        gn_all = self.gram_norm
        # 1. right-hand sides and unconstrained solutions x = H b, streamed over pixel chunks
        #    (cache-sized on CPU), with the per-pixel norms the thresholds need
        b = torch.empty((P, m), dtype=dt, device=dev)
        x = torch.empty((P, m), dtype=dt, device=dev)
        bnorm = torch.empty((P,), dtype=dt, device=dev)
        xnorm = torch.empty((P,), dtype=dt, device=dev)
        xneg = torch.empty((P,), dtype=dt, device=dev)

        def stage1(sl: slice) -> None:
            bs, xs = b[sl], x[sl]
            _rowvec(self._masked_y(y, sl), _take(self.A, sl), out=bs)
            _rowvec(bs, _take(H, sl), out=xs)
            bnorm[sl] = _norm2(bs)
            xnorm[sl] = _norm2(xs)
            xneg[sl] = xs.clamp_max(0).sum(1)

        _for_chunks(stage1, P, n, workers)
        # infeasibility threshold in gradient units. x_m·G_mm < −thr for some m needs
        # Σ_m min(x_m, 0) · max_m G_mm < −thr: a cheap test that selects a superset
        thr = (0.25 * tol * (_expand_rows(gn_all, P) * xnorm + bnorm)).clamp_min(tiny)
        need = xneg * _expand_rows(self.gram_diag_max, P) < -thr
        sing = _expand_rows(self.singular, P)
        nod = _expand_rows(self.no_data, P)
        irregular = sing | nod  # x = H b = 0 there (H = 0 or b = 0)
        any_irregular = bool(irregular.any())
        if any_irregular:
            need &= ~irregular
        # 2. exact correction of the pixels with negative entries: one compacted sub-batch
        iters = torch.zeros((P,), dtype=torch.long, device=dev)
        done = torch.ones((P,), dtype=torch.bool, device=dev)
        zset = torch.zeros((P, m), dtype=torch.bool, device=dev)
        redo = sing & ~nod
        idx = need.nonzero().squeeze(1)
        if idx.numel():
            gd = _expand_rows(G.diagonal(dim1=1, dim2=2), P)

            def correct(sl: slice) -> None:
                ic = idx[sl]
                xs, zs, ds, fs, its = _bpp(H, ic, x[ic], gd[ic], thr[ic].unsqueeze(1),
                                           min(max_iter, _BPP_ROUNDS))
                x[ic], zset[ic], done[ic], iters[ic] = xs, zs, ds, its
                redo[ic] |= fs | ~ds

            # split between the workers (each a compacted sub-batch of at most n_corr pixels)
            nw = min(workers, max(1, idx.numel() // 2048))
            _for_chunks(correct, idx.numel(), min(n_corr, -(-idx.numel() // nw)), nw)
        # 3. independent KKT check with the exact G and b (streamed); refine where it fails
        r = torch.empty((P,), dtype=dt, device=dev)

        plain = ~zset.any(1) & ~irregular  # all-free pixels: refined right here, streamed

        def stage3(sl: slice) -> None:
            Gs, Hs, gns, bs = _take(G, sl), _take(H, sl), _take(gn_all, sl), b[sl]
            gd = Gs.diagonal(dim1=1, dim2=2)
            xs = x[sl].clamp_min_(0)
            g = _rowvec(xs, Gs, sub=bs)
            rs = _kkt_ratio(g, xs, gd, gns, bnorm[sl])
            for _ in range(refine):
                fix = ~(rs <= tol) & plain[sl]
                nf = int(fix.sum())
                if nf == 0:
                    break
                if 4 * nf >= fix.numel():  # many: whole chunk, masked
                    xn = (xs - _rowvec(g, Hs)).clamp_min_(0)
                    gn = _rowvec(xn, Gs, sub=bs)
                    rn = _kkt_ratio(gn, xn, gd, gns, bnorm[sl])
                    fix &= rn < rs
                    xs.copy_(torch.where(fix.unsqueeze(1), xn, xs))
                    g = torch.where(fix.unsqueeze(1), gn, g)
                    rs = torch.where(fix, rn, rs)
                    continue
                li = fix.nonzero().squeeze(1)  # few: those rows only
                Gl = Gs if Gs.shape[0] == 1 else Gs[li]
                Hl = Hs if Hs.shape[0] == 1 else Hs[li]
                xl = xs[li]
                xn = (xl - _rowvec(g[li], Hl)).clamp_min_(0)
                gn = _rowvec(xn, Gl, sub=bs[li])
                rn = _kkt_ratio(gn, xn, Gl.diagonal(dim1=1, dim2=2), gns if gns.shape[0] == 1
                                else gns[li], bnorm[sl][li])
                ok = (rn < rs[li]).unsqueeze(1)
                xs[li] = torch.where(ok, xn, xl)
                g[li] = torch.where(ok, gn, g[li])
                rs[li] = torch.minimum(rn, rs[li])
            r[sl] = rs

        _for_chunks(stage3, P, n, workers)
        bad = ~(r <= tol) & ~irregular & ~redo & ~plain
        for _ in range(refine):
            idx = bad.nonzero().squeeze(1)
            if idx.numel() == 0:
                break
            for s in range(0, idx.numel(), n_corr):
                ic = idx[s:s + n_corr]
                xs, rs = self._refine_rows(ic, x[ic], zset[ic], b[ic])
                better = rs < r[ic]
                x[ic] = torch.where(better.view(-1, 1), xs, x[ic])
                r[ic] = torch.where(better, rs, r[ic])
            bad[idx] = ~(r[idx] <= tol)
        # 4. robust fallback: singular G, Cholesky failures, unfinished or still failing pixels
        redo |= ~(r <= tol) & ~irregular
        if any_irregular:
            redo &= ~nod
        idx = redo.nonzero().squeeze(1)
        for s in range(0, idx.numel(), n_corr):
            ic = idx[s:s + n_corr]
            Gs = G if G.shape[0] == 1 else G[ic]
            bs = b[ic]
            thr_s = (tol * 0.25 * bnorm[ic]).clamp_min(tiny).view(-1, 1)
            eps = float(torch.finfo(dt).eps)
            piv_tol = min(eps**0.5, 100.0 * m * eps)
            xs, ds, its = _lawson_hanson(Gs, bs, thr_s, piv_tol, max_iter)
            rs = nnls_kkt_residual(Gs, bs, xs, gn_all if gn_all.shape[0] == 1 else gn_all[ic])
            better = ~(rs >= r[ic])  # keep the earlier answer where it was at least as good
            x[ic] = torch.where(better.view(-1, 1), xs, x[ic])
            done[ic] = torch.where(better, ds, done[ic])
            r[ic] = torch.where(better, rs, r[ic])
            iters[ic] = iters[ic] + its
        if any_irregular:
            x = torch.where(nod.view(-1, 1), zero, x)
            r = torch.where(nod, zero, r)
        r = torch.where(torch.isfinite(r), r, torch.full_like(r, float("inf")))
        return x, done & (r <= tol), iters, r, nod.clone()

    def _refine_rows(
        self, idx: Tensor, x: Tensor, Z: Tensor, b: Tensor
    ) -> tuple[Tensor, Tensor]:
        """One step of iterative refinement on the zero set ``Z`` with the exact ``G``.

        ``x ← x − G_FF⁻¹ g_F`` (``g = Gx − b``; ``G_FF⁻¹`` applied through ``H`` and the ``Z``
        block, :func:`_zero_set_solve`). Returns the refined ``x`` (clamped at 0) and its KKT
        residual.
        """
        G, H = self.gram, self.gram_inv
        Gs = G if G.shape[0] == 1 else G[idx]
        Hs = H if H.shape[0] == 1 else H[idx]
        g = _rowvec(x, Gs) - b
        u = -_rowvec(torch.where(Z, torch.zeros((), dtype=x.dtype, device=x.device), g), Hs)
        d, ok = _zero_set_solve_any(H, idx, Z, u)
        xs = torch.where(ok.view(-1, 1), x + d, x).clamp_min(0)
        gn = self.gram_norm if self.gram_norm.shape[0] == 1 else self.gram_norm[idx]
        return xs, nnls_kkt_residual(Gs, b, xs, gn)

    # -- ADMM ---------------------------------------------------------------------------------
    def _admm_factors(self, rho: float | None) -> tuple[Tensor, Tensor]:
        key = "auto" if rho is None else repr(float(rho))
        if key in self._admm_cache:
            return self._admm_cache[key]
        G = self.gram
        m = self.num_bands
        gd = G.diagonal(dim1=1, dim2=2)
        if rho is None:
            r = gd.mean(1)
            r = torch.where(r > 0, r, torch.ones_like(r))
        else:
            if not float(rho) > 0:
                raise ValueError(f"rho must be > 0, got {rho}")
            r = torch.full((G.shape[0],), float(rho), dtype=G.dtype, device=G.device)
        K = torch.empty_like(G)
        eye = torch.eye(m, dtype=G.dtype, device=G.device)
        n = _chunk_len(G.shape[0], 8 * m * m * G.element_size(), None, None, G.device)
        with torch.no_grad():
            for s in range(0, G.shape[0], n):
                sl = slice(s, s + n)
                L, _ = torch.linalg.cholesky_ex(G[sl] + r[sl].view(-1, 1, 1) * eye)
                K[sl] = torch.cholesky_inverse(L)
        self._admm_cache[key] = (K, r)
        return K, r

    def _solve_chunk_admm(
        self, y: Tensor, sl: slice, tol: float, max_iter: int, admm_iters: int | None,
        rho: float | None, x0: Tensor | None,
    ) -> tuple[Tensor, ...]:
        K, r = self._admm_factors(rho)
        K, r = _take(K, sl), _take(r, sl)
        b = self._rhs(y, sl)
        n, m = b.shape
        dev, dt = b.device, b.dtype
        G, Gi, sing, nod = self._chunk_parts(sl, n)
        r = _expand_rows(r.view(-1, 1), n)
        zero = torch.zeros((), dtype=dt, device=dev)
        if x0 is None:
            z = torch.where((sing | nod).view(-1, 1), zero, _rowvec(b, Gi)).clamp_min(0)
        else:
            z = x0.to(dt).clamp_min(0)
        u = (b - _rowvec(z, G)) / r
        if admm_iters is not None:  # fixed iterations, out of place: differentiable
            for _ in range(int(admm_iters)):
                x = _rowvec(b + r * (z - u), K)
                z = (x + u).clamp_min(0)
                u = u + x - z
            iters = torch.full((n,), int(admm_iters), dtype=torch.long, device=dev)
            done = torch.ones((n,), dtype=torch.bool, device=dev)
            x, conv, res = self._finish(G, b, z, nod, done, tol)
            return x, conv, iters, res, nod.clone()
        # tolerance-driven: iterate on the sub-batch that has not converged
        iters = torch.zeros((n,), dtype=torch.long, device=dev)
        done = torch.zeros((n,), dtype=torch.bool, device=dev)
        act = torch.arange(n, device=dev)
        Ka, ra, ba, za, ua = _expand_rows(K, n), r, b, z, u
        check = 10
        it = 0
        while act.numel() > 0 and it < max_iter:
            z_prev = za
            for _ in range(check):
                x = _rowvec(ba + ra * (za - ua), Ka)
                z_prev = za
                za = (x + ua).clamp_min(0)
                ua = ua + x - za
            it += check
            xs = za.abs().amax(1).clamp_min(torch.finfo(dt).tiny)
            prim = (x - za).abs().amax(1) / xs
            dual = (za - z_prev).abs().amax(1) / xs
            ok = (prim <= tol) & (dual <= tol)
            iters[act] = it
            if bool(ok.any()):
                fin = act[ok]
                z[fin] = za[ok]
                done[fin] = True
                keep = ~ok
                act, Ka, ra = act[keep], Ka[keep], ra[keep]
                ba, za, ua = ba[keep], za[keep], ua[keep]
        if act.numel() > 0:
            z[act] = za
        x, _, res = self._finish(G, b, z, nod, done, tol)
        return x, done | nod, iters, res, nod.clone()


def _empty_result(m: int, dtype: torch.dtype, device: torch.device, method: str) -> NNLSResult:
    """The result for zero pixels: ``x (0, M)`` and empty per-pixel fields."""
    return NNLSResult(
        torch.zeros((0, m), dtype=dtype, device=device),
        torch.zeros((0,), dtype=torch.bool, device=device),
        torch.zeros((0,), dtype=torch.long, device=device),
        torch.zeros((0,), dtype=dtype, device=device),
        torch.zeros((0,), dtype=torch.bool, device=device),
        method,
    )


def prepare_nnls(
    A: Tensor,
    *,
    mask: Tensor | None = None,
    beta: float = 0.0,
    diff_order: int = 1,
    chunk_size: int | None = None,
    max_memory: int | None = None,
    num_threads: int | None = None,
) -> NNLSProblem:
    """Factorise the per-pixel systems once (calibration fixed, only ``y`` changes per frame).

    Args:
        A: ``(O, M)`` shared or ``(P, O, M)`` per-pixel sensing matrices (float32/float64, any
            device, finite).
        mask: ``(P, O)`` bool, ``True`` = observation used; ``None`` = all used.
        beta: smoothness weight ``β ≥ 0`` on ``‖D x‖²`` (data scale, e.g. DN²).
        diff_order: order of ``D`` (0 identity, 1 first difference, 2 second difference).
        chunk_size / max_memory: pixels per chunk or working-memory budget (bytes) for the
            factorisation; the stored result is ``2·P·M²`` floats regardless.
        num_threads: CPU threads (default ``torch.get_num_threads()``); each runs
            single-threaded kernels on its share of the pixels (see :func:`_workers`).

    Returns:
        :class:`NNLSProblem`; call ``.solve(y)`` per frame.

    Example:
        >>> A = torch.rand(1000, 30, 25)
        >>> prob = prepare_nnls(A, beta=1e2)
        >>> res = prob.solve(torch.rand(1000, 30) * 255)
        >>> res.x.shape
        torch.Size([1000, 25])
    """
    A, mask, beta = _check_inputs(A, mask, beta, diff_order)
    workers = _workers(A.device, num_threads)
    with cpu_threads(A.device, 1):
        return _prepare(A, mask, beta, diff_order, chunk_size, max_memory, workers)


def _prepare(
    A: Tensor, mask: Tensor | None, beta: float, diff_order: int, chunk_size: int | None,
    max_memory: int | None, workers: int,
) -> NNLSProblem:
    A3 = A.unsqueeze(0) if A.ndim == 2 else A
    _, o, m = A3.shape
    dev, dt = A3.device, A3.dtype
    with torch.no_grad():
        A3 = A3.detach()
        R = smoothness_gram(m, beta, diff_order, device=dev, dtype=dt)
        shared = A3.shape[0] == 1
        if shared and mask is None:
            P = 1
        else:
            P = mask.shape[0] if shared else A3.shape[0]
        item = A3.element_size()
        n = _chunk_len(P, item * (o * m + 8 * m * m), chunk_size, max_memory, dev)
        gram = torch.empty((P, m, m), dtype=dt, device=dev)
        gram_inv = torch.empty((P, m, m), dtype=dt, device=dev)
        singular = torch.empty((P,), dtype=torch.bool, device=dev)
        no_data = torch.zeros((P,), dtype=torch.bool, device=dev)
        eps = torch.finfo(dt).eps
        outer = (A3[0].unsqueeze(2) * A3[0].unsqueeze(1)).reshape(o, m * m) if shared else None

        def factor(sl: slice) -> None:
            w = None if mask is None else mask[sl]
            G = gram[sl]
            if shared:
                if w is None:
                    G.copy_((A3[0].T @ A3[0]).unsqueeze(0))
                else:
                    torch.mm(w.to(dt), outer, out=G.view(-1, m * m))
            else:
                masked_gram(A3[sl], w, out=G)
            G.add_(R)
            L, info = torch.linalg.cholesky_ex(G)
            gd = G.diagonal(dim1=1, dim2=2)
            ld2 = L.diagonal(dim1=1, dim2=2).square()
            bad = (info != 0) | ~(ld2.amin(1) > 20.0 * m * eps * gd.amax(1))
            bad |= ~torch.isfinite(ld2).all(1)
            any_bad = bool(bad.any())
            if any_bad:
                L = torch.where(bad.view(-1, 1, 1), torch.eye(m, dtype=dt, device=dev), L)
            Gi = gram_inv[sl]
            torch.cholesky_inverse(L, out=Gi)  # exactly symmetric
            if any_bad:
                Gi.masked_fill_(bad.view(-1, 1, 1), 0.0)
            singular[sl] = bad
            if w is not None:
                no_data[sl] = ~w.any(1)

        _for_chunks(factor, P, n, workers)
        singular |= no_data
    return NNLSProblem(A3, mask, beta, diff_order, gram, gram_inv, singular, no_data)


def solve_nnls(
    A: Tensor,
    y: Tensor,
    *,
    beta: float = 0.0,
    mask: Tensor | None = None,
    diff_order: int = 1,
    method: str = "active_set",
    tol: float | None = None,
    max_iter: int | None = None,
    refine: int | None = None,
    chunk_size: int | None = None,
    max_memory: int | None = None,
    x0: Tensor | None = None,
    admm_iters: int | None = None,
    rho: float | None = None,
    num_threads: int | None = None,
) -> NNLSResult:
    """Batched non-negative smoothness-regularised least squares, one problem per pixel.

    ``x_p = argmin_{x ≥ 0} Σ_o mask_po (A_p x − y_p)_o² + beta ‖D x‖²``, ``D`` from
    :func:`hsi_torch.spectral.difference_matrix` (``M``, ``diff_order``).

    Args:
        A: ``(O, M)`` shared or ``(P, O, M)`` per pixel; float32 or float64; any device.
        y: ``(P, O)`` observations (e.g. DN). Entries where ``mask`` is False are ignored (may be
            NaN).
        beta: smoothness weight (≥ 0) on the data's scale.
        mask: ``(P, O)`` bool, True = observation used; None = all.
        diff_order: 0, 1 (default) or 2.
        method: ``"active_set"`` (exact, finite termination) or ``"admm"``.
        tol, max_iter, refine, x0, admm_iters, rho: see :meth:`NNLSProblem.solve`.
        chunk_size / max_memory: pixels per chunk or a working-memory budget in bytes; each chunk
            is factorised and solved on its own, so memory stays bounded (per-pixel ``A``;
            default 131 072 pixels per outer chunk on CPU).
        num_threads: CPU threads (default ``torch.get_num_threads()``), see
            :meth:`NNLSProblem.solve`.

    Returns:
        :class:`NNLSResult` with ``x (P, M)``, ``converged``, ``iterations``, ``kkt_residual``,
        ``no_data``.

    Example:
        >>> A = torch.rand(500, 30, 25, dtype=torch.float64)
        >>> y = torch.einsum("pom,pm->po", A, torch.rand(500, 25, dtype=torch.float64))
        >>> res = solve_nnls(A, y, beta=1e-2)
        >>> bool(res.converged.all()), bool((res.x >= 0).all())
        (True, True)
    """
    A, mask, beta = _check_inputs(A, mask, beta, diff_order)
    if not isinstance(y, Tensor) or y.ndim != 2:
        raise ValueError(f"y must be a (P, O) tensor, got {getattr(y, 'shape', type(y))}")
    P = y.shape[0]
    if A.ndim == 3 and A.shape[0] != P:
        raise ValueError(f"A has {A.shape[0]} pixels (shape {tuple(A.shape)}) but y has {P}")
    if mask is not None and mask.shape[0] != P:
        raise ValueError(f"mask has {mask.shape[0]} pixels but y has {P}")
    if P == 0:  # nothing to solve: empty results of the right shapes
        if method not in _METHODS:
            raise ValueError(f"method must be one of {_METHODS}, got {method!r}")
        return _empty_result(A.shape[-1], A.dtype, A.device, method)
    workers = _workers(A.device, num_threads)
    kw = dict(method=method, tol=tol, max_iter=max_iter, refine=refine, admm_iters=admm_iters,
              rho=rho, num_threads=workers)
    if A.ndim == 2 and mask is None:
        prob = prepare_nnls(A, beta=beta, diff_order=diff_order,
                            num_threads=workers)
        return prob.solve(y, chunk_size=chunk_size, max_memory=max_memory, x0=x0, **kw)
    o, m = A.shape[-2:]
    item = A.element_size()
    # the factorisation of one outer chunk is held while it is solved: 2·M² floats a pixel
    per_px = item * (o * m + 8 * m * m + 2 * o + 16 * m)
    n = _chunk_len(P, per_px, chunk_size, max_memory, A.device,
                   default=_default_solve_chunk(A.device))
    inner = n if chunk_size is not None or max_memory is not None else None
    parts: list[NNLSResult] = []
    for s in range(0, P, n):
        sl = slice(s, min(P, s + n))
        prob = prepare_nnls(A if A.ndim == 2 else A[sl],
                            mask=None if mask is None else mask[sl], beta=beta,
                            diff_order=diff_order, chunk_size=inner,
                            num_threads=workers)
        parts.append(prob.solve(y[sl], chunk_size=inner, x0=None if x0 is None else x0[sl],
                                **kw))
    return NNLSResult(
        torch.cat([r.x for r in parts]),
        torch.cat([r.converged for r in parts]),
        torch.cat([r.iterations for r in parts]),
        torch.cat([r.kkt_residual for r in parts]),
        torch.cat([r.no_data for r in parts]),
        method,
    )


def synthetic_brf_problem(
    num_pixels: int,
    *,
    grid: SpectralGrid = DEFAULT_GRID,
    num_views: int = 10,
    opd_range_nm: tuple[float, float] = (1500.0, 6000.0),
    mask_fraction: float = 0.1,
    noise_dn: float = 1.0,
    peak_dn: float = 255.0,
    shared: bool = False,
    spectra: str = "bumps",
    seed: int = 0,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """A realistic random test/benchmark problem with the camera's sensing structure.

    ``A_p[(v, c), m] = g_v(p) · T_v(p, λ_m) · Δλ_m · φ^c(λ_m)`` with BRF-like transmittances
    ``T = ½[1 − cos(2π·OPD/λ)]`` (view OPDs spread over ``opd_range_nm``, ±2 % per pixel unless
    ``shared``), smooth Gaussian "RGB" curves ``φ^c`` (peaks 600/540/460 nm), per-pixel gains
    0.6…1 (1 when ``shared``). ``A`` is scaled so that a white reflectance (1 in every band) gives
    at most about ``peak_dn``. Spectra (times a brightness 0.03…1):

    * ``spectra="bumps"`` (hard case): 1–3 Gaussian bumps on a small floor, normalised to peak 1
      — many bands near 0, so ~30 % of the pixels need the active-set correction;
    * ``spectra="reflectance"`` (realistic): random convex mixtures of 2–3 of the 24 ColorChecker
      reflectances (:func:`hsi_torch.refdata.colorchecker_reflectances`) lit by CIE D65,
      normalised to peak 1 — smooth and positive in every band, like real scenes.

    ``y = A x + N(0, noise_dn²)``; ``mask`` drops a random
    ``mask_fraction`` of the observations and every observation above ``peak_dn`` (saturation).
    Generated in float64 in chunks (memory ≈ the outputs), then cast.

    Returns:
        ``A`` ``(P, 3V, M)`` (``(3V, M)`` when ``shared``), ``y (P, 3V)``, ``mask (P, 3V)`` bool,
        ``x_true (P, M)``, in ``dtype`` on ``device``.
    """
    if num_pixels < 1 or num_views < 1:
        raise ValueError(f"need num_pixels >= 1 and num_views >= 1, got {num_pixels}, {num_views}")
    gen = torch.Generator().manual_seed(int(seed))
    f64 = torch.float64
    lam = grid.wavelengths(dtype=f64)
    dl = grid.band_widths(dtype=f64)
    m, v, P = lam.numel(), num_views, num_pixels
    opd = torch.linspace(opd_range_nm[0], opd_range_nm[1], v, dtype=f64)
    opd = opd[torch.randperm(v, generator=gen)].view(1, v, 1)
    centres = torch.tensor([600.0, 540.0, 460.0], dtype=f64).view(3, 1)
    widths = torch.tensor([40.0, 40.0, 30.0], dtype=f64).view(3, 1)
    phi_dl = (dl * torch.exp(-0.5 * ((lam - centres) / widths) ** 2)).view(1, 1, 3, m)

    def sensing(n: int, jitter: bool) -> Tensor:
        rnd = torch.rand(n, v, 1, generator=gen, dtype=f64) if jitter else torch.full(
            (n, v, 1), 0.5, dtype=f64)
        trans = 0.5 * (1 - torch.cos(2 * torch.pi * opd * (1 + 0.02 * (2 * rnd - 1)) / lam))
        gain = 0.6 + 0.4 * torch.rand(n, v, 1, 1, generator=gen, dtype=f64) if jitter else 1.0
        return (gain * trans.unsqueeze(2) * phi_dl).reshape(n, 3 * v, m)

    if spectra not in ("bumps", "reflectance"):
        raise ValueError(f"spectra must be 'bumps' or 'reflectance', got {spectra!r}")
    scale = peak_dn / float(sensing(1, False).sum(2).amax())
    t = (lam - lam[0]) / (lam[-1] - lam[0])
    if spectra == "reflectance":
        from hsi_torch.refdata import colorchecker_reflectances, illuminant

        refl, _ = colorchecker_reflectances(lam)
        lit = refl.to(f64) * illuminant("D65", lam).to(f64)  # (24, M)
    A_shared = sensing(1, False)[0] * scale if shared else None
    outs: list[list[Tensor]] = [[], [], [], []]
    for s in range(0, P, 16384):
        n = min(P, s + 16384) - s
        a = A_shared.expand(n, -1, -1) if shared else sensing(n, True) * scale
        if spectra == "bumps":
            c = torch.rand(n, 3, 1, generator=gen, dtype=f64) * 1.2 - 0.1
            w = 0.08 + 0.3 * torch.rand(n, 3, 1, generator=gen, dtype=f64)
            h = torch.rand(n, 3, 1, generator=gen, dtype=f64)
            h = h * (torch.rand(n, 3, 1, generator=gen, dtype=f64) < 0.8)
            x = (h * torch.exp(-0.5 * ((t - c) / w) ** 2)).sum(1)
            x = x + 0.05 * torch.rand(n, 1, generator=gen, dtype=f64)
        else:
            pick = torch.randint(0, lit.shape[0], (n, 3), generator=gen)
            wts = -torch.log(torch.rand(n, 3, generator=gen, dtype=f64).clamp_min(1e-12))
            wts = wts * (torch.rand(n, 3, generator=gen, dtype=f64) < 0.8)
            wts[:, 0] += 1e-3  # at least one patch
            x = (wts.unsqueeze(2) * lit[pick]).sum(1) / wts.sum(1, keepdim=True)
        x = x / x.amax(1, keepdim=True).clamp_min(1e-12)
        x = x * (0.03 + 0.97 * torch.rand(n, 1, generator=gen, dtype=f64))
        y = torch.bmm(a, x.unsqueeze(2)).squeeze(2)
        y = y + noise_dn * torch.randn(n, 3 * v, generator=gen, dtype=f64)
        mk = (torch.rand(n, 3 * v, generator=gen, dtype=f64) >= mask_fraction) & (y <= peak_dn)
        for lst, val in zip(outs, (a, y, mk, x), strict=True):
            if not (shared and val is a):
                lst.append(val.to(device=device, dtype=dtype if val.is_floating_point() else None))
    A = A_shared.to(device=device, dtype=dtype) if shared else torch.cat(outs[0])
    return A, torch.cat(outs[1]), torch.cat(outs[2]), torch.cat(outs[3])
