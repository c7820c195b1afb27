"""``hsi-torch calibrate [--config C] --captures DIR --out OUT [--set k=v] [--device D]`` and
``hsi-torch layout`` (docs/calibration.md tells the outputs and the rules in full).

``--out`` is a folder receiving ``calib.npz``, ``calib.report.json``, ``calib_diagnostics.png``
and ``resolved_config.yaml`` (:func:`output_paths`; ``--out NAME.npz`` names the bundle file
itself), all four replaced together only once the whole calibration succeeded
(:func:`hsi_torch.io.atomic.replace_then_commit`); no output may be one of the captures.
``--oracle``: the bundle of a simulated set's ground truth
(:func:`hsi_torch.simulate.oracle.bundle_from_truth`) and its figure, nothing calibrated.
"""

from __future__ import annotations

import argparse
import os
import sys
import warnings
from pathlib import Path
from typing import Any

__all__ = ["run_calibrate", "run_layout", "layout_paths", "output_paths", "figure_path",
           "BUNDLE_NAME"]

#: File name of the bundle inside an ``--out`` folder.
BUNDLE_NAME = "calib.npz"

_PACKAGE_DIR = str(Path(__file__).resolve().parents[1])


def output_paths(out: str | Path) -> tuple[Path, Path, Path]:
    """``(bundle, report_json, resolved_config)`` for ``--out``: a folder ``DIR`` gives
    ``DIR/calib.npz``, ``DIR/calib.report.json``, ``DIR/resolved_config.yaml``; a name ending in
    ``.npz`` gives ``NAME.npz``, ``NAME.report.json``, ``NAME.resolved_config.yaml``."""
    p = Path(out)
    if p.suffix.lower() == ".npz":
        return (p, p.with_name(p.stem + ".report.json"),
                p.with_name(p.stem + ".resolved_config.yaml"))  # fmt: skip
    bundle = p / BUNDLE_NAME
    return bundle, bundle.with_name(bundle.stem + ".report.json"), p / "resolved_config.yaml"


def figure_path(bundle_path: str | Path) -> Path:
    """The diagnostics figure written beside a bundle: ``<stem>_diagnostics.png``."""
    b = Path(bundle_path)
    return b.with_name(b.stem + "_diagnostics.png")


def run_calibrate(args: argparse.Namespace) -> int:
    """Entry point called by :mod:`hsi_torch.cli`: calibrate a capture folder into a bundle."""
    from hsi_torch.calibrate.config import CalibrateConfig
    from hsi_torch.calibrate.figures import plot_calibration
    from hsi_torch.calibrate.pipeline import calibrate_capture_set
    from hsi_torch.cli_common import load_args_config
    from hsi_torch.config import write_resolved_config
    from hsi_torch.console import info
    from hsi_torch.io.atomic import ReplaceTransaction, atomic_write_json, replace_then_commit
    from hsi_torch.io.paths import check_out_dir
    from hsi_torch.provenance import provenance

    bundle_path, report_path, config_path = output_paths(args.out)
    if bundle_path.is_dir():
        raise ValueError(f"--out {bundle_path} is a folder; give a folder (the bundle is written "
                         f"as {BUNDLE_NAME} inside) or a file name ending in .npz")  # fmt: skip
    check_out_dir(bundle_path.parent)  # before the calibration: it takes a while
    fig = figure_path(bundle_path)
    inputs = _inputs_of(args)
    oracle = bool(getattr(args, "oracle", False))
    pre = ReplaceTransaction(inputs)
    for p in (bundle_path, fig) if oracle else (bundle_path, report_path, config_path, fig):
        pre.check(p)  # before the calibration: an input or a folder in the way
    _check_replaces_a_bundle(bundle_path)
    if oracle:
        return _write_oracle(args.captures, bundle_path, inputs)
    cfg = load_args_config(args, CalibrateConfig, default="calibrate")
    device = getattr(args, "device", None)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("default")
        bundle, report = calibrate_capture_set(args.captures, cfg, device=device)
    for w in caught:  # ours as one plain line each (e.g. a saturated white shot dropped)
        if str(Path(w.filename).resolve()).startswith(_PACKAGE_DIR):
            print(f"hsi-torch: warning: {w.message}", file=sys.stderr)
        else:
            warnings.showwarning(w.message, w.category, w.filename, w.lineno)
    existed = bundle_path.is_file()
    with replace_then_commit(inputs) as tx:  # all four files or none; the old ones kept till then
        tx.write(fig, lambda t: plot_calibration(bundle, t, report=report))
        tx.write(report_path, lambda t: atomic_write_json(
            t, {**report.to_dict(), "provenance": provenance()}))
        tx.write(config_path, lambda t: write_resolved_config(cfg, t.parent, name=t.name))
        # the bundle is moved last; a kill between the moves leaves the commit's journal, and
        # the next run into the folder puts the earlier files back
        tx.write(bundle_path, bundle.save)
    if existed:
        _say_replaced(bundle_path)
    info(str(report))
    info(bundle.summary())
    info(f"wrote {bundle_path} (+ {report_path.name}, {fig.name}, {config_path.name})")
    return 0


def _inputs_of(args: argparse.Namespace) -> Any:
    """The files calibration reads (the capture folder, ``--config``), by identity."""
    from hsi_torch.io.atomic import InputFiles

    inputs = InputFiles()
    if args.captures is not None and Path(args.captures).is_dir():
        inputs.add(args.captures)
    if getattr(args, "config", None) is not None and Path(args.config).is_file():
        inputs.add(args.config)
    return inputs


#: The members every calibration bundle holds (any schema version).
_BUNDLE_MEMBERS = {"meta.npy", "B.npy", "phi.npy", "gain.npy"}


def _check_replaces_a_bundle(bundle_path: Path) -> None:
    """``--out NAME.npz`` may replace an earlier bundle (a rerun), never another file (a lab's
    ``results.npz``). A file whose zip members are a bundle's counts as an earlier bundle (even
    one this version would refuse to load); anything else is refused before the calibration
    starts.

    Raises:
        InputError: ``bundle_path`` exists and is not a calibration bundle.
    """
    import zipfile

    from hsi_torch.errors import InputError

    if not os.path.lexists(bundle_path):
        return
    names: set[str] = set()
    try:
        if bundle_path.is_file() and zipfile.is_zipfile(bundle_path):
            with zipfile.ZipFile(bundle_path) as z:
                names = set(z.namelist())
    except (OSError, zipfile.BadZipFile):
        names = set()
    if not _BUNDLE_MEMBERS <= names:
        raise InputError(
            f"--out {bundle_path} exists and is not a calibration bundle; calibrate replaces "
            "only an earlier bundle: choose another name, or move the file away"
        )


def _say_replaced(bundle_path: Path) -> None:
    print(f"hsi-torch: replaced the existing bundle {bundle_path} (and the files beside it)",
          file=sys.stderr)


def _write_oracle(captures: Path, bundle_path: Path, inputs: Any = ()) -> int:
    """``--oracle``: the bundle of a simulated capture set's ground truth and its figure."""
    from hsi_torch.calibrate.figures import plot_calibration
    from hsi_torch.console import info
    from hsi_torch.io.atomic import replace_then_commit
    from hsi_torch.simulate.oracle import bundle_from_truth

    bundle = bundle_from_truth(captures)
    fig = figure_path(bundle_path)
    existed = bundle_path.is_file()
    with replace_then_commit(inputs) as tx:  # both files or none
        tx.write(fig, lambda t: plot_calibration(bundle, t))
        tx.write(bundle_path, bundle.save)  # moved last (see above)
    if existed:
        _say_replaced(bundle_path)
    info(bundle.summary())
    info(f"wrote the oracle bundle {bundle_path} (+ {fig.name}) from the ground truth of "
         f"{captures}")
    return 0


# --- hsi-torch layout


def layout_paths(out: str | Path) -> tuple[Path, Path]:
    """``(layout_json, overlay_png)`` for ``layout --out``: a name ending in ``.json`` is the
    layout file itself (overlay ``<stem>_overlay.png`` beside it); anything else is a folder
    receiving ``nominal_layout.json`` and ``nominal_layout_overlay.png``."""
    p = Path(out)
    if p.suffix.lower() != ".json":
        p = p / "nominal_layout.json"
    return p, p.with_name(p.stem + "_overlay.png")


def run_layout(args: argparse.Namespace) -> int:
    """Entry point of ``hsi-torch layout``: propose ``nominal_layout.json`` from the design
    (a simulate-style config: geometry + camera) fitted to the white shot(s), parities checked
    on the grid shots (:mod:`hsi_torch.calibrate.layout_fit`); writes the layout and its
    overlay PNG, nothing on an error or when the shots do not support the fit
    (:func:`~hsi_torch.calibrate.layout_fit.check_layout_confidence`, limit
    ``--min-edge-contrast``)."""
    import torch

    from hsi_torch.calibrate.config import CalibrateConfig
    from hsi_torch.calibrate.layout_fit import (
        MIN_EDGE_CONTRAST,
        check_layout_confidence,
        draw_layout_overlay,
        layout_document,
        propose_layout,
        trace_design,
    )
    from hsi_torch.calibrate.registration import GridDetectorConfig
    from hsi_torch.cli_common import config_source, load_args_config
    from hsi_torch.config import load_config
    from hsi_torch.console import info
    from hsi_torch.errors import InputError
    from hsi_torch.io import read_any
    from hsi_torch.io.atomic import (
        InputFiles,
        atomic_write_json,
        check_not_input,
        replace_then_commit,
    )
    from hsi_torch.io.bounded import declared_image_size
    from hsi_torch.io.capture_set import read_capture_set
    from hsi_torch.io.paths import check_out_dir
    from hsi_torch.resources import shipped_config
    from hsi_torch.simulate.capture_sets import design_optics  # lazy: the design's optics
    from hsi_torch.simulate.config import SimulateConfig

    out_json, overlay = layout_paths(args.out)
    check_out_dir(out_json.parent)
    for p in (out_json, overlay):
        if p.exists() and not args.force:
            raise ValueError(f"{p} exists; give another --out or --force to replace it")
    white_files = [Path(p) for p in (args.white or [])]
    grid_files = [Path(p) for p in (args.grid or [])]
    dark_files = [Path(p) for p in (args.dark or [])]
    if args.captures is not None:
        cs = read_capture_set(args.captures)
        white_files = white_files or list(cs.white)
        grid_files = grid_files or list(cs.grid)
        dark_files = dark_files or list(cs.dark)
    if not white_files:
        raise InputError("hsi-torch layout needs a white shot: --white FILE(s), or --captures "
                         "DIR with white-reference captures")  # fmt: skip
    inputs = InputFiles([*white_files, *grid_files, *dark_files])  # never written over
    for p in (out_json, overlay):
        check_not_input(p, inputs)  # before any work
    # the design: geometry and camera of a simulate-style config
    design = load_args_config(args, SimulateConfig, default="simulate")
    geometry, camera = design_optics(design)
    ccfg = load_config(args.calib_config or shipped_config("calibrate"), CalibrateConfig)
    det = GridDetectorConfig.from_dict(ccfg.detector_dict())

    def read(p: Path, size: tuple[int, int] | None) -> torch.Tensor:
        return read_any(p, expected_size=size, demosaic=ccfg.demosaic,
                        cfa_pattern=ccfg.cfa_pattern, black_level=ccfg.black_level,
                        white_level=ccfg.white_level).image  # fmt: skip

    # every shot's size from its header, before any pixel is decoded (a small compressed file
    # may inflate to gigabytes): the design camera's sensor size
    size = (int(camera.height_px), int(camera.width_px))
    for p in [*white_files, *grid_files, *dark_files]:
        hw = declared_image_size(p)
        if hw is not None and hw != size:
            raise InputError(f"{p}: shot size (H, W) = {hw} differs from the design camera's "
                             f"{size}; give the design of this camera (camera.width_px, "
                             "height_px, pixel_pitch_mm, focal_length_mm in the design config)")
    first = read(white_files[0], size)
    dark = None
    if dark_files:
        dark = sum(read(p, size) for p in dark_files) / len(dark_files)
    white = sum([first] + [read(p, size) for p in white_files[1:]]) / len(white_files)
    white = white if dark is None else white - dark
    grids = []
    if grid_files:
        # flat-fielded by the white shot, as calibration detects them
        lim = 0.02 * float(torch.quantile(white.flatten()[:: max(1, white.numel() // 200_000)],
                                          0.99))  # fmt: skip
        inv = torch.where(white > lim, 1.0 / white.clamp_min(1e-12), torch.zeros_like(white))
        for p in grid_files:
            img = read(p, size)
            grids.append((img if dark is None else img - dark) * inv)
    tiles = trace_design(geometry, camera)
    proposal = propose_layout(
        white.mean(0), tiles, grids, det,
        min_inlier_fraction=ccfg.registration.min_inlier_fraction,
    )  # fmt: skip
    # refused (nothing written) when the shots do not single out the fit
    limit = getattr(args, "min_edge_contrast", None)
    check_layout_confidence(proposal, MIN_EDGE_CONTRAST if limit is None else float(limit))
    src = config_source(args, "simulate")
    doc = layout_document(proposal, sources={
        "design": str(src) if src is not None else "defaults",
        "design_overrides": list(getattr(args, "overrides", [])),
        "white": [str(p) for p in white_files], "grid": [str(p) for p in grid_files],
        "dark": [str(p) for p in dark_files],
    })  # fmt: skip
    # both files or none, and an earlier pair (--force) kept until both new ones are complete
    with replace_then_commit(inputs) as tx:
        tx.write(overlay, lambda p: draw_layout_overlay(white.mean(0), proposal, p))
        tx.write(out_json, lambda p: atomic_write_json(p, doc))
    info(str(proposal))
    info(f"wrote {out_json} (+ {overlay.name}): check the overlay, then calibrate with it")
    return 0
