"""Feature tracks across calibrated views for the bundle adjustment (`vio.model.adjust`).

SIFT keypoints in each view (limited to the ROI's projected window when a ROI is given), matched between pairs of
views that see the region from 5-40 deg apart (FLANN, Lowe's ratio), verified against the epipolar geometry of the
views' prior poses (a loose Sampson gate, the poses being off by a few px) and then by a fundamental-matrix RANSAC,
joined into tracks over all pairs (connected components; a track with two keypoints in one view is dropped) and
triangulated from the prior poses (DLT, >= 3 views, parallax, cheirality and reprojection checks).

Pixels are those of the undistorted pinhole images in OpenCV's convention (the centre of the top-left pixel is
(0, 0)); poses are `world_T_cam` (OpenCV axes) in the run's world, metres.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from vio.geometry import inv_T, skew
from vio.model.dense_common import roi_bbox
from vio.model.parallel import ordered_map
from vio.model.records import Roi, View

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class MatchConfig:
    """Feature and track settings (px are pixels of the views' images, angles deg)."""

    max_features: int = 4000  # SIFT keypoints per view (strongest first)
    contrast_threshold: float = 0.04  # SIFT's contrastThreshold (OpenCV's default 0.04; lower finds more)
    min_angle_deg: float = 5.0  # a pair sees the region (ROI centre, else along the optical axes) this far apart
    max_angle_deg: float = 40.0  # ... and at most this far
    max_pairs_per_view: int = 8  # candidate partners per view, spread over the angle range
    ratio: float = 0.8  # Lowe's ratio test
    prior_error_deg: float = 0.5  # expected error of the prior poses as an angle: epipolar and reprojection gates
    ransac_px: float = 1.5  # fundamental-matrix RANSAC threshold, px
    min_pair_matches: int = 16  # a pair with fewer verified matches is dropped
    min_track_views: int = 3  # a track needs this many views
    min_parallax_deg: float = 2.0  # largest angle between a track's rays
    roi_margin_px: int = 16  # the ROI window is grown by this much
    # SIFT runs on the image resized by detect_scale (INTER_AREA; keypoints in full-size px), 0 = by the budget:
    # the largest multiple of 0.05 that brings the image to max_detect_pixels (0.70 for the 2016 x 1512 stills,
    # 1.0 for images up to 1.5 MP; docs/BENCHMARKS.md: the adjustment's features at 0.7)
    detect_scale: float = 0.0
    max_detect_pixels: int = 1_500_000


@dataclass(frozen=True)
class Features:
    """SIFT keypoints of one view."""

    uv: np.ndarray  # (N, 2) float64 keypoint positions, px
    size: np.ndarray  # (N,) float64 SIFT diameter, px
    descriptors: np.ndarray  # (N, 128) float32


@dataclass(frozen=True)
class Tracks:
    """Observations of triangulated scene points, one row per (view, track)."""

    points_world: np.ndarray  # (T, 3) points triangulated from the prior poses, world, m
    view: np.ndarray  # (M,) int64 index of the observing view
    track: np.ndarray  # (M,) int64 index into points_world
    uv: np.ndarray  # (M, 2) float64 observed keypoint, px
    size: np.ndarray  # (M,) float64 its SIFT diameter, px
    features_per_view: np.ndarray  # (V,) int64 keypoints detected in each view
    num_pairs: int  # pairs of views matched
    num_matches: int  # verified matches over all pairs


def detect_scale(view: View, config: MatchConfig) -> float:
    """The factor SIFT's image is resized by for this view (`MatchConfig.detect_scale`)."""
    if config.detect_scale > 0:
        return float(config.detect_scale)
    w, h = view.size
    if config.max_detect_pixels <= 0 or w * h <= config.max_detect_pixels:
        return 1.0
    return max(0.05, np.floor(20.0 * np.sqrt(config.max_detect_pixels / (w * h)) + 1e-9) / 20.0)


def detect(view: View, roi: Roi | None, config: MatchConfig) -> Features:
    """SIFT keypoints of a view's grey image, inside the ROI's projected window (none when the ROI is out of sight)."""
    box = roi_bbox(view, roi, config.roi_margin_px)
    if box is None:
        return Features(np.zeros((0, 2)), np.zeros(0), np.zeros((0, 128), np.float32))
    x0, y0, x1, y1 = box
    grey = cv2.cvtColor(view.image, cv2.COLOR_BGR2GRAY) if view.image.ndim == 3 else view.image
    sift = cv2.SIFT_create(
        nfeatures=config.max_features, contrastThreshold=config.contrast_threshold, enable_precise_upscale=True
    )
    crop, f = grey[y0:y1, x0:x1], detect_scale(view, config)
    if f != 1.0:
        crop = cv2.resize(crop, None, fx=f, fy=f, interpolation=cv2.INTER_AREA)
    keypoints, descriptors = sift.detectAndCompute(crop, None)
    if descriptors is None:
        return Features(np.zeros((0, 2)), np.zeros(0), np.zeros((0, 128), np.float32))
    # pixel centres: u_full + 0.5 = (u_small + 0.5) / f (OpenCV's resize keeps the image's outer edges)
    uv, size = np.array([k.pt for k in keypoints], float).reshape(-1, 2), np.array([k.size for k in keypoints], float)
    if f != 1.0:
        uv, size = (uv + 0.5) / f - 0.5, size / f
    return Features(uv + [x0, y0], size, descriptors.astype(np.float32))


def detect_all(views: list[View], roi: Roi | None, config: MatchConfig) -> list[Features]:
    """`detect` on every view, on every core (vio.model.parallel; each view's keypoints are the serial call's)."""
    return list(ordered_map(lambda v: detect(v, roi, config), views))


def select_pairs(views: list[View], roi: Roi | None, config: MatchConfig) -> list[tuple[int, int]]:
    """Pairs (i < j) seeing the ROI centre (without a ROI: along their optical axes) min..max_angle_deg apart, at
    most max_pairs_per_view partners per view spread evenly over that range."""
    centres = np.array([v.world_T_cam[:3, 3] for v in views])
    if roi is None:
        dirs = np.array([v.world_T_cam[:3, 2] for v in views])
    else:
        target = roi.world_T_support[:3, :3] @ (0.5 * (np.asarray(roi.lo) + roi.hi)) + roi.world_T_support[:3, 3]
        dirs = target - centres
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    angle = np.degrees(np.arccos(np.clip(dirs @ dirs.T, -1.0, 1.0)))
    pairs = set()
    for i in range(len(views)):
        (cand,) = np.nonzero((angle[i] >= config.min_angle_deg) & (angle[i] <= config.max_angle_deg))
        cand = cand[np.argsort(angle[i, cand])]
        if cand.size > config.max_pairs_per_view:
            cand = cand[np.round(np.linspace(0, cand.size - 1, config.max_pairs_per_view)).astype(int)]
        pairs |= {(min(i, int(j)), max(i, int(j))) for j in cand}
    return sorted(pairs)


def _fundamental(va: View, vb: View) -> np.ndarray:
    """F with x_b^T F x_a = 0 from the views' poses."""
    b_T_a = inv_T(vb.world_T_cam) @ va.world_T_cam
    E = skew(b_T_a[:3, 3] / max(np.linalg.norm(b_T_a[:3, 3]), 1e-12)) @ b_T_a[:3, :3]
    return np.linalg.inv(vb.K).T @ E @ np.linalg.inv(va.K)


def _sampson_px(F: np.ndarray, xa: np.ndarray, xb: np.ndarray) -> np.ndarray:
    """(N,) Sampson distance of pixel pairs to F, px."""
    ha, hb = np.column_stack([xa, np.ones(len(xa))]), np.column_stack([xb, np.ones(len(xb))])
    Fa, Ftb = ha @ F.T, hb @ F
    num = np.einsum("ij,ij->i", hb, Fa)
    return np.abs(num) / np.sqrt(Fa[:, 0] ** 2 + Fa[:, 1] ** 2 + Ftb[:, 0] ** 2 + Ftb[:, 1] ** 2 + 1e-30)


def _verify(va: View, vb: View, xa: np.ndarray, xb: np.ndarray, config: MatchConfig) -> np.ndarray:
    """Mask of matches consistent with the prior poses (loose) and with a RANSAC fundamental matrix (tight)."""
    gate_px = float(np.tan(np.radians(config.prior_error_deg)) * max(va.K[0, 0], vb.K[0, 0]))
    keep = _sampson_px(_fundamental(va, vb), xa, xb) < gate_px
    if keep.sum() < config.min_pair_matches:
        return np.zeros(len(xa), bool)
    _, inlier = cv2.findFundamentalMat(xa[keep], xb[keep], cv2.FM_RANSAC, config.ransac_px, 0.999, 2000)
    if inlier is None:
        return np.zeros(len(xa), bool)
    keep[np.flatnonzero(keep)[~inlier.ravel().astype(bool)]] = False
    return keep if keep.sum() >= config.min_pair_matches else np.zeros(len(xa), bool)


def match_pairs(
    views: list[View], features: list[Features], pairs: list[tuple[int, int]], config: MatchConfig
) -> list[tuple[int, int, np.ndarray]]:
    """Verified matches (i, j, (K, 2) keypoint indices in i and j) of each pair. One FLANN index per first view,
    the first views on every core (vio.model.parallel). FLANN's randomised trees draw from OpenCV's random number
    generator (per thread): it is seeded with the view's index before each index is built, so the matches are the
    same whatever the thread count and the order the views are taken in."""
    partners: dict[int, list[int]] = {}
    for i, j in pairs:
        partners.setdefault(i, []).append(j)

    def match_from(i: int) -> list[tuple[int, int, np.ndarray]]:
        if len(features[i].uv) < config.min_pair_matches:
            return []
        cv2.setRNGSeed(i)
        flann = cv2.FlannBasedMatcher({"algorithm": 1, "trees": 4}, {"checks": 64})
        flann.add([features[i].descriptors])
        flann.train()
        found = []
        for j in partners[i]:
            if len(features[j].uv) < config.min_pair_matches:
                continue
            knn = flann.knnMatch(features[j].descriptors, k=2)
            good = [
                (a.trainIdx, a.queryIdx)
                for a, b in (m for m in knn if len(m) == 2)
                if a.distance < config.ratio * b.distance
            ]
            if len(good) < config.min_pair_matches:
                continue
            idx = np.array(good, np.int64)
            _, first = np.unique(idx[:, 0], return_index=True)  # one partner per keypoint of view i
            idx = idx[np.sort(first)]
            keep = _verify(views[i], views[j], features[i].uv[idx[:, 0]], features[j].uv[idx[:, 1]], config)
            if keep.any():
                found.append((i, j, idx[keep]))
        return found

    return [m for found in ordered_map(match_from, sorted(partners)) for m in found]


def build_tracks(features: list[Features], matches: list[tuple[int, int, np.ndarray]]) -> list[np.ndarray]:
    """Tracks as (m, 2) arrays of (view, keypoint): connected components of the match graph, without those that
    hold two keypoints of one view."""
    if not matches:
        return []
    offsets = np.concatenate([[0], np.cumsum([len(f.uv) for f in features])])
    a = np.concatenate([offsets[i] + m[:, 0] for i, _, m in matches])
    b = np.concatenate([offsets[j] + m[:, 1] for _, j, m in matches])
    n = int(offsets[-1])
    _, label = connected_components(coo_matrix((np.ones(len(a)), (a, b)), shape=(n, n)), directed=False)
    nodes = np.unique(np.concatenate([a, b]))
    view = np.searchsorted(offsets, nodes, side="right") - 1
    order = np.lexsort((view, label[nodes]))
    nodes, view, lab = nodes[order], view[order], label[nodes][order]
    starts = np.flatnonzero(np.r_[True, lab[1:] != lab[:-1]])
    tracks = []
    for s, e in zip(starts, np.r_[starts[1:], len(nodes)], strict=True):
        v = view[s:e]
        if np.all(v[1:] != v[:-1]):  # sorted by view within a component: no repeated view
            tracks.append(np.column_stack([v, nodes[s:e] - offsets[v]]))
    return tracks


def _dlt(track: np.ndarray, xn: np.ndarray, cam_T_world: np.ndarray, n_tracks: int) -> np.ndarray:
    """(T, 3) points, world, m: per track the DLT solution (smallest eigenvector of A^T A) of its observations'
    normalised image points xn (M, 2) seen by cameras cam_T_world (M, 3, 4)."""
    r1 = xn[:, :1] * cam_T_world[:, 2] - cam_T_world[:, 0]
    r2 = xn[:, 1:] * cam_T_world[:, 2] - cam_T_world[:, 1]
    AtA = np.zeros((n_tracks, 4, 4))
    np.add.at(AtA, track, r1[:, :, None] * r1[:, None, :] + r2[:, :, None] * r2[:, None, :])
    h = np.linalg.eigh(AtA)[1][:, :, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        return h[:, :3] / h[:, 3:]


def triangulate(views: list[View], features: list[Features], tracks: list[np.ndarray], config: MatchConfig) -> Tracks:
    """Points of the tracks from the views' prior poses (DLT). Observations reprojecting further than the prior
    gate (or behind the camera) are dropped and the point triangulated again; it is kept when then all its
    observations, at least min_track_views, pass, and its rays are min_parallax_deg apart (from its first ray)."""
    if not tracks:
        return Tracks(np.zeros((0, 3)), *np.zeros((2, 0), np.int64), np.zeros((0, 2)), np.zeros(0), np.zeros(0), 0, 0)
    n_tracks = len(tracks)
    track = np.repeat(np.arange(n_tracks), [len(t) for t in tracks])
    view = np.concatenate([t[:, 0] for t in tracks])
    offsets = np.concatenate([[0], np.cumsum([len(f.uv) for f in features])])
    node = offsets[view] + np.concatenate([t[:, 1] for t in tracks])
    uv, size = np.concatenate([f.uv for f in features])[node], np.concatenate([f.size for f in features])[node]
    K = np.array([v.K for v in views])
    cam_T_world = np.array([inv_T(v.world_T_cam)[:3] for v in views])[view]
    xn = np.einsum("mij,mj->mi", np.linalg.inv(K)[view], np.column_stack([uv, np.ones(len(uv))]))[:, :2]
    gate_px = np.tan(np.radians(config.prior_error_deg)) * K[view, 0, 0]
    keep = np.ones(len(track), bool)
    for _ in range(2):  # triangulate, drop observations beyond the gate, triangulate again
        keep &= np.bincount(track[keep], minlength=n_tracks)[track] >= config.min_track_views
        points = _dlt(track[keep], xn[keep], cam_T_world[keep], n_tracks)
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            p_cam = np.einsum("mij,mj->mi", cam_T_world, np.column_stack([points[track], np.ones(len(track))]))
            ok = (np.linalg.norm(p_cam[:, :2] / p_cam[:, 2:] - xn, axis=1) * K[view, 0, 0] < gate_px) & (
                p_cam[:, 2] > 0
            )
        failed = np.bincount(track[keep & ~ok], minlength=n_tracks) > 0
        keep &= ok
    good = ~failed & (np.bincount(track[keep], minlength=n_tracks) >= config.min_track_views)
    rays = np.array([v.world_T_cam[:3, 3] for v in views])[view] - points[track]
    with np.errstate(invalid="ignore"):
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    first = np.flatnonzero(np.r_[True, track[1:] != track[:-1]])
    min_cos = np.ones(n_tracks)
    np.minimum.at(min_cos, track[keep], np.einsum("ij,ij->i", rays, rays[first][track])[keep])
    good &= np.degrees(np.arccos(np.clip(min_cos, -1.0, 1.0))) >= config.min_parallax_deg
    good &= np.all(np.isfinite(points), axis=1)
    sel = keep & good[track]
    new_id = np.cumsum(good) - 1
    return Tracks(points[good], view[sel], new_id[track[sel]], uv[sel], size[sel], np.zeros(0, np.int64), 0, 0)


def find_tracks(views: list[View], roi: Roi | None = None, config: MatchConfig | None = None) -> Tracks:
    """Detect, match, verify, join and triangulate: the tracks the bundle adjustment refines."""
    config = config or MatchConfig()
    features = detect_all(views, roi, config)
    pairs = select_pairs(views, roi, config)
    matches = match_pairs(views, features, pairs, config)
    found = triangulate(views, features, build_tracks(features, matches), config)
    per_view = np.array([len(f.uv) for f in features], np.int64)
    num_matches = int(sum(len(m) for _, _, m in matches))
    log.info(
        "features: median %d per view; %d of %d pairs matched, %d matches; %d tracks, %d observations",
        int(np.median(per_view)), len(matches), len(pairs), num_matches, len(found.points_world), len(found.view),
    )  # fmt: skip
    return dataclasses.replace(found, features_per_view=per_view, num_pairs=len(matches), num_matches=num_matches)
