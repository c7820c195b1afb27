"""The suite's ``--device`` / ``--dtype`` options (tests/conftest.py) select the parametrisation."""

from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _collect(capsys: pytest.CaptureFixture[str], *opts: str) -> tuple[int, str]:
    """``pytest --collect-only`` of one dtype/device-parametrised test with ``opts``, run in this
    process (``pytest.main``: a new session with this conftest, no second torch import)."""
    rc = pytest.main(["--collect-only", "-q", "-p", "no:cacheprovider", "--rootdir", str(ROOT),
                      str(ROOT / "tests/test_spectral.py") + "::test_resample_matches_numpy_interp",
                      *opts])  # fmt: skip
    out = capsys.readouterr()
    return int(rc), out.out + out.err


def test_default_is_cpu_both_dtypes(capsys) -> None:
    rc, out = _collect(capsys)
    assert rc == 0, out
    ids = sorted(line.split("[")[1].rstrip("]") for line in out.splitlines() if "[" in line)
    assert ids == ["cpu-f32", "cpu-f64"], out


def test_dtype_option_selects(capsys) -> None:
    rc, out = _collect(capsys, "--dtype", "float64")
    assert rc == 0, out
    ids = [line.split("[")[1].rstrip("]") for line in out.splitlines() if "[" in line]
    assert ids == ["cpu-f64"], out


def test_bad_options_are_usage_errors(capsys) -> None:
    rc, out = _collect(capsys, "--dtype", "float16")
    assert rc == pytest.ExitCode.USAGE_ERROR and "--dtype: unknown ['float16']" in out
    rc, out = _collect(capsys, "--device", "nonsense")
    assert rc == pytest.ExitCode.USAGE_ERROR and "--device nonsense: not a torch device" in out


def test_a_changed_shared_folder_fails_the_session(tmp_path: Path) -> None:
    """The shared sets of tests/conftest.py are read-only: the check behind them passes an
    untouched folder and fails, naming the file, one whose file a test changed or added."""
    import pytest
    from conftest import _read_only_check

    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "a.tif").write_bytes(b"capture")
    check = _read_only_check(tmp_path)
    assert next(check) == tmp_path
    with pytest.raises(StopIteration):
        next(check)  # untouched: passes
    for change in ("rewrite", "add"):
        check = _read_only_check(tmp_path)
        next(check)
        if change == "rewrite":
            (tmp_path / "sub" / "a.tif").write_bytes(b"changed")
        else:
            (tmp_path / "b.json").write_text("{}")
        with pytest.raises(AssertionError, match="a.tif" if change == "rewrite" else "b.json"):
            next(check)
