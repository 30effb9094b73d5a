"""`vio run` on a rendered synthetic orbit: tracker + keyframes + preintegration + estimator, scored against truth."""

from __future__ import annotations

import json

import numpy as np
import pytest

from vio.config import load_config
from vio.metrics import evaluate
from vio.pipeline import run_capture
from vio.trajio import read_trajectory


@pytest.fixture(scope="module")
def orbit_run(sim_capture, tmp_path_factory):
    capture = sim_capture("orbit", 6.0)
    out = tmp_path_factory.mktemp("orbit_run")
    summary = run_capture(capture, out, load_config(None, ["run.progress=false"]), refine=True)
    return capture, out, summary


def test_rendered_orbit_is_metric(orbit_run):
    capture, out, summary = orbit_run
    assert summary["status"] == "ok" and summary["initialisation"] == "moving"  # phone captures start moving
    assert summary["recoveries"] == [] and summary["num_landmarks"] > 100
    gt = read_trajectory(capture / "mav0" / "state_groundtruth_estimate0" / "data.csv")
    est = read_trajectory(out / "trajectory.tum")
    se3 = evaluate(gt, est, align="se3")
    sim3 = evaluate(gt, est, align="sim3")
    assert se3["coverage_s"] > 4.0
    assert se3["ate_rmse_m"] < 0.02
    assert abs(sim3["scale"] - 1.0) < 0.02  # metric scale from the IMU, no ruler in the scene


def test_landmark_colours_come_from_the_images(orbit_run):
    _, out, summary = orbit_run
    lines = (out / "landmarks.ply").read_text().splitlines()
    body = [ln.split() for ln in lines[lines.index("end_header") + 1 :]]
    grey = {tuple(r[3:6]) for r in body}
    assert len(body) == summary["num_landmarks"] and len(grey) > 10  # sampled pixels, not one default colour
    run = json.loads((out / "run.json").read_text())
    assert run["refine"]["refined"] is True
    online = read_trajectory(out / "trajectory_online.tum")  # the online answer is kept beside the refined one
    assert np.array_equal(online.t_ns, read_trajectory(out / "trajectory.tum").t_ns)


@pytest.mark.slow
def test_sixty_second_orbit_keeps_metric_scale(sim_capture, tmp_path):
    """Issue 5's synthetic target capture, whole: scale error < 0.5 %. ATE is guarded at 20 mm; the issue asks
    for 5 mm, not reached yet (12.4 mm measured, docs/BENCHMARKS.md: a slow yaw drift without loop closure)."""
    capture = sim_capture("orbit", 60.0)
    summary = run_capture(capture, tmp_path, load_config(None, ["run.progress=false"]))
    assert summary["status"] == "ok" and summary["span_s"] > 59.0
    gt = read_trajectory(capture / "mav0" / "state_groundtruth_estimate0" / "data.csv")
    est = read_trajectory(tmp_path / "trajectory.tum")
    sim3 = evaluate(gt, est, align="sim3")
    assert abs(sim3["scale"] - 1.0) < 0.005
    assert sim3["coverage_s"] > 58.0
    assert evaluate(gt, est, align="se3")["ate_rmse_m"] < 0.020
