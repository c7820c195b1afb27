"""A checked reconstruction run: many captures, one bundle → cube files, one input at a time.

:func:`check_run` checks everything a run needs before anything is written (the cube formats'
optional packages, the inputs — files or globs —, the device, the bundle, ``spectra_pixels`` and
``min_views`` against the bundle) and gives a :class:`ReconstructRun`; :meth:`ReconstructRun.start`
creates the output folder and the run's configuration file. :func:`reconstruct_input` reads and
reconstructs one input, :func:`write_outputs` writes its files; a task
(:func:`hsi_torch.recon.batch.tasks.reconstruct_task`) does both, in this process or on a
cluster's workers, so every run writes the same files (:mod:`hsi_torch.recon.batch`). The files
of an input (cube formats, ``_preview.png``, ``_spectra.png``, ``_std.*``), the run's
configuration file ``DIR/runs/<YYYYmmdd-HHMMSS>-<pid>.yaml``, resume and ownership are described
in ``docs/reconstruct.md``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import os
import time
import warnings
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import torch

from hsi_torch import __version__, colour
from hsi_torch.config import ConfigError, config_yaml
from hsi_torch.devices import resolve_device
from hsi_torch.errors import NoValidPixelsError
from hsi_torch.findings import Finding, HSIWarning
from hsi_torch.io import paths
from hsi_torch.io.atomic import (
    InputFiles,
    atomic_write_new,
    clean_stale_temp_files,
    remove_empty_folder,
    remove_file,
    replace_then_commit,
)
from hsi_torch.io.bundle import CalibrationBundle
from hsi_torch.io.cube import require_format, save_cube_formats
from hsi_torch.io.paths import check_out_dir, ensure_out_dir, expand_inputs
from hsi_torch.provenance import provenance
from hsi_torch.recon.config import ReconstructConfig
from hsi_torch.recon.pipeline import ReconstructionResult, Reconstructor
from hsi_torch.recon.precompute_cache import remember_sha256
from hsi_torch.recon.settings import ReconstructSettings
from hsi_torch.recon.uncertainty import relative_std_map

__all__ = [
    "ReconstructRun",
    "check_run",
    "reconstruct_input",
    "write_outputs",
    "output_paths",
    "finding_line",
    "preview_caption",
    "write_run_config",
    "findings_flag",
    "RUNS_DIR",
    "as_settings",
]


def as_settings(settings: ReconstructSettings | ReconstructConfig) -> ReconstructSettings:
    """``settings`` as they are, or those of a :class:`ReconstructConfig`."""
    return settings if isinstance(settings, ReconstructSettings) else settings.settings()


def output_paths(stem: Path, settings: ReconstructSettings | ReconstructConfig) -> list[Path]:
    """The files :func:`write_outputs` produces for ``stem`` under ``settings``
    (:func:`hsi_torch.io.paths.output_paths`)."""
    s = as_settings(settings)
    o = s.output
    return paths.output_paths(stem, o.formats, uncertainty=s.uncertainty.enabled,
                              preview=o.preview, spectra=bool(o.spectra_pixels))  # fmt: skip


def preview_caption(
    name: str,
    settings: ReconstructSettings | ReconstructConfig,
    metadata: dict[str, Any] | None = None,
) -> str:
    """The preview's caption: scene (the input's stem), bundle file, β, rendering; then, when
    the metadata's ``"findings"`` hold warnings or errors, a second line flagging them
    (:func:`findings_flag`)."""
    s = as_settings(settings)
    parts = [name]
    bundle = (metadata or {}).get("bundle")
    if bundle:
        parts.append(f"bundle {Path(bundle).name}")
    parts.append(f"beta {s.solve.beta:g}")
    if s.prior.kind == "tv":
        parts.append(f"TV lam {s.prior.lam}")
    parts.append("sRGB D65")
    stored = (metadata or {}).get("findings") or []
    flag = findings_flag([f if isinstance(f, Finding) else Finding.from_dict(f) for f in stored])
    return " | ".join(parts) + (f"\n{flag}" if flag else "")


def findings_flag(findings: Sequence[Finding]) -> str:
    """``"(!) 2 warnings: fit.residual, capture.pedestal"`` for the warnings and errors among
    ``findings`` (their distinct codes, in order), ``""`` when there are none. ASCII: the
    caption font has no warning sign."""
    bad = [f for f in findings if f.severity in ("warning", "error")]
    if not bad:
        return ""
    codes = list(dict.fromkeys(f.code for f in bad))
    n_err = sum(f.severity == "error" for f in bad)
    n_warn = len(bad) - n_err
    counts = [f"{n} {w}" + ("s" if n > 1 else "")
              for n, w in ((n_err, "error"), (n_warn, "warning")) if n]  # fmt: skip
    return f"(!) {', '.join(counts)}: {', '.join(codes)}"


def _check_points(points: Sequence[tuple[int, int]], h: int, w: int) -> None:
    """Refuse a ``spectra_pixels`` pixel ``(row, col)`` outside the ``h × w`` frame."""
    for r, c in points:
        if not (0 <= r < h and 0 <= c < w):
            raise ValueError(
                f"config key 'spectra_pixels': pixel (row={r}, col={c}) is outside the "
                f"reference frame ({h} rows, {w} columns; [row, col] order)"
            )


def write_outputs(
    result: ReconstructionResult,
    stem: str | os.PathLike,
    settings: ReconstructSettings | ReconstructConfig,
    metadata: dict[str, Any] | None = None,
    timings: dict[str, float] | None = None,
    inputs: InputFiles | Sequence[str | os.PathLike] = (),
) -> list[Path]:
    """Write a reconstruction's cube files, preview and spectra plot, as ``settings.output``
    says — all of them or none (replace-then-commit).

    The files are written concurrently (one thread per file) into a staging folder beside their
    destination (:func:`hsi_torch.io.atomic.replace_then_commit`); only when every one is complete
    are they moved into place, so an earlier run's outputs of this stem stay as they were until
    then, and on an error (a full disk, a folder in the way) they are kept and only the staged
    files are removed, then the (first) error propagates. No output may be one of ``inputs``
    (the capture, the bundle: the same file by identity, whatever its name).
    ``timings``: if given, receives seconds per output (``npz``, ``tiff``, ``envi``,
    ``preview``, ``spectra``; they overlap).

    Returns:
        The paths written.
    """
    with replace_then_commit(inputs) as tx:
        final = Path(stem)
        s = tx.stage_tree(final.parent) / final.name  # the stem in the staging folder
        written = _write_files(result, s, settings, metadata, timings)
    return [final.parent / p.relative_to(s.parent) for p in written]


def _write_files(result: ReconstructionResult, s: Path,
                 settings: ReconstructSettings | ReconstructConfig,
                 metadata: dict[str, Any] | None, timings: dict[str, float] | None
                 ) -> list[Path]:  # fmt: skip
    cfg = as_settings(settings).output
    cube = result.cube.detach().to("cpu", torch.float32)
    valid = result.valid.detach().cpu()
    wl = result.wavelengths_nm.detach().cpu()
    h, w = cube.shape[-2:]
    if cfg.spectra_pixels:
        _check_points(cfg.spectra_pixels, h, w)
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
    jobs = [timed(f, partial(save_cube_formats, s, cube, wl, valid, metadata, formats=(f,),
                             npz_arrays=npz_std if f == "npz" else None))
            for f in cfg.formats]  # fmt: skip
    if std is not None:  # the standard deviation as a cube of its own beside the cube
        s_std = s.with_name(s.name + "_std")
        meta_std = {
            **(metadata or {}),
            "quantity": "standard deviation of every band "
            "(sensor noise, free-set linearisation; 0 on bands at the bound)",
        }
        jobs += [timed(f"{f}_std", partial(save_cube_formats, s_std, std, wl, valid, meta_std,
                                           formats=(f,)))
                 for f in cfg.formats if f != "npz"]  # fmt: skip
    if cfg.preview:
        # invalid pixels black (as a zero spectrum), without a NaN-free copy of the cube
        path = s.with_name(s.name + "_preview.png")
        caption = preview_caption(s.name, settings, metadata)
        jobs.append(timed("preview", lambda: [colour.save_preview_png(
            cube, wl, path, valid=valid, caption=caption, min_size=cfg.preview_size)]))  # fmt: skip
        if std is not None:
            jobs.append(timed("std_preview",
                              lambda: [_save_std_map(cube, std, valid, s, cfg.preview_size)]))
    if cfg.spectra_pixels:
        jobs.append(timed("spectra",
                          lambda: [_plot_points(cube, valid, wl, s, cfg.spectra_pixels, std)]))
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
        raise errors[0]  # the staging folder is removed; nothing earlier was replaced
    return written


def _save_std_map(
    cube: torch.Tensor, std: torch.Tensor, valid: torch.Tensor, s: Path, preview_size: int
) -> Path:
    """``<stem>_std.png``: the mean relative standard deviation ``Σσ / Σŝ`` per pixel, grey
    (black 0, white the 99th percentile of the valid pixels), invalid pixels dark red."""
    rel = relative_std_map(cube, std, valid)
    ok = torch.isfinite(rel)
    any_ok = bool(ok.any())
    top = float(torch.quantile(rel[ok].double(), 0.99)) if any_ok else 0.0
    grey = (rel / top if top > 0 else torch.zeros_like(rel)).clamp(0, 1)
    img = torch.where(ok, grey.expand(3, -1, -1), torch.tensor([0.35, 0.0, 0.0]).view(3, 1, 1))
    med = float(rel[ok].median()) if any_ok else float("nan")
    caption = (
        f"{s.name} | mean relative std (sum of band std / sum of bands) from sensor noise"
        f" | black 0 %, white {100 * top:.3g} % (99th pct), median {100 * med:.3g} %"
        " | dark red: invalid"
    )
    return colour.save_labelled_png(
        img, s.with_name(s.name + "_std.png"), caption=caption, min_size=preview_size
    )


def _plot_points(
    cube: torch.Tensor,
    valid: torch.Tensor,
    wl: torch.Tensor,
    s: Path,
    points: Sequence[tuple[int, int]],
    std: torch.Tensor | None = None,
) -> Path:
    """The spectra at ``points`` (``(row, col)``) → ``<stem>_spectra.png``, with a ±1σ band
    when the run computed the uncertainty (``std``, ``(M, h, w)``)."""

    ys = torch.tensor([p[0] for p in points])
    xs = torch.tensor([p[1] for p in points])
    spectra = cube[:, ys, xs].T  # (K, M)
    # invalid points are left out of the plot (NaN), not drawn as a flat zero spectrum
    spectra = torch.where(valid[ys, xs].unsqueeze(1), spectra, float("nan"))
    if not bool(valid[ys, xs].any()):
        spectra = torch.zeros_like(spectra)  # nothing to draw; keep the axes finite
    labels = [f"(row {r}, col {c})" + ("" if bool(valid[r, c]) else " invalid") for r, c in points]
    sd = None if std is None else torch.where(valid[ys, xs].unsqueeze(1), std[:, ys, xs].T,
                                              float("nan"))  # fmt: skip
    path = s.with_name(s.name + "_spectra.png")
    colour.plot_spectra(wl, spectra, labels=labels, path=path, std=sd, title=s.name,
                        ylabel="reflectance (relative to white reference)")
    return path


@dataclass
class ReconstructRun:
    """A checked ``reconstruct`` run: inputs expanded, configuration, device and bundle validated,
    nothing written yet. What every task of the run gets (:mod:`hsi_torch.recon.batch.tasks`);
    :meth:`start` creates the output folder and the run's configuration file.

    Attributes:
        cfg: the resolved configuration (as recorded: the run's configuration file, the cubes'
            metadata).
        settings: the same, grouped and frozen — what the reconstructor is built from (built
            once, here).
        inputs: the expanded input files, in order.
        bundle_path: the calibration bundle (absolute).
        bundle_sha256: the SHA-256 of its content (computed once per run: resume and the
            workers' caches know the bundle by it).
        bundle_stamp: ``(size, mtime_ns)`` of the bundle file (a worker's quick check that it
            sees the same file).
        out_dir: the output folder.
        frame_size: ``(h, w)`` of the reference frame (the cubes' spatial size).
        wavelengths_nm: the bundle's band centres, nm.
        fingerprint: identifies what changes the outputs (configuration and the bundle's
            content; resume redoes inputs made under another one).
        run_config: ``out_dir/runs/<time>-<pid>.yaml`` once :meth:`start` wrote it.
    """

    cfg: ReconstructConfig
    settings: ReconstructSettings
    inputs: list[Path]
    bundle_path: Path
    bundle_sha256: str
    bundle_stamp: tuple[int, int]
    out_dir: Path
    frame_size: tuple[int, int]
    wavelengths_nm: list[float]
    fingerprint: str
    run_config: Path | None = None
    #: the folders :meth:`start` created (removed again when the run made nothing)
    created: list[Path] = field(default_factory=list, repr=False)

    def start(self) -> Path:
        """Create the output folder and write the run's configuration file; returns the folder."""

        self.created = [d for d in (self.out_dir, self.out_dir / RUNS_DIR) if not d.exists()]
        out = ensure_out_dir(self.out_dir)
        self.run_config = write_run_config(self.cfg, out, self.bundle_path, len(self.inputs))
        return out

    def discard_if_nothing_written(self, summary: Any) -> None:
        """After a run in which every input failed (none processed, none skipped): remove its
        configuration file and the folders this run created, when they are empty — a run that
        made nothing leaves nothing behind (e.g. its only input is missing)."""
        if summary.processed or summary.skipped or self.run_config is None:
            return
        with contextlib.suppress(OSError):
            remove_file(self.run_config)
        for d in sorted(self.created, key=lambda q: -len(q.parts)):
            remove_empty_folder(d)  # only when empty

    def reconstructor(self) -> Reconstructor:
        """A :class:`Reconstructor` of this run's bundle and settings (the per-bundle
        precomputation: seconds and GBs at full size)."""
        return Reconstructor(self.bundle_path, settings=self.settings)


def fingerprint_of(obj: Any) -> str:
    """A short stable hash of a JSON-serialisable ``obj`` (keys sorted)."""
    text = json.dumps(obj, sort_keys=True, default=str)
    return hashlib.sha1(text.encode("utf-8")).hexdigest()


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
    """Check everything a run needs before anything is written: the configuration (built into
    :class:`~hsi_torch.recon.settings.ReconstructSettings`, once), the cube formats' optional
    packages (unless ``formats=False``: a run writing a dataset store instead), the inputs (a
    glob matching nothing fails here), the device (``device_here=False``: only its name — the
    frames run on other machines, e.g. GPU workers of a driver without one), the bundle,
    ``spectra_pixels`` and ``min_views`` against the bundle; the bundle's SHA-256 is computed."""
    if device:
        cfg.device = str(device)
    settings = cfg.settings()
    if formats:
        for fmt in settings.output.formats:  # a missing optional package fails before any work
            try:
                require_format(fmt)
            except ModuleNotFoundError as exc:
                raise ValueError(f"config key 'formats': {exc}") from None
    inputs = expand_inputs(inputs)  # a glob matching nothing fails before anything is written
    resolve_device(settings.solve.device, "config key 'device':", here=device_here)
    bundle_path = Path(os.path.abspath(bundle))
    before = bundle_path.stat() if bundle_path.is_file() else None
    # read once: checked whole and hashed from the same bytes (the hash remembered for the
    # reconstructor's cache key)
    b, sha = CalibrationBundle.load_hashed(bundle_path)
    if before is not None:
        remember_sha256(bundle_path, sha, before)
    h, w = b.frame_size
    points = settings.output.spectra_pixels
    if points:
        _check_points(points, h, w)
    if settings.solve.min_views > b.num_views:
        raise ConfigError(
            f"{settings.solve.min_views} exceeds the {b.num_views} views of the calibration "
            f"bundle {bundle_path}: no pixel could be valid", key="min_views",
            source=config_source,
        )  # fmt: skip
    wavelengths = [float(x) for x in b.wavelengths_nm]
    # the reconstructor reads the bundle again from its file: what it keeps is the valid pixels'
    # factors, and the full-frame arrays are freed before the factorisation takes its memory
    del b
    st = bundle_path.stat()
    # keys that change the outputs (not where/how fast they are computed, nor warnings)
    ignored = ("device", "chunk_size", "fit_residual_warning", "precompute_cache",
               "drift_warn_px", "fit_residual_limit", "pedestal_refuse_factor", "strict")
    config = {k: v for k, v in vars(cfg).items() if k not in ignored}
    fingerprint = fingerprint_of({"config": config, "bundle_sha256": sha})
    return ReconstructRun(
        cfg=cfg, settings=settings, inputs=inputs, bundle_path=bundle_path, bundle_sha256=sha,
        bundle_stamp=(int(st.st_size), int(st.st_mtime_ns)), out_dir=check_out_dir(out_dir),
        frame_size=(int(h), int(w)), wavelengths_nm=wavelengths, fingerprint=fingerprint,
    )  # fmt: skip


def reconstruct_input(
    rec: Reconstructor, path: Path, run: ReconstructRun
) -> tuple[ReconstructionResult, dict[str, Any], list[Finding]]:
    """Read and reconstruct one input: the result, its metadata (as stored with the cube) and
    its findings (:attr:`ReconstructionResult.findings`, to be shown by the caller; not raised
    as Python warnings here).

    Raises:
        RefusedError: the data contradicts the result (an error finding; ``strict``: any
            warning), :class:`~hsi_torch.findings.RefusedError` with the findings.
        NoValidPixelsError: not a single pixel could be reconstructed (the reason named).
    """

    cfg = run.cfg
    with warnings.catch_warnings():  # the run shows them itself, one line each
        warnings.simplefilter("ignore", HSIWarning)
        res = rec.reconstruct_file(path)  # read as rec.settings (= run.settings) say
    if res.stats.get("num_valid", 0) == 0:
        raise NoValidPixelsError(
            f"{path}: no valid pixel: {res.stats.get('no_valid_reason') or 'unknown reason'}"
        )
    cap_meta = res.stats.pop("metadata", {})
    run_config = run.run_config
    meta = {
        "source": os.path.abspath(path),
        "bundle": os.path.abspath(run.bundle_path),
        "capture_exposure_s": cap_meta.get("exposure_s"),
        "radiometric_scale": res.stats.get("radiometric_scale"),
        "notes": [f.message for f in res.findings if f.severity == "info"],
        "findings": [f.to_dict() for f in res.findings],
        "config": dict(vars(cfg)),
        "run_config": run_config.relative_to(run.out_dir).as_posix() if run_config else None,
        "stats": res.stats,
        "timings_s": res.timings,
    }
    return res, meta, list(res.findings)


RUNS_DIR = "runs"


def write_run_config(cfg: ReconstructConfig, out: Path, bundle_path: Path, num_inputs: int) -> Path:
    """Write this run's resolved configuration to ``out/runs/<YYYYmmdd-HHMMSS>-<pid>.yaml`` (a
    new file per run, never one of an earlier or concurrent run; ``-2``, ``-3``, ... if a run of
    the same process already used the name) and return its path. The file appears complete or
    not at all (:func:`hsi_torch.io.atomic.atomic_write_new`); temporary files that killed runs
    left in ``out/runs`` are removed first."""

    folder = out / RUNS_DIR
    clean_stale_temp_files(folder)
    base = f"{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}"
    prov = provenance()
    header = (
        f"resolved configuration of a 'hsi-torch reconstruct' run, hsi_torch {__version__}\n"
        + (f"command: {prov['command']}\n" if prov["command"] else "")
        + f"torch {prov['torch']}, numpy {prov['numpy']}, python {prov['python']}\n"
        f"started {time.strftime('%Y-%m-%d %H:%M:%S')}, {num_inputs} input(s), bundle "
        f"{os.path.abspath(bundle_path)}\n"
        f"rerun with: hsi-torch reconstruct --config <this file> --bundle BUNDLE --out DIR INPUTS"
    )
    names = (f"{base}.yaml" if i == 1 else f"{base}-{i}.yaml" for i in range(1, 10_000))
    return atomic_write_new(folder, names, config_yaml(cfg, header).encode("utf-8"))


def finding_line(finding: Finding) -> str:
    """How a run prints a finding about an input (named beside it, as before findings): its
    message, measured value and limit, fix, then its code —
    ``"<message> (measured …, limit …); fix: <fix> [<code>]"``."""
    text = dataclasses.replace(finding, source=None).text()  # "<severity> [<code>] <rest>"
    return text.split("] ", 1)[1] + f" [{finding.code}]"
