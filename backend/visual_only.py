"""The IMU-free mode (`backend.use_imu = false`): the same projection factors and iSAM2 updates without any
inertial factor, velocity or bias key; scale is fixed only by the gauge of the two-view start (baseline 1).

Start: the first buffered keyframe and the latest one with enough parallax give an essential matrix on
undistorted bearings (`cv2.findEssentialMat` + `cv2.recoverPose`), the keyframes in between are placed by PnP on
the two-view points, then a joint batch solve with a prior on the first pose and on the second pose's position.
Each later keyframe starts from PnP on the admitted landmarks (constant velocity when PnP fails) and is tied to the
previous one by a weak constant-velocity motion prior. A mixin of `VioEstimator`.
"""

from __future__ import annotations

import logging
import time

import cv2
import gtsam
import numpy as np

from backend.keys import L, X
from backend.landmarks import camera_poses, triangulate
from vio.geometry import inv_T
from vio.records import StateEstimate

log = logging.getLogger(__name__)

MIN_COMMON = 30  # tracks shared by the two start keyframes
MIN_PNP = 8  # PnP inliers to trust a pose
MAX_PENDING = 40  # keyframes buffered before the oldest is dropped
MOTION_SIGMAS = np.array([0.2, 0.2, 0.2, 1.0, 1.0, 1.0])  # constant-velocity prior: rad, scale units


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


class VisualOnly:
    """IMU-free initialisation and pose prediction methods of VioEstimator."""

    def _vo_try_initialise(self) -> list[StateEstimate]:
        ks = self.pending
        if len(ks) > MAX_PENDING:
            self.pending = ks = ks[1:]
        if len(ks) < 3:
            return []
        poses = self._vo_start_poses(ks)
        if poses is None:
            return []
        t0 = time.perf_counter()
        k0, k1 = ks[0], ks[-1]
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        priors = [
            gtsam.PriorFactorPose3(X(k0), gtsam.Pose3(poses[k0]), gtsam.noiseModel.Isotropic.Sigma(6, 1e-4)),
            gtsam.PriorFactorPose3(  # fixes the scale: the second pose's position (rotation free)
                X(k1), gtsam.Pose3(poses[k1]), gtsam.noiseModel.Diagonal.Sigmas(np.array([1e3] * 3 + [1e-3] * 3))
            ),
        ]
        for f in priors:
            graph.add(f)
            self.all_factors.add(f)
        for k, T in poses.items():
            values.insert(X(k), gtsam.Pose3(T))
        self._admit_window_landmarks(graph, values, poses)
        if not self._start_window(graph, values, ks, "visual initialisation"):
            return []
        self.initialised, self.init_kind = True, "visual"
        ms = (time.perf_counter() - t0) * 1e3
        self.timings_ms.append(ms)
        log.info("initialised (visual two-view) with %d keyframes, %d landmarks", len(poses), len(self.num_obs))
        self.pending = []
        return [self._state(k, ms) for k in sorted(poses)]

    def _vo_start_poses(self, ks: list[int]) -> dict[int, np.ndarray] | None:
        """world_T_body of the buffered keyframes (world = body of ks[0], unit camera baseline to ks[-1])."""
        k0, k1 = ks[0], ks[-1]
        common = [tr for tr in self.book.tracks.values() if k0 in tr.views and k1 in tr.views]
        if len(common) < MIN_COMMON:
            return None
        xn0 = self.book.normalized(np.stack([tr.views[k0] for tr in common]))
        xn1 = self.book.normalized(np.stack([tr.views[k1] for tr in common]))
        res = two_view(xn0, xn1, 2.0 * self.cfg.pixel_sigma / self.camera.fx)
        if res is None:
            return None
        c1_T_c0, inl = res
        bTc = self.book.body_T_cam
        poses = {k0: np.eye(4), k1: bTc @ inv_T(c1_T_c0) @ inv_T(bTc)}
        Twc = camera_poses(poses, bTc, [k0, k1])
        pts, idx, par = [], [], []
        for i in np.flatnonzero(inl).tolist():
            p = triangulate(Twc, np.stack([xn0[i], xn1[i]]))
            r0, r1 = p - Twc[0, :3, 3], p - Twc[1, :3, 3]
            cos = r0 @ r1 / (np.linalg.norm(r0) * np.linalg.norm(r1) + 1e-12)
            if (Twc[0, :3, :3].T @ r0)[2] > 0 and (Twc[1, :3, :3].T @ r1)[2] > 0:
                pts.append(p)
                idx.append(i)
                par.append(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
        if len(pts) < MIN_COMMON // 2 or np.median(par) < self.cfg.min_parallax_deg:
            return None
        pts = np.asarray(pts)
        for k in ks[1:-1]:
            seen = [n for n, i in enumerate(idx) if k in common[i].views]
            uv = np.array([common[idx[n]].views[k] for n in seen]).reshape(-1, 2)
            T = pnp_pose(pts[seen], uv, self.camera.K, bTc)
            if T is not None:
                poses[k] = T
        return poses

    def _vo_predict(self, prev: int, k: int, ids: np.ndarray) -> np.ndarray:
        """Initial world_T_body of keyframe k: PnP on admitted landmarks, else constant velocity."""
        T_prev = self._pose(prev)
        before = prev - 1
        T_cv = T_prev @ inv_T(self._pose(before)) @ T_prev if self.values.exists(X(before)) else T_prev
        obs = [
            (self.values.atPoint3(L(j)), self.book.tracks[j].views[k])
            for j in ids.tolist()
            if self.book.tracks[j].admitted and self.smoother.has(L(j)) and k in self.book.tracks[j].views
        ]
        if obs:
            T = pnp_pose(
                np.array([o[0] for o in obs]), np.array([o[1] for o in obs]), self.camera.K, self.book.body_T_cam
            )
            if T is not None:
                return T
        return T_cv

    def _vo_motion_prior(self, prev: int, k: int) -> gtsam.NonlinearFactor:
        """Weak constant-velocity prior between keyframes prev and k (keeps poses with few landmarks defined)."""
        T_prev = self._pose(prev)
        delta = inv_T(self._pose(prev - 1)) @ T_prev if self.values.exists(X(prev - 1)) else np.eye(4)
        return gtsam.BetweenFactorPose3(
            X(prev), X(k), gtsam.Pose3(delta), gtsam.noiseModel.Diagonal.Sigmas(MOTION_SIGMAS)
        )
