"""Numbers the viewer shows beside the estimate (no rerun here): the ground truth anchored in the estimate's world,
and the reprojection error of a keyframe's tracked features against the estimated landmarks."""

from __future__ import annotations

import numpy as np

from vio.records import CameraCalib


def anchor_yaw_translation(est_world_T_body: np.ndarray, gt_world_T_body: np.ndarray) -> np.ndarray:
    """(4, 4) est_world_T_gt_world: the rotation about z and translation that put the ground-truth body pose onto the
    estimated one at the same instant. Both worlds are z-up (gravity fixes roll and pitch), so only yaw and position
    are free: this is how the ground truth is drawn in the estimate's world, anchored at the first keyframe."""
    R_d = est_world_T_body[:3, :3] @ gt_world_T_body[:3, :3].T
    yaw = np.arctan2(R_d[1, 0] - R_d[0, 1], R_d[0, 0] + R_d[1, 1])  # best rotation about z in the least-squares sense
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = est_world_T_body[:3, 3] - T[:3, :3] @ gt_world_T_body[:3, 3]
    return T


def reprojection_errors_px(
    camera: CameraCalib,
    world_T_cam: np.ndarray,
    landmark_ids: np.ndarray,
    landmarks_world: np.ndarray,
    track_ids: np.ndarray,
    uv: np.ndarray,
) -> np.ndarray:
    """(M,) pixel distances between tracked features (distorted px) and the projections of the estimated landmarks
    with the same ids (world frame, m) through world_T_cam; landmarks behind the camera are left out."""
    common, i_lm, i_tr = np.intersect1d(np.asarray(landmark_ids), np.asarray(track_ids), return_indices=True)
    if common.size == 0:
        return np.zeros(0)
    cam_T_world = np.linalg.inv(world_T_cam)
    p_cam = (cam_T_world[:3, :3] @ np.asarray(landmarks_world, float)[i_lm].T).T + cam_T_world[:3, 3]
    front = p_cam[:, 2] > 1e-6
    if not front.any():
        return np.zeros(0)
    proj = camera.project(p_cam[front])
    return np.linalg.norm(proj - np.asarray(uv, float)[i_tr][front], axis=1)
