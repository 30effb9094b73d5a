"""`vio measure`: the dimensions a machinist would check, fitted on a model and stated with a 95 % uncertainty.

Input: points (N, 3) mm sampled uniformly on the model's surface (100-300k), with unit outward normals when known
(estimated from neighbours otherwise). With a CAD, the points must already be in the CAD's frame (register first,
`vio.model.register`); without, in any frame (names use its axes). What is measured:
- "box": the box's three pairs of opposite faces (largest plane on each side of three perpendicular normal
  directions): face-to-face distances and the three edge lengths (distances between the corners where three
  fitted planes meet); with a CAD, nominal values from the same procedure on the CAD.
- "auto" with a CAD: the CAD's faces are grouped into regions (planes; cylinders and cones, whose normals turn
  about one axis; anything else is freeform and not measured); each region's primitive is fitted on the model points
  near the region's interior. Distances between antiparallel planes that face each other over a common area, depths
  of recessed parallel planes (pocket floors, hole bottoms), radii (partial cylinders: grooves, fillets) or diameters
  (full bores), cone included angles and countersink diameters (where the cone meets the plane across its axis).
  Nominal values are the same fits on the CAD, so no hand-written feature list is needed.
- "auto" without CAD: planes (`extract_planes`) paired as above, and cylinders found by RANSAC; no cones.

Uncertainty: U95 = k sqrt(u_fit^2 + (scale_sigma_rel * value)^2 + u_model^2), k = 1.96. u_fit is the standard
error of the dimension from the fits' covariances (residuals only; it ignores correlated reconstruction error),
u_scale the trajectory's relative scale sigma times the value (0 for angles, which a scale does not change), and
u_model an optional systematic term: the reconstruction's own error, which the benchmark calibrates.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, replace
from itertools import combinations
from typing import TYPE_CHECKING

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from vio.errors import ModelError
from vio.model import primitives as prim
from vio.model.primitives import Fit

if TYPE_CHECKING:
    import trimesh

log = logging.getLogger(__name__)
K95 = 1.96
SHAPES = ("box", "auto")


@dataclass(frozen=True)
class Dimension:
    """One measured dimension, as a row of an inspection report."""

    name: str  # the feature(s), in the frame of the fits (the CAD's when given), e.g. "+z@76.20 | -z@0.00"
    kind: str  # "distance" | "length" | "radius" | "diameter" | "angle"
    nominal: float | None  # the same fit on the CAD (mm or deg), None without a CAD
    measured: float  # mm, or deg for angles
    deviation: float | None  # measured - nominal, same unit
    U95: float  # expanded uncertainty (k = 1.96), same unit
    components: dict[str, float]  # standard uncertainties u_fit, u_scale, u_model (same unit) and k
    units: str  # "mm" | "deg"
    inliers: int  # model points used by the fit(s)
    rms_mm: float  # RMS residual of the fit(s), mm
    note: str = ""  # e.g. a face pair's non-parallelism, or "base: closure plane"


@dataclass(frozen=True)
class MeasureConfig:
    """Tuning of the fits (lengths in mm, angles in deg)."""

    band_mm: float = 1.0  # model points within this distance of a CAD region's primitive are fitted
    edge_margin_mm: float = 2.0  # points closer than this to an edge or feature are left out (at most 0.3 x region)
    normal_deg: float = 30.0  # model normals within this angle of the CAD's are fitted
    cluster_deg: float = 15.0  # normal clustering for planes without a CAD
    min_plane_fraction: float = 0.002  # smallest face without a CAD, as a fraction of the points
    cad_samples_per_mm2: float = 2.0  # CAD sampling density (nominal fits, region of each model point)
    max_fit_points: int = 20000  # cylinder and cone fits use a random subset of this size
    seed: int = 0


@dataclass(frozen=True)
class _Plane:
    """A planar face: the model's fit, its nominal (CAD) fit, and points for pairing (all / interior)."""

    name: str
    fit: Fit
    pts: np.ndarray  # (N, 3) model points of the fit
    nominal: Fit | None
    geo_all: np.ndarray  # (M, 3) points of the face (CAD samples, or the model's without CAD)
    geo_inner: np.ndarray  # (K, 3) interior points of the face


def measure(
    points_mm: np.ndarray,
    normals: np.ndarray | None,
    shape: str,
    cad: trimesh.Trimesh | None = None,
    scale_sigma_rel: float = 0.0,
    u_model_mm: float = 0.0,
    u_model_deg: float = 0.0,
    base_is_closure: bool = False,
    config: MeasureConfig | None = None,
) -> list[Dimension]:
    """Fit the primitives of `shape` ("box" | "auto", see the module docstring) and return the dimensions.

    points_mm (N, 3) in the CAD's frame when `cad` (a mesh in mm, outward normals) is given; normals (N, 3) unit,
    outward, or None to estimate them. `base_is_closure` notes that the face on the support (outward normal -z) is
    the model's closure on the support plane. Raises ModelError when the shape is not found."""
    cfg = config or MeasureConfig()
    if shape not in SHAPES:
        raise ModelError(f"unknown shape {shape!r}; use one of {', '.join(SHAPES)}")
    pts = np.asarray(points_mm, float)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 100 or not np.isfinite(pts).all():
        raise ModelError(f"measure needs at least 100 finite 3D points, got an array of shape {pts.shape}")
    nrm = prim.estimate_normals(pts) if normals is None else np.asarray(normals, float)
    if nrm.shape != pts.shape:
        raise ModelError(f"normals of shape {nrm.shape} do not match the points' {pts.shape}")
    unc = {"scale_sigma_rel": scale_sigma_rel, "u_model_mm": u_model_mm, "u_model_deg": u_model_deg}
    rng = np.random.default_rng(cfg.seed)
    if shape == "box":
        return _measure_box(pts, nrm, cad, cfg, unc, base_is_closure, rng)
    if cad is not None:
        planes, curved = _cad_features(pts, nrm, cad, cfg, rng)
    else:
        planes, curved = _detect_features(pts, nrm, cfg, rng)
    dims = _pair_dimensions(planes, unc, base_is_closure) + _curved_dimensions(curved, unc)
    if not dims:
        raise ModelError("no measurable feature found (no facing planes, cylinders or cones)")
    return dims


def _dimension(
    name: str,
    kind: str,
    value: float,
    u_fit: float,
    unc: dict[str, float],
    fits: list[Fit],
    nominal: float | None = None,
    note: str = "",
) -> Dimension:
    """A row with U95 from its components (see the module docstring); the RMS and count pool the fits."""
    angle = kind == "angle"
    u = {
        "u_fit": float(u_fit),
        "u_scale": 0.0 if angle else unc["scale_sigma_rel"] * abs(value),
        "u_model": unc["u_model_deg"] if angle else unc["u_model_mm"],
    }
    expanded = K95 * float(np.sqrt(sum(x * x for x in u.values())))
    nominal = None if nominal is None else float(nominal)
    dev = None if nominal is None else float(value - nominal)
    rms = float(np.sqrt(np.mean([f.rms_mm**2 for f in fits])))
    count = sum(f.count for f in fits)
    return Dimension(name, kind, nominal, float(value), dev, expanded, {**u, "k": K95}, "deg" if angle else "mm",
                     count, rms, note)  # fmt: skip


def _axis_name(direction: np.ndarray) -> str:
    i = int(np.argmax(np.abs(direction)))
    if abs(direction[i]) > np.cos(np.radians(1.0)):
        return ("+" if direction[i] > 0 else "-") + "xyz"[i]
    return "n(" + ",".join(f"{c:.2f}" for c in direction) + ")"


def _plane_name(fit: Fit) -> str:
    """E.g. "+z@76.20" (outward normal +z, at z = 76.20 mm), or "n(0.71,0.00,0.71)@12.30" (offset along n)."""
    point, n = fit.point_axis()
    name, i = _axis_name(n), int(np.argmax(np.abs(n)))
    return f"{name}@{(point[i] if name[1] in 'xyz' else point @ n) + 0.0:.2f}"


def _plane_distance(a: Fit, b: Fit, pa: np.ndarray, pb: np.ndarray, at: np.ndarray) -> float:
    """Distance (mm) between two nearly parallel planes along their mean normal through the point `at` (the
    centroid of the smaller face, so that the mean over the common area is what counts, not a tilt's lever arm)."""
    (qa, na), (qb, nb) = a.point_axis(pa), b.point_axis(pb)
    m = na + np.sign(na @ nb) * nb
    m /= np.linalg.norm(m)
    return float(abs((qa - at) @ na / (m @ na) - (qb - at) @ nb / (m @ nb)))


def _pair_kind(a: _Plane, b: _Plane) -> tuple[str, _Plane, _Plane] | None:
    """("distance", a, b) for antiparallel planes over a common area; ("depth", upper, lower) for a plane recessed
    within a parallel one (seen through a hole in it); else None. Judged on the nominal geometry when there is one."""
    (qa, na), (qb, nb) = (a.nominal or a.fit).point_axis(), (b.nominal or b.fit).point_axis()
    if abs(na @ nb) < np.cos(np.radians(1.0)):
        return None
    basis = np.stack(prim.perpendicular_basis(na), axis=1)

    def overlap(upper: _Plane, lower: _Plane) -> float:
        near = cKDTree(upper.geo_all @ basis).query(lower.geo_inner @ basis, distance_upper_bound=1.0)[0] < 1.0
        return float(np.mean(near))

    if na @ nb < 0:
        return ("distance", a, b) if max(overlap(a, b), overlap(b, a)) > 0.05 else None
    upper, lower = (a, b) if (qa - qb) @ na > 0 else (b, a)
    inner, area = lower.geo_inner @ basis, upper.geo_all @ basis
    inside = np.all((inner.mean(axis=0) > area.min(axis=0)) & (inner.mean(axis=0) < area.max(axis=0)))
    recessed = abs((qa - qb) @ na) > 0.1
    return ("depth", upper, lower) if recessed and inside and overlap(upper, lower) < 0.01 else None


def _pair_dimensions(planes: list[_Plane], unc: dict[str, float], base_is_closure: bool) -> list[Dimension]:
    dims = []
    for a, b in combinations(planes, 2):
        pair = _pair_kind(a, b)
        if pair is not None:
            dims.append(_distance(pair[1], pair[2], unc, base_is_closure, "depth; " if pair[0] == "depth" else ""))
    return dims


def _distance(a: _Plane, b: _Plane, unc: dict[str, float], base_is_closure: bool, note: str = "") -> Dimension:
    """The distance between two plane fits at the smaller face, with their non-parallelism (angle, and its spread
    over the smaller face)."""
    small = a if len(a.geo_inner) <= len(b.geo_inner) else b
    other = b if small is a else a

    def dist(p: list[np.ndarray]) -> float:
        return _plane_distance(a.fit, b.fit, p[0], p[1], small.fit.ref[0])

    value, nominal = dist([a.fit.params, b.fit.params]), None
    if a.nominal is not None:
        nominal = _plane_distance(a.nominal, b.nominal, a.nominal.params, b.nominal.params, small.nominal.ref[0])
    (qs, ns), (qo, no) = small.fit.point_axis(), other.fit.point_axis()
    tilt = np.degrees(np.arccos(min(abs(ns @ no), 1.0)))
    on_small = small.pts - np.outer((small.pts - qs) @ ns, ns)
    note += f"non-parallelism {tilt:.3f} deg ({np.ptp((on_small - qo) @ no):.3f} mm over the face)"
    if base_is_closure and min(ns[2], no[2]) < -0.99:
        note += "; base: the model's closure on the support plane"
    u_fit = prim.propagate(dist, [a.fit, b.fit])
    return _dimension(f"{a.name} to {b.name}", "distance", value, u_fit, unc, [a.fit, b.fit], nominal, note)


@dataclass(frozen=True)
class _Curved:
    """A fitted cylinder or cone, with its nominal fit and, for a cone, the plane across its axis."""

    name: str
    fit: Fit  # model fit, kind "cylinder" or "cone"
    nominal: Fit | None
    full: bool  # closed around its axis (a bore: diameter), or partial (a groove, a fillet: radius)
    plane: _Plane | None = None  # for a cone: the face it opens into (countersink diameter)


def _curved_name(fit: Fit) -> str:
    """E.g. "cylinder along z at x=20.00 y=20.00" (where the axis crosses the plane of the other two axes)."""
    point, axis = fit.point_axis()
    i = int(np.argmax(np.abs(axis)))
    p = point - axis * point[i] / axis[i]
    j, k = [c for c in range(3) if c != i]
    return f"{fit.kind} along {_axis_name(axis).lstrip('+-')} at {'xyz'[j]}={p[j]:.2f} {'xyz'[k]}={p[k]:.2f}"


def _countersink_diameter(cone: Fit, plane: Fit, pc: np.ndarray, pp: np.ndarray) -> float:
    """Diameter (mm) of the circle where a cone meets a plane across its axis."""
    (apex, axis), (q, n) = cone.point_axis(pc), plane.point_axis(pp)
    return float(2.0 * ((q - apex) @ n) / (axis @ n) * np.tan(pc[5]))


def _curved_dimensions(curved: list[_Curved], unc: dict[str, float]) -> list[Dimension]:
    dims = []
    for c in curved:
        f, nom = c.fit, c.nominal
        if f.kind == "cylinder":
            factor, kind = (2.0, "diameter") if c.full else (1.0, "radius")
            value, u = factor * f.params[4], factor * np.sqrt(f.cov[4, 4])
            nominal = None if nom is None else factor * nom.params[4]
            dims.append(_dimension(c.name, kind, value, u, unc, [f], nominal))
            continue
        value, u = 2.0 * np.degrees(f.params[5]), 2.0 * np.degrees(np.sqrt(f.cov[5, 5]))
        nominal = None if nom is None else 2.0 * np.degrees(nom.params[5])
        dims.append(_dimension(f"{c.name} included angle", "angle", value, u, unc, [f], nominal))
        if c.plane is not None:
            p = c.plane

            def dia(params: list[np.ndarray], f: Fit = f, p: _Plane = p) -> float:
                return _countersink_diameter(f, p.fit, params[0], params[1])

            value, u = dia([f.params, p.fit.params]), prim.propagate(dia, [f, p.fit])
            nominal = None if nom is None else _countersink_diameter(nom, p.nominal, nom.params, p.nominal.params)
            note = f"where the cone meets {p.name}"
            dims.append(_dimension(f"{c.name} diameter", "diameter", value, u, unc, [f, p.fit], nominal, note))
    return dims


def _cad_regions(cad: trimesh.Trimesh) -> tuple[np.ndarray, int, np.ndarray, set[tuple[int, int]]]:
    """(face labels (F,), number of planar regions (labels below it), vertex pairs (E, 2) of the edges between
    regions, adjacent label pairs). Planar regions: faces joined within 0.5 deg, flat within 0.01 mm and at least
    2 mm wide, coplanar ones merged; the other faces are joined within 20 deg into curved regions."""
    nf, adj, ang = len(cad.faces), cad.face_adjacency, cad.face_adjacency_angles

    def components(pairs: np.ndarray) -> np.ndarray:
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(nf, nf))
        return connected_components(graph, directed=False)[1]

    label, planes = -np.ones(nf, int), []
    comp = components(adj[ang < np.radians(0.5)])
    order = np.argsort(comp, kind="stable")
    for group in np.split(order, np.flatnonzero(np.diff(comp[order])) + 1):
        v = cad.vertices[np.unique(cad.faces[group])]
        n = (cad.face_normals[group] * cad.area_faces[group, None]).sum(axis=0)
        n /= np.linalg.norm(n)
        d = v @ n
        if np.ptp(d) > 0.01 or np.ptp((v - v.mean(axis=0)) @ np.linalg.svd(v - v.mean(axis=0))[2][1]) < 2.0:
            continue
        same = [k for k, (m, e) in enumerate(planes) if n @ m > np.cos(np.radians(0.5)) and abs(d.mean() - e) < 0.01]
        if not same:
            planes.append((n, d.mean()))
        label[group] = same[0] if same else len(planes) - 1
    rest = label < 0
    curved = components(adj[(ang < np.radians(20.0)) & rest[adj[:, 0]] & rest[adj[:, 1]]])
    label[rest] = len(planes) + np.unique(curved[rest], return_inverse=True)[1]
    cut = label[adj[:, 0]] != label[adj[:, 1]]
    pairs = {tuple(sorted(p)) for p in zip(label[adj[cut, 0]].tolist(), label[adj[cut, 1]].tolist(), strict=True)}
    return label, len(planes), cad.face_adjacency_edges[cut], pairs


def _nominal_curved(samples: np.ndarray, normals: np.ndarray) -> Fit | None:
    """The CAD's cylinder or cone on a curved region's samples, or None for a freeform surface."""
    axis, spread, along = prim.axis_from_normals(normals)
    if len(samples) < 50 or spread > 0.05 or np.degrees(np.arccos(np.clip(normals @ normals[0], -1, 1))).max() < 5:
        return None
    fit = prim.fit_cylinder(samples, normals) if abs(along) < 0.05 else prim.fit_cone(samples, normals)
    return fit if fit.rms_mm < 0.05 else None


def _group(labels: np.ndarray, count: int) -> list[np.ndarray]:
    """Indices of each label 0..count-1 (labels outside that range are dropped)."""
    order = np.argsort(labels, kind="stable")
    bounds = np.searchsorted(labels[order], np.arange(count + 1))
    return [order[bounds[i] : bounds[i + 1]] for i in range(count)]


def _cad_features(
    pts: np.ndarray, nrm: np.ndarray, cad: trimesh.Trimesh, cfg: MeasureConfig, rng: np.random.Generator
) -> tuple[list[_Plane], list[_Curved]]:
    """The CAD's planes, cylinders and cones, each fitted on the CAD's samples (nominal) and on the model points
    near the region's interior (measured)."""
    label_f, n_planes, edges, pairs = _cad_regions(cad)
    s, sn, face = prim.sample_surface(cad.vertices, cad.faces, int(cad.area * cfg.cad_samples_per_mm2), rng)
    lab = label_f[face]
    ev = cad.vertices[edges]
    steps = np.maximum(np.ceil(np.linalg.norm(ev[:, 1] - ev[:, 0], axis=1) / 0.25).astype(int), 1) + 1
    t = np.concatenate([np.linspace(0.0, 1.0, k) for k in steps])[:, None]
    e0, e1 = np.repeat(ev[:, 0], steps, axis=0), np.repeat(ev[:, 1], steps, axis=0)
    cap = cfg.edge_margin_mm / 0.3  # margins depend on distances below this only; a bounded search is fast
    to_edge = np.minimum(cKDTree(e0 + t * (e1 - e0)).query(s, distance_upper_bound=cap, workers=1)[0], cap)
    inradius = np.zeros(label_f.max() + 1)
    np.maximum.at(inradius, lab, to_edge)
    interior = to_edge > np.minimum(cfg.edge_margin_mm, 0.3 * inradius)[lab]
    nearest = cKDTree(s).query(pts, workers=1)[1]
    model_lab = np.where(interior[nearest], lab[nearest], -1)
    aligned = np.abs(np.einsum("ij,ij->i", nrm, sn[nearest])) > np.cos(np.radians(cfg.normal_deg))
    by_label = _group(lab, len(inradius))
    model_by_label = _group(np.where(aligned, model_lab, len(inradius)), len(inradius))
    planes: dict[int, _Plane] = {}
    curved: list[tuple[int, str, Fit, Fit, bool]] = []
    for k, region in enumerate(by_label):
        ins = region[interior[region]]
        if len(ins) < 20:
            continue
        nominal = prim.fit_plane(s[ins], sn[ins].mean(axis=0)) if k < n_planes else _nominal_curved(s[ins], sn[ins])
        if nominal is None:
            log.info("CAD region %d (%d samples) is freeform: not measured", k, len(ins))
            continue
        sel = model_by_label[k]
        sel = sel[np.abs(nominal.residuals(pts[sel])) < cfg.band_mm]
        name = _plane_name(nominal) if k < n_planes else _curved_name(nominal)
        if len(sel) < 20:
            log.warning("%s: only %d model points near the CAD's feature; not measured", name, len(sel))
            continue
        if k < n_planes:
            planes[k] = _Plane(name, prim.fit_plane(pts[sel], nominal.ref[1]), pts[sel], nominal, s[region], s[ins])
            continue
        sub = sel[rng.choice(len(sel), size=min(len(sel), cfg.max_fit_points), replace=False)]
        fit = (prim.fit_cylinder if nominal.kind == "cylinder" else prim.fit_cone)(pts[sub], init=nominal)
        curved.append((k, name, fit, nominal, prim.angular_coverage_deg(nominal, s[region]) >= 300.0))
    out = []
    for k, name, fit, nominal, full in curved:
        across = [planes[j] for j in planes if tuple(sorted((j, k))) in pairs]
        across = [p for p in across if abs(p.nominal.ref[1] @ nominal.point_axis()[1]) > np.cos(np.radians(2.0))]
        apex, axis = nominal.point_axis()
        plane = max(across, key=lambda p: (p.nominal.ref[0] - apex) @ axis, default=None)
        out.append(_Curved(name, fit, nominal, full, plane if nominal.kind == "cone" else None))
    return list(planes.values()), out


def _detect_features(
    pts: np.ndarray, nrm: np.ndarray, cfg: MeasureConfig, rng: np.random.Generator
) -> tuple[list[_Plane], list[_Curved]]:
    """Without a CAD: planar faces by normal clustering, then cylinders by RANSAC on the points no face took."""
    min_count = max(100, int(cfg.min_plane_fraction * len(pts)))
    faces = prim.extract_planes(pts, nrm, rng, min_count, cfg.band_mm, cfg.edge_margin_mm, cfg.cluster_deg)
    planes = [_Plane(_plane_name(f), f, pts[inner], None, pts[inner], pts[inner]) for f, _, inner in faces]
    free = np.ones(len(pts), bool)
    for _, members, _ in faces:
        free[members] = False
    idx = np.flatnonzero(free)
    noise_mm = float(np.median([f.rms_mm for f, _, _ in faces])) if faces else 0.05
    found = prim.ransac_cylinders(pts[idx], nrm[idx], rng, max(200, int(0.005 * len(pts))), max(0.15, 6 * noise_mm))
    full = [prim.angular_coverage_deg(f, pts[idx[inl]]) >= 300.0 for f, inl in found]
    return planes, [_Curved(_curved_name(f), f, None, c) for (f, _), c in zip(found, full, strict=True)]


def _box_faces(pts: np.ndarray, nrm: np.ndarray, cfg: MeasureConfig, rng: np.random.Generator) -> list[list]:
    """The box's three axes, each [unit direction, + face, - face] with faces (fit, members, interior) or None,
    ordered like the frame's x, y, z and pointing along them. Raises ModelError without a box."""
    faces = prim.extract_planes(pts, nrm, rng, max(100, int(0.01 * len(pts))), cfg.band_mm, cfg.edge_margin_mm)
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


def _box_length(fits: list[Fit], params: list[np.ndarray], i: int) -> float:
    """Mean length (mm) of the 4 box edges along axis i, between the corners where three fitted planes meet
    (fits and params ordered +x, -x, +y, -y, +z, -z)."""
    geo = [f.point_axis(p) for f, p in zip(fits, params, strict=True)]
    j, k = [c for c in range(3) if c != i]
    lengths = []
    for sj in (0, 1):
        for sk in (0, 1):
            ends = []
            for si in (0, 1):
                rows = [geo[2 * i + si], geo[2 * j + sj], geo[2 * k + sk]]
                ends.append(np.linalg.solve(np.stack([n for _, n in rows]), np.array([q @ n for q, n in rows])))
            lengths.append(np.linalg.norm(ends[1] - ends[0]))
    return float(np.mean(lengths))


def _measure_box(
    pts: np.ndarray,
    nrm: np.ndarray,
    cad: trimesh.Trimesh | None,
    cfg: MeasureConfig,
    unc: dict[str, float],
    base_is_closure: bool,
    rng: np.random.Generator,
) -> list[Dimension]:
    """The box's face-to-face distances and edge lengths (see the module docstring)."""
    axes = _box_faces(pts, nrm, cfg, rng)
    nominal_axes = None
    if cad is not None:
        s, sn, _ = prim.sample_surface(cad.vertices, cad.faces, 20000, rng)  # noise-free: plenty for planes
        nominal_axes = _box_faces(s, sn, cfg, rng)
    dims, fits, nominal_fits = [], [], []
    for g in axes:
        nom = None if nominal_axes is None else max(nominal_axes, key=lambda h: abs(h[0] @ g[0]))
        if nom is not None and nom[0] @ g[0] < 0:
            nom = [-nom[0], nom[2], nom[1]]
        planes = []
        for side in (1, 2):
            f = g[side]
            nf = None if nom is None or nom[side] is None else nom[side][0]
            planes.append(None if f is None else _Plane(_plane_name(f[0]), f[0], pts[f[2]], nf, pts[f[2]], pts[f[2]]))
            fits.append(None if f is None else f[0])
            nominal_fits.append(nf)
        axis = "xyz"[int(np.argmax(np.abs(g[0])))]
        if None not in planes:
            d = _distance(planes[0], planes[1], unc, base_is_closure)
            dims.append(replace(d, name=f"box {axis}: {d.name}"))
            continue
        present = planes[0] or planes[1]
        q, n = present.fit.point_axis()
        sides = np.concatenate([pts[h[1]] for a in axes if a is not g for h in a[1:] if h is not None])
        value = float(np.abs((sides - q) @ n).max())
        u_fit = float(np.sqrt(present.fit.cov[0, 0] + present.fit.rms_mm**2))
        note = f"face opposite {present.name} missing: measured to the farthest points of the side faces"
        dims.append(_dimension(f"box {axis}: {present.name} to the side faces' end", "distance", value, u_fit, unc,
                               [present.fit], None, note))  # fmt: skip
    if None not in fits:
        for i in range(3):

            def length(params: list[np.ndarray], i: int = i) -> float:
                return _box_length(fits, params, i)

            nominal = None
            if nominal_axes is not None and None not in nominal_fits:
                nominal = _box_length(nominal_fits, [f.params for f in nominal_fits], i)
            value, u = length([f.params for f in fits]), prim.propagate(length, fits)
            axis = "xyz"[int(np.argmax(np.abs(axes[i][0])))]
            dims.append(_dimension(f"box edge {axis}", "length", value, u, unc, fits, nominal, "mean of 4 edges"))
    return dims


def report_dict(dimensions: list[Dimension], notes: tuple[str, ...] = ()) -> dict:
    """A JSON-serialisable summary: the dimensions (every field), the coverage factor and notes."""
    return {"k": K95, "dimensions": [asdict(d) for d in dimensions], "notes": list(notes)}


def inspection_report(
    dimensions: list[Dimension], title: str = "Inspection report", notes: tuple[str, ...] = ()
) -> str:
    """A markdown inspection report: one row per dimension with nominal, measured, deviation and U95."""

    def num(x: float | None, digits: int = 3) -> str:
        return "" if x is None else f"{x:.{digits}f}"

    lines = [f"# {title}", "", "| # | feature | kind | nominal | measured | deviation | U95 (k=1.96) | u_fit | "
             "u_scale | u_model | unit | points | RMS mm | note |", "|" + "---|" * 14]  # fmt: skip
    for i, d in enumerate(dimensions, 1):
        c = d.components
        row = [str(i), d.name, d.kind, num(d.nominal), num(d.measured), num(d.deviation), num(d.U95),
               num(c["u_fit"], 4), num(c["u_scale"], 4), num(c["u_model"], 4), d.units, str(d.inliers),
               num(d.rms_mm, 4), d.note]  # fmt: skip
        lines.append("| " + " | ".join(row) + " |")
    lines += ["", "U95 = 1.96 sqrt(u_fit^2 + u_scale^2 + u_model^2): fit residuals, trajectory scale, reconstruction."]
    return "\n".join(lines + [f"- {n}" for n in notes]) + "\n"
