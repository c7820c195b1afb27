"""Calibration bundle (save/load/validation/sensing matrices) and the valid-region summary."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest
import torch

import hsi_torch
from hsi_torch.calibrate.validity import valid_region
from hsi_torch.io.bundle import (
    SCHEMA_VERSION,
    CalibrationBundle,
    file_sha256,
    make_provenance,
)


def _bundle(V=3, M=5, h=4, w=6, seed=0, **kw) -> CalibrationBundle:
    rng = np.random.default_rng(seed)
    view_mask = rng.random((V, h, w)) > 0.2
    modulated = np.ones((V, h, w), bool)
    modulated[0, :2, :2] = False
    valid, _ = valid_region(torch.from_numpy(view_mask), torch.from_numpy(modulated))
    args = dict(
        wavelengths_nm=np.linspace(430, 670, M),
        triangles=rng.uniform(0, 100, (V, 3, 2)),
        parity=np.array([1, -1, -1][:V]),
        view_homographies=np.tile(np.eye(3), (V, 1, 1)),
        sensor_size=(120, 160),
        reference_bbox=(10, 20, w, h),
        B=rng.uniform(0, 1, (V, M, h, w)).astype(np.float32),
        phi=rng.uniform(1, 2, (3, M)),
        gain=rng.uniform(0.8, 1.2, (V, h, w)).astype(np.float32),
        view_mask=view_mask & modulated,
        modulated=modulated,
        valid=valid.numpy(),
        reflection_sequences=[(), (0,), (1,)][:V],
        settings={"beta_phi": 8e5, "pattern_size": [4, 5]},
        provenance={"inputs_sha256": {"scan.npz": "ab" * 32}},
        extras={"opd_nm": np.arange(V, dtype=np.float64)},
    )
    args.update(kw)
    return CalibrationBundle(**args)


def test_save_load_roundtrip(tmp_path):
    b = _bundle()
    p = b.save(tmp_path / "calib.npz")
    assert sorted(x.name for x in tmp_path.iterdir()) == ["calib.npz"]  # no temp file left
    r = CalibrationBundle.load(p)
    for k in ("wavelengths_nm", "triangles", "parity", "view_homographies", "sensor_size",
              "reference_bbox", "B", "phi", "gain", "view_mask", "modulated", "valid"):
        np.testing.assert_array_equal(getattr(r, k), getattr(b, k), err_msg=k)
        assert getattr(r, k).dtype == getattr(b, k).dtype, k
    assert r.reflection_sequences == [(), (0,), (1,)]
    assert r.settings == b.settings and r.provenance == b.provenance
    assert r.software_version == hsi_torch.__version__ and r.schema_version == SCHEMA_VERSION
    np.testing.assert_array_equal(r.extras["opd_nm"], [0.0, 1.0, 2.0])
    assert "3 views, 5 bands" in r.summary()


def test_invalid_bundle_is_refused_and_nothing_written(tmp_path):
    with pytest.raises(ValueError, match=r"'gain' has shape \(3, 4, 5\), expected \(3, 4, 6\)"):
        _bundle(gain=np.ones((3, 4, 5)))
    with pytest.raises(ValueError, match="'view_mask' must be bool"):
        _bundle(view_mask=np.ones((3, 4, 6)))
    b = _bundle()
    b.settings = {"bad": object()}
    target = tmp_path / "calib.npz"
    with pytest.raises(TypeError):
        b.save(target)
    assert list(tmp_path.iterdir()) == []


def _rewrite(src, dst, drop=(), replace=None, meta_update=None):
    with np.load(src) as z:
        data = {k: z[k] for k in z.files if k not in drop}
    if replace:
        data.update(replace)
    if meta_update:
        meta = json.loads(str(data["meta"]))
        meta.update(meta_update)
        data["meta"] = np.array(json.dumps(meta))
    np.savez(dst, **data)
    return dst


def test_load_errors_name_key_and_file(tmp_path):
    good = _bundle().save(tmp_path / "good.npz")
    p = _rewrite(good, tmp_path / "v99.npz", meta_update={"schema_version": 99})
    with pytest.raises(ValueError, match=r"v99.npz: schema_version 99 is not supported"):
        CalibrationBundle.load(p)
    p = _rewrite(good, tmp_path / "nokey.npz", drop=("phi",))
    with pytest.raises(ValueError, match=r"nokey.npz: missing key\(s\) \['phi'\]"):
        CalibrationBundle.load(p)
    p = _rewrite(good, tmp_path / "shape.npz", replace={"B": np.zeros((3, 4, 4, 6), np.float32)})
    with pytest.raises(ValueError, match=r"shape.npz: 'B' has shape"):
        CalibrationBundle.load(p)
    p = _rewrite(good, tmp_path / "dtype.npz", replace={"valid": np.zeros((4, 6), np.uint8)})
    with pytest.raises(ValueError, match=r"dtype.npz: 'valid' must be bool"):
        CalibrationBundle.load(p)
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="junk.npz: not a readable NPZ"):
        CalibrationBundle.load(tmp_path / "junk.npz")
    with pytest.raises(FileNotFoundError):
        CalibrationBundle.load(tmp_path / "absent.npz")


def test_check_compatible():
    b = _bundle()
    b.check_compatible((3, 120, 160))
    b.check_compatible((2, 3, 120, 160))
    with pytest.raises(ValueError, match=r"capture sensor size 100x160 .* bundle's 120x160"):
        b.check_compatible((3, 100, 160))


def test_sensing_model_formula(device, dtype):
    b = _bundle()
    model = b.sensing_model(device=device, dtype=dtype)
    A = model.dense()
    V, M, h, w = b.B.shape
    assert A.shape == (h * w, 3 * V, M) and A.dtype == dtype and A.device.type == device.type
    dl = np.full(M, 60.0)  # uniform 60 nm grid
    expect = np.empty((h * w, 3 * V, M))
    for p in range(h * w):
        i, j = divmod(p, w)
        for v in range(V):
            for c in range(3):
                expect[p, 3 * v + c] = b.gain[v, i, j] * b.B[v, :, i, j] * dl * b.phi[c]
    tol = {"rtol": 1e-5, "atol": 1e-5} if dtype == torch.float32 else {"rtol": 1e-7, "atol": 0}
    torch.testing.assert_close(A.cpu().double(), torch.from_numpy(expect), **tol)
    idx = torch.tensor([0, 7, 23])
    torch.testing.assert_close(b.sensing_model(idx, device=device, dtype=dtype).dense(),
                               A[idx.to(device)])
    mask = b.observation_mask(device)
    assert mask.shape == (h * w, 3 * V) and mask.dtype == torch.bool
    for v in range(V):
        for c in range(3):
            assert torch.equal(mask[:, 3 * v + c].cpu(), torch.from_numpy(b.view_mask[v].ravel()))


def test_provenance_hashes(tmp_path):
    f = tmp_path / "scan.bin"
    f.write_bytes(b"hello calibration")
    assert file_sha256(f) == hashlib.sha256(b"hello calibration").hexdigest()
    prov = make_provenance({"scan": f}, seed=3)
    assert prov["inputs_sha256"]["scan"] == file_sha256(f) and prov["seed"] == 3
    assert prov["created_utc"].endswith("+00:00")


def test_valid_region_counts_and_bbox():
    V, h, w = 4, 10, 12
    vm = torch.zeros(V, h, w, dtype=torch.bool)
    vm[0, 2:8, 3:9] = True
    vm[1, 3:9, 2:8] = True
    vm[2, 2:7, 2:10] = True
    vm[3, 4:6, 4:6] = True
    mod = torch.ones_like(vm)
    mod[2, 4:5, 4:6] = False  # BRF-free patch of view 2
    valid, s = valid_region(vm, mod)
    count = (vm & mod).sum(0)
    assert torch.equal(valid, count >= 3)
    assert s.num_valid == int((count >= 3).sum())
    # union: rows 2..8, cols 2..9
    assert s.union_bbox == (2, 2, 8, 7) and s.bbox_area == 56
    assert s.fraction == pytest.approx(s.num_valid / 56)
    assert s.views_per_pixel_max == 4
    assert f"{s.num_valid} px" in str(s) and "bounding box" in str(s)
    valid4, s4 = valid_region(vm, None, min_views=4)
    assert s4.num_valid == 4 and bool(valid4[4:6, 4:6].all())
    with pytest.raises(ValueError, match="modulated"):
        valid_region(vm, mod[:, :-1])
