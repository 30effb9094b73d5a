"""The visibility check of the depth maps (vio.model.visibility) on ray-cast depth maps of the simulated orbit
around the cube: a silhouette fattened the way windowed stereo fattens it goes, the true depths stay."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from tests.vio.model.test_fuse_mesh import PART_BGR, ground_truth_views
from vio.model.records import DepthMap
from vio.model.visibility import visibility_filter

TOL_M = 1.6e-3  # vio model's: four voxels of 0.4 mm


def part_mask(view) -> np.ndarray:
    return np.all(view.image == PART_BGR, axis=2)


def fatten(dm: DepthMap, part: np.ndarray, px: int) -> np.ndarray:
    """Give the background within `px` pixels of the part's silhouette the depth of the nearest part pixel (in
    place), as a window straddling the silhouette does, where that moves it by more than 5 mm (at the part's
    foot the table is about as near: no bump); returns the mask of those pixels."""
    depth = np.where(part, dm.depth_m, np.float32(1e3)).astype(np.float32)
    nearest = cv2.erode(depth, np.ones((2 * px + 1, 2 * px + 1), np.uint8))
    ring = ~part & (nearest < 1e3) & np.isfinite(nearest) & ~(dm.depth_m - nearest <= 5e-3)
    dm.depth_m[ring] = nearest[ring]
    return ring


@pytest.fixture(scope="module")
def views_and_maps():
    _, views, maps = ground_truth_views(12, size=(960, 720), noise_m=1e-4, outliers=0.0, holes=0.03)
    return views, maps


def test_a_fattened_silhouette_is_dropped_and_true_depths_stay(views_and_maps):
    views, clean = views_and_maps
    maps = [DepthMap(dm.view, dm.depth_m.copy()) for dm in clean]
    rings = [fatten(dm, part_mask(views[dm.view]), 4) for dm in maps[::4]]
    true_before = [np.isfinite(dm.depth_m) for dm in clean]
    report = visibility_filter(views, maps, TOL_M)
    kept_fat = sum(int(np.isfinite(dm.depth_m[ring]).sum()) for dm, ring in zip(maps[::4], rings, strict=True))
    n_fat = sum(int(ring.sum()) for ring in rings)
    assert n_fat > 1000
    assert kept_fat < 0.1 * n_fat, f"{kept_fat} of {n_fat} fattened depths kept"
    lost = 0
    for i, (dm, before) in enumerate(zip(maps, true_before, strict=True)):
        keep = before & ~(rings[i // 4] if i % 4 == 0 else np.zeros_like(before))
        lost += int((keep & ~np.isfinite(dm.depth_m)).sum())
    n_true = sum(int(b.sum()) for b in true_before)
    assert lost < 0.002 * n_true, f"{lost} of {n_true} true depths dropped"
    assert report.depths == n_true + n_fat - sum(
        int((before & ring).sum()) for before, ring in zip(true_before[::4], rings, strict=True)
    )
    assert report.dropped == n_fat - kept_fat + lost


def test_a_depth_no_other_view_sees_is_kept(views_and_maps):
    views, clean = views_and_maps
    one = [DepthMap(clean[0].view, clean[0].depth_m.copy())]
    fatten(one[0], part_mask(views[one[0].view]), 4)
    before = np.isfinite(one[0].depth_m).sum()
    report = visibility_filter(views, one, TOL_M)
    assert report.dropped == 0 and np.isfinite(one[0].depth_m).sum() == before


def test_the_result_does_not_depend_on_the_thread_count(views_and_maps, monkeypatch):
    views, clean = views_and_maps
    results = []
    for threads in ("1", "2"):
        monkeypatch.setenv("VIO_MODEL_THREADS", threads)
        maps = [DepthMap(dm.view, dm.depth_m.copy()) for dm in clean[:8]]
        fatten(maps[0], part_mask(views[maps[0].view]), 4)
        visibility_filter(views, maps, TOL_M)
        results.append([np.isnan(dm.depth_m) for dm in maps])
    assert all(np.array_equal(a, b) for a, b in zip(*results, strict=True))
