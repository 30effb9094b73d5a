"""The same simulated capture written in every supported format reads back as the same records."""

from __future__ import annotations

import numpy as np
import pytest

from tests.writers.phone import write_mars, write_opencamera, write_sensorlogger
from tests.writers.ros import write_ros1, write_ros2
from vio.errors import CaptureError
from vio.readers import detect_format, open_capture


@pytest.fixture(scope="module")
def ref(sim_capture):
    return open_capture(sim_capture("orbit", duration_s=3.0))


def _write(kind, ref, tmp_path):
    if kind == "ros2":
        return write_ros2(ref, tmp_path / "bag2")
    if kind == "ros2-mcap-compressed":
        return write_ros2(ref, tmp_path / "bag2c", compressed=True, mcap=True)
    if kind == "ros1":
        (tmp_path / "r1").mkdir()
        return write_ros1(ref, tmp_path / "r1" / "capture.bag")
    if kind == "mars":
        return write_mars(ref, tmp_path / "mars")
    if kind == "mars-ios":
        return write_mars(ref, tmp_path / "mars", platform="iOS")
    if kind == "opencamera":
        return write_opencamera(ref, tmp_path / "oc")
    if kind == "sensorlogger-android":
        return write_sensorlogger(ref, tmp_path / "sl")
    if kind == "sensorlogger-ios":
        return write_sensorlogger(ref, tmp_path / "sl", platform="iOS")
    raise AssertionError(kind)


FORMAT_OF = {
    "ros2": "ros2",
    "ros2-mcap-compressed": "ros2",
    "ros1": "ros1",
    "mars": "mars",
    "mars-ios": "mars",
    "opencamera": "opencamera",
    "sensorlogger-android": "sensorlogger",
    "sensorlogger-ios": "sensorlogger",
}


@pytest.mark.parametrize("kind", list(FORMAT_OF))
def test_every_format_reads_back_the_same_records(kind, ref, tmp_path):
    path = _write(kind, ref, tmp_path)
    assert detect_format(path) == FORMAT_OF[kind]
    cap = open_capture(path)
    assert cap.format == FORMAT_OF[kind]
    assert cap.warnings == []
    # frame times exact (ns), images bit-exact (lossless FFV1 video / raw or PNG messages)
    np.testing.assert_array_equal(cap.frame_t_ns, ref.frame_t_ns)
    for i in range(0, ref.num_frames, 7):
        np.testing.assert_array_equal(cap.load_image(i), ref.load_image(i))
    # IMU: the same samples; CSV formats print repr(float) (exact), Sensor Logger sums user + gravity (1 ulp-ish)
    np.testing.assert_array_equal(cap.imu.t_ns, ref.imu.t_ns)
    np.testing.assert_allclose(cap.imu.gyro, ref.imu.gyro, rtol=0, atol=1e-12)
    np.testing.assert_allclose(cap.imu.acc, ref.imu.acc, rtol=0, atol=1e-12)
    # calibration through the Kalibr camchain written beside the capture
    c, r = cap.camera, ref.camera
    assert (c.width, c.height) == (r.width, r.height)
    np.testing.assert_allclose([c.fx, c.fy, c.cx, c.cy], [r.fx, r.fy, r.cx, r.cy], rtol=0, atol=1e-12)
    np.testing.assert_allclose(c.dist, r.dist, rtol=0, atol=1e-15)
    np.testing.assert_allclose(c.body_T_cam, r.body_T_cam, rtol=0, atol=1e-12)
    assert cap.imu_calib == ref.imu_calib


def test_frames_stream_in_any_order(ref, tmp_path):
    """Lazy loaders (bag re-read, video re-decode) give the same frame for random access as for sequential."""
    for path in (write_ros2(ref, tmp_path / "b"), write_mars(ref, tmp_path / "m")):
        cap = open_capture(path)
        for i in (5, 2, 2, 9, 0, ref.num_frames - 1):
            np.testing.assert_array_equal(cap.load_image(i), ref.load_image(i))


def test_sensorlogger_image_mode_has_millisecond_times(ref, tmp_path):
    path = write_sensorlogger(ref, tmp_path / "sl", camera="images")
    cap = open_capture(path)
    assert cap.num_frames == ref.num_frames
    assert np.abs(cap.frame_t_ns - ref.frame_t_ns).max() < 1_000_000  # file names are epoch milliseconds
    np.testing.assert_array_equal(cap.load_image(3), ref.load_image(3))


def test_sensorlogger_video_without_frame_times_warns(ref, tmp_path):
    path = write_sensorlogger(ref, tmp_path / "sl", camera="video-noframes")
    cap = open_capture(path)
    assert any("frame_times.csv" in w and "session start" in w for w in cap.warnings)


def test_sensorlogger_without_gravity_is_refused(ref, tmp_path):
    path = write_sensorlogger(ref, tmp_path / "sl", total=False)
    (path / "Gravity.csv").unlink()
    with pytest.raises(CaptureError, match=r"Accelerometer.csv: .*excludes gravity"):
        open_capture(path)


def test_ros_topics_named_or_found(ref, tmp_path):
    path = write_ros2(ref, tmp_path / "bag")
    assert open_capture(path, image_topic="/cam0/image_raw", imu_topic="/imu0").num_frames == ref.num_frames
    with pytest.raises(CaptureError, match="no image topic named '/nope'"):
        open_capture(path, image_topic="/nope")


def test_calib_argument_overrides_and_applies_timeshift(ref, tmp_path):
    from tests.writers import calib_yaml_text

    path = write_mars(ref, tmp_path / "m")
    other = tmp_path / "mine.yaml"
    other.write_text(calib_yaml_text(ref.camera, ref.imu_calib, timeshift_cam_imu_s=0.004))
    cap = open_capture(path, calib=other)
    np.testing.assert_array_equal(cap.frame_t_ns, ref.frame_t_ns + 4_000_000)


def test_lossy_phone_codec_keeps_times_and_imu_exact(ref, tmp_path):
    """mp4v (MPEG-4 part 2, lossy like the phones' H.264): images within codec tolerance, everything else exact."""
    cap = open_capture(write_mars(ref, tmp_path / "m", fourcc="mp4v"))
    np.testing.assert_array_equal(cap.frame_t_ns, ref.frame_t_ns)
    np.testing.assert_array_equal(cap.imu.t_ns, ref.imu.t_ns)
    errs = [np.abs(cap.load_image(i).astype(float) - ref.load_image(i)).mean() for i in range(0, ref.num_frames, 9)]
    assert max(errs) < 4.0  # mean absolute error, grey levels (measured about 1.7 on the orbit texture)


def test_tumvi_layout_needs_a_pinhole_calibration(ref, tmp_path):
    """TUM-VI: ASL layout without cam0/sensor.yaml, mocap0/, and an equidistant dso/camchain.yaml."""
    import shutil

    from tests.writers import calib_yaml_text
    from vio.errors import CalibrationError

    root = tmp_path / "tumvi"
    shutil.copytree(ref.root, root)
    (root / "mav0" / "cam0" / "sensor.yaml").unlink()
    (root / "mav0" / "mocap0").mkdir()
    (root / "dso").mkdir()
    fisheye = calib_yaml_text(ref.camera, None).replace("distortion_model: radtan", "distortion_model: equidistant")
    (root / "dso" / "camchain.yaml").write_text(fisheye)
    with pytest.raises(CalibrationError, match="no camera calibration"):
        open_capture(root)
    (tmp_path / "pinhole.yaml").write_text(calib_yaml_text(ref.camera, None))
    cap = open_capture(root, calib=tmp_path / "pinhole.yaml")
    assert cap.format == "tumvi" and cap.camera.fx == ref.camera.fx


@pytest.mark.parametrize("encoding", ["mono8", "mono16", "bgr8", "rgb8", "bgra8", "rgba8"])
def test_ros_image_encodings_decode_to_the_same_grey(encoding):
    import cv2
    from rosbags.typesys import Stores, get_typestore

    from vio.readers.rosbag import decode_image

    rng = np.random.default_rng(1)
    grey = rng.integers(0, 256, (6, 5), dtype=np.uint8)
    bgr = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
    data, ch = {
        "mono8": (grey, 1),
        "mono16": (grey.astype("<u2") * 256 + 7, 2),
        "bgr8": (bgr, 3),
        "rgb8": (bgr[:, :, ::-1], 3),
        "bgra8": (cv2.cvtColor(bgr, cv2.COLOR_BGR2BGRA), 4),
        "rgba8": (cv2.cvtColor(bgr, cv2.COLOR_BGR2RGBA), 4),
    }[encoding]
    ts = get_typestore(Stores.ROS2_HUMBLE)
    Image, Header, Time = (
        ts.types[k] for k in ("sensor_msgs/msg/Image", "std_msgs/msg/Header", "builtin_interfaces/msg/Time")
    )
    raw = np.ascontiguousarray(data).view(np.uint8).reshape(-1)
    msg = Image(
        header=Header(stamp=Time(sec=1, nanosec=0), frame_id="c"),
        height=6,
        width=5,
        encoding=encoding,
        is_bigendian=0,
        step=5 * ch,
        data=raw,
    )
    np.testing.assert_array_equal(decode_image(msg, Image.__msgtype__, "test"), grey)


def test_sensorlogger_ios_uncalibrated_accelerometer_in_g(ref, tmp_path):
    """Only AccelerometerUncalibrated.csv (iOS: g, CoreMotion sign): converted to m/s^2 specific force."""
    path = write_sensorlogger(ref, tmp_path / "sl", platform="iOS")
    for name in ("Accelerometer.csv", "Gravity.csv"):
        (path / name).unlink()
    lines = ["time,seconds_elapsed,z,y,x"]
    for t, a in zip(ref.imu.t_ns, -ref.imu.acc / 9.80665, strict=True):
        lines.append(f"{int(t)},0.0,{float(a[2])!r},{float(a[1])!r},{float(a[0])!r}")
    (path / "AccelerometerUncalibrated.csv").write_text("\n".join(lines) + "\n")
    cap = open_capture(path)
    np.testing.assert_allclose(cap.imu.acc, ref.imu.acc, rtol=0, atol=1e-12)
