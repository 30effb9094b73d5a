"""Ideal tracks of a phone camera for the estimator's timing tests: the orbit scenario's surface points projected
at each row's own time (rolling shutter) on a clock offset from the IMU's, no images and no tracker.

Convention (backend/time_offset.py): t_imu = t_cam + offset for the top row's mid-exposure; row v of H is read
`readout * v / H` later.
"""

from __future__ import annotations

import numpy as np

from frontend.track_velocity import TrackVelocity
from vio.geometry import inv_T
from vio.records import GRAVITY_WORLD, FeatureTracks, ImuSeries


def _project_at(sc, cam, pts: np.ndarray, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distorted pixels (N, 2) and depths (N,) of points (N, 3), each seen from the pose at its own time t_s (N,)."""
    s = sc.trajectory.sample(t_s)
    T = np.zeros((len(t_s), 4, 4))
    T[:, :3, :3], T[:, :3, 3], T[:, 3, 3] = s.world_R_body, s.p_world, 1.0
    cam_T_world = np.array([inv_T(Tb @ cam.body_T_cam) for Tb in T])
    pc = np.einsum("nij,nj->ni", cam_T_world[:, :3, :3], pts) + cam_T_world[:, :3, 3]
    z = pc[:, 2]
    return cam.project(np.where(z[:, None] > 0.05, pc, np.array([0.0, 0.0, 1.0]))), z


def phone_tracks(
    duration_s: float = 6.0,
    offset_s: float = 0.015,
    readout_s: float = 0.02,
    seed: int = 0,
    px_noise: float = 0.3,
    frame_hz: float = 20.0,
    n_points: int = 400,
):
    """(camera, imu, imu_calib, frame tracks with image velocities (every frame), gt sampler) of the orbit."""
    from vio.sim.api import load_scenario

    sc = load_scenario("orbit", seed=seed, duration_s=duration_s + 0.2)
    rng = np.random.default_rng(seed)
    t_imu = np.arange(0.0, duration_s + 0.2, 1.0 / sc.imu_rate_hz)
    s = sc.trajectory.sample(t_imu)
    acc = np.einsum("nji,nj->ni", s.world_R_body, s.a_world - GRAVITY_WORLD)
    gyro = s.omega_body.copy()
    cal = sc.imu_calib
    dt = 1.0 / sc.imu_rate_hz
    gyro += rng.normal(0, cal.gyroscope_noise_density / np.sqrt(dt), gyro.shape)
    acc += rng.normal(0, cal.accelerometer_noise_density / np.sqrt(dt), acc.shape)
    t0 = sc.t0_ns
    imu = ImuSeries(t0 + np.round(t_imu * 1e9).astype(np.int64), gyro, acc)
    cam = sc.camera
    pts = sc.scene.sample_surface_points(n_points, rng)
    ids_all = np.arange(n_points, dtype=np.int64)
    velocity = TrackVelocity()
    frames = []
    for t_cam in np.arange(0.1, duration_s, 1.0 / frame_hz):  # camera-clock times, s after t0
        t_top = t_cam + offset_s  # IMU time of the top row
        uv, z = _project_at(sc, cam, pts, np.full(n_points, t_top + 0.5 * readout_s))
        for _ in range(4):  # each point at its own row's time
            rows = np.clip(uv[:, 1], 0, cam.height) / cam.height
            uv, z = _project_at(sc, cam, pts, t_top + readout_s * rows)
        uv = uv + rng.normal(0, px_noise, uv.shape)
        inside = (z > 0.1) & (uv[:, 0] > 0) & (uv[:, 0] < cam.width) & (uv[:, 1] > 0) & (uv[:, 1] < cam.height)
        tracks = FeatureTracks(t0 + int(round(t_cam * 1e9)), ids_all[inside], uv[inside])
        frames.append(velocity.add(tracks))
    return cam, imu, cal, frames, sc
