"""Tests of capture files (16-bit TIFF + JSON metadata, NPY/NPZ, RAW) and the linear reader."""

from __future__ import annotations

import json

import numpy as np
import pytest
import tifffile
import torch
from torch.testing import assert_close

from hsi_torch.io import FileFormatError, read_any, read_capture, write_capture
from hsi_torch.io.raw import bayer_half, demosaic_bilinear, demosaic_saturation, load_raw


@pytest.fixture
def bayer16() -> np.ndarray:
    rng = np.random.default_rng(0)
    a = rng.integers(100, 4000, size=(1, 12, 16)).astype(np.uint16)
    a[0, 4, 6] = 4095  # one saturated sample
    return a


def test_write_read_bayer_roundtrip(tmp_path, bayer16):
    meta = {"cfa_pattern": "rggb", "black_level": 64, "white_level": 4095, "exposure_s": 0.01,
            "wavelength_nm": 550.0, "role": "scan"}  # fmt: skip
    p = write_capture(tmp_path / "f.tif", bayer16, meta)
    img, m = read_capture(p)
    assert img.shape == (1, 12, 16) and img.dtype == torch.float32
    assert np.array_equal(img.numpy().astype(np.uint16), bayer16)
    assert m["kind"] == "bayer" and m["cfa_pattern"] == "RGGB" and m["wavelength_nm"] == 550.0
    assert m["hsi_torch_capture"] == 1 and m["exposure_s"] == 0.01
    # an ordinary TIFF reader sees a plain 16-bit grey image with our JSON description
    with tifffile.TiffFile(p) as tif:
        assert tif.pages[0].dtype == np.uint16 and tif.pages[0].shape == (12, 16)
        assert json.loads(tif.pages[0].description)["role"] == "scan"
    assert not list(tmp_path.glob(".*.tmp"))  # no temp file left


def test_write_read_rgb_roundtrip(tmp_path):
    rgb = np.random.default_rng(1).integers(0, 65536, size=(3, 5, 7)).astype(np.uint16)
    p = write_capture(tmp_path / "rgb.tiff", torch.from_numpy(rgb.astype(np.int32)))
    assert tifffile.imread(p).shape == (5, 7, 3)  # stored interleaved for viewers
    img, m = read_capture(p)
    assert m["kind"] == "rgb" and np.array_equal(img.numpy(), rgb.astype(np.float32))


def test_write_capture_rejects_bad_input(tmp_path):
    with pytest.raises(ValueError, match="cfa_pattern"):
        write_capture(tmp_path / "a.tif", np.zeros((1, 4, 4), np.uint16))
    with pytest.raises(ValueError, match=r"\[0, 65535\]"):
        write_capture(tmp_path / "a.tif", np.full((3, 4, 4), 70000.0))
    with pytest.raises(ValueError, match="non-finite"):
        write_capture(tmp_path / "a.tif", np.full((3, 4, 4), np.nan))
    with pytest.raises(ValueError, match="shape"):
        write_capture(tmp_path / "a.tif", np.zeros((2, 4, 4)))
    with pytest.raises(ValueError, match="kind"):
        write_capture(tmp_path / "a.tif", np.zeros((3, 4, 4)), {"kind": "bayer"})
    with pytest.raises(ValueError, match=".tif"):
        write_capture(tmp_path / "a.png", np.zeros((3, 4, 4)))
    assert not list(tmp_path.iterdir())  # nothing written, nothing partial


@pytest.mark.parametrize("method", ["bilinear", "half"])
def test_read_any_bayer_linearises(tmp_path, bayer16, device, method):
    black = [60, 64, 62, 66]  # per CFA cell position, row-major
    meta = {"cfa_pattern": "GBRG", "black_level": black, "white_level": 4095}
    p = write_capture(tmp_path / "b.tif", bayer16, meta)
    cap = read_any(p, demosaic=method, device=device, dtype=torch.float64)
    black_map = np.tile(np.array(black, float).reshape(2, 2), (6, 8))
    lin = torch.tensor(bayer16[0] - black_map, dtype=torch.float64, device=device)[None]
    assert_close(cap.mosaic, lin)
    sat = torch.tensor(bayer16 >= 4095, device=device)
    ref = demosaic_bilinear(lin, "GBRG") if method == "bilinear" else bayer_half(lin, "GBRG")
    assert_close(cap.image, ref)
    assert torch.equal(cap.saturated, demosaic_saturation(sat, "GBRG", method))
    assert cap.saturated.any()
    assert cap.metadata["cfa_pattern"] == "GBRG" and cap.metadata["demosaic"] == method
    assert cap.metadata["black_level"] == black and cap.metadata["source"] == str(p)
    norm = read_any(p, demosaic=method, normalize=True, dtype=torch.float64)
    assert_close(norm.mosaic, lin.cpu() / (4095 - torch.tensor(black_map)[None]))


def test_read_any_rgb_and_sizes(tmp_path):
    rgb = np.random.default_rng(2).integers(0, 1000, size=(3, 6, 9)).astype(np.uint16)
    p = write_capture(tmp_path / "c.tif", rgb, {"black_level": [10, 20, 30]})
    cap = read_any(p, expected_size=(6, 9))
    expected = rgb.astype(np.float32) - np.array([10, 20, 30], np.float32)[:, None, None]
    assert_close(cap.image, torch.from_numpy(expected))
    assert cap.mosaic is None and not cap.saturated.any()  # white level = 65535 (uint16 max)
    with pytest.raises(FileFormatError, match=r"c\.tif.*\(6, 9\).*\(8, 9\)"):
        read_any(p, expected_size=(8, 9))


def test_read_any_npy_npz(tmp_path):
    hwc = np.random.default_rng(3).uniform(0, 1, size=(5, 4, 3)).astype(np.float32)
    np.save(tmp_path / "a.npy", hwc)
    cap = read_any(tmp_path / "a.npy")
    assert_close(cap.image, torch.from_numpy(hwc.transpose(2, 0, 1).copy()))
    assert not cap.saturated.any()  # float file without white level: no saturation
    # mosaic NPY with a metadata sidecar
    m = np.arange(16, dtype=np.uint16).reshape(4, 4)
    np.save(tmp_path / "m.npy", m)
    (tmp_path / "m.npy.json").write_text(json.dumps({"cfa_pattern": "BGGR", "white_level": 15}))
    cap = read_any(tmp_path / "m.npy", demosaic="half")
    assert cap.image.shape == (3, 2, 2)
    assert cap.image[0, 0, 0] == m[1, 1] and cap.image[2, 0, 0] == m[0, 0]
    assert cap.saturated[0, 1, 1]  # the R sample at (3, 3) has value 15 = white
    # NPZ with metadata string
    np.savez(tmp_path / "z.npz", image=m[None], metadata=json.dumps({"cfa_pattern": "RGGB"}))
    assert read_any(tmp_path / "z.npz").metadata["cfa_pattern"] == "RGGB"
    # a Bayer file without a CFA pattern needs one
    np.save(tmp_path / "nocfa.npy", m)
    with pytest.raises(FileFormatError, match="nocfa.npy.*cfa_pattern"):
        read_any(tmp_path / "nocfa.npy")
    assert read_any(tmp_path / "nocfa.npy", cfa_pattern="RGGB").image.shape == (3, 4, 4)


def test_read_any_bad_files(tmp_path, bayer16):
    nan = np.ones((3, 4, 4), np.float32)
    nan[1, 2, 2] = np.nan
    np.save(tmp_path / "nan.npy", nan)
    with pytest.raises(FileFormatError, match="nan.npy.*NaN"):
        read_any(tmp_path / "nan.npy")
    np.save(tmp_path / "cplx.npy", np.ones((3, 4, 4), np.complex64))
    with pytest.raises(FileFormatError, match="cplx.npy.*dtype"):
        read_any(tmp_path / "cplx.npy")
    np.save(tmp_path / "shape.npy", np.ones((5, 4, 4), np.float32))
    with pytest.raises(FileFormatError, match="shape.npy.*shape"):
        read_any(tmp_path / "shape.npy")
    p = write_capture(tmp_path / "ok.tif", bayer16, {"cfa_pattern": "RGGB"})
    data = p.read_bytes()
    for n in (8, 200, len(data) // 2, len(data) - 4):
        (tmp_path / "trunc.tif").write_bytes(data[:n])
        with pytest.raises(FileFormatError, match="trunc.tif"):
            read_any(tmp_path / "trunc.tif")
    npy = (tmp_path / "nan.npy").read_bytes()
    (tmp_path / "trunc.npy").write_bytes(npy[: len(npy) - 10])
    with pytest.raises(FileFormatError, match="trunc.npy"):
        read_any(tmp_path / "trunc.npy")
    (tmp_path / "trunc.npz").write_bytes(b"PK\x03\x04garbage")
    with pytest.raises(FileFormatError, match="trunc.npz"):
        read_any(tmp_path / "trunc.npz")
    (tmp_path / "pic.jpg").write_bytes(b"\xff\xd8\xff")
    with pytest.raises(FileFormatError, match="unsupported file type"):
        read_any(tmp_path / "pic.jpg")
    (tmp_path / "pic.png").write_bytes(b"\x89PNG")  # a PNG cut inside its header
    with pytest.raises(FileFormatError, match="pic.png: not a PNG file"):
        read_any(tmp_path / "pic.png")
    with pytest.raises(FileNotFoundError, match="missing.tif"):
        read_any(tmp_path / "missing.tif")


def test_read_any_raw_real(real_data):
    path = real_data / "raw" / "RAW_KODAK_DC50.KDC"
    cap = read_any(path, expected_size=(512, 768), demosaic="half")
    ref = load_raw(path, demosaic="half")
    assert_close(cap.image, ref.rgb)
    assert torch.equal(cap.saturated, ref.rgb_saturated)
    assert cap.metadata["cfa_pattern"] == "GRBG" and cap.metadata["white_level"] == 16383
    with pytest.raises(FileFormatError, match=r"RAW_KODAK_DC50.KDC.*\(512, 768\).*\(480, 640\)"):
        read_any(path, expected_size=(480, 640))
    # a user-supplied black level overrides the file's
    capb = read_any(path, demosaic="half", black_level=100)
    assert_close(capb.image, ref.rgb - 100)
