"""IMU ablation copies: the capture's images and truth, its IMU drawn again with error terms switched off."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from vio.bench.imu_ablation import main, write_ablation
from vio.readers.asl import read_asl
from vio.sim.api import simulate
from vio.sim.phases import PhasedMotion


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    root = tmp_path_factory.mktemp("ablation")
    kw = {"seed": 313, "duration_s": 1.0, "images": False, "phases": PhasedMotion(still_start_s=0.5, excite_s=1.0)}
    phone = simulate("orbit", root / "phone", imu_grade="phone", **kw)
    ideal = simulate("orbit", root / "ideal", imu_grade="ideal", **kw)
    return root, phone, ideal


def test_nothing_dropped_is_the_capture_and_everything_dropped_is_the_exact_imu(captures):
    root, phone, ideal = captures
    same = read_asl(write_ablation(phone, root / "same", ()))
    orig = read_asl(phone)
    assert np.array_equal(same.imu.t_ns, orig.imu.t_ns)
    np.testing.assert_allclose(same.imu.acc, orig.imu.acc, atol=1e-6)
    np.testing.assert_allclose(same.imu.gyro, orig.imu.gyro, atol=1e-7)
    exact = read_asl(write_ablation(phone, root / "exact", ("gyro_white", "acc_white", "gyro_walk", "acc_walk",
                                                             "gyro_bias0", "acc_bias0")))  # fmt: skip
    truth = read_asl(ideal)
    np.testing.assert_allclose(exact.imu.acc, truth.imu.acc, atol=1e-6)
    np.testing.assert_allclose(exact.imu.gyro, truth.imu.gyro, atol=1e-7)
    assert (root / "exact" / "mav0" / "imu0" / "sensor.yaml").read_text() == (
        phone / "mav0" / "imu0" / "sensor.yaml"
    ).read_text()  # the estimator still assumes the phone's noise
    assert yaml.safe_load((root / "exact" / "scene" / "imu_ablation.yaml").read_text())["dropped"][0] == "gyro_white"


def test_dropping_the_white_noise_keeps_the_biases(captures):
    root, phone, ideal = captures
    white = read_asl(write_ablation(phone, root / "nowhite", ("gyro_white", "acc_white")))
    truth, orig = read_asl(ideal), read_asl(phone)
    bias = white.imu.acc - truth.imu.acc  # what is left: the bias, smooth
    assert np.abs(np.diff(bias, axis=0)).max() < 1e-3 < np.abs(np.diff(orig.imu.acc - truth.imu.acc, axis=0)).max()
    assert np.abs(bias.mean(axis=0)).max() > 0.02  # the initial biases (0.025-0.075 m/s^2 per axis) are still there


def test_bad_input_is_one_line(captures, tmp_path, capsys):
    root, phone, _ = captures
    assert main([str(tmp_path), str(tmp_path / "x")]) == 2
    assert main([str(phone), str(tmp_path / "y"), "--drop", "acc_whit"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "not a simulated capture" in err[0] and "unknown IMU error term(s) acc_whit" in err[1]
