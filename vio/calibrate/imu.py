"""IMU noise from a static log: Allan deviation per axis, the IEEE 952 terms, Kalibr's four numbers (worst axis).

A static log is checked first: 1 s means of the gyro must stay within STATIC_GYRO_RAD_S of their moving median
(over STATIC_WINDOW_S, so that slow bias drift passes) and those of the accelerometer within STATIC_ACC_M_S2 (a
phone that was picked up, turned or carried fails; one handled only at its start and end keeps its longest static
stretch). Kalibr's values are continuous-time (noise densities per
sqrt(Hz), random walks per s per sqrt(Hz)), the worst (largest) axis.
VIO users commonly inflate these for unmodelled effects (vibration, temperature, scale errors); the factor is
reported with the inflated values, never applied to the written file.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vio.calibrate.allan import NoiseFit, fit_noise, overlapping_adev
from vio.errors import CalibrationError
from vio.records import ImuCalib, ImuSeries

STATIC_GYRO_RAD_S = 0.02  # 1 s gyro means further than this from their moving median: it rotated (1.1 deg/s)
STATIC_ACC_M_S2 = 0.2  # 1 s accelerometer means further than this from their moving median: it moved or tilted
STATIC_WINDOW_S = 121  # the moving median's window, s: slow bias drift is not motion; handling up to ~30 s at an end
# or ~60 s inside the log is (the window is reflected at the ends)
HANDLING_MARGIN_S = 2  # seconds cut on each side of a moving second
MIN_STATIC_FRACTION = 0.8  # a log handled at its ends keeps its longest static stretch if it is this much of it
MIN_DURATION_S = 60.0  # shorter logs cannot show the random walk at all
RECOMMENDED_DURATION_S = 3600.0
AXES = ("x", "y", "z")


@dataclass(frozen=True)
class ImuNoise:
    """Allan-deviation results of both sensors; per-axis arrays are (3,) in the IMU body axes x, y, z."""

    rate_hz: float  # sample rate, Hz
    duration_s: float  # span of the static stretch used, s
    span_s: tuple[float, float]  # the stretch used: (start, end) in s since the log's first sample
    log_duration_s: float  # span of the whole log, s
    taus_s: np.ndarray  # (T,) cluster times, s
    gyro_adev: np.ndarray  # (3, T) rad/s
    acc_adev: np.ndarray  # (3, T) m/s^2
    gyro: tuple[NoiseFit, ...]  # per axis: rad/s/sqrt(Hz), rad/s^2/sqrt(Hz), rad/s
    acc: tuple[NoiseFit, ...]  # per axis: m/s^2/sqrt(Hz), m/s^3/sqrt(Hz), m/s^2

    def kalibr(self) -> ImuCalib:
        """Kalibr's four numbers: the worst axis of each."""
        return ImuCalib(
            gyroscope_noise_density=max(f.white for f in self.gyro),
            accelerometer_noise_density=max(f.white for f in self.acc),
            gyroscope_random_walk=max(f.random_walk for f in self.gyro),
            accelerometer_random_walk=max(f.random_walk for f in self.acc),
            rate_hz=self.rate_hz,
        )


def static_span(imu: ImuSeries, where: str) -> tuple[float, float]:
    """The static stretch of the log to use, (start, end) in s since its first sample.

    Seconds in which the IMU moved (see the module docstring), widened by HANDLING_MARGIN_S, are cut: a log handled
    at its start or end (the phone put down, picked up) keeps its longest static stretch when that is at least
    MIN_STATIC_FRACTION of the log and MIN_DURATION_S long. Otherwise CalibrationError, one line naming where it moved.
    """
    from scipy.ndimage import binary_dilation, median_filter

    t_s = (imu.t_ns - imu.t_ns[0]) * 1e-9
    duration = float(t_s[-1]) if len(t_s) else 0.0
    if duration < MIN_DURATION_S:
        raise CalibrationError(
            f"{where}: the IMU log spans {duration:.1f} s; the noise needs a static log of at least "
            f"{MIN_DURATION_S:g} s ({RECOMMENDED_DURATION_S / 3600:g} h recommended)"
        )
    second = np.floor(t_s).astype(np.int64)
    counts = np.bincount(second)
    ok = counts >= 0.5 * np.median(counts)  # whole seconds only (a last partial second is noisy)
    secs = np.flatnonzero(ok)
    moving = np.zeros(len(secs), bool)
    worst = (0.0, "")
    for name, data, limit, unit in (
        ("gyro", imu.gyro, STATIC_GYRO_RAD_S, "rad/s"),
        ("accelerometer", imu.acc, STATIC_ACC_M_S2, "m/s^2"),
    ):
        means = np.stack([np.bincount(second, weights=data[:, j])[ok] / counts[ok] for j in range(3)], axis=1)
        local = median_filter(means, size=(STATIC_WINDOW_S, 1), mode="reflect")
        dev = np.linalg.norm(means - local, axis=1)
        moving |= dev > limit
        i = int(np.argmax(dev))
        if dev[i] / limit > worst[0]:
            worst = (
                dev[i] / limit,
                f"the {name}'s 1 s mean is {dev[i]:.3g} {unit} from its moving median at t = {secs[i]} s "
                f"(limit {limit:g})",
            )
    if not moving.any():
        return 0.0, duration
    still = ~binary_dilation(moving, iterations=HANDLING_MARGIN_S)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], still.astype(np.int8), [0]])))
    runs = edges.reshape(-1, 2)  # [start, stop) indices into secs of each static run
    if len(runs):
        a, b = runs[int(np.argmax(runs[:, 1] - runs[:, 0]))]
        start, end = float(secs[a]), float(secs[b - 1] + 1)
        if b - a >= MIN_STATIC_FRACTION * len(secs) and end - start >= MIN_DURATION_S:
            return start, min(end, duration)
    raise CalibrationError(f"{where}: not a static log: {worst[1]}; record with the IMU lying still")


def imu_noise(imu: ImuSeries, where: str = "IMU log") -> ImuNoise:
    """Allan deviation and noise terms of a static IMU log (its static stretch: `static_span`)."""
    start_s, end_s = static_span(imu, where)
    log_s = float((imu.t_ns[-1] - imu.t_ns[0]) * 1e-9)
    t0 = int(imu.t_ns[0])
    imu = imu.window(t0 + int(round(start_s * 1e9)), t0 + int(round(end_s * 1e9)))
    dt = np.diff(imu.t_ns) * 1e-9
    rate_hz = float(1.0 / np.median(dt))
    duration_s = float((imu.t_ns[-1] - imu.t_ns[0]) * 1e-9)
    curves = {}
    for name, data in (("gyro", imu.gyro), ("acc", imu.acc)):
        per_axis = [overlapping_adev(data[:, j], rate_hz) for j in range(3)]
        taus = per_axis[0][0]
        curves[name] = (np.stack([a for _, a in per_axis]), tuple(fit_noise(taus, a, duration_s) for _, a in per_axis))
    return ImuNoise(
        rate_hz=rate_hz,
        duration_s=duration_s,
        span_s=(start_s, end_s),
        log_duration_s=log_s,
        taus_s=taus,
        gyro_adev=curves["gyro"][0],
        acc_adev=curves["acc"][0],
        gyro=curves["gyro"][1],
        acc=curves["acc"][1],
    )
