"""vio.tracking.images: the decoding thread of the tracker's process gives what decoding in place gives."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from vio.capture import Capture
from vio.errors import CaptureError
from vio.tracking import images


def _capture(load) -> Capture:
    t_ns = np.arange(12, dtype=np.int64) * 50_000_000
    return Capture(Path("mem"), None, None, None, t_ns, load)


def _load(i: int) -> np.ndarray:
    if i == 5:
        raise CaptureError("image cannot be decoded", f"{i}.png")
    return np.full((4, 6), i, np.uint8)


@pytest.mark.parametrize("prefetch", [1, 3, 20])
def test_prefetched_images_are_the_images_in_order(prefetch):
    plain = list(images(_capture(_load), 12))
    ahead = list(images(_capture(_load), 12, prefetch))
    assert len(ahead) == len(plain) == 12
    for i, (a, b) in enumerate(zip(plain, ahead, strict=True)):
        if i == 5:  # the frame that fails to decode is a CaptureError in its place, the next ones follow
            assert isinstance(a, CaptureError) and isinstance(b, CaptureError) and str(a) == str(b)
        else:
            assert np.array_equal(a, b)


def test_an_unexpected_error_in_the_thread_is_raised_at_its_frame():
    def load(i: int) -> np.ndarray:
        if i == 3:
            raise ValueError("broken reader")
        return np.zeros((4, 6), np.uint8)

    got = []
    with pytest.raises(ValueError, match="broken reader"):
        for image in images(_capture(load), 12, 2):
            got.append(image)
    assert len(got) == 3


def test_stopping_early_stops_the_thread():
    calls = []

    def load(i: int) -> np.ndarray:
        calls.append(i)
        return np.zeros((4, 6), np.uint8)

    it = images(_capture(load), 12, 2)
    next(it)
    it.close()
    time.sleep(0.5)
    assert len(calls) <= 5  # the one taken, the two queued, one waiting to be queued, at most one more


def test_tracking_ahead_gives_the_same_tracks(sim_capture):
    from vio.config import load_config
    from vio.readers import open_capture
    from vio.tracking import tracked_frames

    cap = open_capture(sim_capture("orbit", 2.0))
    cfg = load_config(None, [])
    plain = list(tracked_frames(cap, cfg, 30))
    ahead = list(tracked_frames(cap, cfg, 30, prefetch=3))
    assert len(plain) == len(ahead) == 30
    for (kind_a, (frame_a, tr_a, ages_a, col_a, key_a)), (kind_b, (frame_b, tr_b, ages_b, col_b, key_b)) in zip(
        plain, ahead, strict=True
    ):
        assert kind_a == kind_b == "frame" and key_a == key_b
        assert np.array_equal(frame_a.image, frame_b.image)
        assert np.array_equal(tr_a.ids, tr_b.ids) and np.array_equal(tr_a.uv, tr_b.uv)
        assert np.array_equal(tr_a.uv_per_s, tr_b.uv_per_s) and np.array_equal(ages_a, ages_b)
        assert np.array_equal(col_a[0], col_b[0]) and np.array_equal(col_a[1], col_b[1])
