"""``ReconstructConfig``: schema of the shipped ``reconstruct.yaml`` (``hsi-torch reconstruct``).

Generated from :class:`hsi_torch.recon.settings.ReconstructSettings`, the one definition of a
reconstruction setting: one flat field per key of :data:`~hsi_torch.recon.settings.FLAT_KEYS`
that the YAML file has, with the settings field's type (tuples as YAML lists), default and help
text. Loaded by :func:`hsi_torch.config.load_config`; every key can be overridden on the command
line (``--set beta=100``); ``describe_schema(ReconstructConfig)`` prints the reference. The values
are checked where the settings are built (:meth:`ReconstructConfig.settings`, also on creation):
an invalid value fails here, before a run creates its output folder.
"""

from __future__ import annotations

import dataclasses
import typing
from typing import Any

from hsi_torch.recon.settings import (
    BETA_MAX,
    FLAT_KEYS,
    GROUPS,
    RENAMED_KEYS,
    ReconstructSettings,
    thaw,
)

__all__ = ["ReconstructConfig", "BETA_MAX"]


def _as_list(tp: Any) -> Any:
    """A settings field's type in YAML form: ``tuple[X, ...]`` → ``list[X]`` (in unions too)."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is tuple and len(args) == 2 and args[1] is Ellipsis:
        return list[args[0]]  # type: ignore[valid-type]
    if origin in (typing.Union, type(int | None)):
        return typing.Union[tuple(_as_list(a) for a in args)]  # noqa: UP007
    return tp


def _schema_fields() -> list[tuple[str, Any, Any]]:
    out = []
    for key, (group, name) in FLAT_KEYS.items():
        cls = GROUPS[group]
        f = next(f for f in dataclasses.fields(cls) if f.name == name)
        if not f.metadata.get("yaml", True):
            continue
        tp = _as_list(typing.get_type_hints(cls)[name])
        if f.default_factory is not dataclasses.MISSING:
            default = f.default_factory()
            made = dataclasses.field(
                default_factory=lambda d=default: thaw(d), metadata={"help": f.metadata["help"]}
            )
        else:
            made = dataclasses.field(default=f.default, metadata={"help": f.metadata["help"]})
        out.append((key, tp, made))
    return out


def _settings(self: Any) -> ReconstructSettings:
    """These settings, grouped and frozen
    (:class:`~hsi_torch.recon.settings.ReconstructSettings`; built once per run and passed
    whole to the reconstructor and the workers).

    Raises:
        ConfigError: an invalid value (naming its key).
    """
    return ReconstructSettings.from_flat({f.name: getattr(self, f.name)
                                          for f in dataclasses.fields(self)})  # fmt: skip


def _post_init(self: Any) -> None:
    self.settings()  # every value checked where the settings are built (errors name the key)


ReconstructConfig = dataclasses.make_dataclass(
    "ReconstructConfig",
    _schema_fields(),
    namespace={"settings": _settings, "__post_init__": _post_init,
               "__doc__": "Settings of a reconstruction run (see the field help texts).",
               # keys of earlier releases, refused by the loader with what to write instead
               "__renamed_keys__": RENAMED_KEYS},
)
ReconstructConfig.__module__ = __name__
