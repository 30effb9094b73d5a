"""The gyro's rotation between any two times: the body orientation integrated from the rates, on the IMU clock.

Between samples k and k+1 the body turns by Exp((w_k + w_k+1) / 2 - b) dt) (midpoint rule, bias b removed); the
orientations at the samples are the running product of these turns, computed as a prefix scan (log2 N vectorised
quaternion products, so integrating again for another bias costs milliseconds). Between samples the orientation is
interpolated on the sample interval's own turn (constant rate). Angular speed |w| is read the same way.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from vio.records import ImuSeries


def _prefix_product(steps: Rotation) -> Rotation:
    """R_0 = identity, R_k = steps_0 * ... * steps_k-1 (Hillis-Steele scan on quaternions)."""
    q = steps.as_quat()
    n = len(q)
    shift = 1
    while shift < n:
        left = Rotation.from_quat(q[: n - shift])
        right = Rotation.from_quat(q[shift:])
        q = np.concatenate([q[:shift], (left * right).as_quat()])
        shift *= 2
    return Rotation.concatenate([Rotation.identity(), Rotation.from_quat(q)])


class GyroIntegral:
    """The integrated gyro of `imu` with a constant `bias_rad_s` removed (module docstring)."""

    def __init__(self, imu: ImuSeries, bias_rad_s: np.ndarray | None = None) -> None:
        self.t_ns = np.asarray(imu.t_ns, np.int64)
        self.t0_ns = int(self.t_ns[0])
        self.ts = (self.t_ns - self.t0_ns) * 1e-9
        dt = np.diff(self.ts)
        bias = np.zeros(3) if bias_rad_s is None else np.asarray(bias_rad_s, float)
        self.rate = 0.5 * (imu.gyro[1:] + imu.gyro[:-1]) - bias  # (N-1, 3) rad/s over each interval
        self.orientation = _prefix_product(Rotation.from_rotvec(self.rate * dt[:, None]))  # (N,) gyro0_R_body
        self.speed = np.linalg.norm(imu.gyro - bias, axis=1)

    @property
    def span_ns(self) -> tuple[int, int]:
        return int(self.t_ns[0]), int(self.t_ns[-1])

    def at(self, t_ns: np.ndarray, shift_ns: float = 0.0) -> Rotation:
        """gyro0_R_body at times `t_ns` + `shift_ns` (int64 times, a float shift; inside the IMU's span)."""
        s = (np.asarray(t_ns, np.int64) - self.t0_ns) * 1e-9 + shift_ns * 1e-9  # int64 first: no float rounding
        k = np.clip(np.searchsorted(self.ts, s, side="right") - 1, 0, len(self.ts) - 2)
        return self.orientation[k] * Rotation.from_rotvec(self.rate[k] * (s - self.ts[k])[:, None])

    def between(self, ta_ns: np.ndarray, tb_ns: np.ndarray, shift_ns: float = 0.0) -> Rotation:
        """body(ta)_R_body(tb): the body's turn from ta + shift to tb + shift."""
        return self.at(ta_ns, shift_ns).inv() * self.at(tb_ns, shift_ns)

    def mean_speed(self, ta_ns: np.ndarray, tb_ns: np.ndarray, shift_ns: float = 0.0) -> np.ndarray:
        """|turn from ta + shift to tb + shift| / (tb - ta): the mean angular speed over each interval, rad/s."""
        angle = np.linalg.norm(self.between(ta_ns, tb_ns, shift_ns).as_rotvec(), axis=1)
        return angle / ((np.asarray(tb_ns, np.int64) - np.asarray(ta_ns, np.int64)) * 1e-9)
