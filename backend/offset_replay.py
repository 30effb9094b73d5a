"""The start re-run once the camera-IMU time offset is known (issue 16, `camera.time_offset_replay_s`).

The offset's estimate (backend/time_offset.py) needs about 10 s of motion to converge: the start window's first
estimate has young landmarks (-2 to 18 ms for a true 15 ms on the 60 s phone orbit), and the online estimate then
moves the applied offset by at most 2 ms per keyframe. The keyframes of those first seconds keep the offset they
were placed with: their inertial factors integrate the IMU over windows shifted by its error, and their poses are
stamped at the wrong IMU time (at 0.3 m/s, 15 ms is 4.5 mm). Measured before this existed, over the 60 s orbit
with the true offset given the ATE was lower on 4 of 5 seeds than with the estimate, and after the first 15 s the
two were alike (docs/BENCHMARKS.md, "The estimator's half"); what the re-run gives on ten seeds is in "The start
re-run once the offset is known".

`OffsetReplay` keeps the inputs of the keyframes of the first `window_s` seconds (camera time, tracks, the
re-identification describer, and the offset each was placed with). Once the online estimate's standard error is at
most `camera.time_offset_replay_sigma_s` and the estimate differs by more than `MIN_CHANGE_S` from an offset a kept
keyframe was placed with, the estimator starts again from its first keyframe with the offset fixed at the estimate
and re-runs the kept keyframes (estimating online as before from there). Once per run; a run whose estimate has not
converged within `window_s` keeps its first pass and lets the kept inputs go. The re-run's cost falls on the
keyframe that triggers it (its latency in run.json includes it).
"""

from __future__ import annotations

from dataclasses import dataclass

from vio.descriptors import Describe
from vio.records import FeatureTracks

REPLAY_MIN_PAIRS = 20  # the online estimate is taken once at least this many keyframe pairs went into it
MIN_CHANGE_S = 0.001  # the start is re-run only when some kept keyframe was placed this far from the estimate, s


@dataclass(frozen=True)
class KeptKeyframe:
    """One keyframe's input to `VioEstimator.add_keyframe`, and the offset its pose was placed with."""

    t_ns: int  # the frame's camera time, ns
    tracks: FeatureTracks
    describe: Describe | None
    placed_s: float  # the camera-IMU offset the first pass placed its pose with, s


class OffsetReplay:
    """The kept keyframes of the first `window_s` seconds and the decision to re-run them (module docstring)."""

    def __init__(self, window_s: float, enabled: bool) -> None:
        self.window_s = float(window_s)
        self.kept: list[KeptKeyframe] | None = [] if enabled and self.window_s > 0 else None

    def keep(self, t_ns: int, tracks: FeatureTracks, describe: Describe | None, placed_s: float) -> None:
        """Keep a keyframe's input while within the window; past it, let every kept one go (no re-run)."""
        if self.kept is None:
            return
        if self.kept and (int(t_ns) - self.kept[0].t_ns) * 1e-9 > self.window_s:
            self.kept = None
            return
        self.kept.append(KeptKeyframe(int(t_ns), tracks, describe, float(placed_s)))

    def due(self, offset_s: float | None) -> list[KeptKeyframe] | None:
        """The keyframes to re-run with `offset_s` (the converged estimate, None while it is not), or None. Decides
        once: after a converged estimate the kept inputs are let go either way."""
        if self.kept is None or offset_s is None or not self.kept:
            return None
        kept, self.kept = self.kept, None
        change = max(abs(kf.placed_s - offset_s) for kf in kept)
        return kept if change > MIN_CHANGE_S else None
