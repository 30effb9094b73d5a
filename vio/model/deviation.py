"""Signed deviations of a registered model from its CAD (CloudCompare's cloud-to-mesh convention) and completeness.

Every point here is in the CAD's frame, millimetres (register first: `vio.model.register`). A deviation is the
distance to the closest point of the CAD surface, positive on the side its normal points to (outside the part: too
much material, or the surface too far out), negative inside. A mesh model is measured at points sampled uniformly
on its faces (area-weighted, so models with different triangle sizes compare fairly), or at its vertices on request
(what CloudCompare does when the compared entity is a mesh); a point cloud at its points.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from vio.model.closest import SurfaceIndex, build_index, closest_points

log = logging.getLogger(__name__)

COMPLETENESS_MM = 0.5  # a CAD point counts as seen when the model passes within this distance
OVERLAP_MM = 2.0  # a model point counts as on the CAD within this distance (the overlap check of `vio compare`)


@dataclass(frozen=True)
class DeviationStats:
    """Statistics of signed deviations, mm (positive outside the CAD)."""

    count: int  # points measured
    max_positive_mm: float  # upper end of the tolerance window (largest deviation outward)
    max_negative_mm: float  # lower end of the tolerance window (most negative deviation, inward)
    mean_mm: float
    std_mm: float  # standard deviation about the mean
    rms_mm: float  # root mean square (about zero)
    p01_mm: float  # 1st percentile
    p99_mm: float  # 99th percentile
    within_overlap: float  # share of points within OVERLAP_MM of the CAD

    def as_dict(self) -> dict[str, float | int]:
        return {k: (round(v, 5) if isinstance(v, float) else v) for k, v in asdict(self).items()}


def model_points(
    model: trimesh.Trimesh | trimesh.PointCloud, sampling: str, count: int, rng: np.random.Generator
) -> np.ndarray:
    """(N, 3) the points at which a model's deviations are measured, in the model's frame and units.

    sampling: "surface" (`count` points uniform on a mesh's faces) or "vertices"; a point cloud gives its points.
    """
    if isinstance(model, trimesh.PointCloud) or len(model.faces) == 0 or sampling == "vertices":
        return np.array(model.vertices, dtype=np.float64)  # a copy: the caller moves the model afterwards
    if sampling != "surface":
        raise ValueError(f"sampling must be 'surface' or 'vertices', not {sampling!r}")
    points, _ = trimesh.sample.sample_surface(model, count, seed=int(rng.integers(2**31)))
    return np.asarray(points, dtype=np.float64)


def signed_deviations(points_cad_mm: np.ndarray, cad_index: SurfaceIndex) -> np.ndarray:
    """(N,) signed distance of each point (N, 3; CAD frame, mm) to the CAD surface, mm, positive outside (C2M)."""
    signed, _, _ = closest_points(cad_index, points_cad_mm)
    return signed


def deviation_stats(signed_mm: np.ndarray) -> DeviationStats:
    """Tolerance window, mean, standard deviation, RMS and percentiles of signed deviations (N,), mm."""
    d = np.asarray(signed_mm, dtype=np.float64)
    if len(d) == 0:
        raise ValueError("no deviations to summarise")
    p01, p99 = np.percentile(d, [1.0, 99.0])
    return DeviationStats(
        count=len(d),
        max_positive_mm=float(d.max()),
        max_negative_mm=float(d.min()),
        mean_mm=float(d.mean()),
        std_mm=float(d.std()),
        rms_mm=float(np.sqrt(np.mean(d**2))),
        p01_mm=float(p01),
        p99_mm=float(p99),
        within_overlap=float(np.mean(np.abs(d) <= OVERLAP_MM)),
    )


def visible_faces(cad: trimesh.Trimesh, max_tilt_deg: float = 1.0) -> np.ndarray:
    """(F,) bool: every CAD face except the base, i.e. faces on the CAD's lowest plane (z, CAD frame) facing down.

    The base is what the part stands on during a capture, so no camera sees it.
    """
    vertices = np.asarray(cad.vertices, dtype=np.float64)
    z = vertices[:, 2]
    tol = 1e-4 * max(float(np.ptp(vertices, axis=0).max()), 1e-9)
    on_bottom = np.all(z[cad.faces] <= z.min() + tol, axis=1)
    facing_down = np.asarray(cad.face_normals)[:, 2] <= -np.cos(np.radians(max_tilt_deg))
    return ~(on_bottom & facing_down)


def completeness(
    cad: trimesh.Trimesh,
    model_cad_mm: trimesh.Trimesh | trimesh.PointCloud,
    mask: np.ndarray | None = None,
    threshold_mm: float = COMPLETENESS_MM,
    samples: int = 100_000,
    rng: np.random.Generator | None = None,
) -> float:
    """Share (0-1) of the CAD surface that could be seen which lies within `threshold_mm` of the model.

    Both in the CAD frame, mm. `mask` (F,) bool selects the CAD faces that could be seen (default `visible_faces`).
    The CAD surface is sampled uniformly (`samples` points); the distance is to the model's surface for a mesh
    (exact), to its nearest point for a point cloud (so a sparse cloud reads a little low).
    """
    rng = rng if rng is not None else np.random.default_rng(0)
    mask = visible_faces(cad) if mask is None else np.asarray(mask, dtype=bool)
    if not mask.any():
        return 0.0
    seen = cad.submesh([np.flatnonzero(mask)], append=True)
    points, _ = trimesh.sample.sample_surface(seen, samples, seed=int(rng.integers(2**31)))
    if isinstance(model_cad_mm, trimesh.Trimesh) and len(model_cad_mm.faces):
        index = build_index(model_cad_mm.vertices, model_cad_mm.faces, spacing=threshold_mm, levels=1)
        level = index.levels[0]
        # A sample within the threshold settles it (it is on the model), so does none within threshold + cover.
        nearest, _ = level.tree.query(points, distance_upper_bound=threshold_mm + level.cover)
        seen = nearest <= threshold_mm
        unsure = np.flatnonzero(~seen & np.isfinite(nearest))
        seen[unsure] = np.abs(closest_points(index, points[unsure])[0]) <= threshold_mm
        return float(np.mean(seen))
    distance, _ = cKDTree(np.asarray(model_cad_mm.vertices)).query(points)
    return float(np.mean(distance <= threshold_mm))


def colour_limit(stats: DeviationStats) -> float:
    """Symmetric colour-scale limit, mm: the larger of |1st| and |99th| percentile, rounded up to 2 digits."""
    limit = max(abs(stats.p01_mm), abs(stats.p99_mm), 1e-3)
    scale = 10.0 ** (np.floor(np.log10(limit)) - 1)
    return float(np.ceil(limit / scale) * scale)


def deviation_colours(signed_mm: np.ndarray, limit_mm: float) -> np.ndarray:
    """(N, 3) uint8 RGB on a diverging scale (matplotlib 'RdBu_r': blue inside, red outside), saturated at +-limit."""
    from matplotlib import colormaps

    t = np.clip((np.asarray(signed_mm) + limit_mm) / (2 * limit_mm), 0.0, 1.0)
    return (colormaps["RdBu_r"](t)[:, :3] * 255).round().astype(np.uint8)


def ply_bytes(
    vertices: np.ndarray, signed_mm: np.ndarray, colours: np.ndarray, faces: np.ndarray | None, comment: str
) -> bytes:
    """Binary PLY: vertices (V, 3) with RGB and a `deviation_mm` scalar (CloudCompare reads it as a scalar field),
    and faces (F, 3) if given."""
    from vio.writers.mesh import ply_bytes as mesh_ply_bytes

    return mesh_ply_bytes(vertices, faces, colours, True, comment, {"deviation_mm": signed_mm})
