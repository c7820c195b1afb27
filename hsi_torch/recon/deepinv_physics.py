"""The camera as a deepinv physics, so that deepinv's solvers and priors run on our captures.

Needs deepinv (``pip install 'hsi-torch[deepinv]'``); this module is the only one that imports
it, and nothing imports this module unless asked.

* :class:`CameraPhysics` — a ``deepinv.physics.LinearPhysics`` of a calibration bundle
  (:class:`~hsi_torch.recon.camera.CameraOperator`: ``A``, its exact adjoint, the data term's
  proximal operator in closed form) with :class:`CameraNoise` as its noise model.
* :class:`CameraNoise` — a ``deepinv.physics.NoiseModel``: Gaussian with the variance of
  :mod:`hsi_torch.recon.uncertainty` (shot, read and quantisation noise, exposure, sampling).
* :class:`BandwiseDenoiser` — a grey-image denoiser (e.g. ``DRUNet`` with ``in_channels=1``) run
  on every band, so that plug-and-play priors trained on grey images apply to cubes.
* :class:`VectorialTVPrior` — a ``deepinv.optim.Prior``: the spatial mode's vectorial TV plus
  ``x ≥ 0`` with its proximal operator, so that deepinv's PGD / FISTA / ADMM / DRS / HQS solve
  the TV mode's problem (deepinv's own ``TVPrior`` is the band-by-band TV).

Scales: ``y`` in DN above black on the calibration's exposure scale (as the pipeline's), ``x``
reflectance. deepinv's ``L2(sigma)`` data term is ``‖A x − y‖² / (2σ²)``: with
``sigma = 1/√2`` it is the pipeline's ``‖A x − y‖²`` and a ``lambda_reg`` of ``λ`` gives the
spatial mode's objective ``‖A x − y‖² + λ·TV(x)`` (:meth:`CameraOperator.objective`).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

try:
    from deepinv.optim import Prior
    from deepinv.physics import LinearPhysics
    from deepinv.physics.noise import NoiseModel
except Exception as exc:  # ImportError, or deepinv's torchvision built for another torch
    raise ImportError(
        "hsi_torch.recon.deepinv_physics needs deepinv (pip install 'hsi-torch[deepinv]'; it "
        f"imports torchvision, which must match the installed torch): {type(exc).__name__}: {exc}"
    ) from exc

from hsi_torch.io.bundle import CalibrationBundle
from hsi_torch.recon.camera import CameraOperator
from hsi_torch.recon.spatial import grid_edges, prox_tv_nonneg, total_variation
from hsi_torch.recon.uncertainty import SensorNoise

__all__ = ["CameraPhysics", "CameraNoise", "VectorialTVPrior", "BandwiseDenoiser", "L2_SIGMA"]

#: ``sigma`` of deepinv's ``L2`` data fidelity that makes it the pipeline's ``‖A x − y‖²``.
L2_SIGMA = 1.0 / math.sqrt(2.0)


class CameraNoise(NoiseModel):
    """Gaussian noise with the sensor's variance of every observation (``y ← y + σ(y)·ε``).

    Args:
        camera: the :class:`CameraOperator` the observations belong to.
        noise: the raw sensor's noise (default :class:`~hsi_torch.recon.uncertainty.SensorNoise`,
            the simulator's sensor).
        exposure_scale: ``t_white / t_capture`` of the captures.
        layout: ``"rgb"``, ``"bayer"`` or ``"half"`` (how the capture was sampled).
        rng: a ``torch.Generator`` (deepinv's convention), or ``None``.
    """

    def __init__(
        self,
        camera: CameraOperator,
        noise: SensorNoise | None = None,
        *,
        exposure_scale: float = 1.0,
        layout: str = "rgb",
        rng: torch.Generator | None = None,
    ) -> None:
        super().__init__(rng=rng)
        self.camera = camera
        self.noise = noise or SensorNoise()
        self.exposure_scale = float(exposure_scale)
        self.layout = layout

    def forward(self, x: Tensor, seed: int | None = None, **kwargs) -> Tensor:  # noqa: ARG002
        """Noisy observations of clean ones ``x (N, 3V, h, w)`` (0 stays 0 where there is no
        observation)."""
        self.rng_manual_seed(seed)
        var = self.camera.noise_variance(x, self.noise, exposure_scale=self.exposure_scale,
                                         layout=self.layout)  # fmt: skip
        # σ = 0 where there is no observation: sqrt's infinite derivative at 0 is kept out of the
        # graph there (a loss through the noisy physics got NaN gradients)
        none = var <= 0
        std = torch.where(none, torch.zeros_like(var), torch.where(none, 1.0, var).sqrt())
        return x + std * self.randn_like(x)


class CameraPhysics(LinearPhysics):
    """The camera of a calibration bundle as a deepinv ``LinearPhysics`` (module docstring).

    Args:
        bundle: a :class:`~hsi_torch.io.bundle.CalibrationBundle` or the path of one.
        noise: the sensor's noise for :class:`CameraNoise` (``None``: the default sensor);
            ``noise_model=`` (any deepinv noise model) replaces it.
        exposure_scale: ``t_white / t_capture`` of the captures (for the noise model).
        device, dtype: of the operator (float32 or float64).
        **kwargs: passed to ``LinearPhysics`` (e.g. ``max_iter``, ``tol`` of its least-squares
            solver).

    Attributes:
        camera: the :class:`CameraOperator` (``observe`` turns a capture into ``y``);
        img_size: ``(M, h, w)``.
    """

    def __init__(
        self,
        bundle: CalibrationBundle | str,
        *,
        noise: SensorNoise | None = None,
        exposure_scale: float = 1.0,
        noise_model: NoiseModel | None = None,
        device: torch.device | str | None = None,
        dtype: torch.dtype = torch.float32,
        **kwargs,
    ) -> None:
        camera = CameraOperator(bundle, device=device, dtype=dtype)
        if noise_model is None:
            noise_model = CameraNoise(camera, noise, exposure_scale=exposure_scale)
        super().__init__(
            img_size=(camera.num_bands, *camera.frame_size), noise_model=noise_model,
            device=camera.device, **kwargs,
        )  # fmt: skip
        self.camera = camera

    def A(self, x: Tensor, **kwargs) -> Tensor:  # noqa: ARG002
        """``(N, M, h, w)`` cube → ``(N, 3V, h, w)`` registered observations."""
        return self.camera.A(x)

    def A_adjoint(self, y: Tensor, **kwargs) -> Tensor:  # noqa: ARG002
        """``(N, 3V, h, w)`` → ``(N, M, h, w)``, the exact transpose of :meth:`A`."""
        return self.camera.A_adjoint(y)

    def prox_l2(self, z: Tensor, y: Tensor, gamma: float | Tensor, *args, **kwargs) -> Tensor:  # noqa: ARG002
        """``argmin_x (γ/2)‖A x − y‖² + ½‖x − z‖²`` in closed form (per-pixel Cholesky solves,
        :meth:`CameraOperator.prox_l2`) instead of deepinv's iterative least squares: ADMM, DRS
        and HQS take exact data steps."""
        if z is None or isinstance(z, (int, float)):
            z = torch.full_like(self.A_adjoint(y), 0.0 if z is None else float(z))
        return self.camera.prox_l2(z, y, gamma)


class VectorialTVPrior(Prior):
    """The spatial mode's TV + non-negativity as a deepinv prior.

    ``g(x) = Σ_{valid grid} ‖K ∇x‖₂`` (all bands in one norm, ``K`` the brightness weighting) and
    ``x ≥ 0``; ``prox(x, gamma)`` = ``argmin_{z ≥ 0} ½‖z − x‖² + gamma·g(z)`` by the fast gradient
    projection on the dual (``inner_iters`` iterations from a zero dual).

    Args:
        valid: ``(h, w)`` bool, the TV graph (the bundle's valid region: ``camera.valid``).
        brightness_weight: ``α ∈ (0, 1]`` (1: plain vectorial TV; the pipeline's default is
            :data:`~hsi_torch.recon.spatial.BRIGHTNESS_WEIGHT`).
        inner_iters: dual iterations of one prox.
    """

    def __init__(self, valid: Tensor, brightness_weight: float = 1.0, inner_iters: int = 200,
                 **kwargs) -> None:  # fmt: skip
        super().__init__(**kwargs)
        self.explicit_prior = True
        self.valid = valid.bool()
        self.brightness_weight = float(brightness_weight)
        self.inner_iters = int(inner_iters)

    def fn(self, x: Tensor, *args, **kwargs) -> Tensor:  # noqa: ARG002
        """``(N,)`` TV of cubes ``x (N, M, h, w)``."""
        return total_variation(x, self.valid.to(x.device), self.brightness_weight)

    def prox(self, x: Tensor, *args, gamma: float = 1.0, **kwargs) -> Tensor:  # noqa: ARG002
        """``argmin_{z ≥ 0} ½‖z − x‖² + gamma·TV(z)`` of each cube ``(N, M, h, w)``; pixels
        outside the valid grid are only projected on ``z ≥ 0``."""
        ex, ey = grid_edges(self.valid.to(x.device))
        out = [prox_tv_nonneg(xk, float(gamma), ex, ey, self.inner_iters,
                              brightness_weight=self.brightness_weight)[0] for xk in x]  # fmt: skip
        return torch.stack(out) if out else x.clamp_min(0)  # a batch of 0 cubes


class BandwiseDenoiser(torch.nn.Module):
    """A single-channel denoiser applied to every band: ``(N, M, h, w)`` → ``(N, M, h, w)``.

    Args:
        denoiser: a module called as ``denoiser(x, sigma)`` on ``(K, 1, h, w)`` images (deepinv's
            denoisers), e.g. ``deepinv.models.DRUNet(1, 1, pretrained="weights.pth")``.
        batch: bands denoised per call (memory).

    Pixels outside ``valid`` (if given) are set to 0 before and after (our cubes are NaN there).
    """

    def __init__(self, denoiser: torch.nn.Module, batch: int = 8,
                 valid: Tensor | None = None) -> None:  # fmt: skip
        super().__init__()
        self.denoiser = denoiser
        self.batch = int(batch)
        self.valid = None if valid is None else valid.bool()

    def forward(self, x: Tensor, sigma: float | Tensor, *args, **kwargs) -> Tensor:  # noqa: ARG002
        n, m, h, w = x.shape
        keep = None if self.valid is None else self.valid.to(x.device)
        if keep is not None:
            x = torch.where(keep, x, torch.zeros((), dtype=x.dtype, device=x.device))
        flat = x.reshape(n * m, 1, h, w)
        out = torch.cat([self.denoiser(flat[i:i + self.batch], sigma)
                         for i in range(0, n * m, self.batch)])  # fmt: skip
        out = out.reshape(n, m, h, w)
        if keep is not None:
            out = torch.where(keep, out, torch.zeros((), dtype=out.dtype, device=out.device))
        return out
