"""vio simulate calibration (a board on a wall, filmed hand-held) is the oracle of vio calibrate camera."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import yaml

from tests.conftest import ROOT
from vio.calibrate.board import BoardDetector, parse_board
from vio.calibrate.camera import calibrate_camera
from vio.calibrate.views import find_views
from vio.readers import open_capture
from vio.readers.calib import load_calibration


@pytest.fixture(scope="module")
def calibration_capture(tmp_path_factory):
    out = tmp_path_factory.mktemp("simcal") / "cap"
    r = subprocess.run(
        [sys.executable, "-m", "vio.cli", "simulate", "calibration", "--board", "chessboard:9x6:30"]
        + ["--duration", "8", "--seed", "3", "--out", str(out)],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert r.returncode == 0, r.stderr
    return out


def test_the_capture_is_a_capture_with_imu_and_ground_truth(calibration_capture):
    cap = open_capture(calibration_capture)
    assert len(cap.frame_t_ns) == 160 and len(cap.imu) == 1601 and cap.ground_truth is not None
    gyro_rms = np.sqrt(np.mean(cap.imu.gyro**2, axis=0))
    assert np.all(gyro_rms > 0.05)  # hand-held: it turns about every axis
    meta = yaml.safe_load((calibration_capture / "scene" / "board.yaml").read_text())
    assert meta["board"] == "chessboard:9x6:30" and np.asarray(meta["world_T_board"]).shape == (4, 4)


def test_calibration_recovers_the_simulators_intrinsics(calibration_capture, tmp_path):
    truth = load_calibration(calibration_capture).camera
    board = parse_board("chessboard:9x6:30")
    vs = find_views([calibration_capture], BoardDetector(board), max_views=40)
    assert len(vs.views) == 40
    cal = calibrate_camera(vs.views, board, vs.image_size, "radtan")
    for name in ("fx", "fy", "cx", "cy"):
        want = getattr(truth, name)
        assert abs(cal.params()[name] / want - 1) < 0.003, (name, cal.params()[name], want)
    assert abs(cal.dist[0] / truth.dist[0] - 1) < 0.10 and abs(cal.dist[1] / truth.dist[1] - 1) < 0.35
    assert cal.rms_px < 0.2 and cal.coverage > 0.5


def test_a_board_spec_error_is_one_line(tmp_path):
    r = subprocess.run(
        [sys.executable, "-m", "vio.cli", "simulate", "calibration", "--board", "chessboard:9"]
        + ["--out", str(tmp_path / "c")],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "expected chessboard" in r.stderr
    r = subprocess.run(
        [sys.executable, "-m", "vio.cli", "simulate", "orbit", "--board", "chessboard:9x6:30"]
        + ["--out", str(tmp_path / "o"), "--no-images", "--duration", "1"],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert r.returncode == 2 and "--board is for the calibration scenario" in r.stderr
