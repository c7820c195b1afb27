"""The ``hsi-torch`` command line: one entry point, sub-commands dispatched to the owning modules.

Each sub-command parses its arguments here and then lazily imports and calls
``run_<command>(args: argparse.Namespace)`` in its owning module:

=============  ===============================================  ==============================
command        function called                                  typical use
=============  ===============================================  ==============================
simulate       ``hsi_torch.simulate.cli_entry.run_simulate``    render captures + ground truth
calibrate      ``hsi_torch.calibrate.cli_entry.run_calibrate``  captures → calibration bundle
reconstruct    ``hsi_torch.recon.cli_entry.run_reconstruct``    bundle + captures → cubes
experiment     ``hsi_torch.experiments.cli_entry.run_experiment``  named evaluation
demo           ``hsi_torch.demo.run_demo``                      the README's main command
bench          ``scripts/bench_<target>.py`` via ``runpy``      timings
=============  ===============================================  ==============================

The entry function returns an exit status (``int``), ``None`` (= 0), or a
:class:`hsi_torch.batch.BatchSummary` (its report is printed; status 1 if any input failed).

Exit status: 0 success; 1 an error (any :class:`hsi_torch.errors.HSIError` such as ``ConfigError``
or ``FileFormatError``, a ``ValueError``, an ``OSError`` such as ``FileNotFoundError``, ... printed
as one line on stderr; the traceback only with ``--debug``);
2 usage error or a sub-command whose module is not part of this installation; 130 interrupted.
"""

from __future__ import annotations

import argparse
import importlib
import os
import runpy
import sys
import traceback
from collections.abc import Sequence
from pathlib import Path
from typing import Any

__all__ = ["main", "build_parser", "ENTRY_POINTS", "load_args_config"]

PROG = "hsi-torch"

ENTRY_POINTS: dict[str, tuple[str, str]] = {
    "simulate": ("hsi_torch.simulate.cli_entry", "run_simulate"),
    "calibrate": ("hsi_torch.calibrate.cli_entry", "run_calibrate"),
    "reconstruct": ("hsi_torch.recon.cli_entry", "run_reconstruct"),
    "experiment": ("hsi_torch.experiments.cli_entry", "run_experiment"),
    "demo": ("hsi_torch.demo", "run_demo"),
}
BENCH_TARGETS = ("solver", "pipeline")
_FOLDER_OUT = ("simulate", "reconstruct", "experiment", "demo")  # commands whose --out is a folder


def _version() -> str:
    from hsi_torch import __version__

    return __version__


def _add_common(p: argparse.ArgumentParser, config: bool = True, device: bool = True) -> None:
    if config:
        p.add_argument(
            "--config", "-c", type=Path, default=None, metavar="YAML",
            help="YAML configuration file (default: built-in defaults)",
        )  # fmt: skip
        p.add_argument(
            "--set", "-s", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
            help="override a config key, e.g. --set solver.beta=10 (repeatable; value is YAML)",
        )  # fmt: skip
    if device:
        p.add_argument(
            "--device", default=None, help="torch device, e.g. cpu, cuda, cuda:1 (default: cpu)"
        )
    p.add_argument(
        "--debug", action="store_true", default=argparse.SUPPRESS,
        help="show full tracebacks on errors",
    )  # fmt: skip


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``hsi-torch`` (sub-command stored in ``args.command``)."""
    parser = argparse.ArgumentParser(
        prog=PROG,
        description="Snapshot hyperspectral imaging with a birefringent filter and a tapered "
        "kaleidoscope: simulate, calibrate, reconstruct, evaluate.",
    )
    parser.add_argument("--version", action="version", version=f"{PROG} {_version()}")
    parser.add_argument("--debug", action="store_true", help="show full tracebacks on errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    p = sub.add_parser(
        "simulate", help="render captures and ground truth with the virtual prototype"
    )
    _add_common(p)
    p.add_argument("--out", "-o", type=Path, required=True, help="output folder")

    p = sub.add_parser("calibrate", help="build a calibration bundle from calibration captures")
    _add_common(p)
    p.add_argument("--captures", type=Path, required=True, help="folder of calibration captures")
    p.add_argument("--out", "-o", type=Path, required=True, help="output bundle (.npz)")

    p = sub.add_parser("reconstruct", help="reconstruct spectral cubes from captures")
    _add_common(p)
    p.add_argument("--bundle", "-b", type=Path, required=True, help="calibration bundle (.npz)")
    p.add_argument("--out", "-o", type=Path, required=True, help="output folder")
    p.add_argument(
        "--no-resume", dest="resume", action="store_false",
        help="re-process inputs whose outputs already exist",
    )  # fmt: skip
    p.add_argument(
        "--no-progress", dest="progress", action="store_false", help="hide the progress bar"
    )
    p.add_argument("inputs", nargs="+", metavar="INPUT", help="capture files or glob patterns")

    p = sub.add_parser("experiment", help="run a named experiment (synthetic, opd, usaf, design)")
    p.add_argument("name", metavar="NAME", help="experiment name")
    _add_common(p)
    p.add_argument("--out", "-o", type=Path, required=True, help="output folder")

    p = sub.add_parser("demo", help="simulate, calibrate and reconstruct end to end")
    _add_common(p)
    p.add_argument("--out", "-o", type=Path, default=Path("demo_output"), help="output folder")
    p.add_argument("--quick", action="store_true", help="smaller, faster run")

    p = sub.add_parser(
        "bench", help="timing benchmarks (extra arguments go to the script)", add_help=False,
        description="Runs scripts/bench_<target>.py; unknown arguments are passed to it. "
        "'hsi-torch bench <target> --help' lists the script's own options.",
    )  # fmt: skip
    p.add_argument(
        "target", nargs="?", choices=BENCH_TARGETS, default=None,
        help="benchmark to run (default: pipeline)",
    )  # fmt: skip
    p.add_argument(
        "-h", "--help", dest="bench_help", action="store_true",
        help="show this help (after a target: the benchmark script's options)",
    )  # fmt: skip
    p.add_argument(
        "--debug", action="store_true", default=argparse.SUPPRESS, help=argparse.SUPPRESS
    )
    p.set_defaults(_bench_parser=p)  # printed by main() for a bare "bench --help"
    return parser


def load_args_config(args: argparse.Namespace, schema_cls: type) -> Any:
    """Convenience for entry functions: ``load_config(args.config, schema_cls, args.overrides)``."""
    from hsi_torch.config import load_config

    return load_config(getattr(args, "config", None), schema_cls, getattr(args, "overrides", []))


def _err(msg: str) -> None:
    print(f"{PROG}: error: {msg}", file=sys.stderr)


def _exit_code(result: Any) -> int:
    from hsi_torch.batch import BatchSummary, print_summary

    if result is None:
        return 0
    if isinstance(result, BatchSummary):
        print_summary(result)
        return result.exit_code
    if isinstance(result, bool):
        return 0 if result else 1
    if isinstance(result, int):
        return result
    return 0


def _missing_module(exc: ModuleNotFoundError, modname: str) -> bool:
    """True when ``exc`` is about ``modname`` itself (or one of its hsi_torch parents)."""
    name = exc.name or ""
    return name.startswith("hsi_torch") and (modname == name or modname.startswith(name + "."))


def _run_entry(args: argparse.Namespace) -> int:
    modname, funcname = ENTRY_POINTS[args.command]
    try:
        module = importlib.import_module(modname)
    except ModuleNotFoundError as exc:
        if not _missing_module(exc, modname):
            raise
        _err(f"'{args.command}' is not available in this installation (module {modname} not found)")
        return 2
    func = getattr(module, funcname, None)
    if not callable(func):
        _err(f"'{args.command}' is not available: {modname} has no function {funcname}()")
        return 2
    return _exit_code(func(args))


def _check_device(name: str) -> None:
    """Refuse an unknown or unavailable ``--device`` before any work (or output) starts."""
    import torch

    try:
        dev = torch.device(name)
    except (RuntimeError, ValueError) as exc:
        raise ValueError(f"--device {name!r}: not a torch device ({_one_line(exc)})") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"--device {name!r}: CUDA is not available on this machine/torch build")
    if dev.type == "cuda" and dev.index is not None and dev.index >= torch.cuda.device_count():
        raise ValueError(
            f"--device {name!r}: this machine has {torch.cuda.device_count()} CUDA device(s)"
        )
    if dev.type == "mps" and not torch.backends.mps.is_available():
        raise ValueError(f"--device {name!r}: MPS is not available on this machine/torch build")


def _is_missing_cuda(exc: BaseException) -> bool:
    """torch's own error for a CUDA device it does not have (e.g. a config key ``device: cuda``)."""
    if not isinstance(exc, (AssertionError, RuntimeError)) or "CUDA" not in str(exc):
        return False
    import torch

    return not torch.cuda.is_available()


def _scripts_dir() -> Path:
    return Path(__file__).resolve().parents[1] / "scripts"


def _run_bench(args: argparse.Namespace, extra: list[str]) -> int:
    script = _scripts_dir() / f"bench_{args.target}.py"
    if not script.is_file():
        _err(f"benchmark '{args.target}' is not available ({script} not found; benchmarks run "
             "from a source checkout)")  # fmt: skip
        return 2
    old_argv = sys.argv
    sys.argv = [str(script), *extra]
    try:
        runpy.run_path(str(script), run_name="__main__")
    except SystemExit as exc:
        code = exc.code
        if code is None:
            return 0
        if isinstance(code, int):
            return code
        print(code, file=sys.stderr)
        return 1
    finally:
        sys.argv = old_argv
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit status (never raises ``SystemExit``)."""
    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        args, extra = parser.parse_known_args(argv)
        if extra and args.command != "bench":
            parser.error(f"unrecognized arguments: {' '.join(extra)}")
    except SystemExit as exc:  # --help, --version, usage errors
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    if args.command is None:
        parser.print_help(sys.stderr)
        return 2
    debug = bool(getattr(args, "debug", False)) or os.environ.get("HSI_TORCH_DEBUG") == "1"
    args.debug = debug
    created: list[Path] = []  # an --out folder this command creates
    rc = 1
    try:
        rc = _dispatch(args, extra, debug, created)
    finally:
        if rc != 0 and created:  # a failed command leaves no empty folder behind
            _remove_if_empty(created[0])
    return rc


def _remove_if_empty(folder: Path) -> None:
    """Remove ``folder`` and its sub-folders if no file is in any of them."""
    if not folder.is_dir() or any(p.is_file() or p.is_symlink() for p in folder.rglob("*")):
        return
    for d in sorted((p for p in folder.rglob("*") if p.is_dir()), key=lambda p: -len(p.parts)):
        d.rmdir()
    folder.rmdir()


def _dispatch(
    args: argparse.Namespace, extra: list[str], debug: bool, created: list[Path]
) -> int:
    """Run the sub-command; every error becomes one line on stderr and an exit status."""
    from hsi_torch.config import ConfigError
    from hsi_torch.errors import HSIError

    try:
        if args.command == "bench":
            if extra[:1] == ["--"]:
                extra = extra[1:]
            if args.bench_help:
                if args.target is None:  # 'hsi-torch bench --help': this command's own help
                    args._bench_parser.print_help()
                    return 0
                extra = ["--help", *extra]  # 'hsi-torch bench solver --help': the script's
            if args.target is None:
                args.target = "pipeline"
            return _run_bench(args, extra)
        if getattr(args, "device", None):
            _check_device(args.device)
        out = getattr(args, "out", None)
        if args.command in _FOLDER_OUT and out is not None:
            from hsi_torch.batch import check_out_dir

            check_out_dir(out)
            if not Path(out).exists():  # a folder that existed before is never removed
                created.append(Path(out))
        return _run_entry(args)
    except KeyboardInterrupt:
        _err("interrupted")
        return 130
    except (HSIError, ConfigError, ValueError, OSError) as exc:
        if debug:
            traceback.print_exc()
        _err(_one_line(exc))
        return 1
    except Exception as exc:  # noqa: BLE001 - unexpected: still one line unless --debug
        if _is_missing_cuda(exc):  # a user error (config key 'device'), not a bug
            if debug:
                traceback.print_exc()
            _err(f"a CUDA device was requested (--device or config key 'device') but CUDA is not "
                 f"available ({_one_line(exc)})")  # fmt: skip
            return 1
        if debug:
            traceback.print_exc()
            _err(_one_line(exc))
        else:
            _err(f"{_one_line(exc)} (unexpected error; run with --debug for the traceback)")
        return 1


def _one_line(exc: BaseException) -> str:
    text = str(exc) or type(exc).__name__
    if isinstance(exc, OSError) and exc.filename and str(exc.filename) not in text:
        text = f"{text}: {exc.filename}"
    from hsi_torch.errors import HSIError

    plain = isinstance(exc, (HSIError, OSError)) or type(exc) is ValueError
    if not plain:
        text = f"{type(exc).__name__}: {text}"
    return " | ".join(line.strip() for line in text.splitlines() if line.strip())


if __name__ == "__main__":
    sys.exit(main())
