"""Command-line consistency: global -q/--quiet and --no-progress on every sub-command, progress
bars off when stderr is no terminal, one --out meaning, and every example we show works.

Examples (every `hsi-torch ...` line of each `--help` text and of the README's code blocks):
the cheap ones (`config ...`, `--help`, `--version`) are **run**; every other one is **parsed**
by the real parser (no unknown or missing argument) and its configuration is **loaded and
validated** exactly as the command would (the shipped or given `--config`, every `--set` key and
value against the command's schema) — without running the simulation, calibration or
reconstruction itself. The end-to-end runs of `demo --quick`, `simulate` and
`experiment synthetic` are in tests/test_wheel.py.
"""

from __future__ import annotations

import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from hsi_torch import cli, console
from hsi_torch.config import load_config

REPO = Path(__file__).resolve().parents[1]
COMMANDS = ["simulate", "calibrate", "layout", "reconstruct", "experiment", "demo", "config",
            "captures", "cache", "watch"]
REQUIRED = {
    "simulate": ["--out", "o"],
    "calibrate": ["--captures", "c", "--out", "o"],
    "layout": ["--captures", "c", "--out", "o.json"],
    "reconstruct": ["--bundle", "b.npz", "--out", "o", "x.tif"],
    "experiment": ["synthetic", "--out", "o"],
    "demo": [],
    "config": ["list"],
    "captures": ["check", "d"],
    "cache": ["info"],
    "watch": ["--bundle", "b.npz", "--out", "o", "d"],
}


@pytest.mark.parametrize("command", COMMANDS)
def test_quiet_and_no_progress_on_every_command(command):
    parse = cli.build_parser().parse_args
    rest = REQUIRED[command]
    a = parse([command, *rest])
    assert (a.quiet, a.progress, a.debug) == (False, True, False)
    for argv in (["-q", "--no-progress", command, *rest], [command, *rest, "-q", "--no-progress"],
                 ["--quiet", command, *rest, "--no-progress"]):  # fmt: skip
        a = parse(argv)
        assert a.quiet is True and a.progress is False, argv


def test_progress_bars_only_on_a_terminal(monkeypatch):
    class Tty:
        def __init__(self, tty):
            self.tty = tty

        def isatty(self):
            return self.tty

        def write(self, s):
            return len(s)

        def flush(self):
            pass

    monkeypatch.setattr(sys, "stderr", Tty(False))
    assert not console.progress_enabled(True)
    assert console.progress_bar(range(3), enabled=True).disable  # still iterates
    assert list(console.progress_bar(range(3))) == [0, 1, 2]
    monkeypatch.setattr(sys, "stderr", Tty(True))
    assert console.progress_enabled(True) and not console.progress_enabled(False)
    before = console.configure(progress=False)
    try:
        assert not console.progress_enabled(True)
        console.configure(progress=True, quiet=True)
        assert not console.progress_enabled(True)
    finally:
        console.configure(**before)
    assert console.progress_enabled(True)


def test_quiet_prints_only_errors(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert cli.main(["-q", "config", "copy", "simulate", "a.yaml"]) == 0
    out = capsys.readouterr()
    assert (tmp_path / "a.yaml").is_file() and out.out == "" and out.err == ""
    assert cli.main(["config", "copy", "simulate", "b.yaml"]) == 0
    assert "wrote b.yaml" in capsys.readouterr().out
    assert cli.main(["config", "copy", "simulate", "a.yaml", "--quiet"]) == 1
    assert "exists; use --force" in capsys.readouterr().err  # errors still print
    assert console.settings() == {"quiet": False, "progress": True}  # restored after main()


def test_no_carriage_returns_in_logs(tmp_path):
    """A run whose stderr goes to a file (not a terminal) writes no progress-bar lines."""
    r = subprocess.run(
        [sys.executable, "-m", "hsi_torch", "experiment", "synthetic", "--out", str(tmp_path / "s"),
         "--set", "num_seeds=1", "--set", "noise_sigmas=[1]", "--set", "betas=[100]",
         "--set", "designs=[{kind: three_camera, name: 3Camera}]"],
        capture_output=True, text=True, timeout=300, cwd=tmp_path,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert "\r" not in r.stderr and "it/s" not in r.stderr
    assert "experiment 'synthetic' finished" in r.stdout


# ---------------------------------------------------------------------------------------------
# examples


def _schema_and_default(args):
    if args.command == "simulate":
        from hsi_torch.simulate.config import SimulateConfig

        return SimulateConfig, "simulate"
    if args.command == "calibrate":
        from hsi_torch.calibrate.config import CalibrateConfig

        return CalibrateConfig, "calibrate"
    if args.command == "layout":  # --config is the design: a simulate-style config
        from hsi_torch.simulate.config import SimulateConfig

        return SimulateConfig, "simulate"
    if args.command in ("reconstruct", "watch"):
        from hsi_torch.recon.config import ReconstructConfig

        return ReconstructConfig, "reconstruct"
    if args.command == "demo":
        from hsi_torch.experiments.demo import DemoConfig

        return DemoConfig, None
    if args.command == "experiment":
        from hsi_torch.experiments.cli_entry import resolve_experiment

        return resolve_experiment(args.name)[0], args.name
    return None, None


def check_example(line: str) -> str:
    """Run (cheap) or parse + validate (the rest) one `hsi-torch ...` example; returns which."""
    argv = shlex.split(line, comments=True)
    assert argv[0] == "hsi-torch", line
    argv = argv[1:]
    cheap = ("config", "--help", "-h", "--version")
    if not argv or argv[0] in cheap or "--help" in argv or argv[:2] == ["cache", "info"]:
        assert cli.main(argv) == 0, line
        return "ran"
    parser = cli.build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # unknown / missing argument
        raise AssertionError(f"example does not parse: {line}") from exc
    if args.command in ("bench", "captures", "view", "cache"):  # no config; view needs a display
        return "parsed"
    schema, default = _schema_and_default(args)
    load_config(cli.config_source(args, default), schema, args.overrides)
    return "validated"


def _help_examples() -> list[str]:
    parser = cli.build_parser()
    texts = [parser.format_help()]
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    texts += [p.format_help() for name, p in sub.choices.items() if name != "bench"]
    lines = [ln.strip() for t in texts for ln in t.splitlines()]
    return [ln for ln in lines if ln.startswith("hsi-torch ")]


def _readme_examples() -> list[str]:
    """`hsi-torch` lines of the README's fenced code blocks (continuations joined)."""
    out, block, fence = [], [], None
    for line in (REPO / "README.md").read_text(encoding="utf-8").splitlines():
        if line.startswith("```"):
            if fence is None:
                fence, block = line[3:].strip(), []
                continue
            if fence in ("", "bash", "sh", "console"):
                joined = "\n".join(block).replace("\\\n", " ")
                out += [ln.strip() for ln in joined.splitlines()
                        if ln.strip().startswith("hsi-torch ")]  # fmt: skip
            fence = None
        elif fence is not None:
            block.append(line)
    return out


def test_every_help_text_has_examples():
    ex = _help_examples()
    for command in COMMANDS:
        assert any(e.split()[1] == command for e in ex), command
    assert not any("solver.beta" in e for e in ex)  # the old example every command rejected
    def bare(e):
        return " ".join(shlex.split(e, comments=True))

    assert {bare(e) for e in ex} >= {bare(e) for es in cli.EXAMPLES.values() for e in es}


def test_help_examples_work(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    done = {check_example(e) for e in _help_examples()}
    assert {"ran", "validated"} <= done <= {"ran", "validated", "parsed"}  # parsed: captures, view


def test_readme_command_examples_work(tmp_path, monkeypatch, capsys):
    """The README's `hsi-torch` lines, in order, in one folder (so `config copy` feeds the
    `--config` of the lines after it)."""
    monkeypatch.chdir(tmp_path)
    ex = _readme_examples()
    assert len(ex) >= 12
    kinds = [check_example(e) for e in ex]
    assert "ran" in kinds and "validated" in kinds


def test_a_bad_set_key_fails_the_check(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(Exception, match="solver"):
        check_example("hsi-torch reconstruct --bundle b.npz --out o --set solver.beta=10 x.tif")
    with pytest.raises(AssertionError, match="does not parse"):
        check_example("hsi-torch calibrate --out o")
