"""The inertial start: buffer the first `window_s` of keyframes, guess their states (static start when the IMU
rests, otherwise the closed-form moving start of alignment.py), then refine the window jointly and seed the
smoother (window.py)."""

from __future__ import annotations

import logging
import time

import gtsam
import numpy as np

from backend import factors as fb
from backend.admission import LandmarkAdmission
from backend.anchoring import PositionAnchor
from backend.graph_state import GraphState
from backend.initialisation.alignment import InitialGuess, WindowMeasurements, moving_start, static_start
from backend.initialisation.gyro_bias import gyro_bias_from_images
from backend.initialisation.window import Start, elapsed_ms, start_window
from backend.keys import B, V, X
from backend.landmarks import LandmarkBook
from vio.config import InitialisationConfig
from vio.records import CameraCalib, ImuSeries

log = logging.getLogger(__name__)


class InertialInitialiser:
    """Buffers keyframes until a start succeeds (`add` returns it)."""

    def __init__(
        self,
        cfg: InitialisationConfig,
        state: GraphState,
        book: LandmarkBook,
        admission: LandmarkAdmission,
        imu: ImuSeries,
        camera: CameraCalib,
        alignment_pixel_sigma: float,
        anchor: PositionAnchor | None,
    ) -> None:
        self.cfg, self.state, self.book, self.admission = cfg, state, book, admission
        self.imu, self.camera, self.anchor = imu, camera, anchor
        self.alignment_pixel_sigma = alignment_pixel_sigma  # px (config initialisation.alignment_pixel_sigma)
        self.pending: list[int] = []  # keyframes waiting for the start

    def add(self, k: int) -> Start | None:
        self.pending.append(k)
        ks, st = self.pending, self.state
        if (st.t_ns[ks[-1]] - st.t_ns[ks[0]]) * 1e-9 < self.cfg.window_s or len(ks) < 4:
            return None
        guess = self._guess(ks)
        if guess is None:
            self.pending = ks[1:]
            return None
        t0 = time.perf_counter()
        graph, values = self._window_graph(ks, guess)
        if not start_window(st, self.admission, graph, values, ks[-1], "initialisation"):
            self.pending = ks[1:]
            return None
        st.bias = st.values.atConstantBias(B(ks[-1]))
        start = Start(guess.kind, ks, elapsed_ms(t0))
        log.info("initialised (%s start) with %d keyframes, %d landmarks", guess.kind, len(ks), len(st.num_obs))
        self.pending = []
        return start

    def _guess(self, ks: list[int]) -> InitialGuess | None:
        st, cfg = self.state, self.cfg
        rest = static_start(self.imu, st.t_ns[ks[0]], st.t_ns[ks[-1]], cfg.static_max_gyro, cfg.static_max_acc_std)
        if rest is not None:
            world_R_body, bias_gyro = rest
            T = np.eye(4)
            T[:3, :3] = world_R_body
            return InitialGuess({k: T for k in ks}, {k: np.zeros(3) for k in ks}, bias_gyro, np.zeros(3), {}, "static")
        in_window = set(ks)
        obs = {}
        for j, tr in self.book.tracks.items():
            views = {k: self.book.normalized(uv)[0] for k, uv in tr.views.items() if k in in_window}
            if len(views) >= 3:
                obs[j] = views
        if len(obs) < 10:
            st.warn(f"moving start at keyframe {ks[-1]}: only {len(obs)} tracks span the window; waiting")
            return None
        bias_gyro = self._gyro_bias(ks, obs)
        A_R, delta = self._rotations_and_deltas(ks, bias_gyro)
        sigma_norm = self.alignment_pixel_sigma / self.camera.fx * 2.0
        window = WindowMeasurements(ks, A_R, delta, obs, self.camera.body_T_cam, sigma_norm)
        guess = moving_start(window, bias_gyro)
        if not 0.85 < guess.gravity_norm_free / 9.81 < 1.15:
            st.warn(
                f"moving start at keyframe {ks[-1]}: gravity {guess.gravity_norm_free:.2f} m/s^2 from the linear "
                "alignment is implausible (too little excitation); sliding the window"
            )
            return None
        return guess

    def _gyro_bias(self, ks: list[int], obs: dict[int, dict[int, np.ndarray]]) -> np.ndarray:
        """The gyro bias the moving start integrates with: from the images' rotations when they give it and a
        constant bias explains them (`initialisation.gyro_bias_from_images`, `gyro_bias_max_rms_deg`), else the
        current estimate."""
        st = self.state
        current = np.asarray(st.bias.gyroscope(), float)
        if not self.cfg.gyro_bias_from_images:
            return current
        pims = [st.pims[b] for b in ks[1:]]
        t_s = [st.t_ns[k] * 1e-9 for k in ks]
        est = gyro_bias_from_images(ks, t_s, pims, obs, self.camera.body_T_cam, current)
        if est is None:
            log.info("moving start at keyframe %d: the images give no rotations for the gyro bias", ks[-1])
            return current
        step = float(np.linalg.norm(est.bias - current))
        if step > self.cfg.gyro_bias_max_rad_s:
            st.warn(
                f"moving start at keyframe {ks[-1]}: the images' rotations ask for a gyro bias of "
                f"{np.linalg.norm(est.bias):.3f} rad/s, more than {self.cfg.gyro_bias_max_rad_s} rad/s; not used"
            )
            return current
        if est.rms_after_deg > self.cfg.gyro_bias_max_rms_deg:
            log.info(
                "moving start at keyframe %d: the images' rotations ask for a gyro bias of (%.3f, %.3f, %.3f) rad/s "
                "but stay %.2f deg rms from the gyro's (more than %.2f): not used",
                ks[-1],
                *est.bias,
                est.rms_after_deg,
                self.cfg.gyro_bias_max_rms_deg,
            )
            return current
        log.info(
            "moving start at keyframe %d: gyro bias from %d image rotations (%.3f, %.3f, %.3f) rad/s; "
            "image-gyro disagreement %.2f -> %.2f deg rms",
            ks[-1],
            est.pairs,
            *est.bias,
            est.rms_before_deg,
            est.rms_after_deg,
        )
        return est.bias

    def _rotations_and_deltas(
        self, ks: list[int], bias_gyro: np.ndarray
    ) -> tuple[dict[int, np.ndarray], dict[int, tuple[np.ndarray, np.ndarray, float]]]:
        """Each keyframe's rotation in the first's body frame and the IMU deltas from the keyframe before,
        corrected (first order, gtsam's) from the bias the pims were integrated with to `bias_gyro`."""
        st = self.state
        bias = gtsam.imuBias.ConstantBias(np.zeros(3), np.asarray(bias_gyro, float))
        A_R = {ks[0]: np.eye(3)}
        delta = {}
        for a, b in zip(ks[:-1], ks[1:], strict=True):
            pim = st.pims[b]
            at_hat = pim.predict(gtsam.NavState(), pim.biasHat())
            at_new = pim.predict(gtsam.NavState(), bias)
            A_R[b] = A_R[a] @ at_new.attitude().matrix()
            dP = np.asarray(pim.deltaPij()) + at_new.position() - at_hat.position()
            dV = np.asarray(pim.deltaVij()) + at_new.velocity() - at_hat.velocity()
            delta[b] = (dP, dV, pim.deltaTij())
        return A_R, delta

    def _window_graph(self, ks: list[int], guess: InitialGuess) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
        st, cfg = self.state, self.cfg
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        bias0 = gtsam.imuBias.ConstantBias(guess.bias_acc, guess.bias_gyro)
        v_sigma = cfg.velocity_sigma_static if guess.kind == "static" else cfg.velocity_sigma_moving
        first = gtsam.Pose3(guess.world_T_body[ks[0]])
        priors = [
            fb.pose_prior_gravity_aware(ks[0], first, cfg.tilt_sigma_rad, cfg.gauge_sigma_rad, cfg.gauge_sigma_m),
            fb.velocity_prior(ks[0], guess.v_world[ks[0]], v_sigma),
            fb.bias_prior(ks[0], bias0, cfg.bias_sigma_acc, cfg.bias_sigma_gyro),
        ]
        for f in priors:
            st.add(graph, f)
        for k in ks:
            values.insert(X(k), gtsam.Pose3(guess.world_T_body[k]))
            values.insert(V(k), np.asarray(guess.v_world[k], float))
            values.insert(B(k), bias0)
        for a, b in zip(ks[:-1], ks[1:], strict=True):
            st.add(graph, fb.imu_factor(a, b, st.pims[b]))
        for k in ks:
            if self.anchor is not None:  # matched now, added once aligned (see backend.anchoring)
                self.anchor.match(k, st.t_ns[k])
        self.admission.admit_window(guess.world_T_body, graph, values)
        return graph, values
