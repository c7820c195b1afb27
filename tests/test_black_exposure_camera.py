"""Black level, exposure and camera identity from calibration to reconstruction, the pedestal
check, version-1 bundles, and the module's cube-only form.

The end-to-end tests turn the small simulated capture set into a lab's plain files: Bayer TIFFs
without black level (the 512 DN pedestal left in), white shots with ``exposure_s`` and a camera
make/model in their metadata, a scene at half the white's exposure.
"""

from __future__ import annotations

import json
import re
import zipfile
from pathlib import Path

import numpy as np
import pytest
import tifffile
import torch
from test_pipeline import make_bundle, render_capture, true_spectra

from hsi_torch.cli import main
from hsi_torch.errors import FileFormatError
from hsi_torch.io import load_cube, read_any
from hsi_torch.io.bundle import READABLE_SCHEMA_VERSIONS, SCHEMA_VERSION, CalibrationBundle
from hsi_torch.io.capture_set import read_truth
from hsi_torch.io.radiometry import (
    CameraIdentity,
    black_level_rgb,
    camera_mismatches,
    outside_views_index,
    pedestal_limit,
)
from hsi_torch.recon import Reconstructor
from hsi_torch.recon.checks import exposure_info, frame_findings
from hsi_torch.recon.module import HSIReconstructor
from hsi_torch.resources import shipped_config

# ---------------------------------------------------------------------------------------------
# units


def test_black_level_forms():
    assert black_level_rgb(512) == [512.0] * 3
    assert black_level_rgb([1, 2, 3]) == [1.0, 2.0, 3.0]
    # Bayer cell, row-major: GRBG → R is the 2nd, B the 3rd, the greens averaged
    assert black_level_rgb([10, 20, 30, 12], "GRBG") == [20.0, 11.0, 30.0]
    assert black_level_rgb([10, 20, 30, 12]) is None  # 4 values need the pattern
    assert black_level_rgb("abc") is None and black_level_rgb(None) is None


def test_the_bundles_black_level_is_applied_by_the_reader(tmp_path):
    """A file without a black level read with the bundle's per-colour level as a default equals
    reading the mosaic with that level as its Bayer cell, and subtracting it from either
    demosaic (both form a colour from its own sites only); a level given, or the file's own,
    wins (the one rule, :func:`black_level_rule`)."""
    from hsi_torch.io.captures import CaptureDefaults, black_level_rule

    g = np.random.default_rng(0)
    mos = (600 + 3000 * g.random((24, 30))).astype(np.uint16)
    p = tmp_path / "plain.tif"
    tifffile.imwrite(p, mos, photometric="minisblack", metadata=None)
    rgb = (510.0, 512.0, 515.0)
    bundle = CaptureDefaults(black_level_rgb=rgb, cfa_pattern="GBRG")
    for demosaic in ("bilinear", "half"):
        ref = read_any(p, cfa_pattern="GBRG", black_level=[512, 515, 510, 512],
                       demosaic=demosaic, dtype=torch.float64)  # GBRG cell: G B / R G
        cap = read_any(p, demosaic=demosaic, dtype=torch.float64, defaults=bundle)
        torch.testing.assert_close(cap.image, ref.image, rtol=0, atol=1e-9)
        torch.testing.assert_close(cap.mosaic, ref.mosaic, rtol=0, atol=1e-9)
        assert torch.equal(cap.saturated, ref.saturated)
        zero = read_any(p, cfa_pattern="GBRG", demosaic=demosaic, dtype=torch.float64)
        torch.testing.assert_close(cap.image, zero.image - torch.tensor(rgb).view(3, 1, 1),
                                   rtol=0, atol=1e-9)  # fmt: skip
        assert cap.metadata["black_level_source"] == "bundle"
        assert cap.metadata["black_level"] == list(rgb)
        given = read_any(p, demosaic=demosaic, black_level=7, dtype=torch.float64,
                         defaults=bundle)  # fmt: skip
        assert given.metadata["black_level_source"] == "config"
        torch.testing.assert_close(given.image, zero.image - 7, rtol=0, atol=1e-9)
    assert black_level_rule(None, "config", None, (0.0, 0.0, 0.0)) == (0.0, "default")
    assert black_level_rule(None, "config", 64, rgb) == (64, "file")
    assert black_level_rule(3, "sheet", 64, rgb) == (3, "sheet")


def test_outside_views_index_and_limit():
    tri = np.array([[[10.0, 10.0], [50.0, 10.0], [10.0, 50.0]]])
    idx = outside_views_index(tri, (60, 80), margin_px=4)
    y, x = idx // 80, idx % 80
    assert idx.size > 0
    # every sample is more than 4 px from the triangle (beyond its edge lines)
    assert np.all((x < 6) | (y < 6) | (x + y > 60 + 4 * np.sqrt(2)))
    assert (5 * 80 + 5) in set(idx.tolist()) and (20 * 80 + 20) not in set(idx.tolist())
    # both windings give the same pixels
    assert np.array_equal(outside_views_index(tri[:, ::-1], (60, 80), margin_px=4), idx)
    # limit: 0.25 % of a 14-bit span, or 5 sigma of the noise
    assert pedestal_limit(16383 - 512, 2.0) == pytest.approx(0.0025 * 15871)
    assert pedestal_limit(255, 3.0) == 15.0 and pedestal_limit(None, 0.0) == 1.0


def test_camera_mismatches_name_both_cameras():
    bundle = CameraIdentity(make="Canon", model="Canon EOS 5D Mark II", cfa_pattern="RGGB",
                            black_level=(512.0,) * 3, white_level=16383.0)
    same = CameraIdentity(make="canon", model="Canon  EOS 5D Mark II", cfa_pattern="RGGB")
    assert camera_mismatches(bundle, same) == []
    other = CameraIdentity(make="Nikon", model="D700", cfa_pattern="GRBG",
                           black_level=(0.0,) * 3, white_level=4095.0)
    m = camera_mismatches(bundle, other)
    assert "Nikon D700" in m[0] and "Canon EOS 5D Mark II" in m[0]
    assert any("GRBG" in s and "RGGB" in s for s in m)
    assert any("white level is 4095" in s for s in m) and any("black level is 0" in s for s in m)
    assert camera_mismatches(None, other) == []
    assert camera_mismatches(bundle, CameraIdentity()) == []
    assert CameraIdentity.from_dict(bundle.to_dict()) == bundle


def test_exposure_info_words_and_units():
    from hsi_torch.recon.checks import BundleRadiometry

    rad = BundleRadiometry(white_exposure_s=0.02, white_exposure_unit="s")
    t, st = exposure_info({"exposure_s": 0.01}, rad, 0.02)
    assert t == 0.01 and st["radiometric_scale"] == "reflectance"
    assert st["exposure_note"] == "exposure 1/2 of the white's: scaled x2"
    _, st = exposure_info({"exposure_s": 0.08}, rad, 0.02)
    assert st["exposure_note"] == "exposure 4x of the white's: scaled x0.25"
    t, st = exposure_info({}, rad, 0.02)
    assert t is None and st["radiometric_scale"] == "relative"
    (f,) = frame_findings(st)
    assert "exposure_s" in st["exposure_note"] and "relative" in f.message
    assert f.code == "capture.exposure_unknown" and f.severity == "warning"
    # the simulator's relative exposure is not comparable with seconds
    t, st = exposure_info({"exposure": 0.4}, rad, 0.02)
    assert t is None and st["radiometric_scale"] == "relative" and "not comparable" in \
        st["exposure_note"]
    # a bundle without the unit (version 1): compared as before
    t, st = exposure_info({"exposure_s": 0.04}, BundleRadiometry(), 0.02)
    assert t == 0.04 and st["radiometric_scale"] == "reflectance"
    _, st = exposure_info({"exposure_s": 0.04}, rad, 0.02, correction=False)
    assert st["radiometric_scale"] == "uncorrected" and frame_findings(st) == []
    (f,) = frame_findings({**st, "radiometric_scale": "reflectance", "exposure_scale": 2.0,
                           "exposure_note": "n"})
    assert (f.code, f.severity, f.message, f.measured) == ("capture.exposure_scaled", "info", "n",
                                                           2.0)


# ---------------------------------------------------------------------------------------------
# version-1 bundles, bad version-2 settings


def _rewrite_meta(src: Path, dst: Path, edit) -> Path:
    with np.load(src, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(str(arrays["meta"]))
    edit(meta)
    arrays["meta"] = np.array(json.dumps(meta))
    np.savez(dst, **arrays)
    return dst


def test_version_1_bundle_still_loads_and_reconstructs(tmp_path):
    b = make_bundle(white_exposure_s=0.01, black_level_rgb=[5.0, 5.0, 5.0],
                    camera={"make": "Canon", "model": "EOS 5D Mark II"})
    assert SCHEMA_VERSION == 2 and READABLE_SCHEMA_VERSIONS == (1, 2)
    p = b.save(tmp_path / "v2.npz")

    def to_v1(meta):
        meta["schema_version"] = 1
        for k in ("black_level_rgb", "camera"):
            meta["settings"].pop(k)

    old = _rewrite_meta(p, tmp_path / "v1.npz", to_v1)
    b1 = CalibrationBundle.load(old)
    assert b1.schema_version == 1 and b1.camera is None and b1.black_level_rgb is None
    assert CalibrationBundle.load(p).camera.name == "Canon EOS 5D Mark II"
    b1.save(tmp_path / "again.npz")  # kept as version 1
    assert CalibrationBundle.load(tmp_path / "again.npz").schema_version == 1
    s = true_spectra()
    img = render_capture(b1, s)
    np.save(tmp_path / "a.npy", img.numpy())
    for bundle, black in ((old, 0.0), (p, 5.0)):  # v1: nothing subtracted; v2: the bundle's
        res = Reconstructor(bundle, beta=0.0, dtype=torch.float64).reconstruct_file(
            tmp_path / "a.npy")
        assert res.stats["black_level_source"] == ("default" if black == 0 else "bundle")
        assert res.stats["radiometric_scale"] == "relative"  # a.npy carries no exposure
    with zipfile.ZipFile(old) as z:
        assert "meta.npy" in z.namelist()


@pytest.mark.parametrize("key, value, match", [
    ("black_level_rgb", "abc", "settings.black_level_rgb"),
    ("black_level_rgb", [1.0, 2.0], "settings.black_level_rgb"),
    ("camera", [1], "settings.camera"),
    ("white_exposure_unit", 3, "settings.white_exposure_unit"),
])  # fmt: skip
def test_bad_version_2_settings_are_refused_naming_the_key(tmp_path, key, value, match):
    p = make_bundle().save(tmp_path / "ok.npz")
    bad = _rewrite_meta(p, tmp_path / "bad.npz", lambda m: m["settings"].__setitem__(key, value))
    with pytest.raises(FileFormatError, match=rf"bad\.npz.*{match}"):
        CalibrationBundle.load(bad)


# ---------------------------------------------------------------------------------------------
# the module's cube-only form


def test_module_cube_output_drops_into_sequential(device):
    bundle = make_bundle()
    x = render_capture(bundle, true_spectra()).float()[None].to(device)
    rec = HSIReconstructor.from_bundle(bundle, beta=1.0, device=device, output="cube",
                                       fill_value=0.0)
    net = torch.nn.Sequential(rec, torch.nn.Conv2d(8, 4, 3)).to(device)
    out = net(x.requires_grad_(True))
    assert out.shape == (1, 4, 18, 18) and torch.isfinite(out).all()
    out.square().mean().backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
    ref = HSIReconstructor.from_bundle(bundle, beta=1.0, device=device)(x.detach())
    cube = rec(x.detach())
    assert isinstance(cube, torch.Tensor) and cube.shape == ref.cube.shape
    v = ref.valid.unsqueeze(1).expand_as(cube)
    assert torch.equal(cube[v], ref.cube[v]) and bool((cube[~v] == 0).all()) and (~v).any()
    m1 = HSIReconstructor.from_bundle(bundle, beta=1.0, output="cube", fill_value=-1.0)
    assert bool((m1(x.detach().cpu())[~v.cpu()] == -1).all())
    with pytest.raises(ValueError, match="output must be one of"):
        HSIReconstructor.from_bundle(bundle, output="tuple")


def test_state_dict_round_trip_is_bit_exact(tmp_path, dtype):
    """A module loaded from another's state dict (through a file) gives its output bit for bit,
    in float32 as in float64 (the model is formed from φ in float64 both ways)."""
    b1 = make_bundle()
    b2 = make_bundle(seed=3)  # the same geometry, other gains
    x = render_capture(b1, true_spectra()).to(dtype)[None]
    m1 = HSIReconstructor.from_bundle(b1, beta=1.0, dtype=dtype, output="cube")
    m2 = HSIReconstructor.from_bundle(b2, beta=1.0, dtype=dtype, output="cube")
    ref = m1(x)
    assert not torch.equal(m2(x), ref)
    torch.save(m1.state_dict(), tmp_path / "sd.pt")
    m2.load_state_dict(torch.load(tmp_path / "sd.pt", weights_only=False))
    assert torch.equal(m2(x), ref)
    for name, buf in m1.named_buffers():
        assert torch.equal(getattr(m2, name), buf), name


# ---------------------------------------------------------------------------------------------
# end to end on the small simulated capture set, as a lab's plain files


def _plain(src: Path, dst: Path, meta: dict | None = None) -> None:
    a = tifffile.imread(src)
    desc = json.dumps(meta) if meta else None
    dst.parent.mkdir(parents=True, exist_ok=True)
    tifffile.imwrite(dst, a, photometric="minisblack", metadata=None, description=desc)


CANON = {"camera_make": "Canon", "camera_model": "EOS 5D Mark II"}


@pytest.fixture(scope="module")
def lab(small_sim: Path, tmp_path_factory) -> dict[str, Path]:
    """The small simulated set (scenes: the ColorChecker) as plain Bayer TIFFs: no black level
    (512 DN left in the data), no CFA pattern; the white shots name their exposure (0.02 s) and
    camera; a dark frame in ``withdark`` only; a scene at half the white's exposure."""
    sim = small_sim  # the session's shared, read-only set
    root = tmp_path_factory.mktemp("lab")
    out = {"sim": sim}
    for name, dark in (("nodark", False), ("withdark", True)):
        d = root / name
        for sub in ("scan", "grid", "white") + (("dark",) if dark else ()):
            for f in sorted((sim / sub).glob("*.tif")):
                meta = {"exposure_s": 0.02, **CANON} if sub == "white" else None
                _plain(f, d / sub / f.name, meta)
        for f in ("nominal_layout.json", "brf_free_mask.png"):
            (d / f).write_bytes((sim / f).read_bytes())
        out[name] = d
    scenes = root / "scenes"
    cc = tifffile.imread(sim / "scenes" / "colorchecker.tif").astype(np.float64)
    _plain(sim / "scenes" / "colorchecker.tif", scenes / "plain.tif")
    _plain(sim / "scenes" / "colorchecker.tif", scenes / "full.tif", {"exposure_s": 0.02})
    half = np.rint(512 + (cc - 512) / 2).astype(np.uint16)  # half the exposure, same pedestal
    tifffile.imwrite(scenes / "half.tif", half, photometric="minisblack", metadata=None,
                     description=json.dumps({"exposure_s": 0.01}))
    _plain(sim / "scenes" / "colorchecker.tif", scenes / "nikon.tif",
           {"exposure_s": 0.02, "camera_make": "Nikon", "camera_model": "D700"})
    out["scenes"] = scenes
    return out


def _psnr(cube_path: Path, sim: Path) -> tuple[float, float]:
    from hsi_torch.experiments.metrics import erode_px, interior_mask, psnr_from_mse

    truth, _ = read_truth(sim)
    c = load_cube(cube_path)
    cube, valid = c.cube.numpy().astype(np.float64), c.valid.numpy()
    pidx = truth["colorchecker_patch_index"]
    ep = erode_px(truth, 0.3)
    m = valid & np.logical_or.reduce([interior_mask(pidx == k, ep) for k in range(24)])
    t = np.asarray(truth["scene_colorchecker"], np.float64)
    return psnr_from_mse(float(((cube[:, m] - t[:, m]) ** 2).mean())), float(cube[:, m].mean())


def test_plain_tiffs_with_a_pedestal_and_no_dark_frame_are_refused(lab, tmp_path, capsys):
    out = tmp_path / "cal" / "calib.npz"
    # the response fit at its cheapest: the refusal is the pedestal check's, on the frames read
    rc = main(["calibrate", "--captures", str(lab["nodark"]), "--out", str(out),
               "--no-progress", "--set", "cfa_pattern=RGGB", "--set", "response.refine_steps=0",
               "--set", "response.max_pixels=2000"])  # fmt: skip
    err = capsys.readouterr().err
    assert rc == 1 and not out.exists()
    assert "the sensor outside the views reads 51" in err and "DN after black subtraction" in err
    assert "black pedestal of ~51" in err and "black_level" in err and "dark frame" in err
    assert err.count("\n") == 1


@pytest.fixture(scope="module")
def bundle(lab, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("cal") / "calib.npz"
    assert main(["calibrate", "--captures", str(lab["withdark"]), "--out", str(out),
                 "--no-progress", "--set", "cfa_pattern=RGGB"]) == 0  # fmt: skip
    return out


def test_bundle_records_black_level_exposure_and_camera(bundle):
    b = CalibrationBundle.load(bundle)
    s = b.settings
    assert b.schema_version == 2
    assert s["black_level_rgb"] == pytest.approx([512.0] * 3, abs=0.5)
    assert "dark frame" in s["black_level_source"] and "dark_00.tif" in s["black_level_source"]
    assert s["files_black_level_source"] == "default" and s["dark_level_rgb"] is not None
    assert s["white_exposure_s"] == 0.02 and s["white_exposure_unit"] == "s"
    assert s["white_exposure_source"] == "file"
    assert b.camera.name == "Canon EOS 5D Mark II" and b.camera.cfa_pattern == "RGGB"
    assert b.camera.sensor_size == (384, 400) and b.camera.black_level is None
    assert s["pedestal"]["ok"] and max(map(abs, s["pedestal"]["pedestal_dn"])) < 5
    rep = json.loads(bundle.with_name("calib.report.json").read_text())
    assert rep["pedestal"]["ok"] and rep["camera"] == "Canon EOS 5D Mark II"


def _reconstruct(bundle: Path, out: Path, *inputs: Path, sets: tuple[str, ...] = ()) -> int:
    argv = ["reconstruct", "--bundle", str(bundle), "--out", str(out), "--no-progress",
            "--set", "formats=[npz]", "--set", "preview=false"]  # fmt: skip
    for s in sets:
        argv += ["--set", s]
    return main(argv + [str(p) for p in inputs])


def test_plain_scene_gets_the_bundles_black_level_and_says_so(lab, bundle, tmp_path, capsys):
    sc = lab["scenes"]
    assert _reconstruct(bundle, tmp_path / "a", sc / "full.tif") == 0
    said = capsys.readouterr()
    assert "full.tif: black level 512 DN from the calibration bundle (the file carries none)" \
        in said.out and "WARNING" not in said.err
    assert _reconstruct(bundle, tmp_path / "b", sc / "full.tif",
                        sets=("black_level=512",)) == 0  # fmt: skip
    capsys.readouterr()
    got, mean = _psnr(tmp_path / "a" / "full.npz", lab["sim"])
    right, _ = _psnr(tmp_path / "b" / "full.npz", lab["sim"])
    assert got > 28 and abs(got - right) < 0.05, (got, right)
    st = load_cube(tmp_path / "a" / "full.npz").metadata["stats"]
    assert st["black_level_source"] == "bundle" and st["radiometric_scale"] == "reflectance"
    assert max(map(abs, st["pedestal_dn"])) < 5
    # an explicit black level 0 wins over the bundle's: the pedestal is left in and named
    assert _reconstruct(bundle, tmp_path / "c", sc / "full.tif", sets=("black_level=0",)) == 0
    err = capsys.readouterr().err
    assert "WARNING" in err and "the sensor outside the views reads 51" in err
    assert "black pedestal of ~51" in err and "source: config" in err


def test_half_exposure_scene_is_scaled_and_says_so(lab, bundle, tmp_path, capsys):
    sc = lab["scenes"]
    assert _reconstruct(bundle, tmp_path / "o", sc / "full.tif", sc / "half.tif") == 0
    said = capsys.readouterr()
    assert "half.tif: exposure 1/2 of the white's: scaled x2" in said.out
    assert "WARNING" not in said.err
    full, m_full = _psnr(tmp_path / "o" / "full.npz", lab["sim"])
    half, m_half = _psnr(tmp_path / "o" / "half.npz", lab["sim"])
    assert m_half == pytest.approx(m_full, rel=0.01) and half > full - 1.5
    meta = load_cube(tmp_path / "o" / "half.npz").metadata
    assert meta["radiometric_scale"] == "reflectance"
    assert meta["stats"]["exposure_scale"] == pytest.approx(2.0)
    assert meta["stats"]["exposure_note"] == "exposure 1/2 of the white's: scaled x2"


def test_unknown_exposure_is_relative_with_a_warning(lab, bundle, tmp_path, capsys):
    sc = lab["scenes"]
    assert _reconstruct(bundle, tmp_path / "u", sc / "plain.tif") == 0
    err = capsys.readouterr().err
    assert "WARNING" in err and "exposure unknown" in err and "relative" in err
    meta = load_cube(tmp_path / "u" / "plain.npz").metadata
    assert meta["radiometric_scale"] == "relative" and meta["stats"]["exposure_scale"] == 1.0
    # --set exposure_s for files that carry none
    assert _reconstruct(bundle, tmp_path / "k", sc / "plain.tif",
                        sets=("exposure_s=0.01",)) == 0  # fmt: skip
    said = capsys.readouterr()
    assert "WARNING" not in said.err and "exposure 1/2 of the white's: scaled x2" in said.out
    st = load_cube(tmp_path / "k" / "plain.npz").metadata["stats"]
    assert st["capture_exposure_source"] == "config" and st["exposure_scale"] == 2.0


def test_simulated_camera_is_recorded_and_another_cameras_scene_warns(lab, bundle, tmp_path,
                                                                       capsys):
    """The simulator names its camera in every capture (``camera_model``); a ColorChecker
    rendered through another camera's sensitivities (same geometry), reconstructed with this
    camera's bundle, is warned about, naming both cameras."""
    sim = lab["sim"]
    meta = json.loads(tifffile.TiffFile(sim / "white" / "white_00.tif").pages[0].description)
    assert meta["camera_model"] == "Canon EOS 5D Mark II"
    other = tmp_path / "nikon"  # only its scene is used: one scan frame, one white, no grid
    assert main(["simulate", "--config", str(shipped_config("simulate")), "--out", str(other),
                 "--set", "render.figures=false", "--set", "render.progress=false",
                 "--set", "render.dtype=float32", "--set", "camera_sensitivity=Nikon 5100 (NPL)",
                 "--set", "captures.white_shots=1", "--set", "captures.scan_wavelengths_nm=[550]",
                 "--set", "captures.grid.poses=[]"]) == 0  # fmt: skip
    capsys.readouterr()
    scene = other / "scenes" / "colorchecker.tif"
    assert _reconstruct(bundle, tmp_path / "n", scene) == 0
    err = capsys.readouterr().err
    assert "WARNING" in err and "Nikon 5100 (NPL)" in err and "Canon EOS 5D Mark II" in err
    st = load_cube(tmp_path / "n" / "colorchecker.npz").metadata["stats"]
    assert st["camera"] == "Nikon 5100 (NPL)" and len(st["camera_mismatch"]) == 1
    assert st["fit_residual"] < 0.15  # the fit residual alone would not have said it


def test_another_cameras_capture_warns_naming_both(lab, bundle, tmp_path, capsys):
    assert _reconstruct(bundle, tmp_path / "n", lab["scenes"] / "nikon.tif") == 0
    err = capsys.readouterr().err
    assert "WARNING" in err and "Nikon D700" in err and "Canon EOS 5D Mark II" in err
    st = load_cube(tmp_path / "n" / "nikon.npz").metadata["stats"]
    assert st["camera"] == "Nikon D700" and len(st["camera_mismatch"]) == 1


def test_calibrate_pedestal_check_modes(tmp_path):
    """``pedestal_check``: error names the level and the fix (a pedestal, or a black level set too
    high), warn warns and notes, off says nothing; the frame closest to 0 decides (stray light
    in bright frames does not)."""
    import warnings

    from hsi_torch.calibrate.config import CalibrateConfig
    from hsi_torch.calibrate.pipeline import check_pedestal
    from hsi_torch.calibrate.reading import CaptureReader
    from hsi_torch.errors import CalibrationError

    def reader(levels: list[float], black: float = 0.0) -> CaptureReader:
        r = CaptureReader(CalibrateConfig(), (10, 10), "cpu", torch.float32,
                          outside_index=np.arange(100))
        r.black_rgb, r.black_source = [black] * 3, "default"
        r.pedestals = [(tmp_path / f"f{i}.tif", [v] * 3, [2.0] * 3, 16383.0 - black)
                       for i, v in enumerate(levels)]  # fmt: skip
        return r

    notes: list[str] = []
    ped = check_pedestal(reader([1.5, 30.0, 250.0]), "error", notes)  # stray light in 2 frames
    assert ped["ok"] and ped["pedestal_dn"] == [1.5] * 3 and notes == []
    with pytest.raises(CalibrationError, match=r"reads 512\.0 DN after black subtraction .*"
                       r"black pedestal of ~512 DN.*--set black_level=512\) or add a dark frame"):
        check_pedestal(reader([512.0, 700.0]), "error", notes)
    with pytest.raises(CalibrationError, match=r"reads -300\.0 DN.*subtracted \(812 DN\) is "
                                               r"~300 DN too high.*black_level=512"):
        check_pedestal(reader([-300.0], black=812.0), "error", notes)
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        assert not check_pedestal(reader([512.0]), "warn", notes)["ok"]
    assert len(w) == 1 and "black pedestal" in str(w[0].message) and len(notes) == 1
    assert not check_pedestal(reader([512.0]), "off", notes)["ok"] and len(notes) == 1


def test_a_capture_on_another_data_scale_is_warned_about(lab, bundle, tmp_path, capsys):
    """An 8-bit PNG export or a float TIFF normalised to 1 of a scene, with its black level and
    exposure given, reconstructed with a bundle of 16-bit files: every spectrum came out 257x
    (or 65535x) too dark, `radiometric_scale: reflectance`, exit 0 and no word (the fit
    residual and the pedestal check are blind to a scale). The bundle now records the white
    level its white shots were read with, and a capture read with another one (or none) is
    warned about, with the fix; a capture on the calibration's own scale is not."""
    import cv2

    b = CalibrationBundle.load(bundle)
    assert (b.settings["white_level_dn"], b.settings["white_level_source"]) == (65535.0,
                                                                                "default")
    cc = tifffile.imread(lab["scenes"] / "full.tif").astype(np.float64)
    png = tmp_path / "export8.png"
    assert cv2.imwrite(str(png), np.rint(cc / 257).astype(np.uint8))
    flt = tmp_path / "norm.tif"
    tifffile.imwrite(flt, (cc / 65535).astype(np.float32), photometric="minisblack",
                     metadata=None)  # fmt: skip
    sets = ("exposure_s=0.02",)
    assert _reconstruct(bundle, tmp_path / "p", png, sets=(*sets, "black_level=2")) == 0
    err = capsys.readouterr().err
    assert "export8.png: data scale: the capture was read with white level 255 DN (the integer " \
        "type's maximum" in err and "white shots with 65535 DN" in err
    assert "0.00389x what it should be" in err and "--set white_level=65535" in err
    st = load_cube(tmp_path / "p" / "export8.npz").metadata["stats"]
    assert "data scale" in st["data_scale_note"]
    assert _reconstruct(bundle, tmp_path / "f", flt,
                        sets=(*sets, f"black_level={512 / 65535}")) == 0  # fmt: skip
    err = capsys.readouterr().err
    assert "norm.tif: data scale unknown: the capture states no white level (a float file)" in err
    # the calibration's own scale: nothing to say (plain TIFFs as the calibration's)
    assert _reconstruct(bundle, tmp_path / "o", lab["scenes"] / "full.tif") == 0
    assert "WARNING" not in capsys.readouterr().err
    # a file stating its own white level (the simulator's 16383) where the bundle only took the
    # integer type's maximum: the bundle's was the guess, not the capture's
    assert _reconstruct(bundle, tmp_path / "s", lab["sim"] / "scenes" / "colorchecker.tif",
                        sets=sets) == 0  # fmt: skip
    assert "data scale" not in capsys.readouterr().err


def test_data_scale_note_rules():
    from hsi_torch.recon.checks import BundleRadiometry, data_scale_note

    rad = BundleRadiometry(white_level_dn=16383.0, white_level_source="file")
    note = data_scale_note({"white_level": 65535.0, "white_level_source": "default"}, rad)
    assert "4x what it should be" in note and "--set white_level=16383" in note
    assert data_scale_note({"white_level": 16383.0, "white_level_source": "config"}, rad) is None
    note = data_scale_note({"white_level": 255.0, "white_level_source": "config"}, rad)
    assert "the white_level setting" in note and "convert the file" in note
    assert "no white level" in data_scale_note({"white_level": None}, rad)
    # the camera check already named both white levels: said once
    assert data_scale_note({"white_level": 4095.0, "white_level_source": "file"}, rad,
                           ["the capture's white level is 4095 DN, the bundle's 16383 DN"]) is None
    # a bundle that does not record it (made before): nothing to compare
    assert data_scale_note({"white_level": 255.0}, BundleRadiometry()) is None


def test_pedestal_limit_is_the_calibrations_when_the_captures_white_level_is_a_guess():
    """A plain 16-bit TIFF of 14-bit counts (no white level stated: 65535 taken) with 64 DN of
    pedestal left over: the limit was 0.25 % of 65535 − 512 = 163 DN and the pedestal passed
    in silence (the ColorChecker 54 % too bright). With the calibration's white level known the
    limit is its span's, 40 DN, and the pedestal is named."""
    from hsi_torch.io.captures import LinearCapture
    from hsi_torch.recon.checks import BundleRadiometry, measure_capture

    g = torch.Generator().manual_seed(0)
    img = 64.0 + torch.randn(3, 30, 30, generator=g, dtype=torch.float64)
    rad = BundleRadiometry(white_level_dn=16383.0, white_level_source="manifest",
                           outside_index=np.arange(0, 900, 7))  # fmt: skip

    def stats(white_level: float, source: str) -> dict:
        meta = {"kind": "rgb", "black_level": 512.0, "black_level_source": "config",
                "white_level": white_level, "white_level_source": source}  # fmt: skip
        cap = LinearCapture(img.clone(), torch.zeros_like(img, dtype=torch.bool), meta, None)
        return measure_capture(cap, rad, sensor_size=(30, 30))

    st = stats(65535.0, "default")
    assert st["pedestal_limit_dn"][0] == pytest.approx(0.0025 * (16383 - 512), abs=0.01)
    (f,) = [f for f in frame_findings(st) if f.code == "capture.pedestal"]
    assert "black pedestal of ~64 DN" in f.fix and f.severity == "warning"
    assert f.measured == pytest.approx(64, abs=0.5) and f.limit == st["pedestal_limit_dn"][0]
    # a white level the file states is the file's own: its span
    st = stats(65535.0, "file")
    assert st["pedestal_limit_dn"][0] == pytest.approx(0.0025 * (65535 - 512), abs=0.01)


def test_an_rgb_capture_with_a_bundle_of_bayer_mosaics_is_warned_about(lab, bundle, tmp_path,
                                                                         capsys):  # fmt: skip
    """A white-balanced RGB TIFF (R x2, B x1.6: what a camera or raw converter writes) of the
    ColorChecker, exposure and levels given, reconstructed with a bundle calibrated from Bayer
    mosaics: fit residual 0.10 (< 0.15), cube 1.8x off, exit 0 and no word before the fix. Now
    it is warned about; the Bayer file of the same scene is not."""
    full = lab["scenes"] / "full.tif"
    cap = read_any(full, cfa_pattern="RGGB", black_level=512, dtype=torch.float64)
    rgb = (cap.image.numpy() * np.array([2.0, 1.0, 1.6])[:, None, None]).clip(0, 65535)
    p = tmp_path / "developed.tif"
    tifffile.imwrite(p, np.rint(rgb).astype(np.uint16), photometric="rgb", planarconfig="separate",
                     metadata=None, description=json.dumps({"exposure_s": 0.02, "black_level": 0,
                                                            "white_level": 65535}))  # fmt: skip
    assert _reconstruct(bundle, tmp_path / "o", p, full) == 0
    err = capsys.readouterr().err
    assert "developed.tif: the capture is an RGB image but the bundle was calibrated from RGGB " \
        "Bayer mosaics" in err and "raw mosaic" in err
    assert err.count("WARNING") == 1  # the Bayer file of the same scene: nothing to say
    st = load_cube(tmp_path / "o" / "developed.npz").metadata["stats"]
    assert "RGB image" in st["mosaic_note"] and st["fit_residual"] < 0.15


def test_pedestal_warning_of_a_dng_names_the_level_it_subtracted(lab, bundle, tmp_path, capsys):
    """A DNG whose BlackLevel tag (512, four values of the Bayer cell) leaves 256 DN of pedestal
    in: the warning says 512 DN were subtracted and suggests 768. Before the fix it said
    "black level subtracted 0 DN" and "--set black_level=257", which a user following it would
    have made worse (the cube 3 dB instead of 31)."""
    from synthetic_data import write_dng

    cc = tifffile.imread(lab["sim"] / "scenes" / "colorchecker.tif").astype(np.float64)
    f = write_dng(tmp_path / "ped.dng", cc + 256, black_level=512, white_level=16383,
                  exposure_s=0.02)  # fmt: skip
    assert _reconstruct(bundle, tmp_path / "o", f) == 0
    err = capsys.readouterr().err
    assert "WARNING" in err and "reads 25" in err and "black level subtracted 512 DN" in err
    assert re.search(r"--set black_level=7[67]\d\)", err), err
