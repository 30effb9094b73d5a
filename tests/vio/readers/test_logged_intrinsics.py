"""A MARS folder without a calibration opens with the logger's own intrinsics and a clear warning (issue 16)."""

from __future__ import annotations

import numpy as np
import pytest

from tests.writers.phone import write_mars
from vio.errors import CalibrationError
from vio.info import capture_info
from vio.readers import open_capture
from vio.readers.logged_intrinsics import BODY_R_CAM_NOMINAL
from vio.writers.mars import METADATA_HEADER


@pytest.fixture(scope="module")
def ref(sim_capture):
    return open_capture(sim_capture("orbit", duration_s=1.0))


def _metadata(cap, fx: np.ndarray, fy: np.ndarray) -> str:
    """movie_metadata.csv as MARS (Android) writes it: one row per frame, focal lengths in px."""
    rows = [
        f"{int(t)},{fx[i]:.6f},{fy[i]:.6f},{i},10000000,50000000,20700000,100,4.38,0.0,0"
        for i, t in enumerate(cap.frame_t_ns)
    ]
    return "\n".join([METADATA_HEADER, *rows]) + "\n"


def test_android_mars_without_calibration_uses_the_logged_focal_lengths(ref, tmp_path):
    mars = write_mars(ref, tmp_path / "mars")
    (mars / "calib.yaml").unlink()
    n = ref.num_frames
    fx = 500.0 + np.arange(n) % 3  # the lens' focus breathing: 500, 501, 502, ...
    fy = fx - 1.5
    fx[0] = np.nan  # a frame without metadata is ignored
    (mars / "movie_metadata.csv").write_text(_metadata(ref, fx, fy).replace("nan", ""))
    cap = open_capture(mars)
    c = cap.camera
    assert (c.fx, c.fy) == (float(np.nanmedian(fx[1:])), float(np.nanmedian(fy[1:])))
    assert (c.width, c.height) == (ref.camera.width, ref.camera.height)
    assert (c.cx, c.cy) == ((c.width - 1) / 2, (c.height - 1) / 2)
    assert not np.any(c.dist) and c.rate_hz == pytest.approx(20.0)
    np.testing.assert_array_equal(c.body_T_cam[:3, :3], BODY_R_CAM_NOMINAL)
    (warning,) = [w for w in cap.warnings if "movie_metadata.csv" in w]
    assert "approximation" in warning and "vio calibrate camera" in warning and "--calib" in warning
    assert "warning: " + warning in capture_info(mars, offset=False)  # what `vio info` shows


def test_an_imu_yaml_beside_the_log_gives_its_noise(ref, tmp_path):
    from vio.kalibr import kalibr_imu_yaml_text

    mars = write_mars(ref, tmp_path / "mars", platform="iOS")
    (mars / "calib.yaml").unlink()
    (mars / "imu.yaml").write_text(kalibr_imu_yaml_text(ref.imu_calib))
    cap = open_capture(mars)
    assert cap.imu_calib.gyroscope_noise_density == pytest.approx(ref.imu_calib.gyroscope_noise_density, rel=1e-6)
    assert not any("no IMU noise calibration" in w for w in cap.warnings)


def test_ios_mars_metadata_gives_the_intrinsics_too(ref, tmp_path):
    mars = write_mars(ref, tmp_path / "mars", platform="iOS")  # fx, fy per frame in movie_metadata.csv ([sec])
    (mars / "calib.yaml").unlink()
    cap = open_capture(mars)
    assert (cap.camera.fx, cap.camera.fy) == (ref.camera.fx, ref.camera.fy)
    assert any("no calibration given: using the logger's intrinsics" in w for w in cap.warnings)


def test_a_focal_length_in_another_image_size_is_flagged(ref, tmp_path):
    mars = write_mars(ref, tmp_path / "mars")
    (mars / "calib.yaml").unlink()
    big = np.full(ref.num_frames, 3000.0)  # e.g. in the 4032 px sensor's pixels, not the 640 px video's
    (mars / "movie_metadata.csv").write_text(_metadata(ref, big, big))
    cap = open_capture(mars)
    assert any("gives a 12 deg field of view for 640 px wide frames" in w for w in cap.warnings)


def test_without_metadata_or_a_given_calib_it_is_still_an_error(ref, tmp_path):
    mars = write_mars(ref, tmp_path / "mars")
    (mars / "calib.yaml").unlink()
    with pytest.raises(CalibrationError, match="no camera calibration: pass --calib"):
        open_capture(mars)  # Android without movie_metadata.csv: nothing logged
    (mars / "movie_metadata.csv").write_text(
        _metadata(ref, np.full(ref.num_frames, 505.0), np.full(ref.num_frames, 503.5))
    )
    with pytest.raises(CalibrationError, match="calibration not found"):
        open_capture(mars, calib=tmp_path / "missing.yaml")  # a --calib that fails is not replaced by a guess
