"""The camera's timing in the estimator (issue 16, backend/time_offset.py): keyframe poses placed in IMU time,
rolling-shutter views moved to the pose time, and the camera-IMU time offset estimated from ideal phone tracks
(tests/backend/phone_tracks.py: the orbit's points projected at each row's own time, no images)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from backend import factors as fb
from backend.estimator import VioEstimator
from backend.graph_state import GraphState
from backend.smoother import Smoother
from backend.time_offset import CameraTiming, gyro_at, gyro_rotation
from frontend.preintegration import ImuPreintegrator
from tests.backend.phone_tracks import phone_tracks
from vio.config import CameraConfig, Config, ImuConfig, SmootherConfig
from vio.records import CameraCalib, FeatureTracks, ImuSeries

H = 480


def _camera(dist=(0.0, 0.0, 0.0, 0.0)) -> CameraCalib:
    return CameraCalib(640, H, 460.0, 455.0, 321.0, 239.0, np.asarray(dist, float), np.eye(4), 20.0)


def _imu(rate_rad_s: float = 0.5, n: int = 300) -> ImuSeries:
    t = np.arange(n, dtype=np.int64) * 5_000_000  # 200 Hz
    gyro = np.tile([0.0, 0.0, rate_rad_s], (n, 1))
    return ImuSeries(t, gyro, np.tile([0.0, 0.0, 9.81], (n, 1)))


def _timing(cfg: CameraConfig, camera: CameraCalib | None = None) -> CameraTiming:
    camera = camera or _camera()
    state = GraphState(
        Smoother(SmootherConfig()), fb.calibration(camera), fb.PixelNoise(1.0, 0.0, 1.345), 30, lambda msg: None
    )
    return CameraTiming(cfg, camera, _imu(), state, enabled=True)


def test_defaults_leave_keyframe_times_and_views_alone():
    timing = _timing(CameraConfig())
    t = 1_700_000_000_123_456_789
    assert timing.pose_time_ns(t) == t
    uv = np.array([[10.0, 5.0], [300.0, 470.0]])
    tracks = FeatureTracks(t, np.array([1, 2]), uv, uv_per_s=np.array([[100.0, -50.0], [30.0, 80.0]]))
    assert timing.correct(tracks, uv) is uv
    report = timing.report()
    assert not report.estimated and report.value_s == 0.0 and report.readout_s == 0.0


def test_pose_is_placed_at_the_centre_row_in_imu_time():
    timing = _timing(CameraConfig(readout_s=0.02, time_offset_s=0.015))
    assert timing.pose_time_ns(1_000_000_000) == 1_025_000_000  # top row +15 ms, centre row 10 ms later


def test_rolling_shutter_correction_is_exact_for_a_known_velocity():
    """Points move across the image at constant velocity; the readout line meets each at its own row's time. Moved
    by the correction, every view lands where its point was at the pose time (the centre row's)."""
    readout, t_top = 0.02, 0.0
    timing = _timing(CameraConfig(readout_s=readout))
    rng = np.random.default_rng(3)
    uv0 = np.column_stack([rng.uniform(50, 590, 40), rng.uniform(40, 440, 40)])  # positions at t = 0, px
    vel = rng.uniform(-300, 300, (40, 2))  # px/s
    # row v is read at t_top + readout * v / H, and the point is at v0 + vel_v * t: solve for the row
    t_row = (t_top + readout * uv0[:, 1] / H) / (1.0 - vel[:, 1] * readout / H)
    seen = uv0 + t_row[:, None] * vel
    assert np.allclose(seen[:, 1], H * (t_row - t_top) / readout)  # each seen at its own row's time
    tracks = FeatureTracks(0, np.arange(40), seen, uv_per_s=vel)
    at_pose = uv0 + (t_top + 0.5 * readout) * vel  # where the points are at the centre row's time
    assert np.allclose(timing.correct(tracks, seen.copy()), at_pose, atol=1e-9)
    top = np.argmin(seen[:, 1])  # a view above the centre moves forward in time along its velocity
    assert np.sign(timing.correct(tracks, seen.copy())[top, 0] - seen[top, 0]) == np.sign(vel[top, 0])


def test_velocity_in_distorted_pixels_is_mapped_to_undistorted_pixels():
    camera = _camera((-0.2, 0.05, 0.001, -0.001))
    timing = _timing(CameraConfig(readout_s=0.02), camera)
    uv_d = np.array([[50.0, 60.0], [320.0, 240.0], [600.0, 420.0]])
    vel_d = np.array([[120.0, -40.0], [10.0, 10.0], [-200.0, 90.0]])
    tracks = FeatureTracks(0, np.arange(3), uv_d, uv_per_s=vel_d)
    h = 1e-4
    want = (fb.undistorted_px(camera, uv_d) - fb.undistorted_px(camera, uv_d - h * vel_d)) / h
    assert np.allclose(timing.undistorted_velocity(tracks), want, rtol=1e-4)


def test_gyro_rotation_and_rate_of_a_constant_turn():
    imu = _imu(0.5)
    bias = np.array([0.0, 0.0, 0.1])
    R = gyro_rotation(imu, 100_000_000, 600_000_000, bias)
    assert np.allclose(Rotation.from_matrix(R).as_rotvec(), [0.0, 0.0, 0.4 * 0.5], atol=1e-12)
    assert np.allclose(gyro_at(imu, 250_000_000, bias), [0.0, 0.0, 0.4])
    assert gyro_rotation(imu, 100_000_000, 10_000_000_000, bias) is None  # beyond the IMU


def _run(offset_s: float, readout_s: float, estimate: bool, seed: int, start_s: float = 0.0) -> VioEstimator:
    cam, imu, cal, frames, _ = phone_tracks(duration_s=8.0, offset_s=offset_s, readout_s=readout_s, seed=seed)
    cfg = Config(camera=CameraConfig(readout_s=readout_s, estimate_time_offset=estimate, time_offset_s=start_s))
    est = VioEstimator(cam, imu, ImuPreintegrator(imu, cal, ImuConfig()).between, cfg)
    for i, tr in enumerate(frames):
        if i % 2 == 0:  # keyframes at 10 Hz, velocities from the 20 Hz frames
            est.add_keyframe(tr.t_ns, tr)
    return est


@pytest.mark.slow
@pytest.mark.parametrize(("offset_s", "readout_s", "seed"), [(0.015, 0.02, 5), (-0.012, 0.0, 6)])
def test_time_offset_is_recovered_from_ideal_phone_tracks(offset_s, readout_s, seed):
    est = _run(offset_s, readout_s, estimate=True, seed=seed)
    got = est.stats().time_offset
    assert got is not None and got.estimated
    assert got.sigma_s is not None and 0 < got.sigma_s < 0.004  # 1-2 ms after 8 s of orbit
    assert abs(got.value_s - offset_s) < max(3 * got.sigma_s, 0.0025)
    assert got.after_initialisation_s is not None  # a first estimate from the start window
    assert abs(got.after_initialisation_s - offset_s) < abs(offset_s)  # already most of the way
    assert got.num_keyframes > 30 and got.readout_s == readout_s
