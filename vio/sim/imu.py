"""IMU measurement model and grades (Kalibr noise parameters) plus the ground-truth states at IMU rate.

gyro_k = omega_body(t_k) + b_w(t_k) + n_w,   n_w ~ N(0, (gyroscope_noise_density * sqrt(rate))^2)
acc_k  = world_R_body(t_k)^T (a_world(t_k) - g) + b_a(t_k) + n_a, g = (0, 0, -9.81) m/s^2
b_{k+1} = b_k + random_walk * sqrt(dt) * N(0, 1)   (per axis, gyro and accelerometer)

A phone IMU (`PhoneImu`, issue 16) also has per-axis scale-factor errors and axis misalignment (cross-axis
sensitivity): omega_body and the specific force pass through a matrix T = diag(1 + s) + M (M off-diagonal) before the
bias and noise are added; and its timestamps are jittered: sample k is measured at the nominal time (the ground
truth's) but stamped t_k + N(0, jitter^2) (clipped to +-0.4 periods, so stamps still increase).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vio.errors import SimulationError
from vio.geometry import R_to_quat_wxyz
from vio.records import GRAVITY_WORLD, GroundTruth, ImuCalib, ImuSeries
from vio.sim.trajectory import Trajectory


@dataclass(frozen=True)
class ImuGrade:
    """Noise of one IMU grade; densities in Kalibr units, initial biases drawn per axis with a random sign."""

    name: str
    gyro_noise: float  # rad/s/sqrt(Hz)
    acc_noise: float  # m/s^2/sqrt(Hz)
    gyro_walk: float  # rad/s^2/sqrt(Hz)
    acc_walk: float  # m/s^3/sqrt(Hz)
    gyro_bias0: float  # typical initial gyro bias magnitude per axis, rad/s
    acc_bias0: float  # typical initial accelerometer bias magnitude per axis, m/s^2
    noisy: bool = True  # False: the measurements are exact (the calibration still carries small densities)


IMU_GRADES: dict[str, ImuGrade] = {
    # Exact measurements; the YAML carries small positive densities so that estimators stay well-posed.
    "ideal": ImuGrade("ideal", 1e-5, 1e-4, 1e-7, 1e-6, 0.0, 0.0, noisy=False),
    # A phone MEMS IMU (e.g. BMI160/ICM-20600 class as calibrated by Kalibr users).
    "phone": ImuGrade("phone", 0.002, 0.015, 5e-5, 1e-3, 0.005, 0.05),
    # A tactical/industrial MEMS IMU (ADIS16448 class, the EuRoC sensor, with steadier biases).
    "tactical": ImuGrade("tactical", 1.7e-4, 2.0e-3, 2e-6, 5e-5, 5e-4, 0.01),
    # EuRoC's ADIS16448 exactly as its published imu0/sensor.yaml states it (random walks included), initial biases
    # as the tactical grade's: the simulated twin of `vio simulate ... --real-imu` on EuRoC, with the noise the real
    # capture declares. (V1_01's own biases are larger, gyro up to 0.077 rad/s: docs/BENCHMARKS.md, issue 16.)
    "euroc": ImuGrade("euroc", 1.6968e-4, 2.0e-3, 1.9393e-5, 3.0e-3, 5e-4, 0.01),
}


@dataclass(frozen=True)
class PhoneImu:
    """Magnitudes (1 sigma) of a phone IMU's errors beyond noise and bias.

    Datasheet tolerances of phone-class MEMS (Bosch BMI160, TDK ICM-20600/42605): sensitivity (scale factor) about
    +-1 %, cross-axis sensitivity about +-1-2 %, so 1 % and 0.5 % (0.3 deg) per term as 1 sigma; Android
    SensorEvent timestamps scatter by a few tenths of a millisecond around a regular grid.
    """

    gyro_scale: float = 0.01  # per-axis scale-factor error, fraction
    acc_scale: float = 0.01
    gyro_misalignment: float = 0.005  # each off-diagonal term of T, rad (cross-axis sensitivity)
    acc_misalignment: float = 0.005
    jitter_s: float = 3e-4  # timestamp error, s

    def draw(self, rng: np.random.Generator) -> ImuErrors:
        """The errors of one device (scale factors and misalignment), drawn once per capture."""

        def matrix(scale: float, mis: float) -> np.ndarray:
            T = np.eye(3) + np.diag(rng.normal(0.0, scale, 3))
            off = ~np.eye(3, dtype=bool)
            T[off] = rng.normal(0.0, mis, 6)
            return T

        return ImuErrors(
            matrix(self.gyro_scale, self.gyro_misalignment),
            matrix(self.acc_scale, self.acc_misalignment),
            self.jitter_s,
        )


@dataclass(frozen=True)
class ImuErrors:
    """The true errors of one simulated phone IMU (ground truth): measured = T @ true + bias + noise."""

    gyro_T: np.ndarray  # (3, 3) scale factors (diagonal, 1 + s) and misalignment (off-diagonal)
    acc_T: np.ndarray  # (3, 3)
    jitter_s: float  # timestamp error sigma, s

    def yaml_dict(self) -> dict:
        return {
            "gyro_T": [[round(float(v), 9) for v in row] for row in self.gyro_T],
            "acc_T": [[round(float(v), 9) for v in row] for row in self.acc_T],
            "timestamp_jitter_s": float(self.jitter_s),
            "model": "measured = T @ true + bias + noise; stamp = true time + N(0, jitter^2)",
        }


def grade_by_name(name: str) -> ImuGrade:
    try:
        return IMU_GRADES[name]
    except KeyError:
        raise SimulationError(f"unknown IMU grade '{name}' (choose from {', '.join(IMU_GRADES)})") from None


def imu_calib(grade: ImuGrade, rate_hz: float) -> ImuCalib:
    return ImuCalib(grade.gyro_noise, grade.acc_noise, grade.gyro_walk, grade.acc_walk, rate_hz)


def simulate_imu(
    traj: Trajectory,
    t0_ns: int,
    duration_s: float,
    rate_hz: float,
    grade: ImuGrade,
    rng: np.random.Generator,
    errors: ImuErrors | None = None,
    jitter_rng: np.random.Generator | None = None,
) -> tuple[ImuSeries, GroundTruth]:
    """IMU samples at t0_ns + k / rate_hz for t in [0, duration_s], and ground truth at the same times.

    Times are integer ns (k * 1e9 / rate rounded); the ground truth carries the true biases of each sample. With
    `errors` the measurements pass through their matrices and the stamps are jittered by `jitter_rng`.
    """
    n = int(np.floor(duration_s * rate_hz + 1e-9)) + 1
    k = np.arange(n, dtype=np.int64)
    offset_ns = np.round(k * (1e9 / rate_hz)).astype(np.int64)
    t_s = offset_ns.astype(np.float64) * 1e-9
    s = traj.sample(t_s)
    gyro = s.omega_body.copy()
    acc = np.einsum("nji,nj->ni", s.world_R_body, s.a_world - GRAVITY_WORLD)
    if errors is not None:
        gyro = gyro @ errors.gyro_T.T
        acc = acc @ errors.acc_T.T
    b_w = np.zeros((n, 3))
    b_a = np.zeros((n, 3))
    if grade.noisy:
        dt = 1.0 / rate_hz
        sign = rng.choice([-1.0, 1.0], size=(2, 3))
        mag = rng.uniform(0.5, 1.5, size=(2, 3))
        bw0 = sign[0] * mag[0] * grade.gyro_bias0
        ba0 = sign[1] * mag[1] * grade.acc_bias0
        steps = rng.standard_normal((n, 12))
        b_w = bw0 + np.vstack([np.zeros((1, 3)), np.cumsum(steps[:-1, 0:3] * grade.gyro_walk * np.sqrt(dt), axis=0)])
        b_a = ba0 + np.vstack([np.zeros((1, 3)), np.cumsum(steps[:-1, 3:6] * grade.acc_walk * np.sqrt(dt), axis=0)])
        gyro += b_w + steps[:, 6:9] * grade.gyro_noise * np.sqrt(rate_hz)
        acc += b_a + steps[:, 9:12] * grade.acc_noise * np.sqrt(rate_hz)
    t_ns = np.int64(t0_ns) + offset_ns
    gt = GroundTruth(t_ns, s.p_world, R_to_quat_wxyz(s.world_R_body), s.v_world, b_w, b_a)
    stamps = t_ns
    if errors is not None and errors.jitter_s > 0:
        if jitter_rng is None:
            raise SimulationError("timestamp jitter needs its own random generator")
        lim = 0.4 / rate_hz
        jitter = np.clip(jitter_rng.normal(0.0, errors.jitter_s, n), -lim, lim)
        stamps = t_ns + np.round(jitter * 1e9).astype(np.int64)
    return ImuSeries(stamps, gyro, acc), gt
