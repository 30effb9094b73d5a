"""Ray-cast renderer: distorted pinhole camera, textured axis-aligned boxes, mip-mapped trilinear texture lookup.

One undistorted ray per distorted pixel centre (pixel (u, v) is at coordinate (u, v), OpenCV's convention) is
computed once; per frame the rays are rotated into the world, intersected analytically with the room (exit face)
and the solid boxes (entry face, only inside the projected bounding box when it is in front), and the nearest hit
samples its face texture at the mip level matching the pixel footprint. Pixels on a surface boundary are
re-rendered with 2 x 2 sub-samples (anti-aliased edges keep sub-pixel accuracy at silhouettes). Seeded Gaussian
pixel noise (1.5 DN) is added per frame.
"""

from __future__ import annotations

import cv2
import numpy as np

from vio.capture import encode_png
from vio.sim.scene import Scene
from vio.sim.textures import build_atlas, scene_textures

NOISE_DN = 1.5  # pixel noise standard deviation, grey levels
_TINY = np.float32(1e-12)


def _rays(cam, u: np.ndarray, v: np.ndarray) -> np.ndarray:
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

    def __init__(self, scene: Scene, camera) -> None:
        self.scene = scene
        self.camera = camera
        h, w = camera.height, camera.width
        u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        self.rays = _rays(camera, u, v)
        su, sv = np.meshgrid(np.arange(2 * w) * 0.5 - 0.25, np.arange(2 * h) * 0.5 - 0.25)
        self.sub_rays = _rays(camera, su, sv)  # (2, 2h, 2w): pixel (u, v) owns [2v:2v+2, 2u:2u+2]
        self.atlas = _atlas(scene)
        self._pow_half = (0.5 ** np.arange(32)).astype(np.float32)
        self._norm15 = (1.0 + self.rays[0] ** 2 + self.rays[1] ** 2) ** np.float32(0.75)
        self._sub_norm15 = (1.0 + self.sub_rays[0] ** 2 + self.sub_rays[1] ** 2) ** np.float32(0.75)
        self._tables()
        self.focal = np.float32(np.sqrt(camera.fx * camera.fy))
        self._lo = [b.lo.astype(np.float32) for b in scene.boxes]
        self._hi = [b.hi.astype(np.float32) for b in scene.boxes]

    # -- geometry ---------------------------------------------------------------------------------------------
    def _room_exit(self, o: np.ndarray, d: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = self._lo[0], self._hi[0]
        t = [np.where(d[k] > 0, hi[k] - o[k], lo[k] - o[k]) / d[k] for k in range(3)]
        x_min = (t[0] <= t[1]) & (t[0] <= t[2])
        y_min = ~x_min & (t[1] <= t[2])
        t_hit = np.minimum(np.minimum(t[0], t[1]), t[2])
        axis = np.where(x_min, 0, np.where(y_min, 1, 2)).astype(np.int16)
        d_ax = np.where(x_min, d[0], np.where(y_min, d[1], d[2]))
        return t_hit, 2 * axis + (d_ax > 0)

    def _box_entry(self, bi: int, o: np.ndarray, d: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = self._lo[bi], self._hi[bi]
        near, far, pos = [], [], []
        for k in range(3):
            inv = np.float32(1.0) / d[k]
            t1 = (lo[k] - o[k]) * inv
            t2 = (hi[k] - o[k]) * inv
            near.append(np.minimum(t1, t2))
            far.append(np.maximum(t1, t2))
            pos.append(d[k] > 0)
        t_near = np.maximum(np.maximum(near[0], near[1]), near[2])
        t_far = np.minimum(np.minimum(far[0], far[1]), far[2])
        hit = (t_near <= t_far) & (t_near > 0)
        x_max = (near[0] >= near[1]) & (near[0] >= near[2])
        y_max = ~x_max & (near[1] >= near[2])
        face = np.where(x_max, 0 + ~pos[0], np.where(y_max, 2 + ~pos[1], 4 + ~pos[2])).astype(np.int16)
        return np.where(hit, t_near, np.float32(np.inf)), face + np.int16(6 * bi)

    def _window(self, bi: int, cam_R_world: np.ndarray, o: np.ndarray) -> tuple[slice, slice] | None:
        """Pixel window holding the projection of box bi (None: not visible); the whole image if it straddles."""
        cam = self.camera
        p_cam = (self.scene.boxes[bi].corners() - o) @ cam_R_world.T
        if np.any(p_cam[:, 2] < 0.02):
            return slice(0, cam.height), slice(0, cam.width)
        uv = cam.project(p_cam)
        u0, v0 = np.floor(uv.min(axis=0)).astype(int) - 4
        u1, v1 = np.ceil(uv.max(axis=0)).astype(int) + 5
        u0, v0, u1, v1 = max(u0, 0), max(v0, 0), min(u1, cam.width), min(v1, cam.height)
        if u0 >= u1 or v0 >= v1:
            return None
        return slice(v0, v1), slice(u0, u1)

    def trace(self, o: np.ndarray, d: list[np.ndarray], windows: list | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Nearest hit t (in ray units) and surface id (6 * box + face) of world rays (dx, dy, dz) from o."""
        t, sid = self._room_exit(o, d)
        for bi in range(1, len(self.scene.boxes)):
            win = ... if windows is None else windows[bi]
            if win is None:
                continue
            tb, fb = self._box_entry(bi, o, [c[win] for c in d])
            closer = tb < t[win]
            t[win] = np.where(closer, tb, t[win])
            sid[win] = np.where(closer, fb, sid[win])
        return t, sid

    # -- shading ----------------------------------------------------------------------------------------------
    def _tables(self) -> None:
        boxes = self.scene.boxes
        n = 6 * len(boxes)
        self._t_axis = np.repeat(np.arange(6) // 2, 1)[np.arange(n) % 6].astype(np.int8)
        self._t_lo_a = np.zeros(n, np.float32)
        self._t_lo_b = np.zeros(n, np.float32)
        self._t_inv_texel = np.zeros(n, np.float32)
        self._t_shade = np.zeros(n, np.float32)
        for s in range(n):
            bi, face = divmod(s, 6)
            axis = face // 2
            self._t_lo_a[s] = boxes[bi].lo[(axis + 1) % 3]
            self._t_lo_b[s] = boxes[bi].lo[(axis + 2) % 3]
            self._t_inv_texel[s] = 1.0 / boxes[bi].texel_m
            self._t_shade[s] = boxes[bi].shade[face]
        self._t_maxlevel = (self.atlas.levels - 1).astype(np.float32)
        self._t_levels = self.atlas.levels.astype(np.int32)
        self._n_levels = self.atlas.origin.shape[1]
        self._t_org_x = np.ascontiguousarray(self.atlas.origin[..., 0].reshape(-1))
        self._t_org_y = np.ascontiguousarray(self.atlas.origin[..., 1].reshape(-1))
        self._t_max_x = np.ascontiguousarray(self.atlas.size_max[..., 0].reshape(-1))
        self._t_max_y = np.ascontiguousarray(self.atlas.size_max[..., 1].reshape(-1))

    def shade(self, o: np.ndarray, d: list[np.ndarray], t: np.ndarray, sid: np.ndarray, norm15: np.ndarray):
        """Radiance in [0, 1] of the hits (t, sid) of world rays (dx, dy, dz) from o (arrays of one shape).

        norm15 is |ray|^1.5 per ray (the ray lengths do not change under rotation).
        """
        p = [o[k] + t * d[k] for k in range(3)]
        sid = sid.astype(np.int32)
        ax = self._t_axis.take(sid)
        is_x, is_y = ax == 0, ax == 1
        u = np.where(is_x, p[1], np.where(is_y, p[2], p[0]))
        v = np.where(is_x, p[2], np.where(is_y, p[0], p[1]))
        dn = np.abs(np.where(is_x, d[0], np.where(is_y, d[1], d[2])))
        inv_texel = self._t_inv_texel.take(sid)
        tu = (u - self._t_lo_a.take(sid)) * inv_texel
        tv = (v - self._t_lo_b.take(sid)) * inv_texel
        # texels per pixel: distance / (f sqrt(cos)), cos = |d_n| / |d|, distance = t |d|
        footprint = t * norm15 * inv_texel / (self.focal * np.sqrt(np.maximum(dn, np.float32(1e-6))))
        level = np.clip(np.log2(np.maximum(footprint, np.float32(1e-6))), np.float32(0.0), self._t_maxlevel.take(sid))
        l0 = level.astype(np.int32)
        frac = level - l0
        l1 = np.minimum(l0 + 1, self._t_levels.take(sid) - 1)
        val0 = self._lookup(sid, l0, tu, tv)
        val1 = self._lookup(sid, l1, tu, tv)
        return self._t_shade.take(sid) * (val0 + frac * (val1 - val0))

    def _lookup(self, sid: np.ndarray, lv: np.ndarray, tu: np.ndarray, tv: np.ndarray) -> np.ndarray:
        key = sid * np.int32(self._n_levels) + lv
        scale = self._pow_half.take(lv)
        x = np.minimum(np.maximum(tu * scale, np.float32(0.0)), self._t_max_x.take(key)) + self._t_org_x.take(key)
        y = np.minimum(np.maximum(tv * scale, np.float32(0.0)), self._t_max_y.take(key)) + self._t_org_y.take(key)
        shape = x.shape
        if x.ndim == 1:
            x, y = x[None, :], y[None, :]
        out = cv2.remap(self.atlas.image, x, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return out.reshape(shape)

    # -- frames -----------------------------------------------------------------------------------------------
    def render(self, world_T_cam: np.ndarray, rng: np.random.Generator | None = None) -> np.ndarray:
        """(H, W) uint8 image seen from world_T_cam (4x4); noise from rng (None: noise-free)."""
        world_R_cam = world_T_cam[:3, :3].astype(np.float32)
        o = world_T_cam[:3, 3].astype(np.float32)
        d = _rotate(world_R_cam, self.rays[0], self.rays[1])
        cam_R_world = world_T_cam[:3, :3].T
        windows = [None] + [self._window(bi, cam_R_world, world_T_cam[:3, 3]) for bi in range(1, len(self._lo))]
        t, sid = self.trace(o, d, windows)
        img = self.shade(o, d, t, sid, self._norm15)
        edge = np.zeros(sid.shape, bool)
        dh = sid[:, 1:] != sid[:, :-1]
        dv = sid[1:, :] != sid[:-1, :]
        edge[:, 1:] |= dh
        edge[:, :-1] |= dh
        edge[1:, :] |= dv
        edge[:-1, :] |= dv
        vv, uu = np.nonzero(edge)
        if vv.size:  # anti-aliasing: 2 x 2 sub-samples on surface boundaries
            rows = (2 * vv[:, None] + np.array([0, 0, 1, 1])).ravel()
            cols = (2 * uu[:, None] + np.array([0, 1, 0, 1])).ravel()
            ds = _rotate(world_R_cam, self.sub_rays[0][rows, cols], self.sub_rays[1][rows, cols])
            ts, sids = self.trace(o, ds)
            img[vv, uu] = self.shade(o, ds, ts, sids, self._sub_norm15[rows, cols]).reshape(-1, 4).mean(axis=1)
        val = img * np.float32(255.0)
        if rng is not None:
            val += rng.standard_normal(val.shape, dtype=np.float32) * np.float32(NOISE_DN)
        return np.clip(np.rint(val), 0, 255).astype(np.uint8)


_WORKER: dict = {}


def _init_worker(scene: Scene, camera) -> None:
    cv2.setNumThreads(1)
    _WORKER["renderer"] = Renderer(scene, camera)


def _render_one(job: tuple[np.ndarray, np.random.SeedSequence]) -> bytes:
    world_T_cam, seq = job
    return encode_png(_WORKER["renderer"].render(world_T_cam, np.random.default_rng(seq)))


def camera_poses(sc, t_ns: np.ndarray) -> np.ndarray:
    """(F, 4, 4) world_T_cam of scenario `sc` at frame times t_ns."""
    p, R = sc.trajectory.pose((t_ns - sc.t0_ns).astype(np.float64) * 1e-9)
    world_T_body = np.tile(np.eye(4), (len(t_ns), 1, 1))
    world_T_body[:, :3, :3] = R
    world_T_body[:, :3, 3] = p
    return world_T_body @ sc.camera.body_T_cam


def render_pngs(sc, t_ns: np.ndarray, image_seed: np.random.SeedSequence, workers: int | None = None):
    """Yield the PNG bytes of each frame in order; frame i's noise comes from image_seed.spawn(F)[i].

    Frames are rendered by `workers` processes (default 2 when there are 40+ frames), each building its own
    renderer; the bytes do not depend on the number of workers.
    """
    import multiprocessing as mp

    poses = camera_poses(sc, t_ns)
    jobs = list(zip(poses, image_seed.spawn(len(t_ns)), strict=True))
    if workers is None:
        workers = 2 if len(jobs) >= 40 else 1
    if workers <= 1:
        renderer = Renderer(sc.scene, sc.camera)
        for world_T_cam, seq in jobs:
            yield encode_png(renderer.render(world_T_cam, np.random.default_rng(seq)))
        return
    # forkserver: a fresh process forks the workers (forking this process can deadlock OpenCV's thread pool).
    method = "forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn"
    with mp.get_context(method).Pool(workers, initializer=_init_worker, initargs=(sc.scene, sc.camera)) as pool:
        yield from pool.imap(_render_one, jobs, chunksize=4)
