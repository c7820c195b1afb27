"""Shipped files (configs, data) through importlib.resources, the `config` command, every
command's default config, and the real-data folder (setting, HSI_TORCH_DATA)."""

from __future__ import annotations

import argparse

import pytest
import yaml

from hsi_torch import resources
from hsi_torch.cli import build_parser, config_source, main
from hsi_torch.config import load_config
from hsi_torch.resources import real_data_dir, shipped_config, shipped_config_names

SHIPPED = ["calibrate", "design", "mismatch", "opd", "reconstruct", "simulate",
           "simulate_fujimoto", "simulate_full", "simulate_manakov", "synthetic", "usaf"]


def _readme_prototype(cfg) -> tuple:
    return (cfg.geometry.a_in_mm, cfg.geometry.a_out_mm, cfg.geometry.length_mm,
            cfg.brf.material, cfg.brf.thickness_mm, cfg.brf.axis_tilt_deg,
            cfg.brf.axis_azimuth_deg, cfg.diffuser.blur_sigma_mm)


#: the README's default prototype: tube 16 → 40 mm, 160 mm long; quartz 2.5 mm, axis 70° / 40°;
#: diffuser PSF sigma 0.1 mm
README_PROTOTYPE = (16.0, 40.0, 160.0, "quartz", 2.5, 70.0, 40.0, 0.1)


def test_shipped_configs_are_package_files():
    assert shipped_config_names() == SHIPPED
    for name in SHIPPED:
        p = shipped_config(name)
        assert p.is_file() and p.parent == resources.shipped_config_dir()
        assert shipped_config(name + ".yaml") == p
        assert isinstance(yaml.safe_load(p.read_text()), dict)
    with pytest.raises(FileNotFoundError, match="available: calibrate, design"):
        shipped_config("nope")


def test_configs_have_one_home_at_the_top_of_the_checkout(monkeypatch, tmp_path):
    """``configs/`` beside ``hsi_torch/`` is the only copy: a checkout (or an editable install)
    reads it there; an installed package's own ``hsi_torch/configs/`` comes first; neither is an
    error naming both places."""
    root = resources.source_checkout()
    assert root is not None  # the tests run from the checkout
    assert resources.shipped_config_dir() == root / "configs"
    assert not (root / "hsi_torch" / "configs").exists()
    assert sorted(p.stem for p in (root / "configs").glob("*.yaml")) == SHIPPED
    installed = tmp_path / "hsi_torch" / "configs"
    installed.mkdir(parents=True)
    (installed / "only.yaml").write_text("a: 1\n")
    monkeypatch.setattr(resources, "_package_dir", lambda sub: tmp_path / "hsi_torch" / sub)
    assert resources.shipped_config_names() == ["only"]
    installed.joinpath("only.yaml").unlink()
    installed.rmdir()
    monkeypatch.setattr(resources, "source_checkout", lambda: None)
    with pytest.raises(FileNotFoundError, match="configuration files are missing"):
        shipped_config("simulate")


def test_config_command_list_show_copy(tmp_path, capsys):
    assert main(["config"]) == 0
    assert capsys.readouterr().out.split() == SHIPPED
    assert main(["config", "show", "reconstruct"]) == 0
    assert capsys.readouterr().out == shipped_config("reconstruct").read_text()
    dest = tmp_path / "mine.yaml"
    assert main(["config", "copy", "simulate", str(dest)]) == 0
    assert dest.read_text() == shipped_config("simulate").read_text()
    dest.write_text("# edited\n")
    assert main(["config", "copy", "simulate", str(dest)]) == 1  # never overwrites silently
    assert "exists; use --force" in capsys.readouterr().err
    assert dest.read_text() == "# edited\n"
    assert main(["config", "copy", "simulate", str(dest), "--force"]) == 0
    assert dest.read_text() == shipped_config("simulate").read_text()
    assert main(["config", "copy", "usaf", str(tmp_path)]) == 0  # a folder: DEST/usaf.yaml
    assert (tmp_path / "usaf.yaml").is_file()
    assert main(["config", "show", "nope"]) == 1
    assert "no shipped config 'nope'" in capsys.readouterr().err
    assert main(["config", "show"]) == 1


@pytest.mark.parametrize("argv, name", [
    (["simulate", "--out", "x"], "simulate"),
    (["calibrate", "--captures", "c", "--out", "x"], "calibrate"),
    (["reconstruct", "--bundle", "b.npz", "--out", "x", "in.tif"], "reconstruct"),
    (["experiment", "synthetic", "--out", "x"], "synthetic"),
    (["experiment", "opd", "--out", "x"], "opd"),
])  # fmt: skip
def test_every_command_defaults_to_its_shipped_config(argv, name):
    args = build_parser().parse_args(argv)
    default = args.name if args.command == "experiment" else args.command
    assert config_source(args, default) == shipped_config(name)
    args.config = "own.yaml"
    assert str(config_source(args, default)) == "own.yaml"
    args.config = "simulate_full"  # the name of a shipped file (no such file here)
    assert config_source(args, default) == shipped_config("simulate_full")
    args.config = "simulate_full.yaml"
    assert config_source(args, default) == shipped_config("simulate_full")


def test_config_name_prefers_a_real_file(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "simulate.yaml").write_text("camera: {scale: 0.5}\n")
    args = build_parser().parse_args(["simulate", "--out", "x", "--config", "simulate.yaml"])
    assert config_source(args, "simulate").resolve() == (tmp_path / "simulate.yaml").resolve()


def test_simulate_without_config_renders_the_readme_prototype(monkeypatch, tmp_path):
    """The command's wiring, not just the file: `hsi-torch simulate --out x` hands the shipped
    simulate.yaml (the README's default prototype) to the simulator."""
    import hsi_torch.simulate.capture_sets as cs

    seen = {}

    def fake(cfg, out, **kw):
        seen["cfg"] = cfg
        raise KeyboardInterrupt  # stop before any work

    monkeypatch.setattr(cs, "simulate_capture_set", fake)
    assert main(["simulate", "--out", str(tmp_path / "x")]) == 130
    assert _readme_prototype(seen["cfg"]) == README_PROTOTYPE


def test_opd_and_usaf_prototype_null_is_the_shipped_prototype():
    from hsi_torch.experiments.opd import OPDConfig, _load_prototype
    from hsi_torch.experiments.usaf import USAFConfig, _sim_config

    assert _readme_prototype(_load_prototype(OPDConfig())) == README_PROTOTYPE
    sim = _sim_config(USAFConfig(), calibrated=False)
    # usaf: the same design at full size, with its 10 µm diffuser override (docs/experiments.md)
    assert _readme_prototype(sim) == README_PROTOTYPE[:-1] + (0.01,)
    assert (sim.camera.width_px, sim.camera.height_px) == (2896, 2784)
    for name in ("opd", "usaf"):  # the shipped files leave it null, so a copy works anywhere
        cfg_cls = OPDConfig if name == "opd" else USAFConfig
        assert load_config(shipped_config(name), cfg_cls).prototype is None


def test_real_data_dir_setting_env_and_checkout(monkeypatch, tmp_path):
    monkeypatch.delenv(resources.DATA_ENV, raising=False)
    checkout = resources.source_checkout()
    beside = checkout.parent / "shared" / "data" / "real" if checkout else None
    assert real_data_dir() == (beside if beside is not None and beside.is_dir() else None)
    env_dir = tmp_path / "env"
    (env_dir / "cave_stuffed_toys").mkdir(parents=True)
    monkeypatch.setenv(resources.DATA_ENV, str(env_dir))
    assert real_data_dir() == env_dir
    assert real_data_dir("cave_stuffed_toys") == env_dir / "cave_stuffed_toys"
    assert real_data_dir("raw") is None
    own = tmp_path / "own"
    own.mkdir()
    resources.set_real_data_dir(own)
    try:
        assert real_data_dir() == own  # the setting wins over the environment
    finally:
        resources.set_real_data_dir(None)
    with pytest.raises(FileNotFoundError, match="real-data folder not found"):
        resources.set_real_data_dir(tmp_path / "missing")
    monkeypatch.setenv(resources.DATA_ENV, str(tmp_path / "typo"))
    with pytest.raises(FileNotFoundError, match="HSI_TORCH_DATA=.*no such folder"):
        real_data_dir()


def test_data_dir_option_and_optional_cave_scene(monkeypatch, tmp_path):
    """--data-dir applies to one command and is undone after it; an optional CAVE scene is
    skipped when the real-data folder has no CAVE cube, a required one names the variable."""
    from hsi_torch.simulate.capture_sets import build_scene
    from hsi_torch.simulate.config import SceneSpec

    monkeypatch.setenv(resources.DATA_ENV, str(tmp_path))  # a folder without the CAVE cube
    assert build_scene(SceneSpec("cave", optional=True)) is None
    with pytest.raises(FileNotFoundError, match="HSI_TORCH_DATA"):
        build_scene(SceneSpec("cave"))
    seen = {}
    import hsi_torch.resources as r

    def fake_run_config(args: argparse.Namespace) -> int:
        seen["dir"] = r.real_data_dir()
        return 0

    monkeypatch.setattr(r, "run_config", fake_run_config)
    other = tmp_path / "other"
    other.mkdir()
    assert main(["--data-dir", str(other), "config", "list"]) == 0
    assert seen["dir"] == other
    assert main(["config", "list", "--data-dir", str(other)]) == 0  # after the command too
    assert r.get_real_data_dir_setting() is None and r.real_data_dir() == tmp_path
    assert main(["config", "list", "--data-dir", str(tmp_path / "missing")]) == 1


def test_config_copy_never_writes_through_a_symlink_at_dest(tmp_path, capsys):
    """``config copy simulate my.yaml`` where ``my.yaml`` is a symlink to the lab's own file:
    a dangling link made the copy create (or, with ``--force``, write over) the file it points
    to. Now a link at DEST counts as an existing DEST, and ``--force`` replaces the link itself
    (whole or not at all), never the file it points to."""
    from hsi_torch.cli import main

    theirs = tmp_path / "lab" / "settings.yaml"
    theirs.parent.mkdir()
    dangling = tmp_path / "new.yaml"
    dangling.symlink_to(theirs)
    assert main(["config", "copy", "simulate", str(dangling)]) == 1
    assert "exists; use --force" in capsys.readouterr().err
    assert not theirs.exists()
    theirs.write_text("lab: settings\n")
    link = tmp_path / "my.yaml"
    link.symlink_to(theirs)
    assert main(["config", "copy", "simulate", str(link), "--force"]) == 0
    assert theirs.read_text() == "lab: settings\n"
    assert not link.is_symlink() and "simulate" in link.read_text()
