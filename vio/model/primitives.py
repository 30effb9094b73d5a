"""Least-squares primitives for `vio measure`: planes, cylinders and cones fitted to points in millimetres.

Every fit works in the frame of the points it is given (the model's frame, or the CAD's after registration) and
returns its parameters with their covariance, sigma^2 (J^T J)^-1 with sigma^2 from the residuals, so that a derived
dimension can carry the fit's standard error (`propagate`). Each primitive is parametrised around a reference
geometry (a local chart), so that its parameter vector can be perturbed and turned back into geometry.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial import cKDTree

from vio.geometry import sample_triangles

log = logging.getLogger(__name__)


def perpendicular_basis(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors e1, e2 with (e1, e2, axis) right-handed and orthonormal."""
    a = axis / np.linalg.norm(axis)
    helper = np.eye(3)[int(np.argmin(np.abs(a)))]
    e1 = np.cross(a, helper)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(a, e1)


@dataclass(frozen=True)
class Fit:
    """A fitted primitive: `params` in the chart of the reference geometry `ref`, their covariance, the residuals.

    kind "plane": ref (centroid, normal); params (a, b, c) of w = a + b u + c v, w along the normal, u, v in-plane.
    kind "cylinder": ref (point on the axis, axis); params (x, y, alpha, beta, r): axis point ref0 + x e1 + y e2,
    axis direction a0 + alpha e1 + beta e2 (normalised), radius r mm.
    kind "cone": ref (apex, axis); params (x, y, z, alpha, beta, theta): apex ref0 + (x, y, z) in (e1, e2, a0),
    axis as for the cylinder pointing from the apex into the cone, half-angle theta rad.
    """

    kind: str
    ref: tuple[np.ndarray, np.ndarray]  # (point (3,) mm, unit axis or normal (3,))
    params: np.ndarray  # see the class docstring
    cov: np.ndarray  # (P, P) covariance of params
    rms_mm: float  # RMS residual (distance to the surface) of the inliers, mm
    count: int  # number of inliers

    def point_axis(self, params: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(a point (3,) mm, unit direction (3,)) of the geometry: plane point and normal; axis point (the apex for a
        cone) and axis direction."""
        p = self.params if params is None else params
        p0, a0 = self.ref
        e1, e2 = perpendicular_basis(a0)
        if self.kind == "plane":
            n = a0 - p[1] * e1 - p[2] * e2
            return p0 + p[0] * a0, n / np.linalg.norm(n)
        a = a0 + p[-3 if self.kind == "cone" else 2] * e1 + p[-2 if self.kind == "cone" else 3] * e2
        z = p[2] * a0 if self.kind == "cone" else 0.0
        return p0 + p[0] * e1 + p[1] * e2 + z, a / np.linalg.norm(a)

    def residuals(self, points: np.ndarray, params: np.ndarray | None = None) -> np.ndarray:
        """(N,) signed distances (mm, approximately for a cone) of points from the surface."""
        p = self.params if params is None else params
        return _residuals(self.kind, self.ref, p, points)


def _residuals(kind: str, ref: tuple[np.ndarray, np.ndarray], params: np.ndarray, points: np.ndarray) -> np.ndarray:
    point, axis = Fit(kind, ref, params, np.zeros((0, 0)), 0.0, 0).point_axis()
    v = points - point
    h = v @ axis
    if kind == "plane":
        return h
    rho = np.sqrt(np.maximum(np.einsum("ij,ij->i", v, v) - h * h, 0.0))
    if kind == "cylinder":
        return rho - params[4]
    return rho * np.cos(params[5]) - h * np.sin(params[5])


def _covariance(jac: np.ndarray, resid: np.ndarray) -> np.ndarray:
    dof = max(len(resid) - jac.shape[1], 1)
    sigma2 = float(resid @ resid) / dof
    return sigma2 * np.linalg.pinv(jac.T @ jac)


def fit_plane(points: np.ndarray, normal_hint: np.ndarray | None = None, trim_sigma: float = 3.0) -> Fit:
    """Total least-squares plane through points (N, 3) mm, trimmed twice at `trim_sigma` robust sigmas.

    The normal is oriented like `normal_hint` when given (e.g. outward). Covariance of (a, b, c) from the
    residuals of the final inliers."""
    keep = np.ones(len(points), bool)
    for _ in range(3):
        c = points[keep].mean(axis=0)
        q = points[keep] - c
        n = np.linalg.eigh(q.T @ q)[1][:, 0]
        n = -n if normal_hint is not None and n @ normal_hint < 0 else n
        w = (points - c) @ n
        sigma = 1.4826 * np.median(np.abs(w[keep])) + 1e-9
        new = np.abs(w) < trim_sigma * sigma
        if new.sum() < 3 or (new == keep).all():
            break
        keep = new
    e1, e2 = perpendicular_basis(n)
    q = points[keep] - c
    jac = np.stack([np.ones(len(q)), q @ e1, q @ e2], axis=1)
    resid = q @ n
    return Fit("plane", (c, n), np.zeros(3), _covariance(jac, resid), float(np.sqrt(np.mean(resid**2))), len(q))


def _fit_nonlinear(kind: str, ref: tuple[np.ndarray, np.ndarray], x0: np.ndarray, points: np.ndarray) -> Fit:
    """Levenberg-Marquardt on the distances, then one trimming at 3 robust sigmas and a final solve."""

    def solve(pts: np.ndarray, start: np.ndarray):
        return least_squares(lambda p: _residuals(kind, ref, p, pts), start, method="lm", x_scale="jac")

    res = solve(points, x0)
    sigma = 1.4826 * np.median(np.abs(res.fun)) + 1e-9
    keep = np.abs(res.fun) < 3.0 * sigma
    if keep.sum() >= len(x0) + 3 and not keep.all():
        res = solve(points[keep], res.x)
    rms = float(np.sqrt(np.mean(res.fun**2)))
    return Fit(kind, ref, res.x, _covariance(res.jac, res.fun), rms, len(res.fun))


def axis_from_normals(normals: np.ndarray) -> tuple[np.ndarray, float, float]:
    """(axis, spread, mean n . axis) of a surface of revolution from its unit normals (N, 3).

    The axis is the direction along which the normals' component is most constant: zero for a cylinder, sin of
    the half-angle for a cone. `spread` is the standard deviation of that component (0 on a perfect surface)."""
    centred = normals - normals.mean(axis=0)
    w, v = np.linalg.eigh(centred.T @ centred / len(normals))
    axis = v[:, 0]
    return axis, float(np.sqrt(max(w[0], 0.0))), float(np.mean(normals @ axis))


def _axis_point(points: np.ndarray, normals: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Least-squares point nearest to all normal lines, moved to the points' mean height along the axis."""
    n_perp = normals - np.outer(normals @ axis, axis)
    n_perp /= np.linalg.norm(n_perp, axis=1, keepdims=True) + 1e-12
    proj = np.eye(3)[None] - n_perp[:, :, None] * n_perp[:, None, :]  # projectors across each normal line
    lhs = proj.sum(axis=0) + len(points) * np.outer(axis, axis)
    rhs = np.einsum("nij,nj->i", proj, points) + len(points) * axis * (points.mean(axis=0) @ axis)
    return np.linalg.solve(lhs, rhs)


def fit_cylinder(points: np.ndarray, normals: np.ndarray | None = None, init: Fit | None = None) -> Fit:
    """Cylinder through points (N, 3) mm; initialised from `init` (e.g. the CAD's cylinder) or from the normals."""
    if init is not None:
        point, axis = init.point_axis()
    else:
        axis, _, _ = axis_from_normals(normals)
        point = _axis_point(points, normals, axis)
    v = points - point
    r0 = float(np.mean(np.linalg.norm(v - np.outer(v @ axis, axis), axis=1)))
    return _fit_nonlinear("cylinder", (point, axis), np.array([0.0, 0.0, 0.0, 0.0, r0]), points)


def fit_cone(points: np.ndarray, normals: np.ndarray | None = None, init: Fit | None = None) -> Fit:
    """Cone through points (N, 3) mm; the axis points from the apex into the cone (where the points are)."""
    if init is not None:
        apex, axis = init.point_axis()
        theta = float(init.params[5])
    else:
        axis, _, _ = axis_from_normals(normals)
        point = _axis_point(points, normals, axis)
        v = points - point
        h = v @ axis
        rho = np.linalg.norm(v - np.outer(h, axis), axis=1)
        slope, intercept = np.polyfit(h, rho, 1)  # rho = slope * h + intercept; apex where rho = 0
        if slope < 0:
            axis, h, slope = -axis, -h, -slope
        apex = point - axis * intercept / max(slope, 1e-6)
        theta = float(np.arctan(slope))
    return _fit_nonlinear("cone", (apex, axis), np.array([0.0, 0.0, 0.0, 0.0, 0.0, theta]), points)


def angular_coverage_deg(fit: Fit, points: np.ndarray) -> float:
    """How much of the full turn around a cylinder's or cone's axis the points cover, deg (10 deg bins)."""
    point, axis = fit.point_axis()
    e1, e2 = perpendicular_basis(axis)
    v = points - point
    ang = np.degrees(np.arctan2(v @ e2, v @ e1)) % 360.0
    return float(np.count_nonzero(np.bincount((ang // 10).astype(int), minlength=36)[:36]) * 10.0)


def propagate(func: Callable[[Sequence[np.ndarray]], float], fits: Sequence[Fit]) -> float:
    """Standard deviation of func(params of each fit) from the fits' covariances (independent fits).

    Symmetric sigma points along the eigenvectors of each covariance: exact for a function linear in the
    parameters, and free of hand-written Jacobians."""
    params = [f.params.copy() for f in fits]
    var = 0.0
    for i, f in enumerate(fits):
        w, v = np.linalg.eigh(f.cov)
        for lam, vec in zip(w, v.T, strict=True):
            if lam <= 0:
                continue
            step = np.sqrt(lam) * vec
            plus = [p if j != i else p + step for j, p in enumerate(params)]
            minus = [p if j != i else p - step for j, p in enumerate(params)]
            var += (0.5 * (func(plus) - func(minus))) ** 2
    return float(np.sqrt(var))


def sample_surface(
    vertices: np.ndarray, faces: np.ndarray, count: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(points (count, 3), unit face normals (count, 3), face index (count,)) sampled uniformly by area on a mesh;
    points in the mesh's frame and units, normals outward for counter-clockwise faces."""
    tri = np.asarray(vertices, float)[np.asarray(faces)]
    pts, face = sample_triangles(tri, count, rng)
    cross = np.cross(tri[face, 1] - tri[face, 0], tri[face, 2] - tri[face, 0])
    normals = cross / np.maximum(np.linalg.norm(cross, axis=1), 1e-300)[:, None]
    return pts, normals, face


def estimate_normals(points: np.ndarray, k: int = 16) -> np.ndarray:
    """(N, 3) unit normals of a point cloud from the k nearest neighbours (PCA), oriented away from the centroid
    (outward for a convex-ish part)."""
    _, idx = cKDTree(points).query(points, k=k, workers=1)
    nb = points[idx] - points[idx].mean(axis=1, keepdims=True)
    _, vecs = np.linalg.eigh(np.einsum("nki,nkj->nij", nb, nb))
    normals = vecs[:, :, 0]
    flip = np.einsum("ij,ij->i", normals, points - points.mean(axis=0)) < 0
    normals[flip] *= -1
    return normals
