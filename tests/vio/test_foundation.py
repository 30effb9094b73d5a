"""Foundation: Kalibr YAML, the ASL reader on real EuRoC data, atomic writes, the CLI's error handling."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from tests.conftest import ROOT, shared_path
from vio.atomic import atomic_open, write_text
from vio.errors import CalibrationError, CaptureError
from vio.kalibr import camera_yaml_text, imu_yaml_text, read_camera_yaml, read_imu_yaml
from vio.readers.asl import read_asl
from vio.records import CameraCalib, ImuCalib


def test_real_euroc_calibration_and_streams():
    root = shared_path("euroc_v1_01")
    cap = read_asl(root)
    assert cap.camera is not None and (cap.camera.width, cap.camera.height) == (752, 480)
    assert cap.camera.fx == pytest.approx(458.654)
    assert cap.camera.dist[0] == pytest.approx(-0.28340811)
    assert cap.camera.body_T_cam[0, 3] == pytest.approx(-0.0216401454975)
    assert cap.imu_calib is not None and cap.imu_calib.accelerometer_noise_density == pytest.approx(2e-3)
    assert cap.imu is not None and len(cap.imu) > 29000 and np.all(np.diff(cap.imu.t_ns) > 0)
    # The vehicle stands still at the start: specific force magnitude is gravity.
    assert np.linalg.norm(cap.imu.acc[:200].mean(axis=0)) == pytest.approx(9.81, abs=0.15)
    assert cap.num_frames == 95 and cap.load_image(0).shape == (480, 752)
    assert cap.ground_truth is not None and np.allclose(np.linalg.norm(cap.ground_truth.q_wxyz, axis=1), 1.0)


def test_kalibr_yaml_round_trip(tmp_path):
    cam = CameraCalib(640, 480, 500.0, 501.0, 320.5, 240.5, np.array([0.01, -0.02, 1e-4, -2e-4]), np.eye(4), 20.0)
    imu = ImuCalib(0.002, 0.015, 4e-5, 2e-3, 200.0)
    (tmp_path / "cam.yaml").write_text(camera_yaml_text(cam))
    (tmp_path / "imu.yaml").write_text(imu_yaml_text(imu))
    cam2, imu2 = read_camera_yaml(tmp_path / "cam.yaml"), read_imu_yaml(tmp_path / "imu.yaml")
    assert cam2.fx == cam.fx and cam2.cy == cam.cy and np.array_equal(cam2.dist, cam.dist)
    assert imu2 == imu


def test_bad_calibration_is_one_clear_error(tmp_path):
    p = tmp_path / "cam.yaml"
    p.write_text("sensor_type: camera\nintrinsics: [1, 2]\n")
    with pytest.raises(CalibrationError, match="cam.yaml"):
        read_camera_yaml(p)
    p.write_text("T_BS:\n  data: [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]\ngyroscope_noise_density: 1e-3\n")
    with pytest.raises(CalibrationError, match="missing IMU noise"):
        read_imu_yaml(p)


def test_undistort_inverts_distort():
    cam = CameraCalib(640, 480, 500.0, 500.0, 320.0, 240.0, np.array([-0.1, 0.02, 1e-3, -5e-4]), np.eye(4))
    xn = np.random.default_rng(0).uniform(-0.6, 0.6, (200, 2))
    back = cam.undistort_to_normalized(cam.distort_normalized(xn))
    assert np.abs(back - xn).max() < 1e-9
    # EuRoC's strong barrel distortion, over the whole image: pixel -> normalized -> pixel.
    euroc = CameraCalib(
        752,
        480,
        458.654,
        457.296,
        367.215,
        248.375,
        np.array([-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]),
        np.eye(4),
    )
    u, v = np.meshgrid(np.linspace(0, 751, 40), np.linspace(0, 479, 30))
    uv = np.column_stack([u.ravel(), v.ravel()])
    assert np.abs(euroc.distort_normalized(euroc.undistort_to_normalized(uv)) - uv).max() < 1e-6


def test_atomic_write_leaves_old_file_on_failure(tmp_path):
    target = tmp_path / "out.txt"
    write_text(target, "complete\n")
    with pytest.raises(RuntimeError), atomic_open(target) as f:
        f.write("half")
        raise RuntimeError("boom")
    assert target.read_text() == "complete\n"
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"]
    assert target.stat().st_mode & 0o044 == 0o044 or (os.umask(0o022) & 0o044)  # readable by others


def test_backwards_timestamp_names_file_and_row(tmp_path):
    imu = tmp_path / "mav0" / "imu0"
    imu.mkdir(parents=True)
    (imu / "data.csv").write_text("#t,wx,wy,wz,ax,ay,az\n10,0,0,0,0,0,9.81\n5,0,0,0,0,0,9.81\n")
    with pytest.raises(CaptureError, match=r"data.csv:3: IMU timestamp goes backwards"):
        read_asl(tmp_path)


def test_cli_help_and_errors_are_one_line(tmp_path):
    vio = [sys.executable, "-m", "vio.cli"]
    r = subprocess.run([*vio, "--help"], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0 and "simulate" in r.stdout and "run" in r.stdout
    r = subprocess.run([*vio, "info", str(tmp_path / "missing")], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode != 0
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert "missing" in r.stderr


def test_output_folder_in_the_way_is_one_clear_error(tmp_path):
    from vio.readers.eqvio import default_eqvio_path

    capture = default_eqvio_path()  # a valid capture that opens fast (`vio run` opens it before the output folder)
    blocker = tmp_path / "taken"
    blocker.write_text("not a folder")
    cmd = [sys.executable, "-m", "vio.cli", "run", str(capture), "--out", str(blocker)]
    r = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "existing file" in r.stderr
    assert blocker.read_text() == "not a folder"  # nothing lost
