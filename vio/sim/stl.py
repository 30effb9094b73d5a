"""Binary STL output (triangles in metres), written atomically and byte-reproducibly."""

from __future__ import annotations

import os
import struct

import numpy as np

from vio.atomic import write_bytes


def stl_bytes(triangles: np.ndarray, header: str = "vio simulated object, metres") -> bytes:
    """Binary STL of (T, 3, 3) counter-clockwise (outward) triangles; normals computed from the winding."""
    tris = np.asarray(triangles, dtype=np.float64)
    n = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    out = bytearray(header.encode("ascii")[:80].ljust(80, b" "))
    out += struct.pack("<I", tris.shape[0])
    for normal, tri in zip(n, tris, strict=True):
        out += struct.pack("<12fH", *normal, *tri.reshape(-1), 0)
    return bytes(out)


def write_stl(path: str | os.PathLike[str], triangles: np.ndarray) -> None:
    write_bytes(path, stl_bytes(triangles))


def read_stl(path: str | os.PathLike[str]) -> np.ndarray:
    """(T, 3, 3) triangles of a binary STL file, metres (as float64)."""
    with open(path, "rb") as f:
        data = f.read()
    (count,) = struct.unpack_from("<I", data, 80)
    tris = np.zeros((count, 3, 3))
    for i in range(count):
        vals = struct.unpack_from("<12f", data, 84 + 50 * i)
        tris[i] = np.asarray(vals[3:], dtype=np.float64).reshape(3, 3)
    return tris
