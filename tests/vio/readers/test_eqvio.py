"""gtsam's real eqvio file (EuRoC V1_01, first 30 s): IMU, feature tracks in pixels, calibration from meta rows."""

from __future__ import annotations

import numpy as np
import pytest

from vio.errors import CaptureError
from vio.readers.eqvio import default_eqvio_path, is_eqvio_file, read_eqvio


@pytest.fixture(scope="module")
def cap():
    return read_eqvio()


def test_counts_and_rates(cap):
    assert len(cap.imu) == 6001 and cap.num_frames == 601 and len(cap.tracks) == 601
    assert sum(len(t.ids) for t in cap.tracks) == 13316
    assert len(np.unique(np.concatenate([t.ids for t in cap.tracks]))) == 307
    dt = np.diff(cap.frame_t_ns) * 1e-9
    assert abs(np.median(dt) - 0.05) < 1e-4 and abs(np.median(np.diff(cap.imu.t_ns)) * 1e-9 - 0.005) < 1e-5
    assert cap.tracks[0].t_ns == cap.frame_t_ns[0] == 1403715273262143100  # t0_abs read as an exact decimal


def test_calibration_is_euroc_cam0(cap):
    # EuRoC cam0 T_BS (sensor.yaml): rotation close to a 90 deg turn about z, translation (-0.0216, -0.0647, 0.0098)
    T = cap.camera.body_T_cam
    assert np.allclose(T[:3, 3], [-0.0216401454975, -0.064676986768, 0.00981073058949], atol=1e-9)
    assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)
    assert np.allclose(
        T[:3, :3], [[0.0149, -0.9999, 0.0041], [0.9996, 0.0150, 0.0257], [-0.0258, 0.0038, 0.9997]], atol=2e-3
    )
    assert (cap.camera.fx, cap.camera.cy) == (458.654, 248.375) and not np.any(cap.camera.dist)
    # at rest the specific force is about +g (rotors idle, so the raw samples are noisy)
    assert abs(np.linalg.norm(cap.imu.acc[:200].mean(axis=0)) - 9.8) < 0.1


def test_tracks_are_pixels_inside_the_image(cap):
    # undistorted pixels: EuRoC's barrel distortion (k1 = -0.28) pushes the image corners outwards
    uv = np.concatenate([t.uv for t in cap.tracks])
    assert uv[:, 0].min() > -250 and uv[:, 0].max() < 1000 and uv[:, 1].min() > -200 and uv[:, 1].max() < 700
    inside = (uv[:, 0] > 0) & (uv[:, 0] < 752) & (uv[:, 1] > 0) & (uv[:, 1] < 480)
    assert inside.mean() > 0.6
    assert np.median(uv[:, 0]) == pytest.approx(cap.camera.cx, abs=150)


def test_detection_and_errors(tmp_path):
    assert is_eqvio_file(default_eqvio_path())
    lines = default_eqvio_path().read_text().splitlines()
    bad = tmp_path / "bad.csv"
    bad.write_text("\n".join(lines[:60] + ["gps" + lines[60][lines[60].index(",") :]] + lines[61:200]) + "\n")
    with pytest.raises(CaptureError, match=r"bad.csv:61: unknown row_type 'gps'"):
        read_eqvio(bad)
    nometa = tmp_path / "nometa.csv"
    nometa.write_text("\n".join([lines[0]] + [ln for ln in lines[1:300] if "camera_fx" not in ln]) + "\n")
    with pytest.raises(CaptureError, match="meta rows missing: camera_fx"):
        read_eqvio(nometa)
    assert not is_eqvio_file(bad.with_name("missing.csv"))
