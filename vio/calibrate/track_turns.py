"""The camera's turns from feature tracks (a capture that carries tracks, e.g. gtsam's eqvio file, or none of a
board): the relative rotation of two frames from the essential matrix of their common tracks.

The tracks' pixels are undistorted to normalized coordinates with the capture's intrinsics; `cv2.findEssentialMat`
(USAC_ACCURATE, a threshold of 1 px) and `cv2.recoverPose` give cam1_R_cam0, whose inverse is the turn. Between
consecutive frames the baseline is too short for an essential matrix; there the turn is the rotation that best maps
one frame's bearing vectors onto the other's (Kabsch, twice with the worst third of the tracks dropped), which
ignores the little parallax of 1/20 s: good enough for the angular speeds of the cross-correlation. A pair with
fewer than MIN_COMMON common tracks or inliers gives no turn.
"""

from __future__ import annotations

import logging

import numpy as np

from vio.calibrate.epipolar_align import BearingPairs
from vio.calibrate.rotation_align import PAIR_SPAN_S, CameraTurns
from vio.capture import Capture
from vio.errors import CalibrationError
from vio.records import FeatureTracks

log = logging.getLogger(__name__)

# Spans of the refinement's frame pairs, s: long enough for the baseline's direction to be told from a turn (pairs
# 0.2-0.3 s apart leave the rotation about the optical axis's neighbours ambiguous), short enough to keep tracks.
TRACK_SPANS_S = (0.4, 0.6, 0.8, 1.0)
MIN_COMMON = 10  # common tracks (and inliers) a pair needs (the 5-point solver with some redundancy)


def _rotation_only(xa: np.ndarray, xb: np.ndarray) -> np.ndarray:
    """cam_a_R_cam_b as a rotation vector: the rotation taking the b bearings onto the a bearings (Kabsch)."""
    from scipy.spatial.transform import Rotation

    ba = np.column_stack([xa, np.ones(len(xa))])
    bb = np.column_stack([xb, np.ones(len(xb))])
    ba /= np.linalg.norm(ba, axis=1, keepdims=True)
    bb /= np.linalg.norm(bb, axis=1, keepdims=True)
    keep = np.ones(len(ba), bool)
    for _ in range(3):
        R, _ = Rotation.align_vectors(ba[keep], bb[keep])
        res = np.linalg.norm(ba - R.apply(bb), axis=1)
        keep = res <= np.quantile(res, 2.0 / 3.0)
    return R.as_rotvec()


def _turn(
    a: FeatureTracks, b: FeatureTracks, K: np.ndarray, dist: np.ndarray, f_px: float, essential: bool
) -> np.ndarray | None:
    import cv2

    common, ia, ib = np.intersect1d(a.ids, b.ids, return_indices=True)
    if common.size < MIN_COMMON:
        return None
    xa = cv2.undistortPoints(a.uv[ia].reshape(-1, 1, 2), K, dist).reshape(-1, 2)
    xb = cv2.undistortPoints(b.uv[ib].reshape(-1, 1, 2), K, dist).reshape(-1, 2)
    if not essential:
        return _rotation_only(xa, xb)
    E, mask = cv2.findEssentialMat(
        xa, xb, focal=1.0, pp=(0.0, 0.0), method=cv2.USAC_ACCURATE, prob=0.999, threshold=1.0 / f_px
    )
    if E is None or E.shape != (3, 3):
        return None
    n, R, _, _ = cv2.recoverPose(E, xa, xb, focal=1.0, pp=(0.0, 0.0), mask=mask)
    if n < MIN_COMMON:
        return None
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R.T).as_rotvec()  # cam_a_R_cam_b


def _pairs(tracks: list[FeatureTracks], span_ns: float, max_ns: float, essential: bool, K, dist, f_px) -> CameraTurns:
    t = np.array([tr.t_ns for tr in tracks], np.int64)
    t0, t1, rv = [], [], []
    i = 0
    while i < len(t) - 1:
        j = int(np.searchsorted(t, t[i] + span_ns - 1e6))
        if j >= len(t):
            break
        if t[j] - t[i] <= max_ns:
            turn = _turn(tracks[i], tracks[j], K, dist, f_px, essential)
            if turn is not None:
                t0.append(int(t[i]))
                t1.append(int(t[j]))
                rv.append(turn)
        i = j
    return CameraTurns(np.asarray(t0, np.int64), np.asarray(t1, np.int64), np.asarray(rv, float).reshape(-1, 3))


def track_turns(cap: Capture) -> tuple[CameraTurns, CameraTurns, int]:
    """(turns between consecutive frames, turns between frames about PAIR_SPAN_S apart, frames with tracks)."""
    if not cap.tracks:
        raise CalibrationError(f"{cap.root}: the capture has neither a board (--board) nor feature tracks")
    cam = cap.camera
    assert cam is not None
    tracks = [tr for tr in cap.tracks if len(tr.ids) >= MIN_COMMON]
    period_ns = float(np.median(np.diff(cap.frame_t_ns)))
    args = (cam.K, np.asarray(cam.dist, float), float(cam.fx))
    steps = _pairs(tracks, 0.5 * period_ns, 1.5 * period_ns, False, *args)
    turns = _pairs(tracks, PAIR_SPAN_S * 1e9, PAIR_SPAN_S * 1e9 + period_ns, True, *args)
    log.info("tracks: %d steps, %d pairs from %d frames", len(steps.t0_ns), len(turns.t0_ns), len(tracks))
    return steps, turns, len(tracks)


def bearing_pairs(cap: Capture, spans_s: tuple[float, ...] = TRACK_SPANS_S) -> tuple[BearingPairs, float]:
    """The common tracks of frame pairs `spans_s` apart (every frame starts one pair per span), as unit bearings;
    and how many pairs each frame's tracks enter on average (the refinement's covariance is scaled by it)."""
    import cv2

    cam = cap.camera
    assert cam is not None and cap.tracks is not None
    tracks = [tr for tr in cap.tracks if len(tr.ids) >= MIN_COMMON]
    t = np.array([tr.t_ns for tr in tracks], np.int64)
    period_ns = float(np.median(np.diff(cap.frame_t_ns)))
    K, dist = cam.K, np.asarray(cam.dist, float)

    def bearings(uv: np.ndarray) -> np.ndarray:
        x = cv2.undistortPoints(uv.reshape(-1, 1, 2), K, dist).reshape(-1, 2)
        b = np.column_stack([x, np.ones(len(x))])
        return b / np.linalg.norm(b, axis=1, keepdims=True)

    t0, t1, pair, f0, f1 = [], [], [], [], []
    uses = np.zeros(len(t))
    for span_ns in np.asarray(spans_s) * 1e9:
        for i in range(len(t)):
            j = int(np.searchsorted(t, t[i] + span_ns - 1e6))
            if j >= len(t) or t[j] - t[i] > span_ns + period_ns:
                continue
            common, ia, ib = np.intersect1d(tracks[i].ids, tracks[j].ids, return_indices=True)
            if common.size < MIN_COMMON:
                continue
            pair.append(np.full(common.size, len(t0)))
            t0.append(int(t[i]))
            t1.append(int(t[j]))
            f0.append(bearings(tracks[i].uv[ia]))
            f1.append(bearings(tracks[j].uv[ib]))
            uses[[i, j]] += 1
    if not t0:
        raise CalibrationError(f"{cap.root}: no frame pairs share {MIN_COMMON} tracks")
    data = BearingPairs(
        np.asarray(t0, np.int64), np.asarray(t1, np.int64), np.concatenate(pair), np.vstack(f0), np.vstack(f1)
    )
    return data, float(uses[uses > 0].mean())
