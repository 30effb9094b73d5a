"""The metric scale a capture's IMU gives when the images are perfect (issue 15): the estimator's own IMU factors in a
batch graph where the trajectory's shape is known up to a similarity.

The graph: a keyframe every `kf_interval_s` with pose, velocity and bias; gtsam's `CombinedImuFactor` between them
from the estimator's preintegration (`frontend.preintegration`, the capture's Kalibr noise); the estimator's prior
on the first bias; the first pose fixed at the truth (the gauge). The images are replaced by a *shape factor* per
keyframe: its position relative to the first one is `s * R_g * (q_k - q_0)`, with q the ground-truth positions and
three unknowns shared by all keyframes: the scale s, a rotation R_g (the images do not know gravity) and, through
the first pose, the offset. Rotations come from the gyro and, with `rotations="relative"`, from exact relative
rotations between keyframes (what the images measure), or are held at the truth (`"truth"`).

With a tight shape sigma (the default, 0.1 mm) this is the IMU's own limit: the posterior sigma of s and, over
noise draws (seeds), the spread and bias of its optimum, to compare `vio run` with. `angular=True` makes the shape
cost behave as the images' does: its residual is divided by s, so a metric deformation costs less in a larger
reconstruction (pixels are angles: the same metric error seen from s times further away is s times smaller).
With an exact shape and a soft angular factor (images trusted less than they deserve) the scale reads large; with
`shape_noise_m` equal to the factor's sigma (the images' noise model matched) it does not (BENCHMARKS, issue 15).

    python -m vio.bench.scale_shape CAPTURE [CAPTURE ...] [--rotations relative|truth|gyro] [--shape-sigma-m M]
        [--angular] [--kf-interval-s S]
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import gtsam
import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from vio.capture import Capture
from vio.config import load_config

ROTATIONS = ("relative", "truth", "gyro")
_S = gtsam.symbol("s", 0)  # the scale (Vector1)
_G = gtsam.symbol("g", 0)  # the shape's rotation into the world (Rot3)


def _x(k: int) -> int:
    return gtsam.symbol("x", k)


def _v(k: int) -> int:
    return gtsam.symbol("v", k)


def _b(k: int) -> int:
    return gtsam.symbol("b", k)


@dataclass(frozen=True)
class ShapeScale:
    """The optimum and posterior of the scale in the perfect-images graph of one capture."""

    scale_error: float  # s - 1 at the optimum (0.01 = the trajectory 1 % too large)
    sigma_rel: float  # posterior sigma of s (marginal covariance), fraction; nan when not computable
    keyframes: int
    gauge_rotation_deg: float  # the optimum's R_g: how far the shape turned to fit gravity


def _skew(w: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def shape_factor(k: int, dq: np.ndarray, sigma_m: float, angular: bool) -> gtsam.CustomFactor:
    """Keyframe k's position relative to keyframe 0 is s R_g dq (dq: the true relative position, m)."""
    dq = np.asarray(dq, float)

    def error(_factor, values: gtsam.Values, jac: list[np.ndarray] | None) -> np.ndarray:
        xk, x0 = values.atPose3(_x(k)), values.atPose3(_x(0))
        s = float(values.atVector(_S)[0])
        rg = values.atRot3(_G).matrix()
        w = rg @ dq
        e = (xk.translation() - x0.translation()) - s * w
        d = s if angular else 1.0
        if jac is not None:
            jac[0] = np.hstack([np.zeros((3, 3)), xk.rotation().matrix()]) / d
            jac[1] = -np.hstack([np.zeros((3, 3)), x0.rotation().matrix()]) / d
            jac[2] = (-w / d - (e / s**2 if angular else 0.0)).reshape(3, 1)
            jac[3] = s * rg @ _skew(dq) / d
        return e / d

    return gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(3, sigma_m), [_x(k), _x(0), _S, _G], error)


def shape_scale(
    cap: Capture,
    rotations: str = "relative",
    shape_sigma_m: float = 1e-4,
    angular: bool = False,
    kf_interval_s: float = 0.15,
    shape_noise_m: float = 0.0,
    noise_seed: int = 0,
) -> ShapeScale:
    """The perfect-images scale of a simulated capture (it needs ground truth, an IMU and its noise calibration).
    `shape_noise_m` disturbs each keyframe's true relative position by white noise of that sigma (seed
    `noise_seed`): images with an error the shape factor's sigma can match."""
    from frontend.preintegration import ImuPreintegrator

    if rotations not in ROTATIONS:
        raise ValueError(f"rotations must be one of {', '.join(ROTATIONS)}, not {rotations!r}")
    gt, imu = cap.ground_truth, cap.imu
    if gt is None or imu is None or cap.imu_calib is None:
        raise ValueError("the capture needs ground truth, an IMU stream and the IMU's noise calibration")
    cfg = load_config()
    t = gt.t_ns.astype(float)
    lo, hi = max(gt.t_ns[0], imu.t_ns[0]), min(gt.t_ns[-1], imu.t_ns[-1])
    tk = np.arange(lo + 1, hi, int(kf_interval_s * 1e9), dtype=np.int64)
    if len(tk) < 3:
        raise ValueError("the capture is too short for three keyframes")
    R = Slerp(t, Rotation.from_quat(gt.q_wxyz[:, [1, 2, 3, 0]]))(tk.astype(float)).as_matrix()

    def at(col: np.ndarray, when: np.ndarray) -> np.ndarray:
        return np.column_stack([np.interp(when.astype(float), t, col[:, i]) for i in range(3)])

    P, Vw = at(gt.p_world, tk), at(gt.v_world, tk)
    b0 = gtsam.imuBias.ConstantBias(at(gt.b_a, tk[:1])[0], at(gt.b_w, tk[:1])[0])
    pre = ImuPreintegrator(imu, cap.imu_calib, cfg.imu)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    zero = gtsam.imuBias.ConstantBias()
    dq = (
        P
        - P[0]
        + np.random.default_rng(noise_seed).normal(0.0, shape_noise_m, P.shape) * (np.arange(len(P)) > 0)[:, None]
    )
    for k in range(len(tk)):
        values.insert(_x(k), gtsam.Pose3(gtsam.Rot3(R[k]), P[k]))
        values.insert(_v(k), Vw[k])
        values.insert(_b(k), b0)
        if k:
            pim = pre.between(int(tk[k - 1]), int(tk[k]), zero).pim
            graph.add(gtsam.CombinedImuFactor(_x(k - 1), _v(k - 1), _x(k), _v(k), _b(k - 1), _b(k), pim))
            graph.add(shape_factor(k, dq[k], shape_sigma_m, angular))
    values.insert(_S, np.array([1.0]))
    values.insert(_G, gtsam.Rot3())
    exact = gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)
    graph.add(gtsam.PriorFactorPose3(_x(0), gtsam.Pose3(gtsam.Rot3(R[0]), P[0]), exact))
    ini = cfg.initialisation
    graph.add(gtsam.PriorFactorConstantBias(_b(0), zero, gtsam.noiseModel.Diagonal.Sigmas(
        np.array([ini.bias_sigma_acc] * 3 + [ini.bias_sigma_gyro] * 3))))  # fmt: skip
    rot_only = gtsam.noiseModel.Diagonal.Sigmas(np.array([1e-6] * 3 + [1e3] * 3))  # Pose3 tangent: rotation first
    for k in range(1, len(tk)):
        if rotations == "truth":
            graph.add(gtsam.PriorFactorPose3(_x(k), gtsam.Pose3(gtsam.Rot3(R[k]), P[k]), rot_only))
        elif rotations == "relative":
            rel = gtsam.Pose3(gtsam.Rot3(R[k - 1].T @ R[k]), np.zeros(3))
            graph.add(gtsam.BetweenFactorPose3(_x(k - 1), _x(k), rel, rot_only))
    if rotations == "truth":
        graph.add(gtsam.PriorFactorRot3(_G, gtsam.Rot3(), gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(100)
    params.setRelativeErrorTol(1e-10)
    params.setAbsoluteErrorTol(1e-10)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    s = float(result.atVector(_S)[0])
    try:
        sigma = float(np.sqrt(gtsam.Marginals(graph, result).marginalCovariance(_S)[0, 0]))
    except RuntimeError:
        sigma = float("nan")
    turn = float(np.degrees(np.linalg.norm(gtsam.Rot3.Logmap(result.atRot3(_G)))))
    return ShapeScale(s - 1.0, sigma, len(tk), turn)


def main(argv: list[str] | None = None) -> int:
    from vio.errors import VioError
    from vio.readers import open_capture

    ap = argparse.ArgumentParser(prog="python -m vio.bench.scale_shape", description=__doc__.splitlines()[0])
    ap.add_argument("captures", nargs="+", help="simulated captures (they carry ground truth)")
    ap.add_argument(
        "--rotations",
        choices=ROTATIONS,
        default="relative",
        help="what fixes the rotations besides the gyro (default: exact relative rotations)",
    )
    ap.add_argument("--shape-sigma-m", type=float, default=1e-4, help="sigma of each keyframe's shape factor, m")
    ap.add_argument("--angular", action="store_true", help="the shape cost scales as the images' (divided by s)")
    ap.add_argument("--kf-interval-s", type=float, default=0.15,
                    help="keyframe spacing, s (the estimator's is about 0.15 s on the orbit)")  # fmt: skip
    ap.add_argument("--shape-noise-m", type=float, default=0.0,
                    help="white noise on each keyframe's shape, m (the i-th capture's draw: seed i)")  # fmt: skip
    args = ap.parse_args(argv)
    errors = []
    print("capture | keyframes | scale error % | posterior sigma % | shape turned deg")
    for i, path in enumerate(args.captures):
        try:
            cap = open_capture(path, needs=("imu",))
            res = shape_scale(cap, args.rotations, args.shape_sigma_m, args.angular, args.kf_interval_s,
                              shape_noise_m=args.shape_noise_m, noise_seed=i)  # fmt: skip
        except (VioError, ValueError) as exc:
            print(f"{path}: {exc}")
            return 2
        errors.append(100 * res.scale_error)
        print(f"{Path(path).name} | {res.keyframes} | {100 * res.scale_error:+.3f} | {100 * res.sigma_rel:.3f} | "
              f"{res.gauge_rotation_deg:.3f}")  # fmt: skip
    e = np.array(errors)
    print(f"{len(e)} captures: mean {e.mean():+.3f} %, median {np.median(e):+.3f} %, median |error| "
          f"{np.median(np.abs(e)):.3f} %" + (f", sd {e.std(ddof=1):.3f} %" if len(e) > 1 else ""))  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
