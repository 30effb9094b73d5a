"""IMU preintegration between keyframes with gtsam's `PreintegratedCombinedMeasurements`.

Frames and units: the body frame is the IMU frame; the world is z up with gravity (0, 0, -9.81) m/s^2. Gyro
samples are rad/s, accelerometer samples m/s^2 of specific force, both in the body frame; time is integer ns.

Between two keyframe times the IMU stream is resampled so that the integrated interval is exactly `t1 - t0`:
the measurement at each keyframe time is linearly interpolated from the two samples around it, the samples
strictly inside the interval are used as they are, and each step integrates the mean of the two measurements at
its ends over the actual time between them (trapezoidal rule; jittered rates need nothing special). A gap in the
stream is bridged the same way, and one longer than `ImuConfig.max_gap_s` is reported (`Preintegrated.gap` and a
logged warning naming the time) so the estimator can decide what to trust. Before the first or after the last
sample the nearest sample is held, and the uncovered time counts as a gap.

The default (non-manifold) preintegration types are only accurate for short windows: well under pi of integrated
rotation (see DESIGN.md). Keyframes 0.05-0.2 s apart are fine; longer windows log a warning.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import gtsam
import numpy as np
from scipy.spatial.transform import Rotation

from vio.config import ImuConfig
from vio.records import GRAVITY_M_S2, ImuCalib, ImuSeries

log = logging.getLogger(__name__)

_NS = 1e-9
_MAX_SAFE_ROTATION_RAD = 1.5  # beyond this the non-manifold preintegration starts to lose accuracy


def preintegration_params(calib: ImuCalib, cfg: ImuConfig) -> gtsam.PreintegrationCombinedParams:
    """Combined-preintegration parameters: z-up gravity 9.81 m/s^2 and the Kalibr continuous-time noise.

    Measurement covariances are density^2 (gyro (rad/s)^2/Hz, accel (m/s^2)^2/Hz), bias random-walk covariances
    rw^2, each density and random walk first multiplied by `cfg.noise_inflation`; the integration covariance is
    `cfg.integration_sigma^2`. All covariances are isotropic 3x3.
    """
    k = float(cfg.noise_inflation)
    params = gtsam.PreintegrationCombinedParams.MakeSharedU(GRAVITY_M_S2)
    eye = np.eye(3)
    params.setGyroscopeCovariance(eye * (k * calib.gyroscope_noise_density) ** 2)
    params.setAccelerometerCovariance(eye * (k * calib.accelerometer_noise_density) ** 2)
    params.setBiasOmegaCovariance(eye * (k * calib.gyroscope_random_walk) ** 2)
    params.setBiasAccCovariance(eye * (k * calib.accelerometer_random_walk) ** 2)
    params.setIntegrationCovariance(eye * float(cfg.integration_sigma) ** 2)
    return params


def _midpoint_steps(
    meas: np.ndarray, dts: np.ndarray, bias: gtsam.imuBias.ConstantBias
) -> tuple[np.ndarray, np.ndarray]:
    """Per-step (acc, gyro) inputs for gtsam from measurements (M, 6) at the step ends and step lengths (M-1,) s.

    Each step uses the mean of its two end measurements (trapezoidal rule). gtsam applies a step's
    acceleration in the body frame at the *start* of the step (first-order Euler), which for a rotating body
    biases velocity by about |omega x a| dt / 2 per step (0.02 m/s^2 at 0.7 rad/s, 200 Hz). So the mean specific
    force, bias-corrected, is rotated into the start-of-step frame by Exp(omega dt / 2): the midpoint rule,
    second-order accurate. gtsam then subtracts the bias again, hence the add-back.
    """
    mids = 0.5 * (meas[:-1] + meas[1:])
    b_acc, b_gyro = np.asarray(bias.accelerometer()), np.asarray(bias.gyroscope())
    half_turn = Rotation.from_rotvec((mids[:, 3:] - b_gyro) * (0.5 * dts)[:, None])
    acc = half_turn.apply(mids[:, :3] - b_acc) + b_acc
    return acc, mids[:, 3:]


@dataclass(frozen=True)
class Preintegrated:
    """The preintegrated IMU measurement between two keyframe times."""

    pim: gtsam.PreintegratedCombinedMeasurements  # deltas from t0 to t1 in the body frame at t0, bias at t0
    t0_ns: int  # start (keyframe k-1) time, ns
    t1_ns: int  # end (keyframe k) time, ns
    num_samples: int  # real IMU samples used (inside the interval plus the ones interpolated from at the ends)
    max_gap_s: float  # longest time between consecutive real samples over the interval (or uncovered), s
    gap: bool  # True when max_gap_s exceeds ImuConfig.max_gap_s

    @property
    def dt_s(self) -> float:
        return (self.t1_ns - self.t0_ns) * _NS


class ImuPreintegrator:
    """Preintegrates an IMU stream between arbitrary times (normally consecutive keyframes)."""

    def __init__(self, imu: ImuSeries, calib: ImuCalib, cfg: ImuConfig) -> None:
        if len(imu) == 0:
            raise ValueError("ImuPreintegrator needs at least one IMU sample")
        self.t_ns = np.asarray(imu.t_ns, np.int64)
        if np.any(np.diff(self.t_ns) <= 0):
            raise ValueError("IMU timestamps must be strictly increasing")
        self.meas = np.hstack([np.asarray(imu.acc, float), np.asarray(imu.gyro, float)])  # (N, 6) acc | gyro
        self.cfg = cfg
        self.params = preintegration_params(calib, cfg)

    def _interp(self, t_ns: int) -> np.ndarray:
        """(6,) measurement at t_ns: linear between the neighbouring samples, held outside the stream."""
        i = int(np.searchsorted(self.t_ns, t_ns, side="right"))
        if i == 0:
            return self.meas[0]
        if i == len(self.t_ns):
            return self.meas[-1]
        ta, tb = self.t_ns[i - 1], self.t_ns[i]
        w = (t_ns - ta) / (tb - ta)
        return (1.0 - w) * self.meas[i - 1] + w * self.meas[i]

    def resample(self, t0_ns: int, t1_ns: int) -> tuple[np.ndarray, np.ndarray, int, float, int]:
        """Times (M,) int64 ns and measurements (M, 6) from t0 to t1 inclusive, plus samples used, max gap, and
        the time (ns) where the longest gap starts."""
        i0 = int(np.searchsorted(self.t_ns, t0_ns, side="right"))  # first sample strictly after t0
        i1 = int(np.searchsorted(self.t_ns, t1_ns, side="left"))  # first sample at or after t1
        inner_t = self.t_ns[i0:i1]
        times = np.concatenate([[t0_ns], inner_t, [t1_ns]]).astype(np.int64)
        meas = np.vstack([self._interp(t0_ns), self.meas[i0:i1], self._interp(t1_ns)])
        # Real-sample spacing over the interval: the bracketing samples count; uncovered ends count whole.
        lo = max(i0 - 1, 0)
        hi = min(i1 + 1, len(self.t_ns))
        support = self.t_ns[lo:hi]
        edges = np.concatenate([[min(t0_ns, support[0])], support, [max(t1_ns, support[-1])]]).astype(np.int64)
        gaps = np.diff(edges)
        j = int(np.argmax(gaps))
        return times, meas, int(hi - lo), float(gaps[j] * _NS), int(edges[j])

    def between(self, t0_ns: int, t1_ns: int, bias: gtsam.imuBias.ConstantBias) -> Preintegrated:
        """Preintegrate from t0_ns to t1_ns (exactly) with the given bias estimate (linearisation point)."""
        t0_ns, t1_ns = int(t0_ns), int(t1_ns)
        if t1_ns <= t0_ns:
            raise ValueError(f"preintegration interval must be positive (t0={t0_ns} ns, t1={t1_ns} ns)")
        times, meas, used, max_gap_s, gap_t_ns = self.resample(t0_ns, t1_ns)
        pim = gtsam.PreintegratedCombinedMeasurements(self.params, bias)
        dts = np.diff(times) * _NS
        acc, gyro = _midpoint_steps(meas, dts, bias)
        for a, w, dt in zip(acc, gyro, dts, strict=True):
            pim.integrateMeasurement(a, w, dt)
        gap = max_gap_s > self.cfg.max_gap_s
        if gap:
            log.warning(
                "IMU gap of %.3f s at t=%d ns (%.3f s after the keyframe at %d ns); bridged by interpolation",
                max_gap_s,
                gap_t_ns,
                (gap_t_ns - t0_ns) * _NS,
                t0_ns,
            )
        angle = float(np.linalg.norm(gtsam.Rot3.Logmap(pim.deltaRij())))
        if angle > _MAX_SAFE_ROTATION_RAD:
            log.warning(
                "preintegrated rotation %.2f rad over %.3f s from t=%d ns: the non-manifold preintegration loses "
                "accuracy past ~pi; use shorter keyframe intervals",
                angle,
                (t1_ns - t0_ns) * _NS,
                t0_ns,
            )
        return Preintegrated(pim, t0_ns, t1_ns, used, max_gap_s, gap)
