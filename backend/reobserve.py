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
        self._since_refresh = 0

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
        alive = lambda j: self.smoother.has(L(j))  # noqa: E731
        found = self.atlas.match(world_T_body, uv[new], desc[new], ok[new], set(ids.tolist()), alive)
        out = ids.copy()
        for row, lid in found.items():
            src = int(ids[new[row]])
            self._alias[src], self._alias_rev[lid] = lid, src
            out[new[row]] = lid
            self._reid_now.add(lid)
        self.num_reidentified += len(found)
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
        for j in self.atlas.entries:
            if est.exists(L(j)):
                self.atlas.set_position(j, est.atPoint3(L(j)))

    def _unalias(self, j: int) -> int:
        """The track id base that produced landmark j's current view (j's own base when not aliased)."""
        src = self._alias_rev.pop(j, None)
        if src is None:
            return j & _TRACK_MASK
        self._alias.pop(src, None)
        return src & _TRACK_MASK
