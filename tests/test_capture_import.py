"""``hsi-torch captures import`` / ``check``: a lab's own folder of photos (DNG with black level and
ExposureTime, 16-bit PNG, its own names, no simulator metadata) → a capture set that calibrates
and reconstructs like the simulator's own; the sheet's and the manifest's errors; the schema."""

from __future__ import annotations

import csv
import json
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from synthetic_data import write_dng

from hsi_torch.calibrate.config import CalibrateConfig, ResponseSection
from hsi_torch.calibrate.pipeline import CalibrationReport, calibrate_capture_set
from hsi_torch.cli import main
from hsi_torch.config import load_config
from hsi_torch.errors import FileFormatError, InputError, MissingFileError
from hsi_torch.experiments.metrics import cube_scores, erode_px, interior_mask
from hsi_torch.io import read_any, read_capture
from hsi_torch.io.bundle import CalibrationBundle
from hsi_torch.io.capture_import import (
    check_capture_set,
    import_captures,
    read_sheet,
    rows_from_patterns,
)
from hsi_torch.io.capture_manifest import check_manifest, manifest_keys, manifest_schema
from hsi_torch.io.capture_set import read_capture_set, read_nominal_layout, read_truth
from hsi_torch.recon.pipeline import Reconstructor
from hsi_torch.resources import shipped_config

BLACK, WHITE = 512, 16383  # the simulated sensor: 14 bit, black level 512
T_WHITE = 0.02  # the lab's white shots: 20 ms; the scene at half of it
MINIMAL_MANIFEST = {  # the docs' example (docs/calibration.md, "The manifest")
    "schema_version": 1,
    "cfa_pattern": "RGGB",
    "captures": [
        {"file": "mono/m01.png", "type": "scan", "wavelength_nm": 430, "black_level": 512},
        {"file": "flat/flat1.tif", "type": "white", "black_level": 512, "exposure_s": 0.02},
        {"file": "dots/d1.png", "type": "grid", "black_level": 512},
        {"file": "shots/chart.dng", "type": "scene", "name": "chart"},
    ],
}


@pytest.fixture(scope="module")
def sim(small_sim: Path) -> Path:
    """The default small set with its ColorChecker scene (float32 render, no figures): the
    session's shared, read-only ``small_sim``."""
    return small_sim


def _calibrate(capset: Path, **cfg) -> tuple[CalibrationBundle, CalibrationReport]:
    """``calibrate_capture_set(capset)`` with the response fit at its cheapest (no joint
    refinement, a 2 000-pixel sub-grid; ``cfg``: other settings): for the tests of how the
    captures are read (black levels, pedestals, dark and repeated frames), which the response
    does not change; about half the default calibration's time."""
    cheap = ResponseSection(refine_steps=0, max_pixels=2000)
    return calibrate_capture_set(capset, CalibrateConfig(response=cheap, **cfg), progress=False)


def _mosaic(path: Path) -> np.ndarray:
    img, meta = read_capture(path)
    assert meta["black_level"] == BLACK and meta["white_level"] == WHITE
    return img[0].numpy().astype(np.float64)


def _lab_folder(sim: Path, lab: Path) -> Path:
    """The simulated set as a lab would have it: DNGs (black 512, ExposureTime, Make/Model) for
    the scan, white, dark and scene, 16-bit PNGs (no metadata at all) for the grid shots, its own
    folder and file names, a repeated scan frame at 550 nm and an extra one at 700 nm, the scene
    shot at half the white's exposure; the sheet says the rest. Returns the sheet."""
    man = json.loads((sim / "manifest.json").read_text())
    rows = [["file", "role", "wavelength_nm", "exposure_s", "black_level", "cfa_pattern", "name"]]
    cam = {"make": "Lab Optics", "model": "KaleidoCam 1"}
    k = 0
    for e in man["captures"]:
        m = _mosaic(sim / e["file"])
        if e["type"] == "scan":
            lam = e["wavelength_nm"]
            k += 1
            f = f"Monochromator/frame_{k:03d}.dng"
            write_dng(lab / f, m, black_level=BLACK, white_level=WHITE, exposure_s=0.5, **cam)
            rows.append([f, "scan", f"{lam:g}", "", "", "", ""])
            if lam == 550:  # the lab took it twice: the same frame again (averaged)
                write_dng(lab / "Monochromator/frame_550_again.dng", m, black_level=BLACK,
                          white_level=WHITE, exposure_s=0.5, **cam)  # fmt: skip
                rows.append(["Monochromator/frame_550_again.dng", "scan", "550", "", "", "", ""])
            if lam == 670:  # and went on past the grid
                write_dng(lab / "Monochromator/frame_700.dng", np.minimum(m + 1, WHITE),
                          black_level=BLACK,
                          white_level=WHITE, exposure_s=0.5, **cam)  # fmt: skip
                rows.append(["Monochromator/frame_700.dng", "scan", "700", "", "", "", ""])
        elif e["type"] in ("white", "dark"):
            f = f"{'Flat field' if e['type'] == 'white' else 'Dark'}/{Path(e['file']).stem}.dng"
            write_dng(lab / f, m, black_level=BLACK, white_level=WHITE, exposure_s=T_WHITE, **cam)
            rows.append([f, e["type"], "", "", "", "", ""])
        elif e["type"] == "grid":
            f = f"Dots/pose {Path(e['file']).stem[-1]}.png"
            (lab / f).parent.mkdir(parents=True, exist_ok=True)
            assert cv2.imwrite(str(lab / f), m.astype(np.uint16))
            rows.append([f, "grid", "", "", str(BLACK), "RGGB", ""])
        elif e["type"] == "scene":
            half = np.rint((m - BLACK) / 2 + BLACK).clip(0, WHITE)  # half the white's exposure
            f = f"Shots/IMG_{42 + sum(r[1] == 'scene' for r in rows):04d}.dng"  # one per scene
            write_dng(lab / f, half, black_level=BLACK, white_level=WHITE,
                      exposure_s=T_WHITE / 2, **cam)  # fmt: skip
            rows.append([f, "scene", "", "", "", "", e["name"]])
    shutil.copy(sim / "nominal_layout.json", lab / "nominal_layout.json")
    shutil.copy(sim / "brf_free_mask.png", lab / "brf_free_mask.png")
    sheet = lab / "captures.csv"
    with open(sheet, "w", newline="") as f:
        csv.writer(f).writerows(rows)
    return sheet


def _import_sheet(sheet: Path, rows: list[list[str]], out: Path) -> Path:
    """Write ``rows`` as the capture sheet ``sheet`` and import it into ``out`` (exit 0)."""
    with open(sheet, "w", newline="") as f:
        csv.writer(f).writerows(rows)
    assert main(["captures", "import", "--sheet", str(sheet), "--out", str(out)]) == 0
    return out


def _score(cube: np.ndarray, valid: np.ndarray, truth: dict) -> float:
    """Per-pixel PSNR over the ColorChecker's patch interiors (0.3 mm inside, as the demo)."""
    pidx = truth["colorchecker_patch_index"]
    e = erode_px(truth, 0.3)
    inner = valid & (pidx >= 0) & np.logical_or.reduce(
        [interior_mask(pidx == k, e) for k in range(24)])  # fmt: skip
    return cube_scores(cube, np.asarray(truth["scene_colorchecker"], np.float64),
                       inner)["psnr_db"]  # fmt: skip


def test_lab_folder_imported_calibrates_and_reconstructs_like_the_simulators(
    sim: Path, small_sim_calib: Path, tmp_path: Path, capsys
):
    lab = tmp_path / "lab"
    sheet = _lab_folder(sim, lab)
    capset = tmp_path / "capset"
    assert main(["captures", "import", "--sheet", str(sheet), "--out", str(capset)]) == 0
    out = capsys.readouterr().out
    assert "25 of 25 bands" in out
    assert "550 nm: 2 frames, averaged by calibration" in out
    assert "frame_700.dng (700 nm)" in out
    man = json.loads((capset / "manifest.json").read_text())
    assert man["settings_source"] == "sheet" and man["files_root"] == "../lab"
    assert sorted(p.name for p in capset.rglob("*")) == [  # the captures are referenced
        "brf_free_mask.png", "manifest.json", "nominal_layout.json"]
    assert man["sensor_size"] == [384, 400]  # the layout beside the sheet was taken
    check_manifest(man, capset / "manifest.json")

    # what calibration will use, file by file
    assert main(["captures", "check", str(capset)]) == 0
    out = capsys.readouterr().out
    assert "frame_550_again.dng" in out and "2 scan frames at 550 nm" in out
    assert "512 (sheet)" in out and "512 (file)" in out and "0.01 s (file)" in out
    assert "Lab Optics KaleidoCam 1" in out

    # the shipped calibrate.yaml, as `hsi-torch calibrate` of `sim` (the session's small_sim_calib)
    cfg = load_config(shipped_config("calibrate"), CalibrateConfig)
    bundle, report = calibrate_capture_set(capset, cfg, progress=False)
    native = CalibrationBundle.load(small_sim_calib / "calib.npz")
    assert report.counts["scan"] == 26  # 25 bands, one of them two frames
    assert any("550 nm: 2 frames" in n for n in report.notes)
    assert any("frame_700.dng (700 nm)" in n for n in report.notes)
    assert bundle.settings["white_exposure_s"] == pytest.approx(T_WHITE)
    assert bundle.settings["cfa_pattern"] == "RGGB"
    # the same images: the same calibration up to the PNG/DNG round trip (exact) and the averaged
    # duplicate (identical frames)
    np.testing.assert_allclose(bundle.B, native.B, atol=1e-5)
    np.testing.assert_array_equal(bundle.view_homographies, native.view_homographies)

    truth, _ = read_truth(sim)
    rec_lab = Reconstructor(bundle, beta=1e4)
    res = rec_lab.reconstruct_file(lab / "Shots/IMG_0042.dng")
    assert res.stats["exposure_scale"] == pytest.approx(2.0)  # t_white / t_scene from EXIF
    assert res.stats["metadata"]["exposure_source"] == "file"
    res_native = Reconstructor(native, beta=1e4).reconstruct_file(sim / "scenes/colorchecker.tif")
    p_lab = _score(res.cube.numpy(), res.valid.numpy(), truth)
    p_nat = _score(res_native.cube.numpy(), res_native.valid.numpy(), truth)
    print(f"ColorChecker interiors per pixel: lab set {p_lab:.2f} dB, native {p_nat:.2f} dB")
    assert p_nat > 25
    assert abs(p_lab - p_nat) < 0.5


def test_sheet_errors_name_the_line_and_column(tmp_path: Path):
    (tmp_path / "a.png").write_bytes(b"x")
    sheet = tmp_path / "s.csv"

    def bad(text: str, err: type, match: str) -> None:
        sheet.write_text(text)
        with pytest.raises(err, match=match):
            read_sheet(sheet)

    bad("", FileFormatError, "empty; the first line is the header")
    bad("file,role,wavelenght_nm\na.png,scan,430\n", FileFormatError,
        "unknown column 'wavelenght_nm' \\(did you mean 'wavelength_nm'\\?\\)")
    bad("file,wavelength_nm\na.png,430\n", FileFormatError, "no 'role' column")
    bad("file,role\na.png,flat\n", FileFormatError, r"s.csv:2: role 'flat' is not one of")
    bad("file,role\nb.png,white\n", MissingFileError, r"s.csv:2: file .*b.png does not exist")
    bad("file,role,exposure_s\n# comment,,\na.png,white,1/50\n", FileFormatError,
        r"s.csv:3: column 'exposure_s': '1/50' is not a number")
    bad("file,role,black_level\na.png,white,512 512\n", FileFormatError,
        r"s.csv:2: column 'black_level' must be one number >= 0, or 3")
    bad("file,role,cfa_pattern\na.png,grid,RGGG\n", FileFormatError, "must be RGGB, BGGR")
    bad("file,role,wavelength_nm\na.png,white,430\n", FileFormatError,
        "'wavelength_nm' is given for a white capture")
    (tmp_path / "a.jpg").write_bytes(b"x")
    bad("file,role\na.jpg,white\n", FileFormatError, "unsupported file type '.jpg'")
    # empty cells are "not given"; lists of black levels; comments skipped
    sheet.write_text("file,role,black_level,exposure_s,cfa_pattern,name\n"
                     "a.png,grid,512;510;509;511,,rggb,\n#x.png,white,,,,\n"
                     "a.png,scene,,0.01,,chart\n")  # fmt: skip
    rows = read_sheet(sheet)
    assert [r.role for r in rows] == ["grid", "scene"]
    assert rows[0].settings == {"black_level": [512.0, 510.0, 509.0, 511.0], "cfa_pattern": "RGGB"}
    assert rows[1].settings == {"exposure_s": 0.01} and rows[1].name == "chart"


def test_patterns_and_a_plain_png_folder(tmp_path: Path, capsys):
    """Name patterns with {nm}; a folder of 16-bit PNGs in scan/ (no manifest) is found."""
    m = (np.arange(24 * 26).reshape(24, 26) % 4000 + 600).astype(np.uint16)
    for k, lam in enumerate((430, 440, 440.5, 800)):  # distinct frames (one frame is one thing)
        f = tmp_path / "lab/mono" / f"m_{lam:g}nm.png".replace(".5", "p5")
        f.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(f), m + k)
    cv2.imwrite(str(tmp_path / "lab/w.png"), m + 9)
    rows = rows_from_patterns({"scan": ["lab/mono/m_{nm}nm.png"], "white": ["lab/w.png"]},
                              base=tmp_path)  # fmt: skip
    assert sorted(r.wavelength_nm for r in rows if r.role == "scan") == [430, 440, 440.5, 800]
    rep = import_captures(rows, tmp_path / "set", grid_nm=(430, 450, 10), source="manifest")
    assert rep.repeated == {440.0: ["m_440nm.png", "m_440p5nm.png"]}
    assert rep.outside == [("m_800nm.png", 800.0)] and rep.missing == [450.0]
    assert any("no scan frame for 450 nm" in w for w in rep.warnings)
    with pytest.raises(InputError, match="matches no file"):
        rows_from_patterns({"grid": ["lab/none*.png"]}, base=tmp_path)
    with pytest.raises(InputError, match="manifest.json exists"):
        import_captures(rows, tmp_path / "set")

    plain = tmp_path / "plain"
    for lam in range(430, 680, 10):
        (plain / "scan").mkdir(parents=True, exist_ok=True)
        img = m.copy()
        img[-1, -1] = lam
        cv2.imwrite(str(plain / "scan" / f"scan_{lam}nm.png"), img)
    for k, d in enumerate(("white", "grid")):
        (plain / d).mkdir()
        cv2.imwrite(str(plain / d / "x.png"), m + 20 + k)
    cs = read_capture_set(plain)
    cs.require_calibration_captures()  # was: "no monochromator scan captures"
    assert len(cs.scan) == 25
    cap = read_any(cs.scan[0][0], cfa_pattern="RGGB", black_level=512)
    assert cap.metadata["black_level_source"] == "config" and cap.mosaic[0, 0, 0] == 600 - 512


def test_hand_written_manifest_settings_are_honoured_or_refused(sim: Path, tmp_path: Path):
    """Per-file cfa_pattern / black_level / exposure_s of a hand-written manifest reach the
    reader; a key the schema does not know is refused by name."""
    d = tmp_path / "set"
    (d / "white").mkdir(parents=True)
    m = _mosaic(sim / "white/white_00.tif")
    cv2.imwrite(str(d / "white/w.png"), m.astype(np.uint16))  # a PNG knows nothing
    write_dng(d / "white/w.dng", m, black_level=BLACK, white_level=WHITE, exposure_s=0.5)
    man = {"schema_version": 1, "black_level": 500, "captures": [
        {"file": "white/w.png", "type": "white", "cfa_pattern": "RGGB", "black_level": BLACK,
         "exposure_s": 0.02, "white_level": WHITE},
        {"file": "white/w.dng", "type": "white", "exposure_s": 0.03}]}
    (d / "manifest.json").write_text(json.dumps(man))
    shutil.copy(sim / "nominal_layout.json", d / "nominal_layout.json")
    rows, problems = check_capture_set(d)
    png, dng = rows
    assert (png["black_level"], png["black_level_source"]) == (BLACK, "manifest")
    assert (png["exposure_s"], png["exposure_source"]) == (0.02, "manifest")
    assert png["cfa_pattern"] == "RGGB" and png["white_level"] == WHITE
    # the set-level black_level applies to every capture without its own (the DNG's is
    # overridden: the manifest wins over the file), the entry's exposure over the EXIF's
    assert (dng["black_level"], dng["black_level_source"]) == (500, "manifest")
    assert (dng["exposure_s"], dng["exposure_source"]) == (0.03, "manifest")
    for bad_key, match in (({"exposure_time": 0.01}, "unknown key 'exposure_time'"),
                           ({"cfa": "RGGB"}, "unknown key 'cfa'"),
                           ({"black_level": "x"}, "'black_level' must be a number")):
        man2 = {**man, "captures": [{**man["captures"][0], **bad_key}]}
        (d / "manifest.json").write_text(json.dumps(man2))
        with pytest.raises(FileFormatError, match=match):
            read_capture_set(d)
    (d / "manifest.json").write_text(json.dumps({**man, "exposure_time_s": 1}))
    with pytest.raises(FileFormatError, match=r"manifest.json: unknown key 'exposure_time_s'"):
        read_capture_set(d)


def test_a_key_given_twice_in_a_hand_written_manifest_or_layout_is_refused(sim: Path,
                                                                           tmp_path: Path):
    """A hand-edited manifest entry with ``"black_level"`` twice (512, later 0) was read with
    the later value in silence (JSON readers keep it); the nominal layout likewise. Both are
    refused now, naming the file and the key."""
    d = tmp_path / "set"
    (d / "white").mkdir(parents=True)
    cv2.imwrite(str(d / "white/w.png"), _mosaic(sim / "white/white_00.tif").astype(np.uint16))
    shutil.copy(sim / "nominal_layout.json", d / "nominal_layout.json")
    entry = '{"file": "white/w.png", "type": "white", "cfa_pattern": "RGGB", ' \
        '"black_level": 512, "exposure_s": 0.02, "black_level": 0}'
    (d / "manifest.json").write_text('{"schema_version": 1, "captures": [' + entry + ']}')
    with pytest.raises(FileFormatError, match=r"manifest .*manifest.json: key 'black_level' is "
                                              r"given twice in one JSON object"):
        read_capture_set(d)
    entry = entry.replace(', "black_level": 0}', "}")
    (d / "manifest.json").write_text('{"schema_version": 1, "captures": [' + entry + ']}')
    assert read_capture_set(d).settings  # the same without the second key: read
    text = (d / "nominal_layout.json").read_text()
    (d / "nominal_layout.json").write_text(text.replace("{", '{"parity": [1], ', 1))
    with pytest.raises(FileFormatError, match=r"nominal_layout.json: key 'parity' is given twice"):
        read_nominal_layout(d / "nominal_layout.json")


def test_published_schema_accepts_the_manifests_we_write(sim: Path):
    jsonschema = pytest.importorskip("jsonschema")
    schema = manifest_schema()
    jsonschema.Draft202012Validator.check_schema(schema)
    v = jsonschema.Draft202012Validator(schema)
    v.validate(json.loads((sim / "manifest.json").read_text()))
    v.validate(MINIMAL_MANIFEST)
    assert not v.is_valid({**MINIMAL_MANIFEST, "exposure_time": 1})
    check_manifest(MINIMAL_MANIFEST, "example")
    keys = manifest_keys()
    assert {"cfa_pattern", "black_level", "exposure_s", "wavelength_nm"} <= set(keys["entry"])
    doc = (Path(__file__).resolve().parents[1] / "docs/calibration.md").read_text()
    for k in set(keys["set"]) | set(keys["entry"]):  # every key documented
        assert f"`{k}`" in doc, k


def test_copy_makes_a_self_contained_set(tmp_path: Path):
    """A set imported with --copy is self-contained (the files under the set's folder)."""
    m = (np.arange(30 * 32).reshape(30, 32) % 4000 + 600).astype(np.uint16)
    (tmp_path / "lab").mkdir()
    write_dng(tmp_path / "lab/a_430nm.dng", m, black_level=BLACK, white_level=WHITE,
              exposure_s=0.01)  # fmt: skip
    rows = rows_from_patterns({"scan": ["lab/a_*nm.dng"]}, base=tmp_path)
    import_captures(rows, tmp_path / "set", copy=True, grid_nm=(430, 430, 10))
    man = json.loads((tmp_path / "set/manifest.json").read_text())
    assert "files_root" not in man and man["captures"][0]["file"] == "scan/a_430nm.dng"
    assert (tmp_path / "set/scan/a_430nm.dng").is_file()
    cs = read_capture_set(tmp_path / "set")
    assert cs.scan == [(tmp_path / "set/scan/a_430nm.dng", 430.0)]
    md = cs.read(cs.scan[0][0]).metadata
    assert (md["black_level"], md["black_level_source"]) == ([BLACK] * 4, "file")


def test_read_any_metadata_contract(tmp_path: Path):
    """exposure_s / black_level / camera identity with their sources, for a machine-vision TIFF
    with EXIF tags, our TIFF with JSON metadata, a PNG, and keyword overrides."""
    import tifffile

    from hsi_torch.io import write_capture

    m = (np.arange(30 * 32).reshape(30, 32) % 4000 + 600).astype(np.uint16)
    tifffile.imwrite(tmp_path / "mv.tif", m, metadata=None, extratags=[
        (33434, "2I", 1, (1, 250)), (271, "s", 0, "Vision Co"), (272, "s", 0, "MV-1")])
    c = read_any(tmp_path / "mv.tif", cfa_pattern="GRBG")
    md = c.metadata
    assert (md["exposure_s"], md["exposure_source"]) == (0.004, "file")
    assert (md["camera_make"], md["camera_model"]) == ("Vision Co", "MV-1")
    assert (md["black_level"], md["black_level_source"]) == (0.0, "default")
    assert md["white_level"] == 65535 and md["cfa_pattern"] == "GRBG"
    c = read_any(tmp_path / "mv.tif", cfa_pattern="GRBG", black_level=64, exposure_s=0.01,
                 camera_model="X", sources={"black_level": "sheet", "exposure_s": "manifest"})
    md = c.metadata
    assert (md["black_level"], md["black_level_source"]) == (64.0, "sheet")
    assert (md["exposure_s"], md["exposure_source"]) == (0.01, "manifest")
    assert md["camera_model"] == "X" and float(c.mosaic[0, 0, 0]) == 600 - 64
    write_capture(tmp_path / "ours.tif", m, {"cfa_pattern": "RGGB", "black_level": 100,
                                            "exposure_s": 0.5, "camera_make": "Sim"})
    md = read_any(tmp_path / "ours.tif").metadata
    assert (md["black_level_source"], md["exposure_s"], md["exposure_source"]) == ("file", 0.5,
                                                                                  "file")
    assert md["camera_make"] == "Sim" and md["camera_model"] is None
    cv2.imwrite(str(tmp_path / "p.png"), np.stack([m, m // 2, m // 3], -1))  # B, G, R on disk
    md = read_any(tmp_path / "p.png").metadata
    assert md["kind"] == "rgb" and md["cfa_pattern"] is None and md["exposure_s"] is None
    assert md["exposure_source"] is None and md["camera_make"] is None
    assert float(read_any(tmp_path / "p.png").image[0, 0, 0]) == 600 // 3  # R first
    with pytest.raises(FileFormatError, match="exposure_s must be a number > 0"):
        read_any(tmp_path / "p.png", exposure_s=-1)
    with pytest.raises(ValueError, match="is not one of"):
        read_any(tmp_path / "p.png", sources={"black_level": "guess"})
    with pytest.raises(FileFormatError, match="does not match the expected sensor size"):
        read_any(tmp_path / "p.png", expected_size=(31, 32))  # from the header


def test_check_exits_1_when_calibration_would_refuse(tmp_path: Path, capsys):
    m = (np.arange(30 * 32).reshape(30, 32) % 4000 + 600).astype(np.uint16)
    for k, f in enumerate(("mono/s_430nm.png", "mono/s_700nm.png", "w/w.png")):
        (tmp_path / f).parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(tmp_path / f), m + k)
    (tmp_path / "sheet.csv").write_text("file,role,cfa_pattern\nmono/s_430nm.png,scan,RGGB\n"
                                        "mono/s_700nm.png,scan,RGGB\nw/w.png,white,RGGB\n")
    assert main(["captures", "import", "--sheet", str(tmp_path / "sheet.csv"),
                 "--out", str(tmp_path / "set")]) == 0  # fmt: skip
    cap = capsys.readouterr()
    assert "hsi-torch: warning: no scan frame for 440, 450" in cap.err
    assert "no grid captures" in cap.err and "no nominal layout" in cap.err
    assert "s_700nm.png (700 nm)" in cap.out
    assert main(["-q", "captures", "check", str(tmp_path / "set")]) == 1
    cap = capsys.readouterr()
    assert cap.out == ""  # quiet: only the errors
    assert "hsi-torch: error: no grid captures" in cap.err
    assert "error: no scan frame for 440" in cap.err
    assert main(["captures", "check", str(tmp_path / "set")]) == 1
    out = capsys.readouterr().out
    assert "note: scan frames near no band (not used): s_700nm.png (700 nm)" in out
    assert "note: 3 capture(s) with no black level given" in out


def test_repeated_scan_frames_are_averaged_at_one_exposure(tmp_path: Path):
    """Two frames of one band: the mean image (the second, at twice the exposure, scaled to the
    first's first), a sample saturated in either is saturated."""
    import torch

    from hsi_torch.calibrate.config import CalibrateConfig
    from hsi_torch.calibrate.reading import CaptureReader

    a = np.full((24, 26), 1000, np.uint16)
    b = np.full((24, 26), 2000, np.uint16)
    b[3, 4] = 65535
    cv2.imwrite(str(tmp_path / "a.png"), a)
    cv2.imwrite(str(tmp_path / "b.png"), b)
    pa, pb = tmp_path / "a.png", tmp_path / "b.png"
    settings = {pa: {"exposure_s": (0.01, "sheet"), "cfa_pattern": ("RGGB", "sheet")},
                pb: {"exposure_s": (0.02, "sheet"), "cfa_pattern": ("RGGB", "sheet")}}
    r = CaptureReader(CalibrateConfig(black_level=0.0), (24, 26), "cpu", torch.float64,
                      settings=settings)
    img, sat, meta = r.read_mean((pa, pb))
    assert meta["black_level_source"] == "config" and meta["exposure_source"] == "sheet"
    ok = ~sat.any(0)
    assert torch.allclose(img[:, ok], torch.full_like(img[:, ok], 1000.0))
    assert bool(sat[:, 3, 4].any()) and int((~ok).sum()) < 30


@pytest.mark.parametrize("pattern", ["RGGB", "GRBG", "BGGR", "GBRG"])
def test_write_dng_reads_back_through_libraw(tmp_path: Path, pattern: str):
    """The tests' DNG writer: LibRaw returns the same mosaic, black and white level and CFA
    pattern; the EXIF gives the exposure and the camera."""
    import rawpy

    m = np.random.default_rng(3).integers(BLACK, WHITE + 1, (40, 46))
    f = write_dng(tmp_path / "x.dng", m, cfa_pattern=pattern, black_level=BLACK,
                  white_level=WHITE, exposure_s=1 / 60, make="Lab", model="Cam")  # fmt: skip
    with rawpy.imread(str(f)) as r:
        np.testing.assert_array_equal(r.raw_image_visible, m)
        assert list(r.black_level_per_channel) == [BLACK] * 4 and r.white_level == WHITE
    c = read_any(f)
    md = c.metadata
    assert md["cfa_pattern"] == pattern and md["exposure_s"] == pytest.approx(1 / 60, rel=1e-6)
    assert (md["camera_make"], md["camera_model"]) == ("Lab", "Cam")
    np.testing.assert_array_equal(c.mosaic[0].numpy(), m - BLACK)


def test_import_into_a_folder_with_the_users_files_of_those_names_is_refused(sim: Path,
                                                                             tmp_path: Path,
                                                                             capsys):  # fmt: skip
    """``captures import --copy --layout L --out lab/`` where ``lab/`` holds the lab's own
    ``nominal_layout.json`` and ``white/white_00.tif`` replaced both, exit 0. Now refused before
    anything is written, naming them; the files of an interrupted import of the same shots
    (identical copies) do not stop its rerun."""
    whites = sorted((sim / "white").glob("*.tif"))
    argv = ["captures", "import", "--white", str(sim / "white" / "*.tif"), "--layout",
            str(sim / "nominal_layout.json"), "--copy", "-q"]  # fmt: skip
    lab = tmp_path / "lab"
    (lab / "white").mkdir(parents=True)
    mine = {"nominal_layout.json": b'{"mine": 1}', "white/white_00.tif": b"my own white shot"}
    for name, data in mine.items():
        (lab / name).write_bytes(data)
    assert main([*argv, "--out", str(lab)]) == 1
    err = capsys.readouterr().err
    assert "refusing to import into" in err
    assert "nominal_layout.json" in err and "white/white_00.tif" in err
    assert {p.relative_to(lab).as_posix(): p.read_bytes()
            for p in lab.rglob("*") if p.is_file()} == mine  # fmt: skip
    # an interrupted import: one shot copied, no manifest yet; the rerun completes it
    killed = tmp_path / "killed"
    (killed / "white").mkdir(parents=True)
    shutil.copy2(whites[0], killed / "white" / whites[0].name)
    assert main([*argv, "--out", str(killed)]) == 0
    assert len(read_capture_set(killed).white) == len(whites)
    assert (killed / "white" / whites[1].name).read_bytes() == whites[1].read_bytes()


def test_scan_tiffs_with_a_pedestal_beside_dngs_with_their_black_level_are_refused(
    sim: Path, tmp_path: Path
):
    """A lab's scan as plain 16-bit TIFFs (its 512 DN pedestal in the data, no black level in the
    sheet) beside DNG white and dark shots that carry theirs: the TIFFs' pedestal is checked on
    its own, naming them. Before the fix the DNGs' frames read 0 outside the views and the check
    passed: exit 0, B 71 % off, the ColorChecker 13 dB lower, no warning."""
    import rawpy
    import tifffile

    from hsi_torch.errors import CalibrationError

    lab = tmp_path / "lab"
    sheet = _lab_folder(sim, lab)
    rows = list(csv.reader(sheet.open()))
    for r in rows[1:]:
        if r[1] == "scan":
            dng = lab / r[0]
            with rawpy.imread(str(dng)) as raw:  # the stored counts, pedestal included
                m = raw.raw_image_visible.copy()
            r[0] = str(Path(r[0]).with_suffix(".tif"))
            tifffile.imwrite(lab / r[0], m.astype(np.uint16))
            dng.unlink()
            r[5] = "RGGB"
    capset = _import_sheet(sheet, rows, tmp_path / "capset")
    with pytest.raises(CalibrationError, match=r"reads 51\d\.\d DN .*the 2\d scan frames read "
                       r"with black level 0 DN \(source: default\): frame_001\.tif.*different "
                       r"black levels.*"
                       r"these captures carry a black pedestal of ~51\d DN; give their "
                       r"black_level in the sheet"):  # fmt: skip
        _calibrate(capset)
    # with their black level in the sheet, the set calibrates as the DNGs do
    bundle, report = _calibrate_with_scan_black_level(sheet, rows, tmp_path, BLACK)
    assert report.pedestal["ok"]


def test_calibration_captures_that_mix_bayer_patterns_are_refused(sim: Path, tmp_path: Path):
    """The white shots as DNGs that say GRBG (another camera's, or a crop by one pixel) beside
    RGGB scan, dark and grid files of the same make and model: refused, naming both files and
    patterns. Before the fix: exit 0, homographies 6.5 px off, the ColorChecker at 4.1 dB
    instead of 31.3 dB, no warning."""
    import rawpy

    from hsi_torch.errors import CalibrationError

    lab = tmp_path / "lab"
    sheet = _lab_folder(sim, lab)
    for r in list(csv.reader(sheet.open()))[1:]:
        if r[1] == "white":
            with rawpy.imread(str(lab / r[0])) as raw:
                m = raw.raw_image_visible.copy()
            write_dng(lab / r[0], m, cfa_pattern="GRBG", black_level=BLACK, white_level=WHITE,
                      exposure_s=T_WHITE, make="Lab Optics", model="KaleidoCam 1")  # fmt: skip
    capset = tmp_path / "capset"
    assert main(["captures", "import", "--sheet", str(sheet), "--out", str(capset)]) == 0
    with pytest.raises(CalibrationError, match=r"white_0\d\.dng: CFA pattern GRBG \(file\) but "
                       r".*\.(dng|png) has RGGB \((file|sheet)\): the calibration captures mix "
                       r"Bayer patterns"):  # fmt: skip
        calibrate_capture_set(capset, progress=False)


def test_a_sheet_wavelength_that_contradicts_the_file_name_is_refused(tmp_path: Path):
    """Scan frames named by their wavelength (``mono_550nm.png``) with a sheet one band off
    (550 for ``mono_540nm.png``, …): refused naming the line and both values. Before the fix the
    sheet won in silence: calibration exited 0, B 42 % off, the ColorChecker 5.6 dB lower."""
    for lam in (540, 550):  # two frames (distinct: one frame at two wavelengths is refused)
        cv2.imwrite(str(tmp_path / f"mono_{lam}nm.png"), np.full((24, 26), 500 + lam, np.uint16))
    sheet = tmp_path / "s.csv"
    sheet.write_text("file,role,wavelength_nm\nmono_540nm.png,scan,540\n"
                     "mono_550nm.png,scan,560\n")  # fmt: skip
    with pytest.raises(InputError, match=r"s\.csv:3: scan frame mono_550nm\.png: the sheet says "
                       r"560 nm but the file name says 550 nm"):  # fmt: skip
        import_captures(read_sheet(sheet), tmp_path / "set")
    assert not (tmp_path / "set").exists()
    # the same within the tolerance, or an empty cell (the name's), is taken
    sheet.write_text("file,role,wavelength_nm\nmono_540nm.png,scan,540.2\nmono_550nm.png,scan,\n")
    rep = import_captures(read_sheet(sheet), tmp_path / "set2")
    man = json.loads(rep.manifest.read_text())
    assert [e["wavelength_nm"] for e in man["captures"]] == [540.2, 550.0]


def test_dark_frames_of_different_exposures_are_averaged_with_a_warning(sim: Path,
                                                                         tmp_path: Path):
    """A dark frame at the white's 20 ms and one at the scan's 0.5 s (60 DN of dark current):
    one mean dark level is subtracted from every frame; calibration says so (warning and
    report note) instead of in silence (before: exit 0, the bundle's black level 30 DN high,
    B 7 % off, nothing said)."""
    import rawpy

    lab = tmp_path / "lab"
    sheet = _lab_folder(sim, lab)
    rows = list(csv.reader(sheet.open()))
    dark = next(r for r in rows if r[1] == "dark")
    with rawpy.imread(str(lab / dark[0])) as raw:
        m = raw.raw_image_visible.astype(np.float64) + 60
    write_dng(lab / "Dark/dark_long.dng", m, black_level=BLACK, white_level=WHITE,
              exposure_s=0.5)  # fmt: skip
    rows.append(["Dark/dark_long.dng", "dark", "", "", "", "", ""])
    capset = _import_sheet(sheet, rows, tmp_path / "capset")
    with pytest.warns(UserWarning, match=r"dark frames of different exposures averaged "
                      r"\(.*\(0\.02 s\), dark_long\.dng \(0\.5 s\)\)"):  # fmt: skip
        _, report = _calibrate(capset)
    assert any(n.startswith("dark frames of different exposures") for n in report.notes)


def test_a_repeated_scan_frame_of_another_wavelength_is_warned_about(sim: Path, tmp_path: Path):
    """A second take of the 560 nm frame listed as 550 nm (a slip in the sheet; the same file or
    a byte copy is refused by the import, see
    test_one_file_at_two_wavelengths_or_in_two_roles_is_refused): the two frames of "550 nm"
    are averaged, but their patterns differ by ~33 % (noise: < 1 %), and calibration says so,
    naming both (before: averaged in silence, B 3.7 % off)."""
    import rawpy

    lab = tmp_path / "lab"
    sheet = _lab_folder(sim, lab)
    rows = list(csv.reader(sheet.open()))
    r560 = next(r for r in rows if r[1] == "scan" and r[2] == "560")
    with rawpy.imread(str(lab / r560[0])) as raw:
        m = raw.raw_image_visible.astype(np.float64)
    m[0, 0] = min(m[0, 0] + 1, WHITE)  # another take: not the same bytes
    write_dng(lab / "Monochromator/retake_560.dng", m, black_level=BLACK, white_level=WHITE,
              exposure_s=0.5, make="Lab Optics", model="KaleidoCam 1")  # fmt: skip
    rows.append(["Monochromator/retake_560.dng", "scan", "550", "", "", "", ""])
    capset = _import_sheet(sheet, rows, tmp_path / "capset")
    with pytest.warns(UserWarning, match=r"scan: retake_560\.dng differs from "
                      r"frame_\d+\.dng, the frame of the same wavelength it is averaged with, "
                      r"by [23]\d % RMS") as rec:  # fmt: skip
        _, report = _calibrate(capset)
    assert sum("differs from" in str(w.message) for w in rec) == 1  # not the identical repeat
    assert any("is its wavelength right?" in n for n in report.notes)


def test_a_dark_frame_with_a_pedestal_of_its_own_is_named_when_too_much_is_subtracted(
    sim: Path, tmp_path: Path
):
    """The dark frame as a 16-bit PNG (its 512 DN pedestal in the data, no black level in the
    sheet) beside DNGs that carry theirs: 512 DN too much is subtracted from every frame, and
    the refusal names the dark frame as the likely cause (before, it only suggested changing
    the other captures' black level to ~0, which would have hidden the error)."""
    import rawpy

    from hsi_torch.errors import CalibrationError

    lab = tmp_path / "lab"
    sheet = _lab_folder(sim, lab)
    rows = list(csv.reader(sheet.open()))
    dark = next(r for r in rows if r[1] == "dark")
    with rawpy.imread(str(lab / dark[0])) as raw:
        m = raw.raw_image_visible.copy()
    (lab / dark[0]).unlink()
    dark[0] = str(Path(dark[0]).with_suffix(".png"))
    dark[5] = "RGGB"
    assert cv2.imwrite(str(lab / dark[0]), m.astype(np.uint16))
    capset = _import_sheet(sheet, rows, tmp_path / "capset")
    with pytest.raises(CalibrationError, match=r"reads -5\d\d\.\d DN .*too high.*or the dark "
                       r"frame dark_00\.png \(read with black level 0 DN, source: default; its "
                       r"mean, 51\d DN above that"):  # fmt: skip
        _calibrate(capset)


def _add_pedestal(lab: Path, rows: list[list[str]], role: str, dn: int) -> None:
    """Rewrite the DNGs of ``role`` with ``dn`` more in the data and the same BlackLevel tag (512):
    a pedestal the tag does not announce."""
    import rawpy

    for r in rows[1:]:
        if r[1] == role:
            with rawpy.imread(str(lab / r[0])) as raw:
                m = raw.raw_image_visible.astype(np.float64)
            t = 0.5 if role == "scan" else T_WHITE
            write_dng(lab / r[0], np.clip(m + dn, 0, WHITE), black_level=BLACK,
                      white_level=WHITE, exposure_s=t, make="Lab Optics",
                      model="KaleidoCam 1")  # fmt: skip


def _calibrate_with_scan_black_level(sheet: Path, rows: list, tmp_path: Path, level: float):
    """The sheet's scan rows given ``level`` as their black level, imported again and
    calibrated: ``(bundle, report)``."""
    for r in rows[1:]:
        if r[1] == "scan":
            r[4] = str(level)
    capset = _import_sheet(sheet, rows, tmp_path / "capset2")
    return _calibrate(capset)


def _set_with_pedestal(sim: Path, tmp_path: Path, role: str, dn: float) -> tuple[Path, list, Path]:
    """A lab's DNG folder of ``sim`` with ``dn`` DN of pedestal in ``role``'s files that their
    BlackLevel tag misses, imported: ``(sheet, its rows, capture set)``."""
    lab = tmp_path / "lab"
    sheet = _lab_folder(sim, lab)
    rows = list(csv.reader(sheet.open()))
    _add_pedestal(lab, rows, role, dn)
    return sheet, rows, _import_sheet(sheet, rows, tmp_path / "capset")


def test_dng_scan_frames_with_a_pedestal_their_black_level_tag_misses_are_refused(
    sim: Path, tmp_path: Path
):
    """The scan DNGs carry 64 DN more black than their BlackLevel tag (512) says, the white, dark
    and grid files are right: the scan frames are checked as a role of their own and refused,
    naming the role, a file, the level and the limit. Before the fix they were checked together
    with the white shots (the same black level from the same source), whose frames read 3 DN:
    exit 0, no warning, the ColorChecker at 24.2 dB instead of 31.3 dB."""
    from hsi_torch.errors import CalibrationError

    sheet, rows, capset = _set_with_pedestal(sim, tmp_path, "scan", 64)
    with pytest.raises(CalibrationError, match=r"reads 6\d\.\d DN after black subtraction \(R "
                       r"channel; R 6\d\.\d, G 6\d\.\d, B 6\d\.\d DN; the frame closest to 0 "
                       r"of the 26 scan frames read with black level 512 DN \(source: file\): "
                       r"frame_001\.dng, .*; the other frames "
                       r"read [0-4]\.\d DN \(white, 3 frames\), .*limit 39\.7 DN\): these "
                       r"captures carry a black pedestal of ~6\d DN that their files' black "
                       r"level \(512 DN\) does not include: correct the files' black level \(a "
                       r"DNG's BlackLevel tag\) or give their black_level in the sheet or "
                       r"manifest \(e\.g\. 57\d\)"):  # fmt: skip
        _calibrate(capset)
    # their black level in the sheet: the set calibrates, every role ~0 outside the views
    _, report = _calibrate_with_scan_black_level(sheet, rows, tmp_path, BLACK + 64)
    assert report.pedestal["ok"]
    by_role = {g["role"]: g for g in report.pedestal["by_group"]}
    assert by_role["scan"]["black_level_source"] == "sheet"
    assert max(map(abs, by_role["scan"]["pedestal_dn"])) < 5


def test_dng_white_shots_with_a_pedestal_their_black_level_tag_misses_are_warned_about(
    sim: Path, tmp_path: Path
):
    """The white DNGs alone carry 64 DN more black than their tag says: ``pedestal_check: warn``
    warns (and notes in the report) naming the white frames; ``error`` (the default) refuses.
    Before the fix the scan frames (read 2 DN) decided for them: exit 0, no warning, the
    ColorChecker at 27.9 dB instead of 31.3 dB."""
    _, _, capset = _set_with_pedestal(sim, tmp_path, "white", 64)
    with pytest.warns(UserWarning, match=r"reads 6\d\.\d DN after black subtraction .*the 3 white "
                      r"frames read with black level 512 DN \(source: file\): white_00\.dng, "
                      r"white_01\.dng, white_02\.dng; the other frames read .*[0-4]\.\d DN "
                      r"\(scan, 26 frames\); limit 44\.\d DN\): these captures carry a black "
                      r"pedestal of ~6\d DN"):  # fmt: skip
        _, report = _calibrate(capset, pedestal_check="warn")
    assert not report.pedestal["ok"] and report.pedestal["group"]["role"] == "white"
    assert any("white_00.dng" in n and "black pedestal" in n for n in report.notes)
    assert "  white (3 frames, black level 512 DN, file): R 6" in str(report)


def test_clean_sets_pass_the_per_role_pedestal_check_with_stray_light(sim: Path, tmp_path: Path):
    """False alarms: every scan, white and grid frame read as calibration reads them and checked
    role by role, with ``pedestal_check: error``. The simulator's set: each role at <= 0.07 of
    its limit. With the documented 2 % veil of stray light (the white's and the grid's outside
    raised by up to ~30 DN): ~0.2 of the limit (the veil's spread raises the limit with it);
    the scan's dim frames read ~2 DN either way."""
    import torch

    from hsi_torch.calibrate.config import CalibrateConfig
    from hsi_torch.calibrate.reading import CaptureReader, check_pedestal
    from hsi_torch.io.radiometry import outside_views_index

    def check(folder: Path) -> list[dict]:
        cs = read_capture_set(folder)
        lay = cs.layout()
        roles = {p: "scan" for p, _ in cs.scan}
        roles.update({p: role for role in ("white", "grid") for p in getattr(cs, role)})
        reader = CaptureReader(CalibrateConfig(), lay.sensor_size, "cpu", torch.float32,
                               settings=cs.settings, roles=roles,
                               outside_index=outside_views_index(lay.triangles, lay.sensor_size))
        reader.set_dark(cs.dark, "per_pixel")
        for p in roles:
            reader.read(p)
        notes: list[str] = []
        ped = check_pedestal(reader, "error", notes)  # fmt: skip
        assert ped["ok"] and notes == [] and len(ped["by_group"]) == 3
        return ped["by_group"]

    def worst(g: dict) -> float:
        return max(abs(v) / lim for v, lim in zip(g["pedestal_dn"], g["pedestal_limit_dn"],
                                                  strict=True))  # fmt: skip

    assert max(map(worst, check(sim))) < 0.1
    veil = tmp_path / "veil"  # the calibration captures only: check() reads no scene
    assert main(["simulate", "--config", str(shipped_config("simulate")), "--out", str(veil),
                 "--set", "render.figures=false", "--set", "render.progress=false",
                 "--set", "render.dtype=float32", "--set", "captures.scenes=[]",
                 "--set", "mismatch.stray_light_fraction=0.02"]) == 0  # fmt: skip
    groups = {g["role"]: g for g in check(veil)}
    assert max(map(worst, groups.values())) < 0.3
    assert max(groups["white"]["pedestal_dn"]) > 20  # the veil is there, and passes
    assert max(map(abs, groups["scan"]["pedestal_dn"])) < 5


# ---------------------------------------------------------------------------------------------
# one frame as two things; sheets; what `captures check` finds before calibrate


def _png_set(folder: Path, names: list[str], size: tuple[int, int] = (30, 32)) -> None:
    """16-bit grey PNGs of distinct content, one per name."""
    for k, name in enumerate(names):
        m = ((np.arange(size[0] * size[1]).reshape(size) * (k + 3)) % 4000 + 600)
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        assert cv2.imwrite(str(folder / name), m.astype(np.uint16))


def _tiny_layout(path: Path, size: tuple[int, int] = (30, 32)) -> Path:
    path.write_text(json.dumps({"schema_version": 1, "sensor_size": list(size),
                                "triangles_px": [[[1, 1], [20, 1], [1, 20]]], "parity": [1],
                                "reference_bbox": [0, 0, 16, 16]}))  # fmt: skip
    return path


def test_one_file_at_two_wavelengths_or_in_two_roles_is_refused(tmp_path: Path, capsys):
    """The 550 nm frame's file listed again at 560 nm (a copied sheet cell), a byte copy of it
    at 560 nm, or one file as white and dark: the import refuses naming both uses (before:
    "25 of 25 bands", and B(560) = B(550), 31.8 % off); a hand-written manifest that does it
    is refused by `captures check` (exit 1) and by calibration."""
    _png_set(tmp_path, ["m/a.png", "m/b.png", "w.png", "g.png", "d.png"])
    head = "file,role,wavelength_nm,cfa_pattern\n"
    base = "m/a.png,scan,550,RGGB\nw.png,white,,RGGB\ng.png,grid,,RGGB\n"
    shutil.copy(tmp_path / "m/a.png", tmp_path / "m/copy.png")
    for extra, match in (
        ("m/a.png,scan,560,RGGB\n", r"a\.png is used as scan frame at 550 nm and as "
                                          r"scan frame at 560 nm"),
        ("m/copy.png,scan,560,RGGB\n", r"a\.png, .*copy\.png hold the same bytes and are "
                                       r"used as scan frame at 550 nm and as scan frame at 560"),
        ("w.png,dark,,RGGB\n", r"w\.png is used as white and as dark"),
    ):  # fmt: skip
        (tmp_path / "sheet.csv").write_text(head + base + extra)
        out = tmp_path / "set"
        assert main(["captures", "import", "--sheet", str(tmp_path / "sheet.csv"),
                     "--out", str(out)]) == 1  # fmt: skip
        assert re.search(match, capsys.readouterr().err)
        assert not out.exists()  # nothing written
    # a manifest written by hand, past the import
    hand = tmp_path / "hand"
    _png_set(hand, ["s_550nm.png", "w.png", "g.png"])
    (hand / "manifest.json").write_text(json.dumps({"schema_version": 1, "cfa_pattern": "RGGB",
        "captures": [{"file": "s_550nm.png", "type": "scan", "wavelength_nm": 550},
                     {"file": "s_550nm.png", "type": "scan", "wavelength_nm": 560},
                     {"file": "w.png", "type": "white"}, {"file": "g.png", "type": "grid"}]}))
    assert main(["captures", "check", str(hand)]) == 1
    cap = capsys.readouterr()
    assert "error: " in cap.err and "scan frame at 550 nm and as scan frame at 560 nm" in cap.err
    assert cap.out.count("s_550nm.png") >= 2  # the per-file table, both rows
    with pytest.raises(FileFormatError, match="scan frame at 550 nm and as scan frame at 560"):
        read_capture_set(hand).require_calibration_captures()


def test_sheet_separators_line_breaks_and_repeated_lines(tmp_path: Path):
    _png_set(tmp_path, ["s_550nm.png", "chart.png"])
    sheet = tmp_path / "sheet.csv"
    sheet.write_text("file;role;wavelength_nm\ns_550nm.png;scan;550\n")
    with pytest.raises(FileFormatError, match=r"sheet.csv: the header 'file;role;wavelength_nm' "
                       r"is separated by semicolons \(';'\); a capture sheet is comma-separated"):
        read_sheet(sheet)
    # a quoted cell over two lines keeps its line break; the line numbers stay those of the file
    sheet.write_text('file,role,name\nchart.png,scene,"chart\nsecond line"\ns_550nm.png,scan,\n'
                     "s_550nm.png,scan,\n")
    with pytest.raises(FileFormatError, match=r"sheet.csv:5: the same line as .*sheet.csv:4"):
        read_sheet(sheet)
    sheet.write_text('file,role,name\nchart.png,scene,"chart\nsecond line"\ns_550nm.png,scan,\n')
    rows = read_sheet(sheet)
    assert rows[0].name == "chart\nsecond line" and rows[1].where.endswith("sheet.csv:4")


def test_check_lists_every_file_and_finds_what_calibrate_refuses(tmp_path: Path, capsys):
    """Two grid shots of the wrong size: both named, every other file still in the table (before:
    `check` stopped at the first with no table); calibration captures that mix Bayer patterns:
    exit 1 naming both (before: refused only by calibrate)."""
    _png_set(tmp_path, ["s_430nm.png", "w.png", "d.png"])
    _png_set(tmp_path, ["g1.png", "g2.png"], size=(30, 34))
    _tiny_layout(tmp_path / "layout.json")
    (tmp_path / "sheet.csv").write_text(
        "file,role,cfa_pattern\ns_430nm.png,scan,RGGB\nw.png,white,GRBG\ng1.png,grid,RGGB\n"
        "g2.png,grid,RGGB\nd.png,dark,RGGB\n")  # fmt: skip
    assert main(["captures", "import", "--sheet", str(tmp_path / "sheet.csv"), "--layout",
                 str(tmp_path / "layout.json"), "--out", str(tmp_path / "set")]) == 0  # fmt: skip
    capsys.readouterr()
    assert main(["captures", "check", str(tmp_path / "set")]) == 1
    cap = capsys.readouterr()
    table = [line for line in cap.out.splitlines() if not line.startswith("note:")]
    for name in ("s_430nm.png", "w.png", "g1.png", "g2.png", "d.png"):
        assert sum(name in line for line in table) == 1, name
    assert sum("REFUSED" in line and "30x34" in line for line in table) == 2
    for g in ("g1.png", "g2.png"):
        assert re.search(rf"error: .*{g}: image size \(H, W\) = \(30, 34\) does not match the "
                         r"expected sensor size \(30, 32\)", cap.err)
    assert re.search(r"error: the calibration captures mix Bayer patterns: RGGB in s_430nm.png, "
                     r"d.png; GRBG in w.png", cap.err)
