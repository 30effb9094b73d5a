"""The landmark atlas: how each map landmark looked from a few viewpoints, and re-identification against it.

KLT tracks are short-lived; without re-identification every new sighting of a surface point becomes a new
landmark, the map is a chain of short tracks, and the unobservable directions of visual-inertial odometry (yaw
and position) drift along the chain. With it, a new track that is a landmark seen before (the next ring of an
orbit, a corner revisited) observes the old landmark, and the graph closes the loop.

Each landmark keeps up to `MAX_SNAPSHOTS` snapshots: a descriptor (gravity-aligned, from frontend.descriptors) with
the unit viewing direction (landmark to camera, world frame) and depth of the view it came from; a snapshot is
added when the viewing direction differs by more than `SNAPSHOT_SPACING_DEG` from all kept ones. A new track
matches landmark j when, from the predicted pose, j projects within `radius_px` of it, j's nearest snapshot
was taken within `max_view_deg` and a depth ratio of `MAX_DEPTH_RATIO`, the descriptor distance is at most
`max_hamming` bits and clearly better than the second candidate (`ratio`), and no other track claims j.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.spatial import cKDTree

from vio.config import ReidentificationConfig
from vio.descriptors import DESCRIPTOR_BYTES, hamming

MAX_SNAPSHOTS = 6
SNAPSHOT_SPACING_DEG = 10.0
MAX_DEPTH_RATIO = 1.25  # one-level descriptors: compare views within this range of distances only
_MIN_DEPTH_M = 0.05
_EXACT_MARGIN = 1e-9  # m and cosine: `remember`'s all-at-once pass skips only views this far from a threshold


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
    """Snapshots of map landmarks and the matcher of new tracks against them (all in undistorted pixels).

    Storage is columnar (numpy arrays grown by doubling) so that projecting thousands of landmarks per keyframe
    stays a few vectorised operations: landmark rows (id, position) and snapshot slots (landmark row, descriptor,
    viewing direction, depth), `MAX_SNAPSHOTS` slots per landmark at most.
    """

    def __init__(self, K: np.ndarray, body_T_cam: np.ndarray, cfg: ReidentificationConfig) -> None:
        self.K = np.asarray(K, float)
        self.body_T_cam = np.asarray(body_T_cam, float)
        self.cfg = cfg
        self.rows: dict[int, int] = {}  # landmark id -> row
        self._ids = np.zeros(0, np.int64)
        self._pos = np.zeros((0, 3))
        self._slots: list[list[int]] = []  # row -> its snapshot slots, oldest first
        self._snap_row = np.zeros(0, np.int64)
        self._snap_desc = np.zeros((0, DESCRIPTOR_BYTES), np.uint8)
        self._snap_dir = np.zeros((0, 3))
        self._snap_depth = np.zeros(0)
        self._num_snaps = 0
        self._num_rows = 0  # rows used so far, forgotten ones included (`forget`)
        self._free_rows: list[int] = []  # forgotten rows, taken again by new landmarks
        self._free_slots: list[int] = []  # forgotten landmarks' snapshot slots, taken again by new snapshots

    def __len__(self) -> int:
        return len(self.rows)

    def num_snapshots(self, j: int) -> int:
        return len(self._slots[self.rows[j]]) if j in self.rows else 0

    def set_position(self, j: int, p_world: np.ndarray) -> None:
        row = self.rows.get(j)
        if row is None:
            if self._free_rows:
                row = self.rows[j] = self._free_rows.pop()
            else:
                row = self.rows[j] = self._num_rows
                self._num_rows += 1
                if row >= len(self._ids):
                    self._ids = _grow(self._ids, row + 1)
                    self._pos = _grow(self._pos, row + 1)
                self._slots.append([])
            self._ids[row] = j
        self._pos[row] = p_world

    def position(self, j: int) -> np.ndarray:
        return self._pos[self.rows[j]]

    def forget(self, j: int) -> None:
        """Landmark j is no longer a candidate (a duplicate of an older one): its row and snapshot slots are dead
        (no position, no depth: never visible or comparable) and taken again by the next new ones."""
        row = self.rows.pop(j, None)
        if row is None:
            return
        self._ids[row], self._pos[row] = -1, np.nan
        slots = self._slots[row]
        self._snap_depth[slots] = np.nan
        self._free_slots += slots
        self._slots[row] = []
        self._free_rows.append(row)

    def absorb(self, j: int, into: int) -> None:
        """Landmark j is a duplicate of `into`: its snapshots from viewpoints `into` has none near (`remember`'s
        spacing) become `into`'s, then j is forgotten. The old landmark keeps its position and gains the newer
        views' appearance."""
        row, dst = self.rows.get(j), self.rows.get(into)
        if row is not None and dst is not None:
            cos_new = np.cos(np.radians(SNAPSHOT_SPACING_DEG))
            for src in list(self._slots[row]):
                kept = self._slots[dst]
                if kept and float(np.max(self._snap_dir[kept] @ self._snap_dir[src])) > cos_new:
                    continue
                slot = self._new_slot(dst)
                self._snap_row[slot], self._snap_desc[slot] = dst, self._snap_desc[src]
                self._snap_dir[slot], self._snap_depth[slot] = self._snap_dir[src], self._snap_depth[src]
        self.forget(j)

    def _new_slot(self, row: int) -> int:
        slots = self._slots[row]
        if len(slots) >= MAX_SNAPSHOTS:  # keep the first view and the newest ones
            slot = slots.pop(1)
        elif self._free_slots:
            slot = self._free_slots.pop()
        else:
            slot = self._num_snaps
            self._num_snaps += 1
            if slot >= len(self._snap_row):
                n = slot + 1
                self._snap_row, self._snap_desc = _grow(self._snap_row, n), _grow(self._snap_desc, n)
                self._snap_dir, self._snap_depth = _grow(self._snap_dir, n), _grow(self._snap_depth, n)
        slots.append(slot)
        return slot

    def remember(self, world_T_body: np.ndarray, ids: np.ndarray, desc: np.ndarray, ok: np.ndarray) -> None:
        """Keep the descriptors of landmarks seen from world_T_body when the viewpoint is a new one."""
        c = (world_T_body @ self.body_T_cam)[:3, 3]
        cos_new = np.cos(np.radians(SNAPSHOT_SPACING_DEG))
        rows = [self.rows.get(int(j), -1) if good else -1 for j, good in zip(np.asarray(ids).tolist(), ok, strict=True)]
        for i in self._maybe_new(c, rows, cos_new).tolist():
            row, d = rows[i], desc[i]
            ray = c - self._pos[row]
            depth = float(np.linalg.norm(ray))
            if depth < _MIN_DEPTH_M:
                continue
            ray /= depth
            slots = self._slots[row]
            if slots and float(np.max(self._snap_dir[slots] @ ray)) > cos_new:
                continue
            slot = self._new_slot(row)
            self._snap_row[slot], self._snap_desc[slot] = row, d
            self._snap_dir[slot], self._snap_depth[slot] = ray, depth

    def _maybe_new(self, c: np.ndarray, rows: list[int], cos_new: float) -> np.ndarray:
        """Indices into `rows` (atlas rows, -1 for none) whose view from camera centre c may need a new snapshot:
        all at once, leaving out only the rows that are surely too close or surely seen from a kept viewpoint (by
        `_EXACT_MARGIN`: `remember` decides the others one at a time, exactly as it always did)."""
        idx = np.flatnonzero(np.asarray(rows, np.int64) >= 0)
        if not idx.size:
            return idx
        r = np.asarray(rows, np.int64)[idx]
        rays = c - self._pos[r]
        depth = np.sqrt(np.einsum("ij,ij->i", rays, rays))
        with np.errstate(divide="ignore", invalid="ignore"):
            rays /= depth[:, None]
        slots = [self._slots[row] for row in r.tolist()]
        owner = np.repeat(np.arange(idx.size), [len(s) for s in slots])
        flat = np.fromiter((s for row_slots in slots for s in row_slots), np.int64, count=owner.size)
        best = np.full(idx.size, -np.inf)
        np.maximum.at(best, owner, np.einsum("ij,ij->i", self._snap_dir[flat], rays[owner]))
        surely_old = (depth < _MIN_DEPTH_M - _EXACT_MARGIN) | (
            (depth > _MIN_DEPTH_M + _EXACT_MARGIN) & (best > cos_new + _EXACT_MARGIN)
        )
        return idx[~surely_old]

    def _candidates(
        self,
        world_T_body: np.ndarray,
        exclude: set[int],
        alive: Callable[[np.ndarray], np.ndarray],
        near_px: np.ndarray | None = None,
    ) -> tuple[list[int], np.ndarray, np.ndarray]:
        """Landmarks visible from world_T_body with a comparable snapshot: ids, (C, 2) pixels, (C, 32) descriptors.

        With `near_px` ((Q, 2) undistorted px) only the landmarks projecting within `radius_px` of one of those
        pixels: the others cannot match. Leaving them out before their snapshots are compared makes a keyframe
        cheaper where a long capture of one scene has piled up landmarks in view; the candidates that remain, their
        order and their descriptors are those of the whole search (tested)."""
        empty = [], np.zeros((0, 2)), np.zeros((0, DESCRIPTOR_BYTES), np.uint8)
        n, m = self._num_rows, self._num_snaps
        if not n or not m:
            return empty
        world_T_cam = world_T_body @ self.body_T_cam
        R, c = world_T_cam[:3, :3], world_T_cam[:3, 3]
        p_cam = (self._pos[:n] - c) @ R
        z = p_cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = p_cam[:, :2] / z[:, None] * np.diag(self.K)[:2] + self.K[:2, 2]
        w, h = 2.0 * self.K[0, 2], 2.0 * self.K[1, 2]
        visible = (z > _MIN_DEPTH_M) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        if near_px is not None:
            seen = np.flatnonzero(visible)
            if len(near_px) and len(seen):
                # a bound a hair wider than the radius (the KD-tree's test is strict); `match` applies the exact one
                bound = self.cfg.radius_px * (1.0 + 1e-9) + 1e-9
                d, _ = cKDTree(np.asarray(near_px, float).reshape(-1, 2)).query(uv[seen], distance_upper_bound=bound)
                visible[seen[~np.isfinite(d)]] = False
            else:
                visible[:] = False
        srow = self._snap_row[:m]
        cand = np.flatnonzero(visible[srow])  # the snapshots of the landmarks still in question
        if not len(cand):
            return empty
        srow = srow[cand]
        rows, inverse = np.unique(srow, return_inverse=True)
        rays = c - self._pos[rows]
        depth = np.linalg.norm(rays, axis=1)
        rays /= np.maximum(depth, 1e-9)[:, None]
        cos = np.einsum("ij,ij->i", self._snap_dir[cand], rays[inverse])
        ratio = depth[inverse] / self._snap_depth[cand]
        ok = cos >= np.cos(np.radians(self.cfg.max_view_deg))
        ok &= (ratio >= 1.0 / MAX_DEPTH_RATIO) & (ratio <= MAX_DEPTH_RATIO)
        slots = np.flatnonzero(ok)
        if not len(slots):
            return empty
        slots = slots[np.lexsort((-cos[slots], srow[slots]))]  # per landmark row, the closest viewpoint first
        first = np.ones(len(slots), bool)
        first[1:] = srow[slots][1:] != srow[slots][:-1]
        slots = slots[first]
        ids = self._ids[srow[slots]]
        keep = ~np.isin(ids, np.fromiter(exclude, np.int64, len(exclude)))
        keep[keep] = alive(ids[keep])
        if not keep.any():
            return empty
        slots = slots[keep]
        return self._ids[srow[slots]].tolist(), uv[srow[slots]], self._snap_desc[cand[slots]]

    def match(
        self,
        world_T_body: np.ndarray,
        uv_px: np.ndarray,
        desc: np.ndarray,
        ok: np.ndarray,
        exclude: set[int],
        alive: Callable[[np.ndarray], np.ndarray] = lambda ids: np.ones(len(ids), bool),
    ) -> dict[int, int]:
        """Re-identify new tracks (rows of uv_px (N, 2) undistorted px, desc (N, 32), ok (N,)) seen from the
        predicted pose world_T_body; landmarks in `exclude` (seen by their own track now) or not alive (`alive(ids)`:
        a mask) are not candidates. Returns {row: landmark id}, one row per landmark, best (smallest distance) first."""
        uv_px = np.asarray(uv_px, float).reshape(-1, 2)
        ok = np.asarray(ok, bool)
        ids, proj, cand_desc = self._candidates(world_T_body, exclude, alive, near_px=uv_px[ok])
        if not ids or not len(uv_px):
            return {}
        near = np.linalg.norm(uv_px[:, None, :] - proj[None, :, :], axis=2) <= self.cfg.radius_px
        near &= ok[:, None]
        rows = np.flatnonzero(near.any(axis=1))
        if not len(rows):
            return {}
        dist = np.where(near[rows], hamming(desc[rows], cand_desc), 10_000)
        claims: dict[int, tuple[int, int]] = {}  # landmark column -> (distance, row)
        for r, drow in zip(rows.tolist(), dist, strict=True):
            order = np.argsort(drow, kind="stable")
            best = int(drow[order[0]])
            second = int(drow[order[1]]) if len(order) > 1 else 10_000
            if best > self.cfg.max_hamming or best >= self.cfg.ratio * second:
                continue
            col = int(order[0])
            if col not in claims or best < claims[col][0]:
                claims[col] = (best, r)
        return {r: ids[col] for col, (_, r) in sorted(claims.items(), key=lambda item: item[1])}


def _grow(a: np.ndarray, n: int) -> np.ndarray:
    """`a` with at least n rows (capacity doubled), new rows zero."""
    out = np.zeros((max(n, 2 * len(a), 64),) + a.shape[1:], a.dtype)
    out[: len(a)] = a
    return out
