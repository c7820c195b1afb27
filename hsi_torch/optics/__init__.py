"""Optics of the virtual prototype: birefringent filter, tapered kaleidoscope, view layout, and
the plane geometry (homographies, triangles, view warping) every later stage shares.

See ``docs/architecture.md`` for the coordinate conventions and ``docs/optics.md`` for the
physics and default numbers.
"""

from .birefringence import (
    MATERIALS,
    POLARIZER_PRESETS,
    BRFConfig,
    UniaxialMaterial,
    get_material,
    polarizer_transmittance,
    refractive_indices,
    sellmeier_index,
    uniaxial_opd,
    uniaxial_opd_small_angle,
)
from .designs import DESIGN_KINDS, PrototypeDesign, gaussian_bandpass
from .geometry import (
    apply_homography,
    points_in_triangle,
    reference_to_source_matrices,
    triangle_edge_distance,
    view_masks,
    view_sample_grid,
    warp_views,
)
from .kaleidoscope import (
    DEFAULT_CAMERA,
    DEFAULT_GEOMETRY,
    FULL_CAMERA,
    CameraModel,
    KaleidoscopeGeometry,
    RayTrace,
    diffuser_to_sensor_homography,
    enumerate_sequences,
    mirror_planes,
    reflection_isometry,
    sequence_codes,
    trace_rays,
    trace_sensor,
)
from .layout import (
    ViewLayout,
    brf_free_mask,
    build_view_layout,
    fit_homography_dlt,
)

__all__ = [
    "MATERIALS",
    "POLARIZER_PRESETS",
    "BRFConfig",
    "UniaxialMaterial",
    "get_material",
    "polarizer_transmittance",
    "refractive_indices",
    "sellmeier_index",
    "uniaxial_opd",
    "uniaxial_opd_small_angle",
    "DESIGN_KINDS",
    "PrototypeDesign",
    "gaussian_bandpass",
    "DEFAULT_CAMERA",
    "DEFAULT_GEOMETRY",
    "FULL_CAMERA",
    "CameraModel",
    "KaleidoscopeGeometry",
    "RayTrace",
    "diffuser_to_sensor_homography",
    "enumerate_sequences",
    "mirror_planes",
    "reflection_isometry",
    "sequence_codes",
    "trace_rays",
    "trace_sensor",
    "apply_homography",
    "points_in_triangle",
    "reference_to_source_matrices",
    "triangle_edge_distance",
    "view_masks",
    "view_sample_grid",
    "warp_views",
    "ViewLayout",
    "brf_free_mask",
    "build_view_layout",
    "fit_homography_dlt",
]
