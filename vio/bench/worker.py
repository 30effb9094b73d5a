"""Child process of `vio bench`: `python -m vio.bench.worker TASK_JSON` simulates one capture or runs one method.

The result goes to `result.json` beside the task file (atomically): `{"capture": ...}` for a simulation,
`{"rows": [...]}` for a method (one results.json row per estimate, scored against the capture's ground truth).
Any exception becomes an `error` in the result; only a hard crash leaves no result (the parent records that).
"""

from __future__ import annotations

import json
import logging
import resource
import sys
import time
import traceback
from pathlib import Path
from typing import Any

import numpy as np

from vio.atomic import atomic_open, write_json
from vio.bench.report import empty_row
from vio.bench.suites import Case, Method, method_from_dict

log = logging.getLogger("vio.bench.worker")

# Alignment of the drift figure and of the error-over-time series, by the method's kind of frame: a VIO's world
# frame is free in the 4 DoF it cannot observe (position and yaw: align those); a method without metric scale
# gets Sim3; a method started from the ground truth's own initial state (imu_only) is already in the ground
# truth's frame and is not aligned, so its error grows from zero as dead reckoning does.
TRACE_ALIGN = {"se3": "posyaw", "sim3": "sim3", "none": "none"}


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far, MiB (Linux reports ru_maxrss in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _write_trace(path: Path, gt, est, metrics: dict) -> None:
    """aligned.csv: t_s (from the estimate's start), aligned x y z (m, world), position error (m)."""
    from vio.metrics import associate

    i_gt, i_est = associate(gt, est)
    a = metrics["alignment"]
    s, R, t = a["scale"], np.asarray(a["R"]), np.asarray(a["t"])
    p = s * est.p_world[i_est] @ R.T + t
    err = np.linalg.norm(p - gt.p_world[i_gt], axis=1)
    t_s = (est.t_ns[i_est] - gt.t_ns[0]) * 1e-9
    with atomic_open(path, "w", encoding="utf-8", newline="\n") as f:
        f.write("t_s,x,y,z,err_m\n")
        for row in zip(t_s, p[:, 0], p[:, 1], p[:, 2], err, strict=True):
            f.write(",".join(f"{v:.6f}" for v in row) + "\n")


def score(case: Case, res, gt, capture_duration_s: float, folder: Path) -> dict[str, Any]:
    """A results.json row for one MethodOutput `res` against the ground-truth Trajectory `gt`.

    Writes `aligned_<method>.csv` (the error trace) and `metrics_<method>.json` (all metrics, RPE) into `folder`.
    """
    from vio.metrics import evaluate
    from vio.trajio import read_trajectory

    est = read_trajectory(res.trajectory)
    row = empty_row(case, res.method)
    m_sim3 = evaluate(gt, est, align="sim3")
    row["ate_sim3_m"] = m_sim3["ate_rmse_m"]
    row["scale"] = m_sim3["scale"]
    if res.align == "se3":  # a metric method states its scale's uncertainty (vision_only has no metric scale)
        row["scale_sigma_rel"] = (res.info or {}).get("scale_sigma_rel")
    metrics = {"sim3": m_sim3}
    if res.align != "sim3":  # a metric method: SE3 and 4-DoF alignments are meaningful
        metrics["se3"] = evaluate(gt, est, align="se3")
        metrics["posyaw"] = evaluate(gt, est, align="posyaw")
        row["ate_se3_m"] = metrics["se3"]["ate_rmse_m"]
        row["ate_posyaw_m"] = metrics["posyaw"]["ate_rmse_m"]
    if res.align == "none":
        metrics["none"] = evaluate(gt, est, align="none")
    trace = metrics[TRACE_ALIGN[res.align]]
    row["drift_pct"] = trace["drift_pct"]
    row["rtf"] = res.wall_s / capture_duration_s if capture_duration_s > 0 else None
    if res.latencies_ms is not None and np.isfinite(res.latencies_ms).any():
        lat = res.latencies_ms[np.isfinite(res.latencies_ms)]
        row["latency_ms_p50"] = float(np.percentile(lat, 50))
        row["latency_ms_p95"] = float(np.percentile(lat, 95))
        row["latency_ms_max"] = float(lat.max())
    row["peak_rss_mb"] = peak_rss_mb()
    _write_trace(folder / f"aligned_{res.method}.csv", gt, est, trace)
    write_json(folder / f"metrics_{res.method}.json", {"row": row, "info": res.info, "metrics": metrics})
    return row


def run_method(case: Case, method: Method, capture: Path, out: Path) -> list[dict[str, Any]]:
    from vio.bench import methods
    from vio.readers import open_capture
    from vio.trajio import Trajectory

    if method.kind not in ("imu_only", "vio", "vision_only", "model"):
        raise ValueError(f"unknown method kind {method.kind!r}")
    cap = open_capture(capture, needs=())  # scoring reads the ground truth and the frame span only
    if cap.ground_truth is None:
        raise ValueError(f"{capture}: no ground truth to score against")
    gt = Trajectory.from_groundtruth(cap.ground_truth)
    span_ns = cap.frame_t_ns[-1] - cap.frame_t_ns[0] if cap.num_frames > 1 else gt.t_ns[-1] - gt.t_ns[0]
    duration_s = float(span_ns) * 1e-9
    if method.kind == "model":
        from vio.bench.model_method import run_model

        return run_model(case, method, capture, out, lambda o: score(case, o, gt, duration_s, out))
    if method.kind == "imu_only":
        outputs = methods.run_imu_only(capture, out)
    elif method.kind == "vio":
        outputs = methods.run_vio(capture, out, method)
    else:
        outputs = methods.run_vision_only(capture, out, method)
    rows = []
    for o in outputs:
        try:
            rows.append(score(case, o, gt, duration_s, out))
        except Exception as exc:  # noqa: BLE001 - one unscorable estimate must not lose the others
            row = empty_row(case, o.method)
            row["error"] = f"scoring failed: {exc.__class__.__name__}: {exc}"
            rows.append(row)
    return rows


def main(task_path: str) -> int:
    from vio.log import setup_logging

    setup_logging(0)
    task_file = Path(task_path)
    task = json.loads(task_file.read_text(encoding="utf-8"))
    case = Case(**task["case"])
    t0 = time.perf_counter()
    result: dict[str, Any]
    try:
        if task["kind"] == "simulate":
            from vio.sim.api import simulate
            from vio.sim.phases import PhasedMotion

            phases = {"phases": PhasedMotion(**case.phases)} if case.phases else {}
            simulate(
                case.scenario,
                task["capture"],
                seed=case.seed,
                duration_s=case.duration_s,
                imu_grade=case.imu,
                overwrite=True,
                images=case.images,
                **({"part": case.part, "stills_hz": case.stills_hz} if case.stills_hz > 0 else {}),
                **phases,
            )
            result = {"capture": task["capture"]}
        else:
            fields = task["method"]
            method = method_from_dict(fields)
            out = Path(task["out"])
            out.mkdir(parents=True, exist_ok=True)
            result = {"rows": run_method(case, method, Path(task["capture"]), out)}
    except Exception as exc:  # noqa: BLE001 - any failure becomes a row, never a crash of the bench
        traceback.print_exc()
        msg = f"{exc.__class__.__name__}: {exc}".splitlines()[0][:300]
        result = {"error": msg}
        if task["kind"] == "method":
            m = task["method"]
            names = [m["name"]] + (["batch"] if m.get("refine") else [])
            result["rows"] = [{**empty_row(case, n), "error": msg} for n in names]
    result["wall_s"] = time.perf_counter() - t0
    result["peak_rss_mb"] = peak_rss_mb()
    write_json(task_file.parent / "result.json", result)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
