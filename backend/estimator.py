"""The visual-inertial estimator: one keyframe at a time into an iSAM2 (or fixed-lag) smoother.

Per keyframe k: a `CombinedImuFactor` from k-1 (preintegrated with the latest bias estimate), projection factors
of admitted landmarks, newly admitted landmarks with all their views, and known-position factors. The first
keyframes are buffered until a start succeeds (backend/initialisation/). A solver exception or a tracking loss
does not end the run: the smoother is rebuilt from the last good state (backend/recovery.py).

`VioEstimator` composes parts that share one `GraphState` passed to each explicitly: the landmark book and its
admission, track segments, re-identification, the position anchor, recovery, and an initialiser. Each part gets
its own config section.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import gtsam
import numpy as np

from backend import deferred
from backend import factors as fb
from backend.admission import LandmarkAdmission
from backend.anchoring import KnownPosition, PositionAnchor
from backend.blind_admission import BlindAdmission
from backend.fixed_lag import OldLandmarks
from backend.graph_state import GraphState
from backend.initialisation.inertial import InertialInitialiser
from backend.initialisation.visual import VisualInitialiser
from backend.initialisation.window import Start
from backend.keys import B, L, V, X, track_of
from backend.landmarks import LandmarkBook
from backend.offset_replay import REPLAY_MIN_PAIRS, KeptKeyframe, OffsetReplay
from backend.recovery import Recovery
from backend.reidentification import Reidentification
from backend.scale_chunks import ScaleChunks
from backend.segments import TrackSegments
from backend.smoother import Smoother, SolverFailure, batch_solve, first_line
from backend.time_offset import CameraTiming
from backend.uncertainty import ScaleUncertainty, scale_uncertainty
from backend.view_gate import consistent, reprojections
from backend.vision_only import VisionOnlyMotion
from backend.zero_velocity import is_still
from vio.config import Config
from vio.descriptors import Describe
from vio.records import CameraCalib, EstimatorStats, FeatureTracks, ImuSeries, LandmarkMap, StateEstimate

log = logging.getLogger(__name__)

# Preintegrate(t0_ns, t1_ns, bias) -> object with `.pim` (PreintegratedCombinedMeasurements) and `.gap` (bool).
Preintegrate = Callable[[int, int, gtsam.imuBias.ConstantBias], Any]
PRUNE_MARGIN = 20  # keyframes kept beyond the oldest one any part of the estimator looks back to


class VioEstimator:
    """Tightly coupled visual-inertial smoothing. Feed keyframes with `add_keyframe`, then call `finish`."""

    def __init__(
        self,
        camera: CameraCalib,
        imu: ImuSeries,
        preintegrate: Preintegrate,
        cfg: Config,
        positions: list[KnownPosition] | None = None,
        unique_track_ids: bool = False,
    ) -> None:
        self.camera, self.imu, self.preintegrate = camera, imu, preintegrate
        self.unique_track_ids = unique_track_ids  # the tracks' source never reuses an id (the tracker): lost tracks
        # can be forgotten altogether (`_prune`); tracks read from a file may reuse ids
        self.positions = positions
        self.replay = OffsetReplay(
            cfg.camera.time_offset_replay_s, cfg.camera.estimate_time_offset and cfg.estimator.use_imu
        )
        self._build(cfg)

    def _build(self, cfg: Config) -> None:
        """Every part afresh, with nothing in the graph (at the start, and to re-run it: backend/offset_replay.py)."""
        self.cfg, positions, camera, imu = cfg, self.positions, self.camera, self.imu
        self.use_imu = cfg.estimator.use_imu
        self._warnings: list[str] = []
        self.state = GraphState(
            Smoother(cfg.smoother),
            fb.calibration(camera),
            fb.PixelNoise(cfg.estimator.pixel_sigma, cfg.estimator.pixel_sigma_per_s, cfg.estimator.huber_k),
            3 * max(cfg.landmarks.max_track_keyframes, 10),
            self._warn,
        )
        self.timing = CameraTiming(cfg.camera, camera, imu, self.state, self.use_imu)
        self.book = LandmarkBook(camera.K, camera.body_T_cam, cfg.landmarks)
        self.admission = LandmarkAdmission(self.book, self.state, cfg.landmarks.prior_sigma_m)
        self.segments = TrackSegments(cfg.landmarks.max_track_keyframes)
        self.old = OldLandmarks(self.state, cfg.smoother.map_sigma_m)  # fixed lag only (backend/fixed_lag.py)
        self.reidentification = Reidentification(
            cfg.reidentification,
            cfg.reidentification.enabled and self.use_imu,
            self.book,
            self.state,
            camera.body_T_cam,
        )
        max_dt = 0.5 / max(camera.rate_hz, 1.0)
        self.anchor = PositionAnchor(positions, max_dt) if positions else None
        self.recovery = Recovery(cfg.recovery, self.state)
        self.vision = VisionOnlyMotion(cfg.vision_only, self.state, self.book)
        self.blind = BlindAdmission(cfg.blind_admission, self.state, self.book, self.admission)
        if self.use_imu:
            self.initialiser: InertialInitialiser | VisualInitialiser = InertialInitialiser(
                cfg.initialisation,
                self.state,
                self.book,
                self.admission,
                imu,
                camera,
                cfg.initialisation.alignment_pixel_sigma,
                self.anchor,
            )
        else:
            self.initialiser = VisualInitialiser(
                cfg.vision_only,
                self.state,
                self.book,
                self.admission,
                cfg.estimator.pixel_sigma,
                camera.fx,
                cfg.landmarks,
            )
        self._init_kind = ""  # the start that succeeded: static | moving | visual
        self._timings_ms: list[float] = []
        self._num_still = 0  # keyframes with a zero-velocity update
        self._still_k: set[int] = set()  # keyframes held by the phone being at rest (run health, blind admission)
        self._num_variables: list[int] = []  # variables in the smoother after each steady-state keyframe
        self._cpu_ms: list[float] = []  # CPU time of this process in each steady-state keyframe's update, ms
        self._background_ms: list[tuple[float, float]] = []  # (wall, CPU) ms of each background step
        self._chores_k: int | None = None  # the keyframe whose housekeeping (`_chores`) is still to do
        self._scale: ScaleUncertainty | None = None  # from the graph, after finish()
        self._chunks: ScaleChunks | None = None  # bounded memory: fixed lag, factors not kept (backend/scale_chunks.py)
        if cfg.smoother.kind == "fixed_lag" and not cfg.smoother.keep_factors and not cfg.run.refine:
            compute = self.use_imu and cfg.estimator.scale_uncertainty
            self._chunks = ScaleChunks(cfg.landmarks.prior_sigma_m, compute)

    @property
    def initialised(self) -> bool:
        return bool(self._init_kind)

    def _warn(self, msg: str) -> None:
        log.warning(msg)
        self._warnings.append(msg)

    # ----------------------------------------------------------------- public
    def add_keyframe(self, t_ns: int, tracks: FeatureTracks, describe: Describe | None = None) -> list[StateEstimate]:
        """Add a keyframe (tracks in distorted pixels, `t_ns` the frame's camera time); returns the estimates
        produced (several after the start; every keyframe's after the start re-run, backend/offset_replay.py). The
        keyframe's pose is placed in IMU time and each view moved to it (backend/time_offset.py: the camera-IMU
        offset and the rolling shutter).

        `describe` (frontend.descriptors.KeyframeDescriber.describe of the keyframe image) enables landmark
        re-identification (backend/reidentification.py); without it every new track is a new landmark.
        """
        st = self.state
        self.background()  # a no-op when the caller ran it after the last keyframe (the pipeline does)
        k = 0 if st.last_k is None else st.last_k + 1
        t_cam_ns, t_ns = t_ns, self.timing.pose_time_ns(t_ns)
        if st.last_k is not None and t_ns <= st.t_ns[st.last_k]:
            raise ValueError(f"keyframe time {t_ns} ns is not after the previous keyframe's ({st.t_ns[st.last_k]} ns)")
        self.replay.keep(t_cam_ns, tracks, describe, self.timing.offset_s)
        st.t_ns[k] = t_ns
        uv = self.timing.correct(tracks, fb.undistorted_px(self.camera, tracks.uv))
        if st.last_k is not None and self.use_imu:
            pre = self.preintegrate(st.t_ns[st.last_k], t_ns, st.bias)
            st.pims[k] = pre.pim
            if getattr(pre, "gap", False):
                self._warn(f"IMU gap before keyframe {k} (t={t_ns} ns); its inertial factor is weak")
        prev, st.last_k = st.last_k, k
        ids = self.reidentification.apply_aliases(self.segments.landmark_ids(tracks.ids))
        if self.initialised and describe is not None:
            ids = self.reidentification.reidentify(prev, k, ids, uv, tracks.uv, describe)
        self.book.observe(k, ids, uv)
        self.timing.placed(k, ids, uv)
        if not self.initialised:
            start = self.initialiser.add(k)
            return [] if start is None else self._started(start)
        state = self._step(prev, k, ids)
        self.timing.after_step(k)
        offset_s = (
            self.timing.converged(self.cfg.camera.time_offset_replay_sigma_s, REPLAY_MIN_PAIRS)
            if self.replay.kept
            else None
        )
        kept = self.replay.due(offset_s)
        return [state] if kept is None else self._replayed(kept, offset_s)

    def _replayed(self, kept: list[KeptKeyframe], offset_s: float) -> list[StateEstimate]:
        """Start again with the offset fixed at `offset_s` and re-run the kept keyframes (backend/offset_replay.py);
        returns every keyframe's estimate. The first pass's per-keyframe figures stay, the re-run's time is added
        to the keyframe that triggered it."""
        t0, c0 = time.perf_counter(), time.process_time()
        first, pairs = self.timing.report(), self.timing.num_pairs
        lists = (self._timings_ms, self._cpu_ms, self._num_variables, self._background_ms)
        self._build(replace(self.cfg, camera=replace(self.cfg.camera, time_offset_s=offset_s)))
        self.timing.start_known(first.after_initialisation_s, first.initial_s, pairs)
        for kf in kept:
            try:
                self.add_keyframe(kf.t_ns, kf.tracks, kf.describe)
            except (RuntimeError, ValueError) as exc:  # as the pipeline does: one bad keyframe never ends the run
                self._warn(f"offset re-run: keyframe at t={kf.t_ns} ns skipped: {type(exc).__name__}: {exc}")
        self._timings_ms, self._cpu_ms, self._num_variables, self._background_ms = lists
        if self._timings_ms:
            self._timings_ms[-1] += (time.perf_counter() - t0) * 1e3
        if self._cpu_ms:
            self._cpu_ms[-1] += (time.process_time() - c0) * 1e3
        placed = [kf.placed_s for kf in kept]
        span_s = (kept[-1].t_ns - kept[0].t_ns) * 1e-9
        self.timing.replayed(len(kept), span_s, (min(placed), max(placed)))
        log.info(
            "time offset %.2f ms: the first %d keyframes (%.1f s) re-run (placed with %.2f to %.2f ms)",
            offset_s * 1e3,
            len(kept),
            span_s,
            min(placed) * 1e3,
            max(placed) * 1e3,
        )
        return self.states()

    def _started(self, start: Start) -> list[StateEstimate]:
        self._init_kind = start.kind
        if start.kind == "static":  # the start window's keyframes rest on the at-rest priors
            self._still_k.update(start.keyframes)
        self._timings_ms.append(start.solve_ms)
        self.timing.after_start(list(start.keyframes))
        return [self.state.state(k, start.solve_ms, self.use_imu) for k in start.keyframes]

    def finish(self, refine: bool = False) -> dict[str, Any]:
        """Final estimate of all keyframes (and a batch LM refinement when asked), then the scale's uncertainty
        from the graph (metric runs only); returns what was done."""
        info: dict[str, Any] = {"refined": False}
        st = self.state
        self.background()  # one that is due after the last keyframe
        st.sync()
        if self._chunks is not None:
            st.all_factors = self._chunks.gather(st.all_factors)  # every factor kept, in one graph again
        if refine and self._chunks is not None and self._chunks.start > 0:
            self._warn("no batch refinement: the factors of finished chunks were let go (smoother.keep_factors)")
            refine = False
        if refine and self.initialised:
            t0 = time.perf_counter()
            try:
                st.absorb(batch_solve(st.all_factors, st.values))
                info["refined"] = True
            except RuntimeError as exc:
                self._warn(f"batch refinement failed ({first_line(exc)}); keeping the online estimate")
            info["refine_s"] = time.perf_counter() - t0
        if self.initialised and self.use_imu and self.cfg.estimator.scale_uncertainty:
            t0 = time.perf_counter()
            if self._chunks is None:
                self._scale = scale_uncertainty(st.all_factors, st.values, sorted(st.t_ns))
            else:
                self._scale = self._chunks.finish(st.all_factors, st.values, sorted(st.t_ns), st.smoother)
            info["scale_uncertainty_s"] = time.perf_counter() - t0
            if self._scale is None:
                self._warn("the scale's uncertainty could not be computed from the graph")
        return info

    def states(self) -> list[StateEstimate]:
        """The current (smoothed) estimate of every initialised keyframe, in time order (in the known positions'
        frame when they were given and aligned)."""
        st = self.state
        st.sync()
        out = [st.state(k, 0.0, self.use_imu) for k in sorted(st.t_ns) if st.values.exists(X(k))]
        T = self._output_T()
        if T is None:
            return out
        return [replace(s, world_T_body=T @ s.world_T_body, v_world=T[:3, :3] @ s.v_world) for s in out]

    def _output_T(self) -> np.ndarray | None:  # noqa: N802
        return None if self.anchor is None else self.anchor.known_T_est

    def landmarks(self, sync: bool = True) -> LandmarkMap:
        """Every landmark in the graph. With `sync=False` the latest per-keyframe values are used as they are
        (cheap; for live display)."""
        st = self.state
        if sync:
            st.sync()
        ids, pts, nobs = st.landmark_arrays()
        T = self._output_T()
        if T is not None:
            pts = pts @ T[:3, :3].T + T[:3, 3]
        return LandmarkMap(ids, track_of(ids), pts, nobs)

    def stats(self) -> EstimatorStats:
        """Counts, timings and events of the run so far."""
        return EstimatorStats(
            initialisation=self._init_kind,
            keyframe_ms=tuple(self._timings_ms),
            num_zero_velocity_updates=self._num_still,
            num_track_splits=self.segments.num_splits,
            num_reidentified=self.reidentification.num_reidentified,
            num_loop_flushes=self.reidentification.num_loop_flushes,
            num_landmarks_revived=self.old.num_revived,
            num_landmarks_merged=self.reidentification.num_merged,
            num_landmarks_archived=len(self.state.archived),
            num_blind_adjustments=self.blind.num_runs,
            num_blind_admitted=self.blind.num_admitted,
            num_position_factors=self.anchor.num_factors if self.anchor is not None else 0,
            recoveries=tuple(self.recovery.events),
            reidentifications=tuple(self.reidentification.events),
            warnings=tuple(self._warnings),
            scale_sigma_rel=None if self._scale is None else self._scale.sigma_rel,
            scale_pairs=() if self._scale is None else self._scale.pairs,
            smoother_variables=tuple(self._num_variables),
            step_cpu_ms=tuple(self._cpu_ms),
            background_ms=tuple(self._background_ms),
            keyframe_projections=tuple(
                (k, t, self.state.projections.get(k, 0)) for k, t in sorted(self.state.t_ns.items())
            ),
            time_offset=self.timing.report(),
            still_keyframes=tuple(self.state.t_ns[k] for k in sorted(self._still_k)),
        )

    def background(self) -> None:
        """The deferred work after a keyframe (`smoother.background`; backend/deferred.py `background`)."""
        deferred.background(self)

    # ----------------------------------------------------------------- steady state
    def _step(self, prev: int, k: int, ids: np.ndarray) -> StateEstimate:
        t0, c0 = time.perf_counter(), time.process_time()
        st = self.state
        if self._chunks is not None:
            st.all_factors = self._chunks.mark(k, st.all_factors)  # the block being filled
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        t_s = st.t_ns[k] * 1e-9
        if self.use_imu:
            nav = st.pims[k].predict(gtsam.NavState(st.values.atPose3(X(prev)), st.values.atVector(V(prev))), st.bias)
            pred = nav.pose()
            values.insert(V(k), nav.velocity())
            values.insert(B(k), st.bias)
            st.set(V(k), nav.velocity())
            st.set(B(k), st.bias)
            st.add(graph, fb.imu_factor(prev, k, st.pims[k]))
            if is_still(self.cfg.zero_velocity, self.book, self.imu, st.t_ns[k], prev, k, ids):
                zv = self.cfg.zero_velocity
                for f in fb.no_motion_factors(prev, k, zv.sigma_rad, zv.sigma_m, zv.velocity_sigma):
                    st.add(graph, f)
                self._num_still += 1
                self._still_k.add(k)
            stamps = {X(k): t_s, V(k): t_s, B(k): t_s}
        else:
            pred = gtsam.Pose3(self.vision.predict(prev, k, ids))
            st.add(graph, self.vision.motion_prior(prev, k))
            stamps = {X(k): t_s}
        values.insert(X(k), pred)
        st.set(X(k), pred)
        if self.anchor is not None:
            for f in self.anchor.factors(k, st.t_ns[k], st.values):
                st.add(graph, f)
        self._observe_landmarks(k, ids, pred.matrix(), graph, values, stamps, t_s)
        self.reidentification.flush(graph, k)
        try:
            marginalised = st.smoother.update(graph, values, stamps)
            est = st.smoother.estimate_keys(st.recent_keys(k))
            st.dirty = True
            for j, p in self.old.keep(marginalised).items():
                self.reidentification.on_retired(j, p)
        except SolverFailure as exc:
            est = self._recover(prev, k, str(exc))
        st.absorb(est)
        if self.use_imu:
            st.bias = st.values.atConstantBias(B(k))
        self._chores_k = k
        if not st.smoother.deferred:
            deferred.chores(self)
        ms = (time.perf_counter() - t0) * 1e3
        self._timings_ms.append(ms)
        self._num_variables.append(st.smoother.num_variables())
        self._cpu_ms.append((time.process_time() - c0) * 1e3)
        return st.state(k, ms, self.use_imu)

    def _prune(self, k: int) -> None:
        """Bounded memory: forget the track views no part of the estimator looks at again (older than the
        triangulation window and the blind stretch's, with a margin) and, when track ids are never reused, the lost
        tracks and their segments; the estimate is unchanged to the last bit (tests/backend/test_bounded_memory.py)."""
        blind = self.cfg.blind_admission
        horizon = max(self.state.window_keyframes, blind.window_keyframes + blind.before_keyframes) + PRUNE_MARGIN
        self.book.prune(k - horizon, drop_lost=self.unique_track_ids)
        if self.unique_track_ids:
            self.segments.forget_unseen()

    def _observe_landmarks(
        self,
        k: int,
        ids: np.ndarray,
        world_T_body: np.ndarray,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        stamps: dict[int, float],
        t_s: float,
    ) -> None:
        """Keyframe k's views: projection factors on admitted landmarks that they agree with (a disagreeing view
        starts a new track segment), and admission of the tracks that are now well triangulated."""
        st, smoother = self.state, self.state.smoother
        poses = seen = None
        for j in ids.tolist():
            tr = self.book.tracks[j]
            if tr.admitted:
                old = not smoother.has(L(j))  # marginalised out of a fixed lag (None when not kept either)
                if old and self.old.position(j) is None:
                    continue
                gate = self.reidentification.gate_px(j, self.cfg.landmarks.max_reprojection_px)
                seen = reprojections(self.book, self.old, smoother, k, ids, world_T_body) if seen is None else seen
                if consistent(self.book, self.old, smoother, j, world_T_body, tr.views[k], gate, seen[j]):
                    if old:
                        self.old.revive(j, graph, values)
                    st.add_projection(self.reidentification.route(graph, j, k), k, j, tr.views[k], tr.run_start(k))
                    stamps[L(j)] = t_s
                else:
                    self._split_track(j, k)
                continue
            if not self.admission.ready(j):
                continue
            poses = st.known_poses() if poses is None else poses
            p = self.admission.admit(j, poses, graph, values, k_now=k)
            if p is not None:
                self._admitted(j, p, stamps, t_s)
        if self.use_imu:  # no visual constraint at k and before: admit over adjusted poses
            for j, p in self.blind.admit(k, ids, self._still_k, graph, values):
                self._admitted(j, p, stamps, t_s)

    def _admitted(self, j: int, p: np.ndarray, stamps: dict[int, float], t_s: float) -> None:
        self.state.set(L(j), p)
        self.state.retired.discard(j)  # re-admitted after a rebuild: no longer an old landmark
        self.reidentification.on_admit(j, p)
        stamps[L(j)] = t_s

    def _split_track(self, j: int, k: int) -> None:
        """Track drift: the view of keyframe k disagrees with landmark j, so it starts a new landmark."""
        new = self.segments.split(self.reidentification.unalias(j), j)
        uv = self.book.tracks[j].views.pop(k)
        self.book.observe(k, np.array([new]), uv[None])

    def _recover(self, prev: int, k: int, reason: str) -> gtsam.Values:
        """Rebuild the smoother from the last good state (prev) plus keyframe k's inertial factor or motion prior."""
        st = self.state
        self.recovery.record(prev, k, reason)
        self.reidentification.drop_loops()
        self.book.forget_before(prev)
        st.num_obs = {j: n for j, n in st.num_obs.items() if st.values.exists(L(j))}
        bridge = fb.imu_factor(prev, k, st.pims[k]) if self.use_imu else self.vision.motion_prior(prev, k)
        return self.recovery.rebuild(prev, k, bridge, self.use_imu)
