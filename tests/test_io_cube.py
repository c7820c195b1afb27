"""Tests of spectral cube files (TIFF, ENVI via `spectral`, NPZ) and atomic writes (the readers
other tools use, NetCDF and Zarr: tests/test_cube_formats.py)."""

from __future__ import annotations

import os

import numpy as np
import pytest
import torch
from torch.testing import assert_close

from hsi_torch.io import (
    FileFormatError,
    atomic_save_npz,
    atomic_write,
    atomic_write_json,
    load_cube,
    save_cube,
    save_cube_formats,
)

WL = np.arange(430.0, 671.0, 10.0)  # 25 bands


@pytest.fixture
def cube_and_valid():
    rng = np.random.default_rng(0)
    cube = rng.uniform(0, 1, size=(25, 6, 8)).astype(np.float32)
    valid = np.ones((6, 8), bool)
    valid[0, :3] = False
    valid[5, 7] = False
    return cube, valid


@pytest.mark.parametrize("suffix", [".tif", ".tiff", ".hdr", ".img", ".npz"])
def test_cube_roundtrip(tmp_path, cube_and_valid, suffix, device):
    cube, valid = cube_and_valid
    t = torch.from_numpy(cube).to(device)
    written = save_cube(tmp_path / f"c{suffix}", t, torch.tensor(WL), torch.from_numpy(valid),
                        metadata={"beta": 10.0, "description": "test {cube}"})  # fmt: skip
    assert all(p.exists() for p in written)
    loaded = load_cube(tmp_path / f"c{suffix}", device=device)
    assert loaded.cube.shape == (25, 6, 8) and loaded.cube.device.type == device.type
    assert_close(loaded.wavelengths.cpu(), torch.from_numpy(WL))
    assert torch.equal(loaded.valid.cpu(), torch.from_numpy(valid))
    got = loaded.cube.cpu().numpy()
    assert np.array_equal(got[:, valid], cube[:, valid])  # bit-exact float32
    if suffix == ".npz":
        assert np.array_equal(got, cube) and loaded.metadata["beta"] == 10.0
    else:
        assert np.isnan(got[:, ~valid]).all()  # no mask plane: invalid pixels are NaN
    if suffix in (".tif", ".tiff"):
        assert loaded.metadata["wavelength_units"] == "nm" and loaded.metadata["beta"] == 10.0


def test_envi_readable_by_spectral(tmp_path, cube_and_valid):
    import spectral

    cube, _ = cube_and_valid
    wl = WL + 0.125  # non-integer wavelengths survive the header
    img_path, hdr_path = save_cube(tmp_path / "scene.hdr", cube, wl)
    assert img_path.suffix == ".img" and hdr_path.suffix == ".hdr"
    img = spectral.envi.open(str(hdr_path))
    assert img.shape == (6, 8, 25)
    assert np.allclose(img.bands.centers, wl, rtol=0, atol=1e-9)
    assert img.bands.band_unit == "nm" and img.metadata["wavelength units"] == "nm"
    arr = np.asarray(img.load())
    assert np.array_equal(arr, cube.transpose(1, 2, 0))
    assert img.read_band(3).shape == (6, 8) and np.array_equal(img.read_band(3), cube[3])


def test_load_third_party_envi_micrometres(tmp_path):
    import spectral

    rng = np.random.default_rng(1)
    arr = rng.integers(0, 1000, size=(4, 5, 3)).astype(np.uint16)  # (lines, samples, bands)
    meta = {"wavelength": [0.45, 0.55, 0.65], "wavelength units": "micrometers"}
    spectral.envi.save_image(str(tmp_path / "ext.hdr"), arr, interleave="bil", metadata=meta,
                             ext=".img", force=True)  # fmt: skip
    loaded = load_cube(tmp_path / "ext.hdr")
    assert_close(loaded.wavelengths, torch.tensor([450.0, 550.0, 650.0], dtype=torch.float64))
    assert np.array_equal(loaded.cube.numpy(), arr.transpose(2, 0, 1).astype(np.float32))


def test_save_cube_formats_and_errors(tmp_path, cube_and_valid):
    cube, valid = cube_and_valid
    paths = save_cube_formats(tmp_path / "out" / "frame", cube, WL, valid)
    assert sorted(p.name for p in paths) == ["frame.hdr", "frame.img", "frame.npz", "frame.tif",
                                             "frame.vrt"]
    with pytest.raises(ValueError, match=r"wavelengths must have shape \(25,\)"):
        save_cube(tmp_path / "x.npz", cube, WL[:-1])
    with pytest.raises(ValueError, match=r"\(M, H, W\)"):
        save_cube(tmp_path / "x.npz", cube[0], WL)
    with pytest.raises(ValueError, match="suffix"):
        save_cube(tmp_path / "x.png", cube, WL)
    with pytest.raises(ValueError, match="valid"):
        save_cube(tmp_path / "x.npz", cube, WL, valid[:3])
    assert not (tmp_path / "x.npz").exists()


def test_load_cube_bad_files(tmp_path, cube_and_valid):
    cube, _ = cube_and_valid
    save_cube(tmp_path / "c.hdr", cube, WL)
    img = (tmp_path / "c.img").read_bytes()
    (tmp_path / "c.img").write_bytes(img[: len(img) // 2])
    with pytest.raises(FileFormatError, match="c.img.*truncated"):
        load_cube(tmp_path / "c.hdr")
    save_cube(tmp_path / "c.tif", cube, WL)
    data = (tmp_path / "c.tif").read_bytes()
    (tmp_path / "t.tif").write_bytes(data[: len(data) // 3])
    with pytest.raises(FileFormatError, match="t.tif"):
        load_cube(tmp_path / "t.tif")
    import tifffile

    tifffile.imwrite(tmp_path / "plain.tif", cube)  # no wavelengths in the file
    with pytest.raises(FileFormatError, match="plain.tif.*wavelengths"):
        load_cube(tmp_path / "plain.tif")
    assert load_cube(tmp_path / "plain.tif", wavelengths=WL).cube.shape == (25, 6, 8)
    with pytest.raises(FileFormatError, match="3 wavelengths for a cube with 25 bands"):
        load_cube(tmp_path / "plain.tif", wavelengths=[1.0, 2.0, 3.0])
    with pytest.raises(FileNotFoundError, match="missing.npz"):
        load_cube(tmp_path / "missing.npz")


def test_atomic_write_leaves_nothing_on_error(tmp_path):
    target = tmp_path / "sub" / "result.bin"
    with atomic_write(target) as f:
        f.write(b"old")
    assert target.read_bytes() == b"old"
    with pytest.raises(RuntimeError, match="boom"), atomic_write(target) as f:
        f.write(b"new partial data")
        raise RuntimeError("boom")
    assert target.read_bytes() == b"old"  # untouched
    assert sorted(p.name for p in target.parent.iterdir()) == ["result.bin"]  # no temp file
    with pytest.raises(TypeError), atomic_write(tmp_path / "never.txt", "w") as f:
        f.write(b"bytes into a text file")  # type: ignore[arg-type]
    assert not (tmp_path / "never.txt").exists()
    atomic_write_json(tmp_path / "a.json", {"x": np.float32(1.5), "t": torch.tensor([1, 2])})
    assert (tmp_path / "a.json").read_text().count("1.5") == 1
    with pytest.raises(TypeError):
        atomic_write_json(tmp_path / "b.json", {"x": object()})
    assert not (tmp_path / "b.json").exists()
    atomic_save_npz(tmp_path / "n.npz", {"a": torch.arange(3)})
    with np.load(tmp_path / "n.npz") as z:
        assert z["a"].tolist() == [0, 1, 2]
    umask = os.umask(0)
    os.umask(umask)
    assert (tmp_path / "n.npz").stat().st_mode & 0o777 == 0o666 & ~umask  # not mkstemp's 0600
