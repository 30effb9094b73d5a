"""The simulated phone: camera intrinsics, radtan distortion, and the camera-IMU extrinsic `body_T_cam`."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from vio.records import CameraCalib

WIDTH_PX, HEIGHT_PX = 640, 480
FX_PX, FY_PX = 505.0, 503.5
CX_PX, CY_PX = 319.3, 241.6  # deliberately not the image centre
DIST_RADTAN = np.array([-0.045, 0.018, 3.0e-4, -2.0e-4])  # k1, k2, p1, p2: a mild phone lens
CAMERA_RATE_HZ = 20.0
IMU_RATE_HZ = 200.0
T0_NS = 1_700_000_000_000_000_000  # an epoch-sized start time (2023-11-14), so float-precision bugs show


def body_T_cam() -> np.ndarray:
    """(4, 4) camera pose in the IMU body frame: a rear camera of a phone held in landscape.

    Phone/IMU axes (Android): x right, y up, z out of the screen; the rear camera looks along -z with image x along
    body -y and image y along body -x, plus a 0.6-1.2 deg mounting misalignment and a lever arm of a few cm.
    """
    body_R_cam_nominal = np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    tilt = Rotation.from_euler("xyz", [0.8, -0.6, 1.2], degrees=True).as_matrix()
    T = np.eye(4)
    T[:3, :3] = tilt @ body_R_cam_nominal
    T[:3, 3] = [0.031, -0.012, -0.004]
    return T


def default_camera(rate_hz: float = CAMERA_RATE_HZ) -> CameraCalib:
    return CameraCalib(
        width=WIDTH_PX,
        height=HEIGHT_PX,
        fx=FX_PX,
        fy=FY_PX,
        cx=CX_PX,
        cy=CY_PX,
        dist=DIST_RADTAN.copy(),
        body_T_cam=body_T_cam(),
        rate_hz=rate_hz,
    )


STILLS_SIZE = (2016, 1512)  # default full-resolution still, px (a 12 MP phone sensor binned 2x2)
STILLS_OFFSET_NS = 13_000_000  # the first still 13 ms after t0: stills are not synchronised with the video


def stills_camera(width: int, height: int, rate_hz: float) -> CameraCalib:
    """The same camera taking full-resolution stills: the video's lens (same normalized distortion and body_T_cam),
    the sensor read at `width` x `height`. The focal length scales with the width; a sensor of another aspect
    ratio than the video's 4:3 is centre-cropped vertically."""
    s = width / WIDTH_PX
    crop_px = (HEIGHT_PX * s - height) / 2.0
    return CameraCalib(
        width=int(width),
        height=int(height),
        fx=FX_PX * s,
        fy=FY_PX * s,
        cx=(CX_PX + 0.5) * s - 0.5,
        cy=(CY_PX + 0.5) * s - 0.5 - crop_px,
        dist=DIST_RADTAN.copy(),
        body_T_cam=body_T_cam(),
        rate_hz=rate_hz,
    )
