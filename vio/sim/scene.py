"""Scene geometry in the world frame (z up, metres): axis-aligned textured boxes and the part, a triangle mesh.

One box is the room (the camera is inside it; its inner faces are the walls, floor and ceiling); the others are
solid boxes seen from outside (the table, furniture). A box face is numbered `2 * axis + side` (axis 0/1/2 =
x/y/z, side 0 = the low face, 1 = the high face). The part (`PlacedPart`: the measured object, a `vio.sim.parts.Part`
in its own frame in millimetres) stands on a support at `world_T_part`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from vio.errors import SimulationError
from vio.geometry import sample_triangles
from vio.sim.parts import Part

SURFACES = ("speckle", "plain")  # the part's paint (vio.sim.part_render)


@dataclass(frozen=True)
class Box:
    """An axis-aligned box with a procedural texture on each face."""

    name: str
    lo: np.ndarray  # (3,) min corner in world, m
    hi: np.ndarray  # (3,) max corner in world, m
    texel_m: float  # texture resolution, m per texel
    style: str  # texture style: "object", "table", "wall", "furniture"
    inside: bool = False  # True for the room: rays start inside and hit the inner faces
    hidden_faces: tuple[int, ...] = ()  # faces never seen (e.g. the cube's bottom on the table)
    shade: tuple[float, ...] = (1.0, 1.0, 1.0, 1.0, 1.0, 1.0)  # per-face brightness (fixed diffuse lighting)

    def face_extent(self, face: int) -> tuple[int, int, float, float]:
        """(axis_u, axis_v, size_u_m, size_v_m) of a face: texture u runs along axis_u, v along axis_v."""
        axis = face // 2
        a, b = (axis + 1) % 3, (axis + 2) % 3
        return a, b, float(self.hi[a] - self.lo[a]), float(self.hi[b] - self.lo[b])

    def face_area(self, face: int) -> float:
        _, _, su, sv = self.face_extent(face)
        return su * sv

    def corners(self) -> np.ndarray:
        """(8, 3) corners; bit 0/1/2 of the index selects hi in x/y/z."""
        return np.array(
            [[(self.hi if (i >> k) & 1 else self.lo)[k] for k in range(3)] for i in range(8)], dtype=np.float64
        )

    def contains(self, p: np.ndarray, margin: float = 1e-6) -> np.ndarray:
        return np.all((p > self.lo + margin) & (p < self.hi - margin), axis=1)


@dataclass(frozen=True)
class PlacedPart:
    """The part in the world: its mesh (part frame, mm), its pose, and its surface finish."""

    part: Part
    world_T_part: np.ndarray  # (4, 4) part frame (origin on the base, z up) in world, translation in m
    surface: str = "speckle"  # "speckle" | "plain"

    def vertices_world(self) -> np.ndarray:
        """(V, 3) vertices in world, m."""
        v = self.part.vertices_mm * 1e-3
        return v @ self.world_T_part[:3, :3].T + self.world_T_part[:3, 3]

    def triangles_world(self) -> np.ndarray:
        """(F, 3, 3) triangles in world, m, counter-clockwise seen from outside."""
        return self.vertices_world()[self.part.faces]

    def bounds_corners_world(self) -> np.ndarray:
        """(8, 3) corners of the part's bounding box (part frame) in world, m; bit 0/1/2 selects max x/y/z."""
        b = self.part.bounds_mm() * 1e-3
        c = np.array([[b[(i >> k) & 1, k] for k in range(3)] for i in range(8)])
        return c @ self.world_T_part[:3, :3].T + self.world_T_part[:3, 3]

    def seen_faces(self) -> np.ndarray:
        """(F,) bool: faces a camera can see (not the base lying on the support, z = 0 facing down)."""
        v = self.part.vertices_mm[self.part.faces]
        n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        down = n[:, 2] < -0.999 * np.linalg.norm(n, axis=1)
        return ~(down & (np.abs(v[:, :, 2]).max(axis=1) < 1e-6))


@dataclass(frozen=True)
class Scene:
    """The room, the solid boxes, and the measured part."""

    room: Box
    solids: tuple[Box, ...]
    part: PlacedPart | None  # the measured object; None if there is none
    texture_seed: int  # seed of the procedural textures (boxes and the part's speckle)
    meta: dict = field(default_factory=dict)  # descriptive values for scene.yaml

    @property
    def boxes(self) -> tuple[Box, ...]:
        """All boxes; index 0 is the room (surface ids are `6 * box_index + face`)."""
        return (self.room, *self.solids)

    def object_corners_world(self) -> np.ndarray:
        """(8, 3) corners of the part's bounding box in world, m (the cube's corners for the cube)."""
        if self.part is None:
            raise SimulationError("this scene has no part")
        return self.part.bounds_corners_world()

    @cached_property
    def _surfaces(self) -> list[tuple[int, int, float]]:
        out = []
        for bi, box in enumerate(self.boxes):
            for f in range(6):
                if f not in box.hidden_faces:
                    out.append((bi, f, box.face_area(f)))
        return out

    def sample_surface_points(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """(n, 3) world points uniformly (by area) on the surfaces a camera can see (boxes and the part), m.

        Points hidden inside another box (e.g. the table top under the part) or under the part's footprint are
        rejected and redrawn.
        """
        surf = self._surfaces
        area = np.array([s[2] for s in surf] + [self._part_area])
        out = np.zeros((0, 3))
        while out.shape[0] < n:
            m = max(2 * (n - out.shape[0]), 16)
            pick = rng.choice(len(area), size=m, p=area / area.sum())
            uv = rng.uniform(0.0, 1.0, (m, 2))
            pts = np.zeros((m, 3))
            normal = np.zeros((m, 3))  # towards the viewer: outward for solids, inward for the room
            on_part = pick == len(surf)
            if on_part.any():
                pts[on_part], normal[on_part] = self._part_points(int(on_part.sum()), rng)
            for k, (bi, f, _) in enumerate(surf):
                sel = pick == k
                if not sel.any():
                    continue
                box = self.boxes[bi]
                a, b, su, sv = box.face_extent(f)
                axis = f // 2
                pts[sel, axis] = box.hi[axis] if f % 2 else box.lo[axis]
                pts[sel, a] = box.lo[a] + uv[sel, 0] * su
                pts[sel, b] = box.lo[b] + uv[sel, 1] * sv
                normal[sel, axis] = (1.0 if f % 2 else -1.0) * (-1.0 if box.inside else 1.0)
            probe = pts + 1e-4 * normal
            hidden = np.zeros(m, bool)
            for box in self.solids:
                hidden |= box.contains(probe, margin=0.0)
            hidden |= self._under_part(probe) & ~on_part
            out = np.vstack([out, pts[~hidden]])
        return out[:n]

    @cached_property
    def _part_area(self) -> float:
        if self.part is None:
            return 0.0
        tri = self.part.triangles_world()[self.part.seen_faces()]
        return float(0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum())

    def _part_points(self, m: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """m points uniformly on the part's seen faces and their outward normals, world."""
        tri = self.part.triangles_world()[self.part.seen_faces()]
        p, face = sample_triangles(tri, m, rng)
        n = np.cross(tri[face, 1] - tri[face, 0], tri[face, 2] - tri[face, 0])
        return p, n / np.linalg.norm(n, axis=1, keepdims=True)

    def _under_part(self, p: np.ndarray) -> np.ndarray:
        """(N,) bool: points inside the part's bounding box (support points under its footprint), part frame."""
        if self.part is None:
            return np.zeros(len(p), bool)
        T = np.linalg.inv(self.part.world_T_part)
        q = (p @ T[:3, :3].T + T[:3, 3]) * 1e3  # part frame, mm
        b = self.part.part.bounds_mm()
        return np.all((q > b[0] - 1e-3) & (q < b[1] + 1e-3), axis=1)
