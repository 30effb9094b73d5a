"""Grid-bucketed Shi-Tomasi corner detection with sub-pixel refinement.

All coordinates are pixels of the image the corners are detected in (the distorted camera image), x right,
y down, origin at the centre of the top-left pixel (OpenCV's convention).

The minimum-eigenvalue (Shi-Tomasi) response is computed once for the whole image; candidates are its 3x3 local
maxima above `quality_level` times the strongest response. They are accepted strongest first, subject to
(1) a per-cell quota of a `grid_rows` x `grid_cols` grid, so that features spread over the image instead of
piling up on the most textured patch, (2) `min_distance_px` from every existing track and every accepted corner,
(3) `border_px` from the image border. When the quotas leave the target unmet (texture only in part of the
image), a second pass fills up from the remaining candidates without quotas. Accepted corners are then refined to
sub-pixel positions (`refine_subpixel`).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from vio.config import TrackerConfig

_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 20, 0.01)
_MAX_CANDIDATES = 20000  # strongest local maxima considered; more only costs time
_CANDIDATES_PER_SLOT = 8  # candidates examined per corner still wanted (the others fail min_distance first)


def occupancy_mask(shape: tuple[int, int], uv: np.ndarray, radius_px: float, border_px: int) -> np.ndarray:
    """(H, W) uint8 mask: 255 where a new corner may go, 0 near the border and within `radius_px` of any uv."""
    h, w = shape
    mask = np.zeros((h, w), np.uint8)
    b = max(int(border_px), 0)
    if h > 2 * b and w > 2 * b:
        mask[b : h - b, b : w - b] = 255
    r = max(int(round(radius_px)), 1)
    for x, y in np.rint(np.asarray(uv, np.float64).reshape(-1, 2)).astype(np.int64).tolist():
        cv2.circle(mask, (x, y), r, 0, -1)
    return mask


def cell_index(uv: np.ndarray, shape: tuple[int, int], rows: int, cols: int) -> np.ndarray:
    """(N,) int grid-cell index (row-major) of each (N, 2) pixel position."""
    h, w = shape
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    c = np.clip((uv[:, 0] * cols / w).astype(np.int64), 0, cols - 1)
    r = np.clip((uv[:, 1] * rows / h).astype(np.int64), 0, rows - 1)
    return r * cols + c


def _rank_within_cell(cells: np.ndarray, ncells: int) -> np.ndarray:
    """(N,) rank of each candidate among those of its cell, for candidates already sorted strongest first."""
    order = np.argsort(cells, kind="stable")  # stable: keeps strongest-first within each cell
    counts = np.bincount(cells, minlength=ncells)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    rank = np.empty(cells.size, np.int64)
    rank[order] = np.arange(cells.size) - np.repeat(starts, counts)
    return rank


@dataclass(frozen=True)
class CornerResponse:
    """What detection needs from an image alone, before the tracks are known (so it can be computed ahead, in
    another thread: `vio.tracking.images`)."""

    eig: np.ndarray  # (H, W) float32 Shi-Tomasi (minimum eigenvalue) response
    peak: float  # its maximum
    strong: np.ndarray | None  # (H, W) bool: 3x3 local maxima above quality_level * peak (None: no corner at all)


def corner_response(gray: np.ndarray, cfg: TrackerConfig) -> CornerResponse:
    """The Shi-Tomasi response of a grayscale image and its strong local maxima (the candidates before the
    occupancy mask)."""
    eig = cv2.cornerMinEigenVal(gray, blockSize=3, ksize=3)
    peak = float(eig.max())
    if not np.isfinite(peak) or peak <= 1e-7:
        return CornerResponse(eig, peak, None)
    local_max = eig >= cv2.dilate(eig, np.ones((3, 3), np.uint8))
    return CornerResponse(eig, peak, local_max & (eig > cfg.quality_level * peak))


def detect_corners(
    gray: np.ndarray,
    existing_uv: np.ndarray,
    num_wanted: int,
    cfg: TrackerConfig,
    response: CornerResponse | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Detect up to `num_wanted` new corners away from `existing_uv` (N, 2) px (`response`: `corner_response` of
    `gray` when it was computed ahead).

    Returns ((M, 2) float64 px sub-pixel positions, (M,) float64 Shi-Tomasi responses), strongest first within
    each pass. A featureless image gives M = 0.
    """
    empty = np.zeros((0, 2)), np.zeros(0)
    if num_wanted <= 0 or gray.size == 0:
        return empty
    shape = gray.shape[:2]
    response = corner_response(gray, cfg) if response is None else response
    if response.strong is None:
        return empty
    eig = response.eig
    mask = occupancy_mask(shape, existing_uv, cfg.min_distance_px, cfg.border_px)
    cand = response.strong & (mask > 0)
    pts = cv2.findNonZero(cand.view(np.uint8))  # much faster than np.nonzero on a full frame
    if pts is None:
        return empty
    pts = pts.reshape(-1, 2)
    xs, ys = pts[:, 0], pts[:, 1]
    resp = eig[ys, xs]
    order = np.argsort(-resp, kind="stable")[:_MAX_CANDIDATES]
    xs, ys, resp = xs[order], ys[order], resp[order]

    ncells = cfg.grid_rows * cfg.grid_cols
    per_cell = int(np.ceil(cfg.max_features / ncells))
    existing_cells = cell_index(existing_uv, shape, cfg.grid_rows, cfg.grid_cols)
    free = per_cell - np.bincount(existing_cells, minlength=ncells)
    cells = cell_index(np.column_stack([xs, ys]), shape, cfg.grid_rows, cfg.grid_cols)

    r = max(int(round(cfg.min_distance_px)), 1)
    budget = num_wanted + max(2, num_wanted // 10)  # spares for corners that refinement pushes over the border
    taken = np.zeros(xs.size, bool)
    accepted: list[int] = []

    def greedy(order: np.ndarray, quota: bool) -> None:
        for i in order.tolist():
            if len(accepted) >= budget:
                return
            c = cells[i]
            if taken[i] or (quota and free[c] <= 0) or mask[ys[i], xs[i]] == 0:
                continue
            taken[i] = True
            accepted.append(i)
            free[c] -= 1
            cv2.circle(mask, (int(xs[i]), int(ys[i])), r, 0, -1)

    # pass 1: per-cell quotas; only the strongest few candidates of each cell can matter
    rank = _rank_within_cell(cells, ncells)
    greedy(np.flatnonzero(rank < _CANDIDATES_PER_SLOT * np.maximum(free[cells], 0)), quota=True)
    # pass 2: fill up without quotas where texture is concentrated (bounded candidate list)
    if len(accepted) < num_wanted:
        greedy(np.flatnonzero(~taken)[: _CANDIDATES_PER_SLOT * budget], quota=False)
    if not accepted:
        return empty
    idx = np.asarray(accepted)
    uv = np.column_stack([xs[idx], ys[idx]]).astype(np.float64)
    uv = refine_subpixel(gray, uv, int(cfg.subpix_window))
    h, w = shape
    b = cfg.border_px
    inside = (uv[:, 0] >= b) & (uv[:, 0] <= w - 1 - b) & (uv[:, 1] >= b) & (uv[:, 1] <= h - 1 - b)
    return uv[inside][:num_wanted], resp[idx][inside][:num_wanted].astype(np.float64)


def refine_subpixel(gray: np.ndarray, uv: np.ndarray, half_window: int) -> np.ndarray:
    """Sub-pixel corner positions by `cv2.cornerSubPix` in a (2 * half_window + 1)^2 window.

    A corner whose refinement moves more than half the half-window has not converged on a corner (it drifted
    towards the window edge, as happens on blob-like texture); it keeps its integer Shi-Tomasi position.
    `half_window` 0 disables refinement.
    """
    if half_window <= 0 or uv.shape[0] == 0 or min(gray.shape[:2]) <= 2 * half_window + 5:
        return uv
    pts = uv.astype(np.float32).reshape(-1, 1, 2)
    cv2.cornerSubPix(gray, pts, (half_window, half_window), (-1, -1), _SUBPIX_CRITERIA)
    refined = pts.reshape(-1, 2).astype(np.float64)
    converged = np.linalg.norm(refined - uv, axis=1) <= 0.5 * half_window
    return np.where(converged[:, None], refined, uv)
