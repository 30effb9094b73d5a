"""`vio simulate TRAJECTORY --real-imu IMU.csv` (issue 16): the simulator's vision along a recorded trajectory with
the recording's own IMU, through the command line; on EuRoC V1_01 (../shared/data) when it is there."""

from __future__ import annotations

import hashlib
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from tests.conftest import shared_path
from vio.geometry import quat_wxyz_to_R
from vio.readers.asl import read_asl
from vio.sim.api import simulate

VIO = [sys.executable, "-m", "vio.cli"]


def _vio(*args: object) -> subprocess.CompletedProcess:
    return subprocess.run([*VIO, *map(str, args)], capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    """A stand-in recording with an IMU and a ground truth on one clock: a simulated figure eight (no images)."""
    return simulate("figure8", tmp_path_factory.mktemp("rec") / "rec", seed=3, duration_s=6.0, images=False)


def test_real_imu_through_the_command_line(recording, tmp_path):
    mav0 = recording / "mav0"
    out = tmp_path / "semi"
    proc = _vio("simulate", mav0 / "state_groundtruth_estimate0" / "data.csv", "--real-imu", mav0 / "imu0" / "data.csv",
                "--start", 1.5, "--duration", 2.0, "--no-images", "--out", out)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    rec, cap = read_asl(recording), read_asl(out)
    # the IMU stream is the recording's samples in the window, untouched
    k = np.searchsorted(rec.imu.t_ns, cap.imu.t_ns)
    np.testing.assert_array_equal(rec.imu.t_ns[k], cap.imu.t_ns)
    np.testing.assert_allclose(cap.imu.gyro, rec.imu.gyro[k], rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(cap.imu.acc, rec.imu.acc[k], rtol=1e-8, atol=1e-12)
    span = (cap.imu.t_ns[-1] - cap.imu.t_ns[0]) * 1e-9
    assert span == pytest.approx(2.0, abs=0.006) and cap.imu.t_ns[0] - rec.ground_truth.t_ns[0] > 1.5e9
    assert cap.imu_calib == rec.imu_calib  # the noise of the sensor.yaml beside the CSV
    # the ground truth at the IMU's times, biases from the trajectory file, poses on the recording's path
    np.testing.assert_array_equal(cap.ground_truth.t_ns, cap.imu.t_ns)
    np.testing.assert_allclose(cap.ground_truth.b_w, rec.ground_truth.b_w[k], atol=1e-9)
    assert np.abs(cap.ground_truth.p_world - rec.ground_truth.p_world[k]).max() < 2e-3
    meta = yaml.safe_load((out / "scene" / "scene.yaml").read_text())
    assert meta["imu_grade"] == "real" and meta["real_imu"]["start_s"] == 1.5
    assert meta["real_imu"]["noise_from"].endswith("imu0/sensor.yaml")


def test_same_seed_renders_the_same_images_with_a_real_or_a_simulated_imu(recording, tmp_path):
    """The semi-real capture and its simulated-IMU twin differ only in the IMU stream."""
    mav0 = recording / "mav0"
    gt = mav0 / "state_groundtruth_estimate0" / "data.csv"
    kw = {"seed": 5, "start_s": 2.0, "duration_s": 0.3, "workers": 1}
    real = simulate(gt, tmp_path / "real", real_imu=mav0 / "imu0" / "data.csv", **kw)
    twin = simulate(gt, tmp_path / "twin", imu_grade="euroc", close_fit=True, **kw)

    def digest(p: Path) -> list[str]:
        return [hashlib.sha256(f.read_bytes()).hexdigest() for f in sorted((p / "mav0" / "cam0" / "data").iterdir())]

    assert len(digest(real)) == 6 and digest(real) == digest(twin)
    assert (real / "mav0" / "cam0" / "data.csv").read_text() == (twin / "mav0" / "cam0" / "data.csv").read_text()


def test_noise_from_imu_calib_and_one_line_errors(recording, tmp_path):
    mav0 = recording / "mav0"
    gt, imu = mav0 / "state_groundtruth_estimate0" / "data.csv", mav0 / "imu0" / "data.csv"
    kalibr = tmp_path / "imu.yaml"
    kalibr.write_text(
        "accelerometer_noise_density: 0.02\naccelerometer_random_walk: 0.001\ngyroscope_noise_density: 0.003\n"
        "gyroscope_random_walk: 4.0e-5\nupdate_rate: 200.0\n"
    )
    out = tmp_path / "noise"
    assert _vio("simulate", gt, "--real-imu", imu, "--imu-calib", kalibr, "--duration", 1, "--no-images",
                "--out", out).returncode == 0  # fmt: skip
    assert read_asl(out).imu_calib.gyroscope_noise_density == 0.003
    lonely = tmp_path / "lonely" / "data.csv"  # an IMU CSV without its sensor.yaml
    lonely.parent.mkdir()
    lonely.write_text(imu.read_text())
    cases = [
        (("orbit", "--real-imu", imu), "--real-imu needs a trajectory file scenario"),
        ((gt, "--real-imu", imu, "--imu", "tactical"), "--imu chooses a simulated IMU's grade"),
        ((gt, "--imu-calib", kalibr), "--imu-calib goes with --real-imu"),
        ((gt, "--real-imu", lonely), "no IMU noise calibration"),
        ((gt, "--real-imu", tmp_path / "none.csv"), "real IMU file not found"),
        ((gt, "--real-imu", imu, "--start", 5.5), "leaves less than 1 s"),
        (("orbit", "--start", 2), "--start and --close-fit are for a trajectory file scenario"),
    ]
    for args, message in cases:
        proc = _vio("simulate", *args, "--no-images", "--out", tmp_path / "x")
        assert proc.returncode == 2, args
        assert "Traceback" not in proc.stderr and message in proc.stderr.strip().splitlines()[-1], proc.stderr


def test_imu_on_another_clock_is_one_line(recording, tmp_path):
    from vio.trajio import read_trajectory, write_tum

    traj = read_trajectory(recording / "mav0" / "state_groundtruth_estimate0" / "data.csv")
    tum = tmp_path / "shifted.tum"
    write_tum(tum, type(traj)(traj.t_ns + 3_600_000_000_000, traj.p_world, traj.q_wxyz))  # an hour later
    proc = _vio("simulate", tum, "--real-imu", recording / "mav0" / "imu0" / "data.csv", "--duration", 1,
                "--no-images", "--out", tmp_path / "x")  # fmt: skip
    assert proc.returncode == 2 and "does not cover the capture" in proc.stderr and "Traceback" not in proc.stderr


def test_euroc_semi_real_capture_body_frame_is_the_imu_frame(tmp_path):
    """EuRoC V1_01: the accelerometer at rest (the first seconds), minus the ground truth's bias, points along
    gravity as the written ground-truth attitude predicts: the trajectory's body is the IMU frame, same clock."""
    mav0 = shared_path("euroc_v1_01", "mav0")
    out = tmp_path / "v101"
    proc = _vio("simulate", mav0 / "state_groundtruth_estimate0" / "data.csv", "--real-imu", mav0 / "imu0" / "data.csv",
                "--duration", 2.0, "--no-images", "--out", out)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    cap = read_asl(out)
    assert cap.imu_calib.gyroscope_noise_density == pytest.approx(1.6968e-4)  # EuRoC's imu0/sensor.yaml
    gt = cap.ground_truth
    f = cap.imu.acc - gt.b_a  # specific force at rest, body frame
    g_body = np.einsum("nji,j->ni", quat_wxyz_to_R(gt.q_wxyz).reshape(-1, 3, 3), np.array([0.0, 0.0, 9.81]))
    cos = np.sum(f.mean(axis=0) * g_body.mean(axis=0)) / (np.linalg.norm(f.mean(axis=0)) * 9.81)
    assert np.degrees(np.arccos(min(cos, 1.0))) < 0.5
    assert np.linalg.norm(f.mean(axis=0)) == pytest.approx(9.81, abs=0.05)
    np.testing.assert_allclose(cap.imu.gyro.mean(axis=0), gt.b_w.mean(axis=0), atol=2e-3)  # at rest: gyro = bias


def test_the_close_fit_keeps_the_motion_the_real_imu_measured():
    """EuRoC V1_01 in flight: the real gyro (bias removed, 0.1 s averages) agrees better with the closely fitted
    spline that `--real-imu` renders along than with the simulator's usual smoothed one."""
    from scipy.ndimage import uniform_filter1d

    from vio.sim.api import load_scenario

    mav0 = shared_path("euroc_v1_01", "mav0")
    rec = read_asl(mav0.parent)
    gt_csv = mav0 / "state_groundtruth_estimate0" / "data.csv"
    errors = []
    for close in (False, True):
        sc = load_scenario(gt_csv, start_s=30.0, duration_s=20.0, close_fit=close)
        inside = (rec.imu.t_ns >= sc.t0_ns) & (rec.imu.t_ns <= sc.t0_ns + 20_000_000_000)
        t_s = (rec.imu.t_ns[inside] - sc.t0_ns) * 1e-9
        b_w = np.column_stack([np.interp(rec.imu.t_ns[inside], rec.ground_truth.t_ns, rec.ground_truth.b_w[:, k])
                               for k in range(3)])  # fmt: skip
        residual = rec.imu.gyro[inside] - b_w - sc.trajectory.sample(t_s).omega_body
        errors.append(float(np.sqrt(np.mean(uniform_filter1d(residual, 20, axis=0) ** 2))))
    assert errors[1] < 0.8 * errors[0]
