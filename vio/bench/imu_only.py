"""The IMU-only baseline: the original thesis's method (strapdown dead reckoning) done as well as it can be.

Steps, all in the world frame (z up, gravity (0, 0, -9.81) m/s^2) with the body = IMU frame:

1. **Initial state.** If the capture starts at rest (a static window at the start, see `detect_static`), roll and
   pitch come from the mean accelerometer (gravity alignment), the gyro bias from the mean gyro, the
   accelerometer bias component along gravity from the norm of the mean specific force, and the velocity is zero.
   Heading is not observable from an IMU without a magnetometer: it is taken from the ground truth's first pose,
   as is the starting position (the estimate is expressed in the ground truth's frame). If the capture does not
   start at rest, the full initial attitude and velocity are taken from the ground truth (a generous assumption
   in the baseline's favour, reported as `init == "ground_truth"`).
2. **Attitude** by exact SO(3) integration of the bias-corrected gyro: `R <- R Exp(w dt)`, with `w` the mean of
   the two samples at the ends of each step (Rodrigues' formula; no small-angle approximation).
3. **Position and velocity** by a filterpy `KalmanFilter` over the state `[p_world, v_world]` with the
   gravity-compensated world acceleration `R (acc - b_a) + g` as the control input (the mean of both ends of each
   step) and process noise from the accelerometer noise density.
4. **Zero-velocity updates** (ZUPT pseudo-measurements `v = 0`) only inside windows where the IMU really rests
   (gyro and accelerometer quiet, specific force equal to gravity). A scenario that never stops gets none, which
   is the honest case: nothing bounds the drift.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from filterpy.kalman import KalmanFilter

from vio.geometry import R_to_quat_wxyz
from vio.records import GRAVITY_M_S2, GRAVITY_WORLD, ImuCalib, ImuSeries
from vio.trajio import Trajectory

log = logging.getLogger(__name__)

_NS = 1e-9


@dataclass(frozen=True)
class ImuOnlyConfig:
    static_window_s: float = 0.5  # length of the windows tested for rest, s
    static_max_gyro: float = 0.03  # |mean gyro| above this means motion, rad/s
    static_max_gyro_std: float = 0.01  # per-axis gyro std above the white noise's own plus this means motion, rad/s
    static_max_acc_std: float = 0.03  # per-axis accelerometer std above the noise's own plus this: motion, m/s^2
    static_max_acc_norm_err: float = 0.15  # | |mean acc| - g | above this means motion, m/s^2
    zupt: bool = True  # apply zero-velocity pseudo-measurements in detected rest windows
    zupt_sigma_m_s: float = 0.01  # sigma of a ZUPT pseudo-measurement, m/s
    output_rate_hz: float = 50.0  # rate of the output trajectory, Hz (the integration runs at the IMU rate)


@dataclass(frozen=True)
class ImuOnlyResult:
    trajectory: Trajectory  # body pose in world at `output_rate_hz`
    init: str  # "static" (gravity alignment at rest) or "ground_truth" (moving start)
    zupt_count: int  # number of zero-velocity pseudo-measurements applied
    static_s: float  # total time detected as rest, s
    bias_gyro: np.ndarray  # (3,) gyro bias used, rad/s
    bias_acc: np.ndarray  # (3,) accelerometer bias used, m/s^2


def so3_exp(phi: np.ndarray) -> np.ndarray:
    """Rotation matrix of the rotation vector `phi` (rad), exact (Rodrigues)."""
    angle = float(np.sqrt(phi @ phi))
    K = np.array([[0.0, -phi[2], phi[1]], [phi[2], 0.0, -phi[0]], [-phi[1], phi[0], 0.0]])
    if angle < 1e-8:
        return np.eye(3) + K + 0.5 * K @ K
    return np.eye(3) + (np.sin(angle) / angle) * K + ((1.0 - np.cos(angle)) / angle**2) * (K @ K)


def detect_static(imu: ImuSeries, cfg: ImuOnlyConfig, calib: ImuCalib | None = None) -> np.ndarray:
    """(N,) bool: samples inside a window of `static_window_s` where the IMU rests (see ImuOnlyConfig).

    The std thresholds add twice the per-sample white noise std of `calib` (density * sqrt(rate)) when given.
    """
    n = len(imu)
    static = np.zeros(n, bool)
    if n < 3:
        return static
    rate = (n - 1) / max((imu.t_ns[-1] - imu.t_ns[0]) * _NS, 1e-9)
    w = max(int(round(cfg.static_window_s * rate)), 3)
    sg = 2.0 * calib.gyroscope_noise_density * np.sqrt(rate) if calib is not None else 0.0
    sa = 2.0 * calib.accelerometer_noise_density * np.sqrt(rate) if calib is not None else 0.0
    for i0 in range(0, n - w + 1, max(w // 2, 1)):
        g, a = imu.gyro[i0 : i0 + w], imu.acc[i0 : i0 + w]
        quiet = (
            np.linalg.norm(g.mean(axis=0)) < cfg.static_max_gyro
            and g.std(axis=0).max() < cfg.static_max_gyro_std + sg
            and a.std(axis=0).max() < cfg.static_max_acc_std + sa
            and abs(np.linalg.norm(a.mean(axis=0)) - GRAVITY_M_S2) < cfg.static_max_acc_norm_err
        )
        if quiet:
            static[i0 : i0 + w] = True
    return static


def _yaw_only(R: np.ndarray) -> np.ndarray:
    yaw = np.arctan2(R[1, 0], R[0, 0])
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def gravity_align(acc_mean_body: np.ndarray, world_R_body_heading: np.ndarray) -> np.ndarray:
    """world_R_body whose body z maps the mean specific force onto world +z, with the heading of the given pose.

    At rest the accelerometer measures `R^T (0, 0, +g)`; roll and pitch follow from its direction. The yaw is
    that of `world_R_body_heading`, applied about the world z axis (so the result keeps roll and pitch).
    """
    f = acc_mean_body / np.linalg.norm(acc_mean_body)
    z = np.array([0.0, 0.0, 1.0])
    # Smallest rotation tilt_R_body taking f (body) to world z.
    axis = np.cross(f, z)
    s, c = np.linalg.norm(axis), float(f @ z)
    R_tilt = np.eye(3) if s < 1e-12 else so3_exp(axis / s * np.arctan2(s, c))
    # Remove the tilt estimate's own yaw, then apply the reference heading.
    return _yaw_only(world_R_body_heading) @ _yaw_only(R_tilt).T @ R_tilt


def dead_reckon(
    imu: ImuSeries,
    calib: ImuCalib | None,
    world_T_body0: np.ndarray,
    v0_world: np.ndarray | None,
    cfg: ImuOnlyConfig | None = None,
) -> ImuOnlyResult:
    """Integrate the IMU from `world_T_body0` (4x4, the reference pose at the first IMU sample).

    `v0_world` (m/s) is used only for a moving start; a static start uses zero velocity and the gravity-aligned
    attitude with the heading of `world_T_body0`.
    """
    cfg = cfg or ImuOnlyConfig()
    n = len(imu)
    if n < 2:
        raise ValueError("dead_reckon needs at least 2 IMU samples")
    static = detect_static(imu, cfg, calib)
    bias_g = np.zeros(3)
    bias_a = np.zeros(3)
    if static[0]:
        i1 = int(np.argmin(static)) if not static.all() else n
        # The detector's resolution is half a window: leave out the last half window before motion starts.
        rate = (n - 1) / ((imu.t_ns[-1] - imu.t_ns[0]) * _NS)
        i1 = max(i1 - int(0.5 * cfg.static_window_s * rate), min(i1, 10))
        acc_mean = imu.acc[:i1].mean(axis=0)
        bias_g = imu.gyro[:i1].mean(axis=0)
        f_hat = acc_mean / np.linalg.norm(acc_mean)
        bias_a = (np.linalg.norm(acc_mean) - GRAVITY_M_S2) * f_hat  # the only observable component at rest
        R = gravity_align(acc_mean, world_T_body0[:3, :3])
        v0 = np.zeros(3)
        init = "static"
    else:
        R = world_T_body0[:3, :3].copy()
        v0 = np.zeros(3) if v0_world is None else np.asarray(v0_world, float)
        init = "ground_truth"

    sigma_a = calib.accelerometer_noise_density if calib is not None else 0.02  # m/s^2/sqrt(Hz)
    kf = KalmanFilter(dim_x=6, dim_z=3, dim_u=3)
    kf.x = np.concatenate([world_T_body0[:3, 3], v0])
    kf.P = np.diag([1e-8] * 3 + ([1e-6] * 3 if init == "static" else [1e-4] * 3))
    kf.H = np.hstack([np.zeros((3, 3)), np.eye(3)])
    kf.R = np.eye(3) * cfg.zupt_sigma_m_s**2
    cache: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def model(dt_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if dt_ns not in cache:
            dt = dt_ns * _NS
            F = np.eye(6)
            F[:3, 3:] = np.eye(3) * dt
            B = np.vstack([np.eye(3) * 0.5 * dt * dt, np.eye(3) * dt])
            Q = B @ B.T * (sigma_a**2 / dt)  # white acceleration noise of density sigma_a over dt
            cache[dt_ns] = (F, B, Q)
        return cache[dt_ns]

    step = max(int(round(1.0 / (cfg.output_rate_hz * max(np.median(np.diff(imu.t_ns)) * _NS, 1e-6)))), 1)
    keep = list(range(0, n, step))
    if keep[-1] != n - 1:
        keep.append(n - 1)
    out_p = np.zeros((len(keep), 3))
    out_R = np.zeros((len(keep), 3, 3))
    out_p[0], out_R[0] = kf.x[:3], R
    j = 1
    zupts = 0
    gyro = imu.gyro - bias_g
    acc = imu.acc - bias_a
    a_prev = R @ acc[0] + GRAVITY_WORLD
    for k in range(n - 1):
        dt_ns = int(imu.t_ns[k + 1] - imu.t_ns[k])
        R_next = R @ so3_exp(0.5 * (gyro[k] + gyro[k + 1]) * dt_ns * _NS)
        a_next = R_next @ acc[k + 1] + GRAVITY_WORLD
        F, B, Q = model(dt_ns)
        kf.predict(u=0.5 * (a_prev + a_next), B=B, F=F, Q=Q)
        if cfg.zupt and static[k + 1]:
            kf.update(np.zeros(3))
            zupts += 1
        R, a_prev = R_next, a_next
        if j < len(keep) and keep[j] == k + 1:
            out_p[j], out_R[j] = kf.x[:3], R
            j += 1
    rate = (n - 1) / ((imu.t_ns[-1] - imu.t_ns[0]) * _NS)
    traj = Trajectory(imu.t_ns[keep].astype(np.int64), out_p, R_to_quat_wxyz(out_R).reshape(-1, 4))
    log.debug("imu_only: init %s, %d ZUPTs, %d samples", init, zupts, n)
    return ImuOnlyResult(traj, init, zupts, float(static.sum() / rate), bias_g, bias_a)
