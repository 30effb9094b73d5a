"""The camera's timing in the estimator (issue 16): rolling shutter and the camera-IMU time offset.

Convention (Kalibr's `timeshift_cam_imu`): t_imu = t_cam + offset, the offset of the top row's mid-exposure; a
rolling-shutter camera reads row v of H `readout * v / H` after the top row. A keyframe's pose is placed at the
IMU time of its image's centre row, `t_cam + offset + readout / 2` (for a global-shutter camera, readout 0, at
`t_cam + offset`; with the default offset 0 the frame time itself, so nothing changes). Each observation is moved
from its row's time to that pose time with the track's image velocity (VINS-Mono's feature-velocity correction):
`uv - readout * (v / H - 1/2) * velocity`.

The offset is estimated (`camera.estimate_time_offset`) from rotations. Keyframe poses placed `d` seconds before
the images were really taken turn, between keyframes i and j, by what the gyro turned over the placed interval
shifted by `d`: to first order `Log(dR_gyro^T R_i^T R_j) = d (w_j - dR_gyro^T w_i)`, with dR_gyro the bias-corrected
gyro's integral over the placed interval and w its rate at each end (averaged over +-20 ms). R_i, R_j are the
images' own rotations: PnP on the landmarks' current estimates, started at the smoother's pose. The smoother's
rotations would not do: they are a compromise with the gyro and hold only part of the shift (40-66 % on the orbit),
and the projection residuals hold almost none of it (the poses absorb it: 3 %). The information is the angular
acceleration: the gyro's noise over it bounds the estimate at `gyro_noise_density / sqrt(integral |dw/dt|^2 dt)`.

Each keyframe that has settled (`time_offset_settle` keyframes after it entered the graph) is paired with the one
`time_offset_lag` before it; least squares gives that pair's `d`, and the offset the pair was placed with plus `d`
is its estimate of the offset. The start window's pairs give the first estimate (at initialisation; its landmarks
are young: -2 to 18 ms for a true 15 on the 60 s orbit), applied until `MIN_ONLINE_PAIRS` pairs were read
online; from then on the offset is the weighted mean (weight |w_j - dR^T w_i|^2) of the online pairs (the last
`time_offset_window`, or all), applied to the keyframes that follow, at most `MAX_STEP_S` per keyframe. Its stated
sigma is the standard error of that mean from the pairs' scatter. Once that error is small enough the estimator
re-runs its first keyframes with the estimate (backend/offset_replay.py; `start_known` holds the offset meanwhile).
"""

from __future__ import annotations

from collections import deque

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from backend.graph_state import GraphState
from backend.keys import B, L, X
from vio.config import CameraConfig
from vio.errors import ConfigError
from vio.records import CameraCalib, FeatureTracks, ImuSeries, TimeOffsetEstimate

MIN_PNP_POINTS = 12  # a keyframe with fewer landmarks in view gives no visual rotation
GATE_PX = 3.0  # views further than this from the smoother's projection are left out of the visual rotation, px
RATE_HALF_WINDOW_S = 0.02  # the gyro rate at a keyframe is its mean over this much either side, s
TRACE_EVERY_S = 2.0  # run.json's trace of the offset: one value per this much capture time, s
MAX_KEPT_KEYFRAMES = 300  # views kept for the estimate at most this many keyframes back
MIN_ONLINE_PAIRS = 10  # the start window's estimate is applied until this many pairs were read online
MIN_RATE_CHANGE = 0.005  # rad/s: a pair whose ends turn at (almost) the same rate gives no estimate
MAX_STEP_S = 0.002  # the offset applied to the next keyframe moves by at most this much per keyframe, s
_H_S = 0.001  # half-step of the central difference that maps a distorted pixel velocity to an undistorted one, s


class CameraTiming:
    """Places keyframe poses in IMU time and moves each observation to its pose's time; estimates the offset."""

    def __init__(
        self, cfg: CameraConfig, camera: CameraCalib, imu: ImuSeries, state: GraphState, enabled: bool
    ) -> None:
        self.cfg, self.camera, self.imu, self.state = cfg, camera, imu, state
        self.readout_s = max(float(cfg.readout_s), 0.0)
        if self.readout_s >= 1.0 / max(camera.rate_hz, 1e-9):
            raise ConfigError(
                f"config camera.readout_s: {self.readout_s:g} s is not shorter than the frame interval "
                f"({1.0 / camera.rate_hz:g} s at {camera.rate_hz:g} Hz); a readout is typically 5-35 ms"
            )
        self.estimating = bool(cfg.estimate_time_offset) and enabled
        self.offset_s = float(cfg.time_offset_s)
        self._after_start: float | None = None
        self._placed: dict[int, float] = {}  # keyframe -> the offset its pose was placed with, s
        self._views: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # keyframe -> landmark ids, corrected pixels
        window = int(cfg.time_offset_window)
        self._estimates: deque[tuple[float, float]] = deque(maxlen=window if window > 0 else None)
        self._used = 0
        self._trace: list[tuple[float, float]] = []  # (s since the first keyframe, offset applied from then on s)
        self._start_known = False  # a re-run: the offset is known, the start window's estimate is not applied
        self._hold_pairs = MIN_ONLINE_PAIRS  # the online estimate is applied once this many pairs went into it
        self._initial_s = self.offset_s  # the offset the run began with (a re-run's first pass's)
        self._replay: tuple[int, float, tuple[float, float]] | None = None  # (keyframes, s, first pass placed range)
        self.history: list[tuple[int, float, float]] = []  # (k, that keyframe's estimate s, offset after it s)

    # ----------------------------------------------------------------- placing and correcting
    def pose_time_ns(self, t_cam_ns: int) -> int:
        """IMU time of the pose of a frame stamped t_cam_ns (its centre row's mid-exposure)."""
        return int(t_cam_ns) + int(round((self.offset_s + 0.5 * self.readout_s) * 1e9))

    def correct(self, tracks: FeatureTracks, uv: np.ndarray) -> np.ndarray:
        """(N, 2) undistorted pixels `uv` of `tracks` moved from each row's time to the pose time."""
        if self.readout_s <= 0.0:
            return uv
        vel = self.undistorted_velocity(tracks)
        dt_s = self.readout_s * (np.asarray(tracks.uv, float)[:, 1] / self.camera.height - 0.5)
        return uv - dt_s[:, None] * vel

    def undistorted_velocity(self, tracks: FeatureTracks) -> np.ndarray:
        """(N, 2) image velocity in undistorted px/s (0 when the tracks carry none)."""
        uv_d = np.asarray(tracks.uv, float).reshape(-1, 2)
        if tracks.uv_per_s is None:
            return np.zeros_like(uv_d)
        vel_d = np.asarray(tracks.uv_per_s, float).reshape(-1, 2)
        if not np.any(self.camera.dist):
            return vel_d
        a = self._undistort(uv_d + _H_S * vel_d)
        b = self._undistort(uv_d - _H_S * vel_d)
        return (a - b) / (2.0 * _H_S)

    def _undistort(self, uv_d: np.ndarray) -> np.ndarray:
        cam = self.camera
        xn = cam.undistort_to_normalized(uv_d)
        return np.column_stack([cam.fx * xn[:, 0] + cam.cx, cam.fy * xn[:, 1] + cam.cy])

    # ----------------------------------------------------------------- estimating
    def after_start(self, keyframes: list[int]) -> None:
        """The first estimate, from the start window's pairs (applied until the online pairs take over)."""
        if not self.estimating:
            return
        lag = max(1, min(int(self.cfg.time_offset_lag), len(keyframes) - 1))
        got = [e for e in (self._pair_estimate(k - lag, k) for k in keyframes[lag:]) if e is not None]
        self.history += [(-1, tau, float("nan")) for tau, _ in got]
        if got and not self._start_known:
            self._after_start = _weighted_mean(got)
            self.offset_s = self._after_start

    @property
    def num_pairs(self) -> int:
        """Keyframe pairs in the online estimate."""
        return len(self._estimates)

    def start_known(self, after_initialisation_s: float | None, initial_s: float, hold_pairs: int) -> None:
        """A re-run with the offset known (backend/offset_replay.py): neither the start window's estimate nor the
        online one is applied until `hold_pairs` pairs were read again (as many as gave the known offset: fewer
        would move it by their noise); the report keeps the first pass's start estimate and initial offset."""
        self._start_known, self._after_start, self._initial_s = True, after_initialisation_s, initial_s
        self._hold_pairs = max(int(hold_pairs), MIN_ONLINE_PAIRS)

    def replayed(self, keyframes: int, span_s: float, placed_s: tuple[float, float]) -> None:
        """Record, for the report, that the first `keyframes` (over `span_s`) were re-run; `placed_s` is the range
        of offsets the first pass had placed them with."""
        self._replay = (int(keyframes), float(span_s), placed_s)

    def converged(self, max_sigma_s: float, min_pairs: int) -> float | None:
        """The online estimate once at least `min_pairs` pairs went into it and its standard error is at most
        `max_sigma_s`, else None."""
        if not self.estimating or len(self._estimates) < max(min_pairs, MIN_ONLINE_PAIRS, 2):
            return None
        mean, sigma = self._mean_sigma()
        return mean if sigma <= max_sigma_s else None

    def _mean_sigma(self) -> tuple[float, float]:
        """The weighted mean of the online pairs' estimates and its standard error from their scatter, s."""
        tau, w = np.array(self._estimates).T
        mean = float(np.sum(w * tau) / np.sum(w))
        lag = max(int(self.cfg.time_offset_lag), 1)  # pairs that overlap are not independent
        n_eff = float(np.sum(w) ** 2 / np.sum(w * w)) / lag
        var = float(np.sum(w * (tau - mean) ** 2) / np.sum(w))
        return mean, float(np.sqrt(var / max(n_eff - 1.0, 1.0)))

    def placed(self, k: int, ids: np.ndarray, uv: np.ndarray) -> None:
        """Remember the offset keyframe k's pose was placed with, and its views (landmark ids, corrected pixels)."""
        if self.estimating:
            self._placed[k] = self.offset_s
            self._views[k] = (np.asarray(ids).copy(), np.asarray(uv, float).copy())
            for old in [kk for kk in self._views if kk < k - MAX_KEPT_KEYFRAMES]:  # a start that never comes
                self._views.pop(old)
                self._placed.pop(old, None)

    def after_step(self, k: int) -> None:
        """Read the keyframe that has settled since and update the offset for the keyframes that follow."""
        if not self.estimating:
            return
        kj = k - max(int(self.cfg.time_offset_settle), 0)
        ki = kj - max(int(self.cfg.time_offset_lag), 1)
        for old in [kk for kk in self._placed if kk < ki]:
            del self._placed[old]
            self._views.pop(old, None)
        got = self._pair_estimate(ki, kj)
        if got is None:
            return
        self._estimates.append(got)
        if len(self._estimates) >= self._hold_pairs:
            target = _weighted_mean(self._estimates)
            self.offset_s += float(np.clip(target - self.offset_s, -MAX_STEP_S, MAX_STEP_S))
        self.history.append((kj, got[0], self.offset_s))
        t_s = (self.state.t_ns[kj] - self.state.t_ns[min(self.state.t_ns)]) * 1e-9
        if not self._trace or t_s - self._trace[-1][0] >= TRACE_EVERY_S:
            self._trace.append((round(t_s, 3), self.offset_s))

    def _pair_estimate(self, ki: int, kj: int) -> tuple[float, float] | None:
        """(offset estimate s, weight) from the rotation between keyframes ki and kj against the gyro, or None."""
        st = self.state
        if ki not in self._placed or kj not in self._placed or ki not in st.t_ns or kj not in st.t_ns:
            return None
        if not (st.values.exists(X(ki)) and st.values.exists(X(kj)) and st.values.exists(B(kj))):
            return None
        bias = np.asarray(st.values.atConstantBias(B(kj)).gyroscope())
        ti, tj = st.t_ns[ki], st.t_ns[kj]
        dR = gyro_rotation(self.imu, ti, tj, bias)
        if dR is None:
            return None
        Ri, Rj = self._visual_rotation(ki), self._visual_rotation(kj)
        if Ri is None or Rj is None:
            return None
        r = Rotation.from_matrix(dR.T @ Ri.T @ Rj).as_rotvec()
        a = gyro_at(self.imu, tj, bias) - dR.T @ gyro_at(self.imu, ti, bias)
        aa = float(a @ a)
        if aa < MIN_RATE_CHANGE**2:
            return None
        self._used += 1
        placed = 0.5 * (self._placed[ki] + self._placed[kj])
        return placed + float(r @ a) / aa, aa

    def _visual_rotation(self, k: int) -> np.ndarray | None:
        """world_R_body of keyframe k from its views alone (PnP on the landmarks' current estimates, started at the
        smoother's pose): the camera's rotation when the images were taken, whatever time the pose was placed at."""
        st = self.state
        if k not in self._views:
            return None
        ids, uv = self._views[k]
        keep = [i for i, j in enumerate(ids.tolist()) if st.smoother.has(L(j))]
        if len(keep) < MIN_PNP_POINTS:
            return None
        est = st.smoother.estimate_keys([L(int(ids[i])) for i in keep])
        p_world = np.array([est.atPoint3(L(int(ids[i]))) for i in keep])
        world_T_cam = st.pose(k) @ st.body_P_cam.matrix()
        cam_T_world = np.linalg.inv(world_T_cam)
        K = st.K.K()
        pc = p_world @ cam_T_world[:3, :3].T + cam_T_world[:3, 3]
        z = pc[:, 2]
        proj = (pc[:, :2] / np.maximum(z, 1e-9)[:, None]) @ K[:2, :2].T + K[:2, 2]
        good = (z > 0.05) & (np.linalg.norm(proj - uv[keep], axis=1) <= GATE_PX)
        if good.sum() < MIN_PNP_POINTS:
            return None
        rvec, _ = cv2.Rodrigues(cam_T_world[:3, :3])
        ok, rvec, tvec = cv2.solvePnP(
            p_world[good], uv[keep][good], K, None, rvec, cam_T_world[:3, 3].copy(), True, cv2.SOLVEPNP_ITERATIVE
        )
        if not ok:
            return None
        cam_R_world = cv2.Rodrigues(rvec)[0]
        return cam_R_world.T @ st.body_P_cam.rotation().matrix().T

    def report(self) -> TimeOffsetEstimate:
        """What run.json says about the offset and the readout."""
        sigma = self._mean_sigma()[1] if self.estimating and len(self._estimates) >= 2 else None
        return TimeOffsetEstimate(
            estimated=self.estimating,
            value_s=self.offset_s,
            initial_s=float(self._initial_s),
            after_initialisation_s=self._after_start,
            sigma_s=sigma,
            num_keyframes=self._used,
            readout_s=self.readout_s,
            trace=tuple(self._trace),
            replayed_keyframes=0 if self._replay is None else self._replay[0],
            replayed_span_s=None if self._replay is None else self._replay[1],
            replayed_from_s=None if self._replay is None else self._replay[2],
        )


def _weighted_mean(estimates) -> float:
    tau, w = np.array(list(estimates)).T
    return float(np.sum(w * tau) / np.sum(w))


def gyro_at(imu: ImuSeries, t_ns: int, bias_gyro: np.ndarray) -> np.ndarray:
    """(3,) bias-corrected angular rate at t_ns, rad/s, body frame: the gyro (linear between samples) averaged over
    +-RATE_HALF_WINDOW_S (one sample's noise would dilute the regression on the rate change)."""
    t = float(t_ns - imu.t_ns[0]) + np.linspace(-RATE_HALF_WINDOW_S, RATE_HALF_WINDOW_S, 9) * 1e9
    ts = (imu.t_ns - imu.t_ns[0]).astype(float)
    return np.array([np.interp(t, ts, imu.gyro[:, i]).mean() for i in range(3)]) - bias_gyro


def gyro_rotation(imu: ImuSeries, t0_ns: int, t1_ns: int, bias_gyro: np.ndarray) -> np.ndarray | None:
    """body(t0)_R_body(t1) from the bias-corrected gyro (midpoint rule, ends interpolated); None outside the IMU."""
    if t0_ns < imu.t_ns[0] or t1_ns > imu.t_ns[-1] or t1_ns <= t0_ns:
        return None
    w = imu.window(t0_ns, t1_ns)
    ts = np.concatenate([[t0_ns], w.t_ns[(w.t_ns > t0_ns) & (w.t_ns < t1_ns)], [t1_ns]])
    rel = (ts - imu.t_ns[0]).astype(float)
    base = (imu.t_ns - imu.t_ns[0]).astype(float)
    g = np.column_stack([np.interp(rel, base, imu.gyro[:, i]) for i in range(3)]) - bias_gyro
    steps = 0.5 * (g[1:] + g[:-1]) * (np.diff(ts) * 1e-9)[:, None]
    R = np.eye(3)
    for m in Rotation.from_rotvec(steps).as_matrix():
        R = R @ m
    return R
