"""Landmark re-identification inside the estimator (a mixin of `VioEstimator`).

Per keyframe, before its tracks are booked: the pose is predicted from the IMU, every track is described
(gravity-aligned ORB, oriented from the predicted attitude), the landmarks seen by their own tracks get new
snapshots in the atlas, and the tracks the backend has never seen are matched against the atlas. A matched track
is aliased to the old landmark: its views become that landmark's projection factors (the first one gated by the
search radius instead of `max_reprojection_px`, since it may close a loop after drift). When a later view
disagrees with the landmark (`_split_track`) the alias ends and the track continues as a landmark of its own.
"""

from __future__ import annotations

from collections.abc import Callable

import gtsam
import numpy as np

from backend.atlas import LandmarkAtlas, gravity_angles_deg
from backend.keys import L, V, X
from backend.smoother import SolverFailure

# describe(uv_px distorted (N, 2), angle_deg (N,)) -> ((N, 32) uint8 descriptors, (N,) bool described)
Describe = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]

_TRACK_MASK = (1 << 40) - 1


class Reidentification:
    """Mixin: needs `camera`, `cfg`, `book`, `smoother`, `values`, `pims`, `bias` of the estimator."""

    def _init_reid(self) -> None:
        self.atlas = LandmarkAtlas(self.camera.K, self.camera.body_T_cam, self.cfg)
        self._alias: dict[int, int] = {}  # track segment id -> landmark id it re-identified
        self._alias_rev: dict[int, int] = {}  # landmark id -> track segment id
        self._reid_now: set[int] = set()  # landmarks re-identified at the current keyframe
        self.num_reidentified = 0
        self.reid_events: list[tuple[int, int, np.ndarray]] = []  # (t_ns, landmark id, distorted pixel (2,))
        self._since_refresh = 0
        self._last_obs: dict[int, int] = {}  # landmark id -> last keyframe with a projection factor on it
        self._loops = gtsam.NonlinearFactorGraph()  # re-observations of old landmarks, waiting for the next flush
        self._loop_landmarks: set[int] = set()
        self.num_loop_flushes = 0
        self._loop_budget = self.cfg.reid_max_loops

    def _apply_aliases(self, ids: np.ndarray) -> np.ndarray:
        return np.array([self._alias.get(j, j) for j in ids.tolist()], np.int64)

    def _reidentify(
        self, prev: int, k: int, ids: np.ndarray, uv: np.ndarray, uv_distorted: np.ndarray, describe: Describe
    ) -> np.ndarray:
        """Landmark ids for keyframe k's tracks with re-identified new tracks replaced by their old landmark."""
        self._reid_now = set()
        if not self.cfg.reid or not self.cfg.use_imu:
            return ids
        self._refresh_atlas()
        state = gtsam.NavState(self.values.atPose3(X(prev)), self.values.atVector(V(prev)))
        nav = self.pims[k].predict(state, self.bias)
        world_T_body = nav.pose().matrix()
        angles = gravity_angles_deg(world_T_body @ self.camera.body_T_cam, uv, self.book.K)
        desc, ok = describe(uv_distorted, angles)
        seen = np.array([j in self.book.tracks and self.book.tracks[j].admitted for j in ids.tolist()], bool)
        self.atlas.remember(world_T_body, ids[seen], desc[seen], ok[seen])
        new = np.flatnonzero([j not in self.book.tracks for j in ids.tolist()])
        if not len(new):
            return ids
        max_age = self.cfg.reid_max_age_keyframes

        def alive(j: int) -> bool:
            return self.smoother.has(L(j)) and (max_age <= 0 or k - self._last_obs.get(j, k) <= max_age)

        found = self.atlas.match(world_T_body, uv[new], desc[new], ok[new], set(ids.tolist()), alive)
        out = ids.copy()
        for row, lid in found.items():
            if k - self._last_obs.get(lid, k) > self.cfg.reid_defer_keyframes:  # an old landmark: a loop link
                if self._loop_budget <= 0:
                    continue
                self._loop_budget -= 1
            src = int(ids[new[row]])
            self.reid_events.append((self.t_ns[k], lid, np.array(uv_distorted[new[row]], float)))
            self._alias[src], self._alias_rev[lid] = lid, src
            out[new[row]] = lid
            self._reid_now.add(lid)
        self.num_reidentified += len(self._reid_now)
        return out

    def _refresh_atlas(self) -> None:
        """Every `reid_refresh_keyframes`, pull all landmark positions from the smoother into the atlas."""
        self._since_refresh += 1
        if self._since_refresh < max(self.cfg.reid_refresh_keyframes, 1):
            return
        self._since_refresh = 0
        try:
            est = self.smoother.estimate()
        except SolverFailure:
            return
        for j in list(self.atlas.rows):
            if est.exists(L(j)):
                self.atlas.set_position(j, est.atPoint3(L(j)))

    def _loop_graph(self, graph: gtsam.NonlinearFactorGraph, j: int, k: int) -> gtsam.NonlinearFactorGraph:
        """Where a new view of landmark j goes: the keyframe's graph, or the loop batch when j is an old landmark
        re-identified (not observed for `reid_defer_keyframes`) and waiting for the next flush.

        A factor on an old landmark makes iSAM2 re-eliminate every clique from that landmark to the root (most of
        the graph after a loop); batching them pays that once per flush instead of once per keyframe (measured on
        the 60 s orbit: see docs/BENCHMARKS.md). After a flush the landmark sits near the root (iSAM2 orders the
        keys of new factors last) and its next views are cheap.
        """
        if j in self._loop_landmarks:
            return self._loops
        if j in self._reid_now and k - self._last_obs.get(j, k) > self.cfg.reid_defer_keyframes:
            self._loop_landmarks.add(j)
            return self._loops
        return graph

    def _flush_loops(self, graph: gtsam.NonlinearFactorGraph, k: int) -> None:
        """Every `reid_flush_keyframes`, move the waiting loop factors into the keyframe's graph and renew the
        budget of loop links (`reid_max_loops` old landmarks re-identified per flush period)."""
        if k % max(self.cfg.reid_flush_keyframes, 1):
            return
        self._loop_budget = self.cfg.reid_max_loops
        if self._loops.size():
            graph.push_back(self._loops)
            self._drop_loops()
            self.num_loop_flushes += 1

    def _drop_loops(self) -> None:
        self._loops = gtsam.NonlinearFactorGraph()
        self._loop_landmarks = set()

    def _unalias(self, j: int) -> int:
        """The track id base that produced landmark j's current view (j's own base when not aliased)."""
        src = self._alias_rev.pop(j, None)
        if src is None:
            return j & _TRACK_MASK
        self._alias.pop(src, None)
        return src & _TRACK_MASK
