"""The same simulated capture replayed as ASL, ROS 2 bag and MARS logger gives the same trajectory."""

from __future__ import annotations

import numpy as np
import pytest

from tests.writers.phone import write_mars
from tests.writers.ros import write_ros2
from vio.config import load_config
from vio.readers import open_capture
from vio.trajio import read_trajectory

pytest.importorskip("vio.pipeline")


@pytest.mark.slow
def test_asl_ros2_and_mars_give_the_same_trajectory(sim_capture, tmp_path):
    from vio.metrics import evaluate
    from vio.pipeline import run_capture

    asl = sim_capture("orbit", duration_s=3.0)
    ref = open_capture(asl)
    inputs = {"asl": asl, "ros2": write_ros2(ref, tmp_path / "bag"), "mars": write_mars(ref, tmp_path / "mars")}
    cfg = load_config(None, [])
    trajs = {}
    for name, path in inputs.items():
        summary = run_capture(path, tmp_path / f"out_{name}", cfg).summary
        assert summary["status"] == "ok" and summary["format"] == ("asl" if name == "asl" else name)
        trajs[name] = read_trajectory(tmp_path / f"out_{name}" / "trajectory.tum")
    base = trajs["asl"]
    for name in ("ros2", "mars"):
        other = trajs[name]
        np.testing.assert_array_equal(other.t_ns, base.t_ns)
        ate = evaluate(base, other, align="none")["ate_rmse_m"]
        assert ate < 0.010, f"{name}: ATE against the ASL run {ate * 1e3:.2f} mm"
