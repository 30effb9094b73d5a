"""`vio run`: the only module that knows both the frontends and the backend.

Frames go through the OpenCV tracker (or precomputed tracks, e.g. gtsam's eqvio file), the keyframe selector
picks keyframes, the estimator preintegrates the IMU between them and updates the smoother; estimates go to the
sinks (rerun) and, at the end, to trajectory.tum, states.csv, landmarks.ply and run.json in `out`.
A tracking loss or a solver exception does not end the run; they are counted and reported in run.json.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import sys
import time
from typing import Any

import numpy as np

from backend.estimator import VioEstimator
from frontend.descriptors import KeyframeDescriber
from frontend.keyframes import KeyframeSelector
from frontend.preintegration import ImuPreintegrator
from vio import outputs
from vio.atomic import ensure_dir
from vio.capture import Capture
from vio.config import Config
from vio.errors import CaptureError, EstimationError

log = logging.getLogger(__name__)
_TRACK_MASK = (1 << 40) - 1  # landmark id -> the tracker's track id (backend.estimator._segment_ids)


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


def _frames_and_tracks(cap: Capture, cfg: Config, stop: int):
    """Yield (frame or None, tracks, ages) for every frame: from the tracker, or the capture's own tracks."""
    if cap.tracks is not None:
        first_seen: dict[int, int] = {}
        for i, tr in enumerate(cap.tracks[:stop]):
            ages = np.array([i - first_seen.setdefault(int(j), i) for j in tr.ids], np.int64)
            yield None, tr, ages
        return
    from frontend.tracker import FeatureTracker

    tracker = FeatureTracker(cap.camera, cfg.tracker)
    for frame in cap.frames(0, stop):
        tracks = tracker.track(frame)
        yield frame, tracks, tracker.ages()


def _sample_colours(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(N, 3) uint8 RGB at the nearest pixel (grey images give grey)."""
    h, w = image.shape[:2]
    u = np.clip(np.rint(uv[:, 0]).astype(int), 0, w - 1)
    v = np.clip(np.rint(uv[:, 1]).astype(int), 0, h - 1)
    px = image[v, u]
    return np.repeat(px[:, None], 3, axis=1) if px.ndim == 1 else px[:, ::-1]


def run_capture(
    capture: str | os.PathLike[str] | Capture,
    out: str | os.PathLike[str],
    cfg: Config,
    positions: str | None = None,
    rrd: str | None = None,
    serve: bool = False,
    spawn: bool = False,
    port: int = 0,
    refine: bool | None = None,
    calib: str | None = None,
) -> dict[str, Any]:
    """Estimate the whole capture; writes the four output files into `out` and returns the run summary."""
    t_start = time.perf_counter()
    cpu_start = time.process_time()
    out = ensure_dir(out)  # first: a folder in the way fails before any work
    cap = open_any(capture, calib)
    if cap.camera is None or cap.imu is None or cap.imu_calib is None:
        raise CaptureError("capture needs camera calibration, IMU samples and IMU noise calibration", cap.root)
    known = None
    if positions is not None:
        from vio.positions import read_positions

        known = read_positions(positions)
    refine = cfg.run.refine if refine is None else bool(refine)
    sink = None
    if rrd or serve or spawn:
        from vio.viz.rerun_sink import make_rerun_sink

        sink = make_rerun_sink(rrd=rrd, serve=serve, spawn=spawn, port=port)
        sink.on_start(cap.camera, cap.imu, cap.ground_truth)
    pre = ImuPreintegrator(cap.imu, cap.imu_calib, cfg.imu)
    est = VioEstimator(
        cap.camera, cap.imu, pre.between, cfg.backend, cfg.imu.bias_init_sigma_acc, cfg.imu.bias_init_sigma_gyro, known
    )
    selector = KeyframeSelector(cfg.keyframes)
    n_frames = cap.num_frames if cap.tracks is None else len(cap.tracks)
    stop = n_frames if cfg.run.max_frames <= 0 else min(n_frames, cfg.run.max_frames)
    bar = _Progress(stop, cfg.run.progress)
    colours: dict[int, np.ndarray] = {}
    errors: list[str] = []
    n_kf = n_done = 0
    t_first = t_last = None
    for n_done, (frame, tracks, ages) in enumerate(_frames_and_tracks(cap, cfg, stop), start=1):
        t_first = tracks.t_ns if t_first is None else t_first
        t_last = tracks.t_ns
        if frame is not None:
            new = [i for i, j in enumerate(tracks.ids.tolist()) if j not in colours]
            if new:
                for j, c in zip(tracks.ids[new].tolist(), _sample_colours(frame.image, tracks.uv[new]), strict=True):
                    colours[j] = c
            if sink is not None:
                sink.on_frame(frame, tracks.ids, tracks.uv, ages)
        if selector.consider(tracks):
            n_kf += 1
            try:
                describe = None
                if frame is not None and cfg.backend.reid:
                    describe = KeyframeDescriber(frame.image).describe
                produced = est.add_keyframe(tracks.t_ns, tracks, describe)
            except (RuntimeError, ValueError) as exc:  # never end the run on one bad keyframe
                msg = f"keyframe at t={tracks.t_ns} ns skipped: {type(exc).__name__}: {exc}"
                log.warning(msg)
                errors.append(msg)
                produced = []
            if sink is not None and produced:
                lm_ids, lm_pts, _ = est.landmarks(sync=False)
                produced[-1] = dataclasses.replace(produced[-1], landmark_ids=lm_ids, landmarks_world=lm_pts)
                for s in produced:
                    sink.on_estimate(s, {"solve_ms": s.solve_ms, "num_landmarks": len(lm_ids)})
        bar.update(n_done, n_kf)
    bar.close()
    online_states = est.states() if refine else []  # kept beside the refined answer, for comparison
    refine_info = est.finish(refine)
    states = est.states()
    ids, pts, nobs = est.landmarks()
    rgb = np.array([colours.get(int(j) & _TRACK_MASK, (200, 200, 200)) for j in ids], np.uint8).reshape(-1, 3)
    wall = time.perf_counter() - t_start
    span_s = (t_last - t_first) * 1e-9 if t_first is not None else 0.0
    tm = np.asarray(est.timings_ms)
    summary: dict[str, Any] = {
        "status": "ok" if states else "not_initialised",
        "capture": str(cap.root),
        "format": cap.format,
        "num_frames": n_done,
        "num_keyframes": n_kf,
        "num_states": len(states),
        "num_landmarks": int(len(ids)),
        "initialisation": est.init_kind,
        "num_zero_velocity_updates": est.num_still,
        "num_track_splits": est.num_splits,
        "num_reidentified": est.num_reidentified,
        "num_loop_flushes": est.num_loop_flushes,
        "num_position_factors": est.anchor.num_factors if est.anchor is not None else 0,
        "span_s": span_s,
        "wall_time_s": wall,
        "realtime_factor": span_s / wall if wall > 0 else 0.0,
        "cpu_time_s": time.process_time() - cpu_start,  # this process only (the machine may be shared)
        "keyframe_ms": {
            "median": float(np.median(tm)) if tm.size else 0.0,
            "p95": float(np.percentile(tm, 95)) if tm.size else 0.0,
            "max": float(tm.max()) if tm.size else 0.0,
            "per_keyframe": [round(float(x), 2) for x in tm],
        },
        "recoveries": est.recoveries,
        "refine": refine_info,
        "warnings": list(cap.warnings) + est.warnings + errors,
        "config": cfg.to_dict(),
    }
    outputs.write_run_json(out / "run.json", summary)
    if sink is not None:
        sink.close()
    if not states:
        raise EstimationError(f"{cap.root}: the estimator never initialised ({n_kf} keyframes); see {out / 'run.json'}")
    outputs.write_trajectory(out / "trajectory.tum", states)
    if online_states:
        outputs.write_trajectory(out / "trajectory_online.tum", online_states)
    outputs.write_states(out / "states.csv", states)
    outputs.write_landmarks_ply(out / "landmarks.ply", pts, rgb, nobs)
    log.info(
        "%d keyframes, %d landmarks, %.1f s wall (%.2fx real time), %d recoveries",
        len(states),
        len(ids),
        wall,
        summary["realtime_factor"],
        len(est.recoveries),
    )
    return summary
