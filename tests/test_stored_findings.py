"""Every cube carries its findings: stored in each cube format, flagged in the preview's
caption, listed in the run's summary and JSON report, and read back when a rerun skips the cube."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from hsi_torch.errors import FileFormatError, InputError
from hsi_torch.findings import Finding, findings_from_dicts, findings_summary
from hsi_torch.io.cube import (
    CUBE_FORMATS,
    OPTIONAL_FORMATS,
    load_cube,
    read_cube_findings,
    read_cube_metadata,
    save_cube,
)
from hsi_torch.recon.batch import driver
from hsi_torch.recon.batch.report import REPORT_SUFFIX
from hsi_torch.recon.batch.run import findings_flag, preview_caption
from hsi_torch.recon.config import ReconstructConfig

SUFFIX = {"npz": ".npz", "tiff": ".tif", "envi": ".hdr", "netcdf": ".nc", "zarr": ".zarr"}

FINDINGS = [
    Finding("fit.residual", "warning", "the spectra do not explain the capture {really}",
            measured=[0.31, 0.02], limit=0.15, fix="check the bundle", source="frame 0"),
    Finding("capture.black_level", "info", "black level from the bundle", measured=None),
    Finding("capture.pedestal", "warning", "pedestal, \"quoted\" = odd", measured=501.5,
            limit=[0, 64]),
]  # fmt: skip


def _cube() -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    return torch.rand(3, 4, 5, generator=g), torch.tensor([450.0, 550.0, 650.0])


def _skip_missing(fmt: str) -> None:
    for mod in OPTIONAL_FORMATS.get(fmt, ()):
        pytest.importorskip(mod)


@pytest.mark.parametrize("fmt", CUBE_FORMATS)
def test_findings_round_trip_every_format(tmp_path: Path, fmt: str) -> None:
    _skip_missing(fmt)
    cube, wl = _cube()
    path = tmp_path / f"c{SUFFIX[fmt]}"
    save_cube(path, cube, wl, metadata={"scene": "x"}, findings=FINDINGS)
    loaded = load_cube(path)
    assert loaded.findings == FINDINGS  # measured as a list, None, a float; limit a list
    assert findings_from_dicts(loaded.metadata["findings"]) == FINDINGS
    assert read_cube_findings(path) == FINDINGS  # metadata only
    assert read_cube_metadata(path)["findings"] == [f.to_dict() for f in FINDINGS]
    torch.testing.assert_close(loaded.cube, cube)
    # a cube stored without findings has none
    plain = tmp_path / f"p{SUFFIX[fmt]}"
    save_cube(plain, cube, wl, metadata={"scene": "x"})
    assert load_cube(plain).findings == [] and read_cube_findings(plain) == []


def test_findings_in_metadata_as_objects_or_dicts(tmp_path: Path) -> None:
    cube, wl = _cube()
    save_cube(tmp_path / "a.npz", cube, wl, metadata={"findings": FINDINGS})
    save_cube(tmp_path / "b.npz", cube, wl, metadata={"findings": [f.to_dict() for f in FINDINGS]})
    assert read_cube_findings(tmp_path / "a.npz") == read_cube_findings(tmp_path / "b.npz")
    assert read_cube_findings(tmp_path / "a.npz") == FINDINGS


def test_malformed_findings_refused_on_write(tmp_path: Path) -> None:
    cube, wl = _cube()
    with pytest.raises(InputError, match="severity"):
        save_cube(tmp_path / "a.npz", cube, wl, metadata={"findings": [{"code": "x"}]})
    with pytest.raises(InputError, match="must be a list"):
        save_cube(tmp_path / "a.npz", cube, wl, metadata={"findings": "fit.residual"})
    assert not (tmp_path / "a.npz").exists()


def test_malformed_stored_findings_name_the_file(tmp_path: Path) -> None:
    cube, wl = _cube()
    bad = tmp_path / "bad.npz"  # written by hand: save_cube refuses it
    meta = json.dumps({"findings": [{"code": "fit.residual", "severity": "fatal",
                                     "message": "m"}]})  # fmt: skip
    np.savez(bad, cube=cube.numpy(), wavelengths_nm=wl.numpy(), metadata=np.array(meta))
    for read in (load_cube, read_cube_findings):
        with pytest.raises(FileFormatError, match=r"bad\.npz.*fatal"):
            read(bad)
    notlist = tmp_path / "notlist.npz"
    np.savez(notlist, cube=cube.numpy(), wavelengths_nm=wl.numpy(),
             metadata=np.array(json.dumps({"findings": {"code": "x"}})))  # fmt: skip
    with pytest.raises(FileFormatError, match=r"notlist\.npz.*must be a list"):
        read_cube_findings(notlist)
    hdr = tmp_path / "e.hdr"
    save_cube(hdr, cube, wl, findings=FINDINGS)
    text = hdr.read_text().replace('hsi_torch findings = [{"code"', "hsi_torch findings = [{code")
    hdr.write_text(text)
    with pytest.raises(FileFormatError, match=r"e\.hdr.*not JSON"):
        read_cube_findings(hdr)


def test_preview_caption_flags_warnings() -> None:
    cfg = ReconstructConfig()
    meta = {"bundle": "/x/calib.npz", "findings": [f.to_dict() for f in FINDINGS]}
    cap = preview_caption("scene", cfg, meta)
    assert cap.splitlines()[0].startswith("scene | bundle calib.npz")
    assert cap.splitlines()[1] == "(!) 2 warnings: fit.residual, capture.pedestal"
    info_only = {"findings": [FINDINGS[1].to_dict()]}
    assert "(!)" not in preview_caption("scene", cfg, info_only)
    assert "\n" not in preview_caption("scene", cfg, {})
    err = Finding("fit.residual", "error", "refused")
    assert findings_flag([err, FINDINGS[0]]) == "(!) 1 error, 1 warning: fit.residual"
    assert findings_flag([]) == ""


class _Unreadable:
    store = None

    def stored_findings(self, inp: Path) -> list[Finding]:
        raise FileFormatError(f"{inp}.npz: metadata 'findings': not a finding")


def test_unreadable_stored_findings_become_a_warning(tmp_path: Path, capsys) -> None:
    found = driver._stored_findings(_Unreadable(), tmp_path / "a.npy")  # type: ignore[arg-type]
    assert [f.code for f in found] == ["run.findings_unreadable"]
    assert "a.npy.npz" in found[0].message
    assert "WARNING" in capsys.readouterr().err


# --- a run and its rerun ------------------------------------------------------------------


@pytest.fixture
def findings_ws(ws: tuple[Path, Path, Path]) -> tuple[Path, Path, Path]:
    """``ws`` plus ``caps/bad.npy``, a file that is not a capture (fails)."""
    root, bundle, caps = ws
    (caps / "bad.npy").write_bytes(b"not an npy file")
    return root, bundle, caps


def _run(caps: Path, bundle: Path, out: Path, fmt: str = "files"):
    from hsi_torch.recon.batch.entry import reconstruct_many

    # an NPY capture has no exposure time: the run reports "exposure unknown"; and a fit
    # residual limit no fit meets: the run reports the fit residual — two warnings, always
    return reconstruct_many([caps / "a.npy", caps / "bad.npy"], bundle, out, progress=False,
                            overrides=["fit_residual_warning=1e-12", "formats=[npz,envi]"],
                            output_format=fmt)  # fmt: skip


def test_rerun_reports_the_stored_findings(findings_ws, monkeypatch, capsys) -> None:
    from hsi_torch import colour

    root, bundle, caps = findings_ws
    out = root / "out"
    captions: list[str] = []
    real = colour.save_preview_png

    def spy(*a, caption=None, **kw):
        captions.append(caption)
        return real(*a, caption=caption, **kw)

    monkeypatch.setattr(colour, "save_preview_png", spy)
    first = _run(caps, bundle, out)
    a, bad = caps / "a.npy", caps / "bad.npy"
    assert first.processed == [a] and [f.input for f in first.failed] == [bad]
    found = first.findings[a]
    warned = [f for f in found if f.severity == "warning"]
    assert any("fit residual" in f.message for f in warned)
    n = len(warned)
    assert captions and f"(!) {n} warning{'s' if n > 1 else ''}: " in captions[0]
    # stored with the cube, in both formats written
    assert read_cube_findings(out / "a.npz") == found == read_cube_findings(out / "a.hdr")
    assert "findings: " in first.report() and "warnings" in first.report()
    capsys.readouterr()

    second = _run(caps, bundle, out)
    assert second.skipped == [a] and second.processed == []
    assert second.findings[a] == found  # the same findings come back
    err = capsys.readouterr().err
    assert "(skipped; stored with its outputs)" in err and "fit residual" in err

    # one report per run, neither overwritten
    r1, r2 = first.findings_report, second.findings_report
    assert r1 is not None and r2 is not None and r1 != r2 and r1.exists() and r2.exists()
    assert r1.name.endswith(REPORT_SUFFIX) and r1.parent == out / "runs"
    doc1, doc2 = json.loads(r1.read_text()), json.loads(r2.read_text())
    rows1 = {Path(r["input"]).name: r for r in doc1["inputs"]}
    rows2 = {Path(r["input"]).name: r for r in doc2["inputs"]}
    assert rows1["a.npy"]["status"] == "processed" and rows2["a.npy"]["status"] == "skipped"
    assert rows1["bad.npy"]["status"] == rows2["bad.npy"]["status"] == "failed"
    assert rows1["bad.npy"]["error"] and rows1["bad.npy"]["outputs"] == []
    for rows in (rows1, rows2):
        assert findings_from_dicts(rows["a.npy"]["findings"]) == found
        assert str(out / "a.npz") in rows["a.npy"]["outputs"]
    assert doc2["counts"] == {"processed": 0, "skipped": 1, "failed": 1}
    assert doc1["run_config"].startswith("runs/") and doc1["run_config"].endswith(".yaml")


def test_rerun_into_a_store_reports_the_stored_findings(findings_ws) -> None:
    pytest.importorskip("numcodecs")
    root, bundle, caps = findings_ws
    out = root / "out"
    first = _run(caps, bundle, out, fmt="zarr")
    a = caps / "a.npy"
    assert first.processed == [a]
    second = _run(caps, bundle, out, fmt="zarr")
    assert second.skipped == [a]
    assert second.findings[a] == first.findings[a] and first.findings[a]
    doc = json.loads(second.findings_report.read_text())
    row = next(r for r in doc["inputs"] if r["status"] == "skipped")
    assert row["outputs"] == [str(out / "cubes.zarr")]


def test_viewer_layers_carry_the_findings(tmp_path: Path) -> None:
    from hsi_torch.viewer.data import read_layers

    cube, wl = _cube()
    save_cube(tmp_path / "scene.npz", cube, wl, findings=FINDINGS)
    (_, bands, _), (_, rgb, _) = read_layers(tmp_path / "scene.npz")
    assert bands["name"] == "scene (bands) (!) 2 warnings"
    assert rgb["name"] == "scene (sRGB) (!) 2 warnings"
    assert bands["metadata"]["findings"] == FINDINGS
    save_cube(tmp_path / "clean.npz", cube, wl, findings=[FINDINGS[1]])  # info only: no flag
    (_, bands, _), _ = read_layers(tmp_path / "clean.npz")
    assert bands["name"] == "clean (bands)" and bands["metadata"]["findings"] == [FINDINGS[1]]


def test_cli_rerun_prints_the_stored_findings_and_their_count(ws, capsys) -> None:
    from hsi_torch.cli import main

    root, bundle, caps = ws
    out = root / "out"
    argv = ["reconstruct", "--bundle", str(bundle), "--out", str(out), "--no-progress",
            "--set", "fit_residual_warning=1e-12", "--set", "formats=[npz]",
            str(caps / "a.npy")]  # fmt: skip
    assert main(argv) == 0
    first = capsys.readouterr().err
    assert main(argv) == 0
    second = capsys.readouterr().err
    reports = sorted((out / "runs").glob("*" + REPORT_SUFFIX))
    assert len(reports) == 2  # one per run
    docs = [json.loads(r.read_text()) for r in reports]  # (names in the same second: any order)
    assert sorted(d["inputs"][0]["status"] for d in docs) == ["processed", "skipped"]
    stored = docs[0]["inputs"][0]["findings"]
    assert stored and stored == docs[1]["inputs"][0]["findings"]
    n = sum(f["severity"] == "warning" for f in stored)
    assert n >= 1  # the fit residual
    counts = findings_summary(findings_from_dicts(stored))
    assert "1 processed" in first and f"findings: {counts} (report: " in first
    assert "1 skipped" in second and f"findings: {counts} (report: " in second
    assert second.count("(skipped; stored with its outputs): warning [") == n
