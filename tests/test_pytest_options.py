"""The suite's ``--device`` / ``--dtype`` options (tests/conftest.py) select the parametrisation."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _collect(*opts: str) -> tuple[int, str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    out = subprocess.run(
        [sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider",
         "tests/test_spectral.py::test_resample_matches_numpy_interp", *opts],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    return out.returncode, out.stdout + out.stderr


def test_default_is_cpu_both_dtypes() -> None:
    rc, out = _collect()
    assert rc == 0, out
    ids = sorted(line.split("[")[1].rstrip("]") for line in out.splitlines() if "[" in line)
    assert ids == ["cpu-f32", "cpu-f64"], out


def test_dtype_option_selects() -> None:
    rc, out = _collect("--dtype", "float64")
    assert rc == 0, out
    ids = [line.split("[")[1].rstrip("]") for line in out.splitlines() if "[" in line]
    assert ids == ["cpu-f64"], out


def test_bad_options_are_usage_errors() -> None:
    rc, out = _collect("--dtype", "float16")
    assert rc != 0 and "--dtype: unknown ['float16']" in out
    rc, out = _collect("--device", "nonsense")
    assert rc != 0 and "--device nonsense: not a torch device" in out
