"""Mesh and point-cloud files, written atomically (temporary file, then rename): binary STL and PLY.

STL carries no unit: the caller states it with `scale` (part.stl is in millimetres: scale 1000 for a mesh in
metres). PLY is binary little-endian (or ASCII) with optional per-vertex RGB colours and triangle faces; a point
cloud is a PLY without faces. The same input gives the same bytes.
"""

from __future__ import annotations

import os

import numpy as np

from vio.atomic import write_bytes

_STL_RECORD = np.dtype([("normal", "<f4", (3,)), ("vertices", "<f4", (3, 3)), ("attribute", "<u2")])


def stl_bytes(vertices: np.ndarray, faces: np.ndarray, header: str = "", scale: float = 1.0) -> bytes:
    """Binary STL (little-endian float32) of an indexed mesh, coordinates multiplied by `scale`; each facet normal
    from its counter-clockwise winding. `header` (ASCII, at most 80 characters) must not start with "solid"."""
    tri = np.asarray(vertices, dtype=np.float64)[np.asarray(faces, dtype=np.int64)] * float(scale)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(normal, axis=1, keepdims=True)
    normal = np.divide(normal, length, out=np.zeros_like(normal), where=length > 0)
    records = np.zeros(len(tri), dtype=_STL_RECORD)
    records["normal"], records["vertices"] = normal, tri
    head = header.encode("ascii", errors="replace")[:80].ljust(80, b" ")
    return head + np.uint32(len(tri)).tobytes() + records.tobytes()


def write_stl(
    path: str | os.PathLike[str], vertices: np.ndarray, faces: np.ndarray, header: str = "", scale: float = 1.0
) -> None:
    """Write a binary STL atomically: vertices (V, 3) times `scale` (e.g. 1000: metres to millimetres), faces
    (F, 3) counter-clockwise seen from outside."""
    write_bytes(path, stl_bytes(vertices, faces, header, scale))


def ply_bytes(
    vertices: np.ndarray,
    faces: np.ndarray | None = None,
    colours: np.ndarray | None = None,
    binary: bool = True,
    comment: str = "",
    scalars: dict[str, np.ndarray] | None = None,
) -> bytes:
    """PLY 1.0 of vertices (V, 3) (written as float64 `x y z`), optional colours (V, 3) uint8 RGB
    (`red green blue`), optional per-vertex float scalars (name -> (V,), e.g. `deviation_mm`, which CloudCompare
    reads as a scalar field; float32) and triangles (F, 3) (`vertex_indices`, int32); binary little-endian or ASCII."""
    v = np.ascontiguousarray(vertices, dtype=np.float64).reshape(-1, 3)
    f = None if faces is None else np.ascontiguousarray(faces, dtype=np.int64).reshape(-1, 3)
    c = None if colours is None else np.ascontiguousarray(colours, dtype=np.uint8).reshape(-1, 3)
    if c is not None and len(c) != len(v):
        raise ValueError(f"{len(c)} colours for {len(v)} vertices")
    if f is not None and len(f) and (f.min() < 0 or f.max() >= len(v)):
        raise ValueError("face indices out of range")
    lines = ["ply", f"format {'binary_little_endian' if binary else 'ascii'} 1.0"]
    lines += [f"comment {line}" for line in comment.splitlines() if line]
    lines += [f"element vertex {len(v)}", "property double x", "property double y", "property double z"]
    if c is not None:
        lines += ["property uchar red", "property uchar green", "property uchar blue"]
    s = {k: np.asarray(a, np.float32).reshape(-1) for k, a in (scalars or {}).items()}
    if any(len(a) != len(v) for a in s.values()):
        raise ValueError(f"scalars must have one value per vertex ({len(v)})")
    lines += [f"property float {k}" for k in s]
    if f is not None:
        lines += [f"element face {len(f)}", "property list uchar int vertex_indices"]
    head = ("\n".join([*lines, "end_header"]) + "\n").encode("ascii")
    if binary:
        fields = [("xyz", "<f8", (3,))] + ([("rgb", "u1", (3,))] if c is not None else [])
        fields += [(f"s_{k}", "<f4") for k in s]
        rec = np.zeros(len(v), dtype=fields)
        rec["xyz"] = v
        if c is not None:
            rec["rgb"] = c
        for k, a in s.items():
            rec[f"s_{k}"] = a
        body = rec.tobytes()
        if f is not None:
            frec = np.zeros(len(f), dtype=[("n", "u1"), ("idx", "<i4", (3,))])
            frec["n"], frec["idx"] = 3, f
            body += frec.tobytes()
        return head + body
    rows = [" ".join(f"{x:.9g}" for x in p) for p in v]
    if c is not None:
        rows = [f"{r} {a} {b} {g}" for r, (a, b, g) in zip(rows, c.tolist(), strict=True)]
    for a in s.values():
        rows = [f"{r} {x:.9g}" for r, x in zip(rows, a.tolist(), strict=True)]
    if f is not None:
        rows += [f"3 {a} {b} {g}" for a, b, g in f.tolist()]
    return head + ("\n".join(rows) + "\n").encode("ascii")


def write_mesh_ply(
    path: str | os.PathLike[str],
    vertices: np.ndarray,
    faces: np.ndarray,
    colours: np.ndarray | None = None,
    binary: bool = True,
    comment: str = "",
) -> None:
    """Write a triangle mesh (vertices (V, 3), faces (F, 3), optional colours (V, 3) uint8 RGB) as PLY, atomically."""
    write_bytes(path, ply_bytes(vertices, faces, colours, binary, comment))


def write_points_ply(
    path: str | os.PathLike[str],
    points: np.ndarray,
    colours: np.ndarray | None = None,
    binary: bool = True,
    comment: str = "",
) -> None:
    """Write a point cloud (points (N, 3), optional colours (N, 3) uint8 RGB) as PLY without faces, atomically."""
    write_bytes(path, ply_bytes(points, None, colours, binary, comment))
