"""The on-disk cache of the per-bundle precomputation (:mod:`hsi_torch.recon.precompute_cache`):
a second reconstructor (as in a new process) loads it instead of factorising and gives the same
cube bit for bit; another bundle content or setting misses it; a foreign, altered or truncated
entry is refused and recomputed; the bundle and its folder are never written."""

from __future__ import annotations

import os
import stat
import warnings
import zlib

import numpy as np
import pytest
import torch
from test_pipeline import make_bundle, render_capture, true_spectra

from hsi_torch.recon import precompute_cache as disk
from hsi_torch.recon import sensing as sensing_mod
from hsi_torch.recon.pipeline import Reconstructor
from hsi_torch.recon.settings import ReconstructSettings


@pytest.fixture
def bundle_file(tmp_path):
    path = tmp_path / "bundle" / "calib.npz"
    path.parent.mkdir()
    make_bundle().save(path)
    return path


def fresh_process() -> None:
    """Forget what this process keeps (what a new process would not have)."""
    sensing_mod.clear_sensing_cache()
    disk._HASHES.clear()


def counts() -> dict[str, int]:
    return dict(sensing_mod.BUILD_COUNTS)


def entries(folder) -> list:
    return sorted(p for p in folder.iterdir() if p.suffix == ".hsicache")


def folder_state(folder) -> dict:
    return {p.name: (p.stat().st_size, p.stat().st_mtime_ns) for p in folder.iterdir()}


def test_second_reconstructor_loads_the_cache_bit_identical(bundle_file, tmp_path, device, dtype):
    cache = tmp_path / "cache"
    capture = render_capture(make_bundle(), true_spectra()).to(dtype)
    before_bundle = folder_state(bundle_file.parent)
    fresh_process()
    c0 = counts()
    rec1 = Reconstructor(bundle_file, beta=2.0, device=device, dtype=dtype,
                         precompute_cache=str(cache))
    c1 = counts()
    assert c1["factorisation"] - c0["factorisation"] == 1 and c1["loaded"] == c0["loaded"]
    assert len(entries(cache)) == 1
    r1 = rec1.reconstruct_frame(capture)

    fresh_process()
    rec2 = Reconstructor(bundle_file, beta=2.0, device=device, dtype=dtype,
                         precompute_cache=str(cache))
    c2 = counts()
    assert c2["factorisation"] == c1["factorisation"] and c2["sensing"] == c1["sensing"]
    assert c2["loaded"] - c1["loaded"] == 1
    assert rec2.sensing is not rec1.sensing
    assert rec2.sensing.device == rec1.sensing.device and rec2.sensing.dtype == dtype
    r2 = rec2.reconstruct_frame(capture)
    assert torch.equal(r1.valid, r2.valid)
    assert torch.equal(torch.nan_to_num(r1.cube, nan=-1.0), torch.nan_to_num(r2.cube, nan=-1.0))
    assert r1.stats["num_pivoted"] == r2.stats["num_pivoted"]
    # what the frame statistics take from the bundle came back too
    s1, s2 = rec1.sensing, rec2.sensing
    assert (s1.sensor_size, s1.reference_bbox, s1.exposure_s, s1.cfa_pattern) == (
        s2.sensor_size, s2.reference_bbox, s2.exposure_s, s2.cfa_pattern)
    assert torch.equal(s1.grid(), s2.grid()) and torch.equal(s1.homographies, s2.homographies)
    for name, v in vars(s1.problem).items():
        if isinstance(v, torch.Tensor):
            assert torch.equal(v, getattr(s2.problem, name)), name
    # the same process asking again gets the one it has
    assert Reconstructor(bundle_file, beta=2.0, device=device, dtype=dtype,
                         precompute_cache=str(cache)).sensing is rec2.sensing
    assert folder_state(bundle_file.parent) == before_bundle  # nothing written beside the bundle


def test_other_content_or_settings_miss(bundle_file, tmp_path):
    cache = tmp_path / "cache"
    fresh_process()
    Reconstructor(bundle_file, beta=2.0, precompute_cache=str(cache))
    c = counts()
    for kw in ({"beta": 3.0}, {"diff_order": 2}, {"dtype": torch.float64}):
        fresh_process()
        Reconstructor(bundle_file, **{"beta": 2.0, **kw}, precompute_cache=str(cache))
        assert counts()["factorisation"] == c["factorisation"] + 1, kw
        assert counts()["loaded"] == c["loaded"], kw
        c = counts()
    assert len(entries(cache)) == 4
    # settings that do not change the precomputation share the entry
    fresh_process()
    Reconstructor(bundle_file, beta=2.0, min_views=4, solver="admm", precompute_cache=str(cache))
    assert counts()["loaded"] == c["loaded"] + 1 and counts()["factorisation"] == c["factorisation"]
    # another content under the same name misses (and the entry of the new content is written)
    make_bundle(seed=5).save(bundle_file)
    fresh_process()
    c = counts()
    rec = Reconstructor(bundle_file, beta=2.0, precompute_cache=str(cache))
    assert counts()["factorisation"] == c["factorisation"] + 1
    assert len(entries(cache)) == 5
    g = make_bundle(seed=5).gain
    assert torch.allclose(rec.sensing.model.gain[:, 0].double(),
                          torch.as_tensor(g[0].reshape(-1)[rec.sensing.pixel_index.numpy()]))


def test_off_and_in_memory_bundles_write_nothing(bundle_file, tmp_path, monkeypatch):
    monkeypatch.setenv(disk.CACHE_ENV, str(tmp_path / "user"))
    fresh_process()
    Reconstructor(bundle_file, precompute_cache="off")
    Reconstructor(make_bundle(seed=3))  # an object: no file, no key
    assert not (tmp_path / "user").exists()
    Reconstructor(bundle_file)  # default "auto": the user cache folder
    assert len(entries(tmp_path / "user" / "precompute")) == 1
    assert ReconstructSettings().solve.precompute_cache == "auto"


def tamper(path, where: float = 0.5) -> None:
    """Flip four bytes at a fraction of the file (the header and its checksums unchanged)."""
    size = path.stat().st_size
    with open(path, "r+b") as f:
        f.seek(int(size * where))
        b = f.read(4)
        f.seek(-4, os.SEEK_CUR)
        f.write(bytes(x ^ 0x5A for x in b))


@pytest.mark.parametrize("damage",
                         ["tampered", "truncated", "foreign", "garbage", "header", "object"])
def test_a_bad_entry_is_refused_and_recomputed(bundle_file, tmp_path, damage):
    cache = tmp_path / "cache"
    capture = render_capture(make_bundle(), true_spectra()).float()
    fresh_process()
    ref = Reconstructor(bundle_file, beta=2.0, precompute_cache=str(cache)).reconstruct_frame(
        capture)
    (entry,) = entries(cache)
    if damage == "tampered":
        tamper(entry)
    elif damage == "truncated":
        data = entry.read_bytes()
        entry.write_bytes(data[: len(data) // 2])
    elif damage == "foreign":  # another entry's file under this name: its key differs
        other = tmp_path / "other.npz"
        make_bundle(seed=9).save(other)
        fresh_process()
        Reconstructor(other, beta=2.0, precompute_cache=str(cache))
        (foreign,) = [p for p in entries(cache) if p != entry]
        os.replace(foreign, entry)
    elif damage == "garbage":
        entry.write_bytes(b"not a zip file at all")
    elif damage == "header":  # the header edited (its checksum no longer matches)
        tamper(entry, 0.001)
    else:  # a header that declares an object array (what a pickle would carry), checksum right
        data = entry.read_bytes()
        n = len(disk.MAGIC)
        length = int.from_bytes(data[n:n + 8], "little")
        text = data[n + 12:n + 12 + length].replace(b'"|b1"', b'"|O8"', 1)
        entry.write_bytes(data[:n + 8] + zlib.crc32(text).to_bytes(4, "little") + text
                          + data[n + 12 + length:])
    fresh_process()
    c = counts()
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        rec = Reconstructor(bundle_file, beta=2.0, precompute_cache=str(cache))
    msgs = [str(w.message) for w in got if issubclass(w.category, disk.PrecomputeCacheWarning)]
    assert any("refused" in m and str(entry) in m for m in msgs), msgs
    assert counts()["factorisation"] == c["factorisation"] + 1 and counts()["loaded"] == c["loaded"]
    out = rec.reconstruct_frame(capture)
    assert torch.equal(torch.nan_to_num(out.cube, nan=-1.0), torch.nan_to_num(ref.cube, nan=-1.0))
    # the recomputed entry replaced the bad one and is used by the next process
    fresh_process()
    c = counts()
    Reconstructor(bundle_file, beta=2.0, precompute_cache=str(cache))
    assert counts()["loaded"] == c["loaded"] + 1


def test_read_only_folder_falls_back_to_the_user_cache(bundle_file, tmp_path, monkeypatch):
    monkeypatch.setenv(disk.CACHE_ENV, str(tmp_path / "user"))
    folder = bundle_file.parent
    real = disk._writable_folder  # root may write anywhere: the bundle's folder is made read-only
    monkeypatch.setattr(disk, "_writable_folder",
                        lambda f: not str(f).startswith(str(folder.resolve())) and real(f))
    folder.chmod(stat.S_IRUSR | stat.S_IXUSR)
    try:
        fresh_process()
        with pytest.warns(disk.PrecomputeCacheWarning, match="not writable"):
            Reconstructor(bundle_file, precompute_cache="beside")
        assert sorted(p.name for p in folder.iterdir()) == ["calib.npz"]
        assert len(entries(tmp_path / "user" / "precompute")) == 1
    finally:
        folder.chmod(stat.S_IRWXU)


def test_a_failed_write_is_a_warning(bundle_file, tmp_path, monkeypatch):
    def refuse(*args, **kwargs):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(disk, "atomic_write", refuse)
    fresh_process()
    with pytest.warns(disk.PrecomputeCacheWarning, match="could not write"):
        rec = Reconstructor(bundle_file, precompute_cache=str(tmp_path / "c"))
    out = rec.reconstruct_frame(render_capture(make_bundle(), true_spectra()).float())
    assert bool(out.valid.any())


def test_cache_folder_policies(bundle_file, tmp_path, monkeypatch):
    monkeypatch.setenv(disk.CACHE_ENV, str(tmp_path / "user"))
    user = tmp_path / "user" / "precompute"
    assert disk.cache_folder("auto", bundle_file) == (user, None)
    assert disk.cache_folder("off", bundle_file) == (None, None)
    assert disk.cache_folder("auto", None) == (None, None)
    assert disk.cache_folder("beside", bundle_file) == (
        bundle_file.parent.resolve() / ".hsi_torch_cache", None)
    assert disk.cache_folder(str(tmp_path / "mine"), bundle_file) == (tmp_path / "mine", None)
    blocker = tmp_path / "file"
    blocker.write_text("x")  # a folder cannot be made below a file
    folder, note = disk.cache_folder(str(blocker / "sub"), bundle_file)
    assert folder == user and "not writable" in note
    monkeypatch.delenv(disk.CACHE_ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert disk.user_cache_dir() == tmp_path / "xdg" / "hsi_torch" / "precompute"


def test_beside_keeps_the_entry_next_to_the_bundle(bundle_file):
    fresh_process()
    Reconstructor(bundle_file, precompute_cache="beside")
    folder = bundle_file.parent / ".hsi_torch_cache"
    (entry,) = entries(folder)
    assert entry.name.startswith("calib-")
    fresh_process()
    c = counts()
    Reconstructor(bundle_file, precompute_cache="beside")
    assert counts()["loaded"] == c["loaded"] + 1


def test_entries_are_bounded_least_recently_used_first(tmp_path, monkeypatch):
    folder = tmp_path / "c"
    arrays = {"a": np.arange(300_000, dtype=np.float64)}  # 2.4 MB an entry
    monkeypatch.setenv(disk.MAX_GB_ENV, str(8e6 / 2**30))
    paths = [disk.entry_path(folder, f"b{i}.npz", f"{i:064x}") for i in range(3)]
    for i, p in enumerate(paths):
        assert disk.save_entry(p, f"{i:064x}", arrays)
        os.utime(p, ns=(i * 10**9, i * 10**9))
    assert len(entries(folder)) == 3
    assert disk.load_entry(paths[0], f"{0:064x}") is not None  # used: now the newest
    monkeypatch.setenv(disk.MAX_GB_ENV, str(5.5e6 / 2**30))
    disk.save_entry(paths[1], f"{1:064x}", arrays)  # rewritten: the least recently used goes
    assert sorted(entries(folder)) == sorted([paths[0], paths[1]])
    got, meta = disk.load_entry(paths[0], f"{0:064x}")
    assert np.array_equal(got["a"], arrays["a"]) and list(meta["arrays"]) == ["a"]
    # memory-mapped, aligned as a fresh allocation (the kernels that read it take the same paths)
    assert isinstance(got["a"], np.memmap) and got["a"].ctypes.data % disk.ALIGN == 0
    with pytest.raises(TypeError, match="numbers only"):  # never written
        disk.save_entry(paths[2], "k", {"o": np.array([object()], dtype=object)})


def test_the_bundle_hash_is_remembered_by_file_identity(bundle_file, tmp_path, monkeypatch):
    calls = []
    real = disk._hash_file
    monkeypatch.setattr(disk, "_hash_file", lambda p: calls.append(p) or real(p))
    memo = tmp_path / "memo"
    fresh_process()
    sha = disk.content_sha256(bundle_file, memo)
    fresh_process()  # a later process: the memo file answers, the bundle is not read
    assert disk.content_sha256(bundle_file, memo) == sha and len(calls) == 1
    assert (memo / disk.HASH_MEMO).is_file()
    make_bundle(seed=7).save(bundle_file)  # rewritten: hashed again, another answer
    fresh_process()
    assert disk.content_sha256(bundle_file, memo) != sha and len(calls) == 2
    (memo / disk.HASH_MEMO).write_text("{not json")  # a damaged memo is ignored
    fresh_process()
    assert disk.content_sha256(bundle_file, memo) == real(bundle_file) and len(calls) == 3


def test_the_tv_factor_is_cached_beside_the_sensing(bundle_file, tmp_path):
    """The TV prior's packed ``(G + ρI)⁻¹`` goes into its own entry on the first TV frame; a new
    process loads it (no factorisation) and gives the same cube bit for bit; a damaged entry is
    refused with a warning and recomputed."""
    from hsi_torch.recon.spatial import _compiled as spatial_compiled
    from hsi_torch.recon.spatial import problem as spatial_problem

    if not spatial_compiled.AVAILABLE:
        pytest.skip("numba not installed: the TV factor is not packed")
    cache = tmp_path / "cache"
    capture = render_capture(make_bundle(), true_spectra())
    packs = []
    real_pack = spatial_compiled.pack_inverse_rows

    def counting_pack(*a, **k):
        packs.append(1)
        return real_pack(*a, **k)

    def run() -> torch.Tensor:
        fresh_process()
        spatial_problem._FACTORS.clear()
        rec = Reconstructor(bundle_file, beta=2.0, prior="tv", precompute_cache=str(cache))
        return rec.reconstruct_frame(capture).cube

    mp = pytest.MonkeyPatch()
    mp.setattr(spatial_compiled, "pack_inverse_rows", counting_pack)
    try:
        c1 = run()
        assert len(packs) == 1 and len(entries(cache)) == 2  # the sensing's and the TV factor's
        sp = next(iter(spatial_problem._FACTORS.values()))
        assert sp.factor._dense is None  # the compiled path never forms the dense inverse
        c2 = run()
        assert len(packs) == 1  # loaded, not recomputed
        assert torch.equal(torch.nan_to_num(c1, nan=-1.0), torch.nan_to_num(c2, nan=-1.0))
        tv_entry = max(entries(cache), key=lambda p: p.stat().st_mtime_ns)
        data = bytearray(tv_entry.read_bytes())
        data[-5] ^= 0xFF  # a flipped byte in the packed inverse
        tv_entry.write_bytes(bytes(data))
        with pytest.warns(disk.PrecomputeCacheWarning):
            c3 = run()
        assert len(packs) == 2
        assert torch.equal(torch.nan_to_num(c1, nan=-1.0), torch.nan_to_num(c3, nan=-1.0))
    finally:
        mp.undo()


def test_a_cached_sensing_keeps_the_bundles_stray_light_and_defect_corrections(tmp_path):
    """The cache kept only some fields of the bundle's radiometry: a second run (loading the
    entry) lost the veil subtraction (``stray_light: subtract``) and the defect mask the first
    run applied — the same command gave another cube, in silence. Every field now comes back."""
    path = tmp_path / "calib.npz"
    b = make_bundle(stray_light="subtract", white_level_dn=16383.0,
                    camera={"make": "Lab", "model": "Cam 1", "white_level": 16383.0})
    H, W = b.sensor_size
    b.extras = {"unreached_index": np.array([W * (H - 1) + W - 1, W * H - 2], np.int64),
                "defect_pixels": np.array([W * 5 + 7], np.int64)}
    b.save(path)
    cache = tmp_path / "cache"
    capture = render_capture(make_bundle(), true_spectra()) + 40.0  # a veil of 40 DN
    fresh_process()
    rec1 = Reconstructor(path, beta=2.0, precompute_cache=str(cache))
    r1 = rec1.reconstruct_frame(capture)
    fresh_process()
    rec2 = Reconstructor(path, beta=2.0, precompute_cache=str(cache))
    assert counts()["loaded"] >= 1 and rec2.sensing is not rec1.sensing
    a, c = rec1.sensing.radiometry, rec2.sensing.radiometry
    for name in vars(a):
        va, vc = getattr(a, name), getattr(c, name)
        if isinstance(va, np.ndarray):
            np.testing.assert_array_equal(va, vc, err_msg=name)
        else:
            assert va == vc, name
    assert c.veil_index is not None and c.defect_index is not None
    r2 = rec2.reconstruct_frame(capture)
    assert r2.stats.get("stray_light_veil_dn") == r1.stats.get("stray_light_veil_dn") is not None
    assert torch.equal(torch.nan_to_num(r1.cube, nan=-1.0), torch.nan_to_num(r2.cube, nan=-1.0))


def _rss_file_mib() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("RssFile:"):
                return int(line.split()[1]) / 1024
    raise AssertionError("no RssFile in /proc/self/status")


linux_only = pytest.mark.skipif(not os.path.exists("/proc/self/smaps"),
                                reason="release_pages reads /proc/self/smaps (Linux)")


@linux_only
def test_release_pages_drops_a_mapped_entrys_pages_and_loses_nothing(tmp_path):
    """An entry's mapped array read once is resident; released, the process's file-mapped set
    shrinks by about its size, and read again it gives the same bytes (from the file)."""
    rng = np.random.default_rng(0)
    data = rng.random(16 << 20, dtype=np.float32)  # 64 MiB
    path = tmp_path / "e.hsicache"
    disk.save_entry(path, "key", {"g": data, "small": np.arange(3)}, {})
    got = disk.load_entry(path, "key")
    assert got is not None
    g = torch.from_numpy(got[0]["g"])  # as the sensing holds it
    assert float(g.sum()) == pytest.approx(float(data.sum(dtype=np.float64)), rel=1e-4)
    before = _rss_file_mib()
    released = disk.release_pages(g)
    after = _rss_file_mib()
    assert released >= data.nbytes - 2 * os.sysconf("SC_PAGE_SIZE")
    assert before - after > 48  # MiB: most of the 64 MiB left the resident set
    np.testing.assert_array_equal(got[0]["g"], data)  # read back from the file, unchanged
    assert _rss_file_mib() - after > 48


@linux_only
def test_release_pages_leaves_written_mappings_and_private_memory_alone(tmp_path):
    """Where dropping pages would lose data it does nothing: a mapping with a copy-on-write page
    (the array was written to), and private memory (numpy, torch), whose dropped pages would
    read back as zeros."""
    path = tmp_path / "e.hsicache"
    disk.save_entry(path, "key", {"g": np.ones(1 << 20, np.float32)}, {})
    got = disk.load_entry(path, "key")
    g = got[0]["g"]
    g[1 << 19] = 7.0  # a copy-on-write page: the file is not changed, this process's copy is
    assert disk.release_pages(g) == 0
    assert g[1 << 19] == 7.0 and float(g.sum()) == (1 << 20) + 6.0
    g2 = disk.load_entry(path, "key")[0]["g"]  # a fresh mapping, written in its first bytes only
    g2[0] = 5.0
    released = disk.release_pages(g2)  # the whole pages after the written one may go
    assert g2[0] == 5.0 and float(g2.sum()) == (1 << 20) + 4.0
    assert released <= g2.nbytes - os.sysconf("SC_PAGE_SIZE")
    private = np.random.default_rng(1).random(1 << 21)
    tensor = torch.rand(1 << 21, dtype=torch.float64)
    keep_np, keep_t = private.copy(), tensor.clone()
    assert disk.release_pages(private, tensor, None) == 0
    np.testing.assert_array_equal(private, keep_np)
    assert torch.equal(tensor, keep_t)


def test_a_tv_frame_releases_the_mapped_factors_between_its_stages(bundle_file, tmp_path,
                                                                     monkeypatch):
    """A TV frame from a cached bundle hands the per-pixel ``G⁻¹`` and ``G`` and the TV factor to
    :func:`release_pages` once each stage is done with them, and the cube is the same bit for bit
    as without releasing (the pages come back from the file)."""
    from hsi_torch.recon.spatial import _compiled as spatial_compiled
    from hsi_torch.recon.spatial import problem as spatial_problem

    if not spatial_compiled.AVAILABLE:
        pytest.skip("numba not installed: the compiled TV path is not used")
    cache = tmp_path / "cache"
    capture = render_capture(make_bundle(), true_spectra())
    real = disk.release_pages
    calls: list[int] = []

    def recording(*arrays):
        n = real(*arrays)
        calls.append(n)
        return n

    def run() -> torch.Tensor:
        fresh_process()
        spatial_problem._FACTORS.clear()
        rec = Reconstructor(bundle_file, beta=2.0, prior="tv", precompute_cache=str(cache))
        return rec.reconstruct_frame(capture).cube

    run()  # writes both entries
    kept = run()  # loads them: mapped
    monkeypatch.setattr(disk, "release_pages", recording)
    released = run()
    assert len(calls) == 3  # G⁻¹ before the spatial solve, G after its start, the TV factor
    if os.path.exists("/proc/self/smaps"):
        assert all(n > 0 for n in calls)  # all three were mapped from the entries
    assert torch.equal(torch.nan_to_num(kept, nan=-1.0), torch.nan_to_num(released, nan=-1.0))


_URING = """
import ctypes, mmap, sys
import numpy as np
from hsi_torch.recon import precompute_cache as disk
params = (ctypes.c_uint8 * 120)()
fd = ctypes.CDLL(None, use_errno=True).syscall(425, 256, params)  # io_uring_setup (x86-64)
if fd < 0:
    sys.exit(3)
ring = mmap.mmap(fd, 256 * 64, mmap.MAP_SHARED, mmap.PROT_READ | mmap.PROT_WRITE,
                 offset=0x10000000)  # the submission entries: kernel pages, no file behind
a = np.frombuffer(ring, dtype=np.uint8)
a[:] = 7
print(disk.release_pages(a), int(a.sum()) == 7 * a.size)
"""


@linux_only
def test_release_pages_leaves_mappings_of_kernel_objects_alone(tmp_path):
    """A mapping with an inode that is no regular file (here an io_uring ring,
    ``anon_inode:[io_uring]``; a GPU driver's ``/dev`` mappings are alike) holds pages no file
    keeps: dropped, they read back as a bus error. They are left alone."""
    import platform
    import subprocess
    import sys

    if platform.machine() != "x86_64":
        pytest.skip("the io_uring_setup syscall number used is x86-64's")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    r = subprocess.run([sys.executable, "-c", _URING], capture_output=True, text=True, env=env,
                       timeout=120)
    if r.returncode == 3:
        pytest.skip("io_uring is not available here")
    assert r.returncode == 0, (r.returncode, r.stderr[-2000:])
    assert r.stdout.split() == ["0", "True"]
