"""Camera-IMU rotation and time offset from rotations alone: the camera's turns (from the board, or from feature
tracks) against the gyro's.

1. Time offset, coarse: the camera's angular speed between consecutive frames against the gyro's mean angular speed
   over the same interval shifted by a candidate offset d; speeds are frame-free, so this needs no rotation yet. The
   d of the highest Pearson correlation wins (1 ms grid, parabolic refinement).
2. Rotation, closed form (hand-eye): for frame pairs (i, j) the camera's turn a_c (rotation vector in the camera
   frame) and the gyro's turn a_b over [t_i + d, t_j + d] satisfy a_b = body_R_cam a_c; body_R_cam is the rotation
   that best maps one set onto the other (Kabsch). Pairs that miss it by far more than the others (OUTLIER_*) are
   left out and the rotation solved again.
3. Joint refinement: body_R_cam, d and a constant gyro bias minimise the rotation residuals
   Log(gyro turn^-1 * body_R_cam * camera turn * body_R_cam^T) over the pairs (scipy least squares); their standard
   deviations are sigma^2 (J^T J)^-1 with sigma the RMS residual. Pairs do not overlap in time, so their gyro noise is
   independent.
Convention (Kalibr's `timeshift_cam_imu`): t_imu = t_cam + offset.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from vio.calibrate.gyro import GyroIntegral
from vio.errors import CalibrationError
from vio.geometry import parabolic_peak
from vio.records import ImuSeries

log = logging.getLogger(__name__)

PAIR_SPAN_S = 0.2  # time between the two frames of a refinement pair, s (longer: more turn per pair, more bias)
GRID_STEP_NS = 1_000_000  # cross-correlation grid, ns
MIN_PAIRS = 10
OUTLIER_FACTOR = 5.0  # a pair whose turns disagree by more than this many times the median (and ...
OUTLIER_FLOOR_RAD = np.deg2rad(0.5)  # ... by more than this) is left out of the rotation
MIN_RMS_SPEED_RAD_S = np.deg2rad(3.0)  # below this RMS angular speed (bias removed) the camera did not rotate
SPEED_BIN_S = 0.2  # the rotation check reads the gyro's mean rate over bins of this length (noise averaged out)
WEAK_AXIS_RAD = np.deg2rad(5.0)  # an axis turned less than this (RMS of the pairs' turns about it) is weak


@dataclass(frozen=True)
class CameraTurns:
    """The camera's rotation between pairs of frames, times on the camera clock."""

    t0_ns: np.ndarray  # (P,) int64 first frame of each pair, ns
    t1_ns: np.ndarray  # (P,) int64 second frame, ns
    rotvec: np.ndarray  # (P, 3) cam(t0)_R_cam(t1) as a rotation vector in the camera frame, rad


@dataclass(frozen=True)
class RotationAlignment:
    """Result of steps 1-3 (module docstring)."""

    body_R_cam: np.ndarray  # (3, 3)
    offset_ns: float  # t_imu = t_cam + offset, ns (refined)
    offset_xcorr_ns: float  # the coarse step's offset, ns
    correlation: float  # Pearson correlation of camera and gyro angular speeds at the coarse offset
    gyro_bias_rad_s: np.ndarray  # (3,) constant gyro bias, rad/s
    rotation_std_rad: np.ndarray  # (3,) one sigma of body_R_cam about the body axes, rad
    offset_std_ns: float  # one sigma of the offset, ns
    residual_rms_rad: float  # RMS of the pairs' rotation residuals, rad
    pairs: int  # pairs in the refinement
    axis_turn_rad: np.ndarray  # (3,) RMS turn of the pairs about the principal axes (smallest first), rad
    xcorr_offsets_ns: np.ndarray  # (D,) the offsets the cross-correlation tried, ns
    xcorr: np.ndarray  # (D,) the correlation at each
    steps: CameraTurns  # the camera's turns between consecutive frames (the cross-correlation's input)


def turns_from_poses(t_ns: np.ndarray, world_R_cam: Rotation, span_s: float, max_gap_s: float) -> CameraTurns:
    """Pairs of frames about `span_s` apart (each starting where the previous ended, so they do not overlap), from
    camera orientations in any fixed frame; a pair whose frames are farther apart than `span_s + max_gap_s` is skipped
    (frames without the board in between)."""
    t0, t1, rv = [], [], []
    i = 0
    n = len(t_ns)
    span_ns, gap_ns = span_s * 1e9, max_gap_s * 1e9
    while i < n - 1:
        j = int(np.searchsorted(t_ns, t_ns[i] + span_ns - 1e6))  # the first frame at least span_s later (1 ms slack)
        if j >= n:
            break
        if t_ns[j] - t_ns[i] <= span_ns + gap_ns:
            t0.append(int(t_ns[i]))
            t1.append(int(t_ns[j]))
            rv.append((world_R_cam[i].inv() * world_R_cam[j]).as_rotvec())
        i = j
    return CameraTurns(np.asarray(t0, np.int64), np.asarray(t1, np.int64), np.asarray(rv, float).reshape(-1, 3))


def xcorr_offset(
    turns: CameraTurns, gyro: GyroIntegral, max_offset_s: float
) -> tuple[float, float, np.ndarray, np.ndarray]:
    """Step 1: (offset ns, correlation, the offsets tried ns, the correlation at each) from angular speeds."""
    lim = int(round(max_offset_s * 1e9))
    lo, hi = gyro.span_ns
    inside = (turns.t0_ns - lim >= lo) & (turns.t1_ns + lim <= hi)
    t0, t1 = turns.t0_ns[inside], turns.t1_ns[inside]
    if t0.size < MIN_PAIRS:
        raise CalibrationError(
            f"only {t0.size} frame pairs lie inside the IMU's span +-{max_offset_s:g} s; the camera and IMU "
            "recordings must overlap (check the capture's clocks with vio info)"
        )
    cam_speed = np.linalg.norm(turns.rotvec[inside], axis=1) / ((t1 - t0) * 1e-9)
    offsets = np.arange(-lim, lim + 1, GRID_STEP_NS, dtype=np.int64)
    corr = np.empty(len(offsets))
    c = cam_speed - cam_speed.mean()
    for k, d in enumerate(offsets):
        g = gyro.mean_speed(t0, t1, float(d))
        g = g - g.mean()
        corr[k] = float(g @ c) / (float(np.linalg.norm(g) * np.linalg.norm(c)) + 1e-12)
    k = int(np.argmax(corr))
    best = float(offsets[k]) + parabolic_peak(corr, k) * GRID_STEP_NS
    if k in (0, len(corr) - 1):
        raise CalibrationError(
            f"the camera-IMU time offset is at the search limit (+-{max_offset_s:g} s): widen --max-offset-ms or "
            "check that the IMU and the images come from the same recording"
        )
    return best, float(corr[k]), offsets, corr


def hand_eye(rotvec_cam: np.ndarray, rotvec_body: np.ndarray) -> np.ndarray:
    """Step 2: the (3, 3) body_R_cam minimising sum |a_body - R a_cam|^2 (Kabsch)."""
    u, _, vt = np.linalg.svd(rotvec_body.T @ rotvec_cam)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def _residuals(x: np.ndarray, R0: Rotation, turns: CameraTurns, imu: ImuSeries, offset0: float) -> np.ndarray:
    R = R0 * Rotation.from_rotvec(x[:3])
    d = offset0 + x[3] * 1e6  # x[3] in ms, for a well-scaled problem
    gyro = GyroIntegral(imu, x[4:7])
    body_turn = gyro.between(turns.t0_ns, turns.t1_ns, d)
    predicted = R * Rotation.from_rotvec(turns.rotvec) * R.inv()
    return (body_turn.inv() * predicted).as_rotvec().ravel()


def check_rotation(gyro: GyroIntegral, duration_s: float) -> None:
    """CalibrationError when the gyro says the capture hardly turned (module constants)."""
    edges = np.arange(gyro.ts[0], gyro.ts[-1], SPEED_BIN_S)
    if len(edges) < 3:
        raise CalibrationError(f"the IMU record is {duration_s:.2f} s long: too short for a calibration")
    t_ns = gyro.t0_ns + np.round(edges * 1e9).astype(np.int64)
    rate = gyro.between(t_ns[:-1], t_ns[1:]).as_rotvec() / SPEED_BIN_S  # mean rate per bin, body frame
    speed = float(np.sqrt(np.sum(np.var(rate, axis=0))))
    if speed < MIN_RMS_SPEED_RAD_S:
        raise CalibrationError(
            f"the capture hardly rotates (RMS angular speed {np.rad2deg(speed):.1f} deg/s over {duration_s:.1f} s; "
            f"at least {np.rad2deg(MIN_RMS_SPEED_RAD_S):g} deg/s is needed): film the board while turning the phone "
            "about all three axes"
        )


def align_rotation(
    steps: CameraTurns, turns: CameraTurns, imu: ImuSeries, max_offset_s: float = 0.2
) -> RotationAlignment:
    """Steps 1-3 of the module docstring: `steps` are the camera's turns between consecutive frames (step 1),
    `turns` those between frames about PAIR_SPAN_S apart (steps 2 and 3)."""
    gyro = GyroIntegral(imu)
    check_rotation(gyro, (gyro.span_ns[1] - gyro.span_ns[0]) * 1e-9)
    offset0, corr, tried_ns, corr_curve = xcorr_offset(steps, gyro, max_offset_s)
    lo, hi = gyro.span_ns
    margin = 0.05e9 + abs(offset0)
    keep = (turns.t0_ns - margin >= lo) & (turns.t1_ns + margin <= hi)
    sel = CameraTurns(turns.t0_ns[keep], turns.t1_ns[keep], turns.rotvec[keep])
    if len(sel.t0_ns) < MIN_PAIRS:
        raise CalibrationError(f"only {len(sel.t0_ns)} frame pairs for the rotation; at least {MIN_PAIRS} are needed")
    body = gyro.between(sel.t0_ns, sel.t1_ns, offset0).as_rotvec()
    R0 = Rotation.from_matrix(hand_eye(sel.rotvec, body))
    # Outlier pairs (a wrong board pose, a bad essential matrix): far off the closed-form solution.
    miss = np.linalg.norm(body - R0.apply(sel.rotvec), axis=1)
    good = miss <= max(OUTLIER_FACTOR * float(np.median(miss)), OUTLIER_FLOOR_RAD)
    if not good.all():
        log.info("rotation: %d of %d pairs dropped as outliers", int((~good).sum()), len(good))
        sel = CameraTurns(sel.t0_ns[good], sel.t1_ns[good], sel.rotvec[good])
        R0 = Rotation.from_matrix(hand_eye(sel.rotvec, body[good]))
    sol = least_squares(_residuals, np.zeros(7), args=(R0, sel, imu, offset0), x_scale=[1e-3] * 3 + [1.0] + [1e-3] * 3)
    r = sol.fun
    dof = max(r.size - 7, 1)
    sigma2 = float(r @ r) / dof
    cov = sigma2 * np.linalg.pinv(sol.jac.T @ sol.jac)
    R = R0 * Rotation.from_rotvec(sol.x[:3])
    # The perturbation is on the right (camera axes); about the body axes the covariance is R cov R^T.
    cov_body = R.as_matrix() @ cov[:3, :3] @ R.as_matrix().T
    a = sel.rotvec
    axis_turn = np.sqrt(np.linalg.eigvalsh(a.T @ a / len(a)))
    log.info("rotation: %d pairs, residual RMS %.3f deg", len(a), np.rad2deg(np.sqrt(sigma2)))
    return RotationAlignment(
        body_R_cam=R.as_matrix(),
        offset_ns=offset0 + float(sol.x[3]) * 1e6,
        offset_xcorr_ns=offset0,
        correlation=corr,
        gyro_bias_rad_s=np.asarray(sol.x[4:7]),
        rotation_std_rad=np.sqrt(np.maximum(np.diag(cov_body), 0.0)),
        offset_std_ns=float(np.sqrt(max(cov[3, 3], 0.0))) * 1e6,
        residual_rms_rad=float(np.sqrt(np.mean(r**2) * 3)),
        pairs=len(a),
        axis_turn_rad=axis_turn,
        xcorr_offsets_ns=tried_ns,
        xcorr=corr_curve,
        steps=steps,
    )
