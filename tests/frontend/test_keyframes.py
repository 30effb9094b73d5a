"""KeyframeSelector: first frame, time, parallax and survival triggers, and the minimum interval."""

from __future__ import annotations

import numpy as np
import pytest

from frontend.keyframes import KeyframeSelector
from vio.config import KeyframeConfig
from vio.errors import ConfigError
from vio.records import FeatureTracks

MS = 1_000_000


def tracks(t_ms: float, ids, uv) -> FeatureTracks:
    return FeatureTracks(int(round(t_ms * MS)), np.asarray(ids, np.int64), np.asarray(uv, float).reshape(-1, 2))


def grid_uv(n: int) -> np.ndarray:
    return np.column_stack([np.arange(n) % 10 * 50.0 + 20, np.arange(n) // 10 * 40.0 + 20])


def test_first_frame_is_a_keyframe_even_when_empty():
    sel = KeyframeSelector(KeyframeConfig())
    assert sel.consider(tracks(0, [], np.zeros((0, 2))))
    assert sel.last_reason == "first"


def test_still_tracks_give_keyframes_by_time_only():
    cfg = KeyframeConfig(max_interval_s=0.2, min_interval_s=0.05)
    sel = KeyframeSelector(cfg)
    ids, uv = np.arange(100), grid_uv(100)
    kf_times = [t for t in range(0, 1001, 10) if sel.consider(tracks(t, ids, uv))]
    assert kf_times == [0, 200, 400, 600, 800, 1000]
    assert sel.last_reason == "time"


def test_parallax_triggers_after_enough_motion():
    cfg = KeyframeConfig(min_parallax_px=12.0, max_interval_s=10.0, min_interval_s=0.05)
    sel = KeyframeSelector(cfg)
    ids, uv = np.arange(100), grid_uv(100)
    decisions = [sel.consider(tracks(t * 10, ids, uv + [t * 1.0, 0.0])) for t in range(40)]
    kf = [i for i, d in enumerate(decisions) if d]
    assert kf == [0, 12, 24, 36]
    assert sel.last_reason in ("parallax", "")


def test_parallax_is_the_median_so_a_few_fast_tracks_do_not_trigger():
    sel = KeyframeSelector(KeyframeConfig(min_parallax_px=12.0, max_interval_s=10.0))
    ids, uv = np.arange(100), grid_uv(100)
    assert sel.consider(tracks(0, ids, uv))
    moved = uv.copy()
    moved[:30] += 50.0  # 30% of tracks jump; the median does not
    assert not sel.consider(tracks(100, ids, moved))
    assert sel.last_parallax_px == pytest.approx(0.0)


def test_survival_triggers_when_tracks_are_lost():
    cfg = KeyframeConfig(min_survival=0.7, max_interval_s=10.0, min_interval_s=0.0)
    sel = KeyframeSelector(cfg)
    uv = grid_uv(100)
    assert sel.consider(tracks(0, np.arange(100), uv))
    assert not sel.consider(tracks(10, np.arange(25, 100), uv[25:]))  # 75% alive
    uv_now = np.vstack([uv[35:], grid_uv(30) + 3.0])
    assert sel.consider(tracks(20, np.arange(35, 130), uv_now))  # 65% of the keyframe's tracks alive
    assert sel.last_reason == "survival" and sel.last_survival == pytest.approx(0.65)
    assert sel.consider(tracks(30, np.arange(1000, 1050), grid_uv(50)))  # nothing in common
    assert sel.num_keyframes == 3


def test_min_interval_holds_back_even_large_parallax():
    sel = KeyframeSelector(KeyframeConfig(min_interval_s=0.05, min_parallax_px=5.0))
    ids, uv = np.arange(50), grid_uv(50)
    assert sel.consider(tracks(0, ids, uv))
    assert not sel.consider(tracks(20, ids, uv + 100.0))
    assert not sel.consider(tracks(40, ids[:5], uv[:5]))
    assert sel.consider(tracks(50, ids, uv + 100.0))


def test_inconsistent_intervals_are_rejected():
    with pytest.raises(ConfigError, match="min_interval_s"):
        KeyframeSelector(KeyframeConfig(min_interval_s=1.0, max_interval_s=0.2))
