"""io.capture_set: the one reader and writer of capture-set folders (manifest, nominal layout,
BRF-free mask, ground truth), on small hand-made folders (no simulation)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from hsi_torch.errors import FileFormatError, MissingFileError
from hsi_torch.io import write_capture
from hsi_torch.io.capture_set import (
    CAPTURE_SET_SCHEMA_VERSION,
    read_capture_set,
    read_nominal_layout,
    read_truth,
    write_capture_set_index,
    write_truth,
)

H, W = 12, 16
LAYOUT = {
    "sensor_size": [H, W],
    "triangles_px": [[[1.0, 10.0], [7.0, 10.0], [4.0, 1.0]],
                     [[8.0, 1.0], [14.0, 1.0], [11.0, 10.0]]],
    "parity": [1, -1],
    "reference_view": 0,
    "reference_bbox": [1, 1, 7, 10],
    "reflection_sequences": [[], [0]],
    "brf_free_patch": {"polygon_px": [[3.0, 7.0], [5.0, 7.0], [4.0, 5.0]],
                       "usable_mask": "brf_free_mask.png"},
}


def _write_set(root: Path) -> list[dict]:
    entries = []
    for k, (file, typ, extra) in enumerate((
            ("scan/scan_550nm.tif", "scan", {"wavelength_nm": 550.0}),
            ("white/white_00.tif", "white", {}), ("grid/grid_00.tif", "grid", {}),
            ("dark/dark_00.tif", "dark", {}), ("scenes/cc.tif", "scene", {"name": "cc"}))):
        img = np.full((3, H, W), 100 + k, np.uint16)  # one frame is one thing: distinct
        write_capture(root / file, img, {"kind": "rgb"})
        entries.append({"file": file, "type": typ, "exposure": 0.5, **extra})
    mask = np.zeros((H, W), bool)
    mask[6, 4] = True
    write_truth(root, {"B": np.ones((2, 3, 10, 7), np.float32)}, {"exposure": 0.5})
    write_capture_set_index(root, captures=entries, nominal_layout=LAYOUT, brf_free_mask=mask,
                            generator="test", cfa_pattern=None)  # fmt: skip
    return entries


def test_round_trip(tmp_path: Path):
    _write_set(tmp_path)
    cs = read_capture_set(tmp_path)
    assert cs.manifest["schema_version"] == CAPTURE_SET_SCHEMA_VERSION
    assert cs.manifest["generator"] == "test"
    assert cs.manifest["ground_truth"] == "ground_truth/truth.npz"
    assert cs.scan == [(tmp_path / "scan/scan_550nm.tif", 550.0)]
    assert cs.white == [tmp_path / "white/white_00.tif"] and cs.grid and cs.dark
    assert cs.scene("cc") == tmp_path / "scenes/cc.tif"
    cs.require_calibration_captures()
    lay = cs.layout()
    assert lay.num_views == 2 and lay.sensor_size == (H, W) and lay.reference_bbox == (1, 1, 7, 10)
    assert lay.parity.tolist() == [1, -1] and lay.reflection_sequences == [(), (0,)]
    assert lay.brf_free_polygon().shape == (3, 2)
    mask = cs.read_brf_free_mask((H, W))
    assert mask.dtype == bool and mask.sum() == 1 and mask[6, 4]
    assert sorted(cs.files()) == ["brf_free_mask.png", "dark/dark_00.tif", "grid/grid_00.tif",
                                  "nominal_layout.json", "scan/scan_550nm.tif",
                                  "white/white_00.tif"]  # fmt: skip
    arrays, meta = read_truth(tmp_path)
    assert arrays["B"].shape == (2, 3, 10, 7) and meta["exposure"] == 0.5
    assert meta["schema_version"] == CAPTURE_SET_SCHEMA_VERSION
    with pytest.raises(MissingFileError, match="no scene 'x'"):
        cs.scene("x")


def test_plain_folders_and_name_wavelengths(tmp_path: Path):
    img = np.zeros((3, H, W), np.uint16)
    for f in ("scan/mono_552p5nm.tif", "scan/scan_430nm.tif", "white/w.tif", "scenes/a.tif"):
        write_capture(tmp_path / f, img, {"kind": "rgb"})
    cs = read_capture_set(tmp_path)
    assert cs.manifest is None
    assert sorted(w for _, w in cs.scan) == [430.0, 552.5]
    assert cs.scenes == {"a": tmp_path / "scenes/a.tif"}
    with pytest.raises(FileFormatError, match="no circle-grid captures"):
        cs.require_calibration_captures()
    with pytest.raises(MissingFileError, match="nominal layout"):
        cs.layout()
    with pytest.raises(MissingFileError, match="ground truth"):
        read_truth(tmp_path)


def test_bad_manifests_name_the_file(tmp_path: Path):
    entries = _write_set(tmp_path)
    mpath = tmp_path / "manifest.json"
    m = json.loads(mpath.read_text())
    mpath.write_text(json.dumps({**m, "schema_version": 2}))
    with pytest.raises(FileFormatError, match=r"manifest.json: schema_version 2 is not supported"):
        read_capture_set(tmp_path)
    mpath.write_text(json.dumps({**m, "captures": [{"type": "scan"}]}))
    with pytest.raises(FileFormatError, match=r"captures\[0\] needs 'file' and 'type'"):
        read_capture_set(tmp_path)
    mpath.write_text(json.dumps({**m, "captures": [{**entries[0], "file": "scan/none.tif"}]}))
    with pytest.raises(MissingFileError, match="none.tif does not exist"):
        read_capture_set(tmp_path)
    mpath.write_text("{")
    with pytest.raises(FileFormatError, match="not valid JSON"):
        read_capture_set(tmp_path)
    with pytest.raises(ValueError, match="type 'flat'"):
        write_capture_set_index(tmp_path, captures=[{"file": "x.tif", "type": "flat"}],
                                nominal_layout=LAYOUT, brf_free_mask=np.zeros((H, W), bool))


@pytest.mark.parametrize("key,value,match", [
    ("parity", [1, 2], "parity must be 2 values of ±1"),
    ("triangles_px", [[1, 2]], r"triangles_px must be \(V, 3, 2\)"),
    ("reference_bbox", [0, 0, 0, 5], r"reference_bbox must be \(x0, y0, w, h\)"),
    ("reference_view", 1, "reference_view must be 0"),
])  # fmt: skip
def test_bad_layouts_name_the_key(tmp_path: Path, key, value, match):
    p = tmp_path / "nominal_layout.json"
    p.write_text(json.dumps({**LAYOUT, key: value}))
    with pytest.raises(FileFormatError, match=match):
        read_nominal_layout(p)
    p.write_text(json.dumps({k: v for k, v in LAYOUT.items() if k != "sensor_size"}))
    with pytest.raises(FileFormatError, match="missing key 'sensor_size'"):
        read_nominal_layout(p)


@pytest.mark.parametrize("root", ["../elsewhere", "ABS", "link"])
def test_files_root_outside_the_set_is_refused_unless_allowed(tmp_path: Path, root: str):
    """``files_root`` used to let a manifest read (and record in its bundle) files anywhere:
    ``../x``, an absolute path or a symlink out of the folder is refused naming the key, unless
    the manifest says ``allow_files_outside``; a files_root inside the folder still works."""
    elsewhere = tmp_path / "elsewhere"
    entries = _write_set(elsewhere)
    s = tmp_path / "set"
    s.mkdir()
    (s / "link").symlink_to(elsewhere)
    value = str(elsewhere) if root == "ABS" else root
    m = {"schema_version": 1, "files_root": value, "captures": entries}
    (s / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(FileFormatError, match=r"manifest.json: files_root .* points outside the "
                       r"capture set's folder .*allow_files_outside"):
        read_capture_set(s)
    (s / "manifest.json").write_text(json.dumps({**m, "allow_files_outside": True}))
    assert read_capture_set(s).white == [s / value / "white/white_00.tif"]
    inner = s / "inner"
    _write_set(inner)
    (s / "manifest.json").write_text(json.dumps({**m, "files_root": "inner"}))
    assert read_capture_set(s).white == [inner / "white/white_00.tif"]
