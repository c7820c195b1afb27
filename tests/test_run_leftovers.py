"""A run that makes nothing leaves nothing behind; the spectra plot shows the ±1σ band when the
run computed the uncertainty."""

from __future__ import annotations

import numpy as np
import torch
from test_pipeline import make_bundle, render_capture, true_spectra

from hsi_torch import colour
from hsi_torch.cli import main


def test_a_run_whose_only_input_is_missing_leaves_no_folder(tmp_path, capsys):
    bpath = tmp_path / "calib.npz"
    make_bundle().save(bpath)
    out = tmp_path / "out"
    code = main(["reconstruct", "--bundle", str(bpath), "--out", str(out), "--no-progress",
                 str(tmp_path / "missing.tif")])  # fmt: skip
    assert code == 1
    assert "missing.tif" in capsys.readouterr().err
    assert not out.exists()  # created by this run, emptied again
    # an existing folder is kept as it was: no runs/ folder, no configuration file left in it
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    assert main(["reconstruct", "--bundle", str(bpath), "--out", str(out), "--no-progress",
                 str(tmp_path / "missing.tif")]) == 1  # fmt: skip
    assert sorted(p.name for p in out.iterdir()) == ["keep.txt"]


def test_spectra_plot_draws_the_sigma_band():
    wl = torch.arange(430.0, 671.0, 10.0)
    spectra = torch.rand(3, 25)
    plain = colour.plot_spectra(wl, spectra)
    banded = colour.plot_spectra(wl, spectra, std=0.05 * torch.ones(3, 25))
    n_plain = sum(len(ax.collections) for ax in plain.axes)
    n_banded = sum(len(ax.collections) for ax in banded.axes)
    assert n_banded == n_plain + 3  # one shaded band per spectrum
    band = banded.axes[0].collections[0].get_paths()[0].vertices
    assert np.isclose(band[:, 1].max(), float(spectra[0].max()) + 0.05, atol=1e-6)


def test_uncertainty_run_plots_spectra_with_the_band(tmp_path, monkeypatch):
    bundle = make_bundle(white_exposure_s=0.01)
    bpath = tmp_path / "calib.npz"
    bundle.save(bpath)
    np.save(tmp_path / "a.npy", render_capture(bundle, true_spectra()).numpy())
    seen = {}
    real = colour.plot_spectra

    def spy(*args, **kwargs):
        seen["std"] = kwargs.get("std")
        return real(*args, **kwargs)

    monkeypatch.setattr(colour, "plot_spectra", spy)
    out = tmp_path / "out"
    assert main(["reconstruct", "--bundle", str(bpath), "--out", str(out), "--no-progress",
                 "--set", "uncertainty=true", "--set", "spectra_pixels=[[10, 10]]",
                 str(tmp_path / "a.npy")]) == 0  # fmt: skip
    assert (out / "a_spectra.png").is_file()
    std = seen["std"]
    assert std is not None and std.shape == (1, bundle.wavelengths_nm.size)
    assert bool((std[torch.isfinite(std)] >= 0).all())
