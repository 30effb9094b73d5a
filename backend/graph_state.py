"""The state every part of the estimator works on: the smoother, the latest value of every variable, every
factor (for the batch refinement), keyframe times, preintegrations and per-landmark observation counts, with the
small helpers that edit them. The estimator owns one and passes it to its parts explicitly.
"""

from __future__ import annotations

import logging
from array import array
from collections.abc import Callable, Iterable
from typing import Any

import gtsam
import numpy as np

from backend import factors as fb
from backend.keys import B, L, V, X
from backend.smoother import Smoother, SolverFailure, value_of
from vio.records import StateEstimate

log = logging.getLogger(__name__)

Warn = Callable[[str], None]
__all__ = ["GraphState", "Warn", "value_of"]


class LandmarkArchive:
    """Landmarks dropped from the live bookkeeping, in 16 bytes each: id and projection count (their last value
    stays in `GraphState.values`, which the scale's uncertainty and `--refine` read). A live landmark costs about
    2 KB more (its counts, track and atlas rows); the fixed lag's duplicates of older landmarks come here
    (`GraphState.archive`), so the map of a long capture of one scene grows by little more than its values."""

    def __init__(self) -> None:
        self._ids, self._nobs = array("q"), array("q")

    def __len__(self) -> int:
        return len(self._ids)

    def add(self, j: int, num_obs: int) -> None:
        self._ids.append(j)
        self._nobs.append(num_obs)

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """(ids (M,) int64, projection counts (M,) int64)."""
        return np.frombuffer(self._ids, np.int64).copy(), np.frombuffer(self._nobs, np.int64).copy()


class GraphState:
    """Variables, factors and bookkeeping of one estimator run (see the module docstring)."""

    def __init__(
        self,
        smoother: Smoother,
        calibration: tuple[gtsam.Cal3_S2, gtsam.Pose3],
        pixel_noise: fb.PixelNoise,
        window_keyframes: int,
        warn: Warn,
    ) -> None:
        self.smoother = smoother
        self.K, self.body_P_cam = calibration
        self.pixel_noise = pixel_noise
        self.window_keyframes = window_keyframes  # keyframes refreshed after each update and used to triangulate
        self.warn = warn
        self.values = gtsam.Values()  # latest estimate of every variable ever added
        self.all_factors = gtsam.NonlinearFactorGraph()  # every measurement factor + the initial priors (batch)
        self.t_ns: dict[int, int] = {}  # keyframe index -> time, ns
        self.pims: dict[int, Any] = {}  # k -> preintegration from the keyframe before k
        self.num_obs: dict[int, int] = {}  # landmark id -> projection factors in the graph
        self.last_obs: dict[int, int] = {}  # landmark id -> last keyframe with a projection factor on it
        # `last_obs` turned round (keyframe -> its landmarks), and each landmark's rank of first observation: the
        # background step asks for the latest keyframe's landmarks, in that order (`landmarks_last_seen_at`)
        self._last_seen_at: dict[int, dict[int, None]] = {}
        self._first_seen: dict[int, int] = {}
        self.projections: dict[int, int] = {}  # keyframe index -> projection factors on its pose (run health)
        self.retired: set[int] = set()  # landmarks that left the fixed lag; `values` keeps their last estimate
        self.archived = LandmarkArchive()  # duplicates out of the live bookkeeping (`archive`)
        self.bias = gtsam.imuBias.ConstantBias()  # latest bias estimate (preintegration uses it)
        self.last_k: int | None = None
        self.dirty = False  # True when the smoother holds estimates not yet pulled into `values`

    # ------------------------------------------------------------------ values
    def pose(self, k: int) -> np.ndarray:
        """world_T_body (4, 4) of keyframe k."""
        return self.values.atPose3(X(k)).matrix()

    def set(self, key: int, value: Any) -> None:
        if self.values.exists(key):
            self.values.update(key, value)
        else:
            self.values.insert(key, value)

    def absorb(self, est: gtsam.Values) -> None:
        """Copy every value of `est` into `values` (inserted or replaced), in one call into gtsam."""
        self.values.insert_or_assign(est)

    def sync(self) -> None:
        """Pull the full smoother estimate (every keyframe and landmark) into `values`."""
        if self.dirty:
            try:
                self.absorb(self.smoother.estimate())
            except SolverFailure as exc:
                self.warn(f"final estimate failed ({exc}); keeping the last per-keyframe estimates")
            self.dirty = False

    # ------------------------------------------------------------------ factors
    def add(self, graph: gtsam.NonlinearFactorGraph, factor: gtsam.NonlinearFactor) -> None:
        """Add a measurement factor to the update `graph` and to the whole graph kept for the batch refinement."""
        graph.add(factor)
        self.all_factors.add(factor)

    def add_projection(
        self, graph: gtsam.NonlinearFactorGraph, k: int, j: int, uv: np.ndarray, since_k: int | None = None
    ) -> None:
        """The projection factor of landmark j seen at undistorted pixel uv (2,) in keyframe k; `since_k` is the
        keyframe where the track's unbroken run of views that includes k began (its age sets the noise)."""
        age_s = 0.0 if since_k is None else 1e-9 * (self.t_ns[k] - self.t_ns.get(since_k, self.t_ns[k]))
        self.add(graph, fb.projection_factor(uv, k, j, self.K, self.body_P_cam, self.pixel_noise.at(age_s)))
        self.num_obs[j] = self.num_obs.get(j, 0) + 1
        before = self.last_obs.get(j)
        if before is not None and before != k:
            self._unlist(j, before)
        self.last_obs[j] = k
        self._last_seen_at.setdefault(k, {})[j] = None
        self._first_seen.setdefault(j, len(self._first_seen))
        self.projections[k] = self.projections.get(k, 0) + 1

    def landmarks_last_seen_at(self, k: int) -> list[int]:
        """The landmarks whose last projection factor is in keyframe k, in the order they were first observed: what
        iterating `last_obs` gives, without its cost on a long capture. The order matters to the background step,
        where it sets iSAM2's ordering: another order read p95 59-62 against 41-47 ms in the 60 s orbit's first
        minute."""
        return sorted(self._last_seen_at.get(k, ()), key=self._first_seen.__getitem__)

    def landmark_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every landmark with a value, the archived duplicates included: ids (M,) int64 in ascending order, world
        positions (M, 3) m, projection counts (M,) int64."""
        ids = [j for j in self.num_obs if self.values.exists(L(j))]
        nobs = [self.num_obs[j] for j in ids]
        a_ids, a_nobs = self.archived.arrays()
        live = set(ids)
        for j, n in zip(a_ids.tolist(), a_nobs.tolist(), strict=True):
            if j not in live:  # an id admitted again after its archiving is the live one
                ids.append(j)
                nobs.append(n)
        order = np.argsort(np.asarray(ids, np.int64), kind="stable")
        ids_arr = np.asarray(ids, np.int64)[order]
        pts = np.array([self.values.atPoint3(L(j)) for j in ids_arr.tolist()]).reshape(-1, 3)
        return ids_arr, pts, np.asarray(nobs, np.int64)[order]

    def unlist_retired(self, js: Iterable[int]) -> None:
        """Landmarks that left the fixed lag leave the keyframe -> landmarks index (`landmarks_last_seen_at` is
        asked about the latest keyframe only), so the index holds the window's keyframes alone. Kept, each old
        keyframe's dict held the table it had when the keyframe's ~150 landmarks were first filed there: 1.8 MiB a
        minute of the 60 s orbit (tracemalloc)."""
        for j in js:
            k = self.last_obs.get(j)
            if k is not None:
                self._unlist(j, k)

    def archive(self, j: int) -> None:
        """Old landmark j leaves the live bookkeeping for the archive: it is no longer an old landmark or a count
        here; its value stays in `values` (the factors of an open scale chunk, or all of them for `--refine`, may name
        it). Only for a landmark no new factor will name (a retired one whose track has ended and that
        re-identification no longer offers)."""
        self.archived.add(j, self.num_obs.pop(j, 0))
        self.retired.discard(j)
        k = self.last_obs.pop(j, None)
        if k is not None:
            self._unlist(j, k)
        self._first_seen.pop(j, None)

    def _unlist(self, j: int, k: int) -> None:
        others = self._last_seen_at.get(k)
        if others is None:
            return
        others.pop(j, None)
        if not others:
            del self._last_seen_at[k]

    # ------------------------------------------------------------------ windows
    def window(self, k: int) -> range:
        """Keyframes whose estimates are refreshed after each update and used to triangulate new landmarks."""
        return range(max(k - self.window_keyframes, 0), k + 1)

    def recent_keys(self, k: int) -> list[int]:
        return [key for kk in self.window(k) for key in (X(kk), V(kk), B(kk)) if self.smoother.has(key)]

    def known_poses(self) -> dict[int, np.ndarray]:
        """world_T_body of the keyframes in the window of the latest keyframe."""
        return {k: self.pose(k) for k in self.window(self.last_k) if self.values.exists(X(k))}

    def state(self, k: int, solve_ms: float, use_imu: bool) -> StateEstimate:
        """Keyframe k's estimate (no velocity or bias without the IMU)."""
        if not use_imu:
            return StateEstimate(
                k, self.t_ns[k], self.pose(k), np.zeros(3), np.zeros(3), np.zeros(3), solve_ms=solve_ms
            )
        b = self.values.atConstantBias(B(k))
        return StateEstimate(
            k,
            self.t_ns[k],
            self.pose(k),
            np.asarray(self.values.atVector(V(k))),
            b.gyroscope(),
            b.accelerometer(),
            solve_ms=solve_ms,
        )
