"""Rigid registration of a model (mesh vertices, surface samples or a point cloud) to its CAD: no scale, on purpose.

A scale error of the reconstruction must show in the deviations, not be absorbed by the alignment. Frames: the
model's own frame (whatever the file is in, converted to millimetres by the caller) and the CAD's frame (mm); the
result is `cad_T_model`.

Coarse: the oriented bounding boxes (and, for shapes whose box is ambiguous, the principal axes) of model and CAD,
with every proper rotation that maps one box's axes onto the other's (24; those whose extents disagree are pruned),
each refined by a few point-to-plane ICP iterations against samples of the CAD; the best is kept. Fine: robust
point-to-plane ICP against the exact closest points of the CAD surface (`vio.model.closest`). The points are first
thinned to an even density (one per cell of 1 % of their box's diagonal), so that a rough face does not outweigh
a smooth one by its larger area.
"""

from __future__ import annotations

import itertools
import logging
import warnings
from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from vio.errors import ModelError
from vio.model.closest import SurfaceIndex, build_index, closest_points, nearest_samples

log = logging.getLogger(__name__)

_FINALISTS = 4  # coarse candidates refined further after the first few iterations
_HUBER = 1.345  # Huber's threshold in robust scales (95 % efficiency for Gaussian noise)
_MIN_SIGMA_MM = 0.5  # floor of the robust scale: deviations of a few tenths (a scale error, a face a little
# off) are weighed as least squares; at 0.05 mm the fit was nearly L1 and faces pulled by their point counts
_EXACT_ITERATIONS = 5  # the last ICP iterations, against exact closest points (0.1-0.25 s each for 20k points)
_MIN_REJECT_MM = 2.0  # deviations within this of the median are the part's, never rejected: when the sides of a
# box fit to 0.3 mm, 6 robust scales rejected a top and bottom 0.7 mm off, and the box slid 8 mm along its height
_EVEN_CELL = 0.01  # points thinned to one per cell of this share of their box's diagonal: a rough face (a
# wrinkled marching-cubes top has twice a flat face's area) must not outweigh the others


@dataclass(frozen=True)
class Registration:
    """The rigid transform that puts the model on its CAD, and how well it fits."""

    cad_T_model: np.ndarray  # (4, 4) rigid, model frame (mm) -> CAD frame (mm)
    rms_mm: float  # RMS point-to-surface distance of the inliers, mm
    inlier_fraction: float  # share of the points within max(`reject_sigma` robust scales, 2 mm) of the median residual
    iterations: int  # fine ICP iterations run
    candidate: str  # the coarse candidate chosen, e.g. "obb/7" (frame kind / rotation index of 24)
    num_candidates: int  # coarse candidates refined (after pruning by extents)
    coarse_rms_mm: float  # RMS of the best 90 % of the chosen candidate's residuals after its short ICP, mm


def box_rotations() -> np.ndarray:
    """(24, 3, 3) the proper rotations that map the coordinate axes onto themselves (signed permutations, det +1)."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            r = np.zeros((3, 3))
            r[np.arange(3), perm] = signs
            if np.linalg.det(r) > 0:
                out.append(r)
    return np.array(out)


def register(
    model_points_mm: np.ndarray,
    cad: trimesh.Trimesh,
    *,
    index: SurfaceIndex | None = None,
    rng: np.random.Generator | None = None,
    reject_sigma: float = 6.0,
    fine_points: int = 20_000,
    coarse_points: int = 1_000,
    coarse_iterations: int = 10,
    max_iterations: int = 50,
) -> Registration:
    """Register model points (N, 3), mm, in the model's frame, to the CAD mesh (mm, CAD frame); rigid only.

    `index` is the CAD's `SurfaceIndex` if the caller has one (it is built otherwise). ICP is robust: residuals are
    weighed by Huber's function and those more than `reject_sigma` robust scales from the median are ignored (see
    `_icp`); it runs on random subsets of `coarse_points` / `fine_points`.
    """
    points = np.asarray(model_points_mm, dtype=np.float64)
    points = points[np.isfinite(points).all(axis=1)]
    if len(points) < 10:
        raise ModelError(f"the model has {len(points)} finite points; at least 10 are needed to register it")
    spread = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)  # (3,) along the principal axes
    if spread[1] <= 1e-6 * spread[0] or spread[0] == 0.0:
        where = "at one point" if spread[0] == 0.0 else "on a line"
        raise ModelError(f"the model's {len(points)} points all lie {where}: no surface to register to the CAD")
    rng = rng if rng is not None else np.random.default_rng(0)
    index = index if index is not None else build_index(cad.vertices, cad.faces)
    points = _even(points, _EVEN_CELL * float(np.linalg.norm(np.ptp(points, axis=0))), rng)
    fine = points[rng.choice(len(points), min(fine_points, len(points)), replace=False)]
    coarse = fine[rng.choice(len(fine), min(coarse_points, len(fine)), replace=False)]
    candidates = _candidates(fine, np.asarray(cad.vertices, dtype=np.float64))
    scored = []
    for name, cad_T_model in candidates:  # a few iterations each, then the best few go on
        refined, _, score, _, _ = _icp(coarse, index, cad_T_model, 4, reject_sigma, exact=False, level=1)
        scored.append((score, name, refined))
    scored.sort(key=lambda s: s[0])
    finalists = []
    for _, name, cad_T_model in scored[:_FINALISTS]:
        refined, _, score, _, _ = _icp(coarse, index, cad_T_model, coarse_iterations, reject_sigma, False, level=1)
        finalists.append((score, name, refined))
    coarse_rms, name, cad_T_model = min(finalists, key=lambda s: s[0])
    log.debug("coarse: %d candidates, best %s with RMS %.3f mm (best 90 %%)", len(scored), name, coarse_rms)
    # Fine: against the planes of the nearest CAD samples until converged, then against the exact closest points.
    cad_T_model, _, _, _, it_near = _icp(fine, index, cad_T_model, max_iterations, reject_sigma, exact=False)
    cad_T_model, rms, _, inliers, it_exact = _icp(fine, index, cad_T_model, _EXACT_ITERATIONS, reject_sigma, True)
    iterations = it_near + it_exact
    log.info("registered %d points: RMS %.4f mm after %d iterations (from %s)", len(points), rms, iterations, name)
    return Registration(cad_T_model, rms, inliers, iterations, name, len(scored), coarse_rms)


def _even(points: np.ndarray, cell: float, rng: np.random.Generator) -> np.ndarray:
    """One point (a random one) per occupied cube of edge `cell` (same units): about even density over the surface."""
    if not cell > 0:
        return points
    order = rng.permutation(len(points))
    keys = np.floor(points[order] / cell).astype(np.int64)
    return points[order[np.unique(keys, axis=0, return_index=True)[1]]]


def _frames(points: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """{kind: (box_T_frame (4, 4), extents (3,))} for the oriented bounding box and the principal axes.

    Points in a plane (a scan of one face) have no hull volume: trimesh then warns or, for some inputs, fails in
    Qhull, and the principal axes alone are used."""
    out = {}
    try:
        with warnings.catch_warnings(), np.errstate(all="ignore"):
            warnings.simplefilter("ignore", RuntimeWarning)
            to_box, extents = trimesh.bounds.oriented_bounds(points)
        if np.isfinite(to_box).all() and np.isfinite(extents).all():
            out["obb"] = (np.asarray(to_box, dtype=np.float64), np.asarray(extents, dtype=np.float64))
    except Exception as exc:  # scipy's QhullError and trimesh's errors on flat or tiny point sets
        log.debug("no oriented bounding box (%s: %s); principal axes only", type(exc).__name__, exc)
    centre = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centre, full_matrices=False)
    if np.linalg.det(vt) < 0:
        vt[2] *= -1
    to_pca = np.eye(4)
    to_pca[:3, :3], to_pca[:3, 3] = vt, -vt @ centre
    local = (points - centre) @ vt.T
    out["pca"] = (to_pca, local.max(axis=0) - local.min(axis=0))
    return out


def _candidates(model: np.ndarray, cad_vertices: np.ndarray) -> list[tuple[str, np.ndarray]]:
    """Coarse cad_T_model candidates: each frame kind's box of model and CAD, under the 24 box rotations."""
    out = []
    rotations = box_rotations()
    cad_frames = _frames(cad_vertices)
    for kind, (modelbox_T_model, model_ext) in _frames(model).items():
        if kind not in cad_frames:
            continue
        cadbox_T_cad, cad_ext = cad_frames[kind]
        mismatch = np.array([np.abs(np.abs(r) @ model_ext - cad_ext).max() for r in rotations]) / cad_ext.max()
        keep = np.flatnonzero(mismatch <= mismatch.min() + 0.05)
        for k in keep:
            r = np.eye(4)
            r[:3, :3] = rotations[k]
            out.append((f"{kind}/{k}", np.linalg.inv(cadbox_T_cad) @ r @ modelbox_T_model))
    return out


def _icp(
    points: np.ndarray,
    index: SurfaceIndex,
    cad_T_model: np.ndarray,
    iterations: int,
    reject_sigma: float,
    exact: bool,
    level: int = 0,
) -> tuple[np.ndarray, float, float, float, int]:
    """Robust point-to-plane ICP (IRLS). Returns (cad_T_model, RMS of the inliers mm, trimmed RMS mm (the best 90 %,
    to rank candidates), inlier share, iterations run).

    Residuals are weighed by Huber's function of their distance from the median residual (scale: 1.4826 MAD, at
    least `_MIN_SIGMA_MM`) and rejected beyond `reject_sigma` scales (and at least `_MIN_REJECT_MM`). About the
    median, not zero: a model with a systematic offset (a scale error) is not tilted to shed its worst side, as
    trimming the worst share would do.
    exact=False pairs each point with a near CAD sample (`nearest_samples`, no finer than `level`) and that sample's
    face plane: fast, for the first iterations; exact=True with its exact closest point on the CAD and the plane of
    that face.
    """
    cad_T_model = cad_T_model.copy()
    rms, score, share, it = np.inf, np.inf, 0.0, 0
    while it < iterations:
        it += 1
        p = points @ cad_T_model[:3, :3].T + cad_T_model[:3, 3]
        if exact:
            _, q, face = closest_points(index, p)
        else:
            q, face = nearest_samples(index, p, finest=level)
        n = index.normals[face]
        r = np.einsum("ij,ij->i", p - q, n)
        spread = np.abs(r - np.median(r))
        sigma = max(1.4826 * float(np.median(spread)), _MIN_SIGMA_MM)
        inlier = spread <= max(reject_sigma * sigma, _MIN_REJECT_MM)
        weight = np.where(spread <= _HUBER * sigma, 1.0, _HUBER * sigma / np.maximum(spread, 1e-12))[inlier]
        rms, share = float(np.sqrt(np.mean(r[inlier] ** 2))), float(inlier.mean())
        score = float(np.sqrt(np.mean(np.sort(r**2)[: max(1, int(0.9 * len(r)))])))
        a = np.hstack([np.cross(p[inlier], n[inlier]), n[inlier]])
        h = a.T @ (a * weight[:, None])
        h += 1e-9 * np.trace(h) * np.eye(6)  # keeps unobservable directions (a cylinder's axis) at zero
        x = np.linalg.solve(h, -a.T @ (weight * r[inlier]))
        step = np.eye(4)
        step[:3, :3], step[:3, 3] = Rotation.from_rotvec(x[:3]).as_matrix(), x[3:]
        cad_T_model = step @ cad_T_model
        if np.linalg.norm(x[:3]) < 1e-7 and np.linalg.norm(x[3:]) < 1e-5:  # rad, mm
            break
    return cad_T_model, rms, score, share, it
