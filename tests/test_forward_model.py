"""The forward model ``A_p = g_v(p) B_v(p, λ) Δλ φ^c(λ)``: the factored operators agree with the
dense matrices written out element by element, ``A_adjoint`` is the adjoint of ``A``, and the
bundle-layout constructor keeps the observation order ``o = 3·v + c``."""

from __future__ import annotations

import numpy as np
import torch
from torch.testing import assert_close

from hsi_torch.forward_model import DenseSensing, SensingModel


def _factors(P, V, M, device, dtype, seed=0):
    g = torch.Generator().manual_seed(seed)
    B = torch.rand(P, V, M, generator=g, dtype=torch.float64)
    gain = 0.5 + torch.rand(P, V, generator=g, dtype=torch.float64)
    resp = torch.rand(3, M, generator=g, dtype=torch.float64)
    return [t.to(device=device, dtype=dtype) for t in (B, gain, resp)]


def _dense_reference(B, gain, resp) -> np.ndarray:
    """``A[p, 3v + c, m] = gain[p, v] · B[p, v, m] · resp[c, m]`` by explicit loops (numpy)."""
    B, gain, resp = (t.double().cpu().numpy() for t in (B, gain, resp))
    P, V, M = B.shape
    A = np.zeros((P, 3 * V, M))
    for v in range(V):
        for c in range(3):
            A[:, 3 * v + c, :] = gain[:, v, None] * B[:, v, :] * resp[c][None, :]
    return A


def test_dense_matches_the_formula(device, dtype):
    B, gain, resp = _factors(7, 4, 9, device, dtype)
    model = SensingModel(B, gain, resp)
    ref = torch.as_tensor(_dense_reference(B, gain, resp), device=device, dtype=dtype)
    assert_close(model.dense(), ref)
    assert (model.num_pixels, model.num_views, model.num_obs, model.num_bands) == (7, 4, 12, 9)


def test_a_transposed_view_gives_the_contiguous_answer(device, dtype):
    """``A`` of a transposed view (e.g. a ``(M, P)`` truth's columns) is computed as for
    contiguous rows: the same bits (from a view, CPU bmm ran one BLAS call per pixel)."""
    B, gain, resp = _factors(300, 10, 25, device, dtype, seed=2)
    model = SensingModel(B, gain, resp)
    s = torch.rand(25, 300, device=device, dtype=dtype).T
    assert torch.equal(model.A(s), model.A(s.contiguous()))


def test_operators_agree_with_the_dense_matrices(device, dtype):
    B, gain, resp = _factors(11, 5, 8, device, dtype, seed=1)
    model = SensingModel(B, gain, resp)
    A = model.dense()
    s = torch.rand(11, 8, device=device, dtype=dtype)
    y = torch.rand(11, 15, device=device, dtype=dtype)
    assert_close(model.A(s), torch.einsum("pom,pm->po", A, s))
    assert_close(model.A_adjoint(y), torch.einsum("pom,po->pm", A, y))
    # adjointness <A s, y> = <s, Aᵀ y>, pixel by pixel
    assert_close((model.A(s) * y).sum(1), (s * model.A_adjoint(y)).sum(1))
    # sub-batches by index and by slice
    idx = torch.tensor([3, 0, 7], device=device)
    assert_close(model.A(s[idx], idx), model.A(s)[idx])
    assert_close(model.A(s[2:5], slice(2, 5)), model.A(s)[2:5])
    assert_close(model.select(idx).dense(), A[idx])


def test_gram_columns_and_the_dense_twin(device, dtype):
    B, gain, resp = _factors(6, 3, 7, device, dtype, seed=2)
    model = SensingModel(B, gain, resp)
    A = model.dense()
    mask = torch.rand(6, 9, generator=torch.Generator().manual_seed(3)).to(device) > 0.3
    reg = torch.eye(7, device=device, dtype=dtype) * 0.5
    W = mask.to(dtype)
    assert_close(model.gram(mask, reg=reg), A.transpose(1, 2) @ (W.unsqueeze(2) * A) + reg)
    cols = torch.tensor([[0, 4], [6, 1], [2, 3], [5, 5], [1, 0], [3, 6]], device=device)
    idx = torch.arange(6, device=device)
    assert_close(model.columns(idx, cols), torch.gather(A, 2, cols.unsqueeze(1).expand(6, 9, 2)))
    twin = DenseSensing(A)
    s = torch.rand(6, 7, device=device, dtype=dtype)
    assert_close(twin.A(s), model.A(s))
    assert_close(twin.gram(mask, reg=reg), model.gram(mask, reg=reg))


def test_shared_model_broadcasts_one_matrix(device, dtype):
    B, gain, resp = _factors(1, 4, 6, device, dtype, seed=4)
    model = SensingModel(B, gain, resp)
    assert model.shared
    s = torch.rand(5, 6, device=device, dtype=dtype)
    assert_close(model.A(s), s @ model.dense()[0].T)


def test_from_factors_keeps_the_bundle_layout(device, dtype):
    """Bundle arrays ``B (V, M, h, w)``, ``gain (V, h, w)``, ``phi (3, M)``, ``Δλ (M,)``: pixel
    ``p`` is row-major ``y·w + x`` and ``Δλ`` is folded into the response."""
    V, M, h, w = 3, 5, 2, 4
    gen = torch.Generator().manual_seed(5)
    B = torch.rand(V, M, h, w, generator=gen, dtype=torch.float64)
    gain = torch.rand(V, h, w, generator=gen, dtype=torch.float64)
    phi = torch.rand(3, M, generator=gen, dtype=torch.float64)
    dl = torch.full((M,), 10.0, dtype=torch.float64)
    keep = torch.tensor([6, 1])
    model = SensingModel.from_factors(B, gain, phi, dl, pixel_index=keep, device=device,
                                      dtype=dtype)  # fmt: skip
    for row, p in enumerate(keep.tolist()):
        yy, xx = divmod(p, w)
        for v in range(V):
            for c in range(3):
                want = gain[v, yy, xx] * B[v, :, yy, xx] * dl * phi[c]
                got = model.dense()[row, 3 * v + c]
                assert_close(got, want.to(device=device, dtype=dtype))
