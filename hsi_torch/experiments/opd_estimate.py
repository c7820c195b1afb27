"""OPD estimation: the optical path difference of a view-channel from its transmittance spectrum
(docs/experiments.md, *OPD validation*, gives the estimator and its measured errors).

Between crossed polarizers ``T(k) ∝ ½[1 − cos(2π Δ k)]`` with ``k = 1/λ`` (nm⁻¹), so the
modulation frequency in ``k`` *is* the OPD ``Δ`` in nm. :func:`estimate_opd` (batched, any
device/dtype): **coarse**, the largest non-DC FFT bin of ``T`` resampled onto ``N`` uniform ``k``
samples, mean removed, windowed (one bin ``1/(N δk)`` ≈ 1.2 µm over 430–670 nm); **fft**, the same
zero-padded ``pad_factor``× with a parabolic peak; **fit**, a least-squares cosine
``T ≈ a + b·cos(2π Δ (k − k_c) + φ)`` on the original samples (grid search within ± one coarse
bin, then Levenberg–Marquardt), unbiased for a pure cosine where the FFT peak is not (2–5 fringes).

**Dispersion.** A single-frequency fit measures the *group* OPD ``Δ_g = d(Δ k)/dk = Δ − λ dΔ/dλ``
near ``k_0 = ½(1/λ_min + 1/λ_max)``, so the estimates are compared with the ray tracer's group OPD
at ``k_0`` (:func:`group_opd_nm`); the phase OPD at 550 nm (the
:class:`~hsi_torch.optics.ViewLayout` convention) is listed too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from hsi_torch.spectral import resample_spectra

__all__ = ["OPDEstimate", "estimate_opd", "group_opd_nm", "band_centre_nm"]


@dataclass
class OPDEstimate:
    """OPD estimates of ``P`` spectra (all tensors ``(P,)`` in the input's dtype/device).

    Attributes:
        coarse_nm: FFT bin of the largest non-DC peak × ``bin_nm``.
        fft_nm: zero-padded FFT peak refined by parabolic interpolation.
        fit_nm: least-squares cosine fit (``NaN`` when ``fit=False``).
        offset, amplitude, phase: the fit ``T ≈ offset + amplitude·cos(2π fit_nm (k − k_c) +
            phase)``, ``amplitude ≥ 0``.
        modulation: ``amplitude / offset`` (≈ 1 for an ideal crossed-polarizer fringe).
        rms: root-mean-square residual of the fit.
        bin_nm: one coarse FFT bin in nm of OPD; k_c: centre wavenumber of the fit (nm⁻¹).
    """

    coarse_nm: Tensor
    fft_nm: Tensor
    fit_nm: Tensor
    offset: Tensor
    amplitude: Tensor
    phase: Tensor
    modulation: Tensor
    rms: Tensor
    bin_nm: float
    k_c: float

    def model(self, wavelengths_nm: Tensor) -> Tensor:
        """``(P, L)`` fitted cosine at ``wavelengths_nm (L,)``."""
        k = 1.0 / wavelengths_nm.to(self.fit_nm) - self.k_c
        arg = 2 * math.pi * self.fit_nm[:, None] * k[None] + self.phase[:, None]
        return self.offset[:, None] + self.amplitude[:, None] * torch.cos(arg)


def _window(name: str, n: int, device, dtype) -> Tensor:
    if name == "hann":
        return torch.hann_window(n, periodic=False, device=device, dtype=dtype)
    if name in ("none", "rect", "boxcar"):
        return torch.ones(n, device=device, dtype=dtype)
    raise ValueError(f"window must be 'hann' or 'none', got {name!r}")


def _cosine_lstsq(x: Tensor, t: Tensor, f: Tensor) -> tuple[Tensor, Tensor]:
    """Linear LS of ``t (P, M)`` on ``[1, cos 2πfx, sin 2πfx]`` for frequencies ``f (P, F)``.

    Returns ``coef (P, F, 3)`` and the residual sum of squares ``(P, F)``."""
    arg = 2 * math.pi * f[..., None] * x[:, None, :]  # (P, F, M)
    basis = torch.stack([torch.ones_like(arg), torch.cos(arg), torch.sin(arg)], -1)  # (P,F,M,3)
    g = torch.einsum("pfmi,pfmj->pfij", basis, basis)
    g = g + 1e-12 * g.diagonal(dim1=-2, dim2=-1).mean(-1)[..., None, None] * torch.eye(
        3, device=x.device, dtype=x.dtype)
    rhs = torch.einsum("pfmi,pm->pfi", basis, t)
    coef = torch.linalg.solve(g, rhs.unsqueeze(-1)).squeeze(-1)
    res = t[:, None, :] - torch.einsum("pfmi,pfi->pfm", basis, coef)
    return coef, res.pow(2).sum(-1)


def _lm_refine(x: Tensor, t: Tensor, p: Tensor, iters: int) -> tuple[Tensor, Tensor]:
    """Levenberg–Marquardt on ``t ≈ a + c cos 2πfx + s sin 2πfx``, ``p = (a, c, s, f) (P, 4)``.

    Returns the refined parameters and the residual sum of squares ``(P,)``."""

    def residual(q: Tensor) -> Tensor:
        arg = 2 * math.pi * q[:, 3:4] * x
        return t - (q[:, 0:1] + q[:, 1:2] * torch.cos(arg) + q[:, 2:3] * torch.sin(arg))

    r = residual(p)
    cost = r.pow(2).sum(-1)
    mu = torch.full_like(cost, 1e-3)
    eye = torch.eye(4, device=x.device, dtype=x.dtype)
    for _ in range(iters):
        arg = 2 * math.pi * p[:, 3:4] * x
        cs, sn = torch.cos(arg), torch.sin(arg)
        dfr = 2 * math.pi * x * (-p[:, 1:2] * sn + p[:, 2:3] * cs)
        jac = torch.stack([torch.ones_like(cs), cs, sn, dfr], -1)  # (P, M, 4)
        jtj = jac.transpose(1, 2) @ jac
        jtr = (jac.transpose(1, 2) @ r.unsqueeze(-1)).squeeze(-1)
        d = jtj.diagonal(dim1=-2, dim2=-1).clamp_min(torch.finfo(x.dtype).tiny)
        lhs = jtj + mu[:, None, None] * torch.diag_embed(d) + 1e-30 * eye
        step = torch.linalg.solve(lhs, jtr.unsqueeze(-1)).squeeze(-1)
        cand = p + step
        r_c = residual(cand)
        c_c = r_c.pow(2).sum(-1)
        ok = c_c <= cost
        p = torch.where(ok[:, None], cand, p)
        r = torch.where(ok[:, None], r_c, r)
        cost = torch.where(ok, c_c, cost)
        mu = torch.where(ok, mu * 0.3, mu * 10.0).clamp(1e-9, 1e9)
    return p, cost


def estimate_opd(
    transmittance: Tensor,
    wavelengths_nm: Tensor,
    *,
    num_k: int | None = None,
    window: str = "hann",
    pad_factor: int = 32,
    fit: bool = True,
    search_bins: float = 1.0,
    search_points: int = 41,
    iters: int = 20,
) -> OPDEstimate:
    """OPD (nm) of transmittance spectra from their modulation in wavenumber ``k = 1/λ``.

    Args:
        transmittance: ``(P, M)`` (or ``(M,)``) spectra ``T(λ_m)``, any scale (a throughput or
            the line average of a monochromator scan only scales/damps the fringe).
        wavelengths_nm: ``(M,)`` strictly increasing wavelengths (nm), ``M ≥ 4``.
        num_k: samples of the uniform ``k`` grid (default ``M``); sets the coarse bin.
        window: ``'hann'`` or ``'none'`` (applied after the mean is removed).
        search_bins, search_points: the fit's grid search spans ``fft ± search_bins`` coarse
            bins with ``search_points`` frequencies (then ``iters`` LM steps).

    Returns:
        :class:`OPDEstimate`; OPDs in nm (``|Δ|``: the sign of an OPD is not observable).

    Convention:
        ``T(k) = a + b cos(2π Δ (k − k_c) + φ)``, ``k`` in nm⁻¹, ``k_c`` the mean of ``1/λ_m``.
    """
    if not isinstance(transmittance, Tensor):
        raise TypeError(f"transmittance must be a tensor, got {type(transmittance).__name__}")
    t = transmittance if transmittance.is_floating_point() else transmittance.double()
    if t.ndim == 1:
        t = t[None]
    if t.ndim != 2:
        raise ValueError(f"transmittance must be (P, M) or (M,), got {tuple(transmittance.shape)}")
    dev, dt = t.device, t.dtype
    wl = torch.as_tensor(wavelengths_nm, device=dev, dtype=dt).reshape(-1)
    m = wl.numel()
    if m != t.shape[1]:
        raise ValueError(f"wavelengths_nm has {m} samples but transmittance has {t.shape[1]}")
    if m < 4:
        raise ValueError(f"need at least 4 wavelengths, got {m}")
    if not bool((wl[1:] > wl[:-1]).all()) or bool((wl <= 0).any()):
        raise ValueError("wavelengths_nm must be positive and strictly increasing")
    if not bool(torch.isfinite(t).all()):
        raise ValueError("transmittance holds non-finite values")
    n = int(num_k or m)
    k_src = torch.flip(1.0 / wl, [0])  # ascending
    t_k = torch.flip(t, [1])
    kg = torch.linspace(float(k_src[0]), float(k_src[-1]), n, device=dev, dtype=dt)
    tu = resample_spectra(t_k, k_src, kg, dim=-1, extrapolate="edge")
    dk = float(kg[1] - kg[0])
    bin_nm = 1.0 / (n * dk)
    x = (tu - tu.mean(-1, keepdim=True)) * _window(window, n, dev, dt)
    spec = torch.fft.rfft(x, n=n).abs()
    spec[:, 0] = -1.0
    coarse = spec.argmax(-1).to(dt) * bin_nm
    # refined FFT: zero padding + parabolic interpolation, peak searched near the coarse bin
    npad = int(pad_factor) * n
    sp = torch.fft.rfft(x, n=npad).abs()
    fr = torch.arange(sp.shape[1], device=dev, dtype=dt) / (npad * dk)
    near = (fr[None] - coarse[:, None]).abs() <= bin_nm
    near &= fr[None] >= 0.5 * bin_nm
    j = torch.where(near, sp, torch.full_like(sp, -1.0)).argmax(-1)
    j = j.clamp(1, sp.shape[1] - 2)
    a, b, c = (sp.gather(1, (j + o)[:, None])[:, 0] for o in (-1, 0, 1))
    den = a - 2 * b + c
    delta = torch.where(den.abs() > 0, 0.5 * (a - c) / torch.where(den == 0, 1, den), 0)
    fft_nm = (j.to(dt) + delta.clamp(-1, 1)) / (npad * dk)

    k = 1.0 / wl
    k_c = float(k.mean())
    xs = (k - k_c)[None].expand(t.shape[0], -1)
    nan = torch.full_like(fft_nm, float("nan"))
    if not fit:
        return OPDEstimate(coarse, fft_nm, nan, nan, nan, nan, nan, nan, bin_nm, k_c)
    steps = torch.linspace(-1.0, 1.0, int(search_points), device=dev, dtype=dt)
    f_grid = (fft_nm[:, None] + search_bins * bin_nm * steps[None]).clamp_min(0.25 * bin_nm)
    coef, rss = _cosine_lstsq(xs, t, f_grid)
    best = rss.argmin(-1)
    c0 = coef[torch.arange(t.shape[0], device=dev), best]  # (P, 3)
    f0 = f_grid.gather(1, best[:, None])
    p, cost = _lm_refine(xs, t, torch.cat([c0, f0], -1), iters)
    off, cc, ss, f = p.unbind(-1)
    amp = torch.sqrt(cc**2 + ss**2)
    phase = -torch.atan2(ss, cc)
    neg = f < 0
    f = f.abs()
    phase = torch.where(neg, -phase, phase)
    modulation = amp / off.abs().clamp_min(torch.finfo(dt).tiny)
    rms = (cost / m).sqrt()
    return OPDEstimate(coarse, fft_nm, f, off, amp, phase, modulation, rms, bin_nm, k_c)


def band_centre_nm(wavelengths_nm: Tensor | list[float]) -> float:
    """Wavelength of the band-centre wavenumber ``k_0 = ½(1/λ_min + 1/λ_max)`` (nm)."""
    wl = torch.as_tensor(wavelengths_nm, dtype=torch.float64)
    return float(2.0 / (1.0 / wl.min() + 1.0 / wl.max()))


def group_opd_nm(brf: Any, alpha: Tensor, sigma: Tensor, wavelength_nm: float,
                 h_nm: float = 0.5) -> Tensor:
    """Group OPD ``Δ_g = d(Δ k)/dk = Δ − λ dΔ/dλ`` (nm) at ``wavelength_nm`` (central difference).

    This is the local frequency in ``k`` of the fringe ``cos(2π Δ(λ)/λ)``: what a
    single-frequency estimate over a band around ``wavelength_nm`` measures.

    Args:
        brf: :class:`~hsi_torch.optics.BRFConfig`.
        alpha, sigma: ray angles at the filter (rad), any broadcastable shape.
    """
    lam = torch.tensor([wavelength_nm - h_nm, wavelength_nm, wavelength_nm + h_nm],
                       dtype=torch.float64, device=alpha.device)
    d = brf.opd_nm(alpha.to(torch.float64)[..., None], sigma.to(torch.float64)[..., None], lam)
    dd = (d[..., 2] - d[..., 0]) / (2 * h_nm)
    return (d[..., 1] - wavelength_nm * dd).to(alpha.dtype)
