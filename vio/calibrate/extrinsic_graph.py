"""Camera-IMU extrinsic and time offset by a GTSAM batch graph: body_T_cam is a variable with a prior.

Variables: the body's pose X(k), velocity V(k) and IMU bias B(k) at every frame that shows the board, the board's
pose in a gravity-aligned world (`n_T_board`, z up) and the extrinsic `body_T_cam`. Factors:
- board: the frame's PnP pose `board_T_cam` (`vio.calibrate.board_motion`, with its covariance) against
  n_T_board^-1 * X(k) * body_T_cam (a Python `gtsam.CustomFactor` on three poses, analytic Jacobians);
- IMU: `ImuFactor` between consecutive frames, preintegrated over [t_k + d, t_k+1 + d] on the IMU clock (d the
  time offset, t_imu = t_cam + d), and a bias random walk (`BetweenFactorConstantBias`);
- priors: the extrinsic (rotation from the hand-eye step, translation from the given calibration, both loose), the
  first bias, and n_T_board's yaw and position (the gauge; its tilt, i.e. gravity in the board frame, is free).
The time offset is refined on the graph: the optimum of the graph's error over d (bounded Brent search around the
rotation step's offset), its one sigma from the error's curvature (the error is -log likelihood: sigma^2 = 1 / e'').
The extrinsic's standard deviations are its marginal covariance at that offset.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from functools import partial

import numpy as np
from scipy.optimize import minimize_scalar
from scipy.spatial.transform import Rotation

from vio.calibrate.board_motion import BoardMotion
from vio.errors import CalibrationError
from vio.records import ImuCalib, ImuSeries

log = logging.getLogger(__name__)

GRAVITY_M_S2 = 9.81
ROT_PRIOR_RAD = np.deg2rad(2.0)  # the extrinsic rotation's prior around the hand-eye result (loose)
TRANS_PRIOR_M = 0.10  # the extrinsic translation's prior around the given calibration's (a phone: within 10 cm)
GYRO_BIAS_PRIOR_RAD_S = 0.02
ACC_BIAS_PRIOR_M_S2 = 0.2
GAUGE_SIGMA = 1e-6  # n_T_board yaw (rad) and position (m)
FREE_SIGMA_RAD = 1.0  # n_T_board tilt
OFFSET_SEARCH_NS = 5e6  # the offset is searched within +-5 ms of the rotation step's
CURVATURE_STEP_NS = 0.5e6


@dataclass(frozen=True)
class GraphSolution:
    body_T_cam: np.ndarray  # (4, 4)
    cov: np.ndarray  # (6, 6) marginal covariance of body_T_cam (right perturbation: rotation rad, translation m)
    offset_ns: float  # t_imu = t_cam + offset
    offset_std_ns: float
    error: float  # the graph's error at the solution (0.5 chi^2)
    frames: int
    gyro_bias_rad_s: np.ndarray  # (3,) at the first frame
    acc_bias_m_s2: np.ndarray  # (3,)
    gravity_board: np.ndarray  # (3,) unit vector, up, in the board frame


def _board_error(measured, this, values, H):
    """Log(Z^-1 * W^-1 * X * E) for the keys (W, X, E); Jacobians on right perturbations of each pose."""
    import gtsam

    W, X, E = (values.atPose3(k) for k in this.keys())
    P = W.inverse().compose(X).compose(E)
    e = gtsam.Pose3.Logmap(measured.between(P))
    if H is not None:
        Jinv = gtsam.Pose3.LogmapDerivative(e)
        H[0] = -Jinv @ P.inverse().AdjointMap()
        H[1] = Jinv @ E.inverse().AdjointMap()
        H[2] = Jinv
    return e


def _interp(t_s: np.ndarray, ts: np.ndarray, values: np.ndarray) -> np.ndarray:
    return np.column_stack([np.interp(t_s, ts, values[:, k]) for k in range(3)])


def _preintegrate(imu: ImuSeries, ts: np.ndarray, a_s: float, b_s: float, params, bias):
    """Preintegrated measurements over [a_s, b_s] (seconds from the IMU's first sample), knots at the samples inside
    and the interpolated end points, each sub-interval with the mean of its two knots' readings."""
    import gtsam

    inside = ts[(ts > a_s) & (ts < b_s)]
    knots = np.concatenate([[a_s], inside, [b_s]])
    gyro, acc = _interp(knots, ts, imu.gyro), _interp(knots, ts, imu.acc)
    pim = gtsam.PreintegratedImuMeasurements(params, bias)
    for i in range(len(knots) - 1):
        dt = knots[i + 1] - knots[i]
        if dt > 0:
            pim.integrateMeasurement(0.5 * (acc[i] + acc[i + 1]), 0.5 * (gyro[i] + gyro[i + 1]), dt)
    return pim


class ExtrinsicGraph:
    """The graph of the module docstring for one capture; `solve(offset_ns)` optimises it at one time offset."""

    def __init__(
        self,
        motion: BoardMotion,
        imu: ImuSeries,
        noise: ImuCalib,
        body_R_cam0: np.ndarray,
        body_t_cam0: np.ndarray,
        offset0_ns: float,
        gyro_bias0: np.ndarray,
    ) -> None:
        import gtsam

        lo = imu.t_ns[0] + abs(offset0_ns) + OFFSET_SEARCH_NS + 1e7
        hi = imu.t_ns[-1] - abs(offset0_ns) - OFFSET_SEARCH_NS - 1e7
        keep = (motion.t_ns >= lo) & (motion.t_ns <= hi)
        if keep.sum() < 10:
            raise CalibrationError(f"only {int(keep.sum())} frames with the board inside the IMU's span")
        self.t_ns = motion.t_ns[keep]
        self.Z = motion.board_T_cam[keep]
        self.cov = motion.cov[keep]
        self.imu = imu
        self.ts = (imu.t_ns - imu.t_ns[0]) * 1e-9
        self.noise = noise
        p = gtsam.PreintegrationParams.MakeSharedU(GRAVITY_M_S2)
        p.setGyroscopeCovariance(noise.gyroscope_noise_density**2 * np.eye(3))
        p.setAccelerometerCovariance(noise.accelerometer_noise_density**2 * np.eye(3))
        p.setIntegrationCovariance(1e-8 * np.eye(3))
        self.params = p
        E0 = np.eye(4)
        E0[:3, :3], E0[:3, 3] = body_R_cam0, body_t_cam0
        self.E0 = E0
        self.key_w, self.key_e = gtsam.symbol("w", 0), gtsam.symbol("e", 0)  # n_T_board, body_T_cam
        self.initial = self._initial_values(E0, offset0_ns, np.asarray(gyro_bias0, float))

    def _initial_values(self, E0: np.ndarray, offset_ns: float, bg: np.ndarray):
        import gtsam
        from gtsam.symbol_shorthand import B, V, X

        # Gravity (up) in the board frame: the mean specific force, turned into the board frame, points up.
        t_s = (self.t_ns - self.imu.t_ns[0]) * 1e-9 + offset_ns * 1e-9
        f = _interp(t_s, self.ts, self.imu.acc)
        board_R_body = self.Z[:, :3, :3] @ E0[:3, :3].T
        up = np.einsum("kij,kj->i", board_R_body, f)
        up /= np.linalg.norm(up)
        n_R_board = Rotation.align_vectors([[0.0, 0.0, 1.0]], [up])[0].as_matrix()
        W = np.eye(4)
        W[:3, :3] = n_R_board
        values = gtsam.Values()
        values.insert(self.key_w, gtsam.Pose3(W))
        values.insert(self.key_e, gtsam.Pose3(E0))
        n_T_body = W @ self.Z @ np.linalg.inv(E0)
        p = n_T_body[:, :3, 3]
        dt = np.gradient((self.t_ns - self.t_ns[0]) * 1e-9)
        v = np.gradient(p, axis=0) / dt[:, None]
        for k in range(len(self.t_ns)):
            values.insert(X(k), gtsam.Pose3(n_T_body[k]))
            values.insert(V(k), v[k])
            values.insert(B(k), gtsam.imuBias.ConstantBias(np.zeros(3), bg))
        return values

    def _graph(self, offset_ns: float):
        import gtsam
        from gtsam.symbol_shorthand import B, V, X

        g = gtsam.NonlinearFactorGraph()
        n = len(self.t_ns)
        for k in range(n):
            model = gtsam.noiseModel.Gaussian.Covariance(self.cov[k])
            g.add(
                gtsam.CustomFactor(model, [self.key_w, X(k), self.key_e], partial(_board_error, gtsam.Pose3(self.Z[k])))
            )
        t_s = (self.t_ns - self.imu.t_ns[0]) * 1e-9 + offset_ns * 1e-9
        zero_bias = gtsam.imuBias.ConstantBias()
        walk = np.concatenate(
            [np.full(3, self.noise.accelerometer_random_walk), np.full(3, self.noise.gyroscope_random_walk)]
        )
        for k in range(n - 1):
            pim = _preintegrate(self.imu, self.ts, t_s[k], t_s[k + 1], self.params, zero_bias)
            g.add(gtsam.ImuFactor(X(k), V(k), X(k + 1), V(k + 1), B(k), pim))
            sig = walk * np.sqrt(max(t_s[k + 1] - t_s[k], 1e-6))
            g.add(gtsam.BetweenFactorConstantBias(B(k), B(k + 1), zero_bias, gtsam.noiseModel.Diagonal.Sigmas(sig)))
        bias_sig = np.concatenate([np.full(3, ACC_BIAS_PRIOR_M_S2), np.full(3, GYRO_BIAS_PRIOR_RAD_S)])
        b0 = self.initial.atConstantBias(B(0))
        g.add(gtsam.PriorFactorConstantBias(B(0), b0, gtsam.noiseModel.Diagonal.Sigmas(bias_sig)))
        e_sig = np.concatenate([np.full(3, ROT_PRIOR_RAD), np.full(3, TRANS_PRIOR_M)])
        g.add(gtsam.PriorFactorPose3(self.key_e, gtsam.Pose3(self.E0), gtsam.noiseModel.Diagonal.Sigmas(e_sig)))
        W0 = self.initial.atPose3(self.key_w).matrix()
        # Gauge: yaw about the world's z and the position are fixed; the tilt is free. In W's own (board) axes the
        # rotation covariance is R^T diag(free, free, gauge) R.
        R = W0[:3, :3]
        cov = np.zeros((6, 6))
        cov[:3, :3] = R.T @ np.diag([FREE_SIGMA_RAD**2, FREE_SIGMA_RAD**2, GAUGE_SIGMA**2]) @ R
        cov[3:, 3:] = GAUGE_SIGMA**2 * np.eye(3)
        g.add(gtsam.PriorFactorPose3(self.key_w, gtsam.Pose3(W0), gtsam.noiseModel.Gaussian.Covariance(cov)))
        return g

    def _optimise(self, offset_ns: float, start):
        import gtsam

        graph = self._graph(offset_ns)
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(100)
        params.setRelativeErrorTol(1e-10)
        params.setAbsoluteErrorTol(1e-10)
        result = gtsam.LevenbergMarquardtOptimizer(graph, start, params).optimize()
        return graph, result

    def error_at(self, offset_ns: float) -> float:
        graph, result = self._optimise(offset_ns, self.initial)
        return float(graph.error(result))

    def solve(self, offset0_ns: float) -> GraphSolution:
        """The offset of the smallest error within OFFSET_SEARCH_NS of `offset0_ns`, and the extrinsic there."""
        import gtsam
        from gtsam.symbol_shorthand import B

        graph, result = self._optimise(offset0_ns, self.initial)
        self.initial = result  # later solves start from here
        best = minimize_scalar(
            self.error_at,
            bounds=(offset0_ns - OFFSET_SEARCH_NS, offset0_ns + OFFSET_SEARCH_NS),
            method="bounded",
            options={"xatol": 2e4},
        )
        d = float(best.x)
        h = CURVATURE_STEP_NS
        e0, ep, em = self.error_at(d), self.error_at(d + h), self.error_at(d - h)
        curvature = (ep + em - 2.0 * e0) / h**2
        std = float(1.0 / np.sqrt(curvature)) if curvature > 0 else float("inf")
        graph, result = self._optimise(d, self.initial)
        marg = gtsam.Marginals(graph, result)
        E = result.atPose3(self.key_e).matrix()
        W = result.atPose3(self.key_w).matrix()
        b = result.atConstantBias(B(0))
        return GraphSolution(
            body_T_cam=E,
            cov=marg.marginalCovariance(self.key_e),
            offset_ns=d,
            offset_std_ns=std,
            error=float(graph.error(result)),
            frames=len(self.t_ns),
            gyro_bias_rad_s=np.asarray(b.gyroscope()),
            acc_bias_m_s2=np.asarray(b.accelerometer()),
            gravity_board=W[:3, :3].T @ np.array([0.0, 0.0, 1.0]),
        )
