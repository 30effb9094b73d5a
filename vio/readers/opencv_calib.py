"""Calibration files written by OpenCV's `FileStorage` (`%YAML:1.0`, `!!opencv-matrix` nodes), read by OpenCV.

PyYAML cannot read these files (the `%YAML:1.0` directive and the `!!opencv-matrix` tag), so they are parsed by
`cv2.FileStorage`, the library that writes them. Two layouts:

- **OpenCV's calibration sample** (`samples/cpp/calibration.cpp`, the tutorial's `camera_calibration`):
  `image_width`, `image_height`, `camera_matrix` (3x3 K), `distortion_coefficients` (k1, k2, p1, p2[, k3, ...]).
  It has no camera-IMU extrinsics: `body_T_cam` is the identity, with a warning to run `vio calibrate camera-imu`.
- **ORB-SLAM2 / ORB-SLAM3 settings**: `Camera.fx/fy/cx/cy`, `Camera.k1/k2/p1/p2[/k3]`, `Camera.width/height`,
  `Camera.fps` (frames per second; ORB-SLAM2's files carry no image size, which the capture's images then give),
  `Camera.type` (`PinHole`; `KannalaBrandt8` fisheye is refused), and ORB-SLAM3's
  version 1.0 files with `Camera1.fx ...` (the first camera). The camera-IMU extrinsics of ORB-SLAM3's inertial
  settings, `Tbc` (older files) or `IMU.T_b_c1` (version 1.0), are **body_T_cam**: they map a point from the
  camera frame to the body (IMU) frame, Kalibr's `T_BS` / the inverse of Kalibr's `T_cam_imu` (ORB-SLAM3's EuRoC
  settings carry EuRoC's cam0 `T_BS` there). The IMU noise `IMU.NoiseGyro` (rad/s/sqrt(Hz)), `IMU.NoiseAcc`
  (m/s^2/sqrt(Hz)), `IMU.GyroWalk` (rad/s^2/sqrt(Hz)), `IMU.AccWalk` (m/s^3/sqrt(Hz)) are continuous-time densities,
  Kalibr's units (ORB-SLAM3's EuRoC values are EuRoC's `sensor.yaml` values), `IMU.Frequency` in Hz.

This project's camera is pinhole with four radtan coefficients. A fifth coefficient k3 is dropped with a warning when
its effect at the image corners is below `K3_TOLERANCE_PX`, else refused (calibrate without k3, e.g.
`cv2.CALIB_FIX_K3`, or with `vio calibrate camera`). Neither layout has a camera-IMU time shift (0).
"""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Any

import numpy as np

from vio.errors import CalibrationError
from vio.records import CameraCalib, ImuCalib

log = logging.getLogger(__name__)

K3_TOLERANCE_PX = 0.5  # the largest displacement (px, at the image corners) of a k3 that may be dropped
_OPENCV_KEYS = re.compile(r"^(camera_matrix|Camera1?\.fx)\s*:", re.MULTILINE)
ORB_IMU_KEYS = ("IMU.NoiseGyro", "IMU.NoiseAcc", "IMU.GyroWalk", "IMU.AccWalk")


def is_opencv_calibration(text: str) -> bool:
    """Whether a file's text is an OpenCV FileStorage calibration (an `!!opencv-matrix` node, or the keys of
    OpenCV's calibration sample or of ORB-SLAM settings) rather than a Kalibr/ASL YAML."""
    return "!!opencv-matrix" in text or bool(_OPENCV_KEYS.search(text))


def _open(path: Path) -> Any:
    import cv2

    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:  # the Python binding wraps a parse error in a SystemError
        cause = exc.__cause__ or exc.__context__ or exc
        raise CalibrationError(f"{path}: not a readable OpenCV FileStorage file ({_parse_detail(cause)})") from None
    if not fs.isOpened():
        raise CalibrationError(f"{path}: cannot be opened as an OpenCV FileStorage file")
    return fs


def _parse_detail(exc: BaseException) -> str:
    """OpenCV's parse message without its source location: "line 3: Missing , between the elements"."""
    text = " ".join(str(exc).split())
    m = re.search(r"\((\d+)\): (.*?)'?$", text)
    return f"line {m.group(1)}: {m.group(2)}" if m else "parse error"


def _number(fs: Any, path: Path, key: str, required: bool = True) -> float | None:
    node = fs.getNode(key)
    if node.empty():
        if required:
            raise CalibrationError(f"{path}: missing '{key}'")
        return None
    if not (node.isReal() or node.isInt()):
        raise CalibrationError(f"{path}: '{key}' must be a number")
    value = float(node.real())
    if not np.isfinite(value):
        raise CalibrationError(f"{path}: '{key}' must be finite")
    return value


def _matrix(fs: Any, path: Path, key: str) -> np.ndarray | None:
    node = fs.getNode(key)
    if node.empty():
        return None
    m = node.mat()
    if m is None:
        raise CalibrationError(f"{path}: '{key}' must be an !!opencv-matrix (rows, cols, dt, data)")
    m = np.asarray(m, dtype=np.float64)
    if not np.isfinite(m).all():
        raise CalibrationError(f"{path}: '{key}' holds a value that is not finite")
    return m


def _radtan(path: Path, coeffs: np.ndarray, fx: float, fy: float, cx: float, cy: float, w: int, h: int, warn: list):
    """(k1, k2, p1, p2) from OpenCV's coefficient vector; a k3 dropped (with a warning) when negligible."""
    c = np.asarray(coeffs, float).ravel()
    if c.size < 4:
        raise CalibrationError(f"{path}: distortion needs at least k1, k2, p1, p2 ({c.size} values)")
    extra = c[4:]
    if extra.size > 1 and np.any(extra[1:] != 0):
        raise CalibrationError(
            f"{path}: the rational/thin-prism/tilted distortion model ({c.size} coefficients) is not supported; "
            "recalibrate with k1, k2, p1, p2 only (`vio calibrate camera`)"
        )
    k3 = float(extra[0]) if extra.size else 0.0
    if k3:
        if not (w and h):  # size unknown (ORB-SLAM2): the principal point taken as the centre
            w, h = int(round(2.0 * cx + 1.0)), int(round(2.0 * cy + 1.0))
        corners = np.array([[0.0, 0.0], [w - 1.0, 0.0], [0.0, h - 1.0], [w - 1.0, h - 1.0]])
        r = np.hypot((corners[:, 0] - cx) / fx, (corners[:, 1] - cy) / fy).max()
        shift_px = abs(k3) * r**7 * max(fx, fy)
        if shift_px > K3_TOLERANCE_PX:
            raise CalibrationError(
                f"{path}: k3 = {k3:.6g} moves the image corners by {shift_px:.1f} px; this project's camera has "
                "k1, k2, p1, p2 only: recalibrate without k3 (cv2.CALIB_FIX_K3, or `vio calibrate camera`)"
            )
        warn.append(f"{path}: k3 = {k3:.3g} dropped (at most {shift_px:.2f} px at the image corners)")
    return c[:4].copy()


def _body_T_cam(fs: Any, path: Path, warn: list) -> np.ndarray:
    for key in ("IMU.T_b_c1", "Tbc"):
        T = _matrix(fs, path, key)
        if T is None:
            continue
        if T.shape != (4, 4):
            raise CalibrationError(f"{path}: {key} must be a 4x4 matrix, got {T.shape[0]}x{T.shape[1]}")
        R = T[:3, :3]
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-3) or not np.allclose(T[3], [0, 0, 0, 1], atol=1e-9):
            raise CalibrationError(f"{path}: {key} is not a rigid transform")
        return T
    warn.append(
        f"{path}: no camera-IMU extrinsics (Tbc / IMU.T_b_c1): body_T_cam assumed to be the identity; "
        "calibrate it with `vio calibrate camera-imu`"
    )
    return np.eye(4)


def _imu(fs: Any, path: Path) -> ImuCalib | None:
    present = [k for k in ORB_IMU_KEYS if not fs.getNode(k).empty()]
    if not present:
        return None
    if len(present) < len(ORB_IMU_KEYS):
        missing = ", ".join(k for k in ORB_IMU_KEYS if k not in present)
        raise CalibrationError(f"{path}: IMU noise incomplete: missing {missing}")
    g, a, gw, aw = (_number(fs, path, k) for k in ORB_IMU_KEYS)
    rate = _number(fs, path, "IMU.Frequency", required=False) or 200.0
    if min(g, a, gw, aw, rate) <= 0:
        raise CalibrationError(f"{path}: IMU noise and frequency must be positive")
    return ImuCalib(g, a, gw, aw, rate)


def read_opencv_calibration(path: str | Path) -> tuple[CameraCalib, ImuCalib | None, tuple[str, ...]]:
    """The camera, the IMU noise (ORB-SLAM3 inertial settings; else None) and the warnings (what was assumed or
    dropped) of an OpenCV FileStorage calibration (module docstring for the layouts and conventions); a one-line
    CalibrationError for anything else. `vio.readers.calib.load_calibration` wraps them in a `Calibration`."""
    path = Path(path)
    fs = _open(path)
    try:
        warn: list[str] = []
        if not fs.getNode("camera_matrix").empty():
            K = _matrix(fs, path, "camera_matrix")
            if K is None or K.shape != (3, 3):
                raise CalibrationError(f"{path}: camera_matrix must be 3x3")
            fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
            w, h = int(_number(fs, path, "image_width")), int(_number(fs, path, "image_height"))
            dist = _matrix(fs, path, "distortion_coefficients")
            coeffs = np.zeros(4) if dist is None else dist
            rate = 30.0
            imu = None
        else:
            prefix = "Camera1." if not fs.getNode("Camera1.fx").empty() else "Camera."
            if fs.getNode(prefix + "fx").empty():
                raise CalibrationError(
                    f"{path}: an OpenCV FileStorage file without a camera (expected camera_matrix, or ORB-SLAM's "
                    "Camera.fx / Camera1.fx)"
                )
            ctype = fs.getNode("Camera.type")
            if not ctype.empty() and ctype.string().lower() not in ("pinhole", ""):
                raise CalibrationError(
                    f"{path}: Camera.type '{ctype.string()}' is not supported (PinHole with radtan only)"
                )
            fx, fy, cx, cy = (_number(fs, path, prefix + k) for k in ("fx", "fy", "cx", "cy"))
            w = int(_number(fs, path, "Camera.width", required=False) or 0)
            h = int(_number(fs, path, "Camera.height", required=False) or 0)
            if (w == 0) != (h == 0):
                raise CalibrationError(f"{path}: needs both Camera.width and Camera.height (the image size, px)")
            # ORB-SLAM2's settings carry no image size: 0 x 0 here, the capture's images give it (`finish_capture`)
            names = ("k1", "k2", "p1", "p2", "k3")
            coeffs = np.array([_number(fs, path, prefix + k, required=False) or 0.0 for k in names])
            rate = _number(fs, path, "Camera.fps", required=False) or 30.0
            imu = _imu(fs, path)
        if min(fx, fy) <= 0 or w < 0 or h < 0 or rate <= 0:
            raise CalibrationError(f"{path}: focal lengths, image size and frame rate must be positive")
        dist = _radtan(path, coeffs, fx, fy, cx, cy, w, h, warn)
        body_T_cam = _body_T_cam(fs, path, warn)
    finally:
        fs.release()
    camera = CameraCalib(w, h, fx, fy, cx, cy, dist, body_T_cam, float(rate))
    return camera, imu, tuple(warn)
