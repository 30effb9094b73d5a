"""The CAD's faces grouped into regions for `vio measure` "auto" with a CAD: planes, and cylinders and cones (whose
normals turn about one axis; anything else is freeform and not measured). Each region's primitive is fitted on the
CAD's samples (the nominal) and on the model points near the region's interior (the measured), in the CAD's frame.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from vio.model import primitives as prim
from vio.model.measure_report import curved_name, plane_name
from vio.model.primitives import Fit

if TYPE_CHECKING:
    import trimesh

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Plane:
    """A planar face: the model's fit, its nominal (CAD) fit, and points for pairing (all / interior)."""

    name: str
    fit: Fit
    pts: np.ndarray  # (N, 3) model points of the fit
    nominal: Fit | None
    geo_all: np.ndarray  # (M, 3) points of the face (CAD samples, or the model's without CAD)
    geo_inner: np.ndarray  # (K, 3) interior points of the face


@dataclass(frozen=True)
class Curved:
    """A fitted cylinder or cone, with its nominal fit and, for a cone, the plane across its axis."""

    name: str
    fit: Fit  # model fit, kind "cylinder" or "cone"
    nominal: Fit | None
    full: bool  # closed around its axis (a bore: diameter), or partial (a groove, a fillet: radius)
    plane: Plane | None = None  # for a cone: the face it opens into (countersink diameter)


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


def cad_features(
    pts: np.ndarray,
    nrm: np.ndarray,
    cad: trimesh.Trimesh,
    rng: np.random.Generator,
    *,
    band_mm: float,
    edge_margin_mm: float,
    normal_deg: float,
    cad_samples_per_mm2: float,
    max_fit_points: int,
) -> tuple[list[Plane], list[Curved]]:
    """The CAD's planes, cylinders and cones, each fitted on the CAD's samples (nominal) and on the model points
    near the region's interior (measured). pts (N, 3) mm in the CAD's frame, nrm (N, 3) unit outward; the keyword
    arguments are those of `vio.model.measure.MeasureConfig`."""
    label_f, n_planes, edges, pairs = _cad_regions(cad)
    s, sn, face = prim.sample_surface(cad.vertices, cad.faces, int(cad.area * cad_samples_per_mm2), rng)
    lab = label_f[face]
    ev = cad.vertices[edges]
    steps = np.maximum(np.ceil(np.linalg.norm(ev[:, 1] - ev[:, 0], axis=1) / 0.25).astype(int), 1) + 1
    t = np.concatenate([np.linspace(0.0, 1.0, k) for k in steps])[:, None]
    e0, e1 = np.repeat(ev[:, 0], steps, axis=0), np.repeat(ev[:, 1], steps, axis=0)
    cap = edge_margin_mm / 0.3  # margins depend on distances below this only; a bounded search is fast
    to_edge = np.minimum(cKDTree(e0 + t * (e1 - e0)).query(s, distance_upper_bound=cap, workers=1)[0], cap)
    inradius = np.zeros(label_f.max() + 1)
    np.maximum.at(inradius, lab, to_edge)
    interior = to_edge > np.minimum(edge_margin_mm, 0.3 * inradius)[lab]
    nearest = cKDTree(s).query(pts, workers=1)[1]
    model_lab = np.where(interior[nearest], lab[nearest], -1)
    aligned = np.abs(np.einsum("ij,ij->i", nrm, sn[nearest])) > np.cos(np.radians(normal_deg))
    by_label = _group(lab, len(inradius))
    model_by_label = _group(np.where(aligned, model_lab, len(inradius)), len(inradius))
    planes: dict[int, Plane] = {}
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
        sel = sel[np.abs(nominal.residuals(pts[sel])) < band_mm]
        name = plane_name(nominal) if k < n_planes else curved_name(nominal)
        if len(sel) < 20:
            log.warning("%s: only %d model points near the CAD's feature; not measured", name, len(sel))
            continue
        if k < n_planes:
            planes[k] = Plane(name, prim.fit_plane(pts[sel], nominal.ref[1]), pts[sel], nominal, s[region], s[ins])
            continue
        sub = sel[rng.choice(len(sel), size=min(len(sel), max_fit_points), replace=False)]
        fit = (prim.fit_cylinder if nominal.kind == "cylinder" else prim.fit_cone)(pts[sub], init=nominal)
        curved.append((k, name, fit, nominal, prim.angular_coverage_deg(nominal, s[region]) >= 300.0))
    out = []
    for k, name, fit, nominal, full in curved:
        across = [planes[j] for j in planes if tuple(sorted((j, k))) in pairs]
        across = [p for p in across if abs(p.nominal.ref[1] @ nominal.point_axis()[1]) > np.cos(np.radians(2.0))]
        apex, axis = nominal.point_axis()
        plane = max(across, key=lambda p: (p.nominal.ref[0] - apex) @ axis, default=None)
        out.append(Curved(name, fit, nominal, full, plane if nominal.kind == "cone" else None))
    return list(planes.values()), out
