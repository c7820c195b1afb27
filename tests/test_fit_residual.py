"""The per-frame fit-residual check on simulated captures: quiet for the right bundle even on a
dark, noise-dominated capture; a warning for a bundle of another geometry."""

from __future__ import annotations

from pathlib import Path

import pytest

from hsi_torch.cli import main
from hsi_torch.recon.checks import frame_findings
from hsi_torch.recon.config import ReconstructConfig
from hsi_torch.recon.pipeline import Reconstructor
from hsi_torch.simulate.oracle import bundle_from_truth

_MINIMAL = ["--set", "captures.scan_wavelengths_nm=[550]", "--set", "captures.white_shots=0",
            "--set", "captures.grid.poses=[]", "--set", "render.figures=false",
            "--set", "render.dtype=float32"]  # fmt: skip


def _simulate(out: Path, *overrides: str) -> Path:
    args = ["-q", "simulate", "--out", str(out), *_MINIMAL]
    for o in overrides:
        args += ["--set", o]
    assert main(args) == 0
    return out


@pytest.fixture(scope="module")
def dark_set(tmp_path_factory) -> Path:
    """The default prototype filming the ColorChecker with 1/20 of the default exposure: the
    observations are dominated by shot and read noise."""
    return _simulate(tmp_path_factory.mktemp("dark"), "sensor.exposure=0.04",
                     "captures.scenes=[{kind: colorchecker, name: colorchecker, params: "
                     "{width_mm: 8.4, center_mm: [0.0, 1.4]}}]")


@pytest.fixture(scope="module")
def other_geometry(tmp_path_factory) -> Path:
    """The same sensor behind another kaleidoscope (exit side 34 mm instead of 40 mm)."""
    return _simulate(tmp_path_factory.mktemp("other"), "geometry.a_out_mm=34",
                     "captures.scenes=[]")


def test_dark_capture_right_bundle_no_warning(dark_set: Path):
    rec = Reconstructor(bundle_from_truth(dark_set))
    res = rec.reconstruct_file(dark_set / "scenes" / "colorchecker.tif")
    fit = res.stats["fit_residual"]
    assert 0.05 < fit < 0.15, fit  # noise-dominated (0.03 at the default exposure), no warning
    assert not [f for f in frame_findings(res.stats, ReconstructConfig().settings())
                if f.code == "fit.residual"]


def test_bundle_of_another_geometry_warns(dark_set: Path, other_geometry: Path):
    rec = Reconstructor(bundle_from_truth(other_geometry))
    res = rec.reconstruct_file(dark_set / "scenes" / "colorchecker.tif")
    fit = res.stats["fit_residual"]
    assert fit > 0.2, fit
    found = frame_findings(res.stats, ReconstructConfig().settings())
    assert any(f.code == "fit.residual" and "geometry" in f.fix for f in found)
