"""The machined parts the simulator films: the study's three built-ins, or a user's STL, as watertight meshes.

A `Part` is in its own frame, in millimetres: x, y centred on the footprint, z = 0 on the base (the face it stands
on), z up; faces are counter-clockwise seen from outside (outward normals). The built-ins are constructed with
manifold3d (`vio.sim.part_shapes`); STL files are read and checked with trimesh. The simulator places the part on
the table top (z = 0 there).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vio.errors import PartError
from vio.writers import mesh as mesh_writer

PART_NAMES = ("cube", "cube_features", "freeform")
UNITS_TO_MM = {"mm": 1.0, "m": 1000.0}

_DESCRIPTIONS = {
    "cube": "76.2 mm cube",
    "cube_features": (
        "76.2 mm cube with two 90 deg countersunk holes (through 8 mm, blind 10 mm), a 6 mm radius groove, "
        "a 30 x 14 x 10 mm pocket and an undercut slot under a lip"
    ),
    "freeform": "90 x 70 mm block with a smooth wave-and-saddle top and a step with a 6 mm concave fillet",
}


@dataclass(frozen=True, eq=False)
class Part:
    """A solid part as a closed triangle mesh in its own frame (see the module docstring), millimetres."""

    name: str  # "cube", "cube_features", "freeform", or the STL file's stem
    vertices_mm: np.ndarray = field(repr=False)  # (V, 3) float64, part frame, mm
    faces: np.ndarray = field(repr=False)  # (F, 3) int64 vertex indices, counter-clockwise seen from outside
    description: str  # one line for scene.yaml
    dimensions_mm: dict[str, float]  # nominal dimensions a machinist would check (angles in deg, named *_deg)

    def volume_mm3(self) -> float:
        """Enclosed volume, mm^3 (divergence theorem; positive for outward normals)."""
        tri = self.vertices_mm[self.faces]
        return float(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0)

    def bounds_mm(self) -> np.ndarray:
        """(2, 3) axis-aligned bounds in the part frame, mm: row 0 the minimum, row 1 the maximum."""
        return np.stack([self.vertices_mm.min(axis=0), self.vertices_mm.max(axis=0)])


def build_part(name_or_path: str | os.PathLike[str], units: str = "mm") -> Part:
    """A built-in part (`PART_NAMES`), or the part in an STL file (ASCII or binary).

    `units` is the STL file's length unit, stated by the user (`--object-units`): "mm" or "m"; built-ins are in mm
    and ignore it. An STL part is scaled to mm and moved so that it stands on z = 0 centred on its footprint
    (the x, y centre of its bounding box); the file itself is never modified.
    """
    name = str(name_or_path)
    if name in PART_NAMES:
        return _built_in(name)
    if units not in UNITS_TO_MM:
        raise PartError(f"{name}: unknown object units {units!r}; use one of {', '.join(UNITS_TO_MM)}")
    vertices, faces = read_stl_mesh(name)
    vertices = vertices * UNITS_TO_MM[units]
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    vertices = vertices - np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
    size = hi - lo
    return _part(
        Path(name).stem,
        vertices,
        faces,
        f"user part from {Path(name).name}, {size[0]:.1f} x {size[1]:.1f} x {size[2]:.1f} mm",
        {"x": float(size[0]), "y": float(size[1]), "z": float(size[2])},
    )


def _built_in(name: str) -> Part:
    from vio.sim import part_shapes

    solid, dims = {
        "cube": (
            part_shapes.cube_solid,
            {"x": part_shapes.CUBE_MM, "y": part_shapes.CUBE_MM, "z": part_shapes.CUBE_MM},
        ),
        "cube_features": (part_shapes.cube_features_solid, part_shapes.CUBE_FEATURES_MM),
        "freeform": (part_shapes.freeform_solid, part_shapes.FREEFORM_MM),
    }[name]
    mesh = solid().to_mesh64()
    vertices = np.array(mesh.vert_properties, dtype=np.float64)[:, :3]
    return _part(name, vertices, np.array(mesh.tri_verts, dtype=np.int64), _DESCRIPTIONS[name], dict(dims))


def _part(name: str, vertices: np.ndarray, faces: np.ndarray, description: str, dims: dict[str, float]) -> Part:
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    vertices.setflags(write=False)
    faces.setflags(write=False)
    return Part(name, vertices, faces, description, dims)


def write_stl(path: str | os.PathLike[str], vertices: np.ndarray, faces: np.ndarray, header: str) -> None:
    """Write a binary STL atomically (`vio.writers.mesh.write_stl`, the project's one STL writer); the same mesh gives
    the same bytes."""
    mesh_writer.write_stl(path, vertices, faces, header)


def read_stl_mesh(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3) float64, faces (F, 3) int64) of a closed STL mesh (ASCII or binary), in the file's units.

    Coincident vertices are merged. A missing file, a file that is not an STL, an STL without faces, or a mesh
    that is not watertight or not consistently wound raises `PartError` (one line naming the file). A closed mesh
    wound inside out is turned outside in, so the faces returned are counter-clockwise seen from outside.
    """
    import trimesh

    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise PartError(f"{path}: STL file not found") from None
    except OSError as exc:
        raise PartError(f"{path}: cannot read the STL file ({exc.strerror or exc})") from None
    binary = len(data) >= 84 and len(data) == 84 + 50 * int(np.frombuffer(data, "<u4", 1, 80)[0])
    if not binary and not data.lstrip()[:5].lower() == b"solid":
        raise PartError(f"{path}: not an STL file (neither binary STL nor ASCII 'solid ...')")
    try:
        mesh = trimesh.load_mesh(trimesh.util.wrap_as_stream(data), file_type="stl")
    except Exception as exc:  # trimesh raises many kinds on malformed text
        raise PartError(f"{path}: not a readable STL file ({type(exc).__name__}: {exc})") from None
    if len(mesh.faces) == 0:
        raise PartError(f"{path}: the STL has no faces")
    if not np.isfinite(mesh.vertices).all():
        raise PartError(f"{path}: the STL has non-finite vertex coordinates")
    if not mesh.is_watertight:
        raise PartError(f"{path}: the mesh is not watertight (it has open edges or holes); close it first")
    if not mesh.is_winding_consistent:
        raise PartError(f"{path}: the mesh's faces are not consistently wound; repair its normals first")
    faces = np.array(mesh.faces, dtype=np.int64)
    if mesh.volume < 0:
        faces = faces[:, ::-1]
    return np.array(mesh.vertices, dtype=np.float64), np.ascontiguousarray(faces)
