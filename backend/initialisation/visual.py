"""The start without an IMU (`estimator.mode: vision_only`): the first buffered keyframe and the latest one with
enough parallax give an essential matrix on undistorted bearings (`cv2.findEssentialMat` + `cv2.recoverPose`), the
keyframes in between are placed by PnP on the two-view points, then a joint batch solve with a prior on the first
pose and on the second pose's position (which fixes the scale: a unit baseline)."""

from __future__ import annotations

import logging
import time

import gtsam
import numpy as np

from backend.admission import LandmarkAdmission
from backend.graph_state import GraphState
from backend.initialisation.window import Start, elapsed_ms, start_window
from backend.keys import X
from backend.landmarks import LandmarkBook, camera_poses, triangulate
from backend.vision_only import MIN_COMMON, pnp_pose, two_view
from vio.config import LandmarkConfig, VisionOnlyConfig
from vio.geometry import inv_T

log = logging.getLogger(__name__)

MAX_PENDING = 40  # keyframes buffered before the oldest is dropped


class VisualInitialiser:
    """Buffers keyframes until a two-view start succeeds (`add` returns it)."""

    def __init__(
        self,
        cfg: VisionOnlyConfig,
        state: GraphState,
        book: LandmarkBook,
        admission: LandmarkAdmission,
        pixel_sigma: float,
        fx: float,
        landmarks: LandmarkConfig,
    ) -> None:
        self.cfg, self.state, self.book, self.admission = cfg, state, book, admission
        self.thresh_norm = 2.0 * pixel_sigma / fx  # essential-matrix inlier threshold, normalized units
        self.min_parallax_deg = landmarks.min_parallax_deg
        self.pending: list[int] = []

    def add(self, k: int) -> Start | None:
        self.pending.append(k)
        ks = self.pending
        if len(ks) > MAX_PENDING:
            self.pending = ks = ks[1:]
        if len(ks) < 3:
            return None
        poses = self._start_poses(ks)
        if poses is None:
            return None
        t0 = time.perf_counter()
        st, k0, k1 = self.state, ks[0], ks[-1]
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        s_pose, s_base = self.cfg.start_pose_sigma, self.cfg.baseline_sigma
        priors = [
            gtsam.PriorFactorPose3(X(k0), gtsam.Pose3(poses[k0]), gtsam.noiseModel.Isotropic.Sigma(6, s_pose)),
            gtsam.PriorFactorPose3(  # fixes the scale: the second pose's position (rotation free)
                X(k1), gtsam.Pose3(poses[k1]), gtsam.noiseModel.Diagonal.Sigmas(np.array([1e3] * 3 + [s_base] * 3))
            ),
        ]
        for f in priors:
            st.add(graph, f)
        for kk, T in poses.items():
            values.insert(X(kk), gtsam.Pose3(T))
        self.admission.admit_window(poses, graph, values)
        if not start_window(st, self.admission, graph, values, k1, "visual initialisation"):
            self.pending = ks[1:]
            return None
        start = Start("visual", sorted(poses), elapsed_ms(t0))
        log.info("initialised (visual two-view) with %d keyframes, %d landmarks", len(poses), len(st.num_obs))
        self.pending = []
        return start

    def _start_poses(self, ks: list[int]) -> dict[int, np.ndarray] | None:
        """world_T_body of the buffered keyframes (world = body of ks[0], unit camera baseline to ks[-1])."""
        k0, k1 = ks[0], ks[-1]
        common = [tr for tr in self.book.tracks.values() if k0 in tr.views and k1 in tr.views]
        if len(common) < MIN_COMMON:
            return None
        xn0 = self.book.normalized(np.stack([tr.views[k0] for tr in common]))
        xn1 = self.book.normalized(np.stack([tr.views[k1] for tr in common]))
        res = two_view(xn0, xn1, self.thresh_norm)
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
        if len(pts) < MIN_COMMON // 2 or np.median(par) < self.min_parallax_deg:
            return None
        pts = np.asarray(pts)
        for k in ks[1:-1]:
            seen = [n for n, i in enumerate(idx) if k in common[i].views]
            uv = np.array([common[idx[n]].views[k] for n in seen]).reshape(-1, 2)
            T = pnp_pose(pts[seen], uv, self.book.K, bTc)
            if T is not None:
                poses[k] = T
        return poses
