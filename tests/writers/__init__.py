"""Test-only writers: take a (simulated or real) ASL capture and write it in each phone/robot log format.

They exist so the readers can be checked against a known answer; they are not part of the library.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import yaml

from vio.capture import Capture
from vio.geometry import inv_T
from vio.records import CameraCalib, ImuCalib


def calib_yaml_text(camera: CameraCalib, imu: ImuCalib | None, timeshift_cam_imu_s: float = 0.0) -> str:
    """A Kalibr camchain (cam0 with T_cam_imu) plus an imu0 section with the Kalibr noise keys."""
    data: dict = {
        "cam0": {
            "camera_model": "pinhole",
            "intrinsics": [float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy)],
            "distortion_model": "radtan",
            "distortion_coeffs": [float(v) for v in camera.dist],
            "resolution": [int(camera.width), int(camera.height)],
            "T_cam_imu": [[float(v) for v in row] for row in inv_T(camera.body_T_cam)],
            "timeshift_cam_imu": float(timeshift_cam_imu_s),
            "rate_hz": float(camera.rate_hz),
        }
    }
    if imu is not None:
        data["imu0"] = {
            "gyroscope_noise_density": imu.gyroscope_noise_density,
            "accelerometer_noise_density": imu.accelerometer_noise_density,
            "gyroscope_random_walk": imu.gyroscope_random_walk,
            "accelerometer_random_walk": imu.accelerometer_random_walk,
            "update_rate": imu.rate_hz,
        }
    return yaml.safe_dump(data, sort_keys=False)


def write_calib(folder: Path, cap: Capture, timeshift_cam_imu_s: float = 0.0) -> Path:
    assert cap.camera is not None
    path = Path(folder) / "calib.yaml"
    path.write_text(calib_yaml_text(cap.camera, cap.imu_calib, timeshift_cam_imu_s))
    return path


def write_video(path: Path, cap: Capture, fps: float | None = None, fourcc: str = "FFV1") -> int:
    """All frames of `cap` as a grayscale video (FFV1: lossless; "mp4v"/"MJPG": lossy); returns the count."""
    first = cap.load_image(0)
    h, w = first.shape[:2]
    rate = fps or (cap.camera.rate_hz if cap.camera else 20.0)
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), rate, (w, h), isColor=False)
    assert vw.isOpened(), f"cannot open a video writer for {path}"
    for i in range(cap.num_frames):
        vw.write(cap.load_image(i))
    vw.release()
    return cap.num_frames


def fmt_row(values: np.ndarray) -> str:
    return ",".join(repr(float(v)) for v in values)
