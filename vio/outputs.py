"""The run's output files, each written atomically: trajectory.tum, states.csv, landmarks.ply, run.json (built
here from the estimator's stats, the pipeline's counts and the run's health; written last, so that a run.json with
a final status means the other files are this run's)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from vio.atomic import atomic_open, write_json
from vio.capture import Capture
from vio.config import Config
from vio.errors import EstimationError
from vio.geometry import R_to_quat_wxyz
from vio.health import RunHealth
from vio.records import EstimatorStats, LandmarkMap, StateEstimate
from vio.trajio import Trajectory, write_tum

RUN_FILES = ("run.json", "trajectory.tum", "trajectory_online.tum", "states.csv", "landmarks.ply")  # what a run writes
STATES_HEADER = "t_ns,px,py,pz,qw,qx,qy,qz,vx,vy,vz,bwx,bwy,bwz,bax,bay,baz"


def trajectory_of(states: list[StateEstimate]) -> Trajectory:
    """Body (IMU) poses in world of the given keyframe states. Raises EstimationError (one line) when the estimate
    diverged: a position beyond 1e6 m or not finite, or a rotation that is not one (the solver blew up)."""
    t = np.array([s.t_ns for s in states], np.int64)
    p = np.array([s.world_T_body[:3, 3] for s in states]).reshape(-1, 3)
    R = np.array([s.world_T_body[:3, :3] for s in states]).reshape(-1, 3, 3)
    with np.errstate(invalid="ignore", over="ignore"):
        bad = ~np.isfinite(p).all(axis=1) | (np.abs(p) > 1e6).any(axis=1) | ~np.isfinite(R).all(axis=(1, 2))
        bad |= np.abs(np.einsum("nij,nkj->nik", R, R) - np.eye(3)).max(axis=(1, 2), initial=0.0) > 1e-3
    if bad.any():
        k = int(np.argmax(bad))
        raise EstimationError(
            f"the estimate diverged: keyframe {k} (t = {t[k] * 1e-9:.3f} s) has no valid pose "
            f"({int(bad.sum())} of {len(states)} keyframes); nothing written"
        )
    q = (
        R_to_quat_wxyz(np.array([s.world_T_body[:3, :3] for s in states])).reshape(-1, 4)
        if states
        else np.zeros((0, 4))
    )
    return Trajectory(t, p, q)


def write_trajectory(path: str | Path, states: list[StateEstimate]) -> None:
    """trajectory.tum: `t_s x y z qx qy qz qw`, IMU body in world, metres."""
    write_tum(path, trajectory_of(states))


def write_states(path: str | Path, states: list[StateEstimate]) -> None:
    """states.csv: t_ns, position (m), q_wxyz, velocity (m/s, world), gyro bias (rad/s), accel bias (m/s^2)."""
    traj = trajectory_of(states)
    with atomic_open(path, "w", encoding="utf-8", newline="\n") as f:
        f.write(STATES_HEADER + "\n")
        for s, q in zip(states, traj.q_wxyz, strict=True):
            vals = (*s.world_T_body[:3, 3], *q, *s.v_world, *s.bias_gyro, *s.bias_acc)
            f.write(f"{int(s.t_ns)}," + ",".join(f"{v:.9g}" for v in vals) + "\n")


def write_landmarks_ply(path: str | Path, p_world: np.ndarray, rgb: np.ndarray, num_obs: np.ndarray) -> None:
    """landmarks.ply (ASCII): x y z (m, world), red green blue (uint8), observation count per point."""
    p_world = np.asarray(p_world, float).reshape(-1, 3)
    rgb = np.asarray(rgb, np.uint8).reshape(-1, 3)
    num_obs = np.asarray(num_obs, np.int64).reshape(-1)
    header = [
        "ply",
        "format ascii 1.0",
        "comment vio landmarks: world frame, metres",
        f"element vertex {p_world.shape[0]}",
        "property float x",
        "property float y",
        "property float z",
        "property uchar red",
        "property uchar green",
        "property uchar blue",
        "property int observations",
        "end_header",
    ]
    with atomic_open(path, "w", encoding="utf-8", newline="\n") as f:
        f.write("\n".join(header) + "\n")
        for p, c, n in zip(p_world, rgb, num_obs, strict=True):
            f.write(f"{p[0]:.6f} {p[1]:.6f} {p[2]:.6f} {c[0]} {c[1]} {c[2]} {n}\n")


def write_run_json(path: str | Path, summary: dict[str, Any]) -> None:
    write_json(path, summary)


def start_run(out: Path) -> None:
    """Remove the previous run's files (and temporaries a killed run left) from `out`, then write a run.json that
    says `running`: until the run's own run.json replaces it, nothing in `out` looks like a complete run."""
    discard_run(out)
    write_run_json(out / "run.json", stopped_summary("running", "the run has not finished (or was killed)"))


def discard_run(out: Path) -> None:
    """Remove a run's files and the temporaries of an interrupted write from `out`."""
    for name in RUN_FILES:
        (out / name).unlink(missing_ok=True)
        for tmp in out.glob(f".{name}.*.tmp"):
            tmp.unlink(missing_ok=True)


def stopped_summary(status: str, reason: str) -> dict[str, Any]:
    """run.json of a run that is going on (`running`) or ended without an estimate (`interrupted`, `failed`)."""
    return {"status": status, "reasons": [reason]}


@dataclass(frozen=True)
class RunCounts:
    """What the pipeline counted and timed over a run."""

    num_frames: int  # frames read
    num_keyframes: int  # keyframes given to the estimator
    num_states: int  # keyframes with a final estimate
    num_landmarks: int
    span_s: float  # sensor time from the first to the last frame, s
    wall_s: float  # wall time of the whole run, s
    cpu_s: float  # CPU time of this process (the machine may be shared), s


def run_summary(
    cap: Capture,
    cfg: Config,
    stats: EstimatorStats,
    counts: RunCounts,
    refine: dict[str, Any],
    errors: list[str],
    health: RunHealth,
) -> dict[str, Any]:
    """The contents of run.json (`status` and `reasons` from the run's health, vio/health.py)."""
    tm = np.asarray(stats.keyframe_ms)
    return {
        "status": health.status,
        "reasons": list(health.reasons),
        "capture": str(cap.root),
        "format": cap.format,
        "num_frames": counts.num_frames,
        "num_keyframes": counts.num_keyframes,
        "num_states": counts.num_states,
        "num_landmarks": counts.num_landmarks,
        "initialisation": stats.initialisation,
        "num_zero_velocity_updates": stats.num_zero_velocity_updates,
        "num_track_splits": stats.num_track_splits,
        "num_reidentified": stats.num_reidentified,
        "num_loop_flushes": stats.num_loop_flushes,
        "num_landmarks_revived": stats.num_landmarks_revived,
        "num_landmarks_merged": stats.num_landmarks_merged,
        "num_landmarks_archived": stats.num_landmarks_archived,
        "num_blind_adjustments": stats.num_blind_adjustments,
        "num_blind_admitted": stats.num_blind_admitted,
        "smoother_variables_max": max(stats.smoother_variables, default=0),
        "num_position_factors": stats.num_position_factors,
        "span_s": counts.span_s,
        "wall_time_s": counts.wall_s,
        "realtime_factor": counts.span_s / counts.wall_s if counts.wall_s > 0 else 0.0,
        "cpu_time_s": counts.cpu_s,
        "keyframe_ms": {
            "median": float(np.median(tm)) if tm.size else 0.0,
            "p95": float(np.percentile(tm, 95)) if tm.size else 0.0,
            "max": float(tm.max()) if tm.size else 0.0,
            "per_keyframe": [round(float(x), 2) for x in tm],
        },
        "background_ms": _background_summary(stats.background_ms),
        "scale": {
            "sigma_rel": stats.scale_sigma_rel,  # relative standard deviation of the metric scale (graph)
            "pairs": [{"k_a": a, "k_b": b, "distance_m": d, "sigma_m": s} for a, b, d, s in stats.scale_pairs],
        },
        "recoveries": [dataclasses.asdict(r) for r in stats.recoveries],
        "health": health.to_dict(cfg),
        "refine": refine,
        "warnings": list(cap.warnings) + list(stats.warnings) + errors,
        "config": cfg.to_dict(),
    }


def _background_summary(steps: tuple[tuple[float, float], ...]) -> dict[str, Any]:
    """run.json `background_ms`: the smoother's deferred steps between keyframes (`smoother.background`)."""
    if not steps:
        return {"count": 0}
    wall, cpu = np.asarray(steps, float).T
    return {
        "count": len(steps),
        "median": float(np.median(wall)),
        "p95": float(np.percentile(wall, 95)),
        "max": float(wall.max()),
        "cpu_total_s": float(cpu.sum() * 1e-3),
    }


def camera_timing(stats: EstimatorStats, readout_source: str) -> dict[str, Any]:
    """run.json `camera_timing`: the rolling-shutter readout used and the camera-IMU time offset (t_imu = t_cam +
    offset, top row, on top of a calibration's timeshift_cam_imu), fixed or estimated, with its standard error."""
    to = stats.time_offset
    if to is None:
        return {}
    return {
        "readout_s": to.readout_s,
        "readout_source": readout_source,
        "time_offset_s": to.value_s,
        "time_offset_method": (
            "estimated: the images' rotations (PnP) between keyframes against the gyro's, start window then online"
            if to.estimated
            else "fixed: camera.time_offset_s"
        ),
        "time_offset_sigma_s": to.sigma_s,
        "time_offset_initial_s": to.initial_s,
        "time_offset_after_initialisation_s": to.after_initialisation_s,
        "time_offset_keyframes": to.num_keyframes,
        "time_offset_trace": [list(x) for x in to.trace],
        "time_offset_replayed_keyframes": to.replayed_keyframes,
        "time_offset_replayed_span_s": to.replayed_span_s,
        "time_offset_replayed_from_s": None if to.replayed_from_s is None else list(to.replayed_from_s),
    }


def write_estimate(
    out: Path,
    states: list[StateEstimate],
    online_states: list[StateEstimate],
    landmarks: LandmarkMap,
    rgb: np.ndarray,
) -> None:
    """trajectory.tum, states.csv and landmarks.ply (and trajectory_online.tum when the run was refined)."""
    write_trajectory(out / "trajectory.tum", states)
    if online_states:
        write_trajectory(out / "trajectory_online.tum", online_states)
    write_states(out / "states.csv", states)
    write_landmarks_ply(out / "landmarks.ply", landmarks.points_world, rgb, landmarks.num_obs)
