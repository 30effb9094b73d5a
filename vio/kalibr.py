"""Kalibr YAML: the one reader (and writer) of camera and IMU calibration files.

Two layouts carry the same quantities in Kalibr's names and units:
- ASL/EuRoC `sensor.yaml`, one per sensor: camera `intrinsics: [fu, fv, cu, cv]` (px), `resolution: [w, h]`,
  `distortion_model: radtan`, `distortion_coefficients: [k1, k2, p1, p2]`, `T_BS` (the sensor's pose in the body
  frame, 4x4 or OpenCV's {rows, cols, data}), `rate_hz`; IMU noise keys (below) and `T_BS` = identity.
- Kalibr camchain: a `cam0:` section with `camera_model: pinhole`, `intrinsics`, `distortion_coeffs`,
  `resolution`, `T_cam_imu` (the IMU's pose in the camera frame: the inverse of body_T_cam) and optional
  `timeshift_cam_imu` (s, t_imu = t_cam + shift); IMU noise in an `imu0:` section or an IMU YAML (`update_rate`).
IMU noise keys: gyroscope_noise_density rad/s/sqrt(Hz), accelerometer_noise_density m/s^2/sqrt(Hz),
gyroscope_random_walk rad/s^2/sqrt(Hz), accelerometer_random_walk m/s^3/sqrt(Hz).
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from vio.errors import CalibrationError, VioError
from vio.geometry import inv_T
from vio.records import CameraCalib, ImuCalib

IMU_KEYS = (
    "gyroscope_noise_density",
    "accelerometer_noise_density",
    "gyroscope_random_walk",
    "accelerometer_random_walk",
)


def read_yaml(path: Path, error: type[VioError] = CalibrationError) -> dict[str, Any]:
    """Read a YAML mapping, tolerating OpenCV's `%YAML:1.0` directive that EuRoC files carry.

    Problems raise `error` (CalibrationError unless the caller reads another kind of file) naming the file.
    """
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise error(f"{path}: file not found") from None
    except UnicodeDecodeError:
        raise error(f"{path}: not a text file (cannot decode as UTF-8)") from None
    except OSError as exc:
        raise error(f"{path}: cannot be read ({exc.strerror or exc})") from None
    text = re.sub(r"^%YAML[: ]\d\.\d.*$", "", text, flags=re.MULTILINE)
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError:
        raise error(f"{path}: not valid YAML") from None
    if not isinstance(data, dict):
        raise error(f"{path}: expected a mapping of keys")
    return data


def _transform(path: Path, value: Any, key: str) -> np.ndarray:
    """A (4, 4) rigid transform from a nested list, a flat list of 16, or OpenCV's {rows, cols, data}."""
    if isinstance(value, dict):
        value = value.get("data")
    try:
        T = np.asarray(value, dtype=float).reshape(4, 4)
    except (TypeError, ValueError):
        raise CalibrationError(f"{path}: {key} must be a 4x4 matrix (16 numbers)") from None
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-3) or not np.allclose(T[3], [0, 0, 0, 1]):
        raise CalibrationError(f"{path}: {key} is not a rigid transform")
    return T


def _body_T_sensor(path: Path, sec: dict[str, Any]) -> np.ndarray:
    """ASL `T_BS`: the sensor's pose in the body (IMU) frame; the identity when absent."""
    value = sec.get("T_BS")
    return np.eye(4) if value is None else _transform(path, value, "T_BS")


def _camera(path: Path, sec: dict[str, Any], camchain: bool) -> CameraCalib:
    """A pinhole-radtan camera from an ASL camera `sensor.yaml` or (`camchain`) a camchain's `cam0:` section."""
    where, dist_key = ("cam0 ", "distortion_coeffs") if camchain else ("", "distortion_coefficients")
    try:
        fx, fy, cx, cy = (float(v) for v in sec["intrinsics"])
        width, height = (int(v) for v in sec["resolution"])
    except (KeyError, TypeError, ValueError):
        raise CalibrationError(
            f"{path}: {where}needs 'intrinsics: [fu, fv, cu, cv]' and 'resolution: [w, h]'"
        ) from None
    model = str(sec.get("camera_model", "pinhole")).lower()
    dmodel = str(sec.get("distortion_model", "radtan")).lower()
    if model != "pinhole" or dmodel not in ("radtan", "radial-tangential", "none"):
        raise CalibrationError(
            f"{path}: camera model '{model}-{dmodel}' is not supported (pinhole-radtan only; "
            "recalibrate with Kalibr's pinhole-radtan model)"
        )
    try:
        dist = np.asarray(sec.get(dist_key, [0.0, 0.0, 0.0, 0.0]), dtype=float)
    except (TypeError, ValueError):
        dist = np.zeros(0)
    if dist.shape != (4,):
        raise CalibrationError(f"{path}: {dist_key} must be [k1, k2, p1, p2]")
    if min(fx, fy) <= 0 or width <= 0 or height <= 0:
        raise CalibrationError(f"{path}: focal lengths and resolution must be positive")
    if not camchain:
        body_T_cam = _body_T_sensor(path, sec)
    elif "T_cam_imu" in sec:
        body_T_cam = inv_T(_transform(path, sec["T_cam_imu"], "T_cam_imu"))
    else:
        raise CalibrationError(f"{path}: cam0 lacks T_cam_imu (the camera-IMU extrinsics from Kalibr's imucam step)")
    try:
        rate_hz = float(sec.get("rate_hz", 30.0 if camchain else 20.0))
    except (TypeError, ValueError):
        raise CalibrationError(f"{path}: {where}rate_hz must be a number (frames per second)") from None
    if not (np.isfinite(rate_hz) and rate_hz > 0):
        raise CalibrationError(f"{path}: {where}rate_hz must be a positive number (frames per second)")
    return CameraCalib(width, height, fx, fy, cx, cy, dist, body_T_cam, rate_hz)


def imu_from_section(path: Path, sec: dict[str, Any]) -> ImuCalib:
    """IMU noise from a mapping with Kalibr's noise keys; the rate from `update_rate` (Kalibr) or `rate_hz` (ASL)."""
    missing = [k for k in IMU_KEYS if k not in sec]
    if missing:
        raise CalibrationError(f"{path}: missing IMU noise key(s) {', '.join(missing)} (Kalibr names)")
    try:
        values = {k: float(sec[k]) for k in IMU_KEYS}
        rate = float(sec.get("update_rate", sec.get("rate_hz", 200.0)))
    except (TypeError, ValueError):
        raise CalibrationError(f"{path}: IMU noise values must be numbers") from None
    if any(v <= 0 or not np.isfinite(v) for v in values.values()):
        raise CalibrationError(f"{path}: IMU noise parameters must be positive and finite")
    return ImuCalib(**values, rate_hz=rate)


def read_camera_yaml(path: Path) -> CameraCalib:
    """An ASL/EuRoC camera `sensor.yaml`."""
    return _camera(path, read_yaml(path), camchain=False)


def read_imu_yaml(path: Path) -> ImuCalib:
    """An ASL/EuRoC IMU `sensor.yaml`; the IMU defines the body frame, so its `T_BS` must be the identity."""
    data = read_yaml(path)
    imu = imu_from_section(path, data)
    if not np.allclose(_body_T_sensor(path, data), np.eye(4), atol=1e-9):
        raise CalibrationError(f"{path}: the IMU defines the body frame; its T_BS must be the identity")
    return imu


def camchain_camera(path: Path, cam: dict[str, Any]) -> tuple[CameraCalib, int]:
    """The camera of a camchain's `cam0:` section and its `timeshift_cam_imu` in ns (t_imu = t_cam + shift)."""
    camera = _camera(path, cam, camchain=True)
    return camera, int(round(float(cam.get("timeshift_cam_imu", 0.0)) * 1e9))


def _fmt_matrix(T: np.ndarray) -> str:
    rows = [", ".join(f"{v:.12g}" for v in row) for row in np.asarray(T)]
    return "  cols: 4\n  rows: 4\n  data: [" + ",\n         ".join(rows) + "]\n"


def camera_yaml_text(cam: CameraCalib, comment: str = "vio camera", distortion_model: str = "radial-tangential") -> str:
    """An ASL camera `sensor.yaml` (what `read_camera_yaml` reads back exactly; another `distortion_model`, e.g.
    equidistant, is written for other tools and refused by vio's reader)."""
    d = ", ".join(f"{v:.12g}" for v in cam.dist)
    return (
        "%YAML:1.0\n"
        "sensor_type: camera\n"
        f"comment: {json.dumps(comment)}\n"  # quoted: a comment may hold a colon
        "T_BS:\n" + _fmt_matrix(cam.body_T_cam) + f"rate_hz: {cam.rate_hz:g}\n"
        f"resolution: [{cam.width}, {cam.height}]\n"
        "camera_model: pinhole\n"
        f"intrinsics: [{cam.fx:.12g}, {cam.fy:.12g}, {cam.cx:.12g}, {cam.cy:.12g}] # fu, fv, cu, cv\n"
        f"distortion_model: {distortion_model}\n"
        f"distortion_coefficients: [{d}]\n"
    )


def imu_yaml_text(imu: ImuCalib, comment: str = "vio imu") -> str:
    """An ASL IMU `sensor.yaml` (noise written with 7 significant digits)."""
    return (
        "%YAML:1.0\n"
        "sensor_type: imu\n"
        f"comment: {json.dumps(comment)}\n"
        "T_BS:\n" + _fmt_matrix(np.eye(4)) + f"rate_hz: {imu.rate_hz:g}\n"
        f"gyroscope_noise_density: {imu.gyroscope_noise_density:.6e}  # rad/s/sqrt(Hz)\n"
        f"gyroscope_random_walk: {imu.gyroscope_random_walk:.6e}  # rad/s^2/sqrt(Hz)\n"
        f"accelerometer_noise_density: {imu.accelerometer_noise_density:.6e}  # m/s^2/sqrt(Hz)\n"
        f"accelerometer_random_walk: {imu.accelerometer_random_walk:.6e}  # m/s^3/sqrt(Hz)\n"
    )


def camchain_yaml_text(
    cam: CameraCalib,
    distortion_model: str = "radtan",
    comment: str = "vio camchain",
    timeshift_s: float | None = None,
) -> str:
    """A Kalibr camchain with one camera (`cam0:`): what `read_camchain` reads back (radtan; another
    `distortion_model`, e.g. equidistant, is written for Kalibr-compatible tools and refused by vio's reader).

    `cam.body_T_cam` is written as Kalibr's `T_cam_imu` (its inverse); `rate_hz` is vio's addition to the section.
    """
    d = ", ".join(f"{v:.12g}" for v in cam.dist)
    rows = "".join("  - [" + ", ".join(f"{v:.12g}" for v in row) + "]\n" for row in inv_T(cam.body_T_cam))
    text = (
        "".join(f"# {line}\n" for line in comment.splitlines()) + "cam0:\n"
        "  camera_model: pinhole\n"
        f"  intrinsics: [{cam.fx:.12g}, {cam.fy:.12g}, {cam.cx:.12g}, {cam.cy:.12g}]  # fu, fv, pu, pv (px)\n"
        f"  distortion_model: {distortion_model}\n"
        f"  distortion_coeffs: [{d}]\n"
        f"  resolution: [{cam.width}, {cam.height}]\n"
        f"  rate_hz: {cam.rate_hz:g}\n"
        "  T_cam_imu:  # the IMU's pose in the camera frame (body_T_cam inverted)\n" + rows
    )
    if timeshift_s is not None:
        text += f"  timeshift_cam_imu: {timeshift_s:.9g}  # s, t_imu = t_cam + shift\n"
    return text + "  cam_overlaps: []\n  rostopic: /cam0/image_raw\n"


def kalibr_imu_yaml_text(imu: ImuCalib, comment: str = "vio imu") -> str:
    """A Kalibr IMU YAML (`imu.yaml` beside a camchain; continuous-time noise densities and random walks)."""
    return (
        "".join(f"# {line}\n" for line in comment.splitlines())
        + f"accelerometer_noise_density: {imu.accelerometer_noise_density:.6e}  # m/s^2/sqrt(Hz)\n"
        f"accelerometer_random_walk: {imu.accelerometer_random_walk:.6e}  # m/s^3/sqrt(Hz)\n"
        f"gyroscope_noise_density: {imu.gyroscope_noise_density:.6e}  # rad/s/sqrt(Hz)\n"
        f"gyroscope_random_walk: {imu.gyroscope_random_walk:.6e}  # rad/s^2/sqrt(Hz)\n"
        "rostopic: /imu0\n"
        f"update_rate: {imu.rate_hz:g}  # Hz\n"
    )
