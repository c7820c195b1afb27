"""The TV operators on the active-pixel grid: gradient, its adjoint, the brightness weighting
``K``, the vectorial TV and its proximal operator under ``z ≥ 0`` (out of place, differentiable,
and in place for the tolerance-driven solve).

TV is the *vectorial* (coupled across bands) isotropic total variation on the active-pixel grid,
with forward differences between 4-neighbours that are both active:

    ``TV(s) = Σ_{i,j} sqrt( Σ_m (s[m,i,j+1] − s[m,i,j])² + (s[m,i+1,j] − s[m,i,j])² )``

(a difference is 0 when either pixel is inactive; edges of the valid region are free). With a
brightness weight ``α < 1`` the TV is ``Σ‖K ∇s‖`` (:func:`brightness_weighted`).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = [
    "grid_edges",
    "grid_gradient",
    "grid_gradient_adjoint",
    "brightness_weighted",
    "total_variation",
    "prox_tv_nonneg",
]


def grid_edges(active: Tensor) -> tuple[Tensor, Tensor]:
    """Edge masks of the active-pixel grid.

    Args:
        active: ``(h, w)`` bool.

    Returns:
        ``ex (h, w)``: pixel ``(i, j)`` and its right neighbour ``(i, j+1)`` are both active
        (False in the last column); ``ey (h, w)``: ``(i, j)`` and ``(i+1, j)`` both active (False
        in the last row).
    """
    if active.ndim != 2:
        raise ValueError(f"active must be (h, w), got {tuple(active.shape)}")
    a = active.bool()
    ex = torch.zeros_like(a)
    ey = torch.zeros_like(a)
    ex[:, :-1] = a[:, :-1] & a[:, 1:]
    ey[:-1, :] = a[:-1, :] & a[1:, :]
    return ex, ey


def grid_gradient(cube: Tensor, ex: Tensor, ey: Tensor) -> Tensor:
    """Forward differences on the active grid: ``(…, M, h, w)`` → ``(…, 2, M, h, w)``.

    ``[0]`` along x (columns), ``[1]`` along y (rows); 0 where an edge is inactive.
    """
    zero = torch.zeros((), dtype=cube.dtype, device=cube.device)
    dx = torch.nn.functional.pad(cube[..., :, 1:] - cube[..., :, :-1], (0, 1))
    dy = torch.nn.functional.pad(cube[..., 1:, :] - cube[..., :-1, :], (0, 0, 0, 1))
    if ex.dtype == torch.bool:
        return torch.stack([torch.where(ex, dx, zero), torch.where(ey, dy, zero)], dim=-4)
    return torch.stack([dx * ex, dy * ey], dim=-4)  # edge weights


def grid_gradient_adjoint(p: Tensor, ex: Tensor, ey: Tensor) -> Tensor:
    """Adjoint of :func:`grid_gradient`: ``(…, 2, M, h, w)`` → ``(…, M, h, w)`` (= −divergence)."""
    zero = torch.zeros((), dtype=p.dtype, device=p.device)
    if ex.dtype == torch.bool:
        px = torch.where(ex, p[..., 0, :, :, :], zero)
        py = torch.where(ey, p[..., 1, :, :, :], zero)
    else:  # edge weights
        px, py = p[..., 0, :, :, :] * ex, p[..., 1, :, :, :] * ey
    out = -px - py
    out = out + torch.nn.functional.pad(px[..., :, :-1], (1, 0))
    return out + torch.nn.functional.pad(py[..., :-1, :], (0, 0, 1, 0))


def _brightness_weight_(g: Tensor, alpha: float) -> Tensor:
    """:func:`brightness_weighted` of ``g (2, M, h, w)`` in place (bands along dim 1)."""
    return g.add_(g.sum(1, keepdim=True), alpha=(alpha - 1.0) / g.shape[1])


def brightness_weighted(g: Tensor, brightness_weight: float | Tensor, dim: int = -3) -> Tensor:
    """``K g`` with ``K = I − (1 − α) u uᵀ``, ``u = (1, …, 1)/√M`` along ``dim`` (the bands):
    the flat-spectrum (brightness) component of every band vector scaled by ``α``, the rest
    (the spectral shape) kept. Symmetric, ``‖K‖ = max(1, α)``. Out of place."""
    if not isinstance(brightness_weight, Tensor) and float(brightness_weight) == 1.0:
        return g
    m = g.shape[dim]
    return g + ((brightness_weight - 1.0) / m) * g.sum(dim, keepdim=True)


def total_variation(cube: Tensor, active: Tensor, brightness_weight: float = 1.0) -> Tensor:
    """Vectorial isotropic TV of ``cube (…, M, h, w)`` on the ``active (h, w)`` grid → ``(…)``.

    ``Σ_{i,j} sqrt(Σ_m dx² + dy²)`` over forward differences between active 4-neighbours
    (inactive pixels may hold anything, NaN included); with ``brightness_weight`` ``α ≠ 1`` the
    differences are weighted by :func:`brightness_weighted` first (``Σ ‖K ∇s‖``).

    Differentiable: where a pixel's difference vector is 0 (a flat patch) its term contributes
    the subgradient 0, not the NaN of ``sqrt`` at 0.
    """
    if active.shape != cube.shape[-2:]:
        raise ValueError(f"active must be (h, w) = {tuple(cube.shape[-2:])} of the cube "
                         f"{tuple(cube.shape)}, got {tuple(active.shape)}")  # fmt: skip
    ex, ey = grid_edges(active.to(cube.device))
    zero = torch.zeros((), dtype=cube.dtype, device=cube.device)
    c = torch.where(active.to(cube.device), cube, zero)
    g = brightness_weighted(grid_gradient(c, ex, ey), brightness_weight)
    sq = g.square().sum((-4, -3))
    flat = sq == 0  # sqrt's derivative is infinite at 0: keep the graph away from it there
    return torch.where(flat, zero, torch.where(flat, torch.ones_like(sq), sq).sqrt()).sum((-2, -1))


#: ``‖D‖² ≤ 8`` on the 2-D grid (``‖K‖ ≤ 1``, edge weights ``≤ 1``): the dual step of the fast
#: gradient projection is ``1 / (8t)`` (:func:`fgp_dual_step`).
GRADIENT_NORM_BOUND_SQ = 8.0


def fgp_dual_step(t: float | Tensor) -> float | Tensor:
    """The FGP dual step ``1 / (8t)`` of the prox with weight ``t > 0`` (every backend)."""
    return 1.0 / (GRADIENT_NORM_BOUND_SQ * t)


def fista_momentum(k: float) -> tuple[float, float]:
    """FISTA's next ``k' = (1 + sqrt(1 + 4k²)) / 2`` and the extrapolation weight ``(k − 1)/k'``
    (every backend of the prox; ``k = 1`` at the start of a prox)."""
    k_new = (1.0 + math.sqrt(1.0 + 4.0 * k * k)) / 2.0
    return k_new, (k - 1.0) / k_new


def _project_unit(p: Tensor) -> Tensor:
    """Project every pixel's ``(2, M)`` dual vector onto the unit ball (out of place)."""
    n2 = p.square().sum((-4, -3), keepdim=True)
    return p * n2.clamp_min(1.0).rsqrt()  # no sqrt at 0: finite gradients


def prox_tv_nonneg(
    v: Tensor,
    t: float | Tensor,
    ex: Tensor,
    ey: Tensor,
    iters: int,
    p0: Tensor | None = None,
    nonneg: bool = True,
    brightness_weight: float = 1.0,
) -> tuple[Tensor, Tensor]:
    """``argmin_{z ≥ 0} ½‖z − v‖² + t·TV(z)`` by fast gradient projection on the dual.

    Beck & Teboulle's FGP: ``z(p) = max(v − t Dᵀp, 0)``, ``p ← Π(r + D z(r) / (8t))`` with FISTA
    extrapolation ``r`` (``‖D‖² ≤ 8`` in 2-D), ``Π`` the projection of each pixel's ``(2, M)``
    vector onto the unit ball. With ``brightness_weight`` ``α ≤ 1`` the operator is ``K D``
    (:func:`brightness_weighted`, ``‖K‖ = 1``: same step). Out of place (differentiable).

    Args:
        v: ``(M, h, w)``; t: ``> 0`` (a float or a 0-d tensor); ex, ey: :func:`grid_edges`.
        iters: dual iterations; p0: ``(2, M, h, w)`` dual warm start (``None``: 0).
        nonneg: project on ``z ≥ 0`` (else plain TV denoising).
        brightness_weight: ``α`` in ``(0, 1]`` (1: plain vectorial TV).

    Returns:
        ``z (M, h, w)`` and the final dual ``p (2, M, h, w)``.
    """
    p = torch.zeros((2, *v.shape), dtype=v.dtype, device=v.device) if p0 is None else p0
    step = fgp_dual_step(t)

    def primal(q: Tensor) -> Tensor:
        z = v - t * grid_gradient_adjoint(brightness_weighted(q, brightness_weight), ex, ey)
        return z.clamp_min(0) if nonneg else z

    r, k = p, 1.0
    for _ in range(int(iters)):
        g = brightness_weighted(grid_gradient(primal(r), ex, ey), brightness_weight)
        p_new = _project_unit(r + step * g)
        k_new, mom = fista_momentum(k)
        r = p_new + mom * (p_new - p)
        p, k = p_new, k_new
    return primal(p), p


class _ProxWorkspace:
    """Buffers of the in-place TV prox (no autograd): the tolerance-driven solve runs thousands
    of cube-sized passes, and out-of-place ops would allocate a cube for each."""

    def __init__(self, shape: tuple[int, ...], ex: Tensor, ey: Tensor, dtype: torch.dtype,
                 device: torch.device, brightness_weight: float = 1.0) -> None:
        self.alpha = float(brightness_weight)
        self.kq = None if self.alpha == 1.0 else torch.empty((2, *shape), dtype=dtype,
                                                               device=device)
        self.p = torch.zeros((2, *shape), dtype=dtype, device=device)
        self.p_new = torch.empty_like(self.p)
        self.r = torch.empty_like(self.p)
        self.g = torch.empty_like(self.p)
        self.z = torch.empty(shape, dtype=dtype, device=device)
        self.weighted = ex.dtype != torch.bool
        self.wq = torch.empty_like(self.p) if self.weighted else self.p
        self.n2 = torch.empty((1, 1, *shape[-2:]), dtype=dtype, device=device)
        self.ex = ex.to(dtype)
        self.ey = ey.to(dtype)

    def primal(self, v: Tensor, t: float, q: Tensor, nonneg: bool) -> Tensor:
        """``z = max(v − t Dᵀq, 0)`` into :attr:`z` (``q`` is 0 off the edges)."""
        z = self.z
        if self.kq is not None:  # (K D)ᵀ = Dᵀ K
            q = _brightness_weight_(self.kq.copy_(q), self.alpha)
        if self.weighted:  # Dᵀ of the weighted gradient: weights first
            torch.mul(q[0], self.ex, out=self.wq[0])
            torch.mul(q[1], self.ey, out=self.wq[1])
            q = self.wq
        px, py = q[0], q[1]
        torch.add(px, py, out=z)  # Dᵀq = −px − py + shifted px, py
        z[:, :, 1:] -= px[:, :, :-1]
        z[:, 1:, :] -= py[:, :-1, :]
        z.mul_(t).add_(v)  # v − t Dᵀq
        return z.clamp_min_(0) if nonneg else z

    def gradient(self, z: Tensor) -> Tensor:
        """``D z`` into :attr:`g`."""
        g = self.g
        torch.sub(z[:, :, 1:], z[:, :, :-1], out=g[0, :, :, :-1])
        g[0, :, :, -1] = 0
        torch.sub(z[:, 1:, :], z[:, :-1, :], out=g[1, :, :-1, :])
        g[1, :, -1, :] = 0
        g[0].mul_(self.ex)
        g[1].mul_(self.ey)
        return g if self.alpha == 1.0 else _brightness_weight_(g, self.alpha)

    def prox(self, v: Tensor, t: float, iters: int, nonneg: bool = True) -> Tensor:
        """:func:`prox_tv_nonneg` in place, warm-started from the last call's dual."""
        step = fgp_dual_step(t)
        p, p_new, r = self.p, self.p_new, self.r
        r.copy_(p)
        k = 1.0
        for _ in range(int(iters)):
            g = self.gradient(self.primal(v, t, r, nonneg))
            torch.add(r, g, alpha=step, out=p_new)
            torch.sum(p_new.square(), dim=(0, 1), keepdim=True, out=self.n2)
            p_new.mul_(self.n2.clamp_min_(1.0).rsqrt_())
            k_new, mom = fista_momentum(k)
            # r = p_new + ((k − 1)/k_new)(p_new − p); then p ← p_new
            torch.sub(p_new, p, out=r)
            r.mul_(mom).add_(p_new)
            p.copy_(p_new)
            k = k_new
        return self.primal(v, t, p, nonneg)


