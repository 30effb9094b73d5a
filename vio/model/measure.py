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
The CAD's regions are in `vio.model.cad_regions`, the detection without CAD in `vio.model.detect`, the report's
rows and text in `vio.model.measure_report`.

Uncertainty: U95 = k sqrt(u_fit^2 + (scale_sigma_rel * value)^2 + u_model^2), k = 1.96. u_fit is the standard
error of the dimension from the fits' covariances (residuals only; it ignores correlated reconstruction error),
u_scale the trajectory's relative scale sigma times the value (0 for angles, which a scale does not change), and
u_model an optional systematic term: the reconstruction's own error, which the benchmark calibrates; for a
dimension that ends on a base closed on the support plane, the base's standard uncertainty is added to it in
quadrature (`u_base_mm`, from model.json's `base_sigma_mm`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from itertools import combinations
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from vio.errors import ModelError
from vio.model import primitives as prim
from vio.model.cad_regions import Curved, Plane, cad_features
from vio.model.detect import box_faces, extract_planes, ransac_cylinders
from vio.model.measure_report import Dimension, curved_name, dimension, plane_name
from vio.model.primitives import Fit

if TYPE_CHECKING:
    import trimesh

log = logging.getLogger(__name__)
SHAPES = ("box", "auto")


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


def measure(
    points_mm: np.ndarray,
    normals: np.ndarray | None,
    shape: str,
    cad: trimesh.Trimesh | None = None,
    scale_sigma_rel: float = 0.0,
    u_model_mm: float = 0.0,
    u_model_deg: float = 0.0,
    base_is_closure: bool = False,
    u_base_mm: float = 0.0,
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
    if base_is_closure:
        unc["u_base_mm"] = u_base_mm
    rng = np.random.default_rng(cfg.seed)
    if shape == "box":
        return _measure_box(pts, nrm, cad, cfg, unc, base_is_closure, rng)
    if cad is not None:
        planes, curved = cad_features(
            pts,
            nrm,
            cad,
            rng,
            band_mm=cfg.band_mm,
            edge_margin_mm=cfg.edge_margin_mm,
            normal_deg=cfg.normal_deg,
            cad_samples_per_mm2=cfg.cad_samples_per_mm2,
            max_fit_points=cfg.max_fit_points,
        )
    else:
        planes, curved = _detect_features(pts, nrm, cfg, rng)
    dims = _pair_dimensions(planes, unc, base_is_closure) + _curved_dimensions(curved, unc)
    if not dims:
        raise ModelError("no measurable feature found (no facing planes, cylinders or cones)")
    return dims


def _plane_distance(a: Fit, b: Fit, pa: np.ndarray, pb: np.ndarray, at: np.ndarray) -> float:
    """Distance (mm) between two nearly parallel planes along their mean normal through the point `at` (the
    centroid of the smaller face, so that the mean over the common area is what counts, not a tilt's lever arm)."""
    (qa, na), (qb, nb) = a.point_axis(pa), b.point_axis(pb)
    m = na + np.sign(na @ nb) * nb
    m /= np.linalg.norm(m)
    return float(abs((qa - at) @ na / (m @ na) - (qb - at) @ nb / (m @ nb)))


def _pair_kind(a: Plane, b: Plane) -> tuple[str, Plane, Plane] | None:
    """("distance", a, b) for antiparallel planes over a common area; ("depth", upper, lower) for a plane recessed
    within a parallel one (seen through a hole in it); else None. Judged on the nominal geometry when there is one."""
    (qa, na), (qb, nb) = (a.nominal or a.fit).point_axis(), (b.nominal or b.fit).point_axis()
    if abs(na @ nb) < np.cos(np.radians(1.0)):
        return None
    basis = np.stack(prim.perpendicular_basis(na), axis=1)

    def overlap(upper: Plane, lower: Plane) -> float:
        near = cKDTree(upper.geo_all @ basis).query(lower.geo_inner @ basis, distance_upper_bound=1.0)[0] < 1.0
        return float(np.mean(near))

    if na @ nb < 0:
        return ("distance", a, b) if max(overlap(a, b), overlap(b, a)) > 0.05 else None
    upper, lower = (a, b) if (qa - qb) @ na > 0 else (b, a)
    inner, area = lower.geo_inner @ basis, upper.geo_all @ basis
    inside = np.all((inner.mean(axis=0) > area.min(axis=0)) & (inner.mean(axis=0) < area.max(axis=0)))
    recessed = abs((qa - qb) @ na) > 0.1
    return ("depth", upper, lower) if recessed and inside and overlap(upper, lower) < 0.01 else None


def _pair_dimensions(planes: list[Plane], unc: dict[str, float], base_is_closure: bool) -> list[Dimension]:
    dims = []
    for a, b in combinations(planes, 2):
        pair = _pair_kind(a, b)
        if pair is not None:
            dims.append(_distance(pair[1], pair[2], unc, base_is_closure, "depth; " if pair[0] == "depth" else ""))
    return dims


def _distance(a: Plane, b: Plane, unc: dict[str, float], base_is_closure: bool, note: str = "") -> Dimension:
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
        unc = _with_base(unc)
    u_fit = prim.propagate(dist, [a.fit, b.fit])
    return dimension(f"{a.name} to {b.name}", "distance", value, u_fit, unc, [a.fit, b.fit], nominal, note)


def _with_base(unc: dict[str, float]) -> dict[str, float]:
    """The uncertainty terms of a dimension that ends on the base closed on the support plane: u_model grows by the
    base's own standard uncertainty (`u_base_mm`, from `vio model`'s two estimates of the plane)."""
    return {**unc, "u_model_mm": float(np.hypot(unc["u_model_mm"], unc.get("u_base_mm", 0.0)))}


def _countersink_diameter(cone: Fit, plane: Fit, pc: np.ndarray, pp: np.ndarray) -> float:
    """Diameter (mm) of the circle where a cone meets a plane across its axis."""
    (apex, axis), (q, n) = cone.point_axis(pc), plane.point_axis(pp)
    return float(2.0 * ((q - apex) @ n) / (axis @ n) * np.tan(pc[5]))


def _curved_dimensions(curved: list[Curved], unc: dict[str, float]) -> list[Dimension]:
    dims = []
    for c in curved:
        f, nom = c.fit, c.nominal
        if f.kind == "cylinder":
            factor, kind = (2.0, "diameter") if c.full else (1.0, "radius")
            value, u = factor * f.params[4], factor * np.sqrt(f.cov[4, 4])
            nominal = None if nom is None else factor * nom.params[4]
            dims.append(dimension(c.name, kind, value, u, unc, [f], nominal))
            continue
        value, u = 2.0 * np.degrees(f.params[5]), 2.0 * np.degrees(np.sqrt(f.cov[5, 5]))
        nominal = None if nom is None else 2.0 * np.degrees(nom.params[5])
        dims.append(dimension(f"{c.name} included angle", "angle", value, u, unc, [f], nominal))
        if c.plane is not None:
            p = c.plane

            def dia(params: list[np.ndarray], f: Fit = f, p: Plane = p) -> float:
                return _countersink_diameter(f, p.fit, params[0], params[1])

            value, u = dia([f.params, p.fit.params]), prim.propagate(dia, [f, p.fit])
            nominal = None if nom is None else _countersink_diameter(nom, p.nominal, nom.params, p.nominal.params)
            note = f"where the cone meets {p.name}"
            dims.append(dimension(f"{c.name} diameter", "diameter", value, u, unc, [f, p.fit], nominal, note))
    return dims


def _detect_features(
    pts: np.ndarray, nrm: np.ndarray, cfg: MeasureConfig, rng: np.random.Generator
) -> tuple[list[Plane], list[Curved]]:
    """Without a CAD: planar faces by normal clustering, then cylinders by RANSAC on the points no face took."""
    min_count = max(100, int(cfg.min_plane_fraction * len(pts)))
    faces = extract_planes(pts, nrm, rng, min_count, cfg.band_mm, cfg.edge_margin_mm, cfg.cluster_deg)
    planes = [Plane(plane_name(f), f, pts[inner], None, pts[inner], pts[inner]) for f, _, inner in faces]
    free = np.ones(len(pts), bool)
    for _, members, _ in faces:
        free[members] = False
    idx = np.flatnonzero(free)
    noise_mm = float(np.median([f.rms_mm for f, _, _ in faces])) if faces else 0.05
    found = ransac_cylinders(pts[idx], nrm[idx], rng, max(200, int(0.005 * len(pts))), max(0.15, 6 * noise_mm))
    full = [prim.angular_coverage_deg(f, pts[idx[inl]]) >= 300.0 for f, inl in found]
    return planes, [Curved(curved_name(f), f, None, c) for (f, _), c in zip(found, full, strict=True)]


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
    axes = box_faces(pts, nrm, rng, cfg.band_mm, cfg.edge_margin_mm)
    nominal_axes = None
    if cad is not None:
        s, sn, _ = prim.sample_surface(cad.vertices, cad.faces, 20000, rng)  # noise-free: plenty for planes
        nominal_axes = box_faces(s, sn, rng, cfg.band_mm, cfg.edge_margin_mm)
    dims, fits, nominal_fits = [], [], []
    for g in axes:
        nom = None if nominal_axes is None else max(nominal_axes, key=lambda h: abs(h[0] @ g[0]))
        if nom is not None and nom[0] @ g[0] < 0:
            nom = [-nom[0], nom[2], nom[1]]
        planes = []
        for side in (1, 2):
            f = g[side]
            nf = None if nom is None or nom[side] is None else nom[side][0]
            planes.append(None if f is None else Plane(plane_name(f[0]), f[0], pts[f[2]], nf, pts[f[2]], pts[f[2]]))
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
        dims.append(dimension(f"box {axis}: {present.name} to the side faces' end", "distance", value, u_fit, unc,
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
            to_base = base_is_closure and abs(axes[i][0][2]) > 0.99  # vertical edges end on the base
            edge_unc = _with_base(unc) if to_base else unc
            dims.append(dimension(f"box edge {axis}", "length", value, u, edge_unc, fits, nominal, "mean of 4 edges"))
    return dims
