"""The depth oracle: the true depth of a placed part and its table, edges in the image, and the error counts."""

from __future__ import annotations

import numpy as np

from vio.bench.depth_truth import DepthErrors, edge_distance, part_surface, true_depth
from vio.model.records import View
from vio.sim.parts import build_part
from vio.sim.scene import PlacedPart

K = np.array([[240.0, 0.0, 127.5], [0.0, 240.0, 95.5], [0.0, 0.0, 1.0]])


def _look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """world_T_cam of a camera (OpenCV axes: z forward, y down) at `eye` looking at `target`, world z up."""
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    T[:3, 3] = eye
    return T


def _cube_view(eye) -> View:
    return View("v", np.zeros((192, 256), np.uint8), K, _look_at(np.asarray(eye, float), np.array([0.0, 0.0, 0.038])))


def _cube(world_T_part: np.ndarray):
    return part_surface(PlacedPart(build_part("cube"), world_T_part))  # 76.2 mm, base on z = 0 of its frame


def test_true_depth_of_the_top_face_and_the_table_seen_from_above():
    view = _cube_view([0.0, 1e-4, 0.3])  # straight down (a hair off the pole for the look-at)
    pose = np.eye(4)
    z, part, normals = true_depth(_cube(pose), view)
    assert part[96, 128] and abs(z[96, 128] - (0.3 - 0.0762)) < 1e-6  # the top face
    np.testing.assert_allclose(normals[96, 128], [0.0, 0.0, 1.0], atol=1e-6)
    assert not part[2, 2] and abs(z[2, 2] - 0.3) < 2e-3  # the table (z-depth grows off-axis only by rounding)
    lifted = pose.copy()
    lifted[2, 3] = 0.01  # the part and its table 1 cm higher: both 1 cm nearer
    z2, part2, _ = true_depth(_cube(lifted), view)
    np.testing.assert_allclose(z2[part & part2], z[part & part2] - 0.01, atol=1e-6)
    table = ~part & ~part2  # the lifted part's silhouette is a little wider
    assert table.mean() > 0.5
    np.testing.assert_allclose(z2[table], z[table] - 0.01, atol=5e-6)  # float32 rays


def test_errors_are_counted_by_distance_to_the_nearest_edge():
    view = _cube_view([0.25, -0.25, 0.3])  # three faces and the table in sight
    z, part, normals = true_depth(_cube(np.eye(4)), view)
    dist = edge_distance(part, normals)
    crease = edge_distance(part, normals, "crease")
    assert np.isfinite(crease).all() and (crease[part] < 1.5).sum() > 50  # two creases cross the image
    assert dist[part].max() > 8  # the faces are wider than the bands near their edges
    depth = np.where(part, z, np.nan).astype(np.float32)
    depth[dist < 2] = np.nan  # no depth at the edges
    near = (dist >= 2) & (dist < 4)
    depth[near] += np.where(crease[near] == dist[near], 2e-3, -2e-3).astype(np.float32)  # behind at creases
    errors = DepthErrors()
    errors.add(depth, z, part, normals)
    table = errors.table()
    first, second, *rest = table["bands"]
    assert first["coverage"] == 0.0 and first["median_abs_error_mm"] is None
    assert second["coverage"] == 1.0 and second["off_1mm"] == 1.0
    assert abs(second["median_abs_error_mm"] - 2.0) < 1e-3
    assert all(band["pixels"] > 0 for band in rest[:2])
    for band in (b for b in rest if b["pixels"]):
        assert band["coverage"] == 1.0 and band["off_1mm"] == 0.0 and band["p99_abs_error_mm"] < 1e-3
    crease_row, sil_row = table["near_edges"]["crease"], table["near_edges"]["silhouette"]
    assert crease_row["behind_1mm"] == 1.0 and crease_row["in_front_1mm"] == 0.0
    assert sil_row["in_front_1mm"] == 1.0 and sil_row["behind_1mm"] == 0.0
    assert 0.0 < crease_row["coverage"] < 1.0 and 0.0 < sil_row["coverage"] < 1.0
