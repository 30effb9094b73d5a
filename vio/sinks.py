"""What the pipeline tells its sinks (file writers, the rerun viewer). The estimator never draws."""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np

from vio.records import CameraCalib, Frame, GroundTruth, ImuSeries, StateEstimate


class EstimateSink(Protocol):
    """Subscribers receive records in sensor-time order, one keyframe at a time."""

    def on_start(self, camera: CameraCalib | None, imu: ImuSeries | None, ground_truth: GroundTruth | None) -> None:
        """Once, before the first frame: static calibration, the whole IMU stream, ground truth if any."""

    def on_frame(self, frame: Frame, ids: np.ndarray, uv: np.ndarray, ages: np.ndarray) -> None:
        """Every tracked frame: the image, track ids, distorted pixels (N, 2) and track ages in frames (N,)."""

    def on_estimate(self, estimate: StateEstimate, stats: dict[str, Any]) -> None:
        """Every keyframe estimate; stats holds e.g. `solve_ms`, `reproj_px_median`, `num_landmarks`."""

    # Optional: `on_health(health: vio.health.RunHealth)`, once after the last keyframe, before `close`.

    def close(self) -> None:
        """After the last keyframe."""
