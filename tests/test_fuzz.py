"""Property-based fuzzing (hypothesis) of the readers, the config loader and the solver.

Every reader, given random bytes, a truncated file, random headers or random metadata, either
returns a valid result or raises an :class:`hsi_torch.errors.HSIError` (whose message names the
file) — never a raw exception, never a hang (each call runs under an alarm). The config loader,
given random keys and values, returns a checked instance (every float finite) or raises
``ConfigError``. ``solve_nnls`` on random, rank-deficient and masked problems (β = 0 included)
returns a finite ``x ≥ 0`` whose converged pixels satisfy the KKT conditions, checked here
independently in numpy; the others are flagged. The bundle reader survives random key removals,
dtype and shape changes and version numbers.

The examples are derandomized (a fixed seed: the same cases every run) with small budgets, so
this file runs in well under a minute on two cores. For a longer campaign set
``HSI_FUZZ_EXAMPLES=<n>``: every test then draws ``n`` random (not derandomized) examples, e.g.
``HSI_FUZZ_EXAMPLES=2000 python -m pytest tests/test_fuzz.py --hypothesis-seed=1``.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import signal
import tempfile
import zipfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import tifffile
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_pipeline import make_bundle

from hsi_torch.config import ConfigError, load_config
from hsi_torch.errors import HSIError
from hsi_torch.io import load_cube, read_any, save_cube
from hsi_torch.io.bundle import CalibrationBundle
from hsi_torch.io.captures import LinearCapture
from hsi_torch.recon.nnls import solve_nnls
from hsi_torch.spectral import difference_matrix

_BUDGET = os.environ.get("HSI_FUZZ_EXAMPLES")
settings.register_profile(
    "hsi_fuzz", derandomize=not _BUDGET, database=None, deadline=None, print_blob=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)  # fmt: skip


def fuzz(n: int):
    """``@settings`` of this file: fixed seed, ``n`` examples (or ``$HSI_FUZZ_EXAMPLES``)."""
    return settings(settings.get_profile("hsi_fuzz"), max_examples=int(_BUDGET or n))


@contextlib.contextmanager
def no_hang(seconds: float = 20.0) -> Iterator[None]:
    """Fail (``TimeoutError``) when the block runs longer than ``seconds`` (SIGALRM)."""
    if not hasattr(signal, "setitimer"):
        yield
        return

    def on_alarm(signum, frame):
        raise TimeoutError(f"no answer within {seconds} s (a hang)")

    old = signal.signal(signal.SIGALRM, on_alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


def clear_or_valid(fn, *args, **kwargs):
    """``fn(*args)``; an exception must be an HSIError that names the file (if one is given)."""
    with no_hang():
        try:
            return fn(*args, **kwargs)
        except HSIError as exc:
            path = args[0] if args and isinstance(args[0], Path) else None
            if path is not None:  # the file, or its ENVI companion (.hdr/.img)
                assert path.stem in str(exc), f"the error does not name the file: {exc}"
            assert "\n" not in str(exc).strip() or len(str(exc)) < 2000
            return None


@pytest.fixture(scope="module")
def scratch() -> Iterator[Path]:
    with tempfile.TemporaryDirectory(prefix="hsi_fuzz_") as d:
        yield Path(d)


def _check_capture(cap: LinearCapture | None) -> None:
    if cap is None:
        return
    assert cap.image.ndim == 3 and cap.image.shape[0] == 3
    assert cap.saturated.shape == cap.image.shape and cap.saturated.dtype == torch.bool
    assert isinstance(cap.metadata, dict)


# ---------------------------------------------------------------------------------------------
# capture and cube readers

_CAPTURE_SUFFIXES = [".tif", ".npy", ".npz"]


def _valid_capture_bytes(kind: str, suffix: str, meta: dict, seed: int = 0) -> bytes:
    rng = np.random.default_rng(seed)
    shape = (6, 8) if kind == "bayer" else (6, 8, 3)
    arr = rng.integers(0, 4096, size=shape).astype(np.uint16)
    buf = io.BytesIO()
    if suffix == ".tif":
        tifffile.imwrite(buf, arr, description=json.dumps(meta), metadata=None,
                         photometric="minisblack" if kind == "bayer" else "rgb")  # fmt: skip
    elif suffix == ".npy":
        np.save(buf, arr)
    else:
        np.savez(buf, image=arr, metadata=np.array(json.dumps(meta)))
    return buf.getvalue()


_json_scalars = (st.none() | st.booleans() | st.integers(-(2**70), 2**70)
                 | st.floats(allow_nan=True, allow_infinity=True) | st.text(max_size=8))
_json_values = st.recursive(
    _json_scalars, lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=6), c,
                                                                          max_size=3),
    max_leaves=8,
)
_meta_keys = st.sampled_from(["kind", "cfa_pattern", "black_level", "white_level", "exposure_s",
                              "hsi_torch_capture", "wavelength_nm", "role", "x"])
_metadata = st.dictionaries(_meta_keys, _json_values | st.sampled_from(
    ["bayer", "rgb", "RGGB", "gbrg", "XYZW", [64, 64, 64, 64], [1, 2, 3], 4095, 0.01]),
    max_size=5)


@fuzz(120)
@given(data=st.binary(max_size=600), suffix=st.sampled_from([*_CAPTURE_SUFFIXES, ".dng"]))
def test_capture_reader_on_random_bytes(scratch, data, suffix):
    p = scratch / f"random{suffix}"
    p.write_bytes(data)
    _check_capture(clear_or_valid(read_any, p))


@fuzz(120)
@given(kind=st.sampled_from(["bayer", "rgb"]), suffix=st.sampled_from(_CAPTURE_SUFFIXES),
       cut=st.floats(0, 1), flips=st.lists(st.tuples(st.integers(0, 400), st.integers(0, 255)),
                                           max_size=6))
def test_capture_reader_on_truncated_and_corrupted_headers(scratch, kind, suffix, cut, flips):
    data = bytearray(_valid_capture_bytes(kind, suffix, {"kind": kind, "cfa_pattern": "RGGB"}))
    for pos, val in flips:  # header/IFD bytes changed
        if pos < len(data):
            data[pos] = val
    data = data[: int(round(cut * len(data)))] if cut < 0.97 else data
    p = scratch / f"cut{suffix}"
    p.write_bytes(bytes(data))
    _check_capture(clear_or_valid(read_any, p))
    _check_capture(clear_or_valid(read_any, p, expected_size=(6, 8), demosaic="half"))


@fuzz(150)
@given(kind=st.sampled_from(["bayer", "rgb"]), suffix=st.sampled_from([".tif", ".npz"]),
       meta=_metadata)
def test_capture_reader_on_random_metadata(scratch, kind, suffix, meta):
    try:
        text = json.dumps(meta)
    except ValueError:
        text = json.dumps(meta, allow_nan=True)
    p = scratch / f"meta{suffix}"
    raw = _valid_capture_bytes(kind, suffix, {}, seed=1)
    if suffix == ".tif":
        arr = tifffile.imread(io.BytesIO(raw))
        tifffile.imwrite(p, arr, description=text, metadata=None,
                         photometric="minisblack" if kind == "bayer" else "rgb")  # fmt: skip
    else:
        with np.load(io.BytesIO(raw)) as z:
            np.savez(p, image=z["image"], metadata=np.array(text))
    cap = clear_or_valid(read_any, p, default_cfa_pattern="RGGB")
    _check_capture(cap)
    if cap is not None:  # what was accepted is what the file says
        assert cap.metadata["kind"] == kind


@fuzz(60)
@given(fmt=st.sampled_from([".npz", ".tif", ".hdr"]), cut=st.floats(0, 1),
       data=st.binary(max_size=300), flips=st.lists(st.tuples(st.integers(0, 300),
                                                               st.integers(0, 255)), max_size=4))
def test_cube_reader_on_truncated_and_random_files(scratch, fmt, cut, data, flips):
    d = scratch / "cubes"
    d.mkdir(exist_ok=True)
    cube = np.random.default_rng(0).random((3, 4, 5)).astype(np.float32)
    paths = save_cube(d / f"c{fmt}", cube, [450.0, 550.0, 650.0])
    for p in paths:  # each file of the format (ENVI: .img and .hdr) cut and changed
        b = bytearray(p.read_bytes())
        for pos, val in flips:
            if pos < len(b):
                b[pos] = val
        p.write_bytes(bytes(b[: int(round(cut * len(b)))]))
    res = clear_or_valid(load_cube, d / f"c{fmt}")
    if res is not None:
        assert res.cube.ndim == 3 and res.wavelengths.shape == (res.cube.shape[0],)
    r = d / f"r{fmt}"
    r.write_bytes(data)
    clear_or_valid(load_cube, r, wavelengths=[450.0, 550.0, 650.0])


# ---------------------------------------------------------------------------------------------
# the config loader


def _finite_everywhere(obj) -> bool:
    import dataclasses

    if dataclasses.is_dataclass(obj):
        return all(_finite_everywhere(getattr(obj, f.name)) for f in dataclasses.fields(obj))
    if isinstance(obj, float):
        return math.isfinite(obj)
    if isinstance(obj, (list, tuple)):
        return all(_finite_everywhere(v) for v in obj)
    if isinstance(obj, dict):
        return all(_finite_everywhere(v) for v in obj.values())
    return True


def _schemas():
    from hsi_torch.calibrate.config import CalibrateConfig
    from hsi_torch.recon.config import ReconstructConfig
    from hsi_torch.simulate.config import SimulateConfig

    return [ReconstructConfig, CalibrateConfig, SimulateConfig]


def _keys_of(cls, prefix=""):
    import dataclasses
    import typing

    hints = typing.get_type_hints(cls)
    out = []
    for f in dataclasses.fields(cls):
        out.append(prefix + f.name)
        tp = hints[f.name]
        if dataclasses.is_dataclass(tp):
            out += _keys_of(tp, prefix + f.name + ".")
    return out


_SCHEMA_KEYS = {cls.__name__: _keys_of(cls) for cls in _schemas()}
_yaml_values = st.sampled_from([
    "1", "-3", "0", "1e3", ".inf", "-.inf", ".nan", "1e999", "null", "true", "abc", "[1, 2]",
    "[[1, 2], [3, 4]]", "{a: 1}", "''", "[", "RGGB", "float64", "cpu", "'1e-3'", "0x10",
    "[.nan]", "99999999999999999999999999", "!!python/object:os.system ls",
])


@fuzz(150)
@given(which=st.integers(0, 2), items=st.lists(st.tuples(st.integers(0, 200),
                                                         _json_values), max_size=4),
       extra=st.dictionaries(st.text(max_size=5), _json_scalars, max_size=2))
def test_config_loader_on_random_keys_and_values(which, items, extra):
    cls = _schemas()[which]
    keys = _SCHEMA_KEYS[cls.__name__]
    data: dict = dict(extra)
    for i, value in items:
        node = data
        parts = keys[i % len(keys)].split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {}) if isinstance(node.get(part, {}), dict) else {}
        node[parts[-1]] = value
    with no_hang():
        try:
            cfg = load_config(data, cls)
        except ConfigError as exc:
            assert str(exc).startswith("<dict>")
            return
    assert isinstance(cfg, cls) and _finite_everywhere(cfg)


@fuzz(150)
@given(which=st.integers(0, 2), picks=st.lists(st.tuples(st.integers(0, 200), _yaml_values),
                                               min_size=1, max_size=3),
       junk=st.text(max_size=12))
def test_config_overrides_and_yaml_files(scratch, which, picks, junk):
    cls = _schemas()[which]
    keys = _SCHEMA_KEYS[cls.__name__]
    overrides = [f"{keys[i % len(keys)]}={v}" for i, v in picks]
    with no_hang():
        for src, ov in ((None, overrides), (None, [junk]), (None, [f"{junk}={junk}"])):
            try:
                cfg = load_config(src, cls, overrides=ov)
                assert _finite_everywhere(cfg)
            except ConfigError:
                pass
        p = scratch / "cfg.yaml"
        p.write_text("\n".join(f"{o.replace('=', ': ', 1)}" for o in overrides) + "\n" + junk)
        try:
            assert _finite_everywhere(load_config(p, cls))
        except ConfigError as exc:
            assert str(p) in str(exc)


# ---------------------------------------------------------------------------------------------
# the solver


def _kkt_violation(A, y, w, beta, order, x) -> np.ndarray:
    """Per pixel ``‖min(diag(G)·x, g)‖ / (‖G‖₂‖x‖ + ‖b‖)``, from scratch in float64 numpy."""
    P, O, M = A.shape
    D = difference_matrix(M, order, dtype=torch.float64).numpy() if beta > 0 else np.zeros((1, M))
    out = np.zeros(P)
    for p in range(P):
        Aw = A[p] * w[p][:, None]
        G = Aw.T @ A[p] + beta * D.T @ D
        b = Aw.T @ np.where(w[p], y[p], 0.0)
        g = G @ x[p] - b
        r = np.minimum(np.diag(G) * x[p], g)
        out[p] = np.linalg.norm(r) / (np.linalg.norm(G, 2) * np.linalg.norm(x[p])
                                      + np.linalg.norm(b) + 1e-300)
    return out


@st.composite
def nnls_problems(draw):
    P = draw(st.integers(0, 6))
    O = draw(st.integers(1, 9))
    M = draw(st.integers(1, 7))
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    A = rng.random((P, O, M)) * 10.0 ** draw(st.integers(-3, 3))
    kind = draw(st.sampled_from(["plain", "zero_column", "duplicate_column", "low_rank"]))
    if kind == "zero_column" and M > 1:
        A[:, :, rng.integers(M)] = 0.0
    elif kind == "duplicate_column" and M > 1:
        A[:, :, -1] = A[:, :, 0]
    elif kind == "low_rank":
        A = rng.random((P, O, 1)) @ rng.random((P, 1, M))
    x_true = np.where(rng.random((P, M)) < 0.4, 0.0, rng.random((P, M)))
    y = np.einsum("pom,pm->po", A, x_true) + draw(st.sampled_from([0.0, 0.01, 1.0])) * \
        rng.standard_normal((P, O))  # fmt: skip
    w = rng.random((P, O)) < draw(st.sampled_from([1.0, 0.7, 0.3, 0.0]))
    y = np.where(w | (rng.random((P, O)) < 0.5), y, np.nan)  # NaN only where masked
    beta = draw(st.sampled_from([0.0, 0.0, 1e-3, 1.0, 1e3]))
    order = draw(st.sampled_from([0, 1, 2]))
    if beta > 0 and M < order + 1:
        order = 0
    return A, y, w, beta, order


@fuzz(150)
@given(problem=nnls_problems(), solver=st.sampled_from(["active_set", "active_set", "admm"]))
def test_solve_nnls_kkt_or_flagged_never_nan(problem, solver):
    A, y, w, beta, order = problem
    with no_hang():
        res = solve_nnls(torch.from_numpy(A), torch.from_numpy(y), mask=torch.from_numpy(w),
                         beta=beta, diff_order=order, solver=solver)  # fmt: skip
    x = res.x.numpy()
    assert x.shape == (A.shape[0], A.shape[2]) and np.all(np.isfinite(x)) and np.all(x >= 0)
    assert not np.any(np.isnan(res.kkt_residual.numpy()))
    nod = res.no_data.numpy()
    assert np.array_equal(nod, ~w.any(1)) and np.all(x[nod] == 0)
    conv = res.converged.numpy() & ~nod
    viol = _kkt_violation(A, y, w, beta, order, x)
    tol = 1e-8 if solver == "active_set" else 1e-4
    assert np.all(viol[conv] <= tol), (viol[conv], res.kkt_residual.numpy()[conv])


# ---------------------------------------------------------------------------------------------
# the bundle reader


@pytest.fixture(scope="module")
def bundle_arrays() -> dict[str, np.ndarray]:
    """The arrays of a small valid bundle file (4 views, 8 bands, 6x6 reference frame)."""
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "b.npz"
        make_bundle(t=6, missing=1).save(p)
        with np.load(p) as z:
            return {k: z[k] for k in z.files}


_array_keys = ["wavelengths_nm", "layout_triangles", "layout_parity", "layout_view_homographies",
               "layout_sensor_size", "layout_reference_bbox", "B", "phi", "gain", "view_mask",
               "modulated", "valid", "meta"]
_dtypes = st.sampled_from(["float32", "float16", "int64", "int8", "uint8", "bool", "complex64",
                           "U3"])
_change = st.one_of(
    st.tuples(st.just("drop"), st.sampled_from(_array_keys)),
    st.tuples(st.just("dtype"), st.sampled_from(_array_keys), _dtypes),
    st.tuples(st.just("shape"), st.sampled_from(_array_keys),
              st.sampled_from(["add_axis", "drop_axis", "transpose", "half", "empty", "scalar"])),
    st.tuples(st.just("value"), st.sampled_from(_array_keys),
              st.sampled_from([np.nan, np.inf, -1.0, 0.0, 1e30])),
    st.tuples(st.just("meta"), st.sampled_from(["schema_version", "reflection_sequences",
                                                "settings", "provenance", "software_version",
                                                "whole"]), _json_values),
)


def _mutated(arrays: dict[str, np.ndarray], change: tuple) -> dict[str, np.ndarray]:
    a = dict(arrays)
    op, key = change[0], change[1]
    if (key if op != "meta" else "meta") not in a:
        return a  # dropped by an earlier change
    if op == "drop":
        a.pop(key, None)
    elif op == "dtype":
        with np.errstate(all="ignore"), contextlib.suppress(ValueError, TypeError, OverflowError):
            a[key] = a[key].astype(change[2])
    elif op == "shape":
        v = a[key]
        how = change[2]
        if how == "add_axis":
            v = v[None]
        elif how == "drop_axis" and v.ndim and v.shape[0]:
            v = v[0]
        elif how == "transpose":
            v = v.T
        elif how == "half" and v.ndim:
            v = v[: max(0, v.shape[0] // 2)]
        elif how == "empty":
            v = v.reshape(-1)[:0]
        elif how == "scalar":
            v = np.asarray(v.reshape(-1)[0] if v.size else 0)
        a[key] = v
    elif op == "value":
        v = np.array(a[key], copy=True)
        if v.size and v.dtype.kind in "fiu":
            with np.errstate(all="ignore"), contextlib.suppress(ValueError, OverflowError):
                v.reshape(-1)[0] = change[2]
        a[key] = v
    else:  # meta
        try:
            meta = json.loads(str(a["meta"]))
        except ValueError:
            meta = {}
        meta = meta if isinstance(meta, dict) else {}
        if key == "whole":
            meta = change[2]
        else:
            meta[key] = change[2]
        a["meta"] = np.array(json.dumps(meta, allow_nan=True))
    return a


@fuzz(200)
@given(changes=st.lists(_change, min_size=1, max_size=3))
def test_bundle_reader_on_changed_keys_dtypes_shapes_and_versions(scratch, bundle_arrays,
                                                                  changes):
    arrays = bundle_arrays
    for c in changes:
        arrays = _mutated(arrays, c)
    p = scratch / "bundle.npz"
    np.savez(p, **arrays)
    b = clear_or_valid(CalibrationBundle.load, p)
    if b is not None:  # accepted: consistent, usable
        b.validate()
        A = b.sensing_model(dtype=torch.float64).dense()
        assert A.shape == (b.frame_size[0] * b.frame_size[1], 3 * b.num_views, b.num_bands)


@fuzz(40)
@given(cut=st.floats(0, 0.999), data=st.binary(max_size=400))
def test_bundle_reader_on_truncated_and_random_files(scratch, bundle_arrays, cut, data):
    p = scratch / "cut.npz"
    np.savez(p, **bundle_arrays)
    raw = p.read_bytes()
    p.write_bytes(raw[: int(cut * len(raw))])
    clear_or_valid(CalibrationBundle.load, p)
    q = scratch / "junk.npz"
    q.write_bytes(data)
    clear_or_valid(CalibrationBundle.load, q)
    z = scratch / "zip.npz"  # a zip archive of random members
    with zipfile.ZipFile(z, "w") as f:
        f.writestr("meta.npy", data)
        f.writestr("B.npy", data[::-1])
    clear_or_valid(CalibrationBundle.load, z)


def _npy_bytes_declaring(shape: tuple[int, ...], dtype: str, payload: bytes) -> bytes:
    """An ``.npy`` member whose header declares ``shape`` but which holds only ``payload``."""
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        buf, {"descr": np.dtype(dtype).str, "fortran_order": False, "shape": shape})
    return buf.getvalue() + payload


_member_names = st.sampled_from(["B", "gain", "valid", "phi", "layout_triangles", "meta",
                                 "wavelengths_nm", "extra_x", "payload", "B.npy", "../evil",
                                 "layout_reference_bbox"])
_shapes = st.lists(st.sampled_from([0, 1, 3, 4, 6, 8, 10**3, 10**6, 10**9]), min_size=0,
                   max_size=4).map(tuple)


@fuzz(80)
@given(edits=st.lists(st.tuples(_member_names, _shapes,
                                st.sampled_from(["<f4", "<f8", "|b1", "<i8", "<U8", "<c16"]),
                                st.binary(max_size=64)), min_size=1, max_size=3))
def test_bundle_reader_on_unknown_and_oversized_members(scratch, bundle_arrays, edits):
    """Members added or replaced by ones whose ``.npy`` header declares any shape (up to 10^9
    elements per axis, deflated to nothing): a valid bundle or an HSIError, and nothing large
    is ever allocated (the sizes are checked from the headers before decompressing)."""
    import tracemalloc

    p = scratch / "members.npz"
    np.savez(p, **bundle_arrays)
    names = {n + ".npy": n for n in bundle_arrays}
    with zipfile.ZipFile(p) as zin:
        members = {i.filename: zin.read(i) for i in zin.infolist()}
    for name, shape, dtype, payload in edits:
        fname = name if name.endswith(".npy") or name.startswith("..") else name + ".npy"
        members[fname] = _npy_bytes_declaring(shape, dtype, payload)
    with zipfile.ZipFile(p, "w", zipfile.ZIP_DEFLATED) as zout:
        for fname, data in members.items():
            zout.writestr(fname, data)
    assert names  # (the valid members are kept unless replaced)
    tracemalloc.start()
    try:
        b = clear_or_valid(CalibrationBundle.load, p)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 64 << 20, f"{peak / 2**20:.0f} MiB allocated while reading"
    if b is not None:
        b.validate()


# ---------------------------------------------------------------------------------------------
# the manifest of a capture set


_paths = st.one_of(
    st.sampled_from(["scan/scan_550nm.tif", "white/w.tif", "../outside.tif", "/etc/passwd",
                     "scan/../scan/scan_550nm.tif", "scan/link.tif", "scan", "", " ",
                     "scan/missing.tif", "a\x00b"]),
    st.text(max_size=12), _json_scalars, st.lists(st.text(max_size=3), max_size=2),
)
_entry = st.fixed_dictionaries(
    {"file": _paths, "type": st.sampled_from(["scan", "white", "grid", "dark", "scene", "x", 3,
                                              None])},
    optional={"wavelength_nm": _json_scalars | st.sampled_from(["abc", "550", -1, 0, 550.0]),
              "name": _json_scalars},
)


@fuzz(150)
@given(entries=st.one_of(st.lists(_entry, max_size=4), _json_scalars),
       top=st.dictionaries(st.sampled_from(["nominal_layout", "brf_free_mask",
                                            "allow_files_outside", "schema_version"]),
                           _paths | st.booleans(), max_size=3))
def test_manifest_reader_on_random_entries(scratch, entries, top):
    """Random manifests: a capture set whose every file is a regular file inside the folder
    (unless the manifest opts in) with finite positive wavelengths, or an HSIError naming the
    manifest."""
    from hsi_torch.io.capture_set import read_capture_set

    root = scratch / "mset"
    if not root.is_dir():
        (root / "scan").mkdir(parents=True)
        (root / "white").mkdir()
        (root / "scan" / "scan_550nm.tif").write_bytes(b"x")
        (root / "white" / "w.tif").write_bytes(b"x")
        (scratch / "outside.tif").write_bytes(b"secret")
        (root / "scan" / "link.tif").symlink_to(scratch / "outside.tif")
    manifest = {"schema_version": 1, "captures": entries, **top}
    (root / "manifest.json").write_text(json.dumps(manifest, allow_nan=True))
    with no_hang():
        try:
            cs = read_capture_set(root)
        except HSIError as exc:
            assert "manifest.json" in str(exc) or "mset" in str(exc), str(exc)
            return
    outside_ok = manifest.get("allow_files_outside") is True
    files = [p for p, _ in cs.scan] + cs.white + cs.grid + cs.dark + list(cs.scenes.values())
    for f in files:
        assert f.is_file()
        if not outside_ok:
            assert f.resolve().is_relative_to(root.resolve()), f
    for _, wl in cs.scan:
        assert wl is None or (math.isfinite(wl) and wl > 0)


# ---------------------------------------------------------------------------------------------
# the run's Zarr store


@pytest.fixture(scope="module")
def zarr_store(scratch) -> Path:
    """A small valid dataset store with one complete frame."""
    pytest.importorskip("numcodecs")
    from hsi_torch.io.dataset import CubeDataset, write_frame

    store = scratch / "proto.zarr"
    with CubeDataset.open(store, ["/d/a.tif"], [430.0, 440.0], (3, 4)) as ds:
        write_frame(store, ds.index["/d/a.tif"], np.ones((2, 3, 4)), np.ones((3, 4), bool), {})
    return store


_codecs = st.one_of(
    st.none(), _json_scalars,
    st.fixed_dictionaries({"id": st.sampled_from(["pickle", "zstd", "blosc", "vlen-utf8",
                                                   "json2", "msgpack2", "gzip", "", "x"])},
                          optional={"level": _json_scalars, "protocol": _json_scalars,
                                    "evil": _json_scalars}),
)


@fuzz(60)
@given(array=st.sampled_from(["cube", "valid", "done", "metadata", "source", "wavelength", "y",
                              "x"]),
       field=st.sampled_from(["compressor", "filters", "dtype", "chunks", "shape"]),
       value=st.one_of(_codecs, st.lists(_codecs, max_size=2),
                       st.sampled_from(["|O", "<f4", "|b1", "<U4", "O"])),
       chunk=st.binary(max_size=64), consolidated=st.booleans())
def test_dataset_store_on_changed_array_metadata(scratch, zarr_store, array, field, value,
                                                 chunk, consolidated):
    """An array's compressor, filters, dtype, chunks or shape changed (in ``.zarray`` and/or
    ``.zmetadata``) and a chunk replaced: opening the store works or raises an HSIError; no
    codec outside the store's own is ever used, even by a numcodecs that would unpickle."""
    import shutil

    import numcodecs.pickles as pickles

    from hsi_torch.io.dataset import CubeDataset

    store = scratch / "fz.zarr"
    shutil.rmtree(store, ignore_errors=True)
    shutil.copytree(zarr_store, store)
    zpath = store / array / ".zarray"
    meta = json.loads(zpath.read_text())
    meta[field] = value
    zpath.write_text(json.dumps(meta, allow_nan=True))
    if consolidated:
        zm = json.loads((store / ".zmetadata").read_text())
        zm["metadata"][f"{array}/.zarray"] = meta
        (store / ".zmetadata").write_text(json.dumps(zm, allow_nan=True))
    first = sorted(p for p in (store / array).iterdir() if not p.name.startswith("."))[0]
    first.write_bytes(chunk)
    used: list[str] = []
    real_get = __import__("numcodecs").get_codec

    def spy(config):
        used.append(str(config.get("id")))
        return real_get(config)

    old = pickles.ALLOW_UNSAFE_PICKLE_DECODE if hasattr(pickles, "ALLOW_UNSAFE_PICKLE_DECODE") \
        else None
    pickles.ALLOW_UNSAFE_PICKLE_DECODE = True  # as numcodecs < 0.16.6 did
    import numcodecs

    numcodecs.get_codec = spy
    try:
        with no_hang():
            try:
                with CubeDataset.open(store, ["/d/a.tif"], [430.0, 440.0], (3, 4)) as ds:
                    ds.frame_record(0)
            except HSIError as exc:
                assert "fz.zarr" in str(exc), repr(exc)
    finally:
        numcodecs.get_codec = real_get
        pickles.ALLOW_UNSAFE_PICKLE_DECODE = old
    assert set(used) <= {"zstd", "vlen-utf8"}, used


# ---------------------------------------------------------------------------------------------
# the capture-set builder's sheet

_sheet_cells = st.one_of(
    st.sampled_from(["", "scan", "white", "grid", "dark", "scene", "flat", "550", "-5", "nan",
                     "inf", "1e400", "abc", "RGGB", "XYZW", "512", "[512, 512, 512]", "0.01",
                     "a.dng", "../a.dng", "/etc/passwd", "sub/b.png", " ", '"', "a,b"]),
    st.text(max_size=12),
)
_sheet_columns = st.lists(st.sampled_from(["file", "role", "wavelength_nm", "exposure_s",
                                           "black_level", "white_level", "cfa_pattern", "name",
                                           "wavelenght_nm", "", "File", "ROLE"]),
                          min_size=0, max_size=6)  # fmt: skip


@fuzz(150)
@given(columns=_sheet_columns,
       rows=st.lists(st.lists(_sheet_cells, max_size=7), max_size=5),
       raw=st.one_of(st.none(), st.binary(max_size=200)))
def test_sheet_reader_on_random_sheets(scratch, columns, rows, raw):
    """Random capture sheets (headers, cells, bytes): rows whose files exist, roles known and
    numbers finite and positive, or an HSIError naming the sheet — never another exception."""
    import csv
    import io

    from hsi_torch.io.capture_import import read_sheet

    folder = scratch / "sheet"
    if not folder.is_dir():
        (folder / "sub").mkdir(parents=True)
        (folder / "a.dng").write_bytes(b"x")
        (folder / "sub" / "b.png").write_bytes(b"x")
    sheet = folder / "captures.csv"
    if raw is not None:
        sheet.write_bytes(raw)
    else:
        buf = io.StringIO()
        csv.writer(buf).writerows([columns, *rows])
        sheet.write_text(buf.getvalue(), encoding="utf-8")
    with no_hang():
        try:
            got = read_sheet(sheet)
        except HSIError as exc:
            assert "captures.csv" in str(exc), str(exc)
            return
    for r in got:
        assert r.file.is_file(), r
        assert r.role in ("scan", "white", "grid", "dark", "scene"), r
        if r.wavelength_nm is not None:
            assert math.isfinite(r.wavelength_nm) and r.wavelength_nm > 0, r
        for k, v in r.settings.items():
            if isinstance(v, float):
                assert math.isfinite(v), (k, v)
