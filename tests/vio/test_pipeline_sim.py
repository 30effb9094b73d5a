"""`vio run` on a rendered synthetic orbit: tracker + keyframes + preintegration + estimator, scored against truth."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.conftest import ROOT
from vio.config import load_config
from vio.metrics import evaluate
from vio.pipeline import run_capture
from vio.trajio import read_trajectory


@pytest.fixture(scope="module")
def orbit_run(sim_capture, tmp_path_factory):
    capture = sim_capture("orbit", 6.0)
    out = tmp_path_factory.mktemp("orbit_run")
    summary = run_capture(capture, out, load_config(None, ["run.progress=false", "run.refine=true"])).summary
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
    """Issue 5's synthetic target capture, whole: ATE (SE3) < 5 mm (12.4 mm before landmark re-identification closed
    the loops between rings) and a scale error inside the run's own 95 % interval. Measured on this seed: 2.27 mm,
    -0.41 % at a stated sigma of 0.47 %, 284 tracks re-identified in 24 flushes (anchored tracks and a 0.5 px sigma;
    before them 4.45 mm, -0.59 % at 0.57 %, and over 300 re-identified: tracks live longer now). A fixed 0.5 %
    bound was this one seed's luck: with a perfect camera the phone IMU allows 0.41 % (1 sigma) on this motion, and
    over ten held-out seeds the median |error| is 0.34 % (401-410; docs/BENCHMARKS.md, "Anchored tracks")."""
    capture = sim_capture("orbit", 60.0)
    summary = run_capture(capture, tmp_path, load_config(None, ["run.progress=false"])).summary
    assert summary["status"] == "ok" and summary["span_s"] > 59.0
    gt = read_trajectory(capture / "mav0" / "state_groundtruth_estimate0" / "data.csv")
    est = read_trajectory(tmp_path / "trajectory.tum")
    sim3 = evaluate(gt, est, align="sim3")
    sigma = summary["scale"]["sigma_rel"]
    assert 0.002 < sigma < 0.01  # the graph's statement: near the accelerometer's limit, not inflated
    assert abs(sim3["scale"] - 1.0) < 1.96 * sigma
    assert sim3["coverage_s"] > 58.0
    assert evaluate(gt, est, align="se3")["ate_rmse_m"] < 0.005
    assert summary["num_reidentified"] > 200 and summary["num_loop_flushes"] > 10


def test_re_identified_tracks_are_the_same_surface_points(sim_capture, tmp_path):
    """The simulator as oracle for loop closure: on a quick orbit that comes round to its first ring's views
    from the second ring, each re-identified track's pixel and the first view of the landmark it was given, cast
    into the true scene from the true poses, hit the same surface point (measured: median 3.2 mm, 89 % within
    1 cm; a corner 1 cm away is ~10 px at the orbit's distance, inside the 20 px search radius)."""
    from vio.readers import open_capture
    from vio.sim.api import load_scenario
    from vio.sim.render import Renderer

    quick = ROOT / "data" / "synthetic" / "orbit_quick.yaml"
    capture = sim_capture(str(quick), 10.0)
    result = run_capture(capture, tmp_path, load_config(None, ["run.progress=false"]))
    events = result.stats.reidentifications
    assert result.summary["num_reidentified"] == len(events) >= 100
    cap = open_capture(capture)
    renderer = Renderer(load_scenario(str(quick), seed=0).scene, cap.camera)
    gt = read_trajectory(capture / "mav0" / "state_groundtruth_estimate0" / "data.csv")
    world_T_body = gt.world_T_body()
    K = cap.camera.K

    def surface(t_ns: int, uv_distorted: np.ndarray) -> np.ndarray:
        i = int(np.argmin(np.abs(gt.t_ns - t_ns)))
        return renderer.surface_points(world_T_body[i] @ cap.camera.body_T_cam, uv_distorted[None])[0][0]

    dist = []
    for ev in events:  # the landmark's first view (undistorted pixels) is its own track's
        xn = (ev.first_uv_px - K[:2, 2]) / np.diag(K)[:2]
        first = cap.camera.project(np.array([[xn[0], xn[1], 1.0]]))[0]
        dist.append(np.linalg.norm(surface(ev.t_ns, ev.uv_px) - surface(ev.first_t_ns, first)))
    dist = np.array(dist)
    assert np.median(dist) < 0.005 and np.mean(dist < 0.01) > 0.8, np.percentile(dist, [50, 80, 95])
