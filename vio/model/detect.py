"""Planar faces, cylinders and a box's faces found on points without a CAD (`vio measure` without CAD, and the box).

Points (N, 3) mm with unit outward normals (N, 3), in any frame; the fits are those of `vio.model.primitives`.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from vio.errors import ModelError
from vio.model.primitives import Fit, fit_cylinder, fit_plane, perpendicular_basis


def _is_curved(points: np.ndarray, fit: Fit, min_radius_mm: float, rng: np.random.Generator) -> bool:
    """Whether points near a fitted plane curve more than 1 / min_radius_mm with a sag (over their extent) above
    their noise: the quadric w = a + b u + c v + d u^2 + e u v + f v^2 on up to 2000 of them."""
    if len(points) < 10:
        return True
    c, n = fit.ref
    e1, e2 = perpendicular_basis(n)
    q = points[rng.choice(len(points), size=min(2000, len(points)), replace=False)] - c
    u, v, w = q @ e1, q @ e2, q @ n
    design = np.stack([np.ones_like(u), u, v, u * u, u * v, v * v], axis=1)
    coef = np.linalg.lstsq(design, w, rcond=None)[0]
    kappa, vec = np.linalg.eigh(np.array([[2 * coef[3], coef[4]], [coef[4], 2 * coef[5]]]))
    i = int(np.argmax(np.abs(kappa)))
    along = np.stack([u, v], axis=1) @ vec[:, i]
    sag = abs(kappa[i]) * (np.quantile(along, 0.98) - np.quantile(along, 0.02)) ** 2 / 8.0
    return bool(abs(kappa[i]) > 1.0 / min_radius_mm and sag > max(fit.rms_mm, 0.02))


def _coplanar(a: Fit, b: Fit) -> bool:
    """Same plane within 1 deg and max(3 RMS residuals, 0.05 mm)."""
    (qa, na), (qb, nb) = a.point_axis(), b.point_axis()
    return bool(na @ nb > np.cos(np.radians(1.0)) and abs((qb - qa) @ na) < max(3.0 * a.rms_mm, 0.05))


def extract_planes(
    points: np.ndarray,
    normals: np.ndarray,
    rng: np.random.Generator,
    min_count: int,
    band_mm: float = 1.0,
    edge_margin_mm: float = 2.0,
    cluster_deg: float = 15.0,
    min_radius_mm: float = 2000.0,
    max_tries: int = 30,
) -> list[tuple[Fit, np.ndarray, np.ndarray]]:
    """Planar faces of a model, largest first: [(fit, member indices, interior indices)].

    One face per try: the normal direction most points share (within `cluster_deg`), then the most populated
    offset along it (bins of `band_mm`), a trimmed least-squares plane, its members (within 4 residual sigmas),
    and the interior: members farther than `edge_margin_mm` from the points of edges, holes and features (off the
    plane by more than 6 sigmas, or of another orientation); the fit is redone on the interior. An interior that
    curves more than 1 / `min_radius_mm` (a sag of 0.36 mm over 76 mm at 2 m) with a sag above its noise (RMS
    residual) is not a face.
    """
    cos_c = np.cos(np.radians(cluster_deg))
    searchable = np.ones(len(points), bool)
    claimed = np.zeros(len(points), bool)
    faces: list[tuple[Fit, np.ndarray, np.ndarray]] = []
    for _ in range(max_tries):
        idx = np.flatnonzero(searchable & ~claimed)
        if len(idx) < min_count:
            break
        cand = normals[rng.choice(idx, size=min(128, len(idx)), replace=False)]
        sub = normals[rng.choice(idx, size=min(4000, len(idx)), replace=False)]
        c = cand[int(np.argmax((sub @ cand.T > cos_c).sum(axis=0)))]
        cluster = idx[normals[idx] @ c > cos_c]
        if len(cluster) < min_count:
            searchable[cluster] = False
            continue
        off = points[cluster] @ c
        edges = np.arange(off.min(), off.max() + 2 * band_mm, band_mm)
        hist = np.histogram(off, edges)[0]
        mode = edges[int(np.argmax(hist))] + band_mm / 2
        near = cluster[np.abs(off - mode) < band_mm]
        if len(near) < min_count:
            searchable[cluster] = False
            continue
        fit = fit_plane(points[near], c)
        resid = np.abs(fit.residuals(points))
        member = np.zeros(len(points), bool)
        member[cluster[resid[cluster] < 4.0 * fit.rms_mm + 1e-6]] = True
        members = np.flatnonzero(member)
        if len(members) < min_count or _is_curved(points[near], fit, 100.0, rng):  # early out: spheres, waves
            searchable[near] = False
            continue
        # edges: points near the plane but clearly off it (> 6 sigma) or of another orientation
        other = np.flatnonzero(
            (resid < 2.0 * edge_margin_mm) & ~member & ((resid > 6.0 * fit.rms_mm) | (normals @ c < cos_c))
        )
        interior = members
        if len(other):
            gap = cKDTree(points[other]).query(points[members], distance_upper_bound=edge_margin_mm, workers=1)[0]
            interior = members[np.isinf(gap)]  # no edge point within the margin (bounded search: fast)
        if len(interior) < max(10, min_count // 4) or _is_curved(points[interior], fit, min_radius_mm, rng):
            searchable[near] = False
            continue
        claimed[members] = True
        fit = fit_plane(points[interior], c)
        same = [k for k, f in enumerate(faces) if _coplanar(f[0], fit)]  # e.g. a face cut in two by a groove
        if same:
            old = faces.pop(same[0])
            members, interior = np.union1d(old[1], members), np.union1d(old[2], interior)
            fit = fit_plane(points[interior], c)
        faces.append((fit, members, interior))
    faces.sort(key=lambda f: -len(f[1]))
    return faces


def ransac_cylinders(
    points: np.ndarray,
    normals: np.ndarray,
    rng: np.random.Generator,
    min_count: int,
    tol_mm: float = 0.3,
    radius_mm: tuple[float, float] = (0.5, 100.0),
    max_models: int = 8,
) -> list[tuple[Fit, np.ndarray]]:
    """Cylinders among points with normals (N, 3) mm: [(fit, inlier indices)], by RANSAC on pairs of nearby
    points (the axis is the cross product of their normals, the centre where their normal lines meet).

    Inliers lie within `tol_mm` of the surface with normals within 10 deg of square to the axis. A candidate whose
    refit leaves an RMS above 0.3 tol (a freeform patch) or whose normals tilt along the axis (a sphere's band) is
    dropped; the search stops after three such in a row."""
    free = np.arange(len(points))
    found: list[tuple[Fit, np.ndarray]] = []
    sin10 = np.sin(np.radians(10.0))
    misses = 0
    while len(found) < max_models and len(free) >= min_count and misses < 3:
        k = min(16, len(free) - 1)
        i = rng.choice(len(free), size=400)
        j = cKDTree(points[free]).query(points[free[i]], k=k + 1)[1][np.arange(400), rng.integers(1, k + 1, 400)]
        p1, p2, n1, n2 = points[free[i]], points[free[j]], normals[free[i]], normals[free[j]]
        axis = np.cross(n1, n2)
        ok = np.linalg.norm(axis, axis=1) > np.sin(np.radians(3.0))
        axis = axis[ok] / np.linalg.norm(axis[ok], axis=1, keepdims=True)
        p1, p2, n1, n2 = p1[ok], p2[ok], n1[ok], n2[ok]
        # p1 + t n1 and p2 + s n2 meet (in projection along the axis): least squares for (t, s)
        d, b = p2 - p1, np.einsum("ij,ij->i", n1, n2)
        t = (np.einsum("ij,ij->i", d, n1) - b * np.einsum("ij,ij->i", d, n2)) / np.maximum(1 - b * b, 1e-9)
        centre, radius = p1 + t[:, None] * n1, np.abs(t)
        sample = free[rng.choice(len(free), size=min(3000, len(free)), replace=False)]
        v = points[sample][None] - centre[:, None]
        h = np.einsum("mnj,mj->mn", v, axis)
        rho = np.sqrt(np.maximum(np.einsum("mnj,mnj->mn", v, v) - h * h, 0))
        ortho = np.abs(normals[sample] @ axis.T).T < sin10
        score = ((np.abs(rho - radius[:, None]) < tol_mm) & ortho).sum(axis=1)
        score[(radius < radius_mm[0]) | (radius > radius_mm[1])] = 0
        best = int(np.argmax(score)) if len(score) else 0
        if not len(score) or score[best] * len(free) / len(sample) < min_count:
            break
        fit = Fit("cylinder", (centre[best], axis[best]), np.array([0, 0, 0, 0, radius[best]]), np.eye(5), 0.0, 0)
        for _ in range(2):
            ortho = np.abs(normals[free] @ fit.point_axis()[1]) < sin10
            inl = free[(np.abs(fit.residuals(points[free])) < tol_mm) & ortho]
            if len(inl) < min_count:
                break
            fit = fit_cylinder(points[inl], init=fit)
        if len(inl) < min_count:
            break
        point, axis = fit.point_axis()
        tilt = np.corrcoef(normals[inl] @ axis, (points[inl] - point) @ axis)[0, 1] if len(inl) > 2 else 1.0
        # inliers spread over +-tol (RMS 0.4-0.6 tol) are a freeform patch; normals that tilt along the axis a sphere
        accept = fit.rms_mm < 0.3 * tol_mm and abs(tilt) < 0.5
        if accept:
            found.append((fit, inl))
        misses = 0 if accept else misses + 1
        free = np.setdiff1d(free, inl)
    return found


def box_faces(
    pts: np.ndarray, nrm: np.ndarray, rng: np.random.Generator, band_mm: float, edge_margin_mm: float
) -> list[list]:
    """The box's three axes, each [unit direction, + face, - face] with faces (fit, members, interior) or None,
    ordered like the frame's x, y, z and pointing along them. Raises ModelError without a box."""
    faces = extract_planes(pts, nrm, rng, max(100, int(0.01 * len(pts))), band_mm, edge_margin_mm)
    groups: list[list] = []
    for face in faces:  # largest first: the largest plane on each side of a direction is the box's face
        n = face[0].point_axis()[1]
        g = next((g for g in groups if abs(g[0] @ n) > np.cos(np.radians(3.0))), None)
        if g is None:
            groups.append(g := [n, None, None])
        side = 1 if g[0] @ n > 0 else 2
        g[side] = g[side] or face
    groups.sort(key=lambda g: -sum(len(f[1]) for f in g[1:] if f is not None))
    axes: list[list] = []
    for g in groups:
        if len(axes) < 3 and all(abs(g[0] @ h[0]) < np.sin(np.radians(3.0)) for h in axes):
            axes.append(g)
    found = sum(f is not None for g in axes for f in g[1:])
    if len(axes) < 3 or found < 5:
        raise ModelError(f"no box-like structure: {len(faces)} planar faces in {len(axes)} perpendicular directions")
    axes.sort(key=lambda g: int(np.argmax(np.abs(g[0]))))
    for g in axes:
        if g[0][np.argmax(np.abs(g[0]))] < 0:
            g[:] = [-g[0], g[2], g[1]]
    return axes
