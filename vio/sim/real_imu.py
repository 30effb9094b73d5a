"""A semi-real capture: the simulator's vision along a recorded trajectory, with the recording's own IMU.

`vio simulate TRAJECTORY --real-imu IMU.csv` renders the images along the trajectory file's poses (the spline of
`vio.sim.trajectory.spline_trajectory`) and writes the real IMU samples that lie in the capture's span as its IMU
stream, in place of simulated ones. What this assumes, and what was checked on EuRoC V1_01:

- **Same clock.** The IMU timestamps and the trajectory's are on one clock (EuRoC: the VI sensor's; the
  ground truth `state_groundtruth_estimate0` was estimated with its time offset to the IMU removed).
- **Body = IMU frame.** The trajectory is the IMU's pose in a gravity-aligned world (z up, gravity -z). EuRoC's
  `state_groundtruth_estimate0/data.csv` is (its `sensor.yaml` has `T_BS` = identity; the accelerometer at rest
  minus the ground truth's accelerometer bias lies 0.2 deg from gravity rotated by the ground truth's attitude, and
  its magnitude is 9.808 m/s^2). EuRoC's `vicon0` / `vicon_groundtruth_200hz.txt` is the Vicon markers' pose, not
  the IMU's: do not use it as the scenario.
- **The recorded motion, not a smoothed one.** The images are rendered along the trajectory followed closely
  (`spline_trajectory(..., close=True)`: on EuRoC's 20 Hz ground truth, 0.1 s position knots and every pose's
  orientation), because the IMU measured the real motion: with the simulator's usual smoothing (0.2 s knots,
  orientation at 10 Hz) the real gyro differed from the rendered motion by 18x its declared noise density at 2-5 Hz
  (5.5x with the close fit) and the accelerometer by 14x (2x).
- **The IMU's noise** comes from `--imu-calib` (a Kalibr IMU YAML or an ASL `sensor.yaml`), else from the
  `sensor.yaml` beside the CSV (EuRoC's `imu0/sensor.yaml`); it is written into the capture's `imu0/sensor.yaml`.

The ground truth is written at the real IMU's times: pose, velocity from the spline, biases interpolated from the
trajectory file's bias columns when it has them (an ASL ground-truth CSV), zero otherwise (`scene/scene.yaml` says
which).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vio.errors import SimulationError, VioError
from vio.geometry import R_to_quat_wxyz
from vio.records import GroundTruth, ImuCalib, ImuSeries
from vio.sim.trajectory import Trajectory

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RealImu:
    """A real IMU recording: samples on the trajectory's clock and the noise calibration to write with them."""

    imu: ImuSeries  # gyro rad/s, specific force m/s^2, IMU (body) frame, t_ns on the trajectory's clock
    calib: ImuCalib  # noise densities and random walks (Kalibr names and units)
    source: Path  # the IMU CSV
    calib_source: Path  # the YAML the noise came from


def load_real_imu(path: str | Path, calib: str | Path | None = None) -> RealImu:
    """Read an EuRoC/ASL `imu0/data.csv` (t_ns, gyro rad/s, acc m/s^2) and its noise calibration: `calib` (Kalibr
    IMU YAML, camchain with `imu0:`, or ASL `sensor.yaml`) or the `sensor.yaml` beside the CSV.

    Errors (a missing file, a malformed row, no calibration) raise a one-line VioError."""
    from vio.kalibr import imu_from_section, read_yaml
    from vio.readers.asl import read_imu_csv

    path = Path(path)
    if not path.is_file():
        raise SimulationError(f"{path}: real IMU file not found (expected an EuRoC/ASL imu0/data.csv)")
    warnings: list[str] = []
    imu = read_imu_csv(path, warnings)
    for w in warnings:
        log.warning(w)
    cal_path = Path(calib) if calib is not None else path.parent / "sensor.yaml"
    if not cal_path.is_file():
        raise SimulationError(
            f"{path}: no IMU noise calibration ({cal_path} not found); pass --imu-calib with a Kalibr IMU YAML "
            "(e.g. from `vio calibrate imu`) or the recording's imu0/sensor.yaml"
        )
    data = read_yaml(cal_path)
    section = data.get("imu0", data)
    if not isinstance(section, dict):
        raise SimulationError(f"{cal_path}: not an IMU calibration (Kalibr noise keys)")
    imu_calib = imu_from_section(cal_path, section)
    return RealImu(imu, imu_calib, path, cal_path)


def imu_window(real: RealImu, t0_ns: int, duration_s: float) -> ImuSeries:
    """The real samples that span [t0_ns, t0_ns + duration] (with the last one at or before the start and the
    first one at or after the end, so every frame lies inside); a one-line error when the recording does not cover
    it (another clock, or a trajectory longer than the IMU log)."""
    t_end = int(t0_ns) + int(round(duration_s * 1e9))
    imu = real.imu
    first, last = int(imu.t_ns[0]), int(imu.t_ns[-1])
    if first > t0_ns or last < t_end:
        raise SimulationError(
            f"{real.source}: the IMU ({first * 1e-9:.3f}..{last * 1e-9:.3f} s) does not cover the capture "
            f"({t0_ns * 1e-9:.3f}..{t_end * 1e-9:.3f} s): the trajectory and the IMU must share a clock"
        )
    i0 = int(np.searchsorted(imu.t_ns, t0_ns, side="right")) - 1
    i1 = int(np.searchsorted(imu.t_ns, t_end, side="left")) + 1
    return ImuSeries(imu.t_ns[i0:i1].copy(), imu.gyro[i0:i1].copy(), imu.acc[i0:i1].copy())


def ground_truth_at(traj: Trajectory, t0_ns: int, t_ns: np.ndarray, biases: GroundTruth | None) -> GroundTruth:
    """Body states at the IMU times `t_ns` from the trajectory (time 0 at `t0_ns`); the biases interpolated from
    `biases` (a ground truth with bias columns, e.g. EuRoC's) or zero."""
    t_s = (np.asarray(t_ns, np.int64) - np.int64(t0_ns)).astype(np.float64) * 1e-9
    s = traj.sample(t_s)
    n = t_s.shape[0]
    b_w, b_a = np.zeros((n, 3)), np.zeros((n, 3))
    if biases is not None:
        tb = (biases.t_ns - np.int64(t0_ns)).astype(np.float64) * 1e-9
        b_w = np.column_stack([np.interp(t_s, tb, biases.b_w[:, k]) for k in range(3)])
        b_a = np.column_stack([np.interp(t_s, tb, biases.b_a[:, k]) for k in range(3)])
    return GroundTruth(
        np.asarray(t_ns, np.int64).copy(), s.p_world, R_to_quat_wxyz(s.world_R_body), s.v_world, b_w, b_a
    )


def trajectory_biases(path: str | Path) -> GroundTruth | None:
    """The bias columns of an ASL ground-truth CSV (17 columns), or None for a file without them (TUM)."""
    from vio.readers.asl import read_groundtruth_csv

    try:
        return read_groundtruth_csv(Path(path))
    except VioError:
        return None
