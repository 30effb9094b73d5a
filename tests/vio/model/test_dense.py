"""Multi-view stereo against the simulator's ground-truth depth: a speckled cube seen by five pinhole views
(1008x756 px, optical axes 6-15 deg from the middle one's), the ROI geometry, neighbour choice and bad settings."""

from __future__ import annotations

import numpy as np
import pytest

from vio.errors import ConfigError
from vio.model.dense import DenseConfig, depth_maps, iter_depth_maps, select_neighbours
from vio.model.dense_common import Crop, roi_bbox, roi_window
from vio.model.records import Roi, View
from vio.records import CameraCalib

SIZE = (1008, 756)
TIMES_S = (2.3, 2.65, 3.0, 3.35, 3.7)  # optical axes about 6 deg apart; the reference is the middle one
REF = 2
# Measured with these views (seed 0, 1008x756, half the default stills' resolution): sweep median 0.11 mm, p90
# 0.38 mm, completeness 0.89; sgbm median 0.26 mm, p90 0.73 mm, completeness 0.96. The bounds leave about 2x.
BOUNDS = {"sweep": (0.25, 0.8, 0.8), "sgbm": (0.5, 1.5, 0.85)}  # median mm, p90 mm, completeness


def true_depth(renderer, view: View) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) ground-truth z-depth (m) of a pinhole view and the mask of pixels that see the part."""
    w, h = view.size
    K = view.K
    u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    x, y = (u - np.float32(K[0, 2])) / np.float32(K[0, 0]), (v - np.float32(K[1, 2])) / np.float32(K[1, 1])
    R = view.world_T_cam[:3, :3].astype(np.float32)
    rays = [R[k, 0] * x + R[k, 1] * y + R[k, 2] for k in range(3)]  # (x, y, 1): t is the z-depth
    t, _, prim = renderer.trace(view.world_T_cam[:3, 3].astype(np.float32), rays)
    return t, prim >= 0


@pytest.fixture(scope="module")
def scene():
    """Five rendered pinhole views of the speckled cube, the renderer, and the ROI (the cube grown by 15 mm)."""
    from vio.sim.api import load_scenario
    from vio.sim.render import Renderer, camera_poses
    from vio.sim.rig import stills_camera

    sc = load_scenario("orbit", 0, 4.0)
    cam = stills_camera(*SIZE, 2.0)
    pinhole = CameraCalib(*SIZE, cam.fx, cam.fy, cam.cx, cam.cy, np.zeros(4), cam.body_T_cam)
    renderer = Renderer(sc.scene, pinhole)
    t_ns = sc.t0_ns + (np.array(TIMES_S) * 1e9).astype(np.int64)
    rng = np.random.default_rng(5)
    views = [
        View(f"v{i}", renderer.render(T, rng), pinhole.K, T, int(t))
        for i, (T, t) in enumerate(zip(camera_poses(sc, t_ns, pinhole), t_ns, strict=True))
    ]
    lo, hi = sc.scene.part.bounds_corners_world().min(axis=0), sc.scene.part.bounds_corners_world().max(axis=0)
    roi = Roi(np.eye(4), lo - [0.015, 0.015, 0.005], hi + 0.015)
    return views, renderer, roi


@pytest.mark.parametrize("method", ["sweep", "sgbm"])
def test_depth_of_a_speckled_cube_matches_the_truth(scene, method):
    views, renderer, roi = scene
    (dm,) = iter_depth_maps(views, roi, DenseConfig(method=method), references=[REF])
    assert dm.view == REF and dm.depth_m.shape == (SIZE[1], SIZE[0]) and dm.depth_m.dtype == np.float32
    truth, part = true_depth(renderer, views[REF])
    found = np.isfinite(dm.depth_m)
    err_mm = np.abs(dm.depth_m - truth)[found & part] * 1e3
    median_max, p90_max, completeness_min = BOUNDS[method]
    assert np.median(err_mm) < median_max
    assert np.percentile(err_mm, 90) < p90_max
    assert (found & part).sum() / part.sum() > completeness_min
    assert np.all((dm.confidence >= 0) & (dm.confidence <= 1)) and np.all(dm.confidence[~found] == 0)


def test_without_roi_at_reduced_resolution(scene):
    """A first pass without a ROI (whole image, a depth range) with the output at half resolution: measured median
    0.22 mm, p90 0.89 mm, completeness 0.71 on the part, 96 % of all depths within 5 mm."""
    views, renderer, _ = scene
    config = DenseConfig(depth_range_m=(0.3, 0.9), max_image_pixels=200_000)
    (dm,) = iter_depth_maps(views, None, config, references=[REF])
    truth, part = true_depth(renderer, views[REF])
    found = np.isfinite(dm.depth_m)
    err_mm = np.abs(dm.depth_m - truth) * 1e3
    assert np.median(err_mm[found & part]) < 0.45 and (found & part).sum() / part.sum() > 0.5
    assert np.mean(err_mm[found] < 5.0) > 0.9


def test_depths_stay_inside_the_roi_box(scene):
    views, _, roi = scene
    (dm,) = iter_depth_maps(views, roi, references=[REF])
    v, u = np.nonzero(np.isfinite(dm.depth_m))
    K, T = views[REF].K, views[REF].world_T_cam
    z = dm.depth_m[v, u].astype(float)
    p_cam = np.column_stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z])
    p_world = p_cam @ T[:3, :3].T + T[:3, 3]
    slack = 1e-3
    assert np.all((p_world >= roi.lo - slack) & (p_world <= roi.hi + slack))


def test_roi_window_brackets_the_true_depth(scene):
    views, renderer, roi = scene
    view = views[REF]
    x0, y0, x1, y1 = roi_bbox(view, roi, margin_px=8)
    assert x0 % 2 == 0 and y0 % 2 == 0 and 0 <= x0 < x1 <= SIZE[0] and 0 <= y0 < y1 <= SIZE[1]
    window = roi_window(
        Crop(view.image[y0:y1, x0:x1].astype(np.float32), view.K, view.world_T_cam, x0, y0), roi, DenseConfig()
    )
    truth, part = true_depth(renderer, view)
    part_crop, truth_crop = part[y0:y1, x0:x1], truth[y0:y1, x0:x1]
    assert part_crop.sum() == part.sum()  # the whole part is inside the window
    assert np.all(window.z_near[part_crop] <= truth_crop[part_crop] + 1e-6)
    assert np.all(window.z_far[part_crop] >= truth_crop[part_crop] - 1e-6)
    away = Roi(np.eye(4), roi.lo + [5.0, 0, 0], roi.hi + [5.0, 0, 0])  # 5 m to the side: not in sight
    assert roi_bbox(view, away, margin_px=8) is None
    assert list(iter_depth_maps(views, away)) == []


def test_neighbours_are_5_to_25_degrees_apart_and_spread(scene):
    views, _, roi = scene
    nbrs = select_neighbours(views, roi, DenseConfig())
    axes = np.array([v.world_T_cam[:3, 2] for v in views])
    for i, js in enumerate(nbrs):
        assert js and i not in js and len(js) <= DenseConfig().num_neighbours
        angles = np.degrees(np.arccos(np.clip(axes[js] @ axes[i], -1, 1)))
        assert np.all((angles >= 5.0) & (angles <= 25.0))
    assert set(nbrs[REF]) == {0, 1, 3, 4}
    assert select_neighbours(views, roi, DenseConfig(min_angle_deg=30.0, max_angle_deg=40.0)) == [[]] * len(views)


def test_bad_method_is_a_config_error(scene):
    views, _, roi = scene
    with pytest.raises(ConfigError, match="dense method must be one of sweep, sgbm, got 'patchmatch'"):
        depth_maps(views, roi, DenseConfig(method="patchmatch"))
    assert depth_maps([], roi) == []


@pytest.mark.parametrize("method", ["sweep", "sgbm"])
def test_depth_maps_on_threads_are_the_serial_ones(scene, method, monkeypatch):
    """vio.model.parallel runs the views on every core; the maps must be the serial loop's, bit for bit, in order."""
    views, _, roi = scene
    refs = [0, REF, 4]
    monkeypatch.setenv("VIO_MODEL_THREADS", "1")
    serial = depth_maps(views, roi, DenseConfig(method=method), references=refs)
    monkeypatch.setenv("VIO_MODEL_THREADS", "3")
    threaded = depth_maps(views, roi, DenseConfig(method=method), references=refs)
    assert [m.view for m in threaded] == [m.view for m in serial] and len(serial) >= 2
    for a, b in zip(serial, threaded, strict=True):
        assert np.array_equal(a.depth_m, b.depth_m, equal_nan=True) and np.array_equal(a.confidence, b.confidence)
