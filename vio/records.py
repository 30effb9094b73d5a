"""Typed records passed between stages. Units and frames are in each field's comment.

Frames: world is z-up with gravity (0, 0, -9.81) m/s^2; body is the IMU frame; the camera frame is OpenCV's
(x right, y down, z forward). Transforms are 4x4 homogeneous matrices named `target_T_source`.
Time is integer nanoseconds (`t_ns`); seconds are only used to compute dt.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

GRAVITY_M_S2 = 9.81
GRAVITY_WORLD = np.array([0.0, 0.0, -GRAVITY_M_S2])  # m/s^2, world frame (z up)


@dataclass(frozen=True)
class ImuSample:
    t_ns: int  # sensor time, ns
    gyro: np.ndarray  # (3,) angular rate of body in body frame, rad/s
    acc: np.ndarray  # (3,) specific force (includes the reaction to gravity) in body frame, m/s^2


@dataclass(frozen=True)
class ImuSeries:
    """A whole IMU stream as arrays (the efficient form of a sequence of `ImuSample`)."""

    t_ns: np.ndarray  # (N,) int64, strictly increasing, ns
    gyro: np.ndarray  # (N, 3) rad/s, body frame
    acc: np.ndarray  # (N, 3) m/s^2 specific force, body frame

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    def __iter__(self) -> Iterator[ImuSample]:
        for i in range(len(self)):
            yield ImuSample(int(self.t_ns[i]), self.gyro[i], self.acc[i])

    def window(self, t0_ns: int, t1_ns: int) -> ImuSeries:
        """Samples with t0_ns <= t <= t1_ns."""
        i0, i1 = np.searchsorted(self.t_ns, [t0_ns, t1_ns], side="left")
        i1 = i1 + 1 if i1 < len(self) and self.t_ns[i1] == t1_ns else i1
        return ImuSeries(self.t_ns[i0:i1], self.gyro[i0:i1], self.acc[i0:i1])


@dataclass(frozen=True)
class Frame:
    t_ns: int  # exposure mid-point in sensor time, ns
    cam_id: int  # camera index (0 for the only camera of a phone capture)
    image: np.ndarray  # (H, W) uint8 grayscale, or (H, W, 3) uint8 BGR


@dataclass(frozen=True)
class FeatureTracks:
    t_ns: int  # frame time, ns
    ids: np.ndarray  # (N,) int64 track ids, stable across frames
    uv: np.ndarray  # (N, 2) float64 pixel coordinates in the *distorted* image, px
    cam_id: int = 0
    # (N, 2) image velocity of each track, distorted px/s (backward difference to the previous frame, 0 for a new
    # track; frontend/track_velocity.py); None when not measured
    uv_per_s: np.ndarray | None = None


@dataclass(frozen=True)
class CameraCalib:
    """Pinhole camera with radial-tangential (radtan, OpenCV k1 k2 p1 p2) distortion."""

    width: int  # px
    height: int  # px
    fx: float  # px
    fy: float  # px
    cx: float  # px
    cy: float  # px
    dist: np.ndarray  # (4,) radtan k1, k2, p1, p2
    body_T_cam: np.ndarray  # (4, 4) camera pose in the body (IMU) frame, Kalibr's T_BS
    rate_hz: float = 20.0  # nominal frame rate, Hz

    @property
    def K(self) -> np.ndarray:  # noqa: N802 - the conventional name
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def project(self, p_cam: np.ndarray) -> np.ndarray:
        """Project (N, 3) points in the camera frame to (N, 2) distorted pixels (no visibility check)."""
        p_cam = np.atleast_2d(np.asarray(p_cam, dtype=float))
        xn = p_cam[:, :2] / p_cam[:, 2:3]
        return self.distort_normalized(xn)

    def distort_normalized(self, xn: np.ndarray) -> np.ndarray:
        """Map (N, 2) undistorted normalized coordinates to (N, 2) distorted pixels."""
        k1, k2, p1, p2 = (float(c) for c in self.dist)
        x, y = xn[:, 0], xn[:, 1]
        r2 = x * x + y * y
        radial = 1.0 + k1 * r2 + k2 * r2 * r2
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        return np.column_stack([self.fx * xd + self.cx, self.fy * yd + self.cy])

    def undistort_to_normalized(self, uv: np.ndarray, iterations: int = 20) -> np.ndarray:
        """Map (N, 2) distorted pixels to (N, 2) undistorted normalized coordinates (Gauss-Newton on radtan)."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        target = np.column_stack([(uv[:, 0] - self.cx) / self.fx, (uv[:, 1] - self.cy) / self.fy])
        k1, k2, p1, p2 = (float(c) for c in self.dist)
        # the products are grouped as `a * b * c` groups them, so the result is the same to the last bit whatever
        # is reused between the terms (the Jacobian is symmetric: j12 == j21)
        p1_2, p2_2, p1_6, p2_6, k1_2, k2_4 = 2.0 * p1, 2.0 * p2, 6.0 * p1, 6.0 * p2, 2.0 * k1, 4.0 * k2
        tx, ty = target[:, 0].copy(), target[:, 1].copy()
        x, y = tx.copy(), ty.copy()
        for _ in range(iterations):
            xx, yy, xy = x * x, y * y, x * y
            r2 = xx + yy
            radial = 1.0 + k1 * r2 + k2 * r2 * r2
            drad = k1_2 + k2_4 * r2  # d(radial)/d(r2) * 2
            fx_ = x * radial + p1_2 * x * y + p2 * (r2 + 2.0 * x * x) - tx
            fy_ = y * radial + p1 * (r2 + 2.0 * y * y) + p2_2 * x * y - ty
            j11 = radial + xx * drad + p1_2 * y + p2_6 * x
            j12 = xy * drad + p1_2 * x + p2_2 * y
            j22 = radial + yy * drad + p1_6 * y + p2_2 * x
            det = j11 * j22 - j12 * j12
            dx = (j22 * fx_ - j12 * fy_) / det
            dy = (-j12 * fx_ + j11 * fy_) / det
            x -= dx
            y -= dy
            if max(np.abs(dx).max(initial=0.0), np.abs(dy).max(initial=0.0)) < 1e-14:
                break
        return np.column_stack([x, y])


@dataclass(frozen=True)
class ImuCalib:
    """IMU noise in Kalibr's names and units (continuous-time densities)."""

    gyroscope_noise_density: float  # rad/s/sqrt(Hz)
    accelerometer_noise_density: float  # m/s^2/sqrt(Hz)
    gyroscope_random_walk: float  # rad/s^2/sqrt(Hz)
    accelerometer_random_walk: float  # m/s^3/sqrt(Hz)
    rate_hz: float = 200.0  # nominal sample rate, Hz


@dataclass(frozen=True)
class GroundTruth:
    """Ground-truth body states (EuRoC `state_groundtruth_estimate0` columns)."""

    t_ns: np.ndarray  # (N,) int64, ns
    p_world: np.ndarray  # (N, 3) body position in world, m
    q_wxyz: np.ndarray  # (N, 4) world_R_body as a unit quaternion, w first
    v_world: np.ndarray  # (N, 3) body velocity in world, m/s
    b_w: np.ndarray  # (N, 3) gyro bias, rad/s
    b_a: np.ndarray  # (N, 3) accelerometer bias, m/s^2

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    def world_T_body(self, i: int) -> np.ndarray:
        """(4, 4) pose of sample i."""
        from scipy.spatial.transform import Rotation

        T = np.eye(4)
        w, x, y, z = self.q_wxyz[i]
        T[:3, :3] = Rotation.from_quat([x, y, z, w]).as_matrix()
        T[:3, 3] = self.p_world[i]
        return T


@dataclass(frozen=True)
class Keyframe:
    k: int  # keyframe index (shared by the X(k), V(k), B(k) keys)
    t_ns: int  # keyframe time, ns
    tracks: FeatureTracks  # the features seen in this keyframe
    preintegrated: Any = None  # gtsam.PreintegratedCombinedMeasurements from keyframe k-1 to k (None for k=0)
    imu_gap: bool = False  # True when the IMU had a gap longer than allowed between k-1 and k


@dataclass(frozen=True)
class StateEstimate:
    k: int  # keyframe index
    t_ns: int  # keyframe time, ns
    world_T_body: np.ndarray  # (4, 4) body (IMU) pose in world
    v_world: np.ndarray  # (3,) velocity of the body in world, m/s
    bias_gyro: np.ndarray  # (3,) rad/s
    bias_acc: np.ndarray  # (3,) m/s^2
    landmark_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (M,) track ids
    landmarks_world: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (M, 3) m, world
    solve_ms: float = 0.0  # wall time of the update that produced this estimate, ms


@dataclass(frozen=True)
class LandmarkMap:
    """The estimator's landmarks (in the output frame: the known positions' frame when they were given)."""

    ids: np.ndarray  # (M,) int64 landmark ids (track id plus segment; see backend/keys.py)
    track_ids: np.ndarray  # (M,) int64 the tracker's track id each landmark came from
    points_world: np.ndarray  # (M, 3) m, world
    num_obs: np.ndarray  # (M,) int64 projection factors on each landmark

    def __len__(self) -> int:
        return int(self.ids.shape[0])


@dataclass(frozen=True)
class ReidentificationEvent:
    """A new track re-identified as a landmark already in the map."""

    t_ns: int  # keyframe time of the re-identification, ns
    landmark_id: int  # the old landmark
    uv_px: np.ndarray  # (2,) distorted pixel of the new track in that keyframe
    first_t_ns: int  # time of the landmark's first kept view, ns
    first_uv_px: np.ndarray  # (2,) undistorted pixel of that first view


@dataclass(frozen=True)
class RecoveryEvent:
    """A solver failure the estimator survived by rebuilding from the last good keyframe."""

    k: int  # keyframe whose update failed
    t_ns: int  # its time, ns
    reason: str  # the solver's message
    restart_from_k: int  # the keyframe the smoother was rebuilt from


@dataclass(frozen=True)
class TimeOffsetEstimate:
    """The camera-IMU time offset the estimator used (t_imu = t_cam + offset; the top row's mid-exposure, on top of a
    calibration's timeshift_cam_imu already applied to the frame times) and how it was obtained."""

    estimated: bool  # True: estimated by the estimator (backend/time_offset.py); False: fixed by the config
    value_s: float  # the offset at the end of the run, s
    initial_s: float  # the config's starting value, s
    after_initialisation_s: float | None  # the estimate from the start window, s (None: not estimated there)
    sigma_s: float | None  # standard error of the estimate from the scatter of per-keyframe estimates, s
    num_keyframes: int  # keyframes whose residuals went into the estimate
    readout_s: float  # rolling-shutter readout used (0: global shutter), s
    trace: tuple[tuple[float, float], ...] = ()  # (s since the first keyframe, the offset applied from then, s)
    replayed_keyframes: int = 0  # keyframes re-run with the converged offset (backend/offset_replay.py; 0: none)
    replayed_span_s: float | None = None  # the capture time they span, s
    replayed_from_s: tuple[float, float] | None = None  # (min, max) offset the first pass had placed them with, s


@dataclass(frozen=True)
class EstimatorStats:
    """What the estimator reports about a run (counts, timings, events); `run.json` is built from it."""

    initialisation: str  # "static" | "moving" | "visual" | "" (never initialised)
    keyframe_ms: tuple[float, ...]  # wall time of each keyframe's update (one entry for the whole start), ms
    num_zero_velocity_updates: int
    num_track_splits: int
    num_reidentified: int
    num_loop_flushes: int
    num_position_factors: int
    recoveries: tuple[RecoveryEvent, ...]
    reidentifications: tuple[ReidentificationEvent, ...]
    warnings: tuple[str, ...]
    num_landmarks_revived: int = 0  # old landmarks back in a fixed-lag window after being marginalised
    num_landmarks_merged: int = 0  # retired duplicates of older landmarks left out of the atlas (merge_radius_m)
    num_landmarks_archived: int = 0  # ... and out of the live bookkeeping too (archive_merged)
    num_blind_adjustments: int = 0  # window adjustments at keyframes without a visual constraint
    num_blind_admitted: int = 0  # landmarks admitted over those adjusted poses (backend/blind_admission.py)
    smoother_variables: tuple[int, ...] = ()  # variables in the smoother after each steady-state keyframe
    step_cpu_ms: tuple[float, ...] = ()  # CPU time of each steady-state keyframe's update (no start), ms
    # (wall, CPU) ms of each background step between keyframes (`smoother.background`: relinearisation and
    # marginalisation after the keyframe's estimate is out)
    background_ms: tuple[tuple[float, float], ...] = ()
    scale_sigma_rel: float | None = None  # relative standard deviation of the metric scale, from the graph
    scale_pairs: tuple[tuple[int, int, float, float], ...] = ()  # (k_a, k_b, distance m, its sigma m) behind it
    # (k, t_ns, projection factors on the keyframe's pose in the whole graph) per keyframe, in time order; 0: the
    # keyframe's pose rests on the IMU (or the vision-only motion model) alone
    keyframe_projections: tuple[tuple[int, int, int], ...] = ()
    time_offset: TimeOffsetEstimate | None = None  # the camera-IMU time offset and readout (backend/time_offset.py)
    # times (ns) of the keyframes held by a zero-velocity update or a static start: at rest, they need no visual
    # constraint (run health does not count them as IMU alone)
    still_keyframes: tuple[int, ...] = ()
