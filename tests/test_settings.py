"""The reconstruction's settings: one frozen, nested object built from the flat configuration,
validated where it is built, passed whole, and the key of the workers' reconstructor cache."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from test_pipeline import make_bundle, render_capture, true_spectra

from hsi_torch.config import ConfigError, load_config
from hsi_torch.recon.batch import tasks
from hsi_torch.recon.batch.run import check_run
from hsi_torch.recon.config import ReconstructConfig
from hsi_torch.recon.module import HSIReconstructor
from hsi_torch.recon.pipeline import Reconstructor
from hsi_torch.recon.settings import (
    FLAT_KEYS,
    GROUPS,
    ReconstructSettings,
    SolveSettings,
)


def test_every_config_key_has_its_place_and_the_defaults_agree():
    cfg = ReconstructConfig()
    api_only = {k for k, (g, f) in FLAT_KEYS.items()
                if not GROUPS[g].__dataclass_fields__[f].metadata["yaml"]}
    assert {"sat_threshold", "noise_quantization_dn"} <= api_only
    assert "temporal" not in api_only  # the sequence group: reconstruct --sequence reads it
    assert {f.name for f in dataclasses.fields(cfg)} == set(FLAT_KEYS) - api_only
    s = cfg.settings()
    assert s == ReconstructSettings()  # the configuration's defaults are the settings'
    flat = s.flat()
    assert {k: flat[k] for k in vars(cfg)} == vars(cfg)
    assert ReconstructSettings.from_flat(flat) == s
    custom = load_config({"beta": 10, "prior": "tv", "lam": "auto", "formats": ["npz"],
                          "black_level": [1, 2, 3, 4], "noise_read_e": 5},
                         ReconstructConfig).settings()  # fmt: skip
    assert custom.solve.beta == 10.0 and custom.prior.kind == "tv"
    assert custom.prior.lam == "auto" and custom.output.formats == ("npz",)
    assert custom.input.black_level == (1.0, 2.0, 3.0, 4.0) and custom.uncertainty.read_e == 5
    with pytest.raises(dataclasses.FrozenInstanceError):
        custom.solve.beta = 1.0  # type: ignore[misc]
    hash(custom)  # hashable: sequences are tuples


def test_the_key_covers_every_field_without_a_list():
    s = ReconstructSettings()
    assert s.key() == ReconstructSettings().key() and len(s.key()) == 64
    assert s.replace(beta=5.0).key() != s.key()
    assert s.replace(noise_quantization_dn=0.0).key() != s.key()  # a group's last field too

    @dataclass_frozen
    class SolveWithMore(SolveSettings):
        new_knob: int = 0

    more = dataclasses.replace(s, solve=SolveWithMore())
    assert more.replace(beta=2.0).solve.new_knob == 0  # replace keeps the group's class
    assert more.key() != s.key()  # a field added to a group changes the key by itself
    assert dataclasses.replace(s, solve=SolveWithMore(new_knob=1)).key() != more.key()


def dataclass_frozen(cls):
    return dataclasses.dataclass(frozen=True)(cls)


def test_validated_once_with_the_key_named_whatever_the_route():
    bundle = make_bundle()
    for make in (lambda: ReconstructConfig(lam=-1.0),
                 lambda: load_config({"lam": -1.0}, ReconstructConfig),
                 lambda: Reconstructor(bundle, prior="tv", lam=-1.0),
                 lambda: HSIReconstructor.from_bundle(bundle, lam=-1.0),
                 lambda: ReconstructSettings.from_flat(lam=-1.0)):  # fmt: skip
        with pytest.raises(ConfigError, match="key 'lam': must be >= 0"):
            make()
    with pytest.raises(ConfigError, match="key 'nope'"):
        ReconstructSettings.from_flat(nope=1)
    with pytest.raises(ConfigError, match="key 'lam': must be >= 0"):
        Reconstructor(bundle, ReconstructSettings(), lam=-1.0)  # overrides: validated alike
    with pytest.raises(TypeError, match="must be a ReconstructSettings"):
        Reconstructor(bundle, {"beta": 3.0})


def test_the_reconstructors_take_the_settings_whole():
    """No keyword lists: the settings are given whole; keywords are flat-key overrides on them
    (``settings.replace``), whatever their number."""
    import inspect

    for fn in (Reconstructor.__init__, HSIReconstructor.__init__, HSIReconstructor.from_bundle):
        params = inspect.signature(fn).parameters
        assert not set(params) & set(FLAT_KEYS), fn  # no setting copied into a signature
        assert "settings" in params and any(p.kind is p.VAR_KEYWORD for p in params.values())


def test_settings_or_overrides_give_the_same_reconstruction():
    bundle = make_bundle()
    img = render_capture(bundle, true_spectra())
    s = ReconstructSettings.from_flat(beta=0.0, dtype="float64", min_views=3)
    by_settings = Reconstructor(bundle, settings=s)
    by_keywords = Reconstructor(bundle, beta=0.0, dtype=torch.float64)
    assert by_settings.settings == by_keywords.settings == s
    assert Reconstructor(bundle, s.replace(beta=5.0), beta=0.0).settings == s
    a = by_settings.reconstruct_frame(img)
    b = by_keywords.reconstruct_frame(img)
    torch.testing.assert_close(a.cube, b.cube, equal_nan=True, rtol=0, atol=0)
    mod = HSIReconstructor.from_bundle(bundle, settings=s)
    assert mod.settings == s and mod.beta == 0.0
    cube, _ = mod(img.unsqueeze(0).double())
    torch.testing.assert_close(cube[0], a.cube, equal_nan=True, rtol=1e-9, atol=1e-9)


def test_the_workers_cache_is_keyed_by_the_settings(tmp_path):
    bpath = tmp_path / "calib.npz"
    make_bundle().save(bpath)
    (tmp_path / "a.npy").write_bytes(b"")
    run = check_run([tmp_path / "a.npy"], bpath, tmp_path / "out", ReconstructConfig())
    plan = tasks.FramePlan(run=run)
    tasks.forget_prepared()
    rec, secs = tasks.prepared_reconstructor(plan)
    assert secs is not None and rec.settings == run.settings
    assert tasks.prepared_reconstructor(plan) == (rec, None)  # cached
    # another value of any setting: prepared again
    other = dataclasses.replace(run, settings=run.settings.replace(min_views=4))
    rec2, secs2 = tasks.prepared_reconstructor(tasks.FramePlan(run=other))
    assert secs2 is not None and rec2 is not rec and rec2.settings.solve.min_views == 4

    # a field added to the settings (and forgotten everywhere else) still changes the key
    @dataclass_frozen
    class SolveWithMore(SolveSettings):
        new_knob: int = 0

    grown = dataclasses.replace(other.settings, solve=SolveWithMore(**vars(other.settings.solve)))
    grown_run = dataclasses.replace(other, settings=grown)
    _, secs3 = tasks.prepared_reconstructor(tasks.FramePlan(run=grown_run))
    assert secs3 is not None  # not served the reconstructor of the other settings
    tasks.forget_prepared()


def test_keys_without_effect_are_named_once_per_run(tmp_path, capsys):
    """``--set lam=2`` without ``prior: tv`` (or ``admm_iters`` with the active-set solver, the
    noise model without ``uncertainty``, ...) changed nothing and said nothing. Now the run warns
    once (not once per input), naming the key, its value and why; a key that does act is not
    named."""
    import numpy as np

    from hsi_torch.cli import main

    s = ReconstructSettings.from_flat(lam=2, admm_iters=5, noise_read_e=7, drift_check=False,
                                      refine_registration=False, drift_warn_px=2, preview=False,
                                      preview_size=99)  # fmt: skip
    msgs = s.inert()
    assert len(msgs) == 5
    # refine_registration: auto (the default) measures the drift, and decides by drift_warn_px
    assert not any("drift_warn_px" in m for m in ReconstructSettings.from_flat(
        drift_check=False, drift_warn_px=2).inert())
    assert msgs[0].startswith("setting lam=2.0 has no effect") and "prior: tv" in msgs[0]
    assert any("admm_iters=5" in m and "active_set" in m for m in msgs)
    assert not ReconstructSettings.from_flat(prior="tv", lam=2, solver="admm",
                                             admm_iters=5).inert()  # fmt: skip
    assert not ReconstructSettings().inert()

    bundle = make_bundle(white_exposure_s=0.01)
    bpath = tmp_path / "calib.npz"
    bundle.save(bpath)
    img = render_capture(bundle, true_spectra()).numpy()
    for name in ("a", "b"):
        np.save(tmp_path / f"{name}.npy", img)
    argv = ["reconstruct", "--bundle", str(bpath), "--out", str(tmp_path / "out"),
            "--no-progress", "--set", "lam=2", "--set", "admm_iters=5", "--set", "preview=false",
            str(tmp_path / "a.npy"), str(tmp_path / "b.npy")]  # fmt: skip
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert err.count("setting lam=2.0 has no effect") == 1
    assert err.count("setting admm_iters=5 has no effect") == 1


def test_python_keywords_without_effect_warn():
    """``Reconstructor(bundle, lam=2)`` (no ``prior="tv"``) said nothing; now a ``UserWarning``
    names the key. Given whole (``settings=``, as a run's driver does) it stays quiet: the run
    warns once itself."""
    import warnings

    bundle = make_bundle(white_exposure_s=0.01)
    with pytest.warns(UserWarning, match="setting lam=2.0 has no effect"):
        Reconstructor(bundle, lam=2)
    with pytest.warns(UserWarning, match="setting admm_iters=3 has no effect"):
        HSIReconstructor.from_bundle(bundle, admm_iters=3)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        Reconstructor(bundle, settings=ReconstructSettings.from_flat(lam=2))
        Reconstructor(bundle, prior="tv", lam=2)
