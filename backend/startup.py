"""The estimator's first window: buffer keyframes, guess (static or moving start), refine jointly, seed the smoother.

A mixin of `VioEstimator` (it uses the estimator's state: `pending`, `t_ns`, `pims`, `book`, `values`, ...).
"""

from __future__ import annotations

import logging
import time

import gtsam
import numpy as np

from backend import factors as fb
from backend.initialisation import InitialGuess, moving_start, static_start
from backend.keys import B, L, V, X
from backend.smoother import SolverFailure, batch_solve, first_line
from vio.records import StateEstimate

log = logging.getLogger(__name__)


class WindowInitialiser:
    """Initialisation methods of VioEstimator."""

    def _try_initialise(self) -> list[StateEstimate]:
        ks = self.pending
        if (self.t_ns[ks[-1]] - self.t_ns[ks[0]]) * 1e-9 < self.cfg.init_window_s or len(ks) < 4:
            return []
        guess = self._guess(ks)
        if guess is None:
            self.pending = ks[1:]
            return []
        t0 = time.perf_counter()
        graph, values = self._window_graph(ks, guess)
        if not self._start_window(graph, values, ks, "initialisation"):
            return []
        self.bias = self.values.atConstantBias(B(ks[-1]))
        self.initialised, self.init_kind = True, guess.kind
        ms = (time.perf_counter() - t0) * 1e3
        self.timings_ms.append(ms)
        log.info("initialised (%s start) with %d keyframes, %d landmarks", guess.kind, len(ks), len(self.num_obs))
        self.pending = []
        return [self._state(k, ms) for k in ks]

    def _start_window(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, ks: list[int], what: str) -> bool:
        """Solve the first window in batch and hand it to the smoother; on failure undo and wait for more keyframes."""
        try:
            values = batch_solve(graph, values)
            self.smoother.update(graph, values, {key: 0.0 for key in values.keys()})
        except (RuntimeError, SolverFailure) as exc:
            self._warn(f"{what} at keyframe {ks[-1]} failed ({first_line(exc)}); retrying later")
            self.smoother.reset()
            self.pending = ks[1:]
            for j in list(self.num_obs):
                self.book.tracks[j].admitted = False
            self.num_obs.clear()
            return False
        self._absorb(self.smoother.estimate())
        return True

    def _guess(self, ks: list[int]) -> InitialGuess | None:
        rest = static_start(self.imu, self.t_ns[ks[0]], self.t_ns[ks[-1]], self.cfg)
        if rest is not None:
            world_R_body, bias_gyro = rest
            T = np.eye(4)
            T[:3, :3] = world_R_body
            return InitialGuess({k: T for k in ks}, {k: np.zeros(3) for k in ks}, bias_gyro, np.zeros(3), {}, "static")
        A_R = {ks[0]: np.eye(3)}
        delta = {}
        for a, b in zip(ks[:-1], ks[1:], strict=True):
            pim = self.pims[b]
            A_R[b] = A_R[a] @ pim.deltaRij().matrix()
            delta[b] = (np.asarray(pim.deltaPij()), np.asarray(pim.deltaVij()), pim.deltaTij())
        obs = {}
        for j, tr in self.book.tracks.items():
            views = {k: self.book.normalized(uv)[0] for k, uv in tr.views.items() if k in A_R}
            if len(views) >= 3:
                obs[j] = views
        if len(obs) < 10:
            self._warn(f"moving start at keyframe {ks[-1]}: only {len(obs)} tracks span the window; waiting")
            return None
        sigma_norm = self.cfg.pixel_sigma / self.camera.fx * 2.0
        guess = moving_start(ks, A_R, delta, obs, self.camera.body_T_cam, sigma_norm, self.bias.gyroscope())
        if not 0.85 < guess.gravity_norm_free / 9.81 < 1.15:
            self._warn(
                f"moving start at keyframe {ks[-1]}: gravity {guess.gravity_norm_free:.2f} m/s^2 from the linear "
                "alignment is implausible (too little excitation); sliding the window"
            )
            return None
        return guess

    def _window_graph(self, ks: list[int], guess: InitialGuess) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        bias0 = gtsam.imuBias.ConstantBias(guess.bias_acc, guess.bias_gyro)
        static = guess.kind == "static"
        priors = [
            fb.pose_prior_gravity_aware(ks[0], gtsam.Pose3(guess.world_T_body[ks[0]]), 0.1, 1e-3, 1e-3),
            fb.velocity_prior(ks[0], guess.v_world[ks[0]], 0.01 if static else 0.5),
            fb.bias_prior(ks[0], bias0, self.bias_sigma_acc, self.bias_sigma_gyro),
        ]
        for f in priors:
            graph.add(f)
            self.all_factors.add(f)
        for k in ks:
            values.insert(X(k), gtsam.Pose3(guess.world_T_body[k]))
            values.insert(V(k), np.asarray(guess.v_world[k], float))
            values.insert(B(k), bias0)
        for a, b in zip(ks[:-1], ks[1:], strict=True):
            self._add(graph, fb.imu_factor(a, b, self.pims[b]))
        for k in ks:
            if self.anchor is not None:  # matched now, added once aligned (see backend.anchoring)
                self.anchor.match(k, self.t_ns[k])
        self._admit_window_landmarks(graph, values, guess.world_T_body)
        return graph, values

    def _admit_window_landmarks(
        self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, poses: dict[int, np.ndarray]
    ) -> None:
        """Admit every track that triangulates over the window's poses: a landmark, a weak prior, its views."""
        for j, tr in self.book.tracks.items():
            p = self.book.try_admit(j, poses)
            if p is None:
                continue
            values.insert(L(j), p)
            graph.add(fb.landmark_prior(j, p, self.cfg.landmark_prior_sigma_m))
            for kk, uv in tr.views.items():
                if kk in poses:
                    self._add_projection(graph, kk, j, uv)
            tr.admitted = True
