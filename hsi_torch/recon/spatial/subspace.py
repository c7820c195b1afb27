"""The TV prior on a spectral subspace: the spatial solve in ``k`` channels instead of ``M``.

Natural spectra hold far fewer dimensions than the ``M`` bands. With an orthonormal basis
``U (M, k)`` of the frame's leading spectral components, the prior is put on the coefficients
``c_p = Uᵀ s_p`` only, and the complement of every pixel is left to its own data term:

    ``min_s  Σ_p q_p(s_p) + λ · TV_α(Uᵀ s)``,   ``q_p(s) = sᵀG_p s − 2 b_pᵀ s``

(the per-pixel terms of :func:`~.admm.solve_spatial`). For ``U = I`` the TV is the vectorial
TV of the full-band problem; for ``k < M`` it is that TV of the projection onto the subspace.
``U`` always holds the flat spectrum (the first component) and is rotated so that
``Uᵀ(1, …, 1)/√M = (1, …, 1)/√k``: the brightness weighting ``K = I − (1 − α) u uᵀ`` of the
coefficients is then the same band-sum formula with ``k`` bands.

Solved in two steps:

1. **The subspace problem, without the bound.** Minimising ``q_p`` over the complement of ``U``
   leaves a ``k``-variable quadratic per pixel, ``cᵀS_p c − 2 b̃_pᵀ c`` with the Schur
   complement ``S_p = (Uᵀ G_p⁻¹ U)⁻¹`` and ``b̃_p = S_p Uᵀ G_p⁻¹ b_p`` (one batched product with
   the stored per-pixel ``G⁻¹``), so the spatial problem is the ADMM of :mod:`.admm` on ``k``
   channels (the compiled kernels, ``(S_p + ρI)⁻¹`` packed, the same ``ρ`` as the full-band
   problem), without the projection onto ``z ≥ 0`` (a coefficient may be negative),
   warm-started from ``Uᵀ G_p⁻¹ b_p`` (the minimiser for ``λ = 0``, so ``λ = 0`` returns the
   per-pixel NNLS answer). Its answer ``c`` determines the TV's pull on every pixel,
   ``φ_p = b̃_p − S_p c_p`` (``= (λ/2)·(KD)ᵀp`` at the optimum: a vector of the subspace).
2. **Non-negativity, exact per pixel.** Each pixel then solves its own NNLS with that pull held
   fixed: ``min_{s ≥ 0} q_p(s) + 2 (U φ_p)ᵀ s``, i.e. the per-pixel solver with the right-hand
   side ``b_p − U φ_p`` (the compiled active-set kernel, KKT-exact). A pixel whose
   unconstrained answer ``G_p⁻¹(b_p − U φ_p)`` is non-negative keeps it; where every pixel's
   is, the result is also the minimiser of the problem above with ``s ≥ 0``. Elsewhere the
   bound is enforced with the TV's pull of step 1 held fixed (not re-balanced against the
   neighbours): a deviation from the full-band problem's minimiser.

Cost per ADMM iteration: ``k(k + 1)/2`` numbers of the packed inverse and ``k`` channels of
dual iterations per pixel instead of ``M(M + 1)/2`` and ``M``; the extra work per frame is the
basis (an ``M × M`` covariance of the per-pixel answers), ``G⁻¹U`` and ``S`` (batched
products with ``G⁻¹``), the factor of ``S + ρI`` (``k × k`` per pixel), and the second
per-pixel NNLS pass. Measured (``docs/spatial.md``, "Spectral subspace"): the scores of the
full-band solve need ``k`` close to ``M``, and with the basis chosen per frame its set-up
costs more than the iterations save, so it is an option (``spectral_rank``), not the default.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch
from torch import Tensor

from hsi_torch.recon.nnls import _compiled as nnls_compiled
from hsi_torch.recon.spatial.problem import ShiftedInverse, SpatialProblem

__all__ = ["spectral_basis", "SubspaceProblem", "subspace_problem", "restore_nonneg"]


def spectral_basis(x: Tensor, k: int, active: Tensor | None = None) -> Tensor:
    """An orthonormal basis ``U (M, k)`` of the leading spectral components of ``x``.

    The first direction is the flat spectrum ``u = (1, …, 1)/√M``; the other ``k − 1`` are the
    leading eigenvectors of ``Σ_p r_p r_pᵀ`` over the ``active`` pixels, ``r_p`` the part of
    ``x_p`` orthogonal to ``u`` (uncentred: the components carrying the most energy). The basis
    is then rotated within its span (a Householder reflection) so that ``Uᵀu = (1, …, 1)/√k``.

    Args:
        x: ``(P, M)`` spectra (the frame's per-pixel answers); k: ``1 ≤ k ≤ M``;
            active: ``(P,)`` bool, the pixels used (default all).

    Returns:
        ``(M, k)``, ``x``'s dtype and device, ``UᵀU = I``.
    """
    if x.ndim != 2:
        raise ValueError(f"x must be (P, M), got {tuple(x.shape)}")
    m = x.shape[1]
    if not 1 <= int(k) <= m:
        raise ValueError(f"the subspace rank k must be in [1, {m}], got {k}")
    k = int(k)
    xd = (x if active is None else x[active]).detach().to(torch.float64)
    u = torch.full((m,), 1.0 / math.sqrt(m), dtype=torch.float64, device=x.device)
    r = xd - (xd @ u).unsqueeze(1) * u
    return _rotated_basis(r.T @ r, k, x.dtype)


def _rotated_basis(cov: Tensor, k: int, dtype: torch.dtype) -> Tensor:
    """The flat spectrum and the ``k − 1`` leading eigenvectors of ``cov`` on its complement,
    rotated so that ``Uᵀu = (1, …, 1)/√k``."""
    m = cov.shape[0]
    u = torch.full((m,), 1.0 / math.sqrt(m), dtype=torch.float64, device=cov.device)
    proj = torch.eye(m, dtype=torch.float64, device=cov.device) - torch.outer(u, u)
    _, vec = torch.linalg.eigh(proj @ cov @ proj)
    basis = torch.cat([u.unsqueeze(1), vec[:, m - k + 1 :].flip(1)], 1)  # (M, k)
    basis, _ = torch.linalg.qr(basis)  # orthonormal to rounding
    basis = basis * torch.sign(basis[:, :1].T @ u.unsqueeze(1)).squeeze()  # first column = +u
    target = torch.full((k,), 1.0 / math.sqrt(k), dtype=torch.float64, device=cov.device)
    e1 = torch.zeros(k, dtype=torch.float64, device=cov.device)
    e1[0] = 1.0
    v = e1 - target
    nv = float(v @ v)
    if nv > 1e-30:  # H = I − 2vvᵀ/vᵀv maps e1 to target; U H: Uᵀu = H e1 = target
        basis = basis - 2.0 * torch.outer(basis @ v, v) / nv
    return basis.to(dtype)


@dataclasses.dataclass
class SubspaceProblem:
    """One frame's reduced problem (:func:`subspace_problem`).

    Attributes:
        basis: ``U (M, k)``; problem: the ``k``-channel :class:`~.problem.SpatialProblem`
            (``gram`` = ``S (P, k, k)``, the full-band problem's ``ρ``, grid and edge weights);
        b: ``(P, k)`` the reduced right-hand sides ``b̃``; start: ``(P, k)`` ``Uᵀ G⁻¹ b``, the
            subspace part of every pixel's unconstrained answer (the minimiser for ``λ = 0``:
            the ADMM's warm start); rows: the full-band problem's
            ``row_index`` (pixels with their own Gram matrix in this frame), or ``None``.
    """

    basis: Tensor
    problem: SpatialProblem
    b: Tensor
    start: Tensor
    rows: Tensor | None = None


def _schur(ginv: Tensor, basis: Tensor, b: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``S = (Uᵀ G⁻¹ U)⁻¹`` ``(n, k, k)``, ``b̃ = S c`` and ``c = Uᵀ G⁻¹ b`` ``(n, k)`` (the
    subspace part of the unconstrained per-pixel answer) for ``ginv (n, M, M)`` symmetric,
    ``b (n, M)``."""
    n, m = b.shape
    k = basis.shape[1]
    w = (ginv.reshape(n * m, m) @ basis).reshape(n, m, k)  # G⁻¹U, one GEMM
    c = basis.T.unsqueeze(0) @ w  # (n, k, k)
    c = 0.5 * (c + c.transpose(1, 2))
    c = c.to(torch.float64)
    L, info = torch.linalg.cholesky_ex(c)
    bad = info != 0  # G⁻¹ = 0 (a singular G or no data: the NNLS problem stores 0)
    if bool(bad.any()):
        c[bad] = torch.eye(k, dtype=c.dtype, device=c.device)
        L, _ = torch.linalg.cholesky_ex(c)
    s = torch.cholesky_inverse(L).to(b.dtype)
    c0 = (w.transpose(1, 2) @ b.unsqueeze(2)).squeeze(2)
    bt = (s @ c0.unsqueeze(2)).squeeze(2)
    if bool(bad.any()):  # no data term in the subspace: the TV alone decides c there
        s[bad] = 0
        bt[bad] = 0
    return s, bt, c0


def subspace_problem(
    sp: SpatialProblem,
    ginv: Tensor,
    b: Tensor,
    basis: Tensor,
    row_ginv: Tensor | None = None,
    chunk: int = 16384,
) -> SubspaceProblem:
    """The reduced ``k``-channel problem of one frame (see the module docstring).

    Args:
        sp: the frame's full-band :class:`~.problem.SpatialProblem` (:meth:`~.problem.
            SpatialProblem.for_frame`: its grid, edge weights, ``ρ`` and frame rows are kept);
        ginv: ``(P|1, M, M)`` the per-pixel ``G⁻¹`` (the NNLS problem's ``gram_inv``);
        b: ``(P, M)`` ``AᵀWy``; basis: ``(M, k)`` orthonormal (:func:`spectral_basis`);
        row_ginv: ``(r, M, M)`` ``G⁻¹`` of ``sp.row_index`` (their own Gram matrices in this
            frame); chunk: pixels per batched product (bounds the temporaries).

    Returns:
        :class:`SubspaceProblem`.
    """
    P, m = b.shape
    if basis.ndim != 2 or basis.shape[0] != m:
        raise ValueError(f"basis must be ({m}, k), got {tuple(basis.shape)}")
    if ginv.shape[-2:] != (m, m) or ginv.shape[0] not in (1, P):
        raise ValueError(f"ginv must be ({P}|1, {m}, {m}), got {tuple(ginv.shape)}")
    k = basis.shape[1]
    basis = basis.to(b)
    s = torch.empty((P, k, k), dtype=b.dtype, device=b.device)
    bt = torch.empty((P, k), dtype=b.dtype, device=b.device)
    c0 = torch.empty((P, k), dtype=b.dtype, device=b.device)
    with torch.no_grad():
        for a in range(0, P, chunk):
            e = min(P, a + chunk)
            g = ginv.expand(P, m, m)[a:e] if ginv.shape[0] == 1 else ginv[a:e]
            s[a:e], bt[a:e], c0[a:e] = _schur(g.contiguous(), basis, b[a:e])
        if sp.row_index is not None:
            if row_ginv is None or row_ginv.shape != (sp.row_index.shape[0], m, m):
                raise ValueError("row_ginv must hold G⁻¹ of the frame's own rows (sp.row_index)")
            rs, rb, rc = _schur(row_ginv.contiguous(), basis, b.index_select(0, sp.row_index))
            s.index_copy_(0, sp.row_index, rs)
            bt.index_copy_(0, sp.row_index, rb)
            c0.index_copy_(0, sp.row_index, rc)
    red = dataclasses.replace(
        sp, gram=s, factor=ShiftedInverse(s, sp.rho), row_index=None, row_gram=None, row_inv=None
    )
    return SubspaceProblem(basis, red, bt, c0, sp.row_index)


def restore_nonneg(
    sub: SubspaceProblem,
    c: Tensor,
    b: Tensor,
    gram: Tensor,
    ginv: Tensor,
    gram_diag: Tensor,
    gram_norm: Tensor,
    skip: Tensor,
    tol: float,
    rounds: int,
    refine: int,
    num_threads: int,
    row_gram: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """Step 2 of the module docstring: every pixel's NNLS ``min_{s ≥ 0} sᵀG s − 2(b − Uφ)ᵀs``
    with the TV's pull ``φ = b̃ − S c`` of the subspace answer ``c (P, k)`` held fixed (the
    compiled active-set kernel of :mod:`hsi_torch.recon.nnls`, CPU).

    Args:
        gram, ginv: ``(P|1, M, M)``; gram_diag ``(P|1, M)``; gram_norm ``(P|1,)`` (the NNLS
            problem's); skip: ``(P,)`` bool, pixels solved without pivoting (singular or no
            data); tol, rounds, refine: the active-set solve's KKT tolerance, exchange rounds
            and refinement steps; row_gram: ``(r, M, M)`` the frame's own ``G`` of
            ``sub.problem.row_index`` (their NNLS uses it).

    Returns:
        ``x (P, M) ≥ 0`` and the right-hand sides ``b − Uφ (P, M)`` it is the NNLS answer of.
    """
    sp = sub.problem
    phi = sub.b - (sp.gram @ c.unsqueeze(2)).squeeze(2)
    phi = phi * sp.active.unsqueeze(1).to(phi.dtype)  # outside the graph: no pull
    rhs = (b - phi @ sub.basis.T).contiguous()
    x = _nnls(gram, ginv, rhs, gram_diag, gram_norm, skip, tol, rounds, refine, num_threads)
    if sub.rows is not None:  # the frame's own Gram matrices
        rows = sub.rows
        g = row_gram.contiguous()
        gi = torch.cholesky_inverse(torch.linalg.cholesky(g))
        xr = _nnls(
            g,
            gi,
            rhs.index_select(0, rows),
            g.diagonal(dim1=1, dim2=2).contiguous(),
            torch.linalg.matrix_norm(g, 2),
            skip.index_select(0, rows),
            tol,
            rounds,
            refine,
            num_threads,
        )
        x.index_copy_(0, rows, xr)
    return x, rhs


def _nnls(
    gram: Tensor,
    ginv: Tensor,
    rhs: Tensor,
    gd: Tensor,
    gn: Tensor,
    skip: Tensor,
    tol: float,
    rounds: int,
    refine: int,
    num_threads: int,
) -> Tensor:
    out = nnls_compiled.solve_frame_cpu(
        gram.numpy(),
        ginv.numpy(),
        rhs.numpy().copy(),
        gd.numpy(),
        gn.numpy(),
        skip.numpy(),
        float(tol),
        int(rounds),
        int(refine),
        int(num_threads),
    )
    return torch.from_numpy(np.ascontiguousarray(out[0]))
