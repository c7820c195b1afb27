"""Valid reconstruction region: reference-frame pixels seen by enough BRF-modulated views."""

from __future__ import annotations

from dataclasses import dataclass

import torch

__all__ = ["ValidRegionSummary", "valid_region"]


@dataclass
class ValidRegionSummary:
    """Statistics of the valid region.

    Attributes:
        num_valid: number of valid reference-frame pixels.
        min_views: the threshold used (modulated views per pixel).
        union_bbox: ``(x0, y0, w, h)`` bounding box (reference-frame px) of the union of the
            registered views, ``(0, 0, 0, 0)`` when empty.
        bbox_area: ``w · h`` of ``union_bbox``.
        fraction: ``num_valid / bbox_area`` (0 when the box is empty).
        views_per_pixel_max: largest number of modulated views at a pixel.
        views_per_pixel_mean: mean number of modulated views over valid pixels.
    """

    num_valid: int
    min_views: int
    union_bbox: tuple[int, int, int, int]
    bbox_area: int
    fraction: float
    views_per_pixel_max: int
    views_per_pixel_mean: float

    def __str__(self) -> str:
        x0, y0, w, h = self.union_bbox
        return (
            f"valid region: {self.num_valid} px with >= {self.min_views} modulated views = "
            f"{100 * self.fraction:.1f} % of the {w}x{h} bounding box of the registered views "
            f"(at x0={x0}, y0={y0}); views per valid pixel: mean {self.views_per_pixel_mean:.2f}, "
            f"max {self.views_per_pixel_max}"
        )


def valid_region(
    view_masks: torch.Tensor, modulated: torch.Tensor | None = None, min_views: int = 3
) -> tuple[torch.Tensor, ValidRegionSummary]:
    """Pixels with at least ``min_views`` BRF-modulated registered views.

    Args:
        view_masks: ``(V, h, w)`` bool: view v is present (registered, inside its triangle) at the
            reference-frame pixel.
        modulated: ``(V, h, w)`` bool: view v is BRF-modulated there (``False`` on the BRF-free
            patch); ``None`` means every present view is modulated.
        min_views: threshold (3 by default: three views, nine colour observations, per pixel).

    Returns:
        ``(valid (h, w) bool, summary)``.
    """
    if view_masks.ndim != 3:
        raise ValueError(f"view_masks must be (V, h, w), got {tuple(view_masks.shape)}")
    vm = view_masks.to(torch.bool)
    if modulated is not None:
        if modulated.shape != vm.shape:
            raise ValueError(
                f"modulated must have the shape of view_masks {tuple(vm.shape)}, "
                f"got {tuple(modulated.shape)}"
            )
        vm_mod = vm & modulated.to(device=vm.device, dtype=torch.bool)
    else:
        vm_mod = vm
    if min_views < 1:
        raise ValueError(f"min_views must be >= 1, got {min_views}")
    count = vm_mod.sum(0)
    valid = count >= min_views
    union = vm.any(0)
    rows = torch.nonzero(union.any(1)).flatten()
    cols = torch.nonzero(union.any(0)).flatten()
    if rows.numel():
        y0, y1 = int(rows[0]), int(rows[-1])
        x0, x1 = int(cols[0]), int(cols[-1])
        bbox = (x0, y0, x1 - x0 + 1, y1 - y0 + 1)
    else:
        bbox = (0, 0, 0, 0)
    area = bbox[2] * bbox[3]
    n_valid = int(valid.sum())
    mean_views = float(count[valid].float().mean()) if n_valid else 0.0
    summary = ValidRegionSummary(
        num_valid=n_valid,
        min_views=int(min_views),
        union_bbox=bbox,
        bbox_area=area,
        fraction=n_valid / area if area else 0.0,
        views_per_pixel_max=int(count.max()) if count.numel() else 0,
        views_per_pixel_mean=mean_views,
    )
    return valid, summary
