"""Capture phases around the scenario's motion (issue 15): still start, brisk excitation, still end."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import yaml

from tests.conftest import ROOT
from vio.errors import SimulationError
from vio.readers.asl import read_asl
from vio.sim.api import load_scenario
from vio.sim.phases import EXCITE_RMS_M_S2, RAMP_S, PhasedMotion, phased, scenario_clock

VIO = [sys.executable, "-m", "vio.cli"]


def test_no_phase_leaves_the_scenario_untouched():
    plain = load_scenario("orbit", seed=3, duration_s=4.0, imu_grade_name="ideal")
    none = load_scenario("orbit", seed=3, duration_s=4.0, imu_grade_name="ideal", phases=PhasedMotion())
    t = np.linspace(0.0, 4.0, 41)
    assert none.duration_s == 4.0 and none.phases is None and none.motion_s is None
    for a, b in zip(plain.trajectory.pose(t), none.trajectory.pose(t), strict=True):
        np.testing.assert_array_equal(a, b)
    fn = plain.trajectory.pose
    assert phased(fn, PhasedMotion(), 4.0, np.random.default_rng(0)) is fn


def test_the_clock_covers_the_motion_once_and_rests_at_both_ends():
    t = np.linspace(-1.0, 20.0, 4201)
    tau = scenario_clock(t, 3.0, 10.0)
    assert tau[t <= 3.0].max() == 0.0 and tau[t >= 3.0 + 10.0 + RAMP_S].min() == pytest.approx(10.0)
    assert np.all(np.diff(tau) >= -1e-12)  # never runs backwards
    rate = np.gradient(tau, t)
    assert rate[(t > 3.0 + RAMP_S + 0.01) & (t < 13.0 - 0.01)] == pytest.approx(1.0, abs=1e-9)


def test_phases_of_an_orbit_are_still_then_brisk_then_the_orbit():
    """Still at the first pose (zero velocity and acceleration), shaking at about 5.6 m/s^2 RMS, then the orbit
    itself from its first pose to its last, then still at the last pose."""
    base = load_scenario("orbit", seed=5, duration_s=6.0, imu_grade_name="ideal")
    m = PhasedMotion(still_start_s=2.0, excite_s=4.0, still_end_s=1.5)
    sc = load_scenario("orbit", seed=5, duration_s=6.0, imu_grade_name="ideal", phases=m)
    assert sc.motion_s == 6.0 and sc.duration_s == pytest.approx(2.0 + 4.0 + 6.0 + RAMP_S + 1.5)
    t = np.arange(0.0, sc.duration_s, 0.005)
    s = sc.trajectory.sample(t)
    still = (t < 2.0) | (t > sc.duration_s - 1.5)
    assert np.abs(s.v_world[still]).max() < 1e-9 and np.abs(s.a_world[still]).max() < 1e-6
    assert np.abs(s.omega_body[t < 2.0 + 4.0]).max() < 1e-9  # the shaking translates only
    shake = (t > 2.5) & (t < 5.5)
    rms = np.sqrt(np.mean(np.sum(s.a_world[shake] ** 2, axis=1)))
    assert rms == pytest.approx(EXCITE_RMS_M_S2, rel=0.05)
    p0, R0 = base.trajectory.pose(np.array([0.0, 6.0]))
    p1, R1 = sc.trajectory.pose(np.array([0.0, sc.duration_s]))
    np.testing.assert_allclose(p1, p0, atol=1e-12)
    np.testing.assert_allclose(R1, R0, atol=1e-12)


def test_the_same_seed_shakes_the_same_way_and_another_seed_does_not():
    m = PhasedMotion(excite_s=3.0)
    t = np.linspace(0.0, 3.0, 61)
    a = load_scenario("figure8", seed=7, duration_s=2.0, phases=m).trajectory.pose(t)[0]
    b = load_scenario("figure8", seed=7, duration_s=2.0, phases=m).trajectory.pose(t)[0]
    c = load_scenario("figure8", seed=8, duration_s=2.0, phases=m).trajectory.pose(t)[0]
    np.testing.assert_array_equal(a, b)
    assert np.abs((a - a[0]) - (c - c[0])).max() > 1e-3


@pytest.mark.parametrize(
    "motion, match",
    [
        (PhasedMotion(still_start_s=-1.0), "--still-start must be between"),
        (PhasedMotion(excite_s=0.4), "--excite must be 0 or at least"),
        (PhasedMotion(still_end_s=float("nan")), "--still-end must be between"),
    ],
)
def test_bad_phase_lengths_are_refused(motion, match):
    with pytest.raises(SimulationError, match=match):
        load_scenario("orbit", seed=0, duration_s=2.0, phases=motion)


def test_cli_simulate_with_phases(tmp_path):
    out = tmp_path / "p"
    cmd = [*VIO, "simulate", "orbit", "--out", str(out), "--duration", "1", "--no-images", "--imu", "ideal"]
    r = subprocess.run(
        [*cmd, "--still-start", "1", "--excite", "2", "--still-end", "0.5"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr
    cap = read_asl(out)
    assert cap.imu.t_ns[-1] - cap.imu.t_ns[0] == pytest.approx((1 + 2 + 1 + RAMP_S + 0.5) * 1e9, abs=1e7)
    acc = np.asarray(cap.imu.acc)
    rest = acc[: int(0.9 * 200)]  # the first 0.9 s: still, the accelerometer reads gravity alone
    assert np.linalg.norm(rest, axis=1) == pytest.approx(9.81, abs=1e-6)
    phases = yaml.safe_load((out / "scene" / "scene.yaml").read_text())["phases"]
    assert phases["still_start_s"] == 1.0 and phases["excite_s"] == 2.0 and phases["motion_start_s"] == 3.0
    bad = subprocess.run(
        [*VIO, "simulate", "calibration", "--out", str(tmp_path / "c"), "--excite", "2"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
    )
    assert bad.returncode != 0 and "not available for the calibration scenario" in bad.stderr
    assert "Traceback" not in bad.stderr and len(bad.stderr.strip().splitlines()) == 1
