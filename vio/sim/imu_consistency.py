"""How well a capture's IMU agrees with its ground truth: the measure behind the semi-real gap (issue 16).

For a capture whose ground truth is written at the IMU's times (`vio simulate ... --real-imu`, or any simulated
capture), the motion the IMU should have measured follows from the ground truth: the body rate from consecutive
orientations and the specific force R^T (a - g) from the velocity's central differences (the ground truth is a
smooth spline, so differences over one 5 ms sample are exact to far below any IMU noise). The residual
IMU - (that motion + the ground truth's biases) is then compared with the noise the capture declares:

- its Allan deviation at tau = 0.1, 1 and 10 s against the declared noise's at the same tau
  (`sqrt(N^2 / tau + K^2 tau / 3)`, white noise N and random walk K): the effective noise the estimator meets
  between keyframes (the ground truth's biases are removed, so a random walk as declared would leave less);
- dead reckoning over short windows (0.15 s, a keyframe interval; 0.5 s; 1 s) from the ground-truth state with the
  capture's IMU, against the same with a simulated IMU that has exactly the declared white noise: how much worse the
  IMU predicts the ground truth than its calibration says it should.

A real IMU that disagrees with the ground truth by far more than its declared noise either has more noise than
declared (vibration, bias instability) or the ground truth is less accurate than the IMU: on a semi-real capture
either makes the IMU and the rendered vision disagree.

- the regression slopes between the two accelerations (world frame, gravity and the ground truth's biases removed,
  means over `SLOPE_BLOCK_S` blocks): `<a_gt, a_imu> / <a_gt, a_gt>` and `<a_gt, a_imu> / <a_imu, a_imu>`. A
  semi-real capture's images follow the ground truth, so the estimator fits the IMU to the ground truth's motion:
  acceleration in the ground truth that the IMU did not measure (or an IMU that reads dynamic accelerations too
  small) makes the first slope less than 1 and the metric scale comes out that much too small (errors in the
  regressor attenuate the fit). Both slopes below 1 mean that both accelerations hold error; a pure scale factor k
  of the IMU would give k and 1/k.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from vio.calibrate.allan import overlapping_adev
from vio.errors import CaptureError
from vio.geometry import quat_wxyz_to_R
from vio.records import GRAVITY_WORLD

WINDOWS_S = (0.15, 0.5, 1.0)
TAUS_S = (0.1, 1.0, 10.0)
SLOPE_BLOCK_S = 0.5


@dataclass(frozen=True)
class ImuConsistency:
    """The residual of a capture's IMU against its ground truth (module docstring)."""

    gyro_adev_ratio: dict[float, float]  # tau s -> residual Allan deviation / the declared noise's (median axis)
    acc_adev_ratio: dict[float, float]
    prediction: dict[float, tuple[float, float, float, float]]  # window s -> (position rms m, rotation rms deg) for
    # the capture's IMU, then for a simulated IMU with the declared white noise
    acc_slope: tuple[float, float] = (float("nan"), float("nan"))  # <gt, imu>/<gt, gt>, <gt, imu>/<imu, imu>


def _truth(t_ns: np.ndarray, q_wxyz: np.ndarray, v_world: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(world_R_body (N,3,3), body rate (N,3) rad/s, specific force (N,3) m/s^2) at interior samples (N-2)."""
    R = quat_wxyz_to_R(q_wxyz).reshape(-1, 3, 3)
    t = (t_ns - t_ns[0]).astype(np.float64) * 1e-9
    dt2 = (t[2:] - t[:-2])[:, None]
    omega = Rotation.from_matrix(np.einsum("nji,njk->nik", R[:-2], R[2:])).as_rotvec() / dt2
    a_world = (v_world[2:] - v_world[:-2]) / dt2
    Rm = R[1:-1]
    return Rm, omega, np.einsum("nji,nj->ni", Rm, a_world - GRAVITY_WORLD)


def imu_consistency(capture: str | Path, skip_s: float = 0.0, seed: int = 0) -> ImuConsistency:
    """The consistency of an ASL capture's IMU with its ground truth written at the IMU's times (the first
    `skip_s` seconds left out, e.g. a vehicle standing with its rotors on)."""
    from vio.readers.asl import read_asl

    cap = read_asl(capture)
    imu, gt, cal = cap.imu, cap.ground_truth, cap.imu_calib
    if imu is None or gt is None or cal is None or not np.array_equal(imu.t_ns, gt.t_ns):
        raise CaptureError("needs an IMU, its noise calibration and a ground truth at the IMU's times", capture)
    R, w_true, f_true = _truth(gt.t_ns, gt.q_wxyz, gt.v_world)
    keep = slice(1, -1)
    t_s = (gt.t_ns[keep] - gt.t_ns[0]) * 1e-9
    sel = t_s >= skip_s
    rate = 1e9 / float(np.median(np.diff(imu.t_ns)))
    gyro = imu.gyro[keep][sel] - gt.b_w[keep][sel]
    acc = imu.acc[keep][sel] - gt.b_a[keep][sel]
    R, w_true, f_true, t_s = R[sel], w_true[sel], f_true[sel], t_s[sel]
    p, v = gt.p_world[keep][sel], gt.v_world[keep][sel]
    ratios = []
    for res, density, walk in (
        (gyro - w_true, cal.gyroscope_noise_density, cal.gyroscope_random_walk),
        (acc - f_true, cal.accelerometer_noise_density, cal.accelerometer_random_walk),
    ):
        adev = [overlapping_adev(res[:, k], rate) for k in range(3)]
        declared = {tau: np.sqrt(density**2 / tau + walk**2 * tau / 3.0) for tau in TAUS_S}  # IEEE 952
        ratios.append(
            {tau: float(np.median([np.interp(tau, taus, ad) for taus, ad in adev]) / declared[tau]) for tau in TAUS_S}
        )
    rng = np.random.default_rng(seed)
    sim_gyro = w_true + rng.normal(0.0, cal.gyroscope_noise_density * np.sqrt(rate), w_true.shape)
    sim_acc = f_true + rng.normal(0.0, cal.accelerometer_noise_density * np.sqrt(rate), f_true.shape)
    prediction = {}
    for window in WINDOWS_S:
        n = int(round(window * rate))
        starts = np.arange(0, len(t_s) - n - 1, max(1, int(rate // 2)))
        real = np.array([_dead_reckon(t_s, R, p, v, gyro, acc, i, n) for i in starts])
        sim = np.array([_dead_reckon(t_s, R, p, v, sim_gyro, sim_acc, i, n) for i in starts])
        rms = lambda e: np.sqrt(np.mean(e**2, axis=0))  # noqa: E731
        prediction[window] = (*rms(real), *rms(sim))
    return ImuConsistency(ratios[0], ratios[1], prediction, _acc_slopes(t_s, R, acc, v, rate))


def _acc_slopes(t_s, R, acc, v, rate: float) -> tuple[float, float]:
    """The two regression slopes between the IMU's and the ground truth's world accelerations (module docstring)."""
    a_imu = np.einsum("nij,nj->ni", R, acc) + GRAVITY_WORLD
    n = max(int(round(SLOPE_BLOCK_S * rate)), 1)
    i0 = np.arange(0, len(t_s) - n, n)
    if len(i0) < 2:
        return float("nan"), float("nan")
    a_gt = (v[i0 + n] - v[i0]) / (t_s[i0 + n] - t_s[i0])[:, None]
    a_im = np.add.reduceat(a_imu[: i0[-1] + n], i0, axis=0)[: len(i0)] / n
    cross = float(np.sum(a_gt * a_im))
    return cross / float(np.sum(a_gt**2)), cross / float(np.sum(a_im**2))


def _dead_reckon(t_s, R, p, v, gyro, acc, i0: int, n: int) -> tuple[float, float]:
    """Position (m) and rotation (deg) error after integrating samples i0..i0+n-1 from the true state at i0."""
    Rk, pk, vk = R[i0].copy(), p[i0].copy(), v[i0].copy()
    for i in range(i0, i0 + n):
        dt = t_s[i + 1] - t_s[i]
        a_w = Rk @ acc[i] + GRAVITY_WORLD
        pk, vk = pk + vk * dt + 0.5 * a_w * dt * dt, vk + a_w * dt
        Rk = Rk @ Rotation.from_rotvec(gyro[i] * dt).as_matrix()
    dR = Rotation.from_matrix(R[i0 + n].T @ Rk).as_rotvec()
    return float(np.linalg.norm(pk - p[i0 + n])), float(np.degrees(np.linalg.norm(dR)))


def consistency_text(c: ImuConsistency) -> str:
    """The measure as lines a person reads."""
    lines = ["residual Allan deviation / the declared noise's (white + random walk) at tau:"]
    for name, r in (("gyro", c.gyro_adev_ratio), ("acc", c.acc_adev_ratio)):
        lines.append(f"  {name}: " + ", ".join(f"{tau:g} s {v:.1f}x" for tau, v in r.items()))
    lines.append("dead reckoning from the ground truth (rms): this IMU | an IMU with the declared white noise")
    for w, (pr, rr, ps, rs) in c.prediction.items():
        lines.append(f"  {w:g} s: {pr * 1e3:.2f} mm, {rr:.3f} deg | {ps * 1e3:.2f} mm, {rs:.3f} deg")
    fwd, rev = c.acc_slope
    lines.append(
        f"acceleration slopes over {SLOPE_BLOCK_S:g} s blocks: IMU on ground truth {fwd:.4f}, ground truth on IMU "
        f"{rev:.4f} (a semi-real run's scale reads about {100 * (fwd - 1):+.2f} % from the first)"
    )
    return "\n".join(lines)
