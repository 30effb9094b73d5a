"""Calibration for captures that do not carry their own: where it is found, and presets when there is none.

Accepted `--calib` values (and files found beside a capture, see `find_calibration`), read by `vio.kalibr` or, for
OpenCV FileStorage files, by `vio.readers.opencv_calib`:
- a Kalibr camchain (`cam0:` with `intrinsics`, `distortion_coeffs` radtan, `resolution`, `T_cam_imu`, optional
  `timeshift_cam_imu` [s], defined by Kalibr as t_imu = t_cam + shift); the same file may carry an `imu0:` section
  with the Kalibr noise keys, otherwise a Kalibr IMU YAML beside it (`imu.yaml`, `*imu*.yaml`) is used;
- an ASL/EuRoC folder (or its `mav0/`) with `cam0/sensor.yaml` and `imu0/sensor.yaml`;
- an ASL `sensor.yaml` of the camera itself;
- a file written by OpenCV's `FileStorage` (`%YAML:1.0`, `!!opencv-matrix`): OpenCV's calibration sample output
  (`camera_matrix`, `distortion_coefficients`) or an ORB-SLAM2/ORB-SLAM3 settings file (`Camera.fx ...`, `Tbc` /
  `IMU.T_b_c1` as body_T_cam, `IMU.Noise*`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from vio.errors import CalibrationError
from vio.kalibr import IMU_KEYS, camchain_camera, imu_from_section, read_camera_yaml, read_imu_yaml, read_yaml
from vio.records import CameraCalib, ImuCalib

log = logging.getLogger(__name__)

CALIB_NAMES = ("calib.yaml", "camchain-imucam.yaml", "camchain-imu.yaml", "camchain.yaml")  # first found wins:
# `vio calibrate camera-imu` writes camchain-imu.yaml beside the camera-only camchain.yaml, and it is the complete one
# IMU noise presets (Kalibr order and units: gyroscope_noise_density rad/s/sqrt(Hz), accelerometer_noise_density
# m/s^2/sqrt(Hz), gyroscope_random_walk rad/s^2/sqrt(Hz), accelerometer_random_walk m/s^3/sqrt(Hz), rate Hz).
# PHONE_IMU_DEFAULT is assumed when a capture has no IMU noise calibration: a typical phone MEMS IMU with a safety
# margin (an assumption, stated in the warning and in docs/capture_formats.md). EUROC_IMU is EuRoC's ADIS16448 as
# published in the dataset's mav0/imu0/sensor.yaml (for gtsam's eqvio file, which carries no noise).
PHONE_IMU_DEFAULT = ImuCalib(1.0e-3, 1.0e-2, 1.0e-4, 1.0e-3, 200.0)
EUROC_IMU = ImuCalib(1.6968e-4, 2.0e-3, 1.9393e-5, 3.0e-3, 200.0)


@dataclass(frozen=True)
class Calibration:
    """What a calibration file gives a capture: the camera, the IMU noise (if any) and the camera-IMU time shift."""

    camera: CameraCalib | None
    imu: ImuCalib | None
    timeshift_cam_imu_ns: int = 0  # Kalibr: t_imu = t_cam + shift; added to frame times, ns
    source: Path | None = None
    warnings: tuple[str, ...] = ()  # what was assumed or dropped while reading it; carried into Capture.warnings


def imu_yaml_beside(path: Path) -> ImuCalib | None:
    """IMU noise from a Kalibr IMU YAML beside a camchain (`imu.yaml`, `*imu*.yaml`), if there is one."""
    for cand in sorted(path.parent.glob("*.yaml")):
        if cand == path or "imu" not in cand.name.lower() or "camchain" in cand.name.lower():
            continue
        data = read_yaml(cand)
        section = data.get("imu0", data)
        if isinstance(section, dict) and all(k in section for k in IMU_KEYS):
            return imu_from_section(cand, section)
    return None


def read_camchain(path: Path) -> Calibration:
    """Read a Kalibr camchain YAML (cam0 only; other cameras are ignored) and its IMU noise, if any."""
    path = Path(path)
    data = read_yaml(path)
    cam = data.get("cam0")
    if not isinstance(cam, dict):
        raise CalibrationError(f"{path}: not a Kalibr camchain (no 'cam0:' section)")
    camera, shift_ns = camchain_camera(path, cam)
    imu_section = data.get("imu0")
    imu = imu_from_section(path, imu_section) if isinstance(imu_section, dict) else imu_yaml_beside(path)
    return Calibration(camera, imu, shift_ns, path)


def read_asl_calibration(folder: Path) -> Calibration:
    """The calibration of an ASL/EuRoC folder (or its `mav0/`): cam0 and, when present, imu0 `sensor.yaml`."""
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
                return read_calibration_file(path / name)
        return read_asl_calibration(path)
    if _is_opencv_file(path):
        return _read_opencv(path)
    data = read_yaml(path)
    if "cam0" in data:
        return read_camchain(path)
    if "intrinsics" in data:
        return Calibration(read_camera_yaml(path), None, 0, path)
    raise CalibrationError(
        f"{path}: neither a Kalibr camchain (cam0:), an ASL camera sensor.yaml (intrinsics:), nor an OpenCV/ORB-SLAM "
        "calibration (camera_matrix: / Camera.fx:)"
    )


def _is_opencv_file(path: Path) -> bool:
    """Whether a calibration file was written by OpenCV's FileStorage (`vio.readers.opencv_calib`)."""
    from vio.readers.opencv_calib import is_opencv_calibration

    try:
        text = Path(path).read_text(encoding="utf-8", errors="replace")
    except OSError:
        return False  # read_yaml names the problem
    return is_opencv_calibration(text)


def read_calibration_file(path: Path) -> Calibration:
    """A calibration file stored beside a capture: a Kalibr camchain or an OpenCV/ORB-SLAM FileStorage file."""
    if _is_opencv_file(path):
        return _read_opencv(path)
    return read_camchain(path)


def _read_opencv(path: Path) -> Calibration:
    from vio.readers.opencv_calib import read_opencv_calibration

    camera, imu, warnings = read_opencv_calibration(path)
    return Calibration(camera, imu, 0, Path(path), warnings)


def find_calibration(folder: Path) -> Calibration | None:
    """A calibration stored with a capture: the first of `CALIB_NAMES` in `folder`, else `*camchain*.yaml`."""
    folder = Path(folder)
    for name in CALIB_NAMES:
        if (folder / name).is_file():
            return read_calibration_file(folder / name)
    found = sorted(folder.glob("*camchain*.yaml"))
    return read_camchain(found[0]) if found else None


def missing_calibration_message(capture: Path) -> str:
    """The one-line error for a capture without camera calibration."""
    return (
        f"{capture}: no camera calibration: pass --calib with a Kalibr camchain YAML, an ASL mav0 folder or an "
        "OpenCV/ORB-SLAM calibration YAML, or put calib.yaml beside the capture (see docs/capture_formats.md)"
    )
