"""One source of defaults: every shipped config round-trips through its schema, the schemas'
defaults are the library's (the optics, sensor and detector dataclasses), and the shipped default
configs say what the schemas say."""

from __future__ import annotations

import dataclasses

import pytest
import yaml

from hsi_torch.calibrate.config import BlobSection, CalibrateConfig, RegistrationSection
from hsi_torch.calibrate.registration import BlobDetectorParams, GridDetectorConfig
from hsi_torch.config import dump_config, load_config, to_dict
from hsi_torch.experiments.design import DesignSweepConfig
from hsi_torch.experiments.mismatch import MismatchConfig
from hsi_torch.experiments.opd import OPDConfig
from hsi_torch.experiments.synthetic import SyntheticConfig
from hsi_torch.experiments.usaf import USAFConfig
from hsi_torch.optics import BRFConfig, CameraModel, KaleidoscopeGeometry, PrototypeDesign
from hsi_torch.optics.sensor import DiffuserModel, SensorModel
from hsi_torch.recon.config import ReconstructConfig
from hsi_torch.resources import shipped_config, shipped_config_names
from hsi_torch.simulate.config import (
    BRFSection,
    CameraConfig,
    DesignSection,
    DiffuserConfig,
    GeometryConfig,
    SensorSection,
    SimulateConfig,
)

SCHEMAS = {
    "calibrate": CalibrateConfig,
    "design": DesignSweepConfig,
    "mismatch": MismatchConfig,
    "opd": OPDConfig,
    "reconstruct": ReconstructConfig,
    "simulate": SimulateConfig,
    "simulate_full": SimulateConfig,
    "simulate_manakov": SimulateConfig,
    "simulate_fujimoto": SimulateConfig,
    "synthetic": SyntheticConfig,
    "usaf": USAFConfig,
}


def test_every_shipped_config_has_a_schema():
    assert sorted(shipped_config_names()) == sorted(SCHEMAS)


@pytest.mark.parametrize("name", sorted(SCHEMAS))
def test_shipped_config_round_trips(name, tmp_path):
    cfg = load_config(shipped_config(name), SCHEMAS[name])
    out = dump_config(cfg, tmp_path / f"{name}.yaml")
    again = load_config(out, SCHEMAS[name])
    assert again == cfg
    assert yaml.safe_load(out.read_text()) == to_dict(cfg)


def _defaults(cls: type) -> dict:
    out = {}
    for f in dataclasses.fields(cls):
        if f.default is not dataclasses.MISSING:
            out[f.name] = f.default
        elif f.default_factory is not dataclasses.MISSING:
            out[f.name] = f.default_factory()
    return out


# (config section, the library dataclass it configures, fields that deliberately differ)
MIRRORS = [
    (GeometryConfig, KaleidoscopeGeometry, set()),
    (CameraConfig, CameraModel, set()),
    (BRFSection, BRFConfig, set()),
    (DesignSection, PrototypeDesign, set()),
    # the simulator's exposure is the fill fraction of the full well for a white seen without the
    # filters; SensorModel.exposure is a plain multiplier on electrons (see SensorSection)
    (SensorSection, SensorModel, {"exposure"}),
    (DiffuserConfig, DiffuserModel, set()),
    (BlobSection, BlobDetectorParams, set()),
    (RegistrationSection, GridDetectorConfig, {"blob"}),
]


@pytest.mark.parametrize(
    "section, library, differ", MIRRORS, ids=lambda x: getattr(x, "__name__", "")
)
def test_config_defaults_are_the_library_defaults(section, library, differ):
    mine, theirs = _defaults(section), _defaults(library)
    shared = sorted((set(mine) & set(theirs)) - differ)
    assert len(shared) >= 2, f"{section.__name__} shares no field with {library.__name__}"
    for name in shared:
        a, b = mine[name], theirs[name]
        if isinstance(b, tuple) and isinstance(a, list):
            b = list(b)
        assert a == b, f"{section.__name__}.{name} = {a!r} but {library.__name__}.{name} = {b!r}"


def test_blob_section_is_the_detector_default():
    detector = GridDetectorConfig.from_dict(CalibrateConfig().detector_dict())
    assert detector.blob == BlobDetectorParams()


def test_reconstruct_config_is_generated_from_the_settings():
    """One definition: each key of reconstruct.yaml has the settings field's default and help
    text (a setting added to a group reaches the YAML schema without being listed again)."""
    from hsi_torch.recon.settings import FLAT_KEYS, GROUPS, ReconstructSettings

    cfg = _defaults(ReconstructConfig)
    flat = ReconstructSettings().flat()
    assert cfg and all(cfg[k] == flat[k] for k in cfg)
    for f in dataclasses.fields(ReconstructConfig):
        group, name = FLAT_KEYS[f.name]
        (src,) = [g for g in dataclasses.fields(GROUPS[group]) if g.name == name]
        assert f.metadata["help"] == src.metadata["help"] and f.metadata["help"]


def test_shipped_calibrate_yaml_is_the_schema_default_but_the_blob_area():
    """``calibrate.yaml`` and ``CalibrateConfig()`` agree on every key but the one the YAML
    tunes for the simulator's grids (and says so): ``registration.blob.max_area``."""
    shipped = to_dict(load_config(shipped_config("calibrate"), CalibrateConfig))
    default = to_dict(CalibrateConfig())
    assert shipped["registration"]["blob"].pop("max_area") == 2000.0
    assert default["registration"]["blob"].pop("max_area") == 1.0e5
    assert shipped == default


def test_shipped_simulate_yaml_is_the_schema_default():
    """The small prototype's shipped config and ``SimulateConfig()`` describe the same device."""
    shipped = to_dict(load_config(shipped_config("simulate"), SimulateConfig))
    default = to_dict(SimulateConfig())
    for section in ("geometry", "camera", "brf", "sensor", "diffuser", "objective"):
        assert shipped[section] == default[section], section
