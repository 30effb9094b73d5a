"""The estimator on ideal synthetic tracks: the simulator's trajectory and scene, projected with pixel noise.

No images and no tracker: surface points of the scenario are projected with the ground-truth poses (distorted
pixels, Gaussian noise), the IMU is sampled from the same trajectory, and the estimator must recover metric poses.
"""

from __future__ import annotations

import numpy as np
import pytest

from backend.estimator import VioEstimator
from backend.smoother import Smoother, SolverFailure
from frontend.preintegration import ImuPreintegrator
from vio.config import Config, ImuConfig
from vio.geometry import inv_T
from vio.health import imu_only_spans, recovery_spans
from vio.records import GRAVITY_WORLD, FeatureTracks, ImuSeries


def synthetic_run(
    duration_s=6.0, seed=0, px_noise=0.5, imu_noise=True, kf_hz=10.0, n_points=400, gyro_bias=(0.004, -0.003, 0.002)
):
    """(camera, imu ImuSeries, imu_calib, keyframe times (K,), tracks list, gt world_T_body (K, 4, 4)).

    gyro_bias (rad/s) is added to the gyro when imu_noise is on."""
    from vio.sim.api import load_scenario

    sc = load_scenario("orbit", seed=seed, duration_s=duration_s)
    rng = np.random.default_rng(seed)
    t_imu = np.arange(0.0, duration_s, 1.0 / sc.imu_rate_hz)
    s = sc.trajectory.sample(t_imu)
    acc = np.einsum("nji,nj->ni", s.world_R_body, s.a_world - GRAVITY_WORLD)
    gyro = s.omega_body.copy()
    cal = sc.imu_calib
    if imu_noise:
        dt = 1.0 / sc.imu_rate_hz
        gyro += rng.normal(0, cal.gyroscope_noise_density / np.sqrt(dt), gyro.shape) + np.asarray(gyro_bias)
        acc += rng.normal(0, cal.accelerometer_noise_density / np.sqrt(dt), acc.shape) + np.array([0.03, -0.02, 0.04])
    t0 = sc.t0_ns
    imu = ImuSeries(t0 + np.round(t_imu * 1e9).astype(np.int64), gyro, acc)
    pts = sc.scene.sample_surface_points(n_points, rng)
    t_kf = np.arange(0.0, duration_s - 0.01, 1.0 / kf_hz)
    sk = sc.trajectory.sample(t_kf)
    cam = sc.camera
    tracks, gt = [], []
    for i, t in enumerate(t_kf):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = sk.world_R_body[i], sk.p_world[i]
        gt.append(T)
        p_cam = (inv_T(T @ cam.body_T_cam) @ np.column_stack([pts, np.ones(len(pts))]).T).T[:, :3]
        ok = p_cam[:, 2] > 0.1
        uv = cam.project(p_cam[ok]) + rng.normal(0, px_noise, (int(ok.sum()), 2))
        ids = np.flatnonzero(ok)
        inside = (uv[:, 0] > 0) & (uv[:, 0] < cam.width) & (uv[:, 1] > 0) & (uv[:, 1] < cam.height)
        tracks.append(FeatureTracks(t0 + int(round(t * 1e9)), ids[inside].astype(np.int64), uv[inside]))
    return cam, imu, cal, np.array([tr.t_ns for tr in tracks]), tracks, np.array(gt)


def ate_se3(gt_p: np.ndarray, est_p: np.ndarray) -> float:
    """Position RMSE after the best rigid alignment (Umeyama without scale), m."""
    mg, me = gt_p.mean(0), est_p.mean(0)
    U, _, Vt = np.linalg.svd((gt_p - mg).T @ (est_p - me))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    return float(np.sqrt((((est_p - me) @ R.T + mg - gt_p) ** 2).sum(1).mean()))


def run_estimator(data, cfg=None):
    cam, imu, cal, t_kf, tracks, gt = data
    pre = ImuPreintegrator(imu, cal, ImuConfig())
    est = VioEstimator(cam, imu, pre.between, cfg or Config())
    for t, tr in zip(t_kf, tracks, strict=True):
        est.add_keyframe(int(t), tr)
    return est


@pytest.fixture(scope="module")
def data():
    return synthetic_run()


def test_moving_start_recovers_metric_trajectory(data):
    est = run_estimator(data)
    assert est.stats().initialisation == "moving"
    states = est.states()
    gt = data[5]
    assert len(states) >= len(gt) - 12  # the first window may slide a little
    idx = [int(np.searchsorted(data[3], s.t_ns)) for s in states]
    p = np.array([s.world_T_body[:3, 3] for s in states])
    assert ate_se3(gt[idx, :3, 3], p) < 0.02
    # gravity is observed: the world z axis seen in the body agrees with the truth without any alignment
    up = np.array([s.world_T_body[2, :3] for s in states])  # world z in body axes
    tilt = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", up, gt[idx, 2, :3]), -1, 1)))
    assert np.median(tilt) < 1.0
    lm = est.landmarks()
    assert len(lm) > 100 and lm.num_obs.min() >= 3


def test_moving_start_with_a_large_gyro_bias():
    """EuRoC V1_01's gyro bias (0.077 rad/s about z) turns a 1 s window by 4-5 deg: integrated at bias zero, the
    closed-form alignment collapsed (every keyframe near the origin) and the run diverged; the images' own
    rotations give the bias before the alignment (backend/initialisation/gyro_bias.py)."""
    truth = np.array([-0.002, 0.021, 0.077])
    data = synthetic_run(seed=1, gyro_bias=tuple(truth))
    est = run_estimator(data)
    stats = est.stats()
    assert stats.initialisation == "moving" and not stats.recoveries
    states = est.states()
    idx = [int(np.searchsorted(data[3], s.t_ns)) for s in states]
    assert ate_se3(data[5][idx, :3, 3], np.array([s.world_T_body[:3, 3] for s in states])) < 0.02
    assert np.abs(states[-1].bias_gyro - truth).max() < 0.005


@pytest.mark.parametrize(("rms_after_deg", "used"), [(1.2, False), (0.4, True)])
def test_an_image_gyro_bias_a_constant_bias_does_not_explain_is_not_used(data, monkeypatch, rms_after_deg, used):
    """On the 60 s orbit (seeds 101, 102, 105) the images' rotations asked for a gyro bias 0.03-0.05 rad/s too large
    about x and stayed 1.2-1.9 deg rms from the gyro's at it (the orbit's look-at motion confounds rotation and
    translation in the essential matrix); seed 102's run then lost its landmarks for 40 of its 60 s. Such an
    estimate is not used: the moving start integrates with the current bias, and the run holds."""
    import backend.initialisation.inertial as inertial
    from backend.initialisation.gyro_bias import GyroBiasEstimate

    wrong = np.array([0.04, 0.0, 0.0])
    seen = []
    real_moving_start = inertial.moving_start

    def spy(window, bias_gyro):
        seen.append(np.asarray(bias_gyro, float).copy())
        return real_moving_start(window, bias_gyro)

    monkeypatch.setattr(inertial, "gyro_bias_from_images", lambda *a: GyroBiasEstimate(wrong, 6, 2.0, rms_after_deg))
    monkeypatch.setattr(inertial, "moving_start", spy)
    est = run_estimator(data)
    assert seen, "the moving start never ran"
    assert np.allclose(seen[0], wrong) == used
    if not used:
        assert est.stats().initialisation == "moving"
        assert np.abs(est.states()[-1].bias_gyro - np.array([0.004, -0.003, 0.002])).max() < 0.005


def test_online_estimate_close_to_batch(data):
    est = run_estimator(data)
    idx = [int(np.searchsorted(data[3], s.t_ns)) for s in est.states()]
    online = ate_se3(data[5][idx, :3, 3], np.array([s.world_T_body[:3, 3] for s in est.states()]))
    assert est.finish(refine=True)["refined"]
    batch = ate_se3(data[5][idx, :3, 3], np.array([s.world_T_body[:3, 3] for s in est.states()]))
    assert batch < 0.02
    assert online < 1.5 * batch + 0.005  # as good as the full batch solve (a 6 s run: mm-level noise either way)


def test_solver_failure_is_recovered(data, monkeypatch):
    calls = {"n": 0}
    original = Smoother.update

    def flaky(self, graph, values, stamps):
        calls["n"] += 1
        if calls["n"] == 20:
            raise SolverFailure("injected failure")
        return original(self, graph, values, stamps)

    monkeypatch.setattr(Smoother, "update", flaky)
    est = run_estimator(data)
    recoveries = est.stats().recoveries
    assert len(recoveries) == 1 and recoveries[0].reason == "injected failure"
    (span,) = recovery_spans(est.stats())  # run health: from the keyframe rebuilt from to the one that failed
    assert span.end_t_ns == recoveries[0].t_ns and span.start_t_ns == est.state.t_ns[recoveries[0].restart_from_k]
    assert len(est.states()) >= len(data[5]) - 12
    assert all(np.isfinite(s.world_T_body).all() for s in est.states())


def test_tracking_loss_does_not_end_the_run(data):
    cam, imu, cal, t_kf, tracks, gt = data
    lost = [
        FeatureTracks(tr.t_ns, tr.ids[:0], tr.uv[:0]) if 30 <= i < 38 else tr  # 0.8 s without any feature
        for i, tr in enumerate(tracks)
    ]
    est = run_estimator((cam, imu, cal, t_kf, lost, gt))
    states = est.states()
    # run health: the keyframes without features have no projection factor, and only they (IMU alone)
    kfs = est.stats().keyframe_projections
    assert [k for k, _, n in kfs if n == 0] == list(range(30, 38))
    spans = imu_only_spans(kfs, {s.t_ns for s in states}, 1)
    assert [(s.start_t_ns, s.end_t_ns) for s in spans] == [(kfs[29][1], kfs[38][1])]
    assert len(states) >= len(gt) - 12 and all(np.isfinite(s.world_T_body).all() for s in states)
    idx = [int(np.searchsorted(t_kf, s.t_ns)) for s in states]
    assert ate_se3(gt[idx, :3, 3], np.array([s.world_T_body[:3, 3] for s in states])) < 0.05
