"""Visibility check of the depth maps before fusion: a depth that other views see through is dropped.

Each depth of a reference view is a point X in space. Every other depth map j gives its own evidence about X: X
projects to a pixel of j at depth z_j; if even the nearest depth of j around that pixel (5 x 5) lies more than
`tol_m` beyond z_j, view j sees through X: X is in j's free space (a free-space violation); if j's depth at the
pixel is within `tol_m` of z_j, j supports X; a depth nearer than z_j (X hidden behind j's surface) or no depth says
nothing. A depth with more violations than supports is dropped (the stability rule of visibility-based depth map
fusion, Merrell et al., ICCV 2007, reduced to a keep-or-drop test). It removes what one view's stereo put where the
others see empty space: windows straddling a silhouette give the background beside it the foreground's depth (the
cube's edges bulged by 1-2 mm with true poses), and the occluding contour of a dark cloth matched in one view of the
Middlebury temple left a 6 mm blob beside its base. A correct depth is rarely seen through (only at pixel rounding
on an edge, or where view j's own depths stop short of its silhouette, which the 5 x 5 minimum absorbs; with 3 x 3 a
true edge of seed 102's cube lost depths and bulged by 2.2 mm, against 1.6-1.7 mm with 5 x 5, 7 x 7 or 3 x 3 with
two violations at least) and keeps its place even with no support. The check is one-sided: a depth in front of the
surface is seen through, one behind it is only hidden, so on a surface whose depths scatter by more than `tol_m`
(the table at grazing angles, about 3 mm) it would remove the near half of the scatter; `vio model` fits the support
plane before it (with it first, the temple's plane tilted by 1.0 deg instead of 0.4). Depths are set to NaN in place
(the maps of 120 full-size stills take 1.5 GB; copies would double that).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from vio.model.parallel import ordered_map
from vio.model.records import DepthMap, View

log = logging.getLogger(__name__)

NEAREST_PX = 5  # a violation needs every depth of view j in this square around the pixel to lie beyond the point


@dataclass(frozen=True)
class VisibilityReport:
    """What the visibility check did (model.json `visibility`)."""

    depths: int  # depths checked, all maps
    dropped: int  # depths dropped (more views saw through them than supported them)
    tol_m: float  # the depth tolerance of a support and of a violation, m
    time_s: float


@dataclass(frozen=True)
class _Crop:
    """The part of a depth map that holds depths (maps are full-size, their depths lie in the ROI's window)."""

    x0: int
    y0: int
    depth: np.ndarray  # (h, w) float32 z-depth, NaN unknown
    nearest: np.ndarray  # (h, w) float32 smallest depth in the NEAREST_PX neighbourhood, NaN where none
    K: np.ndarray  # (3, 3) of the crop's pixels
    cam_T_world: np.ndarray  # (4, 4)


def _crop(view: View, dm: DepthMap) -> _Crop | None:
    valid = np.isfinite(dm.depth_m)
    rows, cols = np.flatnonzero(valid.any(axis=1)), np.flatnonzero(valid.any(axis=0))
    if len(rows) == 0:
        return None
    r = NEAREST_PX // 2
    y0, y1, x0, x1 = max(rows[0] - r, 0), rows[-1] + r + 1, max(cols[0] - r, 0), cols[-1] + r + 1
    depth = dm.depth_m[y0:y1, x0:x1]  # a view: nothing is written until every map has been checked
    far = np.where(np.isfinite(depth), depth, np.float32(np.inf))
    nearest = cv2.erode(far, np.ones((NEAREST_PX, NEAREST_PX), np.uint8), borderType=cv2.BORDER_REPLICATE)
    nearest[~np.isfinite(nearest)] = np.nan
    K = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, 1.0]]) @ np.asarray(view.K, float)
    return _Crop(int(x0), int(y0), depth, nearest, K, np.linalg.inv(np.asarray(view.world_T_cam, float)))


def _seen_through(i: int, crops: Sequence[_Crop | None], tol_m: float) -> tuple[np.ndarray, np.ndarray] | None:
    """(rows, columns) in crop i's pixels of the depths with more violations than supports, or None."""
    ci = crops[i]
    if ci is None:
        return None
    r, c = np.nonzero(np.isfinite(ci.depth))
    z = ci.depth[r, c]
    K = ci.K
    pts = np.stack([(c - K[0, 2]) / K[0, 0] * z, (r - K[1, 2]) / K[1, 1] * z, z]).astype(np.float32)
    world_T_cam = np.linalg.inv(ci.cam_T_world)
    support = np.zeros(len(z), np.int16)
    violate = np.zeros(len(z), np.int16)
    tol = np.float32(tol_m)
    for j, cj in enumerate(crops):
        if j == i or cj is None:
            continue
        T = (cj.cam_T_world @ world_T_cam).astype(np.float32)
        x, y, zj = (T[k, :3] @ pts + T[k, 3] for k in range(3))
        front = zj > 1e-3
        inv = np.float32(1.0) / np.where(front, zj, np.float32(1.0))
        u = np.rint(x * inv * np.float32(cj.K[0, 0]) + np.float32(cj.K[0, 2])).astype(np.int32)
        v = np.rint(y * inv * np.float32(cj.K[1, 1]) + np.float32(cj.K[1, 2])).astype(np.int32)
        h, w = cj.depth.shape
        idx = np.flatnonzero(front & (u >= 0) & (u < w) & (v >= 0) & (v < h))
        if len(idx) == 0:
            continue
        zz = zj[idx]
        vi, ui = v[idx], u[idx]
        violate[idx] += cj.nearest[vi, ui] > zz + tol  # NaN (no depth around): False
        support[idx] += np.abs(cj.depth[vi, ui] - zz) <= tol
    bad = violate > support
    return r[bad], c[bad]


def visibility_filter(views: Sequence[View], maps: Sequence[DepthMap], tol_m: float) -> VisibilityReport:
    """Drop (set to NaN, in place) the depths of `maps` that more of the other maps see through than support;
    `tol_m` is the depth tolerance of both tests (the fusion's truncation distance). See the module docstring."""
    t0 = time.perf_counter()
    crops = [_crop(views[dm.view], dm) for dm in maps]
    total = sum(0 if c is None else int(np.isfinite(c.depth).sum()) for c in crops)
    found = list(ordered_map(lambda i: _seen_through(i, crops, tol_m), range(len(maps))))
    dropped = 0
    for dm, crop, bad in zip(maps, crops, found, strict=True):
        if crop is None or bad is None or len(bad[0]) == 0:
            continue
        dm.depth_m[bad[0] + crop.y0, bad[1] + crop.x0] = np.nan
        dropped += len(bad[0])
    report = VisibilityReport(total, dropped, float(tol_m), time.perf_counter() - t0)
    log.info(
        "visibility: %d of %d depths seen through by other views, dropped (%.2f %%), %.1f s",
        dropped,
        total,
        100.0 * dropped / max(total, 1),
        report.time_s,
    )
    return report
