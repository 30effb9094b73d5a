"""Mesh quality as the study's Table 2 tabulated it: planar holes, inverted, overlapping and intersecting triangles,
bad edges; plus vertex and face counts and watertightness.

Coincident vertices are merged first (an STL has no connectivity of its own). Definitions:
- planar holes: boundary loops (connected chains of edges used by one face);
- inverted triangles: faces whose winding disagrees with their neighbours' (across edges shared by two faces); in a
  closed component the orientation with positive volume is the right one, in an open one the majority's;
- overlapping triangles: faces that share a plane with another face and overlap it with positive area (duplicates,
  faces folded back onto a neighbour, coplanar faces lying on top of each other);
- bad edges: boundary edges (one face) plus non-manifold edges (three or more faces);
- intersecting triangles: faces that cross another face that shares no vertex with them: each edge is cast as a ray
  segment with Embree against the mesh, and both faces of an edge that pierces a face count, and that face.
Counts of triangles are numbers of faces involved (each face once).
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass

import numpy as np
import trimesh
from scipy import sparse
from scipy.sparse.csgraph import breadth_first_order, connected_components
from scipy.spatial import cKDTree

log = logging.getLogger(__name__)

_MAX_RECASTS = 16  # rays re-cast past faces that share a vertex with the edge


@dataclass(frozen=True)
class MeshQuality:
    """Counts of mesh defects (see the module docstring)."""

    vertices: int  # after merging coincident vertices
    faces: int
    watertight: bool  # every edge used by exactly two faces
    planar_holes: int  # boundary loops
    inverted_triangles: int
    overlapping_triangles: int
    bad_edges: int  # boundary_edges + non_manifold_edges
    boundary_edges: int
    non_manifold_edges: int
    intersecting_triangles: int

    def as_dict(self) -> dict[str, int | bool]:
        return asdict(self)


def mesh_quality(vertices: np.ndarray, faces: np.ndarray) -> MeshQuality:
    """Quality counts of a triangle mesh: vertices (V, 3) in any unit and frame, faces (F, 3) vertex indices."""
    mesh = trimesh.Trimesh(np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64), process=False)
    mesh.merge_vertices()
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces, dtype=np.int64)
    directed = f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)  # directed edge i belongs to face i // 3
    key = np.sort(directed, axis=1) @ np.array([len(v), 1], dtype=np.int64)  # one integer per undirected edge
    _, first, edge_of, uses = np.unique(key, return_index=True, return_inverse=True, return_counts=True)
    boundary = np.flatnonzero(uses == 1)
    non_manifold = int(np.sum(uses > 2))
    shared = np.flatnonzero(uses[edge_of] == 2)
    pair = shared[np.argsort(edge_of[shared], kind="stable")].reshape(-1, 2)  # both directed edges of a 2-face edge
    fa, fb = pair[:, 0] // 3, pair[:, 1] // 3
    same_direction = directed[pair[:, 0], 0] == directed[pair[:, 1], 0]  # the two windings disagree
    return MeshQuality(
        vertices=len(v),
        faces=len(f),
        watertight=bool(len(boundary) == 0 and non_manifold == 0),
        planar_holes=_loops(directed[np.isin(edge_of, boundary)], len(v)),
        inverted_triangles=_inverted(v, f, fa, fb, same_direction, edge_of, uses),
        overlapping_triangles=_overlapping(v, f, fa, fb, same_direction),
        bad_edges=int(len(boundary) + non_manifold),
        boundary_edges=int(len(boundary)),
        non_manifold_edges=non_manifold,
        intersecting_triangles=len(_intersecting(v, f, directed[first], edge_of)),
    )


def _loops(edges: np.ndarray, num_vertices: int) -> int:
    """Number of connected chains of boundary edges (E, 2)."""
    if len(edges) == 0:
        return 0
    graph = sparse.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(num_vertices,) * 2)
    _, labels = connected_components(graph, directed=False)
    return len(np.unique(labels[edges[:, 0]]))


def _inverted(
    v: np.ndarray,
    f: np.ndarray,
    fa: np.ndarray,
    fb: np.ndarray,
    same_direction: np.ndarray,
    edge_of: np.ndarray,
    uses: np.ndarray,
) -> int:
    """Faces whose winding disagrees with the consistent orientation of their component (edges shared by two)."""
    flip = same_direction.astype(np.int8)
    n = len(f)
    count, labels = connected_components(sparse.coo_matrix((np.ones(len(fa)), (fa, fb)), shape=(n, n)), directed=False)
    # One BFS from a virtual root joined to one face of each component; parity = flips along the tree path.
    roots = np.unique(labels, return_index=True)[1]
    rows = np.concatenate([fa, fb, np.full(count, n)])
    cols = np.concatenate([fb, fa, roots])
    data = np.concatenate([flip, flip, np.zeros(count, np.int8)]) + 1  # +1 keeps zeros stored
    graph = sparse.csr_matrix((data, (rows, cols)), shape=(n + 1, n + 1))
    visit, pred = breadth_first_order(graph, n, directed=True, return_predecessors=True)
    visit = visit[1:]
    step = np.asarray(graph[pred[visit], visit]).ravel() - 1
    parity = np.zeros(n + 1, np.int8)
    parity_list, pred_list = parity.tolist(), pred.tolist()
    for node, s in zip(visit.tolist(), step.tolist(), strict=True):
        parity_list[node] = parity_list[pred_list[node]] ^ s
    parity = np.array(parity_list[:n], dtype=np.int8)
    # Signed volume of each component oriented as parity 0 (parity-1 faces flipped): positive means parity 1 is wrong.
    tri = v[f]
    volume = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])) * np.where(parity == 1, -1.0, 1.0)
    comp_volume = np.bincount(labels, volume, minlength=count)
    open_face = np.zeros(n, bool)
    open_face[np.flatnonzero(uses[edge_of] != 2) // 3] = True  # directed edge i belongs to face i // 3
    closed = np.bincount(labels, open_face, minlength=count) == 0
    ones = np.bincount(labels, parity, minlength=count)
    sizes = np.bincount(labels, minlength=count)
    wrong_one = np.where(closed, comp_volume > 0, ones <= sizes - ones)  # is parity 1 the inverted class?
    return int(np.sum(np.where(wrong_one, ones, sizes - ones)))


def _overlapping(v: np.ndarray, f: np.ndarray, fa: np.ndarray, fb: np.ndarray, same_direction: np.ndarray) -> int:
    """Faces overlapping a coplanar face with positive area.

    fa, fb (E,) are the faces on either side of each edge shared by exactly two faces, `same_direction` (E,) whether
    both traverse it the same way. Neighbours in one plane overlap when one is folded back onto the other. Apart from
    that, a patch of edge-connected coplanar faces does not overlap itself (it would have to wind round twice), so
    only faces of different patches in one plane are tested, by the separating-axis test in that plane.
    """
    tri = v[f]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area2 = np.linalg.norm(cross, axis=1)
    scale = max(float(np.ptp(v, axis=0).max()), 1e-12)
    normal = np.divide(cross, area2[:, None], out=np.zeros_like(cross), where=area2[:, None] > 1e-12 * scale**2)
    sign = np.where(normal[np.arange(len(f)), np.argmax(np.abs(normal), axis=1)] < 0, -1.0, 1.0)
    plane_n = normal * sign[:, None]  # one sign per plane
    offset = np.einsum("ij,ij->i", plane_n, tri[:, 0]) / scale
    key = np.round(np.hstack([plane_n, offset[:, None]]) * 1e3).astype(np.int64)
    _, group = np.unique(key, axis=0, return_inverse=True)
    group = np.where(area2 > 1e-12 * scale**2, group.ravel(), -1 - np.arange(len(f)))  # degenerate: alone
    in_plane = group[fa] == group[fb]
    folded = in_plane & ((np.einsum("ij,ij->i", normal[fa], normal[fb]) < 0) != same_direction)
    involved = [fa[folded], fb[folded]]
    flat_pairs = in_plane & ~folded
    graph = sparse.coo_matrix((np.ones(flat_pairs.sum()), (fa[flat_pairs], fb[flat_pairs])), shape=(len(f),) * 2)
    _, patch = connected_components(graph, directed=False)
    # Groups holding more than one patch: faces of different patches may overlap.
    group_patches = np.unique(np.stack([group, patch], axis=1), axis=0)
    multi = np.unique(group_patches[:, 0], return_counts=True)
    tested = np.flatnonzero(np.isin(group, multi[0][multi[1] > 1]))
    if len(tested) > 1:
        involved.append(_coplanar_overlaps(tri[tested], plane_n[tested], group[tested], patch[tested], scale))
        involved[-1] = tested[involved[-1]]
    return len(np.unique(np.concatenate(involved)))


def _coplanar_overlaps(
    tri: np.ndarray, n: np.ndarray, group: np.ndarray, patch: np.ndarray, scale: float
) -> np.ndarray:
    """Indices of triangles (T, 3, 3) overlapping a triangle of the same plane `group` but another `patch`."""
    _, group = np.unique(group, return_inverse=True)
    u = np.cross(n, np.eye(3)[np.argmin(np.abs(n), axis=1)])
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    ref_u, ref_w = np.zeros((group.max() + 1, 3)), np.zeros((group.max() + 1, 3))
    ref_u[group], ref_w[group] = u, np.cross(n, u)  # one basis per group (any member's)
    flat = np.stack([np.einsum("fkj,fj->fk", tri, ref_u[group]), np.einsum("fkj,fj->fk", tri, ref_w[group])], -1)
    centre = flat.mean(axis=1)
    radius = np.linalg.norm(flat - centre[:, None], axis=2).max(axis=1)
    order = np.argsort(group, kind="stable")
    starts = np.flatnonzero(np.r_[True, group[order][1:] != group[order][:-1]])
    pairs = [np.zeros((0, 2), np.int64)]
    for lo, hi in zip(starts, np.r_[starts[1:], len(order)], strict=True):
        members = order[lo:hi]
        if len(members) <= 64:
            i, j = np.triu_indices(len(members), k=1)
            local = np.stack([i, j], axis=1)
        else:
            local = cKDTree(centre[members]).query_pairs(2 * radius[members].max(), output_type="ndarray")
        pairs.append(members[local.reshape(-1, 2)])
    pairs = np.concatenate(pairs)
    pairs = pairs[patch[pairs[:, 0]] != patch[pairs[:, 1]]]
    pairs = pairs[np.linalg.norm(centre[pairs[:, 0]] - centre[pairs[:, 1]], axis=1) < radius[pairs].sum(axis=1)]
    hits = [np.zeros(0, np.int64)]
    for chunk in range(0, len(pairs), 500_000):
        part = pairs[chunk : chunk + 500_000]
        hits.append(part[_overlap_2d(flat[part[:, 0]], flat[part[:, 1]], 1e-7 * scale)].ravel())
    return np.concatenate(hits)


def _overlap_2d(a: np.ndarray, b: np.ndarray, tol: float) -> np.ndarray:
    """(P,) bool: 2D triangles a[i], b[i] (P, 3, 2) overlap by more than `tol` along every separating axis."""
    edges = np.concatenate([np.roll(a, -1, axis=1) - a, np.roll(b, -1, axis=1) - b], axis=1)  # (P, 6, 2)
    axes = np.stack([-edges[..., 1], edges[..., 0]], axis=-1)
    axes /= np.maximum(np.linalg.norm(axes, axis=2, keepdims=True), 1e-300)
    pa = a[:, None, :, 0] * axes[:, :, None, 0] + a[:, None, :, 1] * axes[:, :, None, 1]  # (P, 6 axes, 3 corners)
    pb = b[:, None, :, 0] * axes[:, :, None, 0] + b[:, None, :, 1] * axes[:, :, None, 1]
    depth = np.minimum(pa.max(axis=2), pb.max(axis=2)) - np.maximum(pa.min(axis=2), pb.min(axis=2))
    return depth.min(axis=1) > tol


def intersecting_faces(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Indices of the faces of a connected mesh (shared vertices, as marching cubes makes it) that cross a face
    they share no vertex with (see the module docstring)."""
    f = np.asarray(faces, dtype=np.int64)
    v = np.asarray(vertices, dtype=np.float64)
    directed = f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    key = np.sort(directed, axis=1) @ np.array([len(v), 1], dtype=np.int64)
    _, first, edge_of = np.unique(key, return_index=True, return_inverse=True)
    return _intersecting(v, f, directed[first], edge_of)


def _intersecting(v: np.ndarray, f: np.ndarray, edges: np.ndarray, edge_of: np.ndarray) -> np.ndarray:
    """Faces crossing a face they share no vertex with: every edge (E, 2) cast as a ray segment with Embree.

    edge_of (3F,) maps each face's directed edges to rows of `edges`. Returns the faces' indices.
    """
    from embreex import rtcore_scene as rtcs
    from embreex.mesh_construction import TriangleMesh

    if len(f) < 2:
        return np.zeros(0, np.int64)
    scene = rtcs.EmbreeScene()
    TriangleMesh(scene, v[f].astype(np.float32))
    a, b = v[edges[:, 0]], v[edges[:, 1]]
    length = np.linalg.norm(b - a, axis=1)
    ok = np.flatnonzero(length > 0)
    edges, a, b, length = edges[ok], a[ok], b[ok], length[ok]
    direction = (b - a) / length[:, None]
    start = 1e-4 * length  # skip the ends: faces around the end vertices touch the edge there
    active = np.arange(len(edges))
    hits: list[tuple[np.ndarray, np.ndarray]] = []
    for _ in range(_MAX_RECASTS):
        if len(active) == 0:
            break
        origin = (a[active] + direction[active] * start[active, None]).astype(np.float32)
        tfar = (length[active] * (1 - 1e-4) - start[active]).astype(np.float32)
        found = scene.run(origin, direction[active].astype(np.float32), dists=tfar, output=1)
        face = found["primID"]
        hit = face >= 0
        touching = np.zeros(len(active), bool)
        corners, ends = f[face[hit]], edges[active[hit]]
        touching[hit] = (corners[:, :, None] == ends[:, None, :]).any(axis=(1, 2))
        real = hit & ~touching
        hits.append((active[real], face[real]))
        again = hit & touching  # the first face hit shares a vertex: look past it
        start[active[again]] += found["tfar"][again] + 1e-5 * length[active[again]]
        active = active[again]
    edge_hit = np.concatenate([h[0] for h in hits])
    face_hit = np.concatenate([h[1] for h in hits]).astype(np.int64)
    if len(edge_hit) == 0:
        return np.zeros(0, np.int64)
    # Both faces bordering a piercing edge cross the pierced face (the edge is part of each), and so does it.
    bordering = np.flatnonzero(np.isin(edge_of, ok[edge_hit])) // 3
    return np.union1d(bordering, face_hit)
