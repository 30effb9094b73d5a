"""vio calibrate imu: our Allan deviation against allantools, the simulator's noise recovered, files, bad logs."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from tests.conftest import ROOT
from vio.calibrate.allan import BIAS_INSTABILITY_FACTOR, cluster_sizes, overlapping_adev
from vio.calibrate.imu import imu_noise
from vio.errors import CalibrationError
from vio.kalibr import camchain_yaml_text
from vio.readers.calib import load_calibration
from vio.sim import rig
from vio.sim.api import load_scenario
from vio.sim.imu import grade_by_name, simulate_imu


def test_overlapping_adev_matches_allantools():
    allantools = pytest.importorskip("allantools", reason="allantools (LGPL, test-only reference) not installed")
    rng = np.random.default_rng(5)
    y = 0.01 * rng.standard_normal(30000) + 1e-4 * np.cumsum(rng.standard_normal(30000)) + 0.3
    m = cluster_sizes(len(y))
    taus, adev = overlapping_adev(y, 100.0, m)
    taus_ref, adev_ref, _, _ = allantools.oadev(y, rate=100.0, data_type="freq", taus=m / 100.0)
    assert np.allclose(taus, taus_ref) and np.allclose(adev, adev_ref, rtol=1e-9)


def _static_imu(duration_s: float, rate_hz: float, seed: int):
    sc = load_scenario("static", seed, duration_s, "phone")
    rng = np.random.default_rng(np.random.SeedSequence(seed).spawn(5)[1])  # the simulator's IMU stream
    imu, _ = simulate_imu(sc.trajectory, sc.t0_ns, sc.duration_s, rate_hz, grade_by_name("phone"), rng)
    return imu


def test_a_static_day_recovers_the_simulators_four_parameters():
    """The random walk's information grows with the log's length over the white/walk crossover (69 s for this
    gyro), not with the sample rate: a 24 h log at 10 Hz is as informative about K as at 200 Hz and 20x faster.
    (A 1 h log leaves a per-axis spread of ~15 % on K: docs/BENCHMARKS.md.)"""
    g = grade_by_name("phone")
    noise = imu_noise(_static_imu(86400.0, 10.0, seed=0))
    k = noise.kalibr()
    for got, want in (
        (k.gyroscope_noise_density, g.gyro_noise),
        (k.accelerometer_noise_density, g.acc_noise),
        (k.gyroscope_random_walk, g.gyro_walk),
        (k.accelerometer_random_walk, g.acc_walk),
    ):
        assert abs(got / want - 1) < 0.10, (got, want)
    # white + random walk has its minimum at sqrt(2 N K / sqrt(3)): that is the bias instability read there
    for fits, n, w in ((noise.gyro, g.gyro_noise, g.gyro_walk), (noise.acc, g.acc_noise, g.acc_walk)):
        expected = np.sqrt(2 * n * w / np.sqrt(3)) / BIAS_INSTABILITY_FACTOR
        assert all(abs(f.bias_instability / expected - 1) < 0.15 for f in fits)
    assert noise.rate_hz == pytest.approx(10.0)


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "vio.cli", *args], capture_output=True, text=True, cwd=ROOT)


def test_cli_writes_an_imu_yaml_that_vio_reads_beside_the_camchain(tmp_path):
    cap = tmp_path / "static"
    r = _run("simulate", "static", "--duration", "150", "--imu", "phone", "--no-images", "--out", str(cap))
    assert r.returncode == 0, r.stderr
    out = tmp_path / "calib" / "imu.yaml"
    r = _run("calibrate", "imu", str(cap), "--out", str(out))
    assert r.returncode == 0, r.stderr
    assert "not applied" in r.stdout and "short for the random walk" in r.stdout
    for name in ("imu_allan_gyro.png", "imu_allan_acc.png"):
        assert (out.parent / name).read_bytes()[:4] == b"\x89PNG"
    assert (out.parent / "imu0" / "sensor.yaml").is_file() and (out.parent / "imu_calibration.json").is_file()
    (out.parent / "camchain.yaml").write_text(camchain_yaml_text(rig.default_camera()))
    imu = load_calibration(out.parent).imu  # what `vio run --calib calib/` reads
    g = grade_by_name("phone")
    assert abs(imu.gyroscope_noise_density / g.gyro_noise - 1) < 0.05
    assert abs(imu.accelerometer_noise_density / g.acc_noise - 1) < 0.05
    assert imu.rate_hz == pytest.approx(200.0)


def _one_line_error(*args: str) -> str:
    r = _run(*args)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr
    return r.stderr


def test_a_moving_log_is_one_line(tmp_path):
    cap = tmp_path / "orbit"
    assert _run("simulate", "orbit", "--duration", "65", "--no-images", "--out", str(cap)).returncode == 0
    err = _one_line_error("calibrate", "imu", str(cap), "--out", str(tmp_path / "imu.yaml"))
    assert "not a static log" in err and "record with the IMU lying still" in err
    assert not (tmp_path / "imu.yaml").exists()


def test_a_short_log_is_refused():
    with pytest.raises(CalibrationError, match="at least 60 s"):
        imu_noise(_static_imu(20.0, 200.0, seed=1))


def _handled(imu, spans_s):
    """The log with the IMU turned and tilted (as by a hand) during each (start, end) span, s since its start."""
    from vio.records import ImuSeries

    t_s = (imu.t_ns - imu.t_ns[0]) * 1e-9
    gyro, acc = imu.gyro.copy(), imu.acc.copy()
    for a, b in spans_s:
        inside = (t_s >= a) & (t_s < b)
        gyro[inside] += [0.3, -0.2, 0.1]
        acc[inside] += [0.0, 2.0, -0.5]
    return ImuSeries(imu.t_ns, gyro, acc)


def test_a_log_handled_at_its_ends_keeps_its_static_stretch():
    imu = _static_imu(200.0, 200.0, seed=2)
    noise = imu_noise(_handled(imu, [(0.0, 6.0), (196.0, 201.0)]))
    start, end = noise.span_s
    assert 6.0 <= start <= 9.0 and 192.0 <= end <= 196.0 and noise.log_duration_s == pytest.approx(200.0)
    g = grade_by_name("phone")
    assert abs(noise.kalibr().gyroscope_noise_density / g.gyro_noise - 1) < 0.05


def test_a_log_bumped_in_the_middle_is_refused():
    imu = _static_imu(200.0, 200.0, seed=2)
    with pytest.raises(
        CalibrationError, match=r"not a static log: the (gyro|accelerometer)'s 1 s mean .* t = 10[0-2] s"
    ):
        imu_noise(_handled(imu, [(100.0, 103.0)]))
