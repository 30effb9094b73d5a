"""`vio run`: the only module that knows both the frontends and the backend; it wires the stages and does nothing
else.

Frames go through the OpenCV tracker (or precomputed tracks, e.g. gtsam's eqvio file), the keyframe selector
(`frontend.keyframes`: the tracker's own, or here for precomputed tracks) picks keyframes, the estimator
preintegrates the IMU between them and updates the smoother; estimates go to the sinks (the rerun viewer is one,
built by the command line) and, at the end, `vio.outputs` writes trajectory.tum, states.csv, landmarks.ply and
run.json in `out`. A tracking loss, a solver exception or a frame that fails to decode
does not end the run; `vio.health` reports them in run.json as spans with a cause, and the run's status.
"""

from __future__ import annotations

import dataclasses
import gc
import logging
import os
import sys
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from backend.estimator import VioEstimator
from backend.uncertainty import motion_excitation, scale_advice
from frontend.descriptors import KeyframeDescriber
from frontend.keyframes import KeyframeSelector
from frontend.preintegration import ImuPreintegrator
from frontend.track_velocity import TrackVelocity
from vio import outputs
from vio.atomic import ensure_dir
from vio.capture import Capture
from vio.config import Config
from vio.errors import CaptureError, EstimationError, VioError
from vio.health import HealthMonitor, TooManySkipped
from vio.records import EstimatorStats, FeatureTracks, Frame, LandmarkMap, StateEstimate
from vio.sinks import EstimateSink
from vio.tracking import TrackColours, tracked_frames

log = logging.getLogger(__name__)

# Python's full (generation 2) garbage collections scan every object the run keeps: 21-64 ms each, seven in a run
# over the first 220 s of the 10-minute orbit; with the freeze the worst keyframe per minute of the whole orbit fell
# from 71-236 ms CPU to 76-118 ms (docs/BENCHMARKS.md). Every this many keyframes the objects alive are
# frozen (`gc.freeze`: out of the collector's sight; reference counting still frees them), so a full collection
# scans only what came since; short-lived cycles are collected before they are frozen. Unfrozen at the end.
GC_FREEZE_KEYFRAMES = 25


@dataclass(frozen=True)
class RunResult:
    """What `run_capture` produced: the run summary written to run.json, the estimator's stats, the estimate."""

    out: Path  # the output folder
    summary: dict[str, Any]  # the contents of run.json
    stats: EstimatorStats
    states: list[StateEstimate]  # every keyframe's final estimate, in time order
    landmarks: LandmarkMap


def open_any(capture: str | os.PathLike[str] | Capture, calib: str | None = None) -> Capture:
    """A Capture object, or a path opened with the format detected."""
    if isinstance(capture, Capture):
        return capture
    from vio.readers import open_capture

    return open_capture(capture, calib=calib)


class _Progress:
    """A one-line progress bar with frames per second, only when stderr is a terminal."""

    def __init__(self, total: int, enabled: bool) -> None:
        self.total, self.enabled = total, enabled and sys.stderr.isatty()
        self.t0 = time.perf_counter()
        self.last = 0.0

    def update(self, i: int, kf: int) -> None:
        now = time.perf_counter()
        if not self.enabled or (now - self.last < 0.25 and i < self.total):
            return
        self.last = now
        fps = i / max(now - self.t0, 1e-9)
        n = int(30 * i / max(self.total, 1))
        sys.stderr.write(f"\r[{'#' * n}{'.' * (30 - n)}] {i}/{self.total} frames, {kf} keyframes, {fps:.1f} fps")
        sys.stderr.flush()

    def close(self) -> None:
        if self.enabled:
            sys.stderr.write("\n")


# (frame or None, tracks, track ages in frames (N,), the new tracks' colours (ids, RGB) or None without images,
# whether the frame is a keyframe: the tracker's choice, or None for the capture's own tracks)
Tracked = tuple[Frame | None, FeatureTracks, np.ndarray, tuple[np.ndarray, np.ndarray] | None, bool | None]


def _frames_and_tracks(cap: Capture, cfg: Config, stop: int, monitor: HealthMonitor, viewer: bool) -> Iterator[Tracked]:
    """Yield (frame or None, tracks, ages, the new tracks' colours or None, keyframe or None) for every frame: the
    capture's own tracks (the keyframes left to the caller), or the tracker's (with its keyframes), in a process of
    its own when `cfg.run.tracker_process` and the capture can be opened again there (`Capture.reopen`,
    `vio.track_worker`: frames without an image then are the non-keyframes, unless a `viewer` needs them all). A
    frame whose image fails to decode is skipped with a warning and counted by `monitor`."""
    if cap.tracks is not None:
        velocity = TrackVelocity()
        first_seen: dict[int, int] = {}
        for i, tr in enumerate(cap.tracks[:stop]):
            ages = np.array([i - first_seen.setdefault(int(j), i) for j in tr.ids], np.int64)
            yield None, velocity.add(tr), ages, None, None
        return
    if cfg.run.tracker_process and cap.reopen is not None:
        from vio.track_worker import tracked_in_worker

        items = tracked_in_worker(cap.reopen, cfg, stop, viewer)
    else:
        items = tracked_frames(cap, cfg, stop)
    for kind, payload in items:
        if kind == "skip":
            t_ns, i, reason = payload
            log.warning("frame %d (t=%d ns) skipped: %s", i, t_ns, reason)
            monitor.skip(t_ns, reason)
            continue
        yield payload


def _add_keyframe(est: VioEstimator, frame: Frame | None, tracks: FeatureTracks, cfg: Config) -> list[StateEstimate]:
    """One keyframe into the estimator; an error in it is logged and skipped, never ends the run."""
    describe = None
    if frame is not None and cfg.reidentification.enabled:
        describe = KeyframeDescriber(frame.image).describe
    return est.add_keyframe(tracks.t_ns, tracks, describe)


def run_capture(
    capture: str | os.PathLike[str] | Capture,
    out: str | os.PathLike[str],
    cfg: Config,
    positions: str | None = None,
    sinks: Sequence[EstimateSink] = (),
    calib: str | None = None,
) -> RunResult:
    """Estimate the whole capture; writes the output files into `out` (see vio.outputs) and returns them.

    Sinks receive the calibration, every frame and every estimate as the run goes; they are closed at the end.
    run.json is written last: while the run goes (or after it was killed) it says `running`, after Ctrl-C
    `interrupted`, after an error `failed`; the previous run's files in `out` are removed first, so a folder never
    mixes two runs. A failed run (no estimate, too many frames that do not decode) raises after writing run.json.
    """
    out = ensure_dir(out)  # first: a folder in the way fails before any work
    outputs.start_run(out)
    try:
        try:
            result, failure = _run(capture, out, cfg, positions, sinks, calib)
        finally:
            for sink in sinks:
                sink.close()
    except KeyboardInterrupt:
        outputs.discard_run(out)  # an interrupted write_estimate may have left some files: none is kept
        outputs.write_run_json(out / "run.json", outputs.stopped_summary("interrupted", "interrupted by the user"))
        raise
    except VioError as exc:
        outputs.discard_run(out)
        outputs.write_run_json(out / "run.json", outputs.stopped_summary("failed", str(exc)))
        raise
    if failure is not None:  # run.json already says failed, with the run's health
        raise failure
    return result


def _run(
    capture: str | os.PathLike[str] | Capture,
    out: Path,
    cfg: Config,
    positions: str | None,
    sinks: Sequence[EstimateSink],
    calib: str | None,
) -> tuple[RunResult, VioError | None]:
    """The run (see run_capture); a failure is returned with the result (run.json written), not raised."""
    t_start, cpu_start = time.perf_counter(), time.process_time()
    cap = open_any(capture, calib)
    if cap.camera is None or cap.imu is None or cap.imu_calib is None:
        raise CaptureError("capture needs camera calibration, IMU samples and IMU noise calibration", cap.root)
    cap, axes_note = _with_axes(cap, cfg)
    known = None
    if positions is not None:
        from vio.readers.positions import read_positions

        known = read_positions(positions)
    refine = cfg.run.refine  # the batch refinement is decided by the config only
    cfg, readout_source = _with_readout(cap, cfg)
    for sink in sinks:
        sink.on_start(cap.camera, cap.imu, cap.ground_truth)
    pre = ImuPreintegrator(cap.imu, cap.imu_calib, cfg.imu)
    est = VioEstimator(cap.camera, cap.imu, pre.between, cfg, known, unique_track_ids=cap.tracks is None)
    selector = KeyframeSelector(cfg.keyframes)
    n_frames = cap.num_frames if cap.tracks is None else len(cap.tracks)
    stop = n_frames if cfg.run.max_frames <= 0 else min(n_frames, cfg.run.max_frames)
    bar = _Progress(stop, cfg.run.progress)
    colours = TrackColours()
    monitor = HealthMonitor(cfg, stop)
    errors: list[str] = []
    failure, kind = "", EstimationError
    n_kf = n_done = 0
    t_first = t_last = None
    try:
        frames = _frames_and_tracks(cap, cfg, stop, monitor, bool(sinks))
        for n_done, (frame, tracks, ages, new_colours, keyframe) in enumerate(frames, start=1):
            t_first = tracks.t_ns if t_first is None else t_first
            t_last = tracks.t_ns
            monitor.frame(tracks.t_ns, len(tracks.ids))
            if new_colours is not None:
                colours.add(*new_colours)
            if frame is not None:
                for sink in sinks:
                    sink.on_frame(frame, tracks.ids, tracks.uv, ages)
            if selector.consider(tracks) if keyframe is None else keyframe:
                n_kf += 1
                try:
                    produced = _add_keyframe(est, frame, tracks, cfg)
                except (RuntimeError, ValueError) as exc:  # never end the run on one bad keyframe
                    errors.append(f"keyframe at t={tracks.t_ns} ns skipped: {type(exc).__name__}: {exc}")
                    log.warning(errors[-1])
                    monitor.keyframe_skipped(tracks.t_ns, f"{type(exc).__name__}: {str(exc).strip()}")
                    produced = []
                if n_kf % GC_FREEZE_KEYFRAMES == 0:
                    gc.freeze()  # what the run keeps is scanned no more: no full collection of it mid-run
                if sinks and produced:
                    live = est.landmarks(sync=False)
                    produced[-1] = dataclasses.replace(
                        produced[-1], landmark_ids=live.track_ids, landmarks_world=live.points_world
                    )
                    for s in produced:
                        for sink in sinks:
                            sink.on_estimate(s, {"solve_ms": s.solve_ms, "num_landmarks": len(live)})
                try:  # the smoother's deferred work, once the keyframe's estimate is out (smoother.background)
                    est.background()
                except (RuntimeError, ValueError) as exc:
                    errors.append(f"background step after t={tracks.t_ns} ns skipped: {type(exc).__name__}: {exc}")
                    log.warning(errors[-1])
            bar.update(n_done, n_kf)
    except TooManySkipped as exc:
        failure, kind = f"{cap.root}: {exc}", CaptureError
    finally:
        bar.close()
        gc.unfreeze()  # the caller's collector as it was (its next full collection sees everything again)
    online_states = est.states() if refine and not failure else []  # kept beside the refined answer
    refine_info = est.finish(refine and not failure)
    states, landmarks, stats = est.states(), est.landmarks(), est.stats()
    if not states and not failure:
        failure, kind = f"{cap.root}: the estimator never initialised ({n_kf} keyframes)", EstimationError
    health = monitor.report(stats, [s.t_ns for s in states], cap.imu, failure)
    for sink in sinks:
        on_health = getattr(sink, "on_health", None)
        if on_health is not None:
            on_health(health)
    wall = time.perf_counter() - t_start
    span_s = (t_last - t_first) * 1e-9 if t_first is not None else 0.0
    summary = outputs.run_summary(
        cap,
        cfg,
        stats,
        outputs.RunCounts(n_done, n_kf, len(states), len(landmarks), span_s, wall, time.process_time() - cpu_start),
        refine_info,
        errors,
        health,
    )
    summary["scale"].update(_scale_advice(cap, stats, states, gravity_frame=positions is None))
    summary["scale"].update(axes_note)
    summary["camera_timing"] = outputs.camera_timing(stats, readout_source)
    result = RunResult(out, summary, stats, states, landmarks)
    if failure:
        outputs.write_run_json(out / "run.json", summary)
        return result, kind(f"{failure}; see {out / 'run.json'}")
    outputs.write_estimate(out, states, online_states, landmarks, colours.of(landmarks.track_ids))
    outputs.write_run_json(out / "run.json", summary)  # last: a run.json with a final status means complete
    scale = "" if stats.scale_sigma_rel is None else f", scale sigma {100 * stats.scale_sigma_rel:.2f} % (graph)"
    log.info(
        "%d keyframes, %d landmarks, %.1f s wall (%.2fx real time), %d recoveries%s",
        len(states),
        len(landmarks),
        wall,
        summary["realtime_factor"],
        len(stats.recoveries),
        scale,
    )
    if summary["scale"].get("advice"):
        log.info("%s", summary["scale"]["advice"])
    return result, None


def _with_readout(cap: Capture, cfg: Config) -> tuple[Config, str]:
    """The config with the rolling-shutter readout to use, and where it came from: `config` (camera.readout_s >= 0),
    or with camera.readout_s < 0 the capture's own (a MARS folder's movie_metadata.csv), else 0 (global shutter)."""
    if cfg.camera.readout_s >= 0:
        return cfg, "config"
    readout_s, source = 0.0, "none: global shutter"
    if cap.format == "mars":
        from vio.readers.mars import readout_ns

        got = readout_ns(cap.root)
        if got:
            readout_s, source = got * 1e-9, "capture: movie_metadata.csv"
    if readout_s > 0:
        log.info("rolling shutter: readout %.2f ms (%s)", readout_s * 1e3, source)
    return dataclasses.replace(cfg, camera=dataclasses.replace(cfg.camera, readout_s=readout_s)), source


PHONE_FORMATS = ("mars", "opencamera", "sensorlogger")  # phone apps' logs
AXES_ADVICE = (
    "a phone accelerometer's axes are off by about 1 %, which the metric scale inherits: calibrate them once "
    "(vio calibrate imu-axes) and run with --set imu.axes=FILE"
)


def _with_axes(cap: Capture, cfg: Config) -> tuple[Capture, dict[str, Any]]:
    """The capture with its accelerometer corrected by `imu.axes` (vio/calibrate/imu_axes.py), and run.json's
    `scale.imu_axes` (the file used, or None) with `scale.axes_advice` for a phone app's log that has none."""
    if cfg.imu.axes:
        from vio.calibrate.imu_axes import corrected, read_correction

        cap = dataclasses.replace(cap, imu=corrected(cap.imu, read_correction(cfg.imu.axes)))
        return cap, {"imu_axes": cfg.imu.axes}
    if cap.format in PHONE_FORMATS:
        return cap, {"imu_axes": None, "axes_advice": AXES_ADVICE}
    return cap, {"imu_axes": None}


def _scale_advice(
    cap: Capture, stats: EstimatorStats, states: list[StateEstimate], gravity_frame: bool
) -> dict[str, Any]:
    """run.json `scale.excitation` (the run's squared body acceleration integrated, (m/s^2)^2 s) and `scale.advice`
    (how to capture next time, or None): metric runs in the gravity-aligned world only (known positions bring their
    own frame and scale)."""
    if stats.scale_sigma_rel is None or cap.imu is None or cap.imu_calib is None or not gravity_frame:
        return {}
    density = cap.imu_calib.accelerometer_noise_density
    excitation = motion_excitation(cap.imu, states, density)
    return {"excitation": excitation, "advice": scale_advice(stats.scale_sigma_rel, excitation, density)}
