"""One function per benchmarked method. Each reads a capture folder and writes its estimate into `out`.

Every function returns a list of `MethodOutput` (a `vio` run with refinement yields two: the online estimate
`vio` and the batch optimum `batch` of the same graph). Wall times cover the estimation only, not the capture
reading that every method shares.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vio.bench.suites import Method
from vio.errors import EstimationError
from vio.trajio import write_tum

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class MethodOutput:
    method: str  # results.json `method`
    trajectory: Path  # TUM file of the body pose in the method's world frame
    wall_s: float  # wall time of the estimation, s
    latencies_ms: np.ndarray | None = None  # (K,) per-keyframe update time, ms (online methods only)
    align: str = "se3"  # the method's frame: se3 (metric, free position+yaw), sim3 (no scale), none (GT's frame)
    info: dict | None = None  # method-specific facts (initialisation, ZUPT count, warnings)


def gt_state_at(capture_gt, t_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth (world_T_body 4x4, v_world (3,)) at time t_ns (nearest sample at or after, else last)."""
    i = min(int(np.searchsorted(capture_gt.t_ns, t_ns)), len(capture_gt) - 1)
    return capture_gt.world_T_body(i), np.asarray(capture_gt.v_world[i], float)


def run_imu_only(capture_dir: Path, out: Path) -> list[MethodOutput]:
    """The thesis's method: gravity-aligned strapdown integration with a filterpy Kalman filter (see imu_only)."""
    from vio.bench.imu_only import dead_reckon
    from vio.readers import open_capture

    cap = open_capture(capture_dir, needs=("imu",))
    if cap.imu is None or cap.ground_truth is None:
        raise EstimationError(f"{capture_dir}: imu_only needs an IMU stream and ground truth (for the heading)")
    T0, v0 = gt_state_at(cap.ground_truth, int(cap.imu.t_ns[0]))
    t0 = time.perf_counter()
    res = dead_reckon(cap.imu, cap.imu_calib, T0, v0)
    wall = time.perf_counter() - t0
    path = out / "trajectory.tum"
    write_tum(path, res.trajectory)
    info = {"init": res.init, "zupt_count": res.zupt_count, "static_s": res.static_s}
    return [MethodOutput("imu_only", path, wall, None, "none", info)]


def _latencies(run: dict) -> np.ndarray | None:
    """Per-keyframe update times (ms) from a run.json (`keyframe_ms.per_keyframe`)."""
    per = (run.get("keyframe_ms") or {}).get("per_keyframe")
    return np.asarray(per, float) if isinstance(per, list) and per else None


def _pipeline(capture_dir: Path, out: Path, method: Method) -> tuple[dict, float]:
    """One `run_capture` into `out` with the progress bar off; returns (run.json, wall time s).

    With `method.refine`, the pipeline writes the online estimate (the smoother's estimate of every keyframe just
    before the batch refinement replaces it) to `out/trajectory_online.tum` beside the refined `trajectory.tum`.
    """
    from vio.config import load_config
    from vio.pipeline import run_capture

    cfg = load_config(None, ["run.progress=false", *method.overrides], method.presets)
    cfg = dataclasses.replace(cfg, run=dataclasses.replace(cfg.run, refine=method.refine))
    (out / "trajectory_online.tum").unlink(missing_ok=True)
    t0 = time.perf_counter()
    run_capture(capture_dir, out, cfg)
    wall = time.perf_counter() - t0
    run = json.loads((out / "run.json").read_text(encoding="utf-8"))
    if run.get("status") != "ok":
        log.warning("%s: run status %s", out, run.get("status"))
    return run, wall


def _info(run: dict) -> dict:
    keys = ("status", "initialisation", "num_keyframes", "num_states", "num_landmarks", "recoveries", "refine")
    info = {k: run[k] for k in keys if k in run}
    sigma = (run.get("scale") or {}).get("sigma_rel")  # the run's own 1-sigma relative scale uncertainty
    if sigma is not None:
        info["scale_sigma_rel"] = sigma
    return info


def run_vio(capture_dir: Path, out: Path, method: Method) -> list[MethodOutput]:
    """The online estimator as shipped (`vio.pipeline.run_capture`); with `refine`, also its batch optimum.

    The online estimate is the smoother's final estimate of every keyframe (trajectory.tum of a run without
    `--refine`); its wall time excludes any refinement. The batch optimum is Levenberg-Marquardt over the same
    factor graph after the online pass; one run gives both (the pipeline saves the online trajectory of a refined
    run as `trajectory_online.tum`).
    """
    name = method.name
    run, wall = _pipeline(capture_dir, out, method)
    if not method.refine:
        return [MethodOutput(name, out / "trajectory.tum", wall, _latencies(run), "se3", _info(run))]
    refine_s = float((run.get("refine") or {}).get("refine_s", 0.0))
    if not (run.get("refine") or {}).get("refined", False) or not (out / "trajectory_online.tum").exists():
        raise EstimationError(f"{out}: the batch refinement did not run or failed; see run.json warnings")
    online = MethodOutput(name, out / "trajectory_online.tum", wall - refine_s, _latencies(run), "se3", _info(run))
    return [online, MethodOutput("batch", out / "trajectory.tum", wall, None, "se3", _info(run))]


def run_vision_only(capture_dir: Path, out: Path, method: Method) -> list[MethodOutput]:
    """The same frontend and graph without the IMU (the method's presets, `vision_only`: projection factors only,
    two-view start with unit baseline, PnP pose guesses); scale is unobservable, so it is scored after Sim3
    alignment."""
    res = run_vio(capture_dir, out, dataclasses.replace(method, refine=False))
    return [MethodOutput(r.method, r.trajectory, r.wall_s, r.latencies_ms, "sim3", r.info) for r in res]
