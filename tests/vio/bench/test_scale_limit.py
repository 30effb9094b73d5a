"""The accelerometer's limit on the metric scale (vio.bench.scale_limit): the filter's sigma against the closed form
and against the spread of a least-squares scale over noise draws; the module as a command on a simulated capture."""

from __future__ import annotations

import subprocess
import sys

import numpy as np

from vio.bench.scale_limit import scale_limit, scale_sigma
from vio.records import GroundTruth, ImuCalib

RATE_HZ = 200.0
PHONE = ImuCalib(0.002, 0.015, 5e-5, 1e-3, RATE_HZ)


def _sway(duration_s: float) -> GroundTruth:
    """Body axes fixed to the world; velocity sin waves on x (0.3 Hz) and y (0.7 Hz), accelerations about 0.5 m/s^2."""
    t = np.arange(0.0, duration_s, 1.0 / RATE_HZ)
    n = len(t)
    v = np.column_stack([0.25 * np.sin(2 * np.pi * 0.3 * t), 0.1 * np.sin(2 * np.pi * 0.7 * t), np.zeros(n)])
    p = np.cumsum(v, axis=0) / RATE_HZ
    q = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    return GroundTruth((t * 1e9).astype(np.int64), p, q, v, np.zeros((n, 3)), np.zeros((n, 3)))


def test_filter_sigma_matches_the_closed_form():
    lim = scale_limit(_sway(20.0), PHONE)
    assert abs(lim.sigma_rel / lim.sigma_rel_closed - 1.0) < 0.02
    assert lim.sigma_rel_bias_known <= lim.sigma_rel
    longer = scale_limit(_sway(40.0), PHONE)
    assert abs(lim.sigma_rel / longer.sigma_rel - np.sqrt(2.0)) < 0.05  # twice the excitation: sigma / sqrt(2)


def test_filter_sigma_is_the_spread_of_the_least_squares_scale():
    """Simulator as oracle: y = s a + b + n with a constant unknown bias; the least-squares s over 400 noise draws
    scatters by the filter's sigma (no bias walk in the calibration, so the two models agree)."""
    calib = ImuCalib(0.002, 0.015, 5e-5, 1e-12, RATE_HZ)
    gt = _sway(10.0)
    t_s = (gt.t_ns - gt.t_ns[0]) * 1e-9
    a = np.gradient(gt.v_world, t_s, axis=0)
    sigma = scale_sigma(a, 1.0 / RATE_HZ, calib, bias_sigma=10.0)
    rng = np.random.default_rng(7)
    n = len(a)
    # unknowns [s, b_x, b_y, b_z]; rows per sample and axis
    A = np.zeros((3 * n, 4))
    A[:, 0] = a.ravel()
    A[:, 1:] = np.tile(np.eye(3), (n, 1))
    pinv = np.linalg.pinv(A)
    noise = rng.normal(0.0, calib.accelerometer_noise_density * np.sqrt(RATE_HZ), (400, 3 * n))
    y = a.ravel() * 1.0 + np.tile([0.05, -0.03, 0.02], n) + noise
    s_hat = (pinv @ y.T)[0]
    assert abs(np.std(s_hat) / sigma - 1.0) < 0.12  # 400 draws: the std is known to about 4 %


def test_command_on_a_simulated_capture(sim_capture):
    cap = sim_capture("orbit", 3.0, images=False)
    res = subprocess.run(
        [sys.executable, "-m", "vio.bench.scale_limit", str(cap)], capture_output=True, text=True, check=False
    )
    assert res.returncode == 0, res.stderr
    row = res.stdout.strip().splitlines()[-1].split(" | ")
    assert len(row) == 6 and float(row[1]) > 2.9 and all(float(x) > 0 for x in row[2:])
    bad = subprocess.run(
        [sys.executable, "-m", "vio.bench.scale_limit", str(cap / "nope")], capture_output=True, text=True, check=False
    )
    assert bad.returncode == 2 and len(bad.stdout.strip().splitlines()) == 2 and "Traceback" not in bad.stderr
