"""A camera spinning about its centre in front of a textured plane: exact images (homography K R K^-1) + gyro."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from vio.capture import Capture
from vio.records import CameraCalib, ImuCalib, ImuSeries

AXIS = np.array([0.3, 1.0, 0.15]) / np.linalg.norm([0.3, 1.0, 0.15])
FREQS = np.array([0.45, 0.83, 1.37])  # Hz
AMPS = np.array([0.06, 0.035, 0.02])  # rad


def angle(t_s: np.ndarray) -> np.ndarray:
    return (AMPS[None, :] * np.sin(2 * np.pi * FREQS[None, :] * t_s[:, None])).sum(axis=1)


def rate(t_s: np.ndarray) -> np.ndarray:
    return (AMPS[None, :] * 2 * np.pi * FREQS[None, :] * np.cos(2 * np.pi * FREQS[None, :] * t_s[:, None])).sum(axis=1)


def rotation_capture(duration_s: float = 6.0, fps: float = 30.0, offset_s: float = 0.0, seed: int = 0) -> Capture:
    """Frames recorded with t_cam = t_true - offset_s (so t_imu = t_cam + offset_s); IMU in the camera frame."""
    rng = np.random.default_rng(seed)
    w, h = 480, 360
    cam = CameraCalib(w, h, 400.0, 400.0, w / 2, h / 2, np.zeros(4), np.eye(4), fps)
    pad = 240
    tex = rng.random((h + 2 * pad, w + 2 * pad)).astype(np.float32)
    tex = cv2.GaussianBlur(tex, (0, 0), 3.0)
    tex = cv2.normalize(tex, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    K = cam.K
    K_tex = K.copy()
    K_tex[0, 2] += pad
    K_tex[1, 2] += pad
    t0 = 1_000_000_000_000
    n = int(duration_s * fps)
    t_true = t0 + np.round(np.arange(n) * 1e9 / fps).astype(np.int64)
    frames = []
    for tt in t_true:
        R = Rotation.from_rotvec(AXIS * angle(np.array([(tt - t0) * 1e-9]))[0]).as_matrix()
        H = K @ R.T @ np.linalg.inv(K_tex)
        frames.append(cv2.warpPerspective(tex, H, (w, h), flags=cv2.INTER_LINEAR))
    t_imu = t0 - 500_000_000 + np.arange(int((duration_s + 1.0) * 200)) * 5_000_000
    ts = (t_imu - t0) * 1e-9
    gyro = AXIS[None, :] * rate(ts)[:, None]
    world_R_body = Rotation.from_rotvec(AXIS[None, :] * angle(ts)[:, None])
    acc = world_R_body.inv().apply([0.0, 0.0, 9.81])  # at rest in place: specific force = -gravity, body frame
    imu = ImuSeries(t_imu.astype(np.int64), gyro, acc)
    calib = ImuCalib(1e-3, 1e-2, 1e-4, 1e-3, 200.0)
    t_cam = t_true - int(round(offset_s * 1e9))
    return Capture(Path("synthetic-rotation"), cam, calib, imu, t_cam, lambda i: frames[i], format="synthetic")
