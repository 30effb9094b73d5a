"""What the dense matchers share: their settings, a view's crop to the region of interest, and each crop pixel's
depth interval inside the ROI box (`vio.model.dense` drives them; `dense_sweep` and `dense_sgbm` match).

Pixel coordinates follow OpenCV (the centre of the top-left pixel is (0, 0)); depths are z-depths along the camera's
optical axis, metres; poses are `world_T_cam` (OpenCV axes) in the run's world.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from vio.geometry import inv_T
from vio.model.records import DepthMap, Roi, View

METHODS = ("sweep", "sgbm")


@dataclass(frozen=True)
class DenseConfig:
    """Multi-view stereo settings (angles deg, lengths px unless stated)."""

    method: str = "sweep"  # "sweep" (plane sweep + NCC) or "sgbm" (rectified pairs, semi-global matching)
    num_neighbours: int = 4  # neighbours per reference view (sweep: averaged; sgbm: one pair each)
    min_angle_deg: float = 5.0  # optical axes of a neighbour at least this far apart
    max_angle_deg: float = 25.0  # ... and at most this far
    best_angle_deg: float = 12.0  # preferred angle between optical axes
    ncc_window_px: int = 7  # NCC window side (sweep) or SGBM block size
    levels: int = 2  # sweep: pyramid levels (1: full-resolution sweep; 2: half-resolution sweep, then refine)
    step_px: float = 1.5  # sweep: largest image shift between consecutive planes in any neighbour (coarsest level)
    max_planes: int = 256  # sweep: at most this many planes (the step grows for wide depth ranges)
    max_sweep_pixels: int = 300_000  # sweep: more levels until the coarsest crop has at most this many pixels
    max_image_pixels: int = 0  # sweep: depth computed at the first level with at most this many pixels (0: full)
    min_ncc: float = 0.5  # sweep: smallest accepted mean NCC at the best depth
    uniqueness: float = 0.05  # sweep: best NCC must beat the best outside +-2 planes by this much (coarsest level)
    smooth_px: int = 21  # sweep: a finer level's seed is the mean inverse depth over this window (full-resolution px)
    fine_radius_px: float = 2.0  # sweep: search radius around the seed, px of shift
    fine_step_px: float = 0.5  # sweep: step of that search, px of shift
    fine_passes: int = 1  # sweep: searches at full resolution, each seeded by the smoothed previous one
    rim_px: int = 4  # sweep: depths this close to a hole wider than 6 rim_px + 3 (a silhouette) are dropped
    sgbm_min_agree: int = 2  # sgbm: pairs whose depth agrees with the median (within 0.2 %)
    margin_px: int = 8  # the ROI window is grown by this much
    depth_range_m: tuple[float, float] = (0.15, 2.0)  # depths searched without a ROI, m


@dataclass(frozen=True)
class Crop:
    """A view's grey image cut to its work area: pixel (u, v) of the full image is (u - x0, v - y0) here."""

    image: np.ndarray  # (h, w) float32 grey levels
    K: np.ndarray  # (3, 3) intrinsics of the full image, px
    world_T_cam: np.ndarray  # (4, 4) camera in world, m
    x0: int  # column of the crop's first pixel in the full image
    y0: int  # row of the crop's first pixel in the full image


@dataclass(frozen=True)
class Window:
    """A reference view's crop with the depth interval (m) of each of its pixels' rays inside the ROI box."""

    crop: Crop
    z_near: np.ndarray  # (h, w) float32 smallest accepted z-depth, m; NaN where the ray misses the ROI
    z_far: np.ndarray  # (h, w) float32 largest accepted z-depth, m


def gray(image: np.ndarray) -> np.ndarray:
    """(H, W) float32 grey levels of a grayscale or BGR uint8 image."""
    g = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    return g.astype(np.float32)


def pixel_rays(K: np.ndarray, x0: int, y0: int, x1: int, y1: int) -> np.ndarray:
    """(h, w, 3) camera rays K^-1 [u, v, 1] (z = 1) of the pixels [x0, x1) x [y0, y1)."""
    u, v = np.meshgrid(np.arange(x0, x1, dtype=np.float64), np.arange(y0, y1, dtype=np.float64))
    x = (u - K[0, 2] - K[0, 1] * (v - K[1, 2]) / K[1, 1]) / K[0, 0]
    return np.stack([x, (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)


def _box_corners(roi: Roi) -> np.ndarray:
    lo, hi = np.asarray(roi.lo, float), np.asarray(roi.hi, float)
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])


def roi_bbox(view: View, roi: Roi | None, margin_px: int) -> tuple[int, int, int, int] | None:
    """Pixel rectangle (x0, y0, x1, y1) holding the ROI box's projection grown by margin_px (x0, y0 even; the
    whole image without a ROI or when the box straddles the camera plane), None when the box is not in sight."""
    w, h = view.size
    if roi is None:
        return 0, 0, w, h
    support_T_cam = inv_T(roi.world_T_support) @ view.world_T_cam
    p_cam = (_box_corners(roi) - support_T_cam[:3, 3]) @ support_T_cam[:3, :3]
    if np.all(p_cam[:, 2] <= 0):
        return None
    if np.any(p_cam[:, 2] <= 1e-3):
        return 0, 0, w, h
    uv = p_cam @ view.K.T
    uv = uv[:, :2] / uv[:, 2:]
    x0, y0 = (max(int(np.floor(c)) - margin_px, 0) // 2 * 2 for c in uv.min(axis=0))
    x1, y1 = (min(int(np.ceil(c)) + margin_px + 1, n) for c, n in zip(uv.max(axis=0), (w, h), strict=True))
    return (x0, y0, x1, y1) if x0 < x1 and y0 < y1 else None


def roi_window(crop: Crop, roi: Roi | None, config: DenseConfig) -> Window | None:
    """Each crop pixel's depth interval inside the ROI box (`depth_range_m` without a ROI); None when no ray of the
    crop meets the box."""
    h, w = crop.image.shape
    if roi is None:
        near, far = config.depth_range_m
        return Window(crop, np.full((h, w), near, np.float32), np.full((h, w), far, np.float32))
    support_T_cam = inv_T(roi.world_T_support) @ crop.world_T_cam
    rays = pixel_rays(crop.K, crop.x0, crop.y0, crop.x0 + w, crop.y0 + h) @ support_T_cam[:3, :3].T
    with np.errstate(divide="ignore", invalid="ignore"):  # slab test; t is the z-depth
        t_lo = (np.asarray(roi.lo, float) - support_T_cam[:3, 3]) / rays
        t_hi = (np.asarray(roi.hi, float) - support_T_cam[:3, 3]) / rays
    t_near = np.maximum(np.nan_to_num(np.minimum(t_lo, t_hi), nan=-np.inf).max(axis=-1), 0.02)
    t_far = np.nan_to_num(np.maximum(t_lo, t_hi), nan=np.inf).min(axis=-1)
    miss = t_far <= t_near
    if miss.all():
        return None
    t_near[miss], t_far[miss] = np.nan, np.nan
    return Window(crop, t_near.astype(np.float32), t_far.astype(np.float32))


def depth_points(view: View, dm: DepthMap, rng: np.random.Generator | None = None, limit: int = 0) -> np.ndarray:
    """World points (N, 3) m of a depth map's known pixels (`view` is its reference); at most `limit` of them,
    drawn at random with `rng`, when limit > 0."""
    vv, uu = np.nonzero(np.isfinite(dm.depth_m))
    if limit > 0 and len(vv) > limit and rng is not None:
        keep = rng.choice(len(vv), limit, replace=False)
        vv, uu = vv[keep], uu[keep]
    z = dm.depth_m[vv, uu].astype(np.float64)
    cam = np.linalg.solve(view.K, np.stack([uu * z, vv * z, z]))
    return cam.T @ view.world_T_cam[:3, :3].T + view.world_T_cam[:3, 3]
