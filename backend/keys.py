"""GTSAM keys: `X(k)` pose (world_T_body), `V(k)` velocity (world, m/s), `B(k)` IMU bias share the keyframe index
k; `L(j)` is landmark j (world point, m). No arithmetic on keys.

A landmark id j is the tracker's track id plus `segment << SEGMENT_SHIFT`: one long KLT track may become several
landmarks when it drifts off its first one (backend/segments.py). The encoding lives here and only here.
"""

from __future__ import annotations

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, L, V, X

__all__ = ["B", "L", "V", "X", "SEGMENT_SHIFT", "landmark_id", "landmarks_in", "segment_of", "track_of"]

SEGMENT_SHIFT = 40
_TRACK_MASK = (1 << SEGMENT_SHIFT) - 1


def landmark_id(track_id: int, segment: int) -> int:
    """The landmark id of segment `segment` of track `track_id`."""
    return int(track_id) + (int(segment) << SEGMENT_SHIFT)


def track_of(landmark_ids: int | np.ndarray) -> int | np.ndarray:
    """The tracker's track id of landmark id(s)."""
    if isinstance(landmark_ids, np.ndarray):
        return landmark_ids & _TRACK_MASK
    return int(landmark_ids) & _TRACK_MASK


def segment_of(landmark_id: int) -> int:
    """The segment number of a landmark id."""
    return int(landmark_id) >> SEGMENT_SHIFT


def landmarks_in(keys: list[int]) -> list[int]:
    """The landmark ids j of the `L(j)` among `keys`."""
    syms = [gtsam.Symbol(key) for key in keys]
    return [int(sym.index()) for sym in syms if chr(sym.chr()) == "l"]
