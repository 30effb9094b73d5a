"""Multi-view stereo: one depth map per view from its neighbouring views' pixels (`depth_maps`, `iter_depth_maps`).

Views are undistorted pinhole images with metric poses (`vio.model.views`). For each reference view this module
picks neighbours (optical axes 5-25 deg apart, looking at the same region, spread in direction), limits the work to
the region of interest (the ROI box's pixel window and, per pixel, the depth interval where the ray is inside the
box), and runs one of two matchers on the window:

- "sweep" (default, `vio.model.dense_sweep`): plane-sweep stereo, windowed NCC over 2-4 neighbours, sub-sample
  parabola, minimum-NCC and uniqueness checks;
- "sgbm" (`vio.model.dense_sgbm`): rectified pairs with OpenCV's semi-global matcher and its left-right check,
  the pairs' depths merged by their median.

Depths are z-depths along the reference camera's optical axis (m); NaN where unknown, outside the ROI window, or
outside the ROI box.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Collection, Iterator

import numpy as np

from vio.errors import ConfigError
from vio.geometry import inv_T
from vio.model.dense_common import METHODS, Crop, DenseConfig, gray, roi_bbox, roi_window
from vio.model.dense_sgbm import sgbm_depth
from vio.model.dense_sweep import sweep_depth
from vio.model.parallel import ordered_map
from vio.model.records import DepthMap, Roi, View

log = logging.getLogger(__name__)

__all__ = ["DenseConfig", "depth_maps", "iter_depth_maps", "select_neighbours"]


def select_neighbours(
    views: list[View], roi: Roi | None, config: DenseConfig, usable: list[bool] | None = None
) -> list[list[int]]:
    """Per view, up to `num_neighbours` other views whose optical axes are min..max_angle_deg apart, that see the
    same point (the ROI centre, else the closest point of the two optical axes) inside their image, preferring
    angles near best_angle_deg and baselines in different directions of the reference image. Views not `usable`
    are nobody's neighbour."""
    centres = np.array([v.world_T_cam[:3, 3] for v in views])
    axes = np.array([v.world_T_cam[:3, 2] for v in views])
    cos = np.clip(axes @ axes.T, -1.0, 1.0)
    angle = np.degrees(np.arccos(cos))
    target = None
    if roi is not None:
        target = roi.world_T_support[:3, :3] @ (0.5 * (roi.lo + roi.hi)) + roi.world_T_support[:3, 3]
    out = []
    for i, v in enumerate(views):
        cands = []
        ok = (angle[i] >= config.min_angle_deg) & (angle[i] <= config.max_angle_deg)
        for j in np.flatnonzero(ok & (np.ones(len(views), bool) if usable is None else np.asarray(usable))):
            p = target if target is not None else _axes_meet(centres[i], axes[i], centres[j], axes[j])
            if p is None or not (_sees(v, p) and _sees(views[j], p)):
                continue
            b_cam = v.world_T_cam[:3, :3].T @ (centres[j] - centres[i])
            cands.append((abs(angle[i, j] - config.best_angle_deg), int(j), np.arctan2(b_cam[1], b_cam[0])))
        chosen: list[tuple[int, float]] = []
        for min_sep in (np.radians(60.0), 0.0):  # spread in direction first, then fill up
            for _, j, direction in sorted(cands):
                if len(chosen) >= config.num_neighbours or any(j == c for c, _ in chosen):
                    continue
                sep = [abs(np.angle(np.exp(1j * (direction - d)))) for _, d in chosen]
                if all(s >= min_sep for s in sep):
                    chosen.append((j, direction))
        out.append([j for j, _ in chosen])
    return out


def _axes_meet(c1: np.ndarray, a1: np.ndarray, c2: np.ndarray, a2: np.ndarray) -> np.ndarray | None:
    """Midpoint of the closest points of two optical axes when both lie in front of their cameras, else None."""
    b = a1 @ a2
    d = c2 - c1
    den = 1.0 - b * b
    if den < 1e-9:
        return None
    s = (d @ a1 - b * (d @ a2)) / den
    t = (b * (d @ a1) - d @ a2) / den
    return 0.5 * (c1 + s * a1 + c2 + t * a2) if s > 0 and t > 0 else None


def _sees(view: View, p_world: np.ndarray, border: float = 0.1) -> bool:
    """True when the point is in front of the view and projects inside its image (less a border share)."""
    p = inv_T(view.world_T_cam) @ np.append(p_world, 1.0)
    if p[2] <= 0:
        return False
    u, v, _ = view.K @ (p[:3] / p[2])
    w, h = view.size
    return border * w <= u <= (1 - border) * w and border * h <= v <= (1 - border) * h


def iter_depth_maps(
    views: list[View],
    roi: Roi | None = None,
    config: DenseConfig | None = None,
    references: Collection[int] | None = None,
) -> Iterator[DepthMap]:
    """Depth maps one view at a time (so a caller can fuse each and drop it: a full-size float32 map of a
    2016x1512 still is 12 MB), for the views in `references` (default: all; the others serve as neighbours only).
    Views without neighbours or without the ROI in sight yield nothing."""
    config = config or DenseConfig()
    if config.method not in METHODS:
        raise ConfigError(f"dense method must be one of {', '.join(METHODS)}, got {config.method!r}")
    match = sweep_depth if config.method == "sweep" else sgbm_depth
    boxes = [roi_bbox(v, roi, config.margin_px) for v in views]
    neighbours = select_neighbours(views, roi, config, [b is not None for b in boxes])

    def crop(j: int) -> Crop:  # cut when needed: 120 float32 stills would take 1.5 GB
        x0, y0, x1, y1 = boxes[j]
        v = views[j]
        return Crop(gray(v.image[y0:y1, x0:x1]), np.asarray(v.K, float), np.asarray(v.world_T_cam, float), x0, y0)

    def one(i: int) -> DepthMap | None:
        view = views[i]
        window = None if boxes[i] is None else roi_window(crop(i), roi, config)
        if window is None or not neighbours[i]:
            log.info("view %s: %s, no depth map", view.name, "ROI not seen" if window is None else "no neighbours")
            return None
        start = time.perf_counter()
        depth, score = match(window, [crop(j) for j in neighbours[i]], config)
        x0, y0 = window.crop.x0, window.crop.y0
        w, h = view.size
        ch, cw = depth.shape
        depth_m = np.full((h, w), np.nan, np.float32)
        confidence = np.zeros((h, w), np.float32)
        depth_m[y0 : y0 + ch, x0 : x0 + cw] = depth
        confidence[y0 : y0 + ch, x0 : x0 + cw] = np.where(np.isfinite(depth), score, 0.0)
        log.debug(
            "view %s: %d neighbours, window %dx%d, %d depths, %.2f s",
            view.name,
            len(neighbours[i]),
            cw,
            ch,
            int(np.isfinite(depth).sum()),
            time.perf_counter() - start,
        )
        return DepthMap(i, depth_m, confidence)

    todo = [i for i in range(len(views)) if references is None or i in references]
    for depth_map in ordered_map(one, todo):  # on every core, in order (vio.model.parallel)
        if depth_map is not None:
            yield depth_map


def depth_maps(
    views: list[View],
    roi: Roi | None = None,
    config: DenseConfig | None = None,
    references: Collection[int] | None = None,
) -> list[DepthMap]:
    """All depth maps (see `iter_depth_maps`; prefer it for many full-resolution views)."""
    return list(iter_depth_maps(views, roi, config, references))
