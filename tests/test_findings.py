"""The findings model: round trip through JSON, severities, warning classes, strict escalation."""

from __future__ import annotations

import json
import sys
import warnings

import pytest

from hsi_torch.errors import InputError
from hsi_torch.findings import (
    CaptureWarning,
    DriftWarning,
    Finding,
    FitWarning,
    HSIWarning,
    RefusedError,
    escalated,
    findings_from_dicts,
    findings_summary,
    refusals,
    refuse_or_warn,
    warn_findings,
    warning_class,
    worst_severity,
)


def _fit() -> Finding:
    return Finding("fit.residual", "warning", "the bundle does not explain the capture",
                   measured=0.27, limit=0.15, fix="recalibrate", source="a.dng")  # fmt: skip


def test_round_trip_through_json_is_exact() -> None:
    f = _fit()
    assert Finding.from_dict(json.loads(json.dumps(f.to_dict()))) == f
    g = Finding("capture.pedestal", "warning", "x", measured=[float("nan"), 1.0])
    assert g.to_dict()["measured"] == [None, 1.0]  # non-finite numbers stored as null


def test_bad_severity_and_bad_dicts_are_refused() -> None:
    with pytest.raises(ValueError, match="severity"):
        Finding("fit.residual", "fatal", "x")
    with pytest.raises(InputError, match="not a finding"):
        Finding.from_dict({"code": "a"})
    with pytest.raises(InputError, match="cube.tif: 'findings' must be a list"):
        findings_from_dicts({"code": "a"}, "cube.tif")
    assert findings_from_dicts(None) == []


@pytest.mark.parametrize(
    ("code", "cls"),
    [("fit.residual", FitWarning), ("capture.pedestal", CaptureWarning),
     ("drift.unmeasurable", DriftWarning), ("other.thing", HSIWarning)],
)  # fmt: skip
def test_warning_class_by_area(code: str, cls: type) -> None:
    assert warning_class(code) is cls


def test_warn_findings_raises_only_warnings_with_the_finding_attached() -> None:
    info = Finding("capture.black_level", "info", "from the bundle")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        warn_findings([_fit(), info])
    assert len(caught) == 1 and caught[0].category is FitWarning
    assert caught[0].message.finding == _fit()
    assert "measured 0.27, limit 0.15" in str(caught[0].message)


def _judge_here(fs: list[Finding], **kw) -> list[Finding]:
    return refuse_or_warn(fs, **kw)  # stacklevel 2: the warning points at the caller of this


def test_refuse_or_warn_warns_at_the_caller_or_refuses_naming_the_source() -> None:
    info = Finding("capture.black_level", "info", "from the bundle")
    with pytest.warns(FitWarning) as caught:
        line = sys._getframe().f_lineno + 1
        out = _judge_here([_fit(), info])
    assert out == [_fit(), info]
    assert (caught[0].filename, caught[0].lineno) == (__file__, line)
    with pytest.raises(RefusedError, match=r"^a\.dng: refused: error \[fit") as refused:
        refuse_or_warn([_fit(), info], strict=True, source="a.dng")
    assert "a.dng" not in str(refused.value)[len("a.dng: "):]  # named once, at the head
    assert [f.severity for f in refused.value.findings] == ["error", "info"]
    with pytest.raises(RefusedError) as refused:
        refuse_or_warn([_fit()], strict=True)  # no source: the findings' own texts
    assert str(refused.value) == refused.value.findings[0].text()


def test_strict_makes_warnings_errors_and_summaries_count() -> None:
    fs = [_fit(), Finding("capture.black_level", "info", "x")]
    assert refusals(fs) == [] and worst_severity(fs) == "warning"
    strict = escalated(fs, strict=True)
    assert [f.severity for f in strict] == ["error", "info"] and len(refusals(strict)) == 1
    assert escalated(fs, strict=False) == fs
    assert findings_summary(strict) == "1 error, 1 info"
    assert findings_summary([]) == "no findings" and worst_severity([]) is None
