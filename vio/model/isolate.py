"""Isolate the part: the support plane it stands on (RANSAC) and the region of interest around it.

World is the run's world frame (metres). The support frame has its origin on the plane below the point the cameras
look at, z along the plane's upward normal, and x, y along the sides of the part's footprint (minimum-area
rectangle of the cluster of points above the plane), so a box-like part is axis-aligned in the fusion grid.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

import cv2
import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from vio.errors import ModelError
from vio.model.dense_common import depth_points
from vio.model.records import DepthMap, Roi, SupportPlane, View

log = logging.getLogger(__name__)

_MIN_POINTS = 50  # fewer points than this cannot give a plane or a part
_CLOSE_M = 5e-3  # the footprint's closing radius
# table points around the part that refit the support plane: their mean height's standard error at the table
# depth's 3 mm spread is 0.13 mm at 500 (a 90 x 70 mm part leaves 1,700-2,000 in its margin, a 76 mm cube 9,000-18,000)
_MIN_TABLE_POINTS = 500
_PROBE = 200  # points nearest the look-at point that set the cluster's cell size: a run's landmarks put 300-400 on
# a 76 mm cube, so 2000 reached into the table's haze (landmarks 8-30 mm above it) and gave 0.19-0.25 m cells
# that joined the table to the part (60 s orbits, seeds 101 and 102: 1.4 x 1.1 m regions; 200: 0.10 x 0.10 m)


def support_plane(
    points_world: np.ndarray,
    up_hint: np.ndarray,
    rng: np.random.Generator,
    threshold_m: float = 1e-3,
    iterations: int = 1000,
    max_tilt_deg: float = 45.0,
    sample_size: int = 4000,
) -> SupportPlane:
    """The plane with the most points within `threshold_m` (RANSAC), refitted by least squares on its inliers.

    points_world (N, 3) m; up_hint (3,) a direction roughly up (gravity's opposite, or the mean camera position
    minus the points' centroid): planes tilted more than `max_tilt_deg` from it are not candidates, and the normal
    returned points to its side. Hypotheses are scored on a random subset of `sample_size` points.
    Raises ModelError when no plane has enough inliers.
    """
    pts = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    up = np.asarray(up_hint, dtype=np.float64)
    if len(pts) < _MIN_POINTS or not np.linalg.norm(up) > 0:
        raise ModelError(f"no support plane: {len(pts)} points (need {_MIN_POINTS}) or no up direction")
    up = up / np.linalg.norm(up)
    sub = pts[rng.choice(len(pts), min(sample_size, len(pts)), replace=False)]
    tri = sub[rng.integers(0, len(sub), (iterations, 3))]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(n, axis=1)
    ok = length > 1e-12
    n = n[ok] / length[ok, None]
    n *= np.sign(n @ up)[:, None] + (n @ up == 0)[:, None]
    keep = n @ up >= np.cos(np.radians(max_tilt_deg))
    n, d = n[keep], np.einsum("ij,ij->i", n[keep], tri[ok][keep, 0])
    if len(n) == 0:
        raise ModelError(f"no support plane within {max_tilt_deg:g} deg of the up direction")
    best = 0
    best_count = -1
    for start in range(0, len(n), 256):  # (256, sample) distance blocks
        counts = (np.abs(sub @ n[start : start + 256].T - d[start : start + 256]) < threshold_m).sum(axis=0)
        if counts.max() > best_count:
            best, best_count = start + int(counts.argmax()), int(counts.max())
    normal, offset = n[best], d[best]
    for _ in range(3):  # least-squares refit on the inliers of the current plane
        inliers = pts[np.abs(pts @ normal - offset) < threshold_m]
        if len(inliers) < 3:
            break
        centroid = inliers.mean(axis=0)
        normal = np.linalg.svd(inliers - centroid, full_matrices=False)[2][2]
        normal = normal if normal @ up >= 0 else -normal
        offset = float(normal @ centroid)
    resid = pts @ normal - offset
    inl = np.abs(resid) < threshold_m
    if inl.sum() < max(_MIN_POINTS, 0.02 * len(pts)):
        raise ModelError(f"no support plane: the best plane has only {int(inl.sum())} of {len(pts)} points")
    rms = float(np.sqrt(np.mean(resid[inl] ** 2)))
    log.info(
        "support plane: normal %s, d %.4f m, %d inliers, rms %.3f mm", normal.round(4), offset, inl.sum(), rms * 1e3
    )
    return SupportPlane(normal=normal, d_m=float(offset), inlier_rms_m=rms)


def support_plane_from_depth(
    points_world: np.ndarray,
    views: Sequence[View],
    up_world: np.ndarray | None,
    rng: np.random.Generator,
    max_below: float = 0.05,
) -> SupportPlane:
    """The support plane from a first (coarse, noisy) depth pass, which sees the table little and at grazing angles.

    Points (N, 3) world m. `up_world` is the world's up when known (a run's world is gravity-aligned): RANSAC
    within 10 deg of it; else up is guessed from the cameras (they look down at the part: mean camera centre minus
    the look-at point) and RANSAC within 30 deg. The plane is accepted only when at most `max_below` of the points
    near the part (within 0.3 x the cameras' median horizontal distance from the look-at point) lie more than
    3 mm below it under the part (`_below_under_part`; a cloth draping lower around it is no objection): a part
    stands on its support. Otherwise, with a known up, the plane is the horizontal one under
    those points (the lowest 1 mm height slice holding a fifth of their typical density). Raises ModelError when
    neither gives a plane."""
    target = look_at_point(views)
    centres = np.array([v.world_T_cam[:3, 3] for v in views])
    known = up_world is not None
    up = np.asarray(up_world, float) if known else centres.mean(axis=0) - target
    up = up / max(float(np.linalg.norm(up)), 1e-12)
    pts = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    flat = lambda p: p - np.outer((p - target) @ up, up)  # noqa: E731  projection on the plane through target
    radius = 0.3 * float(np.median(np.linalg.norm(flat(centres) - target, axis=1)))
    near = pts[np.linalg.norm(flat(pts) - target, axis=1) < radius]
    if len(near) < _MIN_POINTS:
        raise ModelError(f"no support plane: {len(near)} depth points near where the cameras look")
    try:
        plane = support_plane(pts, up, rng, max_tilt_deg=10.0 if known else 30.0)
        below = _below_under_part(plane, near)
        if below <= max_below:
            return plane
        reason = f"{100 * below:.0f} % of the part's points below the RANSAC plane"
    except ModelError as exc:
        reason = str(exc)
    if not known:
        raise ModelError(f"no support plane from the first depth pass ({reason})")
    h = near @ up
    lo, hi = np.percentile(h, [10.0, 90.0])
    counts, edges = np.histogram(h, bins=np.arange(h.min(), h.max() + 2e-3, 1e-3))
    bulk = np.median(counts[(edges[:-1] >= lo) & (edges[:-1] <= hi)])
    d = float(edges[np.argmax(counts >= 0.2 * bulk)])  # the lowest 1 mm slice as dense as a fifth of the bulk
    log.info("support plane: horizontal under the part's points at %.4f m (%s)", d, reason)
    resid = near @ up - d
    rms = float(np.sqrt(np.mean(resid[np.abs(resid) < 1e-3] ** 2))) if (np.abs(resid) < 1e-3).any() else 0.0
    return SupportPlane(normal=up, d_m=d, inlier_rms_m=rms)


def _below_under_part(plane: SupportPlane, points: np.ndarray, cell_m: float = 5e-3, body_m: float = 0.01) -> float:
    """Share of the points under the part that lie more than 3 mm below the plane. Under the part: in the cells
    (`cell_m`, on the plane, grown by one) of the points standing more than `body_m` above it. A plane through the
    middle of the part has the part's lower points below it there; the true support only noise (the Middlebury
    temple's cloth drapes lower around the temple: 9 % of all the points near it lie below its plane)."""
    T = _support_frame(plane, points.mean(axis=0), np.array([1.0, 0.0, 0.0]))
    local = (points - T[:3, 3]) @ T[:3, :3]
    uv, h = local[:, :2], local[:, 2]
    body = h > body_m
    if body.sum() < _MIN_POINTS:
        return float(np.mean(h < -3e-3))
    lo = uv.min(axis=0)
    ij = ((uv - lo) / cell_m).astype(int)
    grid = np.zeros(ij.max(axis=0) + 1, bool)
    grid[ij[body, 0], ij[body, 1]] = True
    grid = ndimage.binary_dilation(grid)
    under = grid[ij[:, 0], ij[:, 1]]
    return float(np.mean(h[under] < -3e-3))


def look_at_point(views: Sequence[View]) -> np.ndarray:
    """(3,) world point closest (least squares) to all the views' optical axes, m."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for view in views:
        axis, centre = view.world_T_cam[:3, 2], view.world_T_cam[:3, 3]
        P = np.eye(3) - np.outer(axis, axis)
        A += P
        b += P @ centre
    if len(views) == 0:
        raise ModelError("no views to find where the cameras look")
    return np.linalg.lstsq(A + 1e-9 * np.eye(3), b, rcond=None)[0]


def _support_frame(plane: SupportPlane, origin_world: np.ndarray, x_dir: np.ndarray) -> np.ndarray:
    """(4, 4) world_T_support: origin on the plane below origin_world, z the normal, x along x_dir in the plane."""
    z = plane.normal
    x = x_dir - (x_dir @ z) * z
    if np.linalg.norm(x) < 1e-9:  # x_dir along the normal: any direction in the plane
        x = np.eye(3)[int(np.argmin(np.abs(z)))] - z * z[int(np.argmin(np.abs(z)))]
    x = x / np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    T[:3, 3] = origin_world - plane.height(origin_world) * z
    return T


def _footprint(local: np.ndarray, cell_m: float, min_points: int, gap_cells: float = 3.0) -> np.ndarray:
    """Mask of the points (N, 3) in a support frame whose origin lies under the part: the part standing there.

    Seen from above, a part's points crowd its footprint (a cube's top and its sides land on one square) while a
    table's stray points are thin: cells of `cell_m` on the plane holding, with their 8 neighbours, at least
    `min_points` points, closed over gaps of about 1 cm (sparse patches of a face: with 3.5 mm cells a cube's
    footprint fell apart on seed 103 with known positions; a fixed 4-cell closing joined a first depth pass's
    table noise over a metre with 8.7 mm cells), 8-connected, the component nearest the origin. In
    height, the part is the lowest run of its points without a gap wider than `gap_cells` cells (points floating
    above it are not the part)."""
    ij = np.floor(local[:, :2] / cell_m).astype(np.int64)
    lo = ij.min(axis=0)
    ij -= lo
    counts = np.zeros(tuple(ij.max(axis=0) + 1), np.float32)
    np.add.at(counts, (ij[:, 0], ij[:, 1]), 1.0)
    occupied = (cv2.boxFilter(counts, -1, (3, 3), normalize=False) >= min_points - 0.5).astype(np.uint8)
    k = 2 * int(np.ceil(_CLOSE_M / cell_m)) + 1  # closes gaps of about 2 _CLOSE_M
    occupied = cv2.morphologyEx(occupied, cv2.MORPH_CLOSE, np.ones((k, k), np.uint8))
    _, labels = cv2.connectedComponents(occupied, connectivity=8)
    cells = np.argwhere(labels > 0)
    if len(cells) == 0:
        return np.zeros(len(local), bool)
    nearest = cells[np.argmin(np.linalg.norm(cells + 0.5 + lo, axis=1))]
    member = labels[ij[:, 0], ij[:, 1]] == labels[nearest[0], nearest[1]]
    h = np.sort(local[member, 2])
    gaps = np.flatnonzero(np.diff(h) > gap_cells * cell_m)
    return member & (local[:, 2] <= (h[gaps[0]] if len(gaps) else h[-1]))


def haze_height(plane: SupportPlane, points_world: np.ndarray, sigmas: float = 3.0, band_m: float = 0.05) -> float:
    """`sigmas` robust standard deviations (1.4826 MAD) of the heights of the points within `band_m` of the plane,
    m: how high a run's table landmarks scatter (6-7 mm on 60 s orbits, so that 3 sigmas is 17-20 mm)."""
    h = plane.height(np.asarray(points_world, dtype=np.float64).reshape(-1, 3))
    h = h[np.abs(h) < band_m]
    return sigmas * 1.4826 * float(np.median(np.abs(h - np.median(h)))) if len(h) else 0.0


def _footprint_angle(local: np.ndarray, neighbours: int = 12) -> float:
    """Angle (rad, in the plane of a support frame) of the footprint's sides from points (N, 3) in that frame.

    The normals of the side faces (local PCA of `neighbours` points; steeper than 70 deg) vote for one of four
    directions 90 deg apart (mean of exp(4i angle)); without a clear vote (a round part), the minimum-area
    rectangle of the points decides."""
    sub = local[:: max(1, len(local) // 20000)]
    if len(sub) > neighbours:
        nn = cKDTree(sub).query(sub, k=neighbours)[1]
        nb = sub[nn] - sub[nn].mean(axis=1, keepdims=True)
        values, vectors = np.linalg.eigh(np.einsum("nki,nkj->nij", nb, nb))
        n = vectors[:, :, 0]
        side = (np.abs(n[:, 2]) < np.cos(np.radians(20.0))) & (values[:, 0] < 0.1 * values[:, 1])
        vote = np.exp(4j * np.arctan2(n[side, 1], n[side, 0])).mean() if side.sum() >= 50 else 0.0
        if abs(vote) > 0.5:
            return float(np.angle(vote) / 4.0)
    return float(np.radians(cv2.minAreaRect(local[:, :2].astype(np.float32))[2]))


def region_of_interest(
    plane: SupportPlane | None,
    views: Sequence[View],
    points_world: np.ndarray,
    margin_m: float = 0.01,
    user_box: np.ndarray | None = None,
    min_height_m: float = 1e-3,
    cell_m: float | None = None,
    min_points: int = 3,
) -> Roi:
    """The box around the part in the support frame: the points above the plane that crowd the footprint nearest to
    where the cameras look (`look_at_point`), their extent plus `margin_m` (below the plane too).

    The part: points from `min_height_m` up, their footprint on the plane in cells of `cell_m` (`_footprint`:
    cells holding with their neighbours >= `min_points` points, the connected piece nearest the look-at point, the
    lowest run of heights without a wide gap; cell_m None: 2.5 times the median distance on the plane to the
    `min_points`-th neighbour among the `_PROBE` points nearest to the look-at point, at least 2 mm). A footprint,
    not 3D clusters: a run's landmarks on a part's sides are sparse (in 3D, a cube fell apart into its faces and
    the region took one side, seed 104 of the 60 s orbit), but seen from above they all land on the part.

    `user_box` (2, 3) world min/max corners replaces the cluster (the support
    frame then has x along the world x; without a plane, it has the world's axes and its origin at the centre of
    the box's bottom). Raises ModelError when no part is found, or without both a plane and a user box.
    """
    if user_box is not None:
        box = np.asarray(user_box, dtype=np.float64).reshape(2, 3)
        if plane is None:
            T = np.eye(4)
            T[:3, 3] = [0.5 * (box[0, 0] + box[1, 0]), 0.5 * (box[0, 1] + box[1, 1]), box[:, 2].min()]
        else:
            T = _support_frame(plane, look_at_point(views), np.array([1.0, 0.0, 0.0]))
        corners = np.array([[box[(i >> k) & 1, k] for k in range(3)] for i in range(8)])
        local = (corners - T[:3, 3]) @ T[:3, :3]
        return Roi(T, local.min(axis=0), local.max(axis=0))
    if plane is None:
        raise ModelError("no support plane and no --roi box: cannot isolate the part")
    target = look_at_point(views)
    pts = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    above = pts[plane.height(pts) >= min_height_m]
    if len(above) < _MIN_POINTS:
        raise ModelError(f"no part found: only {len(above)} points stand {1e3 * min_height_m:g} mm above the plane")
    T0 = _support_frame(plane, target, np.array([1.0, 0.0, 0.0]))  # any in-plane x first
    above = (above - T0[:3, 3]) @ T0[:3, :3]
    if cell_m is None:  # footprint cells that hold min_points points: 2.5 x the k-th neighbour distance on the plane
        near_target = np.linalg.norm(above[:, :2], axis=1)  # among the points nearest the look-at point, few
        probe = above[np.argpartition(near_target, min(_PROBE, len(above) - 1))[:_PROBE]]  # enough to be the part
        knn = cKDTree(above[:, :2]).query(probe[:, :2], k=min_points + 1)[0][:, -1]
        cell_m = float(max(2.5 * np.median(knn), 2e-3))
    local0 = above[_footprint(above, cell_m, min_points)]
    if len(local0) < min_points:
        raise ModelError("no part found: the points above the plane are too sparse to form a cluster")
    a = _footprint_angle(local0)
    xy = local0[:, :2] @ np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    if np.ptp(xy[:, 1]) > np.ptp(xy[:, 0]):  # x along the longer side
        a += 0.5 * np.pi
    T = _support_frame(plane, target, T0[:3, :3] @ np.array([np.cos(a), np.sin(a), 0.0]))
    local = (local0 @ T0[:3, :3].T + T0[:3, 3] - T[:3, 3]) @ T[:3, :3]
    lo, hi = local.min(axis=0) - margin_m, local.max(axis=0) + margin_m
    lo[2] = -margin_m
    log.info(
        "region of interest: %d of %d points above the plane (cells %.1f mm), %.1f x %.1f x %.1f mm with margins",
        len(local0),
        len(above),
        1e3 * cell_m,
        *(1e3 * (hi - lo)),
    )
    return Roi(T, lo, hi)


def refine_plane(
    plane: SupportPlane,
    roi: Roi,
    views: Sequence[View],
    maps: Sequence[DepthMap],
    rng: np.random.Generator,
    per_map: int = 50_000,
    band_m: float = 8e-3,
    wall_m: float = 10e-3,
    clear_m: float = 3e-3,
    max_shift_m: float = 5e-3,
    max_tilt_deg: float = 2.0,
    weight: float = 0.5,
) -> tuple[SupportPlane, Roi, dict[str, Any]]:
    """The support plane refitted on the dense depth of the table around the part, and the ROI re-based on it.

    The plane found before the stereo comes from a run's landmarks, which scatter several mm about a table seen
    at an angle (7.5 mm on 60 s orbits); the part's base closes on this plane, so its error goes straight into
    the part's height. Here the table is the depth points within `band_m` of the plane inside the ROI (its margin
    around the part), except where the part stands: 1 mm footprint cells holding two points or more from
    `wall_m` up (the table's own depth noise reaches 5 mm), grown by `clear_m`. Fitted by least squares, from
    the points within `band_m` / 2 of their median height, then trimmed at 3 robust scales (3 rounds). Refused
    (the old plane kept, the reason in the report) when fewer than _MIN_TABLE_POINTS surround the part, or they do
    on fewer than 3 of 4 sides, or the fit moves the plane more than `max_shift_m` under the part or tilts it more
    than `max_tilt_deg`.

    Neither estimate is sub-millimetre: on the 60 s orbit (seed 104) the landmarks' plane sat 1.07 mm under the
    table that the cube's measured top and the run's true scale imply, the dense fit 0.79 mm above it (the table's
    stereo depth spreads 3 mm: little texture, seen obliquely). The plane returned is the `weight` blend of the
    two (0.5: their mean), and the report's `u_base_mm` (the base's standard uncertainty: half their difference
    for the mean) goes with every dimension measured to the base. Returns (plane, roi, report for model.json)."""
    T = roi.world_T_support
    world = [depth_points(views[dm.view], dm, rng, per_map) for dm in maps]
    p = (np.concatenate(world) - T[:3, 3]) @ T[:3, :3] if world else np.zeros((0, 3))
    p = p[((p >= roi.lo) & (p <= roi.hi)).all(axis=1)]
    report: dict[str, Any] = {"refined": False}
    if len(p) == 0:
        report["reason"] = "no depth inside the region of interest"
        return plane, roi, report
    cell = 1e-3
    ij = np.floor((p[:, :2] - roi.lo[:2]) / cell).astype(np.int64)
    shape = tuple(np.floor((roi.hi[:2] - roi.lo[:2]) / cell).astype(int) + 1)
    counts = np.zeros(shape, np.float32)
    up = p[:, 2] >= wall_m
    np.add.at(counts, (ij[up, 0], ij[up, 1]), 1.0)
    grow = 2 * int(np.ceil(clear_m / cell)) + 1
    part = cv2.dilate((counts >= 2).astype(np.uint8), np.ones((grow, grow), np.uint8))
    table = p[(np.abs(p[:, 2]) < band_m) & (part[ij[:, 0], ij[:, 1]] == 0)]
    centre = p[up, :2].mean(axis=0) if up.any() else 0.5 * (roi.lo[:2] + roi.hi[:2])
    angle = np.arctan2(table[:, 1] - centre[1], table[:, 0] - centre[0])
    sides = len(np.unique(np.floor((angle + np.pi) / (0.5 * np.pi)).astype(int) % 4))
    report.update(table_points=int(len(table)), sides=sides)
    if len(table) < _MIN_TABLE_POINTS or sides < 3:
        report["reason"] = f"{len(table)} table points around the part, on {sides} of 4 sides"
        return plane, roi, report
    inl = np.abs(table[:, 2] - np.median(table[:, 2])) < 0.5 * band_m  # centred on the table, not the old plane
    for _ in range(3):  # least squares on the inliers, then inliers within 3 robust scales of the median
        c = table[inl].mean(axis=0)
        n = np.linalg.svd(table[inl] - c, full_matrices=False)[2][2]
        n = n if n[2] > 0 else -n
        r = (table - c) @ n
        mid = float(np.median(r[inl]))
        inl = np.abs(r - mid) < max(3.0 * 1.4826 * float(np.median(np.abs(r[inl] - mid))), 1e-4)
    under = 0.5 * (roi.lo[:2] + roi.hi[:2])  # the new plane's height under the part, in the old support frame
    lift = float(c[2] - (n[:2] @ (under - c[:2])) / n[2])
    tilt = float(np.degrees(np.arccos(min(1.0, float(n[2])))))
    rms = float(np.std(r[inl]))
    report.update(lift_mm=round(1e3 * lift, 4), tilt_deg=round(tilt, 4), rms_mm=round(1e3 * rms, 4))
    if abs(lift) > max_shift_m or tilt > max_tilt_deg:
        report["reason"] = f"the table's depth moved the plane {1e3 * lift:+.1f} mm and {tilt:.2f} deg: not taken"
        return plane, roi, report
    nb = (1.0 - weight) * np.array([0.0, 0.0, 1.0]) + weight * n
    nb /= np.linalg.norm(nb)
    normal = T[:3, :3] @ nb
    on = T[:3, :3] @ np.array([under[0], under[1], weight * lift]) + T[:3, 3]
    new = SupportPlane(normal=normal, d_m=float(normal @ on), inlier_rms_m=rms)
    report.update(refined=True, weight=weight, u_base_mm=round(1e3 * abs(lift) * max(weight, 1.0 - weight), 4))
    log.info(
        "support plane: the table's depth around the part puts it %+.3f mm from the landmarks' (tilt %.3f deg, "
        "%d points); the base takes %.0f %% of that, +-%.3f mm",
        1e3 * lift,
        tilt,
        int(inl.sum()),
        100 * weight,
        report["u_base_mm"],
    )
    return new, Roi(_support_frame(new, T[:3, 3], T[:3, 0]), roi.lo.copy(), roi.hi.copy()), report
