"""Unit tests of the backend's pieces: static start, gravity rotation, yaw fit, landmark admission."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from backend.anchoring import fit_yaw_translation
from backend.initialisation.alignment import rotation_to_z_up, static_start
from backend.landmarks import LandmarkBook, triangulate
from vio.config import InitialisationConfig, LandmarkConfig
from vio.geometry import inv_T, make_T
from vio.records import GRAVITY_M_S2, ImuSeries

AT_REST = (InitialisationConfig().static_max_gyro, InitialisationConfig().static_max_acc_std)  # defaults


def test_rotation_to_z_up():
    rng = np.random.default_rng(1)
    for v in [*rng.normal(size=(5, 3)), np.array([0, 0, -2.0]), np.array([0, 0, 3.0])]:
        R = rotation_to_z_up(v)
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(R), 1.0)
        assert np.allclose(R @ (v / np.linalg.norm(v)), [0, 0, -1], atol=1e-12)


def _rest_imu(world_R_body, bias_gyro, vibration, seconds=1.0, rate=200.0, seed=0):
    rng = np.random.default_rng(seed)
    n = int(seconds * rate)
    t = (np.arange(n) * 1e9 / rate).astype(np.int64)
    f = world_R_body.T @ np.array([0, 0, GRAVITY_M_S2])
    acc = f + rng.normal(0, vibration, (n, 3))
    gyro = bias_gyro + rng.normal(0, vibration * 0.1, (n, 3))
    return ImuSeries(t, gyro, acc)


def test_static_start_recovers_tilt_and_gyro_bias_despite_vibration():
    R = Rotation.from_euler("xyz", [20, -35, 70], degrees=True).as_matrix()
    bias = np.array([0.01, -0.02, 0.07])
    imu = _rest_imu(R, bias, vibration=0.25)  # white; EuRoC idling rotors: 1 m/s^2 raw but mostly high frequency
    out = static_start(imu, 0, int(imu.t_ns[-1]), *AT_REST)
    assert out is not None
    world_R_body, b = out
    up_err = np.degrees(np.arccos(np.clip((world_R_body.T @ [0, 0, 1]) @ (R.T @ [0, 0, 1]), -1, 1)))
    assert up_err < 0.5 and np.abs(b - bias).max() < 0.01


def test_static_start_rejects_motion():
    imu = _rest_imu(np.eye(3), np.zeros(3), vibration=0.01)
    t_s = imu.t_ns * 1e-9
    acc = imu.acc + np.column_stack([2.0 * np.sin(2 * np.pi * t_s), np.zeros_like(t_s), np.zeros_like(t_s)])
    assert static_start(ImuSeries(imu.t_ns, imu.gyro, acc), 0, int(imu.t_ns[-1]), *AT_REST) is None
    gyro = imu.gyro + np.column_stack([np.zeros_like(t_s), np.zeros_like(t_s), 0.5 * t_s])
    assert static_start(ImuSeries(imu.t_ns, gyro, imu.acc), 0, int(imu.t_ns[-1]), *AT_REST) is None


def test_fit_yaw_translation():
    rng = np.random.default_rng(2)
    p = rng.normal(size=(20, 3))
    T = make_T(Rotation.from_euler("z", 123, degrees=True).as_matrix(), [1.0, -2.0, 0.5])
    q = p @ T[:3, :3].T + T[:3, 3]
    assert np.allclose(fit_yaw_translation(p, q), T, atol=1e-10)


def _book():
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    return LandmarkBook(K, np.eye(4), LandmarkConfig(min_views=3, min_parallax_deg=2.0, max_reprojection_px=2.0))


def _views(book, p_world, xs):
    """Cameras on the x axis looking along +z at p_world; returns poses and pixels."""
    poses = {k: make_T(np.eye(3), [x, 0, 0]) for k, x in enumerate(xs)}
    uv = {}
    for k, T in poses.items():
        pc = inv_T(T)[:3, :3] @ p_world + inv_T(T)[:3, 3]
        uv[k] = book.K[:2, :2] @ (pc[:2] / pc[2]) + book.K[:2, 2]
    return poses, uv


def test_triangulation_and_admission():
    book = _book()
    p = np.array([0.3, -0.2, 4.0])
    poses, uv = _views(book, p, [0.0, 0.1, 0.2, 0.3])
    Twc = np.stack(list(poses.values()))
    assert np.allclose(triangulate(Twc, book.normalized(np.stack(list(uv.values())))), p, atol=1e-9)
    for k in (0, 1):
        book.observe(k, np.array([7]), uv[k][None])
    assert book.try_admit(7, poses) is None  # two views only
    book.observe(2, np.array([7]), uv[2][None])
    assert np.allclose(book.try_admit(7, poses), p, atol=1e-9)  # 3 views, 2.9 deg parallax


def test_admission_rejects_low_parallax_and_drops_an_outlier_view():
    book = _book()
    p = np.array([0.0, 0.0, 20.0])
    poses, uv = _views(book, p, [0.0, 0.1, 0.2])  # 0.6 deg of parallax
    book.observe(0, np.array([1]), uv[0][None])
    book.observe(1, np.array([1]), uv[1][None])
    book.observe(2, np.array([1]), uv[2][None])
    assert book.try_admit(1, poses) is None
    p = np.array([0.2, 0.1, 3.0])
    poses, uv = _views(book, p, [0.0, 0.1, 0.2, 0.3, 0.4])
    uv[3] = uv[3] + [8.0, 0.0]  # a track jump
    for k in range(5):
        book.observe(k, np.array([2]), uv[k][None])
    assert np.allclose(book.try_admit(2, poses), p, atol=1e-6)
    assert sorted(book.tracks[2].views) == [0, 1, 2, 4]


def test_pixel_noise_grows_with_the_views_age_and_shares_models():
    import gtsam

    from backend.factors import PixelNoise

    flat = PixelNoise(1.0, 0.0, 1.345)
    assert flat.at(0.0) is flat.at(5.0)  # one model for every view
    assert flat.at(3.0).noise().sigmas()[0] == 1.0
    grow = PixelNoise(0.3, 0.4, 1.345)
    sig = [float(grow.at(a).noise().sigmas()[0]) for a in (0.0, 0.5, 2.0, 2.01)]
    assert np.allclose(sig, [0.3, 0.5, 1.1, 1.1])  # 0.3 + 0.4 a, rounded to 0.05 px
    assert grow.at(2.0) is grow.at(2.01)  # same level, same model
    assert isinstance(grow.at(-1.0), gtsam.noiseModel.Robust) and grow.sigma(-1.0) == 0.3


def test_a_views_run_starts_after_its_tracks_last_gap():
    from backend.landmarks import Track

    tr = Track()
    for k in (3, 4, 5, 9, 10, 11):  # seen at 3-5, lost, re-identified at 9-11
        tr.views[k] = np.zeros(2)
    assert [tr.run_start(k) for k in (3, 5, 9, 11)] == [3, 3, 9, 9]
