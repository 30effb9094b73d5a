"""The image velocity of each feature track, for the estimator's rolling-shutter and time-offset corrections.

A feature seen at pixel row v of a rolling-shutter image was read `readout * v / H` after the top row, and a
camera-IMU time offset moves every observation in time; to first order a feature observed `dt` away from the time
of the pose it is attached to sits at `uv - dt * velocity` at that time (VINS-Mono's feature-velocity correction).
The velocity is the backward difference to the previous frame, distorted px per second of frame time: the
velocity at the middle of the frame interval (the error is the image acceleration times half a frame interval,
times `dt`). A track new in this frame has velocity 0 (no correction).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from vio.records import FeatureTracks

_NS = 1e-9


class TrackVelocity:
    """Adds `uv_per_s` to each frame's FeatureTracks (call `add` once per frame, in time order)."""

    def __init__(self) -> None:
        self._t_ns: int | None = None
        self._ids = np.zeros(0, np.int64)
        self._uv = np.zeros((0, 2))

    def add(self, tracks: FeatureTracks) -> FeatureTracks:
        """The same tracks with `uv_per_s` (N, 2) distorted px/s measured against the previous frame's tracks."""
        ids = np.asarray(tracks.ids, np.int64)
        uv = np.asarray(tracks.uv, np.float64).reshape(-1, 2)
        vel = np.zeros_like(uv)
        if self._t_ns is not None and tracks.t_ns > self._t_ns and ids.size and self._ids.size:
            dt_s = (int(tracks.t_ns) - self._t_ns) * _NS
            order = np.argsort(self._ids)
            pos = np.searchsorted(self._ids[order], ids)
            pos = np.minimum(pos, self._ids.size - 1)
            seen = self._ids[order][pos] == ids
            prev = order[pos[seen]]
            vel[seen] = (uv[seen] - self._uv[prev]) / dt_s
        self._t_ns, self._ids, self._uv = int(tracks.t_ns), ids.copy(), uv.copy()
        return dataclasses.replace(tracks, uv_per_s=vel)
