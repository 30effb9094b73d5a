"""Camera-IMU calibration: the camera's pose in the IMU frame (`body_T_cam`, Kalibr's T_cam_imu inverted) and the
camera clock's offset (Kalibr's `timeshift_cam_imu`: t_imu = t_cam + shift), each with its standard deviation and
whether the motion excited it enough.

With a board (`calibrate_with_board`): the board's pose in every frame (`board_motion`) gives the camera's turns;
rotation and time offset come from them against the gyro (`rotation_align`: speed cross-correlation, hand-eye,
joint refinement); then the GTSAM batch graph (`extrinsic_graph`) estimates the whole extrinsic, translation
included, and refines the time offset on the accelerometer and gyro together. The graph's answers are the result;
the rotation step's are kept for the report.
Without a board, from feature tracks (`calibrate_with_tracks`, e.g. gtsam's eqvio file): the turns come from
essential matrices between frames (`track_turns`) for the rotation step, which `epipolar_align` then refines on the
tracks themselves (the gyro's turns must satisfy every track's epipolar constraint); the rotation and the time
offset are estimated, the translation is not (it needs the board's metric positions) and stays the given
calibration's.

Excitation: a quantity is `excited` when its one sigma is within half the accuracy a VIO needs of it (the EXCITED_*
limits); otherwise the summary says which motion was missing.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from vio.calibrate.board import Board
from vio.calibrate.board_motion import board_motion
from vio.calibrate.rotation_align import PAIR_SPAN_S, RotationAlignment, align_rotation, turns_from_poses
from vio.capture import Capture
from vio.errors import CalibrationError
from vio.records import ImuCalib

log = logging.getLogger(__name__)

EXCITED_ROT_RAD = np.deg2rad(0.1)  # one sigma of each rotation axis, rad
EXCITED_TRANS_M = 0.0025  # one sigma of each translation axis, m
EXCITED_OFFSET_NS = 0.5e6  # one sigma of the time offset, ns
MAX_OFFSET_S = 0.2  # the cross-correlation searches +-this, s


@dataclass(frozen=True)
class CameraImuCalibration:
    """The result; frames and conventions in the module docstring."""

    body_T_cam: np.ndarray  # (4, 4) the camera's pose in the IMU frame, m
    rotation_std_rad: np.ndarray  # (3,) about the body axes
    translation_std_m: np.ndarray | None  # (3,) along the body axes; None when not estimated (no board)
    timeshift_ns: float  # t_imu = t_cam + shift, including the shift the capture's frames were read with
    timeshift_std_ns: float
    excited: dict[str, bool]  # rotation, translation, time_offset
    rotation_step: RotationAlignment  # the rotation-only estimate (before the graph)
    frames_used: int  # frames with the board (or with tracks)
    frames_total: int
    method: str  # "board" | "tracks"
    notes: list[str] = field(default_factory=list)  # what the motion lacked, in words

    def summary(self) -> dict:
        """The result as plain numbers (for JSON)."""
        R = Rotation.from_matrix(self.body_T_cam[:3, :3])
        ra = self.rotation_step
        return {
            "method": self.method,
            "body_T_cam": self.body_T_cam.tolist(),
            "T_cam_imu": np.linalg.inv(self.body_T_cam).tolist(),
            "rotation_rpy_deg": R.as_euler("xyz", degrees=True).tolist(),
            "rotation_std_deg": np.rad2deg(self.rotation_std_rad).tolist(),
            "translation_m": self.body_T_cam[:3, 3].tolist(),
            "translation_std_m": None if self.translation_std_m is None else self.translation_std_m.tolist(),
            "timeshift_cam_imu_s": self.timeshift_ns * 1e-9,
            "timeshift_std_s": self.timeshift_std_ns * 1e-9,
            "excited": self.excited,
            "notes": self.notes,
            "frames_used": self.frames_used,
            "frames_total": self.frames_total,
            "rotation_step": {
                "timeshift_xcorr_s": ra.offset_xcorr_ns * 1e-9,
                "speed_correlation": ra.correlation,
                "timeshift_s": ra.offset_ns * 1e-9,
                "timeshift_std_s": ra.offset_std_ns * 1e-9,
                "body_R_cam": ra.body_R_cam.tolist(),
                "rotation_std_deg": np.rad2deg(ra.rotation_std_rad).tolist(),
                "gyro_bias_rad_s": ra.gyro_bias_rad_s.tolist(),
                "pairs": ra.pairs,
                "residual_rms_deg": float(np.rad2deg(ra.residual_rms_rad)),
                "axis_turn_rms_deg": np.rad2deg(ra.axis_turn_rad).tolist(),
            },
        }


def frame_period_s(cap: Capture) -> float:
    """The median time between frames, s (the calibration's rate_hz may be a guess for still images)."""
    if cap.num_frames < 2:
        raise CalibrationError(f"{cap.root}: the capture has fewer than 2 frames")
    return float(np.median(np.diff(cap.frame_t_ns))) * 1e-9


def _excitation(rot_std: np.ndarray, trans_std: np.ndarray | None, offset_std_ns: float) -> tuple[dict, list[str]]:
    excited = {
        "rotation": bool(np.all(rot_std <= EXCITED_ROT_RAD)),
        "translation": None if trans_std is None else bool(np.all(trans_std <= EXCITED_TRANS_M)),
        "time_offset": bool(offset_std_ns <= EXCITED_OFFSET_NS),
    }
    notes = []
    if not excited["rotation"]:
        notes.append("rotation weakly excited: turn the phone further about every axis (pan, tilt and roll)")
    if excited["translation"] is False:
        notes.append("translation weakly excited: turn the phone faster and about more than one axis")
    if not excited["time_offset"]:
        notes.append("time offset weakly excited: turn the phone back and forth more briskly")
    return excited, notes


def calibrate_with_board(
    cap: Capture,
    board: Board,
    imu_noise: ImuCalib,
    detector: str = "classic",
    max_offset_s: float = MAX_OFFSET_S,
    read_shift_ns: int = 0,
) -> CameraImuCalibration:
    """Rotation, translation and time offset of `cap`'s camera (module docstring). `cap` must carry the camera's
    intrinsics; `read_shift_ns` is the time shift its frame times were read with (the result's shift includes it)."""
    from vio.calibrate.extrinsic_graph import OFFSET_SEARCH_NS, ExtrinsicGraph

    if cap.imu is None:
        raise CalibrationError(f"{cap.root}: the capture has no IMU stream")
    assert cap.camera is not None
    motion = board_motion(cap, board, detector)
    if len(motion) < 10:
        raise CalibrationError(
            f"{cap.root}: the board is in only {len(motion)} of {cap.num_frames} frames; at least 10 are needed"
        )
    world_R_cam = Rotation.from_matrix(motion.board_T_cam[:, :3, :3])
    period_s = frame_period_s(cap)
    steps = turns_from_poses(motion.t_ns, world_R_cam, 0.5 * period_s, 0.5 * period_s)
    turns = turns_from_poses(motion.t_ns, world_R_cam, PAIR_SPAN_S, period_s)
    ra = align_rotation(steps, turns, cap.imu, max_offset_s)
    graph = ExtrinsicGraph(
        motion, cap.imu, imu_noise, ra.body_R_cam, cap.camera.body_T_cam[:3, 3], ra.offset_ns, ra.gyro_bias_rad_s
    )
    sol = graph.solve(ra.offset_ns)
    R = sol.body_T_cam[:3, :3]
    cov_rot = R @ sol.cov[:3, :3] @ R.T  # right perturbation (camera axes) -> body axes
    cov_trans = R @ sol.cov[3:, 3:] @ R.T  # t' = t + R dt
    rot_std = np.sqrt(np.maximum(np.diag(cov_rot), 0.0))
    trans_std = np.sqrt(np.maximum(np.diag(cov_trans), 0.0))
    excited, notes = _excitation(rot_std, trans_std, sol.offset_std_ns)
    if abs(sol.offset_ns - ra.offset_ns) > 0.9 * OFFSET_SEARCH_NS:
        notes.append(
            f"the graph's time offset is at the edge of its search (+-{OFFSET_SEARCH_NS * 1e-6:g} ms around the "
            f"rotation step's {(read_shift_ns + ra.offset_ns) * 1e-6:+.1f} ms): treat it with care"
        )
    return CameraImuCalibration(
        body_T_cam=sol.body_T_cam,
        rotation_std_rad=rot_std,
        translation_std_m=trans_std,
        timeshift_ns=read_shift_ns + sol.offset_ns,
        timeshift_std_ns=sol.offset_std_ns,
        excited=excited,
        rotation_step=ra,
        frames_used=len(motion),
        frames_total=motion.frames_searched,
        method="board",
        notes=notes,
    )


def calibrate_with_tracks(
    cap: Capture, max_offset_s: float = MAX_OFFSET_S, read_shift_ns: int = 0
) -> CameraImuCalibration:
    """Rotation and time offset from feature tracks (module docstring); the translation is the capture's."""
    from vio.calibrate.epipolar_align import refine_on_tracks
    from vio.calibrate.track_turns import bearing_pairs, track_turns

    if cap.imu is None:
        raise CalibrationError(f"{cap.root}: the capture has no IMU stream")
    assert cap.camera is not None
    steps, turns, frames = track_turns(cap)
    ra = align_rotation(steps, turns, cap.imu, max_offset_s)
    data, reuse = bearing_pairs(cap)
    ea = refine_on_tracks(data, cap.imu, ra.body_R_cam, ra.offset_ns, ra.gyro_bias_rad_s, cap.camera.fx, reuse)
    body_T_cam = np.eye(4)
    body_T_cam[:3, :3] = ea.body_R_cam
    body_T_cam[:3, 3] = cap.camera.body_T_cam[:3, 3]
    excited, notes = _excitation(ea.rotation_std_rad, None, ea.offset_std_ns)
    notes.append("translation not estimated (it needs a board): kept from the given calibration")
    return CameraImuCalibration(
        body_T_cam=body_T_cam,
        rotation_std_rad=ea.rotation_std_rad,
        translation_std_m=None,
        timeshift_ns=read_shift_ns + ea.offset_ns,
        timeshift_std_ns=ea.offset_std_ns,
        excited=excited,
        rotation_step=ra,
        frames_used=frames,
        frames_total=cap.num_frames,
        method="tracks",
        notes=notes,
    )
