"""The camera's motion seen from a calibration board: the board's pose in every frame of a capture (PnP).

Each frame is searched for the board (`vio.calibrate.board.BoardDetector`); where it is found, the pose comes from
`cv2.solvePnP` (iterative, then Levenberg-Marquardt refinement) with the calibrated intrinsics and distortion. Its
covariance is sigma^2 (J^T J)^-1 with J the Jacobian of the corners' pixels with respect to a perturbation of
`board_T_cam` on the right (GTSAM's Pose3 tangent order: rotation, then translation, both in the camera frame), and
sigma the RMS reprojection error over every view (at least `MIN_SIGMA_PX`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from vio.calibrate.board import Board, BoardDetector
from vio.capture import Capture
from vio.errors import CalibrationError, CaptureError
from vio.records import CameraCalib

log = logging.getLogger(__name__)

MIN_SIGMA_PX = 0.05  # floor of the corner noise used for the pose covariance, px
MIN_CORNERS = 8  # fewer corners than this in a view: no pose
MAX_VIEW_RMS_PX = 2.0  # a PnP solution with a larger RMS reprojection error is not a view of the board


@dataclass(frozen=True)
class BoardMotion:
    """The board's pose in the frames where it was found; times on the capture's (camera) clock."""

    t_ns: np.ndarray  # (F,) int64 frame times, ns
    board_T_cam: np.ndarray  # (F, 4, 4) the camera's pose in the board frame (x along columns, z into the board), m
    cov: np.ndarray  # (F, 6, 6) covariance of a right perturbation of board_T_cam (rad, m): rotation, translation
    rms_px: np.ndarray  # (F,) RMS reprojection error of each pose, px
    frames_searched: int  # frames of the capture searched for the board

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])


def _project(camera: CameraCalib, cam_T_board: np.ndarray, corners: np.ndarray) -> np.ndarray:
    p = corners @ cam_T_board[:3, :3].T + cam_T_board[:3, 3]
    return camera.project(p)


def _pose_jacobian(camera: CameraCalib, board_T_cam: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """(2N, 6) d pixels / d xi for board_T_cam * Exp(xi) (central differences; the projection is smooth)."""
    import gtsam

    pose = gtsam.Pose3(board_T_cam)
    J = np.empty((2 * len(corners), 6))
    h = 1e-6
    for k in range(6):
        d = np.zeros(6)
        d[k] = h
        plus = np.linalg.inv(pose.compose(gtsam.Pose3.Expmap(d)).matrix())
        minus = np.linalg.inv(pose.compose(gtsam.Pose3.Expmap(-d)).matrix())
        J[:, k] = (_project(camera, plus, corners) - _project(camera, minus, corners)).ravel() / (2 * h)
    return J


def board_motion(cap: Capture, board: Board, detector: str = "classic") -> BoardMotion:
    """The board's pose in every frame of `cap` that shows it (module docstring).

    CalibrationError (one line) when the capture has no calibrated camera or the board is found in no frame."""
    import cv2

    camera = cap.camera
    if camera is None:
        raise CalibrationError(f"{cap.root}: no camera calibration (pass --calib with the camera's camchain)")
    det = BoardDetector(board, detector)
    corners_all = board.corners_board()
    t_ns, poses, jacs, res, rms = [], [], [], [], []
    for i in range(cap.num_frames):
        try:
            gray = cap.load_image(i)
        except CaptureError as exc:
            log.info("frame %d skipped: %s", i, exc)
            continue
        found = det.detect(gray)
        if found is None or len(found.ids) < MIN_CORNERS:
            continue
        obj = corners_all[found.ids]
        ok, rvec, tvec = cv2.solvePnP(obj, found.uv, camera.K, camera.dist, flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok:
            continue
        rvec, tvec = cv2.solvePnPRefineLM(obj, found.uv, camera.K, camera.dist, rvec, tvec)
        cam_T_board = np.eye(4)
        cam_T_board[:3, :3] = cv2.Rodrigues(rvec)[0]
        cam_T_board[:3, 3] = np.asarray(tvec, float).ravel()
        r = found.uv - _project(camera, cam_T_board, obj)
        view_rms = float(np.sqrt(np.mean(np.sum(r**2, axis=1))))
        if view_rms > MAX_VIEW_RMS_PX or cam_T_board[2, 3] <= 0:
            log.info("frame %d: board pose rejected (RMS %.2f px)", i, view_rms)
            continue
        board_T_cam = np.linalg.inv(cam_T_board)
        t_ns.append(int(cap.frame_t_ns[i]))
        poses.append(board_T_cam)
        jacs.append(_pose_jacobian(camera, board_T_cam, obj))
        res.append(r.ravel())
        rms.append(view_rms)
    if not poses:
        raise CalibrationError(f"{cap.root}: no {board.describe()} found in any of {cap.num_frames} frame(s)")
    dof = sum(r.size for r in res) - 6 * len(res)
    sigma = max(float(np.sqrt(sum(float(r @ r) for r in res) / max(dof, 1))), MIN_SIGMA_PX)
    cov = np.array([sigma**2 * np.linalg.inv(J.T @ J) for J in jacs])
    log.info("board found in %d of %d frames (corner noise %.3f px)", len(poses), cap.num_frames, sigma)
    return BoardMotion(np.asarray(t_ns, np.int64), np.array(poses), cov, np.asarray(rms), cap.num_frames)
