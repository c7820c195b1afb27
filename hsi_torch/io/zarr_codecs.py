"""Which Zarr codecs a store may name before anything of it is decoded: the run's dataset store
(:data:`STORE_CODECS`, what :mod:`hsi_torch.io.dataset` writes) and a cube file's ``<stem>.zarr``
(:data:`SAFE_CODECS`, numcodecs' compressors and filters that only decode data). A codec such as
``pickle`` runs code when it decodes: a store that names one is refused
(:func:`check_zarr_codecs`)."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Any

from hsi_torch.errors import FileFormatError
from hsi_torch.io.bounded import read_json_bounded
from hsi_torch.io.safety import short_repr

__all__ = ["STORE_CODECS", "SAFE_CODECS", "check_zarr_codecs", "check_array_meta"]


def _s(value: Any, limit: int = 60) -> str:
    return short_repr(value, limit)


#: The codecs of the run's store (what this module writes) → the configuration keys they may
#: carry besides ``id``. Nothing else is ever decoded from a ``cubes.zarr``.
STORE_CODECS: dict[str, frozenset[str]] = {
    "zstd": frozenset({"level", "checksum"}),
    "vlen-utf8": frozenset(),
}
#: Codecs accepted in a cube file's Zarr store (``<stem>.zarr``, written by xarray/zarr):
#: numcodecs' compressors, checksums and filters that decode bytes without running code (no
#: ``pickle``; Zarr 3 names included). Configuration keys are not restricted.
SAFE_CODECS: frozenset[str] = frozenset({
    "zstd", "blosc", "lz4", "gzip", "zlib", "bz2", "lzma", "vlen-utf8", "vlen-bytes",
    "delta", "fixedscaleoffset", "quantize", "bitround", "shuffle", "packbits", "astype",
    "crc32", "crc32c", "adler32", "fletcher32", "jenkins_lookup3",
    "bytes", "transpose", "sharding_indexed",
})  # fmt: skip
#: dtypes of the run's store's arrays
_STORE_DTYPES = frozenset({"<f4", "<f8", "<i8", "|b1", "|O"})


def _codec_list(meta: dict[str, Any], key: str, store: Any, array: str) -> list[Any] | None:
    """``meta[key]`` (an array's ``filters`` or Zarr 3 ``codecs``): ``None`` or a list.

    Raises:
        FileFormatError: anything else (naming the store, the array and the key).
    """
    value = meta.get(key)
    if value is not None and not isinstance(value, list):
        raise FileFormatError(f"{store}: array {array!r}: {key} {_s(value)} is not a list")
    return value


def _check_codec(conf: Any, allowed: Any, array: str, role: str, store: Any) -> None:
    if not isinstance(conf, dict):
        raise FileFormatError(f"{store}: array {array!r}: its {role} is not a codec "
                              f"description ({_s(conf)})")  # fmt: skip
    cid = conf.get("id", conf.get("name"))
    names = sorted(allowed)
    if not isinstance(cid, str) or cid not in allowed:
        raise FileFormatError(
            f"{store}: array {array!r} names the {role} codec {_s(cid)}, which is not one "
            f"this store is read with ({', '.join(names)}); refusing to decode it (a crafted "
            "store can run code through a codec such as 'pickle')")
    if isinstance(allowed, dict):
        bad = [k for k, v in conf.items() if k != "id" and not (
            type(v) is int if k == "level" else type(v) is bool)]  # fmt: skip
        if bad and not [k for k in bad if k not in allowed[cid]]:
            raise FileFormatError(f"{store}: array {array!r}: {role} codec {cid!r} with "
                                  f"settings of the wrong type ({_s(bad)})")  # fmt: skip
        extra = sorted(str(k) for k in conf if k not in ("id", *allowed[cid]))
        if extra:
            raise FileFormatError(f"{store}: array {array!r}: {role} codec {cid!r} with "
                                  f"unexpected settings {_s(extra)}")  # fmt: skip


def check_array_meta(meta: Any, array: str, store: Any, allowed: Any = None) -> None:
    """Refuse array metadata (Zarr 2 ``.zarray`` or Zarr 3 ``zarr.json``) whose compressor,
    filters or codecs are not in ``allowed`` (default :data:`STORE_CODECS`, which also fixes
    the dtypes)."""
    strict = allowed is None
    allowed = STORE_CODECS if strict else allowed
    if not isinstance(meta, dict):
        raise FileFormatError(f"{store}: array {array!r}: metadata is not a JSON object")
    comp = meta.get("compressor")
    if comp is not None:
        _check_codec(comp, allowed, array, "compressor", store)
    filters = _codec_list(meta, "filters", store, array)
    for f in filters or []:
        _check_codec(f, allowed, array, "filter", store)
    codecs = _codec_list(meta, "codecs", store, array)  # Zarr 3
    if codecs is not None:
        for c in codecs:
            _check_codec(c, allowed, array, "codec", store)
            inner = c.get("configuration", {}) if isinstance(c, dict) else {}
            for key in ("codecs", "index_codecs"):  # sharding: codecs inside codecs
                for ci in (inner.get(key) or []) if isinstance(inner, dict) else []:
                    _check_codec(ci, allowed, array, "codec", store)
    if strict:
        dt = meta.get("dtype")
        if not isinstance(dt, str) or dt not in _STORE_DTYPES:
            raise FileFormatError(f"{store}: array {array!r} has dtype {_s(dt)}, not one of "
                                  f"this store's ({', '.join(sorted(_STORE_DTYPES))})")  # fmt: skip
        if dt == "|O" and [f.get("id") for f in filters or []] != ["vlen-utf8"]:
            raise FileFormatError(f"{store}: array {array!r}: an object array must have the "
                                  "vlen-utf8 filter")  # fmt: skip


def check_zarr_codecs(
    path: str | os.PathLike, allowed: Any = None, max_arrays: int = 10_000
) -> None:
    """Check every array of the Zarr store at ``path`` before anything is decoded: the arrays
    of its consolidated metadata (``.zmetadata``), and the ``.zarray`` / ``zarr.json`` files
    of its folder and of each folder one level below (where the arrays of a group are).

    Args:
        allowed: codec ids accepted (default :data:`STORE_CODECS`, the run's store; a cube
            file's store uses :data:`SAFE_CODECS`).
        max_arrays: bound on the sub-folders looked at.

    Raises:
        FileFormatError: a codec outside ``allowed`` (the message names the array and codec),
            or metadata that is not JSON.
    """
    root = Path(path)

    def load(p: Path) -> Any:  # a regular file of bounded size and depth (no FIFO, no bomb)
        return read_json_bounded(p, "store metadata")

    zmeta = root / ".zmetadata"
    if zmeta.is_file():
        md = load(zmeta)
        entries = md.get("metadata") if isinstance(md, dict) else None
        if not isinstance(entries, dict):
            raise FileFormatError(f"{root}: .zmetadata holds no 'metadata' object")
        for key, meta in entries.items():
            if str(key).endswith((".zarray", "zarr.json")):
                check_array_meta(meta, str(key).rsplit("/", 1)[0], root, allowed)
    folders = [root]
    with contextlib.suppress(OSError):
        folders += [Path(e.path) for e in os.scandir(root) if e.is_dir()][:max_arrays]
    for d in folders:
        for name in (".zarray", "zarr.json"):
            f = d / name
            if f.is_file():
                meta = load(f)
                if name == "zarr.json" and isinstance(meta, dict) and (
                        meta.get("node_type") != "array"):
                    continue
                check_array_meta(meta, d.name if d != root else "/", root, allowed)
