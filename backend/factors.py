"""Factor builders for the visual-inertial graph.

Camera model: the tracks' distorted pixels are undistorted exactly (radtan Gauss-Newton, `CameraCalib`) and
re-projected with the same focal lengths and principal point, so the projection factors use a `Cal3_S2` pinhole
with `body_P_sensor = body_T_cam`; the pixel noise model keeps its meaning (distortion is small near the centre).
"""

from __future__ import annotations

import gtsam
import numpy as np

from backend.keys import B, L, V, X
from vio.records import CameraCalib

# Pose3 tangent order is (rotation, translation); NavState-like priors follow it.


def calibration(camera: CameraCalib) -> tuple[gtsam.Cal3_S2, gtsam.Pose3]:
    """The pinhole calibration of the undistorted pixels and body_P_sensor (camera pose in the IMU frame)."""
    K = gtsam.Cal3_S2(camera.fx, camera.fy, 0.0, camera.cx, camera.cy)
    return K, gtsam.Pose3(np.asarray(camera.body_T_cam, float))


def undistorted_px(camera: CameraCalib, uv_distorted: np.ndarray) -> np.ndarray:
    """(N, 2) distorted pixels -> (N, 2) undistorted pixels of the same pinhole K."""
    if not np.any(camera.dist):
        return np.asarray(uv_distorted, float).reshape(-1, 2)
    xn = camera.undistort_to_normalized(uv_distorted)
    return np.column_stack([camera.fx * xn[:, 0] + camera.cx, camera.fy * xn[:, 1] + camera.cy])


def pixel_noise(sigma_px: float, huber_k: float) -> gtsam.noiseModel.Base:
    """Isotropic 2D pixel noise with a Huber loss (threshold in sigmas)."""
    base = gtsam.noiseModel.Isotropic.Sigma(2, sigma_px)
    return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(huber_k), base)


class PixelNoise:
    """Projection noise that grows with the observation's age: sigma = sigma_px + per_s * age_s, where age_s is the
    time since the view that started the track's current unbroken run of keyframe views. A KLT track drifts off its
    first position like a random walk (measured: median error 0.20 px after 1-2 frames, 0.43 px after 6-10, 1.10 px
    after 31-50; `python -m vio.bench.klt_error`), so a young view deserves more weight than an old one. per_s = 0
    is one sigma for every view. Sigmas are rounded to `step_px` (one gtsam noise model per level)."""

    def __init__(self, sigma_px: float, per_s: float, huber_k: float, step_px: float = 0.05) -> None:
        self.sigma_px, self.per_s, self.huber_k, self.step_px = float(sigma_px), float(per_s), huber_k, step_px
        self._models: dict[int, gtsam.noiseModel.Base] = {}

    def sigma(self, age_s: float) -> float:
        """The sigma of a view `age_s` old, px (before rounding)."""
        return self.sigma_px + self.per_s * max(float(age_s), 0.0)

    def at(self, age_s: float = 0.0) -> gtsam.noiseModel.Base:
        """The robust noise model of a view `age_s` old."""
        level = max(int(round(self.sigma(age_s) / self.step_px)), 1) if self.per_s > 0 else 0
        model = self._models.get(level)
        if model is None:
            model = pixel_noise(level * self.step_px if level else self.sigma_px, self.huber_k)
            self._models[level] = model
        return model


def projection_factor(
    uv_px: np.ndarray, k: int, track_id: int, K: gtsam.Cal3_S2, body_P_cam: gtsam.Pose3, noise: gtsam.noiseModel.Base
) -> gtsam.GenericProjectionFactorCal3_S2:
    """Observation of landmark L(track_id) at undistorted pixel uv_px from the camera of keyframe k."""
    return gtsam.GenericProjectionFactorCal3_S2(
        np.asarray(uv_px, float), noise, X(k), L(int(track_id)), K, False, False, body_P_cam
    )


def imu_factor(k0: int, k1: int, pim: gtsam.PreintegratedCombinedMeasurements) -> gtsam.CombinedImuFactor:
    """Preintegrated IMU and bias random walk between keyframes k0 and k1."""
    return gtsam.CombinedImuFactor(X(k0), V(k0), X(k1), V(k1), B(k0), B(k1), pim)


def pose_prior_gravity_aware(
    k: int, world_T_body: gtsam.Pose3, sigma_tilt_rad: float, sigma_yaw_rad: float, sigma_pos_m: float
) -> gtsam.PriorFactorPose3:
    """Prior on X(k): tight on yaw and position (the unobservable gauge), loose on roll/pitch (gravity observes them).

    The rotation covariance is set in world axes (x, y tilt; z yaw) and rotated into the body tangent space.
    """
    R = world_T_body.rotation().matrix()
    cov_world = np.diag([sigma_tilt_rad**2, sigma_tilt_rad**2, sigma_yaw_rad**2])
    cov = np.zeros((6, 6))
    cov[:3, :3] = R.T @ cov_world @ R
    cov[3:, 3:] = np.eye(3) * sigma_pos_m**2
    return gtsam.PriorFactorPose3(X(k), world_T_body, gtsam.noiseModel.Gaussian.Covariance(cov))


def velocity_prior(k: int, v_world: np.ndarray, sigma_m_s: float) -> gtsam.PriorFactorVector:
    return gtsam.PriorFactorVector(V(k), np.asarray(v_world, float), gtsam.noiseModel.Isotropic.Sigma(3, sigma_m_s))


def bias_prior(
    k: int, bias: gtsam.imuBias.ConstantBias, sigma_acc: float, sigma_gyro: float
) -> gtsam.PriorFactorConstantBias:
    """Prior on B(k); gtsam's bias vector order is (accelerometer m/s^2, gyro rad/s)."""
    sig = np.array([sigma_acc] * 3 + [sigma_gyro] * 3)
    return gtsam.PriorFactorConstantBias(B(k), bias, gtsam.noiseModel.Diagonal.Sigmas(sig))


def position_factor(k: int, p_world: np.ndarray, sigma_m: float) -> gtsam.GPSFactor:
    """A known body position (tripod ring, turntable, GNSS) of keyframe k, metres, world frame."""
    return gtsam.GPSFactor(X(k), np.asarray(p_world, float), gtsam.noiseModel.Isotropic.Sigma(3, sigma_m))


def no_motion_factors(
    k0: int, k1: int, sigma_rad: float, sigma_m: float, velocity_sigma_m_s: float
) -> list[gtsam.NonlinearFactor]:
    """Zero-velocity update: V(k1) = 0 and X(k0) == X(k1) (for keyframes detected at rest)."""
    between = gtsam.BetweenFactorPose3(
        X(k0), X(k1), gtsam.Pose3(), gtsam.noiseModel.Diagonal.Sigmas(np.array([sigma_rad] * 3 + [sigma_m] * 3))
    )
    return [between, velocity_prior(k1, np.zeros(3), velocity_sigma_m_s)]


def landmark_prior(j: int, p_world: np.ndarray, sigma_m: float) -> gtsam.PriorFactorPoint3:
    """A weak prior on a new landmark (keeps a barely-constrained point from making the system indeterminate)."""
    return gtsam.PriorFactorPoint3(L(int(j)), np.asarray(p_world, float), gtsam.noiseModel.Isotropic.Sigma(3, sigma_m))
