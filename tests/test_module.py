"""HSIReconstructor: equals the pipeline, buffers move with .to(), differentiable (gradcheck)."""

from __future__ import annotations

import pytest
import torch
from test_pipeline import make_bundle, rel_err, render_capture, true_spectra

from hsi_torch.io.raw import mosaic
from hsi_torch.recon.module import HSIReconstructor, ReconstructionOutput
from hsi_torch.recon.pipeline import Reconstructor


def test_exported_from_package():
    import hsi_torch

    assert hsi_torch.HSIReconstructor is HSIReconstructor


def test_module_equals_pipeline(device, dtype):
    bundle = make_bundle(cfa_pattern="GRBG")
    s1, s2 = true_spectra(seed=1), true_spectra(seed=2, zeros=True)
    x = torch.stack([render_capture(bundle, s1), render_capture(bundle, s2)]).to(device, dtype)
    mod = HSIReconstructor.from_bundle(bundle, beta=3.0, device=device, dtype=dtype)
    rec = Reconstructor(bundle, beta=3.0, device=device, dtype=dtype)
    out = mod(x)
    assert isinstance(out, ReconstructionOutput)
    assert out.cube.shape == (2, 8, 20, 20) and out.valid.shape == (2, 20, 20)
    for i in range(2):
        r = rec.reconstruct_frame(x[i])
        torch.testing.assert_close(out.cube[i], r.cube, equal_nan=True, rtol=0, atol=0)
        assert torch.equal(out.valid[i], r.valid)
    # Bayer input demosaiced with the bundle's CFA pattern
    xb = mosaic(x, "GRBG")
    rb = rec.reconstruct_frame(xb[0])
    torch.testing.assert_close(mod(xb).cube[0], rb.cube, equal_nan=True)


def test_to_dtype_and_device_moves_everything(device):
    bundle = make_bundle()
    s = true_spectra()
    mod = HSIReconstructor.from_bundle(bundle, beta=0.0)
    assert mod.model_transmittance.dtype == torch.float32 and mod.gram.dtype == torch.float32
    mod = mod.to(device=device, dtype=torch.float64)
    for name, buf in mod.named_buffers():
        assert buf.device.type == device.type, name
        if buf.is_floating_point():
            assert buf.dtype == torch.float64, name
    assert {"B", "phi", "gain", "homographies", "gram", "gram_inv", "model_transmittance"} <= {
        n for n, _ in mod.named_buffers()
    }
    x = render_capture(bundle, s).to(device, torch.float64)[None]
    cube, valid = mod(x)
    # refactorised in float64: exact to float32 rounding of the sensing factors only
    assert rel_err(cube[0][:, valid[0]], s.to(device)[:, valid[0]]) < 1e-5
    # float32 input to a float64 module: output in the input's dtype
    assert mod(x.float()).cube.dtype == torch.float32
    with pytest.raises(ValueError, match="sensor size"):
        mod(torch.zeros(1, 3, 40, 41, dtype=torch.float64, device=device))
    # state_dict carries the calibration, not the derived factorisation
    sd = mod.state_dict()
    assert "B" in sd and "gram" not in sd


def test_half_precision_is_refused_and_the_module_left_as_it_was():
    """.half() / .bfloat16() / .to(float16): the solver factorises in float32 or float64 only; the
    refusal names the precision and comes before any buffer is converted (it used to convert
    every buffer, then fail in the factorisation with the module half converted)."""
    bundle = make_bundle()
    mod = HSIReconstructor.from_bundle(bundle, beta=1.0)
    x = render_capture(bundle, true_spectra()).float()[None]
    before = mod(x).cube
    for convert in (lambda m: m.half(), lambda m: m.bfloat16(),
                    lambda m: m.to(torch.float16)):  # fmt: skip
        with pytest.raises(TypeError, match="float32 or float64, not torch.(b?float16)"):
            convert(mod)
        assert all(b.dtype != torch.float16 and b.dtype != torch.bfloat16
                   for b in mod.buffers())  # fmt: skip
    torch.testing.assert_close(mod(x).cube, before, rtol=0, atol=0, equal_nan=True)


def test_gradcheck_active_set():
    bundle = make_bundle(t=5, missing=1)
    s = true_spectra(t=5, seed=4, zeros=True)
    x0 = render_capture(bundle, s)[None]
    mod = HSIReconstructor.from_bundle(bundle, beta=0.5, dtype=torch.float64)
    cube, valid = mod(x0)
    assert (cube[:, :, valid[0]] == 0).any()  # some constraints active
    v = valid[0]

    def f(x: torch.Tensor) -> torch.Tensor:
        return mod(x).cube[0][:, v]

    x = x0.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(f, (x,), eps=1e-6, atol=1e-6, rtol=1e-4)


def test_admm_fixed_iterations_differentiable():
    bundle = make_bundle(t=5, missing=1)
    s = true_spectra(t=5, seed=5)
    x0 = render_capture(bundle, s)[None]
    mod = HSIReconstructor.from_bundle(
        bundle, beta=0.5, dtype=torch.float64, solver="admm", admm_iters=30
    )
    v = mod(x0).valid[0]
    x = x0.clone().requires_grad_(True)
    loss = mod(x).cube[0][:, v].square().sum()
    (g,) = torch.autograd.grad(loss, x)
    d = torch.randn_like(x0)
    h = 1e-3  # the loss is locally quadratic: central differences are exact up to rounding
    num = (mod(x0 + h * d).cube[0][:, v].square().sum() - mod(x0 - h * d).cube[0][:, v]
           .square().sum()) / (2 * h)
    torch.testing.assert_close((g * d).sum(), num, rtol=1e-6, atol=1e-9)


def test_inside_a_torch_pipeline(device):
    bundle = make_bundle()
    mod = HSIReconstructor.from_bundle(bundle, beta=1.0, device=device, nan_invalid=False)
    conv = torch.nn.Conv2d(8, 4, 3, padding=1).to(device)
    x = (render_capture(bundle, true_spectra()).float()[None]).to(device).requires_grad_(True)
    cube, valid = mod(x)
    out = conv(cube)
    loss = out.square().mean()
    loss.backward()
    assert x.grad is not None and torch.isfinite(x.grad).all()
    assert x.grad.abs().sum() > 0 and conv.weight.grad.abs().sum() > 0
    # gradient only reaches sensor pixels sampled by some valid view
    assert (x.grad == 0).any()


def test_sampling_grid_buffer_recomputed_in_new_dtype():
    from test_pipeline import _tilted

    from hsi_torch.optics.geometry import view_sample_grid

    bundle = _tilted(make_bundle())  # non-integer sampling positions
    mod = HSIReconstructor.from_bundle(bundle, beta=1.0)
    assert mod.sample_grid.dtype == torch.float32 and mod.sample_grid.shape[:2] == (1, 4)
    assert mod.sensing is mod.sensing  # view (and its work buffer) kept between calls
    mod = mod.double()
    ref = view_sample_grid(torch.as_tensor(bundle.view_homographies), mod.reference_bbox,
                           mod.sensor_size, mod.pixel_index, dtype=torch.float64)
    assert torch.equal(mod.sample_grid, ref)  # float64 positions, not float32 ones upcast
    assert not torch.equal(mod.sample_grid, ref.float().double())
    x = torch.rand(2, 3, 40, 40, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    rec = Reconstructor(bundle, beta=1.0, dtype=torch.float64)
    # equal up to A's float32 rounding (the module's A was built in float32, then upcast)
    torch.testing.assert_close(mod(x).cube[1], rec.reconstruct_frame(x[1]).cube, equal_nan=True,
                               rtol=1e-5, atol=1e-8)


def test_deepcopy_and_torch_save_roundtrip(tmp_path):
    import copy

    bundle = make_bundle()
    mod = HSIReconstructor.from_bundle(bundle, beta=1.0)
    x = render_capture(bundle, true_spectra()).float()[None]
    sat = torch.zeros_like(x, dtype=torch.bool)
    sat[0, 0, 3, 3] = True
    ref = mod(x, sat).cube  # caches the sensing view, its lock and work buffer
    twin = copy.deepcopy(mod)
    torch.save(mod, tmp_path / "mod.pt")
    loaded = torch.load(tmp_path / "mod.pt", weights_only=False)
    for m in (twin, loaded):
        torch.testing.assert_close(m(x, sat).cube, ref, equal_nan=True, rtol=0, atol=0)


def test_one_object_for_networks_and_files(tmp_path):
    """The module and the file front door are one class: a module built with ``from_bundle``
    reconstructs files, and ``Reconstructor`` (the same class without the full-frame calibration
    arrays) runs as a module; both give the same cube. ``Reconstructor`` keeps no calibration in
    its state dict and refuses to load one; the module's state dict loads into another module."""
    from hsi_torch.errors import InputError
    from hsi_torch.io import write_capture
    from hsi_torch.recon.pipeline import HSIReconstructor as OneClass

    assert HSIReconstructor is OneClass and issubclass(Reconstructor, HSIReconstructor)
    bundle = make_bundle()
    x = render_capture(bundle, true_spectra(seed=3)).float()
    mod = HSIReconstructor.from_bundle(bundle, beta=3.0)
    rec = Reconstructor(bundle, beta=3.0)
    by_method = mod.reconstruct_frame(x)  # the file API on the module
    by_forward = rec(x[None])  # the module API on the file front door
    torch.testing.assert_close(by_method.cube, by_forward.cube[0], equal_nan=True, rtol=0, atol=0)
    assert torch.equal(by_method.valid, by_forward.valid[0])
    path = tmp_path / "frame.tif"
    write_capture(path, x)
    a, b = mod.reconstruct_file(path), rec.reconstruct_file(path)
    torch.testing.assert_close(a.cube, b.cube, equal_nan=True, rtol=0, atol=0)
    assert a.stats["num_valid"] == b.stats["num_valid"] > 0
    assert "B" in mod.state_dict() and "B" not in rec.state_dict()
    with pytest.raises(InputError, match="without the bundle's calibration arrays"):
        rec.load_state_dict(mod.state_dict())
    other = HSIReconstructor.from_bundle(make_bundle(seed=5), beta=3.0)
    other.load_state_dict(mod.state_dict())
    torch.testing.assert_close(other(x[None]).cube, mod(x[None]).cube, equal_nan=True)
