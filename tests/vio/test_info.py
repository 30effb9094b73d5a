"""`vio info` and the camera-IMU time-offset estimate."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tests.conftest import ROOT, shared_path
from tests.rotation_capture import rotation_capture
from tests.writers.phone import write_mars
from vio.info import capture_info
from vio.readers.offset import estimate_time_offset, pair_rotation


@pytest.mark.parametrize("offset_s", [0.025, -0.04])
def test_time_offset_is_recovered_from_rotation_rates(offset_s):
    cap = rotation_capture(duration_s=4.0, fps=20.0, offset_s=offset_s)
    est = estimate_time_offset(cap)
    assert est.offset_ns is not None and est.note == ""
    assert abs(est.offset_ns * 1e-9 - offset_s) < 0.002
    assert est.correlation > 0.95 and est.pairs > 60
    assert abs(est.rate_ratio - 1.0) < 0.05


def test_essential_matrix_rotation_with_translation():
    """Pairs with parallax take the essential-matrix path; the rotation angle is still right."""
    rng = np.random.default_rng(3)
    p_w = np.column_stack([rng.uniform(-1, 1, 200), rng.uniform(-1, 1, 200), rng.uniform(1.5, 4.0, 200)])
    R = Rotation.from_rotvec([0.01, 0.04, -0.02]).as_matrix()
    t = np.array([0.15, -0.02, 0.05])
    p_c1 = p_w @ R.T + t
    xn0 = p_w[:, :2] / p_w[:, 2:]
    xn1 = p_c1[:, :2] / p_c1[:, 2:]
    angle = pair_rotation(xn0, xn1, focal_px=500.0)
    assert angle is not None and abs(angle - np.linalg.norm([0.01, 0.04, -0.02])) < 1e-3


def test_static_capture_reports_no_offset_and_real_streams():
    text = capture_info(shared_path("euroc_v1_01"))
    assert "format: asl" in text and "95 frames, 20.00 Hz" in text
    assert "29120 samples, 200.0 Hz" in text and "gaps: none" in text
    assert "ground truth: 2895 poses" in text
    assert "not estimated (too little rotation to correlate)" in text


def test_cli_info_on_a_phone_capture(tmp_path):
    cap = rotation_capture(duration_s=3.0, fps=20.0, offset_s=0.03)
    write_mars(cap, tmp_path / "mars")
    r = subprocess.run(
        [sys.executable, "-m", "vio.cli", "info", str(tmp_path / "mars")], capture_output=True, text=True, cwd=ROOT
    )
    assert r.returncode == 0, r.stderr
    assert "format: mars" in r.stdout and "60 frames, 20.00 Hz" in r.stdout
    line = next(x for x in r.stdout.splitlines() if x.startswith("camera-IMU time offset"))
    ms = float(line.split(":")[1].split("ms")[0])
    assert abs(ms - 30.0) < 2.0


def test_info_lists_problems_instead_of_failing(tmp_path):
    cap = rotation_capture(duration_s=2.0, fps=20.0)
    path = write_mars(cap, tmp_path / "mars")
    (path / "calib.yaml").unlink()
    text = capture_info(path)
    assert "calibration: MISSING" in text
    assert "warning:" in text and "no camera calibration" in text


def test_time_offset_on_the_simulated_orbit(sim_capture):
    """Real texture and parallax (essential-matrix path): a 30 ms shift of the frame clock is recovered."""
    import dataclasses

    from vio.readers import open_capture

    cap = open_capture(sim_capture("orbit", duration_s=3.0))
    base = estimate_time_offset(cap, max_offset_s=0.1)
    shifted = estimate_time_offset(dataclasses.replace(cap, frame_t_ns=cap.frame_t_ns - 30_000_000), max_offset_s=0.1)
    assert base.offset_ns is not None and shifted.offset_ns is not None
    assert base.correlation > 0.9 and shifted.correlation > 0.9
    # the simulator's gyro itself sits about +3 ms from its ground-truth rotation (see docs/BENCHMARKS.md)
    assert abs(base.offset_ns * 1e-6) < 8.0
    assert abs((shifted.offset_ns - base.offset_ns) * 1e-6 - 30.0) < 2.0


def test_info_on_gtsams_eqvio_tracks():
    import gtsam

    text = capture_info(gtsam.findExampleDataFile("eqvio_processed_30s.csv"))
    assert "format: eqvio" in text and "601 frames of precomputed feature tracks" in text
    assert "6001 samples, 200.0 Hz" in text and "time offset" not in text


def test_info_reports_every_problem_not_only_the_first(sim_capture, tmp_path):
    """Issue 20: an accelerometer without gravity, a calibration for another image size, a ground-truth file with a
    NaN and an image that does not decode: the three problems are listed, the image is left out of the time offset,
    and the rest of the summary stands."""
    import os
    import shutil

    cap = tmp_path / "cap"
    shutil.copytree(sim_capture("orbit", 4.0), cap, copy_function=os.link)
    mav0 = cap / "mav0"
    imu_csv = mav0 / "imu0" / "data.csv"
    lines = imu_csv.read_text().splitlines()
    rows = np.array([r.split(",") for r in lines[1:]], float)
    rows[:, 4:7] = 0.5 * (rows[:, 4:7] - np.median(rows[:, 4:7], axis=0))  # linear acceleration: no gravity
    imu_csv.unlink()
    imu_csv.write_text(lines[0] + "\n" + "\n".join(f"{int(r[0])}," + ",".join(f"{v:.9g}" for v in r[1:]) for r in rows))
    yaml_path = mav0 / "cam0" / "sensor.yaml"
    text = yaml_path.read_text().replace("resolution: [640, 480]", "resolution: [1280, 960]")
    yaml_path.unlink()
    yaml_path.write_text(text)
    gt_csv = mav0 / "state_groundtruth_estimate0" / "data.csv"
    gt = gt_csv.read_text().splitlines()
    gt[5] = ",".join([gt[5].split(",")[0], "nan", *gt[5].split(",")[2:]])
    gt_csv.unlink()
    gt_csv.write_text("\n".join(gt) + "\n")
    first = sorted((mav0 / "cam0" / "data").iterdir())[0]
    first.unlink()
    first.write_bytes(b"not a png")
    r = subprocess.run([sys.executable, "-m", "vio.cli", "info", str(cap)], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0 and "Traceback" not in r.stderr, r.stderr
    out = r.stdout
    assert "problems: 3 (vio run stops at the first)" in out, out
    assert "NaN in ground truth" in out and "accelerometer has no gravity" in out
    assert "images are 640x480 but the calibration is for 1280x960" in out
    assert "camera: 80 frames" in out and "imu: " in out  # the readable streams are still described
    assert "camera-IMU time offset: " in out  # estimated from the frames that decode


def test_info_reports_every_unreadable_stream_of_a_phone_log(tmp_path):
    """A MARS folder whose IMU goes backwards, whose video is empty and whose calibration is not YAML: three lines."""
    path = write_mars(rotation_capture(duration_s=1.0, fps=10.0), tmp_path / "mars")
    imu = path / "gyro_accel.csv"
    lines = imu.read_text().splitlines()
    lines[1:] = lines[1:][::-1]
    imu.write_text("\n".join(lines) + "\n")
    (path / "movie.mp4").write_bytes(b"")
    (path / "calib.yaml").write_text("cam0: [unclosed\n")
    text = capture_info(path)
    assert "problems: " in text and "IMU timestamp goes backwards" in text
    assert "movie.mp4: video cannot be opened" in text and "calib.yaml: not valid YAML" in text


@pytest.mark.parametrize("ros", ["ros1", "ros2"])
def test_info_reports_every_problem_of_a_bag(tmp_path, ros):
    """A bag whose calibration is not YAML and whose accelerometer is in g: both listed (the calibration used to
    end the report), with what follows (no camera calibration), and the streams that read are described."""
    import dataclasses

    from tests.writers.ros import write_ros1, write_ros2
    from vio.records import ImuSeries

    cap = rotation_capture(duration_s=1.0, fps=10.0)
    cap = dataclasses.replace(cap, imu=ImuSeries(cap.imu.t_ns, cap.imu.gyro, cap.imu.acc / 9.81))
    if ros == "ros1":
        path = write_ros1(cap, tmp_path / "log.bag")
        calib = tmp_path / "calib.yaml"
    else:
        path = write_ros2(cap, tmp_path / "bag2")
        calib = path / "calib.yaml"
    calib.write_text("cam0: [unclosed\n")
    r = subprocess.run([sys.executable, "-m", "vio.cli", "info", str(path)], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0 and "Traceback" not in r.stderr, r.stderr
    assert "problems: 3 (vio run stops at the first)" in r.stdout, r.stdout
    assert "calib.yaml: not valid YAML" in r.stdout and "accelerometer looks like it is in g" in r.stdout
    assert "no camera calibration: pass --calib" in r.stdout
    assert f"format: {ros}" in r.stdout and "camera: 10 frames" in r.stdout and "imu: " in r.stdout


def test_info_reports_every_problem_of_an_eqvio_file(tmp_path):
    """gtsam's eqvio file with a bad IMU row, two bad feature rows and an unknown row type: the first problem of
    each row type (with the count of its bad rows), and what follows from leaving those streams out."""
    import gtsam

    lines = open(gtsam.findExampleDataFile("eqvio_processed_30s.csv"), encoding="utf-8").read().splitlines()
    imu_rows = [i for i, s in enumerate(lines) if s.startswith("imu,")]
    feature_rows = [i for i, s in enumerate(lines) if s.startswith("vision_feature,")]
    cells = lines[imu_rows[10]].split(",")
    cells[2] = "soon"  # t_rel
    lines[imu_rows[10]] = ",".join(cells)
    for i in feature_rows[100:102]:
        cells = lines[i].split(",")
        cells[2] = "nan"
        lines[i] = ",".join(cells)
    lines.insert(5, "junk" + lines[5][lines[5].index(",") :])
    path = tmp_path / "eqvio.csv"
    path.write_text("\n".join(lines) + "\n")
    text = capture_info(path)
    assert "problems: 5 (vio run stops at the first)" in text, text
    assert f"{path}:{imu_rows[10] + 2}: t_rel 'soon' is not a number" in text  # the insert moved the rows by one
    assert f"{path}:{feature_rows[100] + 2}: t_rel is not finite (the first of 2 bad vision_feature rows)" in text
    assert f"{path}:6: unknown row_type 'junk'" in text
    assert "no IMU stream" in text and "no camera frames" in text
