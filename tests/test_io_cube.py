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


def _npz_declaring(path, shape, dtype="<f4"):
    """An NPZ whose ``cube`` member's header declares ``shape`` but holds a few bytes only (what
    a compressed file of zeros inflates to, without writing gigabytes here)."""
    import io
    import zipfile

    head = io.BytesIO()
    np.lib.format.write_array_header_1_0(head, {"descr": dtype, "fortran_order": False,
                                                "shape": tuple(shape)})  # fmt: skip
    wl = io.BytesIO()
    np.save(wl, WL)
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("cube.npy", head.getvalue() + b"\0" * 64)
        z.writestr("wavelengths_nm.npy", wl.getvalue())
    return path


def test_npz_cube_declaring_gigabytes_is_refused_before_decoding(tmp_path, monkeypatch):
    bomb = _npz_declaring(tmp_path / "bomb.npz", (25, 20000, 20000))  # 37 GiB declared
    assert bomb.stat().st_size < 10_000
    with pytest.raises(FileFormatError, match=r"bomb.npz.*\(25, 20000, 20000\).*37.25 GiB.*"
                       r"HSI_TORCH_MAX_CUBE_GB"):
        load_cube(bomb)
    # the cap is the caller's to raise, or the environment's
    path = tmp_path / "c.npz"
    save_cube(path, np.zeros((25, 64, 64), np.float32), WL)  # 400 kB
    with pytest.raises(FileFormatError, match="c.npz.*0.00 GiB"):
        load_cube(path, max_bytes=100_000)
    monkeypatch.setenv("HSI_TORCH_MAX_CUBE_GB", "0.0001")
    with pytest.raises(FileFormatError, match="c.npz"):
        load_cube(path)
    assert load_cube(path, max_bytes=1 << 20).cube.shape == (25, 64, 64)
    for bad in ("inf", "nan", "-1", "lots"):
        monkeypatch.setenv("HSI_TORCH_MAX_CUBE_GB", bad)
        with pytest.raises(ValueError, match="HSI_TORCH_MAX_CUBE_GB"):
            load_cube(path)


@pytest.mark.parametrize("fmt", [".tif", ".hdr"])
def test_tiff_and_envi_cubes_are_bounded_by_their_headers(tmp_path, monkeypatch, fmt):
    save_cube(tmp_path / f"c{fmt}", np.zeros((25, 64, 64), np.float32), WL)
    monkeypatch.setenv("HSI_TORCH_MAX_CUBE_GB", "0.0001")  # 105 kB < the 410 kB cube
    with pytest.raises(FileFormatError, match=r"c\.(tif|hdr).*\(25, 64, 64\) float32"):
        load_cube(tmp_path / f"c{fmt}")


def test_a_file_named_npz_that_is_not_one_says_so(tmp_path):
    (tmp_path / "notes.npz").write_text("just text\n")
    np.save(tmp_path / "array.npy", np.zeros(3))
    os.replace(tmp_path / "array.npy", tmp_path / "array.npz")
    for name, what in (("notes.npz", "starts with b'just'"), ("array.npz", "an NPY array")):
        with pytest.raises(FileFormatError, match=f"{name}: not an NPZ file") as e:
            load_cube(tmp_path / name)
        assert what in str(e.value) and "allow_pickle" not in str(e.value)


def test_envi_header_that_describes_another_cube_is_refused(tmp_path, cube_and_valid):
    cube, _ = cube_and_valid  # (25, 6, 8)
    save_cube(tmp_path / "c.hdr", cube, WL)
    hdr = (tmp_path / "c.hdr").read_text()
    img = (tmp_path / "c.img").read_bytes()
    # a data file larger than its header says (another cube's, or appended bytes)
    (tmp_path / "c.img").write_bytes(img + img[: 6 * 8 * 4])
    with pytest.raises(FileFormatError, match=r"c.img.*holds 4992 bytes.*declares 4800 .*"
                       "another cube"):
        load_cube(tmp_path / "c.hdr")
    (tmp_path / "c.img").write_bytes(img)
    for key, lie in (("bands = 25", "bands = 24"), ("samples = 8", "samples = 4"),
                     ("data type = 4", "data type = 5"), ("lines = 6", "lines = 3")):
        (tmp_path / "c.hdr").write_text(hdr.replace(key, lie))
        with pytest.raises(FileFormatError, match=r"c\.(img|hdr)"):
            load_cube(tmp_path / "c.hdr")
    # bands and the data file agree, the wavelength list does not
    cut = np.ascontiguousarray(cube[:24])
    save_cube(tmp_path / "d.hdr", cut, WL[:24])
    (tmp_path / "d.hdr").write_text((tmp_path / "d.hdr").read_text().replace(
        "wavelength = {", "wavelength = {420, "))
    with pytest.raises(FileFormatError, match="d.hdr.*25 values of 'wavelength' for 24 bands"):
        load_cube(tmp_path / "d.hdr")
    (tmp_path / "c.hdr").write_text(hdr)
    assert_close(load_cube(tmp_path / "c.hdr").cube, torch.from_numpy(cube))
