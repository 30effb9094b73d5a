"""Image velocities of feature tracks (frontend/track_velocity.py): the backward difference to the previous frame."""

from __future__ import annotations

import numpy as np

from frontend.track_velocity import TrackVelocity
from vio.records import FeatureTracks

MS = 1_000_000


def _tracks(t_ms: float, ids: list[int], uv: list[list[float]]) -> FeatureTracks:
    return FeatureTracks(int(round(t_ms * MS)), np.asarray(ids, np.int64), np.asarray(uv, float).reshape(-1, 2))


def test_velocity_is_the_displacement_over_the_frame_interval_and_zero_for_new_tracks():
    tv = TrackVelocity()
    first = tv.add(_tracks(0, [3, 7], [[10, 20], [30, 40]]))
    assert np.array_equal(first.uv_per_s, np.zeros((2, 2)))  # no previous frame
    # 50 ms later: track 7 moved (+5, -2) px, track 3 is gone, track 9 is new; order differs from the first frame
    second = tv.add(_tracks(50, [9, 7], [[1, 1], [35, 38]]))
    assert np.allclose(second.uv_per_s, [[0.0, 0.0], [100.0, -40.0]])  # px/s
    assert np.array_equal(second.uv, [[1, 1], [35, 38]]) and np.array_equal(second.ids, [9, 7])
    third = tv.add(_tracks(75, [7, 9], [[36, 38], [1, 3]]))  # a 25 ms interval
    assert np.allclose(third.uv_per_s, [[40.0, 0.0], [0.0, 80.0]])


def test_empty_frames_and_frames_without_common_tracks_give_zero_velocity():
    tv = TrackVelocity()
    assert tv.add(_tracks(0, [], [])).uv_per_s.shape == (0, 2)
    tv.add(_tracks(50, [1], [[5, 5]]))
    out = tv.add(_tracks(100, [2], [[6, 6]]))
    assert np.array_equal(out.uv_per_s, np.zeros((1, 2)))
