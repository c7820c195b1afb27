"""The on-disk cache of the per-bundle precomputation (:mod:`hsi_torch.recon.precompute_cache`):
a second reconstructor (as in a new process) loads it instead of factorising and gives the same
cube bit for bit; another bundle content or setting misses it; a foreign, altered or truncated
entry is refused and recomputed; the bundle and its folder are never written."""

from __future__ import annotations

import json
import os
import shutil
import stat
import warnings

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
    """Flip four bytes at a fraction of a file (its size and name unchanged)."""
    size = path.stat().st_size
    with open(path, "r+b") as f:
        f.seek(int(size * where))
        b = f.read(4)
        f.seek(-4, os.SEEK_CUR)
        f.write(bytes(x ^ 0x5A for x in b))


def biggest_member(entry):
    """The largest array file of an entry folder."""
    return max(entry.glob("*.npy"), key=lambda p: p.stat().st_size)


def read_index(entry) -> dict:
    return json.loads((entry / disk.INDEX).read_text())


def write_index(entry, index: dict) -> None:
    (entry / disk.INDEX).write_text(json.dumps(index))


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
        tamper(biggest_member(entry))
    elif damage == "truncated":
        member = biggest_member(entry)
        data = member.read_bytes()
        member.write_bytes(data[: len(data) // 2])
    elif damage == "foreign":  # another entry's folder under this name: its key differs
        other = tmp_path / "other.npz"
        make_bundle(seed=9).save(other)
        fresh_process()
        Reconstructor(other, beta=2.0, precompute_cache=str(cache))
        (foreign,) = [p for p in entries(cache) if p != entry]
        shutil.rmtree(entry)
        os.rename(foreign, entry)
    elif damage == "garbage":
        (entry / disk.INDEX).write_bytes(b"not json at all")
    elif damage == "header":  # the index edited (its MAC no longer matches)
        index = read_index(entry)
        index["beta"] = 3.0
        write_index(entry, index)
    else:  # an index that declares an object array (what a pickle would carry)
        index = read_index(entry)
        name = next(n for n, d in index["arrays"].items() if d["dtype"] == "|b1")
        index["arrays"][name]["dtype"] = "|O8"
        write_index(entry, index)
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

    monkeypatch.setattr(disk, "_write_new", refuse)
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
        os.utime(p / disk.INDEX, ns=(i * 10**9, i * 10**9))  # last used: its index's time
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
    real = disk.file_sha256
    monkeypatch.setattr(disk, "file_sha256", lambda p: calls.append(p) or real(p))
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
        (tv_entry,) = [p for p in entries(cache) if (p / "inverse.npy").exists()]
        data = bytearray((tv_entry / "inverse.npy").read_bytes())
        data[-5] ^= 0xFF  # a flipped byte in the packed inverse
        (tv_entry / "inverse.npy").write_bytes(bytes(data))
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


# ------------------------------------------------------------ trust, cross-checks, the command


def relabel(src, dest, key: str, secret: bytes | None = None) -> None:
    """Put the entry folder ``src`` at ``dest`` holding ``key`` (its MAC recomputed with
    ``secret`` when given: what only this user's software can do)."""
    if dest.exists():
        shutil.rmtree(dest)
    shutil.copytree(src, dest)
    index = read_index(dest)
    index["key"] = key
    if secret is not None:
        got = {n: np.load(dest / f"{n}.npy") for n in index["arrays"]}
        index["mac"] = disk._mac(secret, index, got)
    write_index(dest, index)


def test_another_bundles_entry_relabelled_is_not_used(bundle_file, tmp_path):
    """An entry made for a bundle with gains ×2, relabelled with the real bundle's key (what a
    CRC let through: the cube came out 2× too dark, no warning), fails its MAC: refused,
    recomputed, the cube right."""
    cache = tmp_path / "cache"
    capture = render_capture(make_bundle(), true_spectra()).float()
    bright = make_bundle()
    bright.gain = bright.gain * 2.0
    other = tmp_path / "bright.npz"
    bright.save(other)
    fresh_process()
    ref = Reconstructor(bundle_file, beta=2.0, precompute_cache=str(cache)).reconstruct_frame(
        capture)
    (entry,) = entries(cache)
    key = read_index(entry)["key"]
    fresh_process()
    Reconstructor(other, beta=2.0, precompute_cache=str(cache))
    (foreign,) = [p for p in entries(cache) if p != entry]
    relabel(foreign, entry, key)
    fresh_process()
    c = counts()
    with pytest.warns(disk.PrecomputeCacheWarning, match="refused.*MAC"):
        rec = Reconstructor(bundle_file, beta=2.0, precompute_cache=str(cache))
    assert counts()["loaded"] == c["loaded"]
    out = rec.reconstruct_frame(capture)
    assert torch.equal(torch.nan_to_num(out.cube, nan=-1.0), torch.nan_to_num(ref.cube, nan=-1.0))


def test_a_hash_memo_line_mapping_a_bundle_to_another_hash_is_ignored(bundle_file, tmp_path,
                                                                        monkeypatch):
    """``bundle_hashes.json`` naming this bundle's identity with another bundle's hash (and that
    bundle's valid line's MAC) would make it load the other bundle's entry: the line's MAC binds
    identity and hash, so it is ignored and the bundle hashed."""
    cache = tmp_path / "cache"
    other = tmp_path / "other.npz"
    make_bundle(seed=9).save(other)
    fresh_process()
    sha_other = disk.content_sha256(other, cache)
    sha = disk.file_sha256(bundle_file)
    memo = json.loads((cache / disk.HASH_MEMO).read_text())
    (line,) = memo.values()
    st = bundle_file.stat()
    ident = (str(bundle_file.resolve()), st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns,
             st.st_ctime_ns)
    memo[json.dumps(ident)] = dict(line)  # this bundle -> the other's hash, the other's MAC
    (cache / disk.HASH_MEMO).write_text(json.dumps(memo))
    calls = []
    real = disk.file_sha256
    monkeypatch.setattr(disk, "file_sha256", lambda p: calls.append(p) or real(p))
    fresh_process()
    assert disk.content_sha256(bundle_file, cache) == sha != sha_other and len(calls) == 1
    fresh_process()  # its own line, written by this software, is used
    assert disk.content_sha256(bundle_file, cache) == sha and len(calls) == 1


@pytest.mark.parametrize("what", ["gram_inv", "gram", "obs_mask", "pixel_index"])
def test_an_inconsistent_entry_is_refused_before_a_kernel_reads_it(bundle_file, tmp_path, what):
    """An entry with a valid MAC whose arrays disagree (a short ``gram_inv`` or ``gram``, a short
    ``obs_mask``, a ``pixel_index`` out of range): refused with a warning naming the array and
    recomputed; no crash (SIGSEGV in the compiled kernel), no IndexError on every run."""
    cache = tmp_path / "cache"
    capture = render_capture(make_bundle(), true_spectra()).float()
    fresh_process()
    ref = Reconstructor(bundle_file, beta=2.0, precompute_cache=str(cache)).reconstruct_frame(
        capture)
    (entry,) = entries(cache)
    index = read_index(entry)
    name = {"gram_inv": "problem.gram_inv", "gram": "problem.gram"}.get(what, what)
    a = np.load(entry / f"{name}.npy")
    a = a + len(a) * 7 if what == "pixel_index" else a[: len(a) // 2]
    np.save(entry / f"{name}.npy", a)
    index["arrays"][name]["shape"] = list(a.shape)
    got = {n: np.load(entry / f"{n}.npy") for n in index["arrays"]}
    index["mac"] = disk._mac(disk._secret(cache, create=False), index, got)
    write_index(entry, index)
    fresh_process()
    c = counts()
    with pytest.warns(disk.PrecomputeCacheWarning, match=f"refused.*{name}"):
        rec = Reconstructor(bundle_file, beta=2.0, precompute_cache=str(cache))
    assert counts()["factorisation"] == c["factorisation"] + 1
    out = rec.reconstruct_frame(capture)
    assert torch.equal(torch.nan_to_num(out.cube, nan=-1.0), torch.nan_to_num(ref.cube, nan=-1.0))


def test_an_entry_rewritten_in_place_after_loading_is_not_used_stale(bundle_file, tmp_path):
    """The entry's ``G⁻¹`` file rewritten in place (same inode) after a reconstructor loaded it:
    the next frame notices (its size and times changed), warns, and the entry (now failing its
    MAC) is recomputed: the cube is still right."""
    cache = tmp_path / "cache"
    capture = render_capture(make_bundle(), true_spectra()).float()
    fresh_process()
    ref = Reconstructor(bundle_file, beta=2.0, precompute_cache=str(cache)).reconstruct_frame(
        capture)
    (entry,) = entries(cache)
    fresh_process()
    rec = Reconstructor(bundle_file, beta=2.0, precompute_cache=str(cache))
    member = entry / "problem.gram_inv.npy"
    inode = member.stat().st_ino
    a = np.load(member)
    with open(member, "r+b") as f:  # in place: the same file, the mapping sees the new bytes
        f.seek(member.stat().st_size - a.nbytes)
        f.write((a * 0.5).tobytes())
    assert member.stat().st_ino == inode
    c = counts()
    with pytest.warns(disk.PrecomputeCacheWarning, match="written to after it was loaded"):
        out = rec.reconstruct_frame(capture)
    assert counts()["factorisation"] == c["factorisation"] + 1
    assert torch.equal(torch.nan_to_num(out.cube, nan=-1.0), torch.nan_to_num(ref.cube, nan=-1.0))


_TRUNCATE = """
import sys, warnings
from pathlib import Path
import torch
sys.path.insert(0, sys.argv[3])
from test_pipeline import make_bundle, render_capture, true_spectra
from hsi_torch.recon.pipeline import Reconstructor
bundle, cache = Path(sys.argv[1]), Path(sys.argv[2])
capture = render_capture(make_bundle(), true_spectra()).float()
rec = Reconstructor(bundle, beta=2.0, precompute_cache=str(cache))
(entry,) = [p for p in cache.iterdir() if p.suffix == ".hsicache"]
for m in entry.glob("*.npy"):
    m.write_bytes(m.read_bytes()[:128])  # truncated under the mapping (same inode)
with warnings.catch_warnings(record=True) as got:
    warnings.simplefilter("always")
    out = rec.reconstruct_frame(capture)
print(any("truncated" in str(w.message) for w in got))
torch.save(out.cube, cache.parent / "cube.pt")
"""


def test_an_entry_truncated_after_loading_is_survived(bundle_file, tmp_path):
    """Every file of a loaded entry truncated under the mapping: the next frame (in a child
    process, where a SIGBUS shows as a negative return code) warns and recomputes; the cube is
    right."""
    import subprocess
    import sys

    cache = tmp_path / "cache"
    capture = render_capture(make_bundle(), true_spectra()).float()
    fresh_process()
    ref = Reconstructor(bundle_file, beta=2.0, precompute_cache=str(cache)).reconstruct_frame(
        capture)
    tests = os.path.dirname(os.path.abspath(__file__))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    r = subprocess.run([sys.executable, "-c", _TRUNCATE, str(bundle_file), str(cache), tests],
                       capture_output=True, text=True, env=env, timeout=600)
    assert r.returncode == 0, (r.returncode, r.stderr[-3000:])
    assert r.stdout.split() == ["True"]
    out = torch.load(tmp_path / "cube.pt")
    assert torch.equal(torch.nan_to_num(out, nan=-1.0), torch.nan_to_num(ref.cube, nan=-1.0))


@pytest.mark.parametrize("value", ["inf", "nan", "1e400", "-1", "abc"])
def test_a_bad_cache_bound_is_a_warning_naming_the_variable(tmp_path, monkeypatch, value):
    monkeypatch.setenv(disk.MAX_GB_ENV, value)
    with pytest.warns(disk.PrecomputeCacheWarning, match=f"{disk.MAX_GB_ENV}=.*default"):
        assert disk._max_bytes() == int(disk.DEFAULT_MAX_GB * 2**30)
    path = disk.entry_path(tmp_path / "c", "b.npz", "ab" * 32)
    with pytest.warns(disk.PrecomputeCacheWarning, match=disk.MAX_GB_ENV):
        assert disk.save_entry(path, "ab" * 32, {"a": np.arange(3.0)})
    assert disk.load_entry(path, "ab" * 32) is not None


def share_with_a_group(folder) -> str:
    """Make ``folder`` writable by a group that is not the user's private one (root: any gid;
    else one of the user's other groups); world-writable where there is none. Returns the
    warning's words."""
    gids = [12345] if os.geteuid() == 0 else os.getgroups()
    gids = [g for g in gids if not disk._private_group(g)]
    if not gids:
        folder.chmod(0o777)
        return "writable by group and others"
    os.chown(folder, -1, gids[0])
    folder.chmod(0o775)
    return "writable by its group"


def test_a_cache_folder_others_may_write_is_ignored(bundle_file, tmp_path, monkeypatch):
    """A cache folder its group may write (a shared folder): its entry is ignored with a warning
    naming the folder's mode, nothing is written there, and the run uses the user cache folder."""
    monkeypatch.setenv(disk.CACHE_ENV, str(tmp_path / "user"))
    cache = tmp_path / "shared"
    fresh_process()
    Reconstructor(bundle_file, beta=2.0, precompute_cache=str(cache))
    (entry,) = entries(cache)
    words = share_with_a_group(cache)
    before = folder_state(cache)
    fresh_process()
    c = counts()
    with pytest.warns(disk.PrecomputeCacheWarning, match=words):
        Reconstructor(bundle_file, beta=2.0, precompute_cache=str(cache))
    assert counts()["loaded"] == c["loaded"]
    assert counts()["factorisation"] == c["factorisation"] + 1
    assert folder_state(cache) == before
    assert len(entries(tmp_path / "user" / "precompute")) == 1
    # asked directly, the entry of such a folder is refused too
    key = read_index(entry)["key"]
    with pytest.warns(disk.PrecomputeCacheWarning, match=words):
        assert disk.load_entry(entry, key) is None
    cache.chmod(0o700)
    assert disk.load_entry(entry, key) is not None


@pytest.mark.parametrize("plant", ["fifo", "device", "symlink", "huge"])
def test_fifos_devices_links_and_huge_indexes_are_misses(tmp_path, plant):
    """What is no regular file (a FIFO would hang a reader), a symbolic link, or an index over
    the bound, where an entry's file should be: refused at once, with a warning."""
    path = disk.entry_path(tmp_path / "c", "b.npz", "ab" * 32)
    assert disk.save_entry(path, "ab" * 32, {"a": np.arange(3.0)})
    target = path / ("a.npy" if plant in ("fifo", "device") else disk.INDEX)
    target.unlink()
    if plant == "fifo":
        os.mkfifo(target)
    elif plant == "device":
        target.symlink_to("/dev/zero")
    elif plant == "symlink":
        outside = tmp_path / "outside.json"
        outside.write_text("{}")
        target.symlink_to(outside)
    else:
        with open(target, "wb") as f:
            f.truncate(disk.MAX_HEADER_BYTES + 1)
    with pytest.warns(disk.PrecomputeCacheWarning, match="refused"):
        assert disk.load_entry(path, "ab" * 32) is None


def test_concurrent_writers_leave_one_valid_entry(tmp_path):
    import threading

    folder = tmp_path / "c"
    path = disk.entry_path(folder, "b.npz", "cd" * 32)
    arrays = {"a": np.arange(1 << 18, dtype=np.float64), "b": np.ones((7, 3), bool)}
    results = []
    threads = [threading.Thread(target=lambda: results.append(
        disk.save_entry(path, "cd" * 32, arrays))) for _ in range(4)]  # fmt: skip
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert all(results)
    assert [p.name for p in folder.iterdir() if not p.name.startswith(".")] == [path.name]
    got, _meta = disk.load_entry(path, "cd" * 32)
    assert np.array_equal(got["a"], arrays["a"]) and np.array_equal(got["b"], arrays["b"])


def test_a_large_entry_says_its_size(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(disk, "NOTE_BYTES", 1000)
    path = disk.entry_path(tmp_path / "c", "b.npz", "ef" * 32)
    disk.save_entry(path, "ef" * 32, {"a": np.arange(1000.0)})
    err = capsys.readouterr().err
    assert str(path) in err and "GiB" in err and "hsi-torch cache" in err


def test_the_cache_command_shows_and_clears_only_what_it_wrote(tmp_path, capsys):
    """``hsi-torch cache info`` names the folder, its entries, their size and the bound;
    ``clear`` removes the entries (name *and* index recognised), never a look-alike, never
    through a symbolic link, never outside the folder."""
    from hsi_torch.cli import main

    folder = tmp_path / "c"
    path = disk.entry_path(folder, "b.npz", "ab" * 32)
    assert disk.save_entry(path, "ab" * 32, {"a": np.arange(1000.0)})
    outside = tmp_path / "precious-abababababababababababab.hsicache"
    outside.mkdir()  # an entry look-alike outside the folder, linked in under an entry's name
    (outside / disk.INDEX).write_text(json.dumps({"format": 2, "key": "ab" * 32}))
    (outside / "thesis.npy").write_text("mine")
    (folder / "link-abababababababababababab.hsicache").symlink_to(outside)
    (folder / "notes-abababababababababababab.hsicache").write_text("not an entry")
    (folder / "notes.txt").write_text("mine too")
    fake = folder / "fake-abababababababababababab.hsicache"
    fake.mkdir()
    (fake / "x.npy").write_text("no index: not the cache's")
    array = folder / "array-abababababababababababab.hsicache"
    array.mkdir()
    (array / disk.INDEX).write_text("[2]")  # an index that is not an object: not the cache's
    assert main(["cache", "info", "--folder", str(folder)]) == 0
    out = capsys.readouterr().out
    assert str(folder) in out and path.name in out and "1 entr" in out and "GiB" in out
    assert main(["cache", "clear", "--folder", str(folder)]) == 0
    out = capsys.readouterr().out
    assert "removed 1 entr" in out
    assert not path.exists()
    assert sorted(p.name for p in folder.iterdir()) == sorted(
        [disk.KEY_FILE, "link-abababababababababababab.hsicache",
         "notes-abababababababababababab.hsicache", "notes.txt", fake.name, array.name])
    assert (outside / "thesis.npy").read_text() == "mine" and (fake / "x.npy").exists()


def test_a_tv_factor_entry_rewritten_after_loading_is_not_used_stale(bundle_file, tmp_path):
    """The TV prior's packed inverse, loaded from its entry, rewritten in place before the next
    TV frame: that frame warns, refuses the entry (MAC) and recomputes it; the cube is right."""
    from hsi_torch.recon.spatial import _compiled as spatial_compiled
    from hsi_torch.recon.spatial import problem as spatial_problem

    if not spatial_compiled.AVAILABLE:
        pytest.skip("numba not installed: the TV factor is not packed")
    cache = tmp_path / "cache"
    capture = render_capture(make_bundle(), true_spectra())
    fresh_process()
    spatial_problem._FACTORS.clear()
    ref = Reconstructor(bundle_file, beta=2.0, prior="tv", precompute_cache=str(cache))
    c1 = ref.reconstruct_frame(capture).cube  # writes both entries
    fresh_process()
    spatial_problem._FACTORS.clear()
    rec = Reconstructor(bundle_file, beta=2.0, prior="tv", precompute_cache=str(cache))
    rec.reconstruct_frame(capture)  # loads both
    (tv_entry,) = [p for p in entries(cache) if (p / "inverse.npy").exists()]
    member = tv_entry / "inverse.npy"
    a = np.load(member)
    with open(member, "r+b") as f:
        f.seek(member.stat().st_size - a.nbytes)
        f.write((a * 3.0).tobytes())
    with pytest.warns(disk.PrecomputeCacheWarning, match="inverse.npy was written to"):
        c2 = rec.reconstruct_frame(capture).cube
    assert torch.equal(torch.nan_to_num(c1, nan=-1.0), torch.nan_to_num(c2, nan=-1.0))


def test_the_users_private_group_may_write_the_folder(tmp_path, monkeypatch):
    """``umask 002`` systems make folders writable by the user's private group (named as the
    user, no other member): that is the user's own, as Debian's ssh allows; any other group
    is not."""
    folder = tmp_path / "c"
    folder.mkdir(mode=0o775)
    folder.chmod(0o775)
    monkeypatch.setattr(disk, "_private_group", lambda gid: True)
    assert disk.folder_problem(folder) is None
    monkeypatch.setattr(disk, "_private_group", lambda gid: False)
    assert "writable by its group" in disk.folder_problem(folder)
    folder.chmod(0o777)
    monkeypatch.setattr(disk, "_private_group", lambda gid: True)
    assert "writable by group and others" in disk.folder_problem(folder)


def _mapped_file(t: torch.Tensor) -> str | None:
    """The file whose mapping holds ``t``'s memory, from ``/proc/self/maps`` (``None``: none)."""
    addr = t.data_ptr()
    with open("/proc/self/maps") as f:
        for line in f:
            parts = line.split()
            lo, hi = (int(v, 16) for v in parts[0].split("-"))
            if lo <= addr < hi:
                return parts[5] if len(parts) > 5 else None
    return None


@pytest.mark.skipif(not os.path.exists("/proc/self/maps"), reason="needs /proc/self/maps")
def test_the_reconstructors_buffers_are_the_mapped_cache_entry(bundle_file, tmp_path):
    """A reconstructor loaded from the disk cache registers the entry's memory-mapped arrays as
    its buffers, not copies: the buffers are the sensing's tensors and their memory is a mapping
    of the entry's files; ``forward`` and the file method give the same cube; the object works
    in ``nn.Sequential``."""
    cache = tmp_path / "cache"
    capture = render_capture(make_bundle(), true_spectra()).float()
    fresh_process()
    Reconstructor(bundle_file, beta=2.0, precompute_cache=str(cache))  # writes the entry
    fresh_process()
    c0 = counts()
    rec = Reconstructor(bundle_file, beta=2.0, precompute_cache=str(cache), output="cube")
    assert counts()["loaded"] == c0["loaded"] + 1
    sens = rec.sensing
    assert rec.gram is sens.problem.gram and rec.model_transmittance is sens.model.transmittance
    (entry,) = entries(cache)
    for name in ("gram", "gram_inv", "model_transmittance"):
        where = _mapped_file(getattr(rec, name))
        assert where is not None and where.startswith(str(entry)), (name, where)
    assert rec.B is None and "B" not in rec.state_dict()  # no full-frame calibration kept
    res = rec.reconstruct_frame(capture)
    cube = torch.nn.Sequential(rec, torch.nn.Identity())(capture[None])[0]
    torch.testing.assert_close(cube, torch.where(res.valid, res.cube, 0.0), rtol=0, atol=0)
