"""End-to-end CLI regressions found by exercising ``hsi-torch`` as a user (QA pass).

Each test pins one defect that was found and fixed: resume after a settings change, nothing left
behind by a run that fails before processing, output-path errors, PNG permissions, calibrate
``--out`` handling, ``bench <target> --help``, the experiment summary line, bundle-load messages,
Bayer files without metadata, the shipped default β.
"""

from __future__ import annotations

import os
import stat
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from test_pipeline import make_bundle, render_capture, true_spectra

from hsi_torch.cli import main
from hsi_torch.io import load_cube, write_capture
from hsi_torch.io.paths import expand_inputs
from hsi_torch.io.raw import mosaic
from hsi_torch.resources import shipped_config


@pytest.fixture
def ws(tmp_path):
    bundle = make_bundle(white_exposure_s=0.01, cfa_pattern="RGGB")
    bpath = tmp_path / "calib.npz"
    bundle.save(bpath)
    caps = tmp_path / "caps"
    caps.mkdir()
    s = true_spectra()
    img = render_capture(bundle, s)
    np.save(caps / "a.npy", img.numpy())
    return tmp_path, bpath, caps, img


def _rec(bpath, out, *extra):
    return main(["reconstruct", "--bundle", str(bpath), "--out", str(out), "--no-progress",
                 "--set", "dtype=float64", *extra])  # fmt: skip


def _bump_mtime(p: Path) -> None:
    st = p.stat()
    os.utime(p, ns=(st.st_atime_ns, st.st_mtime_ns + 5_000_000_000))


def test_resume_redoes_inputs_when_config_bundle_or_input_change(ws, capsys):
    tmp, bpath, caps, img = ws
    out = tmp / "out"
    a = str(caps / "a.npy")
    assert _rec(bpath, out, "--set", "beta=0", a) == 0
    assert "1 processed" in capsys.readouterr().err
    assert _rec(bpath, out, "--set", "beta=0", a) == 0  # same settings: skipped
    assert "1 skipped" in capsys.readouterr().err
    # another beta: the old cube must not be kept while the run records claim beta=5
    assert _rec(bpath, out, "--set", "beta=5", a) == 0
    assert "1 processed" in capsys.readouterr().err
    meta = load_cube(out / "a.npz").metadata
    assert meta["config"]["beta"] == 5.0
    assert "beta: 5.0" in (out / meta["run_config"]).read_text()  # this run's own record
    # the input file was replaced (re-simulated): redone, and the new content is in the cube
    np.save(caps / "a.npy", 0.5 * img.numpy())
    _bump_mtime(caps / "a.npy")
    assert _rec(bpath, out, "--set", "beta=5", a) == 0
    assert "1 processed" in capsys.readouterr().err
    # the same bundle touched: known by its content, still skipped
    _bump_mtime(bpath)
    assert _rec(bpath, out, "--set", "beta=5", a) == 0
    assert "1 skipped" in capsys.readouterr().err
    # a recalibrated bundle at the same path: redone
    make_bundle(white_exposure_s=0.01, cfa_pattern="RGGB", seed=3).save(bpath)
    assert _rec(bpath, out, "--set", "beta=5", a) == 0
    assert "1 processed" in capsys.readouterr().err
    # the device is not a setting of the result: still skipped
    assert _rec(bpath, out, "--set", "beta=5", "--device", "cpu", a) == 0
    assert "1 skipped" in capsys.readouterr().err


def test_failing_before_processing_leaves_nothing(ws, capsys):
    tmp, bpath, caps, _ = ws
    out = tmp / "never"
    assert _rec(bpath, out, str(caps / "*.tif")) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "matches no files" in err
    assert not out.exists()  # no folder with the record of a run that never ran
    assert _rec(bpath, out, "--set", "betta=1", str(caps / "a.npy")) == 1
    assert "did you mean 'beta'" in capsys.readouterr().err and not out.exists()


def test_output_path_errors_are_one_clear_line(ws, capsys):
    tmp, bpath, caps, _ = ws
    f = tmp / "afile"
    f.write_text("x")
    assert _rec(bpath, f, str(caps / "a.npy")) == 1
    err = capsys.readouterr().err
    assert err == f"hsi-torch: error: output folder {f} exists and is not a folder\n"
    assert _rec(bpath, f / "sub", str(caps / "a.npy")) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"hsi-torch: error: cannot create output folder {f / 'sub'}: ")
    assert "Errno" not in err and err.count("\n") == 1


def test_literal_path_with_glob_characters(tmp_path):
    p = tmp_path / "scan[1].tif"
    p.write_bytes(b"")
    (tmp_path / "scan1.tif").write_bytes(b"")
    assert expand_inputs([str(p)]) == [p]  # the file itself, not the pattern's match scan1.tif


def test_pngs_get_ordinary_permissions(ws):
    tmp, bpath, caps, _ = ws
    out = tmp / "out"
    assert _rec(bpath, out, "--set", "spectra_pixels=[[10, 10]]", str(caps / "a.npy")) == 0
    umask = os.umask(0)
    os.umask(umask)
    want = 0o666 & ~umask
    for name in ("a_preview.png", "a_spectra.png", "a.npz", "a.tif"):
        assert stat.S_IMODE((out / name).stat().st_mode) == want, name  # was 0600 for PNGs


def test_bayer_file_without_metadata_uses_bundle_cfa_and_config_levels(ws, capsys):
    tmp, bpath, caps, img = ws
    scale = 30000.0 / float(img.max())  # well below the uint16 white level: nothing saturated
    raw = torch.round(mosaic(img, "RGGB") * scale + 64.0).to(torch.int32)
    raw16 = raw.numpy().astype(np.uint16)
    np.save(caps / "bayer.npy", raw16[0])  # plain (H, W) uint16, no metadata at all
    write_capture(caps / "meta.tif", raw16, {"kind": "bayer", "cfa_pattern": "RGGB",
                                             "black_level": 64, "white_level": 65535})
    out = tmp / "out"
    assert _rec(bpath, out, "--set", "black_level=64", "--set", "beta=0",
                str(caps / "bayer.npy"), str(caps / "meta.tif")) == 0  # fmt: skip
    a, b = load_cube(out / "bayer.npz"), load_cube(out / "meta.npz")
    assert torch.equal(a.valid, b.valid) and int(a.valid.sum()) > 100
    torch.testing.assert_close(a.cube[:, a.valid], b.cube[:, b.valid], rtol=0, atol=0)
    # the black level matters: without it the same file gives another cube
    capsys.readouterr()
    assert _rec(bpath, tmp / "out0", "--set", "beta=0", str(caps / "bayer.npy")) == 0
    c = load_cube(tmp / "out0" / "bayer.npz")
    assert float((c.cube[:, c.valid] - a.cube[:, a.valid]).abs().max()) > 1e-2
    # a bundle without a CFA pattern: the error says how to give one on the command line
    nb = tmp / "nocfa.npz"
    make_bundle(white_exposure_s=0.01).save(nb)
    assert _rec(nb, tmp / "out1", str(caps / "bayer.npy")) == 1
    assert "--set cfa_pattern=" in capsys.readouterr().err


def test_shipped_reconstruct_config_is_the_schema_default():
    from hsi_torch.config import load_config
    from hsi_torch.recon.config import ReconstructConfig

    cfg = load_config(shipped_config("reconstruct"), ReconstructConfig)
    assert cfg == ReconstructConfig()
    # beta = 1 gave 17 dB on the default prototype's ColorChecker interiors, 1e4 gives 35.5 dB
    assert cfg.beta == 1e4


def test_calibrate_out_is_a_folder_like_every_out(tmp_path, capsys):
    """--out DIR means DIR/calib.npz (+ report, figure, resolved config); a bad capture folder
    writes nothing, neither there nor a DIR.npz beside it."""
    d = tmp_path / "bundles"
    d.mkdir()
    rc = main(["calibrate", "--captures", str(tmp_path / "nothing"), "--out", str(d)])
    assert rc == 1
    assert list(d.iterdir()) == [] and not (tmp_path / "bundles.npz").exists()
    (d / "calib.npz").mkdir()  # the bundle's own path taken by a folder: refused, named
    assert main(["calibrate", "--captures", str(tmp_path), "--out", str(d)]) == 1
    assert f"--out {d / 'calib.npz'} is a folder" in capsys.readouterr().err


def test_calibrate_output_paths_folder_and_file_forms():
    from hsi_torch.calibrate.cli_entry import figure_path, output_paths

    assert output_paths("cal/first.npz") == (
        Path("cal/first.npz"), Path("cal/first.report.json"),
        Path("cal/first.resolved_config.yaml"))  # fmt: skip
    assert output_paths("cal/second") == (
        Path("cal/second/calib.npz"), Path("cal/second/calib.report.json"),
        Path("cal/second/resolved_config.yaml"))  # fmt: skip
    assert figure_path("cal/first.npz") == Path("cal/first_diagnostics.png")
    assert figure_path(output_paths("cal/second")[0]) == Path("cal/second/calib_diagnostics.png")


def test_bench_help_reaches_the_script(capsys):
    assert main(["bench", "solver", "--help"]) == 0
    assert "--pixels" in capsys.readouterr().out  # the script's options, not the wrapper's
    assert main(["bench", "pipeline", "-h"]) == 0
    assert "--tile" in capsys.readouterr().out
    assert main(["bench", "--help"]) == 0
    text = capsys.readouterr().out
    assert "solver" in text and "pipeline" in text and "--pixels" not in text


# a tiny experiment, registered by the test below, to check the CLI's closing line
from dataclasses import dataclass  # noqa: E402


@dataclass
class _FakeCfg:
    n: int = 2


def _fake_run(cfg: _FakeCfg, out: Path, *, device=None) -> dict:
    for i in range(cfg.n):
        (out / f"table{i}.csv").write_text("a,b\n")
    return {}


def test_experiment_reports_where_results_went(tmp_path, capsys):
    from hsi_torch.experiments.cli_entry import EXPERIMENTS, register_experiment

    register_experiment("qa_fake", __name__, "_FakeCfg", "_fake_run")
    try:
        t0 = time.perf_counter()
        assert main(["experiment", "qa_fake", "--out", str(tmp_path / "e"), "--set", "n=3"]) == 0
        assert time.perf_counter() - t0 < 30
    finally:
        EXPERIMENTS.pop("qa_fake")
    out = capsys.readouterr().out
    assert "experiment 'qa_fake' finished" in out and str(tmp_path / "e") in out
    assert "table2.csv" in out and "resolved_config.yaml" in out


def test_bundle_junk_message_is_not_about_pickles(tmp_path, capsys, ws):
    _, _, caps, _ = ws
    junk = tmp_path / "x.dng"
    junk.write_bytes(np.random.default_rng(0).bytes(4096))
    assert main(["reconstruct", "--bundle", str(junk), "--out", str(tmp_path / "o"),
                 str(caps / "a.npy")]) == 1  # fmt: skip
    err = capsys.readouterr().err
    assert f"calibration bundle {junk}: not a readable NPZ file" in err
    assert "pickle" not in err and not (tmp_path / "o").exists()
    other = tmp_path / "other.npz"
    np.savez(other, a=np.zeros(3))
    assert main(["reconstruct", "--bundle", str(other), "--out", str(tmp_path / "o"),
                 str(caps / "a.npy")]) == 1  # fmt: skip
    assert "not a bundle written by 'hsi-torch calibrate'" in capsys.readouterr().err


def _raise_missing_cuda(cfg: _FakeCfg, out: Path, *, device=None) -> dict:
    raise AssertionError("Torch not compiled with CUDA enabled")  # what torch raises


def test_unavailable_device_is_a_clear_error_before_any_output(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    out = tmp_path / "sim"
    assert main(["simulate", "--out", str(out), "--device", "cuda"]) == 1
    err = capsys.readouterr().err
    assert err == ("hsi-torch: error: --device 'cuda': CUDA is not available on this "
                   "machine/torch build\n")
    assert not out.exists()  # simulate used to create the folder, then crash with AssertionError
    assert main(["demo", "--out", str(out), "--device", "gpu"]) == 1
    assert "--device 'gpu': not a torch device" in capsys.readouterr().err
    # a config key 'device: cuda' reaches torch, whose AssertionError is reported as a user error
    from hsi_torch.experiments.cli_entry import EXPERIMENTS, register_experiment

    register_experiment("qa_cuda", __name__, "_FakeCfg", "_raise_missing_cuda")
    try:
        assert main(["experiment", "qa_cuda", "--out", str(tmp_path / "e")]) == 1
    finally:
        EXPERIMENTS.pop("qa_cuda")
    err = capsys.readouterr().err
    assert "CUDA is not available" in err and "unexpected error" not in err


@pytest.mark.parametrize("command", [["simulate"], ["demo"], ["experiment", "opd"]])
def test_folder_out_that_is_a_file(tmp_path, capsys, command):
    f = tmp_path / "afile"
    f.write_text("x")
    assert main([*command, "--out", str(f)]) == 1
    err = capsys.readouterr().err
    assert err == f"hsi-torch: error: output folder {f} exists and is not a folder\n"


def test_spectra_plot_leaves_invalid_points_out(ws, monkeypatch):
    import hsi_torch.colour as colour

    tmp, bpath, caps, _ = ws
    seen = {}
    real = colour.plot_spectra

    def spy(wl, spectra, **kw):
        seen["spectra"] = torch.as_tensor(spectra).clone()
        return real(wl, spectra, **kw)

    monkeypatch.setattr(colour, "plot_spectra", spy)
    # (1, 1) lies in the 2-view corner of the test bundle (invalid), (10, 10) is valid
    assert _rec(bpath, tmp / "out", "--set", "spectra_pixels=[[10, 10], [1, 1]]", "--set", "beta=0",
                str(caps / "a.npy")) == 0  # fmt: skip
    s = seen["spectra"]
    assert torch.isfinite(s[0]).all() and float(s[0].max()) > 0.1
    assert torch.isnan(s[1]).all()  # was drawn as a flat zero "spectrum"
    assert (tmp / "out" / "a_spectra.png").stat().st_size > 1000
