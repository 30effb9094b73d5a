"""Calibrated views: a simulated run's stills and video frames (the simulator is the oracle), Middlebury's temple
(real data in ../shared/data), a COLMAP text model written and read back, and bad inputs."""

from __future__ import annotations

import logging
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tests.conftest import shared_path
from vio.errors import CaptureError, VioError
from vio.geometry import R_to_quat_wxyz, inv_T
from vio.model.views import undistorter, views_from_colmap, views_from_middlebury, views_from_run
from vio.readers import open_capture
from vio.records import CameraCalib
from vio.trajio import Trajectory

STILLS_SIZE = (1008, 756)
DURATION_S = 2.5
TEMPLE_SR = ("middlebury_temple", "templeSparseRing", "templeSR_par.txt")
TEMPLE_RING = ("middlebury_temple", "templeRing_subset_13-31", "templeR_par.txt")


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    """A 2.5 s orbit with 2 Hz stills of 1008x756 px: (capture, scenario)."""
    from vio.sim.api import load_scenario, simulate

    out = tmp_path_factory.mktemp("views") / "orbit"
    simulate("orbit", out, seed=3, duration_s=DURATION_S, stills_hz=2.0, stills_size=STILLS_SIZE)
    sc = load_scenario("orbit", 3, DURATION_S, stills_hz=2.0, stills_size=STILLS_SIZE)
    return open_capture(out), sc


def _angle(R: np.ndarray) -> float:
    return float(Rotation.from_matrix(R).magnitude())


def test_stills_views_reproduce_true_poses(sim):
    cap, sc = sim
    from vio.sim.render import camera_poses

    views = views_from_run(cap, Trajectory.from_groundtruth(cap.ground_truth))
    assert len(views) == len(cap.stills) == 5
    t_ns = np.array([v.t_ns for v in views])
    np.testing.assert_array_equal(t_ns, cap.stills.t_ns)
    truth = camera_poses(sc, t_ns, sc.stills_camera)
    for view, T in zip(views, truth, strict=True):
        assert view.size == STILLS_SIZE and view.image.dtype == np.uint8
        np.testing.assert_allclose(view.K, cap.stills.camera.K)
        assert np.linalg.norm(view.world_T_cam[:3, 3] - T[:3, 3]) < 1e-6
        assert _angle(view.world_T_cam[:3, :3].T @ T[:3, :3]) < 1e-6


def test_linear_interpolation_is_coarser(sim):
    """SLERP + linear position from 200 Hz ground truth: micrometres off (the cubic default: nanometres)."""
    cap, sc = sim
    from vio.sim.render import camera_poses

    views = views_from_run(cap, Trajectory.from_groundtruth(cap.ground_truth), interpolation="linear")
    truth = camera_poses(sc, cap.stills.t_ns, sc.stills_camera)
    err = max(np.linalg.norm(v.world_T_cam[:3, 3] - T[:3, 3]) for v, T in zip(views, truth, strict=True))
    assert 1e-8 < err < 2e-5


def test_undistortion_puts_a_cad_vertex_where_the_pinhole_projects_it(sim):
    cap, sc = sim
    from vio.sim.render import camera_poses

    cam: CameraCalib = cap.stills.camera
    world_T_cam = camera_poses(sc, cap.stills.t_ns[:1], sc.stills_camera)[0]
    corners = sc.scene.part.bounds_corners_world()
    p_cam = (corners - world_T_cam[:3, 3]) @ world_T_cam[:3, :3]
    undistort = undistorter(cam.K, cam.dist, (cam.width, cam.height))
    for p in p_cam:
        if not p[2] > 0:
            continue
        u_d, v_d = cam.project(p[None])[0]  # where the lens puts the vertex in the still
        uv = cam.K @ (p / p[2])  # where the pinhole view must have it
        if not (20 < uv[0] < cam.width - 20 and 20 < uv[1] < cam.height - 20):
            continue
        xx, yy = np.meshgrid(np.arange(cam.width), np.arange(cam.height))
        blob = np.exp(-((xx - u_d) ** 2 + (yy - v_d) ** 2) / (2 * 1.5**2)).astype(np.float32)
        out = undistort(blob)
        centroid = np.array([(out * xx).sum(), (out * yy).sum()]) / out.sum()
        assert np.linalg.norm(centroid - uv[:2]) < 0.1


def test_view_images_line_up_with_a_pinhole_rendering(sim):
    """The undistorted still and a distortion-free rendering from the true pose agree to a tenth of a pixel."""
    cap, sc = sim
    from vio.sim.render import Renderer

    view = views_from_run(cap, Trajectory.from_groundtruth(cap.ground_truth))[2]
    K = view.K
    pinhole = CameraCalib(*view.size, K[0, 0], K[1, 1], K[0, 2], K[1, 2], np.zeros(4), np.eye(4))
    rendered = Renderer(sc.scene, pinhole).render(view.world_T_cam).astype(np.float32)
    w, h = view.size
    win = (slice(h // 4, 3 * h // 4), slice(w // 4, 3 * w // 4))
    hann = cv2.createHanningWindow((w // 2, h // 2), cv2.CV_32F)
    (dx, dy), response = cv2.phaseCorrelate(view.image[win].astype(np.float32), rendered[win], hann)
    assert response > 0.3
    assert np.hypot(dx, dy) < 0.1


def test_video_views_about_2hz_with_the_video_calibration(sim):
    cap, sc = sim
    from vio.sim.render import camera_poses

    views = views_from_run(cap, Trajectory.from_groundtruth(cap.ground_truth), source="video")
    t_ns = np.array([v.t_ns for v in views])
    assert len(views) == 5 and np.all(np.abs(np.diff(t_ns) - 500_000_000) <= 50_000_000)
    assert views[0].size == (cap.camera.width, cap.camera.height)
    truth = camera_poses(sc, t_ns, sc.camera)
    assert max(np.linalg.norm(v.world_T_cam[:3, 3] - T[:3, 3]) for v, T in zip(views, truth, strict=True)) < 1e-6
    assert len(views_from_run(cap, Trajectory.from_groundtruth(cap.ground_truth), max_views=3)) == 3


def test_images_outside_the_trajectory_are_skipped(sim, caplog):
    cap, _ = sim
    traj = Trajectory.from_groundtruth(cap.ground_truth)
    late = traj.subset(traj.t_ns >= cap.stills.t_ns[2] - 5_000_000)
    with caplog.at_level(logging.WARNING, logger="vio.model.views"):
        views = views_from_run(cap, late)
    assert [v.t_ns for v in views] == list(cap.stills.t_ns[2:])
    assert "2 of 5 stills lie outside" in caplog.text
    gap = traj.subset((traj.t_ns < cap.stills.t_ns[1] - 100_000_000) | (traj.t_ns > cap.stills.t_ns[3] - 200_000_000))
    assert [v.t_ns for v in views_from_run(cap, gap)] == [cap.stills.t_ns[i] for i in (0, 3, 4)]
    with pytest.raises(CaptureError, match="none of the stills lies inside"):
        views_from_run(cap, traj.subset(traj.t_ns > cap.stills.t_ns[-1]))
    with pytest.raises(CaptureError, match="view source"):
        views_from_run(cap, traj, source="photos")


def test_middlebury_sparse_ring():
    """16 views of 640x480; the camera centres lie on a horizontal circle of radius 0.5626 m (found by a circle
    fit, residual 0.13 mm), 0.56-0.57 m from the temple's bounding-box centre, each looking at it within 3 deg."""
    views = views_from_middlebury(shared_path(*TEMPLE_SR))
    assert len(views) == 16 and all(v.size == (640, 480) for v in views)
    np.testing.assert_allclose(views[0].K, [[1520.4, 0, 302.32], [0, 1525.9, 246.87], [0, 0, 1]])
    centres = np.array([v.world_T_cam[:3, 3] for v in views])
    mean = centres.mean(axis=0)
    _, _, (e1, e2, normal) = np.linalg.svd(centres - mean)
    assert np.abs((centres - mean) @ normal).max() < 2e-3  # a plane ring
    xy = np.column_stack([(centres - mean) @ e1, (centres - mean) @ e2])
    a, b, c = np.linalg.lstsq(np.column_stack([2 * xy, np.ones(len(xy))]), (xy**2).sum(axis=1), rcond=None)[0]
    radius = np.sqrt(c + a * a + b * b)
    assert abs(radius - 0.5626) < 1e-3
    assert np.abs(np.linalg.norm(xy - [a, b], axis=1) - radius).max() < 5e-4
    box_centre = 0.5 * (np.array([-0.073568, 0.021728, -0.012445]) + np.array([0.028855, 0.181892, 0.062736]))
    for v in views:
        to_box = box_centre - v.world_T_cam[:3, 3]
        assert 0.55 < np.linalg.norm(to_box) < 0.58
        assert np.degrees(np.arccos(v.world_T_cam[:3, 2] @ to_box / np.linalg.norm(to_box))) < 3.0
        # x = K [R | t] X: the box centre projects where the view's pose and K put it
        p = inv_T(v.world_T_cam) @ np.append(box_centre, 1.0)
        assert 0 < (v.K @ p[:3])[0] / p[2] < 640


def test_middlebury_subset_skips_absent_images(caplog):
    with caplog.at_level(logging.WARNING, logger="vio.model.views"):
        views = views_from_middlebury(shared_path(*TEMPLE_RING))
    assert [v.name for v in views] == [f"templeR{i:04d}.png" for i in range(13, 32)]
    assert "28 of 47 images absent" in caplog.text


def _write_par(tmp_path: Path, lines: list[str]) -> Path:
    path = tmp_path / "set_par.txt"
    path.write_text("\n".join(lines) + "\n")
    cv2.imwrite(str(tmp_path / "a.png"), np.full((48, 64), 128, np.uint8))
    return path


GOOD_PAR = "a.png 100 0 32 0 100 24 0 0 1 1 0 0 0 1 0 0 0 1 0 0 0.5"


@pytest.mark.parametrize(
    ("lines", "message"),
    [
        (["1", GOOD_PAR.rsplit(" ", 1)[0]], "set_par.txt:2: expected 'name k11..k33 r11..r33 t1 t2 t3' (22 fields)"),
        (["1", GOOD_PAR.replace(" 100 ", " x ", 1)], "set_par.txt:2: a.png: not a number"),
        (["2", GOOD_PAR], "set_par.txt:1: header says 2 images, the file lists 1"),
        (["one", GOOD_PAR], "set_par.txt:1: first line must be the number of images"),
        (["1", GOOD_PAR.replace(" 1 0 0 0 1 0 0 0 1 ", " 2 0 0 0 1 0 0 0 1 ")], "set_par.txt:2: rotation is not"),
        (["1", GOOD_PAR.replace("a.png", "b.png")], "none of the listed images is present"),
    ],
)
def test_middlebury_bad_input_is_one_line(tmp_path, lines, message):
    with pytest.raises(CaptureError) as err:
        views_from_middlebury(_write_par(tmp_path, lines))
    assert message in str(err.value) and "\n" not in str(err.value)


def test_middlebury_good_minimal_and_missing_file(tmp_path):
    (view,) = views_from_middlebury(_write_par(tmp_path, ["1", GOOD_PAR]))
    np.testing.assert_allclose(view.world_T_cam[:3, 3], [0, 0, -0.5])
    with pytest.raises(VioError, match="nothing_par.txt: file not found"):
        views_from_middlebury(tmp_path / "nothing_par.txt")


def _write_colmap(root: Path, cameras: list[str], views, image_names: list[str], camera_ids: list[int]) -> None:
    (root / "cameras.txt").write_text("# Camera list\n" + "\n".join(cameras) + "\n")
    lines = ["# Image list with two lines of data per image:", "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, ..."]
    for k, (v, name, cam) in enumerate(zip(views, image_names, camera_ids, strict=True), start=1):
        cam_T_world = inv_T(v.world_T_cam)
        q = R_to_quat_wxyz(cam_T_world[:3, :3])
        t = cam_T_world[:3, 3]
        lines.append(f"{k} {' '.join(f'{x:.17g}' for x in (*q, *t))} {cam} {name}")
        lines.append("" if k % 2 else "10.5 20.5 -1 30.25 40.75 7")  # 2D points: none, or two
    (root / "images.txt").write_text("\n".join(lines) + "\n")


def test_colmap_round_trip_of_simulated_stills(sim, tmp_path):
    """Distorted stills written with an OPENCV camera (COLMAP's principal point is half a pixel further) read back
    with the same K, poses (1e-9) and undistorted images as views_from_run gives; a PINHOLE camera too."""
    cap, _ = sim
    views = views_from_run(cap, Trajectory.from_groundtruth(cap.ground_truth))
    cam = cap.stills.camera
    names = []
    for i in range(len(views)):
        names.append(f"still_{i}.png")
        cv2.imwrite(str(tmp_path / names[-1]), cap.stills.load_image(i))
    k1, k2, p1, p2 = (float(c) for c in cam.dist)
    intrinsics = f"{cam.width} {cam.height} {cam.fx!r} {cam.fy!r} {cam.cx + 0.5!r} {cam.cy + 0.5!r}"
    opencv, pinhole = f"1 OPENCV {intrinsics} {k1!r} {k2!r} {p1!r} {p2!r}", f"2 PINHOLE {intrinsics}"
    ids = [1, 1, 2, 1, 2]
    _write_colmap(tmp_path, [opencv, pinhole], views, names, ids)
    back = views_from_colmap(tmp_path, tmp_path)
    assert [v.name for v in back] == names
    for v, b, cam_id, i in zip(views, back, ids, range(len(views)), strict=True):
        np.testing.assert_allclose(b.K, v.K, atol=1e-9)
        np.testing.assert_allclose(b.world_T_cam, v.world_T_cam, atol=1e-9)
        expected = v.image if cam_id == 1 else cap.stills.load_image(i)
        np.testing.assert_array_equal(b.image, expected)


def test_colmap_simple_models(tmp_path):
    cv2.imwrite(str(tmp_path / "a.png"), np.full((48, 64, 3), 100, np.uint8))
    view = SimpleNamespace(world_T_cam=np.eye(4))
    for model, params in [
        ("SIMPLE_PINHOLE", "50 32.5 24.5"),
        ("SIMPLE_RADIAL", "50 32.5 24.5 0.01"),
        ("RADIAL", "50 32.5 24.5 0.01 -0.002"),
    ]:
        _write_colmap(tmp_path, [f"7 {model} 64 48 {params}"], [view], ["a.png"], [7])
        (back,) = views_from_colmap(tmp_path, tmp_path)
        np.testing.assert_allclose(back.K, [[50, 0, 32], [0, 50, 24], [0, 0, 1]])
        assert back.image.shape == (48, 64, 3) and (back.image[24, 32] == 100).all()


@pytest.mark.parametrize(
    ("camera", "image_line", "message"),
    [
        ("1 FISHEYE 64 48 50 32 24 0.1", None, "cameras.txt:2: camera model FISHEYE not supported"),
        ("1 PINHOLE 64 48 50 50 32", None, "cameras.txt:2: PINHOLE takes 4 parameters, got 3"),
        ("1 PINHOLE 64 48 50 50 32 24", "1 1 0 0 0 0 0 0 9 a.png", "images.txt:2: camera 9 is not in cameras.txt"),
        ("1 PINHOLE 64 48 50 50 32 24", "1 2 0 0 0 0 0 0 1 a.png", "images.txt:2: quaternion norm 2.0000 is not 1"),
        ("1 PINHOLE 64 48 50 50 32 24", "1 1 0 0 0 0 0 1 a.png", "images.txt:2: expected 'IMAGE_ID QW QX QY QZ"),
        ("1 PINHOLE 64 48 50 50 32 24", "1 1 0 0 0 0 0 0 1 b.png", "b.png missing or cannot be decoded"),
    ],
)
def test_colmap_bad_input_is_one_line(tmp_path, camera, image_line, message):
    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((48, 64), np.uint8))
    (tmp_path / "cameras.txt").write_text("# cameras\n" + camera + "\n")
    (tmp_path / "images.txt").write_text("# images\n" + (image_line or "1 1 0 0 0 0 0 0 1 a.png") + "\n\n")
    with pytest.raises(CaptureError) as err:
        views_from_colmap(tmp_path, tmp_path)
    assert message in str(err.value) and "\n" not in str(err.value)
