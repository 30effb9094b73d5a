"""Landmark re-identification: new tracks that are landmarks already in the map close loops.

Per keyframe, before its tracks are booked: the pose is predicted from the IMU, every track is described
(gravity-aligned ORB, oriented from the predicted attitude), the landmarks seen by their own tracks get new
snapshots in the atlas (backend/atlas.py), and the tracks the backend has never seen are matched against the
atlas. A matched track is aliased to the old landmark: its views become that landmark's projection factors (the
first one gated by the search radius instead of `max_reprojection_px`, since it may close a loop after drift).
When a later view disagrees with the landmark the alias ends (`unalias`) and the track continues as a landmark of
its own.

Re-observations of old landmarks (unobserved for `defer_keyframes`) wait in a loop batch that enters the
smoother every `flush_keyframes`: a factor on an old landmark makes iSAM2 re-eliminate every clique from that
landmark to the root (most of the graph after a loop), so batching pays that once per flush instead of once per
keyframe (measured on the 60 s orbit: see docs/BENCHMARKS.md). After a flush the landmark sits near the root
(iSAM2 orders the keys of new factors last) and its next views are cheap.
"""

from __future__ import annotations

import itertools

import gtsam
import numpy as np

from backend.atlas import LandmarkAtlas, gravity_angles_deg
from backend.graph_state import GraphState
from backend.keys import L, V, X, landmarks_in, track_of
from backend.landmarks import LandmarkBook
from backend.smoother import SolverFailure
from vio.config import ReidentificationConfig
from vio.descriptors import Describe
from vio.records import ReidentificationEvent

_NEIGHBOURS = list(itertools.product((-1, 0, 1), repeat=3))  # a grid cell and the 26 around it


class Reidentification:
    """Aliases of re-identified tracks, the atlas they are matched against, and the batch of loop factors."""

    def __init__(
        self, cfg: ReidentificationConfig, enabled: bool, book: LandmarkBook, state: GraphState, body_T_cam: np.ndarray
    ) -> None:
        self.cfg, self.enabled, self.book, self.state = cfg, enabled, book, state
        self.body_T_cam = np.asarray(body_T_cam, float)
        self.atlas = LandmarkAtlas(book.K, body_T_cam, cfg)
        self._alias: dict[int, int] = {}  # track segment id -> landmark id it re-identified
        self._alias_rev: dict[int, int] = {}  # landmark id -> track segment id
        self._now: set[int] = set()  # landmarks re-identified at the current keyframe
        self._since_refresh = 0
        self._loops = gtsam.NonlinearFactorGraph()  # re-observations of old landmarks, waiting for the next flush
        self._loop_landmarks: set[int] = set()
        self._loop_budget = cfg.max_loops
        self.num_reidentified = 0
        self.num_loop_flushes = 0
        self.events: list[ReidentificationEvent] = []
        self._grid: dict[tuple[int, int, int], list[int]] = {}  # cells of merge_radius_m -> retired atlas landmarks
        self._cell_of: dict[int, tuple[int, int, int]] = {}
        self.num_merged = 0  # retired landmarks left out of the atlas as duplicates

    def apply_aliases(self, ids: np.ndarray) -> np.ndarray:
        return np.array([self._alias.get(j, j) for j in ids.tolist()], np.int64)

    def gate_px(self, j: int, default_px: float) -> float:
        """Reprojection gate of a new view of admitted landmark j: the search radius while j is aliased."""
        return self.cfg.radius_px if j in self._alias_rev else default_px

    def on_admit(self, j: int, p_world: np.ndarray) -> None:
        """A landmark entered the graph at a steady-state keyframe: it becomes a re-identification candidate."""
        self.atlas.set_position(j, p_world)

    def on_retired(self, j: int, p_world: np.ndarray) -> None:
        """Landmark j left the fixed-lag window at p_world (backend/fixed_lag.py): it stays a candidate there,
        unless it duplicates an older one (`merge_radius_m`: the atlas of a long capture stays the scene's size)."""
        if j not in self.atlas.rows:
            return
        self.atlas.set_position(j, p_world)
        r = self.cfg.merge_radius_m
        if r <= 0:
            return
        cell = tuple(np.floor(np.asarray(p_world, float) / r).astype(np.int64).tolist())
        old = self._cell_of.pop(j, None)
        if old is not None:  # retired before, seen again, retired again: filed where it is now, and kept
            self._grid[old].remove(j)
            self._grid.setdefault(cell, []).append(j)
            self._cell_of[j] = cell
            return
        near = (i for d in _NEIGHBOURS for i in self._grid.get((cell[0] + d[0], cell[1] + d[1], cell[2] + d[2]), ()))
        twin = next(
            (i for i in near if i in self.atlas.rows and np.linalg.norm(self.atlas.position(i) - p_world) <= r), None
        )
        if twin is not None:
            if self.cfg.merge_snapshots:
                self.atlas.absorb(j, twin)
            else:
                self.atlas.forget(j)
            self.num_merged += 1
            if self.cfg.archive_merged and j not in self._loop_landmarks:  # no factor names it again: only its
                # value stays (the scale's chunks, --refine, the output)
                self.book.tracks.pop(j, None)
                src = self._alias_rev.pop(j, None)
                if src is not None:
                    self._alias.pop(src, None)
                self.state.archive(j)
            return
        self._grid.setdefault(cell, []).append(j)
        self._cell_of[j] = cell

    def reidentify(
        self, prev: int, k: int, ids: np.ndarray, uv: np.ndarray, uv_distorted: np.ndarray, describe: Describe
    ) -> np.ndarray:
        """Landmark ids for keyframe k's tracks (undistorted uv (N, 2)) with re-identified new tracks replaced by
        their old landmark."""
        self._now = set()
        if not self.enabled:
            return ids
        self._refresh_atlas()
        st = self.state
        nav = st.pims[k].predict(gtsam.NavState(st.values.atPose3(X(prev)), st.values.atVector(V(prev))), st.bias)
        world_T_body = nav.pose().matrix()
        angles = gravity_angles_deg(world_T_body @ self.body_T_cam, uv, self.book.K)
        desc, ok = describe(uv_distorted, angles)
        seen = np.array([j in self.book.tracks and self.book.tracks[j].admitted for j in ids.tolist()], bool)
        self.atlas.remember(world_T_body, ids[seen], desc[seen], ok[seen])
        new = np.flatnonzero([j not in self.book.tracks for j in ids.tolist()])
        if not len(new):
            return ids
        max_age = self.cfg.max_age_keyframes

        def alive(js: np.ndarray) -> np.ndarray:
            has, retired, last = st.smoother.has, st.retired, st.last_obs
            return np.fromiter(
                ((j in retired or has(L(j))) and (max_age <= 0 or k - last.get(j, k) <= max_age) for j in js.tolist()),
                bool,
                len(js),
            )

        found = self.atlas.match(world_T_body, uv[new], desc[new], ok[new], set(ids.tolist()), alive)
        out = ids.copy()
        for row, lid in found.items():
            if k - st.last_obs.get(lid, k) > self.cfg.defer_keyframes:  # an old landmark: a loop link
                if self._loop_budget <= 0:
                    continue
                self._loop_budget -= 1
            src = int(ids[new[row]])
            k0, uv0 = self.book.tracks[lid].first_view()
            self.events.append(
                ReidentificationEvent(st.t_ns[k], lid, np.array(uv_distorted[new[row]], float), st.t_ns[k0], uv0)
            )
            self._alias[src], self._alias_rev[lid] = lid, src
            out[new[row]] = lid
            self._now.add(lid)
        self.num_reidentified += len(self._now)
        return out

    def _refresh_atlas(self) -> None:
        """Every `refresh_keyframes`, pull all landmark positions from the smoother into the atlas."""
        self._since_refresh += 1
        if self._since_refresh < max(self.cfg.refresh_keyframes, 1):
            return
        self._since_refresh = 0
        try:
            est = self.state.smoother.estimate()
        except SolverFailure:
            return
        rows = self.atlas.rows
        for j in landmarks_in(est.keys()):  # the smoother's only: the atlas' others have left it, their values final
            if j in rows:
                self.atlas.set_position(j, est.atPoint3(L(j)))

    def route(self, graph: gtsam.NonlinearFactorGraph, j: int, k: int) -> gtsam.NonlinearFactorGraph:
        """Where a new view of landmark j goes: the keyframe's graph, or the loop batch when j is an old landmark
        re-identified (not observed for `defer_keyframes`) and waiting for the next flush."""
        if j in self._loop_landmarks:
            return self._loops
        if j in self._now and k - self.state.last_obs.get(j, k) > self.cfg.defer_keyframes:
            self._loop_landmarks.add(j)
            return self._loops
        return graph

    def flush(self, graph: gtsam.NonlinearFactorGraph, k: int) -> None:
        """Every `flush_keyframes`, move the waiting loop factors into the keyframe's graph and renew the budget
        of loop links (`max_loops` old landmarks re-identified per flush period)."""
        if k % max(self.cfg.flush_keyframes, 1):
            return
        self._loop_budget = self.cfg.max_loops
        if self._loops.size():
            graph.push_back(self._loops)
            self.drop_loops()
            self.num_loop_flushes += 1

    def drop_loops(self) -> None:
        """Forget the waiting loop factors (the smoother is being rebuilt)."""
        self._loops = gtsam.NonlinearFactorGraph()
        self._loop_landmarks = set()

    def unalias(self, j: int) -> int:
        """End landmark j's alias; returns the track id that produced j's current view (j's own when not aliased)."""
        src = self._alias_rev.pop(j, None)
        if src is None:
            return track_of(j)
        self._alias.pop(src, None)
        return track_of(src)
