"""Keyframe selection by parallax, track survival and time.

A frame becomes a keyframe when, measured against the last keyframe,
- at least `max_interval_s` has passed (the estimator needs IMU factors that stay short), or
- the median displacement of the tracks seen in both frames reaches `min_parallax_px` (enough baseline to
  triangulate; distorted pixels, not rotation-compensated), or
- fewer than `min_survival` of the last keyframe's tracks are still alive (the view is being lost),
but never sooner than `min_interval_s` after it. The first frame is always a keyframe. A frame with no tracks in
common with the last keyframe counts as zero survival.
"""

from __future__ import annotations

import numpy as np

from vio.config import KeyframeConfig
from vio.errors import ConfigError
from vio.records import FeatureTracks

_NS_PER_S = 1_000_000_000


class KeyframeSelector:
    """Decides frame by frame whether the tracks of a frame start a new keyframe (call in time order)."""

    def __init__(self, cfg: KeyframeConfig) -> None:
        if cfg.min_interval_s > cfg.max_interval_s:
            raise ConfigError(
                f"config keyframes: min_interval_s ({cfg.min_interval_s}) > max_interval_s ({cfg.max_interval_s})"
            )
        self.cfg = cfg
        self._kf_t_ns: int | None = None
        self._kf_ids = np.zeros(0, np.int64)
        self._kf_uv = np.zeros((0, 2))
        self.num_keyframes = 0
        self.last_reason = ""  # why the last call decided as it did: first | time | parallax | survival | "" (no)
        self.last_parallax_px = 0.0  # median displacement since the last keyframe at the last call, px
        self.last_survival = 1.0  # fraction of the last keyframe's tracks alive at the last call

    def consider(self, tracks: FeatureTracks) -> bool:
        """True when this frame is a keyframe; the selector then measures the next frames against it."""
        reason = self._decide(tracks)
        self.last_reason = reason
        if reason:
            self._kf_t_ns = int(tracks.t_ns)
            self._kf_ids = np.asarray(tracks.ids, np.int64).copy()
            self._kf_uv = np.asarray(tracks.uv, np.float64).reshape(-1, 2).copy()
            self.num_keyframes += 1
        return bool(reason)

    def _decide(self, tracks: FeatureTracks) -> str:
        if self._kf_t_ns is None:
            self.last_parallax_px, self.last_survival = 0.0, 1.0
            return "first"
        dt_s = (int(tracks.t_ns) - self._kf_t_ns) / _NS_PER_S
        ids = np.asarray(tracks.ids, np.int64)
        _, i_kf, i_now = np.intersect1d(self._kf_ids, ids, assume_unique=True, return_indices=True)
        self.last_survival = i_kf.size / self._kf_ids.size if self._kf_ids.size else (1.0 if ids.size == 0 else 0.0)
        if i_kf.size:
            uv = np.asarray(tracks.uv, np.float64).reshape(-1, 2)
            self.last_parallax_px = float(np.median(np.linalg.norm(uv[i_now] - self._kf_uv[i_kf], axis=1)))
        else:
            self.last_parallax_px = 0.0
        if dt_s < self.cfg.min_interval_s:
            return ""
        if dt_s >= self.cfg.max_interval_s:
            return "time"
        if self.last_parallax_px >= self.cfg.min_parallax_px:
            return "parallax"
        if self.last_survival < self.cfg.min_survival or (i_kf.size == 0 and self._kf_ids.size):
            return "survival"
        return ""
