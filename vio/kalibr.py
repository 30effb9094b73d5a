"""Kalibr / EuRoC sensor YAML files (`sensor.yaml` for cam0 and imu0)."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from vio.errors import CalibrationError
from vio.records import CameraCalib, ImuCalib

_IMU_KEYS = (
    "gyroscope_noise_density",
    "accelerometer_noise_density",
    "gyroscope_random_walk",
    "accelerometer_random_walk",
)


def read_yaml(path: Path) -> dict[str, Any]:
    """Read a YAML file, tolerating OpenCV's `%YAML:1.0` directive that EuRoC files carry."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise CalibrationError(f"{path}: file not found") from None
    text = re.sub(r"^%YAML[: ]\d\.\d.*$", "", text, flags=re.MULTILINE)
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError:
        raise CalibrationError(f"{path}: not valid YAML") from None
    if not isinstance(data, dict):
        raise CalibrationError(f"{path}: expected a mapping of calibration keys")
    return data


def _matrix(path: Path, data: dict[str, Any], key: str) -> np.ndarray:
    value = data.get(key)
    if value is None:
        return np.eye(4)
    if isinstance(value, dict):
        value = value.get("data")
    arr = np.asarray(value, dtype=float)
    if arr.size != 16:
        raise CalibrationError(f"{path}: {key} must have 16 entries, got {arr.size}")
    T = arr.reshape(4, 4)
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-3) or not np.allclose(T[3], [0, 0, 0, 1]):
        raise CalibrationError(f"{path}: {key} is not a rigid transform")
    return T


def read_camera_yaml(path: Path) -> CameraCalib:
    data = read_yaml(path)
    try:
        fx, fy, cx, cy = (float(v) for v in data["intrinsics"])
        width, height = (int(v) for v in data["resolution"])
    except (KeyError, TypeError, ValueError):
        raise CalibrationError(f"{path}: needs 'intrinsics: [fu, fv, cu, cv]' and 'resolution: [w, h]'") from None
    model = str(data.get("distortion_model", "radtan")).lower()
    if model not in ("radtan", "radial-tangential", "none"):
        raise CalibrationError(f"{path}: distortion model '{model}' is not supported (radtan only)")
    dist = np.asarray(data.get("distortion_coefficients", [0, 0, 0, 0]), dtype=float)
    if dist.shape != (4,):
        raise CalibrationError(f"{path}: distortion_coefficients must be [k1, k2, p1, p2]")
    if min(fx, fy) <= 0 or width <= 0 or height <= 0:
        raise CalibrationError(f"{path}: focal lengths and resolution must be positive")
    return CameraCalib(
        width=width,
        height=height,
        fx=fx,
        fy=fy,
        cx=cx,
        cy=cy,
        dist=dist,
        body_T_cam=_matrix(path, data, "T_BS"),
        rate_hz=float(data.get("rate_hz", 20.0)),
    )


def read_imu_yaml(path: Path) -> ImuCalib:
    data = read_yaml(path)
    missing = [k for k in _IMU_KEYS if k not in data]
    if missing:
        raise CalibrationError(f"{path}: missing IMU noise key(s) {', '.join(missing)} (Kalibr names)")
    values = {k: float(data[k]) for k in _IMU_KEYS}
    if any(v <= 0 or not np.isfinite(v) for v in values.values()):
        raise CalibrationError(f"{path}: IMU noise parameters must be positive and finite")
    T = _matrix(path, data, "T_BS")
    if not np.allclose(T, np.eye(4), atol=1e-9):
        raise CalibrationError(f"{path}: the IMU defines the body frame; its T_BS must be the identity")
    return ImuCalib(**values, rate_hz=float(data.get("rate_hz", 200.0)))


def _fmt_matrix(T: np.ndarray) -> str:
    rows = [", ".join(f"{v:.12g}" for v in row) for row in np.asarray(T)]
    return "  cols: 4\n  rows: 4\n  data: [" + ",\n         ".join(rows) + "]\n"


def camera_yaml_text(cam: CameraCalib, comment: str = "vio camera") -> str:
    d = ", ".join(f"{v:.12g}" for v in cam.dist)
    return (
        "%YAML:1.0\n"
        "sensor_type: camera\n"
        f"comment: {comment}\n"
        "T_BS:\n" + _fmt_matrix(cam.body_T_cam) + f"rate_hz: {cam.rate_hz:g}\n"
        f"resolution: [{cam.width}, {cam.height}]\n"
        "camera_model: pinhole\n"
        f"intrinsics: [{cam.fx:.12g}, {cam.fy:.12g}, {cam.cx:.12g}, {cam.cy:.12g}] # fu, fv, cu, cv\n"
        "distortion_model: radial-tangential\n"
        f"distortion_coefficients: [{d}]\n"
    )


def imu_yaml_text(imu: ImuCalib, comment: str = "vio imu") -> str:
    return (
        "%YAML:1.0\n"
        "sensor_type: imu\n"
        f"comment: {comment}\n"
        "T_BS:\n" + _fmt_matrix(np.eye(4)) + f"rate_hz: {imu.rate_hz:g}\n"
        f"gyroscope_noise_density: {imu.gyroscope_noise_density:.6e}  # rad/s/sqrt(Hz)\n"
        f"gyroscope_random_walk: {imu.gyroscope_random_walk:.6e}  # rad/s^2/sqrt(Hz)\n"
        f"accelerometer_noise_density: {imu.accelerometer_noise_density:.6e}  # m/s^2/sqrt(Hz)\n"
        f"accelerometer_random_walk: {imu.accelerometer_random_walk:.6e}  # m/s^3/sqrt(Hz)\n"
    )
