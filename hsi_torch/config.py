"""Typed, validated configuration files (YAML) built on dataclasses.

A *schema* is a (possibly nested) dataclass owned by the module that uses it. :func:`load_config`
reads a YAML file (or a dict), applies command-line overrides, checks every key and type against
the schema and returns an instance; :func:`dump_config` writes the resolved configuration back as
YAML (each run stores it beside its outputs).

The rules, with example messages: docs/io_config_cli.md. Field types: ``bool``, ``int``,
``float``, ``str``, :class:`pathlib.Path`, ``Optional`` and unions, ``Literal[...]``, ``Enum``,
``list[X]``, ``tuple[X, ...]``, ``tuple[X, Y]``, ``dict[str, X]``, nested dataclasses, ``Any``,
:data:`ExistingPath`. ``int`` → ``float`` and numeric strings → numbers are accepted (PyYAML
reads ``1e-3`` as a string); a ``float`` must be finite (optional keys use ``null``); ``bool``
never mixes with numbers; a relative ``Path`` is joined to the config file's folder (a dict
source: ``base_dir``; an override: the current directory), ``~`` expanded. Errors:
:class:`ConfigError` (a ``ValueError``) naming the source file and the dotted key — an unknown
key (the closest valid key suggested, or the text a schema's ``__renamed_keys__`` gives for an
old key), a wrong type or ``Literal`` choice, a missing key or file, invalid YAML, and errors
raised by a schema's ``__post_init__``.

Example:
    >>> @dataclass
    ... class Solver:
    ...     beta: float = 1.0
    ...     method: Literal["active_set", "admm"] = "active_set"
    >>> @dataclass
    ... class Run:
    ...     solver: Solver = field(default_factory=Solver)
    >>> load_config({"solver": {"beta": 2}}, Run, overrides=["solver.method=admm"])
    Run(solver=Solver(beta=2.0, method='admm'))
"""

from __future__ import annotations

import copy
import dataclasses
import difflib
import enum
import math
import os
import types
import typing
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path, PurePath
from typing import Annotated, Any, Literal, TypeVar, Union

import yaml

from hsi_torch import __version__
from hsi_torch.errors import ConfigError  # defined with the other errors; re-exported here
from hsi_torch.io.atomic import atomic_write_text
from hsi_torch.io.safety import short_repr, short_text

__all__ = [
    "ConfigError",
    "ExistingPath",
    "MustExist",
    "load_config",
    "safe_yaml_load",
    "MAX_YAML_VALUES",
    "parse_override",
    "apply_overrides",
    "to_dict",
    "dump_config",
    "config_yaml",
    "write_resolved_config",
    "RESOLVED_CONFIG_NAME",
    "describe_schema",
]

RESOLVED_CONFIG_NAME = "resolved_config.yaml"

T = TypeVar("T")
KeyPath = tuple[str | int, ...]


@dataclass(frozen=True)
class MustExist:
    """Marker for ``Annotated[Path, MustExist()]``: the path must exist after resolution."""

    kind: Literal["any", "file", "dir"] = "any"


ExistingPath = Annotated[Path, MustExist()]
"""A ``Path`` field that must exist (file or folder) once resolved."""


def _fmt_key(path: KeyPath) -> str:
    out = ""
    for part in path:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += ("." if out else "") + part
    return out


@dataclass
class _Ctx:
    source: str
    base_dir: Path
    overridden: dict[KeyPath, str] = field(default_factory=dict)

    def override_of(self, path: KeyPath) -> str | None:
        """The override text that set ``path`` or its closest overridden parent, if any."""
        for i in range(len(path), 0, -1):
            if path[:i] in self.overridden:
                return self.overridden[path[:i]]
        return None

    def error(self, path: KeyPath, message: str) -> ConfigError:
        text = self.override_of(path)
        if text is not None:
            message += f" (from override '{text}')"
        return ConfigError(message, _fmt_key(path) or None, self.source)


# ----------------------------------------------------------------------------------------------
# overrides


def help_meta(text: str) -> dict[str, str]:
    """``field(metadata=help_meta("..."))``: the help text :func:`describe_schema` prints."""
    return {"help": text}


def option(default: Any = dataclasses.MISSING, text: str = "", *, factory: Any = None) -> Any:
    """A schema field with its help text: ``option(1.0, "...")`` is
    ``field(default=1.0, metadata=help_meta("..."))``; ``option(text="...", factory=list)`` a
    ``default_factory`` field."""
    if factory is not None:
        return field(default_factory=factory, metadata=help_meta(text))
    return field(default=default, metadata=help_meta(text))


def parse_override(text: str) -> tuple[KeyPath, Any]:
    """Parse ``"a.b.c=value"`` into ``(("a", "b", "c"), yaml.safe_load("value"))``.

    Integer parts index into lists (``views.0.x=1``). The value is YAML: ``beta=1e-3`` gives the
    string ``"1e-3"`` (accepted by float fields), ``sizes=[1, 2]`` a list, ``name=`` ``None``.
    """
    if not isinstance(text, str) or "=" not in text:
        raise ConfigError(f"override {text!r} must have the form key.sub=value")
    key, _, raw = text.partition("=")
    key = key.strip()
    if not key or any(not p for p in key.split(".")):
        raise ConfigError(f"override {text!r} has an empty key part")
    parts: list[str | int] = [int(p) if p.isascii() and p.isdigit() else p for p in key.split(".")]
    try:
        value = safe_yaml_load(raw) if raw.strip() else None
    except yaml.YAMLError as exc:
        problem = getattr(exc, "problem", None) or str(exc)
        raise ConfigError(f"override {short_repr(text)}: value is not valid YAML "
                          f"({short_text(problem, 300)})") from None  # fmt: skip
    except ValueError as exc:  # expands too far
        raise ConfigError(f"override {short_repr(text)}: {exc}") from None
    return tuple(parts), value


#: Most values (scalars, list items, mapping entries; aliases counted every time they are
#: used) one configuration document may expand to.
MAX_YAML_VALUES = 100_000


def safe_yaml_load(text: str, max_values: int = MAX_YAML_VALUES) -> Any:
    """``yaml.safe_load`` that refuses a document expanding to more than ``max_values`` values,
    and a mapping with a key given twice.

    YAML aliases (``*a``) repeat an anchored node: nine levels of nine-fold repetition are a few
    hundred bytes of text but 10⁹ values once expanded (an alias bomb). The composed node graph
    is measured first (every use of an alias counted, each distinct node visited once), so the
    refusal costs no more than the text itself.

    A key given twice in one mapping (``beta: 1000`` … ``beta: 10``) is refused too: plain YAML
    keeps the later value in silence, so the run would use a setting the reader of the file may
    not see.

    Raises:
        yaml.YAMLError: invalid YAML, or a key given twice in one mapping.
        ValueError: the document expands to more than ``max_values`` values.
    """
    loader = yaml.SafeLoader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        sizes: dict[int, int] = {}

        def size(n: yaml.Node) -> int:
            key = id(n)
            if key in sizes:
                return sizes[key]
            sizes[key] = max_values + 1  # a node reached again while measured (a cycle)
            if isinstance(n, yaml.SequenceNode):
                total = 1 + sum(size(c) for c in n.value)
            elif isinstance(n, yaml.MappingNode):
                _refuse_duplicate_keys(n)
                total = 1 + sum(size(k) + size(v) for k, v in n.value)
            else:
                total = 1
            sizes[key] = total = min(total, max_values + 1)
            return total

        if size(node) > max_values:
            raise ValueError(
                f"the YAML expands to more than {max_values} values (aliases such as *a repeat "
                "a value each time they are used); write the values out")
        return loader.construct_document(node)
    except RecursionError:
        raise ValueError("the YAML is nested too deeply") from None
    finally:
        loader.dispose()


_MERGE_TAG = "tag:yaml.org,2002:merge"


def _refuse_duplicate_keys(node: yaml.MappingNode) -> None:
    """Raise a ``yaml.YAMLError`` (with the line of the second one) for a scalar key given twice
    in one mapping; merge keys (``<<``) are left to YAML's own rules."""
    seen: dict[tuple[str, str], yaml.Node] = {}
    for key, _ in node.value:
        if not isinstance(key, yaml.ScalarNode) or key.tag == _MERGE_TAG:
            continue
        ident = (key.tag, key.value)
        first = seen.get(ident)
        if first is None:
            seen[ident] = key
            continue
        raise yaml.constructor.ConstructorError(
            None,
            None,
            f"key {short_repr(key.value)} is given twice in one mapping (first at line "
            f"{first.start_mark.line + 1}); YAML would keep the later value in silence: keep "
            "one of them",
            key.start_mark)


def apply_overrides(data: dict[str, Any], overrides: Sequence[str]) -> dict[KeyPath, str]:
    """Apply ``key.sub=value`` overrides to a nested dict in place; returns key path → text."""
    applied: dict[KeyPath, str] = {}
    for text in overrides:
        parts, value = parse_override(text)
        node: Any = data
        for i, part in enumerate(parts[:-1]):
            nxt = parts[i + 1]
            if isinstance(node, dict):
                if not isinstance(node.get(part), (dict, list)):
                    node[part] = {}
                node = node[part]
            elif isinstance(node, list) and isinstance(part, int):
                if part >= len(node):
                    raise ConfigError(
                        f"override '{text}': index {part} is out of range (length {len(node)})",
                        _fmt_key(parts[:i]))
                if not isinstance(node[part], (dict, list)):
                    node[part] = {} if not isinstance(nxt, int) else []
                node = node[part]
            else:
                raise ConfigError(
                    f"override '{text}': cannot descend into a {type(node).__name__}",
                    _fmt_key(parts[:i]) or None)
        last = parts[-1]
        if isinstance(node, dict):
            node[last] = value
        elif isinstance(node, list) and isinstance(last, int) and last < len(node):
            node[last] = value
        else:
            raise ConfigError(
                f"override '{text}': cannot set {last!r} on a {type(node).__name__}",
                _fmt_key(parts[:-1]) or None)
        applied[parts] = text
    return applied


# ----------------------------------------------------------------------------------------------
# conversion


def _type_name(tp: Any) -> str:
    if tp is type(None):
        return "None"
    origin = typing.get_origin(tp)
    if origin is Annotated:
        return _type_name(typing.get_args(tp)[0])
    if origin in (Union, types.UnionType):
        return " | ".join(_type_name(a) for a in typing.get_args(tp))
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in typing.get_args(tp))
    if origin is not None:
        args = ", ".join("..." if a is Ellipsis else _type_name(a) for a in typing.get_args(tp))
        return f"{getattr(origin, '__name__', str(origin))}[{args}]"
    return getattr(tp, "__name__", str(tp))


def _got(value: Any) -> str:
    # bounded: a value built from YAML aliases may expand to gigabytes when printed whole
    return f"{type(value).__name__} {short_repr(value, 60)}"


def _convert(value: Any, tp: Any, path: KeyPath, ctx: _Ctx) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)

    if tp is Any or tp is object:
        return value
    if origin is Annotated:
        out = _convert(value, args[0], path, ctx)
        for marker in args[1:]:
            if isinstance(marker, MustExist) and out is not None:
                p = Path(out)
                try:
                    ok = {"any": p.exists, "file": p.is_file, "dir": p.is_dir}[marker.kind]()
                except (OSError, ValueError) as exc:  # e.g. an embedded NUL, a too-long name
                    raise ctx.error(path, f"invalid path {str(p)!r} ({exc})") from None
                if not ok:
                    what = {"any": "path", "file": "file", "dir": "folder"}[marker.kind]
                    raise ctx.error(path, f"{what} not found: {p}")
        return out
    if origin in (Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        candidates = [a for a in args if a is not type(None)]
        if len(candidates) == 1:  # Optional[X]: keep X's precise error message
            return _convert(value, candidates[0], path, ctx)
        # exact-type matches first, so that e.g. int | str keeps "3" a str and 3 an int
        candidates.sort(key=lambda a: 0 if isinstance(a, type) and type(value) is a else 1)
        errors: list[ConfigError] = []
        for cand in candidates:
            try:
                return _convert(value, cand, path, ctx)
            except ConfigError as exc:
                errors.append(exc)
        for exc in errors:  # a number of the right kind but not finite: say so
            if "finite" in exc.problem:
                raise exc
        raise ctx.error(path, f"expected {_type_name(tp)}, got {_got(value)}")
    if tp is type(None):
        if value is not None:
            raise ctx.error(path, f"expected null, got {_got(value)}")
        return None
    if origin is Literal:
        for choice in args:
            if value == choice and type(value) is type(choice):
                return choice
        msg = f"expected {_type_name(tp)}, got {_got(value)}"
        if isinstance(value, str):
            close = difflib.get_close_matches(value, [a for a in args if isinstance(a, str)], 1)
            if close:
                msg += f" (did you mean {close[0]!r}?)"
        raise ctx.error(path, msg)
    if tp is bool:
        if not isinstance(value, bool):
            raise ctx.error(path, f"expected bool (true/false), got {_got(value)}")
        return value
    if tp is int:
        if isinstance(value, bool):
            raise ctx.error(path, f"expected int, got {_got(value)}")
        if isinstance(value, int):
            return value
        try:
            num = float(value) if isinstance(value, str) else value
        except ValueError:
            num = None
        if isinstance(num, float) and num.is_integer():
            return int(num)
        raise ctx.error(path, f"expected int, got {_got(value)}")
    if tp is float:
        if isinstance(value, bool):
            raise ctx.error(path, f"expected float, got {_got(value)}")
        try:
            num = float(value) if isinstance(value, (int, float, str)) else None
        except OverflowError:  # an int beyond float range
            num = math.inf
        except ValueError:  # a string that is no number
            num = None
        if num is None:
            raise ctx.error(path, f"expected float, got {_got(value)}")
        if not math.isfinite(num):
            raise ctx.error(path, f"expected a finite float, got {_got(value)}")
        return num
    if tp is str:
        if not isinstance(value, str):
            raise ctx.error(path, f"expected str, got {_got(value)} (quote it in YAML)")
        return value
    if isinstance(tp, type) and issubclass(tp, PurePath):
        if not isinstance(value, (str, os.PathLike)) or (isinstance(value, str) and not value):
            raise ctx.error(path, f"expected a path (str), got {_got(value)}")
        p = Path(os.path.expanduser(os.fspath(value)))
        if not p.is_absolute():
            base = Path.cwd() if ctx.override_of(path) is not None else ctx.base_dir
            p = base / p
        return tp(p)
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        for member in tp:
            if value == member.value or value == member.name:
                return member
        choices = ", ".join(repr(m.value) for m in tp)
        raise ctx.error(path, f"expected one of {choices}, got {_got(value)}")
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        return _convert_dataclass(value, tp, path, ctx)
    if origin in (list, Sequence) or tp in (list, Sequence):
        if not isinstance(value, (list, tuple)):
            raise ctx.error(path, f"expected a list, got {_got(value)}")
        item_tp = args[0] if args else Any
        return [_convert(v, item_tp, (*path, i), ctx) for i, v in enumerate(value)]
    if origin is tuple or tp is tuple:
        if not isinstance(value, (list, tuple)):
            raise ctx.error(path, f"expected a list of {_type_name(tp)}, got {_got(value)}")
        if not args:
            return tuple(value)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(v, args[0], (*path, i), ctx) for i, v in enumerate(value))
        if len(value) != len(args):
            raise ctx.error(
                path, f"expected {len(args)} items ({_type_name(tp)}), got {len(value)}")
        return tuple(
            _convert(v, a, (*path, i), ctx)
            for i, (v, a) in enumerate(zip(value, args, strict=True)))
    if origin in (dict, Mapping) or tp in (dict, Mapping):
        if not isinstance(value, Mapping):
            raise ctx.error(path, f"expected a mapping, got {_got(value)}")
        k_tp, v_tp = args if args else (Any, Any)
        return {
            _convert(k, k_tp, (*path, str(k)), ctx): _convert(v, v_tp, (*path, str(k)), ctx)
            for k, v in value.items()
        }
    if isinstance(tp, type):
        if not isinstance(value, tp):
            raise ctx.error(path, f"expected {tp.__name__}, got {_got(value)}")
        return value
    raise TypeError(f"unsupported type annotation {tp!r} for config key '{_fmt_key(path)}'")


def _convert_dataclass(value: Any, cls: type, path: KeyPath, ctx: _Ctx) -> Any:
    if not isinstance(value, Mapping):
        raise ctx.error(path, f"expected a mapping for {cls.__name__}, got {_got(value)}")
    hints = typing.get_type_hints(cls, include_extras=True)
    fields = [f for f in dataclasses.fields(cls) if f.init]
    names = [f.name for f in fields]
    renamed = getattr(cls, "__renamed_keys__", None) or {}
    for key in value:
        if not isinstance(key, str):
            raise ctx.error(path, f"keys must be strings, got {_got(key)}")
        if key not in names and key in renamed:  # a key of an earlier release
            raise ctx.error((*path, key), renamed[key])
        if key not in names:
            close = difflib.get_close_matches(key, names, n=1, cutoff=0.6)
            hint = f" (did you mean '{_fmt_key((*path, close[0]))}'?)" if close else ""
            valid = ", ".join(names)
            raise ctx.error((*path, key), f"unknown key{hint}; valid keys here: {valid}")
    kwargs: dict[str, Any] = {}
    for f in fields:
        if f.name in value:
            kwargs[f.name] = _convert(value[f.name], hints[f.name], (*path, f.name), ctx)
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise ctx.error((*path, f.name), f"missing required key ({_type_name(hints[f.name])})")
    try:
        return cls(**kwargs)
    except (ValueError, TypeError) as exc:
        if isinstance(exc, ConfigError):
            raise
        raise ctx.error(path, f"invalid {cls.__name__}: {short_text(str(exc))}") from exc


# ----------------------------------------------------------------------------------------------
# public API


def load_config(
    source: str | os.PathLike | Mapping[str, Any] | None,
    schema_cls: type[T],
    overrides: Sequence[str] | None = None,
    base_dir: str | os.PathLike | None = None,
) -> T:
    """Load, override and validate a configuration.

    Args:
        source: YAML file path, an already-parsed mapping, or ``None`` (all defaults).
        schema_cls: the dataclass describing the configuration.
        overrides: ``["key.sub=value", ...]`` applied after reading (values parsed as YAML).
        base_dir: folder that relative ``Path`` values of a mapping source are joined to
            (default: the current directory; for a file: the file's folder, always).

    Returns:
        An instance of ``schema_cls``.

    Raises:
        ConfigError: missing/unreadable file, invalid YAML, unknown key, wrong type, missing
            required key, missing file for an :data:`ExistingPath`, failed ``__post_init__``.
    """
    if not (dataclasses.is_dataclass(schema_cls) and isinstance(schema_cls, type)):
        raise TypeError(f"schema_cls must be a dataclass type, got {schema_cls!r}")
    if source is None or isinstance(source, Mapping):
        data = copy.deepcopy(dict(source or {}))
        src_name = "<config>" if source is None else "<dict>"
        base = Path(base_dir) if base_dir is not None else Path.cwd()
    else:
        cfg_path = Path(source)
        src_name = str(cfg_path)
        if not cfg_path.is_file():
            what = "is a directory" if cfg_path.is_dir() else "not found"
            raise ConfigError(f"config file {what}", source=src_name)
        try:
            data = safe_yaml_load(cfg_path.read_text(encoding="utf-8"))
        except yaml.YAMLError as exc:
            mark = getattr(exc, "problem_mark", None)
            where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
            problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
            raise ConfigError(f"invalid YAML{where}: {problem}", source=src_name) from None
        except (OSError, UnicodeDecodeError) as exc:
            raise ConfigError(f"cannot read config file ({exc})", source=src_name) from None
        except ValueError as exc:  # expands too far (an alias bomb)
            raise ConfigError(str(exc), source=src_name) from None
        if data is None:
            data = {}
        base = cfg_path.resolve().parent
    if not isinstance(data, dict):
        raise ConfigError(f"top level must be a mapping, got {_got(data)}", source=src_name)
    ctx = _Ctx(source=src_name, base_dir=base)
    try:
        ctx.overridden = apply_overrides(data, list(overrides or []))
    except ConfigError as exc:
        raise ConfigError(exc.problem, exc.key, src_name) from None
    return _convert_dataclass(data, schema_cls, (), ctx)


def to_dict(instance: Any) -> Any:
    """Plain-Python (YAML/JSON-safe) form of a config: dataclasses → dicts (field order), paths →
    str, tuples → lists, enums → values."""
    if dataclasses.is_dataclass(instance) and not isinstance(instance, type):
        return {
            f.name: to_dict(getattr(instance, f.name))
            for f in dataclasses.fields(instance)
            if f.init
        }
    if isinstance(instance, PurePath):
        return str(instance)
    if isinstance(instance, enum.Enum):
        return to_dict(instance.value)
    if isinstance(instance, Mapping):
        return {str(k) if isinstance(k, PurePath) else k: to_dict(v) for k, v in instance.items()}
    if isinstance(instance, (list, tuple)):
        return [to_dict(v) for v in instance]
    if hasattr(instance, "item") and hasattr(instance, "ndim") and instance.ndim == 0:
        return instance.item()  # numpy / torch scalars
    return instance


def config_yaml(instance: Any, header: str | None = None) -> str:
    """The YAML text :func:`dump_config` writes (``header`` as leading ``#`` comment lines)."""
    text = yaml.safe_dump(to_dict(instance), sort_keys=False, default_flow_style=None, width=100)
    if header:
        text = "".join(f"# {line}\n" for line in header.splitlines()) + text
    return text


def dump_config(instance: Any, path: str | os.PathLike, header: str | None = None) -> Path:
    """Write the resolved configuration as YAML, atomically (loadable again by
    :func:`load_config` with the same schema). ``header`` becomes leading ``#`` comment lines."""
    return atomic_write_text(path, config_yaml(instance, header))


def write_resolved_config(
    instance: Any, out_dir: str | os.PathLike, name: str = RESOLVED_CONFIG_NAME
) -> Path:
    """Write ``instance`` as ``out_dir/resolved_config.yaml`` (every run does this beside its
    outputs, so a result can be reproduced with ``--config out_dir/resolved_config.yaml``)."""
    return dump_config(
        instance, Path(out_dir) / name, header=f"resolved configuration, hsi_torch {__version__}")


def describe_schema(schema_cls: type, prefix: str = "") -> str:
    """A plain-text reference of a schema: one line per key with type, default and the field's
    ``metadata["help"]`` (for README config tables and ``--help`` epilogues)."""
    hints = typing.get_type_hints(schema_cls, include_extras=True)
    lines: list[str] = []
    for f in dataclasses.fields(schema_cls):
        if not f.init:
            continue
        tp = hints[f.name]
        key = f"{prefix}{f.name}"
        if dataclasses.is_dataclass(tp) and isinstance(tp, type):
            lines.append(describe_schema(tp, prefix=key + "."))
            continue
        if f.default is not dataclasses.MISSING:
            default = f" = {to_dict(f.default)!r}"
        elif f.default_factory is not dataclasses.MISSING:
            default = f" = {to_dict(f.default_factory())!r}"
        else:
            default = " (required)"
        help_text = f.metadata.get("help", "")
        lines.append(
            f"{key}: {_type_name(tp)}{default}" + (f"  # {help_text}" if help_text else "")
        )
    return "\n".join(lines)
