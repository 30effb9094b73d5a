"""The landmark atlas: how each map landmark looked from a few viewpoints, and re-identification against it.

KLT tracks are short-lived; without re-identification every new sighting of a surface point becomes a new
landmark, the map is a chain of short tracks, and the unobservable directions of visual-inertial odometry (yaw
and position) drift along the chain. With it, a new track that is a landmark seen before (the next ring of an
orbit, a corner revisited) observes the old landmark, and the graph closes the loop.

Each landmark keeps up to `MAX_SNAPSHOTS` snapshots: a descriptor (frontend.descriptors, gravity-aligned) with
the unit viewing direction (landmark to camera, world frame) and depth of the view it came from; a snapshot is
added when the viewing direction differs by more than `SNAPSHOT_SPACING_DEG` from all kept ones. A new track
matches landmark j when, from the predicted pose, j projects within `reid_radius_px` of it, j's nearest snapshot
was taken within `reid_max_view_deg` and a depth ratio of `MAX_DEPTH_RATIO`, the descriptor distance is at most
`reid_max_hamming` bits and clearly better than the second candidate (`reid_ratio`), and no other track claims j.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from frontend.descriptors import hamming
from vio.config import BackendConfig

MAX_SNAPSHOTS = 6
SNAPSHOT_SPACING_DEG = 10.0
MAX_DEPTH_RATIO = 1.25  # one-level descriptors: compare views within this range of distances only
_MIN_DEPTH_M = 0.05


@dataclass
class _Entry:
    p_world: np.ndarray  # (3,) m
    desc: list[np.ndarray] = field(default_factory=list)  # (32,) uint8 each
    dirs: list[np.ndarray] = field(default_factory=list)  # (3,) unit vector landmark -> camera, world
    depths: list[float] = field(default_factory=list)  # m


def gravity_angles_deg(world_T_cam: np.ndarray, uv_px: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(N,) image direction of world down (-z) at each undistorted pixel, deg as OpenCV's `KeyPoint.angle`."""
    uv_px = np.asarray(uv_px, float).reshape(-1, 2)
    down_cam = world_T_cam[:3, :3].T @ np.array([0.0, 0.0, -1.0])
    rays = np.column_stack([(uv_px - K[:2, 2]) / np.diag(K)[:2], np.ones(len(uv_px))])
    moved = rays + 0.05 * down_cam
    z = np.where(moved[:, 2] > 1e-6, moved[:, 2], 1e-6)
    uv2 = moved[:, :2] / z[:, None] * np.diag(K)[:2] + K[:2, 2]
    d = uv2 - uv_px
    return np.degrees(np.arctan2(d[:, 1], d[:, 0]))


class LandmarkAtlas:
    """Snapshots of map landmarks and the matcher of new tracks against them (all in undistorted pixels)."""

    def __init__(self, K: np.ndarray, body_T_cam: np.ndarray, cfg: BackendConfig) -> None:
        self.K = np.asarray(K, float)
        self.body_T_cam = np.asarray(body_T_cam, float)
        self.cfg = cfg
        self.entries: dict[int, _Entry] = {}

    def __len__(self) -> int:
        return len(self.entries)

    def set_position(self, j: int, p_world: np.ndarray) -> None:
        entry = self.entries.get(j)
        if entry is None:
            self.entries[j] = _Entry(np.asarray(p_world, float).copy())
        else:
            entry.p_world = np.asarray(p_world, float).copy()

    def remember(self, world_T_body: np.ndarray, ids: np.ndarray, desc: np.ndarray, ok: np.ndarray) -> None:
        """Keep the descriptors of landmarks seen from world_T_body when the viewpoint is a new one."""
        c = (world_T_body @ self.body_T_cam)[:3, 3]
        for j, d, good in zip(np.asarray(ids).tolist(), desc, ok, strict=True):
            entry = self.entries.get(int(j))
            if entry is None or not good:
                continue
            ray = c - entry.p_world
            depth = float(np.linalg.norm(ray))
            if depth < _MIN_DEPTH_M:
                continue
            ray /= depth
            if entry.dirs and max(float(r @ ray) for r in entry.dirs) > np.cos(np.radians(SNAPSHOT_SPACING_DEG)):
                continue
            if len(entry.desc) >= MAX_SNAPSHOTS:  # keep the first views and the newest
                entry.desc.pop(1), entry.dirs.pop(1), entry.depths.pop(1)
            entry.desc.append(np.asarray(d, np.uint8).copy())
            entry.dirs.append(ray)
            entry.depths.append(depth)

    def _candidates(
        self, world_T_body: np.ndarray, exclude: set[int], alive: Callable[[int], bool]
    ) -> tuple[list[int], np.ndarray, np.ndarray]:
        """Landmarks visible from world_T_body with a comparable snapshot: ids, (C, 2) pixels, (C, 32) descriptors."""
        world_T_cam = world_T_body @ self.body_T_cam
        R, c = world_T_cam[:3, :3], world_T_cam[:3, 3]
        ids = [j for j, e in self.entries.items() if e.desc and j not in exclude and alive(j)]
        if not ids:
            return [], np.zeros((0, 2)), np.zeros((0, 32), np.uint8)
        P = np.array([self.entries[j].p_world for j in ids])
        p_cam = (P - c) @ R
        z = p_cam[:, 2]
        front = z > _MIN_DEPTH_M
        uv = np.full((len(ids), 2), -1e9)
        uv[front] = p_cam[front, :2] / z[front, None] * np.diag(self.K)[:2] + self.K[:2, 2]
        w, h = 2.0 * self.K[0, 2], 2.0 * self.K[1, 2]
        inside = front & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        out_ids, out_uv, out_desc = [], [], []
        cos_max = np.cos(np.radians(self.cfg.reid_max_view_deg))
        for i in np.flatnonzero(inside).tolist():
            e = self.entries[ids[i]]
            ray = c - e.p_world
            depth = float(np.linalg.norm(ray))
            cos = np.array(e.dirs) @ (ray / depth)
            best = int(np.argmax(cos))
            ratio = depth / e.depths[best]
            if cos[best] < cos_max or not 1.0 / MAX_DEPTH_RATIO <= ratio <= MAX_DEPTH_RATIO:
                continue
            out_ids.append(ids[i])
            out_uv.append(uv[i])
            out_desc.append(e.desc[best])
        if not out_ids:
            return [], np.zeros((0, 2)), np.zeros((0, 32), np.uint8)
        return out_ids, np.array(out_uv), np.array(out_desc)

    def match(
        self,
        world_T_body: np.ndarray,
        uv_px: np.ndarray,
        desc: np.ndarray,
        ok: np.ndarray,
        exclude: set[int],
        alive: Callable[[int], bool] = lambda j: True,
    ) -> dict[int, int]:
        """Re-identify new tracks (rows of uv_px (N, 2) undistorted px, desc (N, 32), ok (N,)) seen from the
        predicted pose world_T_body; landmarks in `exclude` (seen by their own track now) or not `alive(j)` are not
        candidates. Returns {row: landmark id}, one row per landmark."""
        ids, proj, cand_desc = self._candidates(world_T_body, exclude, alive)
        if not ids or not len(uv_px):
            return {}
        uv_px = np.asarray(uv_px, float).reshape(-1, 2)
        near = np.linalg.norm(uv_px[:, None, :] - proj[None, :, :], axis=2) <= self.cfg.reid_radius_px
        near &= np.asarray(ok, bool)[:, None]
        rows = np.flatnonzero(near.any(axis=1))
        if not len(rows):
            return {}
        dist = np.where(near[rows], hamming(desc[rows], cand_desc), 10_000)
        claims: dict[int, tuple[int, int]] = {}  # landmark column -> (distance, row)
        for r, drow in zip(rows.tolist(), dist, strict=True):
            order = np.argsort(drow, kind="stable")
            best = int(drow[order[0]])
            second = int(drow[order[1]]) if len(order) > 1 else 10_000
            if best > self.cfg.reid_max_hamming or best > self.cfg.reid_ratio * second:
                continue
            col = int(order[0])
            if col not in claims or best < claims[col][0]:
                claims[col] = (best, r)
        return {r: ids[col] for col, (_, r) in claims.items()}
