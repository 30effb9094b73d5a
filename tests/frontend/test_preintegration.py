"""IMU preintegration: deltas between keyframes match the true relative motion; interpolation, jitter, gaps."""

from __future__ import annotations

import logging

import gtsam
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from frontend.preintegration import ImuPreintegrator, preintegration_params
from tests.conftest import shared_path
from vio.config import ImuConfig
from vio.records import GRAVITY_WORLD, ImuCalib, ImuSeries

CALIB = ImuCalib(
    gyroscope_noise_density=1.7e-4,
    accelerometer_noise_density=2.0e-3,
    gyroscope_random_walk=1.9e-5,
    accelerometer_random_walk=3.0e-3,
)
ZERO_BIAS = gtsam.imuBias.ConstantBias()


def _rz(a: np.ndarray) -> np.ndarray:
    return Rotation.from_rotvec(np.outer(a, [0.0, 0.0, 1.0])).as_matrix()


def _rx(b: np.ndarray) -> np.ndarray:
    return Rotation.from_rotvec(np.outer(b, [1.0, 0.0, 0.0])).as_matrix()


def truth(t_s: np.ndarray) -> dict[str, np.ndarray]:
    """Closed-form smooth motion: world_R_body = Rz(alpha) Rx(beta) on a wobbling circle (all derivatives exact)."""
    t = np.asarray(t_s, float)
    alpha, dalpha = 0.6 * t + 0.3 * np.sin(1.1 * t), 0.6 + 0.33 * np.cos(1.1 * t)
    beta, dbeta = 0.4 * np.sin(1.7 * t), 0.68 * np.cos(1.7 * t)
    R = _rz(alpha) @ _rx(beta)
    # omega_body = Rx(beta)^T [0, 0, alpha'] + [beta', 0, 0]
    omega = np.einsum("nji,j->ni", _rx(beta), [0.0, 0.0, 1.0]) * dalpha[:, None]
    omega[:, 0] += dbeta
    r, w, h, u = 1.5, 0.5, 0.3, 2.3
    p = np.column_stack([r * np.cos(w * t), r * np.sin(w * t), 1.0 + h * np.sin(u * t)])
    v = np.column_stack([-r * w * np.sin(w * t), r * w * np.cos(w * t), h * u * np.cos(u * t)])
    a = np.column_stack([-r * w * w * np.cos(w * t), -r * w * w * np.sin(w * t), -h * u * u * np.sin(u * t)])
    acc = np.einsum("nji,nj->ni", R, a - GRAVITY_WORLD)  # specific force in body = R^T (a - g)
    return {"R": R, "p": p, "v": v, "omega": omega, "acc": acc}


def imu_at(t_ns: np.ndarray) -> ImuSeries:
    s = truth(t_ns * 1e-9)
    return ImuSeries(np.asarray(t_ns, np.int64), s["omega"], s["acc"])


def prediction_errors(pre, t0_ns: int, t1_ns: int) -> tuple[float, float, float]:
    """Predict the state at t1 from the true state at t0; return (position m, rotation rad, velocity m/s) errors."""
    s = truth(np.array([t0_ns, t1_ns]) * 1e-9)
    state0 = gtsam.NavState(gtsam.Rot3(s["R"][0]), s["p"][0], s["v"][0])
    pred = pre.pim.predict(state0, ZERO_BIAS)
    dp = np.linalg.norm(pred.position() - s["p"][1])
    dr = np.linalg.norm(gtsam.Rot3.Logmap(gtsam.Rot3(s["R"][1].T @ pred.attitude().matrix())))
    dv = np.linalg.norm(pred.velocity() - s["v"][1])
    return float(dp), float(dr), float(dv)


def worst_over_keyframes(imu: ImuSeries, kf_ns: np.ndarray, cfg: ImuConfig | None = None):
    pi = ImuPreintegrator(imu, CALIB, cfg or ImuConfig())
    worst = np.zeros(3)
    for t0, t1 in zip(kf_ns[:-1], kf_ns[1:], strict=True):
        pre = pi.between(int(t0), int(t1), ZERO_BIAS)
        assert pre.pim.deltaTij() == pytest.approx((t1 - t0) * 1e-9, abs=1e-12)
        worst = np.maximum(worst, prediction_errors(pre, int(t0), int(t1)))
    return worst


T0_NS = 1_000_000_000_000  # an arbitrary large epoch, as on real devices


def test_params_follow_kalibr_densities():
    cfg = ImuConfig(noise_inflation=2.0, integration_sigma=1e-3)
    p = preintegration_params(CALIB, cfg)
    np.testing.assert_allclose(p.getGyroscopeCovariance(), np.eye(3) * (2 * 1.7e-4) ** 2)
    np.testing.assert_allclose(p.getAccelerometerCovariance(), np.eye(3) * (2 * 2.0e-3) ** 2)
    np.testing.assert_allclose(p.getBiasOmegaCovariance(), np.eye(3) * (2 * 1.9e-5) ** 2)
    np.testing.assert_allclose(p.getBiasAccCovariance(), np.eye(3) * (2 * 3.0e-3) ** 2)
    np.testing.assert_allclose(p.getIntegrationCovariance(), np.eye(3) * 1e-6)
    np.testing.assert_allclose(p.n_gravity, [0.0, 0.0, -9.81])


def test_deltas_match_true_motion_at_200hz():
    imu = imu_at(T0_NS + np.arange(0, 4_000_000_000 + 1, 5_000_000))
    kf = T0_NS + np.arange(0, 4_000_000_000 + 1, 100_000_000)
    dp, dr, dv = worst_over_keyframes(imu, kf)
    # Measured worst over 40 keyframes: 7.7e-7 m, 4.1e-7 rad, 3.3e-6 m/s. Without the midpoint rotation of the
    # specific force (plain gtsam Euler steps) the velocity error is 2.6e-3 m/s, so these bounds catch it.
    assert dp < 2e-6 and dr < 1e-6 and dv < 1e-5, (dp, dr, dv)


def test_off_grid_keyframes_are_interpolated():
    imu = imu_at(T0_NS + np.arange(0, 3_000_000_000 + 1, 5_000_000))
    rng = np.random.default_rng(1)
    kf = np.sort(T0_NS + 7_654_321 + rng.integers(0, 2_900_000_000, 25))
    kf = kf[np.flatnonzero(np.diff(kf, prepend=0) > 40_000_000)]
    assert np.all(kf % 5_000_000 != 0)
    dp, dr, dv = worst_over_keyframes(imu, kf)  # measured 2.7e-6 m, 2.1e-6 rad, 1.0e-5 m/s
    assert dp < 6e-6 and dr < 5e-6 and dv < 3e-5, (dp, dr, dv)


def test_jittered_timestamps():
    rng = np.random.default_rng(2)
    steps = rng.integers(2_000_000, 8_000_000, 800)  # 2-8 ms between samples (125-500 Hz)
    imu = imu_at(T0_NS + np.concatenate([[0], np.cumsum(steps)]))
    kf = T0_NS + np.arange(50_000_000, 3_500_000_000, 120_000_000)
    dp, dr, dv = worst_over_keyframes(imu, kf)  # measured 1.3e-6 m, 7.3e-7 rad, 5.9e-6 m/s
    assert dp < 4e-6 and dr < 2e-6 and dv < 1.5e-5, (dp, dr, dv)


def test_sample_on_keyframe_time_and_num_samples():
    imu = imu_at(T0_NS + np.arange(0, 1_000_000_000 + 1, 5_000_000))
    pi = ImuPreintegrator(imu, CALIB, ImuConfig())
    pre = pi.between(T0_NS + 100_000_000, T0_NS + 200_000_000, ZERO_BIAS)
    assert pre.num_samples == 21 and not pre.gap and pre.max_gap_s == pytest.approx(0.005)
    pre = pi.between(T0_NS + 101_000_000, T0_NS + 199_000_000, ZERO_BIAS)
    assert pre.num_samples == 21 and pre.t0_ns == T0_NS + 101_000_000 and pre.dt_s == pytest.approx(0.098)
    with pytest.raises(ValueError, match="positive"):
        pi.between(T0_NS + 5, T0_NS + 5, ZERO_BIAS)


def test_short_gap_bridged_silently(caplog):
    t = T0_NS + np.arange(0, 1_000_000_000 + 1, 5_000_000)
    t = t[(t < T0_NS + 420_000_000) | (t > T0_NS + 450_000_000)]  # samples at 415 and 455 ms: a 40 ms gap
    pi = ImuPreintegrator(imu_at(t), CALIB, ImuConfig(max_gap_s=0.05))
    with caplog.at_level(logging.WARNING):
        pre = pi.between(T0_NS + 400_000_000, T0_NS + 500_000_000, ZERO_BIAS)
    assert not pre.gap and pre.max_gap_s == pytest.approx(0.04)
    assert not caplog.records
    dp, dr, dv = prediction_errors(pre, T0_NS + 400_000_000, T0_NS + 500_000_000)
    assert dp < 1e-4 and dr < 1e-4 and dv < 2e-3, (dp, dr, dv)


def test_long_gap_reported_with_time(caplog):
    t = T0_NS + np.arange(0, 2_000_000_000 + 1, 5_000_000)
    t = t[(t <= T0_NS + 1_230_000_000) | (t >= T0_NS + 1_430_000_000)]
    pi = ImuPreintegrator(imu_at(t), CALIB, ImuConfig(max_gap_s=0.05))
    with caplog.at_level(logging.WARNING, logger="frontend.preintegration"):
        pre = pi.between(T0_NS + 1_200_000_000, T0_NS + 1_400_000_000, ZERO_BIAS)
        ok = pi.between(T0_NS + 1_000_000_000, T0_NS + 1_200_000_000, ZERO_BIAS)
    assert pre.gap and pre.max_gap_s == pytest.approx(0.2)
    assert pre.pim.deltaTij() == pytest.approx(0.2, abs=1e-12)  # still integrated over the whole interval
    assert not ok.gap
    assert len(caplog.records) == 1
    assert f"t={T0_NS + 1_230_000_000} ns" in caplog.records[0].getMessage()


def test_interval_outside_stream_counts_as_gap():
    imu = imu_at(T0_NS + np.arange(0, 1_000_000_000 + 1, 5_000_000))
    pi = ImuPreintegrator(imu, CALIB, ImuConfig(max_gap_s=0.05))
    pre = pi.between(T0_NS + 900_000_000, T0_NS + 1_100_000_000, ZERO_BIAS)
    assert pre.gap and pre.max_gap_s == pytest.approx(0.1)


def test_known_bias_is_removed():
    b_acc, b_gyro = np.array([0.08, -0.05, 0.12]), np.array([0.01, -0.02, 0.015])
    t = T0_NS + np.arange(0, 2_000_000_000 + 1, 5_000_000)
    clean = imu_at(t)
    biased = ImuSeries(t, clean.gyro + b_gyro, clean.acc + b_acc)
    bias = gtsam.imuBias.ConstantBias(b_acc, b_gyro)
    pi = ImuPreintegrator(biased, CALIB, ImuConfig())
    worst = np.zeros(3)
    for t0 in range(T0_NS, T0_NS + 1_900_000_000, 100_000_000):
        pre = pi.between(t0, t0 + 100_000_000, bias)
        s = truth(np.array([t0, t0 + 100_000_000]) * 1e-9)
        pred = pre.pim.predict(gtsam.NavState(gtsam.Rot3(s["R"][0]), s["p"][0], s["v"][0]), bias)
        dr = np.linalg.norm(gtsam.Rot3.Logmap(gtsam.Rot3(s["R"][1].T @ pred.attitude().matrix())))
        err = (np.linalg.norm(pred.position() - s["p"][1]), dr, np.linalg.norm(pred.velocity() - s["v"][1]))
        worst = np.maximum(worst, err)
    assert worst[0] < 2e-6 and worst[1] < 1e-6 and worst[2] < 1e-5, worst


def _sim_prediction_worst(pi: ImuPreintegrator, kf_ns: np.ndarray, state_at) -> np.ndarray:
    worst = np.zeros(3)
    for t0, t1 in zip(kf_ns[:-1], kf_ns[1:], strict=True):
        pre = pi.between(int(t0), int(t1), ZERO_BIAS)
        R0, p0, v0 = state_at(t0)
        R1, p1, v1 = state_at(t1)
        pred = pre.pim.predict(gtsam.NavState(gtsam.Rot3(R0), p0, v0), ZERO_BIAS)
        dr = np.linalg.norm(gtsam.Rot3.Logmap(gtsam.Rot3(R1.T @ pred.attitude().matrix())))
        worst = np.maximum(worst, [np.linalg.norm(pred.position() - p1), dr, np.linalg.norm(pred.velocity() - v1)])
    return worst


def test_ideal_simulated_orbit_matches_ground_truth(sim_capture):
    """The simulator's `ideal` IMU, read back from the ASL files, against its ground-truth states (0.1 s apart)."""
    from vio.readers.asl import read_asl

    cap = read_asl(sim_capture("orbit", duration_s=4.0, imu="ideal", images=False))
    gt = cap.ground_truth
    pi = ImuPreintegrator(cap.imu, cap.imu_calib, ImuConfig())
    rows = {int(t): i for i, t in enumerate(gt.t_ns)}

    def state_at(t_ns: int):
        i = rows[int(t_ns)]
        return gt.world_T_body(i)[:3, :3], gt.p_world[i], gt.v_world[i]

    kf = gt.t_ns[::20]  # every 0.1 s at 200 Hz
    assert kf.size >= 40
    dp, dr, dv = _sim_prediction_worst(pi, kf, state_at)
    # Measured: 2.8e-6 m, 3.4e-6 rad, 3.1e-5 m/s, converging as dt^2 with the IMU rate (x1/4 per doubling).
    # gtsam fed the left sample of each step (the usual loop) gives 1.2e-4 m, 4.1e-4 rad, 2.4e-3 m/s here.
    assert dp < 6e-6 and dr < 7e-6 and dv < 6e-5, (dp, dr, dv)


def test_ideal_simulated_orbit_off_grid_keyframes(sim_capture):
    """Keyframe times between IMU samples, against the simulator's continuous trajectory (the oracle)."""
    from vio.readers.asl import read_asl
    from vio.sim.api import load_scenario

    cap = read_asl(sim_capture("orbit", duration_s=4.0, imu="ideal", images=False))
    scenario = load_scenario("orbit", seed=0, duration_s=4.0)
    pi = ImuPreintegrator(cap.imu, cap.imu_calib, ImuConfig())

    def state_at(t_ns: int):
        s = scenario.trajectory.sample(np.array([(t_ns - scenario.t0_ns) * 1e-9]))
        return s.world_R_body[0], s.p_world[0], s.v_world[0]

    rng = np.random.default_rng(4)
    kf = scenario.t0_ns + 3_141_593 + np.cumsum(rng.integers(50_000_000, 200_000_000, 20))
    kf = kf[kf < cap.imu.t_ns[-1]]
    assert np.all((kf - scenario.t0_ns) % 5_000_000 != 0)
    dp, dr, dv = _sim_prediction_worst(pi, kf, state_at)  # measured 6.7e-6 m, 3.4e-6 rad, 4.3e-5 m/s (0.05-0.2 s)
    assert dp < 1.5e-5 and dr < 7e-6 and dv < 1e-4, (dp, dr, dv)


def test_jittered_imu_on_the_simulated_orbit():
    """IMU sampled at jittered times (2-8 ms apart) from the simulator's trajectory; keyframes 0.1 s apart."""
    from vio.sim.api import load_scenario

    scenario = load_scenario("orbit", seed=0, duration_s=4.0)
    rng = np.random.default_rng(6)
    t_rel = np.concatenate([[0], np.cumsum(rng.integers(2_000_000, 8_000_000, 900))])
    t_rel = t_rel[t_rel <= 3_900_000_000]
    s = scenario.trajectory.sample(t_rel * 1e-9)
    acc = np.einsum("nji,nj->ni", s.world_R_body, s.a_world - GRAVITY_WORLD)
    pi = ImuPreintegrator(ImuSeries(scenario.t0_ns + t_rel, s.omega_body, acc), scenario.imu_calib, ImuConfig())

    def state_at(t_ns: int):
        k = scenario.trajectory.sample(np.array([(t_ns - scenario.t0_ns) * 1e-9]))
        return k.world_R_body[0], k.p_world[0], k.v_world[0]

    kf = scenario.t0_ns + np.arange(10_000_000, 3_800_000_000, 100_000_000)
    assert not any(pi.between(int(a), int(b), ZERO_BIAS).gap for a, b in zip(kf[:-1], kf[1:], strict=True))
    dp, dr, dv = _sim_prediction_worst(pi, kf, state_at)  # measured 4.3e-6 m, 6.0e-6 rad, 4.7e-5 m/s
    assert dp < 1e-5 and dr < 1.2e-5 and dv < 1e-4, (dp, dr, dv)


def test_noise_model_is_consistent_on_phone_grade_imu(sim_capture):
    """With the true states and biases, CombinedImuFactor residuals whiten to chi2 with 15 dof on average.

    This checks the Kalibr-density -> gtsam covariance mapping: a density used as a variance, or a discrete sigma
    used as a density, moves the mean by orders of magnitude. Measured mean: 14.2 (seed 0), 14.8 (seed 1).
    """
    from gtsam.symbol_shorthand import B, V, X

    from vio.readers.asl import read_asl

    cap = read_asl(sim_capture("orbit", duration_s=8.0, imu="phone", images=False))
    gt = cap.ground_truth
    pi = ImuPreintegrator(cap.imu, cap.imu_calib, ImuConfig())
    chi2 = []
    for i in range(0, len(gt) - 20, 20):
        j = i + 20
        b0, b1 = (gtsam.imuBias.ConstantBias(gt.b_a[k], gt.b_w[k]) for k in (i, j))
        pre = pi.between(int(gt.t_ns[i]), int(gt.t_ns[j]), b0)
        factor = gtsam.CombinedImuFactor(X(0), V(0), X(1), V(1), B(0), B(1), pre.pim)
        values = gtsam.Values()
        values.insert(X(0), gtsam.Pose3(gt.world_T_body(i)))
        values.insert(X(1), gtsam.Pose3(gt.world_T_body(j)))
        values.insert(V(0), gt.v_world[i])
        values.insert(V(1), gt.v_world[j])
        values.insert(B(0), b0)
        values.insert(B(1), b1)
        chi2.append(2.0 * factor.error(values))
    assert len(chi2) >= 70
    assert 11.0 < np.mean(chi2) < 20.0, np.mean(chi2)


def test_real_euroc_imu_agrees_with_groundtruth_states():
    """Real ADIS16448 IMU of EuRoC V1_01 against its re-estimated ground-truth states, 0.1 s windows, first 60 s.

    Measured over the whole flight: median 0.25 mm position and 5.0 mm/s velocity error with the ground-truth
    biases, 20 mm/s with zero bias (so the bias linearisation point is really used).
    """
    from vio.kalibr import read_imu_yaml
    from vio.readers.asl import read_groundtruth_csv, read_imu_csv

    mav0 = shared_path("euroc_v1_01", "mav0")
    imu = read_imu_csv(mav0 / "imu0" / "data.csv")
    gt = read_groundtruth_csv(mav0 / "state_groundtruth_estimate0" / "data.csv")
    pi = ImuPreintegrator(imu, read_imu_yaml(mav0 / "imu0" / "sensor.yaml"), ImuConfig())
    rows = np.flatnonzero((gt.t_ns >= imu.t_ns[0]) & (gt.t_ns <= imu.t_ns[0] + 60_000_000_000))[::2]
    err_pos, err_vel, err_vel_zero_bias = [], [], []
    for i, j in zip(rows[:-1], rows[1:], strict=True):
        state0 = gtsam.NavState(gtsam.Pose3(gt.world_T_body(i)), gt.v_world[i])
        for bias, out in ((gtsam.imuBias.ConstantBias(gt.b_a[i], gt.b_w[i]), err_vel), (ZERO_BIAS, err_vel_zero_bias)):
            pre = pi.between(int(gt.t_ns[i]), int(gt.t_ns[j]), bias)
            assert not pre.gap and pre.dt_s == pytest.approx(0.1, abs=1e-3)
            pred = pre.pim.predict(state0, bias)
            out.append(np.linalg.norm(pred.velocity() - gt.v_world[j]))
            if out is err_vel:
                err_pos.append(np.linalg.norm(pred.position() - gt.p_world[j]))
    assert len(err_pos) > 500
    assert np.median(err_pos) < 5e-4 and np.median(err_vel) < 0.01, (np.median(err_pos), np.median(err_vel))
    assert np.median(err_vel_zero_bias) > 2 * np.median(err_vel)
