"""The viewer: cube files → napari layers (every format we write), spectra at points, the napari
plugin (npe2 manifest, reader, click → spectrum, band slider in nm) and ``hsi-torch view``'s
screenshot.

The napari tests run headless: on a virtual X server (``Xvfb``, started here when no display is
set; ``scripts/install.sh test`` installs it with the Qt/X libraries on Debian) and skip with the
reason when napari, Qt or a display cannot be had. ``HSI_TORCH_WRITE_DOC_IMAGES=1`` also writes
the screenshot to ``docs/img/napari_view.png`` (the README's).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from hsi_torch.io.cube import save_cube_formats
from hsi_torch.viewer.data import is_cube_path, read_layers, spectrum_at, std_companion

REPO = Path(__file__).resolve().parents[1]
WL = np.arange(430.0, 671.0, 10.0)


def _cube(h: int = 30, w: int = 40, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    g = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w]
    centre = 450 + 200 * xx / w
    cube = np.exp(-0.5 * ((WL[:, None, None] - centre[None]) / 40.0) ** 2) * (0.3 + 0.5 * yy / h)
    cube = (cube + 0.01 * g.random(cube.shape)).astype(np.float32)
    valid = np.ones((h, w), bool)
    valid[:5, :7] = False
    std = (0.02 + 0.01 * g.random(cube.shape)).astype(np.float32)
    return cube, valid, std


FORMATS = ["tiff", "envi", "npz", "netcdf", "zarr"]
SUFFIX = {"tiff": ".tif", "envi": ".hdr", "npz": ".npz", "netcdf": ".nc", "zarr": ".zarr"}


def _write(tmp: Path, fmt: str, with_std: bool = True) -> Path:
    if fmt in ("netcdf", "zarr"):
        pytest.importorskip("xarray")
        pytest.importorskip("netCDF4" if fmt == "netcdf" else "zarr")
    cube, valid, std = _cube()
    stem = tmp / "scene"
    save_cube_formats(stem, cube, WL, valid, {"scene": "test"}, formats=(fmt,),
                      npz_arrays={"std": std} if with_std and fmt == "npz" else None)  # fmt: skip
    if with_std and fmt != "npz":
        save_cube_formats(tmp / "scene_std", std, WL, valid, {"quantity": "std"}, formats=(fmt,))
    return stem.with_suffix(SUFFIX[fmt])


@pytest.mark.parametrize("fmt", FORMATS)
def test_reader_on_every_format(tmp_path, fmt):
    path = _write(tmp_path, fmt)
    assert is_cube_path(path) and not is_cube_path(tmp_path / ("scene_std" + SUFFIX[fmt]))
    (data, kw, kind), (rgb, rgb_kw, rgb_kind) = read_layers(path)
    cube, valid, std = _cube()
    assert kind == rgb_kind == "image" and data.shape == cube.shape
    np.testing.assert_allclose(data[:, valid], cube[:, valid], rtol=1e-6)
    assert np.isnan(data[:, ~valid]).all()
    np.testing.assert_allclose(kw["metadata"]["wavelengths_nm"], WL)
    assert (kw["metadata"]["valid"] == valid).all()
    # the band axis is in nm: index b sits at 430 + 10 b
    assert kw["scale"][0] == pytest.approx(10.0) and kw["translate"][0] == pytest.approx(430.0)
    assert kw["units"][0] == "nm" and kw["axis_labels"][0] == "wavelength"
    np.testing.assert_allclose(kw["metadata"]["std"][:, valid], std[:, valid], rtol=1e-6)
    assert rgb_kw["rgb"] and rgb.shape == (*cube.shape[1:], 3)
    assert (rgb[~valid] == 0).all() and rgb[valid].max() > 0.5  # black outside, bright inside
    # the sRGB composite follows the spectra: red where the peak is long, blue where short
    assert rgb[20, 38, 0] > rgb[20, 38, 2] and rgb[20, 2, 2] > rgb[20, 2, 0]


def test_no_std_without_companion(tmp_path):
    path = _write(tmp_path, "tiff", with_std=False)
    assert std_companion(path) is None
    assert read_layers(path)[0][1]["metadata"]["std"] is None


def test_run_store_has_a_frame_axis(tmp_path):
    pytest.importorskip("xarray")
    pytest.importorskip("zarr")
    from hsi_torch.io.dataset import CubeDataset, write_frame

    cube, valid, _ = _cube()
    store = tmp_path / "cubes.zarr"
    sources = [tmp_path / "a.tif", tmp_path / "b.tif", tmp_path / "c.tif"]
    with CubeDataset.open(store, sources, WL, cube.shape[1:]) as ds:
        idx = [ds.index[os.path.abspath(s)] for s in sources]
    write_frame(store, idx[0], cube, valid, {"n": 0})
    write_frame(store, idx[2], cube * 0.5, valid, {"n": 2})  # frame 1 never completed
    (data, kw, _), (rgb, _, _) = read_layers(store)
    assert data.shape == (2, *cube.shape) and rgb.shape == (2, *cube.shape[1:], 3)
    np.testing.assert_allclose(data[1][:, valid], 0.5 * cube[:, valid], rtol=1e-6)
    assert kw["metadata"]["frames"] == [str(sources[0]), str(sources[2])]
    assert kw["scale"][:2] == [1.0, 10.0] and kw["axis_labels"][:2] == ["frame", "wavelength"]
    sp = spectrum_at(data, kw["metadata"], 10, 20, frame=1)
    np.testing.assert_allclose(sp.values, 0.5 * cube[:, 10, 20], rtol=1e-6)


def test_spectrum_at_respects_the_valid_mask(tmp_path):
    (data, kw, _), _ = read_layers(_write(tmp_path, "npz"))
    cube, valid, std = _cube()
    sp = spectrum_at(data, kw["metadata"], 12.4, 30.6)
    assert (sp.row, sp.col) == (12, 31)
    np.testing.assert_allclose(sp.values, cube[:, 12, 31], rtol=1e-6)
    np.testing.assert_allclose(sp.std, std[:, 12, 31], rtol=1e-6)
    assert spectrum_at(data, kw["metadata"], 2, 3) is None  # not valid
    assert spectrum_at(data, kw["metadata"], -1, 3) is None  # outside
    assert spectrum_at(data, kw["metadata"], 2, 40) is None


def test_manifest_is_valid_npe2():
    npe2 = pytest.importorskip("npe2")
    mf = npe2.PluginManifest.from_file(REPO / "hsi_torch" / "viewer" / "napari.yaml")
    assert mf.name == "hsi-torch"
    assert {c.id for c in mf.contributions.commands} == {"hsi-torch.get_reader",
                                                         "hsi-torch.spectrum_widget"}
    pats = mf.contributions.readers[0].filename_patterns
    assert {"*.tif", "*.hdr", "*.npz", "*.nc", "*.zarr"} <= set(pats)


def test_importing_the_package_loads_no_napari():
    out = subprocess.run(
        ["python3", "-c", "import sys, hsi_torch, hsi_torch.viewer, hsi_torch.viewer.data, "
         "hsi_torch.metrics, hsi_torch.recon.camera, hsi_torch.cli; "
         "print(sorted(m for m in sys.modules if m.split('.')[0] in "
         "('napari', 'qtpy', 'PyQt5', 'deepinv', 'vispy')))"],
        env={**os.environ, "PYTHONPATH": str(REPO)}, capture_output=True, text=True, timeout=300,
        check=True,
    )  # fmt: skip
    assert out.stdout.strip() == "[]"


# ------------------------------------------------------------------------------------- napari --

@pytest.fixture(scope="module")
def display():
    """A display for Qt: the one set, else a private Xvfb (skip when neither)."""
    if os.environ.get("DISPLAY"):
        yield os.environ["DISPLAY"]
        return
    xvfb = shutil.which("Xvfb")
    if xvfb is None:
        pytest.skip("no display and no Xvfb (scripts/install.sh test installs it on Debian)")
    num = 90 + os.getpid() % 500
    proc = subprocess.Popen([xvfb, f":{num}", "-screen", "0", "1600x1000x24", "-nolisten", "tcp"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    time.sleep(1.5)
    if proc.poll() is not None:
        pytest.skip(f"Xvfb :{num} did not start")
    os.environ["DISPLAY"] = f":{num}"
    try:
        yield os.environ["DISPLAY"]
    finally:
        os.environ.pop("DISPLAY", None)
        proc.terminate()
        proc.wait(timeout=10)


@pytest.fixture(scope="module")
def napari(display):
    os.environ.setdefault("QT_QPA_PLATFORM", "xcb")
    try:
        import napari
        from qtpy.QtWidgets import QApplication  # noqa: F401
    except Exception as exc:  # noqa: BLE001 - any reason napari/Qt cannot load: skip, say why
        pytest.skip(f"napari/Qt not importable: {type(exc).__name__}: {exc}")
    return napari


@pytest.fixture
def viewer(napari):
    v = napari.Viewer(show=False)
    yield v
    v.close()


def _click(viewer, world):
    """A left click at a world position, through napari's mouse-callback machinery."""
    from types import SimpleNamespace

    from napari.utils.interactions import mouse_press_callbacks

    ev = SimpleNamespace(type="mouse_press", button=1, position=tuple(world), modifiers=(),
                         handled=False, is_dragging=False, pos=(0, 0), view_direction=None,
                         dims_displayed=list(range(viewer.dims.ndim))[-2:])  # fmt: skip
    mouse_press_callbacks(viewer, ev)


def test_plugin_reader_and_click(tmp_path, viewer):
    from npe2 import PluginManager, PluginManifest

    from hsi_torch.viewer.plugin import SpectrumWidget

    pm = PluginManager.instance()
    mf = PluginManifest.from_file(REPO / "hsi_torch" / "viewer" / "napari.yaml")
    if mf.name not in pm._manifests:
        pm.register(mf)
    path = _write(tmp_path, "tiff")
    layers = viewer.open(str(path), plugin="hsi-torch")
    assert [ly.name for ly in layers] == ["scene (bands)", "scene (sRGB)"]
    band = layers[0]
    viewer.layers.selection.active = band
    w = SpectrumWidget(viewer)
    # the slider is in nm and moves the viewer
    assert w.slider.maximum() == len(WL) - 1
    w.slider.setValue(12)
    assert w.band_label.text() == "550 nm" and w.current_band() == 12
    assert viewer.dims.point[0] == pytest.approx(550.0)  # the world band coordinate is nm
    # a click on pixel (12, 31) plots that pixel's spectrum with its sigma
    cube, valid, std = _cube()
    _click(viewer, band.data_to_world([12, 12, 31]))
    assert len(w.points) == 1
    name, sp = w.points[0]
    assert name == "scene (bands)" and (sp.row, sp.col) == (12, 31)
    np.testing.assert_allclose(sp.values, cube[:, 12, 31], rtol=1e-6)
    np.testing.assert_allclose(sp.std, std[:, 12, 31], rtol=1e-6)
    line = w.ax.get_lines()[0]
    np.testing.assert_allclose(line.get_xdata(), WL)
    np.testing.assert_allclose(line.get_ydata(), cube[:, 12, 31], rtol=1e-6)
    assert len(w.ax.collections) == 1  # the ±σ band
    # a second point: two curves; a click outside the valid mask adds none
    _click(viewer, band.data_to_world([12, 25, 5]))
    _click(viewer, band.data_to_world([12, 2, 3]))
    assert len(w.points) == 2 and len(w.ax.get_lines()) == 2
    assert "valid region" in w.status.text()
    w.clear()
    assert w.points == [] and w.ax.get_lines() == []


@pytest.mark.slow
def test_view_screenshot_of_a_demo_cube(tmp_path, napari):
    """``hsi-torch view`` on the quick demo's ColorChecker capture reconstructed with its
    calibrated bundle and ``uncertainty=true`` (so the ``_std`` companion exists), three points
    with their ±σ bands: the README's screenshot."""
    from hsi_torch import cli
    from hsi_torch.experiments.demo import demo

    out = tmp_path / "demo"
    demo(out, quick=True, log=lambda *_: None)
    cubes = tmp_path / "cubes"
    assert cli.main(["reconstruct", "--bundle", str(out / "calib.npz"), "--out", str(cubes),
                     "--set", "uncertainty=true", "-q",
                     str(out / "captures" / "scenes" / "colorchecker.tif")]) == 0  # fmt: skip
    cube = cubes / "colorchecker.tif"
    assert std_companion(cube) == cubes / "colorchecker_std.tif"
    png = tmp_path / "view.png"
    rc = cli.main(["view", str(cube), "--point", "71,25", "--point", "63,49", "--point", "63,33",
                   "--band", "600", "--screenshot", str(png)])  # fmt: skip
    assert rc == 0 and png.is_file()
    import matplotlib.image as mpimg

    img = mpimg.imread(png)
    assert img.shape[0] > 400 and img.shape[1] > 600
    assert img[..., :3].std() > 0.05  # not a blank window
    if os.environ.get("HSI_TORCH_WRITE_DOC_IMAGES") == "1":
        shutil.copy(png, REPO / "docs" / "img" / "napari_view.png")


def test_screenshot_over_a_viewed_cube_is_refused_before_napari_starts(tmp_path, capsys):
    """``hsi-torch view cube.tif --screenshot cube.tif`` wrote the window's PNG over the cube
    being viewed (through a symlink too). Now refused before napari starts, the cube unchanged."""
    from hsi_torch import cli

    cube = tmp_path / "cube.tif"
    cube.write_bytes(b"a cube")
    link = tmp_path / "shot.png"
    link.symlink_to(cube)
    for target in (cube, link):
        assert cli.main(["view", str(cube), "--screenshot", str(target)]) == 1
        assert "is an input of this command" in capsys.readouterr().err
    assert cube.read_bytes() == b"a cube"


def test_a_small_file_declaring_a_huge_cube_is_refused_before_decoding(tmp_path, monkeypatch):
    """A 40 kB NPZ of zeros that inflates to 36 MB; the cap made 10 MiB to show the bound (by
    default 1 GiB, $HSI_TORCH_MAX_CUBE_GB): nothing is decoded, the message names the file."""
    np.savez_compressed(tmp_path / "bomb.npz", cube=np.zeros((25, 600, 600), np.float32),
                        wavelengths_nm=WL)  # fmt: skip
    assert (tmp_path / "bomb.npz").stat().st_size < 100_000
    monkeypatch.setenv("HSI_TORCH_MAX_CUBE_GB", str(10 / 1024))
    decoded = []
    real = np.lib.format.read_array
    monkeypatch.setattr(np.lib.format, "read_array",
                        lambda f, *a, **k: decoded.append(real(f, *a, **k)) or decoded[-1])
    with pytest.raises(Exception, match=r"bomb.npz.*\(25, 600, 600\) float32.*0.03 GiB.*0.01 GiB"):
        read_layers(tmp_path / "bomb.npz")
    assert not any(a.size > 1000 for a in decoded)  # nothing large decoded (the headers only)


def _run_store(tmp_path: Path) -> Path:
    from hsi_torch.io.dataset import CubeDataset, write_frame

    cube, valid, _ = _cube()
    store = tmp_path / "cubes.zarr"
    with CubeDataset.open(store, [tmp_path / "a.tif"], WL, cube.shape[1:]) as ds:
        idx = ds.index[os.path.abspath(tmp_path / "a.tif")]
    write_frame(store, idx, cube, valid, {"n": 0})
    return store


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs here")
def test_run_store_with_a_fifo_device_or_bomb_inside_is_refused(tmp_path):
    """A FIFO chunk used to hang the viewer, a /dev/zero chunk to fill the memory, a deeply
    nested .zmetadata to raise RecursionError: each is refused naming the file."""
    pytest.importorskip("xarray")
    pytest.importorskip("zarr")
    import signal

    from hsi_torch.errors import FileFormatError

    def timeout(*_):
        raise TimeoutError("the reader blocked")

    old = signal.signal(signal.SIGALRM, timeout)
    try:
        store = _run_store(tmp_path)
        chunk = store / "cube" / "0.0.0.0"
        saved = chunk.read_bytes()
        chunk.unlink()
        os.mkfifo(chunk)
        signal.alarm(20)
        with pytest.raises(FileFormatError, match=r"cube/0\.0\.0\.0: is a FIFO"):
            read_layers(store)
        chunk.unlink()
        chunk.symlink_to("/dev/zero")
        with pytest.raises(FileFormatError, match=r"cube/0\.0\.0\.0: is a character device"):
            read_layers(store)
        chunk.unlink()
        chunk.write_bytes(saved)
        assert read_layers(store)[0][0].shape[0] == 1  # the store reads again
        zm = store / ".zmetadata"
        zm.write_text("[" * 200_000 + "]" * 200_000)
        with pytest.raises(FileFormatError, match=r"\.zmetadata.*nested too deeply"):
            read_layers(store)
        zm.unlink()
        os.mkfifo(zm)
        with pytest.raises(FileFormatError, match=r"\.zmetadata: is a FIFO"):
            read_layers(store)
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def test_spectra_follow_the_displayed_frame_and_the_band_slider_is_in_nm(tmp_path, viewer):
    """``view run/cubes.zarr --point 80,40`` with frame 1 displayed plotted frame 0's spectrum;
    napari's band slider showed the band index. Now the points' spectra are replotted from the
    displayed frame, and the band slider is labelled with the band's wavelength, for a run store
    and for a single TIFF cube alike."""
    pytest.importorskip("xarray")
    pytest.importorskip("zarr")
    from hsi_torch.io.dataset import CubeDataset, write_frame
    from hsi_torch.viewer.plugin import SpectrumWidget

    cube, valid, _ = _cube()
    store = tmp_path / "cubes.zarr"
    sources = [tmp_path / "a.tif", tmp_path / "b.tif"]
    with CubeDataset.open(store, sources, WL, cube.shape[1:]) as ds:
        idx = [ds.index[os.path.abspath(s)] for s in sources]
    valid1 = valid.copy()
    valid1[20, 30] = False  # not valid in frame 1
    write_frame(store, idx[0], cube, valid, {"n": 0})
    write_frame(store, idx[1], 0.5 * cube, valid1, {"n": 1})
    for data, kw, kind in read_layers(store):
        getattr(viewer, f"add_{kind}")(data, **kw)
    band = next(ly for ly in viewer.layers if ly.metadata.get("hsi_torch"))
    viewer.layers.selection.active = band
    w = SpectrumWidget(viewer)
    w.add_point(band.data_to_world([0, 3, 12, 31]))  # frame 0, pixel (row 12, col 31)
    w.add_point(band.data_to_world([0, 3, 20, 30]))
    np.testing.assert_allclose(w.points[0][1].values, cube[:, 12, 31], rtol=1e-6)
    viewer.dims.set_point(0, float(band.data_to_world([1, 0, 0, 0])[0]))  # show frame 1
    assert w.current_frame() == 1
    (_, sp), (_, gone) = w.points
    assert sp.frame == 1 and (sp.row, sp.col) == (12, 31)
    np.testing.assert_allclose(sp.values, 0.5 * cube[:, 12, 31], rtol=1e-6)  # was frame 0's
    np.testing.assert_allclose(w.ax.get_lines()[0].get_ydata(), 0.5 * cube[:, 12, 31], rtol=1e-6)
    assert gone.frame == 1 and np.isnan(gone.values).all()  # not valid there: no curve
    w.slider.setValue(12)
    assert viewer.dims.axis_labels[1] == "550 nm" and w.band_label.text() == "550 nm"

    viewer.layers.clear()
    for data, kw, kind in read_layers(_write(tmp_path, "tiff")):
        getattr(viewer, f"add_{kind}")(data, **kw)
    band = next(ly for ly in viewer.layers if ly.metadata.get("hsi_torch"))
    viewer.layers.selection.active = band
    w2 = SpectrumWidget(viewer)
    w2.slider.setValue(5)
    assert viewer.dims.axis_labels[0] == "480 nm" and w2.current_frame() is None
