"""Two-view stereo on rectified pairs: OpenCV's semi-global block matcher (`cv2.StereoSGBM`) with its left-right
consistency check, one pair per neighbour, the pairs' depths merged by their median.

A pair is rectified by `cv2.stereoRectify` on the relative pose. The matcher wants matches along rows at smaller
columns in the second image, so the rectified pair is resampled into that canonical layout directly (transposed
when the epipolar lines are vertical, mirrored when the neighbour lies to the left or above), only over the
reference crop and the disparity range of the ROI's depths. Each reference pixel's disparity is read at its exact
rectified position (bilinear; NaN where a neighbour is invalid) and turned into a z-depth along its own ray.
"""

from __future__ import annotations

import cv2
import numpy as np

from vio.geometry import inv_T
from vio.model.dense_common import Crop, DenseConfig, Window, pixel_rays


def _canonical(P: np.ndarray, direction: tuple[bool, bool]) -> np.ndarray:
    """3x3 map from rectified pixels to canonical pixels: (transpose, mirror)."""
    transpose, mirror = direction
    A = np.eye(3)
    if transpose:
        A = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]) @ A
    if mirror:
        A = np.diag([-1.0, 1.0, 1.0]) @ A
    return A @ P[:3, :3]


def _resample(crop: Crop, R_rect: np.ndarray, M: np.ndarray, a0: int, b0: int, w: int, h: int) -> np.ndarray:
    """uint8 canonical image [a0, a0 + w) x [b0, b0 + h) of a crop (M: rectified camera ray -> canonical px)."""
    a, b = np.meshgrid(np.arange(a0, a0 + w, dtype=np.float64), np.arange(b0, b0 + h, dtype=np.float64))
    rays = np.stack([a, b, np.ones_like(a)], axis=-1) @ np.linalg.inv(M).T @ R_rect  # rows: R_rect^T ray
    pix = rays @ crop.K.T
    mx = (pix[..., 0] / pix[..., 2] - crop.x0).astype(np.float32)
    my = (pix[..., 1] / pix[..., 2] - crop.y0).astype(np.float32)
    image = cv2.remap(crop.image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return np.clip(image, 0, 255).astype(np.uint8)


def pair_depth(nbr: Crop, window: Window, config: DenseConfig) -> np.ndarray:
    """(h, w) z-depth of the window's reference crop from one rectified pair (m, NaN where unmatched or
    inconsistent)."""
    ref = window.crop
    h, w = ref.image.shape
    nbr_T_ref = inv_T(nbr.world_T_cam) @ ref.world_T_cam
    size = (int(2 * ref.K[0, 2]) + 1, int(2 * ref.K[1, 2]) + 1)
    no_dist = np.zeros(5)
    R1, R2, P1, P2, *_ = cv2.stereoRectify(
        ref.K, no_dist, nbr.K, no_dist, size, nbr_T_ref[:3, :3], nbr_T_ref[:3, 3:], flags=cv2.CALIB_ZERO_DISPARITY
    )
    transpose = abs(P2[1, 3]) > abs(P2[0, 3])
    tx = P2[1, 3] if transpose else P2[0, 3]
    direction = (transpose, tx > 0)  # tx < 0: the neighbour's match sits at a smaller coordinate
    f_b = abs(tx)  # focal length (px) times baseline (m)
    M1, M2 = _canonical(P1, direction), _canonical(P2, direction)
    rays_ref = pixel_rays(ref.K, ref.x0, ref.y0, ref.x0 + w, ref.y0 + h) @ R1.T  # rectified frame
    can = rays_ref @ M1.T
    ab = can[..., :2] / can[..., 2:]  # canonical coordinates of every reference pixel
    inside = np.isfinite(window.z_near)
    z_rect = np.stack([window.z_near, window.z_far])[:, inside] * rays_ref[inside][:, 2]
    d_lo, d_hi = f_b / z_rect.max() - 2.0, f_b / z_rect.min() + 2.0
    shift = int(np.floor(d_lo))  # the neighbour's image is moved by this many px: disparities start at 0
    n_disp = min(int(np.ceil((d_hi - shift) / 16.0)) * 16, 16 * (config.max_planes // 16))  # near depths cut
    a0, b0 = int(np.floor(ab[..., 0].min())) - n_disp, int(np.floor(ab[..., 1].min()))
    cw, ch = int(np.ceil(ab[..., 0].max())) + 2 - a0, int(np.ceil(ab[..., 1].max())) + 2 - b0
    left = _resample(ref, R1, M1, a0, b0, cw, ch)
    right = _resample(nbr, R2, M2, a0 - shift, b0, cw, ch)
    bs = config.ncc_window_px
    sgbm = cv2.StereoSGBM.create(
        minDisparity=0,
        numDisparities=n_disp,
        blockSize=bs,
        P1=8 * bs * bs,
        P2=32 * bs * bs,
        disp12MaxDiff=1,
        uniquenessRatio=10,
        speckleWindowSize=100,
        speckleRange=2,
        mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    )
    disp = sgbm.compute(left, right).astype(np.float32) / 16.0
    disp[disp <= 0] = np.nan
    mx = (ab[..., 0] - a0).astype(np.float32)
    my = (ab[..., 1] - b0).astype(np.float32)
    d = cv2.remap(disp, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan) + shift
    return (f_b / d / rays_ref[..., 2]).astype(np.float32)


def sgbm_depth(window: Window, nbrs: list[Crop], config: DenseConfig) -> tuple[np.ndarray, np.ndarray]:
    """(h, w) z-depth of the window's reference crop (m; the median of the pairs' depths, NaN where fewer than
    sgbm_min_agree pairs agree with it within 0.2 % or outside the ROI) and the share of pairs that agree."""
    depths = np.stack([pair_depth(nbr, window, config) for nbr in nbrs])
    with np.errstate(invalid="ignore"):
        depths[~((depths >= window.z_near) & (depths <= window.z_far))] = np.nan
    found = np.isfinite(depths)
    depth = np.full(depths.shape[1:], np.nan, np.float32)
    any_found = found.any(axis=0)
    depth[any_found] = np.nanmedian(depths[:, any_found], axis=0)
    with np.errstate(invalid="ignore"):  # pairs that agree with the median within 0.2 % of the depth
        agree = (np.abs(depths - depth) <= 0.002 * depth).sum(axis=0)
    depth[agree < min(config.sgbm_min_agree, len(nbrs))] = np.nan
    return depth, (agree / len(nbrs)).astype(np.float32)
