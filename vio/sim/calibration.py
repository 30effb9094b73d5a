"""The calibration scenario: a board on a wall filmed hand-held by the simulated phone (camera and IMU).

World z up; the wall is the plane y = WALL_Y_M and the board hangs on it centred at BOARD_CENTRE_M, its x along
world x, its y down the wall, its z into the wall. The camera sways in front of it in all six degrees of freedom
(sums of sinusoids with seeded phases, smooth to any order, so the IMU sees the true derivatives): +-0.2 m sideways,
+-0.13 m up and down, 0.33-0.67 m from the wall, its aim wandering over the board and its roll +-30 deg, so the board
is seen head-on and obliquely, near the image centre and near its edges. Frames are rendered by
`vio.sim.board_render` through the rig's camera (pinhole, radtan, global shutter); the IMU, ground truth and
calibration files are those of every simulated capture. `scene/board.yaml` records the board spec,
`world_T_board`, the true `body_T_cam` and the camera clock's offset.

Clock offset (`time_offset_s`, Kalibr's `timeshift_cam_imu`: t_imu = t_cam + shift): frame k is exposed at the true
time t0 + k / rate on the IMU clock and stamped `t_true - time_offset_s` on the camera clock; frames whose stamp falls
outside the IMU's span are left out. With no offset the capture is the one written before the offset existed.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np
import yaml

from vio.atomic import write_text
from vio.calibrate.board import Board, parse_board
from vio.errors import CalibrationError, SimulationError
from vio.geometry import inv_T
from vio.sim import rig
from vio.sim.board_render import BoardTexture, charuco_texture, chessboard_texture, render_board, undistorted_rays
from vio.sim.imu import grade_by_name, imu_calib, simulate_imu
from vio.sim.trajectory import PoseFn, Sinusoids, Trajectory, camera_driven, look_at
from vio.writers.asl import AslWriter

log = logging.getLogger(__name__)

DEFAULT_BOARD = "chessboard:9x6:30"
DEFAULT_DURATION_S = 30.0
WALL_Y_M = 1.0
BOARD_CENTRE_M = np.array([0.0, WALL_Y_M, 1.3])
WORLD_R_BOARD = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # board x, y (down), z (into wall)
IMAGE_NOISE_GREY = 2.0  # sensor noise, grey levels (sigma)
MAX_TIME_OFFSET_S = 0.5  # the largest camera clock offset simulated, s (as the phone camera's)


def world_T_board(board: Board) -> np.ndarray:
    """(4, 4) the board frame in the world: the board's corner grid centred on BOARD_CENTRE_M."""
    T = np.eye(4)
    T[:3, :3] = WORLD_R_BOARD
    T[:3, 3] = BOARD_CENTRE_M - WORLD_R_BOARD @ board.corners_board().mean(axis=0)
    return T


def calibration_camera(rng: np.random.Generator) -> PoseFn:
    """Camera pose function (p_cam, world_R_cam) of the hand-held sway in front of the board (module docstring)."""
    sweep = Sinusoids.make([1.0], [1.0 / 9.0], 1, rng)  # sideways, one sweep per 9 s
    lift = Sinusoids.make([1.0], [1.0 / 7.0], 1, rng)
    reach = Sinusoids.make([1.0], [1.0 / 5.5], 1, rng)
    aim = Sinusoids.make([0.07, 0.02], [1.0 / 6.5, 0.43], 2, rng)
    roll = Sinusoids.make([0.45, 0.07], [1.0 / 8.0, 0.37], 1, rng)
    wobble = Sinusoids.make([0.006, 0.003, 0.0012], [0.93, 1.63, 2.71], 3, rng)

    def fn(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        distance = 0.5 + 0.17 * reach(t)[:, 0]
        p = np.column_stack(
            [0.2 * sweep(t)[:, 0], WALL_Y_M - distance, BOARD_CENTRE_M[2] + 0.13 * lift(t)[:, 0]]
        ) + wobble(t)
        a = aim(t)
        target = BOARD_CENTRE_M + np.column_stack([a[:, 0], np.zeros(len(t)), a[:, 1]])
        return p, look_at(p, target, roll(t)[:, 0])

    return fn


def excite_camera(rng: np.random.Generator) -> PoseFn:
    """Camera pose function of the brisk motion a camera-IMU calibration wants (Kalibr's advice: excite every
    axis): the sway of `calibration_camera` plus turns about every axis at 0.4-1.3 Hz, the aim swinging +-0.1 m over
    the board (about +-11 deg of pan and tilt), the roll +-35 deg, and the hand's shakes of +-2 cm; the board stays in
    view."""
    sweep = Sinusoids.make([1.0], [1.0 / 9.0], 1, rng)
    lift = Sinusoids.make([1.0], [1.0 / 7.0], 1, rng)
    reach = Sinusoids.make([1.0], [1.0 / 5.5], 1, rng)
    aim = Sinusoids.make([0.06, 0.04], [0.45, 1.1], 2, rng)
    roll = Sinusoids.make([0.45, 0.17], [0.35, 1.3], 1, rng)
    shake = Sinusoids.make([0.012, 0.008], [0.8, 1.7], 3, rng)

    def fn(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        distance = 0.52 + 0.12 * reach(t)[:, 0]
        p = np.column_stack(
            [0.15 * sweep(t)[:, 0], WALL_Y_M - distance, BOARD_CENTRE_M[2] + 0.1 * lift(t)[:, 0]]
        ) + shake(t)
        a = aim(t)
        target = BOARD_CENTRE_M + np.column_stack([a[:, 0], np.zeros(len(t)), a[:, 1]])
        return p, look_at(p, target, roll(t)[:, 0])

    return fn


MOTIONS = {"sway": calibration_camera, "excite": excite_camera}  # the intrinsics' gentle sway; camera-IMU's brisk one


def board_texture(board: Board) -> BoardTexture:
    if board.kind == "chessboard":
        return chessboard_texture(board.cols, board.rows, board.square_m)
    return charuco_texture(board.cols, board.rows, board.square_m, board.marker_m, board.dictionary)


def _matrix(T: np.ndarray) -> list[list[float]]:
    return [[round(float(v), 12) for v in row] for row in T]


def _board_yaml(spec: str, board: Board, T: np.ndarray, body_T_cam: np.ndarray, time_offset_s: float) -> str:
    meta = {
        "board": spec,
        "description": board.describe(),
        "world_T_board": _matrix(T),
        "body_T_cam": _matrix(body_T_cam),
        "timeshift_cam_imu_s": float(time_offset_s),
        "frames": "world z up; board x along its columns, y along its rows (down the wall), z into the wall; m",
        "convention": "frames are stamped on the camera clock: t_imu = t_cam + timeshift_cam_imu_s",
    }
    return "# vio simulated calibration board (ground truth)\n" + yaml.safe_dump(meta, sort_keys=False)


def simulate_calibration(
    out: str | os.PathLike[str],
    board_spec: str = DEFAULT_BOARD,
    seed: int = 0,
    duration_s: float | None = None,
    imu_grade: str = "phone",
    overwrite: bool = False,
    images: bool = True,
    time_offset_s: float = 0.0,
    motion: str = "sway",
    camera_motion: PoseFn | None = None,
) -> Path:
    """Write the calibration scenario's capture (ASL layout) under `out`; returns `out` as a Path.

    Seeds are split like every scenario's (`SeedSequence(seed).spawn(5)`: motion, IMU, image noise).
    `time_offset_s` is the camera clock's offset (module docstring); `motion` one of MOTIONS; `camera_motion`
    replaces it (a pose function of time in s, as `calibration_camera` returns), e.g. a motion without rotation."""
    try:
        board = parse_board(board_spec)
    except CalibrationError as exc:  # the same one-line message, as the simulator's error
        raise SimulationError(str(exc)) from None
    dur = DEFAULT_DURATION_S if duration_s is None else float(duration_s)
    if not np.isfinite(dur) or dur <= 0:
        raise SimulationError(f"duration must be positive, got {duration_s}")
    if seed < 0:
        raise SimulationError(f"seed must be non-negative, got {seed}")
    if not np.isfinite(time_offset_s) or abs(time_offset_s) > MAX_TIME_OFFSET_S:
        raise SimulationError(
            f"time offset must be within +-{MAX_TIME_OFFSET_S * 1e3:g} ms, got {time_offset_s * 1e3:g}"
        )
    if motion not in MOTIONS:
        raise SimulationError(f"calibration motion must be one of {', '.join(MOTIONS)}, got {motion!r}")
    ss_motion, ss_imu, ss_img, _, _ = np.random.SeedSequence(seed).spawn(5)
    camera = rig.default_camera()
    pose_fn = MOTIONS[motion](np.random.default_rng(ss_motion)) if camera_motion is None else camera_motion
    traj = Trajectory(camera_driven(pose_fn, camera.body_T_cam), dur)
    grade = grade_by_name(imu_grade)
    imu, gt = simulate_imu(traj, rig.T0_NS, dur, rig.IMU_RATE_HZ, grade, np.random.default_rng(ss_imu))
    T_board = world_T_board(board)
    comment = f"vio simulator (calibration, {board_spec}, seed {seed})"
    with AslWriter(out, overwrite=overwrite) as writer:
        writer.write_camera(camera, comment)
        writer.write_imu(imu_calib(grade, rig.IMU_RATE_HZ), imu, f"{comment}, {grade.name} IMU")
        writer.write_groundtruth(gt)
        meta = _board_yaml(board_spec, board, T_board, camera.body_T_cam, time_offset_s)
        write_text(writer.scene_dir / "board.yaml", meta)
        if images:
            tex, rays = board_texture(board), undistorted_rays(camera)
            n = int(np.floor(dur * rig.CAMERA_RATE_HZ + 1e-9))
            t_ns = rig.T0_NS + np.round(np.arange(n) * (1e9 / rig.CAMERA_RATE_HZ)).astype(np.int64)
            stamps = t_ns - int(round(time_offset_s * 1e9))
            p, R = traj.pose((t_ns - rig.T0_NS) * 1e-9)
            t_end = rig.T0_NS + int(round(dur * 1e9))
            for k, seq in enumerate(ss_img.spawn(n)):
                if not rig.T0_NS <= stamps[k] <= t_end:  # the noise stream stays per frame index
                    continue
                world_T_body = np.eye(4)
                world_T_body[:3, :3], world_T_body[:3, 3] = R[k], p[k]
                cam_T_board = inv_T(world_T_body @ camera.body_T_cam) @ T_board
                img = render_board(tex, camera, cam_T_board, rays, np.random.default_rng(seq), IMAGE_NOISE_GREY)
                writer.add_frame(int(stamps[k]), img)
    log.info("simulated calibration (%.1f s, seed %d, %s) into %s", dur, seed, board.describe(), out)
    return Path(out)
