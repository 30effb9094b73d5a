"""The picture of a camera-IMU calibration, as PNG bytes (matplotlib's Agg canvas, no pyplot state):

- left: the correlation of the camera's and the gyro's angular speeds against the time offset tried, with the
  cross-correlation's peak and the final (refined) offset marked;
- right: both angular speeds over the capture once the final offset and gyro bias are applied (they should lie on
  top of each other; where they do not, the board's poses or the IMU are wrong there).
"""

from __future__ import annotations

import numpy as np

from vio.calibrate.camera_imu import CameraImuCalibration
from vio.calibrate.figures import _png
from vio.calibrate.gyro import GyroIntegral
from vio.records import ImuSeries


def alignment_png(res: CameraImuCalibration, imu: ImuSeries, read_shift_ns: int = 0) -> bytes:
    """The picture of the module docstring; `read_shift_ns` is the shift the capture's frames were read with."""
    from matplotlib.figure import Figure

    ra = res.rotation_step
    fig = Figure(figsize=(11.0, 4.0), layout="constrained")
    ax = fig.add_subplot(1, 2, 1)
    ax.plot((ra.xcorr_offsets_ns + read_shift_ns) * 1e-6, ra.xcorr, color="0.3", lw=1.0)
    ax.axvline((ra.offset_xcorr_ns + read_shift_ns) * 1e-6, color="tab:blue", lw=1.0, label="peak")
    ax.axvline(res.timeshift_ns * 1e-6, color="tab:red", lw=1.0, ls="--", label="refined")
    ax.set_xlabel("timeshift_cam_imu tried (ms)")
    ax.set_ylabel("correlation of angular speeds")
    ax.legend(loc="lower right", fontsize=8)
    steps = ra.steps
    dt = (steps.t1_ns - steps.t0_ns) * 1e-9
    cam = np.rad2deg(np.linalg.norm(steps.rotvec, axis=1) / dt)
    shift = res.timeshift_ns - read_shift_ns
    t0 = int(steps.t0_ns[0])
    t_cam = 0.5 * ((steps.t0_ns - t0) + (steps.t1_ns - t0)) * 1e-9  # the middle of each step, camera clock
    gyro = GyroIntegral(imu, ra.gyro_bias_rad_s)
    t_gyro = ((imu.t_ns - t0) - shift) * 1e-9  # the IMU's samples on the camera clock
    shown = (t_gyro >= t_cam[0]) & (t_gyro <= t_cam[-1])
    ax = fig.add_subplot(1, 2, 2)
    ax.plot(t_gyro[shown], np.rad2deg(gyro.speed[shown]), color="tab:red", lw=0.8, label="gyro")
    ax.plot(t_cam, cam, ".", color="tab:blue", ms=2.5, label=f"camera ({res.method})")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("angular speed (deg/s)")
    ax.legend(loc="upper right", fontsize=8)
    return _png(fig)
