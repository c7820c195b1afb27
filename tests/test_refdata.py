"""Tests of hsi_torch.refdata against colour-science tables and the real data files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from hsi_torch import refdata
from hsi_torch.resources import real_data_dir
from hsi_torch.spectral import DEFAULT_GRID, SpectralGrid

colour = pytest.importorskip("colour")

CAM_DIR = real_data_dir("camera_sensitivities") or Path("<real-data>/camera_sensitivities")

TOL = {torch.float32: dict(rtol=1e-5, atol=1e-6), torch.float64: dict(rtol=1e-10, atol=1e-12)}


def test_d65_and_a_match_colour_science(device, dtype):
    wl = torch.tensor([400.0, 452.5, 560.0, 600.0, 655.0], device=device, dtype=dtype)
    for name in ("D65", "A"):
        sd = colour.SDS_ILLUMINANTS[name]
        expected = np.interp(wl.cpu().double().numpy(), sd.wavelengths, sd.values)
        expected = expected / np.interp(560.0, sd.wavelengths, sd.values)
        got = refdata.illuminant(name, wl)
        assert got.device.type == device.type and got.dtype == dtype
        torch.testing.assert_close(got, torch.tensor(expected, device=device, dtype=dtype),
                                   **TOL[dtype])
    # D65 tabulated value at 460 nm is 117.812 (CIE), i.e. 1.17812 after normalisation
    assert abs(float(refdata.illuminant("D65", [460.0])) - 1.17812) < 1e-6


def test_illuminant_normalise_modes_and_csv(tmp_path):
    p = tmp_path / "lamp.csv"
    p.write_text("wavelength_nm,value\n500,2\n550,4\n600,8\n")
    got = refdata.illuminant(p, [500.0, 525.0, 575.0, 600.0], normalise="max")
    torch.testing.assert_close(got, torch.tensor([0.25, 0.375, 0.75, 1.0]))
    got = refdata.illuminant(str(p), [560.0, 600.0])  # default: 1 at 560 nm (= 4.8)
    torch.testing.assert_close(got, torch.tensor([1.0, 8.0 / 4.8]))
    raw = refdata.illuminant(p, SpectralGrid((550.0,)), normalise=None)
    assert float(raw) == 4.0


def test_errors_name_the_culprit(tmp_path):
    with pytest.raises(ValueError, match="unknown illuminant 'D99'"):
        refdata.illuminant("D99", DEFAULT_GRID)
    with pytest.raises(ValueError, match="outside the tabulated range"):
        refdata.illuminant("A", [250.0, 500.0])
    assert float(refdata.illuminant("A", [250.0], extrapolate="zero")) == 0.0
    with pytest.raises(FileNotFoundError, match="nope.csv"):
        refdata.illuminant(tmp_path / "nope.csv", DEFAULT_GRID)
    bad = tmp_path / "bad.csv"
    bad.write_text("wl,v\n500,1\n500,2\n")
    with pytest.raises(ValueError, match="duplicate wavelengths"):
        refdata.illuminant(bad, [500.0])
    with pytest.raises(ValueError, match="unknown camera"):
        refdata.camera_sensitivities("Hasselblad X", DEFAULT_GRID)
    with pytest.raises(ValueError, match="unknown ColorChecker"):
        refdata.colorchecker_reflectances(DEFAULT_GRID, "Nope")
    with pytest.raises(ValueError, match="1-D"):
        refdata.cie_1931_cmfs(torch.ones(2, 2))
    j = tmp_path / "cam.json"
    j.write_text(json.dumps({"spectral_data": {"data": {}}}))
    with pytest.raises(ValueError, match="spectral_data.data.main"):
        refdata.camera_sensitivities(j, DEFAULT_GRID)


def test_colour_science_cameras(device):
    assert refdata.DEFAULT_CAMERA in refdata.list_cameras()
    assert {"Nikon 5100 (NPL)", "Sigma SDMerill (NPL)"} <= set(refdata.list_cameras())
    wl = torch.tensor([450.0, 530.0, 600.0], device=device, dtype=torch.float64)
    msds = colour.MSDS_CAMERA_SENSITIVITIES["Nikon 5100 (NPL)"]
    expected = np.stack([np.interp(wl.cpu().numpy(), msds.wavelengths, msds.values[:, c])
                         for c in range(3)])
    got = refdata.camera_sensitivities("Nikon 5100 (NPL)", wl, normalise=None)
    torch.testing.assert_close(got.cpu(), torch.tensor(expected))


def test_default_camera_is_the_rawtoaces_canon_csv():
    from colour.characterisation.aces_it import ROOT_RESOURCES_RAWTOACES

    table = np.genfromtxt(Path(ROOT_RESOURCES_RAWTOACES) /
                          "CANON_EOS_5DMark_II_RGB_Sensitivities.csv", delimiter=",", names=True)
    wl = table["wavelength"]
    got = refdata.camera_sensitivities(wavelengths=wl, dtype=torch.float64)  # normalise='max'
    expected = np.stack([table["R"], table["G"], table["B"]]) / max(
        table[c].max() for c in "RGB")
    torch.testing.assert_close(got, torch.tensor(expected))
    # the ratio between channels is kept with 'max'; 'channel' makes every peak 1
    assert abs(float(got[0].max()) - 0.5136) < 1e-9 and float(got[1].max()) == 1.0
    ch = refdata.camera_sensitivities(wavelengths=wl, normalise="channel")
    torch.testing.assert_close(ch.amax(dim=1), torch.ones(3))


def test_camera_csv_loader(tmp_path):
    p = tmp_path / "cam.csv"
    p.write_text("# my camera\nwavelength,R,G,B\n"
                 "400,0.1,0.2,0.4\n500,0.2,1.0,0.3\n600,0.8,0.3,0.0\n")
    got = refdata.camera_sensitivities(p, [450.0, 600.0], normalise=None, dtype=torch.float64)
    torch.testing.assert_close(got, torch.tensor([[0.15, 0.8], [0.6, 0.3], [0.35, 0.0]],
                                                 dtype=torch.float64))


@pytest.mark.real_data
@pytest.mark.skipif(not CAM_DIR.is_dir(), reason=f"real data folder {CAM_DIR} is absent")
def test_json_camera_loader_on_real_files():
    files = sorted(CAM_DIR.glob("*.json"))
    assert len(files) >= 5
    for f in files:
        main = json.loads(f.read_text())["spectral_data"]["data"]["main"]
        wl = np.array(sorted(float(k) for k in main))
        direct = np.array([main[k] for k in sorted(main, key=float)]).T  # (3, S)
        got = refdata.camera_sensitivities(f, wl, normalise=None, dtype=torch.float64)
        torch.testing.assert_close(got, torch.tensor(direct), rtol=0, atol=1e-12)
        # interpolation half-way between two samples
        mid = refdata.camera_sensitivities(f, [552.5], normalise=None, dtype=torch.float64)
        i = int(np.searchsorted(wl, 550.0))
        np.testing.assert_allclose(mid[:, 0].numpy(), 0.5 * (direct[:, i] + direct[:, i + 1]))


def test_colorchecker_reflectances(device, dtype):
    wl = torch.tensor(DEFAULT_GRID.wavelengths_nm, device=device, dtype=dtype)
    refl, names = refdata.colorchecker_reflectances(wl)
    assert refl.shape == (24, 25) and len(names) == 24
    assert names[0] == "dark skin" and names[14] == "red" and names[18].startswith("white")
    sds = colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"]
    assert abs(float(refl[18, 12]) - sds["white 9.5 (.05 D)"][550]) < 1e-6  # 550 nm = index 12
    assert abs(float(refl[14, 20]) - sds["red"][630]) < 1e-6
    assert float(refl[14, 20]) > 0.5 and float(refl[14, 2]) < 0.1  # red: high at 630, low at 450


def test_reflectance_sets(tmp_path):
    refl, names = refdata.reflectance_set("190 patches", DEFAULT_GRID, dtype=torch.float64)
    assert refl.shape == (190, 25) and names[0] == "patch1" and names[-1] == "patch190"
    from colour.characterisation.aces_it import ROOT_RESOURCES_RAWTOACES

    table = np.genfromtxt(Path(ROOT_RESOURCES_RAWTOACES) / "190_Patches.csv", delimiter=",",
                          names=True)
    row = table[table["wavelength"] == 500.0][0]
    assert abs(float(refl[6, 7]) - row["patch7"]) < 1e-12  # 500 nm = index 7
    assert float(refl.min()) >= 0.0
    p = tmp_path / "refl.csv"
    p.write_text("wl,a,b\n400,0.1,0.5\n700,0.7,0.5\n")
    r, n = refdata.reflectance_set(p, [550.0])
    assert n == ["a", "b"]
    torch.testing.assert_close(r[:, 0], torch.tensor([0.4, 0.5]))


def test_cie_cmfs():
    cmfs = refdata.cie_1931_cmfs([555.0, 600.0, 900.0], dtype=torch.float64)
    ref = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    torch.testing.assert_close(cmfs[:, 0], torch.tensor(ref[555.0], dtype=torch.float64))
    assert abs(float(cmfs[1, 0]) - 1.0) < 1e-3  # ȳ(555 nm) ≈ 1
    assert abs(float(cmfs[0, 1]) - 1.0622) < 1e-3  # x̄(600 nm) = 1.0622
    assert torch.all(cmfs[:, 2] == 0)  # zero outside the table


def test_filter_transmittance_csv(tmp_path):
    p = tmp_path / "gel.csv"
    p.write_text("nm,T%\n400,10\n500,50\n600,90\n")
    got = refdata.filter_transmittance(p, [450.0, 600.0])
    torch.testing.assert_close(got, torch.tensor([0.3, 0.9]))


def test_lee_filter_shipped_csv():
    """L068 comes from the CSV shipped in the package (no lighting_filters needed): values at the
    tabulated wavelengths, linear in between, the documented range."""
    from hsi_torch.resources import shipped_data

    table = np.loadtxt(shipped_data("lee_068_sky_blue.csv"), delimiter=",", comments="#",
                       skiprows=6)
    assert table.shape == (60, 2) and table[0, 0] == 405 and table[-1, 0] == 700
    assert "L068" in refdata.list_filters("Lee")
    got = refdata.filter_transmittance("L068", [440.0, 562.5, 700.0], dtype=torch.float64)
    row = {w: t for w, t in table}
    expected = torch.tensor([row[440.0], 0.5 * (row[560.0] + row[565.0]), row[700.0]],
                            dtype=torch.float64)
    torch.testing.assert_close(got, expected)
    assert float(got[0]) > 0.7 > 0.1 > float(got[1])  # Sky Blue: passes blue, blocks yellow
    with pytest.raises(ValueError, match="unknown filter"):
        refdata.filter_transmittance("L9999", [500.0])
    with pytest.raises(ValueError, match="outside the tabulated range"):
        refdata.filter_transmittance("L068", [400.0])


def test_shipped_lee_filter_matches_lighting_filters():
    """The shipped table is the optional package's L068 entry, value for value."""
    pytest.importorskip("lighting_filters")
    import importlib.metadata as md

    path = next(f for f in md.files("lighting_filters") if f.name == "filters.json").locate()
    sd = json.loads(Path(path).read_text())["filters"]["L068"]["sd"]
    wl = sorted(float(k) for k in sd)
    got = refdata.filter_transmittance("L068", wl, dtype=torch.float64)
    expected = torch.tensor([float(sd[f"{w:g}"]) for w in wl], dtype=torch.float64)
    torch.testing.assert_close(got, expected, rtol=0, atol=0)




def test_lee_filter_without_lighting_filters(monkeypatch):
    """Without the optional package: L068 still works, other codes say what to install."""

    def missing():
        raise ModuleNotFoundError("lighting_filters is not installed")

    monkeypatch.setattr(refdata, "_lighting_filters_table", missing)
    assert refdata.list_filters() == ["L068"]
    assert float(refdata.filter_transmittance("L068", [440.0])[0]) > 0.7
    with pytest.raises(ValueError, match="pip install lighting_filters"):
        refdata.filter_transmittance("R80", [500.0])


def test_package_never_imports_scipy_or_lighting_filters():
    """scipy is a test/benchmark dependency only (the independent NNLS reference), and the gel
    filter ships as a CSV: no module of the package imports either (colour-science, a runtime
    dependency, may still pull scipy in for itself)."""
    import ast

    import hsi_torch

    root = Path(hsi_torch.__file__).parent
    offenders = []
    for path in sorted(root.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                     [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            offenders += [f"{path.relative_to(root)}: {n}" for n in names
                          if n.split(".")[0] in ("scipy", "lighting_filters")]
    assert offenders == []
