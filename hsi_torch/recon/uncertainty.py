"""Per-pixel uncertainty of the per-pixel NNLS reconstruction: a standard deviation for every band.

What it is, its assumptions and its measured coverage: ``docs/reconstruct.md``, *Uncertainty*.

**The estimator.** Per pixel the solver returns
``ŝ = argmin_{s ≥ 0} ‖W^{1/2}(A s − y)‖² + β‖D s‖²`` (``W = diag(w_o)``, the pipeline's 0/1 frame
mask). On the free set ``F = {m : ŝ_m > 0}`` (bands ``Z`` on the bound), while ``F`` does not
change under small perturbations of ``y``, the solution is linear in ``y``:

.. math::

    ŝ_F = G_{FF}^{-1} (Aᵀ W y)_F, \\quad ŝ_Z = 0, \\qquad G = AᵀWA + β DᵀD,

    \\mathrm{Cov}(ŝ_F) = G_{FF}^{-1} \\, (A_Fᵀ W Σ_y W A_F) \\, G_{FF}^{-1}, \\qquad
    \\mathrm{Cov}(ŝ_Z) = 0.

The reported standard deviation is ``sqrt(Cov_mm)`` on ``F`` and 0 on ``Z`` (a band held at the
bound by a positive multiplier stays there under small noise). Deviations from the exact spread:
bands that flip between free and bound are not described (linearisation), the bias from β is not
included (the spread around ŝ's own mean), and ``Σ_y`` is diagonal per pixel and estimated from
the measured values (plug-in).

**The observation noise.** A raw sample (DN above black) with mean ``μ``, conversion gain ``g``
e⁻/DN, read noise ``σ_r`` e⁻ and quantisation step ``q`` DN::

    var_raw(μ) = μ / g + (σ_r / g)² + q² / 12        [DN²]

An observation is ``k Σ_j c_oj raw_j`` (exposure ratio ``k = t_white / t_capture``, bilinear
sampling of the view, after a bilinear demosaic for Bayer data), so

    var(y_o) = k² · var_raw(y_o / k) · ‖c_o‖²

(raw variance constant over the at most 4 × 4 px footprint). The *sampling factor* ``‖c_o‖²``
(:func:`sampling_variance_factor`) is ``Σ_j w_j²`` of the four bilinear weights for an RGB
capture, ``wᵀ K w`` for a bilinearly demosaiced Bayer capture (``K`` from
:func:`demosaic_tap_covariance`), and ``Σ_j w_j²`` halved for green after 2 × 2 binning.

Everything is batched over pixels (chunks of ``chunk_size``; no per-pixel Python), on any device
and in any floating dtype; the small ``M × M`` systems are solved in float64 by default.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from hsi_torch.forward_model import DenseSensing, SensingModel
from hsi_torch.io.raw import demosaic_bilinear, validate_cfa_pattern
from hsi_torch.recon.nnls import NNLSProblem, cpu_threads
from hsi_torch.recon.nnls._threads import for_chunks, workers_for

__all__ = [
    "SensorNoise",
    "RawLayout",
    "RAW_LAYOUTS",
    "DEFAULT_ELECTRONS_PER_DN",
    "DEFAULT_READ_NOISE_E",
    "raw_variance",
    "observation_variance",
    "sampling_variance_factor",
    "demosaic_tap_covariance",
    "nnls_band_std",
    "relative_std_map",
]

#: Conversion gain of the simulator's default sensor (e⁻/DN): a 30 000 e⁻ full well over the
#: 14-bit range above a 512 DN black level, ``30000 / (16383 − 512)``.
DEFAULT_ELECTRONS_PER_DN = 30000.0 / (16383.0 - 512.0)
#: Read noise σ of the simulator's default sensor, electrons.
DEFAULT_READ_NOISE_E = 3.0

RawLayout = Literal["rgb", "bayer", "half"]
#: How the capture's RGB values were made from raw samples (see :func:`sampling_variance_factor`).
RAW_LAYOUTS: tuple[str, ...] = ("rgb", "bayer", "half")


@dataclass(frozen=True)
class SensorNoise:
    """Shot + read + quantisation noise of the raw sensor samples (see the module docstring).

    Attributes:
        electrons_per_dn: conversion gain ``g`` (e⁻/DN), > 0.
        read_noise_e: read noise ``σ_r`` (e⁻), ≥ 0.
        quantization_dn: ADC step ``q`` (DN; 1 for integer raw data, 0 for none), ≥ 0.

    Defaults: the simulator's default sensor (:data:`DEFAULT_ELECTRONS_PER_DN`,
    :data:`DEFAULT_READ_NOISE_E`, integer DN).
    """

    electrons_per_dn: float = DEFAULT_ELECTRONS_PER_DN
    read_noise_e: float = DEFAULT_READ_NOISE_E
    quantization_dn: float = 1.0

    def __post_init__(self) -> None:
        g, r, q = self.electrons_per_dn, self.read_noise_e, self.quantization_dn
        if not (isinstance(g, (int, float)) and g > 0 and g != float("inf")):
            raise ValueError(f"electrons_per_dn must be finite and > 0, got {g!r}")
        if not (isinstance(r, (int, float)) and 0 <= r < float("inf")):
            raise ValueError(f"read_noise_e must be finite and >= 0, got {r!r}")
        if not (isinstance(q, (int, float)) and 0 <= q < float("inf")):
            raise ValueError(f"quantization_dn must be finite and >= 0, got {q!r}")

    @property
    def signal_free_variance_dn2(self) -> float:
        """``(σ_r / g)² + q² / 12``: the variance of a raw sample without signal, DN²."""
        return (self.read_noise_e / self.electrons_per_dn) ** 2 + self.quantization_dn**2 / 12.0


def raw_variance(signal_dn: Tensor, noise: SensorNoise) -> Tensor:
    """Variance (DN²) of a raw sample whose mean is ``signal_dn`` (DN above black; negative values
    count as 0): ``μ / g + (σ_r / g)² + q² / 12``. Same shape, dtype and device."""
    return signal_dn.clamp_min(0) / noise.electrons_per_dn + noise.signal_free_variance_dn2


def observation_variance(
    y: Tensor,
    noise: SensorNoise,
    *,
    scale: Tensor | float = 1.0,
    sampling_factor: Tensor | None = None,
) -> Tensor:
    """Variance of the pipeline's observations, estimated from their measured values.

    ``var(y_o) = k² · var_raw(y_o / k) · f_o`` (module docstring).

    Args:
        y: ``(P, O)`` observations (DN above black, already multiplied by the exposure ratio
            ``k``). Values where the observation is masked are irrelevant (NaN allowed).
        noise: the raw sensor's noise.
        scale: ``k`` (scalar; the pipeline's :func:`~hsi_torch.recon.pipeline.exposure_scale`).
        sampling_factor: ``(P, O)`` ``f_o = ‖c_o‖²`` (:func:`sampling_variance_factor`);
            ``None``: 1 (the observations are raw samples).

    Returns:
        ``(P, O)`` variance in DN², ``y``'s dtype and device.
    """
    k = torch.as_tensor(scale, dtype=y.dtype, device=y.device)
    var = k * k * raw_variance(y / k, noise)
    return var if sampling_factor is None else var * sampling_factor.to(var.dtype)


def demosaic_tap_covariance(
    pattern: str, *, dtype: torch.dtype = torch.float64, device: torch.device | str | None = None
) -> Tensor:
    """Covariance of bilinearly demosaiced values at the four taps of a bilinear sample.

    For raw samples of unit variance and no correlation, the demosaiced colour-``c`` values at
    ``(x, y), (x+1, y), (x, y+1), (x+1, y+1)`` have covariance ``K[q, c]`` (``4 × 4``), where
    ``q = 2·(y mod 2) + (x mod 2)`` is the CFA phase of the top-left tap. Computed by
    demosaicing unit impulses with :func:`~hsi_torch.io.raw.demosaic_bilinear` (interior
    stencils; the frame border is not modelled).

    Returns:
        ``(4, 3, 4, 4)`` tensor (tap order as above).
    """
    pat = validate_cfa_pattern(pattern)
    n = 12
    imp = torch.eye(n * n, dtype=torch.float64).reshape(n * n, 1, n, n)
    d = demosaic_bilinear(imp, pat)  # (k, c, y, x): weight of raw sample k in output (c, y, x)
    taps = ((0, 0), (1, 0), (0, 1), (1, 1))
    out = torch.empty((4, 3, 4, 4), dtype=torch.float64)
    for q in range(4):
        x0, y0 = 4 + q % 2, 4 + q // 2
        cols = torch.stack([d[:, :, y0 + dy, x0 + dx] for dx, dy in taps], dim=2)  # (k, c, 4)
        out[q] = torch.einsum("kci,kcj->cij", cols, cols)
    return out.to(device=device, dtype=dtype)


def sampling_variance_factor(
    grid: Tensor,
    image_size: tuple[int, int],
    layout: RawLayout = "rgb",
    cfa_pattern: str | None = None,
) -> Tensor:
    """``‖c_o‖²`` of every observation: the variance factor of sampling the capture (module
    docstring).

    Args:
        grid: ``(1, V, P, 2)`` sampling positions of every valid pixel in every view, normalised
            ``(x, y)`` with ``align_corners=True`` (the pipeline's
            :meth:`~hsi_torch.recon.sensing.BundleSensing.grid`).
        image_size: ``(H, W)`` of the RGB image that is sampled.
        layout: ``"rgb"`` (independent samples), ``"bayer"`` (bilinear demosaic of a mosaic
            with ``cfa_pattern``), ``"half"`` (2 × 2 binned Bayer cells: green is the mean of two
            sites).
        cfa_pattern: the CFA pattern, for ``"bayer"``.

    Returns:
        ``(P, 3V)`` factors (``o = 3·v + c``), ``grid``'s dtype and device; taps outside the
        image (zero padding) do not count.
    """
    if layout not in RAW_LAYOUTS:
        raise ValueError(f"layout must be one of {RAW_LAYOUTS}, got {layout!r}")
    if grid.ndim != 4 or grid.shape[0] != 1 or grid.shape[-1] != 2:
        raise ValueError(f"grid must have shape (1, V, P, 2), got {tuple(grid.shape)}")
    H, W = (int(v) for v in image_size)
    g = grid[0].to(torch.float64)
    px = (g[..., 0] + 1) * 0.5 * (W - 1)
    py = (g[..., 1] + 1) * 0.5 * (H - 1)
    x0, y0 = px.floor(), py.floor()
    fx, fy = px - x0, py - y0
    w = torch.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], dim=-1)
    tx = x0.unsqueeze(-1) + torch.tensor([0, 1, 0, 1], dtype=g.dtype, device=g.device)
    ty = y0.unsqueeze(-1) + torch.tensor([0, 0, 1, 1], dtype=g.dtype, device=g.device)
    inside = (tx >= 0) & (tx <= W - 1) & (ty >= 0) & (ty <= H - 1)
    w = torch.where(inside, w, torch.zeros((), dtype=w.dtype, device=w.device))  # (V, P, 4)
    V, P = w.shape[:2]
    if layout == "bayer":
        if cfa_pattern is None:
            raise ValueError("layout='bayer' needs cfa_pattern")
        K = demosaic_tap_covariance(cfa_pattern, device=g.device)  # (4, 3, 4, 4)
        phase = (y0.remainder(2) * 2 + x0.remainder(2)).long()  # (V, P)
        f = torch.zeros((V, P, 3), dtype=torch.float64, device=g.device)
        for q in range(4):  # the four CFA phases (not a per-pixel loop)
            fq = torch.einsum("vpi,cij,vpj->vpc", w, K[q], w)
            f = torch.where((phase == q).unsqueeze(-1), fq, f)
    else:
        s = w.square().sum(-1, keepdim=True)  # (V, P, 1)
        ch = torch.tensor([1.0, 0.5 if layout == "half" else 1.0, 1.0], dtype=torch.float64,
                          device=g.device)  # fmt: skip
        f = s * ch
    return f.permute(1, 0, 2).reshape(P, 3 * V).to(grid.dtype)


def nnls_band_std(
    sensing: SensingModel | DenseSensing | Tensor,
    x: Tensor,
    obs_var: Tensor,
    weights: Tensor | None = None,
    reg: Tensor | None = None,
    *,
    problem: NNLSProblem | None = None,
    chunk_size: int = 1024,
    compute_dtype: torch.dtype | None = torch.float64,
    num_threads: int | None = None,
) -> Tensor:
    """Standard deviation of every band of per-pixel NNLS solutions (module docstring).

    ``std_F = sqrt(diag(G_FF⁻¹ (A_Fᵀ W Σ_y W A_F) G_FF⁻¹))``, ``std_Z = 0``, with
    ``G = AᵀWA + reg``, ``F = {m : x_m > 0}`` per pixel and ``Σ_y = diag(obs_var)``, computed as
    the squared column norms of ``E G_FF⁻¹`` with ``E = Σ_y^{1/2} W A_F`` (``G_FF`` factorised per
    pixel by Cholesky).

    Args:
        sensing: the ``P`` pixels' operator (:class:`~hsi_torch.forward_model.SensingModel`,
            :class:`~hsi_torch.forward_model.DenseSensing`) or dense ``(O, M)`` / ``(P, O, M)``.
        x: ``(P, M)`` the NNLS solutions (their free sets are used).
        obs_var: ``(P, O)`` observation variances (data units²); ignored where the weight is 0
            (may be NaN there).
        weights: ``(P, O)`` bool mask or non-negative float weights ``w_o`` (``None``: all 1).
        reg: ``(M, M)`` regulariser Gram ``β DᵀD`` the solutions were computed with
            (:func:`~hsi_torch.recon.nnls.smoothness_gram`; ``None``: none, or ``problem``'s).
        problem: the :class:`~hsi_torch.recon.nnls.NNLSProblem` the solutions came from, if
            any: pixels whose bands are all free and whose weights are the problem's mask reuse
            its stored ``G⁻¹`` instead of a factorisation (same result, to rounding).
        chunk_size: pixels per batch (memory ≈ ``chunk_size · (3·O·M + 4·M²)`` floats).
        compute_dtype: dtype of the ``M × M`` algebra (float64 by default; ``None``: ``x``'s).
        num_threads: CPU threads (default ``torch.get_num_threads()``), each running
            single-threaded kernels on its share of the chunks, as the solver does.

    Returns:
        ``(P, M)`` in ``x``'s dtype and device: ≥ 0 and finite on free bands, 0 on bound bands,
        ``inf`` on the free bands of a pixel whose ``G_FF`` is singular (the solution is not
        determined there).
    """
    if isinstance(sensing, Tensor):
        sensing = DenseSensing(sensing)
    if x.ndim != 2 or x.shape[1] != sensing.num_bands:
        raise ValueError(f"x must have shape (P, {sensing.num_bands}), got {tuple(x.shape)}")
    P, M = x.shape
    O = sensing.num_obs
    if obs_var.shape != (P, O):
        raise ValueError(f"obs_var must have shape ({P}, {O}), got {tuple(obs_var.shape)}")
    if weights is not None and weights.shape != (P, O):
        raise ValueError(f"weights must have shape ({P}, {O}), got {tuple(weights.shape)}")
    if not sensing.shared and sensing.num_pixels != P:
        raise ValueError(f"the sensing operator has {sensing.num_pixels} pixels but x has {P}")
    if reg is None and problem is not None:
        reg = problem.reg
    if reg is not None and reg.shape != (M, M):
        raise ValueError(f"reg must have shape ({M}, {M}), got {tuple(reg.shape)}")
    cd = compute_dtype or x.dtype
    dev = x.device
    eye = torch.eye(M, dtype=cd, device=dev)
    zero = torch.zeros((), dtype=cd, device=dev)
    inf = torch.full((), float("inf"), dtype=cd, device=dev)
    eps = torch.finfo(cd).eps
    R = None if reg is None else reg.to(device=dev, dtype=cd)
    stored = None  # (P,) bool: the problem's G⁻¹ is this pixel's G_FF⁻¹
    if problem is not None and (problem.num_pixels in (None, P)):
        same = torch.ones((P,), dtype=torch.bool, device=dev)
        if problem.mask is not None or weights is not None:
            one = torch.ones((), dtype=cd, device=dev)
            wf = one.expand(P, O) if weights is None else weights.to(cd)
            pm = one.expand(P, O) if problem.mask is None else problem.mask.to(cd)
            same = (wf == pm).all(1)
        sing = problem.singular
        stored = same & (x > 0).all(1) & ~(sing.expand(P) if sing.shape[0] == 1 else sing)
    out = torch.empty((P, M), dtype=x.dtype, device=dev)

    def chunk(sl: slice) -> None:
        a = sensing.dense(sl).to(cd)
        n = sl.stop - sl.start
        if a.shape[0] == 1:
            a = a.expand(n, -1, -1)
        w = torch.ones((n, O), dtype=cd, device=dev) if weights is None else weights[sl].to(cd)
        sd = torch.where(w > 0, obs_var[sl].to(cd).clamp_min(0).sqrt(), zero) * w  # w σ
        free = x[sl] > 0
        E = a * (sd.unsqueeze(2) * free.unsqueeze(1).to(cd))  # Σ^{1/2} W A_F (0 on Z)
        fast = None if stored is None else stored[sl]
        nf = 0 if fast is None else int(torch.count_nonzero(fast))
        std = torch.zeros((n, M), dtype=cd, device=dev)
        if nf:
            H = problem.gram_inv
            if nf == n:  # all bands free, the problem's mask: G⁻¹ is stored (the common case)
                Hs = H if H.shape[0] == 1 else H[sl]
                out[sl] = torch.matmul(E, Hs.to(cd)).square().sum(1).sqrt().to(x.dtype)
                return
            i = fast.nonzero().squeeze(1)
            Hs = H.expand(nf, -1, -1) if H.shape[0] == 1 else H.index_select(0, i + sl.start)
            std[i] = torch.matmul(E[i], Hs.to(cd)).square().sum(1).sqrt()
        j = torch.arange(n, device=dev) if fast is None else (~fast).nonzero().squeeze(1)
        a, w, E, fr = a[j], w[j], E[j], free[j]
        G = torch.matmul(a.transpose(1, 2), a * w.unsqueeze(2))  # Aᵀ W A
        if R is not None:
            G = G + R
        ff = fr.unsqueeze(2) & fr.unsqueeze(1)
        Gh = torch.where(ff, G, eye)  # G_FF ⊕ I_Z
        L, info = torch.linalg.cholesky_ex(Gh)
        # singular G_FF: a failed factorisation or a pivot at rounding level (as prepare_nnls)
        piv = torch.where(fr, L.diagonal(dim1=1, dim2=2).square(), inf)
        top = torch.where(fr, Gh.diagonal(dim1=1, dim2=2), zero).amax(1)
        bad = (info != 0) | (~(piv.amin(1) > 20.0 * M * eps * top) & fr.any(1))
        if bool(bad.any()):
            L = torch.where(bad.view(-1, 1, 1), eye, L)
        Ginv = torch.cholesky_inverse(L)  # symmetric: G_FF⁻¹ ⊕ I_Z
        # Cov_F = G_FF⁻¹ Eᵀ E G_FF⁻¹: its diagonal is the squared column norms of E G_FF⁻¹
        # (the columns of E on Z are 0, so those bands get 0)
        sj = torch.matmul(E, Ginv).square().sum(1).sqrt()
        sj = torch.where(bad.unsqueeze(1) & fr, inf, sj)
        std[j] = sj
        out[sl] = std.to(x.dtype)

    with cpu_threads(dev, 1):
        for_chunks(chunk, P, max(1, int(chunk_size)), workers_for(dev, num_threads))
    return out


def relative_std_map(cube: Tensor, std: Tensor, valid: Tensor | None = None) -> Tensor:
    """Mean relative standard deviation per pixel: ``Σ_m σ_m / Σ_m ŝ_m`` ``(h, w)``.

    The ratio of the band means (not the mean of per-band ratios, which bands near 0 dominate);
    NaN where ``valid`` is False or the spectrum sums to 0.

    Args:
        cube, std: ``(M, h, w)``; valid: ``(h, w)`` bool or ``None``.
    """
    if cube.shape != std.shape or cube.ndim != 3:
        raise ValueError(
            f"cube and std must both have shape (M, h, w), got {tuple(cube.shape)} and "
            f"{tuple(std.shape)}"
        )
    num = torch.nan_to_num(std, nan=0.0, posinf=float("inf")).sum(0)
    den = torch.nan_to_num(cube, nan=0.0).sum(0)
    rel = num / den
    bad = ~(den > 0)
    if valid is not None:
        bad |= ~valid.to(torch.bool)
    return torch.where(bad, torch.full_like(rel, float("nan")), rel)
