"""scripts/usaf_demosaic.py: the alternative demosaics it measures the USAF experiment with
(OpenCV edge-aware and VNG on an integer copy, Malvar–He–Cutler in torch) and its hook into the
capture reader."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import usaf_demosaic as ud  # noqa: E402

from hsi_torch.bayer import demosaic_bilinear, mosaic  # noqa: E402

PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")


def _ramp(h: int = 24, w: int = 28) -> torch.Tensor:
    y, x = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    return torch.stack([1000 + 20 * x + 5 * y, 2000 + 10 * x - 3 * y,
                        1500 + 7 * y - 4 * x]).double()


@pytest.mark.parametrize("pattern", PATTERNS)
def test_demosaics_reproduce_a_linear_ramp(pattern):
    """Away from the border every method returns a linear colour ramp: MHC and bilinear exactly,
    OpenCV's edge-aware within its 16-bit rounding, VNG within its 8-bit quantisation — which
    also checks the CFA pattern → OpenCV code mapping (a wrong one swaps or mixes channels)."""
    img = _ramp()
    m = mosaic(img, pattern)[None]
    inner = (slice(None), slice(3, -3), slice(3, -3))
    assert (ud.demosaic_mhc(m, pattern)[0] - img)[inner].abs().max() < 1e-9
    assert (demosaic_bilinear(m, pattern)[0] - img)[inner].abs().max() < 1e-9
    ea = ud.demosaic_edge_aware(m, pattern)[0]
    assert (ea - img)[inner].abs().max() < 0.1  # 16-bit steps of a ~1500 DN range: 0.02 DN
    assert ea.dtype == img.dtype and ea.shape == img.shape
    vng = ud.demosaic_vng(m, pattern)[0]
    assert (vng - img)[inner].abs().max() < 30  # 8 bits over the range: ~6 DN steps
    # measured samples are kept (MHC exactly, also at the border; edge-aware up to rounding
    # inside its replicated one-pixel border ring)
    keep = mosaic(ud.demosaic_mhc(m, pattern)[0], pattern)
    assert torch.equal(keep, m[0])
    assert (mosaic(ea, pattern) - m[0])[inner].abs().max() < 0.05


def test_edge_aware_follows_an_edge_and_mhc_sharpens():
    """A vertical grey edge: edge-aware green interpolates along it (no error at the green
    samples it fills), bilinear blurs it; MHC, borrowing the green plane's detail, has a smaller
    worst red/blue error than bilinear (875 vs 1400 DN on a 2800 DN step)."""
    h, w = 16, 16
    x = torch.arange(w).expand(h, w)
    grey = torch.where(x < 8, 200.0, 3000.0).double()
    img = torch.stack([grey, grey, grey])
    m = mosaic(img, "RGGB")[None]
    inner = (slice(2, -2), slice(2, -2))
    err = {n: (f(m, "RGGB")[0] - img)[(slice(None), *inner)].abs()
           for n, f in (("bilinear", demosaic_bilinear), ("ea", ud.demosaic_edge_aware),
                        ("mhc", ud.demosaic_mhc))}
    assert err["ea"][1].max() < 0.1 < err["bilinear"][1].max()  # green along the edge
    assert err["mhc"][[0, 2]].max() < 0.7 * err["bilinear"][[0, 2]].max()


def test_install_swaps_the_readers_demosaic(monkeypatch, tmp_path):
    """``install`` makes ``read_any`` (the experiment's reader) and, with ``reference``, the
    sensor model use the method; a ``half`` read is left alone."""
    import hsi_torch.io.captures as captures
    from hsi_torch.io import read_any, write_capture
    from hsi_torch.optics.sensor import SensorModel

    monkeypatch.setattr(captures, "_demosaic", captures._demosaic)
    monkeypatch.setattr(SensorModel, "demosaic", SensorModel.demosaic)
    img = _ramp(16, 16) + 100 * torch.rand(3, 16, 16, generator=torch.Generator().manual_seed(0))
    raw = mosaic(img, "RGGB").round()
    path = tmp_path / "cap.tif"
    write_capture(path, raw, {"kind": "bayer", "cfa_pattern": "RGGB", "black_level": 0.0,
                              "white_level": 65535.0})
    before = read_any(path, dtype=torch.float64).image
    ud.install("mhc", reference=True)
    after = read_any(path, dtype=torch.float64).image
    want = ud.demosaic_mhc(raw[None].double(), "RGGB")[0]
    assert torch.allclose(after, want) and not torch.allclose(before, want)
    half = read_any(path, demosaic="half", dtype=torch.float64).image
    assert half.shape == (3, 8, 8)
    s = SensorModel(cfa_pattern="RGGB")
    assert torch.allclose(s.demosaic(raw[None].double())[0], want)
