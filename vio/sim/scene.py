"""Scene geometry: axis-aligned textured boxes in the world frame (z up, metres).

One box is the room (the camera is inside it; its inner faces are the walls, floor and ceiling); the others are
solid boxes seen from outside (the table, furniture, and the object: the cube). A face is numbered
`2 * axis + side` (axis 0/1/2 = x/y/z, side 0 = the low face, 1 = the high face).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from vio.errors import SimulationError


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
class Scene:
    """The room, the solid boxes, and which box is the measured object."""

    room: Box
    solids: tuple[Box, ...]
    object_index: int | None  # index into solids of the object (the cube), None if there is none
    texture_seed: int  # seed of the procedural textures
    meta: dict = field(default_factory=dict)  # descriptive values for scene.yaml

    @property
    def boxes(self) -> tuple[Box, ...]:
        """All boxes; index 0 is the room (surface ids are `6 * box_index + face`)."""
        return (self.room, *self.solids)

    @property
    def object_box(self) -> Box:
        if self.object_index is None:
            raise SimulationError("this scene has no object")
        return self.solids[self.object_index]

    def object_corners_world(self) -> np.ndarray:
        """(8, 3) corners of the object (the cube) in world, m."""
        return self.object_box.corners()

    def object_triangles(self) -> np.ndarray:
        """(12, 3, 3) outward-facing (counter-clockwise) triangles of the object's surface, world, m."""
        c = self.object_box.corners()
        quads = [(0, 2, 6, 4), (1, 5, 7, 3), (0, 4, 5, 1), (2, 3, 7, 6), (0, 1, 3, 2), (4, 6, 7, 5)]
        tris = []
        for a, b, cc, d in quads:
            tris += [(a, b, cc), (a, cc, d)]
        return c[np.array(tris)]

    @cached_property
    def _surfaces(self) -> list[tuple[int, int, float]]:
        out = []
        for bi, box in enumerate(self.boxes):
            for f in range(6):
                if f not in box.hidden_faces:
                    out.append((bi, f, box.face_area(f)))
        return out

    def sample_surface_points(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """(n, 3) world points uniformly (by area) on the textured surfaces a camera can see, m.

        Points hidden inside another box (e.g. the table top under the cube) are rejected and redrawn.
        """
        surf = self._surfaces
        area = np.array([s[2] for s in surf])
        out = np.zeros((0, 3))
        while out.shape[0] < n:
            m = max(2 * (n - out.shape[0]), 16)
            pick = rng.choice(len(surf), size=m, p=area / area.sum())
            uv = rng.uniform(0.0, 1.0, (m, 2))
            pts = np.zeros((m, 3))
            normal = np.zeros((m, 3))  # towards the viewer: outward for solids, inward for the room
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
            out = np.vstack([out, pts[~hidden]])
        return out[:n]
