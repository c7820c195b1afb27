"""The ``hsi-torch`` command line: one entry point, sub-commands dispatched to the owning modules.

Each sub-command parses its arguments here and then lazily imports and calls
``run_<command>(args: argparse.Namespace)`` in its owning module (:data:`ENTRY_POINTS`: command →
module and function; ``bench`` runs ``scripts/bench_<target>.py`` through ``runpy``).

Without ``--config`` a command runs with its shipped configuration file
(``configs/<command>.yaml``, ``<NAME>.yaml`` for ``experiment NAME``; see
:func:`hsi_torch.cli_common.config_source`, re-exported here with :func:`load_args_config`: the
entry functions import them from :mod:`hsi_torch.cli_common`, and nothing in the package imports
this module). ``--data-dir DIR`` (any position) names the real-data folder
(:func:`hsi_torch.resources.set_real_data_dir`; default ``HSI_TORCH_DATA``); ``-q/--quiet``
(only warnings and errors) and ``--no-progress`` (no bars) likewise, through
:mod:`hsi_torch.console` (bars are also off whenever stderr is not a terminal). Every ``--out``
is a folder (``calibrate --out FILE.npz`` also names the bundle file directly).

The entry function returns an exit status (``int``), ``None`` (= 0), or a
:class:`hsi_torch.recon.batch.driver.RunSummary` (its report is printed; status 1 if any input
failed).

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

from hsi_torch.cli_common import config_source, load_args_config
from hsi_torch.provenance import command_line, package_version

__all__ = ["main", "build_parser", "ENTRY_POINTS", "load_args_config", "config_source"]

PROG = "hsi-torch"

ENTRY_POINTS: dict[str, tuple[str, str]] = {
    "simulate": ("hsi_torch.simulate.cli_entry", "run_simulate"),
    "calibrate": ("hsi_torch.calibrate.cli_entry", "run_calibrate"),
    "layout": ("hsi_torch.calibrate.cli_entry", "run_layout"),
    "reconstruct": ("hsi_torch.recon.cli_entry", "run_reconstruct"),
    "watch": ("hsi_torch.recon.cli_entry", "run_watch"),
    "experiment": ("hsi_torch.experiments.cli_entry", "run_experiment"),
    "demo": ("hsi_torch.experiments.cli_entry", "run_demo"),
    "config": ("hsi_torch.resources", "run_config"),
    "captures": ("hsi_torch.io.capture_import", "run_captures"),
    "view": ("hsi_torch.viewer.cli_entry", "run_view"),
    "cache": ("hsi_torch.recon.precompute_cache", "run_cache"),
}
BENCH_TARGETS = ("solver", "pipeline", "simulate")
#: commands whose --out is always a folder (calibrate's is a folder unless it ends in .npz)
_FOLDER_OUT = ("simulate", "reconstruct", "experiment", "demo", "watch")


#: Examples shown by each command's ``--help`` (a test parses every one, validates its config
#: and ``--set`` keys, and runs the cheap ones).
EXAMPLES: dict[str | None, list[str]] = {
    None: [
        "hsi-torch demo --quick                 # simulate -> calibrate -> reconstruct, scored",
        "hsi-torch simulate --out sim/",
        "hsi-torch calibrate --captures sim/ --out calib/",
        "hsi-torch reconstruct --bundle calib/calib.npz --out cubes/ sim/scenes/colorchecker.tif",
    ],
    "simulate": [
        "hsi-torch simulate --out sim/                  # the README's default prototype",
        "hsi-torch simulate --out sim/ --set camera.scale=0.5 --set render.dtype=float32",
        "hsi-torch simulate --config simulate_full --out sim_full/   # original scale, minutes",
    ],
    "calibrate": [
        "hsi-torch calibrate --captures sim/ --out calib/           # writes calib/calib.npz",
        "hsi-torch calibrate --captures sim/ --out calib/ --set response.beta_phi=1e3",
        "hsi-torch calibrate --captures sim/ --out bundles/day1.npz  # a file name works too",
        "hsi-torch calibrate --oracle --captures sim/ --out oracle.npz  # the simulator's truth",
    ],
    "layout": [
        "hsi-torch layout --captures lab/ --out lab/nominal_layout.json   # + _overlay.png",
        "hsi-torch layout --white w1.dng w2.dng --grid g1.dng g2.dng --dark d.dng "
        "--set camera.focal_length_mm=35.5 --out layout/   # the design, adjusted",
        "hsi-torch layout --captures sim/ --config simulate_full --out full_layout.json",
    ],
    "reconstruct": [
        "hsi-torch reconstruct --bundle calib/calib.npz --out cubes/ 'shots/*.tif' extra.dng",
        "hsi-torch reconstruct --bundle calib/calib.npz --out cubes/ --set beta=1000 "
        "--set 'formats=[tiff, envi, netcdf]' scene.tif",
        "hsi-torch reconstruct --bundle calib/calib.npz --out cubes/ --scheduler local:2 "
        "'shots/*.tif'",
        "hsi-torch reconstruct --bundle calib/calib.npz --out run1/ --format zarr "
        "--scheduler tcp://head:8786 'shots/*.dng'",
        "hsi-torch reconstruct --bundle calib/calib.npz --out seq/ --sequence 'burst/*.dng'"
        "   # seq/sequence.zarr + sequence_preview.gif",
        "hsi-torch reconstruct --bundle calib/calib.npz --out seq/ burst/   # a folder: a sequence",
    ],
    "watch": [
        "hsi-torch watch --bundle calib/calib.npz --out live/ tether/   # Ctrl-C stops",
        "hsi-torch watch --bundle calib/calib.npz --out live/ --idle-timeout 60 tether/",
    ],
    "experiment": [
        "hsi-torch experiment synthetic --out out/synthetic",
        "hsi-torch experiment synthetic --out out/quick --set num_seeds=1 --set 'noise_sigmas=[1]'",
        "hsi-torch experiment usaf --out out/usaf --set bundle=calibrated",
        "hsi-torch experiment mismatch --out out/mismatch --set 'effects=[stray_light]'",
    ],
    "demo": [
        "hsi-torch demo --quick --out demo_quick/",
        "hsi-torch demo --set beta=1e3 --no-progress",
        "hsi-torch demo --full --out demo_full/   # original scale, each stage timed",
    ],
    "captures": [
        "hsi-torch captures import --sheet lab/captures.csv --layout lab/nominal_layout.json "
        "--out capset/",
        "hsi-torch captures import --scan 'mono/*_{nm}nm.dng' --white 'flat/*.dng' "
        "--grid 'dots/*.png' --dark 'dark/*.dng' --scene 'shots/*.dng' --out capset/",
        "hsi-torch captures check capset/    # what calibration will use, file by file",
    ],
    "config": [
        "hsi-torch config list",
        "hsi-torch config show simulate",
        "hsi-torch config copy simulate my_sim.yaml    # then: --config my_sim.yaml",
    ],
    "view": [
        "hsi-torch view cubes/scene.tif                # band stack (nm) + sRGB, click: spectra",
        "hsi-torch view demo_output/colorchecker.npz --point 40,52 "
        "--band 550 --screenshot shot.png",
    ],
    "cache": [
        "hsi-torch cache info      # where, the entries, their size, the bound",
        "hsi-torch cache clear     # remove the entries (recomputed when next needed)",
    ],
}


def _epilog(command: str | None) -> str:
    return "examples:\n" + "\n".join(f"  {e}" for e in EXAMPLES[command])


def _add_common(p: argparse.ArgumentParser, config: bool = True, device: bool = True) -> None:
    if config:
        p.add_argument(
            "--config", "-c", type=Path, default=None, metavar="YAML",
            help="YAML configuration file, or the name of a shipped one (default: the "
                 "command's shipped file; see 'hsi-torch config list')")  # fmt: skip
        p.add_argument(
            "--set", "-s", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
            help="override a config key (repeatable; the value is YAML; see the examples)",
        )  # fmt: skip
    if device:
        p.add_argument(
            "--device", default=None, help="torch device, e.g. cpu, cuda, cuda:1 (default: cpu)")
    _add_global(p, argparse.SUPPRESS)


def _add_global(p: argparse.ArgumentParser, default: Any) -> None:
    """Options accepted before and after the sub-command (``default=SUPPRESS`` on the
    sub-parsers, so that they do not overwrite a value given before the sub-command)."""
    p.add_argument(
        "-q", "--quiet", action="store_true", default=default,
        help="print only warnings and errors (no progress bars, no reports)")  # fmt: skip
    p.add_argument(
        "--no-progress", dest="progress", action="store_false", default=default,
        help="no progress bars (they are also off when stderr is not a terminal)")  # fmt: skip
    p.add_argument(
        "--debug", action="store_true", default=default, help="show full tracebacks on errors")
    p.add_argument(
        "--data-dir", type=Path, default=default, metavar="DIR",
        help="real-data folder (CAVE scene, real RAW files, ...; default: $HSI_TORCH_DATA, else "
             "../shared/data/real beside a source checkout)")  # fmt: skip


def _add_cluster_options(p: argparse.ArgumentParser) -> None:
    """``reconstruct``'s options for a run on a Dask cluster and for the dataset store."""
    g = p.add_argument_group(
        "many captures (Dask cluster, dataset store; pip install 'hsi-torch[cluster]')")
    where = g.add_mutually_exclusive_group()
    where.add_argument(
        "--scheduler", metavar="SPEC", default=None,
        help="reconstruct on Dask workers: local:N (N worker processes on this machine, started "
             "and stopped by the command, on 127.0.0.1) or a running scheduler's address, "
             "tls://host:8786 (with --tls-*) or tcp://host:8786 (trusted networks only: a "
             "scheduler can run code in this process)")  # fmt: skip
    where.add_argument(
        "--scheduler-file", type=Path, default=None, metavar="FILE",
        help="the scheduler's address from the file it wrote (dask scheduler "
             "--scheduler-file, dask-mpi, ...)")  # fmt: skip
    for opt, what in (("--tls-ca-file", "the certificate authority that signed the cluster's "
                                        "certificates (PEM)"),
                      ("--tls-cert", "this client's certificate (PEM; may hold the key too)"),
                      ("--tls-key", "this client's private key (PEM)")):
        g.add_argument(opt, type=Path, default=None, metavar="FILE",
                       help=f"for a tls:// scheduler: {what}")  # fmt: skip
    g.add_argument(
        "--threads-per-worker", type=int, default=None, metavar="K",
        help="torch and numba threads per frame in each worker (default: cores / N for "
             "local:N, else the worker's own thread count)")  # fmt: skip
    g.add_argument(
        "--send-bundle", action="store_true",
        help="send the bundle's bytes to the workers instead of its path (workers that do "
             "not see this file system)")  # fmt: skip
    g.add_argument(
        "--format", choices=("files", "zarr"), default="files",
        help="files: the configured cube files per input (default); zarr: one chunked Zarr "
             "store OUT/cubes.zarr for the whole run (one frame per input, opens with "
             "xarray.open_zarr; no previews)")  # fmt: skip


def _add_sequence_options(p: argparse.ArgumentParser, watch: bool) -> None:
    """``reconstruct``'s sequence options, and ``watch``'s (hsi_torch.io.sequence)."""
    g = p.add_argument_group("sequences (moving scenes; pip install 'hsi-torch[cluster]')")
    if not watch:
        g.add_argument("--sequence", action="store_true",
                       help="the inputs are one sequence in time order: write OUT/sequence.zarr "
                            "(time axis) and OUT/sequence_preview.gif; a folder, a sheet or a "
                            "multi-page TIFF is a sequence without it")  # fmt: skip
    g.add_argument("--time-from", default="auto",
                   choices=("auto", "name", "exif", "mtime") if watch else
                   ("auto", "sheet", "name", "exif", "index", "mtime"),
                   help="each frame's time: its name (t=12.5s, 20261207-130500.250), EXIF "
                        "DateTimeOriginal+SubSecTimeOriginal, " + (
                            "or the file's modification time (auto: in that order)" if watch
                            else "a sheet's column, the frame index, or the modification "
                                 "time (auto: sheet, name, EXIF, index)"))  # fmt: skip
    if not watch:
        g.add_argument("--frame-interval", type=float, default=None, metavar="S",
                       help="seconds between frames timed by their index (default 1)")
        return
    g.add_argument("--max-frames", type=int, default=None, metavar="N",
                   help="stop after N frames")
    g.add_argument("--idle-timeout", type=float, default=None, metavar="S",
                   help="stop when no new file arrived for S seconds (default: never)")
    g.add_argument("--settle", type=float, default=1.0, metavar="S",
                   help="a file is complete when unchanged for S seconds and whole by its own "
                        "structure (default 1)")  # fmt: skip


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``hsi-torch`` (sub-command stored in ``args.command``)."""
    raw = argparse.RawDescriptionHelpFormatter
    parser = argparse.ArgumentParser(
        prog=PROG,
        description="Snapshot hyperspectral imaging with a birefringent filter and a tapered "
        "kaleidoscope: simulate, calibrate, reconstruct, evaluate.",
        epilog=_epilog(None), formatter_class=raw)  # fmt: skip
    parser.add_argument("--version", action="version", version=f"{PROG} {package_version()}")
    _add_global(parser, None)
    parser.set_defaults(debug=False, quiet=False, progress=True)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    def command(name: str, help_text: str, **kw: Any) -> argparse.ArgumentParser:
        return sub.add_parser(name, help=help_text, epilog=_epilog(name), formatter_class=raw,
                              **kw)  # fmt: skip

    p = command("simulate", "render captures and ground truth with the virtual prototype")
    _add_common(p)
    p.add_argument("--out", "-o", type=Path, required=True,
                   help="output folder (new or empty, unless --overwrite)")
    p.add_argument(
        "--overwrite", action="store_true",
        help="replace the files of a non-empty --out (the new set is written completely "
             "first, then moved into place)")  # fmt: skip

    p = command("calibrate", "build a calibration bundle from calibration captures")
    _add_common(p)
    p.add_argument("--captures", type=Path, required=True, help="folder of calibration captures")
    p.add_argument(
        "--oracle", action="store_true",
        help="build the bundle from a simulated capture set's ground truth (true B, phi, g, "
             "homographies, masks) instead of calibrating: reconstructing with both measures "
             "what calibration costs")  # fmt: skip
    p.add_argument(
        "--out", "-o", type=Path, required=True,
        help="output folder (writes calib.npz, calib.report.json, calib_diagnostics.png and "
             "resolved_config.yaml there); a name ending in .npz is the bundle file itself",
    )  # fmt: skip

    p = command(
        "layout", "propose nominal_layout.json: the design's ray trace fitted to a white shot",
        description="Fits the design's view layout (the ray trace of --config, a simulate-style\n"
        "config: its geometry and camera; default the shipped simulate.yaml) to the white\n"
        "shot by a similarity (scale, rotation, shift of the optical axis), checks every\n"
        "view's parity on the circle-grid shots and writes nominal_layout.json with an\n"
        "overlay PNG to check by eye (see docs/calibration.md). Refused (exit 1, nothing\n"
        "written) when the white shot's edges do not single out the fit (--min-edge-contrast)\n"
        "or the grid shots decide no view's parity.")  # fmt: skip
    _add_common(p, device=False)
    p.add_argument("--captures", type=Path, default=None,
                   help="capture folder: its white/, grid/ and dark/ shots (or manifest)")
    p.add_argument("--white", nargs="+", metavar="FILE", help="white shot(s)")
    p.add_argument("--grid", nargs="+", metavar="FILE", help="circle-grid shot(s) (parity)")
    p.add_argument("--dark", nargs="+", metavar="FILE", help="dark frame(s)")
    p.add_argument("--calib-config", type=Path, default=None, metavar="YAML",
                   help="calibrate config for reading and grid detection (default: shipped)")
    p.add_argument("--force", action="store_true", help="replace an existing layout/overlay")
    p.add_argument("--min-edge-contrast", type=float, default=None, metavar="X",
                   help="refuse a fit whose edges are less than X times stronger on the white "
                        "shot than off the fit (default 2; a device's white gives 3 or more)")
    p.add_argument(
        "--out", "-o", type=Path, required=True,
        help="the layout file (NAME.json; the overlay is NAME_overlay.png beside it) or a "
             "folder (nominal_layout.json + nominal_layout_overlay.png)")  # fmt: skip

    p = command("reconstruct", "reconstruct spectral cubes from captures")
    _add_common(p)
    p.add_argument("--bundle", "-b", type=Path, required=True, help="calibration bundle (.npz)")
    p.add_argument("--out", "-o", type=Path, required=True, help="output folder")
    p.add_argument(
        "--no-resume", dest="resume", action="store_false",
        help="re-process inputs whose outputs already exist")  # fmt: skip
    p.add_argument("--strict", action="store_true",
                   help="every warning about a frame refuses it: no cube, the run exits 1 "
                        "(the setting strict)")  # fmt: skip
    _add_cluster_options(p)
    _add_sequence_options(p, watch=False)
    p.add_argument("inputs", nargs="+", metavar="INPUT",
                   help="capture files or glob patterns; a folder, a sheet (.csv) or a "
                        "multi-page TIFF is a sequence (see --sequence)")  # fmt: skip

    p = command("watch", "reconstruct each capture as it is written into a folder")
    _add_common(p)
    p.add_argument("--bundle", "-b", type=Path, required=True, help="calibration bundle (.npz)")
    p.add_argument("--out", "-o", type=Path, required=True,
                   help="output folder: OUT/sequence.zarr (resumable by reconstruct "
                        "--sequence), OUT/latest_preview.png, OUT/sequence_preview.gif")
    _add_sequence_options(p, watch=True)
    p.add_argument("folder", type=Path, metavar="FOLDER",
                   help="the folder the camera's tethering software writes into")  # fmt: skip

    p = command("experiment",
                "run a named experiment (synthetic, design, opd, usaf, spatial, mismatch)")
    p.add_argument("name", metavar="NAME",
                   help="experiment name: synthetic, design, opd, usaf, spatial or mismatch")
    _add_common(p)
    p.add_argument("--out", "-o", type=Path, required=True, help="output folder")

    p = command("demo", "simulate, calibrate and reconstruct end to end")
    _add_common(p)
    p.add_argument("--out", "-o", type=Path, default=Path("demo_output"), help="output folder")
    p.add_argument("--quick", action="store_true", help="smaller, faster run")
    p.add_argument(
        "--full", action="store_true",
        help="the original prototype's size (simulate_full.yaml): every stage in its own "
             "process, timed, peak memory measured; a few minutes")  # fmt: skip

    p = command("captures", "build a capture set from a lab's photos (import), or check one")
    cap = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    q = cap.add_parser("import", help="sheet (CSV) or name patterns -> CAPSET/manifest.json")
    q.add_argument("--sheet", type=Path, help="CSV: file,role[,wavelength_nm,exposure_s,...]")
    for role in ("scan", "white", "grid", "dark", "scene"):
        q.add_argument(f"--{role}", action="append", default=[], metavar="PATTERN",
                       help=f"{role} files (glob; repeatable" + ("; {nm} = the wavelength)"
                                                                 if role == "scan" else ")"))
    q.add_argument("--layout", type=Path, help="nominal_layout.json (copied into the set)")
    q.add_argument("--copy", action="store_true", help="copy the files (default: reference)")
    q.add_argument("--out", "-o", type=Path, required=True, help="the capture-set folder")
    _add_global(q, argparse.SUPPRESS)
    q = cap.add_parser("check", help="validate a set; print what calibration will use")
    q.add_argument("dir", type=Path, metavar="DIR", help="the capture-set folder")
    q.add_argument("--layout", type=Path, help="a nominal layout other than the set's")
    _add_global(q, argparse.SUPPRESS)
    _add_global(p, argparse.SUPPRESS)

    p = command(
        "config", "list, show or copy the shipped configuration files",
        description="The configuration files shipped with hsi_torch (each command's default).",
    )  # fmt: skip
    p.add_argument(
        "action", nargs="?", choices=("list", "show", "copy"), default="list",
        help="list the names (default), show NAME, or copy NAME to DEST")  # fmt: skip
    p.add_argument("name", nargs="?", metavar="NAME", help="e.g. simulate, calibrate, synthetic")
    p.add_argument("dest", nargs="?", type=Path, metavar="DEST", help="file or folder (copy)")
    p.add_argument("--force", action="store_true", help="copy: overwrite an existing DEST")
    _add_global(p, argparse.SUPPRESS)

    p = command("view", "open cube files in napari: bands in nm, sRGB, spectra on a click")
    p.add_argument("files", nargs="+", metavar="FILE",
                   help="cube files (.tif .hdr .npz .nc .zarr) or a run's cubes.zarr")
    p.add_argument("--point", action="append", metavar="ROW,COL",
                   help="plot the spectrum at this pixel at once (repeatable)")
    p.add_argument("--band", type=float, metavar="NM", help="show the band nearest NM nm")
    p.add_argument("--screenshot", type=Path, metavar="PNG",
                   help="write the window (viewer + spectra) to PNG and exit")
    p.add_argument("--overwrite", action="store_true",
                   help="let --screenshot replace an existing file that is not an earlier "
                   "screenshot (never a file of the viewed cubes)")
    _add_global(p, argparse.SUPPRESS)

    p = command("cache", "show or clear the precomputation cache (where, entries, size)")
    p.add_argument("action", choices=("info", "clear"), help="info: where, entries, size, bound; "
                   "clear: remove the entries (only what the cache wrote)")  # fmt: skip
    p.add_argument("--folder", type=Path, metavar="DIR",
                   help="a cache folder (default: the user cache folder, $HSI_TORCH_CACHE)")
    _add_global(p, argparse.SUPPRESS)

    p = sub.add_parser(
        "bench", help="timing benchmarks (extra arguments go to the script)", add_help=False,
        description="Runs scripts/bench_<target>.py; unknown arguments are passed to it. "
        "'hsi-torch bench <target> --help' lists the script's own options.")  # fmt: skip
    p.add_argument(
        "target", nargs="?", choices=BENCH_TARGETS, default=None,
        help="benchmark to run (default: pipeline)")  # fmt: skip
    p.add_argument(
        "-h", "--help", dest="bench_help", action="store_true",
        help="show this help (after a target: the benchmark script's options)")  # fmt: skip
    p.add_argument(
        "--debug", action="store_true", default=argparse.SUPPRESS, help=argparse.SUPPRESS)
    p.set_defaults(_bench_parser=p)  # printed by main() for a bare "bench --help"
    return parser


def _err(msg: str) -> None:
    print(f"{PROG}: error: {msg}", file=sys.stderr)


def _exit_code(result: Any) -> int:
    from hsi_torch.recon.batch.driver import RunSummary, print_summary

    if result is None:
        return 0
    if isinstance(result, RunSummary):
        from hsi_torch.console import is_quiet

        if result.exit_code != 0 or not is_quiet():  # failures are reported even when quiet
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
        with command_line(argv, PROG):  # the run records hold the whole command line
            rc = _dispatch(args, extra, debug, created)
    finally:
        if rc != 0 and created:  # a failed command leaves no empty folder behind
            _remove_if_empty(created[0])
    return rc


def _remove_if_empty(folder: Path) -> None:
    """Remove ``folder`` and its sub-folders if no file is in any of them."""
    if not folder.is_dir() or any(p.is_file() or p.is_symlink() for p in folder.rglob("*")):
        return
    from hsi_torch.io.atomic import remove_empty_folder  # lazy: atomic imports numpy

    for d in sorted((p for p in folder.rglob("*") if p.is_dir()), key=lambda p: -len(p.parts)):
        remove_empty_folder(d)
    remove_empty_folder(folder)


def _dispatch(args: argparse.Namespace, extra: list[str], debug: bool, created: list[Path]) -> int:
    """Run the sub-command; every error becomes one line on stderr and an exit status."""
    from hsi_torch import console, resources
    from hsi_torch.errors import ConfigError, HSIError

    data_dir_before = resources.get_real_data_dir_setting()
    console_before = console.configure(
        quiet=bool(getattr(args, "quiet", False)), progress=bool(getattr(args, "progress", True)))
    try:
        if getattr(args, "data_dir", None) is not None:
            resources.set_real_data_dir(args.data_dir)
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
            from hsi_torch.devices import resolve_device  # lazy: the CLI starts without torch

            resolve_device(args.device, "--device")
        out = getattr(args, "out", None)
        if args.command in _FOLDER_OUT and out is not None:
            from hsi_torch.io.paths import check_out_dir

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
    finally:
        resources.set_real_data_dir(data_dir_before)
        console.configure(**console_before)


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
