"""Per-bundle precomputation for reconstruction: sensing matrices, static masks, factorisation.

Everything that depends only on the calibration bundle (and on ``beta``/``diff_order``) is done
once and reused by every frame that shares the bundle (:class:`BundleSensing`): the valid pixels'
flat indices, the factored sensing operator (:class:`~hsi_torch.forward_model.SensingModel`,
``A_p[3v + c, m] = gain[v, p] · B[v, m, p] · Δλ_m · phi[c, m]``: ``V·M`` numbers a pixel instead
of the dense ``3V·M``), the static observation mask, the sampling grid (``H_v⁻¹`` applied to the
reference sensor px in float64, so a frame is warped by *one* ``remap`` over the valid pixels
only) and the solver factorisation (:func:`hsi_torch.recon.nnls.prepare_nnls`).

:func:`precompute_sensing` keeps a small in-process cache (the bundle held weakly) and, for a
bundle given as a file, the disk cache (``precompute_cache``; ``docs/reconstruct.md``, *The
precomputation cache*); :data:`BUILD_COUNTS` counts builds and loads.

Convention:
    Observation index ``o = 3·v + c`` (``v = 0`` the reference view, ``c`` = R, G, B).
    Reference-frame pixel ``p = i·w + j`` (row ``i``, column ``j``). Homographies map view-``v``
    sensor px to reference sensor px (``H_0 = I``); the reference frame is the sensor crop
    ``reference_bbox``.
"""

from __future__ import annotations

import dataclasses
import os
import threading
import weakref
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from hsi_torch.devices import resolve_device, to_numpy
from hsi_torch.forward_model import OnDevice, SensingModel
from hsi_torch.io.bundle import CalibrationBundle, ReferenceFrame
from hsi_torch.io.radiometry import CameraIdentity
from hsi_torch.optics.geometry import view_sample_grid
from hsi_torch.profiling import release_freed_memory
from hsi_torch.recon import precompute_cache as disk
from hsi_torch.recon.checks import BundleRadiometry
from hsi_torch.recon.nnls import NNLSProblem, prepare_nnls
from hsi_torch.recon.nnls.problem import compiled_factorisation
from hsi_torch.spectral import band_widths

__all__ = [
    "BundleSensing",
    "precompute_sensing",
    "build_sensing",
    "load_bundle",
    "bundle_exposure",
    "clear_sensing_cache",
    "BUILD_COUNTS",
    "CACHE_LAYOUT_VERSION",
    "EXPOSURE_KEYS",
]

#: Number of times the expensive parts were built (``"sensing"``: A and masks,
#: ``"factorisation"``: :func:`prepare_nnls`) or loaded from the disk cache (``"loaded"``).
#: Tests use it to check that frames and processes reuse the precomputation.
BUILD_COUNTS: dict[str, int] = {"sensing": 0, "factorisation": 0, "loaded": 0}

#: Version of what :func:`precompute_sensing` stores in the disk cache (part of its key; the
#: code that computes it is part of the key by itself): bump it when the stored arrays change
#: meaning without a change of that code.
CACHE_LAYOUT_VERSION = 1

#: Keys looked up (in order) in ``bundle.settings`` for the exposure time (s) of the white
#: reference the response ``phi`` was calibrated from; nested ``{"response": {...}}`` is searched
#: too. A capture's own exposure is its metadata key ``exposure_s``.
EXPOSURE_KEYS = ("white_exposure_s", "white_reference_exposure_s", "exposure_s")

_CACHE_SIZE = 2
_CACHE: OrderedDict[tuple, BundleSensing] = OrderedDict()


def clear_sensing_cache() -> None:
    """Drop every cached :class:`BundleSensing` (frees the factorisations' memory)."""
    _CACHE.clear()


def load_bundle(bundle: CalibrationBundle | str | os.PathLike) -> CalibrationBundle:
    """Return ``bundle`` itself, or load it from a path (:meth:`CalibrationBundle.load`)."""
    if isinstance(bundle, CalibrationBundle):
        return bundle
    if isinstance(bundle, (str, os.PathLike)):
        return CalibrationBundle.load(Path(bundle))
    raise TypeError(f"bundle must be a CalibrationBundle or a path, got {type(bundle).__name__}")


def bundle_exposure(bundle: CalibrationBundle) -> float | None:
    """Exposure time (s) of the white reference the bundle's response was calibrated at, if known.

    Looks for :data:`EXPOSURE_KEYS` in ``bundle.settings`` and in ``bundle.settings["response"]``.
    """
    places: list[Any] = [bundle.settings]
    if isinstance(bundle.settings, dict) and isinstance(bundle.settings.get("response"), dict):
        places.append(bundle.settings["response"])
    for d in places:
        if not isinstance(d, dict):
            continue
        for k in EXPOSURE_KEYS:
            v = d.get(k)
            if isinstance(v, (int, float)) and not isinstance(v, bool) and v > 0:
                return float(v)
    return None


@dataclass
class BundleSensing(OnDevice, ReferenceFrame):
    """Per-bundle tensors used by every frame (see the module docstring).

    Attributes:
        wavelengths_nm: ``(M,)`` float64, nm (CPU).
        sensor_size: ``(H, W)`` of the captures the bundle belongs to.
        reference_bbox: ``(x0, y0, w, h)``; frame_size: ``(h, w)``.
        homographies: ``(V, 3, 3)`` float64, view-v sensor px → reference sensor px.
        valid: ``(h, w)`` bool, the bundle's valid region (pixels reconstructed).
        pixel_index: ``(P,)`` long, flat row-major indices of the valid pixels.
        model: the sensing operator of the ``P`` pixels (``dtype``, ``device``); dense
            matrices of a subset with ``model.dense(idx)``.
        obs_mask: ``(P, 3V)`` bool static observation mask.
        beta, diff_order: the regularisation the factorisation was made for.
        problem: :class:`~hsi_torch.recon.nnls.NNLSProblem` for ``A``, ``obs_mask``, ``beta``.
        exposure_s: white-reference exposure of the calibration (s) or ``None``.
        cfa_pattern: the bundle's CFA pattern (``settings["cfa_pattern"]``) or ``None``.
        radiometry: what the bundle records about the calibration's black level, exposure unit
            and camera, and the sensor pixels no view reaches
            (:class:`~hsi_torch.recon.checks.BundleRadiometry`), or ``None``.
        sample_grid: ``(1, V, P, 2)`` (``dtype``, ``device``) sensor position of valid pixel ``p``
            in view ``v`` as normalised ``(x, y)`` (``align_corners=True``; see
            :func:`~hsi_torch.optics.geometry.view_sample_grid`); ``None``: computed on first use.
        sample_inside: ``(V, P)`` bool or ``None``: samples of :attr:`sample_grid` that lie on
            the sensor. Only a grid moved for one frame has it
            (:func:`hsi_torch.recon.drift.corrected_sensing`: a drift correction); the frame's
            observations outside the sensor are then dropped. ``None``: all are used.
        staging_lock: guards the per-bundle work buffer of :meth:`staging` (frames of one bundle
            may be reconstructed from several threads).
        _drift_static: the drift check's per-bundle masks, crops and Jacobians, kept on first
            use (:func:`hsi_torch.recon.drift.estimate_drift`; shared with the copies
            ``dataclasses.replace`` makes, rebuilt when their masks or homographies differ).
        spatial_workspace: the spatial prior's frame-sized ADMM buffers (numpy, CPU), kept
            between the frames solved without a warm start
            (:func:`~hsi_torch.recon.spatial.admm.solve_spatial`'s ``workspace``; a sequence's
            :class:`~hsi_torch.recon.frame.WarmStart` has its own): a frame then writes into
            memory the previous one used instead of asking the system for ~340 MB of fresh
            pages at the full-size frame (zero-filled, and as transparent huge pages often
            compacted first). Shared with the copies ``dataclasses.replace`` makes; emptied by
            pickling.
    """

    _ON = "model"  # (no annotation: a class attribute, not a field)
    wavelengths_nm: Tensor
    sensor_size: tuple[int, int]
    reference_bbox: tuple[int, int, int, int]
    homographies: Tensor
    valid: Tensor
    pixel_index: Tensor
    model: SensingModel
    obs_mask: Tensor
    beta: float
    diff_order: int
    problem: NNLSProblem
    exposure_s: float | None = None
    cfa_pattern: str | None = None
    radiometry: BundleRadiometry | None = None
    _problems: dict[tuple[float, int], NNLSProblem] = field(default_factory=dict, repr=False)
    sample_grid: Tensor | None = field(default=None, repr=False)
    sample_inside: Tensor | None = field(default=None, repr=False)
    staging_lock: threading.Lock = field(default_factory=threading.Lock, repr=False)
    _staging: list[Tensor] = field(default_factory=list, repr=False)
    #: the disk-cache entry this sensing belongs to: ``(folder, bundle path, key)`` (``None``:
    #: not cached on disk); further per-bundle factors (the TV prior's) are cached beside it
    disk_entry: tuple[Path, Path, str] | None = field(default=None, repr=False)
    _drift_static: dict[str, Any] = field(default_factory=dict, repr=False)
    spatial_workspace: dict[str, Any] = field(default_factory=dict, repr=False)

    def __getstate__(self) -> dict[str, Any]:  # picklable / deep-copyable: no lock, no buffer
        state = self.__dict__.copy()
        state["staging_lock"] = None
        state["_staging"] = []
        state["_drift_static"] = {}
        state["spatial_workspace"] = {}
        state.pop("_bundle_ref", None)
        state.pop("_disk_stamp", None)  # a copy holds its own memory, not the entry's files
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self.staging_lock = threading.Lock()

    def staging(self, shape: Sequence[int], dtype: torch.dtype, device: torch.device) -> Tensor:
        """A work buffer of ``shape`` kept between frames (the frame's stacked image and
        saturation mask); reallocated when shape, dtype or device change. Hold
        :attr:`staging_lock` while using it."""
        shape = tuple(int(v) for v in shape)
        buf = self._staging[0] if self._staging else None
        if buf is None or buf.shape != shape or buf.dtype != dtype or buf.device != device:
            self._staging[:] = []  # free the old one first
            buf = torch.empty(shape, dtype=dtype, device=device)
            self._staging.append(buf)
        return buf

    def grid(self) -> Tensor:
        """:attr:`sample_grid`, computed (and kept) on first use."""
        if self.sample_grid is None:
            self.sample_grid = view_sample_grid(
                self.homographies, self.reference_bbox, self.sensor_size, self.pixel_index,
                dtype=self.dtype,
            )  # fmt: skip
        return self.sample_grid

    @property
    def num_views(self) -> int:
        return int(self.homographies.shape[0])

    @property
    def num_bands(self) -> int:
        return self.model.num_bands

    @property
    def num_pixels(self) -> int:
        return int(self.pixel_index.shape[0])


    def with_regularisation(self, beta: float, diff_order: int = 1) -> BundleSensing:
        """A view of the same sensing with another ``(beta, diff_order)``: ``A``/masks are shared,
        only the factorisation is (re)computed — and cached on this object."""
        key = (float(beta), int(diff_order))
        if key == (self.beta, self.diff_order):
            return self
        if key not in self._problems:
            self._problems[key] = _factorise(self.model, self.obs_mask, *key, None)
        return dataclasses.replace(
            self, beta=key[0], diff_order=key[1], problem=self._problems[key],
            sample_grid=self.grid(),
        )  # fmt: skip

    def check_capture_size(self, shape: Sequence[int], source: str = "capture") -> None:
        """Raise ``ValueError`` naming ``source`` when ``shape[-2:]`` is not the sensor size."""
        hw = tuple(int(s) for s in shape[-2:])
        if hw != self.sensor_size:
            raise ValueError(
                f"{source}: sensor size {hw[0]}x{hw[1]} (HxW) does not match the calibration "
                f"bundle's {self.sensor_size[0]}x{self.sensor_size[1]}"
            )

    def memory_bytes(self) -> int:
        """Bytes held by the sensing model, the masks, the factorisation and the sampling grid."""
        ts = [self.obs_mask, self.pixel_index]
        if self.sample_grid is not None:
            ts.append(self.sample_grid)
        return int(sum(t.numel() * t.element_size() for t in ts) + self.model.memory_bytes()
                   + self.problem.memory_bytes())


def _factorise(
    model: SensingModel, mask: Tensor, beta: float, diff_order: int, chunk_size: int | None
) -> NNLSProblem:
    BUILD_COUNTS["factorisation"] += 1
    return prepare_nnls(model, mask=mask, beta=beta, diff_order=diff_order,
                        chunk_size=chunk_size)


def precompute_sensing(
    bundle: CalibrationBundle | str | os.PathLike,
    *,
    beta: float = 0.0,
    diff_order: int = 1,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
    chunk_size: int | None = None,
    cache: bool = True,
    disk_cache: str | os.PathLike | None = "auto",
) -> BundleSensing:
    """Build (or fetch from the caches) the per-bundle sensing and factorisation.

    Args:
        bundle: a :class:`CalibrationBundle` or the path of one.
        beta: smoothness weight ``β ≥ 0`` on ``‖D s‖²`` (DN² scale).
        diff_order: order of ``D`` (0, 1, 2).
        device, dtype: where and in which float type ``A`` and the factorisation live.
        chunk_size: pixels per chunk of the factorisation (``None``: the solver's default).
        cache: reuse/insert in the module cache (keyed by the bundle object's identity, or by
            the file's SHA-256 for a path with a disk cache).
        disk_cache: for a bundle given as a path: ``"auto"`` (the user cache folder),
            ``"beside"`` (a ``.hsi_torch_cache`` folder beside the bundle), ``"off"`` or a folder
            (:func:`hsi_torch.recon.precompute_cache.cache_folder`). An in-memory bundle is
            never cached on disk.

    Returns:
        :class:`BundleSensing` with ``P = bundle.valid.sum()`` pixels.
    """
    if dtype not in (torch.float32, torch.float64):
        raise TypeError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
    dev = resolve_device(device)
    beta, diff_order = float(beta), int(diff_order)
    path = Path(bundle) if isinstance(bundle, (str, os.PathLike)) else None
    folder, note = disk.cache_folder(disk_cache, path)
    if note:
        disk._warn(note)
    entry = key = mem_key = None
    if folder is not None and path is not None and path.is_file():
        sha = disk.content_sha256(path, folder)
        # which factorisation made it: the compiled CPU pass and the torch kernels may flag a
        # numerically singular pixel differently
        how = "compiled" if compiled_factorisation(dev) else "torch"
        key = disk.entry_key({"bundle_sha256": sha, "beta": beta, "diff_order": diff_order,
                              "dtype": str(dtype), "device": dev.type, "factorisation": how},
                             CACHE_LAYOUT_VERSION)
        mem_key = ("file", key, str(dev))
        if cache and mem_key in _CACHE:
            _CACHE.move_to_end(mem_key)
            return _CACHE[mem_key]
        entry = disk.entry_path(folder, path, key)
        got = disk.load_entry(entry, key)
        sens = None if got is None else _from_cache(*got, dev, entry)
        if sens is not None:
            sens.disk_entry = (Path(folder), path, key)
            sens._disk_stamp = disk.loaded_stamp(got[0])  # type: ignore[attr-defined]
            BUILD_COUNTS["loaded"] += 1
            _remember(mem_key, sens, cache)
            return sens
    b = load_bundle(bundle)
    id_key = (id(b), str(dev), dtype, beta, diff_order)
    if cache and id_key in _CACHE and _CACHE[id_key]._bundle_ref() is b:  # type: ignore[attr-defined]
        _CACHE.move_to_end(id_key)
        return _CACHE[id_key]
    BUILD_COUNTS["sensing"] += 1
    # identity check for the cache, without keeping the bundle's full-frame arrays alive: a
    # bundle loaded here from a path is freed before the factorisation's memory is taken
    ref = weakref.ref(b)
    exposure = bundle_exposure(b)
    cfa = b.settings.get("cfa_pattern") if isinstance(b.settings, dict) else None
    extra = dict(exposure_s=exposure, cfa_pattern=cfa if isinstance(cfa, str) else None,
                 radiometry=BundleRadiometry.from_bundle(b, exposure))  # fmt: skip
    hand_over = [b]
    del b
    sens = build_sensing(hand_over, beta=beta, diff_order=diff_order, device=dev, dtype=dtype,
                         chunk_size=chunk_size, **extra)  # fmt: skip
    sens._bundle_ref = ref  # type: ignore[attr-defined]
    release_freed_memory()  # the factorisation's chunk temporaries (≈ 0.3 GiB at full size)
    if entry is not None and key is not None:
        stored = _to_cache(sens)
        if stored is not None:
            disk.save_entry(entry, key, *stored)
        sens.disk_entry = (Path(folder), path, key)
        _remember(mem_key, sens, cache)
    _remember(id_key, sens, cache)
    return sens


def build_sensing(
    source: list[Any],
    *,
    beta: float,
    diff_order: int,
    device: torch.device,
    dtype: torch.dtype,
    chunk_size: int | None = None,
    **extra: Any,
) -> BundleSensing:
    """The :class:`BundleSensing` of a bundle's arrays: sensing model, static mask,
    factorisation and sampling grid (the one build, for :func:`precompute_sensing` and for
    :meth:`hsi_torch.recon.pipeline.HSIReconstructor.load_state_dict`).

    Args:
        source: a one-item list holding a :class:`CalibrationBundle` or an object with its
            array attributes (``wavelengths_nm``, ``B (V, M, h, w)``, ``gain (V, h, w)``,
            ``phi (3, M)`` (float64 best), ``view_mask (V, h, w)``, ``valid (h, w)``,
            ``view_homographies (V, 3, 3)``, ``sensor_size``, ``reference_bbox``); emptied once
            the arrays are read, so that a bundle nothing else holds is freed before the
            factorisation takes its memory.
        beta, diff_order, chunk_size: of the factorisation; device, dtype: of the tensors.
        extra: further :class:`BundleSensing` fields (``exposure_s``, ``cfa_pattern``,
            ``radiometry``).
    """
    b = source.pop()
    valid = torch.as_tensor(b.valid, device=device)
    pix = valid.reshape(-1).nonzero().squeeze(1)
    wl = torch.as_tensor(b.wavelengths_nm).to("cpu", torch.float64)
    model = SensingModel.from_factors(
        torch.as_tensor(b.B), torch.as_tensor(b.gain), torch.as_tensor(b.phi), band_widths(wl),
        pixel_index=pix.cpu(), device=device, dtype=dtype,
    )  # fmt: skip
    V = int(b.view_homographies.shape[0])
    vm = torch.as_tensor(b.view_mask, device=device).reshape(V, -1)
    obs = vm[:, pix.to(vm.device)].T.repeat_interleave(3, dim=1)
    x0, y0, w, h = (int(v) for v in b.reference_bbox)
    fields = dict(
        wavelengths_nm=wl, sensor_size=(int(b.sensor_size[0]), int(b.sensor_size[1])),
        reference_bbox=(x0, y0, w, h),
        homographies=torch.as_tensor(b.view_homographies).to(device, torch.float64),
    )  # fmt: skip
    del b
    problem = _factorise(model, obs, beta, diff_order, chunk_size)
    sens = BundleSensing(valid=valid, pixel_index=pix, model=model, obs_mask=obs, beta=beta,
                         diff_order=diff_order, problem=problem, **fields, **extra)  # fmt: skip
    sens._problems[(beta, diff_order)] = problem
    sens.grid()  # the frames' sampling positions, once per bundle
    return sens


def _remember(key: tuple | None, sens: BundleSensing, cache: bool) -> None:
    if not cache or key is None:
        return
    _CACHE[key] = sens
    _CACHE.move_to_end(key)
    while len(_CACHE) > _CACHE_SIZE:
        _CACHE.popitem(last=False)


#: attributes of the factorisation that are the sensing's own objects (stored once)
_SHARED = {"sensing": "model", "mask": "obs_mask"}
_JSON_SCALARS = (bool, int, float, str, type(None))


def _encode(name: str, v: Any, arrays: dict[str, np.ndarray]) -> dict[str, Any] | None:
    """How a cache entry stores the field value ``v`` (an array goes into ``arrays`` under
    ``name``); ``None``: a kind it does not know (then nothing is cached: a field dropped on the
    way through the cache would change what a cached run does)."""
    if isinstance(v, Tensor):
        arrays[name] = to_numpy(v)
        return {"array": name}
    if isinstance(v, np.ndarray):
        arrays[name] = np.asarray(v)
        return {"numpy": name}
    if isinstance(v, CameraIdentity):
        return {"camera": v.to_dict()}
    if isinstance(v, tuple) and all(isinstance(x, _JSON_SCALARS) for x in v):
        return {"tuple": list(v)}
    if isinstance(v, _JSON_SCALARS):
        return {"value": v}
    if isinstance(v, (dict, list)) and not v:
        return {"empty": type(v).__name__}
    return None


def _decode(how: dict[str, Any], arrays: dict[str, np.ndarray], t: Any) -> Any:
    """The value :func:`_encode` stored as ``how`` (``t(name)``: a stored tensor, on the device)."""
    if "array" in how:
        return t(how["array"])
    if "numpy" in how:
        return np.array(arrays[how["numpy"]])
    if "camera" in how:
        return CameraIdentity.from_dict(how["camera"])
    if "tuple" in how:
        return tuple(how["tuple"])
    if "value" in how:
        return how["value"]
    return {"dict": {}, "list": []}[how["empty"]]


def _to_cache(sens: BundleSensing) -> tuple[dict[str, np.ndarray], dict[str, Any]] | None:
    """The arrays and metadata of a disk-cache entry for ``sens`` (``None``: a field of the
    factorisation or of the radiometry is of a kind :func:`_encode` does not know: not cached).

    Every attribute of the :class:`~hsi_torch.recon.nnls.NNLSProblem` is stored under
    ``problem.<name>`` whatever the solver keeps, so a change of its layout needs no change
    here."""
    arrays: dict[str, np.ndarray] = {
        "valid": to_numpy(sens.valid), "pixel_index": to_numpy(sens.pixel_index),
        "obs_mask": to_numpy(sens.obs_mask), "sample_grid": to_numpy(sens.grid()),
        "homographies": to_numpy(sens.homographies),
        "wavelengths_nm": to_numpy(sens.wavelengths_nm),
        "model.transmittance": to_numpy(sens.model.transmittance),
        "model.gain": to_numpy(sens.model.gain), "model.response": to_numpy(sens.model.response),
    }  # fmt: skip
    problem: dict[str, Any] = {}
    for name, v in vars(sens.problem).items():
        own = _SHARED.get(name)
        if own is not None and v is (sens.model if own == "model" else sens.obs_mask):
            problem[name] = {"shared": own}
        elif (how := _encode(f"problem.{name}", v, arrays)) is not None:
            problem[name] = how
        else:
            return None
    rad_meta = None
    if sens.radiometry is not None:
        rad_meta = {}
        for f in dataclasses.fields(sens.radiometry):
            how = _encode(f"radiometry.{f.name}", getattr(sens.radiometry, f.name), arrays)
            if how is None:
                return None
            rad_meta[f.name] = how
    meta = {
        "sensor_size": list(sens.sensor_size), "reference_bbox": list(sens.reference_bbox),
        "beta": sens.beta, "diff_order": sens.diff_order, "exposure_s": sens.exposure_s,
        "cfa_pattern": sens.cfa_pattern, "problem": problem,
        "radiometry": rad_meta,
    }  # fmt: skip
    return arrays, meta


def _from_cache(
    arrays: dict[str, np.ndarray], meta: dict[str, Any], dev: torch.device, entry: Path
) -> BundleSensing | None:
    """The :class:`BundleSensing` of a disk-cache entry (``None``, with a warning, when the
    entry does not hold what this code needs: then it is recomputed and replaced)."""
    def t(name: str) -> Tensor:
        a = arrays[name]
        return torch.from_numpy(a if a.flags.writeable else a.copy()).to(dev)

    try:
        check_cached_shapes(arrays, meta)
        model = SensingModel(t("model.transmittance"), t("model.gain"), t("model.response"))
        obs = t("obs_mask")
        problem = NNLSProblem.__new__(NNLSProblem)
        problem.__dict__.update({
            name: (model if how["shared"] == "model" else obs) if "shared" in how
            else _decode(how, arrays, t) for name, how in meta["problem"].items()})  # fmt: skip
        r = meta["radiometry"]
        rad = None if r is None else BundleRadiometry(
            **{name: _decode(how, arrays, t) for name, how in r.items()})  # fmt: skip
        x0, y0, w, h = (int(v) for v in meta["reference_bbox"])
        beta, order = float(meta["beta"]), int(meta["diff_order"])
        sens = BundleSensing(
            wavelengths_nm=torch.from_numpy(np.array(arrays["wavelengths_nm"])),
            sensor_size=(int(meta["sensor_size"][0]), int(meta["sensor_size"][1])),
            reference_bbox=(x0, y0, w, h), homographies=t("homographies"), valid=t("valid"),
            pixel_index=t("pixel_index"), model=model, obs_mask=obs, beta=beta,
            diff_order=order, problem=problem, exposure_s=meta["exposure_s"],
            cfa_pattern=meta["cfa_pattern"], radiometry=rad, sample_grid=t("sample_grid"),
        )  # fmt: skip
    except (KeyError, TypeError, ValueError, RuntimeError, AttributeError) as exc:
        disk._warn(f"precomputation cache entry {entry} refused: it does not hold what this "
                   f"software needs ({type(exc).__name__}: {exc}); recomputing")
        return None
    sens._problems[(beta, order)] = problem
    return sens


#: Shapes of the factorisation's arrays in a cache entry (``P`` pixels, ``M`` bands); others
#: (a later layout's) are not checked here.
_PROBLEM_SHAPES = {"gram": "PMM", "gram_inv": "PMM", "gram_diag": "PM", "gram_norm": "P",
                   "gram_diag_max": "P", "singular": "P", "no_data": "P", "reg": "MM"}  # fmt: skip


def check_cached_shapes(arrays: dict[str, np.ndarray], meta: dict[str, Any]) -> None:
    """Cross-check the arrays of a disk-cache entry against each other before any kernel reads
    them: ``valid (h, w)`` of the reference frame, ``pixel_index`` its ``P`` valid pixels in
    order, ``wavelengths_nm (M,)``, ``homographies (V, 3, 3)``, the model ``(P, V, M)``,
    ``(P, V)``, ``(C, M)``, ``obs_mask (P, C·V)``, ``sample_grid (1, V, P, 2)`` and the
    factorisation (:data:`_PROBLEM_SHAPES`), one float dtype. A compiled kernel trusts these
    shapes: a short ``gram_inv`` would be read past its end.

    Raises:
        ValueError: naming the first array that disagrees (the entry is refused and recomputed).
    """
    def get(name: str) -> np.ndarray:
        if name not in arrays:
            raise ValueError(f"no array {name!r}")
        return arrays[name]

    def need(name: str, shape: tuple[int, ...], kind: str) -> np.ndarray:
        a = get(name)
        if tuple(a.shape) != shape or a.dtype.kind != kind:
            raise ValueError(f"{name} is {a.dtype} {tuple(a.shape)}, expected {kind} {shape}")
        return a

    _x0, _y0, w, h = (int(v) for v in meta["reference_bbox"])
    valid = need("valid", (h, w), "b")
    P = int(np.count_nonzero(valid))
    pix = get("pixel_index")
    if pix.shape != (P,) or pix.dtype.kind not in "iu" or not np.array_equal(
            pix, np.flatnonzero(valid)):  # fmt: skip
        raise ValueError(f"pixel_index ({pix.dtype} {tuple(pix.shape)}) is not the indices of "
                         f"the {P} valid pixels of the {h} x {w} frame")
    M = int(get("wavelengths_nm").shape[0]) if get("wavelengths_nm").ndim == 1 else -1
    V = int(get("homographies").shape[0])
    need("homographies", (V, 3, 3), "f")
    if M < 1 or V < 1:
        raise ValueError(f"wavelengths_nm {tuple(get('wavelengths_nm').shape)}: not (M,)")
    dt = need("model.transmittance", (P, V, M), "f").dtype
    C = int(get("model.response").shape[0])
    for name, shape, kind in (("model.gain", (P, V), "f"), ("model.response", (C, M), "f"),
                              ("obs_mask", (P, C * V), "b"), ("sample_grid", (1, V, P, 2), "f")):
        a = need(name, shape, kind)
        if kind == "f" and name != "sample_grid" and a.dtype != dt:
            raise ValueError(f"{name} is {a.dtype}, the model {dt}")
    dims = {"P": P, "M": M}
    for name, how in meta["problem"].items():
        ref = how.get("array") or how.get("numpy") if isinstance(how, dict) else None
        if name in _PROBLEM_SHAPES:
            if ref is None:
                raise ValueError(f"the factorisation's {name} is not stored")
            a = need(ref, tuple(dims[c] for c in _PROBLEM_SHAPES[name]), get(ref).dtype.kind)
            if a.dtype.kind == "f" and a.dtype != dt:
                raise ValueError(f"{ref} is {a.dtype}, the model {dt}")
    missing = sorted(set(_PROBLEM_SHAPES) - set(meta["problem"]))
    if missing:
        raise ValueError(f"the factorisation's {missing} are not stored")


def refreshed_sensing(sens: BundleSensing, chunk_size: int | None = None) -> BundleSensing:
    """``sens``, or, when the disk-cache entry it was loaded from was written to, truncated or
    extended since (:func:`~hsi_torch.recon.precompute_cache.changed_since_load`: its mapped
    arrays would be read stale, or fault), the sensing loaded again (checked) or recomputed, with
    a warning. Cheap (a few ``fstat`` calls): the reconstructor asks before every frame."""
    stamp = getattr(sens, "_disk_stamp", None)
    why = disk.changed_since_load(stamp)
    if why is None or sens.disk_entry is None:
        return sens
    folder, path, _key = sens.disk_entry
    disk._warn(f"precomputation cache entry {stamp.entry}: {why} after it was loaded; not used "
               "any more (loaded again if intact, else recomputed)")
    for k in [k for k, v in _CACHE.items() if v is sens]:
        del _CACHE[k]
    return precompute_sensing(path, beta=sens.beta, diff_order=sens.diff_order,
                              device=sens.device, dtype=sens.model.transmittance.dtype,
                              chunk_size=chunk_size, disk_cache=folder)  # fmt: skip


def sample_pixels(ok: Tensor, num_samples: int) -> Tensor | None:
    """Up to ``num_samples`` indices evenly spaced over the ``P`` pixels of ``ok (P,)`` — the same
    ones every frame of a bundle — of which those ``ok`` keeps (``None`` when none is left)."""
    P = int(ok.shape[0])
    k = min(P, int(num_samples))
    if k == 0:
        return None
    idx = torch.linspace(0, P - 1, k, device=ok.device).round().long()
    idx = idx[ok[idx]]
    return idx if idx.numel() else None
