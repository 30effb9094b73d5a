"""Ray casting and shading of the part: a triangle mesh through Embree (embreex), a speckle-painted matte surface.

The part is a watertight mesh placed in the world (`PlacedPart`). Rays are intersected with Embree's BVH (one
query per pixel window, single-threaded, deterministic); the hit's radiance is the albedo times Lambertian shading
under one fixed distant light plus ambient, with the part's own cast shadows (an occlusion ray towards the light),
so cavities, countersinks and overhangs read as in a studio.

Surface (`PlacedPart.surface`):
- `speckle` (default): a light grey powder coat with a sprayed pattern of black dots, as a part is prepared for
  photogrammetry. Dot centres lie on the surface (area-uniform, seeded), radii log-uniform in
  [`DOT_MIN_MM`, `DOT_MAX_MM`] so that both the 640x480 video and the full-resolution stills see texture. Each
  dot's edge is filtered over the pixel footprint (the disc is widened to half a pixel with its contrast scaled
  by the area ratio), so the texture is anti-aliased without supersampling.
- `plain`: the powder coat alone (shading only): where multi-view stereo struggles.
"""

from __future__ import annotations

import numpy as np
from embreex import rtcore_scene as rtcs
from embreex.mesh_construction import TriangleMesh
from scipy.spatial import cKDTree

from vio.geometry import sample_triangles
from vio.sim.scene import PlacedPart

LIGHT_DIR_WORLD = np.array([0.45, 0.25, 1.0]) / np.linalg.norm([0.45, 0.25, 1.0])  # towards the light
AMBIENT = 0.3  # share of the radiance that does not depend on the light direction
COAT_ALBEDO = 0.82  # powder coat, grey level / 255
DOT_ALBEDO = 0.10  # sprayed speckle
DOT_MIN_MM, DOT_MAX_MM = 0.25, 2.5  # speckle dot radii, log-uniform
DOT_COVER = 0.6  # expected dots covering a surface point (about 45 % of the surface is dark)
_NEAREST = 6  # dots that can overlap one point
_SHADOW_EPS_M = 2e-5  # occlusion rays start this far off the surface


class PartSurface:
    """The part's geometry for the renderer: Embree scene, face normals, speckle dots (world frame, metres)."""

    def __init__(self, placed: PlacedPart, seed: np.random.SeedSequence | int) -> None:
        self.placed = placed
        tri = placed.triangles_world()  # (F, 3, 3) m
        self.scene = rtcs.EmbreeScene()
        TriangleMesh(self.scene, tri.astype(np.float32))
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        area2 = np.linalg.norm(n, axis=1)
        self.normals = (n / np.maximum(area2, 1e-30)[:, None]).astype(np.float32)  # outward (CCW winding)
        self.corners_world = placed.bounds_corners_world()
        self.speckle = placed.surface == "speckle"
        if self.speckle:
            self._dots(tri, 0.5 * area2, np.random.default_rng(seed))

    def _dots(self, tri: np.ndarray, area_m2: np.ndarray, rng: np.random.Generator) -> None:
        lo, hi = np.log(DOT_MIN_MM * 1e-3), np.log(DOT_MAX_MM * 1e-3)
        mean_r2 = (np.exp(2 * hi) - np.exp(2 * lo)) / (2 * (hi - lo))  # E[r^2] of log-uniform radii, m^2
        n = int(np.ceil(DOT_COVER * area_m2.sum() / (np.pi * mean_r2)))
        self.dot_centres, _ = sample_triangles(tri, n, rng)
        self.dot_radii = np.exp(rng.uniform(lo, hi, n))
        self.tree = cKDTree(self.dot_centres)

    def intersect(self, o: np.ndarray, d: np.ndarray, t_max: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest hits before t_max of rays o + t d (o (3,), d (N, 3), t in ray units): t (N,), triangle (N,), -1
        where the part is not hit first."""
        n = d.shape[0]
        orig = np.broadcast_to(np.asarray(o, np.float32), (n, 3)).copy()
        res = self.scene.run(orig, np.ascontiguousarray(d, np.float32), dists=t_max.astype(np.float32), output=1)
        prim = res["primID"].astype(np.int32)
        return np.where(prim >= 0, res["tfar"], t_max).astype(np.float32), prim

    def radiance(self, p_world: np.ndarray, prim: np.ndarray, footprint_m: np.ndarray) -> np.ndarray:
        """Radiance in [0, 1] at surface points p (N, 3) on triangles prim (N,), pixel footprint (N,) m."""
        n = self.normals[prim].astype(np.float64)
        cos = n @ LIGHT_DIR_WORLD
        lit = cos > 0
        if lit.any():
            start = (p_world[lit] + _SHADOW_EPS_M * n[lit]).astype(np.float32)
            towards = np.broadcast_to(LIGHT_DIR_WORLD.astype(np.float32), start.shape).copy()
            lit[np.flatnonzero(lit)] = self.scene.run(start, towards, query="OCCLUDED") < 0
        shade = AMBIENT + (1.0 - AMBIENT) * np.where(lit, cos, 0.0)
        return (self.albedo(p_world, footprint_m) * shade).astype(np.float32)

    def albedo(self, p_world: np.ndarray, footprint_m: np.ndarray) -> np.ndarray:
        """(N,) albedo of surface points: coat, darkened by the filtered speckle dots that cover them."""
        if not self.speckle or not len(p_world):
            return np.full(len(p_world), COAT_ALBEDO)
        k = min(_NEAREST, len(self.dot_radii))
        dist, idx = self.tree.query(p_world, k=k)
        dist, idx = dist.reshape(len(p_world), k), idx.reshape(len(p_world), k)
        r = self.dot_radii[idx]
        w = np.maximum(footprint_m, 1e-9)[:, None]
        r_eff = np.maximum(r, 0.5 * w)
        cover = np.clip(0.5 + (r_eff - dist) / w, 0.0, 1.0) * (r / r_eff) ** 2
        dark = 1.0 - np.prod(1.0 - cover, axis=1)
        return COAT_ALBEDO + (DOT_ALBEDO - COAT_ALBEDO) * dark
