"""The frame-independent part of the spatial solve: ``G``, ``ρ``, the factor and the grid.

:func:`prepare_spatial` builds the active grid and a :class:`ShiftedInverse`: ``G_p + ρI``
factorised once when first needed (batched Cholesky, :data:`FACTOR_CHUNK` pixels at a time), its
inverse formed with ``torch.cholesky_inverse`` and applied by a matrix–vector product per pixel
(4× faster than ``torch.cholesky_solve`` for 100 000 25×25 systems on a CPU), kept either dense
(the torch path) or packed by rows (the compiled CPU path: half the memory);
:meth:`SpatialProblem.for_frame` adapts it to one frame (its valid pixels, pixels whose frame
mask changed their Gram matrix, guided edge weights); :func:`bundle_spatial_problem` caches it
with the bundle's NNLS factorisation, and the packed factor in the precomputation cache beside
the bundle's entry (a second process loads it). The default penalty is :data:`RHO_SCALE` × the
median of ``trace(G_p)/M`` over the active pixels.
"""

from __future__ import annotations

import functools
import math
import weakref
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from hsi_torch.recon import precompute_cache as disk
from hsi_torch.recon.nnls import NNLSProblem
from hsi_torch.recon.sensing import BundleSensing
from hsi_torch.recon.spatial import _compiled as compiled
from hsi_torch.recon.spatial.operators import grid_edges

__all__ = ["RHO_SCALE", "SpatialProblem", "prepare_spatial", "guide_weights",
           "bundle_spatial_problem"]


#: The default ADMM penalty ``ρ`` relative to the median of ``trace(G_p)/M`` (the mean
#: eigenvalue of the per-pixel Gram matrices). ``G``'s poorly determined spectral directions,
#: where the prior does its work, have eigenvalues far below the mean and converge at a rate
#: ``≈ 1 − g/ρ``: measured on the full-size prototype's frames, 10 iterations at 0.1 reach the
#: quality (PSNR against the truth) of the converged answer, which 1.0 needed 40–130 for.
RHO_SCALE = 0.1


@dataclass
class SpatialProblem:
    """The frame-independent part of the spatial solve: ``G``, ``ρ``, the factor and the grid.

    Build with :func:`prepare_spatial`; reuse for every frame of one bundle.

    Attributes:
        gram: ``(P|1, M, M)``; rho: the scalar ADMM penalty; factor: ``(G + ρI)⁻¹`` from one
            Cholesky factorisation, formed when first needed, dense (:attr:`inv`, the torch
            path) or packed by rows (the compiled path), shared by :meth:`for_frame`'s
            problems; pixel_index: ``(P,)`` flat indices
            of the pixels in the ``(h, w)`` frame; frame_size; active: ``(P,)`` bool, pixels in
            the TV graph; ex, ey: :func:`grid_edges` of the active grid.
        row_index, row_gram, row_inv: ``(k,)``, ``(k, M, M)``, ``(k, M, M)`` pixels whose Gram
            matrix differs in this frame (a frame mask: saturation, non-finite samples) and their
            own ``G`` and ``(G + ρI)⁻¹`` (:meth:`for_frame`); ``None``: none.
    """

    gram: Tensor
    rho: float
    factor: ShiftedInverse
    pixel_index: Tensor
    frame_size: tuple[int, int]
    active: Tensor
    ex: Tensor
    ey: Tensor
    row_index: Tensor | None = None
    row_gram: Tensor | None = None
    row_inv: Tensor | None = None

    @property
    def num_pixels(self) -> int:
        return int(self.pixel_index.shape[0])

    @property
    def inv(self) -> Tensor:
        """``(P|1, M, M)`` dense ``(G + ρI)⁻¹`` (formed on first use)."""
        return self.factor.dense()

    @property
    def num_bands(self) -> int:
        return int(self.gram.shape[-1])

    def for_frame(
        self, active: Tensor, rows: Tensor | None = None, row_gram: Tensor | None = None,
        weights: tuple[Tensor, Tensor] | None = None,
    ) -> SpatialProblem:
        """This problem for one frame: its ``active (P,)`` pixels and, for the pixels ``rows``,
        the frame's own Gram matrices ``row_gram (k, M, M)`` (factorised here, ``k`` systems;
        the stored factor of the other pixels is shared, not copied). ``weights``: ``(h, w)``
        edge weights in ``[0, 1]`` along x and y (guided TV, :func:`guide_weights`)."""
        P = self.num_pixels
        if active.shape != (P,):
            raise ValueError(f"active must be ({P},), got {tuple(active.shape)}")
        active = active.to(device=self.gram.device, dtype=torch.bool)
        h, w = self.frame_size
        grid = torch.zeros(h * w, dtype=torch.bool, device=self.gram.device)
        grid[self.pixel_index[active]] = True
        ex, ey = grid_edges(grid.view(h, w))
        if weights is not None:
            ex = ex.to(self.gram.dtype) * weights[0].to(self.gram.dtype)
            ey = ey.to(self.gram.dtype) * weights[1].to(self.gram.dtype)
        rows, row_gram, r_inv = self._rows(rows, row_gram)
        return SpatialProblem(self.gram, self.rho, self.factor, self.pixel_index,
                              self.frame_size, active, ex, ey, rows, row_gram, r_inv)

    def with_rows(self, rows: Tensor | None, row_gram: Tensor | None) -> SpatialProblem:
        """This frame problem with other pixels' own Gram matrices (:meth:`for_frame`'s
        ``rows``, ``row_gram``): the same active pixels and TV graph, shared with this one
        together with the compiled path's layout of it (already built for this problem: not
        built again). A sequence's frames with the same valid pixels use it."""
        rows, row_gram, r_inv = self._rows(rows, row_gram)
        new = SpatialProblem(self.gram, self.rho, self.factor, self.pixel_index,
                             self.frame_size, self.active, self.ex, self.ey, rows, row_gram,
                             r_inv)
        for key in ("_graph", "_fgp_grid"):  # cached properties: independent of the rows
            if key in self.__dict__:
                new.__dict__[key] = self.__dict__[key]
        return new

    def _rows(self, rows: Tensor | None, row_gram: Tensor | None
              ) -> tuple[Tensor | None, Tensor | None, Tensor | None]:
        """``rows``, ``row_gram`` and their ``(G + ρI)⁻¹`` (all ``None`` for no rows)."""
        if rows is None or not rows.numel():
            return None, None, None
        eye = torch.eye(self.num_bands, dtype=self.gram.dtype, device=self.gram.device)
        L, _ = torch.linalg.cholesky_ex(row_gram + self.rho * eye)
        return rows, row_gram, torch.cholesky_inverse(L)

    def compiled_inputs(self) -> tuple[np.ndarray, tuple[np.ndarray, ...]] | None:
        """The compiled CPU path's inputs: ``(G + ρI)⁻¹`` packed by rows
        (:func:`~._compiled.pack_inverse_rows`, formed on first use) and the graph (neighbour
        positions and edge weights per pixel, see :mod:`hsi_torch.recon.spatial._compiled`);
        ``None`` where that path does not apply (numba absent, not on the CPU, or the pixels
        not in row-major order)."""
        if not compiled.AVAILABLE or self.gram.device.type != "cpu":
            return None
        pix = self.pixel_index.numpy()
        if pix.size > 1 and not bool((pix[1:] > pix[:-1]).all()):
            return None
        return self.factor.packed(self._graph[0], self.num_pixels), self._graph

    @functools.cached_property
    def _graph(self) -> tuple[np.ndarray, ...]:
        """Per pixel: neighbour positions and edge weights (built once per frame problem: the
        λ searches solve one frame many times)."""
        h, w = self.frame_size
        pix = self.pixel_index.numpy()
        n = pix.size
        dt = self.gram.numpy().dtype
        pos = np.full(h * w, -1, np.int64)
        pos[pix] = np.arange(n)
        ex = self.ex.reshape(-1).numpy().astype(dt)
        ey = self.ey.reshape(-1).numpy().astype(dt)
        own = np.arange(n)
        wx, wy = ex[pix], ey[pix]
        right = np.where(wx != 0, pos[np.minimum(pix + 1, h * w - 1)], own)
        down = np.where(wy != 0, pos[np.minimum(pix + w, h * w - 1)], own)
        has_left = pix % w > 0
        wl = np.where(has_left, ex[np.maximum(pix - 1, 0)], 0).astype(dt)
        left = np.where(wl != 0, pos[np.maximum(pix - 1, 0)], own)
        wu = np.where(pix >= w, ey[np.maximum(pix - w, 0)], 0).astype(dt)
        up = np.where(wu != 0, pos[np.maximum(pix - w, 0)], own)
        row_ptr = np.searchsorted(pix // w, np.arange(h + 1)).astype(np.int64)
        return row_ptr, right, down, left, up, wx, wy, wl, wu

    def fgp_grid(self) -> tuple[np.ndarray, ...]:
        """The row layout of the compiled TV prox (:func:`~._compiled.fgp_grid`)."""
        return self._fgp_grid

    @functools.cached_property
    def _fgp_grid(self) -> tuple[np.ndarray, ...]:
        dt = self.gram.numpy().dtype
        return compiled.fgp_grid(self._graph, self.pixel_index.numpy(), self.frame_size,
                                 self.ex.numpy().astype(dt), self.ey.numpy().astype(dt))

    def _apply(self, x: Tensor, matrices: Tensor, row_matrices: Tensor | None) -> Tensor:
        """``matrices_p x_p`` for all pixels, the frame's own ``row_matrices`` on ``row_index``
        (the compiled product on the CPU where nothing needs a gradient: torch's batched
        ``(P, M, M) @ (P, M, 1)`` product is ≈ 5× slower for ``M = 25``)."""
        out = _rowvec(x, matrices)
        if self.row_index is not None:
            out = out.index_copy(0, self.row_index,
                                 _rowvec(x.index_select(0, self.row_index), row_matrices))
        return out

    def apply_inv(self, x: Tensor) -> Tensor:
        """``(G_p + ρI)⁻¹ x_p`` for all pixels ``(P, M)``."""
        return self._apply(x, self.inv, self.row_inv)

    def apply_gram(self, x: Tensor) -> Tensor:
        """``G_p x_p`` for all pixels ``(P, M)``."""
        return self._apply(x, self.gram, self.row_gram)

    def to_cube(self, x: Tensor) -> Tensor:
        """``(P, M)`` → ``(M, h, w)`` (0 off the pixel set). Differentiable."""
        h, w = self.frame_size
        cube = torch.zeros((x.shape[1], h * w), dtype=x.dtype, device=x.device)
        cube = cube.index_copy(1, self.pixel_index, x.transpose(0, 1))
        return cube.view(x.shape[1], h, w)

    def from_cube(self, cube: Tensor) -> Tensor:
        """``(M, h, w)`` → ``(P, M)``. Differentiable."""
        return cube.reshape(cube.shape[0], -1).index_select(1, self.pixel_index).transpose(0, 1)


def prepare_spatial(
    gram: Tensor,
    pixel_index: Tensor,
    frame_size: tuple[int, int],
    active: Tensor | None = None,
    rho: float | None = None,
) -> SpatialProblem:
    """Factorise ``G_p + ρI`` once (batched Cholesky) and build the active grid.

    Args:
        gram: ``(P, M, M)`` per-pixel or ``(1, M, M)`` shared Gram matrices ``AᵀWA + βDᵀD``
            (float32/float64, any device).
        pixel_index: ``(P,)`` int64 flat indices ``i·w + j`` of the pixels in the frame.
        frame_size: ``(h, w)``.
        active: ``(P,)`` bool, pixels coupled by TV (default all). Inactive pixels (e.g. too few
            views) are solved alone (their prox is the projection on ``≥ 0``).
        rho: ADMM penalty (default :data:`RHO_SCALE` × the median of ``trace(G_p)/M`` over the
            active pixels).

    Returns:
        :class:`SpatialProblem`.
    """
    if gram.ndim != 3 or gram.shape[1] != gram.shape[2]:
        raise ValueError(f"gram must be (P, M, M) or (1, M, M), got {tuple(gram.shape)}")
    if gram.dtype not in (torch.float32, torch.float64):
        raise TypeError(f"gram must be float32 or float64, got {gram.dtype}")
    h, w = (int(v) for v in frame_size)
    pix = pixel_index.to(device=gram.device, dtype=torch.long)
    if pix.ndim != 1 or (gram.shape[0] not in (1, pix.shape[0])):
        raise ValueError(
            f"pixel_index must be (P,) with P = gram's {gram.shape[0]} pixels, got "
            f"{tuple(pix.shape)}"
        )
    P = pix.shape[0]
    if P and (int(pix.min()) < 0 or int(pix.max()) >= h * w):
        raise ValueError(f"pixel_index out of range for the frame size {(h, w)}")
    if active is None:
        active = torch.ones((P,), dtype=torch.bool, device=gram.device)
    elif active.shape != (P,):
        raise ValueError(f"active must be ({P},), got {tuple(active.shape)}")
    active = active.to(device=gram.device, dtype=torch.bool)
    m = gram.shape[-1]
    with torch.no_grad():
        if rho is None:
            tr = gram.diagonal(dim1=1, dim2=2).sum(1) / m
            sel = tr[active] if tr.shape[0] == P and bool(active.any()) else tr
            rho = RHO_SCALE * float(sel.median()) if sel.numel() else 1.0
            if not rho > 0:
                rho = 1.0
    if not float(rho) > 0:
        raise ValueError(f"rho must be > 0, got {rho}")
    factor = ShiftedInverse(gram, float(rho))
    if gram.requires_grad and torch.is_grad_enabled():
        factor.dense()  # differentiable with respect to G: formed here, in the graph
    grid = torch.zeros(h * w, dtype=torch.bool, device=gram.device)
    grid[pix[active]] = True
    ex, ey = grid_edges(grid.view(h, w))
    return SpatialProblem(gram, float(rho), factor, pix, (h, w), active, ex, ey)


class ShiftedInverse:
    """``(G_p + ρI)⁻¹`` of a problem's pixels, formed from one batched Cholesky factorisation
    (:data:`FACTOR_CHUNK` pixels at a time) when first needed, in the form its user reads: dense
    ``(P|1, M, M)`` (:meth:`dense`: the torch path, any device, differentiable) or packed by
    rows (:meth:`packed`: the compiled CPU path, half the memory; the dense one is not formed
    then)."""

    def __init__(self, gram: Tensor, rho: float) -> None:
        self.gram, self.rho = gram, float(rho)
        self._dense: Tensor | None = None
        self._packed: np.ndarray | None = None
        #: ``(entry, key)`` of the precomputation cache holding the packed form (set by
        #: :func:`bundle_spatial_problem`; ``None``: computed in every process)
        self.disk: tuple[Path, str] | None = None

    def dense(self) -> Tensor:
        """``(P|1, M, M)`` symmetric, contiguous."""
        if self._dense is None:
            self._dense = _shifted_inverse(self.gram, self.rho)
        return self._dense

    def packed(self, row_ptr: np.ndarray, num_pixels: int) -> np.ndarray:
        """:func:`~._compiled.pack_inverse_rows` of the ``num_pixels`` pixels in rows
        ``row_ptr`` (float32/float64 like ``G``; a shared ``G`` is expanded)."""
        if self._packed is not None and self.disk is not None:  # its entry changed since?
            why = disk.changed_since_load(disk.loaded_stamp({"inverse": self._packed}))
            if why is not None:
                disk._warn(f"precomputation cache entry {self.disk[0]}: {why} after it was "
                           "loaded; loaded again if intact, else recomputed")  # fmt: skip
                self._packed = None
        if self._packed is None:
            m = self.gram.shape[-1]
            dt = self.gram.numpy().dtype if self.gram.device.type == "cpu" else np.float64

            def chunks():
                for s, e in compiled.row_chunks(row_ptr, FACTOR_CHUNK):
                    if self._dense is not None:
                        inv = self._dense if self._dense.shape[0] == 1 else self._dense[s:e]
                    else:
                        g = self.gram if self.gram.shape[0] == 1 else self.gram[s:e]
                        inv = _shifted_inverse(g.detach(), self.rho)
                    yield s, inv.detach().expand(e - s, m, m).numpy()

            size = num_pixels * (m * (m + 1) // 2)
            if self.disk is not None:
                got = disk.load_entry(*self.disk)
                arr = None if got is None else got[0].get("inverse")
                if arr is not None and arr.shape == (size,) and arr.dtype == dt:
                    self._packed = arr
                    return arr
                if got is not None:
                    disk._warn(f"{self.disk[0]}: not the packed inverse of this problem "
                               f"(recomputed)")
            self._packed = compiled.pack_inverse_rows(chunks(), row_ptr, m, dt)
            if self.disk is not None:
                disk.save_entry(self.disk[0], self.disk[1], {"inverse": self._packed},
                                {"rho": self.rho, "layout": "upper triangle by row runs"})
        return self._packed


#: Layout version of the TV factor's precomputation-cache entries (:func:`bundle_spatial_problem`).
TV_CACHE_LAYOUT = 1

#: Pixels factorised at once by :func:`prepare_spatial`: the Cholesky factor and the shifted
#: Gram matrices exist for one chunk at a time (at the full-size prototype's 306 000 pixels the
#: whole-batch temporaries were 1.5 GB beside the 0.77 GB inverse).
FACTOR_CHUNK = 16384


def _shifted_inverse(gram: Tensor, rho: float) -> Tensor:
    """``(G_p + ρI)⁻¹`` for ``gram (P|1, M, M)`` by batched Cholesky, :data:`FACTOR_CHUNK`
    pixels at a time into one ``(P|1, M, M)`` tensor (symmetric, contiguous)."""
    n, m = gram.shape[0], gram.shape[-1]
    eye = torch.eye(m, dtype=gram.dtype, device=gram.device)
    if gram.requires_grad and torch.is_grad_enabled():  # differentiable w.r.t. G: one op
        L, info = torch.linalg.cholesky_ex(gram + rho * eye)
        if bool((info != 0).any()):
            raise ValueError("G + rho*I is not positive definite: the Gram matrices are not "
                             "symmetric positive semi-definite")
        return torch.cholesky_inverse(L)
    inv = torch.empty((n, m, m), dtype=gram.dtype, device=gram.device)
    with torch.no_grad():
        for s in range(0, n, FACTOR_CHUNK):
            e = min(n, s + FACTOR_CHUNK)
            L, info = torch.linalg.cholesky_ex(gram[s:e] + rho * eye)
            if bool((info != 0).any()):
                raise ValueError("G + rho*I is not positive definite: the Gram matrices are not "
                                 "symmetric positive semi-definite")
            inv[s:e] = torch.cholesky_inverse(L)
    return inv


def _rowvec(x: Tensor, K: Tensor) -> Tensor:
    """``K_p x_p`` for symmetric ``K (P|1, M, M)`` and ``x (P, M)``."""
    if (compiled.AVAILABLE and x.device.type == "cpu" and K.device.type == "cpu"
            and x.dtype == K.dtype and K.is_contiguous()
            and not ((x.requires_grad or K.requires_grad) and torch.is_grad_enabled())):
        xc = x.detach().contiguous()
        out = torch.empty_like(xc)
        compiled.sym_apply(K.detach().numpy(), xc.numpy(), out.numpy())
        return out
    return (K @ x.unsqueeze(-1)).squeeze(-1)


_FACTORS: weakref.WeakKeyDictionary[NNLSProblem, SpatialProblem] = weakref.WeakKeyDictionary()


def guide_weights(sp: SpatialProblem, y: Tensor, mask: Tensor, sigma: float,
                  contrast: float = 3.0) -> tuple[Tensor, Tensor]:
    """Edge weights of a guided TV from the reference view's own RGB samples (``o = 0, 1, 2``).

    ``w = 1 / (1 + (‖Δrgb‖ / (contrast · sqrt(6) σ̂))²)`` between 4-neighbours: 1 where the
    reference view's colour step is within the noise (``sqrt(6)·σ̂`` is the noise of ``‖Δrgb‖``),
    small across real edges, so TV smooths less across edges the RGB image shows. 1 where the
    reference view is masked.

    Returns:
        ``(wx, wy)``, each ``(h, w)``.
    """
    ref = torch.where(mask[:, :3], y[:, :3], torch.zeros((), dtype=y.dtype, device=y.device))
    ok = mask[:, :3].all(1, keepdim=True).to(y.dtype)
    c = sp.to_cube(torch.cat([ref.to(sp.gram.dtype), ok.to(sp.gram.dtype)], 1))
    rgb, have = c[:3], c[3]
    scale = contrast * math.sqrt(6.0) * max(float(sigma), 1e-12)
    dx = (rgb[:, :, 1:] - rgb[:, :, :-1]).square().sum(0).sqrt() / scale
    dy = (rgb[:, 1:, :] - rgb[:, :-1, :]).square().sum(0).sqrt() / scale
    wx = torch.ones_like(have)
    wy = torch.ones_like(have)
    hx = (have[:, 1:] * have[:, :-1]) > 0
    hy = (have[1:, :] * have[:-1, :]) > 0
    wx[:, :-1] = torch.where(hx, 1.0 / (1.0 + dx.square()), wx[:, :-1])
    wy[:-1, :] = torch.where(hy, 1.0 / (1.0 + dy.square()), wy[:-1, :])
    return wx, wy


def bundle_spatial_problem(sens: BundleSensing) -> SpatialProblem:
    """The bundle's :class:`SpatialProblem` for its static mask and ``(β, diff_order)``: one
    batched factorisation of ``G_p + ρI``, cached with the bundle's NNLS factorisation (so every
    frame of a bundle reuses it) and, where the bundle's precomputation is cached on disk
    (:mod:`hsi_torch.recon.precompute_cache`), its packed form in an entry of its own, keyed by
    the sensing's entry and ``ρ`` (a later process loads it instead of factorising)."""
    prob = sens.problem
    sp = _FACTORS.get(prob)
    if sp is None:
        with torch.no_grad():
            sp = prepare_spatial(prob.gram, sens.pixel_index.to(prob.device), sens.frame_size)
        if sens.disk_entry is not None:  # the packed factor cached beside the sensing's
            folder, path, key = sens.disk_entry
            tv_key = disk.entry_key({"sensing": key, "tv_factor": "packed rows",
                                     "rho": sp.rho}, TV_CACHE_LAYOUT)
            sp.factor.disk = (disk.entry_path(folder, path, tv_key), tv_key)
        _FACTORS[prob] = sp
    return sp


