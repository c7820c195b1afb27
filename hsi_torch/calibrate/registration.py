"""Inter-view registration from asymmetric circle-grid captures (OpenCV).

Each view-channel of the kaleidoscope is a (possibly mirrored) projective copy of the reference
view. Registration crops each view's triangle from every target image, undoes its mirror parity,
detects an asymmetric circle grid with OpenCV, maps the detections back to sensor pixels,
aggregates the correspondences with the reference view over all target images and fits one
homography per view with RANSAC. Pixel coordinates, the homographies' direction (view v →
reference view, mirrored views with ``det H_v < 0``) and the reference frame follow the
conventions of :mod:`hsi_torch.optics.geometry`, which also applies and warps them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, field

import cv2
import numpy as np
import torch

from hsi_torch.devices import to_numpy
from hsi_torch.optics.geometry import apply_homography, triangle_edge_distance

__all__ = [
    "BlobDetectorParams",
    "GridDetectorConfig",
    "ViewRegistrationReport",
    "RegistrationResult",
    "to_gray_uint8",
    "detect_circle_grid",
    "crop_triangle",
    "detect_in_views",
    "register_views",
    "fit_homography",
    "check_registration",
    "view_orientation",
]


# --- detection


@dataclass
class BlobDetectorParams:
    """Parameters of ``cv2.SimpleBlobDetector`` (areas in px² of the image it runs on).

    The defaults accept dark circles of roughly 1.3…180 px radius on a light background (the
    simulated small prototype's circles have r ≈ 2.8 px, the full-size prototype's ≈ 20 px);
    narrow ``min_area``/``max_area`` to the circle size of your target when clutter is detected
    (real photos with r ≥ 10 px circles and dark specks: ``min_area=20``).
    ``hsi-torch calibrate`` takes these defaults (section ``registration.blob``).
    """

    min_area: float = 5.0
    max_area: float = 1.0e5
    min_circularity: float = 0.6
    min_convexity: float = 0.8
    min_inertia_ratio: float = 0.1
    min_threshold: float = 10.0
    max_threshold: float = 230.0
    threshold_step: float = 10.0
    min_dist_between_blobs: float = 2.0
    min_repeatability: int = 2
    blob_color: int = 0  # 0: dark blobs, 255: light blobs

    def create(self) -> cv2.SimpleBlobDetector:
        """Build the OpenCV detector."""
        p = cv2.SimpleBlobDetector_Params()
        p.filterByArea = True
        p.minArea = float(self.min_area)
        p.maxArea = float(self.max_area)
        p.filterByCircularity = self.min_circularity > 0
        p.minCircularity = float(self.min_circularity)
        p.filterByConvexity = self.min_convexity > 0
        p.minConvexity = float(self.min_convexity)
        p.filterByInertia = self.min_inertia_ratio > 0
        p.minInertiaRatio = float(self.min_inertia_ratio)
        p.minThreshold = float(self.min_threshold)
        p.maxThreshold = float(self.max_threshold)
        p.thresholdStep = float(self.threshold_step)
        p.minDistBetweenBlobs = float(self.min_dist_between_blobs)
        p.minRepeatability = int(self.min_repeatability)
        p.filterByColor = True
        p.blobColor = int(self.blob_color)
        return cv2.SimpleBlobDetector_create(p)


@dataclass
class GridDetectorConfig:
    """Settings of the circle-grid detection.

    Attributes:
        pattern_size: ``(points per row, rows)`` as ``cv2.findCirclesGrid`` expects for
            ``CALIB_CB_ASYMMETRIC_GRID`` (OpenCV's sample target is ``(4, 11)``).
        equalize: ``"none"``, ``"clahe"`` (always equalise) or ``"auto"`` (try the plain image,
            then a CLAHE-equalised one).
        margin_px: margin added around each triangle's bounding box when cropping.
        fill_outside: paint pixels outside the triangle (beyond ``margin_px``) with the bright
            background so neighbouring views cannot contribute blobs.
        ransac_threshold_px: RANSAC inlier threshold of ``cv2.findHomography`` (px).
    """

    pattern_size: tuple[int, int] = (4, 5)
    blob: BlobDetectorParams = field(default_factory=BlobDetectorParams)
    equalize: str = "auto"
    margin_px: int = 6
    fill_outside: bool = True
    ransac_threshold_px: float = 1.0

    def to_dict(self) -> dict:
        d = asdict(self)
        d["pattern_size"] = list(self.pattern_size)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> GridDetectorConfig:
        d = dict(d)
        blob = BlobDetectorParams(**d.pop("blob", {}))
        if "pattern_size" in d:
            d["pattern_size"] = tuple(int(x) for x in d["pattern_size"])
        return cls(blob=blob, **d)


def to_gray_uint8(image: np.ndarray | torch.Tensor) -> np.ndarray:
    """Convert an image to a contiguous ``(H, W)`` uint8 grey image for OpenCV.

    Accepts numpy ``(H, W)``, ``(H, W, 3)`` (OpenCV BGR order is irrelevant for the mean) or a
    torch ``(H, W)`` / ``(3, H, W)`` tensor (channels first, R, G, B). Float inputs are scaled so
    that their 99.5th percentile maps to 255 (linear data of any range).
    """
    if isinstance(image, torch.Tensor):
        t = image.detach().cpu()
        if t.ndim == 3:
            t = t.float().mean(0)
        arr = t.numpy()
    else:
        arr = np.asarray(image)
        if arr.ndim == 3 and arr.dtype == np.uint8 and arr.shape[2] == 3:
            arr = cv2.cvtColor(arr, cv2.COLOR_BGR2GRAY)
        elif arr.ndim == 3:
            arr = arr.astype(np.float32).mean(axis=2)
    if arr.ndim != 2:
        raise ValueError(f"image must be (H, W), (H, W, 3) or (3, H, W); got shape {arr.shape}")
    if arr.dtype == np.uint8:
        return np.ascontiguousarray(arr)
    arr = arr.astype(np.float32)
    hi = float(np.percentile(arr, 99.5)) if arr.size else 1.0
    lo = min(float(arr.min()), 0.0) if arr.size else 0.0
    scale = 255.0 / (hi - lo) if hi > lo else 1.0
    return np.ascontiguousarray(np.clip((arr - lo) * scale, 0, 255).astype(np.uint8))


def detect_circle_grid(
    gray: np.ndarray, config: GridDetectorConfig | None = None
) -> np.ndarray | None:
    """Detect an asymmetric circle grid in one ``(H, W)`` uint8 image (:func:`to_gray_uint8`):
    ``(N, 2)`` float64 centres ``(x, y)`` in OpenCV's grid order (``N = cols·rows``), or
    ``None`` when the grid is not found."""
    cfg = config or GridDetectorConfig()
    if gray.ndim != 2 or gray.dtype != np.uint8:
        raise ValueError(f"gray must be a (H, W) uint8 array, got {gray.shape} {gray.dtype}")
    if cfg.equalize not in ("none", "clahe", "auto"):
        raise ValueError(f"equalize must be 'none', 'clahe' or 'auto', got {cfg.equalize!r}")
    candidates = []
    if cfg.equalize in ("none", "auto"):
        candidates.append(gray)
    if cfg.equalize in ("clahe", "auto"):
        clahe = cv2.createCLAHE(clipLimit=2.0, tileGridSize=(8, 8))
        candidates.append(clahe.apply(gray))
    detector = cfg.blob.create()
    pattern = (int(cfg.pattern_size[0]), int(cfg.pattern_size[1]))
    for img in candidates:
        ok, centres = cv2.findCirclesGrid(
            img, pattern, flags=cv2.CALIB_CB_ASYMMETRIC_GRID, blobDetector=detector
        )
        if ok and centres is not None and len(centres) == pattern[0] * pattern[1]:
            return centres.reshape(-1, 2).astype(np.float64)
    return None


def crop_triangle(
    gray: np.ndarray,
    triangle: np.ndarray,
    parity: int,
    margin_px: int = 6,
    fill_outside: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Crop one view's triangle (plus a margin) and undo its mirror parity.

    Args:
        gray: ``(H, W)`` uint8 sensor image.
        triangle: ``(3, 2)`` vertices ``(x, y)`` in sensor px.
        parity: ``+1`` (even number of reflections) or ``-1`` (mirrored: the crop is flipped
            left-right).
        margin_px: margin around the triangle's bounding box; with ``fill_outside`` pixels farther
            than this from the triangle are painted with the bright background (the 95th
            percentile of the pixels inside), so that neighbouring views contribute no blobs.

    Returns:
        ``(crop, T)``: the crop ``(h_c, w_c)`` uint8 and the ``(3, 3)`` float64 matrix mapping crop
        px → sensor px.
    """
    tri = np.asarray(triangle, dtype=np.float64).reshape(3, 2)
    H, W = gray.shape
    x0 = int(max(np.floor(tri[:, 0].min()) - margin_px, 0))
    y0 = int(max(np.floor(tri[:, 1].min()) - margin_px, 0))
    x1 = int(min(np.ceil(tri[:, 0].max()) + margin_px, W - 1))
    y1 = int(min(np.ceil(tri[:, 1].max()) + margin_px, H - 1))
    if x1 <= x0 or y1 <= y0:
        raise ValueError(f"triangle {tri.tolist()} lies outside the {W}x{H} image")
    crop = gray[y0 : y1 + 1, x0 : x1 + 1].copy()
    if fill_outside:
        ys, xs = np.mgrid[y0 : y1 + 1, x0 : x1 + 1]
        pts = np.stack([xs, ys], axis=-1).reshape(-1, 2).astype(np.float64)
        dist = triangle_edge_distance(pts, tri).reshape(crop.shape)
        inside = dist >= 0
        if inside.any():
            fill = np.percentile(crop[inside], 95)
            crop[dist < -margin_px] = np.uint8(fill)
    T = np.array([[1.0, 0.0, x0], [0.0, 1.0, y0], [0.0, 0.0, 1.0]])
    if int(parity) < 0:
        crop = np.ascontiguousarray(crop[:, ::-1])
        wc = crop.shape[1]
        T = T @ np.array([[-1.0, 0.0, wc - 1.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    elif int(parity) != 1:
        raise ValueError(f"parity must be +1 or -1, got {parity}")
    return crop, T


def detect_in_views(
    image: np.ndarray | torch.Tensor,
    triangles: np.ndarray | torch.Tensor,
    parity: np.ndarray | torch.Tensor | Sequence[int],
    config: GridDetectorConfig | None = None,
) -> list[np.ndarray | None]:
    """Detect the circle grid in every view's triangle (``(V, 3, 2)`` sensor px, parity
    ``(V,)`` ±1) of one sensor image (as :func:`to_gray_uint8` takes it).

    Returns:
        A list of ``V`` entries: ``(N, 2)`` detections in **sensor px** (grid order as returned by
        the detector on the parity-corrected crop), or ``None`` where the grid was not found.
    """
    cfg = config or GridDetectorConfig()
    gray = to_gray_uint8(image)
    tris = to_numpy(triangles).reshape(-1, 3, 2)
    par = to_numpy(parity).reshape(-1)
    if len(par) != len(tris):
        raise ValueError(f"parity has {len(par)} entries but triangles has {len(tris)} views")
    out: list[np.ndarray | None] = []
    for v in range(len(tris)):
        crop, T = crop_triangle(gray, tris[v], int(par[v]), cfg.margin_px, cfg.fill_outside)
        pts = detect_circle_grid(crop, cfg)
        out.append(None if pts is None else apply_homography(T, pts))
    return out


# --- homography estimation


@dataclass
class ViewRegistrationReport:
    """Per-view registration statistics.

    Attributes:
        images_with_detections: target images where the grid was found in this view *and* in
            the reference view.
        points_used, inliers: correspondences given to RANSAC, and its inliers.
        rms_px: reprojection RMS (px, reference sensor) over the inliers.
        reversed_order_images: images whose detections had to be reversed (180° grid ambiguity).
    """

    view: int
    images_with_detections: int
    points_used: int
    inliers: int
    rms_px: float
    reversed_order_images: int = 0

    def __str__(self) -> str:
        return (
            f"view {self.view:2d}: {self.images_with_detections} images, "
            f"{self.inliers}/{self.points_used} inliers, RMS {self.rms_px:.3f} px"
            + (f", {self.reversed_order_images} reversed" if self.reversed_order_images else "")
        )


@dataclass
class RegistrationResult:
    """Output of :func:`register_views`.

    Attributes:
        view_homographies: ``(V, 3, 3)`` float64 tensor, view-v sensor px → reference sensor px.
        reports: one :class:`ViewRegistrationReport` per view.
        residuals: every correspondence of the non-reference views as an ``(N, 6)`` float64
            array of rows ``(view, x_ref, y_ref, dx, dy, inlier)``: the detected grid point in
            the reference view (sensor px) and ``H_v(x_v) − x_ref`` (px); for the diagnostics
            figure (:func:`hsi_torch.calibrate.figures.plot_calibration`).
    """

    view_homographies: torch.Tensor
    reports: list[ViewRegistrationReport]
    residuals: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))

    def __str__(self) -> str:
        return "\n".join(str(r) for r in self.reports)


def _fit_rms(src: np.ndarray, dst: np.ndarray) -> float:
    """RMS error of a least-squares homography src → dst (inf when degenerate)."""
    if len(src) < 4:
        return float("inf")
    H, _ = cv2.findHomography(np.ascontiguousarray(src), np.ascontiguousarray(dst), 0)
    if H is None:
        return float("inf")
    return float(np.sqrt(np.mean(np.sum((apply_homography(H, src) - dst) ** 2, axis=1))))


def fit_homography(
    src: Sequence[np.ndarray],
    dst: Sequence[np.ndarray],
    ransac_threshold_px: float = 1.0,
    check_reversed: bool = True,
    points: list[np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, float, int]:
    """RANSAC homography from grid correspondences aggregated over several images.

    For each image the detections ``src[k]`` may come in the reversed grid order (the 180°
    ambiguity of the detector's ordering): both orders are fitted to ``dst[k]`` by least squares
    and the one with the lower RMS is kept. The chosen pairs of all images are then given to
    ``cv2.findHomography(..., cv2.RANSAC, ransac_threshold_px)``.

    Args:
        src: per image ``(N_k, 2)`` points (source view, px).
        dst: per image ``(N_k, 2)`` corresponding points (destination, px), same order as the
            detector returned them.
        check_reversed: try the reversed order of each ``src[k]``.
        points: if given, receives ``(src (N, 2), dst (N, 2))`` in the chosen order.

    Returns:
        ``(H (3, 3) float64 with H[2, 2] = 1, inliers (ΣN_k,) bool, rms_px over inliers,
        number of images whose order was reversed)``.
    """
    if len(src) != len(dst) or not src:
        raise ValueError(f"need matching non-empty lists of point sets, got {len(src)}/{len(dst)}")
    s_all, d_all, n_rev = [], [], 0
    for s_k, d_k in zip(src, dst, strict=True):
        s_k = np.asarray(s_k, dtype=np.float64).reshape(-1, 2)
        d_k = np.asarray(d_k, dtype=np.float64).reshape(-1, 2)
        if len(s_k) != len(d_k):
            raise ValueError(f"point sets differ in size: {len(s_k)} vs {len(d_k)}")
        if check_reversed and _fit_rms(s_k[::-1], d_k) < _fit_rms(s_k, d_k):
            s_k = s_k[::-1]
            n_rev += 1
        s_all.append(s_k)
        d_all.append(d_k)
    s_np = np.ascontiguousarray(np.concatenate(s_all))
    d_np = np.ascontiguousarray(np.concatenate(d_all))
    if len(s_np) < 4:
        raise ValueError(f"a homography needs at least 4 correspondences, got {len(s_np)}")
    H, inl = cv2.findHomography(s_np, d_np, cv2.RANSAC, float(ransac_threshold_px))
    if H is None:
        raise ValueError("cv2.findHomography found no homography (degenerate correspondences)")
    inl = inl.ravel().astype(bool)
    H = H / H[2, 2]
    if points is not None:
        points += [s_np, d_np]
    res = apply_homography(H, s_np[inl]) - d_np[inl]
    rms = float(np.sqrt(np.mean(np.sum(res**2, axis=1)))) if inl.any() else float("inf")
    return H, inl, rms, n_rev


def register_views(
    images: Sequence[np.ndarray | torch.Tensor],
    triangles: np.ndarray | torch.Tensor,
    parity: np.ndarray | torch.Tensor | Sequence[int],
    config: GridDetectorConfig | None = None,
    reference_view: int = 0,
) -> RegistrationResult:
    """Estimate each view's homography to the reference view from circle-grid target images.

    For every image the grid is detected in each parity-corrected triangle crop
    (:func:`detect_in_views`); each view's correspondences with the reference view over all
    images give ``H_v`` (:func:`fit_homography`: the 180° ordering ambiguity resolved per image,
    then RANSAC with ``config.ransac_threshold_px``); the reference view gets the identity.

    ``images``: target images of one sensor size (as :func:`to_gray_uint8` takes them);
    ``triangles``, ``parity`` as :func:`detect_in_views`.

    Returns:
        :class:`RegistrationResult` with ``(V, 3, 3)`` float64 homographies and per-view reports.

    Raises:
        ValueError: no images, or the grid was found in no image for some view (the message names
            the views).
    """
    cfg = config or GridDetectorConfig()
    if len(images) == 0:
        raise ValueError("register_views needs at least one target image")
    tris = to_numpy(triangles).reshape(-1, 3, 2)
    V = len(tris)
    detections = [detect_in_views(img, tris, parity, cfg) for img in images]
    missing_ref = all(d[reference_view] is None for d in detections)
    if missing_ref:
        raise ValueError(
            f"circle grid {tuple(cfg.pattern_size)} found in none of the {len(images)} images for "
            f"the reference view {reference_view}; check pattern_size (cols, rows) and blob sizes"
        )
    Hs = np.tile(np.eye(3), (V, 1, 1))
    reports: list[ViewRegistrationReport] = []
    failed: list[int] = []
    residuals: list[np.ndarray] = []
    for v in range(V):
        pairs = [
            (det[v], det[reference_view])
            for det in detections
            if det[v] is not None and det[reference_view] is not None
        ]
        if not pairs:
            failed.append(v)
            continue
        if v == reference_view:
            src = np.concatenate([p[0] for p in pairs])
            reports.append(ViewRegistrationReport(v, len(pairs), len(src), len(src), 0.0))
            continue
        pts: list[np.ndarray] = []
        try:
            H, inl, rms, n_rev = fit_homography(
                [p[0] for p in pairs], [p[1] for p in pairs], cfg.ransac_threshold_px,
                points=pts,
            )  # fmt: skip
        except ValueError:
            failed.append(v)
            continue
        Hs[v] = H
        src_v, dst_v = pts
        res = apply_homography(H, src_v) - dst_v
        residuals.append(np.column_stack([np.full(len(dst_v), v), dst_v, res, inl]))
        reports.append(ViewRegistrationReport(v, len(pairs), len(inl), int(inl.sum()), rms, n_rev))
    if failed:
        raise ValueError(
            f"circle grid {tuple(cfg.pattern_size)} found in no image (together with the reference "
            f"view) for view(s) {failed} of {V}; check the triangles, parity, pattern_size and "
            "blob-detector area limits (`hsi-torch layout` proposes triangles and parities "
            "fitted to your white and grid shots)"
        )
    rows = np.concatenate(residuals) if residuals else np.zeros((0, 6))
    return RegistrationResult(torch.from_numpy(Hs), reports, rows.astype(np.float64))


def view_orientation(h: np.ndarray, triangle: np.ndarray) -> int:
    """``+1`` when ``h`` keeps the orientation of ``triangle (3, 2)``, ``−1`` when it reverses
    it (a mirrored view), 0 when degenerate."""
    def area(t: np.ndarray) -> float:
        e1, e2 = t[1] - t[0], t[2] - t[0]
        return float(e1[0] * e2[1] - e1[1] * e2[0])

    tri = np.asarray(triangle, np.float64).reshape(3, 2)
    a0, a1 = area(tri), area(apply_homography(np.asarray(h, np.float64), tri))
    if a0 == 0 or a1 == 0 or not np.isfinite(a1):
        return 0
    return 1 if (a0 > 0) == (a1 > 0) else -1


def check_registration(
    result: RegistrationResult,
    triangles: np.ndarray | torch.Tensor,
    parity: np.ndarray | torch.Tensor | Sequence[int],
    min_inlier_fraction: float = 0.8,
    layout_name: str = "nominal_layout.json",
) -> None:
    """Refuse a registration that a wrong nominal layout produced.

    A view whose parity is flipped in the layout is still "detected" (a mirrored asymmetric grid
    is an asymmetric grid) but in mirrored order, so its homography keeps about a third of the
    points; a view whose homography reverses orientation while its parity says upright (or the
    reverse) contradicts the layout too.

    ``triangles``, ``parity``: as given to :func:`register_views`; ``min_inlier_fraction``: the
    smallest fraction of RANSAC inliers accepted per view.

    Raises:
        ValueError: naming every view at fault, its inliers / parity, and the fix.
    """
    tris = to_numpy(triangles).reshape(-1, 3, 2)
    par = to_numpy(parity).reshape(-1)
    hs = to_numpy(result.view_homographies)
    problems = []
    for r in result.reports:
        v = r.view
        if v == 0:
            continue
        frac = r.inliers / max(1, r.points_used)
        if frac < min_inlier_fraction:
            problems.append(
                f"view {v}: {r.inliers}/{r.points_used} RANSAC inliers ({100 * frac:.0f} %) — "
                f"its parity in {layout_name} is probably flipped (or its triangle is off)"
            )
            continue
        o = view_orientation(hs[v], tris[v])
        if o != 0 and o != int(par[v]):
            problems.append(
                f"view {v}: the grid shows it {'mirrored' if o < 0 else 'upright'} but its "
                f"parity in {layout_name} is {int(par[v]):+d}"
            )
    if problems:
        raise ValueError(
            "; ".join(problems) + f" (limit registration.min_inlier_fraction = "
            f"{min_inlier_fraction:g}); run `hsi-torch layout` to propose a layout fitted to "
            "your white and grid shots, or correct the parity by hand"
        )
