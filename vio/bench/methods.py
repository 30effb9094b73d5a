"""One function per benchmarked method. Each reads a capture folder and writes its estimate into `out`.

Every function returns a list of `MethodOutput` (a `vio` run with refinement yields two: the online estimate
`vio` and the batch optimum `batch` of the same graph). Wall times cover the estimation only, not the capture
reading that every method shares.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vio.errors import EstimationError
from vio.trajio import Trajectory, read_trajectory, write_tum

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class MethodOutput:
    method: str  # results.json `method`
    trajectory: Path  # TUM file of the body pose in the method's world frame
    wall_s: float  # wall time of the estimation, s
    latencies_ms: np.ndarray | None = None  # (K,) per-keyframe update time, ms (online methods only)
    align: str = "se3"  # the alignment under which the method's headline ATE is meaningful
    info: dict | None = None  # method-specific facts (initialisation, ZUPT count, warnings)


def gt_state_at(capture_gt, t_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth (world_T_body 4x4, v_world (3,)) at time t_ns (nearest sample at or after, else last)."""
    i = min(int(np.searchsorted(capture_gt.t_ns, t_ns)), len(capture_gt) - 1)
    return capture_gt.world_T_body(i), np.asarray(capture_gt.v_world[i], float)


def run_imu_only(capture_dir: Path, out: Path) -> list[MethodOutput]:
    """The thesis's method: gravity-aligned strapdown integration with a filterpy Kalman filter (see imu_only)."""
    from vio.bench.imu_only import dead_reckon
    from vio.capture import read_asl

    cap = read_asl(capture_dir)
    if cap.imu is None or cap.ground_truth is None:
        raise EstimationError(f"{capture_dir}: imu_only needs an IMU stream and ground truth (for the heading)")
    T0, v0 = gt_state_at(cap.ground_truth, int(cap.imu.t_ns[0]))
    t0 = time.perf_counter()
    res = dead_reckon(cap.imu, cap.imu_calib, T0, v0)
    wall = time.perf_counter() - t0
    path = out / "trajectory.tum"
    write_tum(path, res.trajectory)
    info = {"init": res.init, "zupt_count": res.zupt_count, "static_s": res.static_s}
    return [MethodOutput("imu_only", path, wall, None, "se3", info)]


def _latencies(run: dict) -> np.ndarray | None:
    """Per-keyframe update times (ms) from a run.json, whichever of the known layouts it uses."""
    for key in ("keyframe_timings_ms", "per_keyframe_ms", "solve_ms"):
        v = run.get(key) or (run.get("timings") or {}).get(key)
        if isinstance(v, list) and v:
            return np.asarray(v, float)
    kfs = run.get("keyframes") or (run.get("timings") or {}).get("keyframes")
    if isinstance(kfs, list) and kfs and isinstance(kfs[0], dict):
        for key in ("total_ms", "update_ms", "solve_ms", "latency_ms"):
            if key in kfs[0]:
                return np.asarray([k.get(key, np.nan) for k in kfs], float)
    return None


def run_vio(
    capture_dir: Path, out: Path, name: str = "vio", overrides: tuple[str, ...] = (), refine: bool = False
) -> list[MethodOutput]:
    """The online estimator as shipped (`vio.pipeline.run_capture`); with `refine`, also its batch optimum."""
    from vio.config import load_config
    from vio.pipeline import run_capture

    cfg = load_config(None, list(overrides))
    t0 = time.perf_counter()
    run_capture(capture_dir, out, cfg, refine=refine or None)
    wall = time.perf_counter() - t0
    run = json.loads((out / "run.json").read_text(encoding="utf-8"))
    if run.get("status") not in (None, "ok", "success", "completed"):
        log.warning("%s: run status %s", out, run.get("status"))
    lat = _latencies(run)
    info = {k: run[k] for k in ("status", "num_keyframes", "num_landmarks", "recoveries") if k in run}
    outputs = [MethodOutput(name, _online_path(out, refine), wall, lat, "se3", info)]
    if refine:
        outputs.append(MethodOutput("batch", _refined_path(out), wall, None, "se3", info))
    return outputs


def _online_path(out: Path, refine: bool) -> Path:
    for cand in ("trajectory_online.tum", "trajectory.tum"):
        if (out / cand).exists() and (refine is False or cand != "trajectory.tum" or not _has_split(out)):
            return out / cand
    raise EstimationError(f"{out}: the pipeline wrote no trajectory")


def _has_split(out: Path) -> bool:
    return (out / "trajectory_online.tum").exists() or (out / "trajectory_refined.tum").exists()


def _refined_path(out: Path) -> Path:
    for cand in ("trajectory_refined.tum", "trajectory_batch.tum"):
        if (out / cand).exists():
            return out / cand
    if (out / "trajectory_online.tum").exists() and (out / "trajectory.tum").exists():
        return out / "trajectory.tum"
    raise EstimationError(f"{out}: the pipeline wrote no separate refined trajectory")


def run_vision_only(capture_dir: Path, out: Path, overrides: tuple[str, ...] = ()) -> list[MethodOutput]:
    """The same frontend and graph without IMU factors; scale is unobservable, so it is scored after Sim3."""
    from vio.config import BackendConfig

    if "use_imu" not in BackendConfig.__dataclass_fields__:
        raise EstimationError("the backend has no IMU-free mode (BackendConfig.use_imu)")
    res = run_vio(capture_dir, out, "vision_only", (*overrides, "backend.use_imu=false"), refine=False)
    return [MethodOutput(r.method, r.trajectory, r.wall_s, r.latencies_ms, "sim3", r.info) for r in res]


def read_estimate(path: Path) -> Trajectory:
    return read_trajectory(path)
