"""Capture renderer of the virtual prototype: sensor images and the ground truth behind them.

Physics of one sensor pixel ``p`` (``s × s`` sub-pixel rays traced with
:func:`hsi_torch.optics.trace_rays`; a ray with no view, or more reflections than
``max_reflections``, is black):

    E_c(p) = κ · mean_rays[ t · D(α) · V(X) · Σ_λ Δλ_f · φ^c(λ) · Tstack(X, α, σ, λ) · S(X, λ) ]

- ``λ`` runs over the *fine* grid: ``fine_step_nm`` (2 nm) samples tiling the band-pass
  ``[λ_0 − Δλ_0/2, λ_{M−1} + Δλ_{M−1}/2]`` (425–675 nm for the default 430–670/10 nm grid).
  The add-on carries a band-pass filter to the reconstruction band ± half a step in front of
  the camera, so it applies to every capture including the BRF-free patch.
- ``t = R^n`` mirror throughput, ``D(α) = cos^k α`` the diffuser fall-off
  (:class:`~hsi_torch.optics.sensor.DiffuserModel`), ``V(X) = 1 − v·|X|²/R²`` the objective's
  vignetting on the diffuser plane (``R`` the entrance triangle's circumradius).
- ``φ^c(λ) = l(λ) f^c(λ) τ_obj(λ)``: illuminant × camera sensitivity × objective transmission.
- ``Tstack = ½·η·T_BRF(α, σ, λ)`` (unpolarized light, polarizer pair efficiency ``η``,
  :meth:`BRFConfig.transmittance`) outside the BRF-free disk, ``1`` inside it (no filter stack).
- ``S`` the scene reflectance (``Scene.reflectance``; a white target when ``scene=None``).
- ``κ = 1 / max_c Σ_λ Δλ_f φ^c(λ)``: a white target seen without the filter stack
  (``t = D = V = 1``) gives ``E = 1`` in its brightest channel; the sensor exposure then sets the
  fraction of the full well (:class:`~hsi_torch.optics.sensor.SensorModel`, relative units).

Monochromator scan frame at ``λ_j``: objective removed, diffuser lit evenly from all directions
(``V = D = 1``, ``S = 1``) by a line ``g_j(λ)`` (Gaussian or triangular, FWHM ``scan_fwhm_nm``,
peak 1) instead of ``l·τ_obj``: ``E_c = κ_scan · t · Σ_λ Δλ_f g_j f^c Tstack`` with ``κ_scan``
making the BRF-free patch reach 1 at the brightest line of the band in its brightest channel.

Non-ideal effects (:class:`~hsi_torch.simulate.mismatch.Mismatch`, all off by default, each on
its own flag so the ideal path is unchanged): lens distortion and sensor drift move the traced
sensor points (:meth:`CaptureRenderer.sensor_to_pinhole`), a filter thickness map or temperature
change scales each ray's OPD, the monochromator's offset and width change the scan lines, a
scene illuminant changes the scenes' weights, stray light adds a veil to every image. Drift,
temperature and scene illuminant act only with ``after_calibration=True`` (the scene captures).

Ground truth in the reference frame (the sensor crop ``layout.reference_bbox``) — see
:meth:`CaptureRenderer.ground_truth`. With it the reference-frame forward model

    y[v, c, q] ≈ gain[v, q] · Σ_m B[v, m, q] · Δλ_m · phi[c, m] · s[m, q]      (DN above black)

reproduces the noise-free rendering to the discretisation error of the 10 nm grid.

How it is computed: :meth:`CaptureRenderer.render_captures` and :meth:`CaptureRenderer._shade`
(docs/simulate.md, *Numerics and measured times*). Precision: the render dtype for rays, cosines,
rasters and images; float64 for the view layout, the spectral weights and the ground truth.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import torch

from hsi_torch import refdata
from hsi_torch.forward_model import SensingModel
from hsi_torch.optics import (
    BRFConfig,
    CameraModel,
    KaleidoscopeGeometry,
    PrototypeDesign,
    ViewLayout,
    build_view_layout,
    enumerate_sequences,
    sequence_codes,
    trace_rays,
)
from hsi_torch.optics.birefringence import polarizer_transmittance
from hsi_torch.optics.geometry import (
    apply_homography,
    pixel_centres,
    points_in_triangle,
    reference_pixel_points,
    view_sample_grid,
)
from hsi_torch.optics.sensor import DiffuserModel, Exposure, SensorModel, cfa_index
from hsi_torch.simulate.mismatch import (
    Mismatch,
    drift_points,
    radial_undistort,
    stray_light_veil,
)
from hsi_torch.simulate.scenes import (
    CubeScene,
    Scene,
    has_abundances,
    render_scene_abundances,
    render_scene_image,
)
from hsi_torch.spectral import DEFAULT_GRID, SpectralGrid, band_widths, resample_spectra

__all__ = [
    "CaptureSpec",
    "CaptureRenderer",
    "SubpixelTrace",
    "fine_wavelengths",
    "hat_weights",
    "line_profile",
    "subpixel_offsets",
    "blur_scene",
]


# --- spectral helpers


def fine_wavelengths(grid_nm: torch.Tensor, step_nm: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Fine sample centres tiling the band-pass ``[λ_0 − Δλ_0/2, λ_{M−1} + Δλ_{M−1}/2]``.

    Args:
        grid_nm: ``(M,)`` reconstruction grid (nm).
        step_nm: requested fine step; the actual step divides the band-pass evenly.

    Returns:
        ``(wavelengths (L,), widths (L,))`` in nm, dtype/device of ``grid_nm``.
        Default grid, 2 nm: 426, 428, …, 674 (L = 125), widths 2.
    """
    if step_nm <= 0:
        raise ValueError(f"step_nm must be > 0, got {step_nm}")
    g = grid_nm.to(torch.float64)
    dl = band_widths(g)
    lo, hi = float(g[0] - dl[0] / 2), float(g[-1] + dl[-1] / 2)
    n = max(1, int(round((hi - lo) / step_nm)))
    h = (hi - lo) / n
    wl = lo + (torch.arange(n, dtype=torch.float64, device=grid_nm.device) + 0.5) * h
    return wl.to(grid_nm.dtype), torch.full_like(wl, h).to(grid_nm.dtype)


def hat_weights(grid_nm: torch.Tensor, fine_nm: torch.Tensor) -> torch.Tensor:
    """``(M, L)`` linear-interpolation basis ``h_m(λ_l)`` of the grid, constant beyond the ends.

    ``Σ_m h_m = 1`` everywhere, so a spectrum that is linear between grid nodes is reproduced
    exactly: ``s(λ_l) = Σ_m s_m h_m(λ_l)``.
    """
    eye = torch.eye(grid_nm.numel(), dtype=fine_nm.dtype, device=fine_nm.device)
    return resample_spectra(eye, grid_nm.to(fine_nm), fine_nm, dim=-1, extrapolate="edge")


def line_profile(
    centres_nm: torch.Tensor, fine_nm: torch.Tensor, fwhm_nm: float, shape: str = "gaussian"
) -> torch.Tensor:
    """``(J, L)`` monochromator lines of peak 1 centred at ``centres_nm (J,)``.

    ``'gaussian'``: ``exp(−½((λ−λ_j)/σ)²)``, ``σ = FWHM / (2√(2 ln 2))``; ``'triangle'``:
    ``max(0, 1 − |λ−λ_j| / FWHM)`` (equal entrance and exit slits).
    """
    if fwhm_nm <= 0:
        raise ValueError(f"fwhm_nm must be > 0, got {fwhm_nm}")
    d = fine_nm[None, :] - centres_nm.to(fine_nm)[:, None]
    if shape == "gaussian":
        sig = fwhm_nm / (2.0 * math.sqrt(2.0 * math.log(2.0)))
        return torch.exp(-0.5 * (d / sig) ** 2)
    if shape == "triangle":
        return (1.0 - d.abs() / fwhm_nm).clamp_min(0.0)
    raise ValueError(f"line shape must be 'gaussian' or 'triangle', got {shape!r}")


def subpixel_offsets(s: int, device=None, dtype=None) -> torch.Tensor:
    """``(s², 2)`` offsets ``(dx, dy)`` of a regular ``s × s`` sub-pixel pattern (unit pixel)."""
    o = (torch.arange(s, device=device, dtype=dtype or torch.float64) + 0.5) / s - 0.5
    yy, xx = torch.meshgrid(o, o, indexing="ij")
    return torch.stack([xx.reshape(-1), yy.reshape(-1)], dim=-1)


def blur_scene(
    scene: Scene,
    sigma_mm: float,
    extent: tuple[float, float, float, float],
    spacing_mm: float,
    wavelengths_nm: torch.Tensor,
    max_side: int = 1024,
    *,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float64,
) -> CubeScene:
    """The scene blurred on the diffuser plane by a Gaussian of ``sigma_mm``, as a cube scene.

    The scene is rasterised over ``extent`` (mm) every ``spacing_mm`` (at most ``max_side``
    samples a side; 2× supersampled) in ``dtype`` (the render dtype), blurred with
    :meth:`~hsi_torch.optics.sensor.DiffuserModel.blur` and wrapped in a
    :class:`~hsi_torch.simulate.scenes.CubeScene` whose spectra live on ``wavelengths_nm``
    (linear in λ between them, held at the ends).

    A linear-mixture scene (:func:`~hsi_torch.simulate.scenes.has_abundances`) is rasterised as
    its ``K`` abundance planes and kept as a low-rank cube (``endmembers (K, L)`` on
    ``wavelengths_nm``): raster, blur and bilinear sampling are linear, so this equals blurring
    the ``L``-band image, at ``K / L`` of the memory and time (CAVE: 31 planes instead of 125
    bands; ColorChecker: 25; bar and circle targets: 1). Other scenes are rasterised on
    ``wavelengths_nm``. The raster is cropped to where it is not zero (plus one zero pixel),
    which leaves every sample unchanged: outside the crop the cube scene is 0.
    """
    x0, x1, y0, y1 = extent
    w = int(min(max_side, max(8, math.ceil((x1 - x0) / spacing_mm))))
    h = int(min(max_side, max(8, math.ceil((y1 - y0) / spacing_mm))))
    wl = wavelengths_nm.to(device=device or wavelengths_nm.device, dtype=torch.float64)
    endmembers = None
    if has_abundances(scene):
        img = render_scene_abundances(scene, extent, h, w, supersample=2, device=wl.device,
                                      dtype=dtype)
        endmembers = scene.endmember_spectra(wl)  # (K, L) float64, tiny
    else:
        img = render_scene_image(scene, extent, h, w, wl.to(dtype), supersample=2)
    px = min((x1 - x0) / w, (y1 - y0) / h)
    blur = DiffuserModel(blur_sigma_mm=sigma_mm)
    for c in range(0, img.shape[0], 8):  # the blur is per plane: bound its work space
        img[c:c + 8] = blur.blur(img[c:c + 8], px)
    # crop to the planes' support plus one zero pixel: bilinear sampling inside the crop and
    # 0 outside it are then exactly the samples of the whole raster
    nz = img.ne(0).any(0)
    rows, cols = torch.nonzero(nz.any(1)).squeeze(1), torch.nonzero(nz.any(0)).squeeze(1)
    if rows.numel() == 0:
        r0, r1, c0, c1 = 0, 1, 0, 1
    else:
        r0, r1 = max(0, int(rows[0]) - 1), min(h, int(rows[-1]) + 2)
        c0, c1 = max(0, int(cols[0]) - 1), min(w, int(cols[-1]) + 2)
    if (r0, r1, c0, c1) != (0, h, 0, w):
        dx, dy = (x1 - x0) / w, (y1 - y0) / h
        img = img[:, r0:r1, c0:c1].clone()
        extent = (x0 + c0 * dx, x0 + c1 * dx, y0 + r0 * dy, y0 + r1 * dy)
    return CubeScene(img, wl.cpu(), extent_mm=extent, extrapolate="edge", endmembers=endmembers)


# --- data containers


@dataclass
class CaptureSpec:
    """One capture to render.

    Attributes:
        name: identifier (file stem).
        kind: ``'scene'`` (objective on, illuminant ``l``; white reference, circle grid and scene
            captures), ``'scan'`` (monochromator frame, objective off) or ``'dark'``.
        scene: reflectance on the diffuser; ``None`` = white (reflectance 1).
        wavelength_nm: centre of the monochromator line (``'scan'`` only).
    """

    name: str
    kind: str = "scene"
    scene: Any = None
    wavelength_nm: float | None = None

    def __post_init__(self) -> None:
        if self.kind not in ("scene", "scan", "dark"):
            raise ValueError(f"CaptureSpec.kind must be 'scene', 'scan' or 'dark', got "
                             f"{self.kind!r}")
        if self.kind == "scan" and self.wavelength_nm is None:
            raise ValueError(f"scan capture {self.name!r} needs wavelength_nm")


@dataclass
class SubpixelTrace:
    """Sub-pixel rays that reach the diffuser (all others are black).

    Attributes (``N`` rays): ``pixel`` long flat sensor index ``y·W + x``; ``alpha``, ``sigma``
    (rad); ``hit_xy (N, 2)`` mm; ``throughput`` ``R^n``; ``brf_free`` bool; ``view`` layout view
    index or −1 (higher-order tile); ``samples`` = ``s²`` rays per pixel; ``sensor_size (H, W)``.
    """

    pixel: torch.Tensor
    alpha: torch.Tensor
    sigma: torch.Tensor
    hit_xy: torch.Tensor
    throughput: torch.Tensor
    brf_free: torch.Tensor
    view: torch.Tensor
    samples: int
    sensor_size: tuple[int, int]

    @property
    def num_rays(self) -> int:
        return int(self.pixel.numel())


# --- renderer


# rays shaded together: their (rays, L) cosine matrix (4 MB in float32) stays in the CPU cache
# between the phase product, the cosine and the weight product (≈ 1.7× faster than whole bands)
_SHADE_BATCH = 8192


def _select_rays(tr: SubpixelTrace, idx: torch.Tensor | slice) -> SubpixelTrace:
    """The rays ``idx`` (index tensor or slice) of a trace."""
    return SubpixelTrace(pixel=tr.pixel[idx], alpha=tr.alpha[idx], sigma=tr.sigma[idx],
                         hit_xy=tr.hit_xy[idx], throughput=tr.throughput[idx],
                         brf_free=tr.brf_free[idx], view=tr.view[idx], samples=tr.samples,
                         sensor_size=tr.sensor_size)


def _camera_signal(name_or_path: str, wl: torch.Tensor) -> torch.Tensor:
    try:
        return refdata.camera_sensitivities(name_or_path, wl, extrapolate="edge")
    except (FileNotFoundError, ValueError) as exc:  # name the configuration key at fault
        raise type(exc)(f"config key 'camera_sensitivity': {exc}") from None


class CaptureRenderer:
    """Renders captures of the virtual prototype and their ground truth.

    Args:
        geometry, camera, brf: optics (``geometry.max_reflections`` views, normally 2 → 10 views).
        sensor: the raw sensor; ``sensor.exposure`` is the scene/white/grid exposure.
        diffuser: angular fall-off ``cos^k α`` and optional blur of the scene on the diffuser.
        grid: reconstruction grid (default 430…670 nm, 10 nm).
        fine_step_nm: internal wavelength step (see :func:`fine_wavelengths`).
        polarizer_efficiency: ``η`` in ``Tstack = ½ η T_BRF``.
        vignetting: objective vignetting strength ``v`` (``V = 1 − v |X|²/R²``).
        objective_transmission: flat ``τ_obj`` or ``(wavelengths_nm, values)``.
        illuminant, camera_sensitivity: names or file paths (:mod:`hsi_torch.refdata`).
        supersample: ``s`` (``s × s`` rays per pixel).
        max_reflections: reflections traced for the image (3 draws the dark higher-order tiles
            around the ten views as a real camera sees them; they are not views).
        scan_fwhm_nm, scan_line: monochromator line.
        scan_exposure: the BRF-free patch at the brightest scan line fills this fraction of the
            full well.
        chunk: rays per batch; device, dtype: where and how to render.
        layout: a precomputed :class:`ViewLayout` (else built from a float64 trace).
        view_inset_px: truth ``view_mask`` keeps source points this far inside the triangle.
        mismatch: non-ideal effects (:class:`~hsi_torch.simulate.mismatch.Mismatch`; default:
            none). The sensor's own (PRNU, hot/dead pixels, non-linearity) belong to ``sensor``.
        design: the spectral coder (:class:`~hsi_torch.optics.PrototypeDesign`; default: this
            system, the BRF between polarizers). ``manakov``: per ray the filter of its view
            (no polarizers, ``Tstack = T_v(λ)``, 0 on higher-order tiles); ``fujimoto``: each
            ray's OPD times the grain factor of the thin section where it crosses it.
    """

    def __init__(
        self,
        geometry: KaleidoscopeGeometry,
        camera: CameraModel,
        brf: BRFConfig,
        sensor: SensorModel,
        *,
        diffuser: DiffuserModel | None = None,
        grid: SpectralGrid = DEFAULT_GRID,
        fine_step_nm: float = 2.0,
        polarizer_efficiency: float = 0.9,
        vignetting: float = 0.2,
        objective_transmission: float | tuple[Sequence[float], Sequence[float]] = 0.9,
        illuminant: str = refdata.DEFAULT_ILLUMINANT,
        camera_sensitivity: str = refdata.DEFAULT_CAMERA,
        supersample: int = 2,
        max_reflections: int = 3,
        scan_fwhm_nm: float = 10.0,
        scan_line: str = "gaussian",
        scan_exposure: float = 0.8,
        chunk: int = 1 << 16,
        device: torch.device | str = "cpu",
        dtype: torch.dtype = torch.float64,
        layout: ViewLayout | None = None,
        view_inset_px: float = 1.0,
        mismatch: Mismatch | None = None,
        design: PrototypeDesign | None = None,
    ) -> None:
        if supersample < 1:
            raise ValueError(f"supersample must be >= 1, got {supersample}")
        if max_reflections < geometry.max_reflections:
            raise ValueError(f"render max_reflections ({max_reflections}) must be >= "
                             f"geometry.max_reflections ({geometry.max_reflections})")
        if not 0 < polarizer_efficiency <= 1:
            raise ValueError(f"polarizer_efficiency must be in (0, 1], got {polarizer_efficiency}")
        if not 0 <= vignetting < 1:
            raise ValueError(f"vignetting must be in [0, 1), got {vignetting}")
        if dtype not in (torch.float32, torch.float64):
            raise TypeError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
        self.geometry, self.camera, self.brf, self.sensor = geometry, camera, brf, sensor
        #: the camera sensitivity's name or file (the captures' ``camera_model``)
        self.camera_sensitivity = str(camera_sensitivity)
        self.diffuser = diffuser if diffuser is not None else DiffuserModel()
        self.grid = grid
        self.polarizer_efficiency = float(polarizer_efficiency)
        self.vignetting = float(vignetting)
        self.supersample = int(supersample)
        self.max_reflections = int(max_reflections)
        self.scan_fwhm_nm, self.scan_line = float(scan_fwhm_nm), scan_line
        self.scan_exposure = float(scan_exposure)
        self.chunk = int(chunk)
        self.view_inset_px = float(view_inset_px)
        self.mismatch = mismatch if mismatch is not None else Mismatch()
        self.design = design if design is not None else PrototypeDesign()
        if not self.design.has_brf and (self.mismatch.thickness_map
                                        or self.mismatch.brf_delta_t_k != 0):
            raise ValueError(f"design kind {self.design.kind!r} has no birefringent filter: "
                             "the mismatch keys brf_thickness_* and brf_delta_t_k do not apply")
        self.device, self.dtype = torch.device(device), dtype
        dev = self.device

        self.wavelengths = grid.wavelengths(dev, torch.float64)  # (M,)
        self.band_widths = band_widths(self.wavelengths)  # (M,)
        self.fine, self.fine_widths = fine_wavelengths(self.wavelengths, fine_step_nm)  # (L,)
        l_ = refdata.illuminant(illuminant, self.fine, extrapolate="edge")
        f_ = _camera_signal(camera_sensitivity, self.fine)
        if isinstance(objective_transmission, (int, float)):
            tau = torch.full_like(self.fine, float(objective_transmission))
        else:
            src, val = objective_transmission
            tau = resample_spectra(torch.as_tensor(val, dtype=torch.float64, device=dev),
                                   torch.as_tensor(src, dtype=torch.float64, device=dev),
                                   self.fine, extrapolate="edge")
        if bool((tau < 0).any()) or bool((tau > 1).any()):
            raise ValueError("objective transmission must lie in [0, 1]")
        self.illuminant_spd, self.camera_sens, self.objective_tau = l_, f_, tau
        self.phi_fine = l_ * f_ * tau  # (3, L), l·f·τ
        self.kappa = 1.0 / float((self.phi_fine * self.fine_widths).sum(1).max())
        lines = line_profile(self.fine, self.fine, self.scan_fwhm_nm, self.scan_line)  # (L, L)
        self.kappa_scan = 1.0 / float(torch.einsum("jl,cl->jc", lines * self.fine_widths, f_).max())
        self.dn_per_unit = sensor.electrons_at_unity / sensor.gain_e_per_dn
        self.layout = layout if layout is not None else build_view_layout(
            geometry, camera, brf, device=dev)
        self.layout = self.layout.to(dev)
        v = geometry.entrance_vertices(dev, torch.float64)
        self._r2 = float((v - v.mean(0)).pow(2).sum(1).max())
        self._blur_cache: dict[int, Scene] = {}
        self._knots: tuple | None = None
        self._phase: tuple | None = None
        self.num_rays = 0  # sub-pixel rays that reached the diffuser in the last render
        self.opd_knot_step_nm = 10.0
        #: ``manakov``: ``(V, L)`` float64 filter of each view on the fine grid (else ``None``)
        self.view_filters = (self.design.view_filters(self.layout.num_views, self.fine)
                             if not self.design.has_brf else None)
        self._filters_dt: torch.Tensor | None = None

    # ------------------------------------------------------------------ factors
    @property
    def sensor_size(self) -> tuple[int, int]:
        return (self.camera.height_px, self.camera.width_px)

    @property
    def scene_exposure(self) -> float:
        return float(self.sensor.exposure)

    @property
    def mosaic_early(self) -> bool:
        """Accumulate only each pixel's CFA colour (Bayer without PSF): 3× less memory."""
        return self.sensor.output == "bayer" and self.sensor.psf_sigma_px == 0

    def vignetting_factor(self, xy_mm: torch.Tensor) -> torch.Tensor:
        """Objective vignetting ``V(X) = 1 − v·|X|²/R²`` at diffuser points ``(..., 2)`` (≥ 0)."""
        return (1.0 - self.vignetting * xy_mm.pow(2).sum(-1) / self._r2).clamp_min(0.0)

    def stack_transmittance(
        self, alpha: torch.Tensor, sigma: torch.Tensor, brf_free: torch.Tensor,
        wavelengths_nm: torch.Tensor, exact: bool = True, view: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """``(N, L)`` filter-stack transmittance: ``½ η T_BRF`` outside the BRF-free disk, 1 in it.

        Design ``manakov``: the filter of each ray's ``view (N,)`` (required; the fine grid
        only); ``fujimoto``: the grain factors need the rays' diffuser points, so this method
        gives the nominal plate (use :meth:`retardance_cosine` with ``opd_scale``).

        ``exact=False`` (the fine-grid model of the image and the truth, ``wavelengths_nm`` =
        :attr:`fine`) evaluates the exact OPD (:meth:`BRFConfig.opd_nm`) at knots every
        ``opd_knot_step_nm`` and interpolates it linearly in λ before the polarizer formula;
        the OPD is smooth in λ (dispersion only), so the error is < 0.05 nm of OPD (≤ 1e-3 in
        T, tested) at a fifth of the cost. The renderer evaluates the same model in its cosine
        form (:meth:`retardance_cosine`, :meth:`stack_cosine_form`).
        """
        wl = wavelengths_nm.to(alpha)
        if not self.design.has_brf:
            if view is None or wl.numel() != self.fine.numel():
                raise ValueError("design 'manakov': stack_transmittance needs `view` and the "
                                 "fine grid")
            return self._ray_filters(view, alpha.dtype)
        if exact:
            t = self.brf.transmittance(alpha[:, None], sigma[:, None], wl)
        else:
            knots, interp = self._opd_knots(wl)
            opd = self.brf.opd_nm(alpha[:, None], sigma[:, None], knots) @ interp
            t = polarizer_transmittance(opd, wl, math.radians(self.brf.psi_deg),
                                        math.radians(self.brf.chi_deg))
        t = 0.5 * self.polarizer_efficiency * t
        return torch.where(brf_free[:, None], torch.ones_like(t), t)

    def _ray_filters(self, view: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
        """``(N, L)`` ``manakov`` filter of each ray's view on the fine grid (0 for view −1)."""
        if self._filters_dt is None or self._filters_dt.dtype != dtype:
            f = self.view_filters.to(dtype)  # type: ignore[union-attr]
            self._filters_dt = torch.cat([f, torch.zeros_like(f[:1])], 0)  # row V: masked tiles
        v = torch.where(view < 0, self._filters_dt.shape[0] - 1, view)
        return self._filters_dt[v]

    def _opd_scale(self, xy_mm: torch.Tensor, after_calibration: bool) -> torch.Tensor | None:
        """``(N,)`` factor on each ray's OPD (the thin section's grains, the mismatch's thickness
        map and temperature change) or ``None`` when it is 1 everywhere."""
        scale = None
        if self.mismatch.thickness_map or after_calibration:
            scale = self.mismatch.opd_factor(xy_mm, self.brf.thickness_mm, self._r2,
                                             after_calibration)
        if self.design.kind == "fujimoto":
            g = self.design.grain_factor(xy_mm)
            scale = g if scale is None else scale * g
        return scale

    def _opd_knots(self, wl: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        key = (wl.device, wl.dtype, wl.numel())
        if self._knots is None or self._knots[0] != key:
            lo, hi = float(wl.min()), float(wl.max())
            n = max(2, int(math.ceil((hi - lo) / self.opd_knot_step_nm)) + 1)
            knots = torch.linspace(lo, hi, n, device=wl.device, dtype=torch.float64)
            eye = torch.eye(n, device=wl.device, dtype=torch.float64)
            interp = resample_spectra(eye, knots, wl.to(torch.float64), dim=-1)
            self._knots = (key, knots.to(wl.dtype), interp.to(wl.dtype))
        return self._knots[1], self._knots[2]

    def stack_cosine_form(self) -> tuple[float, float]:
        """``(a, b)`` with ``½ η T_BRF = a + b · cos(2π · OPD / λ)`` outside the BRF-free disk.

        The polarizer formula ``cos²χ − sin 2ψ · sin 2(ψ − χ) · sin²(π OPD / λ)``
        (:func:`~hsi_torch.optics.birefringence.polarizer_transmittance`) with
        ``sin² x = (1 − cos 2x) / 2``; crossed polarizers: ``a = η/4``, ``b = −η/4``.
        """
        psi, chi = math.radians(self.brf.psi_deg), math.radians(self.brf.chi_deg)
        k = math.sin(2 * psi) * math.sin(2 * (psi - chi))
        half_eta = 0.5 * self.polarizer_efficiency
        return half_eta * (math.cos(chi) ** 2 - 0.5 * k), half_eta * 0.5 * k

    def retardance_cosine(
        self, alpha: torch.Tensor, sigma: torch.Tensor, brf_free: torch.Tensor,
        opd_scale: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """``(N, L)`` ``cos(2π · OPD(α, σ, λ_l) / λ_l)`` on the fine grid, 1 for BRF-free rays.

        The OPD is the knot-interpolated one of ``stack_transmittance(..., exact=False)``; the
        phase ``2π · OPD / λ`` is one ``(N, knots) @ (knots, L)`` product (interpolation and
        ``2π/λ`` folded into the matrix), so with :meth:`stack_cosine_form`
        ``stack_transmittance(α, σ, free, fine, exact=False) = a + b · cos`` outside the disk
        costs one matrix product and one in-place cosine per ray and wavelength.
        ``opd_scale (N,)`` multiplies each ray's OPD (a filter thickness map or temperature
        change, :meth:`Mismatch.opd_factor`); ``None`` = 1.
        """
        knots, phase = self._phase_knots(alpha.dtype)
        opd = self.brf.opd_nm(alpha[:, None], sigma[:, None], knots)  # (N, knots)
        if opd_scale is not None:
            opd = opd * opd_scale.to(opd)[:, None]
        opd = opd.masked_fill(brf_free[:, None], 0.0)
        return (opd @ phase).cos_()

    def _phase_knots(self, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
        key = (self.device, dtype)
        if self._phase is None or self._phase[0] != key:
            fine = self.fine.to(torch.float64)
            knots, interp = self._opd_knots(fine)  # float64
            phase = interp * (2.0 * math.pi / fine)
            self._phase = (key, knots.to(dtype), phase.to(dtype))
        return self._phase[1], self._phase[2]

    def phi_true(self) -> torch.Tensor:
        """``(3, M)`` float64 ``φ^c_m`` in DN per nm per unit reflectance (× gain × B).

        ``φ_m = dn_per_unit · exposure · κ · Σ_l h_m(λ_l) φ^c(λ_l) Δλ_l / Δλ_m``: the
        exposure-scaled ``l·f·τ`` averaged with the grid's interpolation basis.
        """
        h = hat_weights(self.wavelengths, self.fine)  # (M, L)
        avg = (self.phi_fine * self.fine_widths) @ h.T / self.band_widths  # (3, M)
        return avg * (self.dn_per_unit * self.scene_exposure * self.kappa)

    def scan_line_weights(self, centres_nm: torch.Tensor) -> torch.Tensor:
        """``(J, L)`` normalised weights of the scan lines (sum 1 over the band-pass)."""
        w = line_profile(centres_nm.to(self.fine), self.fine, self.scan_fwhm_nm,
                         self.scan_line) * self.fine_widths
        return w / w.sum(1, keepdim=True)

    # ------------------------------------------------------------------ tracing
    def sensor_to_pinhole(
        self, points_px: torch.Tensor, after_calibration: bool = False
    ) -> torch.Tensor:
        """``(N, 2)`` sensor points → the pinhole-camera points whose rays they receive.

        The identity for the ideal device. With :attr:`mismatch`: the sensor's drift since
        calibration (``after_calibration`` only, :func:`~.mismatch.drift_points`), then the
        lens's radial distortion (:func:`~.mismatch.radial_undistort`).
        """
        m, cam = self.mismatch, self.camera
        if after_calibration and m.drifted:
            points_px = drift_points(points_px, m.drift_shift_px, m.drift_rotation_deg,
                                     ((cam.width_px - 1) / 2.0, (cam.height_px - 1) / 2.0))
        if m.distorted:
            points_px = radial_undistort(points_px, m.distortion_k1, m.distortion_k2,
                                         cam.focal_px, float(cam.cx), float(cam.cy))
        return points_px

    def trace_tiles(
        self, progress: Callable | None = None, after_calibration: bool = False
    ) -> Iterator[tuple[int, int, SubpixelTrace]]:
        """Trace ``s²`` rays per sensor pixel, one band of sensor rows (≈ :attr:`chunk` rays) at
        a time: yields ``(row0, row1, rays of rows row0…row1−1 that reach the diffuser)``.

        A pixel's rays all lie in its band, so a band's pixels are complete once it is shaded.
        Sensor points go through :meth:`sensor_to_pinhole` (lens distortion, and the drift when
        ``after_calibration``) before they are traced.
        """
        dev, dt = self.device, self.dtype
        geom = dataclasses.replace(self.geometry, max_reflections=self.max_reflections)
        seqs = enumerate_sequences(self.max_reflections)
        lay_codes = sequence_codes(self.layout.reflection_sequences)
        all_codes = torch.tensor(sequence_codes(seqs), device=dev)
        view_of = torch.full((int(all_codes.max()) + 1,), -1, dtype=torch.long, device=dev)
        for v, c in enumerate(lay_codes):
            view_of[c] = v
        h, w = self.sensor_size
        s2 = self.supersample**2
        offs = subpixel_offsets(self.supersample, dev, torch.float64)
        rows_per = max(1, self.chunk // (w * s2))
        it = range(0, h, rows_per)
        if progress is not None:
            it = progress(it, desc="tracing + rendering", unit="band")
        for y0 in it:
            y1 = min(h, y0 + rows_per)
            base = pixel_centres(y1 - y0, w, device=dev).reshape(-1, 2)  # (P, 2)
            base[:, 1] += y0
            pts = (base[:, None, :] + offs[None]).reshape(-1, 2)
            if self.mismatch.distorted or (after_calibration and self.mismatch.drifted):
                pts = self.sensor_to_pinhole(pts, after_calibration)
            tr = trace_rays(geom, self.camera, pts.to(dt), sequences=seqs, chunk=self.chunk)
            keep = torch.nonzero(tr.view_index >= 0).squeeze(1)
            pix = torch.arange(y0 * w, y1 * w, device=dev).repeat_interleave(s2)
            hit = tr.hit_xy[keep]
            yield y0, y1, SubpixelTrace(
                pixel=pix[keep], alpha=tr.alpha[keep], sigma=tr.sigma[keep], hit_xy=hit,
                throughput=tr.throughput[keep], brf_free=self.geometry.brf_free_mask(hit),
                view=view_of[tr.sequence_code[keep]], samples=s2, sensor_size=(h, w))

    # ------------------------------------------------------------------ rendering
    def _scene_for_render(self, scene: Any) -> Any:
        if scene is None or self.diffuser.blur_sigma_mm <= 0:
            return scene
        key = id(scene)
        if key not in self._blur_cache:
            v = self.geometry.entrance_vertices(dtype=torch.float64)
            m = 4.0 * self.diffuser.blur_sigma_mm
            ext = (float(v[:, 0].min()) - m, float(v[:, 0].max()) + m,
                   float(v[:, 1].min()) - m, float(v[:, 1].max()) + m)
            hd = self.layout.diffuser_homographies[0]
            px_per_mm = float(torch.linalg.det(hd[:2, :2] / hd[2, 2]).abs().sqrt())
            self._blur_cache[key] = blur_scene(scene, self.diffuser.blur_sigma_mm, ext,
                                               0.5 / px_per_mm, self.fine, device=self.device,
                                               dtype=self.dtype)
        return self._blur_cache[key]

    def release_scenes(self) -> None:
        """Drop the cached blurred scene rasters (they are rebuilt on demand)."""
        self._blur_cache.clear()

    def _shading_plan(
        self, specs: Sequence[CaptureSpec], after_calibration: bool = False
    ) -> dict[str, Any]:
        """Per-render constants: the lit captures (scans first, then scenes, in spec order) and
        the spectral weights ``W[l, column, c]`` that every ray's ``cos(2π OPD/λ)`` row meets.

        Blocks: the scan lines (``g_j f^c Δλ κ_scan``, one column each); the white target
        (``φ^c Δλ κ``), shared by the targets whose single endmember is flat (USAF, circle
        grids: their abundance is the reflectance); and per other scene its ``K`` endmember
        columns ``E_k(λ) φ^c(λ) Δλ κ``. Built in float64, then cast to the render dtype. Each
        capture's numbers come from its own block only, so a capture is bit-identical whatever
        else the set contains.

        Mismatch: the scan lines are centred ``scan_wavelength_offset_nm`` off their nominal
        wavelength with FWHM ``scan_fwhm_actual_nm`` (``κ_scan`` stays the nominal line's);
        ``after_calibration`` scenes are lit by ``scene_illuminant`` (``κ`` stays the white
        reference's).
        """
        dev, dt, f64 = self.device, self.dtype, torch.float64
        mm = self.mismatch
        scan = [i for i, sp in enumerate(specs) if sp.kind == "scan"]
        lit_scenes = [i for i, sp in enumerate(specs) if sp.kind == "scene"]
        phi_fine = self.phi_fine
        if after_calibration and mm.scene_illuminant is not None:
            phi_fine = refdata.illuminant(mm.scene_illuminant, self.fine, extrapolate="edge") \
                * self.camera_sens * self.objective_tau
        phi_w = (phi_fine * self.fine_widths * self.kappa).T  # (L, 3) float64

        def block(w: torch.Tensor) -> dict[str, torch.Tensor]:  # w: (L, columns, 3) float64
            return {"w": w.to(dt), "w_sum": w.sum(0).to(dt)}

        plan: dict[str, Any] = {"order": scan + lit_scenes, "num_scan": len(scan),
                                "scan": None, "white": None, "scenes": [],
                                "after": after_calibration}
        if scan:
            centres = torch.tensor([float(specs[i].wavelength_nm) for i in scan],
                                   device=dev, dtype=f64)
            fwhm = self.scan_fwhm_nm
            if mm.scan_changed:
                centres = centres + mm.scan_wavelength_offset_nm
                fwhm = mm.scan_fwhm_actual_nm or fwhm
            lines = line_profile(centres, self.fine, fwhm, self.scan_line)
            plan["scan"] = block(torch.einsum("jl,cl->ljc", lines * self.fine_widths
                                              * self.kappa_scan, self.camera_sens))
        for i in lit_scenes:
            sc = self._scene_for_render(specs[i].scene)
            entry: dict[str, Any] = {"scene": sc}
            if sc is None:
                entry["kind"] = "white"
            elif has_abundances(sc):
                em = sc.endmember_spectra(self.fine).to(f64)  # (K, L)
                if em.shape[0] == 1 and bool((em == 1).all()):
                    entry["kind"] = "flat"  # S = a(X): the white block times the abundance
                else:
                    entry.update(kind="mix", **block(em.T[:, :, None] * phi_w[:, None, :]))
            else:
                entry.update(kind="generic", fine=self.fine.to(dt), phi_w=phi_w.to(dt))
            if entry["kind"] in ("white", "flat") and plan["white"] is None:
                plan["white"] = block(phi_w[:, None, :])
            plan["scenes"].append(entry)
        return plan

    def _shade(
        self, plan: dict[str, Any], tr: SubpixelTrace, channels: Sequence[int],
        out: torch.Tensor,
    ) -> None:
        """Relative irradiance of every lit capture (order ``plan['order']``) in the given
        colour channels for a batch of rays, written into ``out (N, K_lit, len(channels))``.

        Per ray ``Tstack(λ) = A + B · cos(2π OPD/λ)`` (``A = a, B = b`` behind the filter,
        ``A = 1, B = 0`` in the BRF-free disk, :meth:`stack_cosine_form`), so every spectral
        integral ``Σ_l Tstack_l W_l`` is ``A · Σ_l W_l + B · (cos @ W)``: one product for all
        scan lines, one for the white and flat targets, one per multi-spectral scene
        (``S = Σ_k a_k(X) E_k(λ)``: its ``K`` columns, contracted with the abundances; only on
        the rays where they are not all zero when those are at most half).
        """
        n, nc = tr.num_rays, len(channels)
        ch = list(channels)
        if not self.design.has_brf:  # manakov: Tstack = T_view(λ), i.e. A = 0, B = 1
            cos = self._ray_filters(tr.view, tr.alpha.dtype)  # (n, L)
            dt, dev = cos.dtype, cos.device
            coef_a = torch.zeros((n, 1), dtype=dt, device=dev)
            coef_b = torch.ones((n, 1), dtype=dt, device=dev)
        else:
            a, b = self.stack_cosine_form()
            scale = None
            if self.mismatch.thickness_map or plan["after"] or self.design.kind != "this_system":
                scale = self._opd_scale(tr.hit_xy, plan["after"])
            cos = self.retardance_cosine(tr.alpha, tr.sigma, tr.brf_free, scale)  # (n, L)
            dt, dev = cos.dtype, cos.device
            coef_a = torch.full((n, 1), a, dtype=dt, device=dev).masked_fill_(
                tr.brf_free[:, None], 1.0)
            coef_b = torch.full((n, 1), b, dtype=dt, device=dev).masked_fill_(
                tr.brf_free[:, None], 0.0)

        def integrate(blk: dict[str, torch.Tensor], rows: torch.Tensor | None = None
                      ) -> torch.Tensor:
            """``(n, columns, nc)`` ``A Σ W + B cos @ W`` of a block (on ``rows`` if given)."""
            w, w_sum = blk["w"][:, :, ch], blk["w_sum"][:, ch]
            c, ca, cb = (cos, coef_a, coef_b) if rows is None else (
                cos[rows], coef_a[rows], coef_b[rows])
            y = (c @ w.reshape(w.shape[0], -1)).mul_(cb).add_(ca * w_sum.reshape(1, -1))
            return y.view(c.shape[0], w.shape[1], nc)

        j = plan["num_scan"]
        if j:
            out[:, :j] = integrate(plan["scan"]).mul_(tr.throughput[:, None, None])
        if not plan["scenes"]:
            return
        g_obj = tr.throughput * self.diffuser.falloff(tr.alpha) * self.vignetting_factor(tr.hit_xy)
        white = integrate(plan["white"])[:, 0] if plan["white"] is not None else None
        for k, e in enumerate(plan["scenes"]):
            kind, col = e["kind"], j + k
            if kind == "white":
                out[:, col] = white * g_obj[:, None]
            elif kind == "flat":
                ab = e["scene"].abundances(tr.hit_xy).to(dt)  # (n, 1)
                out[:, col] = white * (ab * g_obj[:, None])
            elif kind == "mix":
                ab = e["scene"].abundances(tr.hit_xy).to(dt)  # (n, K)
                rows = torch.nonzero(ab.ne(0).any(1)).squeeze(1)
                if 2 * rows.numel() > n:
                    y = torch.einsum("nk,nkc->nc", ab, integrate(e))
                    out[:, col] = y.mul_(g_obj[:, None])
                else:
                    y = torch.einsum("nk,nkc->nc", ab[rows], integrate(e, rows))
                    out[:, col] = 0.0
                    out[rows, col] = y.mul_(g_obj[rows, None])
            else:  # any other Scene: its reflectance on the fine grid
                refl = e["scene"].reflectance(tr.hit_xy, e["fine"]).to(dt)  # (n, L)
                phi = e["phi_w"][:, ch]
                y = (refl @ phi).mul_(coef_a)
                y = y.add_((refl.mul_(cos) @ phi).mul_(coef_b))
                out[:, col] = y * g_obj[:, None]

    def render_captures(
        self, specs: Sequence[CaptureSpec], progress: Callable | None = None,
        after_calibration: bool = False,
    ) -> list[torch.Tensor | None]:
        """Noise-free relative irradiance of every capture (exposure not applied), one image each.

        Works one band of sensor rows at a time (:meth:`trace_tiles`): the band's rays are
        traced once, their ``cos(2π OPD/λ)`` on the fine grid is evaluated once and shared by all
        captures (:meth:`_shade`), and the band's pixels are written into every image. With
        early mosaicking each ray is shaded in its pixel's CFA colour only. Memory: the images
        plus one band; no ray outlives its band.

        Returns:
            per spec a ``(C, H, W)`` tensor in the render dtype, ``None`` for ``'dark'`` specs
            (no light). ``C = 1`` (each pixel's CFA colour) when :attr:`mosaic_early`, else
            ``C = 3`` (R, G, B). Multiply by an exposure to get the input of
            :meth:`SensorModel.expose`. :attr:`num_rays` counts the rays that reached the
            diffuser.

        ``after_calibration``: the specs are scene captures taken after calibration; the
        :attr:`mismatch` effects that change the device since then (drift, filter temperature,
        scene illuminant) apply to them. The device effects (distortion, filter thickness map,
        monochromator errors, stray light) apply to every render.
        """
        dev, dt = self.device, self.dtype
        h, w = self.sensor_size
        c_out = 1 if self.mosaic_early else 3
        plan = self._shading_plan(specs, after_calibration)
        order = plan["order"]
        out: list[torch.Tensor | None] = [None] * len(specs)
        self.num_rays = 0
        if not order:
            return out
        for i in order:
            out[i] = torch.zeros(c_out, h * w, device=dev, dtype=dt)
        cfa = torch.tensor(cfa_index(self.sensor.cfa_pattern), device=dev).reshape(-1)
        inv_s2 = 1.0 / self.supersample**2
        k = len(order)
        for y0, y1, tr in self.trace_tiles(progress, after_calibration):
            n = tr.num_rays
            self.num_rays += n
            if n == 0:
                continue
            p0, p1 = y0 * w, y1 * w
            acc = torch.zeros(p1 - p0, k * c_out, device=dev, dtype=dt)
            if self.mosaic_early:  # each ray in its pixel's colour
                ch = cfa[(tr.pixel // w % 2) * 2 + tr.pixel % w % 2]
                groups = [(_select_rays(tr, torch.nonzero(ch == c).squeeze(1)), [c])
                          for c in range(3)]
            else:
                groups = [(tr, [0, 1, 2])]
            for sub, chans in groups:
                m = sub.num_rays
                e = torch.empty(m, k, len(chans), device=dev, dtype=dt)
                for r0 in range(0, m, _SHADE_BATCH):  # the (rays, L) work stays in cache
                    r1 = min(m, r0 + _SHADE_BATCH)
                    self._shade(plan, _select_rays(sub, slice(r0, r1)), chans, e[r0:r1])
                acc.index_add_(0, sub.pixel - p0, e.reshape(m, -1))
            acc = acc.mul_(inv_s2).T
            for j, i in enumerate(order):
                out[i][:, p0:p1] = acc[j * c_out:(j + 1) * c_out]
        imgs = [None if o is None else o.reshape(c_out, h, w) for o in out]
        mm = self.mismatch
        if mm.stray_light_fraction > 0:
            cfa_img = None
            if self.mosaic_early:
                yy = torch.arange(h, device=dev)[:, None] % 2
                xx = torch.arange(w, device=dev)[None, :] % 2
                cfa_img = cfa[yy * 2 + xx]
            centre = (float(self.camera.cx), float(self.camera.cy))
            imgs = [None if im is None else stray_light_veil(
                im, mm.stray_light_fraction, mm.stray_light_width, centre, cfa_img)
                for im in imgs]
        return imgs

    def render(
        self, specs: Sequence[CaptureSpec], progress: Callable | None = None,
        after_calibration: bool = False,
    ) -> torch.Tensor:
        """Noise-free relative irradiance of every capture stacked, ``(K, C, H, W)`` (zeros for
        ``'dark'``); see :meth:`render_captures`, which holds no zero images."""
        imgs = self.render_captures(specs, progress, after_calibration)
        h, w = self.sensor_size
        c_out = 1 if self.mosaic_early else 3
        return torch.stack([torch.zeros(c_out, h, w, device=self.device, dtype=self.dtype)
                            if im is None else im for im in imgs]) if imgs else torch.zeros(
            0, c_out, h, w, device=self.device, dtype=self.dtype)

    def exposure_of(self, spec: CaptureSpec) -> float:
        """Relative exposure of a capture (scan frames: ``scan_exposure``, else the sensor's)."""
        return self.scan_exposure if spec.kind == "scan" else self.scene_exposure

    def expose(
        self, irradiance: torch.Tensor, exposure: float, seed: int | None
    ) -> Exposure:
        """Sensor readout of one noise-free irradiance image ``(C, H, W)`` at ``exposure``.

        Noise comes from a generator seeded with ``seed`` (reproducible per capture).
        ``C = 1`` inputs are already mosaicked (see :meth:`render`).
        """
        gen = torch.Generator(device=irradiance.device)
        if seed is None:
            gen.seed()
        else:
            gen.manual_seed(int(seed))
        scale = exposure / self.sensor.exposure if self.sensor.exposure > 0 else 0.0
        return self.sensor.expose(irradiance * scale, generator=gen)

    def noise_free_dn(self, irradiance: torch.Tensor, exposure: float) -> torch.Tensor:
        """Noise-free, unclipped DN above black: ``irradiance · exposure · dn_per_unit``."""
        return irradiance * (exposure * self.dn_per_unit)

    # ------------------------------------------------------------------ ground truth
    def reference_pixels(self) -> torch.Tensor:
        """``(h·w, 2)`` float64 sensor coordinates of the reference frame's pixels (row-major)."""
        return reference_pixel_points(self.layout.reference_bbox, device=self.device)

    def reference_diffuser_points(self, supersample: int = 1) -> torch.Tensor:
        """``(h·w, s², 2)`` diffuser points (mm) of the reference pixels' sub-samples."""
        q = self.reference_pixels()
        offs = subpixel_offsets(supersample, self.device, torch.float64)
        qs = (q[:, None, :] + offs[None]).reshape(-1, 2)
        x = self.layout.sensor_to_diffuser(0, qs)
        return x.reshape(q.shape[0], -1, 2)

    def scene_truth(self, scene: Any) -> torch.Tensor:
        """``(M, h, w)`` float32 reflectance of a scene on the grid in the reference frame,
        averaged over each reference pixel's ``s × s`` sub-samples (as rendered).

        Evaluated in float64 a block of pixels at a time; a linear-mixture scene as
        ``abundances @ endmember_spectra(grid)``.
        """
        x0, y0, w, h = self.layout.reference_bbox
        sc = self._scene_for_render(scene)
        pts = self.reference_diffuser_points(self.supersample)
        n, s2, _ = pts.shape
        wl = self.wavelengths
        out = torch.ones(n, wl.numel(), dtype=torch.float64, device=self.device)
        if sc is not None:
            em = sc.endmember_spectra(wl).to(torch.float64) if has_abundances(sc) else None
            step = max(1, self.chunk // s2)
            for a in range(0, n, step):
                p = pts[a:a + step].reshape(-1, 2)
                r = (sc.abundances(p).to(torch.float64) @ em if em is not None
                     else sc.reflectance(p, wl).to(torch.float64))
                out[a:a + step] = r.reshape(-1, s2, wl.numel()).mean(1)
        return out.T.reshape(-1, h, w).to(torch.float32)

    def ground_truth(self, progress: Callable | None = None) -> dict[str, torch.Tensor]:
        """Everything calibration must recover, in the reference frame ``(h, w)``.

        For reference pixel ``q`` (diffuser point ``X(q)`` of view 0) and view ``v`` the sensor
        position ``layout.reference_to_view(v, q)`` is traced (float64) to get ``α, σ, t``:

        - ``B (V, M, h, w)``: ``t · Tstack(X, α, σ, λ) / Tstack_free`` (``Tstack_free = 1``)
          averaged over the monochromator line at each grid wavelength — what the scan ratio to
          the reference view's BRF-free patch measures. 0 where the view is absent. (Fine-grid
          T via knot-interpolated OPD, ≤ 1e-3 from the exact formula, evaluated in the cosine
          form of :meth:`stack_cosine_form`.)
        - ``phi (3, M)``: :meth:`phi_true` (DN per nm per unit reflectance).
        - ``gain (V, h, w)``: ``D(α_v(q)) · V_obj(X(q))`` (0 where absent).
        - ``view_mask (V, h, w)``: the traced ray lands in view ``v`` and the source point lies in
          the view's triangle at least ``view_inset_px`` from its edges, inside the sensor.
        - ``modulated``: ``view_mask`` and ``X(q)`` outside the BRF-free disk; ``valid (h, w)``:
          ≥ 3 modulated views.
        - ``alpha, sigma (V, h, w)`` rad, ``throughput (V, h, w)``, ``diffuser_xy (h, w, 2)`` mm,
          ``brf_free (h, w)``.

        The truth is the device calibration sees, in the ideal (pinhole) sensor frame: the
        filter's thickness map (:attr:`mismatch`) is in ``B``; lens distortion, stray light, the
        monochromator's errors, the sensor's defects and every after-calibration effect are not.
        """
        lay = self.layout
        x0, y0, w, h = lay.reference_bbox
        H, W = self.sensor_size
        q = self.reference_pixels()
        n = q.shape[0]
        V, M = lay.num_views, self.wavelengths.numel()
        geom = self.geometry
        x_ref = lay.sensor_to_diffuser(0, q)
        free = geom.brf_free_mask(x_ref)
        vig = self.vignetting_factor(x_ref)
        lw = self.scan_line_weights(self.wavelengths)  # (M, L)
        lw_sum = lw.sum(1)
        ca, cb = self.stack_cosine_form()  # Tstack = ca + cb·cos(2π OPD/λ) behind the filter
        B = torch.zeros(V, M, n, dtype=torch.float32, device=self.device)
        gain = torch.zeros(V, n, dtype=torch.float64, device=self.device)
        alpha = torch.full((V, n), float("nan"), dtype=torch.float64, device=self.device)
        sigma = torch.full_like(alpha, float("nan"))
        thr = torch.zeros_like(gain)
        mask = torch.zeros(V, n, dtype=torch.bool, device=self.device)
        it = range(V)
        if progress is not None:
            it = progress(it, desc="ground truth", unit="view")
        inset = self.view_inset_px
        for v in it:
            p = lay.reference_to_view(v, q)
            tr = trace_rays(geom, self.camera, p, sequences=lay.reflection_sequences,
                            chunk=self.chunk)
            inside = points_in_triangle(p, lay.triangles[v], inset)
            inside &= (p[:, 0] >= 0) & (p[:, 0] <= W - 1) & (p[:, 1] >= 0) & (p[:, 1] <= H - 1)
            ok = (tr.view_index == v) & inside
            mask[v] = ok
            idx = torch.nonzero(ok).squeeze(1)
            alpha[v, idx], sigma[v, idx] = tr.alpha[idx], tr.sigma[idx]
            thr[v, idx] = tr.throughput[idx]
            gain[v, idx] = self.diffuser.falloff(tr.alpha[idx]) * vig[idx]
            for a in range(0, idx.numel(), self.chunk):
                j = idx[a:a + self.chunk]
                fj = free[j, None]
                if not self.design.has_brf:  # manakov: the view's filter, disk or not
                    bj = self.view_filters[v][None].to(lw) @ lw.T  # type: ignore[index]
                    B[v, :, j] = (tr.throughput[j, None] * bj).T.to(torch.float32)
                    continue
                scale = (self._opd_scale(x_ref[j], False)
                         if self.mismatch.thickness_map or self.design.kind != "this_system"
                         else None)
                cos = self.retardance_cosine(tr.alpha[j], tr.sigma[j], free[j], scale)
                bj = (cos @ lw.T).mul_(torch.where(fj, 0.0, cb)).add_(
                    torch.where(fj, 1.0, ca) * lw_sum)  # = Tstack @ lw.T
                B[v, :, j] = (tr.throughput[j, None] * bj).T.to(torch.float32)
        modulated = mask & ~free[None]
        valid = modulated.sum(0) >= 3
        return {
            "wavelengths_nm": self.wavelengths.clone(),
            "band_widths_nm": self.band_widths.clone(),
            "B": B.reshape(V, M, h, w),
            "phi": self.phi_true(),
            "gain": gain.reshape(V, h, w).to(torch.float32),
            "view_mask": mask.reshape(V, h, w),
            "modulated": modulated.reshape(V, h, w),
            "valid": valid.reshape(h, w),
            "alpha": alpha.reshape(V, h, w).to(torch.float32),
            "sigma": sigma.reshape(V, h, w).to(torch.float32),
            "throughput": thr.reshape(V, h, w).to(torch.float32),
            "diffuser_xy": x_ref.reshape(h, w, 2).to(torch.float32),
            "brf_free": free.reshape(h, w),
        }

    def forward_model(self, truth: dict[str, torch.Tensor], cube: torch.Tensor) -> torch.Tensor:
        """Reference-frame forward model ``y[v, c] = gain_v · Σ_m B_vm Δλ_m φ_cm s_m``: the
        true :class:`~hsi_torch.forward_model.SensingModel` of every reference pixel (float64).

        Args:
            truth: :meth:`ground_truth` output.
            cube: ``(M, h, w)`` reflectance (e.g. :meth:`scene_truth`).

        Returns:
            ``(V, 3, h, w)`` float64 noise-free DN above black.
        """
        V, M, h, w = truth["B"].shape
        model = SensingModel.from_factors(truth["B"], truth["gain"], truth["phi"],
                                          truth["band_widths_nm"], dtype=torch.float64)
        y = model.A(cube.to(torch.float64).reshape(M, h * w).T)  # (h·w, 3V)
        return y.T.reshape(V, 3, h, w)

    def sample_views(self, image: torch.Tensor) -> torch.Tensor:
        """Bilinearly sample a sensor image ``(C, H, W)`` at every view's source point of every
        reference pixel → ``(V, C, h, w)`` (NaN outside the sensor)."""
        _, _, w, h = self.layout.reference_bbox
        V = self.layout.num_views
        g = view_sample_grid(self.layout.view_homographies.to(self.device),
                             self.layout.reference_bbox, self.sensor_size)  # (1, V, h·w, 2)
        g = g[0].reshape(V, h, w, 2).to(image)
        img = image.unsqueeze(0).expand(V, -1, -1, -1)
        out = torch.nn.functional.grid_sample(img, g, mode="bilinear", padding_mode="zeros",
                                              align_corners=True)
        outside = (g.abs() > 1).any(-1)
        return out.masked_fill(outside[:, None], float("nan"))

    def diffuser_to_reference(self, xy_mm: torch.Tensor) -> torch.Tensor:
        """Diffuser points ``(..., 2)`` mm → reference-frame px (sensor px − bbox origin)."""
        x0, y0, _, _ = self.layout.reference_bbox
        p = apply_homography(self.layout.diffuser_homographies[0], xy_mm.to(torch.float64))
        return p - torch.tensor([x0, y0], dtype=p.dtype, device=p.device)
