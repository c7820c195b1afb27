"""Shared pytest options and fixtures: devices, dtypes, real-data location.

Devices and dtypes are chosen on the command line, as in kornia's test suite::

    pytest                                   # cpu, float32 and float64
    pytest --device cuda                     # the GPU only
    pytest --device all --dtype float64      # every available device, float64 only

A test asks for the ``device`` and/or ``dtype`` fixture and runs once per selected value; no test
file keeps its own device list.
"""

from __future__ import annotations

import atexit
import hashlib
import importlib.util
import os
import shutil
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest
import torch

from hsi_torch.recon.precompute_cache import CACHE_ENV
from hsi_torch.resources import DATA_ENV, real_data_dir

# the tests' reconstructors cache their precomputation in a folder of this session (also seen
# by the commands the tests start), never in the user's cache folder
_CACHE_DIR = tempfile.mkdtemp(prefix="hsi_torch_test_cache_")
os.environ[CACHE_ENV] = _CACHE_DIR
atexit.register(shutil.rmtree, _CACHE_DIR, True)


def _declare_torchvision_schemas() -> torch.library.Library | None:
    """Let ``import torchvision`` (hence deepinv and torchmetrics) succeed beside a CPU torch.

    The registry's torchvision for torch 2.13 links CUDA libraries, so its compiled extension
    ``torchvision/_C.so`` does not load beside the CPU torch; its import then stops at its own
    unguarded ``register_fake("torchvision::nms")`` / ``("torchvision::qnms")`` ("operator
    torchvision::nms does not exist"). Where the extension does not load, this declares those two
    operator schemas (no kernel) through ``torch.library`` before torchvision is imported: its
    Python modules, deepinv's physics and optimisers and torchmetrics then import and work; only
    ``torchvision.ops`` (the compiled operators) stays unusable. Test suite only: the package never
    imports torchvision. Returns the library holding the schemas (kept alive), or None.
    """
    spec = importlib.util.find_spec("torchvision")
    if spec is None or "torchvision" in sys.modules or not spec.submodule_search_locations:
        return None
    folder = Path(next(iter(spec.submodule_search_locations)))
    for ext in sorted(folder.glob("_C*.so")) + sorted(folder.glob("_C*.pyd")):
        try:
            torch.ops.load_library(str(ext))
        except (OSError, ImportError, RuntimeError):
            continue
    if hasattr(torch.ops.torchvision, "nms"):
        return None  # the extension loaded: torchvision is whole
    lib = torch.library.Library("torchvision", "DEF")
    for name in ("nms", "qnms"):
        lib.define(f"{name}(Tensor dets, Tensor scores, float iou_threshold) -> Tensor")
    return lib


_TORCHVISION_SCHEMAS = _declare_torchvision_schemas()

REPO_ROOT = Path(__file__).resolve().parents[1]
#: the real-data folder: HSI_TORCH_DATA, else ../shared/data/real beside the checkout (or None)
REAL_DATA = real_data_dir()

_DTYPES = {"float32": torch.float32, "float64": torch.float64}
_DTYPE_IDS = {torch.float32: "f32", torch.float64: "f64"}


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--device", action="store", default="cpu",
        help="torch devices the tests run on: cpu (default), cuda, cuda:N, a comma-separated "
             "list, or 'all' (cpu and cuda when available)",
    )  # fmt: skip
    parser.addoption(
        "--dtype", action="store", default="float32,float64",
        help="floating dtypes of the dtype-parametrised tests: float32, float64, a "
             "comma-separated list, or 'all' (default: float32,float64)",
    )  # fmt: skip


def _selected_devices(config: pytest.Config) -> list[str]:
    raw = str(config.getoption("--device"))
    if raw == "all":
        return ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    names = [d.strip() for d in raw.split(",") if d.strip()]
    for d in names:
        if d.startswith("cuda") and not torch.cuda.is_available():
            raise pytest.UsageError(f"--device {d}: CUDA is not available on this machine")
        try:
            torch.device(d)
        except RuntimeError as exc:
            raise pytest.UsageError(f"--device {d}: not a torch device ({exc})") from None
    return names


def _selected_dtypes(config: pytest.Config) -> list[torch.dtype]:
    raw = str(config.getoption("--dtype"))
    names = list(_DTYPES) if raw == "all" else [d.strip() for d in raw.split(",") if d.strip()]
    unknown = [d for d in names if d not in _DTYPES]
    if unknown:
        raise pytest.UsageError(f"--dtype: unknown {unknown}; choose from {list(_DTYPES)}")
    return [_DTYPES[d] for d in names]


def _explicit(metafunc: pytest.Metafunc, name: str) -> bool:
    """The test parametrises ``name`` itself (e.g. integer dtypes of a file reader)."""
    for mark in metafunc.definition.iter_markers("parametrize"):
        names = mark.args[0]
        names = names.split(",") if isinstance(names, str) else names
        if name in (n.strip() for n in names):
            return True
    return False


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    """Parametrise every test that asks for ``device`` / ``dtype`` with the selected values."""
    if "device" in metafunc.fixturenames and not _explicit(metafunc, "device"):
        devs = _selected_devices(metafunc.config)
        metafunc.parametrize("device", [torch.device(d) for d in devs], ids=devs)
    if "dtype" in metafunc.fixturenames and not _explicit(metafunc, "dtype"):
        dts = _selected_dtypes(metafunc.config)
        metafunc.parametrize("dtype", dts, ids=[_DTYPE_IDS[d] for d in dts])


@pytest.fixture
def real_data() -> Path:
    """The folder of real data (``HSI_TORCH_DATA`` or ``../shared/data/real`` beside the project);
    skips the test when there is none."""
    if REAL_DATA is None:
        pytest.skip(f"no real-data folder ({DATA_ENV} unset and ../shared/data/real absent)")
    return REAL_DATA


@pytest.fixture
def ws(tmp_path: Path) -> tuple[Path, Path, Path]:
    """A tiny bundle ``calib.npz`` and one capture ``caps/a.npy`` made from it (a module may
    define its own ``ws`` instead)."""
    import numpy as np
    from test_pipeline import make_bundle, render_capture, true_spectra

    bundle = make_bundle(white_exposure_s=0.01, cfa_pattern="RGGB")
    bpath = tmp_path / "calib.npz"
    bundle.save(bpath)
    caps = tmp_path / "caps"
    caps.mkdir()
    np.save(caps / "a.npy", render_capture(bundle, true_spectra()).numpy())
    return tmp_path, bpath, caps


# ------------------------------------------------------------------ shared simulated sets
#: the small prototype's fast settings: float32 render, no figures, no progress bar
SMALL_SIM_FAST = ("render.figures=false", "render.progress=false", "render.dtype=float32")


def _digests(folder: Path) -> dict[str, str]:
    """SHA-256 of every file below ``folder`` (relative path → digest)."""
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}  # fmt: skip


def _simulate_shared(out: Path, *overrides: str) -> Path:
    from hsi_torch.cli import main
    from hsi_torch.resources import shipped_config

    args = ["simulate", "--config", str(shipped_config("simulate")), "--out", str(out)]
    for o in (*SMALL_SIM_FAST, *overrides):
        args += ["--set", o]
    assert main(args) == 0
    return out


def _read_only_check(folder: Path) -> Iterator[Path]:
    """Yield ``folder``; afterwards fail when a test changed it (the shared folders are
    read-only: a test that needs to change one copies it first)."""
    before = _digests(folder)
    yield folder
    after = _digests(folder)
    changed = sorted(k for k in before.keys() | after.keys() if before.get(k) != after.get(k))
    assert not changed, f"a test changed the shared folder {folder}: {changed[:10]}"


@pytest.fixture(scope="session")
def small_sim(tmp_path_factory) -> Iterator[Path]:
    """The shipped small prototype's capture set with its ColorChecker scene (``simulate
    --config simulate.yaml`` with :data:`SMALL_SIM_FAST`), simulated once per session and shared
    by every module that needs it (each simulation is tens of seconds on 2 cores). Read-only:
    the session fails at its end when a test changed a file of it."""
    out = _simulate_shared(tmp_path_factory.mktemp("shared_sim") / "sim")
    yield from _read_only_check(out)


@pytest.fixture(scope="session")
def small_sim_calib(small_sim: Path, tmp_path_factory) -> Iterator[Path]:
    """``hsi-torch calibrate --captures small_sim --out DIR`` (the shipped calibrate.yaml), once
    per session; returns ``DIR`` (``DIR/calib.npz``, its report). Read-only, as ``small_sim``."""
    from hsi_torch.cli import main

    out = tmp_path_factory.mktemp("shared_calib") / "calib"
    assert main(["calibrate", "--captures", str(small_sim), "--out", str(out), "--no-progress",
                 "-q"]) == 0  # fmt: skip
    yield from _read_only_check(out)

