"""Fuse depth maps into a truncated signed distance field over the region of interest, with free-space carving.

The grid is axis-aligned in the support frame (`Roi.world_T_support`: z up from the plane), voxel centres at `origin
+ index * voxel_m`, with the plane on a voxel boundary. Each voxel is projected into every view (nearest pixel).
Within the truncation distance of the depth it takes the projective signed distance (depth - voxel z-depth, weighted
by the depth map's confidence and the cosine of the viewing angle); in front of the depth by more than the
truncation it gets a free-space vote, behind it by more than the truncation a behind vote; a pixel without depth is
no evidence either way, except in a small hole of a surface (inside the closing of the known pixels, `hole_px`),
where a voxel behind the largest depth around the hole is behind it (stereo leaves holes in the faces: without this
their voxels would be unknown in the views that see the face and dent it). Holes up to about 2 `fill_px` pixels
across in a smooth surface (the textureless interiors of speckle dots, the same in every view that faces them) are
first filled with the least-squares plane through the depths around them, at a fraction of a measured depth's
weight: without that, where every view has the same hole the surface is only bounded to within the truncation
distance (bumps and dents of about 1.5 mm on the cube's faces). Holes along a convex edge, whose rim is two planes
(the NCC windows straddling an edge match neither face), take the farther of the two planes (`fill_creases`). The
field is then: the weighted average (free votes count as +1) where a surface was observed near it; elsewhere inside
only with positive evidence, i.e. behind an observed surface in at least one view, in at least as many views as saw
no depth at its pixel, and seen through by fewer than `min_free_views` views (the part's interior, and cavities the
cameras cannot see into, such as an undercut slot: every view that looks at them sees the part in front); outside
otherwise: seen through, or never observed (a table without depth stays outside; the part's "shadow" on it is behind
the part from one side only, without depth from the other); outside below the support plane, so the part's base
closes on the plane. In the lowest `base_band_m` above the plane, a voxel that no depth measured takes the side of
the voxel above it at that height (`_base_columns`): beside the base the table is seen at grazing angles and gives
no depth, so by votes alone the space there was solid (a flap along the base). Two passes: a coarse grid finds the
band around the surface and the occupancy elsewhere, then the band alone is fused at `voxel_m`.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from vio.errors import ModelError
from vio.model.records import DepthMap, Roi, View

log = logging.getLogger(__name__)

_CHUNK = 1 << 20  # voxels integrated per block (bounds the temporaries at ~40 MB)
_MIN_COS = np.float32(0.05)  # floor of the viewing-angle weight: grazing views still count a little
_DIFF = np.array([[-0.5, 0.0, 0.5]], np.float32)  # central difference


@dataclass(frozen=True)
class FusedVolume:
    """The fused field on a grid in the support frame. > 0 outside the part, < 0 inside, |value| <= 1."""

    tsdf: np.ndarray  # (nx, ny, nz) float32: signed distance / trunc_m, clipped to [-1, 1]
    origin: np.ndarray  # (3,) centre of voxel (0, 0, 0) in the support frame, m
    voxel_m: float  # voxel edge, m
    trunc_m: float  # truncation distance, m
    roi: Roi  # the region fused; roi.world_T_support maps the grid's frame to world

    def support_points(self, ijk: np.ndarray) -> np.ndarray:
        """(N, 3) support-frame positions (m) of (fractional) grid indices (N, 3)."""
        return self.origin + np.asarray(ijk, dtype=np.float64) * self.voxel_m


@dataclass
class _Accumulator:
    """Per-voxel sums: weighted signed distance / truncation and its weight near a surface, free-space weight and
    votes, and the votes of views that saw it behind a surface or saw no depth at its pixel."""

    sdf: np.ndarray
    weight: np.ndarray
    free_weight: np.ndarray
    free: np.ndarray
    behind: np.ndarray
    unknown: np.ndarray

    @classmethod
    def zeros(cls, n: int) -> _Accumulator:
        return cls(*(np.zeros(n, np.float32) for _ in range(3)), *(np.zeros(n, np.uint16) for _ in range(3)))

    def field(self, min_free_views: int) -> np.ndarray:
        """Signed field in [-1, 1]: where a surface was seen near the voxel, the weighted average of its signed
        distances and its free votes (+1 each); elsewhere -1 (inside) if at least one view saw it behind a surface,
        at least as many views saw it behind as saw no depth there, and fewer than `min_free_views` saw through it;
        else +1 (outside: seen through, or no evidence)."""
        inside = (self.behind > 0) & (self.behind >= self.unknown) & (self.free < min_free_views)
        out = np.where(inside, np.float32(-1.0), np.float32(1.0))
        near = self.weight > 0
        w_free = self.free_weight[near]
        out[near] = (self.sdf[near] + w_free) / (self.weight[near] + w_free)
        return out


def despeckle(depth_m: np.ndarray, speckle_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(depth, valid, median): a float32 copy of a depth image (m) with unknown pixels and isolated outliers (more
    than `speckle_m` from the 3x3 median) set to NaN, the mask of the others, and the 3x3 median itself."""
    d = np.array(depth_m, dtype=np.float32)
    valid = np.isfinite(d) & (d > 0)
    d[~valid] = 0.0
    med = cv2.medianBlur(d, 3)
    valid &= np.abs(d - med) <= speckle_m
    d[~valid] = np.nan
    return d, valid, med


def _closing(valid: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """Morphological closing of the known pixels: a hole in a surface is inside it, the background beyond a
    silhouette is not."""
    return cv2.erode(cv2.dilate(valid.astype(np.uint8), kernel), kernel, borderValue=1).astype(bool)


def fill_holes(
    d: np.ndarray, valid: np.ndarray, radius_px: float, max_rms_m: float, creases: bool = False
) -> np.ndarray:
    """Mask of the small holes of a depth image that lie in a plane, filled in `d` in place with that plane.

    A hole is a connected set of unknown pixels inside the morphological closing of the known ones (a square of
    2 `radius_px` + 1 pixels). Its rim is the known pixels within 2 pixels of it; when the rim's depths fit a plane
    z = a + b u + c v within `max_rms_m` RMS (a hole in a face, not a gap between a silhouette and the background),
    the hole takes that plane's depths. Exact on planes whatever their slant; only the rim is used, so a nearby
    edge or the table does not stop a hole in a face from being filled. With `creases`, a hole whose rim is not
    one plane but two meeting at a convex edge inside it takes the farther of the two (`_fill_creases`)."""
    r = int(round(radius_px))
    holes = np.zeros_like(valid)
    if r < 1:
        return holes
    kernel = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
    closed = _closing(valid, kernel)
    lab, n = ndimage.label(closed & ~valid)
    if n == 0:
        return holes
    rim = np.where(valid, ndimage.grey_dilation(lab, size=(5, 5)), 0)
    rr, rc = np.nonzero(rim)
    comp = rim[rr, rc]
    zc = np.float64(np.median(d[valid]))
    z = d[rr, rc].astype(np.float64) - zc
    u, v = rc.astype(np.float64), rr.astype(np.float64)
    mean_u = np.bincount(comp, u, n + 1) / np.maximum(np.bincount(comp, None, n + 1), 1)
    mean_v = np.bincount(comp, v, n + 1) / np.maximum(np.bincount(comp, None, n + 1), 1)
    u, v = u - mean_u[comp], v - mean_v[comp]  # per hole, centred on its rim: well conditioned

    def moment(w: np.ndarray | None) -> np.ndarray:
        return np.bincount(comp, w, n + 1)

    cnt, su, sv, sz = moment(None), moment(u), moment(v), moment(z)
    suu, suv, svv, suz, svz, szz = (
        moment(u * u),
        moment(u * v),
        moment(v * v),
        moment(u * z),
        moment(v * z),
        moment(z * z),
    )
    A = np.stack([np.stack([cnt, su, sv], -1), np.stack([su, suu, suv], -1), np.stack([sv, suv, svv], -1)], -2)
    A += np.eye(3) * 1e-6 * np.maximum(cnt, 1.0)[:, None, None]
    b = np.stack([sz, suz, svz], -1)
    coef = np.linalg.solve(A, b[..., None])[..., 0]
    rms = np.sqrt(np.maximum(szz - (coef * b).sum(-1), 0.0) / np.maximum(cnt, 1.0))
    good = (cnt >= 8) & (rms <= max_rms_m)
    good[0] = False
    hr, hc = np.nonzero(lab)
    hl = lab[hr, hc]
    keep = good[hl]
    kr, kc, kl = hr[keep], hc[keep], hl[keep]
    c = coef[kl]
    d[kr, kc] = (zc + c[:, 0] + c[:, 1] * (kc - mean_u[kl]) + c[:, 2] * (kr - mean_v[kl])).astype(np.float32)
    holes[kr, kc] = True
    if creases:
        _fill_creases(d, valid, holes, lab, n, ~good & (cnt >= 8), (hr, hc, hl), max_rms_m)
    return holes


_CREASE_MIN_SIDE = 12  # rim pixels on each face of a crease
_CREASE_RIM_PX = 4  # a crease's rim: the known pixels this close to its hole (a wider base for the two slopes)
_CREASE_TRIALS = 32  # RANSAC samples per plane
_CREASE_SAMPLE_PX = 8  # a sample's three pixels lie this close (city-block) to each other


def _fill_creases(
    d: np.ndarray,
    valid: np.ndarray,
    holes: np.ndarray,
    lab: np.ndarray,
    n: int,
    candidate: np.ndarray,
    pixels: tuple[np.ndarray, np.ndarray, np.ndarray],
    max_rms_m: float,
) -> None:
    """Holes whose rim is two planes meeting inside the hole at a convex edge (the NCC windows straddling an edge
    of the part match neither face) take the farther of the two planes (a ray meets a convex solid where it has
    entered every face's half-space). Convex: each plane is the farther one on its own side of the rim. Two planes
    whose difference keeps one sign over the whole rim (a silhouette in front of the table) are not a crease, and
    concave creases are left open too: on the simulated cube most of them are the part's foot on the table, whose
    stereo depth spreads 3 mm, and filling them raised flaps along the base (seed 102 std 0.065 -> 0.073 mm, 103
    a +1.7 mm flap), which the base columns (`_base_columns`) handle better. Planes in inverse depth (exact for
    planes); one by RANSAC (seeded by the hole's label), the other by RANSAC on the rest of the rim (the known pixels
    within _CREASE_RIM_PX of the hole)."""
    k = 2 * _CREASE_RIM_PX + 1
    rim = np.where(valid, ndimage.grey_dilation(np.where(candidate[lab], lab, 0), size=(k, k)), 0)
    rr, rc = np.nonzero(rim)
    comp = rim[rr, rc]
    hr, hc, hl = pixels
    (ids,) = np.nonzero(candidate)
    if ids.size == 0:
        return
    rim_order, hole_order = np.argsort(comp, kind="stable"), np.argsort(hl, kind="stable")
    rim_start = np.searchsorted(comp[rim_order], np.arange(n + 2))
    hole_start = np.searchsorted(hl[hole_order], np.arange(n + 2))
    for i in ids:
        r_idx = rim_order[rim_start[i] : rim_start[i + 1]]
        h_idx = hole_order[hole_start[i] : hole_start[i + 1]]
        u, v = rc[r_idx].astype(np.float64), rr[r_idx].astype(np.float64)
        z = d[rr[r_idx], rc[r_idx]].astype(np.float64)
        if len(z) < 2 * _CREASE_MIN_SIDE:
            continue
        planes = _two_planes(u, v, z, max_rms_m, np.random.default_rng(int(i)))
        if planes is None:
            continue
        pa, pb, on_a, on_b = planes
        diff = 1.0 / _plane_z(pa, u, v) - 1.0 / _plane_z(pb, u, v)
        sa, sb = np.mean(diff[on_a] > 0), np.mean(diff[on_b] > 0)
        if not (sa >= 0.8 and sb <= 0.2):  # a's face is the farther one on its side and b's on its: convex
            continue
        hu, hv = hc[h_idx].astype(np.float64), hr[h_idx].astype(np.float64)
        fill = np.maximum(1.0 / _plane_z(pa, hu, hv), 1.0 / _plane_z(pb, hu, hv))
        if not np.all(np.isfinite(fill) & (fill > 0)):
            continue
        d[hr[h_idx], hc[h_idx]] = fill.astype(np.float32)
        holes[hr[h_idx], hc[h_idx]] = True


def _plane_z(p: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return p[0] + p[1] * u + p[2] * v


def _fit_plane(u: np.ndarray, v: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, float]:
    """Inverse depth rho = p0 + p1 u + p2 v (exact for a plane seen by a pinhole camera), least squares in rho
    weighted by z^2 (so in depth to first order), and the RMS of its depths' errors."""
    A = np.column_stack([np.ones_like(u), u - u.mean(), v - v.mean()])
    c = np.linalg.lstsq(A * (z * z)[:, None], z, rcond=None)[0]  # (A c - 1/z) z^2 ~ depth error
    with np.errstate(divide="ignore"):
        rms = float(np.sqrt(np.mean((1.0 / (A @ c) - z) ** 2)))
    return np.array([c[0] - c[1] * u.mean() - c[2] * v.mean(), c[1], c[2]]), rms


def _ransac_plane(
    u: np.ndarray, v: np.ndarray, z: np.ndarray, tol_m: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray] | None:
    """(inverse-depth plane, inlier mask) of the largest plane among z(u, v): each sample is three pixels within
    _CREASE_SAMPLE_PX of each other (so from one face), the best refitted to its inliers twice."""
    best, best_count = None, 0
    for _ in range(_CREASE_TRIALS):
        s = int(rng.integers(len(z)))
        (near,) = np.nonzero(np.abs(u - u[s]) + np.abs(v - v[s]) <= _CREASE_SAMPLE_PX)
        if near.size < 3:
            continue
        idx = np.r_[s, rng.choice(near[near != s], 2, replace=False)]
        A = np.column_stack([np.ones(3), u[idx], v[idx]])
        if abs(np.linalg.det(A)) < 1e-6:
            continue
        p = np.linalg.solve(A, 1.0 / z[idx])
        with np.errstate(divide="ignore", invalid="ignore"):
            count = int(np.count_nonzero(np.abs(1.0 / _plane_z(p, u, v) - z) <= tol_m))
        if count > best_count:
            best, best_count = p, count
    if best is None:
        return None
    for _ in range(2):
        with np.errstate(divide="ignore", invalid="ignore"):
            inl = np.abs(1.0 / _plane_z(best, u, v) - z) <= tol_m
        if inl.sum() < 3:
            return None
        best = _fit_plane(u[inl], v[inl], z[inl])[0]
    with np.errstate(divide="ignore", invalid="ignore"):
        return best, np.abs(1.0 / _plane_z(best, u, v) - z) <= tol_m


def _two_planes(
    u: np.ndarray, v: np.ndarray, z: np.ndarray, max_rms_m: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """(plane a, plane b, masks of the rim pixels on a and on b) for rim depths z(u, v) that are two planes, each
    holding at least _CREASE_MIN_SIDE pixels and fitting them within max_rms_m RMS, together at least 90 % of the
    rim; None otherwise."""
    first = _ransac_plane(u, v, z, 2.0 * max_rms_m, rng)
    if first is None or first[1].sum() < _CREASE_MIN_SIDE:
        return None
    rest = np.flatnonzero(~first[1])
    if rest.size < _CREASE_MIN_SIDE:
        return None
    second = _ransac_plane(u[rest], v[rest], z[rest], 2.0 * max_rms_m, rng)
    if second is None or second[1].sum() < _CREASE_MIN_SIDE:
        return None
    on_a, on_b = first[1], np.zeros_like(first[1])
    on_b[rest[second[1]]] = True
    if on_a.sum() + on_b.sum() < 0.9 * len(z):
        return None
    pa, rms_a = _fit_plane(u[on_a], v[on_a], z[on_a])
    pb, rms_b = _fit_plane(u[on_b], v[on_b], z[on_b])
    if max(rms_a, rms_b) > max_rms_m:
        return None
    return pa, pb, on_a, on_b


def prepare_depth(
    view: View,
    depth: DepthMap,
    speckle_m: float,
    step: int = 1,
    window: tuple[slice, slice] | None = None,
    fill_px: float = 0.0,
    fill_weight: float = 0.3,
    fill_creases: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(depth m, weight, K) of one view, every `step`-th pixel of the (rows, columns) `window` (K (3, 3) px of that
    grid): isolated outliers (farther than `speckle_m` from the 3x3 median) become NaN; weight = confidence x |cos|
    (at least 0.05) of the angle between the ray and the surface normal from the depth gradient.

    With a = fx dz/du, b = fy dz/dv and the ray r = (x, y, 1), the normal is (-a, -b, a x + b y + z) and
    cos = z / (|n| |r|)."""
    rows, cols = _grid(window, step)
    d, valid, med = despeckle(depth.depth_m[rows, cols], speckle_m)
    holes = fill_holes(d, valid, fill_px / step, 0.25 * speckle_m, fill_creases)
    h, w = d.shape
    filled = np.where(valid | holes, d, med)  # normals next to holes from the local median
    shift = np.array([[1.0, 0.0, -(cols.start or 0)], [0.0, 1.0, -(rows.start or 0)], [0.0, 0.0, 1.0]])
    K = np.diag([1.0 / step, 1.0 / step, 1.0]) @ shift @ view.K
    x = ((np.arange(w) - K[0, 2]) / K[0, 0]).astype(np.float32)[None, :]
    y = ((np.arange(h) - K[1, 2]) / K[1, 1]).astype(np.float32)[:, None]
    a = cv2.filter2D(filled, -1, _DIFF * np.float32(K[0, 0]), borderType=cv2.BORDER_REPLICATE)
    b = cv2.filter2D(filled, -1, _DIFF.T * np.float32(K[1, 1]), borderType=cv2.BORDER_REPLICATE)
    nz = a * x
    nz += b * y
    nz += filled
    norm2 = a * a
    norm2 += b * b
    norm2 += nz * nz
    norm2 *= x * x + y * y + np.float32(1.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        weight = filled / np.sqrt(norm2)
    weight = np.where(valid | holes, np.maximum(weight, _MIN_COS), np.float32(0.0))
    if depth.confidence is not None:
        weight *= np.where(holes, np.float32(1.0), np.clip(depth.confidence[rows, cols], 0.0, 1.0))
    weight[holes] *= np.float32(fill_weight)
    return d, weight.astype(np.float32), K


def hole_bounds(d: np.ndarray, radius_px: float) -> tuple[np.ndarray, np.ndarray] | None:
    """For the small holes of the depth image `d` (NaN unknown), the smallest and the largest depth around them:
    (near, far) images where an unknown pixel inside the morphological closing of the known ones (a square of
    2 `radius_px` + 1 pixels: a hole in a surface, not the background beyond a silhouette) takes the minimum and
    the maximum known depth within that square; known pixels keep their depth; NaN elsewhere. None for a radius
    under one pixel. A hole's surface lies between the two: a voxel in front of `near` is seen through it, a voxel
    behind `far` is behind it (speckle dots without texture inside leave such holes in every view that faces them)."""
    r = int(round(radius_px))
    if r < 1:
        return None
    valid = np.isfinite(d)
    kernel = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
    closed = _closing(valid, kernel)
    far = cv2.dilate(np.where(valid, d, np.float32(-np.inf)), kernel)
    near = cv2.erode(np.where(valid, d, np.float32(np.inf)), kernel)
    hole = closed & ~valid & np.isfinite(far) & np.isfinite(near)
    nan = np.float32(np.nan)
    return (
        np.where(valid, d, np.where(hole, near, nan)).astype(np.float32),
        np.where(valid, d, np.where(hole, far, nan)).astype(np.float32),
    )


def _integrate(
    acc: _Accumulator,
    centres: np.ndarray,
    images: tuple[np.ndarray, np.ndarray, np.ndarray],
    cam_T_support: np.ndarray,
    trunc_m: float,
    holes: tuple[np.ndarray, np.ndarray] | None = None,
    empty: np.ndarray | None = None,
) -> None:
    """Add one view's observations (`prepare_depth`) of voxel centres (3, N) float32, support frame, to `acc`.
    `holes` (same grid as the depth, `hole_bounds`) closes small holes for the free and behind tests only (a
    voxel in a hole's ray is free in front of the nearest depth around it, behind the farthest one). `empty` (same
    grid, bool) marks pixels whose whole ray is known to be empty (the backdrop of a silhouette): a voxel seen there
    without a depth is free."""
    d, weight, K = images
    h, w = d.shape
    R = cam_T_support[:3, :3].astype(np.float32)
    t = cam_T_support[:3, 3].astype(np.float32)
    fx, fy, cx, cy = (np.float32(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    flat_d, flat_w = d.ravel(), weight.ravel()
    inv_trunc = np.float32(1.0 / trunc_m)
    zero = np.float32(0.0)
    for s in range(0, centres.shape[1], _CHUNK):
        c = centres[:, s : s + _CHUNK]
        x, y, z = (R[k, 0] * c[0] + R[k, 1] * c[1] + R[k, 2] * c[2] + t[k] for k in range(3))
        inv = np.float32(1.0) / np.maximum(z, np.float32(1e-3))
        u = np.rint(x * inv * fx + cx).astype(np.int32)
        v = np.rint(y * inv * fy + cy).astype(np.int32)
        ok = (z > 1e-3) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        pix = np.where(ok, v * w + u, 0)
        sdf = flat_d.take(pix) - z  # NaN where the depth is unknown: every comparison below is False
        unknown = ok & np.isnan(sdf)
        sdf[~ok] = np.nan
        wt = flat_w.take(pix)
        free = sdf > trunc_m
        behind = sdf < -trunc_m
        hole_free = None
        if empty is not None:  # the backdrop: seen through
            through = unknown & empty.ravel().take(pix)
            free |= through
            unknown &= ~through
        if holes is not None:  # a hole in a surface: free in front of the depths around it, behind behind them
            hole_behind = unknown & (holes[1].ravel().take(pix) - z < -trunc_m)
            hole_free = unknown & (holes[0].ravel().take(pix) - z > trunc_m)
            behind |= hole_behind
            free |= hole_free
            unknown &= ~(hole_behind | hole_free)
        near = (np.abs(sdf) <= trunc_m) & (wt > 0)
        sl = slice(s, s + c.shape[1])
        acc.free[sl] += free
        acc.behind[sl] += behind
        acc.unknown[sl] += unknown
        acc.free_weight[sl] += np.where(free, wt, zero) if hole_free is None else np.where(free & ~hole_free, wt, zero)
        acc.sdf[sl] += np.where(near, wt * sdf * inv_trunc, zero)
        acc.weight[sl] += np.where(near, wt, zero)


def backdrop_mask(image: np.ndarray, level: int, min_area: float = 0.005, margin_px: int = 1) -> np.ndarray:
    """(H, W) bool: the backdrop of an object shot against black. Pixels at or below grey `level`, in connected
    regions of at least `min_area` of the image (dark crevices of the object are small), eroded by `margin_px` (the
    silhouette's soft edge stays unknown)."""
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    dark = (grey <= level).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(dark, connectivity=8)
    big = np.flatnonzero(stats[:, cv2.CC_STAT_AREA] >= min_area * dark.size)
    keep = np.isin(labels, big[big > 0]).astype(np.uint8)
    k = 2 * margin_px + 1
    return cv2.erode(keep, np.ones((k, k), np.uint8)).astype(bool)


def _grid(window: tuple[slice, slice] | None, step: int) -> tuple[slice, slice]:
    """(rows, columns) of every `step`-th pixel of the window (the whole image for None): `prepare_depth`'s grid."""
    rows, cols = window or (slice(None), slice(None))
    return slice(rows.start, rows.stop, step), slice(cols.start, cols.stop, step)


def _on_grid(mask: np.ndarray | None, window: tuple[slice, slice], step: int) -> np.ndarray | None:
    """A full-image mask on `prepare_depth`'s grid."""
    return None if mask is None else mask[_grid(window, step)]


def _base_columns(tsdf: np.ndarray, z0_m: float, voxel_m: float, band_m: float) -> None:
    """In the lowest `band_m` above the plane, a voxel that no depth measured (field exactly -1 or +1, decided by
    votes) takes the side of the voxel above it at `band_m` (in place). Next to the part's base the table is seen at
    grazing angles and gives no depth, so the views on that side say nothing there while the views on the far side
    see it behind the part: by votes alone it would be solid, a flap 1-4 mm high and up to the ROI's margin wide
    along the base (measured on simulated orbits with true poses: +6 to +9 mm of deviation). The part's own base is
    assumed to rise straight for `band_m` where no view measured it."""
    top = int(np.ceil((band_m - z0_m) / voxel_m))
    if band_m <= 0 or top <= 2 or top >= tsdf.shape[2]:
        return
    side = np.where(tsdf[:, :, top] < 0, np.float32(-1.0), np.float32(1.0))
    for k in range(2, top):
        layer = tsdf[:, :, k]
        voted = np.abs(layer) >= 1.0
        layer[voted] = side[voted]


TRUNC_VOXELS = 4.0  # the truncation distance in voxels (fuse_depth_maps' default)
MAX_GRID_VOXELS = 2**28  # 268 M voxels: a 250 mm cube at 0.4 mm. A 1.7 G-voxel grid (a region that took in a metre of
# table) peaked at 16 GB in `vio model`; the 60 s cube's 24 M-voxel grid at 3 GB with its 120 full-size stills


def check_grid(roi: Roi, voxel_m: float, coarse_factor: int = 4) -> None:
    """Raise ModelError (one line, with the region's size) when the fusion grid over `roi` would be too large: called
    before the stereo too, so a region of interest that swallowed the table fails in seconds, not after an hour."""
    cell = coarse_factor * voxel_m
    size = np.array([roi.hi[0] - roi.lo[0], roi.hi[1] - roi.lo[1], roi.hi[2] + 2.0 * voxel_m])
    shape = np.maximum(np.ceil(size / cell).astype(int), 1) * coarse_factor
    if np.prod(shape.astype(np.float64)) > MAX_GRID_VOXELS:
        mm = " x ".join(f"{1e3 * v:.0f}" for v in size)
        raise ModelError(
            f"the region of interest is {mm} mm: a fusion grid of {shape.tolist()} voxels is too large; "
            "give the part's box with --roi, or a larger --voxel-mm"
        )


def fuse_depth_maps(
    views: Sequence[View],
    depth_maps: Sequence[DepthMap],
    roi: Roi,
    voxel_m: float = 4e-4,
    trunc_voxels: float = TRUNC_VOXELS,
    min_free_views: int = 2,
    coarse_factor: int = 4,
    hole_px: float = 8.0,
    fill_px: float = 16.0,
    fill_weight: float = 0.3,
    fill_creases: bool = True,
    base_band_m: float = 4e-3,
    backdrop_below: int = 0,
) -> FusedVolume:
    """Fuse depth maps (z-depth per pixel of `views[dm.view]`) into a FusedVolume over `roi` (voxel edge
    `voxel_m` m, truncation `trunc_voxels` voxels). Holes of up to 2 `fill_px` pixels in a smooth surface are
    filled with the plane through the depths around them, at `fill_weight` times the weight of a measured depth
    (`fill_holes`); with `fill_creases`, holes along a convex edge with the two faces' planes. With
    `backdrop_below` > 0, large image regions at or below that grey level are a backdrop that every ray through
    them crosses empty (`backdrop_mask`: silhouette carving, for objects shot against black).
    See the module docstring for the rule."""
    if not depth_maps:
        raise ModelError("no depth maps to fuse")
    f = int(coarse_factor)
    trunc_m = float(trunc_voxels * voxel_m)
    cell = f * voxel_m
    lo = np.array([roi.lo[0], roi.lo[1], -2.0 * voxel_m])
    shape_c = np.maximum(np.ceil((np.array([roi.hi[0], roi.hi[1], roi.hi[2]]) - lo) / cell).astype(int), 1)
    shape = shape_c * f
    check_grid(roi, voxel_m, f)
    origin = lo + 0.5 * voxel_m
    t0 = time.perf_counter()
    prepared = []
    corners = np.array([[(lo, shape * voxel_m + lo)[(i >> k) & 1][k] for k in range(3)] for i in range(8)])
    coarse = _Accumulator.zeros(int(np.prod(shape_c)))
    ijk_c = np.indices(shape_c, dtype=np.float32).reshape(3, -1).T
    centres_c = np.ascontiguousarray((lo + (ijk_c + 0.5) * cell).T, dtype=np.float32)
    trunc_c = max(trunc_m, 1.5 * cell)
    for dm in depth_maps:
        view = views[dm.view]
        z_typ = np.nanmedian(dm.depth_m[::16, ::16]) if np.isfinite(dm.depth_m[::16, ::16]).any() else 1.0
        step = max(1, int(view.K[0, 0] * cell / (2.0 * z_typ)))  # about 2 pixels per coarse cell
        cam_T_support = np.linalg.inv(view.world_T_cam) @ roi.world_T_support
        window = _window(corners, cam_T_support, view.K, dm.depth_m.shape)  # where the grid is seen
        if window is None:
            continue
        images = prepare_depth(view, dm, trunc_m, step, window, fill_px, fill_weight, fill_creases)
        backdrop = backdrop_mask(view.image, backdrop_below) if backdrop_below > 0 else None
        _integrate(coarse, centres_c, images, cam_T_support, trunc_c, hole_bounds(images[0], hole_px / step),
                   _on_grid(backdrop, window, step))  # fmt: skip
        prepared.append((dm, view, cam_T_support, window, backdrop))
    if not prepared:
        raise ModelError("no depth map sees the region of interest")
    field_c = coarse.field(min_free_views).reshape(shape_c)
    field_c[:, :, 0] = 1.0  # the lowest coarse layer holds the two voxels below the plane: outside
    sign = field_c > 0
    changes = ndimage.binary_dilation(sign, np.ones((3, 3, 3), bool)) & ~ndimage.binary_erosion(
        sign, np.ones((3, 3, 3), bool), border_value=1
    )
    band = (np.abs(field_c) < 1.0) | changes
    t1 = time.perf_counter()
    cells = np.argwhere(band).astype(np.float32)
    offsets = np.indices((f, f, f), dtype=np.float32).reshape(3, -1).T
    fine_ijk = (cells[:, None, :] * f + offsets[None, :, :]).reshape(-1, 3)
    centres = np.ascontiguousarray((origin + fine_ijk * voxel_m).T, dtype=np.float32)
    fine = _Accumulator.zeros(centres.shape[1])
    for dm, view, cam_T_support, window, backdrop in prepared:
        images = prepare_depth(view, dm, trunc_m, 1, window, fill_px, fill_weight, fill_creases)
        _integrate(fine, centres, images, cam_T_support, trunc_m, hole_bounds(images[0], hole_px),
                   _on_grid(backdrop, window, 1))  # fmt: skip
    tsdf = np.repeat(np.repeat(np.repeat(np.where(sign, 1.0, -1.0).astype(np.float32), f, 0), f, 1), f, 2)
    ii = fine_ijk.astype(np.int64)
    tsdf[ii[:, 0], ii[:, 1], ii[:, 2]] = fine.field(min_free_views)
    tsdf[:, :, :2] = 1.0  # below the support plane
    _base_columns(tsdf, origin[2], voxel_m, base_band_m)
    log.info(
        "fused %d depth maps: grid %s at %.2f mm, band %d voxels (%.1f %%), coarse %.1f s, fine %.1f s",
        len(depth_maps),
        shape.tolist(),
        1e3 * voxel_m,
        centres.shape[1],
        100.0 * centres.shape[1] / tsdf.size,
        t1 - t0,
        time.perf_counter() - t1,
    )
    return FusedVolume(tsdf, origin, float(voxel_m), trunc_m, roi)


def _window(
    corners: np.ndarray, cam_T_support: np.ndarray, K: np.ndarray, shape: tuple[int, ...]
) -> tuple[slice, slice] | None:
    """(rows, columns) of the image (shape (H, W)) where support-frame corners (8, 3) m project (the whole image
    if one is behind the camera), or None when they project outside it (less than 3 x 3 pixels)."""
    pc = corners @ cam_T_support[:3, :3].T + cam_T_support[:3, 3]
    if (pc[:, 2] <= 1e-3).any():
        return slice(0, shape[0]), slice(0, shape[1])
    uv = pc[:, :2] / pc[:, 2:] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    c0, r0 = np.clip(np.floor(uv.min(axis=0)).astype(int), 0, [shape[1], shape[0]])
    c1, r1 = np.clip(np.ceil(uv.max(axis=0)).astype(int) + 1, 0, [shape[1], shape[0]])
    if r1 - r0 < 3 or c1 - c0 < 3:
        return None
    return slice(r0, r1), slice(c0, c1)


def fused_points(
    views: Sequence[View],
    depth_maps: Sequence[DepthMap],
    volume: FusedVolume,
    tol_m: float | None = None,
    max_points: int = 2_000_000,
    rng: np.random.Generator | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The depth-map points that agree with the fused surface, for dense.ply: (points (N, 3) world m, colours
    (N, 3) uint8 RGB from the views' images).

    A point agrees when it lies inside the volume's box, at least one voxel above the support plane, and within
    `tol_m` (default two voxels) of the surface (the field interpolated trilinearly). At most
    `max_points / len(depth_maps)` points per view are kept (a random subset from `rng`, default seed 0)."""
    rng = np.random.default_rng(0) if rng is None else rng
    tol_m = 2.0 * volume.voxel_m if tol_m is None else float(tol_m)
    quota = max(1, int(max_points) // max(len(depth_maps), 1))
    support_T_world = np.linalg.inv(volume.roi.world_T_support)
    upper = np.array(volume.tsdf.shape) - 1
    out_p, out_c = [], []
    corners = np.array([[(volume.roi.lo, volume.roi.hi)[(i >> k) & 1][k] for k in range(3)] for i in range(8)])
    for dm in depth_maps:
        view = views[dm.view]
        K = view.K
        window = _window(corners, np.linalg.inv(view.world_T_cam) @ volume.roi.world_T_support, K, dm.depth_m.shape)
        if window is None:
            continue
        rows, cols = window
        d = despeckle(dm.depth_m[rows, cols], volume.trunc_m)[0]
        v, u = np.nonzero(np.isfinite(d))
        if len(v) > 4 * quota:  # enough candidates to fill the quota after the agreement test
            pick = np.sort(rng.choice(len(v), 4 * quota, replace=False))
            v, u = v[pick], u[pick]
        z = d[v, u].astype(np.float64)
        v, u = v + rows.start, u + cols.start
        p_cam = np.column_stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z])
        T = support_T_world @ view.world_T_cam
        p = p_cam @ T[:3, :3].T + T[:3, 3]
        ijk = (p - volume.origin) / volume.voxel_m
        ok = (ijk >= 0).all(axis=1) & (ijk <= upper).all(axis=1) & (p[:, 2] >= volume.voxel_m)
        idx = np.nonzero(ok)[0]
        value = ndimage.map_coordinates(volume.tsdf, ijk[idx].T, order=1, mode="nearest")
        idx = idx[np.abs(value) * volume.trunc_m <= tol_m]
        if len(idx) > quota:
            idx = np.sort(rng.choice(idx, quota, replace=False))
        image = view.image if view.image.ndim == 3 else view.image[:, :, None].repeat(3, axis=2)
        out_c.append(image[v[idx], u[idx]][:, ::-1])  # BGR -> RGB
        out_p.append(p[idx] @ volume.roi.world_T_support[:3, :3].T + volume.roi.world_T_support[:3, 3])
    if not out_p:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    return np.concatenate(out_p), np.ascontiguousarray(np.concatenate(out_c), dtype=np.uint8)
