"""The per-minute latency table of `vio.bench.cost_over_time`."""

from __future__ import annotations

import numpy as np

from vio.bench.cost_over_time import per_minute, rss_mib


def test_per_minute_splits_keyframes_by_capture_time():
    t_s = np.array([0.0, 30.0, 59.9, 60.0, 61.0, 150.0])
    ms = np.array([10.0, 20.0, 30.0, 100.0, 200.0, 5.0])
    rows = per_minute(t_s, ms)
    assert [r["minute"] for r in rows] == [1, 2, 3]
    assert [r["keyframes"] for r in rows] == [3, 2, 1]
    assert rows[0]["p50"] == 20.0 and rows[0]["max"] == 30.0
    assert rows[1]["max"] == 200.0 and 100.0 < rows[1]["p95"] < rows[1]["p99"] <= 200.0
    assert per_minute(np.zeros(0), np.zeros(0)) == []


def test_rss_is_this_process():
    assert 10.0 < rss_mib() < 100_000.0


def test_live_latency_queues_behind_background_work():
    from vio.bench.cost_over_time import live_latency

    arrive = np.array([0.0, 0.1, 0.2, 0.3])
    update = np.array([0.01, 0.01, 0.02, 0.01])
    after = np.array([0.0, 0.25, 0.0, 0.0])  # a 250 ms step after the second keyframe
    latency, wait = live_latency(arrive, update, after)
    # the third keyframe comes at 0.2 s, the thread is free at 0.1 + 0.01 + 0.25 = 0.36 s
    np.testing.assert_allclose(wait, [0.0, 0.0, 0.16, 0.08])
    np.testing.assert_allclose(latency, [0.01, 0.01, 0.18, 0.09])
    # nothing behind: the latency is the update itself
    latency, wait = live_latency(arrive, update, np.zeros(4))
    np.testing.assert_allclose(latency, update)
    assert not wait.any()


def test_the_start_queue_ends_at_the_first_keyframe_that_did_not_wait():
    from vio.bench.cost_over_time import start_queue

    t_ns = np.arange(8, dtype=np.int64) * 100
    wait = np.array([0.0, 0.0, 0.0, 0.2, 0.1, 0.0, 0.3, 0.0])  # the start solved at keyframe 2; 6 waits later
    assert start_queue(t_ns, wait, 200) == {"index": 2, "drained_index": 5}
    assert start_queue(t_ns, wait, None) == {"index": 0, "drained_index": 1}
    assert start_queue(t_ns, np.zeros(8), 700) == {"index": 7, "drained_index": 8}
