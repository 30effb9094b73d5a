"""The zero-velocity test between two keyframes: the phone is at rest when the tracks they share barely move and
the IMU over the last `window_s` passes the at-rest test (config section `zero_velocity`)."""

from __future__ import annotations

import numpy as np

from backend.initialisation.alignment import static_start
from backend.landmarks import LandmarkBook
from vio.config import ZeroVelocityConfig
from vio.records import ImuSeries

_EXACT_MARGIN = 1e-6  # px: within this of the threshold the median is computed again view by view, as it was


def is_still(
    zv: ZeroVelocityConfig, book: LandmarkBook, imu: ImuSeries, t1_ns: int, prev: int, k: int, ids: np.ndarray
) -> bool:
    """At rest between keyframes prev and k (k at IMU time t1_ns): the tracks shared with prev moved less than
    `max_flow_px` (median, px) and the IMU over the last `window_s` passes the at-rest test."""
    if zv.max_flow_px <= 0:
        return False
    shared = [tr.views for tr in (book.tracks[j] for j in ids.tolist()) if prev in tr.views]
    if len(shared) < 5:
        return False
    d = np.array([v[k] for v in shared]) - np.array([v[prev] for v in shared])
    flow = float(np.median(np.sqrt(np.einsum("ij,ij->i", d, d))))  # all at once; near the threshold, as before:
    if abs(flow - zv.max_flow_px) <= _EXACT_MARGIN:
        flow = float(np.median([np.linalg.norm(v[k] - v[prev]) for v in shared]))
    if flow > zv.max_flow_px:
        return False
    return static_start(imu, t1_ns - int(zv.window_s * 1e9), t1_ns, zv.max_gyro_std, zv.max_acc_std) is not None
