"""Calibration files written by OpenCV's FileStorage (issue 16): OpenCV's calibration sample output and ORB-SLAM2 /
ORB-SLAM3 settings, read wherever a Kalibr YAML is (`--calib`, a file beside the capture), with their conventions.

The fixtures are written here the way those tools write them (`%YAML:1.0`, `!!opencv-matrix` with `dt: d` / `dt: f`),
and one through `cv2.FileStorage` itself."""

from __future__ import annotations

import subprocess
import sys

import cv2
import numpy as np
import pytest

from tests.writers.phone import write_mars
from vio.errors import CalibrationError
from vio.geometry import inv_T
from vio.readers import open_capture
from vio.readers.calib import load_calibration

# A camera-to-body transform (ORB-SLAM3's Tbc): EuRoC's cam0 T_BS, the camera's pose in the IMU frame.
TBC = np.array(
    [
        [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975],
        [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768],
        [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949],
        [0.0, 0.0, 0.0, 1.0],
    ]
)


def _matrix_text(name: str, M: np.ndarray, dt: str = "f") -> str:
    data = ", ".join(f"{v:.12g}" for v in np.asarray(M).ravel())
    return f"{name}: !!opencv-matrix\n   rows: {M.shape[0]}\n   cols: {M.shape[1]}\n   dt: {dt}\n   data: [{data}]\n"


OPENCV_SAMPLE = (
    "%YAML:1.0\n---\n"
    'calibration_time: "Mon 30 Nov 2026 10:00:00 UTC"\n'
    "nframes: 13\nimage_width: 640\nimage_height: 480\nboard_width: 9\nboard_height: 6\nsquare_size: 25.\n"
    "flags: 0\n"
    + _matrix_text("camera_matrix", np.array([[532.8, 0, 342.5], [0, 532.9, 233.9], [0, 0, 1.0]]), "d")
    + _matrix_text("distortion_coefficients", np.array([[-0.28], [0.02], [0.0012], [-0.0003], [0.0]]), "d")
    + "avg_reprojection_error: 0.196\n"
)

ORB_SLAM2 = """%YAML:1.0

# Camera calibration and distortion parameters (OpenCV)
Camera.fx: 458.654
Camera.fy: 457.296
Camera.cx: 367.215
Camera.cy: 248.375

Camera.k1: -0.28340811
Camera.k2: 0.07395907
Camera.p1: 0.00019359
Camera.p2: 1.76187114e-05

Camera.width: 752
Camera.height: 480

# Camera frames per second
Camera.fps: 20.0

# Color order of the images (0: BGR, 1: RGB. It is ignored if images are grayscale)
Camera.RGB: 1

ORBextractor.nFeatures: 1000
ORBextractor.scaleFactor: 1.2
"""

ORB_SLAM3_INERTIAL = (
    ORB_SLAM2.replace("%YAML:1.0\n", '%YAML:1.0\n\nCamera.type: "PinHole"\n')
    + "\n# Transformation from camera to body-frame (imu)\n"
    + _matrix_text("Tbc", TBC)
    + "\n# IMU noise\nIMU.NoiseGyro: 1.7e-4 #1.6968e-04\nIMU.NoiseAcc: 2.0000e-3 #2.0e-3\n"
    "IMU.GyroWalk: 1.9393e-05\nIMU.AccWalk: 3.0000e-03 # 3e-03\nIMU.Frequency: 200\n"
)

ORB_SLAM3_V1 = (
    '%YAML:1.0\n\nFile.version: "1.0"\n\nCamera.type: "PinHole"\n\n'
    "Camera1.fx: 458.654\nCamera1.fy: 457.296\nCamera1.cx: 367.215\nCamera1.cy: 248.375\n\n"
    "Camera1.k1: -0.28340811\nCamera1.k2: 0.07395907\nCamera1.p1: 0.00019359\nCamera1.p2: 1.76187114e-05\n\n"
    "Camera.width: 752\nCamera.height: 480\n\nCamera.fps: 20\nCamera.RGB: 1\n\n"
    + _matrix_text("IMU.T_b_c1", TBC)
    + "\nIMU.NoiseGyro: 1.7e-4\nIMU.NoiseAcc: 2.0000e-3\nIMU.GyroWalk: 1.9393e-05\nIMU.AccWalk: 3.0000e-03\n"
    "IMU.Frequency: 200.0\nIMU.InsertKFsWhenLost: 0\n"
)


@pytest.mark.parametrize("text", [ORB_SLAM3_INERTIAL, ORB_SLAM3_V1], ids=["Tbc", "IMU.T_b_c1"])
def test_orb_slam3_inertial_settings_give_camera_extrinsics_and_imu_noise(text, tmp_path):
    path = tmp_path / "EuRoC.yaml"
    path.write_text(text)
    cal = load_calibration(path)
    c = cal.camera
    assert (c.width, c.height, c.fx, c.fy, c.cx, c.cy, c.rate_hz) == (752, 480, 458.654, 457.296, 367.215, 248.375, 20)
    np.testing.assert_allclose(c.dist, [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05], rtol=0, atol=1e-15)
    # Tbc maps camera points into the body frame: it is body_T_cam as it stands (dt: f keeps 7 digits)
    np.testing.assert_allclose(c.body_T_cam, TBC, rtol=0, atol=1e-7)
    assert c.body_T_cam[:3, 2] @ np.array([0.0, 0.0, 1.0]) > 0.99  # EuRoC's camera looks along the IMU's z
    imu = cal.imu
    assert (imu.gyroscope_noise_density, imu.accelerometer_noise_density) == (1.7e-4, 2.0e-3)
    assert (imu.gyroscope_random_walk, imu.accelerometer_random_walk, imu.rate_hz) == (1.9393e-05, 3.0e-3, 200.0)
    assert cal.warnings == ()


def test_orb_slam2_settings_without_extrinsics_warn_and_assume_identity(tmp_path):
    path = tmp_path / "EuRoC.yaml"
    path.write_text(ORB_SLAM2)
    cal = load_calibration(path)
    assert cal.camera.fx == 458.654 and cal.camera.rate_hz == 20.0 and cal.imu is None
    np.testing.assert_array_equal(cal.camera.body_T_cam, np.eye(4))
    assert len(cal.warnings) == 1 and "vio calibrate camera-imu" in cal.warnings[0]


def test_opencv_calibration_sample_output(tmp_path):
    path = tmp_path / "out_camera_data.yml"
    path.write_text(OPENCV_SAMPLE)
    cal = load_calibration(path)
    c = cal.camera
    assert (c.width, c.height, c.fx, c.fy, c.cx, c.cy) == (640, 480, 532.8, 532.9, 342.5, 233.9)
    np.testing.assert_allclose(c.dist, [-0.28, 0.02, 0.0012, -0.0003], rtol=0, atol=1e-15)
    assert cal.imu is None and cal.timeshift_cam_imu_ns == 0


def test_a_file_written_by_cv2_filestorage_round_trips(tmp_path):
    """Whatever header this OpenCV version writes (%YAML:1.0 or %YAML 1.2), its own output reads back exactly."""
    K = np.array([[505.25, 0.0, 319.3], [0.0, 503.5, 241.6], [0.0, 0.0, 1.0]])
    dist = np.array([[-0.045, 0.018, 3.0e-4, -2.0e-4, 1e-9]])  # k3 negligible: dropped with a warning
    path = tmp_path / "cam.yml"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", dist)
    fs.release()
    cal = load_calibration(path)
    np.testing.assert_array_equal(cal.camera.K, K)
    np.testing.assert_array_equal(cal.camera.dist, dist.ravel()[:4])
    assert len(cal.warnings) == 2 and "k3 = 1e-09 dropped" in cal.warnings[0]


def test_a_large_k3_or_a_fisheye_is_refused_in_one_line(tmp_path):
    big = tmp_path / "k3.yml"
    big.write_text(OPENCV_SAMPLE.replace("[-0.28, 0.02, 0.0012, -0.0003, 0]", "[-0.28, 0.02, 0.0012, -0.0003, 0.3]"))
    with pytest.raises(CalibrationError, match=r"k3 = 0\.3 moves the image corners by .* recalibrate without k3"):
        load_calibration(big)
    fisheye = tmp_path / "kb.yaml"
    fisheye.write_text(ORB_SLAM3_V1.replace('"PinHole"', '"KannalaBrandt8"'))
    with pytest.raises(CalibrationError, match="Camera.type 'KannalaBrandt8' is not supported"):
        load_calibration(fisheye)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("%YAML:1.0\nCamera.fx: [458.6, 457.2\n", r"not a readable OpenCV FileStorage file \(line \d+: "),
        (ORB_SLAM2.replace("Camera.width: 752\n", ""), "needs both Camera.width and Camera.height"),
        (ORB_SLAM2.replace("Camera.cy: 248.375", "Camera.cy: abc"), "'Camera.cy' must be a number"),
        (ORB_SLAM3_INERTIAL.replace("rows: 4\n   cols: 4", "rows: 2\n   cols: 8"), "Tbc must be a 4x4 matrix"),
        (
            ORB_SLAM3_INERTIAL.replace("IMU.AccWalk: 3.0000e-03 # 3e-03\n", ""),
            "IMU noise incomplete: missing IMU.AccWalk",
        ),
    ],
    ids=["syntax", "no-size", "not-a-number", "bad-Tbc", "partial-imu"],
)
def test_malformed_opencv_files_give_one_line(text, message, tmp_path):
    path = tmp_path / "settings.yaml"
    path.write_text(text)
    with pytest.raises(CalibrationError, match=message) as info:
        load_calibration(path)
    assert "\n" not in str(info.value) and str(path) in str(info.value)


def test_orb_slam2_settings_without_an_image_size_take_the_images(sim_capture, tmp_path):
    settings = tmp_path / "orb2.yaml"
    settings.write_text(ORB_SLAM2.replace("Camera.width: 752\nCamera.height: 480\n", ""))
    assert (load_calibration(settings).camera.width, load_calibration(settings).camera.height) == (0, 0)
    cap = open_capture(sim_capture("orbit", duration_s=1.0), calib=settings)
    assert (cap.camera.width, cap.camera.height, cap.camera.fx) == (640, 480, 458.654)


def test_orb_slam3_file_as_calib_of_a_capture_and_beside_it(sim_capture, tmp_path):
    """`--calib SETTINGS.yaml` replaces a capture's calibration, and a `calib.yaml` in that format beside a phone log
    is found; the extrinsics keep ORB-SLAM3's camera-to-body meaning (not Kalibr's T_cam_imu)."""
    ref = open_capture(sim_capture("orbit", duration_s=1.0))
    B = ref.camera.body_T_cam
    settings = tmp_path / "settings.yaml"
    text = ORB_SLAM3_V1.replace("752", "640").replace("Camera.height: 480", "Camera.height: 480")
    settings.write_text(text.replace(_matrix_text("IMU.T_b_c1", TBC), _matrix_text("IMU.T_b_c1", B, "d")))
    cap = open_capture(sim_capture("orbit", duration_s=1.0), calib=settings)
    np.testing.assert_allclose(cap.camera.body_T_cam, B, rtol=0, atol=1e-12)
    assert not np.allclose(cap.camera.body_T_cam, inv_T(B), atol=1e-3)
    assert cap.camera.fx == 458.654 and cap.imu_calib.gyroscope_noise_density == 1.7e-4
    mars = write_mars(ref, tmp_path / "mars")
    (mars / "calib.yaml").write_text(settings.read_text())
    assert open_capture(mars).camera.fx == 458.654


def test_run_with_a_malformed_opencv_calib_is_one_line_without_traceback(sim_capture, tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("%YAML:1.0\nTbc: !!opencv-matrix\n   rows: 4\n   cols: 4\n   dt: f\n   data: [1, 0\n")
    capture = sim_capture("orbit", duration_s=1.0)
    proc = subprocess.run(
        [sys.executable, "-m", "vio.cli", "track", str(capture), "--out", str(tmp_path / "t.csv"), "--calib", str(bad)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert proc.stderr.strip().splitlines()[-1].startswith(f"vio track: error: {bad}: not a readable OpenCV")
