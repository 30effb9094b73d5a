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
    landmark_track_ids: np.ndarray,
    landmarks_world: np.ndarray,
    track_ids: np.ndarray,
    uv: np.ndarray,
) -> np.ndarray:
    """(M,) pixel distances between tracked features (distorted px) and the projections of the estimated landmarks
    (world frame, m) through world_T_cam, matched by the track id each landmark came from (`landmark_track_ids`);
    landmarks behind the camera are left out.

    Several landmarks may share a track id (a long track split into segments, listed oldest first): a feature is
    compared with the last of them, the one its current view belongs to."""
    newest_first = np.arange(len(landmark_track_ids))[::-1]
    common, i_new, i_tr = np.intersect1d(
        np.asarray(landmark_track_ids)[newest_first], np.asarray(track_ids), return_indices=True
    )  # intersect1d keeps the first instance of a repeated id
    i_lm = newest_first[i_new]
    if common.size == 0:
        return np.zeros(0)
    cam_T_world = np.linalg.inv(world_T_cam)
    p_cam = (cam_T_world[:3, :3] @ np.asarray(landmarks_world, float)[i_lm].T).T + cam_T_world[:3, 3]
    front = p_cam[:, 2] > 1e-6
    if not front.any():
        return np.zeros(0)
    proj = camera.project(p_cam[front])
    return np.linalg.norm(proj - np.asarray(uv, float)[i_tr][front], axis=1)
