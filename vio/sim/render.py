"""Ray-cast renderer: distorted pinhole camera, textured axis-aligned boxes, and the part as a triangle mesh.

One undistorted ray per distorted pixel centre (pixel (u, v) is at coordinate (u, v), OpenCV's convention) is
computed once; per frame the rays are rotated into the world, intersected analytically with the room (exit face)
and the solid boxes (entry face, only inside the projected bounding box when it is in front), and, inside the
part's projected bounding box, with the part's mesh through Embree (vio.sim.part_render). A box hit samples its
face texture at the mip level matching the pixel footprint; a part hit is shaded (speckle albedo, Lambertian light,
cast shadows). Pixels on a surface boundary or a crease of the part are re-rendered with 8 sub-samples in an
N-rooks pattern (anti-aliased edges keep sub-pixel accuracy at silhouettes). Seeded Gaussian pixel noise (1.5 DN)
is added per frame.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np

from vio.records import CameraCalib
from vio.sim.part_render import PartSurface
from vio.sim.scene import Scene
from vio.sim.textures import build_atlas, scene_textures

if TYPE_CHECKING:
    from vio.sim.scenario import Scenario

NOISE_DN = 1.5  # pixel noise standard deviation, grey levels
# Sub-sample offsets (px) of boundary pixels: 8 rooks (every row and column once), so edges of any slope are
# located to 1/8 px.
_ROOKS = np.array([0, 4, 7, 5, 2, 6, 1, 3])
_SUB_DX = ((np.arange(8) + 0.5) / 8.0 - 0.5).astype(np.float32)
_SUB_DY = ((_ROOKS + 0.5) / 8.0 - 0.5).astype(np.float32)
_TINY = np.float32(1e-12)
_REMAP_MAX, _REMAP_COLS = 32767, 4096  # cv2.remap's largest map side; the row length of flattened lookups
_CREASE_COS = np.float32(np.cos(np.radians(20.0)))  # neighbouring part pixels whose normals differ more: an edge


def _rays(cam: CameraCalib, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Undistorted camera-frame rays (x, y, 1) through distorted pixel coordinates: (2, h, w) x, y float32."""
    uv = np.column_stack([u.ravel(), v.ravel()])
    xy = cam.undistort_to_normalized(uv, iterations=4)
    residual = np.abs(cam.distort_normalized(xy) - uv).max()
    if residual > 1e-6:  # strong distortion: let the solver run to convergence
        xy = cam.undistort_to_normalized(uv)
    return xy.T.reshape(2, *u.shape).astype(np.float32)


def _rotate(R: np.ndarray, rx: np.ndarray, ry: np.ndarray) -> list[np.ndarray]:
    """World components of camera rays (rx, ry, 1) rotated by world_R_cam; exact zeros nudged to 1e-12."""
    out = []
    for k in range(3):
        c = R[k, 0] * rx + R[k, 1] * ry + np.float32(R[k, 2])
        c[c == 0] = _TINY
        out.append(c)
    return out


_ATLAS_CACHE: dict[str, object] = {}


def _atlas(scene: Scene):
    """The scene's texture atlas, cached per process for the last scene (tests simulate the same scene often)."""
    key = repr((scene.texture_seed, [(b.name, b.lo.tolist(), b.hi.tolist(), b.texel_m, b.style) for b in scene.boxes]))
    if key not in _ATLAS_CACHE:
        _ATLAS_CACHE.clear()
        _ATLAS_CACHE[key] = build_atlas(scene_textures(scene))
    return _ATLAS_CACHE[key]


class Renderer:
    """Renders grayscale frames of a scenario's scene from camera poses (world_T_cam)."""

    def __init__(self, scene: Scene, camera: CameraCalib) -> None:
        self.scene = scene
        self.camera = camera
        h, w = camera.height, camera.width
        u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        self.rays = _rays(camera, u, v)
        pu, pv = np.meshgrid(np.arange(-1.0, w + 1.0), np.arange(-1.0, h + 1.0))
        self.rays_pad = _rays(camera, pu, pv)  # (2, h + 2, w + 2): pixel (u, v) at [v + 1, u + 1]
        self.atlas = _atlas(scene)
        self._norm15 = (1.0 + self.rays[0] ** 2 + self.rays[1] ** 2) ** np.float32(0.75)
        self._tables()
        self.focal = np.float32(np.sqrt(camera.fx * camera.fy))
        self._lo = [b.lo.astype(np.float32) for b in scene.boxes]
        self._hi = [b.hi.astype(np.float32) for b in scene.boxes]
        self.part_sid = 6 * len(scene.boxes)  # surface id of every part hit (boxes use 6 * box + face)
        speckle_seed = np.random.SeedSequence([scene.texture_seed, 1])
        self.part = PartSurface(scene.part, speckle_seed) if scene.part is not None else None

    # -- geometry ---------------------------------------------------------------------------------------------
    def _room_exit(self, o: np.ndarray, d: list[np.ndarray], inv: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = self._lo[0], self._hi[0]
        t = [np.where(d[k] > 0, hi[k] - o[k], lo[k] - o[k]) * inv[k] for k in range(3)]
        x_min = (t[0] <= t[1]) & (t[0] <= t[2])
        y_min = ~x_min & (t[1] <= t[2])
        t_hit = np.minimum(np.minimum(t[0], t[1]), t[2])
        axis = np.where(x_min, 0, np.where(y_min, 1, 2)).astype(np.int16)
        d_ax = np.where(x_min, d[0], np.where(y_min, d[1], d[2]))
        return t_hit, 2 * axis + (d_ax > 0)

    def _box_entry(
        self, bi: int, o: np.ndarray, d: list[np.ndarray], inv: list[np.ndarray], t: np.ndarray, sid: np.ndarray
    ) -> None:
        """Update the nearest hits (t, sid) in place with box bi, seen from outside: only its faces turned towards
        o can be entered, and a ray enters a convex box through at most one of them."""
        lo, hi = self._lo[bi], self._hi[bi]
        for k in range(3):
            if o[k] > hi[k]:
                plane, face = hi[k], 2 * k + 1
            elif o[k] < lo[k]:
                plane, face = lo[k], 2 * k
            else:
                continue
            a, b = (k + 1) % 3, (k + 2) % 3
            tk = (plane - o[k]) * inv[k]
            pa = o[a] + tk * d[a]
            pb = o[b] + tk * d[b]
            hit = (tk > 0) & (tk < t) & (pa >= lo[a]) & (pa <= hi[a]) & (pb >= lo[b]) & (pb <= hi[b])
            t[hit] = tk[hit]
            sid[hit] = 6 * bi + face

    def _window(self, corners: np.ndarray, cam_R_world: np.ndarray, o: np.ndarray) -> tuple[slice, slice] | None:
        """Pixel window holding the projection of a box with these (8, 3) world corners (None: not visible); the
        whole image if it straddles the camera plane."""
        cam = self.camera
        p_cam = (corners - o) @ cam_R_world.T
        if np.any(p_cam[:, 2] < 0.02):
            return slice(0, cam.height), slice(0, cam.width)
        uv = cam.project(p_cam)
        u0, v0 = np.floor(uv.min(axis=0)).astype(int) - 4
        u1, v1 = np.ceil(uv.max(axis=0)).astype(int) + 5
        u0, v0, u1, v1 = max(u0, 0), max(v0, 0), min(u1, cam.width), min(v1, cam.height)
        if u0 >= u1 or v0 >= v1:
            return None
        return slice(v0, v1), slice(u0, u1)

    def trace(
        self, o: np.ndarray, d: list[np.ndarray], windows: list | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Nearest hit t (in ray units), surface id (6 * box + face, or `part_sid`) and part triangle (-1: a box) of
        world rays (dx, dy, dz) from o. `windows[i]` limits box i (the last entry: the part) to a pixel window."""
        inv = [np.float32(1.0) / c for c in d]
        t, sid = self._room_exit(o, d, inv)
        for bi in range(1, len(self.scene.boxes)):
            win = ... if windows is None else windows[bi]
            if win is None:
                continue
            tw, sw = t[win], sid[win]  # views
            self._box_entry(bi, o, [c[win] for c in d], [c[win] for c in inv], tw, sw)
        prim = np.full(t.shape, -1, np.int32)
        win = ... if windows is None else windows[-1]
        if self.part is not None and win is not None:
            dw = np.stack([c[win] for c in d], axis=-1)
            tp, pw = self.part.intersect(o, dw.reshape(-1, 3), t[win].reshape(-1))
            tp, pw = tp.reshape(dw.shape[:-1]), pw.reshape(dw.shape[:-1])
            hit = pw >= 0
            t[win] = np.where(hit, tp, t[win])
            sid[win] = np.where(hit, self.part_sid, sid[win])
            prim[win] = pw
        return t, sid, prim

    # -- shading ----------------------------------------------------------------------------------------------
    def _tables(self) -> None:
        """Per-surface constants packed in one table (one gather per frame), and per (surface, level) atlas rows."""
        boxes = self.scene.boxes
        n = 6 * len(boxes)
        # columns: axis, lo along u (texels), lo along v (texels), 1 / texel, max level, shade
        self._surf = np.zeros((n, 6), np.float32)
        for s in range(n):
            bi, face = divmod(s, 6)
            axis = face // 2
            inv_texel = 1.0 / boxes[bi].texel_m
            self._surf[s] = (
                axis,
                boxes[bi].lo[(axis + 1) % 3] * inv_texel,
                boxes[bi].lo[(axis + 2) % 3] * inv_texel,
                inv_texel,
                self.atlas.levels[s] - 1,
                boxes[bi].shade[face],
            )
        self._n_levels = self.atlas.origin.shape[1]
        # columns: max texel x, max texel y, atlas origin x, atlas origin y, 0.5 ** level
        lv = np.tile(np.arange(self._n_levels), n)
        self._level_rows = np.column_stack(
            [self.atlas.size_max.reshape(-1, 2), self.atlas.origin.reshape(-1, 2), 0.5**lv]
        ).astype(np.float32)

    def shade(
        self, o: np.ndarray, d: list[np.ndarray], t: np.ndarray, sid: np.ndarray, prim: np.ndarray, norm15: np.ndarray
    ) -> np.ndarray:
        """Radiance in [0, 1] of the hits (t, sid, prim) of world rays (dx, dy, dz) from o (arrays of one shape).

        norm15 is |ray|^1.5 per ray (the ray lengths do not change under rotation).
        """
        on_part = prim >= 0
        if not on_part.any():
            return self._shade_boxes(o, d, t, sid, norm15)
        # every ray through the box shader (cheaper than gathering the box rays), part hits as the room's face 0
        out = self._shade_boxes(o, d, t, np.where(on_part, 0, sid), norm15)
        dp = np.stack([c[on_part] for c in d], axis=-1).astype(np.float64)
        tp = t[on_part].astype(np.float64)
        p = o.astype(np.float64) + tp[:, None] * dp
        footprint = tp * np.linalg.norm(dp, axis=1) / float(self.focal)  # m per pixel at the hit
        out[on_part] = self.part.radiance(p, prim[on_part], footprint)
        return out

    def _shade_boxes(self, o: np.ndarray, d: list[np.ndarray], t: np.ndarray, sid: np.ndarray, norm15: np.ndarray):
        """Radiance in [0, 1] of box hits: the face texture at the mip level of the pixel footprint."""
        sid = sid.astype(np.int32)
        surf = self._surf.take(sid, axis=0)
        ax = surf[..., 0]
        is_x, is_y = ax == 0, ax == 1
        p = [o[k] + t * d[k] for k in range(3)]
        u = np.where(is_x, p[1], np.where(is_y, p[2], p[0]))
        v = np.where(is_x, p[2], np.where(is_y, p[0], p[1]))
        dn = np.abs(np.where(is_x, d[0], np.where(is_y, d[1], d[2])))
        inv_texel = surf[..., 3]
        tu = u * inv_texel - surf[..., 1]
        tv = v * inv_texel - surf[..., 2]
        # texels per pixel: distance / (f sqrt(cos)), cos = |d_n| / |d|, distance = t |d|
        footprint = t * norm15 * inv_texel / (self.focal * np.sqrt(np.maximum(dn, np.float32(1e-6))))
        max_level = surf[..., 4]
        level = np.clip(np.log2(np.maximum(footprint, np.float32(1e-6))), np.float32(0.0), max_level)
        l0 = level.astype(np.int32)
        frac = level - l0
        key0 = sid * np.int32(self._n_levels) + l0
        key1 = key0 + (l0 < max_level)
        val0 = self._lookup(key0, tu, tv)
        val1 = self._lookup(key1, tu, tv)
        return surf[..., 5] * (val0 + frac * (val1 - val0))

    def _lookup(self, key: np.ndarray, tu: np.ndarray, tv: np.ndarray) -> np.ndarray:
        row = self._level_rows.take(key, axis=0)
        scale = row[..., 4]
        x = np.minimum(np.maximum(tu * scale, np.float32(0.0)), row[..., 0]) + row[..., 2]
        y = np.minimum(np.maximum(tv * scale, np.float32(0.0)), row[..., 1]) + row[..., 3]
        shape, n = x.shape, x.size
        if x.ndim == 1 or max(shape) >= _REMAP_MAX:  # remap wants a 2D map with sides below SHRT_MAX
            rows = -(-n // _REMAP_COLS)
            x = np.pad(x.ravel(), (0, rows * _REMAP_COLS - n)).reshape(rows, _REMAP_COLS)
            y = np.pad(y.ravel(), (0, rows * _REMAP_COLS - n)).reshape(rows, _REMAP_COLS)
        out = cv2.remap(self.atlas.image, x, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return out.ravel()[:n].reshape(shape)

    def _sub_rays(self, vv: np.ndarray, uu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(E, S) camera rays x, y of the sub-samples of pixels (uu, vv), bilinear in the per-pixel ray grid.

        The undistortion map is smooth: interpolating it over one pixel errs by ~1e-4 px.
        """
        x = uu[:, None] + _SUB_DX[None, :] + np.float32(1.0)
        y = vv[:, None] + _SUB_DY[None, :] + np.float32(1.0)
        x0 = np.floor(x).astype(np.int32)
        y0 = np.floor(y).astype(np.int32)
        fx, fy = x - x0, y - y0
        out = []
        for comp in self.rays_pad:
            top = comp[y0, x0] + fx * (comp[y0, x0 + 1] - comp[y0, x0])
            bot = comp[y0 + 1, x0] + fx * (comp[y0 + 1, x0 + 1] - comp[y0 + 1, x0])
            out.append((top + fy * (bot - top)).astype(np.float32))
        return out[0], out[1]

    def surface_points(self, world_T_cam: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points (N, 3) seen at distorted pixels uv (N, 2) from world_T_cam, and their surface ids (N,)."""
        xy = self.camera.undistort_to_normalized(np.asarray(uv, np.float64))
        d = [world_T_cam[k, 0] * xy[:, 0] + world_T_cam[k, 1] * xy[:, 1] + world_T_cam[k, 2] for k in range(3)]
        d = [np.where(c == 0, 1e-12, c) for c in d]
        o = world_T_cam[:3, 3]
        t, sid, _ = self.trace(o, d)
        return o + t[:, None] * np.column_stack(d), sid

    # -- frames -----------------------------------------------------------------------------------------------
    def render(self, world_T_cam: np.ndarray, rng: np.random.Generator | None = None) -> np.ndarray:
        """(H, W) uint8 image seen from world_T_cam (4x4); noise from rng (None: noise-free)."""
        val = self.radiance(world_T_cam) * np.float32(255.0)
        if rng is not None:
            val += rng.standard_normal(val.shape, dtype=np.float32) * np.float32(NOISE_DN)
        return np.clip(np.rint(val), 0, 255).astype(np.uint8)

    def radiance(self, world_T_cam: np.ndarray, rows: tuple[int, int] | None = None) -> np.ndarray:
        """(R, W) float32 noise-free radiance in [0, 1] (1: white, 255 grey levels) of image rows [r0, r1) (None:
        every row) seen from world_T_cam (4x4). A row band is what a rolling shutter reads at one time
        (`vio.sim.phone`); anti-aliasing sees the band's own rows only."""
        r0, r1 = (0, self.camera.height) if rows is None else (int(rows[0]), int(rows[1]))
        band = rows is not None
        rays = self.rays[:, r0:r1] if band else self.rays
        world_R_cam = world_T_cam[:3, :3].astype(np.float32)
        o = world_T_cam[:3, 3].astype(np.float32)
        d = _rotate(world_R_cam, rays[0], rays[1])
        cam_R_world, c = world_T_cam[:3, :3].T, world_T_cam[:3, 3]
        corners = [b.corners() for b in self.scene.boxes[1:]]
        corners += [self.part.corners_world] if self.part is not None else []
        windows = [None] + [self._window(k, cam_R_world, c) for k in corners]
        if band:
            windows = [None] + [_clip_window(w, r0, r1) for w in windows[1:]]
        t, sid, prim = self.trace(o, d, windows)
        img = self.shade(o, d, t, sid, prim, self._norm15[r0:r1] if band else self._norm15)
        edge = np.zeros(sid.shape, bool)
        dh = sid[:, 1:] != sid[:, :-1]
        dv = sid[1:, :] != sid[:-1, :]
        if self.part is not None and (prim >= 0).any():  # creases of the part: normals that turn sharply
            n = self.part.normals[np.maximum(prim, 0)]
            dh |= (
                (prim[:, 1:] >= 0) & (prim[:, :-1] >= 0) & (np.einsum("ijk,ijk->ij", n[:, 1:], n[:, :-1]) < _CREASE_COS)
            )
            dv |= (prim[1:, :] >= 0) & (prim[:-1, :] >= 0) & (np.einsum("ijk,ijk->ij", n[1:], n[:-1]) < _CREASE_COS)
        edge[:, 1:] |= dh
        edge[:, :-1] |= dh
        edge[1:, :] |= dv
        edge[:-1, :] |= dv
        vv, uu = np.nonzero(edge)
        if vv.size:  # anti-aliasing: N-rooks sub-samples on surface boundaries
            rx, ry = self._sub_rays(vv + r0 if band else vv, uu)
            ds = _rotate(world_R_cam, rx, ry)
            ts, sids, prims = self.trace(o, ds)
            norm15 = (1.0 + rx * rx + ry * ry) ** np.float32(0.75)
            img[vv, uu] = self.shade(o, ds, ts, sids, prims, norm15).mean(axis=1)
        return img


def _clip_window(win: tuple[slice, slice] | None, r0: int, r1: int) -> tuple[slice, slice] | None:
    """A full-image pixel window restricted to rows [r0, r1), in the band's own row numbers (None: outside)."""
    if win is None:
        return None
    v0, v1 = max(win[0].start, r0), min(win[0].stop, r1)
    if v0 >= v1:
        return None
    return slice(v0 - r0, v1 - r0), win[1]


def camera_poses(sc: Scenario, t_ns: np.ndarray, camera: CameraCalib | None = None) -> np.ndarray:
    """(F, 4, 4) world_T_cam of scenario `sc`'s camera (or `camera`, e.g. the stills) at times t_ns."""
    p, R = sc.trajectory.pose((t_ns - sc.t0_ns).astype(np.float64) * 1e-9)
    world_T_body = np.tile(np.eye(4), (len(t_ns), 1, 1))
    world_T_body[:, :3, :3] = R
    world_T_body[:, :3, 3] = p
    return world_T_body @ (sc.camera if camera is None else camera).body_T_cam
