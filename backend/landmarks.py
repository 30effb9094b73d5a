"""Landmark admission: a track becomes a graph landmark only once it is well triangulated.

Admitting a landmark on first sight makes iSAM2 throw `IndeterminantLinearSystemException`, so a track enters
after `min_views` keyframe views with `min_parallax_deg` of ray parallax, in front of every camera, with every
view reprojecting within `max_reprojection_px`. Observations are kept in undistorted pixels (see factors.py).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from vio.config import LandmarkConfig

OUTLIER_FACTOR = 2.5  # a view reprojecting beyond this many times max_reprojection_px is an outlier


@dataclass(slots=True)
class Track:
    """One feature track's keyframe observations: keyframe index -> undistorted pixel (2,)."""

    views: dict[int, np.ndarray] = field(default_factory=dict)
    admitted: bool = False
    rejected_until: int = -1  # do not retry triangulation before this many views
    # after `LandmarkBook.prune`: (earliest kept view, the start of the unbroken run it belonged to), and the
    # track's first view (keyframe, pixel), which its pruned views no longer show
    origin: tuple[int, int] | None = None
    first: tuple[int, np.ndarray] | None = None

    def run_start(self, k: int) -> int:
        """The first keyframe of the unbroken run of views (consecutive keyframes) that ends at or passes k."""
        start = k
        while start - 1 in self.views:
            start -= 1
        if self.origin is not None and start == self.origin[0]:
            return self.origin[1]
        return start

    def first_view(self) -> tuple[int, np.ndarray]:
        """(keyframe, undistorted pixel) of the track's first view, also after its old views were pruned."""
        if self.first is not None:
            return self.first
        k0 = min(self.views)
        return k0, self.views[k0]


def camera_poses(world_T_body: dict[int, np.ndarray], body_T_cam: np.ndarray, ks: list[int]) -> np.ndarray:
    """(M, 4, 4) world_T_cam for keyframes ks."""
    return np.stack([world_T_body[k] @ body_T_cam for k in ks])


def triangulate(world_T_cam: np.ndarray, xn: np.ndarray) -> np.ndarray:
    """Linear (DLT) triangulation of one point from M views: world_T_cam (M, 4, 4), normalized xn (M, 2) -> (3,)."""
    cam_T_world_R = np.transpose(world_T_cam[:, :3, :3], (0, 2, 1))
    c = world_T_cam[:, :3, 3]
    rows = []
    rhs = []
    for R, ci, (x, y) in zip(cam_T_world_R, c, xn, strict=True):
        a1 = R[0] - x * R[2]  # (R (P - c))_x - x (R (P - c))_z = 0
        a2 = R[1] - y * R[2]
        rows += [a1, a2]
        rhs += [a1 @ ci, a2 @ ci]
    A = np.asarray(rows)
    sol, *_ = np.linalg.lstsq(A, np.asarray(rhs), rcond=None)
    return sol


def project(world_T_cam: np.ndarray, p_world: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project one world point into M cameras: returns (M, 2) pixels and (M,) depths (m)."""
    R = world_T_cam[:, :3, :3]
    p_cam = np.einsum("mji,mj->mi", R, p_world[None, :] - world_T_cam[:, :3, 3])
    z = p_cam[:, 2]
    uv = np.column_stack([K[0, 0] * p_cam[:, 0] / z + K[0, 2], K[1, 1] * p_cam[:, 1] / z + K[1, 2]])
    return uv, z


def parallax_deg(world_T_cam: np.ndarray, xn: np.ndarray) -> float:
    """Largest angle between the world-frame viewing rays, deg."""
    rays = np.column_stack([xn, np.ones(len(xn))])
    rays = np.einsum("mij,mj->mi", world_T_cam[:, :3, :3], rays)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    cos = np.clip(rays @ rays.T, -1.0, 1.0)
    return float(np.degrees(np.arccos(cos.min())))


class LandmarkBook:
    """Observation buffer and admission test for all tracks."""

    def __init__(self, K: np.ndarray, body_T_cam: np.ndarray, cfg: LandmarkConfig) -> None:
        self.K = np.asarray(K, float)
        self.K_inv = np.linalg.inv(self.K)
        self.body_T_cam = np.asarray(body_T_cam, float)
        self.cfg = cfg
        self.tracks: dict[int, Track] = {}
        self._viewed: set[int] = set()  # tracks given views since `prune` last left them with none

    def observe(self, k: int, ids: np.ndarray, uv_px: np.ndarray) -> None:
        """Record keyframe k's observations (undistorted pixels)."""
        js = ids.tolist()
        for j, uv in zip(js, uv_px, strict=True):
            self.tracks.setdefault(int(j), Track()).views[k] = np.asarray(uv, float)
        self._viewed.update(js)

    def normalized(self, uv_px: np.ndarray) -> np.ndarray:
        uv_px = np.atleast_2d(uv_px)
        return (uv_px - self.K[:2, 2]) / np.array([self.K[0, 0], self.K[1, 1]])

    def try_admit(
        self, j: int, world_T_body: dict[int, np.ndarray], min_parallax_deg: float | None = None
    ) -> np.ndarray | None:
        """Triangulate track j from the views whose pose is known; returns the world point (3,) if admissible.

        Admissible: `min_views` views, `min_parallax_deg` of parallax (the config's unless given), in front of
        every camera (> 5 cm), median
        reprojection error within `max_reprojection_px`. Views reprojecting beyond `OUTLIER_FACTOR` times that
        are dropped from the track (they never become factors); the point is re-triangulated without them.
        """
        tr = self.tracks[j]
        ks = [k for k in tr.views if k in world_T_body]
        if len(ks) < self.cfg.min_views or len(ks) < tr.rejected_until:
            return None
        Twc = camera_poses(world_T_body, self.body_T_cam, ks)
        uv = np.stack([tr.views[k] for k in ks])
        xn = self.normalized(uv)
        if parallax_deg(Twc, xn) < (self.cfg.min_parallax_deg if min_parallax_deg is None else min_parallax_deg):
            return None
        p = triangulate(Twc, xn)
        proj, z = project(Twc, p, self.K)
        err = np.linalg.norm(proj - uv, axis=1)
        good = err <= OUTLIER_FACTOR * self.cfg.max_reprojection_px
        if np.isfinite(err).all() and np.median(err) <= self.cfg.max_reprojection_px and good.sum() >= len(ks) - 1:
            if not good.all():
                Twc, xn, uv = Twc[good], xn[good], uv[good]
                for k in np.asarray(ks)[~good].tolist():
                    del tr.views[k]
                p = triangulate(Twc, xn)
                proj, z = project(Twc, p, self.K)
                err = np.linalg.norm(proj - uv, axis=1)
            if (
                len(uv) >= self.cfg.min_views
                and np.all(z > 0.05)
                and err.max() <= OUTLIER_FACTOR * self.cfg.max_reprojection_px
            ):
                return p
        tr.rejected_until = len(ks) + 1
        return None

    def reprojection_px(self, world_T_body: np.ndarray, p_world: np.ndarray, uv_px: np.ndarray) -> tuple[float, float]:
        """Reprojection error (px) and depth (m) of a world point in the camera of one body pose."""
        Twc = (world_T_body @ self.body_T_cam)[None]
        proj, z = project(Twc, p_world, self.K)
        return float(np.linalg.norm(proj[0] - uv_px)), float(z[0])

    def reprojections_px(
        self, world_T_body: np.ndarray, p_world: np.ndarray, uv_px: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """`reprojection_px` of N world points (N, 3) against their pixels (N, 2) at once: (N,) errors px and (N,)
        depths m (equal to the one-point version up to rounding in the last bits)."""
        Twc = world_T_body @ self.body_T_cam
        p_cam = (np.asarray(p_world, float).reshape(-1, 3) - Twc[:3, 3]) @ Twc[:3, :3]
        z = p_cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            du = self.K[0, 0] * p_cam[:, 0] / z + self.K[0, 2] - uv_px[:, 0]
            dv = self.K[1, 1] * p_cam[:, 1] / z + self.K[1, 2] - uv_px[:, 1]
            return np.sqrt(du * du + dv * dv), z

    def prune(self, before: int, drop_lost: bool) -> int:
        """Bounded memory: drop the views of keyframes before `before` (older than anything the estimator looks
        at again: admission, the blind stretch and the at-rest test look at most a window back); with `drop_lost`
        (the source never reuses a track id, as the tracker does) also the tracks left without views that never
        became landmarks. An admitted track stays (its landmark can be seen again), its first view kept apart.
        Returns the number of views dropped. What the estimator computes is unchanged: `run_start` answers as
        before (`origin`), and no decision counts views outside the window."""
        dropped, gone, emptied = 0, [], []
        for j in self._viewed:  # not every track: the landmarks of a long run keep tracks with no views left
            tr = self.tracks.get(j)
            if tr is None or not tr.views:
                emptied.append(j)
                continue
            if min(tr.views) >= before:
                continue
            if tr.admitted and tr.first is None:
                k0, uv0 = tr.first_view()
                tr.first = (k0, np.array(uv0))  # a copy: the view is a row of its keyframe's whole pixel array
            kept = {kk: uv for kk, uv in tr.views.items() if kk >= before}
            if kept:
                k_first = min(kept)
                if k_first - 1 in tr.views:  # its run began among the pruned views
                    tr.origin = (k_first, tr.run_start(k_first))
            dropped += len(tr.views) - len(kept)
            tr.views = kept  # a new dict: one emptied by deletions keeps its table
            if not kept:
                emptied.append(j)
                if not tr.admitted and drop_lost:
                    gone.append(j)
        self._viewed.difference_update(emptied)
        for j in gone:
            del self.tracks[j]
        return dropped

    def forget_before(self, k: int) -> None:
        """Drop views older than keyframe k and un-admit every landmark (used after a solver rebuild)."""
        for tr in self.tracks.values():
            tr.views = {kk: uv for kk, uv in tr.views.items() if kk >= k}
            if tr.origin is not None:  # a run that began among pruned views now begins at k at the earliest
                tr.origin = None if tr.origin[0] < k else (tr.origin[0], max(tr.origin[1], k))
            tr.admitted = False
            tr.rejected_until = -1
