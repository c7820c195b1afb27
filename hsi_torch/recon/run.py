"""A checked reconstruction run: many captures, one bundle → cube files, one input at a time.

:func:`check_run` checks everything a run needs before anything is written (the cube formats'
optional packages, the inputs — files or globs —, the device, the bundle, ``spectra_points`` and
``min_views`` against the bundle) and gives a :class:`ReconstructRun`; :meth:`ReconstructRun.start`
creates the output folder and the run's configuration file. :func:`reconstruct_input` reads and
reconstructs one input, :func:`write_outputs` writes its files, :func:`run_serial` runs every
input in this process (:func:`hsi_torch.batch.run_batch`). The distributed run
(:mod:`hsi_torch.recon.many`) uses the same pieces on its workers, so both write the same files.

For every input ``DIR/<stem>``: the cube in the configured formats (``<stem>.tif`` OME-TIFF with
its GDAL ``<stem>.vrt``, ``<stem>.hdr/.img``, ``<stem>.npz``; optionally ``<stem>.nc`` and
``<stem>.zarr``), ``<stem>_preview.png`` (sRGB, D65, enlarged, with a caption) and, with
``spectra_points``, ``<stem>_spectra.png``; with ``uncertainty``, the per-band standard deviation
as ``<stem>_std.*`` in the non-NPZ formats, the key ``std`` in ``<stem>.npz`` and a map of the mean
relative standard deviation, ``<stem>_std.png``. Every file is written atomically; if writing an
input's outputs fails, the files already written for that input are removed. Each run records its
configuration in a file of its own, ``DIR/runs/<YYYYmmdd-HHMMSS>-<pid>.yaml`` (rerun it with
``--config``; a later run into the same folder never overwrites it), and every cube's metadata
holds its configuration and the name of that file (``run_config``). Resume skips inputs whose
outputs exist unchanged and were made from the same input file, configuration and bundle —
anything else is reconstructed again. Two inputs with the same stem from different folders would
write the same files: the later one fails with an error naming both (in the same run or a later
one) and the earlier one's outputs are kept. A capture of which not a single pixel could be
reconstructed (all saturated, no finite data, ...) fails with the reason; no all-NaN cube is
written.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import torch

from hsi_torch import __version__, colour
from hsi_torch.batch import (
    BatchSummary,
    check_out_dir,
    ensure_out_dir,
    expand_inputs,
    fingerprint_of,
    run_batch,
)
from hsi_torch.config import ConfigError, config_yaml
from hsi_torch.console import info, warn
from hsi_torch.errors import NoValidPixelsError
from hsi_torch.io.atomic import atomic_write_new, clean_stale_temp_files
from hsi_torch.io.cube import remove_output, require_format, save_cube_formats
from hsi_torch.profiling import release_freed_memory
from hsi_torch.recon.checks import check_notes, check_warnings
from hsi_torch.recon.config import ReconstructConfig
from hsi_torch.recon.pipeline import ReconstructionResult, Reconstructor
from hsi_torch.recon.sensing import load_bundle
from hsi_torch.recon.uncertainty import DEFAULT_ELECTRONS_PER_DN, SensorNoise, relative_std_map

__all__ = [
    "ReconstructRun", "check_run", "reconstruct_input", "reconstruct_to_files", "run_serial",
    "write_outputs", "output_paths", "frame_warnings", "preview_caption", "write_run_config",
    "RUNS_DIR",
]

_SUFFIXES = {"tiff": [".tif", ".vrt"], "envi": [".hdr", ".img"], "npz": [".npz"],
             "netcdf": [".nc"], "zarr": [".zarr"]}


def output_paths(stem: Path, cfg: ReconstructConfig) -> list[Path]:
    """The files :func:`write_outputs` produces for ``stem`` under ``cfg``."""
    out = [stem.with_name(stem.name + s) for f in cfg.formats for s in _SUFFIXES[f]]
    if cfg.uncertainty:
        out += [stem.with_name(stem.name + "_std" + s) for f in cfg.formats if f != "npz"
                for s in _SUFFIXES[f]]  # fmt: skip
    if cfg.preview:
        out.append(stem.with_name(stem.name + "_preview.png"))
        if cfg.uncertainty:
            out.append(stem.with_name(stem.name + "_std.png"))
    if cfg.spectra_points:
        out.append(stem.with_name(stem.name + "_spectra.png"))
    return out


def preview_caption(
    name: str, cfg: ReconstructConfig, metadata: dict[str, Any] | None = None
) -> str:
    """The preview's caption: scene (the input's stem), bundle file, β, rendering."""
    parts = [name]
    bundle = (metadata or {}).get("bundle")
    if bundle:
        parts.append(f"bundle {Path(bundle).name}")
    parts.append(f"beta {cfg.beta:g}")
    if cfg.prior == "tv":
        parts.append(f"TV lam {cfg.lam}")
    parts.append("sRGB D65")
    return " | ".join(parts)


def _check_points(points: Sequence[tuple[int, int]], h: int, w: int) -> None:
    for x, y in points:
        if not (0 <= x < w and 0 <= y < h):
            raise ValueError(
                f"config key 'spectra_points': point (x={x}, y={y}) is outside the reference "
                f"frame (w={w}, h={h})"
            )


def write_outputs(
    result: ReconstructionResult,
    stem: str | os.PathLike,
    cfg: ReconstructConfig,
    metadata: dict[str, Any] | None = None,
    timings: dict[str, float] | None = None,
) -> list[Path]:
    """Write a reconstruction's cube files, preview and spectra plot (all atomic).

    The files are written concurrently (one thread per file). On an error the files already
    written for this stem are removed, then the (first) error propagates.
    ``timings``: if given, receives seconds per output (``npz``, ``tiff``, ``envi``,
    ``preview``, ``spectra``; they overlap).

    Returns:
        The paths written.
    """

    s = Path(stem)
    cube = result.cube.detach().to("cpu", torch.float32)
    valid = result.valid.detach().cpu()
    wl = result.wavelengths_nm.detach().cpu()
    h, w = cube.shape[-2:]
    if cfg.spectra_points:
        _check_points(cfg.spectra_points, h, w)
    tm = timings if timings is not None else {}

    def timed(name: str, fn: Callable[[], list[Path]]) -> Callable[[], list[Path]]:
        def run() -> list[Path]:
            t0 = time.perf_counter()
            out = fn()
            tm[name] = time.perf_counter() - t0
            return out

        return run

    std = None if result.std is None else result.std.detach().to("cpu", torch.float32)
    npz_std = None if std is None else {"std": std}
    jobs = [
        timed(f, partial(save_cube_formats, s, cube, wl, valid, metadata, formats=(f,),
                         npz_arrays=npz_std if f == "npz" else None))
        for f in cfg.formats
    ]
    if std is not None:  # the standard deviation as a cube of its own beside the cube
        s_std = s.with_name(s.name + "_std")
        meta_std = {**(metadata or {}), "quantity": "standard deviation of every band "
                    "(sensor noise, free-set linearisation; 0 on bands at the bound)"}
        jobs += [timed(f"{f}_std", partial(save_cube_formats, s_std, std, wl, valid, meta_std,
                                           formats=(f,)))
                 for f in cfg.formats if f != "npz"]  # fmt: skip
    if cfg.preview:
        # invalid pixels black (as a zero spectrum), without a NaN-free copy of the cube
        path = s.with_name(s.name + "_preview.png")
        caption = preview_caption(s.name, cfg, metadata)
        jobs.append(timed("preview", lambda: [colour.save_preview_png(
            cube, wl, path, valid=valid, caption=caption, min_size=cfg.preview_size)]))
        if std is not None:
            jobs.append(timed("std_preview", lambda: [_save_std_map(cube, std, valid, s, cfg)]))
    if cfg.spectra_points:
        jobs.append(timed("spectra", lambda: [_plot_points(cube, valid, wl, s, cfg)]))
    # the files are independent: written concurrently (mostly kernel copies and fsync waits,
    # which release the GIL); every file is still atomic
    results: list[list[Path]] = []
    errors: list[BaseException] = []
    with ThreadPoolExecutor(max_workers=max(1, len(jobs))) as pool:
        futures = [pool.submit(job) for job in jobs]
        for fut in futures:
            try:
                results.append(fut.result())
            except BaseException as exc:  # noqa: BLE001 - re-raised below after cleanup
                errors.append(exc)
    written = [p for r in results for p in r]
    if errors:
        for p in written:
            remove_output(p)
        raise errors[0]
    return written


def _save_std_map(
    cube: torch.Tensor, std: torch.Tensor, valid: torch.Tensor, s: Path, cfg: ReconstructConfig
) -> Path:
    """``<stem>_std.png``: the mean relative standard deviation ``Σσ / Σŝ`` per pixel, grey
    (black 0, white the 99th percentile of the valid pixels), invalid pixels dark red."""
    rel = relative_std_map(cube, std, valid)
    ok = torch.isfinite(rel)
    top = float(torch.quantile(rel[ok].double(), 0.99)) if bool(ok.any()) else 0.0
    grey = (rel / top if top > 0 else torch.zeros_like(rel)).clamp(0, 1)
    bad = torch.tensor([0.35, 0.0, 0.0]).view(3, 1, 1)
    img = torch.where(ok, grey, torch.zeros_like(grey)).expand(3, -1, -1)
    img = torch.where(ok, img, bad)
    med = float(rel[ok].median()) if bool(ok.any()) else float("nan")
    caption = (f"{s.name} | mean relative std (sum of band std / sum of bands) from sensor noise"
               f" | black 0 %, white {100 * top:.3g} % (99th pct), median {100 * med:.3g} %"
               " | dark red: invalid")
    return colour.save_labelled_png(img, s.with_name(s.name + "_std.png"), caption=caption,
                                    min_size=cfg.preview_size)


def _plot_points(
    cube: torch.Tensor, valid: torch.Tensor, wl: torch.Tensor, s: Path, cfg: ReconstructConfig
) -> Path:
    """The spectra at ``cfg.spectra_points`` → ``<stem>_spectra.png``."""

    xs = torch.tensor([p[0] for p in cfg.spectra_points])
    ys = torch.tensor([p[1] for p in cfg.spectra_points])
    spectra = cube[:, ys, xs].T  # (K, M)
    # invalid points are left out of the plot (NaN), not drawn as a flat zero spectrum
    spectra = torch.where(valid[ys, xs].unsqueeze(1), spectra, float("nan"))
    if not bool(valid[ys, xs].any()):
        spectra = torch.zeros_like(spectra)  # nothing to draw; keep the axes finite
    labels = [
        f"(x={x}, y={y})" + ("" if bool(valid[y, x]) else " invalid")
        for x, y in cfg.spectra_points
    ]
    path = s.with_name(s.name + "_spectra.png")
    colour.plot_spectra(wl, spectra, labels=labels, path=path,
                 title=s.name, ylabel="reflectance (relative to white reference)")
    return path


def _resolve_device(name: str, here: bool = True) -> torch.device:
    try:
        dev = torch.device(name)
    except RuntimeError as exc:
        raise ValueError(f"config key 'device': invalid torch device {name!r} ({exc})") from None
    if here and dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"config key 'device': {name!r} requested but CUDA is not available")
    return dev


@dataclass
class ReconstructRun:
    """A checked ``reconstruct`` run: inputs expanded, configuration, device and bundle validated,
    nothing written yet. What the serial run and the distributed one
    (:func:`hsi_torch.recon.many.run_many`) share; :meth:`start` creates the output folder and
    the run's configuration file.

    Attributes:
        cfg: the resolved configuration.
        inputs: the expanded input files, in order.
        bundle_path: the calibration bundle (absolute).
        out_dir: the output folder.
        device, dtype: where and in what precision frames are solved.
        frame_size: ``(h, w)`` of the reference frame (the cubes' spatial size).
        wavelengths_nm: the bundle's band centres, nm.
        fingerprint: identifies the settings that change the outputs (configuration and bundle
            file; resume redoes inputs made under another one).
        run_config: ``out_dir/runs/<time>-<pid>.yaml`` once :meth:`start` wrote it.
    """

    cfg: ReconstructConfig
    inputs: list[Path]
    bundle_path: Path
    out_dir: Path
    device: torch.device
    dtype: torch.dtype
    frame_size: tuple[int, int]
    wavelengths_nm: list[float]
    fingerprint: str
    run_config: Path | None = None

    def start(self) -> Path:
        """Create the output folder and write the run's configuration file; returns the folder."""

        out = ensure_out_dir(self.out_dir)
        self.run_config = write_run_config(self.cfg, out, self.bundle_path, len(self.inputs))
        return out

    def reconstructor(self) -> Reconstructor:
        """A :class:`Reconstructor` of this run's bundle and settings (the per-bundle
        precomputation: seconds and GBs at full size)."""
        cfg = self.cfg
        return Reconstructor(
            self.bundle_path, beta=cfg.beta, diff_order=cfg.diff_order, solver=cfg.solver,
            admm_iters=cfg.admm_iters, device=self.device, dtype=self.dtype,
            chunk_size=cfg.chunk_size, min_views=cfg.min_views, nan_invalid=cfg.nan_invalid,
            exposure_correction=cfg.exposure_correction, prior=cfg.prior, lam=cfg.lam,
            spatial_iters=cfg.spatial_iters, uncertainty=cfg.uncertainty,
            noise=SensorNoise(cfg.noise_electrons_per_dn or DEFAULT_ELECTRONS_PER_DN,
                              cfg.noise_read_e),
        )  # fmt: skip


def check_run(
    inputs: Any,
    bundle: str | os.PathLike,
    out_dir: str | os.PathLike,
    cfg: ReconstructConfig,
    *,
    device: str | None = None,
    formats: bool = True,
    config_source: str | None = None,
    device_here: bool = True,
) -> ReconstructRun:
    """Check everything a run needs before anything is written: the cube formats' optional
    packages (unless ``formats=False``: a run writing a dataset store instead), the inputs (a
    glob matching nothing fails here), the device (``device_here=False``: only its name — the
    frames run on other machines, e.g. GPU workers of a driver without one), the bundle,
    ``spectra_points`` and ``min_views`` against the bundle."""
    if formats:
        for fmt in cfg.formats:  # an optional package that is missing fails before any work
            try:
                require_format(fmt)
            except ModuleNotFoundError as exc:
                raise ValueError(f"config key 'formats': {exc}") from None
    paths = expand_inputs(inputs)  # a glob matching nothing fails before anything is written
    if device:
        cfg.device = str(device)
    dev = _resolve_device(cfg.device, here=device_here)
    dtype = torch.float64 if cfg.dtype == "float64" else torch.float32
    bundle_path = Path(os.path.abspath(bundle))
    b = load_bundle(bundle_path)
    h, w = b.frame_size
    if cfg.spectra_points:
        _check_points(cfg.spectra_points, h, w)
    if cfg.min_views > b.num_views:
        raise ConfigError(
            f"{cfg.min_views} exceeds the {b.num_views} views of the calibration bundle "
            f"{bundle_path}: no pixel could be valid", key="min_views", source=config_source,
        )  # fmt: skip
    wavelengths = [float(x) for x in b.wavelengths_nm]
    # the reconstructor reads the bundle again from its file: what it keeps is the valid pixels'
    # factors, and the full-frame arrays are freed before the factorisation takes its memory
    del b
    st = bundle_path.stat()
    # keys that change the outputs (not where/how fast they are computed, nor warnings)
    ignored = ("device", "chunk_size", "fit_residual_warning")
    settings = {k: v for k, v in vars(cfg).items() if k not in ignored}
    fingerprint = fingerprint_of({
        "config": settings,
        "bundle": [str(bundle_path), st.st_size, st.st_mtime_ns],
    })  # fmt: skip
    return ReconstructRun(
        cfg=cfg, inputs=paths, bundle_path=bundle_path, out_dir=check_out_dir(out_dir),
        device=dev, dtype=dtype, frame_size=(int(h), int(w)), wavelengths_nm=wavelengths,
        fingerprint=fingerprint,
    )  # fmt: skip


def reconstruct_input(
    rec: Reconstructor, path: Path, run: ReconstructRun
) -> tuple[ReconstructionResult, dict[str, Any], list[str]]:
    """Read and reconstruct one input: the result, its metadata (as stored with the cube) and
    its warnings (:func:`frame_warnings`, to be shown by the caller).

    Raises:
        NoValidPixelsError: not a single pixel could be reconstructed (the reason named).
    """

    cfg = run.cfg
    res = rec.reconstruct_file(
        path, cfg.demosaic, cfa_pattern=cfg.cfa_pattern, black_level=cfg.black_level,
        white_level=cfg.white_level, exposure_s=cfg.exposure_s,
    )  # fmt: skip
    if res.stats.get("num_valid", 0) == 0:
        raise NoValidPixelsError(
            f"{path}: no valid pixel: {res.stats.get('no_valid_reason') or 'unknown reason'}"
        )
    warnings = frame_warnings(res.stats, cfg)
    cap_meta = res.stats.pop("metadata", {})
    run_config = run.run_config
    meta = {
        "source": os.path.abspath(path),
        "bundle": os.path.abspath(run.bundle_path),
        "capture_exposure_s": cap_meta.get("exposure_s"),
        "radiometric_scale": res.stats.get("radiometric_scale"),
        "notes": check_notes(res.stats),
        "config": {k: v for k, v in vars(cfg).items()},
        "run_config": run_config.relative_to(run.out_dir).as_posix() if run_config else None,
        "stats": res.stats,
        "timings_s": res.timings,
    }
    return res, meta, warnings


def reconstruct_to_files(rec: Reconstructor, path: Path, run: ReconstructRun) -> list[Path]:
    """Reconstruct one input and write its files (:func:`write_outputs`) into the run's folder;
    warnings are printed. Returns the files written."""

    res, meta, warnings = reconstruct_input(rec, path, run)
    for msg in meta.get("notes", []):
        info(f"{path.name}: {msg}")
    for msg in warnings:
        warn(f"WARNING {path}: {msg}")
    written = write_outputs(res, run.out_dir / path.stem, run.cfg, meta)
    del res
    release_freed_memory()  # frames do not pile up freed blocks in the allocator's arenas
    return written


def run_serial(
    run: ReconstructRun, *, resume: bool = True, progress: bool = True
) -> BatchSummary:
    """The run in this process (:func:`hsi_torch.batch.run_batch`): one reconstructor, built on
    the first input that needs it, then every input in order. :meth:`ReconstructRun.start`
    must have been called. Returns the :class:`hsi_torch.batch.BatchSummary`."""

    state: dict[str, Any] = {"rec": None}

    def process(path: Path) -> list[Path]:
        if state["rec"] is None:  # built on the first input that needs it
            state["rec"] = run.reconstructor()
        return reconstruct_to_files(state["rec"], path, run)

    out, cfg = run.out_dir, run.cfg
    return run_batch(
        run.inputs, process, out, resume=resume, progress=progress,
        desc="reconstruct", fingerprint=run.fingerprint,
        planned_outputs=lambda p: output_paths(out / p.stem, cfg),
    )  # fmt: skip


RUNS_DIR = "runs"


def write_run_config(
    cfg: ReconstructConfig, out: Path, bundle_path: Path, num_inputs: int
) -> Path:
    """Write this run's resolved configuration to ``out/runs/<YYYYmmdd-HHMMSS>-<pid>.yaml`` (a
    new file per run, never one of an earlier or concurrent run; ``-2``, ``-3``, ... if a run of
    the same process already used the name) and return its path. The file appears complete or
    not at all (:func:`hsi_torch.io.atomic.atomic_write_new`); temporary files that killed runs
    left in ``out/runs`` are removed first."""

    folder = out / RUNS_DIR
    clean_stale_temp_files(folder)
    base = f"{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}"
    header = (
        f"resolved configuration of a 'hsi-torch reconstruct' run, hsi_torch {__version__}\n"
        f"started {time.strftime('%Y-%m-%d %H:%M:%S')}, {num_inputs} input(s), bundle "
        f"{os.path.abspath(bundle_path)}\n"
        f"rerun with: hsi-torch reconstruct --config <this file> --bundle BUNDLE --out DIR INPUTS"
    )
    names = (f"{base}.yaml" if i == 1 else f"{base}-{i}.yaml" for i in range(1, 10_000))
    return atomic_write_new(folder, names, config_yaml(cfg, header).encode("utf-8"))


def frame_warnings(stats: dict[str, Any], cfg: ReconstructConfig) -> list[str]:
    """Warnings about one reconstructed frame: a fit residual above
    ``cfg.fit_residual_warning`` (the bundle probably belongs to another geometry, or the
    black level / exposure is wrong), pixels whose solve did not converge, and the capture
    checks (:func:`hsi_torch.recon.checks.check_warnings`: a pedestal outside the views, an
    unknown exposure ratio, another camera)."""
    out: list[str] = check_warnings(stats)
    fit = stats.get("fit_residual")
    lim = cfg.fit_residual_warning
    if lim is not None and isinstance(fit, float) and fit > lim:
        out.append(
            f"relative fit residual {fit:.3f} > {lim:g}: the spectra do not explain the "
            "capture; is the calibration bundle from this camera and geometry (and are the black "
            "level and exposure right)?"
        )
    n = int(stats.get("num_not_converged", 0))
    if n:
        out.append(
            f"{n} of {stats.get('num_valid', '?')} pixels did not converge (KKT residual above "
            f"the solver tolerance; max {stats.get('max_kkt', float('nan')):.1e}); try "
            "dtype=float64 or a larger beta"
        )
    return out

