"""The capture record: what a recording holds once a reader in `vio.readers` has read it.

Every format (ASL/EuRoC, ROS bags, phone logs, gtsam's eqvio file) is read into this one record; open one with
`vio.readers.open_capture`, which detects the format and validates what was read. Times are sensor-clock integer
nanoseconds; the IMU stream and the calibration use `vio.records`' units and frames.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from vio.records import CameraCalib, FeatureTracks, Frame, GroundTruth, ImuCalib, ImuSeries

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Stills:
    """Full-resolution photos taken during the capture by the video's camera (ASL `mav0/cam1` with an image larger
    than cam0's), on the IMU clock. The estimator ignores them; the part model uses them."""

    camera: CameraCalib  # the stills' own intrinsics, distortion and body_T_cam
    t_ns: np.ndarray  # (S,) int64 still times, ns
    load_image: Callable[[int], np.ndarray]  # still index -> (H, W) uint8 grayscale

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])


@dataclass
class Capture:
    """A recording: calibration, IMU stream, frame times with an image loader, optional ground truth.

    Mutable on purpose: `vio.readers` applies a calibration, a camera-IMU time shift and the final checks (frames
    outside the IMU span dropped, warnings added) to the record a format reader returned.
    """

    root: Path  # the capture folder or file as given
    camera: CameraCalib | None  # cam0 intrinsics, radtan distortion and body_T_cam; None when not calibrated
    imu_calib: ImuCalib | None  # IMU noise (Kalibr names and units); None when the capture carries none
    imu: ImuSeries | None  # gyro rad/s and specific force m/s^2 in the body (IMU) frame, t_ns int64
    frame_t_ns: np.ndarray  # (F,) int64 frame times, ns, in the IMU's clock once a time shift is applied
    load_image: Callable[[int], np.ndarray]  # frame index -> (H, W) uint8 grayscale
    ground_truth: GroundTruth | None = None  # body states in the world frame, when the capture has them
    scene_dir: Path | None = None  # `scene/` of a synthetic capture (object.stl in metres, scene.yaml)
    warnings: list[str] = field(default_factory=list)  # one line each: problems where going on is safe
    format: str = "asl"  # one of `vio.readers.FORMATS`
    tracks: list[FeatureTracks] | None = None  # precomputed feature tracks (e.g. gtsam's eqvio file); no images
    stills: Stills | None = None  # full-resolution stills, when the capture has a stills stream
    # how `vio.readers.open_capture` opened it (path, calibration, options): another process opens the same capture
    # (`vio.track_worker`); None for a capture built in memory
    reopen: tuple[str, str | None, dict[str, Any]] | None = None

    @property
    def num_frames(self) -> int:
        return int(self.frame_t_ns.shape[0])

    def frames(self, start: int = 0, stop: int | None = None) -> Iterator[Frame]:
        """Frames `start..stop-1` (cam 0), images decoded on the way."""
        stop = self.num_frames if stop is None else min(stop, self.num_frames)
        for i in range(start, stop):
            yield Frame(int(self.frame_t_ns[i]), 0, self.load_image(i))

    def warn(self, message: str) -> None:
        """Record a warning and log it."""
        self.warnings.append(message)
        log.warning(message)
