"""`pip install hsi-torch` works anywhere: the built wheel, installed into a fresh virtual
environment, runs `hsi-torch demo --quick`, `hsi-torch simulate` (the README's default prototype)
and `hsi-torch experiment synthetic` from an empty folder.

Offline by construction: an sdist is built from a copy of the sources (setuptools' PEP 517 hook)
and the wheel from the unpacked sdist without build isolation (`pip wheel --no-deps
--no-build-isolation`, the machine's setuptools), so the top-level `configs/` folder is checked
to travel through both; the venv is a plain one whose ``.pth`` file adds the running
interpreter's site-packages folders after its own (torch and the other dependencies come from the
environment running the tests: a venv, a conda env or a system Python — ``venv
--system-site-packages`` would see only the *base* Python's packages from inside a venv), and the
wheel is installed with `--no-index --no-deps`; the declared dependencies are then checked
against what the venv sees. Skipped, with the reason, when
the wheel cannot be built here. The subprocesses run without PYTHONPATH, so the package they
import is the installed wheel (checked).
"""

from __future__ import annotations

import os
import shutil
import site
import subprocess
import sys
import sysconfig
import tarfile
import zipfile
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
SHIPPED_CONFIGS = ("simulate", "simulate_full", "calibrate", "reconstruct", "synthetic", "design",
                   "opd", "usaf")  # fmt: skip


def _run(cmd: list[str], cwd: Path, env: dict[str, str], timeout: int = 600):
    return subprocess.run([str(c) for c in cmd], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=timeout)  # fmt: skip


def _tail(r: subprocess.CompletedProcess) -> str:
    return (r.stdout[-1500:] + "\n" + r.stderr[-3000:]).strip()


def _running_site_dirs() -> list[str]:
    """The site-packages folders of the interpreter running the tests, in its order: its own
    (a venv's or conda env's), then the base Python's where it sees them, then the user's."""
    dirs = list(site.getsitepackages())
    if site.ENABLE_USER_SITE:
        dirs.append(site.getusersitepackages())
    for key in ("purelib", "platlib"):
        dirs.append(sysconfig.get_paths()[key])
    out: list[str] = []
    for d in dirs:
        if os.path.isdir(d) and d not in out:
            out.append(d)
    return out


def _see_running_packages(py: Path, cwd: Path, env: dict[str, str]) -> None:
    """Make the fresh venv of ``py`` see the running interpreter's packages (torch, kornia, …):
    a ``.pth`` file in its site-packages adds the running interpreter's site folders after its
    own (``site.addsitedir``, so their own ``.pth`` files apply). ``venv --system-site-packages``
    does not do this from inside a venv or conda env: it points at the *base* Python, which
    lacks the environment's packages."""
    r = _run([py, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], cwd, env)
    assert r.returncode == 0, _tail(r)
    purelib = Path(r.stdout.strip().splitlines()[-1])
    purelib.mkdir(parents=True, exist_ok=True)
    lines = [f"import site; site.addsitedir({d!r})" for d in _running_site_dirs()]
    (purelib / "_hsi_torch_test_running_env.pth").write_text("\n".join(lines) + "\n")


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """``(venv python, env, wheel)``: the wheel built from this checkout, installed in a venv."""
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "src"
    src.mkdir()
    for name in ("pyproject.toml", "setup.py", "README.md"):
        shutil.copy(REPO / name, src / name)
    for folder in ("hsi_torch", "configs"):
        shutil.copytree(REPO / folder, src / folder,
                        ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))  # fmt: skip
    env = {k: v for k, v in os.environ.items()
           if k not in ("PYTHONPATH", "HSI_TORCH_DATA", "PIP_REQUIRE_VIRTUALENV")}  # fmt: skip
    env["PIP_DISABLE_PIP_VERSION_CHECK"] = "1"
    # the sdist first (what an index serves), then the wheel built from the unpacked sdist: the
    # configs/ folder must travel through both
    r = _run([sys.executable, "-c", "import sys; from setuptools import build_meta as b; "
              "print(b.build_sdist(sys.argv[1]))", tmp / "sdist"], src, env)  # fmt: skip
    if r.returncode != 0:
        pytest.skip(f"cannot build the sdist offline here: {_tail(r)[-600:]}")
    sdist = tmp / "sdist" / r.stdout.strip().splitlines()[-1]
    with tarfile.open(sdist) as tar:
        members = tar.getnames()
        safe = {"filter": "data"} if hasattr(tarfile, "data_filter") else {}
        tar.extractall(tmp / "unpacked", **safe)
    top = members[0].split("/")[0]
    for cfg in SHIPPED_CONFIGS:
        assert f"{top}/configs/{cfg}.yaml" in members, cfg
    assert not any("/hsi_torch/configs/" in m for m in members)  # one copy, at the top
    r = _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
              "--no-index", "-w", tmp / "dist", tmp / "unpacked" / top], tmp, env)  # fmt: skip
    wheels = sorted((tmp / "dist").glob("hsi_torch-*.whl"))
    if r.returncode != 0 or not wheels:
        pytest.skip(f"cannot build the wheel offline here: {_tail(r)[-600:]}")
    venv = tmp / "venv"
    r = _run([sys.executable, "-m", "venv", "--without-pip", venv], tmp, env)
    if r.returncode != 0:
        pytest.skip(f"cannot create a virtual environment here: {_tail(r)[-600:]}")
    py = venv / "bin" / "python"
    _see_running_packages(py, tmp, env)
    r = _run([py, "-m", "pip", "install", "--no-index", "--no-deps", wheels[0]], tmp, env)
    assert r.returncode == 0, _tail(r)
    env["PATH"] = f"{venv / 'bin'}{os.pathsep}{env.get('PATH', '')}"
    env["VIRTUAL_ENV"] = str(venv)
    return py, env, wheels[0]


@pytest.mark.slow
def test_wheel_holds_configs_and_data(installed):
    *_, wheel = installed
    names = zipfile.ZipFile(wheel).namelist()
    for cfg in SHIPPED_CONFIGS:
        assert f"hsi_torch/configs/{cfg}.yaml" in names, cfg
    assert "hsi_torch/data/lee_068_sky_blue.csv" in names
    assert "hsi_torch/data/README.md" in names
    assert "hsi_torch/io/capture_set.schema.json" in names  # the manifest's published schema
    meta = zipfile.ZipFile(wheel).read(next(n for n in names if n.endswith("/METADATA")))
    requires = [ln for ln in meta.decode().splitlines() if ln.startswith("Requires-Dist:")]
    base = [r for r in requires if "extra ==" not in r]
    assert not any("scipy" in r or "lighting" in r.lower() for r in base), base
    assert any("xarray" in r and "formats" in r for r in requires)


@pytest.mark.slow
def test_installed_commands_run_from_an_empty_folder(installed, tmp_path):
    py, env, _ = installed
    work = tmp_path / "empty"
    work.mkdir()
    # the package imported is the wheel's, and its declared dependencies are all satisfied
    check = (
        "import hsi_torch, importlib.metadata as md, sys\n"
        "from packaging.requirements import Requirement\n"
        "print(hsi_torch.__file__)\n"
        "bad = []\n"
        "for r in map(Requirement, md.requires('hsi-torch') or []):\n"
        "    if r.marker is not None and 'extra' in str(r.marker):\n"
        "        continue\n"
        "    try:\n"
        "        v = md.version(r.name)\n"
        "    except md.PackageNotFoundError:\n"
        "        bad.append(r.name); continue\n"
        "    if not r.specifier.contains(v, prereleases=True):\n"
        "        bad.append(f'{r.name} {v}')\n"
        "print('MISSING', bad)\n"
    )
    r = _run([py, "-c", check], work, env)
    assert r.returncode == 0, _tail(r)
    where, missing = r.stdout.strip().splitlines()[-2:]
    assert Path(where).resolve().is_relative_to(Path(py).parent.parent.resolve()), where
    assert missing == "MISSING []", missing

    hsi = [str(Path(py).parent / "hsi-torch")]
    r = _run([*hsi, "demo", "--quick", "--no-progress"], work, env)
    assert r.returncode == 0, _tail(r)
    out = work / "demo_output"
    for f in ("calib.npz", "calib_diagnostics.png", "colorchecker.tif", "colorchecker.vrt",
              "colorchecker_panel.png", "summary.json"):  # fmt: skip
        assert (out / f).is_file(), f
    assert "colorchecker: 24 patches" in r.stdout

    args = ["simulate", "--out", "x", "-q", "--set", "camera.scale=0.5",
            "--set", "captures.scenes=[]", "--set", "render.figures=false"]  # fmt: skip
    r = _run([*hsi, *args], work, env)
    assert r.returncode == 0, _tail(r)
    assert r.stdout == ""  # -q
    cfg = yaml.safe_load((work / "x" / "resolved_config.yaml").read_text())
    # the README's default prototype: tube 16 -> 40 mm, quartz 2.5 mm / 70 deg / 40 deg, 0.1 mm
    assert cfg["geometry"]["a_out_mm"] == 40.0 and cfg["geometry"]["a_in_mm"] == 16.0
    assert (cfg["brf"]["material"], cfg["brf"]["thickness_mm"], cfg["brf"]["axis_tilt_deg"],
            cfg["brf"]["axis_azimuth_deg"]) == ("quartz", 2.5, 70.0, 40.0)  # fmt: skip
    assert cfg["diffuser"]["blur_sigma_mm"] == 0.1
    assert (work / "x" / "manifest.json").is_file() and (work / "x" / "ground_truth").exists()

    r = _run([*hsi, "experiment", "synthetic", "--out", "y", "--set", "num_seeds=1",
              "--set", "noise_sigmas=[1]", "--set", "betas=[100]"], work, env)  # fmt: skip
    assert r.returncode == 0, _tail(r)
    assert (work / "y" / "results.csv").is_file() and "\r" not in r.stderr
    assert sorted(p.name for p in work.iterdir()) == ["demo_output", "x", "y"]
