"""Landmark re-identification: gravity-aligned descriptors (frontend.descriptors) and the atlas (backend.atlas)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from backend.atlas import LandmarkAtlas, gravity_angles_deg
from backend.landmarks import LandmarkBook
from backend.reidentification import Reidentification
from frontend.descriptors import KeyframeDescriber
from vio.config import LandmarkConfig, ReidentificationConfig
from vio.descriptors import hamming

K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])


def _texture(seed: int = 0) -> np.ndarray:
    """A 480 x 640 blob texture with plenty of corners."""
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.uniform(0, 255, (480, 640)).astype(np.float32), (0, 0), 3.0)
    return cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)


def _corners(img: np.ndarray, n: int = 80) -> np.ndarray:
    pts = cv2.goodFeaturesToTrack(img, n, 0.01, 15).reshape(-1, 2)
    centre = np.array([320.0, 240.0])
    return pts[np.linalg.norm(pts - centre, axis=1) < 150]  # stay inside the rotated image


def test_hamming_counts_differing_bits():
    rng = np.random.default_rng(1)
    a = rng.integers(0, 256, (4, 32), dtype=np.uint8)
    b = rng.integers(0, 256, (3, 32), dtype=np.uint8)
    brute = np.array([[sum(bin(x ^ y).count("1") for x, y in zip(ra, rb, strict=True)) for rb in b] for ra in a])
    assert np.array_equal(hamming(a, b), brute)
    assert np.all(np.diag(hamming(a, a)) == 0)


def test_descriptors_follow_the_given_orientation():
    """Rotating the image and the orientation together leaves the descriptor nearly unchanged; rotating only the
    image does not (so the orientation is really used, and matching needs it)."""
    img = _texture()
    pts = _corners(img)
    rot = cv2.getRotationMatrix2D((320.0, 240.0), 35.0, 1.0)
    img_r = cv2.warpAffine(img, rot, (640, 480))
    pts_r = np.column_stack([pts, np.ones(len(pts))]) @ rot.T
    d0, ok0 = KeyframeDescriber(img).describe(pts, np.zeros(len(pts)))
    d1, ok1 = KeyframeDescriber(img_r).describe(pts_r, np.full(len(pts), -35.0))
    d2, ok2 = KeyframeDescriber(img_r).describe(pts_r, np.zeros(len(pts)))
    both = ok0 & ok1 & ok2
    assert both.sum() > 10
    same = np.diag(hamming(d0[both], d1[both]))
    unaligned = np.diag(hamming(d0[both], d2[both]))
    others = hamming(d0[both], d0[both])[~np.eye(both.sum(), dtype=bool)]
    assert np.median(same) < 25 < np.median(unaligned) and np.median(others) > 90


def test_points_near_the_border_are_not_described():
    img = _texture()
    desc, ok = KeyframeDescriber(img).describe(np.array([[2.0, 2.0], [320.0, 240.0], [639.0, 100.0]]), np.zeros(3))
    assert ok.tolist() == [False, True, False]
    assert not desc[0].any() and desc[1].any()


def _look(yaw_deg: float, roll_deg: float = 0.0, c=(0.0, -1.0, 0.0)) -> np.ndarray:
    """world_T_cam of a level camera at c looking horizontally (yaw about world z), rolled about its optical axis."""
    z = np.array([np.sin(np.radians(yaw_deg)), np.cos(np.radians(yaw_deg)), 0.0])  # optical axis
    y = np.array([0.0, 0.0, -1.0])  # image down = world down
    x = np.cross(y, z)
    R = np.column_stack([x, y, z])
    r = np.radians(roll_deg)
    Rz = np.array([[np.cos(r), -np.sin(r), 0.0], [np.sin(r), np.cos(r), 0.0], [0.0, 0.0, 1.0]])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R @ Rz, c
    return T


def test_gravity_points_down_the_image_of_a_level_camera_and_turns_with_roll():
    uv = np.array([[320.0, 240.0], [100.0, 400.0]])
    assert np.allclose(gravity_angles_deg(_look(0.0), uv, K), 90.0, atol=1e-6)  # straight down the image
    rolled = gravity_angles_deg(_look(0.0, roll_deg=30.0), uv[:1], K)
    assert rolled[0] == pytest.approx(60.0, abs=1e-6)  # the image turns against the camera


def _atlas(cfg: ReidentificationConfig | None = None) -> tuple[LandmarkAtlas, np.ndarray, np.ndarray]:
    """An atlas of 40 landmarks 1-2 m in front of a camera at the origin, with random descriptors."""
    rng = np.random.default_rng(3)
    atlas = LandmarkAtlas(K, np.eye(4), cfg or ReidentificationConfig())
    pts = np.column_stack([rng.uniform(-0.6, 0.6, 40), rng.uniform(0.0, 0.3, 40), rng.uniform(-0.4, 0.4, 40)])
    desc = rng.integers(0, 256, (40, 32), dtype=np.uint8)
    for j, p in enumerate(pts):
        atlas.set_position(100 + j, p)
    atlas.remember(_look(0.0), np.arange(100, 140), desc, np.ones(40, bool))
    return atlas, pts, desc


def _pixels(world_T_cam: np.ndarray, pts: np.ndarray) -> np.ndarray:
    p = (pts - world_T_cam[:3, 3]) @ world_T_cam[:3, :3]
    return p[:, :2] / p[:, 2:] * 500.0 + np.array([320.0, 240.0])


def test_atlas_re_identifies_new_tracks_at_the_landmark_projections():
    atlas, pts, desc = _atlas()
    pose = _look(5.0, c=(0.05, -1.0, 0.0))  # a little moved and turned
    uv = _pixels(pose, pts[:10]) + 1.5
    noisy = desc[:10].copy()
    noisy[:, 0] ^= 0b00010101  # a few bits flipped
    found = atlas.match(pose, uv, noisy, np.ones(10, bool), exclude=set())
    assert found == {i: 100 + i for i in range(10)}
    # landmarks seen now by their own tracks, or no longer in the solver, are never candidates
    assert 100 not in atlas.match(pose, uv, noisy, np.ones(10, bool), exclude={100}).values()
    dead = atlas.match(pose, uv, noisy, np.ones(10, bool), exclude=set(), alive=lambda ids: np.zeros(len(ids), bool))
    assert dead == {}


def test_atlas_rejects_far_pixels_wrong_descriptors_and_new_viewpoints():
    atlas, pts, desc = _atlas()
    pose = _look(0.0)
    uv = _pixels(pose, pts[:5])
    ones = np.ones(5, bool)
    assert atlas.match(pose, uv + 30.0, desc[:5], ones, set()) == {}  # outside the search radius
    assert atlas.match(pose, uv, 255 - desc[:5], ones, set()) == {}  # a different point
    assert atlas.match(pose, uv, desc[:5], ~ones, set()) == {}  # not described
    far = _look(60.0, c=(-0.87, -0.5, 0.0))  # 60 deg round: only snapshots within max_view_deg compare
    assert atlas.match(far, _pixels(far, pts[:5]), desc[:5], ones, set()) == {}


def test_atlas_ratio_test_and_one_track_per_landmark():
    atlas, pts, desc = _atlas()
    pose = _look(0.0)
    uv = _pixels(pose, pts[:1])
    twin = LandmarkAtlas(K, np.eye(4), ReidentificationConfig())
    for j in (1, 2):  # two landmarks at the same pixel with the same descriptor: ambiguous
        twin.set_position(j, pts[0] + 0.001 * j)
    twin.remember(pose, np.array([1, 2]), np.repeat(desc[:1], 2, axis=0), np.ones(2, bool))
    assert twin.match(pose, uv, desc[:1], np.ones(1, bool), set()) == {}
    two = np.repeat(uv, 2, axis=0) + np.array([[0.0, 0.0], [2.0, 0.0]])  # two tracks claim one landmark
    best_second = np.vstack([desc[:1], desc[:1] ^ np.uint8(1)])
    assert atlas.match(pose, two, best_second, np.ones(2, bool), set()) == {0: 100}


def test_leaving_out_landmarks_far_from_every_new_track_changes_no_candidate():
    """`match` compares only the landmarks that project near one of the new tracks: a map of 2,000 landmarks with
    several snapshots each (some from viewpoints too far to compare, some forgotten), seen from a moved camera.
    The candidates kept are exactly those of the whole search that lie within the radius of a track, in the same
    order, with the same pixels and descriptors; the others could never have matched."""
    rng = np.random.default_rng(11)
    cfg = ReidentificationConfig()
    atlas = LandmarkAtlas(K, np.eye(4), cfg)
    n = 2000
    pts = np.column_stack([rng.uniform(-1.0, 1.0, n), rng.uniform(-0.2, 1.0, n), rng.uniform(-0.6, 0.6, n)])
    for j, p in enumerate(pts):
        atlas.set_position(j, p)
    for yaw in (0.0, 12.0, 25.0, 40.0):
        c = (np.sin(np.radians(yaw)) * 1.0, -np.cos(np.radians(yaw)) * 1.0, 0.0)
        atlas.remember(_look(yaw, c=c), np.arange(n), rng.integers(0, 256, (n, 32), dtype=np.uint8), np.ones(n, bool))
    for j in range(0, n, 7):
        atlas.forget(j)
    pose = _look(8.0, c=(0.14, -0.99, 0.02))
    queries = np.vstack([_pixels(pose, pts[rng.choice(n, 25, replace=False)]), rng.uniform(0, 640, (5, 2))])
    queries += rng.normal(0.0, 6.0, queries.shape)
    alive = lambda ids: ids % 5 != 1  # noqa: E731
    exclude = set(range(3, n, 11))
    ids, proj, desc = atlas._candidates(pose, exclude, alive)
    near = np.linalg.norm(proj[:, None, :] - queries[None, :, :], axis=2).min(axis=1) <= cfg.radius_px
    assert 0.05 * len(ids) < near.sum() < 0.8 * len(ids)  # the test leaves out a real share of the candidates
    kept_ids, kept_proj, kept_desc = atlas._candidates(pose, exclude, alive, near_px=queries)
    assert kept_ids == np.asarray(ids)[near].tolist()
    assert np.array_equal(kept_proj, proj[near]) and np.array_equal(kept_desc, desc[near])
    assert atlas._candidates(pose, exclude, alive, near_px=np.zeros((0, 2)))[0] == []


def test_atlas_keeps_a_few_snapshots_from_distinct_viewpoints():
    atlas, pts, desc = _atlas()
    for yaw in (2.0, 4.0):  # too close to the first view: no new snapshot
        atlas.remember(_look(yaw), np.array([100]), desc[:1], np.ones(1, bool))
    assert atlas.num_snapshots(100) == 1
    for i in range(1, 12):
        c = (np.sin(np.radians(12.0 * i)) * 1.0, -np.cos(np.radians(12.0 * i)) * 1.0, 0.0)
        atlas.remember(_look(12.0 * i, c=c), np.array([100]), desc[:1], np.ones(1, bool))
    assert atlas.num_snapshots(100) == 6  # bounded


def test_forgotten_landmarks_are_no_candidates_and_their_rows_and_slots_are_taken_again():
    atlas, pts, desc = _atlas()
    pose = _look(5.0, c=(0.05, -1.0, 0.0))
    uv = _pixels(pose, pts) + 1.5
    before = atlas.match(pose, uv, desc, np.ones(40, bool), exclude=set())
    assert len(before) > 30
    for j in range(100, 125):
        atlas.forget(j)
    assert len(atlas) == 15 and atlas.num_snapshots(110) == 0 and atlas.num_snapshots(130) == 1
    after = atlas.match(pose, uv, desc, np.ones(40, bool), exclude=set())
    assert after == {row: j for row, j in before.items() if j >= 125}
    atlas.set_position(200, pts[3])  # a new landmark takes a forgotten row and slot: the storage stays
    atlas.remember(_look(0.0), np.array([200]), desc[3:4], np.ones(1, bool))
    assert atlas._num_rows == 40 and atlas._num_snaps == 40 and atlas.rows[200] < 25
    assert atlas.match(pose, uv[3:4], desc[3:4], np.ones(1, bool), exclude=set()) == {0: 200}


def test_a_retiring_duplicate_of_an_older_landmark_leaves_the_atlas():
    book = LandmarkBook(K, np.eye(4), LandmarkConfig())
    cfg = ReidentificationConfig(merge_radius_m=0.005, archive_merged=False)
    reid = Reidentification(cfg, True, book, None, np.eye(4))  # the atlas alone: no graph state to archive from
    p = np.array([0.3, 1.2, 0.1])
    for j, q in [(1, p), (2, p + [0.004, 0.0, 0.0]), (3, p + [0.0, 0.006, 0.0]), (4, p + [0.0, 0.0, -0.003])]:
        reid.on_admit(j, q)
    for j, q in [(1, p), (2, p + [0.004, 0.0, 0.0]), (3, p + [0.0, 0.006, 0.0])]:
        reid.on_retired(j, q)
    assert set(reid.atlas.rows) == {1, 3, 4} and reid.num_merged == 1  # 2 was 4 mm from 1; 3 is 6 mm away
    reid.on_retired(1, p + [0.0, 0.002, 0.0])  # seen again and retired again, filed where it is now
    reid.on_retired(4, p + [0.0, 0.0, -0.003])
    assert set(reid.atlas.rows) == {1, 3} and reid.num_merged == 2
    off = Reidentification(ReidentificationConfig(), True, book, None, np.eye(4))
    off.on_admit(1, p)
    off.on_admit(2, p)
    off.on_retired(1, p)
    off.on_retired(2, p)
    assert set(off.atlas.rows) == {1, 2}  # merge_radius_m 0: off


def test_a_merged_duplicate_hands_its_new_viewpoints_to_the_older_landmark():
    """`merge_snapshots`: the duplicate's snapshots from viewpoints the older landmark has none near become the older
    one's (at most MAX_SNAPSHOTS, the first view kept); the duplicate leaves the atlas."""
    from backend.atlas import MAX_SNAPSHOTS

    book = LandmarkBook(K, np.eye(4), LandmarkConfig())
    cfg = ReidentificationConfig(merge_radius_m=0.005, archive_merged=False, merge_snapshots=True)
    reid = Reidentification(cfg, True, book, None, np.eye(4))
    atlas = reid.atlas
    p = np.array([0.0, 0.0, 0.0])
    desc = np.arange(3 * 32, dtype=np.uint8).reshape(3, 32)

    def around(deg):  # a camera 1 m from the point, deg round it
        return _look(deg, c=(-np.sin(np.radians(deg)), -np.cos(np.radians(deg)), 0.0))

    reid.on_admit(1, p)
    atlas.remember(around(0.0), np.array([1]), desc[:1], np.ones(1, bool))
    reid.on_admit(2, p + [0.003, 0.0, 0.0])
    atlas.remember(around(3.0), np.array([2]), desc[1:2], np.ones(1, bool))  # near 1's viewpoint: not handed over
    atlas.remember(around(40.0), np.array([2]), desc[2:3], np.ones(1, bool))  # a new viewpoint for 1
    reid.on_retired(1, p)
    reid.on_retired(2, p + [0.003, 0.0, 0.0])
    assert set(atlas.rows) == {1} and reid.num_merged == 1
    slots = atlas._slots[atlas.rows[1]]
    assert len(slots) == 2 and np.array_equal(atlas._snap_desc[slots[1]], desc[2])
    for i in range(3, 12):  # more duplicates, each from a new viewpoint: the first view and the newest stay
        reid.on_admit(i, p)
        atlas.remember(around(40.0 + 15.0 * i), np.array([i]), desc[2:3], np.ones(1, bool))
        reid.on_retired(i, p)
    slots = atlas._slots[atlas.rows[1]]
    assert len(slots) == MAX_SNAPSHOTS and np.array_equal(atlas._snap_desc[slots[0]], desc[0])
    assert set(atlas.rows) == {1}
