"""Illumination × sensor response φ^c(λ) and view throughput g_v from white-reference shots.

Model: the white observation of view ``v``, colour ``c`` is
``I_v^c = g_v · b_vᵀ φ^c + ε`` with ``(b_v)_m = B_v(λ_m) Δλ_m``. The estimation alternates:

* **φ-step** (g fixed), for each colour independently and exactly (one batched linear solve)::

      (φ^c, α_c) = argmin Σ_obs w (I^c − g b_vᵀ φ^c)² + β_φ ‖D φ^c‖² + γ_h ‖φ^c − α_c f̃^c‖²

  whose normal equations are ``[[K, −γ f̃], [−γ f̃ᵀ, γ f̃ᵀf̃]] [φ; α] = [Σ w g b I; 0]`` with
  ``K = Σ w g² b bᵀ + β DᵀD + γ I``.
* **g-step** (φ fixed): regularised least squares, either one scalar per view
  (:func:`solve_gain`, ridge towards 1) or a smooth field g_v(p) (:func:`fit_gain_field`: a 2-D
  Legendre polynomial of total degree ≤ ``degree`` on the reference frame, with a ridge on the
  non-constant coefficients weighted by degree², solved exactly).

Scale ambiguity: ``(s·g, φ/s)`` explain the data equally well. After every g-step the gain is
normalised so that the **reference view's gain has mean 1** (over its masked pixels for a field)
and φ is multiplied by the same factor, so ``g·φ`` — what the sensing matrix uses — is unchanged.

Normalised weights (``normalise=True``, the default): ``β_eff = β_φ · s``, ``γ_eff = γ_h · s``
with ``s = Σ_obs w ‖b_obs‖² / M`` (:func:`data_scale`), so the prior does not weaken as the number
of observations grows (a full-size sensor has ~55× the pixels of the small simulated one);
``normalise=False`` gives the original prototype's absolute weights. The reasons and the
measurements are in ``docs/calibration.md``, *Response*.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from hsi_torch.spectral import difference_matrix

__all__ = [
    "DEFAULT_BETA_PHI",
    "DEFAULT_GAMMA_H",
    "data_scale",
    "ResponseResult",
    "solve_phi",
    "solve_gain",
    "estimate_response",
    "legendre_basis_2d",
    "fit_gain_field",
    "estimate_response_field",
]


#: Relative smoothness weight on ‖D φ‖² (times :func:`data_scale`); chosen on the small and the
#: full-size simulated sets (docs/calibration.md).
DEFAULT_BETA_PHI = 1e-2
#: Relative weight of the shape prior ‖φ − α f̃‖² (times :func:`data_scale`).
DEFAULT_GAMMA_H = 1e-2


@dataclass
class ResponseResult:
    """Output of the alternating estimation.

    Attributes:
        phi: ``(3, M)`` φ^c(λ_m) (data units per unit of ``b``).
        alpha: ``(3,)`` scale of the shape prior per colour.
        gain: ``(V,)`` scalar gains, or ``(V, h, w)`` gain field; reference mean = 1.
        coefficients: ``(V, K)`` Legendre coefficients of the gain field (``None`` for scalars).
        residual_rms: RMS of the weighted data residual after each alternation.
        beta_phi_effective, gamma_h_effective: the absolute weights used (the relative ones
            times :func:`data_scale` when normalised).
    """

    phi: torch.Tensor
    alpha: torch.Tensor
    gain: torch.Tensor
    coefficients: torch.Tensor | None = None
    residual_rms: list[float] = field(default_factory=list)
    beta_phi_effective: float = float("nan")
    gamma_h_effective: float = float("nan")


def _check_obs(I: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Bring I to (N, V, 3) and b to (N, V, M) (b broadcast over N without copying)."""
    if I.ndim == 2:
        I = I[None]
    if I.ndim != 3 or I.shape[-1] != 3:
        raise ValueError(f"I must be (V, 3) or (N, V, 3), got {tuple(I.shape)}")
    N, V, _ = I.shape
    if b.ndim == 2:
        b = b[None].expand(N, *b.shape)
    if b.ndim != 3 or b.shape[:2] != (N, V):
        raise ValueError(
            f"b must be (V, M) or (N, V, M) with (N, V) = ({N}, {V}), got {tuple(b.shape)}"
        )
    return I, b


def _obs_weights(weights: torch.Tensor | None, N: int, V: int, like: torch.Tensor) -> torch.Tensor:
    """Observation weights broadcast to (N, V) in ``like``'s dtype/device (default: ones)."""
    w = (
        torch.ones((), dtype=like.dtype, device=like.device)
        if weights is None
        else torch.as_tensor(weights, dtype=like.dtype, device=like.device)
    )
    return w.expand(N, V)


def _check_white(white: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, int, int, int, int]:
    """Bring white to (S, V, 3, h, w) and check ``b (V, M, h, w)`` against it."""
    if white.ndim == 4:
        white = white[None]
    if white.ndim != 5 or white.shape[2] != 3:
        raise ValueError(f"white must be (S, V, 3, h, w) or (V, 3, h, w), got {tuple(white.shape)}")
    S, V, _, h, w = white.shape
    if b.ndim != 4 or b.shape[0] != V or b.shape[2:] != (h, w):
        raise ValueError(f"b must be (V, M, h, w) = ({V}, M, {h}, {w}), got {tuple(b.shape)}")
    return white, S, V, h, w


def data_scale(b: torch.Tensor, weights: torch.Tensor | None = None) -> float:
    """Mean diagonal of the white data's Gram matrix: ``s = Σ_obs w ‖b_obs‖² / M``.

    Args:
        b: ``(N, V, M)`` (or ``(V, M)``) ``B_v(λ_m) Δλ_m`` per observation.
        weights: ``(N, V)`` observation weights (default 1).

    The reference scale of the normalised weights (module docstring): it counts the observations
    and their filter throughput, not the signal level.
    """
    if b.ndim == 2:
        b = b[None]
    N, V, M = b.shape
    w = _obs_weights(weights, N, V, b)
    return float(torch.einsum("nv,nvm->", w.to(torch.float64), b.to(torch.float64) ** 2) / M)


def _weights(beta_phi: float, gamma_h: float, normalise: bool, b: torch.Tensor,
             weights: torch.Tensor | None) -> tuple[float, float]:
    """Absolute ``(β_φ, γ_h)``: relative ones times :func:`data_scale` when ``normalise``."""
    if beta_phi < 0 or gamma_h < 0:
        raise ValueError(f"beta_phi and gamma_h must be >= 0, got {beta_phi}, {gamma_h}")
    if not normalise:
        return float(beta_phi), float(gamma_h)
    s = data_scale(b, weights)
    return float(beta_phi) * s, float(gamma_h) * s


def solve_phi(
    I: torch.Tensor,
    b: torch.Tensor,
    g: torch.Tensor,
    f_prior: torch.Tensor,
    *,
    weights: torch.Tensor | None = None,
    beta_phi: float = 8e5,
    gamma_h: float = 8e5,
    diff_order: int = 1,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Exact φ-step: the joint linear least-squares solution for ``(φ^c, α_c)``, batched over c.

    Args:
        I: ``(V, 3)`` or ``(N, V, 3)`` white observations.
        b: ``(V, M)`` or ``(N, V, M)``: ``B_v(λ_m) Δλ_m`` per observation.
        g: ``(V,)`` or ``(N, V)`` gains.
        f_prior: ``(3, M)`` relative sensitivity shape prior f̃^c.
        weights: optional ``(N, V)`` (or ``(V,)``) non-negative observation weights.
        gamma_h: 0 disables the prior; α is then the LS fit of φ to f̃.
        diff_order: order of the difference matrix ``D`` (1 or 2).

    Returns:
        ``(phi (3, M), alpha (3,))``.
    """
    I, b = _check_obs(I, b)
    N, V, M = b.shape
    dt, dev = I.dtype, I.device
    g = torch.as_tensor(g, dtype=dt, device=dev)
    g = g.expand(N, V) if g.ndim <= 1 or g.shape[0] != N else g
    w = _obs_weights(weights, N, V, I)
    f = torch.as_tensor(f_prior, dtype=dt, device=dev)
    if f.shape != (3, M):
        raise ValueError(f"f_prior must be (3, M) = (3, {M}), got {tuple(f.shape)}")
    wg = w * g
    ata = torch.einsum("nv,nvm,nvk->mk", wg * g, b, b)
    aty = torch.einsum("nv,nvm,nvc->cm", wg, b, I)  # (3, M)
    D = difference_matrix(M, diff_order, device=dev, dtype=dt)
    eye = torch.eye(M, dtype=dt, device=dev)
    K = ata + beta_phi * (D.T @ D) + gamma_h * eye
    if gamma_h == 0:
        phi = torch.linalg.solve(K.expand(3, M, M), aty[..., None])[..., 0]
        alpha = (phi * f).sum(1) / (f * f).sum(1).clamp_min(torch.finfo(dt).tiny)
        return phi, alpha
    A = torch.zeros(3, M + 1, M + 1, dtype=dt, device=dev)
    A[:, :M, :M] = K
    A[:, :M, M] = -gamma_h * f
    A[:, M, :M] = -gamma_h * f
    A[:, M, M] = gamma_h * (f * f).sum(1)
    rhs = torch.zeros(3, M + 1, 1, dtype=dt, device=dev)
    rhs[:, :M, 0] = aty
    x = torch.linalg.solve(A, rhs)[..., 0]
    return x[:, :M], x[:, M]


def solve_gain(
    I: torch.Tensor,
    b: torch.Tensor,
    phi: torch.Tensor,
    *,
    weights: torch.Tensor | None = None,
    reg: float = 1e-4,
) -> torch.Tensor:
    """Scalar g-step: ``g_v = argmin Σ_{n,c} w (I − g_v a)² + λ (g_v − 1)²`` with ``a = b_vᵀφ^c``.

    ``λ_v = reg · Σ w a²`` (relative to view v's data term). Closed form per view.

    Returns:
        ``(V,)`` gains (not yet scale-normalised).
    """
    I, b = _check_obs(I, b)
    N, V, M = b.shape
    w = _obs_weights(weights, N, V, I)
    a = torch.einsum("nvm,cm->nvc", b, phi.to(I.dtype))
    saa = torch.einsum("nv,nvc->v", w, a * a)
    sai = torch.einsum("nv,nvc->v", w, a * I)
    lam = reg * saa
    if bool((saa <= 0).any()):
        bad = torch.nonzero(saa <= 0).flatten().tolist()
        raise ValueError(f"views {bad} have no usable white observations (zero weight or signal)")
    return (sai + lam) / (saa + lam)


def _residual_rms(I, b, g, phi, w) -> float:
    pred = g[..., None] * torch.einsum("nvm,cm->nvc", b, phi)
    r2 = (w[..., None] * (I - pred) ** 2).sum()
    n = (w[..., None] > 0).expand_as(I).sum().clamp_min(1)
    return float((r2 / n).sqrt())


def _refine_joint(
    I: torch.Tensor, b: torch.Tensor, w: torch.Tensor, L: torch.Tensor, C: torch.Tensor,
    phi: torch.Tensor, alpha: torch.Tensor, f: torch.Tensor, *, beta_phi: float, gamma_h: float,
    reg: float, ridge_w: torch.Tensor, ridge_c0: torch.Tensor, ref_coef: torch.Tensor,
    reference_view: int, diff_order: int, steps: int, tol: float = 1e-10,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:  # fmt: skip
    """Joint Levenberg–Marquardt refinement of (φ, α, C) under the gauge ``ref_coef·C_ref = 1``.

    Objective: ``Σ w (I − g a)² + β‖Dφ‖² + γ‖φ − α f̃‖² + Σ_v λ_v Σ_k ridge_w_k (C_vk − c0_k)²``
    with ``g[n, v] = Σ_k C_vk L[n, k]``, ``a = b φᵀ`` and ``λ_v = reg · trace(G_v)/K``.
    Alternation alone converges slowly on this bilinear problem (zig-zag); these steps solve the
    same objective to convergence. Sizes: I (N, V, 3), b (N, V, M), w (N, V), L (N, K), C (V, K).
    """
    N, V, M = b.shape
    K = L.shape[1]
    dt, dev = I.dtype, I.device
    D = difference_matrix(M, diff_order, device=dev, dtype=dt)
    DtD = D.T @ D
    n_phi, n_c = 3 * M, V * K
    n = n_phi + 3 + n_c
    e = torch.zeros(n, dtype=dt, device=dev)
    e[n_phi + 3 + reference_view * K : n_phi + 3 + (reference_view + 1) * K] = ref_coef

    def gram(Cc, ph):
        g = L @ Cc.T  # (N, V)
        a = torch.einsum("nvm,cm->nvc", b, ph)
        G = torch.einsum("nv,nk,nl->vkl", w * (a * a).sum(-1), L, L)
        return g, a, G

    def objective(Cc, ph, al, lam):
        g, a, _ = gram(Cc, ph)
        r = I - g[..., None] * a
        val = (w[..., None] * r * r).sum()
        val = val + beta_phi * ((ph @ D.T) ** 2).sum()
        val = val + gamma_h * ((ph - al[:, None] * f) ** 2).sum()
        return val + (lam[:, None] * ridge_w * (Cc - ridge_c0) ** 2).sum()

    mu = 1e-6
    for _ in range(steps):
        g, a, G = gram(C, phi)
        lam = reg * torch.diagonal(G, dim1=1, dim2=2).sum(1) / K
        r = I - g[..., None] * a
        Hm = torch.zeros(n, n, dtype=dt, device=dev)
        grad = torch.zeros(n, dtype=dt, device=dev)
        A = torch.einsum("nv,nvm,nvk->mk", w * g * g, b, b)
        wg = w * g
        for c in range(3):
            sl = slice(c * M, (c + 1) * M)
            Hm[sl, sl] = A + beta_phi * DtD + gamma_h * torch.eye(M, dtype=dt, device=dev)
            Hm[sl, n_phi + c] = -gamma_h * f[c]
            Hm[n_phi + c, sl] = -gamma_h * f[c]
            Hm[n_phi + c, n_phi + c] = gamma_h * (f[c] * f[c]).sum()
            X = torch.einsum("nvm,nv,nk->mvk", b, wg * a[..., c], L).reshape(M, n_c)
            # cross term of the Gauss–Newton Hessian (+ the exact second-order part w·(−r)·b·L)
            X = X - torch.einsum("nvm,nv,nk->mvk", b, w * r[..., c], L).reshape(M, n_c)
            Hm[sl, n_phi + 3 :] = X
            Hm[n_phi + 3 :, sl] = X.T
            grad[sl] = (
                -torch.einsum("nv,nvm->m", wg * r[..., c], b)
                + beta_phi * (DtD @ phi[c])
                + gamma_h * (phi[c] - alpha[c] * f[c])
            )
            grad[n_phi + c] = -gamma_h * (f[c] * (phi[c] - alpha[c] * f[c])).sum()
        Gr = G + lam[:, None, None] * torch.diag(ridge_w)[None]
        for v in range(V):
            sl = slice(n_phi + 3 + v * K, n_phi + 3 + (v + 1) * K)
            Hm[sl, sl] = Gr[v]
        gC = -torch.einsum("nvc,nvc,nk->vk", w[..., None] * a, r, L)
        gC = gC + lam[:, None] * ridge_w * (C - ridge_c0)
        grad[n_phi + 3 :] = gC.reshape(-1)
        f0 = objective(C, phi, alpha, lam)
        scale = torch.diagonal(Hm).abs().clamp_min(torch.finfo(dt).tiny)
        accepted = False
        for _ in range(12):
            KKT = torch.zeros(n + 1, n + 1, dtype=dt, device=dev)
            KKT[:n, :n] = Hm + mu * torch.diag(scale)
            KKT[:n, n] = e
            KKT[n, :n] = e
            rhs = torch.cat([-grad, torch.zeros(1, dtype=dt, device=dev)])
            delta = torch.linalg.solve(KKT, rhs)[:n]
            ph_new = phi + delta[:n_phi].reshape(3, M)
            al_new = alpha + delta[n_phi : n_phi + 3]
            C_new = C + delta[n_phi + 3 :].reshape(V, K)
            f1 = objective(C_new, ph_new, al_new, lam)
            if bool(f1 <= f0):
                phi, alpha, C = ph_new, al_new, C_new
                mu = max(mu / 10, 1e-12)
                accepted = True
                break
            mu *= 10
        if not accepted or bool((f0 - f1).abs() <= tol * f0.abs()):
            break
    return phi, alpha, C


def estimate_response(
    I: torch.Tensor,
    b: torch.Tensor,
    f_prior: torch.Tensor,
    *,
    weights: torch.Tensor | None = None,
    beta_phi: float = DEFAULT_BETA_PHI,
    gamma_h: float = DEFAULT_GAMMA_H,
    normalise: bool = True,
    n_iter: int = 3,
    gain_reg: float = 1e-4,
    reference_view: int = 0,
    diff_order: int = 1,
    g_init: torch.Tensor | None = None,
    refine_steps: int = 20,
) -> ResponseResult:
    """Alternating estimation of φ^c (3, M) and scalar per-view gains g_v (V,).

    Each alternation is a φ-step (:func:`solve_phi`) then a g-step (:func:`solve_gain`) followed
    by the scale normalisation ``g_ref = 1``; a final φ-step makes φ consistent with the final g.

    Args:
        I: ``(V, 3)`` or ``(N, V, 3)`` white observations (N shots or pixels per view).
        b: ``(V, M)`` or ``(N, V, M)``, ``B_v(λ_m) Δλ_m``.
        f_prior: ``(3, M)`` shape prior.
        weights: optional ``(N, V)`` observation weights (0 = missing).
        beta_phi, gamma_h: regularisation weights, relative to :func:`data_scale` when
            ``normalise`` (default), else absolute (the original prototype: ``8e5``, ``8e5``).
        gain_reg: relative ridge of the g-step towards 1.
        reference_view: the view whose gain is fixed to 1.
        g_init: optional ``(V,)`` initial gains (default ones).
        refine_steps: maximum joint Levenberg–Marquardt steps on the same objective after the
            alternations (0 = the plain alternation of the original prototype). Alternation
            alone converges slowly on this bilinear problem when the gains are far from 1.

    Returns:
        :class:`ResponseResult` with ``gain (V,)``.
    """
    I, b = _check_obs(I, b)
    N, V, M = b.shape
    dt, dev = I.dtype, I.device
    w = _obs_weights(weights, N, V, I)
    g = (torch.ones(V, dtype=dt, device=dev) if g_init is None
         else torch.as_tensor(g_init, dtype=dt, device=dev).clone())  # fmt: skip
    hist: list[float] = []
    beta_phi, gamma_h = _weights(beta_phi, gamma_h, normalise, b, w)
    kw = dict(weights=w, beta_phi=beta_phi, gamma_h=gamma_h, diff_order=diff_order)
    for _ in range(n_iter):
        phi, alpha = solve_phi(I, b, g, f_prior, **kw)
        g = solve_gain(I, b, phi, weights=w, reg=gain_reg)
        g = g / g[reference_view]
        hist.append(_residual_rms(I, b, g.expand(N, V), phi, w))
    phi, alpha = solve_phi(I, b, g, f_prior, **kw)
    if refine_steps > 0:
        one = torch.ones(1, dtype=dt, device=dev)
        phi, alpha, C = _refine_joint(
            I, b, w, torch.ones(N, 1, dtype=dt, device=dev), g[:, None], phi, alpha,
            torch.as_tensor(f_prior, dtype=dt, device=dev), beta_phi=beta_phi, gamma_h=gamma_h,
            reg=gain_reg, ridge_w=one, ridge_c0=one, ref_coef=one,
            reference_view=reference_view, diff_order=diff_order, steps=refine_steps,
        )  # fmt: skip
        g = C[:, 0] / C[reference_view, 0]
    hist.append(_residual_rms(I, b, g.expand(N, V), phi, w))
    return ResponseResult(phi, alpha, g, None, hist, beta_phi, gamma_h)


def legendre_basis_2d(
    h: int,
    w: int,
    degree: int,
    *,
    stride: int = 1,
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Products of Legendre polynomials ``P_i(x̂) P_j(ŷ)``, ``i + j ≤ degree``, on an h×w grid.

    ``x̂, ŷ ∈ [−1, 1]`` span the pixel centres of the h×w frame. With ``stride = s`` the functions
    are sampled at every ``s``-th pixel only (rows and columns ``0, s, 2s, …``), in the same
    coordinates. Returns ``(basis (K, ⌈h/s⌉, ⌈w/s⌉), total_degree (K,))`` with
    ``K = (degree+1)(degree+2)/2``; the first function is the constant 1.
    """
    if degree < 0:
        raise ValueError(f"degree must be >= 0, got {degree}")
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    dtype = dtype or torch.get_default_dtype()

    def coords(n: int) -> torch.Tensor:
        if n <= 1:
            return torch.zeros(1, device=device, dtype=dtype)
        return torch.linspace(-1, 1, n, device=device, dtype=dtype)[::stride]

    xs, ys = coords(w), coords(h)

    def leg(t: torch.Tensor) -> list[torch.Tensor]:
        out = [torch.ones_like(t), t]
        for n in range(1, degree):
            out.append(((2 * n + 1) * t * out[n] - n * out[n - 1]) / (n + 1))
        return out[: degree + 1]

    px, py = leg(xs), leg(ys)
    basis, deg = [], []
    for total in range(degree + 1):
        for j in range(total + 1):
            i = total - j
            basis.append(py[j][:, None] * px[i][None, :])
            deg.append(total)
    return torch.stack(basis), torch.tensor(deg, device=device, dtype=dtype)


def fit_gain_field(
    white: torch.Tensor,
    b: torch.Tensor,
    phi: torch.Tensor,
    mask: torch.Tensor,
    *,
    degree: int = 2,
    smoothness: float = 1e-3,
    basis: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Smooth gain field g_v(p) on the reference frame by penalised least squares (φ fixed).

    ``g_v(p) = Σ_k c_vk L_k(p)`` (see :func:`legendre_basis_2d`) minimising
    ``Σ_{s,c,p} m_v(p) (I_svc(p) − g_v(p) a_vc(p))² + λ_v Σ_k deg_k² c_vk²`` with
    ``a_vc(p) = Σ_m b_vm(p) φ_cm`` and ``λ_v = smoothness · trace(G_v)/K`` (``G_v`` the data
    Gram matrix). One batched ``(V, K, K)`` solve; not normalised.

    Args:
        white: ``(S, V, 3, h, w)`` or ``(V, 3, h, w)`` registered white shots.
        b: ``(V, M, h, w)`` ``B_v(p, λ_m) Δλ_m`` in the reference frame.
        phi: ``(3, M)``.
        mask: ``(V, h, w)`` bool/float observation weights.
        basis: ``(basis (K, h, w), total_degree (K,))`` to use instead of
            ``legendre_basis_2d(h, w, degree)`` (e.g. a strided sub-grid of a larger frame).

    Returns:
        ``(gain (V, h, w), coefficients (V, K))``.
    """
    white, S, V, h, w = _check_white(white, b)
    dt, dev = white.dtype, white.device
    m = torch.as_tensor(mask, device=dev).to(dt)
    if m.shape != (V, h, w):
        raise ValueError(f"mask must be (V, h, w) = ({V}, {h}, {w}), got {tuple(m.shape)}")
    a = torch.einsum("vmhw,cm->vchw", b.to(dt), phi.to(dt))
    Ibar = white.mean(0)
    L, deg = legendre_basis_2d(h, w, degree, device=dev, dtype=dt) if basis is None else basis
    K = L.shape[0]
    saa = S * m * (a * a).sum(1)  # (V, h, w)
    sai = S * m * (a * Ibar).sum(1)
    Lf = L.reshape(K, -1)
    G = torch.einsum("vp,kp,lp->vkl", saa.reshape(V, -1), Lf, Lf)
    r = torch.einsum("vp,kp->vk", sai.reshape(V, -1), Lf)
    diag = torch.diagonal(G, dim1=1, dim2=2)
    if bool((diag[:, 0] <= 0).any()):
        bad = torch.nonzero(diag[:, 0] <= 0).flatten().tolist()
        raise ValueError(f"views {bad} have no usable white observations inside their masks")
    lam = smoothness * diag.sum(1) / K  # (V,)
    G = G + lam[:, None, None] * torch.diag(deg * deg)[None]
    coef = torch.linalg.solve(G, r[..., None])[..., 0]
    gain = torch.einsum("vk,khw->vhw", coef, L)
    return gain, coef


def estimate_response_field(
    white: torch.Tensor,
    b: torch.Tensor,
    f_prior: torch.Tensor,
    mask: torch.Tensor,
    *,
    beta_phi: float = DEFAULT_BETA_PHI,
    gamma_h: float = DEFAULT_GAMMA_H,
    normalise: bool = True,
    n_iter: int = 3,
    degree: int = 2,
    smoothness: float = 1e-3,
    reference_view: int = 0,
    diff_order: int = 1,
    refine_steps: int = 20,
    max_pixels: int | None = None,
    band_widths_nm: torch.Tensor | None = None,
) -> ResponseResult:
    """Alternating estimation of φ^c and a smooth gain field g_v(p) from registered white shots.

    φ-step: :func:`solve_phi` with one observation per (pixel, view), the shots averaged and
    weighted by their number ``S`` (equivalent to summing over shots). g-step:
    :func:`fit_gain_field`, then normalisation so that the mean of ``g_ref`` over its mask is 1
    (φ rescaled accordingly).

    Args:
        white: ``(S, V, 3, h, w)`` or ``(V, 3, h, w)`` registered white shots (DN).
        b: ``(V, M, h, w)`` ``B_v(p, λ_m) Δλ_m`` in the reference frame.
        f_prior: ``(3, M)``.
        mask: ``(V, h, w)`` bool: pixel present in view v (and reliable).
        beta_phi, gamma_h, normalise, n_iter, diff_order, reference_view, refine_steps: see
            :func:`estimate_response`; degree, smoothness: see :func:`fit_gain_field`.
        max_pixels: estimate on a regular sub-grid (every ``s``-th row and column,
            ``s = ⌈sqrt(h·w / max_pixels)⌉``) when the frame has more pixels; the gain field is
            then evaluated on the whole frame from its coefficients and the gauge (mean reference
            gain 1) re-applied there. The white shots of every pixel are averaged anyway, the
            unknowns (``3M`` values of φ, ``V·K`` gain coefficients) are few, and calibration
            errors are systematic, so the sub-grid costs nothing measurable while bounding time
            and memory at full sensor size. ``None``: every pixel.
        band_widths_nm: ``(M,)`` ``Δλ_m``: ``b`` is then the transmittance ``B`` itself and is
            multiplied by ``Δλ`` after the sub-sampling (no full-frame copy).

    Returns:
        :class:`ResponseResult` with ``gain (V, h, w)`` and its coefficients, float64 (the
        estimation runs in float64 whatever the input dtype).
    """
    white, S, V, h, w = _check_white(white, b)
    dt, dev = torch.float64, white.device  # the normal equations sum ~1e6 terms: float64
    mask_b = torch.as_tensor(mask, device=dev).to(torch.bool)
    if mask_b.shape != (V, h, w):
        raise ValueError(f"mask must be (V, h, w) = ({V}, {h}, {w}), got {tuple(mask_b.shape)}")
    if not bool(mask_b[reference_view].any()):
        raise ValueError(f"the reference view {reference_view} has an empty mask")
    if max_pixels is not None and max_pixels < 1:
        raise ValueError(f"max_pixels must be >= 1 or None, got {max_pixels}")
    stride = 1 if max_pixels is None else max(1, math.ceil(math.sqrt(h * w / max_pixels)))
    full_basis = None
    if stride > 1:
        full_basis = legendre_basis_2d(h, w, degree, device=dev, dtype=dt)
        full_ref = mask_b[reference_view]
        white = white[..., ::stride, ::stride]
        b = b[..., ::stride, ::stride]
        mask_b = mask_b[:, ::stride, ::stride]
        h, w = mask_b.shape[1:]
        if not bool(mask_b[reference_view].any()):
            raise ValueError(f"the reference view {reference_view} has no pixel on the "
                             f"sub-grid of stride {stride} (max_pixels={max_pixels})")
    basis = legendre_basis_2d(*(full_ref.shape if stride > 1 else (h, w)), degree, stride=stride,
                              device=dev, dtype=dt)
    M = b.shape[1]
    ref = mask_b[reference_view]
    white, b = white.to(dt), b.to(dt)
    if band_widths_nm is not None:
        b = b * torch.as_tensor(band_widths_nm, dtype=dt, device=dev).view(1, -1, 1, 1)
    Iobs = white.mean(0).permute(2, 3, 0, 1).reshape(h * w, V, 3)
    bobs = b.permute(2, 3, 0, 1).reshape(h * w, V, M)
    wobs = (S * mask_b.to(dt)).permute(1, 2, 0).reshape(h * w, V)
    gain = torch.ones(V, h, w, dtype=dt, device=dev)
    coef = None
    hist: list[float] = []
    beta_phi, gamma_h = _weights(beta_phi, gamma_h, normalise, bobs, wobs)
    kw = dict(weights=wobs, beta_phi=beta_phi, gamma_h=gamma_h, diff_order=diff_order)

    def gobs(gf: torch.Tensor) -> torch.Tensor:
        return gf.permute(1, 2, 0).reshape(h * w, V)

    for _ in range(n_iter):
        phi, alpha = solve_phi(Iobs, bobs, gobs(gain), f_prior, **kw)
        gain, coef = fit_gain_field(white, b, phi, mask_b, degree=degree, smoothness=smoothness,
                                    basis=basis)
        s = gain[reference_view][ref].mean()
        gain = gain / s
        coef = coef / s
        hist.append(_residual_rms(Iobs, bobs, gobs(gain), phi * s, wobs / S))
    phi, alpha = solve_phi(Iobs, bobs, gobs(gain), f_prior, **kw)
    if refine_steps > 0:
        L, deg = basis
        Lobs = L.reshape(L.shape[0], -1).T  # (h*w, K)
        ref_coef = Lobs[ref.reshape(-1)].mean(0)
        phi, alpha, coef = _refine_joint(
            Iobs, bobs, wobs, Lobs, coef, phi, alpha,
            torch.as_tensor(f_prior, dtype=dt, device=dev), beta_phi=beta_phi, gamma_h=gamma_h,
            reg=smoothness, ridge_w=deg * deg, ridge_c0=torch.zeros_like(deg), ref_coef=ref_coef,
            reference_view=reference_view, diff_order=diff_order, steps=refine_steps,
        )  # fmt: skip
        gain = torch.einsum("vk,khw->vhw", coef, L)
    hist.append(_residual_rms(Iobs, bobs, gobs(gain), phi, wobs / S))
    if full_basis is not None:  # the field on the whole frame, gauge over the whole reference mask
        gain = torch.einsum("vk,khw->vhw", coef, full_basis[0])
        s0 = gain[reference_view][full_ref].mean()
        gain, coef, phi = gain / s0, coef / s0, phi * s0
    return ResponseResult(phi, alpha, gain, coef, hist, beta_phi, gamma_h)
