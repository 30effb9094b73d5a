"""Smooth body trajectories for the simulator: poses plus consistent velocity, acceleration and angular rate.

A trajectory maps time since the start of the capture (float seconds, small numbers only) to the IMU body pose
in the world (z up). Derivatives come from 5-point central differences of the pose functions with h = 1 ms;
for the smooth (sums of sinusoids, quintic splines) functions used here their error is ~1e-8 in m/s^2 and
rad/s, far below any IMU noise, and they are exactly the derivatives of the poses written as ground truth.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import make_lsq_spline
from scipy.spatial.transform import Rotation, RotationSpline

_H_S = 1e-3  # finite-difference step, s


@dataclass(frozen=True)
class TrajectorySample:
    """Body (IMU) states at N times."""

    p_world: np.ndarray  # (N, 3) body position in world, m
    world_R_body: np.ndarray  # (N, 3, 3) body orientation in world
    v_world: np.ndarray  # (N, 3) body velocity in world, m/s
    a_world: np.ndarray  # (N, 3) body acceleration in world (without gravity), m/s^2
    omega_body: np.ndarray  # (N, 3) angular rate of the body, in the body frame, rad/s


PoseFn = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


def _vee(S: np.ndarray) -> np.ndarray:
    """(N, 3, 3) nearly skew matrices -> (N, 3) vectors of their skew part."""
    return 0.5 * np.stack([S[:, 2, 1] - S[:, 1, 2], S[:, 0, 2] - S[:, 2, 0], S[:, 1, 0] - S[:, 0, 1]], axis=1)


class Trajectory:
    """A body trajectory from a vectorised pose function `t_s (N,) -> (p_world (N,3), world_R_body (N,3,3))`."""

    def __init__(self, pose_fn: PoseFn, duration_s: float) -> None:
        self._pose_fn = pose_fn
        self.duration_s = float(duration_s)

    def pose(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Body position (N, 3) m and orientation world_R_body (N, 3, 3) at times t_s (s since start)."""
        return self._pose_fn(np.atleast_1d(np.asarray(t_s, dtype=np.float64)))

    def sample(self, t_s: np.ndarray) -> TrajectorySample:
        """Pose, velocity, acceleration and body angular rate at times t_s (s since start)."""
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        n = t.shape[0]
        offsets = np.array([-2.0, -1.0, 0.0, 1.0, 2.0]) * _H_S
        p_all, R_all = self._pose_fn((t[None, :] + offsets[:, None]).reshape(-1))
        p = p_all.reshape(5, n, 3)
        R = R_all.reshape(5, n, 3, 3)
        v = (p[0] - 8.0 * p[1] + 8.0 * p[3] - p[4]) / (12.0 * _H_S)
        a = (-p[0] + 16.0 * p[1] - 30.0 * p[2] + 16.0 * p[3] - p[4]) / (12.0 * _H_S * _H_S)
        R_dot = (R[0] - 8.0 * R[1] + 8.0 * R[3] - R[4]) / (12.0 * _H_S)
        omega = _vee(np.einsum("nji,njk->nik", R[2], R_dot))
        return TrajectorySample(p[2].copy(), R[2].copy(), v, a, omega)


def look_at(p_cam: np.ndarray, target: np.ndarray, roll_rad: np.ndarray) -> np.ndarray:
    """world_R_cam (N, 3, 3) for an OpenCV camera at p_cam looking at target, world z up, rolled about its axis."""
    z = target - p_cam
    z /= np.linalg.norm(z, axis=1, keepdims=True)
    x = np.cross(z, np.array([0.0, 0.0, 1.0]))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(z, x)
    c, s = np.cos(roll_rad)[:, None], np.sin(roll_rad)[:, None]
    x_r = c * x + s * y
    y_r = -s * x + c * y
    return np.stack([x_r, y_r, z], axis=2)


def camera_driven(cam_fn: PoseFn, body_T_cam: np.ndarray) -> PoseFn:
    """Turn a camera pose function (p_cam, world_R_cam) into the body (IMU) pose function."""
    body_R_cam = body_T_cam[:3, :3]
    body_t_cam = body_T_cam[:3, 3]

    def fn(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p_cam, world_R_cam = cam_fn(t)
        world_R_body = world_R_cam @ body_R_cam.T
        return p_cam - world_R_body @ body_t_cam, world_R_body

    return fn


@dataclass(frozen=True)
class Sinusoids:
    """Sum of sinusoids per axis with seeded random phases: sum_i A_i sin(2 pi f_i t + phi_i)."""

    amplitudes: np.ndarray  # (K,) amplitude per term (unit of the signal)
    freqs_hz: np.ndarray  # (K,) Hz
    phases: np.ndarray  # (D, K) rad, one row per output dimension
    gains: np.ndarray  # (D,) per-dimension amplitude scale

    @staticmethod
    def make(amplitudes, freqs_hz, dims: int, rng: np.random.Generator, gains=None) -> Sinusoids:
        amps = np.asarray(amplitudes, float)
        return Sinusoids(
            amps,
            np.asarray(freqs_hz, float),
            rng.uniform(0.0, 2.0 * np.pi, (dims, amps.size)),
            np.ones(dims) if gains is None else np.asarray(gains, float),
        )

    def __call__(self, t: np.ndarray) -> np.ndarray:
        """(N, D) values at times t (s)."""
        arg = 2.0 * np.pi * t[:, None, None] * self.freqs_hz[None, None, :] + self.phases[None, :, :]
        return (np.sin(arg) * self.amplitudes).sum(axis=2) * self.gains


def smoothstep7(x: np.ndarray) -> np.ndarray:
    """C3 step from 0 (x <= 0) to 1 (x >= 1)."""
    x = np.clip(x, 0.0, 1.0)
    return x**4 * (35.0 - 84.0 * x + 70.0 * x**2 - 20.0 * x**3)


def spline_trajectory(
    t_ns: np.ndarray, p_world: np.ndarray, q_wxyz: np.ndarray, close: bool = False
) -> tuple[Trajectory, int]:
    """A smooth trajectory through recorded body poses (e.g. EuRoC ground truth or a TUM file).

    Position: least-squares quintic B-spline with knots every ~0.2 s (smooths mm-level motion-capture noise and
    keeps accelerations physical). Orientation: scipy's RotationSpline through the poses decimated to ~10 Hz.
    `close` follows the recording more closely, for a real IMU that measured its motion (`vio.sim.real_imu`): knots
    every two pose intervals (at least 50 ms) and the orientation through the poses at up to 40 Hz (on EuRoC's
    20 Hz ground truth: 0.1 s knots, every pose), so the rendered motion keeps what the poses hold up to a few Hz.
    Returns the trajectory (time 0 is 50 ms after the first pose) and that start time in ns.
    """
    t_ns = np.asarray(t_ns, np.int64)
    t = (t_ns - t_ns[0]).astype(np.float64) * 1e-9
    span = float(t[-1])
    k = 5
    dt_pose = float(np.median(np.diff(t)))
    knot_s, rot_step_s = (max(2.0 * dt_pose, 0.05), max(dt_pose, 0.025)) if close else (0.2, 0.1)
    n_inner = max(int(span / knot_s) - 1, 0)
    inner = np.linspace(0.0, span, n_inner + 2)[1:-1]
    knots = np.concatenate([np.full(k + 1, 0.0), inner, np.full(k + 1, span)])
    pos_spline = make_lsq_spline(t, p_world, knots, k=k)
    step = max(1, int(round(rot_step_s / max(dt_pose, 1e-6))))
    idx = np.unique(np.concatenate([np.arange(0, t.size, step), [t.size - 1]]))
    q_xyzw = np.asarray(q_wxyz, float)[idx][:, [1, 2, 3, 0]]
    rot_spline = RotationSpline(t[idx], Rotation.from_quat(q_xyzw))

    margin = 0.05  # s cut at both ends so that the finite differences stay inside the splines

    def fn(tq: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        tc = np.clip(tq + margin, 0.0, span)
        return pos_spline(tc), rot_spline(tc).as_matrix().reshape(-1, 3, 3)

    return Trajectory(fn, span - 2.0 * margin), int(t_ns[0]) + int(margin * 1e9)
