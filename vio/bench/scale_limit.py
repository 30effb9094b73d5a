"""The information limit of the metric scale that a capture's accelerometer carries (issue 15), from its ground truth.

With the trajectory's shape and orientation known exactly (a perfect camera), the accelerometer measures
`y_k = s * a_body_k + b_k + n_k` (body-frame kinematic acceleration a_body, gravity removed), with white noise n
(the Kalibr density) and a bias b that walks (the Kalibr random walk) from a prior. The only unknown that carries
scale is s. A Kalman filter over the capture's ground-truth accelerations gives the posterior standard deviation of
s: no estimator of that capture's scale can do better. It is close to the closed form

    sigma_s = accelerometer_noise_density / sqrt(integral over the capture of |a_body - mean a_body|^2 dt),

so the scale is observable in proportion to the acceleration the capture carries, not to its length or speed.

    .venv/bin/python -m vio.bench.scale_limit CAPTURE [CAPTURE ...]
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from vio.records import GroundTruth, ImuCalib


@dataclass(frozen=True)
class ScaleLimit:
    """The accelerometer's limit on the relative scale of one capture (1 sigma, fractions)."""

    duration_s: float  # span of the ground truth, s
    excitation: float  # integral of |a_body - mean|^2 dt, (m/s^2)^2 s
    sigma_rel: float  # Kalman-filter posterior sigma of s (bias walking from its prior)
    sigma_rel_bias_known: float  # the same with the bias known at the start (a perfect still start)
    sigma_rel_closed: float  # accelerometer_noise_density / sqrt(excitation)


def body_acceleration(gt: GroundTruth) -> tuple[np.ndarray, np.ndarray]:
    """(t_s (N,), a_body (N, 3) m/s^2): the kinematic acceleration in the body frame, from the ground-truth
    velocities (central differences) rotated by world_R_body^T."""
    t_s = (gt.t_ns - gt.t_ns[0]) * 1e-9
    a_world = np.gradient(np.asarray(gt.v_world, float), t_s, axis=0)
    q = np.asarray(gt.q_wxyz, float)
    return t_s, Rotation.from_quat(q[:, [1, 2, 3, 0]]).inv().apply(a_world)


def scale_sigma(a_body: np.ndarray, dt_s: float, calib: ImuCalib, bias_sigma: float) -> float:
    """Posterior sigma of the scale s from accelerometer samples at spacing dt_s (Kalman filter over
    [s, b_x, b_y, b_z]; s starts diffuse, the bias at `bias_sigma` m/s^2 and walks at the calibration's rate)."""
    sig_n2 = calib.accelerometer_noise_density**2 / dt_s  # discrete white-noise variance per sample
    P = np.diag([1e4, bias_sigma**2, bias_sigma**2, bias_sigma**2])
    q = calib.accelerometer_random_walk**2 * dt_s
    H = np.hstack([np.zeros((3, 1)), np.eye(3)])
    for a in a_body:
        H[:, 0] = a
        S = H @ P @ H.T + np.eye(3) * sig_n2
        K = np.linalg.solve(S, H @ P).T
        P = P - K @ H @ P
        P[1:, 1:] += np.eye(3) * q
    return float(np.sqrt(P[0, 0]))


def scale_limit(gt: GroundTruth, calib: ImuCalib, bias_sigma: float = 0.1) -> ScaleLimit:
    """The accelerometer's scale limit of a capture with ground truth `gt` and IMU noise `calib`; `bias_sigma`
    (m/s^2) is the initial bias prior (the estimator's `initialisation.bias_sigma_acc`)."""
    t_s, a_body = body_acceleration(gt)
    dt = float(np.median(np.diff(t_s)))
    excitation = float(np.sum((a_body - a_body.mean(axis=0)) ** 2) * dt)
    closed = calib.accelerometer_noise_density / np.sqrt(excitation) if excitation > 0 else float("inf")
    return ScaleLimit(
        float(t_s[-1]),
        excitation,
        scale_sigma(a_body, dt, calib, bias_sigma),
        scale_sigma(a_body, dt, calib, 1e-6),
        float(closed),
    )


def main(argv: list[str] | None = None) -> int:
    from vio.errors import VioError
    from vio.readers import open_capture

    ap = argparse.ArgumentParser(prog="python -m vio.bench.scale_limit", description=__doc__.splitlines()[0])
    ap.add_argument("captures", nargs="+", help="simulated captures (they carry ground truth)")
    args = ap.parse_args(argv)
    print("capture | s | excitation (m/s^2)^2 s | sigma % | bias known % | closed form %")
    for path in args.captures:
        try:
            cap = open_capture(path, needs=("imu",))
        except VioError as exc:
            print(f"{path}: {exc}")
            return 2
        if cap.ground_truth is None or cap.imu_calib is None:
            print(f"{path}: needs ground truth and the IMU's noise calibration")
            return 2
        lim = scale_limit(cap.ground_truth, cap.imu_calib)
        print(
            f"{Path(path).name} | {lim.duration_s:.1f} | {lim.excitation:.1f} | {100 * lim.sigma_rel:.3f} | "
            f"{100 * lim.sigma_rel_bias_known:.3f} | {100 * lim.sigma_rel_closed:.3f}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
