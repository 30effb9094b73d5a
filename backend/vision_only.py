"""Vision only (`estimator.mode: vision_only`, preset `vision_only`): the same projection factors and iSAM2
updates without any inertial factor, velocity or bias key; scale is fixed only by the gauge of the two-view start
(baseline 1).

Here: the two-view geometry and PnP that the start (backend/initialisation/visual.py) and the steady state use,
and the steady state's motion model: each later keyframe starts from PnP on the admitted landmarks (constant
velocity when PnP fails) and is tied to the previous one by a weak constant-velocity motion prior.
"""

from __future__ import annotations

import cv2
import gtsam
import numpy as np

from backend.graph_state import GraphState
from backend.keys import L, X
from backend.landmarks import LandmarkBook
from vio.config import VisionOnlyConfig
from vio.geometry import inv_T

MIN_COMMON = 30  # tracks shared by the two start keyframes
MIN_PNP = 8  # PnP inliers to trust a pose


def two_view(xn0: np.ndarray, xn1: np.ndarray, thresh_norm: float) -> tuple[np.ndarray, np.ndarray] | None:
    """Relative camera pose cam1_T_cam0 (4, 4) with unit baseline and the inlier mask from normalized (N, 2)
    coordinates of the same points in two views; None when the essential matrix fails."""
    E, mask = cv2.findEssentialMat(xn0, xn1, np.eye(3), method=cv2.RANSAC, prob=0.999, threshold=thresh_norm)
    if E is None or E.shape != (3, 3):
        return None
    n, R, t, mask = cv2.recoverPose(E, xn0, xn1, np.eye(3), mask=mask)
    if n < MIN_COMMON // 2:
        return None
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t.ravel() / np.linalg.norm(t)
    return T, mask.ravel() > 0


def pnp_pose(p_world: np.ndarray, uv_px: np.ndarray, K: np.ndarray, body_T_cam: np.ndarray) -> np.ndarray | None:
    """world_T_body (4, 4) from world points (N, 3) seen at undistorted pixels (N, 2); None if PnP fails."""
    if len(p_world) < MIN_PNP:
        return None
    ok, rvec, tvec, inl = cv2.solvePnPRansac(
        p_world.astype(np.float64), uv_px.astype(np.float64), K, None, reprojectionError=3.0, iterationsCount=100
    )
    if not ok or inl is None or len(inl) < max(MIN_PNP, len(p_world) // 3):
        return None
    cam_T_world = np.eye(4)
    cam_T_world[:3, :3], cam_T_world[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
    return inv_T(cam_T_world) @ inv_T(body_T_cam)


class VisionOnlyMotion:
    """Pose prediction and the motion prior between keyframes without an IMU."""

    def __init__(self, cfg: VisionOnlyConfig, state: GraphState, book: LandmarkBook) -> None:
        self.state, self.book = state, book
        s_rot, s_pos = cfg.motion_sigma_rad, cfg.motion_sigma_units
        self.noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([s_rot] * 3 + [s_pos] * 3))

    def predict(self, prev: int, k: int, ids: np.ndarray) -> np.ndarray:
        """Initial world_T_body of keyframe k: PnP on admitted landmarks, else constant velocity."""
        st, tracks = self.state, self.book.tracks
        T_prev = st.pose(prev)
        before = prev - 1
        T_cv = T_prev @ inv_T(st.pose(before)) @ T_prev if st.values.exists(X(before)) else T_prev
        obs = [
            (st.values.atPoint3(L(j)), tracks[j].views[k])
            for j in ids.tolist()
            if tracks[j].admitted and st.smoother.has(L(j)) and k in tracks[j].views
        ]
        if obs:
            T = pnp_pose(
                np.array([o[0] for o in obs]), np.array([o[1] for o in obs]), self.book.K, self.book.body_T_cam
            )
            if T is not None:
                return T
        return T_cv

    def motion_prior(self, prev: int, k: int) -> gtsam.NonlinearFactor:
        """Weak constant-velocity prior between keyframes prev and k (keeps poses with few landmarks defined)."""
        st = self.state
        T_prev = st.pose(prev)
        delta = inv_T(st.pose(prev - 1)) @ T_prev if st.values.exists(X(prev - 1)) else np.eye(4)
        return gtsam.BetweenFactorPose3(X(prev), X(k), gtsam.Pose3(delta), self.noise)
