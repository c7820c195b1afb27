"""Tests of the typed YAML configuration system (example schemas live here, not in the library)."""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import pytest
import yaml

from hsi_torch.config import (
    ConfigError,
    ExistingPath,
    describe_schema,
    dump_config,
    load_config,
    parse_override,
    to_dict,
    write_resolved_config,
)


class Illuminant(enum.Enum):
    D65 = "D65"
    A = "A"


@dataclass
class SolverCfg:
    beta: float = 1.0
    method: Literal["active_set", "admm", "scipy"] = "active_set"
    max_iter: int = 50
    difference_order: Literal[1, 2] = 1


@dataclass
class SceneCfg:
    kind: str = "colorchecker"
    cube_path: Path | None = None
    size: tuple[int, int] = (64, 64)


@dataclass
class ExampleCfg:
    out_name: str
    solver: SolverCfg = field(default_factory=SolverCfg)
    scenes: list[SceneCfg] = field(default_factory=list)
    wavelengths_nm: tuple[float, ...] = (430.0, 550.0, 670.0)
    illuminant: Illuminant = Illuminant.D65
    noise: float | Literal["auto"] = "auto"
    seed: int | None = None
    device: str = "cpu"
    verbose: bool = False
    extras: dict[str, float] = field(default_factory=dict)
    anything: Any = None


@dataclass
class Positive:
    value: float = 1.0

    def __post_init__(self):
        if self.value <= 0:
            raise ValueError(f"value must be > 0, got {self.value}")


@dataclass
class WithPositive:
    p: Positive = field(default_factory=Positive)


@dataclass
class NeedsFile:
    bundle: ExistingPath
    label: str = field(default="x", metadata={"help": "a label"})


def _write(tmp_path: Path, text: str, name: str = "cfg.yaml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_load_full_config(tmp_path):
    p = _write(
        tmp_path,
        """
out_name: run1
solver: {beta: 1e-3, method: admm, max_iter: 200}
scenes:
  - {kind: cube, cube_path: data/scene.npz, size: [32, 48]}
  - kind: colorchecker
wavelengths_nm: [430, 440.5]
illuminant: A
noise: 0.5
seed: 7
extras: {gain: 2}
anything: {free: [1, 2]}
""",
    )
    cfg = load_config(p, ExampleCfg)
    assert cfg.out_name == "run1"
    assert cfg.solver == SolverCfg(beta=1e-3, method="admm", max_iter=200)  # "1e-3" str -> float
    assert isinstance(cfg.solver.beta, float)
    assert cfg.scenes[0].cube_path == tmp_path.resolve() / "data" / "scene.npz"  # relative to file
    assert cfg.scenes[0].size == (32, 48) and cfg.scenes[1] == SceneCfg()
    assert cfg.wavelengths_nm == (430.0, 440.5) and isinstance(cfg.wavelengths_nm[0], float)
    assert cfg.illuminant is Illuminant.A and cfg.noise == 0.5 and cfg.seed == 7
    assert cfg.extras == {"gain": 2.0} and cfg.anything == {"free": [1, 2]}
    # defaults
    d = load_config({"out_name": "x"}, ExampleCfg)
    assert d.solver == SolverCfg() and d.noise == "auto" and d.scenes == []


def test_overrides(tmp_path, monkeypatch):
    p = _write(tmp_path, "out_name: a\nscenes: [{kind: cube}]\n")
    monkeypatch.chdir(tmp_path / "..")
    cfg = load_config(
        p,
        ExampleCfg,
        overrides=["solver.beta=25", "solver.method=scipy", "scenes.0.cube_path=rel/c.npz",
                   "wavelengths_nm=[500, 600]", "seed=", "verbose=true", "out_name=b=c"],
    )  # fmt: skip
    assert cfg.solver.beta == 25.0 and cfg.solver.method == "scipy"
    assert cfg.scenes[0].cube_path == Path.cwd() / "rel" / "c.npz"  # overrides: relative to cwd
    assert cfg.wavelengths_nm == (500.0, 600.0) and cfg.seed is None and cfg.verbose is True
    assert cfg.out_name == "b=c"  # only the first '=' splits
    assert parse_override("a.b.3=[1, x]") == (("a", "b", 3), [1, "x"])
    with pytest.raises(ConfigError, match="key.sub=value"):
        load_config(p, ExampleCfg, overrides=["solver.beta"])
    with pytest.raises(ConfigError, match="empty key"):
        load_config(p, ExampleCfg, overrides=["solver..beta=1"])
    with pytest.raises(ConfigError, match="out of range"):
        load_config(p, ExampleCfg, overrides=["scenes.3.kind=x"])


@pytest.mark.parametrize(
    ("text", "overrides", "key", "pattern"),
    [
        ("out_name: a\nsolver: {betta: 2}", [], "solver.betta", "did you mean 'solver.beta'"),
        ("out_name: a\nsolvr: {beta: 2}", [], "solvr", "did you mean 'solver'"),
        ("out_name: a\nsolver: {beta: abc}", [], "solver.beta", "expected float, got str 'abc'"),
        ("out_name: a\nsolver: {beta: true}", [], "solver.beta", "expected float, got bool"),
        ("out_name: a\nsolver: {max_iter: 2.5}", [], "solver.max_iter", "expected int"),
        ("out_name: a\nsolver: {method: adm}", [], "solver.method", "did you mean 'admm'"),
        (
            "out_name: a\nsolver: {difference_order: 3}",
            [],
            "solver.difference_order",
            "one of 1, 2",
        ),
        ("out_name: a\nverbose: 1", [], "verbose", "expected bool"),
        ("out_name: 5", [], "out_name", "expected str, got int 5"),
        ("solver: {}", [], "out_name", "missing required key"),
        ("out_name: a\nscenes: [{kind: c, size: [1]}]", [], "scenes[0].size", "expected 2 items"),
        ("out_name: a\nscenes: {kind: c}", [], "scenes", "expected a list"),
        ("out_name: a\nsolver: 3", [], "solver", "expected a mapping for SolverCfg"),
        ("out_name: a\nilluminant: F2", [], "illuminant", "one of 'D65', 'A'"),
        ("out_name: a\nnoise: loud", [], "noise", "expected float | one of 'auto'"),
        ("out_name: a", ["solver.beta=x"], "solver.beta", "from override 'solver.beta=x'"),
        ("out_name: a", ["solver.tol=1"], "solver.tol", "unknown key"),
    ],
)
def test_errors_name_file_and_key(tmp_path, text, overrides, key, pattern):
    p = _write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_config(p, ExampleCfg, overrides=overrides)
    err = info.value
    assert err.key == key and err.source == str(p)
    msg = str(err)
    assert msg.startswith(f"{p}: key '{key}'") and "\n" not in msg
    assert pattern in msg


def test_file_level_errors(tmp_path):
    with pytest.raises(ConfigError, match="missing.yaml: config file not found"):
        load_config(tmp_path / "missing.yaml", ExampleCfg)
    p = _write(tmp_path, "out_name: a\nsolver: {beta: [1, 2}\n", "bad.yaml")
    with pytest.raises(ConfigError, match=r"bad.yaml: invalid YAML at line 2"):
        load_config(p, ExampleCfg)
    p = _write(tmp_path, "- 1\n- 2\n", "list.yaml")
    with pytest.raises(ConfigError, match="top level must be a mapping"):
        load_config(p, ExampleCfg)
    p = _write(tmp_path, "", "empty.yaml")
    with pytest.raises(ConfigError, match="empty.yaml: key 'out_name': missing required"):
        load_config(p, ExampleCfg)
    with pytest.raises(TypeError, match="dataclass"):
        load_config({}, dict)  # type: ignore[arg-type]


def test_a_key_given_twice_is_refused_naming_both_lines(tmp_path):
    # plain YAML keeps the later value in silence: a lab that appends `beta: 10` to its copy of
    # a config that already says `beta: 1000` would get 10 without a word
    p = _write(tmp_path, "out_name: a\nsolver:\n  beta: 1000\n  max_iter: 5\n  beta: 10\n",
               "twice.yaml")  # fmt: skip
    with pytest.raises(ConfigError, match=r"twice.yaml: invalid YAML at line 5, column 3: key "
                       r"'beta' is given twice in one mapping \(first at line 3\)"):
        load_config(p, ExampleCfg)
    p = _write(tmp_path, "out_name: a\nout_name: b\n", "top.yaml")
    with pytest.raises(ConfigError, match=r"top.yaml: .*key 'out_name' is given twice"):
        load_config(p, ExampleCfg)
    with pytest.raises(ConfigError, match=r"key 'a' is given twice"):
        load_config({"out_name": "a"}, ExampleCfg, overrides=["extras={a: 1, a: 2}"])
    # a merge key is not a duplicate; the same key in two mappings is fine
    p = _write(tmp_path, "out_name: a\nextras:\n  <<: {x: 1.0}\n  y: 2.0\n"
               "solver: {beta: 2.0, max_iter: 3}\nscenes: [{size: [1, 2]}, {size: [3, 4]}]\n",
               "merge.yaml")  # fmt: skip
    cfg = load_config(p, ExampleCfg)
    assert cfg.extras == {"x": 1.0, "y": 2.0} and cfg.scenes[1].size == (3, 4)
    from hsi_torch.config import safe_yaml_load

    assert safe_yaml_load("a: &x {p: 1}\nb:\n  <<: *x\n  q: 2\n") == {"a": {"p": 1},
                                                                       "b": {"p": 1, "q": 2}}


def test_post_init_and_existing_path(tmp_path):
    with pytest.raises(ConfigError, match=r"key 'p': invalid Positive: value must be > 0"):
        load_config({"p": {"value": -1}}, WithPositive)
    (tmp_path / "b.npz").write_bytes(b"")
    p = _write(tmp_path, "bundle: b.npz\n")
    assert load_config(p, NeedsFile).bundle == tmp_path.resolve() / "b.npz"
    p = _write(tmp_path, "bundle: nothere.npz\n", "c2.yaml")
    with pytest.raises(ConfigError, match=r"c2.yaml: key 'bundle': path not found: .*nothere.npz"):
        load_config(p, NeedsFile)
    # dict sources resolve relative paths against base_dir
    cfg = load_config({"bundle": "b.npz"}, NeedsFile, base_dir=tmp_path)
    assert cfg.bundle == tmp_path / "b.npz"


def test_dump_roundtrip(tmp_path):
    cfg = load_config(
        {"out_name": "r", "scenes": [{"kind": "cube", "cube_path": "c.npz"}], "seed": 3,
         "illuminant": "A", "solver": {"beta": 0.01}},
        ExampleCfg, base_dir=tmp_path,
    )  # fmt: skip
    d = to_dict(cfg)
    assert d["scenes"][0]["cube_path"] == str(tmp_path / "c.npz")
    assert d["illuminant"] == "A" and d["scenes"][0]["size"] == [64, 64]
    out = dump_config(cfg, tmp_path / "run" / "cfg.yaml")
    assert yaml.safe_load(out.read_text()) == d
    assert load_config(out, ExampleCfg) == cfg  # the resolved config loads back identically
    res = write_resolved_config(cfg, tmp_path / "run")
    assert res.name == "resolved_config.yaml" and res.read_text().startswith("# resolved")
    assert load_config(res, ExampleCfg) == cfg


def test_describe_schema():
    text = describe_schema(ExampleCfg)
    assert "out_name: str (required)" in text
    assert "solver.beta: float = 1.0" in text
    assert "solver.method: one of 'active_set', 'admm', 'scipy' = 'active_set'" in text
    assert "label: str = 'x'  # a label" in describe_schema(NeedsFile)
