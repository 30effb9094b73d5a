"""Initialisation without ground truth: the closed-form guesses.

Static start: over a window at rest, the mean accelerometer reading is the reaction to gravity (gives roll and
pitch; yaw is the free gauge and set to 0) and the mean gyro reading is the gyro bias.

Moving start: a closed-form visual-inertial alignment over the first window of keyframes (in the spirit of
Martinelli's closed-form solution and VINS-Mono's linear alignment). The gyro fixes the relative rotations
`A_R_body(k)` in the frame A of the first keyframe's body; then positions p_k, velocities v_k, gravity g_A and the
landmarks are all *linear* unknowns of
    p_{k+1} = p_k + v_k dt + g dt^2 / 2 + A_R_k dP_k        v_{k+1} = v_k + g dt + A_R_k dV_k      (IMU deltas)
    (cam_k(P_j))_x - x (cam_k(P_j))_z = 0,  (cam_k(P_j))_y - y (cam_k(P_j))_z = 0              (bearings x, y)
so metric scale comes straight from the accelerometer (no up-to-scale SfM followed by a scale fit). A second
solve fixes |g| = 9.81 m/s^2; the result is rotated so that g points down the world z axis. The estimator then
refines the window jointly (all factors, Levenberg-Marquardt), which also estimates the biases.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.sparse.linalg import spsolve

from vio.records import GRAVITY_M_S2, ImuSeries

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class InitialGuess:
    """Initial states of the window's keyframes, world frame (z up)."""

    world_T_body: dict[int, np.ndarray]  # k -> (4, 4)
    v_world: dict[int, np.ndarray]  # k -> (3,) m/s
    bias_gyro: np.ndarray  # (3,) rad/s
    bias_acc: np.ndarray  # (3,) m/s^2
    landmarks_world: dict[int, np.ndarray]  # track id -> (3,) m (may be empty)
    kind: str  # "static" | "moving"
    gravity_norm_free: float = GRAVITY_M_S2  # |g| of the unconstrained linear solve, m/s^2 (a quality check)


def rotation_to_z_up(g_dir: np.ndarray) -> np.ndarray:
    """The minimal rotation world_R_A taking the unit vector g_dir (gravity direction in A) to (0, 0, -1)."""
    a = np.asarray(g_dir, float) / np.linalg.norm(g_dir)
    b = np.array([0.0, 0.0, -1.0])
    v = np.cross(a, b)
    c = float(a @ b)
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def static_start(
    imu: ImuSeries, t0_ns: int, t1_ns: int, max_gyro_std: float, max_acc_std: float
) -> tuple[np.ndarray, np.ndarray] | None:
    """(world_R_body (3, 3), gyro bias (3,) rad/s) if the IMU is at rest over [t0, t1], else None.

    At rest: the 0.1 s block means of the gyro and accelerometer vary (norm of their standard deviation) less
    than `max_gyro_std` (rad/s) and `max_acc_std` (m/s^2). Block means ignore motor or hand
    vibration (EuRoC's MAV idles with its rotors running: 1 m/s^2 raw accelerometer noise at rest).
    """
    w = imu.window(t0_ns, t1_ns)
    n_block = max(int(round(0.1 * len(w) / max((t1_ns - t0_ns) * 1e-9, 1e-9))), 1)
    n = len(w) // n_block * n_block
    if n < 5 * n_block:
        return None
    gyro_blocks = w.gyro[:n].reshape(-1, n_block, 3).mean(axis=1)
    acc_blocks = w.acc[:n].reshape(-1, n_block, 3).mean(axis=1)
    gyro_var = float(np.linalg.norm(gyro_blocks.std(axis=0)))
    acc_var = float(np.linalg.norm(acc_blocks.std(axis=0)))
    if gyro_var > max_gyro_std or acc_var > max_acc_std:
        return None
    f = w.acc.mean(axis=0)  # specific force at rest = body_R_world (0, 0, +g)
    world_R_body = rotation_to_z_up(-f)
    return world_R_body, w.gyro.mean(axis=0)


@dataclass(frozen=True)
class WindowMeasurements:
    """What the moving start sees of its window of keyframes ks."""

    ks: list[int]  # keyframe indices, in time order
    A_R_body: dict[int, np.ndarray]  # k -> (3, 3) gyro-integrated rotation in the frame A of ks[0]'s body
    delta_pv: dict[int, tuple[np.ndarray, np.ndarray, float]]  # k -> (dP m, dV m/s, dt s) from the keyframe before
    observations: dict[int, dict[int, np.ndarray]]  # track id -> {k: normalized image coordinates (2,)}
    body_T_cam: np.ndarray  # (4, 4)
    sigma_norm: float  # bearing noise in normalized units times a typical depth


def linear_alignment(
    w: WindowMeasurements, fix_gravity: np.ndarray | None = None
) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray], np.ndarray, dict[int, np.ndarray]]:
    """Solve the linear system of the module docstring in frame A (p_{ks[0]} = 0).

    delta_pv[k] is preintegrated in the body frame of the keyframe before k. With fix_gravity (3,) the gravity is
    known. Returns positions, velocities, gravity (3,), points. Solved as sparse normal equations (a dense solve
    of the ~2000 unknowns took 15 s here).
    """
    ks, A_R_body, delta_pv, observations = w.ks, w.A_R_body, w.delta_pv, w.observations
    body_T_cam, sigma_norm = w.body_T_cam, w.sigma_norm
    nk = len(ks)
    idx = {k: i for i, k in enumerate(ks)}
    pts = [j for j, obs in observations.items() if sum(k in idx for k in obs) >= 2]
    pidx = {j: i for i, j in enumerate(pts)}
    n_g = 0 if fix_gravity is not None else 3
    # unknowns: p_k for k != ks[0] (the origin), v_k, gravity (optional), points
    n = 3 * (nk - 1) + 3 * nk + n_g + 3 * len(pts)
    g_col = 6 * nk - 3

    def p_col(k: int) -> int | None:
        return None if idx[k] == 0 else 3 * (idx[k] - 1)

    def v_col(k: int) -> int:
        return 3 * (nk - 1) + 3 * idx[k]

    def l_col(j: int) -> int:
        return g_col + n_g + 3 * pidx[j]

    rows: list[int] = []
    cols: list[int] = []
    vals: list[float] = []
    rhs: list[float] = []

    def add_row(entries: list[tuple[int | None, float]], value: float, sigma: float) -> None:
        r = len(rhs)
        for c, a in entries:
            if c is not None and a != 0.0:
                rows.append(r)
                cols.append(c)
                vals.append(a / sigma)
        rhs.append(value / sigma)

    def shift(c: int | None, axis: int) -> int | None:
        return None if c is None else c + axis

    sig_p, sig_v = 2e-3, 2e-2  # m, m/s: IMU delta noise incl. unknown accelerometer bias over ~0.1 s
    for a, b in zip(ks[:-1], ks[1:], strict=True):
        dP, dV, dt = delta_pv[b]
        R = A_R_body[a]
        for axis in range(3):
            val = (R @ dP)[axis]
            entries = [(shift(p_col(b), axis), 1.0), (shift(p_col(a), axis), -1.0), (v_col(a) + axis, -dt)]
            if fix_gravity is None:
                entries.append((g_col + axis, -0.5 * dt * dt))
            else:
                val += 0.5 * dt * dt * fix_gravity[axis]
            add_row(entries, val, sig_p)
            val = (R @ dV)[axis]
            entries = [(v_col(b) + axis, 1.0), (v_col(a) + axis, -1.0)]
            if fix_gravity is None:
                entries.append((g_col + axis, -dt))
            else:
                val += dt * fix_gravity[axis]
            add_row(entries, val, sig_v)
    R_bc, t_bc = body_T_cam[:3, :3], body_T_cam[:3, 3]
    for j in pts:
        for k, (x, y) in observations[j].items():
            if k not in idx:
                continue
            Rc = A_R_body[k] @ R_bc  # A_R_cam; cam point = Rc^T (P - p_k - R_k t_bc): linear in P and p_k
            off = A_R_body[k] @ t_bc
            for u, comp in ((x, 0), (y, 1)):
                a_vec = Rc[:, comp] - u * Rc[:, 2]
                entries = [(l_col(j) + i, a_vec[i]) for i in range(3)]
                entries += [(shift(p_col(k), i), -a_vec[i]) for i in range(3)]
                add_row(entries, float(a_vec @ off), sigma_norm)
    A = sparse.csr_matrix((vals, (rows, cols)), shape=(len(rhs), n))
    sol = spsolve((A.T @ A).tocsc(), A.T @ np.asarray(rhs))
    sol = np.asarray(sol).reshape(-1)

    def p_of(k: int) -> np.ndarray:
        c = p_col(k)
        return np.zeros(3) if c is None else sol[c : c + 3]

    p = {k: p_of(k) for k in ks}
    v = {k: sol[v_col(k) : v_col(k) + 3] for k in ks}
    g = sol[g_col : g_col + 3] if fix_gravity is None else np.asarray(fix_gravity, float)
    points = {j: sol[l_col(j) : l_col(j) + 3] for j in pts}
    return p, v, g, points


def moving_start(w: WindowMeasurements, bias_gyro: np.ndarray) -> InitialGuess:
    """Closed-form metric initial guess of the window (see the module docstring), rotated to the z-up world."""
    ks, A_R_body = w.ks, w.A_R_body
    _, _, g_free, _ = linear_alignment(w)
    g_norm = float(np.linalg.norm(g_free))
    g_fixed = g_free / max(g_norm, 1e-9) * GRAVITY_M_S2
    p, v, g, points = linear_alignment(w, g_fixed)
    world_R_A = rotation_to_z_up(g)
    poses = {}
    for k in ks:
        T = np.eye(4)
        T[:3, :3] = world_R_A @ A_R_body[k]
        T[:3, 3] = world_R_A @ p[k]
        poses[k] = T
    vel = {k: world_R_A @ v[k] for k in ks}
    pts = {j: world_R_A @ P for j, P in points.items()}
    log.info("moving start over %d keyframes: |g| free solve %.3f m/s^2", len(ks), g_norm)
    return InitialGuess(poses, vel, np.asarray(bias_gyro, float), np.zeros(3), pts, "moving", g_norm)
