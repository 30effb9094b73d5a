"""The built-in parts as manifold3d solids (constructive solid geometry), millimetres, in the part's own frame.

Frame: x, y centred on the footprint, z = 0 on the base (the face the part stands on), z up. Every builder
returns a `manifold3d.Manifold`, which is watertight with outward normals by construction; `vio.sim.parts`
turns it into a `Part`. The nominal dimensions below are what a machinist would check on the real part.

Curved surfaces are polygons: circles get `CIRCULAR_SEGMENTS` sides (sag r * (1 - cos(pi / n)) = 0.0032 mm at
r = 6 mm, 0.0053 mm at r = 10 mm), and the freeform top is a grid of about 1.5 mm whose linear interpolation is
within 0.02 mm of the smooth height function (measured by the tests).
"""

from __future__ import annotations

import manifold3d as m3
import numpy as np

CIRCULAR_SEGMENTS = 96
CUBE_MM = 76.2  # the study's cube, 3 in
_OVER = 1.0  # mm that a cutter reaches beyond the surface it cuts, so no two faces are coplanar

CUBE_FEATURES_MM = {
    "x": CUBE_MM,
    "y": CUBE_MM,
    "z": CUBE_MM,
    # through hole with a 90 deg countersink in the top face, axis at (x, y)
    "hole_through_x": -20.0,
    "hole_through_y": 20.0,
    "hole_through_diameter": 8.0,
    "hole_through_countersink_diameter": 16.0,
    # blind hole (flat bottom) with a 90 deg countersink in the top face
    "hole_blind_x": 20.0,
    "hole_blind_y": 20.0,
    "hole_blind_diameter": 10.0,
    "hole_blind_depth": 30.0,  # from the top face
    "hole_blind_countersink_diameter": 20.0,
    "countersink_angle_deg": 90.0,  # included angle of both countersinks
    # semicircular groove down the +x face, full height, axis on the face at y = groove_y
    "groove_radius": 6.0,
    "groove_y": 0.0,
    # rectangular pocket in the top face, centred at (pocket_x, pocket_y)
    "pocket_x": 0.0,
    "pocket_y": -18.0,
    "pocket_length_x": 30.0,
    "pocket_width_y": 14.0,
    "pocket_depth": 10.0,
    # undercut slot in the -y face under a lip (self-occluding overhang), centred on x
    "slot_length_x": 56.0,
    "slot_depth_y": 12.0,
    "slot_height_z": 15.0,
    "slot_bottom_z": 20.0,
}

FREEFORM_MM = {
    "x": 90.0,
    "y": 70.0,
    "top_mean_z": 32.0,  # height of the smooth top at x = y = 0
    "wave_amplitude": 6.0,  # top = mean + A sin(pi x / 45) cos(pi y / 70) + saddle (x/45)^2, (y/35)^2 terms
    "saddle_amplitude": 4.0,
    "step_x": 25.0,  # the step occupies x >= step_x
    "step_z": 16.0,  # height of the step's floor
    "fillet_radius": 6.0,  # concave fillet between the step's floor and its wall
}
_FREEFORM_GRID = (61, 47)  # top grid vertices along x, y: 1.5 mm x 1.52 mm


def freeform_top_z(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Height (mm) of the freeform part's smooth top at (x, y) mm, before the step is cut."""
    d = FREEFORM_MM
    hx, hy = d["x"] / 2, d["y"] / 2
    wave = d["wave_amplitude"] * np.sin(np.pi * x / hx) * np.cos(np.pi * y / d["y"])
    saddle = d["saddle_amplitude"] * ((y / hy) ** 2 - (x / hx) ** 2)
    return d["top_mean_z"] + wave + saddle


def cube_solid(side_mm: float = CUBE_MM) -> m3.Manifold:
    """The plain cube: 8 vertices, 12 triangles."""
    return m3.Manifold.cube((side_mm, side_mm, side_mm), center=True).translate((0.0, 0.0, side_mm / 2))


def _countersunk_hole(dims: dict[str, float], hole: str, top_z: float) -> m3.Manifold:
    """Cutter for the hole named `hole` in `dims` (keys `<hole>_x`, `_y`, `_diameter`, `_countersink_diameter`,
    `_depth` if blind), drilled down from the top face at `top_z`, with a 90 deg countersink."""
    r, r_cs = dims[f"{hole}_diameter"] / 2, dims[f"{hole}_countersink_diameter"] / 2
    x, y = dims[f"{hole}_x"], dims[f"{hole}_y"]
    depth = dims.get(f"{hole}_depth", top_z + _OVER)  # through: down past the base
    length = depth + _OVER
    bore = m3.Manifold.cylinder(length, r, r, CIRCULAR_SEGMENTS).translate((x, y, top_z + _OVER - length))
    # a full cone with its apex on the axis, 45 deg half-angle: radius r_cs at the top face; inside the bore below
    cone_h = r_cs + _OVER
    cone = m3.Manifold.cylinder(cone_h, 0.0, cone_h, CIRCULAR_SEGMENTS).translate((x, y, top_z - r_cs))
    return bore + cone


def cube_features_solid() -> m3.Manifold:
    """The cube with two countersunk holes, a groove, a pocket and an undercut slot (`CUBE_FEATURES_MM`)."""
    d = CUBE_FEATURES_MM
    s = d["z"]
    holes = _countersunk_hole(d, "hole_through", s) + _countersunk_hole(d, "hole_blind", s)
    r = d["groove_radius"]
    groove = m3.Manifold.cylinder(s + 2 * _OVER, r, r, CIRCULAR_SEGMENTS).translate((d["x"] / 2, d["groove_y"], -_OVER))
    pocket = m3.Manifold.cube((d["pocket_length_x"], d["pocket_width_y"], d["pocket_depth"] + _OVER), center=True)
    pocket = pocket.translate((d["pocket_x"], d["pocket_y"], s - (d["pocket_depth"] - _OVER) / 2))
    slot = m3.Manifold.cube((d["slot_length_x"], d["slot_depth_y"] + _OVER, d["slot_height_z"]))
    slot = slot.translate((-d["slot_length_x"] / 2, -d["y"] / 2 - _OVER, d["slot_bottom_z"]))
    return m3.Manifold.batch_boolean([cube_solid(s), holes, groove, pocket, slot], m3.OpType.Subtract)


def _heightfield_solid(nx: int, ny: int) -> m3.Manifold:
    """Closed solid under `freeform_top_z` over the footprint: top grid, vertical walls, flat base (a fan)."""
    hx, hy = FREEFORM_MM["x"] / 2, FREEFORM_MM["y"] / 2
    gx, gy = np.meshgrid(np.linspace(-hx, hx, nx), np.linspace(-hy, hy, ny), indexing="ij")
    top = np.stack([gx, gy, freeform_top_z(gx, gy)], axis=-1).reshape(-1, 3)
    idx = np.arange(nx * ny).reshape(nx, ny)
    a, b, c, e = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    top_faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, e], 1)])  # counter-clockwise from above
    ring = np.concatenate([idx[:, 0], idx[-1, 1:], idx[-2::-1, -1], idx[0, -2:0:-1]])  # counter-clockwise
    base = top[ring] * np.array([1.0, 1.0, 0.0])
    below = nx * ny + np.arange(len(ring))
    below_next, ring_next = np.roll(below, -1), np.roll(ring, -1)
    walls = np.concatenate([np.stack([ring, below, below_next], 1), np.stack([ring, below_next, ring_next], 1)])
    centre = nx * ny + len(ring)
    fan = np.stack([np.full(len(ring), centre), below_next, below], 1)
    verts = np.concatenate([top, base, np.zeros((1, 3))])
    faces = np.concatenate([top_faces, walls, fan])
    return m3.Manifold(m3.Mesh64(np.ascontiguousarray(verts), np.ascontiguousarray(faces, dtype=np.uint64)))


def freeform_solid() -> m3.Manifold:
    """Smooth wave-and-saddle top over a 90 x 70 mm block, with a step cut at one end and a concave fillet."""
    d = FREEFORM_MM
    x0, z0, r = d["step_x"], d["step_z"], d["fillet_radius"]
    far, wide = 100.0, d["y"] + 2 * _OVER
    # the removed region: everything above the step floor beyond x0, its lower inner edge rounded with radius r
    cut = (
        m3.Manifold.cube((far, wide, far)).translate((x0 + r, -wide / 2, z0))
        + m3.Manifold.cube((far, wide, far)).translate((x0, -wide / 2, z0 + r))
        + m3.Manifold.cylinder(wide, r, r, CIRCULAR_SEGMENTS)
        .rotate((90.0, 0.0, 0.0))
        .translate((x0 + r, wide / 2, z0 + r))
    )
    return _heightfield_solid(*_FREEFORM_GRID) - cut
