"""The visual-inertial estimator: one keyframe at a time into an iSAM2 (or fixed-lag) smoother.

Per keyframe k: a `CombinedImuFactor` from k-1 (preintegrated with the latest bias estimate), projection factors
of admitted landmarks, newly admitted landmarks with all their views, and known-position factors. The first
`init_window_s` of keyframes are buffered for initialisation (static or moving start, then a joint LM refinement
of the window). A solver exception or a tracking loss does not end the run: the smoother is rebuilt from the last
good state (priors on its pose, velocity and bias), landmarks re-enter through admission, and the event is
recorded in `recoveries`.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import gtsam
import numpy as np

from backend import factors as fb
from backend.anchoring import PositionAnchor
from backend.initialisation import static_start
from backend.keys import B, L, V, X
from backend.landmarks import LandmarkBook
from backend.reobserve import Describe, Reidentification
from backend.smoother import Smoother, SolverFailure, batch_solve, first_line
from backend.startup import WindowInitialiser
from backend.visual_only import VisualOnly
from vio.config import BackendConfig
from vio.records import CameraCalib, FeatureTracks, ImuSeries, StateEstimate

log = logging.getLogger(__name__)

# Preintegrate(t0_ns, t1_ns, bias) -> object with `.pim` (PreintegratedCombinedMeasurements) and `.gap` (bool).
Preintegrate = Callable[[int, int, gtsam.imuBias.ConstantBias], Any]


def _get(values: gtsam.Values, key: int) -> Any:
    """The value of a key of any of the four kinds (X pose, V velocity, B bias, L point)."""
    sym = chr(gtsam.Symbol(key).chr())
    if sym == "x":
        return values.atPose3(key)
    if sym == "v":
        return values.atVector(key)
    if sym == "b":
        return values.atConstantBias(key)
    return values.atPoint3(key)


class VioEstimator(WindowInitialiser, VisualOnly, Reidentification):
    """Tightly coupled visual-inertial smoothing. Feed keyframes with `add_keyframe`, then call `finish`."""

    def __init__(
        self,
        camera: CameraCalib,
        imu: ImuSeries,
        preintegrate: Preintegrate,
        cfg: BackendConfig,
        bias_sigma_acc: float = 0.1,
        bias_sigma_gyro: float = 0.01,
        positions: list[tuple[int, np.ndarray, float]] | None = None,
    ) -> None:
        self.camera, self.imu, self.preintegrate, self.cfg = camera, imu, preintegrate, cfg
        self.bias_sigma_acc, self.bias_sigma_gyro = bias_sigma_acc, bias_sigma_gyro
        self.K, self.body_P_cam = fb.calibration(camera)
        self.noise = fb.pixel_noise(cfg.pixel_sigma, cfg.huber_k)
        self.book = LandmarkBook(camera.K, camera.body_T_cam, cfg)
        self.smoother = Smoother(cfg)
        max_dt = 0.5 / max(camera.rate_hz, 1.0)
        self.anchor = PositionAnchor(positions, max_dt) if positions else None
        self.t_ns: dict[int, int] = {}  # keyframe index -> time
        self.pending: list[int] = []  # keyframes waiting for initialisation
        self.pims: dict[int, Any] = {}  # k -> preintegration from the keyframe before k
        self.values = gtsam.Values()  # latest estimate of every variable ever added
        self.all_factors = gtsam.NonlinearFactorGraph()  # every measurement factor + the initial priors (batch)
        self.initialised = False
        self.last_k: int | None = None
        self.bias = gtsam.imuBias.ConstantBias()
        self.timings_ms: list[float] = []
        self.recoveries: list[dict[str, Any]] = []
        self.warnings: list[str] = []
        self.init_kind = ""
        self.num_obs: dict[int, int] = {}  # track id -> projection factors in the graph
        self.num_still = 0  # keyframes with a zero-velocity update
        self.num_splits = 0  # tracks that drifted off their landmark and became a new one
        self._dirty = False  # True when the smoother holds estimates not yet pulled into `values`
        self._segments: dict[int, tuple[int, int]] = {}  # track id -> (segment, views in the segment)
        self._init_reid()

    # ----------------------------------------------------------------- helpers
    def _pose(self, k: int) -> np.ndarray:
        return self.values.atPose3(X(k)).matrix()

    def _window(self, k: int) -> range:
        """Keyframes whose estimates are refreshed after each update and used to triangulate new landmarks."""
        return range(max(k - 3 * max(self.cfg.max_track_keyframes, 10), 0), k + 1)

    def _recent_keys(self, k: int) -> list[int]:
        return [key for kk in self._window(k) for key in (X(kk), V(kk), B(kk)) if self.smoother.has(key)]

    def _known_poses(self) -> dict[int, np.ndarray]:
        return {k: self._pose(k) for k in self._window(self.last_k) if self.values.exists(X(k))}

    def _sync(self) -> None:
        """Pull the full smoother estimate (every keyframe and landmark) into `values`."""
        if self._dirty:
            try:
                self._absorb(self.smoother.estimate())
            except SolverFailure as exc:
                self._warn(f"final estimate failed ({exc}); keeping the last per-keyframe estimates")
            self._dirty = False

    def _warn(self, msg: str) -> None:
        log.warning(msg)
        self.warnings.append(msg)

    def _state(self, k: int, solve_ms: float) -> StateEstimate:
        if not self.cfg.use_imu:  # no velocity or bias keys
            return StateEstimate(
                k, self.t_ns[k], self._pose(k), np.zeros(3), np.zeros(3), np.zeros(3), solve_ms=solve_ms
            )
        b = self.values.atConstantBias(B(k))
        return StateEstimate(
            k,
            self.t_ns[k],
            self._pose(k),
            np.asarray(self.values.atVector(V(k))),
            b.gyroscope(),
            b.accelerometer(),
            solve_ms=solve_ms,
        )

    def _set(self, key: int, value: Any) -> None:
        if self.values.exists(key):
            self.values.update(key, value)
        else:
            self.values.insert(key, value)

    def _absorb(self, est: gtsam.Values) -> None:
        for key in est.keys():
            self._set(key, _get(est, key))

    def _position_factors(self, k: int) -> list[gtsam.NonlinearFactor]:
        """GPS-like factors of known positions: keyframe k's match, plus all earlier matches on first alignment."""
        if self.anchor is None:
            return []
        matched = self.anchor.match(k, self.t_ns[k]) is not None
        if self.anchor.try_align(self._known_positions_est()):
            todo = [pair for pair in self.anchor.pairs if self.values.exists(X(pair[0]))]
            log.info("known positions aligned (yaw + translation) after %d matches", len(todo))
        elif self.anchor.known_T_est is not None and matched:
            todo = self.anchor.pairs[-1:]
        else:
            return []
        out = [fb.position_factor(kk, self.anchor.to_est(p), sigma) for kk, p, sigma in todo]
        self.anchor.num_factors += len(out)
        return out

    def _known_positions_est(self) -> dict[int, np.ndarray]:
        return {
            kk: self.values.atPose3(X(kk)).translation() for kk, _, _ in self.anchor.pairs if self.values.exists(X(kk))
        }

    # ----------------------------------------------------------------- public
    def add_keyframe(self, t_ns: int, tracks: FeatureTracks, describe: Describe | None = None) -> list[StateEstimate]:
        """Add a keyframe (tracks in distorted pixels); returns the estimates produced (several after init).

        `describe` (frontend.descriptors.KeyframeDescriber.describe of the keyframe image) enables landmark
        re-identification (backend/reobserve.py); without it every new track is a new landmark.
        """
        k = 0 if self.last_k is None else self.last_k + 1
        self.t_ns[k] = int(t_ns)
        uv = fb.undistorted_px(self.camera, tracks.uv)
        if self.last_k is not None and self.cfg.use_imu:
            pre = self.preintegrate(self.t_ns[self.last_k], t_ns, self.bias)
            self.pims[k] = pre.pim
            if getattr(pre, "gap", False):
                self._warn(f"IMU gap before keyframe {k} (t={t_ns} ns); its inertial factor is weak")
        prev, self.last_k = self.last_k, k
        ids = self._apply_aliases(self._segment_ids(tracks.ids))
        if self.initialised and describe is not None:
            ids = self._reidentify(prev, k, ids, uv, tracks.uv, describe)
        self.book.observe(k, ids, uv)
        if not self.initialised:
            self.pending.append(k)
            return self._try_initialise() if self.cfg.use_imu else self._vo_try_initialise()
        return [self._step(prev, k, ids)]

    def _segment_ids(self, track_ids: np.ndarray) -> np.ndarray:
        """Landmark ids: the track id plus `segment << 40`. A new segment starts when a view disagrees with the
        landmark (`_split_track`) or, optionally, every `max_track_keyframes` views.

        KLT tracks drift by pixels over seconds (measured on the eqvio tracks against the EuRoC ground truth:
        median 0.4 px within 10 frames, 3 px after 40), so one long track may become several landmarks.
        """
        n = self.cfg.max_track_keyframes
        out = np.asarray(track_ids, np.int64).copy()
        for i, j in enumerate(out.tolist()):
            seg, count = self._segments.get(j, (0, 0))
            if 0 < n <= count:
                seg, count = seg + 1, 0
            self._segments[j] = (seg, count + 1)
            out[i] = j + (seg << 40)
        return out

    def finish(self, refine: bool = False) -> dict[str, Any]:
        """Final estimate of all keyframes (and a batch LM refinement when asked); returns counts."""
        info: dict[str, Any] = {"refined": False}
        self._sync()
        if refine and self.initialised:
            t0 = time.perf_counter()
            try:
                self._absorb(batch_solve(self.all_factors, self.values))
                info["refined"] = True
            except RuntimeError as exc:
                self._warn(f"batch refinement failed ({first_line(exc)}); keeping the online estimate")
            info["refine_s"] = time.perf_counter() - t0
        return info

    def states(self) -> list[StateEstimate]:
        """The current (smoothed) estimate of every initialised keyframe, in time order (in the known positions'
        frame when they were given and aligned)."""
        self._sync()
        out = [self._state(k, 0.0) for k in sorted(self.t_ns) if self.values.exists(X(k))]
        T = self._output_T()
        if T is None:
            return out
        return [replace(s, world_T_body=T @ s.world_T_body, v_world=T[:3, :3] @ s.v_world) for s in out]

    def _output_T(self) -> np.ndarray | None:  # noqa: N802
        return None if self.anchor is None else self.anchor.known_T_est

    def landmarks(self, sync: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(M,) track ids, (M, 3) world points (m), (M,) number of projection factors.

        With `sync=False` the latest per-keyframe values are used as they are (cheap; for live display).
        """
        if sync:
            self._sync()
        ids = [j for j in sorted(self.num_obs) if self.values.exists(L(j))]
        pts = np.array([self.values.atPoint3(L(j)) for j in ids]).reshape(-1, 3)
        T = self._output_T()
        if T is not None:
            pts = pts @ T[:3, :3].T + T[:3, 3]
        return np.asarray(ids, np.int64), pts, np.array([self.num_obs[j] for j in ids], np.int64)

    # ----------------------------------------------------------------- steady state
    def _add(self, graph: gtsam.NonlinearFactorGraph, factor: gtsam.NonlinearFactor) -> None:
        graph.add(factor)
        self.all_factors.add(factor)

    def _add_projection(self, graph: gtsam.NonlinearFactorGraph, k: int, j: int, uv: np.ndarray) -> None:
        self._add(graph, fb.projection_factor(uv, k, j, self.K, self.body_P_cam, self.noise))
        self.num_obs[j] = self.num_obs.get(j, 0) + 1
        self._last_obs[j] = k

    def _step(self, prev: int, k: int, ids: np.ndarray) -> StateEstimate:
        t0 = time.perf_counter()
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        t_s = self.t_ns[k] * 1e-9
        if self.cfg.use_imu:
            pose_prev = self.values.atPose3(X(prev))
            v_prev = self.values.atVector(V(prev))
            nav = self.pims[k].predict(gtsam.NavState(pose_prev, v_prev), self.bias)
            pred = nav.pose()
            values.insert(V(k), nav.velocity())
            values.insert(B(k), self.bias)
            self._set(V(k), nav.velocity())
            self._set(B(k), self.bias)
            self._add(graph, fb.imu_factor(prev, k, self.pims[k]))
            if self._is_still(prev, k, ids):
                for f in fb.no_motion_factors(prev, k):
                    self._add(graph, f)
                self.num_still += 1
            stamps = {X(k): t_s, V(k): t_s, B(k): t_s}
        else:
            pred = gtsam.Pose3(self._vo_predict(prev, k, ids))
            self._add(graph, self._vo_motion_prior(prev, k))
            stamps = {X(k): t_s}
        values.insert(X(k), pred)
        self._set(X(k), pred)
        for f in self._position_factors(k):
            self._add(graph, f)
        poses = None
        for j in ids.tolist():
            tr = self.book.tracks[j]
            if tr.admitted:
                gate = self.cfg.reid_radius_px if j in self._alias_rev else self.cfg.max_reprojection_px
                if self.smoother.has(L(j)) and self._consistent(j, pred.matrix(), tr.views[k], gate):
                    self._add_projection(self._loop_graph(graph, j, k), k, j, tr.views[k])
                    stamps[L(j)] = t_s
                elif self.smoother.has(L(j)):
                    self._split_track(j, k)
                continue
            if len(tr.views) < self.cfg.min_views:
                continue
            poses = self._known_poses() if poses is None else poses
            p = self.book.try_admit(j, poses)
            if p is None:
                continue
            values.insert(L(j), p)
            self._set(L(j), p)
            self.atlas.set_position(j, p)
            stamps[L(j)] = t_s
            graph.add(fb.landmark_prior(j, p, self.cfg.landmark_prior_sigma_m))
            for kk, uv in tr.views.items():
                if kk in poses and self.smoother.has(X(kk)) or kk == k:
                    self._add_projection(graph, kk, j, uv)
            tr.admitted = True
        self._flush_loops(graph, k)
        try:
            self.smoother.update(graph, values, stamps)
            est = self.smoother.estimate_keys(self._recent_keys(k))
            self._dirty = True
        except SolverFailure as exc:
            est = self._recover(prev, k, str(exc))
        self._absorb(est)
        if self.cfg.use_imu:
            self.bias = self.values.atConstantBias(B(k))
        ms = (time.perf_counter() - t0) * 1e3
        self.timings_ms.append(ms)
        return self._state(k, ms)

    def _consistent(self, j: int, world_T_body: np.ndarray, uv: np.ndarray, gate_px: float) -> bool:
        """A new view of landmark j reprojects within `gate_px` from the predicted pose."""
        p = self.smoother.estimate_keys([L(j)]).atPoint3(L(j))
        err, depth = self.book.reprojection_px(world_T_body, p, uv)
        return depth > 0.05 and err <= gate_px

    def _split_track(self, j: int, k: int) -> None:
        """Track drift: the view of keyframe k disagrees with landmark j, so it starts a new landmark."""
        base = self._unalias(j)
        seg, _ = self._segments.get(base, (j >> 40, 0))
        new = base + ((seg + 1) << 40)
        self._segments[base] = (seg + 1, 1)
        uv = self.book.tracks[j].views.pop(k)
        self.book.observe(k, np.array([new]), uv[None])
        self.num_splits += 1

    def _is_still(self, prev: int, k: int, ids: np.ndarray) -> bool:
        """At rest between keyframes prev and k: the tracks shared with prev moved less than `still_max_px`
        (median) and the IMU over the last `still_window_s` passes the static test (zero-velocity update)."""
        if self.cfg.still_max_px <= 0:
            return False
        moved = [
            np.linalg.norm(tr.views[k] - tr.views[prev])
            for tr in (self.book.tracks[j] for j in ids.tolist())
            if prev in tr.views
        ]
        if len(moved) < 5 or float(np.median(moved)) > self.cfg.still_max_px:
            return False
        t1 = self.t_ns[k]
        return static_start(self.imu, t1 - int(self.cfg.still_window_s * 1e9), t1, self.cfg) is not None

    def _recover(self, prev: int, k: int, reason: str) -> gtsam.Values:
        """Rebuild the smoother from the last good state (prev) plus keyframe k's inertial factor."""
        self._warn(f"solver failed at keyframe {k} ({reason}); rebuilding from keyframe {prev}")
        self.recoveries.append({"k": k, "t_ns": self.t_ns[k], "reason": reason, "restart_from_k": prev})
        self.smoother.reset()
        self._drop_loops()
        self.book.forget_before(prev)
        self.num_obs = {j: n for j, n in self.num_obs.items() if self.values.exists(L(j))}
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        graph.add(
            gtsam.PriorFactorPose3(X(prev), self.values.atPose3(X(prev)), gtsam.noiseModel.Isotropic.Sigma(6, 1e-3))
        )
        if self.cfg.use_imu:
            graph.add(fb.velocity_prior(prev, self.values.atVector(V(prev)), 0.05))
            graph.add(fb.bias_prior(prev, self.values.atConstantBias(B(prev)), 0.02, 1e-3))
            graph.add(fb.imu_factor(prev, k, self.pims[k]))
            keys = (X(prev), V(prev), B(prev), X(k), V(k), B(k))
        else:
            graph.add(self._vo_motion_prior(prev, k))
            keys = (X(prev), X(k))
        for key in keys:
            values.insert(key, _get(self.values, key))
        t_s = self.t_ns[k] * 1e-9
        try:
            self.smoother.update(graph, values, {key: t_s for key in values.keys()})
            return self.smoother.estimate()
        except SolverFailure as exc:  # keep the prediction; the next keyframe rebuilds again from here
            self._warn(f"rebuild at keyframe {k} failed too ({exc}); keeping the inertial prediction")
            self.smoother.reset()
            return values
