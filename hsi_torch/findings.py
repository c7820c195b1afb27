"""Findings: what a check measured, against which limit, and what to do about it.

Every check hsi_torch runs on a capture, a frame, a bundle or a run yields :class:`Finding`
objects instead of printed lines. A finding is plain data (JSON-able through :meth:`to_dict`):
it is stored with the cube in every format we write, listed in the run's summary and report,
raised in Python as a warning of the class its code maps to (:func:`warn_findings`), and read
back on a rerun that skips an existing cube.

Severities, in order: ``"info"`` (a fact worth recording: the black level came from the bundle,
the exposure was scaled), ``"warning"`` (the cube may be wrong in the way the message says),
``"error"`` (the data contradicts the result: the frame is refused, :class:`RefusedError`).
``strict`` runs treat every warning as an error (:func:`escalated`).

Warning classes (all :class:`HSIWarning`, a ``UserWarning``): :class:`CaptureWarning` (black
level, pedestal, exposure, camera, data scale), :class:`FitWarning` (fit residual, unconverged
pixels), :class:`DriftWarning` (sensor drift), :class:`CalibrationWarning` (a bundle's
own findings). Filter them with the standard :mod:`warnings` machinery, e.g.
``warnings.simplefilter("error", hsi_torch.findings.FitWarning)``.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass, replace
from typing import Any

from hsi_torch.errors import InputError

__all__ = [
    "SEVERITIES",
    "Finding",
    "HSIWarning",
    "CaptureWarning",
    "FitWarning",
    "DriftWarning",
    "CalibrationWarning",
    "RefusedError",
    "warning_class",
    "warn_findings",
    "escalated",
    "refusals",
    "refuse_or_warn",
    "worst_severity",
    "findings_from_dicts",
    "findings_summary",
]

#: severities, least to most severe
SEVERITIES = ("info", "warning", "error")


class HSIWarning(UserWarning):
    """Base class of the warnings hsi_torch raises from findings (``.finding`` holds it)."""

    finding: Finding | None = None


class CaptureWarning(HSIWarning):
    """About the capture: black level, pedestal, exposure, camera identity, data scale."""


class FitWarning(HSIWarning):
    """About the solve: a fit residual the bundle does not explain, unconverged pixels."""


class DriftWarning(HSIWarning):
    """About the registration: the sensor moved since calibration, or could not be measured."""


class CalibrationWarning(HSIWarning):
    """About a calibration bundle's own captures (veil, defects, illuminant, layout)."""


#: finding code prefix → warning class (the longest matching prefix wins)
_CLASSES: dict[str, type[HSIWarning]] = {
    "capture.": CaptureWarning,
    "fit.": FitWarning,
    "drift.": DriftWarning,
    "calibration.": CalibrationWarning,
}


@dataclass(frozen=True)
class Finding:
    """One check's outcome.

    Attributes:
        code: a stable dotted identifier, ``<area>.<what>`` (e.g. ``"fit.residual"``,
            ``"capture.pedestal"``, ``"drift.unmeasurable"``); the area picks the warning class.
        severity: ``"info"``, ``"warning"`` or ``"error"`` (:data:`SEVERITIES`).
        message: one sentence saying what was found.
        measured: the measured value (a number, a list or a short string), or ``None``.
        limit: the limit it was compared with (same form), or ``None``.
        fix: what to do about it (a sentence, e.g. the ``--set`` that fixes it), or ``None``.
        source: what it is about (a file, ``"frame 3"``), or ``None``.
    """

    code: str
    severity: str
    message: str
    measured: Any = None
    limit: Any = None
    fix: str | None = None
    source: str | None = None

    def __post_init__(self) -> None:
        if self.severity not in SEVERITIES:
            raise ValueError(f"Finding {self.code!r}: severity must be one of {SEVERITIES}, "
                             f"got {self.severity!r}")  # fmt: skip
        if not isinstance(self.code, str) or not self.code:
            raise ValueError(f"Finding code must be a non-empty string, got {self.code!r}")

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able form (non-finite numbers become ``None``)."""
        return {k: _plain(v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Finding:
        """The inverse of :meth:`to_dict`; unknown keys are ignored, a bad entry raises
        :class:`~hsi_torch.errors.InputError` naming it."""
        if not isinstance(d, Mapping):
            raise InputError(f"a finding must be a mapping, got {type(d).__name__}")
        try:
            return cls(**{k: d[k] for k in cls.__dataclass_fields__ if k in d})
        except (TypeError, ValueError) as exc:
            raise InputError(f"not a finding: {dict(d)!r}: {exc}") from None

    def text(self) -> str:
        """One line: ``"<severity> [<code>] <source>: <message> (measured …, limit …) — fix"``."""
        pairs = (("measured", self.measured), ("limit", self.limit))
        nums = ", ".join(f"{k} {_short(v)}" for k, v in pairs if v is not None)
        return (f"{self.severity} [{self.code}] " + (f"{self.source}: " if self.source else "")
                + self.message + (f" ({nums})" if nums else "")
                + (f"; fix: {self.fix}" if self.fix else ""))  # fmt: skip

    __str__ = text


class RefusedError(InputError):
    """A result the data contradicts: the frame is refused and no cube is written.
    ``.findings`` holds the findings of what was refused: its error findings (under ``strict``
    the escalated warnings too), and the frame's other findings beside them."""

    def __init__(self, message: str, findings: Iterable[Finding] = ()) -> None:
        super().__init__(message)
        self.findings = list(findings)


def warning_class(code: str) -> type[HSIWarning]:
    """The :class:`HSIWarning` subclass a finding code maps to (:class:`HSIWarning` itself for
    an unknown area)."""
    best = max((prefix for prefix in _CLASSES if code.startswith(prefix)), key=len, default="")
    return _CLASSES.get(best, HSIWarning)


def warn_findings(findings: Iterable[Finding], stacklevel: int = 2) -> None:
    """Raise every ``"warning"`` finding as a Python warning of its class (``.finding`` set)."""
    for f in findings:
        if f.severity == "warning":
            w = warning_class(f.code)(f.text())
            w.finding = f
            warnings.warn(w, stacklevel=stacklevel + 1)


def escalated(findings: Iterable[Finding], strict: bool) -> list[Finding]:
    """``findings`` with every warning made an error when ``strict`` (the rest unchanged)."""
    out = list(findings)
    return [replace(f, severity="error") if strict and f.severity == "warning" else f for f in out]


def refusals(findings: Iterable[Finding]) -> list[Finding]:
    """The ``"error"`` findings (those that refuse a frame)."""
    return [f for f in findings if f.severity == "error"]


def refuse_or_warn(findings: Iterable[Finding], strict: bool = False, source: str | None = None,
                   stacklevel: int = 2) -> list[Finding]:
    """The verdict on a frame's findings: escalated under ``strict`` (:func:`escalated`), a
    :class:`RefusedError` on any error finding, else every warning raised as a Python warning
    (:func:`warn_findings`; ``stacklevel`` 2 points at the caller of the function that calls
    this one).

    Args:
        source: named once at the head of the refusal's message (``"<source>: refused: ..."``,
            the findings' own sources left out); ``None``: the findings' texts alone.

    Returns:
        The findings, escalated (nothing refused).

    Raises:
        RefusedError: an error finding; ``.findings`` holds them all.
    """
    out = escalated(findings, strict)
    refused = refusals(out)
    if refused:
        if source is None:
            raise RefusedError("; ".join(f.text() for f in refused), out)
        raise RefusedError(f"{source}: refused: " + "; ".join(
            replace(f, source=None).text() for f in refused), out)  # fmt: skip
    warn_findings(out, stacklevel=stacklevel + 1)
    return out


def worst_severity(findings: Iterable[Finding]) -> str | None:
    """The most severe severity among ``findings`` (``None`` when empty)."""
    ranks = [SEVERITIES.index(f.severity) for f in findings]
    return SEVERITIES[max(ranks)] if ranks else None


def findings_from_dicts(items: Any, source: str = "metadata") -> list[Finding]:
    """Findings stored as a list of dicts (a cube's metadata, a report); ``None`` → ``[]``.
    Raises :class:`~hsi_torch.errors.InputError` naming ``source`` for anything else."""
    if items is None:
        return []
    if not isinstance(items, list):
        raise InputError(f"{source}: 'findings' must be a list, got {type(items).__name__}")
    return [Finding.from_dict(d) for d in items]


def findings_summary(findings: Iterable[Finding]) -> str:
    """``"2 warnings, 1 info"`` (``"no findings"`` when empty), most severe first."""
    fs = list(findings)
    parts = []
    for sev in reversed(SEVERITIES):
        n = sum(f.severity == sev for f in fs)
        if n:
            parts.append(f"{n} {sev}" + ("s" if n > 1 and sev != "info" else ""))
    return ", ".join(parts) or "no findings"


def _plain(v: Any) -> Any:
    if isinstance(v, float):
        return v if math.isfinite(v) else None
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, Mapping):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, (str, int, bool)) or v is None:
        return v
    try:  # numpy / torch scalars
        return _plain(v.item())
    except (AttributeError, ValueError, RuntimeError):
        return str(v)


def _short(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_short(x) for x in v) + "]"
    return str(v)
