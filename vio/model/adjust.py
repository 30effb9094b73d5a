"""Bundle adjustment of the views' poses against their own images, anchored to the visual-inertial positions.

The run's trajectory is metric but its relative errors (about a millimetre and 0.1-0.2 deg between views far
apart) are far above what multi-view stereo needs. Feature tracks (`vio.model.matches`) fix the relative geometry
to a fraction of a pixel; each camera centre is tied to its prior (visual-inertial) position by a `GPSFactor` with
`position_sigma_m`, so the ensemble of views fixes the scale and the gauge (position, orientation) to about
position_sigma_m / sqrt(sum |c_i - mean|^2) in scale, much better than one view's error when the prior errors are
independent. What the anchor cannot fix is an error shared by all prior positions: a scale error of the trajectory
passes through (it is the trajectory's scale, and the images cannot see it), as does any smooth drift's best-fitting
similarity. Intrinsics are held fixed.

Measured on the simulated orbit (noise-free renders, priors with 2-3 mm and 0.2-0.3 deg errors): camera centres
after a similarity alignment to the truth 0.15 mm RMS and rotations 0.015-0.02 deg RMS from 40 stills of
2016x1512 px; 0.3-0.5 mm and 0.03-0.07 deg from 20 of 1008x756 px. SIFT's localisation is the limit there.

Frames: `world_T_cam` (OpenCV axes) in the run's world, metres; pixels of the undistorted pinhole images.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field

import gtsam
import numpy as np

from vio.errors import ModelError
from vio.model.matches import MatchConfig, Tracks, find_tracks
from vio.model.records import Roi, View

log = logging.getLogger(__name__)

MIN_TRACKS = 50  # fewer tracks than this: no adjustment (ModelError)
MIN_VIEW_OBSERVATIONS = 12  # a view seeing fewer tracks keeps its prior pose
SIGMA_STEP_PX = 0.05  # observation sigmas are rounded to this, px (one noise model per level)


@dataclass(frozen=True)
class AdjustConfig:
    """Bundle-adjustment settings. SIFT's localisation error grows with the keypoint's scale (on the simulator's
    renders the median error is about 5 % of the SIFT diameter, the RMS about 9 %), so each observation's sigma is
    max(pixel_sigma_px, keypoint_sigma * diameter)."""

    pixel_sigma_px: float = 0.25  # smallest observation sigma, px
    keypoint_sigma: float = 0.08  # observation sigma per px of SIFT diameter
    huber_k: float = 1.345  # Huber threshold, sigmas
    outlier_sigmas: float = 4.0  # after the first solve, observations reprojecting further are dropped
    max_iterations: int = 50  # Levenberg-Marquardt iterations per solve
    # LM stops when an iteration lowers the error by less than this share: 1e-5 took half the CPU of 1e-7 on the
    # 120 stills of a 60 s capture (13.7 against 27.3 s) and moved no camera centre by more than 0.004 mm
    relative_error_tol: float = 1e-5
    matching: MatchConfig = field(default_factory=MatchConfig)


@dataclass(frozen=True)
class AdjustReport:
    """What the bundle adjustment did."""

    num_views: int  # views given
    num_adjusted: int  # views with enough observations to be adjusted (the others keep their prior pose)
    num_tracks: int  # scene points in the adjustment
    num_observations: int  # projection factors kept after the outlier pass
    features_per_view: float  # median SIFT keypoints per view
    num_pairs: int  # pairs of views with verified matches
    rms_before_px: float  # reprojection RMS of the kept observations: prior poses, points triangulated from them
    rms_after_px: float  # ... after the adjustment
    scale: float  # similarity adjusted = s R prior + t of the adjusted camera centres: s (1 = no scale change)
    scale_sigma: float  # the anchor's scale uncertainty, position_sigma_m / sqrt(sum |c_i - mean|^2)
    rotation_deg: float  # ... the angle of R, deg
    translation_m: float  # ... |t|, m
    shift_median_m: float  # median distance between prior and adjusted camera centres, m
    shift_max_m: float  # largest such distance, m
    time_s: float  # wall time, s (adjust_views: features, matching and adjustment)


def adjust_views(
    views: list[View], roi: Roi | None = None, position_sigma_m: float = 0.005, config: AdjustConfig | None = None
) -> tuple[list[View], AdjustReport]:
    """Views with bundle-adjusted poses (same order, images and K) and what was done: `find_tracks`, then
    `bundle_adjust`. position_sigma_m: absolute accuracy of the prior camera positions (the trajectory's), m.

    With a ROI, features come from its projected window only. That is faster but narrows each camera's field of
    view and weakens its pose: on the simulated orbit (20-30 views of 1008x756 px) the camera centres' error after
    a similarity alignment to the truth was 0.3 mm from whole images, 0.2 mm from the cube's box grown by 20 cm,
    0.5 mm grown by 6 cm and 0.9-1.1 mm grown by 1-3 cm. Too few tracks raise a one-line ModelError.
    """
    t0 = time.perf_counter()
    config = config or AdjustConfig()
    tracks = find_tracks(views, roi, config.matching)
    out, report = bundle_adjust(views, tracks, position_sigma_m, config)
    return out, dataclasses.replace(report, time_s=time.perf_counter() - t0)


def bundle_adjust(
    views: list[View], tracks: Tracks, position_sigma_m: float = 0.005, config: AdjustConfig | None = None
) -> tuple[list[View], AdjustReport]:
    """Poses X(i) and points L(j) by Levenberg-Marquardt from the views' prior poses and the tracks' points:
    projection factors (robust, sigma by keypoint scale) and a `GPSFactor` on each camera centre at its prior
    position with position_sigma_m. Solved twice: outliers are dropped after the first solve. A view seeing fewer
    than MIN_VIEW_OBSERVATIONS tracks keeps its prior pose (a warning)."""
    t0 = time.perf_counter()
    config = config or AdjustConfig()
    if len(tracks.points_world) < MIN_TRACKS:
        raise ModelError(
            f"bundle adjustment: {len(tracks.points_world)} feature tracks over {len(views)} views "
            f"(at least {MIN_TRACKS} needed): too little texture or overlap"
        )
    adjusted = np.bincount(tracks.view, minlength=len(views)) >= MIN_VIEW_OBSERVATIONS
    if (~adjusted).any():
        log.warning("%d of %d views see too few tracks: prior poses kept", int((~adjusted).sum()), len(views))
    if adjusted.sum() < 3:
        raise ModelError(f"bundle adjustment: only {int(adjusted.sum())} views see enough feature tracks")
    obs = adjusted[tracks.view]
    prior = _initial(views, tracks)
    sigma_px = np.maximum(config.pixel_sigma_px, config.keypoint_sigma * tracks.size)
    first = _solve(views, tracks, obs, adjusted, prior, position_sigma_m, sigma_px, config)
    obs &= _reprojection(views, tracks, first) < config.outlier_sigmas * sigma_px
    obs &= (
        np.bincount(tracks.track[obs], minlength=len(tracks.points_world))[tracks.track]
        >= config.matching.min_track_views
    )
    result = _solve(views, tracks, obs, adjusted, first, position_sigma_m, sigma_px, config)
    err_before = _reprojection(views, tracks, prior)[obs]
    err_after = _reprojection(views, tracks, result)[obs]
    out = [
        dataclasses.replace(v, world_T_cam=result.atPose3(gtsam.symbol("x", i)).matrix()) if adjusted[i] else v
        for i, v in enumerate(views)
    ]
    before = np.array([v.world_T_cam[:3, 3] for v in views])[adjusted]
    after = np.array([v.world_T_cam[:3, 3] for v in out])[adjusted]
    scale, R, t = similarity(before, after)
    shifts = np.linalg.norm(after - before, axis=1)
    report = AdjustReport(
        num_views=len(views),
        num_adjusted=int(adjusted.sum()),
        num_tracks=int(np.unique(tracks.track[obs]).size),
        num_observations=int(obs.sum()),
        features_per_view=float(np.median(tracks.features_per_view)) if len(tracks.features_per_view) else 0.0,
        num_pairs=tracks.num_pairs,
        rms_before_px=float(np.sqrt(np.mean(err_before**2))),
        rms_after_px=float(np.sqrt(np.mean(err_after**2))),
        scale=scale,
        scale_sigma=float(position_sigma_m / np.sqrt(np.sum((before - before.mean(axis=0)) ** 2))),
        rotation_deg=float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))),
        translation_m=float(np.linalg.norm(t)),
        shift_median_m=float(np.median(shifts)),
        shift_max_m=float(shifts.max()),
        time_s=time.perf_counter() - t0,
    )
    log.info(
        "bundle adjustment: %d views, %d tracks, %d observations, RMS %.2f -> %.2f px, scale %.5f +- %.5f, "
        "centres moved %.2f mm (median), %.2f mm (max)",
        report.num_adjusted, report.num_tracks, report.num_observations, report.rms_before_px, report.rms_after_px,
        report.scale, report.scale_sigma, 1e3 * report.shift_median_m, 1e3 * report.shift_max_m,
    )  # fmt: skip
    return out, report


def similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares dst ~ s R src + t (Umeyama) of (N, 3) points, m: (s, R (3, 3), t (3,) m)."""
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - mu_s, dst - mu_d
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / (np.sum(a**2) / len(src)))
    return s, R, mu_d - s * R @ mu_s


def _initial(views: list[View], tracks: Tracks) -> gtsam.Values:
    """Prior poses X(i) and points L(j) triangulated from them."""
    values = gtsam.Values()
    for i, v in enumerate(views):
        values.insert(gtsam.symbol("x", i), gtsam.Pose3(v.world_T_cam))
    for j, p in enumerate(tracks.points_world):
        values.insert(gtsam.symbol("l", j), gtsam.Point3(*p))
    return values


def _solve(
    views: list[View],
    tracks: Tracks,
    obs: np.ndarray,
    adjusted: np.ndarray,
    initial: gtsam.Values,
    position_sigma_m: float,
    sigma_px: np.ndarray,
    config: AdjustConfig,
) -> gtsam.Values:
    """Levenberg-Marquardt on projection factors of the kept observations and position priors of adjusted views;
    the result holds every view's pose (unadjusted ones unchanged) and every point (unobserved ones unchanged)."""
    graph = gtsam.NonlinearFactorGraph()
    huber = gtsam.noiseModel.mEstimator.Huber.Create(config.huber_k)
    level = np.maximum(np.round(sigma_px / SIGMA_STEP_PX).astype(int), 1)  # one noise model per sigma level
    noise = {k: gtsam.noiseModel.Robust.Create(huber, gtsam.noiseModel.Isotropic.Sigma(2, k * SIGMA_STEP_PX))
             for k in np.unique(level[obs])}  # fmt: skip
    cal = [gtsam.Cal3_S2(v.K[0, 0], v.K[1, 1], v.K[0, 1], v.K[0, 2], v.K[1, 2]) for v in views]
    for i, j, uv, k in zip(tracks.view[obs], tracks.track[obs], tracks.uv[obs], level[obs], strict=True):
        x, p = gtsam.symbol("x", int(i)), gtsam.symbol("l", int(j))
        graph.add(gtsam.GenericProjectionFactorCal3_S2(uv, noise[k], x, p, cal[i]))
    anchor = gtsam.noiseModel.Isotropic.Sigma(3, position_sigma_m)
    estimate = gtsam.Values()
    for i in np.flatnonzero(adjusted):
        graph.add(gtsam.GPSFactor(gtsam.symbol("x", int(i)), views[i].world_T_cam[:3, 3], anchor))
        estimate.insert(gtsam.symbol("x", int(i)), initial.atPose3(gtsam.symbol("x", int(i))))
    for j in np.unique(tracks.track[obs]):
        estimate.insert(gtsam.symbol("l", int(j)), initial.atPoint3(gtsam.symbol("l", int(j))))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(config.max_iterations)
    params.setRelativeErrorTol(config.relative_error_tol)
    params.setAbsoluteErrorTol(1e-9)
    try:
        result = gtsam.LevenbergMarquardtOptimizer(graph, estimate, params).optimize()
    except RuntimeError as exc:  # e.g. an indeterminant system: a view or point left unconstrained
        first_line = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise ModelError(f"bundle adjustment failed: {first_line}") from None
    merged = gtsam.Values(initial)
    merged.update(result)
    return merged


def _reprojection(views: list[View], tracks: Tracks, values: gtsam.Values) -> np.ndarray:
    """(M,) reprojection error of every observation, px (inf behind the camera)."""
    cam_T_world = np.array([np.linalg.inv(values.atPose3(gtsam.symbol("x", i)).matrix()) for i in range(len(views))])
    points = np.array([values.atPoint3(gtsam.symbol("l", j)) for j in range(len(tracks.points_world))])
    p_cam = np.einsum("mij,mj->mi", cam_T_world[tracks.view, :3, :3], points[tracks.track])
    p_cam += cam_T_world[tracks.view, :3, 3]
    K = np.array([v.K for v in views])[tracks.view]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.einsum("mij,mj->mi", K, p_cam / p_cam[:, 2:])[:, :2]
    err = np.linalg.norm(uv - tracks.uv, axis=1)
    return np.where(p_cam[:, 2] > 0, err, np.inf)
