"""The camera's linear forward model in factored form: one small sensing matrix per pixel.

Every reconstructed pixel ``p`` sees its spectrum ``s_p (M,)`` through ``V`` views and ``3``
colours. The sensing matrix factors into a transmittance per view and band, a throughput per view
and a response per colour and band:

.. math::

    A_p[(v, c), m] = g_v(p) \\; B_v(p, λ_m) \\; Δλ_m \\, φ^c(λ_m)

with the observation index ``o = 3·v + c`` (view-major; ``v = 0`` the reference view). Holding the
factors instead of the dense ``(P, 3V, M)`` matrices takes ``V·M`` numbers a pixel instead of
``3·V·M`` and makes ``A s`` and ``Aᵀ y`` two small contractions each. Dense matrices and Gram
matrices are built on demand for sub-batches (:meth:`SensingModel.dense`,
:meth:`SensingModel.gram`).

Convention:
    ``transmittance``: ``(P, V, M)`` ``B_v(p, λ_m)`` (dimensionless); ``gain``: ``(P, V)``
    ``g_v(p)``; ``response``: ``(3, M)`` ``Δλ_m φ^c(λ_m)`` (data units per unit reflectance, the
    band width folded in). ``P = 1`` broadcasts one sensing matrix to every pixel (e.g. a design
    evaluated at one scene point). Observations ``(P, 3V)``, spectra ``(P, M)``.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

__all__ = ["SensingModel", "DenseSensing", "OnDevice", "PerPixel"]


class OnDevice:
    """``device`` and ``dtype`` of an object from the attribute named by its ``_ON`` (a tensor,
    or an object with ``device`` and ``dtype``, such as the sensing it holds)."""

    _ON = ""

    @property
    def device(self) -> torch.device:
        return getattr(self, self._ON).device

    @property
    def dtype(self) -> torch.dtype:
        return getattr(self, self._ON).dtype


class PerPixel(OnDevice):
    """Sizes of a per-pixel sensing whose ``_ON`` tensor is ``(P, ·, M)`` (``P = 1``: shared)."""

    @property
    def num_pixels(self) -> int:
        return int(getattr(self, self._ON).shape[0])

    @property
    def num_bands(self) -> int:
        return int(getattr(self, self._ON).shape[2])

    @property
    def shared(self) -> bool:
        """One sensing matrix for every pixel (``P = 1``)."""
        return self.num_pixels == 1

    def _index(self, idx: Tensor | slice | Sequence[int]) -> Tensor | slice:
        return idx if isinstance(idx, slice) else torch.as_tensor(idx, dtype=torch.long,
                                                                   device=self.device)


def _gram(a: Tensor, mask: Tensor | None, reg: Tensor | None) -> Tensor:
    """``aᵀ W a (+ reg)`` for dense ``a (n|1, O, M)`` and an ``(n, O)`` bool mask."""
    if mask is not None and a.shape[0] == 1 and mask.shape[0] != 1:
        a = a.expand(mask.shape[0], -1, -1)
    aw = a if mask is None else a * mask.unsqueeze(2).to(a.dtype)
    G = torch.matmul(a.transpose(1, 2), aw)
    return G if reg is None else G + reg


def _rows(t: Tensor, idx: Tensor | slice) -> Tensor:
    """Rows ``idx`` (a slice: a view; an index tensor: a copy) of ``t``."""
    return t[idx] if isinstance(idx, slice) else t.index_select(0, idx)


class SensingModel(PerPixel):
    """Per-pixel linear sensing ``y_p = A_p s_p`` with ``A_p = g_v(p) B_v(p, λ) Δλ φ^c(λ)``.

    A small physics class in the style of a deep-inverse ``Physics``: ``A``, ``A_adjoint``,
    ``gram`` and ``dense`` act on batches of pixels; every method takes an optional pixel index
    so that sub-batches are processed without copying the factors.

    Args:
        transmittance: ``(P, V, M)`` view transmittances ``B`` (``P = 1``: shared by all pixels).
        gain: ``(P, V)`` view throughputs ``g`` (``P`` as ``transmittance``).
        response: ``(3, M)`` ``Δλ_m φ^c(λ_m)``, or ``(C, M)`` for ``C`` channels per view.

    All three must share device and floating dtype.

    Example:
        >>> B = torch.rand(100, 10, 25); g = torch.ones(100, 10); r = torch.rand(3, 25)
        >>> model = SensingModel(B, g, r)
        >>> y = model.A(torch.rand(100, 25))         # (100, 30)
        >>> model.A_adjoint(y).shape
        torch.Size([100, 25])
    """

    _ON = "transmittance"

    def __init__(self, transmittance: Tensor, gain: Tensor, response: Tensor) -> None:
        for name, t, nd in (("transmittance", transmittance, 3), ("gain", gain, 2),
                            ("response", response, 2)):  # fmt: skip
            if not isinstance(t, Tensor):
                raise TypeError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
            if t.ndim != nd:
                raise ValueError(f"{name} must have {nd} dimensions, got {tuple(t.shape)}")
            if not t.is_floating_point():
                raise TypeError(f"{name} must be floating point, got {t.dtype}")
        P, V, M = transmittance.shape
        if gain.shape != (P, V):
            raise ValueError(f"gain must have shape (P, V) = ({P}, {V}), got {tuple(gain.shape)}")
        if response.shape[1] != M:
            raise ValueError(f"response must have shape (C, {M}), got {tuple(response.shape)}")
        if len({transmittance.device, gain.device, response.device}) != 1:
            raise ValueError("transmittance, gain and response must be on one device")
        if len({transmittance.dtype, gain.dtype, response.dtype}) != 1:
            raise TypeError("transmittance, gain and response must share one dtype")
        self.transmittance = transmittance
        self.gain = gain
        self.response = response

    # -- construction ---------------------------------------------------------------------------
    @classmethod
    def from_factors(
        cls,
        transmittance: Tensor,
        gain: Tensor,
        phi: Tensor,
        band_widths_nm: Tensor,
        *,
        pixel_index: Tensor | None = None,
        device: torch.device | str | None = None,
        dtype: torch.dtype | None = None,
    ) -> SensingModel:
        """From calibration-bundle layout: ``B (V, M, h, w)``, ``gain (V, h, w)``, ``phi (3, M)``.

        Args:
            transmittance: ``(V, M, h, w)`` (or ``(V, M, P)``) transmittances.
            gain: ``(V, h, w)`` (or ``(V, P)``) throughputs.
            phi: ``(3, M)`` response per nm; band_widths_nm: ``(M,)`` ``Δλ_m``.
            pixel_index: ``(P,)`` flat row-major pixels to keep (default all).
            device, dtype: of the result (default: ``transmittance``'s).
        """
        dt = dtype or (transmittance.dtype if transmittance.is_floating_point() else None)
        V, M = int(transmittance.shape[0]), int(transmittance.shape[1])
        B = torch.as_tensor(transmittance).reshape(V, M, -1)
        g = torch.as_tensor(gain).reshape(V, -1)
        if pixel_index is not None:
            idx = torch.as_tensor(pixel_index, dtype=torch.long, device=B.device)
            B, g = B.index_select(2, idx), g.index_select(1, idx)
        B = B.to(device=device, dtype=dt).permute(2, 0, 1).contiguous()  # (P, V, M)
        g = g.to(device=device, dtype=dt).T.contiguous()
        r = (torch.as_tensor(phi, dtype=torch.float64)
             * torch.as_tensor(band_widths_nm, dtype=torch.float64)).to(device=B.device, dtype=dt)
        return cls(B, g, r)

    # -- shapes -------------------------------------------------------------------------------
    @property
    def num_views(self) -> int:
        return int(self.transmittance.shape[1])

    @property
    def num_channels(self) -> int:
        return int(self.response.shape[0])

    @property
    def num_obs(self) -> int:
        return self.num_views * self.num_channels

    def to(self, device: torch.device | str | None = None,
           dtype: torch.dtype | None = None) -> SensingModel:
        """The same model on another device / in another floating dtype."""
        return SensingModel(*(t.to(device=device, dtype=dtype) for t in
                              (self.transmittance, self.gain, self.response)))

    def _factors(self, idx: Tensor | slice | None) -> tuple[Tensor, Tensor]:
        B, g = self.transmittance, self.gain
        if self.shared or idx is None:
            return B, g
        return _rows(B, idx), _rows(g, idx)

    # -- operators ------------------------------------------------------------------------------
    def A(self, s: Tensor, idx: Tensor | slice | None = None) -> Tensor:
        """Observations ``y = A s``: ``(n, M)`` → ``(n, 3V)`` for pixels ``idx`` (default all).

        With a shared model (``P = 1``) every row of ``s`` uses the same matrix.
        """
        B, g = self._factors(idx)
        n = s.shape[0]
        # contiguous rows: from a transposed view, bmm on CPU makes one BLAS call per pixel
        # (16 s instead of 0.08 s on 32 768 px)
        rs = s.contiguous().unsqueeze(2) * self.response.T  # (n, M, C): r_cm s_m
        if B.shape[0] == 1:
            y = torch.matmul(B, rs)  # (n, V, C)
        else:
            y = torch.bmm(B, rs)  # reads B once; no (n, V, M) temporary
        return (y * g.unsqueeze(2)).reshape(n, -1)

    def A_adjoint(self, y: Tensor, idx: Tensor | slice | None = None) -> Tensor:
        """``Aᵀ y``: ``(n, 3V)`` → ``(n, M)``. Masked observations must be zero in ``y``."""
        B, g = self._factors(idx)
        n = y.shape[0]
        u = y.reshape(n, self.num_views, self.num_channels) * g.unsqueeze(2)  # (n, V, C)
        # Σ_c r_cm Σ_v u_vc B_vm: one (C, V) × (V, M) product per pixel reads B once
        ub = torch.matmul(u.transpose(1, 2), B)  # (n, C, M)
        return (ub * self.response).sum(1)

    def dense(self, idx: Tensor | slice | None = None) -> Tensor:
        """Dense sensing matrices ``(n, 3V, M)`` of pixels ``idx`` (``(1, 3V, M)`` if shared)."""
        B, g = self._factors(idx)
        a = (g.unsqueeze(2) * B).unsqueeze(2) * self.response  # (n, V, C, M)
        return a.reshape(a.shape[0], -1, self.num_bands)

    def columns(self, idx: Tensor, cols: Tensor) -> Tensor:
        """Columns ``A_p[:, cols_p]`` ``(n, 3V, k)`` of pixels ``idx (n,)`` at band indices
        ``cols (n, k)`` (a different set per pixel)."""
        B, g = self._factors(idx)
        n, k = cols.shape
        if B.shape[0] == 1:
            B, g = B.expand(n, -1, -1), g.expand(n, -1)
        Bc = B.gather(2, cols.unsqueeze(1).expand(n, self.num_views, k))  # (n, V, k)
        rc = self.response.T[cols]  # (n, k, C)
        a = (g.unsqueeze(2) * Bc).unsqueeze(2) * rc.transpose(1, 2).unsqueeze(1)  # (n, V, C, k)
        return a.reshape(n, -1, k)

    def gram(
        self, mask: Tensor | None = None, idx: Tensor | slice | None = None,
        reg: Tensor | None = None,
    ) -> Tensor:
        """Gram matrices ``G = Aᵀ W A (+ reg)`` ``(n, M, M)`` of pixels ``idx``.

        Args:
            mask: ``(n, 3V)`` bool observation mask ``W`` (``None``: all observations).
            reg: optional ``(M, M)`` added (e.g. ``β DᵀD``).

        When the mask keeps or drops whole views (all channels of a view alike, as the static
        mask does), the factored form is used: ``G = (Bᵀ diag(w g²) B) ⊙ (rᵀ r)`` with ``w`` the
        per-view mask and ``r`` the response — a ``V``-term product per pixel instead of a
        ``3V``-term one, without forming the dense matrices (equal to rounding).
        """
        B, g = self._factors(idx)
        V, C = self.num_views, self.num_channels
        wv = None
        if mask is not None and B.shape[0] == mask.shape[0] and mask.shape[1] == V * C:
            mv = mask.view(-1, V, C)
            if bool((mv == mv[:, :, :1]).all()):
                wv = mv[:, :, 0]
        if B.shape[0] == 1 or (mask is not None and wv is None):
            return _gram(self.dense(idx), mask, reg)
        w = g.square()
        if wv is not None:
            w = w * wv.to(w.dtype)
        G = torch.matmul((B * w.unsqueeze(2)).transpose(1, 2), B)  # (n, M, M)
        G.mul_(self.response.T @ self.response)
        return G if reg is None else G.add_(reg)

    def select(self, idx: Tensor | slice | Sequence[int]) -> SensingModel:
        """The model of a subset of pixels (a view for a slice, else a copy of their factors)."""
        if self.shared:
            return self
        i = self._index(idx)
        return SensingModel(_rows(self.transmittance, i), _rows(self.gain, i), self.response)

    def memory_bytes(self) -> int:
        """Bytes held by the factors."""
        return int(sum(t.numel() * t.element_size()
                       for t in (self.transmittance, self.gain, self.response)))


class DenseSensing(PerPixel):
    """Per-pixel sensing given by dense matrices ``A (P, O, M)`` (or ``(1, O, M)``, shared).

    The same interface as :class:`SensingModel` (``A``, ``A_adjoint``, ``dense``, ``gram``), for
    problems without the camera's factored structure (other designs, tests, user matrices).
    """

    _ON = "matrices"

    def __init__(self, A: Tensor) -> None:
        if not isinstance(A, Tensor):
            raise TypeError(f"A must be a torch.Tensor, got {type(A).__name__}")
        if A.ndim == 2:
            A = A.unsqueeze(0)
        if A.ndim != 3:
            raise ValueError(f"A must have shape (O, M) or (P, O, M), got {tuple(A.shape)}")
        self.matrices = A

    @property
    def num_obs(self) -> int:
        return int(self.matrices.shape[1])

    def to(self, device: torch.device | str | None = None,
           dtype: torch.dtype | None = None) -> DenseSensing:
        return DenseSensing(self.matrices.to(device=device, dtype=dtype))

    def dense(self, idx: Tensor | slice | None = None) -> Tensor:
        return self.matrices if self.shared or idx is None else _rows(self.matrices, idx)

    def columns(self, idx: Tensor, cols: Tensor) -> Tensor:
        """Columns ``A_p[:, cols_p]`` ``(n, O, k)`` of pixels ``idx`` at band indices ``cols``."""
        a = self.dense(idx)
        n, k = cols.shape
        if a.shape[0] == 1:
            a = a.expand(n, -1, -1)
        return a.gather(2, cols.unsqueeze(1).expand(n, a.shape[1], k))

    def A(self, s: Tensor, idx: Tensor | slice | None = None) -> Tensor:
        a = self.dense(idx)
        if a.shape[0] == 1:
            return s @ a[0].T
        return torch.bmm(a, s.unsqueeze(2)).squeeze(2)

    def A_adjoint(self, y: Tensor, idx: Tensor | slice | None = None) -> Tensor:
        a = self.dense(idx)
        if a.shape[0] == 1:
            return y @ a[0]
        return torch.bmm(y.unsqueeze(1), a).squeeze(1)

    def gram(
        self, mask: Tensor | None = None, idx: Tensor | slice | None = None,
        reg: Tensor | None = None,
    ) -> Tensor:
        return _gram(self.dense(idx), mask, reg)

    def select(self, idx: Tensor | slice | Sequence[int]) -> DenseSensing:
        return self if self.shared else DenseSensing(_rows(self.matrices, self._index(idx)))

    def memory_bytes(self) -> int:
        return int(self.matrices.numel() * self.matrices.element_size())
