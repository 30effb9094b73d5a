"""The start re-run once the camera-IMU time offset is known (backend/offset_replay.py), on ideal phone tracks
(tests/backend/phone_tracks.py: the orbit's points projected at each row's own time, 15 ms offset, no images)."""

from __future__ import annotations

import numpy as np
import pytest

from backend.estimator import VioEstimator
from backend.offset_replay import MIN_CHANGE_S, OffsetReplay
from frontend.preintegration import ImuPreintegrator
from tests.backend.phone_tracks import phone_tracks
from vio.config import CameraConfig, Config, ImuConfig
from vio.records import FeatureTracks

READOUT_S, OFFSET_S = 0.02, 0.015


def _tracks(t_ns: int) -> FeatureTracks:
    return FeatureTracks(t_ns, np.array([1]), np.array([[10.0, 20.0]]))


def test_keyframes_are_kept_within_the_window_only():
    replay = OffsetReplay(window_s=1.0, enabled=True)
    for t in (0, 500_000_000, 1_000_000_000):
        replay.keep(t, _tracks(t), None, 0.0)
    assert replay.kept is not None and len(replay.kept) == 3
    replay.keep(1_000_000_001, _tracks(1_000_000_001), None, 0.0)  # past the window: nothing is re-run
    assert replay.kept is None
    assert replay.due(0.015) is None


def test_disabled_keeps_nothing():
    for replay in (OffsetReplay(window_s=20.0, enabled=False), OffsetReplay(window_s=0.0, enabled=True)):
        replay.keep(0, _tracks(0), None, 0.0)
        assert replay.kept is None and replay.due(0.015) is None


def test_re_run_only_when_some_keyframe_was_placed_far_from_the_estimate():
    near = OffsetReplay(window_s=20.0, enabled=True)
    for i, placed in enumerate((0.0150, 0.0152, 0.0148)):
        near.keep(i * 100_000_000, _tracks(i * 100_000_000), None, placed)
    assert near.due(None) is None and near.kept is not None  # not converged yet: keep waiting
    assert near.due(0.015) is None  # within MIN_CHANGE_S of every placement: no re-run ...
    assert near.kept is None  # ... and the decision is final
    far = OffsetReplay(window_s=20.0, enabled=True)
    for i, placed in enumerate((0.0, 0.012, 0.015)):
        far.keep(i * 100_000_000, _tracks(i * 100_000_000), None, placed)
    kept = far.due(0.015 + 0.5 * MIN_CHANGE_S)
    assert kept is not None and [kf.placed_s for kf in kept] == [0.0, 0.012, 0.015]
    assert far.kept is None and far.due(0.015) is None  # once


def _run(replay_s: float, seed: int = 5) -> tuple[VioEstimator, list[FeatureTracks]]:
    cam, imu, cal, frames, _ = phone_tracks(duration_s=8.0, offset_s=OFFSET_S, readout_s=READOUT_S, seed=seed)
    cfg = Config(camera=CameraConfig(readout_s=READOUT_S, estimate_time_offset=True, time_offset_replay_s=replay_s))
    est = VioEstimator(cam, imu, ImuPreintegrator(imu, cal, ImuConfig()).between, cfg)
    keyframes = frames[::2]  # keyframes at 10 Hz, velocities from the 20 Hz frames
    for tr in keyframes:
        est.add_keyframe(tr.t_ns, tr)
    return est, keyframes


@pytest.mark.slow
def test_the_start_is_re_run_with_the_converged_offset():
    est, keyframes = _run(replay_s=20.0)
    states = est.states()
    assert [s.k for s in states] == list(range(len(keyframes)))  # every keyframe once, none twice
    report = est.stats().time_offset
    assert report is not None and report.replayed_keyframes > 20
    lo, hi = report.replayed_from_s
    assert lo == 0.0 and hi > lo  # the first pass placed the start window at the initial 0, then moved
    placed = np.array([(s.t_ns - kf.t_ns) * 1e-9 - 0.5 * READOUT_S for s, kf in zip(states, keyframes, strict=True)])
    rerun = placed[: report.replayed_keyframes]
    assert np.ptp(rerun) < 1e-9  # every re-run keyframe placed with the one converged offset (held, not moved)
    assert abs(rerun[0] - OFFSET_S) < 0.005 and abs(rerun[0] - OFFSET_S) < abs(lo - OFFSET_S)
    assert report.initial_s == 0.0 and report.after_initialisation_s is not None  # the first pass's, reported
    assert abs(report.value_s - OFFSET_S) < max(3 * report.sigma_s, 0.0025)


@pytest.mark.slow
def test_without_the_re_run_the_start_keeps_its_first_placement():
    est, keyframes = _run(replay_s=0.0)
    states = est.states()
    report = est.stats().time_offset
    assert report is not None and report.replayed_keyframes == 0 and report.replayed_from_s is None
    first = (states[0].t_ns - keyframes[0].t_ns) * 1e-9 - 0.5 * READOUT_S
    assert abs(first) < 1e-9  # placed at the initial offset, 0
