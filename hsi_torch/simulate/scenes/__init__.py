"""Resolution-independent scenes on the diffuser plane.

A scene is a spectral reflectance field ``r(X, Y, λ)`` on the diffuser plane ``z = 0``, with
``(X, Y)`` in mm in the optics frame of ``docs/architecture.md`` (image ``x`` = ``+X``, image ``y``
= ``+Y``, so ``Y`` grows *downwards* in a rendered image). Any object with

- ``extent``: ``(x_min, x_max, y_min, y_max)`` in mm (the region worth rendering), and
- ``reflectance(xy_mm (N, 2), wavelengths_nm (M,)) -> (N, M)``

is a :class:`Scene`. Results take the device and floating dtype of ``xy_mm``.

Every scene here is also a *linear mixture*: ``reflectance(xy, λ) = abundances(xy) @
endmember_spectra(λ)`` with ``abundances (N, K)`` and ``endmember_spectra (K, M)`` (a ColorChecker
is 25 one-hot patches, a CAVE cube its 31 bands, the bar/circle targets one flat spectrum). The
renderer samples the ``K`` abundance planes on the diffuser and goes to the 2 nm grid with a
``(K, L)`` matrix afterwards (:func:`render_scene_abundances`, :func:`has_abundances`).

Scenes, one module per family: :class:`ColorCheckerScene` (``colorchecker``); :class:`FlatScene`,
:class:`USAF1951Scene`, :class:`CircleGridScene` (OpenCV asymmetric grid) (``targets``, the
spectrally flat ones); :class:`CubeScene` (any cube, e.g. the CAVE scene via
:func:`load_cave_scene`) (``cubes``). ``base`` holds the :class:`Scene` interface and the
sampling: :func:`render_scene_image` samples a scene on a pixel grid. :func:`make_scene` builds
one from a config entry. Every name is importable from this package.
"""

from __future__ import annotations

import math

from hsi_torch.simulate.scenes.base import (
    Extent,
    Scene,
    has_abundances,
    pixel_centres_mm,
    render_scene_abundances,
    render_scene_image,
)
from hsi_torch.simulate.scenes.colorchecker import ColorCheckerScene
from hsi_torch.simulate.scenes.cubes import (
    CAVE_WAVELENGTHS_NM,
    CubeScene,
    load_cave_cube,
    load_cave_scene,
)
from hsi_torch.simulate.scenes.targets import (
    CircleGridScene,
    FlatScene,
    USAF1951Scene,
    USAFElement,
    usaf_frequency,
)

__all__ = [
    "Scene",
    "Extent",
    "ColorCheckerScene",
    "FlatScene",
    "USAF1951Scene",
    "USAFElement",
    "usaf_frequency",
    "CircleGridScene",
    "CubeScene",
    "load_cave_cube",
    "load_cave_scene",
    "render_scene_image",
    "render_scene_abundances",
    "has_abundances",
    "pixel_centres_mm",
    "make_scene",
    "CAVE_WAVELENGTHS_NM",
]


def make_scene(kind: str, **kwargs) -> Scene:
    """Build a scene from a config dict (angles in degrees in keys ending ``_deg``).

    ``kind``: ``'colorchecker'``, ``'white'``/``'flat'``, ``'usaf'``, ``'circle_grid'``,
    ``'cave'``. Other keys go to the scene's constructor; ``rotation_deg``, ``tilt_x_deg``,
    ``tilt_y_deg`` are converted to the ``*_rad`` fields.
    """
    kw = dict(kwargs)
    for k in list(kw):
        if k.endswith("_deg"):
            kw[k[:-4] + "_rad"] = math.radians(float(kw.pop(k)))
    for k in ("center_mm", "translation_mm", "pattern_size", "extent_mm"):
        if k in kw and kw[k] is not None:
            kw[k] = tuple(kw[k])
    kinds = {
        "colorchecker": ColorCheckerScene,
        "white": FlatScene,
        "flat": FlatScene,
        "usaf": USAF1951Scene,
        "circle_grid": CircleGridScene,
        "cave": load_cave_scene,
    }
    if kind not in kinds:
        raise ValueError(f"unknown scene kind {kind!r}; choose from {sorted(kinds)}")
    try:
        return kinds[kind](**kw)
    except TypeError as exc:
        raise TypeError(f"bad parameters for scene {kind!r}: {exc}") from exc
