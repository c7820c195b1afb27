"""The camera as a linear operator on whole cubes: ``A`` from a cube to the registered observations.

A calibration bundle defines, for every valid reference-frame pixel ``p``, the sensing matrix
``A_p[(v, c), m] = g_v(p) · B_v(p, λ_m) · Δλ_m · φ^c(λ_m)``
(:class:`~hsi_torch.forward_model.SensingModel`). :class:`CameraOperator` applies it to image-shaped
tensors, the layout of image-restoration libraries (deepinv, a network's input):

* ``A``: cube ``x (N, M, h, w)`` → observations ``y (N, 3V, h, w)``, ``y[:, 3v + c, i, j]`` the
  colour-``c`` sample of view ``v`` at reference pixel ``(i, j)`` (DN above black, on the
  calibration's exposure scale). Observations a pixel does not have (view absent there) and
  pixels outside the valid region are 0; values of ``x`` outside the valid region are ignored.
* ``A_adjoint``: its exact transpose, ``(N, 3V, h, w)`` → ``(N, M, h, w)`` (0 outside the valid
  region).

:meth:`CameraOperator.observe` turns captures into observations in the same layout (with the mask
of the usable ones, so that ``A x ≈ y`` on the mask), :meth:`CameraOperator.noise_variance` gives
their variance, and :meth:`CameraOperator.objective` scores any solver's cube on the pipeline's
scale. ``hsi_torch.recon.deepinv_physics`` wraps this operator as a deepinv ``LinearPhysics``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from hsi_torch.io.bundle import CalibrationBundle
from hsi_torch.recon.frame import observations_from_samples, prepare_input, sample_views
from hsi_torch.recon.sensing import BundleSensing, precompute_sensing
from hsi_torch.recon.spatial import total_variation
from hsi_torch.recon.uncertainty import SensorNoise, observation_variance, sampling_variance_factor

__all__ = ["CameraOperator"]


class CameraOperator:
    """The bundle's forward model on image-shaped tensors (module docstring).

    Args:
        bundle: a :class:`~hsi_torch.io.bundle.CalibrationBundle` or the path of one.
        device, dtype: where the operator's factors live (float32 or float64).

    Attributes:
        sensing: the pipeline's per-bundle :class:`~hsi_torch.recon.sensing.BundleSensing`
            (``β = 0``), shared with the reconstructor's cache.
        valid: ``(h, w)`` bool, the reconstructed pixels; frame_size ``(h, w)``;
        num_bands ``M``, num_obs ``3V``; wavelengths_nm ``(M,)``.
    """

    def __init__(
        self,
        bundle: CalibrationBundle | str,
        *,
        device: torch.device | str | None = None,
        dtype: torch.dtype = torch.float32,
    ) -> None:
        self.sensing: BundleSensing = precompute_sensing(bundle, beta=0.0, device=device,
                                                         dtype=dtype)  # fmt: skip
        s = self.sensing
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        self.dtype = dtype
        self.frame_size: tuple[int, int] = tuple(int(v) for v in s.frame_size)  # type: ignore
        self.num_bands = int(s.num_bands)
        self.num_obs = 3 * int(s.num_views)
        self.wavelengths_nm = s.wavelengths_nm
        self.valid = s.valid.to(self.device)
        self._pix = s.pixel_index.to(self.device)
        self._mask = s.obs_mask.to(self.device)  # (P, O)

    # -- layout ---------------------------------------------------------------------------------
    def _check(self, t: Tensor, channels: int, name: str, floating: bool = True) -> Tensor:
        h, w = self.frame_size
        if not isinstance(t, Tensor) or t.ndim != 4 or tuple(t.shape[1:]) != (channels, h, w):
            shape = tuple(t.shape) if isinstance(t, Tensor) else type(t).__name__
            raise ValueError(f"{name} must have shape (N, {channels}, {h}, {w}) for this bundle, "
                             f"got {shape}")  # fmt: skip
        if floating and not t.is_floating_point():  # an integer result would be truncated
            raise TypeError(f"{name} must be floating point, got {t.dtype}")
        return t

    def _gather(self, t: Tensor) -> Tensor:
        """``(N, C, h, w)`` → ``(N, P, C)`` at the valid pixels."""
        n, c, h, w = t.shape
        return t.reshape(n, c, h * w).index_select(2, self._pix.to(t.device)).transpose(1, 2)

    def _scatter(self, v: Tensor) -> Tensor:
        """``(N, P, C)`` → ``(N, C, h, w)``, 0 outside the valid pixels."""
        n, _, c = v.shape
        h, w = self.frame_size
        out = v.new_zeros((n, c, h * w))
        out.index_copy_(2, self._pix.to(v.device), v.transpose(1, 2))
        return out.reshape(n, c, h, w)

    def mask(self) -> Tensor:
        """``(1, 3V, h, w)`` bool: the observations the bundle has (view present, pixel valid)."""
        return self._scatter(self._mask[None].to(torch.uint8)).bool()

    # -- operators ------------------------------------------------------------------------------
    def A(self, x: Tensor) -> Tensor:
        """Observations ``(N, 3V, h, w)`` of cubes ``x (N, M, h, w)`` (module docstring)."""
        x = self._check(x, self.num_bands, "x")
        n = x.shape[0]
        s = self._gather(x).reshape(-1, self.num_bands)
        model = self.sensing.model
        P = self._pix.numel()
        y = s.new_zeros((0, self.num_obs), dtype=model.dtype)  # a batch of 0 cubes
        if n:
            y = torch.cat([model.A(s[k * P:(k + 1) * P].to(model.dtype)) for k in range(n)])
        y = y.reshape(n, P, self.num_obs) * self._mask
        return self._scatter(y.to(x.dtype))

    def A_adjoint(self, y: Tensor) -> Tensor:
        """``Aᵀ y``: ``(N, 3V, h, w)`` → ``(N, M, h, w)``, the exact transpose of :meth:`A`."""
        y = self._check(y, self.num_obs, "y")
        model = self.sensing.model
        v = (self._gather(y) * self._mask).to(model.dtype)  # (N, P, O)
        x = (torch.stack([model.A_adjoint(vk) for vk in v]) if len(v)
             else v.new_zeros((0, v.shape[1], self.num_bands)))  # (N, P, M)
        return self._scatter(x.to(y.dtype))

    def gram(self) -> Tensor:
        """``(P, M, M)`` per-pixel ``A_pᵀ W_p A_p`` of the valid pixels (``W_p`` the bundle's
        observation mask), in the operator's dtype; computed once."""
        if getattr(self, "_gram", None) is None:
            self._gram = self.sensing.model.gram(self._mask)
        return self._gram

    def prox_l2(self, z: Tensor, y: Tensor, gamma: float | Tensor) -> Tensor:
        """``argmin_x (γ/2)‖A x − y‖² + ½‖x − z‖²`` exactly: per valid pixel
        ``(γ G_p + I)⁻¹ (γ A_pᵀ y_p + z_p)`` (one batched Cholesky solve; ``A`` is block diagonal
        over pixels); ``x = z`` outside the valid region. ``z (N, M, h, w)``, ``y (N, 3V, h, w)``,
        ``γ > 0`` a float or a 0-d tensor."""
        z = self._check(z, self.num_bands, "z")
        g = torch.as_tensor(gamma, dtype=z.dtype, device=z.device)
        G = self.gram().to(z.dtype)
        eye = torch.eye(self.num_bands, dtype=z.dtype, device=z.device)
        L, info = torch.linalg.cholesky_ex(g * G + eye)
        if bool((info != 0).any()):
            raise ValueError(f"prox_l2: gamma = {float(g)} gives a system that is not positive "
                             "definite")  # fmt: skip
        rhs = g * self._gather(self.A_adjoint(y)) + self._gather(z)  # (N, P, M)
        x = torch.cholesky_solve(rhs.permute(1, 2, 0), L).permute(2, 0, 1)  # (N, P, M)
        out = z.clone()
        flat = out.reshape(z.shape[0], self.num_bands, -1)
        flat.index_copy_(2, self._pix.to(z.device), x.transpose(1, 2))
        return out

    # -- measurements -----------------------------------------------------------------------------
    def observe(
        self,
        image: Tensor,
        saturated: Tensor | None = None,
        *,
        exposure_scale: float = 1.0,
        cfa_pattern: str | None = None,
    ) -> tuple[Tensor, Tensor]:
        """Registered observations of captures, in :meth:`A`'s layout.

        Args:
            image: ``(N, 3, H, W)`` linear RGB or ``(N, 1, H, W)`` Bayer (DN above black), the
                bundle's sensor size.
            saturated: same shape, bool (samples left out), or ``None``.
            exposure_scale: ``t_white / t_capture``
                (:func:`~hsi_torch.recon.checks.exposure_scale`).
            cfa_pattern: for a Bayer input (default the bundle's).

        Returns:
            ``y (N, 3V, h, w)`` (0 where not usable) and ``mask (N, 3V, h, w)`` bool.
        """
        if not isinstance(image, torch.Tensor) or image.ndim != 4:
            shape = tuple(image.shape) if isinstance(image, torch.Tensor) else type(image).__name__
            raise ValueError("image must be (N, 3, H, W) linear RGB or (N, 1, H, W) Bayer, got "
                             f"{shape}")  # fmt: skip
        rgb, sat = prepare_input(image, saturated, cfa_pattern or self.sensing.cfa_pattern)
        H, W = self.sensing.sensor_size
        if tuple(rgb.shape[-2:]) != (H, W):
            raise ValueError(f"capture is {tuple(rgb.shape[-2:])} px, the bundle's sensor is "
                             f"{(H, W)}")  # fmt: skip
        samples, sw = sample_views(self.sensing, rgb.to(self.device, self.dtype),
                                   None if sat is None else sat.to(self.device))  # fmt: skip
        y, ok, _ = observations_from_samples(self.sensing, samples, sw)
        y = torch.where(ok, y * exposure_scale, torch.zeros((), dtype=y.dtype, device=y.device))
        return self._scatter(y), self._scatter(ok.to(torch.uint8)).bool()

    def noise_variance(
        self,
        y: Tensor,
        noise: SensorNoise | None = None,
        *,
        exposure_scale: float = 1.0,
        layout: str = "rgb",
        cfa_pattern: str | None = None,
    ) -> Tensor:
        """Variance (DN²) of every observation ``y (N, 3V, h, w)`` from the sensor's noise
        (:func:`~hsi_torch.recon.uncertainty.observation_variance`, the plug-in estimate from the
        values themselves, with the sampling factor of the views' bilinear sampling for ``layout``
        ``"rgb"``, ``"bayer"`` or ``"half"``); 0 outside the bundle's observations."""
        y = self._check(y, self.num_obs, "y", floating=False)
        noise = noise or SensorNoise()
        f = sampling_variance_factor(self.sensing.grid(), self.sensing.sensor_size, layout,
                                     cfa_pattern or self.sensing.cfa_pattern)  # fmt: skip
        yp = self._gather(y)  # (N, P, O)
        var = observation_variance(yp.reshape(-1, self.num_obs), noise, scale=exposure_scale,
                                   sampling_factor=f.to(y.device).repeat(y.shape[0], 1))
        return self._scatter(var.reshape(yp.shape) * self._mask.to(y.dtype))

    # -- objective --------------------------------------------------------------------------------
    def objective(
        self,
        x: Tensor,
        y: Tensor,
        *,
        mask: Tensor | None = None,
        lam: float = 0.0,
        brightness_weight: float = 1.0,
    ) -> Tensor:
        """``‖mask·(A x − y)‖² + λ·TV(x)`` of each cube ``(N,)`` (TV: the spatial mode's vectorial
        TV on the valid grid, :func:`~hsi_torch.recon.spatial.total_variation`)."""
        r = self.A(x) - y
        if mask is not None:
            r = r * mask
        data = r.square().flatten(1).sum(1)
        if lam == 0:
            return data
        return data + lam * total_variation(x, self.valid.to(x.device), brightness_weight)
