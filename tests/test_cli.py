"""Tests of the `hsi-torch` command line: argument parsing, dispatch, exit codes, error lines."""

from __future__ import annotations

import subprocess
import sys
import types
from dataclasses import dataclass
from pathlib import Path

import pytest
import torch
from test_batch import run_batch

import hsi_torch
from hsi_torch import cli
from hsi_torch.config import ConfigError, write_resolved_config


@dataclass
class SimCfg:
    size: int = 8
    beta: float = 1.0


def _fake_module(monkeypatch, command: str, func) -> types.ModuleType:
    modname, funcname = cli.ENTRY_POINTS[command]
    mod = types.ModuleType(modname)
    setattr(mod, funcname, func)
    monkeypatch.setitem(sys.modules, modname, mod)
    return mod


def test_version_and_help(capsys):
    assert cli.main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"hsi-torch {hsi_torch.__version__}"
    assert cli.main([]) == 2  # no sub-command: help on stderr
    assert "simulate" in capsys.readouterr().err
    assert cli.main(["frobnicate"]) == 2
    assert cli.main(["simulate"]) == 2  # --out is required
    assert "--out" in capsys.readouterr().err
    assert cli.main(["simulate", "--out", "x", "--bogus"]) == 2
    assert "unrecognized arguments: --bogus" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("argv", "command", "expected"),
    [
        (["simulate", "--config", "c.yaml", "--out", "o", "--set", "a.b=1", "-s", "c=2"],
         "simulate",
         {"config": Path("c.yaml"), "out": Path("o"), "overrides": ["a.b=1", "c=2"],
          "device": None, "debug": False}),
        (["calibrate", "--captures", "caps", "--out", "b.npz", "--device", "cuda"],
         "calibrate",
         {"captures": Path("caps"), "out": Path("b.npz"), "config": None, "device": "cuda"}),
        (["reconstruct", "--bundle", "b.npz", "--out", "o", "x.tif", "y*.tif"],
         "reconstruct",
         {"bundle": Path("b.npz"), "inputs": ["x.tif", "y*.tif"], "resume": True,
          "progress": True}),
        (["reconstruct", "-b", "b.npz", "-o", "o", "--no-resume", "--no-progress",
          "--config", "r.yaml", "a.tif"],
         "reconstruct", {"resume": False, "progress": False, "config": Path("r.yaml")}),
        (["experiment", "synthetic", "--config", "e.yaml", "--out", "o"],
         "experiment", {"name": "synthetic", "config": Path("e.yaml")}),
        (["demo"], "demo", {"out": Path("demo_output"), "quick": False}),
        (["--debug", "demo", "--quick", "--out", "d"], "demo",
         {"out": Path("d"), "quick": True, "debug": True}),
        (["demo", "--debug"], "demo", {"debug": True}),
    ],
)  # fmt: skip
def test_dispatch_passes_parsed_args(monkeypatch, argv, command, expected):
    seen = {}

    def entry(args):
        seen["args"] = args
        return 0

    _fake_module(monkeypatch, command, entry)
    # main() refuses an unavailable --device up front; pretend one GPU exists for "--device cuda"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    assert cli.main(argv) == 0
    args = seen["args"]
    assert args.command == command
    for key, value in expected.items():
        assert getattr(args, key) == value, key


def test_entry_return_values(monkeypatch, tmp_path, capsys):
    _fake_module(monkeypatch, "simulate", lambda args: None)
    assert cli.main(["simulate", "--out", "o"]) == 0
    _fake_module(monkeypatch, "simulate", lambda args: 3)
    assert cli.main(["simulate", "--out", "o"]) == 3

    # reconstruct returning a BatchSummary with a failure: every failure printed, exit 1
    good = tmp_path / "good.tif"
    good.write_text("ok")

    def recon(args):
        def process(p):
            if p.name != "good.tif":
                raise ValueError(f"{p}: corrupt")
            return None

        return run_batch(args.inputs, process, args.out, progress=False)

    _fake_module(monkeypatch, "reconstruct", recon)
    rc = cli.main(["reconstruct", "-b", "b.npz", "-o", str(tmp_path / "o"), str(good),
                   str(tmp_path / "gone.tif"), str(tmp_path / "zz.tif")])  # fmt: skip
    err = capsys.readouterr().err
    assert rc == 1
    assert "3 input(s): 1 processed" in err
    assert f"FAILED {tmp_path / 'gone.tif'}: FileNotFoundError" in err
    assert f"FAILED {tmp_path / 'zz.tif'}: FileNotFoundError" in err
    # a glob that matches nothing is a clean one-line error
    rc = cli.main(["reconstruct", "-b", "b.npz", "-o", str(tmp_path / "o"), str(tmp_path / "*.x")])
    err = capsys.readouterr().err
    assert rc == 1 and "matches no files" in err and "Traceback" not in err


@pytest.mark.parametrize(
    ("exc", "text"),
    [
        (ConfigError("unknown key (did you mean 'beta'?)", "betta", "c.yaml"),
         "hsi-torch: error: c.yaml: key 'betta': unknown key (did you mean 'beta'?)"),
        (ValueError("x.tif: image size (4, 4) does not match (8, 8)"),
         "hsi-torch: error: x.tif: image size (4, 4) does not match (8, 8)"),
        (FileNotFoundError("bundle not found: b.npz"), "hsi-torch: error: bundle not found: b.npz"),
        (RuntimeError("solver diverged"),
         "hsi-torch: error: RuntimeError: solver diverged (unexpected error; run with --debug"),
    ],
)  # fmt: skip
def test_errors_are_one_clean_line(monkeypatch, capsys, exc, text):
    def entry(args):
        raise exc

    _fake_module(monkeypatch, "calibrate", entry)
    assert cli.main(["calibrate", "--captures", "c", "--out", "b.npz"]) == 1
    err = capsys.readouterr().err
    assert err.startswith(text) and len(err.strip().splitlines()) == 1
    assert "Traceback" not in err
    # --debug adds the traceback
    assert cli.main(["--debug", "calibrate", "--captures", "c", "--out", "b.npz"]) == 1
    err = capsys.readouterr().err
    assert "Traceback" in err and text.split(" (unexpected")[0] in err


def test_config_typo_through_entry(monkeypatch, tmp_path, capsys):
    cfg = tmp_path / "sim.yaml"
    cfg.write_text("size: 16\nbetta: 3\n")

    def run_simulate(args):
        c = cli.load_args_config(args, SimCfg)
        write_resolved_config(c, args.out)
        return 0

    _fake_module(monkeypatch, "simulate", run_simulate)
    rc = cli.main(["simulate", "--config", str(cfg), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 1
    assert f"{cfg}: key 'betta': unknown key (did you mean 'beta'?)" in err
    cfg.write_text("size: 16\n")
    rc = cli.main(["simulate", "-c", str(cfg), "-o", str(tmp_path / "o"), "--set", "beta=1e-2"])
    assert rc == 0
    assert "beta: 0.01" in (tmp_path / "o" / "resolved_config.yaml").read_text()


def test_missing_modules(monkeypatch, capsys):
    monkeypatch.setitem(cli.ENTRY_POINTS, "simulate", ("hsi_torch.no_such_pkg.cli_entry", "run"))
    assert cli.main(["simulate", "--out", "o"]) == 2
    err = capsys.readouterr().err
    assert "'simulate' is not available" in err and "hsi_torch.no_such_pkg.cli_entry" in err
    # a module that exists but lacks the function
    mod = types.ModuleType("hsi_torch._fake_entry")
    monkeypatch.setitem(sys.modules, "hsi_torch._fake_entry", mod)
    monkeypatch.setitem(cli.ENTRY_POINTS, "simulate", ("hsi_torch._fake_entry", "run_simulate"))
    assert cli.main(["simulate", "--out", "o"]) == 2
    assert "has no function run_simulate()" in capsys.readouterr().err

    # a missing *third-party* dependency inside an existing module is a real error (exit 1)
    def entry(args):
        raise ModuleNotFoundError("No module named 'notapkg'", name="notapkg")

    _fake_module(monkeypatch, "demo", entry)
    assert cli.main(["demo"]) == 1
    assert "notapkg" in capsys.readouterr().err


def test_bench_runs_script(monkeypatch, tmp_path, capsys):
    scripts = tmp_path / "scripts"
    scripts.mkdir()
    (scripts / "bench_solver.py").write_text(
        "import sys\nprint('ARGS', sys.argv[1:])\n"
        "sys.exit(int(sys.argv[-1]) if sys.argv[1:] else 0)\n"
    )
    monkeypatch.setattr(cli, "_scripts_dir", lambda: scripts)
    argv_before = list(sys.argv)
    assert cli.main(["bench", "solver", "--pixels", "1000", "0"]) == 0
    assert "ARGS ['--pixels', '1000', '0']" in capsys.readouterr().out
    assert cli.main(["bench", "solver", "--", "--n", "4"]) == 4  # exit status propagates
    assert sys.argv == argv_before
    assert cli.main(["bench", "pipeline"]) == 2  # script absent
    assert "benchmark 'pipeline' is not available" in capsys.readouterr().err


def test_console_entry_point_subprocess():
    r = subprocess.run(
        [sys.executable, "-m", "hsi_torch.cli", "--version"],
        capture_output=True, text=True, cwd=Path(__file__).resolve().parents[1], timeout=60,
    )  # fmt: skip
    assert r.returncode == 0 and r.stdout.strip() == f"hsi-torch {hsi_torch.__version__}"
