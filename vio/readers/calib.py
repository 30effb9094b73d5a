"""Calibration for captures that do not carry their own: Kalibr camchain YAML, Kalibr IMU YAML, or an ASL folder.

Accepted `--calib` values (and files found beside a capture, see `find_calibration`):
- a Kalibr camchain (`cam0:` with `intrinsics`, `distortion_coeffs` radtan, `resolution`, `T_cam_imu`, optional
  `timeshift_cam_imu` [s], defined by Kalibr as t_imu = t_cam + shift); the same file may carry an `imu0:` section
  with the Kalibr noise keys, otherwise a Kalibr IMU YAML beside it (`imu.yaml`, `*imu*.yaml`) is used;
- an ASL/EuRoC folder (or its `mav0/`) with `cam0/sensor.yaml` and `imu0/sensor.yaml`;
- an ASL `sensor.yaml` of the camera itself.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from vio.errors import CalibrationError
from vio.geometry import inv_T
from vio.kalibr import read_camera_yaml, read_imu_yaml, read_yaml
from vio.records import CameraCalib, ImuCalib

log = logging.getLogger(__name__)

CALIB_NAMES = ("calib.yaml", "camchain.yaml", "camchain-imucam.yaml")
_IMU_KEYS = (
    "gyroscope_noise_density",
    "accelerometer_noise_density",
    "gyroscope_random_walk",
    "accelerometer_random_walk",
)
# Used when a capture has no IMU noise calibration: a typical phone MEMS IMU with a safety margin (assumption, stated
# in the warning and in docs/capture_formats.md).
PHONE_IMU_DEFAULT = ImuCalib(
    gyroscope_noise_density=1.0e-3,
    accelerometer_noise_density=1.0e-2,
    gyroscope_random_walk=1.0e-4,
    accelerometer_random_walk=1.0e-3,
    rate_hz=200.0,
)


@dataclass(frozen=True)
class Calibration:
    camera: CameraCalib | None
    imu: ImuCalib | None
    timeshift_cam_imu_ns: int = 0  # Kalibr: t_imu = t_cam + shift; added to frame times
    source: Path | None = None


def _rigid(path: Path, value: Any, key: str) -> np.ndarray:
    try:
        T = np.asarray(value, dtype=float).reshape(4, 4)
    except (TypeError, ValueError):
        raise CalibrationError(f"{path}: {key} must be a 4x4 matrix") from None
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-3) or not np.allclose(T[3], [0, 0, 0, 1]):
        raise CalibrationError(f"{path}: {key} is not a rigid transform")
    return T


def _camchain_camera(path: Path, cam: dict[str, Any]) -> tuple[CameraCalib, int]:
    try:
        fx, fy, cx, cy = (float(v) for v in cam["intrinsics"])
        width, height = (int(v) for v in cam["resolution"])
    except (KeyError, TypeError, ValueError):
        raise CalibrationError(f"{path}: cam0 needs 'intrinsics: [fu, fv, pu, pv]' and 'resolution: [w, h]'") from None
    model = str(cam.get("camera_model", "pinhole")).lower()
    dmodel = str(cam.get("distortion_model", "radtan")).lower()
    if model != "pinhole" or dmodel not in ("radtan", "radial-tangential", "none"):
        raise CalibrationError(
            f"{path}: camera model '{model}-{dmodel}' is not supported (pinhole-radtan only; "
            "recalibrate with Kalibr's pinhole-radtan model)"
        )
    dist = np.asarray(cam.get("distortion_coeffs", [0.0, 0.0, 0.0, 0.0]), dtype=float)
    if dist.shape != (4,):
        raise CalibrationError(f"{path}: distortion_coeffs must be [k1, k2, p1, p2]")
    if "T_cam_imu" in cam:
        body_T_cam = inv_T(_rigid(path, cam["T_cam_imu"], "T_cam_imu"))
    else:
        raise CalibrationError(f"{path}: cam0 lacks T_cam_imu (the camera-IMU extrinsics from Kalibr's imucam step)")
    shift_ns = int(round(float(cam.get("timeshift_cam_imu", 0.0)) * 1e9))
    camera = CameraCalib(width, height, fx, fy, cx, cy, dist, body_T_cam, float(cam.get("rate_hz", 30.0)))
    return camera, shift_ns


def _imu_from_dict(path: Path, data: dict[str, Any]) -> ImuCalib:
    missing = [k for k in _IMU_KEYS if k not in data]
    if missing:
        raise CalibrationError(f"{path}: missing IMU noise key(s) {', '.join(missing)} (Kalibr names)")
    try:
        values = {k: float(data[k]) for k in _IMU_KEYS}
        rate = float(data.get("update_rate", data.get("rate_hz", 200.0)))
    except (TypeError, ValueError):
        raise CalibrationError(f"{path}: IMU noise values must be numbers") from None
    if any(v <= 0 or not np.isfinite(v) for v in values.values()):
        raise CalibrationError(f"{path}: IMU noise parameters must be positive and finite")
    return ImuCalib(**values, rate_hz=rate)


def _sibling_imu_yaml(path: Path) -> ImuCalib | None:
    for cand in sorted(path.parent.glob("*.yaml")):
        if cand == path or "imu" not in cand.name.lower() or "camchain" in cand.name.lower():
            continue
        data = read_yaml(cand)
        section = data.get("imu0", data)
        if isinstance(section, dict) and all(k in section for k in _IMU_KEYS):
            return _imu_from_dict(cand, section)
    return None


def read_camchain(path: Path) -> Calibration:
    """Read a Kalibr camchain YAML (cam0 only; other cameras are ignored) and its IMU noise, if any."""
    path = Path(path)
    data = read_yaml(path)
    cam = data.get("cam0")
    if not isinstance(cam, dict):
        raise CalibrationError(f"{path}: not a Kalibr camchain (no 'cam0:' section)")
    camera, shift_ns = _camchain_camera(path, cam)
    imu_section = data.get("imu0")
    imu = _imu_from_dict(path, imu_section) if isinstance(imu_section, dict) else _sibling_imu_yaml(path)
    return Calibration(camera, imu, shift_ns, path)


def read_asl_calibration(folder: Path) -> Calibration:
    folder = Path(folder)
    mav0 = folder / "mav0" if (folder / "mav0").is_dir() else folder
    cam_yaml, imu_yaml = mav0 / "cam0" / "sensor.yaml", mav0 / "imu0" / "sensor.yaml"
    if not cam_yaml.exists():
        raise CalibrationError(f"{folder}: no cam0/sensor.yaml (expected an ASL folder with the calibration)")
    imu = read_imu_yaml(imu_yaml) if imu_yaml.exists() else None
    return Calibration(read_camera_yaml(cam_yaml), imu, 0, folder)


def load_calibration(path: str | Path) -> Calibration:
    """Read the calibration named by `--calib`: a camchain YAML, an ASL folder, or an ASL camera sensor.yaml."""
    path = Path(path)
    if not path.exists():
        raise CalibrationError(f"{path}: calibration not found")
    if path.is_dir():
        for name in CALIB_NAMES:
            if (path / name).is_file():
                return read_camchain(path / name)
        return read_asl_calibration(path)
    data = read_yaml(path)
    if "cam0" in data:
        return read_camchain(path)
    if "intrinsics" in data:
        return Calibration(read_camera_yaml(path), None, 0, path)
    raise CalibrationError(f"{path}: neither a Kalibr camchain (cam0:) nor an ASL camera sensor.yaml (intrinsics:)")


def find_calibration(folder: Path) -> Calibration | None:
    """A calibration stored with a capture: `calib.yaml`, `camchain.yaml` or `*camchain*.yaml` in `folder`."""
    folder = Path(folder)
    for name in CALIB_NAMES:
        if (folder / name).is_file():
            return read_camchain(folder / name)
    found = sorted(folder.glob("*camchain*.yaml"))
    return read_camchain(found[0]) if found else None


def missing_calibration_message(capture: Path) -> str:
    return (
        f"{capture}: no camera calibration: pass --calib with a Kalibr camchain YAML or an ASL mav0 folder, "
        "or put calib.yaml beside the capture (see docs/capture_formats.md)"
    )
