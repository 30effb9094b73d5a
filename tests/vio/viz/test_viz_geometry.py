"""The viewer's numbers: ground truth anchored by yaw and position, reprojection errors in pixels."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from vio.records import CameraCalib
from vio.viz.geometry import anchor_yaw_translation, reprojection_errors_px


def _pose(rotvec, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def test_anchor_recovers_yaw_and_translation():
    rng = np.random.default_rng(3)
    for _ in range(20):
        gt = _pose(rng.normal(size=3), rng.normal(size=3))
        yaw_move = _pose([0, 0, rng.uniform(-np.pi, np.pi)], rng.normal(size=3))
        T = anchor_yaw_translation(yaw_move @ gt, gt)
        np.testing.assert_allclose(T, yaw_move, atol=1e-12)


def test_anchor_ignores_roll_pitch_error():
    gt = _pose([0.1, -0.2, 0.3], [1, 2, 3])
    est = _pose([0, 0, 0.5], [0, 0, 0]) @ gt @ _pose([0.02, -0.01, 0.0], [0, 0, 0])  # a small tilt error
    T = anchor_yaw_translation(est, gt)
    assert np.allclose(T[2], [0, 0, 1, T[2, 3]]) and np.allclose(T[:2, 2], 0)  # a rotation about z only
    np.testing.assert_allclose(T[:3, :3] @ gt[:3, 3] + T[:3, 3], est[:3, 3], atol=1e-12)  # positions coincide


def test_reprojection_errors_px():
    cam = CameraCalib(640, 480, 450.0, 455.0, 320.0, 240.0, np.array([-0.2, 0.05, 1e-3, -1e-3]), np.eye(4))
    rng = np.random.default_rng(0)
    world_T_cam = _pose([0.1, 0.2, -0.1], [0.5, -0.3, 0.2])
    p_cam = np.column_stack([rng.uniform(-1, 1, (30, 2)), rng.uniform(2, 5, 30)])
    p_world = (world_T_cam[:3, :3] @ p_cam.T).T + world_T_cam[:3, 3]
    uv = cam.project(p_cam)
    ids = np.arange(100, 130)
    shift = np.zeros_like(uv)
    shift[::2, 0] = 3.0  # every other feature tracked 3 px off
    order = rng.permutation(30)  # tracks arrive in another order than the landmarks, plus some unknown ids
    track_ids = np.concatenate([ids[order], [7, 8]])
    track_uv = np.vstack([(uv + shift)[order], [[1, 1], [2, 2]]])
    err = reprojection_errors_px(cam, world_T_cam, ids, p_world, track_ids, track_uv)
    assert err.shape == (30,)
    np.testing.assert_allclose(np.sort(err), np.sort(np.linalg.norm(shift, axis=1)), atol=1e-9)
    behind = p_world.copy()
    behind[:] = world_T_cam[:3, 3] - world_T_cam[:3, 2]  # one metre behind the camera
    assert reprojection_errors_px(cam, world_T_cam, ids, behind, track_ids, track_uv).size == 0
    assert reprojection_errors_px(cam, world_T_cam, ids, p_world, np.array([1, 2]), uv[:2]).size == 0


def test_reprojection_uses_the_newest_segment_of_a_split_track():
    """A track split into segments gives several landmarks with its track id, oldest first (the estimator's order):
    its feature is compared with the newest, the landmark its current view belongs to."""
    cam = CameraCalib(640, 480, 450.0, 455.0, 320.0, 240.0, np.zeros(4), np.eye(4))
    world_T_cam = np.eye(4)
    here, drifted = np.array([0.1, -0.2, 3.0]), np.array([0.4, 0.1, 3.0])
    uv = cam.project(here)
    track_ids = np.array([5, 9, 5])  # track 5: segment 0 (drifted off), track 9, then track 5's segment 1
    err = reprojection_errors_px(cam, world_T_cam, track_ids, np.array([drifted, here, here]), np.array([5]), uv)
    np.testing.assert_allclose(err, [0.0], atol=1e-9)
