"""A camera calibration from what a phone logger recorded, for a capture that comes without one.

MARS logger's `movie_metadata.csv` lists the focal lengths `fx[px], fy[px]` of every frame (Android: from
Camera2's lens intrinsics; iOS: from AVFoundation's intrinsic matrix). When neither `--calib` nor a calibration file
beside the capture is given, `logged_calibration` builds an approximate camera from them:

- focal lengths: the median of the per-frame `fx`, `fy` (px, taken as pixels of the recorded video frames);
- principal point: the image centre, ((W - 1) / 2, (H - 1) / 2) px (OpenCV's pixel-centre convention);
- distortion: zero (radtan [0, 0, 0, 0]);
- `body_T_cam`: the nominal rear camera of a phone whose IMU has Android's/iOS's device axes (x right, y up, z out of
  the screen) and whose sensor is read in landscape (Android `SENSOR_ORIENTATION` 90, the usual rear camera): the
  camera looks along body -z, image x along body -y, image y along body -x; no lever arm;
- the frame rate from the frame times;
- the IMU noise from a Kalibr IMU YAML in the folder (`imu.yaml`, `*imu*.yaml`) when there is one.

It is an approximation (a real lens has distortion and an off-centre principal point; the logged focal length is
the lens maker's nominal value), so the capture carries a warning that says so and how to calibrate
(`vio calibrate camera`, `vio calibrate camera-imu`, then `--calib`).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from vio.readers.calib import Calibration, imu_yaml_beside
from vio.readers.tables import read_lines, read_table
from vio.records import CameraCalib

log = logging.getLogger(__name__)

FX_COLUMN, FY_COLUMN = "fx[px]", "fy[px]"
# The nominal rear camera in a phone's IMU axes (see the module docstring): columns are the camera axes in the body.
BODY_R_CAM_NOMINAL = np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
PLAUSIBLE_HFOV_DEG = (20.0, 130.0)  # a phone camera's horizontal field of view; outside: the fx is suspect


def _column(header: list[str], name: str) -> int | None:
    names = [h.strip().lower() for h in header]
    return names.index(name) if name in names else None


def logged_focal_lengths(folder: Path) -> tuple[float, float, int] | None:
    """Median (fx, fy) px and the number of frames that gave them, from `movie_metadata.csv`; None when the file
    or its `fx[px]`/`fy[px]` columns are absent or hold no positive finite value."""
    path = Path(folder) / "movie_metadata.csv"
    if not path.is_file():
        return None
    lines, _ = read_lines(path)
    header = lines[0].split(",") if lines else []
    ix, iy = _column(header, FX_COLUMN), _column(header, FY_COLUMN)
    if ix is None or iy is None:
        return None
    scale = 1_000_000_000 if "[sec]" in header[0].lower() or "[s]" in header[0].lower() else 1
    table = read_table(path, 0, [ix, iy], time_scale=scale, what="frame metadata")
    v = table.values
    ok = np.isfinite(v).all(axis=1) & (v > 0).all(axis=1)
    if not ok.any():
        return None
    return float(np.median(v[ok, 0])), float(np.median(v[ok, 1])), int(ok.sum())


def logged_calibration(
    folder: Path, width: int, height: int, frame_t_ns: np.ndarray, warnings: list[str]
) -> Calibration | None:
    """The approximate calibration of a MARS folder from its logged focal lengths (module docstring), for frames of
    `width` x `height` px; the warning that says what was assumed is appended to `warnings`. None when nothing
    was logged."""
    found = logged_focal_lengths(folder)
    if found is None or width <= 0 or height <= 0:
        return None
    fx, fy, n = found
    dt = np.diff(np.asarray(frame_t_ns, np.int64))
    rate_hz = float(1e9 / np.median(dt)) if dt.size and np.median(dt) > 0 else 30.0
    body_T_cam = np.eye(4)
    body_T_cam[:3, :3] = BODY_R_CAM_NOMINAL
    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    camera = CameraCalib(int(width), int(height), fx, fy, cx, cy, np.zeros(4), body_T_cam, rate_hz)
    warnings.append(
        f"{folder / 'movie_metadata.csv'}: no calibration given: using the logger's intrinsics (median fx {fx:.2f}, "
        f"fy {fy:.2f} px over {n} frames), the principal point at the image centre ({cx:.1f}, {cy:.1f}), zero "
        "distortion and the nominal rear-camera rotation without lever arm: an approximation (expect a less "
        "accurate scale and trajectory); calibrate with `vio calibrate camera` and `vio calibrate camera-imu`, "
        "then pass --calib"
    )
    hfov = float(np.degrees(2.0 * np.arctan(width / (2.0 * fx))))
    if not PLAUSIBLE_HFOV_DEG[0] <= hfov <= PLAUSIBLE_HFOV_DEG[1]:
        warnings.append(
            f"{folder / 'movie_metadata.csv'}: the logged fx {fx:.1f} px gives a {hfov:.0f} deg field of view for "
            f"{width} px wide frames (a phone camera has {PLAUSIBLE_HFOV_DEG[0]:g}-{PLAUSIBLE_HFOV_DEG[1]:g}): it may "
            "be in another image size's pixels; calibrate the camera"
        )
    imu = imu_yaml_beside(folder / "movie_metadata.csv")  # an IMU noise YAML in the folder (e.g. imu.yaml), if any
    return Calibration(camera, imu, 0, folder / "movie_metadata.csv")
