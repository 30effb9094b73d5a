"""vio calibrate camera: OpenCV's known answer, simulated board views as the oracle, files vio reads, bad input."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tests.conftest import ROOT, shared_path
from vio.calibrate.board import BoardDetector, parse_board
from vio.calibrate.camera import calibrate_camera
from vio.calibrate.views import View, find_views
from vio.errors import CalibrationError
from vio.readers.calib import load_calibration
from vio.sim import rig
from vio.sim.board_render import charuco_texture, chessboard_texture, render_board, undistorted_rays

OPENCV_TEST = {"fx": 532.80992189, "fy": 532.93346422, "cx": 342.4952186, "cy": 233.8879292}  # OpenCV's test
OPENCV_TEST_RMS_PX = 0.196334638034


def _opencv_images() -> list:
    folder = shared_path("opencv_chessboard_stereo")
    images = [folder / f"left{i:02d}.jpg" for i in range(1, 15) if i != 10]
    if not all(p.exists() for p in images):
        pytest.skip(f"{folder}: left01..14.jpg incomplete")
    return images


@pytest.mark.parametrize("model", ["opencv", "radtan"])
def test_opencv_known_answer(model):
    """OpenCV's own calibration test: left01..14 without left10, 9x6 corners, default flags (opencv) and Kalibr's
    radtan (k3 fixed) both land within 1 px of its intrinsics with its RMS."""
    board = parse_board("chessboard:9x6:25")
    vs = find_views(_opencv_images(), BoardDetector(board))
    assert len(vs.views) == 13 and not vs.rejected
    cal = calibrate_camera(vs.views, board, vs.image_size, model)
    assert not cal.dropped
    for k, v in OPENCV_TEST.items():
        assert abs(cal.params()[k] - v) < 1.0, (k, cal.params()[k])
    assert abs(cal.rms_px - OPENCV_TEST_RMS_PX) < 0.005
    assert all(0 < cal.std[k] < 1.0 for k in OPENCV_TEST)  # sub-pixel one-sigma on fx, fy, cx, cy


def test_cli_writes_a_camchain_that_vio_reads(tmp_path):
    out = tmp_path / "calib" / "camchain.yaml"
    r = subprocess.run(
        [sys.executable, "-m", "vio.cli", "calibrate", "camera", *map(str, _opencv_images())]
        + ["--board", "chessboard:9x6:25", "--out", str(out)],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert r.returncode == 0, r.stderr
    assert "RMS 0.196 px" in r.stdout
    folder = out.parent
    for name in ("camera_coverage.png", "camera_residuals.png", "camera_calibration.json"):
        assert (folder / name).read_bytes()[:4] in (b"\x89PNG", b"{\n  ")
    # what `vio run --calib` reads: the camchain, the folder, or the ASL sensor.yaml
    for calib in (out, folder, folder / "cam0" / "sensor.yaml"):
        cam = load_calibration(calib).camera
        assert abs(cam.fx - OPENCV_TEST["fx"]) < 1.0 and abs(cam.cy - OPENCV_TEST["cy"]) < 1.0
        assert cam.dist.shape == (4,) and (cam.width, cam.height) == (640, 480)
        assert np.allclose(cam.body_T_cam[:3, 2], [0, 0, -1])  # the nominal phone mount: camera looks along -z


@pytest.fixture(scope="module")
def sim_views():
    """Views of a 9x6 chessboard rendered through the simulator's phone camera at random poses."""
    cam = rig.default_camera()
    board = parse_board("chessboard:9x6:30")
    tex = chessboard_texture(9, 6, 0.03)
    rays = undistorted_rays(cam)
    rng = np.random.default_rng(7)
    det = BoardDetector(board)
    views, images = [], []
    centre = board.corners_board().mean(axis=0)
    for k in range(16):
        R = Rotation.from_euler("xyz", rng.uniform(-35, 35, 3), degrees=True).as_matrix()
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = [rng.uniform(-0.08, 0.08), rng.uniform(-0.06, 0.06), rng.uniform(0.3, 0.6)] - R @ centre
        img = render_board(tex, cam, T, rays, rng, 2.0)
        d = det.detect(img)
        if d is not None:
            views.append(View(f"sim{k}", d, 1.0))
            images.append(img)
    return cam, board, views, images


def test_simulated_views_recover_the_intrinsics(sim_views):
    cam, board, views, _ = sim_views
    assert len(views) >= 12
    cal = calibrate_camera(views, board, (cam.width, cam.height), "radtan")
    truth = {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy}
    for k, v in truth.items():
        assert abs(cal.params()[k] / v - 1) < 0.003, (k, cal.params()[k], v)
        assert abs(cal.params()[k] - v) < 4 * cal.std[k] + 0.05  # the truth within the stated uncertainty
    assert abs(cal.dist[0] / cam.dist[0] - 1) < 0.05 and abs(cal.dist[1] / cam.dist[1] - 1) < 0.25
    assert cal.rms_px < 0.15


def test_an_outlier_view_is_dropped_with_its_reason(sim_views):
    cam, board, views, _ = sim_views
    bad = views[3]
    rng = np.random.default_rng(0)
    noisy = type(bad.detection)(bad.detection.ids, bad.detection.uv + rng.normal(0, 2.0, bad.detection.uv.shape))
    corrupted = [*views[:3], View(bad.name, noisy, 1.0), *views[4:]]
    cal = calibrate_camera(corrupted, board, (cam.width, cam.height), "radtan")
    assert [n for n, _ in cal.dropped] == [bad.name]
    assert "x the median view RMS" in cal.dropped[0][1]
    assert bad.name not in cal.view_names and abs(cal.fx / cam.fx - 1) < 0.003


def test_charuco_views(tmp_path):
    cam = rig.default_camera()
    board = parse_board("charuco:8x6:30:22:DICT_4X4_50")
    tex = charuco_texture(8, 6, 0.03, 0.022, "DICT_4X4_50")
    rays = undistorted_rays(cam)
    rng = np.random.default_rng(3)
    det = BoardDetector(board)
    centre = board.corners_board().mean(axis=0)
    views = []
    for k in range(12):
        R = Rotation.from_euler("xyz", rng.uniform(-35, 35, 3), degrees=True).as_matrix()
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = [rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05), rng.uniform(0.35, 0.55)] - R @ centre
        d = det.detect(render_board(tex, cam, T, rays, rng, 2.0))
        if d is not None:
            views.append(View(f"c{k}", d, 1.0))
    assert len(views) >= 10
    cal = calibrate_camera(views, board, (cam.width, cam.height), "radtan")
    assert abs(cal.fx / cam.fx - 1) < 0.003 and abs(cal.cy / cam.cy - 1) < 0.005


def test_frames_picked_from_a_video(sim_views, tmp_path):
    import cv2

    cam, board, _, images = sim_views
    path = tmp_path / "board.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 15.0, (cam.width, cam.height), False)
    blank = np.full((cam.height, cam.width), 128, np.uint8)
    for img in [blank, *images]:
        writer.write(img)
    writer.release()
    vs = find_views([path], BoardDetector(board), max_views=8)
    assert len(vs.views) == 8 and vs.rate_hz == pytest.approx(15.0)
    reasons = dict(vs.rejected)
    assert reasons["board.avi#0"] == "board not found"
    assert sum(r == "not needed for coverage" for r in reasons.values()) == len(images) - 8
    cal = calibrate_camera(vs.views, board, vs.image_size, "radtan")
    assert abs(cal.fx / cam.fx - 1) < 0.01


def test_blurred_video_frames_are_dropped_with_the_reason(sim_views, tmp_path):
    import cv2

    cam, board, _, images = sim_views
    path = tmp_path / "shaky.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (cam.width, cam.height), False)
    for i, img in enumerate(images):
        writer.write(cv2.GaussianBlur(img, (0, 0), 4.0) if i % 4 == 0 else img)  # every 4th frame shaken
    writer.release()
    vs = find_views([path], BoardDetector(board), max_views=40)
    blurred = sorted(int(n.split("#")[1]) for n, r in vs.rejected if r.startswith("blurred"))
    assert blurred == list(range(0, len(images), 4))
    assert len(vs.views) == len(images) - len(blurred)


def test_the_sb_detector(sim_views):
    cam, board, _, images = sim_views
    det = BoardDetector(board, "sb")
    views = [View(str(i), d, 1.0) for i, img in enumerate(images) if (d := det.detect(img)) is not None]
    assert len(views) == len(images)
    cal = calibrate_camera(views, board, (cam.width, cam.height), "radtan")
    assert abs(cal.fx / cam.fx - 1) < 0.003 and abs(cal.cx / cam.cx - 1) < 0.003 and cal.rms_px < 0.2


def test_equidistant_writes_kalibr_files_that_vio_run_refuses_clearly(sim_views, tmp_path):
    import cv2

    from vio.calibrate.camera_files import calibrate_camera_files

    _, _, _, images = sim_views
    paths = []
    for i, img in enumerate(images):
        paths.append(tmp_path / f"{i:02d}.png")
        cv2.imwrite(str(paths[-1]), img)
    text = calibrate_camera_files(paths, "chessboard:9x6:30", tmp_path / "out" / "camchain.yaml", "equidistant")
    assert "pinhole-equidistant" in text and "for other tools" in text
    assert "distortion_model: equidistant" in (tmp_path / "out" / "camchain.yaml").read_text()
    with pytest.raises(CalibrationError, match="pinhole-radtan only"):
        load_calibration(tmp_path / "out" / "camchain.yaml")


def _one_line_error(args: list[str]) -> str:
    r = subprocess.run([sys.executable, "-m", "vio.cli", *args], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr
    return r.stderr


def test_no_board_in_any_view_is_one_line(tmp_path):
    import cv2

    for i in range(3):
        cv2.imwrite(str(tmp_path / f"{i}.png"), np.full((480, 640), 100 + 40 * i, np.uint8))
    err = _one_line_error(
        ["calibrate", "camera", *[str(tmp_path / f"{i}.png") for i in range(3)]]
        + ["--board", "chessboard:9x6:25", "--out", str(tmp_path / "c.yaml")]
    )
    assert "no chessboard 9x6 inner corners, 25 mm squares found in any of 3 view(s)" in err


def test_bad_board_spec_is_one_line(tmp_path):
    err = _one_line_error(["calibrate", "camera", "x.png", "--board", "chess:9x6", "--out", str(tmp_path / "c.yaml")])
    assert "expected chessboard:COLSxROWS:SQUARE_MM" in err
