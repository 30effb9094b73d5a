"""Run health: the spans of a run where the estimate is less trustworthy, and the run's status.

Spans (each with its start, end and cause; times are sensor-clock ns, end exclusive: the first good sample after):
- `tracking_lost` / `tracking_thin`: frames with no tracked features / fewer than `health.min_tracked_features`
  (shorter than `health.min_span_s`: not reported);
- `imu_only`: keyframes with fewer than `health.min_keyframe_projections` projection factors in the whole graph,
  from the last keyframe with enough to the next one: the pose there rests on the inertial factors alone (on the
  motion model in vision-only mode);
- `imu_gap`: more than `imu.max_gap_s` without an IMU sample inside the frames' span;
- `recovery`: a solver failure the estimator survived by rebuilding from an earlier keyframe (the estimator has no
  other re-initialisation);
- `keyframe_skipped`: a keyframe whose update raised an error the run went on without (start = end);
- `frames_skipped`: frames whose image failed to decode (or has the wrong size), skipped.

`status` is `failed` when there is no estimate (or too many frames failed to decode), `degraded` when any span was
found (the reasons say which), else `ok`. Only `failed` ends `vio run` with a non-zero exit status.
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from dataclasses import asdict, dataclass

import numpy as np

from vio.config import Config
from vio.records import EstimatorStats, ImuSeries

KINDS = ("tracking_lost", "tracking_thin", "imu_only", "imu_gap", "recovery", "keyframe_skipped", "frames_skipped")
_LABELS = {
    "tracking_lost": "tracking lost",
    "tracking_thin": "tracking thin",
    "imu_only": "IMU alone",
    "imu_gap": "IMU gap",
    "recovery": "solver recovery",
    "keyframe_skipped": "keyframe skipped",
    "frames_skipped": "frames skipped",
}
MAX_REASONS = 12  # reasons listed one by one; the rest are counted


@dataclass(frozen=True)
class HealthSpan:
    kind: str  # one of KINDS
    start_t_ns: int  # first affected sample, ns
    end_t_ns: int  # first good sample after the span (the last affected one at the end of the run), ns
    cause: str  # one line


@dataclass(frozen=True)
class RunHealth:
    status: str  # ok | degraded | failed
    reasons: tuple[str, ...]  # one line per problem, times in s from the first frame
    spans: tuple[HealthSpan, ...]  # in time order
    t0_ns: int  # the first frame's time: `start_s`/`end_s` in run.json count from here, ns
    num_frames_skipped: int
    tracked_features: dict[str, float]  # min / median of the tracked features per frame
    first_estimate_t_ns: int | None = None  # the first keyframe with an estimate (the start's end), ns

    def to_dict(self, cfg: Config) -> dict[str, object]:
        """The `health` object of run.json."""
        spans = []
        for s in self.spans:
            d = asdict(s)
            d["start_s"] = round((s.start_t_ns - self.t0_ns) * 1e-9, 3)
            d["end_s"] = round((s.end_t_ns - self.t0_ns) * 1e-9, 3)
            d["duration_s"] = round((s.end_t_ns - s.start_t_ns) * 1e-9, 3)
            spans.append(d)
        return {
            "status": self.status,
            "reasons": list(self.reasons),
            "spans": spans,
            "num_frames_skipped": self.num_frames_skipped,
            "first_estimate_s": (
                None if self.first_estimate_t_ns is None else round((self.first_estimate_t_ns - self.t0_ns) * 1e-9, 3)
            ),
            "tracked_features": self.tracked_features,
            "config": asdict(cfg.health),
        }


class TooManySkipped(Exception):
    """More frames failed to decode than `health.max_skipped_frames` allows (the pipeline turns it into an error)."""


class HealthMonitor:
    """Collects, frame by frame, what run health is computed from; `report` turns it into a RunHealth."""

    def __init__(self, cfg: Config, num_frames: int) -> None:
        self.cfg = cfg
        self.max_skipped = int(cfg.health.max_skipped_frames * num_frames)
        self.frame_t_ns: list[int] = []
        self.num_tracked: list[int] = []
        self.skipped: list[tuple[int, str]] = []  # (t_ns, cause)
        self.keyframes_skipped: list[tuple[int, str]] = []  # (t_ns, cause)

    def frame(self, t_ns: int, num_tracked: int) -> None:
        self.frame_t_ns.append(int(t_ns))
        self.num_tracked.append(int(num_tracked))

    def keyframe_skipped(self, t_ns: int, cause: str) -> None:
        self.keyframes_skipped.append((int(t_ns), cause))

    def skip(self, t_ns: int, cause: str) -> None:
        """A frame that could not be used; raises TooManySkipped past the allowed fraction."""
        self.skipped.append((int(t_ns), cause))
        if len(self.skipped) > self.max_skipped:
            raise TooManySkipped(
                f"{len(self.skipped)} frames failed to decode, more than health.max_skipped_frames "
                f"({self.cfg.health.max_skipped_frames:g} of the frames); first: {self.skipped[0][1]}"
            )

    def report(
        self, stats: EstimatorStats, state_t_ns: Sequence[int], imu: ImuSeries | None, failure: str = ""
    ) -> RunHealth:
        """The run's health from what was collected, the estimator's stats and the keyframes with an estimate."""
        times = sorted([*self.frame_t_ns, *(t for t, _ in self.skipped)])
        t0 = times[0] if times else 0
        spans = [
            *self._tracking_spans(),
            *imu_only_spans(
                stats.keyframe_projections,
                set(state_t_ns),
                self.cfg.health.min_keyframe_projections,
                stats.still_keyframes,
            ),
            *imu_gap_spans(imu, times, self.cfg.imu.max_gap_s),
            *recovery_spans(stats),
            *(HealthSpan("keyframe_skipped", t, t, cause[:200]) for t, cause in self.keyframes_skipped),
            *self._skipped_spans(),
        ]
        spans.sort(key=lambda s: (s.start_t_ns, KINDS.index(s.kind)))
        tracked = np.asarray(self.num_tracked, float)
        counts = {
            "min": float(tracked.min()) if tracked.size else 0.0,
            "median": float(np.median(tracked)) if tracked.size else 0.0,
        }
        reasons = [describe_span(s, t0) for s in spans]
        if len(reasons) > MAX_REASONS:
            reasons = [*reasons[:MAX_REASONS], f"... and {len(reasons) - MAX_REASONS} more spans (see health.spans)"]
        if failure:
            status, reasons = "failed", [failure, *reasons]
        else:
            status = "degraded" if spans else "ok"
        first = min(state_t_ns) if len(state_t_ns) else None
        return RunHealth(status, tuple(reasons), tuple(spans), t0, len(self.skipped), counts, first)

    def _tracking_spans(self) -> list[HealthSpan]:
        h = self.cfg.health
        t = np.asarray(self.frame_t_ns, np.int64)
        n = np.asarray(self.num_tracked, np.int64)
        out = []
        for i0, i1 in runs(n < h.min_tracked_features):
            end = int(t[i1]) if i1 < t.size else int(t[-1])
            if (end - int(t[i0])) * 1e-9 < h.min_span_s:
                continue
            low = int(n[i0:i1].min())
            kind = "tracking_lost" if low == 0 else "tracking_thin"
            what = "no tracked features" if low == 0 else f"as few as {low} tracked features"
            out.append(
                HealthSpan(kind, int(t[i0]), end, f"{what} in {i1 - i0} frames (< {h.min_tracked_features} needed)")
            )
        return out

    def _skipped_spans(self) -> list[HealthSpan]:
        if not self.skipped:
            return []
        t_skip = np.array([t for t, _ in self.skipped], np.int64)
        t_all = np.array(sorted([*self.frame_t_ns, *t_skip.tolist()]), np.int64)
        bad = np.isin(t_all, t_skip)
        causes = dict(self.skipped)
        out = []
        for i0, i1 in runs(bad):
            end = int(t_all[i1]) if i1 < t_all.size else int(t_all[-1])
            n = i1 - i0
            cause = f"{n} frame(s) skipped (first: {causes[int(t_all[i0])]})"
            out.append(HealthSpan("frames_skipped", int(t_all[i0]), end, cause))
        return out


def runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[i0, i1) index ranges of the consecutive True values of a boolean array."""
    m = np.concatenate([[False], np.asarray(mask, bool), [False]])
    edges = np.flatnonzero(np.diff(m.astype(np.int8)))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2], strict=True)]


def imu_only_spans(
    keyframes: Sequence[tuple[int, int, int]],
    estimated: set[int],
    min_projections: int,
    still: Collection[int] = (),
) -> list[HealthSpan]:
    """Spans bridged by keyframes with fewer than `min_projections` projection factors, from the last keyframe with
    enough before them to the first one after (only keyframes with an estimate count). A keyframe in `still` (times,
    ns: held by a zero-velocity update or a static start) is at rest and counts as constrained: holding the phone
    still, as `vio run`'s capture advice asks, is not a degraded run."""
    rest = set(still)
    kf = [(t, min_projections if t in rest else n) for _, t, n in keyframes if t in estimated]
    if not kf:
        return []
    t = np.array([x for x, _ in kf], np.int64)
    n = np.array([x for _, x in kf], np.int64)
    out = []
    for i0, i1 in runs(n < min_projections):
        start = int(t[i0 - 1]) if i0 > 0 else int(t[i0])
        end = int(t[i1]) if i1 < t.size else int(t[-1])
        cause = f"{i1 - i0} keyframe(s) without visual constraints (< {min_projections} projection factors)"
        out.append(HealthSpan("imu_only", start, end, cause))
    return out


def imu_gap_spans(imu: ImuSeries | None, frame_t_ns: Sequence[int], max_gap_s: float) -> list[HealthSpan]:
    """Intervals longer than `max_gap_s` between IMU samples, inside the frames' span."""
    if imu is None or len(imu) < 2 or not len(frame_t_ns):
        return []
    t = imu.t_ns
    dt = np.diff(t)
    gaps = np.flatnonzero((dt > max_gap_s * 1e9) & (t[1:] > frame_t_ns[0]) & (t[:-1] < frame_t_ns[-1]))
    return [
        HealthSpan("imu_gap", int(t[i]), int(t[i + 1]), f"no IMU sample for {dt[i] * 1e-6:.0f} ms (> {max_gap_s:g} s)")
        for i in gaps.tolist()
    ]


def recovery_spans(stats: EstimatorStats) -> list[HealthSpan]:
    """A solver recovery: from the keyframe the smoother was rebuilt from to the one whose update failed."""
    times = {k: t for k, t, _ in stats.keyframe_projections}
    out = []
    for r in stats.recoveries:
        start = times.get(r.restart_from_k, r.t_ns)
        reason = r.reason.splitlines()[0] if r.reason else "solver failure"
        out.append(HealthSpan("recovery", int(start), int(r.t_ns), f"{reason[:160]}; rebuilt from an earlier keyframe"))
    return out


def describe_span(span: HealthSpan, t0_ns: int) -> str:
    """One line: what, when (s from the first frame, t0_ns), how long, and why."""
    a, b = (span.start_t_ns - t0_ns) * 1e-9, (span.end_t_ns - t0_ns) * 1e-9
    return f"{_LABELS[span.kind]} {a:.2f}-{b:.2f} s ({b - a:.2f} s): {span.cause}"


def summary_lines(summary: dict[str, object]) -> list[str]:
    """The printed end of `vio run`: status, counts, one line per reason, and the scale's sigma with the capture
    advice when it is large (backend/uncertainty.py)."""
    head = (
        f"status: {summary['status']} - {summary['num_states']} keyframes, {summary['num_landmarks']} landmarks, "
        f"{summary['span_s']:.1f} s of capture in {summary['wall_time_s']:.1f} s"
    )
    lines = [head, *(f"  {r}" for r in summary.get("reasons", []))]  # type: ignore[union-attr]
    scale = summary.get("scale") or {}
    if scale.get("advice"):  # type: ignore[union-attr]
        lines.append(str(scale["advice"]))  # type: ignore[index]
    elif scale.get("sigma_rel") is not None:  # type: ignore[union-attr]
        lines.append(f"scale sigma {100 * scale['sigma_rel']:.2f} % (from the graph)")  # type: ignore[index]
    if scale.get("axes_advice"):  # type: ignore[union-attr]
        lines.append(str(scale["axes_advice"]))  # type: ignore[index]
    return lines
