"""The `Scenario` record: everything that defines a simulated capture except the measurement noise draws.

It sits at the bottom of the simulator: `vio.sim.api.load_scenario` builds it, and the renderer and the capture
writer read it. Times are integer ns (`t0_ns`) plus float seconds since t0 for the trajectory; poses are body
(IMU) in world, world z up.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vio.records import CameraCalib, ImuCalib
from vio.sim.imu import ImuErrors
from vio.sim.phases import PhasedMotion
from vio.sim.phone import PhoneCamera, frame_times
from vio.sim.scene import Scene
from vio.sim.trajectory import Trajectory


@dataclass(frozen=True)
class Scenario:
    """Everything that defines a simulated capture except the measurement noise draws."""

    name: str  # "orbit", "figure8", "room", or the trajectory file path
    seed: int
    trajectory: Trajectory  # body (IMU) motion; `.sample(t_s)` with t_s in s since t0_ns
    scene: Scene
    camera: CameraCalib
    imu_calib: ImuCalib
    imu_grade: str
    t0_ns: int  # time of t_s = 0, ns
    duration_s: float
    camera_rate_hz: float
    imu_rate_hz: float
    stills_camera: CameraCalib | None = None  # full-resolution stills (`mav0/cam1`), None: no stills stream
    stills_offset_ns: int = 0  # time of the first still after t0_ns, ns
    phone: PhoneCamera | None = None  # rolling shutter, blur, exposure, clock offset (None: the default camera)
    imu_errors: ImuErrors | None = None  # scale factors, misalignment, timestamp jitter (None: none)
    real_imu: dict | None = None  # a real IMU recording written instead of a simulated one (`vio.sim.real_imu`)
    phases: PhasedMotion | None = None  # still start, excitation, still end around the motion (None: none)
    motion_s: float | None = None  # the scenario's own motion, s (duration_s less the phases; None: all of it)

    def frame_times_ns(self) -> np.ndarray:
        """(F,) camera frame times, ns: t0 + k / rate for k / rate < duration (they coincide with IMU samples).
        With a phone camera: the stamps on the camera clock (`phone_frame_times`)."""
        if self.phone is not None:
            return self.phone_frame_times()[0]
        n = int(np.floor(self.duration_s * self.camera_rate_hz + 1e-9))
        return np.int64(self.t0_ns) + np.round(np.arange(n) * (1e9 / self.camera_rate_hz)).astype(np.int64)

    def phone_frame_times(self) -> tuple[np.ndarray, np.ndarray]:
        """(stamps on the camera clock, true top-row mid-exposure times on the IMU clock), ns (`vio.sim.phone`)."""
        if self.phone is None:
            t = self.frame_times_ns()
            return t, t
        return frame_times(self.t0_ns, self.duration_s, self.camera_rate_hz, self.phone)

    def stills_times_ns(self) -> np.ndarray:
        """(S,) times of the stills, ns: t0 + offset + k / rate within the duration (empty without stills)."""
        if self.stills_camera is None:
            return np.zeros(0, np.int64)
        period_ns = 1e9 / self.stills_camera.rate_hz
        n = int(np.floor((self.duration_s * 1e9 - self.stills_offset_ns) / period_ns + 1e-9)) + 1
        t = np.int64(self.t0_ns + self.stills_offset_ns) + np.round(np.arange(n) * period_ns).astype(np.int64)
        return t[t < self.t0_ns + int(round(self.duration_s * 1e9))]
