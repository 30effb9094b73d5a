"""MARS logger folders with H.264 video as phones write them (issue 16): written by `vio.writers.mars` through
PyAV, read back by the MARS reader (PyAV decoding, sensor orientation, readout time)."""

from __future__ import annotations

from dataclasses import replace

import av
import cv2
import numpy as np
import pytest

from vio.errors import CaptureError
from vio.readers import open_capture
from vio.readers.mars import readout_ns
from vio.readers.video_av import AvVideoFrames
from vio.sim.api import simulate
from vio.sim.phone import PRESETS


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    """A 0.8 s portrait phone capture (no blur, for speed) as ASL and as MARS."""
    base = tmp_path_factory.mktemp("mars")
    phone = replace(PRESETS["phone"], exposure_s=0.0)
    asl = simulate("orbit", base / "asl", seed=21, duration_s=0.8, workers=1, phone=phone, mars=base / "mars")
    return asl, base / "mars"


def test_mars_h264_capture_round_trips_through_the_reader(captures):
    asl, mars = captures
    a, m = open_capture(asl), open_capture(mars)
    assert m.format == "mars"
    assert m.warnings == []
    assert m.num_frames == a.num_frames > 10
    assert np.array_equal(m.frame_t_ns, a.frame_t_ns)
    assert np.array_equal(m.imu.t_ns, a.imu.t_ns)
    np.testing.assert_allclose(m.imu.gyro, a.imu.gyro, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(m.imu.acc, a.imu.acc, rtol=1e-8, atol=1e-12)
    assert (m.camera.width, m.camera.height, m.camera.fx) == (a.camera.width, a.camera.height, a.camera.fx)
    for i in (0, m.num_frames // 2, m.num_frames - 1, 1):  # out of order: the decoder reopens
        img, ref = m.load_image(i), a.load_image(i)
        assert img.shape == ref.shape == (480, 640)  # the sensor's orientation, as calibrated
        assert np.abs(img.astype(int) - ref).mean() < 4.0  # lossy H.264, as on the phone


def test_mars_video_is_h264_in_portrait_and_states_its_readout(captures):
    _, mars = captures
    video = AvVideoFrames(mars / "movie.mp4")
    assert video.codec == "h264"
    assert video.rotation_deg == 90
    assert (video.width, video.height) == (640, 480)
    with av.open(str(mars / "movie.mp4")) as c:
        assert c.streams.video[0].codec_context.name == "h264"
    # OpenCV turns portrait video upright, which no longer matches the calibration: the reason for PyAV
    cv = cv2.VideoCapture(str(mars / "movie.mp4"))
    ok, upright = cv.read()
    cv.release()
    assert ok and upright.shape[:2] == (640, 480)
    assert readout_ns(mars) == 20_000_000
    assert (mars / "scene" / "groundtruth.csv").is_file()


def test_truncated_h264_video_is_a_one_line_error(captures, tmp_path):
    _, mars = captures
    bad = tmp_path / "bad"
    bad.mkdir()
    for name in ("frame_timestamps.txt", "gyro_accel.csv", "calib.yaml", "imu.yaml"):
        (bad / name).write_bytes((mars / name).read_bytes())
    (bad / "movie.mp4").write_bytes((mars / "movie.mp4").read_bytes()[:2000])
    with pytest.raises(CaptureError) as exc:
        open_capture(bad)
    assert "movie.mp4" in str(exc.value) and "\n" not in str(exc.value)
