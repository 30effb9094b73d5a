"""Trajectory metrics: alignments recover known transforms, RPE/drift/coverage definitions, the `vio eval` CLI."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation

from vio.errors import CaptureError
from vio.evaluate import evaluate_files
from vio.metrics import align_posyaw, associate, evaluate, interpolate, path_distances, segment_pairs, umeyama
from vio.trajio import Trajectory, write_tum

T0_NS = 1_700_000_000_000_000_000


def make_gt(duration_s: float = 30.0, rate_hz: float = 20.0) -> Trajectory:
    """A wavy circle (radius 2 m, 0.25 rad/s) with a tumbling attitude."""
    t_ns = T0_NS + np.arange(0, int(duration_s * 1e9), int(1e9 / rate_hz), dtype=np.int64)
    ts = (t_ns - T0_NS) * 1e-9
    p = np.column_stack([2 * np.cos(0.25 * ts), 2 * np.sin(0.25 * ts), 1 + 0.4 * np.sin(0.6 * ts)])
    rv = np.column_stack([0.2 * np.sin(ts), 0.3 * np.cos(0.4 * ts), 0.25 * ts])
    return Trajectory(t_ns, p, Rotation.from_rotvec(rv).as_quat()[:, [3, 0, 1, 2]])


def transformed(traj: Trajectory, s: float, R: Rotation, t: np.ndarray) -> Trajectory:
    """The trajectory expressed in another world frame: p' = s R p + t, R_wb' = R R_wb."""
    q = (R * Rotation.from_quat(traj.q_wxyz[:, [1, 2, 3, 0]])).as_quat()[:, [3, 0, 1, 2]]
    return Trajectory(traj.t_ns, s * R.apply(traj.p_world) + t, q)


def test_umeyama_recovers_known_similarity():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(50, 3))
    R = Rotation.from_rotvec([0.3, -1.2, 2.0])
    s, R_est, t = umeyama(src, 1.7 * R.apply(src) + [1.0, -2.0, 0.5], with_scale=True)
    assert s == pytest.approx(1.7, rel=1e-12)
    np.testing.assert_allclose(R_est, R.as_matrix(), atol=1e-12)
    np.testing.assert_allclose(t, [1.0, -2.0, 0.5], atol=1e-12)


@pytest.mark.parametrize(
    ("align", "s", "rotvec", "zero"),
    [
        ("se3", 1.0, [0.4, -0.3, 1.1], True),
        ("sim3", 0.8, [0.4, -0.3, 1.1], True),
        ("sim3", 1.0, [0.0, 0.0, 0.0], True),
        ("posyaw", 1.0, [0.0, 0.0, -2.5], True),
        ("posyaw", 1.0, [0.05, 0.0, -2.5], False),  # a tilt is observable: posyaw must not remove it
        ("se3", 1.05, [0.0, 0.0, 0.3], False),  # a scale error survives SE3 alignment
        ("none", 1.0, [0.0, 0.0, 0.0], True),
        ("none", 1.0, [0.0, 0.0, 0.01], False),
    ],
)
def test_alignment_removes_exactly_its_degrees_of_freedom(align, s, rotvec, zero):
    gt = make_gt()
    t = np.zeros(3) if align == "none" else np.array([3.0, -1.0, 0.7])
    est = transformed(gt, 1.0 / s, Rotation.from_rotvec(rotvec), t)
    m = evaluate(gt, est, align=align)
    if zero:
        assert m["ate_rmse_m"] < 1e-9 and m["ate_rot_rmse_deg"] < 1e-6 and m["drift_pct"] < 1e-7
    else:
        assert m["ate_rmse_m"] > 1e-3
    assert m["scale"] == pytest.approx(s, rel=1e-9)


def test_posyaw_is_the_least_squares_optimum():
    rng = np.random.default_rng(3)
    gt = make_gt()
    est = transformed(gt, 1.0, Rotation.from_rotvec([0.02, -0.03, 0.9]), np.array([1.0, 2.0, -0.5]))
    noisy = est.p_world + rng.normal(scale=0.05, size=est.p_world.shape)
    _, R, t = align_posyaw(noisy, gt.p_world)
    assert np.allclose(R[2], [0, 0, 1]) and np.allclose(R[:, 2], [0, 0, 1])

    def cost(x: np.ndarray) -> float:
        Rz = Rotation.from_rotvec([0.0, 0.0, x[0]])
        return float(np.sum((Rz.apply(noisy) + x[1:] - gt.p_world) ** 2))

    yaw = np.arctan2(R[1, 0], R[0, 0])
    best = minimize(cost, np.array([yaw + 0.2, *(t + 0.3)]), method="BFGS", options={"gtol": 1e-10})
    assert cost(np.array([yaw, *t])) <= best.fun + 1e-9
    assert abs(yaw - best.x[0]) < 1e-5


def test_association_nearest_within_tolerance():
    gt = make_gt(rate_hz=100.0)
    rng = np.random.default_rng(1)
    off = rng.integers(-4_000_000, 4_000_000, 30)
    off[::5] = 30_000_000  # 30 ms away from any ground-truth time... unless another sample is near
    idx = np.arange(10, 310, 10)
    est = Trajectory(gt.t_ns[idx] + off, gt.p_world[idx], gt.q_wxyz[idx])
    i_gt, i_est = associate(gt, est, max_dt_s=0.01)
    expect = np.round((est.t_ns - T0_NS) / 10_000_000).astype(int)  # nearest 100 Hz sample
    np.testing.assert_array_equal(i_est, np.arange(30))
    np.testing.assert_array_equal(i_gt, expect)
    i_gt, i_est = associate(gt, est, max_dt_s=0.003)
    assert np.all(np.abs(gt.t_ns[i_gt] - est.t_ns[i_est]) <= 3_000_000) and 0 < i_gt.size < 30


def test_segment_pairs_match_brute_force_with_stationary_periods():
    rng = np.random.default_rng(5)
    steps = rng.uniform(0.0, 0.2, 400)
    steps[rng.random(400) < 0.2] = 0.0  # plateaus: the platform stands still
    dist = np.concatenate([[0.0], np.cumsum(steps)])
    for length in (0.5, 2.0, 7.0):
        i, j = segment_pairs(dist, length, rel_tol=0.1)
        want = []
        for a in range(dist.size - 1):
            err = np.abs((dist[a + 1 :] - dist[a]) - length)
            b = int(np.argmin(err))
            if err[b] <= 0.1 * length:
                want.append((a, a + 1 + b))
        assert list(zip(i.tolist(), j.tolist(), strict=True)) == want


def test_rpe_of_a_scale_error_on_a_straight_line():
    t_ns = T0_NS + np.arange(0, 20_000_000_000, 50_000_000, dtype=np.int64)
    x = (t_ns - T0_NS) * 1e-9 * 0.5  # 0.5 m/s along x
    p = np.column_stack([x, np.zeros_like(x), np.zeros_like(x)])
    q = np.tile([1.0, 0.0, 0.0, 0.0], (x.size, 1))
    gt, est = Trajectory(t_ns, p, q), Trajectory(t_ns, 1.02 * p, q)
    m = evaluate(gt, est, align="none")
    assert set(m["rpe"]) == {"1m", "2m", "5m", "10m"}  # the line is 9.975 m long: within 10 % of 10 m
    # 400 poses 2.5 cm apart; a start pose has a partner while 90 % of L remains: 40 for 10 m, 220 for 5 m.
    assert m["rpe"]["10m"]["pairs"] == 40 and m["rpe"]["5m"]["pairs"] == 220
    for entry in m["rpe"].values():
        assert entry["trans_pct"] == pytest.approx(2.0, rel=1e-6)
        assert entry["rot_max_deg"] < 1e-6
    assert m["drift_pct"] == pytest.approx(2.0, rel=1e-9)
    assert m["estimate_scale_error_pct"] == pytest.approx(2.0, rel=1e-9)  # signed: the estimate is too large
    assert evaluate(est, gt, align="none")["estimate_scale_error_pct"] == pytest.approx(100 * (1 / 1.02 - 1))
    assert m["path_length_m"] == pytest.approx(9.975)
    np.testing.assert_allclose(path_distances(p)[-1], 9.975)


def test_coverage_counts_only_what_the_estimate_covers():
    gt = make_gt(duration_s=30.0, rate_hz=20.0)
    keep = (gt.t_ns - T0_NS < 20_000_000_000) & ~((gt.t_ns - T0_NS > 8e9) & (gt.t_ns - T0_NS < 11e9))
    m = evaluate(gt, gt.subset(np.flatnonzero(keep)), align="se3")
    assert m["gt_span_s"] == pytest.approx(29.95)
    assert m["coverage_s"] == pytest.approx(19.95 - 3.0, abs=1e-9)  # the step from 8.0 to 11.0 s does not count


def test_no_overlap_is_a_clear_error(tmp_path):
    gt = make_gt()
    later = Trajectory(gt.t_ns + 100_000_000_000, gt.p_world, gt.q_wxyz)
    write_tum(tmp_path / "gt.tum", gt)
    write_tum(tmp_path / "est.tum", later)
    with pytest.raises(CaptureError, match=r"only 0 estimated pose\(s\) within 10 ms.*est\.tum"):
        evaluate_files(tmp_path / "gt.tum", tmp_path / "est.tum")


def test_evaluate_files_and_cli(tmp_path):
    gt = make_gt()
    rng = np.random.default_rng(2)
    est = transformed(gt, 1.0, Rotation.from_rotvec([0, 0, 0.5]), np.array([1.0, 0.0, 0.0]))
    est = Trajectory(est.t_ns, est.p_world + rng.normal(scale=0.01, size=est.p_world.shape), est.q_wxyz)
    write_tum(tmp_path / "gt.tum", gt)
    write_tum(tmp_path / "est.tum", est)
    report = evaluate_files(tmp_path / "gt.tum", tmp_path / "est.tum", align="posyaw", json_out=tmp_path / "m.json")
    saved = json.loads((tmp_path / "m.json").read_text())
    assert saved["align"] == "posyaw" and 0.01 < saved["ate_rmse_m"] < 0.025
    assert f"rmse {1e3 * saved['ate_rmse_m']:.2f} mm" in report
    cmd = [
        sys.executable,
        "-m",
        "vio.cli",
        "eval",
        "--gt",
        str(tmp_path / "gt.tum"),
        "--est",
        str(tmp_path / "est.tum"),
    ]
    out = subprocess.run([*cmd, "--align", "sim3"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "Sim3" in out.stdout and "RPE" in out.stdout
    bad = subprocess.run([*cmd[:-1], str(tmp_path / "missing.tum")], capture_output=True, text=True, timeout=120)
    assert bad.returncode != 0 and "Traceback" not in bad.stderr and "not found" in bad.stderr


def test_interpolated_sync_removes_the_time_offset_error():
    gt = make_gt(rate_hz=200.0)
    t_est = gt.t_ns[5::40] + 2_500_000  # 10 Hz, half-way between ground-truth samples
    ts = (t_est - T0_NS) * 1e-9
    p = np.column_stack([2 * np.cos(0.25 * ts), 2 * np.sin(0.25 * ts), 1 + 0.4 * np.sin(0.6 * ts)])
    rv = np.column_stack([0.2 * np.sin(ts), 0.3 * np.cos(0.4 * ts), 0.25 * ts])
    est = Trajectory(t_est, p, Rotation.from_rotvec(rv).as_quat()[:, [3, 0, 1, 2]])
    nearest = evaluate(gt, est, align="none")
    interp = evaluate(gt, est, align="none", sync="interpolate")
    assert interp["pairs"] == nearest["pairs"] == len(est)
    assert nearest["ate_rmse_m"] > 5e-4  # 2.5 ms at about 0.5 m/s
    assert interp["ate_rmse_m"] < 1e-5 and interp["ate_rot_rmse_deg"] < 1e-3  # interpolation error only
    mid = interpolate(gt, gt.t_ns[:1] + 2_500_000)  # half-way: the mean position, the half rotation
    np.testing.assert_allclose(mid.p_world[0], gt.p_world[:2].mean(axis=0))
    half = Rotation.from_quat(gt.q_wxyz[0, [1, 2, 3, 0]]).inv() * Rotation.from_quat(mid.q_wxyz[0, [1, 2, 3, 0]])
    full = Rotation.from_quat(gt.q_wxyz[0, [1, 2, 3, 0]]).inv() * Rotation.from_quat(gt.q_wxyz[1, [1, 2, 3, 0]])
    np.testing.assert_allclose(2 * half.as_rotvec(), full.as_rotvec(), atol=1e-12)
