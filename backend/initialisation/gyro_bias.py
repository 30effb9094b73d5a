"""The gyro bias of a moving start, from the images' own rotations (VINS-Mono's gyroscope-bias step).

The closed-form moving start (alignment.py) takes the window's relative rotations from the gyro. A real phone's or
drone's gyro bias is easily 0.05-0.1 rad/s (EuRoC V1_01's ADIS16448: 0.077 rad/s about z), which over a 1 s window
turns the rotations by 4-5 degrees; the bearing equations then fit no metric structure and the linear solve
collapses towards zero translation (every keyframe at the origin). Before that solve, the rotation of each
keyframe relative to the window's first is measured from the images (five-point essential matrix on the tracks,
RANSAC) and the constant gyro bias that makes the preintegrated rotations agree with them is found by Gauss-Newton.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import gtsam
import numpy as np

MIN_POINTS = 15  # tracks seen in both keyframes for a pair's rotation
MIN_INLIER_SHARE = 0.6  # the essential matrix must explain this share of them
THRESHOLD_NORM = 1.5e-3  # RANSAC epipolar threshold in normalised units (about 1 px at 600 px focal length)
MIN_SPAN_S = 0.3  # pairs closer in time than this carry too little of the bias to be used


@dataclass(frozen=True)
class GyroBiasEstimate:
    bias: np.ndarray  # (3,) rad/s
    pairs: int  # keyframe pairs used
    rms_before_deg: float  # rms rotation disagreement image vs gyro at the bias the pims were integrated with
    rms_after_deg: float  # the same at the estimated bias


def visual_rotation(x0: np.ndarray, x1: np.ndarray) -> np.ndarray | None:
    """cam0_R_cam1 from (N, 2) normalised coordinates of the same points in two views, or None."""
    if len(x0) < MIN_POINTS:
        return None
    E, mask = cv2.findEssentialMat(x0, x1, np.eye(3), cv2.RANSAC, 0.999, THRESHOLD_NORM)
    if E is None or E.shape != (3, 3) or mask is None or mask.sum() < MIN_INLIER_SHARE * len(x0):
        return None
    _, R, _, _ = cv2.recoverPose(E, x0, x1, np.eye(3), mask=mask.copy())
    return R.T  # recoverPose gives cam1_R_cam0 (x1 = R x0 + t)


def rotations_at(pims: list[gtsam.PreintegratedImuMeasurements], bias_gyro: np.ndarray) -> list[np.ndarray]:
    """Rotations A_R_body of each keyframe after the first (the chained pims, bias-corrected to bias_gyro)."""
    bias = gtsam.imuBias.ConstantBias(np.zeros(3), np.asarray(bias_gyro, float))
    R = np.eye(3)
    out = []
    for pim in pims:
        R = R @ pim.predict(gtsam.NavState(), bias).attitude().matrix()
        out.append(R)
    return out


def gyro_bias_from_images(
    ks: list[int],
    t_s: list[float],
    pims: list[gtsam.PreintegratedImuMeasurements],
    observations: dict[int, dict[int, np.ndarray]],
    body_T_cam: np.ndarray,
    bias_gyro: np.ndarray,
) -> GyroBiasEstimate | None:
    """The gyro bias (3,) rad/s that makes the gyro's rotations agree with the images', or None.

    ks: the window's keyframes; t_s their times, s; pims[i] preintegrates from ks[i] to ks[i + 1] (integrated at
    `bias_gyro`); observations: track id -> {k: normalised undistorted coordinates (2,)}. Uses every keyframe
    at least MIN_SPAN_S after the first whose rotation to it the images give.
    """
    R_bc = np.asarray(body_T_cam, float)[:3, :3]
    measured: dict[int, np.ndarray] = {}  # index i (ks[i]) -> A_R_body from the images
    for i, k in enumerate(ks[1:], start=1):
        if t_s[i] - t_s[0] < MIN_SPAN_S:
            continue
        common = [obs for obs in observations.values() if ks[0] in obs and k in obs]
        if len(common) < MIN_POINTS:
            continue
        x0 = np.array([o[ks[0]] for o in common], float)
        x1 = np.array([o[k] for o in common], float)
        c0_R_c1 = visual_rotation(x0, x1)
        if c0_R_c1 is not None:
            measured[i] = R_bc @ c0_R_c1 @ R_bc.T
    if len(measured) < 2:
        return None

    def residual(b: np.ndarray) -> np.ndarray:
        Rs = rotations_at(pims, b)
        return np.concatenate([gtsam.Rot3.Logmap(gtsam.Rot3(Rs[i - 1].T @ Rv)) for i, Rv in measured.items()])

    b = np.asarray(bias_gyro, float).copy()
    r0 = residual(b)
    r = r0
    for _ in range(4):
        J = np.empty((len(r), 3))
        h = 1e-4
        for a in range(3):
            db = np.zeros(3)
            db[a] = h
            J[:, a] = (residual(b + db) - r) / h
        step = np.linalg.lstsq(J, -r, rcond=None)[0]
        b = b + step
        r = residual(b)
        if np.linalg.norm(step) < 1e-6:
            break

    def rms_deg(v: np.ndarray) -> float:
        return float(np.degrees(np.sqrt(np.mean(np.sum(v.reshape(-1, 3) ** 2, axis=1)))))

    return GyroBiasEstimate(b, len(measured), rms_deg(r0), rms_deg(r))
