"""`torch.compile` around HSIReconstructor: the solver is one graph break (it runs eagerly under
`torch.compiler.disable`), no recompiles from frame to frame, the compiled result equals eager."""

from __future__ import annotations

import pytest
import torch
from test_pipeline import make_bundle, render_capture, true_spectra

from hsi_torch.recon.module import HSIReconstructor


class UserNet(torch.nn.Module):
    """A user's network around the reconstructor: a pre-step, the module, a post-step."""

    def __init__(self, rec: HSIReconstructor) -> None:
        super().__init__()
        self.rec = rec
        self.gain = torch.nn.Parameter(torch.tensor(1.0))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        cube, valid = self.rec(torch.relu(x) * self.gain)
        return torch.nan_to_num(cube).mean(1) * valid


@pytest.fixture(scope="module")
def setup():
    bundle = make_bundle()
    frames = [torch.stack([render_capture(bundle, true_spectra(seed=s))]).float()
              for s in (1, 2, 3)]  # fmt: skip
    net = UserNet(HSIReconstructor.from_bundle(bundle, beta=3.0))
    return net, frames


def test_graph_breaks_only_at_the_solver(setup):
    net, frames = setup
    torch._dynamo.reset()
    ex = torch._dynamo.explain(net)(frames[0])
    # one break, at the disabled solver, counted in the module's frame and in the caller's
    assert ex.graph_break_count <= 2
    reasons = [str(b.reason) for b in ex.break_reasons]
    assert reasons and all("reconstruct_prepared" in r for r in reasons), reasons


def test_no_recompiles_from_frame_to_frame(setup):
    from torch._dynamo.testing import CompileCounter

    net, frames = setup
    torch._dynamo.reset()
    counter = CompileCounter()
    compiled = torch.compile(net, backend=counter)
    compiled(frames[0])
    first = counter.frame_count
    for x in frames[1:]:
        compiled(x)
    assert counter.frame_count == first <= 3  # the graphs around the solver, compiled once
    # a user's parameter before the module still gets its gradient through the eager solver
    net.gain.grad = None
    torch.compile(net, backend="aot_eager")(frames[0]).sum().backward()
    assert net.gain.grad is not None and torch.isfinite(net.gain.grad)


@pytest.mark.slow
def test_torch_compile_on_cpu_gives_the_eager_output(setup):
    """The default backend (inductor) on CPU; the compiled output equals the eager one."""
    net, frames = setup
    torch._dynamo.reset()
    compiled = torch.compile(net)
    for x in frames[:2]:
        with torch.no_grad():
            torch.testing.assert_close(compiled(x), net(x), rtol=1e-6, atol=1e-6)


def test_readme_module_snippet_runs(tmp_path, monkeypatch):
    """The nn.Module example of docs/python_api.md, run as written in a folder holding a bundle
    (calib/calib.npz) and a capture (shots/scene_001.tif) exposed half as long as the white
    reference."""
    import re
    from pathlib import Path

    import numpy as np

    from hsi_torch.io import write_capture

    text = (Path(__file__).resolve().parents[1] / "docs" / "python_api.md").read_text("utf-8")
    block = next(b for b in re.findall(r"```python\n(.*?)```", text, flags=re.S)
                 if "HSIReconstructor.from_bundle" in b)  # fmt: skip
    bundle = make_bundle()
    bundle.settings["white_exposure_s"] = 0.02
    (tmp_path / "calib").mkdir()
    bundle.save(tmp_path / "calib" / "calib.npz")
    s = true_spectra(seed=4)
    img = render_capture(bundle, s).numpy() * 0.5  # taken at 0.01 s: half the signal
    write_capture(tmp_path / "shots" / "scene_001.tif", np.round(img * 50).clip(0, 65535),
                  {"kind": "rgb", "exposure_s": 0.01})  # fmt: skip
    monkeypatch.chdir(tmp_path)
    ns: dict = {}
    exec(compile(block, "docs/python_api.md", "exec"), ns)
    assert ns["scale"] == 2.0 and ns["cube"].shape == (1, 8, 20, 20)
    assert ns["net"].weight.grad is not None  # loss.backward() ran
    # the same as the file pipeline (which applies the same exposure ratio)
    from hsi_torch.recon import Reconstructor

    ref = Reconstructor("calib/calib.npz", beta=1e4).reconstruct_file("shots/scene_001.tif")
    assert ref.stats["exposure_scale"] == 2.0
    torch.testing.assert_close(ns["cube"][0].detach(), ref.cube, equal_nan=True)
    assert torch.equal(ns["valid"][0], ref.valid)
