"""Bad input: every case gives one line naming the file (and row) and the problem, as an error or a warning."""

from __future__ import annotations

import shutil
import subprocess
import sys

import numpy as np
import pytest

from tests.conftest import ROOT
from tests.rotation_capture import rotation_capture
from tests.writers.phone import write_mars
from tests.writers.ros import write_ros2
from vio.errors import CalibrationError, CaptureError
from vio.readers import open_capture
from vio.readers.validate import gyro_scale_vs_gravity
from vio.writers.asl import AslWriter


@pytest.fixture(scope="module")
def source():
    return rotation_capture(duration_s=2.0, fps=20.0)


@pytest.fixture(scope="module")
def asl_master(source, tmp_path_factory):
    root = tmp_path_factory.mktemp("bad") / "asl"
    with AslWriter(root) as w:
        w.write_camera(source.camera)
        w.write_imu(source.imu_calib, source.imu)
        for i in range(source.num_frames):
            w.add_frame(int(source.frame_t_ns[i]), source.load_image(i))
    return root


@pytest.fixture
def asl(asl_master, tmp_path):
    dst = tmp_path / "asl"
    shutil.copytree(asl_master, dst)
    return dst


@pytest.fixture
def mars(source, tmp_path):
    return write_mars(source, tmp_path / "mars")


def _imu_lines(asl):
    p = asl / "mav0" / "imu0" / "data.csv"
    return p, p.read_text().splitlines()


def test_clean_capture_has_no_warnings(asl):
    assert open_capture(asl).warnings == []


def test_one_garbage_row_is_dropped_with_a_warning(asl):
    p, lines = _imu_lines(asl)
    lines[100] = "12x,not,a,number"
    p.write_text("\n".join(lines) + "\n")
    cap = open_capture(asl)
    assert any("imu0/data.csv:101: 1 garbage IMU row(s) dropped" in w for w in cap.warnings)


def test_a_value_beyond_any_sensor_is_dropped_and_many_are_an_error(asl):
    """Issue 20's fuzzer found a single 1e308 gyro sample passing every check (it would wreck the preintegration)."""
    p, lines = _imu_lines(asl)
    fields = lines[100].split(",")
    t_bad = int(fields[0])
    lines[100] = ",".join([fields[0], "1e308", *fields[2:]])
    p.write_text("\n".join(lines) + "\n")
    cap = open_capture(asl)
    assert any(f"1 of {len(cap.imu) + 1} IMU samples beyond any sensor's range" in w for w in cap.warnings)
    assert t_bad not in cap.imu.t_ns and np.abs(cap.imu.gyro).max() < 100
    for k in range(100, 130):
        fields = lines[k].split(",")
        lines[k] = ",".join([*fields[:4], "5000", *fields[5:]])
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(CaptureError, match="IMU samples beyond any sensor's range"):
        open_capture(asl)


def test_many_garbage_rows_are_an_error_naming_the_first(asl):
    p, lines = _imu_lines(asl)
    for k in range(50, 80):
        lines[k] = "garbage"
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(CaptureError, match=r"imu0/data.csv:51: expected at least 7 fields"):
        open_capture(asl)


def test_truncated_last_row_is_dropped_with_a_warning(asl):
    p, _ = _imu_lines(asl)
    text = p.read_text()
    p.write_text(text[: len(text) - 30])  # cut mid-row, no final newline
    cap = open_capture(asl)
    assert any("last row is truncated" in w for w in cap.warnings)


def test_backwards_timestamp_names_file_and_row(mars):
    p = mars / "gyro_accel.csv"
    lines = p.read_text().splitlines()
    lines[40], lines[41] = lines[41], lines[40]
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(CaptureError, match=r"gyro_accel.csv:42: IMU timestamp goes backwards"):
        open_capture(mars)


def test_repeated_timestamps_are_dropped_with_a_warning(mars):
    p = mars / "gyro_accel.csv"
    lines = p.read_text().splitlines()
    lines.insert(30, lines[30])
    p.write_text("\n".join(lines) + "\n")
    cap = open_capture(mars)
    assert any("gyro_accel.csv:32: 1 repeated IMU timestamp(s) dropped" in w for w in cap.warnings)


def test_nan_rows_are_dropped_with_a_warning(asl):
    p, lines = _imu_lines(asl)
    f = lines[60].split(",")
    f[3] = "nan"
    lines[60] = ",".join(f)
    p.write_text("\n".join(lines) + "\n")
    cap = open_capture(asl)
    assert any("data.csv:61: 1 IMU row(s) with NaN/inf dropped" in w for w in cap.warnings)


def test_imu_gap_warns_with_the_row(asl):
    p, lines = _imu_lines(asl)
    del lines[200:240]  # 0.2 s without IMU
    p.write_text("\n".join(lines) + "\n")
    cap = open_capture(asl)
    assert any("data.csv:201: 1 IMU gap(s)" in w and "largest 205.0 ms" in w for w in cap.warnings)


def _scale_imu(asl, gyro=1.0, acc=1.0):
    p, lines = _imu_lines(asl)
    out = [lines[0]]
    for line in lines[1:]:
        f = line.split(",")
        vals = [float(x) * gyro for x in f[1:4]] + [float(x) * acc for x in f[4:7]]
        out.append(",".join([f[0], *(repr(v) for v in vals)]))
    p.write_text("\n".join(out) + "\n")


def test_accelerometer_in_g_is_an_error(asl):
    _scale_imu(asl, acc=1 / 9.81)
    with pytest.raises(CaptureError, match=r"accelerometer looks like it is in g"):
        open_capture(asl)


def test_linear_acceleration_without_gravity_is_an_error(asl):
    _scale_imu(asl, acc=0.01)
    with pytest.raises(CaptureError, match=r"accelerometer has no gravity"):
        open_capture(asl)


def test_gyro_in_degrees_is_an_error(asl):
    _scale_imu(asl, gyro=180 / np.pi)
    with pytest.raises(CaptureError, match=r"gyro looks like it is in deg/s"):
        open_capture(asl)


def test_gravity_direction_measures_the_gyro_scale(source):
    s, seen = gyro_scale_vs_gravity(source.imu)
    assert seen > 0.3 and abs(s - 1.0) < 0.05
    deg = type(source.imu)(source.imu.t_ns, source.imu.gyro * 180 / np.pi, source.imu.acc)
    s_deg, _ = gyro_scale_vs_gravity(deg)
    assert abs(s_deg * 180 / np.pi - 1.0) < 0.05


def test_missing_image_is_skipped_with_a_warning(asl):
    first = sorted((asl / "mav0" / "cam0" / "data").iterdir())[5]
    first.unlink()
    cap = open_capture(asl)
    assert cap.num_frames == 39
    assert any("cam0/data.csv:7: 1 listed image(s) missing" in w for w in cap.warnings)


def test_all_images_missing_is_an_error(asl):
    shutil.rmtree(asl / "mav0" / "cam0" / "data")
    with pytest.raises(CaptureError, match="none of the 40 listed images exist"):
        open_capture(asl)


def test_corrupt_image_names_the_file(asl):
    bad = sorted((asl / "mav0" / "cam0" / "data").iterdir())[3]
    bad.write_bytes(b"\x89PNG not really")
    cap = open_capture(asl)
    with pytest.raises(CaptureError, match=rf"{bad.name}: image missing or cannot be decoded"):
        cap.load_image(3)


def test_empty_folder_is_an_error(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(CaptureError, match="capture folder is empty"):
        open_capture(tmp_path / "empty")


def test_clocks_that_do_not_overlap_are_an_error(asl):
    p, lines = _imu_lines(asl)
    out = [lines[0]] + [str(int(line.split(",", 1)[0]) + 10**15) + "," + line.split(",", 1)[1] for line in lines[1:]]
    p.write_text("\n".join(out) + "\n")
    with pytest.raises(CaptureError, match="camera and IMU clocks do not overlap"):
        open_capture(asl)


def test_frames_outside_the_imu_span_are_skipped(asl):
    p, lines = _imu_lines(asl)
    p.write_text("\n".join(lines[:-300]) + "\n")  # IMU ends 1.5 s early
    cap = open_capture(asl)
    assert cap.num_frames < 40
    assert any("frames lie outside the IMU span" in w for w in cap.warnings)
    cap.load_image(cap.num_frames - 1)


def test_capture_without_imu_is_an_error(asl):
    (asl / "mav0" / "imu0" / "data.csv").unlink()
    with pytest.raises(CaptureError, match="no IMU stream"):
        open_capture(asl)


def test_missing_calibration_is_one_calibration_error(mars):
    (mars / "calib.yaml").unlink()
    with pytest.raises(CalibrationError, match=r"no camera calibration: pass --calib"):
        open_capture(mars)


def test_calibration_for_another_image_size_is_an_error(mars, tmp_path):
    text = (mars / "calib.yaml").read_text().replace("- 480\n  - 360", "- 640\n  - 480")
    (tmp_path / "c.yaml").write_text(text)
    with pytest.raises(CalibrationError, match=r"images are 480x360 but the calibration is for 640x480"):
        open_capture(mars, calib=tmp_path / "c.yaml")


def test_more_timestamps_than_video_frames_warns(mars):
    p = mars / "frame_timestamps.txt"
    lines = p.read_text().splitlines()
    last = int(lines[-1])
    p.write_text("\n".join(lines + [str(last + 50_000_000), str(last + 100_000_000)]) + "\n")
    cap = open_capture(mars)
    assert cap.num_frames == 40
    assert any("42 frame timestamps but the video movie.mp4 has 40 frames" in w for w in cap.warnings)


def test_corrupt_video_is_an_error(mars):
    (mars / "movie.mp4").write_bytes(b"\x00" * 1000)
    with pytest.raises(CaptureError, match=r"movie.mp4: video cannot be opened"):
        open_capture(mars)


def test_corrupt_bag_is_an_error(source, tmp_path):
    bag = write_ros2(source, tmp_path / "bag")
    db = next(bag.glob("*.db3"))
    db.write_bytes(db.read_bytes()[:2000])
    with pytest.raises(CaptureError, match="bag"):
        open_capture(bag)


def test_bag_file_that_is_not_a_bag(tmp_path):
    (tmp_path / "x.bag").write_bytes(b"not a bag at all")
    with pytest.raises(CaptureError, match=r"x.bag: cannot read the bag"):
        open_capture(tmp_path / "x.bag")


def test_capture_without_frames_is_an_error(asl):
    (asl / "mav0" / "cam0" / "data.csv").write_text("#timestamp [ns],filename\n")
    with pytest.raises(CaptureError, match="no camera frames"):
        open_capture(asl)


def _vio(*args):
    return subprocess.run([sys.executable, "-m", "vio.cli", *args], capture_output=True, text=True, cwd=ROOT)


def test_cli_empty_folder_is_one_line_no_traceback(tmp_path):
    (tmp_path / "e").mkdir()
    r = _vio("info", str(tmp_path / "e"))
    assert r.returncode != 0
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert "capture folder is empty" in r.stderr


def test_cli_backwards_timestamps_is_one_line_no_traceback(mars, tmp_path):
    p = mars / "gyro_accel.csv"
    lines = p.read_text().splitlines()
    lines[10], lines[11] = lines[11], lines[10]
    p.write_text("\n".join(lines) + "\n")
    r = _vio("run", str(mars), "--out", str(tmp_path / "out"))
    assert r.returncode != 0
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert "gyro_accel.csv:12: IMU timestamp goes backwards" in r.stderr
    r = _vio("info", str(mars))  # vio info lists it among the problems and describes the rest
    assert r.returncode == 0 and "Traceback" not in r.stderr
    assert "  error: " in r.stdout and "gyro_accel.csv:12: IMU timestamp goes backwards" in r.stdout


def test_a_calibration_folder_prefers_the_camera_imu_camchain(tmp_path):
    """`vio calibrate camera` writes camchain.yaml, then `vio calibrate camera-imu` camchain-imu.yaml beside it:
    `--calib folder/` takes the complete one (the extrinsic and the clock offset), not the camera-only one."""
    from vio.kalibr import camchain_yaml_text
    from vio.readers.calib import load_calibration
    from vio.records import CameraCalib

    mount = np.eye(4)
    mount[:3, 3] = [0.01, 0.02, 0.0]
    (tmp_path / "camchain.yaml").write_text(
        camchain_yaml_text(CameraCalib(640, 480, 500.0, 500.0, 320.0, 240.0, np.zeros(4), np.eye(4)))
    )
    (tmp_path / "camchain-imu.yaml").write_text(
        camchain_yaml_text(CameraCalib(640, 480, 500.0, 500.0, 320.0, 240.0, np.zeros(4), mount), timeshift_s=0.015)
    )
    calib = load_calibration(tmp_path)
    assert calib.source.name == "camchain-imu.yaml"
    np.testing.assert_allclose(calib.camera.body_T_cam, mount, atol=1e-12)
    assert calib.timeshift_cam_imu_ns == 15_000_000


@pytest.mark.parametrize("rate", ["../../etc/passwd", "-20", "nan"])
def test_a_camchain_rate_that_is_not_a_frame_rate_is_one_line(tmp_path, rate):
    """Found by the fuzzer: a rate_hz replaced by a path ended `vio info` on a MARS capture in a ValueError."""
    from vio.errors import CalibrationError
    from vio.kalibr import camchain_yaml_text
    from vio.readers.calib import load_calibration
    from vio.records import CameraCalib

    text = camchain_yaml_text(CameraCalib(640, 480, 500.0, 500.0, 320.0, 240.0, np.zeros(4), np.eye(4)))
    (tmp_path / "camchain.yaml").write_text(text.replace("rate_hz: 20", f"rate_hz: '{rate}'"))
    with pytest.raises(CalibrationError, match="rate_hz must be a"):
        load_calibration(tmp_path / "camchain.yaml")
