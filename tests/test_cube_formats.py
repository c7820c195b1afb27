"""Cube files opened with the readers people use: tifffile (OME metadata), GDAL (rasterio),
`spectral` (ENVI), xarray (NetCDF, Zarr); the optional formats' clear error when the extra is
missing; older TIFFs still load."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
import torch

from hsi_torch.io import cube as cube_io
from hsi_torch.io import load_cube, save_cube, save_cube_formats

WL = np.arange(430.0, 671.0, 10.0)  # 25 bands


@pytest.fixture
def cube_valid():
    rng = np.random.default_rng(3)
    cube = rng.uniform(0, 1, size=(25, 7, 9)).astype(np.float32)
    valid = np.ones((7, 9), bool)
    valid[0, :4] = False
    return cube, valid


def _nan_cube(cube, valid):
    return np.where(valid[None], cube, np.float32(np.nan))


def test_tiff_is_ome_with_named_channels(tmp_path, cube_valid):
    import tifffile

    cube, valid = cube_valid
    tif, vrt = save_cube(tmp_path / "scene.tif", cube, WL, valid, {"scene": "scene", "beta": 1e4})
    assert (tif.name, vrt.name) == ("scene.tif", "scene.vrt")
    with tifffile.TiffFile(tif) as t:
        assert t.is_ome and len(t.pages) == 25
        series = t.series[0]
        assert series.axes == "CYX" and series.shape == (25, 7, 9)
        data = series.asarray()
        image = tifffile.xml2dict(t.ome_metadata)["OME"]["Image"]
    chans = image["Pixels"]["Channel"]
    assert [c["Name"] for c in chans] == [f"{w:g} nm" for w in WL]
    assert [c["EmissionWavelength"] for c in chans] == WL.tolist()
    assert {c["EmissionWavelengthUnit"] for c in chans} == {"nm"}
    assert np.array_equal(data, _nan_cube(cube, valid), equal_nan=True)
    assert json.loads(image["Description"])["beta"] == 1e4
    # our reader reads it back (wavelengths, metadata, valid = all bands finite)
    c = load_cube(tif)
    assert np.array_equal(c.cube.numpy(), data, equal_nan=True)
    assert c.wavelengths.tolist() == WL.tolist() and c.metadata["beta"] == 1e4
    assert torch.equal(c.valid, torch.from_numpy(valid))
    # same cube and metadata: same bytes (the OME UUID is derived from the content description)
    again = save_cube(tmp_path / "again.tif", cube, WL, valid, {"scene": "scene", "beta": 1e4})
    assert again[0].read_bytes() == tif.read_bytes()


def test_other_ome_tiffs_give_their_channel_wavelengths(tmp_path, cube_valid):
    """An OME-TIFF written by another tool: wavelengths from EmissionWavelength (µm here)."""
    import tifffile

    cube, _ = cube_valid
    tifffile.imwrite(tmp_path / "other.ome.tif", cube[:3], ome=True, photometric="minisblack",
                     metadata={"axes": "CYX", "Channel": {
                         "Name": ["a", "b", "c"], "EmissionWavelength": [0.45, 0.55, 0.65],
                         "EmissionWavelengthUnit": ["µm"] * 3}})  # fmt: skip
    c = load_cube(tmp_path / "other.ome.tif")
    torch.testing.assert_close(c.wavelengths, torch.tensor([450.0, 550.0, 650.0],
                                                           dtype=torch.float64))


def test_older_json_description_tiff_still_loads(tmp_path, cube_valid):
    import tifffile

    cube, _ = cube_valid
    desc = json.dumps({"hsi_torch_cube": 1, "wavelengths_nm": WL.tolist(), "beta": 3.0})
    tifffile.imwrite(tmp_path / "old.tif", cube, photometric="minisblack", description=desc,
                     metadata=None)  # fmt: skip
    c = load_cube(tmp_path / "old.tif")
    assert c.wavelengths.tolist() == WL.tolist() and c.metadata["beta"] == 3.0
    assert np.array_equal(c.cube.numpy(), cube)


def test_gdal_reads_25_named_bands(tmp_path, cube_valid):
    """GDAL (through rasterio) opens the .vrt as 25 bands named by wavelength with NaN no-data,
    the pixels being the OME-TIFF's; the ENVI pair as 25 bands with NaN no-data too."""
    rasterio = pytest.importorskip("rasterio")
    cube, valid = cube_valid
    save_cube_formats(tmp_path / "s", cube, WL, valid, formats=("tiff", "envi"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "not georeferenced": a camera frame has no CRS
        with rasterio.open(tmp_path / "s.vrt") as ds:
            assert ds.count == 25 and (ds.height, ds.width) == (7, 9)
            assert list(ds.descriptions) == [f"{w:g} nm" for w in WL]
            assert ds.tags(3) == {"wavelength": "450", "wavelength_units": "nm"}
            assert np.isnan(ds.nodata)
            assert np.array_equal(ds.read(), _nan_cube(cube, valid), equal_nan=True)
        with rasterio.open(tmp_path / "s.img") as ds:
            assert ds.count == 25 and np.isnan(ds.nodata)
            assert ds.tags(1)["wavelength"] == "430" and ds.tags(1)["wavelength_units"] == "nm"
            assert np.array_equal(ds.read(), _nan_cube(cube, valid), equal_nan=True)
        with rasterio.open(tmp_path / "s.tif") as ds:  # the TIFF alone: one page per band
            assert len(ds.subdatasets) == 25


def test_envi_data_ignore_value_in_spectral(tmp_path, cube_valid):
    import spectral

    cube, valid = cube_valid
    _, hdr = save_cube(tmp_path / "e.hdr", cube, WL, valid)
    img = spectral.envi.open(str(hdr))
    assert img.metadata["data ignore value"] == "nan"
    assert img.bands.centers == WL.tolist() and img.bands.band_unit == "nm"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # spectral warns about the NaN it was told to ignore
        arr = np.asarray(img.load()).transpose(2, 0, 1)
    assert np.array_equal(arr, _nan_cube(cube, valid), equal_nan=True)


@pytest.mark.parametrize("fmt", ["netcdf", "zarr"])
def test_xarray_formats(tmp_path, cube_valid, fmt):
    xr = pytest.importorskip("xarray")
    pytest.importorskip("netCDF4" if fmt == "netcdf" else "zarr")
    cube, valid = cube_valid
    (path,) = save_cube_formats(tmp_path / "s", cube, WL, valid, {"beta": 7.0}, formats=(fmt,))
    assert path.name == ("s.nc" if fmt == "netcdf" else "s.zarr")
    opener = xr.open_dataset if fmt == "netcdf" else xr.open_zarr
    with opener(path) as ds:
        da = ds["cube"]
        assert da.dims == ("wavelength", "y", "x") and da.shape == (25, 7, 9)
        assert da["wavelength"].values.tolist() == WL.tolist()
        assert da["wavelength"].attrs["units"] == "nm"
        assert np.array_equal(da.sel(wavelength=550).values, _nan_cube(cube, valid)[12],
                              equal_nan=True)  # fmt: skip
        assert np.array_equal(ds["valid"].values.astype(bool), valid)
        assert json.loads(da.attrs["hsi_torch_metadata"])["beta"] == 7.0
    c = load_cube(path)  # and back through our reader
    assert torch.equal(c.valid, torch.from_numpy(valid)) and c.metadata["beta"] == 7.0
    # rewriting replaces the file/folder atomically
    save_cube(path, cube * 0.5, WL, valid)
    assert np.allclose(load_cube(path).cube.numpy()[:, valid], 0.5 * cube[:, valid])
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]


def test_to_xarray_on_cube_and_result(cube_valid):
    pytest.importorskip("xarray")
    from hsi_torch.io import Cube
    from hsi_torch.recon.pipeline import ReconstructionResult

    cube, valid = cube_valid
    c = Cube(torch.from_numpy(_nan_cube(cube, valid)), torch.from_numpy(WL),
             torch.from_numpy(valid))  # fmt: skip
    da = c.to_xarray()
    assert da.name == "cube" and da.sel(wavelength=430).shape == (7, 9)
    assert da["valid"].values.tolist() == valid.tolist()
    res = ReconstructionResult(torch.from_numpy(cube), torch.from_numpy(valid),
                               torch.from_numpy(WL))  # fmt: skip
    da2 = res.to_xarray({"scene": "x"})
    assert np.array_equal(da2.values, da.values, equal_nan=True)
    assert json.loads(da2.attrs["hsi_torch_metadata"]) == {"scene": "x"}


def test_missing_optional_packages_say_what_to_install(tmp_path, monkeypatch, capsys,
                                                      cube_valid):  # fmt: skip
    import importlib.util
    import sys

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name == "xarray" else real(name, *a))
    monkeypatch.setitem(sys.modules, "xarray", None)  # `import xarray` fails
    cube, valid = cube_valid
    with pytest.raises(ModuleNotFoundError, match=r"pip install 'hsi-torch\[formats\]'"):
        save_cube_formats(tmp_path / "s", cube, WL, valid, formats=("npz", "netcdf"))
    assert list(tmp_path.iterdir()) == []  # checked before anything was written
    with pytest.raises(ModuleNotFoundError, match="hsi-torch"):
        cube_io.cube_to_xarray(cube, WL, valid)
    from hsi_torch.cli import main

    rc = main(["reconstruct", "--bundle", str(tmp_path / "b.npz"), "--out", str(tmp_path / "o"),
               "--set", "formats=[zarr]", "x.tif"])  # fmt: skip
    assert rc == 1
    err = capsys.readouterr().err
    assert "config key 'formats'" in err and "hsi-torch[formats]" in err
    assert not (tmp_path / "o").exists()
