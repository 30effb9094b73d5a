"""vio calibrate imu-axes: the simulated phone accelerometer's axes recovered from a tumble, what it needs of a log,
the file, and `vio run --set imu.axes=FILE`."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from tests.conftest import ROOT
from vio.calibrate.imu_axes import corrected, fit_acc_axes, read_correction
from vio.errors import CalibrationError
from vio.readers import open_capture
from vio.records import GRAVITY_M_S2, ImuSeries


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "vio.cli", *args], cwd=ROOT, capture_output=True, text=True)


def _one_line_error(*args: str) -> str:
    r = _run(*args)
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr
    return r.stderr


@pytest.fixture(scope="module")
def tumble(tmp_path_factory):
    cap = tmp_path_factory.mktemp("tumble") / "cap"
    r = _run("simulate", "tumble", "--camera", "phone", "--no-images", "--seed", "7", "--out", str(cap))
    assert r.returncode == 0, r.stderr
    return cap


def test_a_tumble_recovers_the_phone_accelerometers_axes(tumble):
    """The simulated phone's accelerometer (1 % scale factors, 0.5 % cross-axis terms, its noise and bias): after the
    correction what is left of T is a rotation (not observable from gravity's magnitude) to 0.1 %."""
    fit = fit_acc_axes(open_capture(tumble, needs=("imu",)).imu)
    T = np.asarray(yaml.safe_load((tumble / "scene" / "scene.yaml").read_text())["imu_errors"]["acc_T"])
    assert np.abs(np.diag(T) - 1).max() > 0.005  # the errors are there to find
    M = fit.correction @ T
    assert np.abs(M.T @ M - np.eye(3)).max() < 5e-3 and np.abs(np.diag(M) - 1).max() < 1e-3, M
    assert fit.poses == 24 and (fit.scale_sigma < 1e-3).all()
    assert fit.residual_rms_m_s2 < 0.02 < fit.before_rms_m_s2


def test_the_cli_writes_the_file_that_run_reads(tumble, tmp_path):
    out = tmp_path / "axes.yaml"
    r = _run("calibrate", "imu-axes", str(tumble), "--out", str(out))
    assert r.returncode == 0, r.stderr
    assert "24 still orientations" in r.stdout and "imu.axes=" in r.stdout
    K = read_correction(out)
    assert np.allclose(K, np.triu(K)) and np.abs(K - np.eye(3)).max() < 0.05
    imu = open_capture(tumble, needs=("imu",)).imu
    assert np.allclose(corrected(imu, K).acc, imu.acc @ K.T) and corrected(imu, K).gyro is imu.gyro


def test_a_log_turned_about_one_axis_only_is_refused():
    """Gravity in one plane of the IMU leaves the third axis's scale unknown: a clear error, not a fit."""
    rate, t_ns, acc = 100.0, [], []
    for i, angle in enumerate(np.linspace(0, 2 * np.pi, 16, endpoint=False)):
        g = Rotation.from_rotvec([angle, 0.0, 0.0]).apply([0.0, 0.0, GRAVITY_M_S2])
        n = int(3 * rate)
        t_ns.append((i * 4.0 + np.arange(n) / rate) * 1e9)
        acc.append(np.repeat(g[None, :], n, axis=0))
    t = np.concatenate(t_ns).astype(np.int64)
    gyro = np.zeros((len(t), 3))
    gyro[np.diff(t, prepend=t[0]) > 1e8] = 1.0  # a turn between the still stretches
    with pytest.raises(CalibrationError, match="did not cover"):
        fit_acc_axes(ImuSeries(t, gyro, np.concatenate(acc)))


def test_bad_logs_and_files_are_one_line(tmp_path):
    orbit = tmp_path / "orbit"
    assert _run("simulate", "orbit", "--duration", "10", "--no-images", "--out", str(orbit)).returncode == 0
    err = _one_line_error("calibrate", "imu-axes", str(orbit), "--out", str(tmp_path / "a.yaml"))
    assert "still orientations found" in err and not (tmp_path / "a.yaml").exists()
    bad = tmp_path / "bad.yaml"
    bad.write_text("accelerometer_correction: [[2, 0, 0], [0, 1, 0], [0, 0, 1]]\n")
    with pytest.raises(CalibrationError, match="within 0.1 of identity"):
        read_correction(bad)


class _Stop(Exception):
    pass


def test_run_applies_the_correction_to_every_accelerometer_sample(sim_capture, tmp_path, monkeypatch):
    from vio import pipeline
    from vio.config import load_config

    cap = sim_capture(duration_s=4.0)
    axes = tmp_path / "axes.yaml"
    K = np.array([[1.02, 0.003, 0.0], [0.0, 0.99, -0.002], [0.0, 0.0, 1.0]])
    axes.write_text(yaml.safe_dump({"accelerometer_correction": K.tolist()}))
    seen = []

    def preintegrator(imu, calib, cfg):
        seen.append(imu)
        raise _Stop

    monkeypatch.setattr(pipeline, "ImuPreintegrator", preintegrator)
    for overrides in ([], [f"imu.axes={axes}"]):
        with pytest.raises(_Stop):
            pipeline._run(cap, tmp_path / "run", load_config(None, overrides), None, [], None)
    raw, fixed = seen
    assert np.allclose(fixed.acc, raw.acc @ K.T) and np.array_equal(fixed.gyro, raw.gyro)


def test_run_with_a_bad_axes_file_is_one_line(sim_capture, tmp_path):
    cap = sim_capture(duration_s=4.0)
    bad = tmp_path / "bad.yaml"
    bad.write_text("not: [a, matrix]\n")
    err = _one_line_error("run", str(cap), "--out", str(tmp_path / "r"), "--set", f"imu.axes={bad}")
    assert "accelerometer_correction" in err


def test_a_phone_logs_run_without_axes_says_how_to_calibrate_them():
    from pathlib import Path

    from vio import pipeline
    from vio.capture import Capture
    from vio.config import load_config
    from vio.health import summary_lines

    def capture(fmt: str) -> Capture:
        return Capture(Path("x"), None, None, None, np.zeros(0, np.int64), lambda i: np.zeros((1, 1)), format=fmt)

    cfg = load_config(None, [])
    assert pipeline._with_axes(capture("asl"), cfg)[1] == {"imu_axes": None}
    _, note = pipeline._with_axes(capture("mars"), cfg)
    assert "vio calibrate imu-axes" in note["axes_advice"]
    summary = {"status": "ok", "num_states": 3, "num_landmarks": 9, "span_s": 1.0, "wall_time_s": 1.0, "scale": note}
    assert summary_lines(summary)[-1] == note["axes_advice"]


def test_the_benchmark_of_the_axes_runs_one_seed(tmp_path):
    """`python -m vio.bench.imu_axes_limit` on one short seed: three scale errors and the axes left after the
    correction (the 30-seed table is in docs/BENCHMARKS.md)."""
    from vio.bench.imu_axes_limit import VARIANTS, one_seed, parse_seeds, table

    assert parse_seeds("201-203,207") == [201, 202, 203, 207]
    row = one_seed(7, tmp_path, duration_s=12.0)
    assert set(row["scale_error"]) == set(VARIANTS) and all(np.isfinite(list(row["scale_error"].values())))
    assert row["axes_left"] < 5e-3
    assert "corrected by imu-axes" in table([row, row])


def test_local_gravity_sets_the_scale_of_the_correction(tumble, tmp_path):
    """K is fitted to the gravity it is given, so the run's scale inherits it: 9.78 instead of 9.81 scales K by
    9.78 / 9.81. `--latitude` gives WGS 84 normal gravity (9.7803 at the equator, 9.8322 at the poles)."""
    from vio.calibrate.imu_axes import local_gravity, normal_gravity

    assert normal_gravity(0.0) == pytest.approx(9.7803253, abs=1e-6)
    assert normal_gravity(90.0) == pytest.approx(9.8321849, abs=1e-6)
    assert normal_gravity(45.0, 1000.0) == pytest.approx(normal_gravity(45.0) - 3.086e-3)
    imu = open_capture(tumble, needs=("imu",)).imu
    K981, K978 = fit_acc_axes(imu, 9.81).correction, fit_acc_axes(imu, 9.78).correction
    assert np.allclose(K978, K981 * 9.78 / 9.81, atol=1e-6)
    with pytest.raises(CalibrationError, match="not both"):
        local_gravity(9.8, 45.0, 0.0)
    r = _run("calibrate", "imu-axes", str(tumble), "--out", str(tmp_path / "a.yaml"), "--latitude", "47.4")
    assert r.returncode == 0 and "WGS 84 normal gravity at 47.4 deg" in r.stdout, r.stderr
    assert yaml.safe_load((tmp_path / "a.yaml").read_text())["gravity_m_s2"] == pytest.approx(normal_gravity(47.4))
    err = _one_line_error("calibrate", "imu-axes", str(tumble), "--out", str(tmp_path / "b.yaml"), "--gravity", "98.1")
    assert "not a surface gravity" in err and not (tmp_path / "b.yaml").exists()
