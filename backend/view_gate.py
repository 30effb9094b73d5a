"""The gate on a new view of an admitted landmark: it must reproject within a few pixels of where the predicted pose
sees the landmark, in front of the camera; a view that fails starts a new track segment (backend/segments.py)."""

from __future__ import annotations

import numpy as np

from backend.fixed_lag import OldLandmarks
from backend.keys import L
from backend.landmarks import LandmarkBook
from backend.smoother import Smoother

_MIN_DEPTH_M = 0.05  # a landmark's new view must be at least this far in front of the camera, m
_EXACT_MARGIN = 1e-6  # px and m: the all-at-once reprojection decides only when this far from a threshold


def reprojections(
    book: LandmarkBook, old: OldLandmarks, smoother: Smoother, k: int, ids: np.ndarray, world_T_body: np.ndarray
) -> dict[int, tuple[float, float]]:
    """Landmark id -> (reprojection error px, depth m) of keyframe k's view of it from the predicted pose, for
    every admitted landmark among `ids` that has a position (all at once: one call per landmark cost more)."""
    js, pts, fresh = [], [], []
    for j in ids.tolist():
        if not book.tracks[j].admitted:
            continue
        p = old.position(j)
        if p is None and not smoother.has(L(j)):
            continue
        js.append(j)
        pts.append(p)
        if p is None:
            fresh.append(len(js) - 1)
    if fresh:
        points = smoother.estimate_points([L(js[i]) for i in fresh])
        for i, p in zip(fresh, points, strict=True):
            pts[i] = p
    uv = np.array([book.tracks[j].views[k] for j in js]).reshape(-1, 2)
    err, depth = book.reprojections_px(world_T_body, np.array(pts).reshape(-1, 3), uv)
    return dict(zip(js, zip(err.tolist(), depth.tolist(), strict=True), strict=True))


def consistent(
    book: LandmarkBook,
    old: OldLandmarks,
    smoother: Smoother,
    j: int,
    world_T_body: np.ndarray,
    uv: np.ndarray,
    gate_px: float,
    seen: tuple[float, float],
) -> bool:
    """A new view of landmark j reprojects within `gate_px` from the predicted pose. `seen` is the error and depth
    from `reprojections`; within `_EXACT_MARGIN` of a threshold (or not finite) they are computed again one landmark
    at a time, so the decision is the same to the last bit as it always was."""
    err, depth = seen
    if abs(err - gate_px) > _EXACT_MARGIN and abs(depth - _MIN_DEPTH_M) > _EXACT_MARGIN:
        return depth > _MIN_DEPTH_M and err <= gate_px
    p = old.position(j)
    if p is None:
        p = smoother.estimate_keys([L(j)]).atPoint3(L(j))
    err, depth = book.reprojection_px(world_T_body, p, uv)
    return depth > _MIN_DEPTH_M and err <= gate_px
