"""The watertight mesh of the fused field: marching cubes, the largest connected piece, outward normals, checks.

Marching cubes (scikit-image, Lewiner) runs on the field padded with one layer of "outside", so the surface is
closed wherever the part touches the grid's border; the support plane already closes the base (vio.model.fuse).
Vertices are mapped from grid indices to the support frame, then to world metres.
"""

from __future__ import annotations

import logging

import numpy as np

from vio.errors import ModelError
from vio.model.fuse import FusedVolume
from vio.model.records import Mesh

log = logging.getLogger(__name__)


def _trimesh(mesh: Mesh):
    import trimesh

    return trimesh.Trimesh(mesh.vertices, mesh.faces, process=False, validate=False)


def _largest_piece(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The connected piece (through shared edges) with the most faces, vertices re-indexed."""
    import trimesh

    tm = trimesh.Trimesh(vertices, faces, process=False, validate=False)
    pieces = trimesh.graph.connected_components(tm.face_adjacency, nodes=np.arange(len(faces)), min_len=1)
    keep = max(pieces, key=len)
    if len(pieces) > 1:
        log.info("mesh: kept the largest of %d pieces (%d of %d faces)", len(pieces), len(keep), len(faces))
    faces = faces[np.sort(keep)]
    used, inverse = np.unique(faces, return_inverse=True)
    return vertices[used], inverse.reshape(-1, 3)


def _volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Signed enclosed volume (divergence theorem), positive for outward normals; units of vertices cubed."""
    tri = vertices[faces]
    return float(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0)


def _smooth(vertices: np.ndarray, faces: np.ndarray, iterations: int, max_rounds: int = 4) -> np.ndarray:
    """Taubin-smoothed vertices; where smoothing made faces cross each other (thin folds of the field), those faces
    and their neighbours keep their marching-cubes positions (which do not intersect), round by round."""
    import trimesh

    from vio.model.quality import intersecting_faces

    tm = trimesh.Trimesh(vertices, faces, process=False, validate=False)
    trimesh.smoothing.filter_taubin(tm, lamb=0.5, nu=0.53, iterations=iterations)
    smoothed = np.array(tm.vertices)
    for _ in range(max_rounds):
        bad = intersecting_faces(smoothed, faces)
        if len(bad) == 0:
            break
        ring = np.unique(faces[bad])
        ring = np.unique(faces[np.isin(faces, ring).any(axis=1)])  # and their neighbours
        smoothed[ring] = vertices[ring]
        log.info("mesh: %d faces crossed after smoothing; %d vertices left unsmoothed", len(bad), len(ring))
    return smoothed


def mesh_from_volume(volume: FusedVolume, frame: str = "world", smooth_iterations: int = 10) -> Mesh:
    """The part's surface (zero level of the field) as a closed mesh in metres, in `frame`: "world" (the run's
    world) or "support" (the part on its base: z up, origin on the plane). Only the largest connected piece is
    kept; faces are counter-clockwise seen from outside. `smooth_iterations` > 0 applies Taubin smoothing
    (volume-preserving, lambda 0.5, mu -0.53). Raises ModelError when the field has no surface."""
    from skimage import measure

    if frame not in ("world", "support"):
        raise ValueError(f"frame must be 'world' or 'support', got {frame!r}")
    field = np.pad(volume.tsdf, 1, constant_values=1.0)
    field[field == 0.0] = np.float32(1e-6)  # no vertex exactly on a grid node: no degenerate triangles
    if not (field.min() < 0.0 < field.max()):
        raise ModelError("no part surface in the fused volume (nothing inside the region of interest)")
    verts, faces, _, _ = measure.marching_cubes(field, level=0.0, allow_degenerate=False)
    vertices, faces = _largest_piece(verts.astype(np.float64), faces.astype(np.int64))
    vertices = volume.support_points(vertices - 1.0)  # undo the padding
    if _volume(vertices, faces) < 0:
        faces = faces[:, ::-1]
    if smooth_iterations > 0:
        vertices = _smooth(vertices, faces, smooth_iterations)
    if frame == "world":
        T = volume.roi.world_T_support
        vertices = vertices @ T[:3, :3].T + T[:3, 3]
    return Mesh(np.ascontiguousarray(vertices), np.ascontiguousarray(faces, dtype=np.int64), frame=frame)


BASE_SNAP_M = 1e-9  # support-frame vertices this close to the plane are put on it exactly


def to_support(mesh: Mesh, world_T_support: np.ndarray) -> Mesh:
    """A world-frame mesh in the support frame (the part on its base, z up, origin on the plane), for part.stl.

    The bottom closed on the plane comes back from the world frame with heights of about 1e-17 m of either sign;
    those within BASE_SNAP_M are set to 0 exactly, so the base stays flat once part.stl rounds it to float32 mm
    (a base left at +-5e-17 had 6 of its faces reported crossing their neighbours after that rounding)."""
    if mesh.frame != "world":
        raise ValueError(f"expected a world-frame mesh, got frame {mesh.frame!r}")
    T = np.linalg.inv(world_T_support)
    vertices = mesh.vertices @ T[:3, :3].T + T[:3, 3]
    vertices[np.abs(vertices[:, 2]) < BASE_SNAP_M, 2] = 0.0
    return Mesh(vertices, mesh.faces, "support", mesh.colours)


def mesh_checks(mesh: Mesh) -> dict[str, object]:
    """Topology and size of a mesh: watertight, winding consistent, non-manifold edges (shared by more than two
    faces), boundary edges (one face), number of connected pieces, volume (m^3, positive for outward normals),
    area (m^2), number of vertices and faces."""
    import trimesh

    tm = _trimesh(mesh)
    edges = np.sort(tm.edges, axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    pieces = trimesh.graph.connected_components(tm.face_adjacency, nodes=np.arange(len(mesh.faces)), min_len=1)
    return {
        "watertight": bool(tm.is_watertight),
        "winding_consistent": bool(tm.is_winding_consistent),
        "non_manifold_edges": int((counts > 2).sum()),
        "boundary_edges": int((counts == 1).sum()),
        "pieces": len(pieces),
        "volume_m3": _volume(mesh.vertices, mesh.faces),
        "area_m2": float(tm.area),
        "vertices": len(mesh.vertices),
        "faces": len(mesh.faces),
    }
