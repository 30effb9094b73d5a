"""Camera-IMU time offset from motion: the rotation rate seen in the images against the gyro's.

For consecutive frames, KLT tracks give point pairs; their relative rotation comes from a pure-rotation fit
(Kabsch on unit bearing vectors, i.e. the infinite homography) when that explains the flow to sub-pixel level, and
otherwise from the essential matrix (USAC_ACCURATE: RANSAC with local optimisation; plain RANSAC was 5x noisier)
and cheirality. The rotation angle over each frame interval is compared with the gyro's integrated rotation over
the same interval shifted by a candidate offset; the offset with the highest correlation wins (1 ms grid, parabolic
refinement). Convention (Kalibr's `timeshift_cam_imu`): t_imu = t_cam + offset.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from vio.capture import Capture
from vio.errors import CaptureError
from vio.geometry import parabolic_peak

log = logging.getLogger(__name__)

MAX_WIDTH = 640  # frames are downscaled to at most this width for tracking, px
KABSCH_MAX_PX = 0.7  # median residual below which the pure-rotation fit is used, px


@dataclass(frozen=True)
class OffsetEstimate:
    offset_ns: int | None  # t_imu = t_cam + offset; None when it could not be estimated
    correlation: float  # Pearson correlation of camera vs gyro rotation rates at the chosen offset
    pairs: int  # frame pairs with a rotation estimate
    note: str  # why it is unreliable, or ""
    rate_ratio: float = float("nan")  # image rotation rate / gyro rotation rate at the offset (1: gyro in rad/s)


def _bearings(xn: np.ndarray) -> np.ndarray:
    b = np.column_stack([xn, np.ones(xn.shape[0])])
    return b / np.linalg.norm(b, axis=1, keepdims=True)


def _kabsch(b0: np.ndarray, b1: np.ndarray) -> np.ndarray:
    """R minimising sum |b1 - R b0|^2."""
    u, _, vt = np.linalg.svd(b1.T @ b0)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def pair_rotation(xn0: np.ndarray, xn1: np.ndarray, focal_px: float) -> float | None:
    """Rotation angle (rad) between two views from matched undistorted normalized points; None if unreliable."""
    if xn0.shape[0] < 12:
        return None
    b0, b1 = _bearings(xn0), _bearings(xn1)
    keep = np.ones(b0.shape[0], bool)
    R = np.eye(3)
    for _ in range(3):
        R = _kabsch(b0[keep], b1[keep])
        res = np.linalg.norm(b1 - b0 @ R.T, axis=1) * focal_px
        keep = res < max(3.0 * float(np.median(res)), 0.5)
        if keep.sum() < 12:
            return None
    if float(np.median(res[keep])) < KABSCH_MAX_PX:
        return float(np.linalg.norm(Rotation.from_matrix(R).as_rotvec()))
    E, mask = cv2.findEssentialMat(
        xn0, xn1, focal=1.0, pp=(0.0, 0.0), method=cv2.USAC_ACCURATE, prob=0.999, threshold=1.0 / focal_px
    )
    if E is None or E.shape != (3, 3):
        return None
    n, R, _, _ = cv2.recoverPose(E, xn0, xn1, focal=1.0, pp=(0.0, 0.0), mask=mask)
    if n < 12:
        return None
    return float(np.linalg.norm(Rotation.from_matrix(R).as_rotvec()))


def image_rotations(cap: Capture, max_pairs: int = 300) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t0_ns, t1_ns, angle_rad) for up to `max_pairs` consecutive frame pairs (angle NaN where unreliable; frames
    that do not decode are left out)."""
    cam = cap.camera
    n = min(cap.num_frames, max_pairs + 1)
    t0s, t1s, angles = [], [], []
    prev = None
    scale = None
    for i in range(n):
        try:
            img = cap.load_image(i)
        except CaptureError:  # a frame that does not decode: no pair with it (vio run skips it too)
            prev = None
            continue
        if scale is None:
            scale = min(1.0, MAX_WIDTH / img.shape[1])
        small = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA) if scale < 1 else img
        if prev is not None:
            angle = float("nan")
            p0 = cv2.goodFeaturesToTrack(prev, 400, 0.01, 8)
            if p0 is not None and len(p0) >= 12:
                p1, st, _ = cv2.calcOpticalFlowPyrLK(prev, small, p0, None, winSize=(21, 21), maxLevel=3)
                ok = st.reshape(-1) == 1
                if ok.sum() >= 12:
                    a, b = p0.reshape(-1, 2)[ok] / scale, p1.reshape(-1, 2)[ok] / scale
                    if cam is not None:
                        K, dist, f = cam.K, cam.dist, cam.fx
                    else:  # no calibration: a guessed pinhole (angles approximate)
                        f = float(max(img.shape))
                        K, dist = np.array([[f, 0, img.shape[1] / 2], [0, f, img.shape[0] / 2], [0, 0, 1.0]]), None
                    xa = cv2.undistortPoints(a.reshape(-1, 1, 2), K, dist).reshape(-1, 2)
                    xb = cv2.undistortPoints(b.reshape(-1, 1, 2), K, dist).reshape(-1, 2)
                    got = pair_rotation(xa, xb, f)
                    angle = float("nan") if got is None else got
            t0s.append(int(cap.frame_t_ns[i - 1]))
            t1s.append(int(cap.frame_t_ns[i]))
            angles.append(angle)
        prev = small
    return np.asarray(t0s, np.int64), np.asarray(t1s, np.int64), np.asarray(angles, float)


def _gyro_angles(cap: Capture, t0: np.ndarray, t1: np.ndarray, offset_ns: np.ndarray) -> np.ndarray:
    """|integral of gyro| over [t0 + d, t1 + d] for each offset d: (D, P) array, rad."""
    imu = cap.imu
    assert imu is not None
    ts = (imu.t_ns - imu.t_ns[0]).astype(float) * 1e-9
    dt = np.diff(ts)
    mid = 0.5 * (imu.gyro[1:] + imu.gyro[:-1]) * dt[:, None]
    cum = np.vstack([np.zeros(3), np.cumsum(mid, axis=0)])
    a = ((t0[None, :] + offset_ns[:, None]) - imu.t_ns[0]).astype(float) * 1e-9
    b = ((t1[None, :] + offset_ns[:, None]) - imu.t_ns[0]).astype(float) * 1e-9
    diff = np.stack([np.interp(b, ts, cum[:, k]) - np.interp(a, ts, cum[:, k]) for k in range(3)], axis=-1)
    return np.linalg.norm(diff, axis=-1)


def estimate_time_offset(cap: Capture, max_offset_s: float = 0.3, max_pairs: int = 300) -> OffsetEstimate:
    """Estimate t_imu - t_cam from rotation rates (see the module docstring)."""
    if cap.imu is None or len(cap.imu) < 10 or cap.num_frames < 10:
        return OffsetEstimate(None, float("nan"), 0, "needs frames and an IMU")
    t0, t1, ang = image_rotations(cap, max_pairs)
    ok = np.isfinite(ang)
    t0, t1, ang = t0[ok], t1[ok], ang[ok]
    lim = int(max_offset_s * 1e9)
    inside = (t0 - lim >= cap.imu.t_ns[0]) & (t1 + lim <= cap.imu.t_ns[-1])
    t0, t1, ang = t0[inside], t1[inside], ang[inside]
    if ang.size < 8:
        return OffsetEstimate(None, float("nan"), int(ang.size), "too few frame pairs with tracked rotation")
    cam_rate = ang / ((t1 - t0) * 1e-9)
    if float(np.std(cam_rate)) < 0.02:
        return OffsetEstimate(None, float("nan"), int(ang.size), "too little rotation to correlate")
    offsets = np.arange(-lim, lim + 1, 1_000_000, dtype=np.int64)
    gyro_rate = _gyro_angles(cap, t0, t1, offsets) / ((t1 - t0) * 1e-9)[None, :]
    c = cam_rate - cam_rate.mean()
    g = gyro_rate - gyro_rate.mean(axis=1, keepdims=True)
    corr = (g @ c) / (np.linalg.norm(g, axis=1) * np.linalg.norm(c) + 1e-12)
    k = int(np.argmax(corr))
    best = float(offsets[k]) + parabolic_peak(corr, k) * 1e6
    note = "" if corr[k] >= 0.5 else "weak correlation: the estimate is unreliable"
    if k in (0, len(corr) - 1):
        note = f"best offset at the search limit (+-{max_offset_s:g} s): unreliable"
    gk = gyro_rate[k]
    ratio = float(np.dot(gk, cam_rate) / max(float(np.dot(gk, gk)), 1e-12))
    return OffsetEstimate(int(round(best)), float(corr[k]), int(ang.size), note, ratio)
