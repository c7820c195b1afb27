"""``hsi-torch reconstruct``: outputs, bad inputs, resume, resolved config, nothing partial."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_pipeline import make_bundle, render_capture, true_spectra

from hsi_torch.cli import main
from hsi_torch.io import load_cube, write_capture


@pytest.fixture
def workspace(tmp_path):
    bundle = make_bundle(white_exposure_s=0.01)
    bpath = tmp_path / "calib.npz"
    bundle.save(bpath)
    caps = tmp_path / "caps"
    caps.mkdir()
    s = true_spectra()
    img = render_capture(bundle, s).numpy()
    np.save(caps / "a.npy", img)  # float RGB, no metadata
    np.save(caps / "b.npy", 0.5 * img)
    # a uint16 RGB TIFF taken with twice the white reference's exposure
    write_capture(caps / "c.tif", np.round(2 * img).clip(0, 65535).astype(np.uint16),
                  {"kind": "rgb", "exposure_s": 0.02})
    (caps / "corrupt.tif").write_bytes(b"II*\x00garbage")
    np.save(caps / "small.npy", img[:, :30, :30])  # wrong sensor size
    return tmp_path, bpath, caps, s


def _files(d):
    return sorted(p.relative_to(d).as_posix() for p in d.rglob("*") if p.is_file())


def test_reconstruct_cli_end_to_end(workspace, capsys):
    tmp, bpath, caps, s = workspace
    out = tmp / "out"
    argv = ["reconstruct", "--bundle", str(bpath), "--out", str(out), "--no-progress",
            "--set", "beta=0", "--set", "dtype=float64", "--set", "spectra_pixels=[[10, 10]]",
            str(caps / "*.tif"), str(caps / "*.npy")]
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 1
    assert "FAILED" in err and "corrupt.tif" in err and "small.npy" in err
    assert "2 failed" in err and "3 processed" in err
    assert "30x30" in err or "(30, 30)" in err  # the size mismatch is named
    files = _files(out)
    for stem in ("a", "b", "c"):
        for suf in (".npz", ".tif", ".hdr", ".img", "_preview.png", "_spectra.png"):
            assert f"{stem}{suf}" in files
    assert not any(f.startswith(("corrupt", "small")) for f in files)
    assert not any(f.endswith(".tmp") or "/." in f or f.startswith(".") and "done" not in f
                   for f in files)
    (run_cfg,) = [f for f in files if f.startswith("runs/") and f.endswith(".yaml")]
    assert load_cube(out / "a.npz").metadata["run_config"] == run_cfg
    valid = torch.as_tensor(make_bundle().valid)
    a = load_cube(out / "a.npz")
    torch.testing.assert_close(a.cube[:, valid].double(), s[:, valid], rtol=1e-5, atol=1e-5)
    assert torch.equal(a.valid, valid)
    b = load_cube(out / "b.tif")
    torch.testing.assert_close(b.cube[:, valid].double(), 0.5 * s[:, valid], rtol=1e-5,
                               atol=1e-5)
    assert torch.isnan(b.cube[:, ~valid]).all()
    # exposure 0.02 s vs the white reference's 0.01 s: scaled back (uint16 rounding only)
    c = load_cube(out / "c.npz")
    dc = (c.cube[:, valid].double() - s[:, valid]).abs()
    assert float(dc.mean()) < 1e-3 and float(dc.max()) < 2e-2  # (unscaled would be off by ~s)
    assert c.metadata["stats"]["exposure_scale"] == pytest.approx(0.5)
    import spectral

    img = spectral.envi.open(str(out / "a.hdr"))
    np.testing.assert_allclose(img.bands.centers, np.arange(430.0, 641.0, 30.0))
    np.testing.assert_allclose(np.asarray(img.load())[10, 10, :], a.cube[:, 10, 10].numpy())

    # resume: nothing recomputed, outputs untouched; the bad files fail again
    mtimes = {f: (out / f).stat().st_mtime_ns for f in files if not f.startswith("runs/")}
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 1 and "3 skipped" in err
    assert all((out / f).stat().st_mtime_ns == t for f, t in mtimes.items())
    # --no-resume with only the good files: reprocessed, exit 0
    code = main(["reconstruct", "--bundle", str(bpath), "--out", str(out), "--no-progress",
                 "--no-resume", "--set", "formats=[npz]", "--set", "preview=false",
                 str(caps / "a.npy")])
    assert code == 0
    assert (out / "a.npz").stat().st_mtime_ns != mtimes["a.npz"]


def test_reconstruct_cli_errors(workspace, capsys):
    tmp, bpath, caps, _ = workspace
    out = tmp / "out2"
    code = main(["reconstruct", "--bundle", str(bpath), "--out", str(out), "--set", "betta=1",
                 str(caps / "a.npy")])
    assert code == 1 and "betta" in capsys.readouterr().err
    code = main(["reconstruct", "--bundle", str(tmp / "missing.npz"), "--out", str(out),
                 str(caps / "a.npy")])
    assert code == 1 and "missing.npz" in capsys.readouterr().err
    code = main(["reconstruct", "--bundle", str(bpath), "--out", str(out),
                 "--set", "spectra_pixels=[[1, 50]]", str(caps / "a.npy")])
    assert code == 1 and "'spectra_pixels': pixel (row=1, col=50)" in capsys.readouterr().err


def test_spectra_pixels_are_row_col_and_the_old_key_is_refused(workspace, tmp_path, capsys,
                                                                monkeypatch):  # fmt: skip
    """``spectra_points`` was (x, y) while ``view --point`` is (row, col): a pixel copied from
    one to the other was another pixel. The key is now ``spectra_pixels``, [row, col]; the old
    key is refused (command line, config file, Python) saying how to swap it."""
    import hsi_torch.colour as colour
    from hsi_torch.errors import ConfigError
    from hsi_torch.recon.batch import run as run_mod
    from hsi_torch.recon.settings import ReconstructSettings

    tmp, bpath, caps, _ = workspace
    old = ["reconstruct", "--bundle", str(bpath), "--out", str(tmp_path / "o"),
           str(caps / "a.npy")]  # fmt: skip
    assert main([*old, "--set", "spectra_points=[[4, 3]]"]) == 1
    err = capsys.readouterr().err
    assert "renamed to spectra_pixels, whose pixels are [row, col]" in err
    assert "spectra_points=[[400, 300]] becomes spectra_pixels=[[300, 400]]" in err
    cfg = tmp_path / "old.yaml"
    cfg.write_text("spectra_points: [[4, 3]]\n")
    assert main([*old, "--config", str(cfg)]) == 1
    assert "renamed to spectra_pixels" in capsys.readouterr().err
    with pytest.raises(ConfigError, match="renamed to spectra_pixels"):
        ReconstructSettings.from_flat(spectra_points=[[4, 3]])
    assert not (tmp_path / "o").exists()
    # the order: a 20 x 30 frame takes row 5, col 25 and refuses row 25, col 5
    run_mod._check_points([(5, 25)], 20, 30)
    with pytest.raises(ValueError, match=r"pixel \(row=25, col=5\) is outside"):
        run_mod._check_points([(25, 5)], 20, 30)
    # the plot shows the spectrum of row 1, col 3
    plotted = {}
    monkeypatch.setattr(colour, "plot_spectra",
                        lambda wl, spectra, **kw: plotted.update(spectra=spectra, **kw))
    cube = torch.arange(2 * 4 * 6, dtype=torch.float32).reshape(2, 4, 6)
    run_mod._plot_points(cube, torch.ones(4, 6, dtype=torch.bool), torch.tensor([500.0, 510.0]),
                         tmp_path / "x", [(1, 3)])  # fmt: skip
    torch.testing.assert_close(plotted["spectra"][0], cube[:, 1, 3])
    assert plotted["labels"] == ["(row 1, col 3)"]


def test_reconstruct_cli_warns_for_a_bundle_from_another_geometry(workspace, capsys):
    import dataclasses

    tmp, bpath, caps, _ = workspace
    b = make_bundle(white_exposure_s=0.01)
    T = np.array([[1, 0, 5], [0, 1, 5], [0, 0, 1.0]])  # same sizes, views 5 px elsewhere
    H = b.view_homographies
    other = tmp / "other.npz"
    dataclasses.replace(b, view_homographies=np.stack([H[0]] + [T @ h for h in H[1:]])).save(other)
    # a.npy carries no exposure: given here (the white reference's), so only the geometry warns
    argv = ["--no-progress", "--set", "beta=0", "--set", "dtype=float64",
            "--set", "exposure_s=0.01", "--set", "formats=[npz]", "--set", "preview=false",
            str(caps / "a.npy")]
    assert main(["reconstruct", "--bundle", str(bpath), "--out", str(tmp / "ok"), *argv]) == 0
    err = capsys.readouterr().err
    assert "WARNING" not in err
    fit_ok = load_cube(tmp / "ok" / "a.npz").metadata["stats"]["fit_residual"]
    assert main(["reconstruct", "--bundle", str(other), "--out", str(tmp / "bad"), *argv]) == 0
    err = capsys.readouterr().err
    assert "WARNING" in err and "a.npy" in err and "fit residual" in err
    st = load_cube(tmp / "bad" / "a.npz").metadata["stats"]
    assert st["fit_residual"] > 0.1 > 1e-3 > fit_ok and st["num_not_converged"] == 0


def test_frame_findings_limits():
    from hsi_torch.recon.checks import frame_findings
    from hsi_torch.recon.config import ReconstructConfig

    cfg = ReconstructConfig().settings()
    ok = {"fit_residual": 0.03, "num_not_converged": 0, "num_valid": 100, "max_kkt": 1e-7}
    assert frame_findings(ok, cfg) == []
    w = frame_findings({**ok, "fit_residual": 0.25, "num_not_converged": 7}, cfg)
    assert [(f.code, f.severity) for f in w] == [("fit.residual", "warning"),
                                                  ("fit.not_converged", "warning")]
    assert "0.250 > fit_residual_warning=0.15" in w[0].message and "7 of 100 pixels" in w[1].message
    assert (w[0].measured, w[0].limit, w[1].measured) == (0.25, 0.15, 7)
    (e,) = frame_findings({**ok, "fit_residual": 0.9}, cfg)
    assert (e.severity, e.limit) == ("error", 0.5)
    off = ReconstructConfig(fit_residual_warning=None).settings()
    assert frame_findings({**ok, "fit_residual": 0.25}, off) == []
    assert frame_findings({**ok, "fit_residual": float("nan")}, cfg) == []
    with pytest.raises(ValueError, match="fit_residual_warning"):
        ReconstructConfig(fit_residual_warning=0.0)
    with pytest.raises(ValueError, match="fit_residual_limit"):
        ReconstructConfig(fit_residual_limit=-1)


def test_write_outputs_same_files_as_per_format_writers(tmp_path):
    """The shared conversion/NaN fill and the preview's valid= route write the same bytes as
    save_cube per format and the NaN-free copy; a failing format leaves nothing behind."""
    import filecmp
    import zipfile

    from hsi_torch.colour import save_preview_png
    from hsi_torch.io import cube as cube_io
    from hsi_torch.recon.batch.run import write_outputs
    from hsi_torch.recon.config import ReconstructConfig
    from hsi_torch.recon.pipeline import ReconstructionResult

    g = torch.Generator().manual_seed(0)
    M, h, w = 6, 30, 40
    wl = torch.linspace(430.0, 670.0, M, dtype=torch.float64)
    for nan_invalid in (True, False):
        cube = torch.rand(M, h, w, generator=g)
        valid = torch.rand(h, w, generator=g) > 0.3
        cube[:, ~valid] = float("nan") if nan_invalid else 0.0
        kept = cube.clone()
        res = ReconstructionResult(cube, valid, wl, {}, {})
        d = tmp_path / str(nan_invalid)
        tm: dict[str, float] = {}
        written = write_outputs(res, d / "x", ReconstructConfig(), {"k": 1}, timings=tm)
        assert {"npz", "tiff", "envi", "preview"} <= set(tm)
        assert torch.equal(torch.nan_to_num(cube, 7.0), torch.nan_to_num(kept, 7.0))
        assert {q.name for q in written} >= {"x.tif", "x.hdr", "x.img", "x.npz"}
        for suf in (".tif", ".hdr"):
            for p in cube_io.save_cube(d / f"ref{suf}", cube, wl, valid, {"k": 1}):
                if p.suffix == ".vrt":  # names its own TIFF
                    assert p.read_text().replace("ref.tif", "x.tif") == (d / "x.vrt").read_text()
                    continue
                assert filecmp.cmp(p, d / ("x" + p.suffix), shallow=False), p
        ref = cube_io.save_cube(d / "ref.npz", cube, wl, valid, {"k": 1})[0]
        with zipfile.ZipFile(ref) as za, zipfile.ZipFile(d / "x.npz") as zb:
            assert za.namelist() == zb.namelist()
            assert all(za.read(n) == zb.read(n) for n in za.namelist())
        prev = torch.where(valid.unsqueeze(0), torch.nan_to_num(cube, nan=0.0), 0.0)
        ref_png = save_preview_png(prev, wl, d / "ref.png", caption="x | beta 10000 | sRGB D65",
                                   min_size=512)  # fmt: skip
        assert filecmp.cmp(ref_png, d / "x_preview.png", shallow=False)
    # one output that fails (here the preview): every file of the stem is removed
    import hsi_torch.colour as colour

    def boom(*a, **k):
        raise OSError("disk full")

    orig_prev = colour.save_preview_png
    colour.save_preview_png = boom
    try:
        with pytest.raises(OSError, match="disk full"):
            write_outputs(res, tmp_path / "g", ReconstructConfig(spectra_pixels=[[2, 1]]))
    finally:
        colour.save_preview_png = orig_prev
    assert not any(p.name.startswith("g") for p in tmp_path.iterdir())
    # a format that fails: the formats already written by the call are removed
    orig = cube_io._save_envi
    cube_io._save_envi = boom
    try:
        with pytest.raises(OSError, match="disk full"):
            cube_io.save_cube_formats(tmp_path / "f", cube, wl, valid,
                                      formats=("npz", "tiff", "envi"))
    finally:
        cube_io._save_envi = orig
    assert not any(p.name.startswith("f") for p in tmp_path.iterdir())


def test_preview_percentile_equals_torch_quantile():
    """The preview's percentile (two kthvalue selections) is bit-identical to torch.quantile."""
    from hsi_torch.colour import _robust_max

    g = torch.Generator().manual_seed(0)
    for dt in (torch.float32, torch.float64):
        for n in (1, 2, 7, 1000, 64_071, 640_700):
            y = torch.rand(2, n, generator=g, dtype=dt) ** 3
            y[1, : n // 2] = 0  # many ties, as the invalid pixels of a preview
            for q in (99.5, 50.0, 100.0, 0.1):
                ref = torch.quantile(y, q / 100.0, dim=-1)
                assert torch.equal(_robust_max(y, q), ref), (dt, n, q)
    y = torch.rand(1, 100, generator=g)
    y[0, 3] = float("nan")
    assert torch.isnan(_robust_max(y, 99.5)).all()  # NaN as torch.quantile
