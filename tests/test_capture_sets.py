"""Capture-set folder: completeness, manifest, metadata, truth file, determinism, config errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from hsi_torch.cli import main
from hsi_torch.config import ConfigError, load_config
from hsi_torch.io import read_capture
from hsi_torch.resources import shipped_config
from hsi_torch.simulate.config import SimulateConfig

TINY = [
    "camera.scale=0.5", "render.supersample=1", "render.dtype=float32",
    "render.progress=false", "captures.scan_wavelengths_nm=[450, 550, 650]",
    "captures.white_shots=2", "render.figures=false",
]


@pytest.fixture(scope="module")
def capture_set(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("sim") / "set"
    args = ["simulate", "--config", str(shipped_config("simulate")), "--out", str(out)]
    for o in [*TINY, "render.figures=true"]:
        args += ["--set", o]
    assert main(args) == 0
    return out


def test_folder_complete_and_manifest_lists_every_file(capture_set: Path):
    man = json.loads((capture_set / "manifest.json").read_text())
    listed = {c["file"] for c in man["captures"]}
    on_disk = {str(p.relative_to(capture_set)) for p in capture_set.rglob("*.tif")}
    assert listed == on_disk
    types = [c["type"] for c in man["captures"]]
    assert types.count("scan") == 3 and types.count("white") == 2
    assert types.count("grid") == 3 and types.count("dark") == 1 and types.count("scene") == 1
    assert [c["wavelength_nm"] for c in man["captures"] if c["type"] == "scan"] == [450, 550, 650]
    for name in ("nominal_layout.json", "brf_free_mask.png", "resolved_config.yaml",
                 "ground_truth/truth.npz", "ground_truth/truth.json",
                 "figures/capture_views.png", "figures/transmittance.png"):
        assert (capture_set / name).is_file(), name
    nom = json.loads((capture_set / "nominal_layout.json").read_text())
    assert "view_homographies" not in nom and len(nom["triangles_px"]) == 10
    assert nom["brf_free_patch"]["usable_pixels"] >= 1
    # every capture: 16-bit, metadata agrees with the manifest
    for c in man["captures"]:
        img, meta = read_capture(capture_set / c["file"])
        assert img.shape == (1, *man["sensor_size"])
        assert meta["kind"] == man["output"] == "bayer"
        assert meta["cfa_pattern"] == man["cfa_pattern"]
        assert meta["black_level"] == man["black_level"]
        assert meta["type"] == c["type"]
        assert float(img.max()) <= man["white_level"]
    dark, _ = read_capture(capture_set / "dark" / "dark_00.tif")
    assert abs(float(dark.mean()) - man["black_level"]) < 1.0


def test_truth_file(capture_set: Path):
    t = np.load(capture_set / "ground_truth" / "truth.npz")
    V, M = 10, 25
    _, _, w, h = t["reference_bbox"]
    assert t["B"].shape == (V, M, h, w) and t["gain"].shape == (V, h, w)
    assert t["phi"].shape == (3, M) and t["valid"].shape == (h, w)
    assert t["view_homographies"].shape == (V, 3, 3)
    assert t["scene_colorchecker"].shape == (M, h, w)
    assert t["colorchecker_spectra"].shape == (24, M)
    assert t["grid_00_centres_ref_px"].shape == (20, 2)
    np.testing.assert_array_equal(t["valid"], t["modulated"].sum(0) >= 3)
    assert (t["colorchecker_patch_index"] >= -1).all() and t["colorchecker_patch_index"].max() > 0
    doc = json.loads((capture_set / "ground_truth" / "truth.json").read_text())
    assert doc["valid_pixels"] == int(t["valid"].sum()) > 0
    assert set(doc["shapes"]) == set(t.files)


def test_deterministic_with_seed(capture_set: Path, tmp_path: Path):
    from hsi_torch.simulate.capture_sets import simulate_capture_set

    cfg = load_config(shipped_config("simulate"), SimulateConfig,
                      [*TINY, "captures.scenes=[]", "captures.grid.poses=[]"])
    simulate_capture_set(cfg, tmp_path / "a", progress=False, log=lambda m: None)
    a, _ = read_capture(tmp_path / "a" / "white" / "white_00.tif")
    b, _ = read_capture(capture_set / "white" / "white_00.tif")
    a2, _ = read_capture(tmp_path / "a" / "white" / "white_01.tif")
    # same seed and capture index → identical; white shots differ only by noise
    b_idx = [c["file"] for c in json.loads((capture_set / "manifest.json").read_text())
             ["captures"]].index("white/white_00.tif")
    a_idx = [c["file"] for c in json.loads((tmp_path / "a" / "manifest.json").read_text())
             ["captures"]].index("white/white_00.tif")
    assert a_idx == b_idx
    assert np.array_equal(a.numpy(), b.numpy())
    assert not np.array_equal(a.numpy(), a2.numpy())
    assert abs(float(a.mean() - a2.mean())) < 2.0


@pytest.mark.parametrize("override,key", [
    ("captures.scan_fwhm=3", "captures.scan_fwhm"),
    ("render.dtype=float16", "render.dtype"),
    ("sensor.output=raw", "sensor.output"),
    ("camera.width_px=abc", "camera.width_px"),
])
def test_config_errors_name_the_key(override: str, key: str):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        load_config(shipped_config("simulate"), SimulateConfig, [override])


def test_configs_load():
    for name in ("simulate.yaml", "simulate_full.yaml"):
        cfg = load_config(shipped_config(name), SimulateConfig)
        assert cfg.captures.scan_wavelengths_nm is None
    full = load_config(shipped_config("simulate_full"), SimulateConfig)
    assert (full.camera.width_px, full.camera.height_px) == (2896, 2784)


def test_bench_simulate_reports_stages_and_peak_memory(tmp_path: Path, capsys):
    """scripts/bench_simulate.py on a tiny set: child process, every stage timed, peak RSS."""
    import runpy

    script = Path(__file__).resolve().parents[1] / "scripts" / "bench_simulate.py"
    bench = runpy.run_path(str(script))
    args = ["--config", str(shipped_config("simulate")), "--out", str(tmp_path / "b")]
    for o in ["camera.scale=0.25", "render.supersample=1", "captures.scan_wavelengths_nm=[550]",
              "captures.white_shots=1", "captures.grid.poses=[]", "render.figures=false"]:
        args += ["--set", o]
    assert bench["main"](args) == 0
    out = capsys.readouterr().out
    for stage in ("setup", "trace+render", "sensor+write", "truth", "peak GiB"):
        assert stage in out
    row = next(line for line in out.splitlines() if line.startswith("simulate.yaml"))
    assert row.split()[1] == "100x96"
    peak = float(row.split()[-1])
    assert 0.1 < peak < 4.0  # GiB of the child (torch alone is > 0.1)
    assert (tmp_path / "b" / "simulate" / "manifest.json").is_file()  # --out keeps the set


def test_bench_simulate_refuses_a_folder_it_did_not_write(tmp_path: Path):
    """``scripts/bench_simulate.py --out lab`` wrote its capture set into ``lab/simulate/``
    whatever ``lab`` held (a lab's own ``simulate/manifest.json`` was replaced). Now a folder
    holding files but no earlier run of the script is refused before anything runs, naming
    them, as ``demo`` and ``experiment`` refuse theirs; its own earlier folder is accepted."""
    import runpy

    script = Path(__file__).resolve().parents[1] / "scripts" / "bench_simulate.py"
    bench = runpy.run_path(str(script))
    lab = tmp_path / "lab"
    (lab / "simulate").mkdir(parents=True)
    (lab / "simulate" / "manifest.json").write_text('{"device": true}')
    (lab / "notes.txt").write_text("the lab's")
    ran: list[Path] = []

    def fake_run_one(config, out, overrides, threads):
        ran.append(out)
        raise RuntimeError("the benchmark ran")

    bench["main"].__globals__["_run_one"] = fake_run_one  # no child process in this test
    args = ["--config", str(shipped_config("simulate")), "--out"]
    with pytest.raises(SystemExit, match="is not empty \\(notes.txt, simulate\\) and holds no "
                                         "earlier run of bench_simulate.py"):  # fmt: skip
        bench["main"]([*args, str(lab)])
    assert not ran
    assert (lab / "simulate" / "manifest.json").read_text() == '{"device": true}'
    assert sorted(p.name for p in lab.iterdir()) == ["notes.txt", "simulate"]
    # a new folder, then the same folder again (the script's own marker): the benchmark runs
    for _ in range(2):
        with pytest.raises(RuntimeError, match="the benchmark ran"):
            bench["main"]([*args, str(tmp_path / "mine")])
    assert ran == [tmp_path / "mine" / "simulate"] * 2
