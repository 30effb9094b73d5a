"""Camera-IMU rotation and time offset refined on feature tracks directly (no board): the gyro's turn, carried into
the camera frame by body_R_cam, must make every common track of two frames satisfy the epipolar constraint.

For a pair (i, j) the camera's turn is C = body_R_cam^T G body_R_cam with G the gyro's turn over [t_i + d, t_j + d]
(bias removed). With bearings f_a (frame i) and f_b (frame j) of one track, n = (C f_b) x f_a is perpendicular to the
baseline t; the baseline is the unit vector that minimises sum (n . t)^2 over the pair's tracks (the smallest
eigenvector, solved inside every evaluation; its sign kept that of the starting point's), and each track's residual
is the algebraic epipolar error n . t = f_a^T [t]x C f_b (rad for small errors). A pair whose camera hardly moved
constrains C just the same (every n is then near zero). body_R_cam, d and a constant gyro bias minimise the
residuals with a robust (Cauchy) loss of scale ROBUST_SCALE_PX / f; their standard deviations come from the
Jacobian, with sigma the inliers' RMS, scaled by how many pairs each frame enters (overlapping pairs share their
frames' tracking errors).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from vio.calibrate.gyro import GyroIntegral
from vio.errors import CalibrationError
from vio.records import ImuSeries

log = logging.getLogger(__name__)

ROBUST_SCALE_PX = 1.0
MIN_PAIRS = 20


@dataclass(frozen=True)
class BearingPairs:
    """Common tracks of frame pairs as unit bearing vectors; times on the camera clock."""

    t0_ns: np.ndarray  # (P,) int64
    t1_ns: np.ndarray  # (P,) int64
    pair: np.ndarray  # (M,) pair index of each track
    f0: np.ndarray  # (M, 3) bearing in the first frame (camera axes)
    f1: np.ndarray  # (M, 3) bearing in the second frame


@dataclass(frozen=True)
class EpipolarAlignment:
    body_R_cam: np.ndarray  # (3, 3)
    offset_ns: float  # t_imu = t_cam + offset
    gyro_bias_rad_s: np.ndarray  # (3,)
    rotation_std_rad: np.ndarray  # (3,) about the body axes
    offset_std_ns: float
    residual_rms_rad: float  # of the inliers
    inlier_fraction: float
    pairs: int
    tracks: int


def _baselines(x, R0: Rotation, data: BearingPairs, imu: ImuSeries, offset0: float) -> tuple[np.ndarray, np.ndarray]:
    """(n per track (M, 3), the unit baseline per pair (P, 3), sign arbitrary)."""
    R = R0 * Rotation.from_rotvec(x[:3])
    d = offset0 + x[3] * 1e6
    G = GyroIntegral(imu, x[4:7]).between(data.t0_ns, data.t1_ns, d)
    C = (R.inv() * G * R).as_matrix()  # (P, 3, 3) cam_i_R_cam_j
    n = np.cross(np.einsum("mij,mj->mi", C[data.pair], data.f1), data.f0)
    M = np.einsum("mi,mj->mij", n, n)
    S = np.zeros((len(data.t0_ns), 3, 3))
    np.add.at(S, data.pair, M)
    _, vecs = np.linalg.eigh(S)
    return n, vecs[:, :, 0]


def _residuals(x, R0: Rotation, data: BearingPairs, imu: ImuSeries, offset0: float, t_ref: np.ndarray) -> np.ndarray:
    n, t = _baselines(x, R0, data, imu, offset0)
    t *= np.where(np.einsum("pi,pi->p", t, t_ref) < 0, -1.0, 1.0)[:, None]  # a continuous sign for the Jacobian
    return np.einsum("mi,mi->m", n, t[data.pair])


def refine_on_tracks(
    data: BearingPairs,
    imu: ImuSeries,
    body_R_cam0: np.ndarray,
    offset0_ns: float,
    gyro_bias0: np.ndarray,
    focal_px: float,
    reuse: float = 1.0,
) -> EpipolarAlignment:
    """The refinement of the module docstring, started from a rotation-step estimate. `reuse` is how many pairs
    each frame's tracks enter: the pairs' residuals are that many times correlated, so the covariance is scaled by
    it (independent pairs: 1)."""
    if len(data.t0_ns) < MIN_PAIRS:
        raise CalibrationError(f"only {len(data.t0_ns)} frame pairs with common tracks; at least {MIN_PAIRS} needed")
    R0 = Rotation.from_matrix(body_R_cam0)
    x0 = np.concatenate([np.zeros(4), gyro_bias0])
    scale = ROBUST_SCALE_PX / focal_px
    t_ref = _baselines(x0, R0, data, imu, offset0_ns)[1]
    sol = least_squares(
        _residuals,
        x0,
        args=(R0, data, imu, offset0_ns, t_ref),
        loss="cauchy",
        f_scale=scale,
        x_scale=[1e-3] * 3 + [1.0] + [1e-3] * 3,
    )
    r = sol.fun
    inlier = np.abs(r) < 3.0 * scale
    sigma2 = float(r[inlier] @ r[inlier]) / max(int(inlier.sum()) - 7, 1)
    J = sol.jac[inlier]
    cov = reuse * sigma2 * np.linalg.pinv(J.T @ J)
    R = R0 * Rotation.from_rotvec(sol.x[:3])
    cov_body = R.as_matrix() @ cov[:3, :3] @ R.as_matrix().T
    log.info("epipolar refinement: %d pairs, %d tracks, %.0f %% inliers", len(data.t0_ns), len(r), 100 * inlier.mean())
    return EpipolarAlignment(
        body_R_cam=R.as_matrix(),
        offset_ns=offset0_ns + float(sol.x[3]) * 1e6,
        gyro_bias_rad_s=np.asarray(sol.x[4:7]),
        rotation_std_rad=np.sqrt(np.maximum(np.diag(cov_body), 0.0)),
        offset_std_ns=float(np.sqrt(max(cov[3, 3], 0.0))) * 1e6,
        residual_rms_rad=float(np.sqrt(np.mean(r[inlier] ** 2))),
        inlier_fraction=float(inlier.mean()),
        pairs=len(data.t0_ns),
        tracks=len(r),
    )
