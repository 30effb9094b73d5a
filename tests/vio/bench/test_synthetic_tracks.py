"""True feature tracks for a simulated capture (vio.bench.synthetic_tracks): every noise-free observation is the
projection of its track's surface point from the ground-truth camera pose, the noise has the sigma asked for, hidden
points end their tracks, and the estimator runs on them."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from vio.bench.synthetic_tracks import true_tracks
from vio.errors import VioError
from vio.readers import open_capture


def _world_T_cam(cap, t_ns: int) -> np.ndarray:
    gt = cap.ground_truth
    t = gt.t_ns.astype(float)
    R = Slerp(t, Rotation.from_quat(gt.q_wxyz[:, [1, 2, 3, 0]]))([float(t_ns)]).as_matrix()[0]
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = [np.interp(float(t_ns), t, gt.p_world[:, k]) for k in range(3)]
    return T @ cap.camera.body_T_cam


def _residuals(cap, tracks, points) -> np.ndarray:
    out = []
    for tr in tracks:
        T = _world_T_cam(cap, tr.t_ns)
        pc = (points[tr.ids] - T[:3, 3]) @ T[:3, :3]
        out.append(tr.uv - cap.camera.project(pc))
    return np.vstack(out)


@pytest.fixture(scope="module")
def capture(sim_capture):
    return open_capture(sim_capture("orbit", 3.0))


def test_noise_free_tracks_are_the_true_projections(capture):
    tracks, points = true_tracks(capture, 0.0)
    assert len(tracks) == capture.num_frames
    assert all(len(tr.ids) == 150 for tr in tracks)
    r = _residuals(capture, tracks, points)
    assert np.max(np.abs(r)) < 0.01  # px: the scenario's camera poses and the ground truth's agree
    lengths = np.bincount(np.concatenate([tr.ids for tr in tracks]))
    assert 10 < np.mean(lengths[lengths > 0]) < 40  # tracks end (mean lifetime 25 frames, cut by the view)


def test_noise_has_the_sigma_asked_for(capture):
    tracks, points = true_tracks(capture, 0.5, seed=3)
    r = _residuals(capture, tracks, points)
    assert abs(np.std(r) / 0.5 - 1.0) < 0.03
    assert abs(np.mean(r)) < 0.01


def test_points_are_on_the_seen_surface_and_hidden_ones_end(capture):
    """A track's point is what its first pixel sees: casting the ray again from that pixel lands on it."""
    from vio.bench.imu_ablation import simulated_scenario
    from vio.sim.render import Renderer, camera_poses

    tracks, points = true_tracks(capture, 0.0, seed=1)
    sc = simulated_scenario(capture.root)
    renderer = Renderer(sc.scene, capture.camera)
    T = camera_poses(sc, np.array([capture.frame_t_ns[-1]]), capture.camera)[0]
    hit, _ = renderer.surface_points(T, tracks[-1].uv)
    assert np.max(np.linalg.norm(hit - points[tracks[-1].ids], axis=1)) < 1e-3


def test_not_a_simulated_capture(tmp_path):
    from vio.bench.imu_ablation import simulated_scenario

    with pytest.raises(VioError, match="not a simulated capture"):
        simulated_scenario(tmp_path)


def test_command_runs_the_estimator(sim_capture, tmp_path):
    cap = sim_capture("orbit", 4.0)
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "vio.bench.synthetic_tracks", str(cap), str(out), "--noise-px", "0.3"]
    res = subprocess.run([*cmd, "--set", "estimator.pixel_sigma=0.5"], capture_output=True, text=True, check=False)
    assert res.returncode == 0, res.stdout + res.stderr
    assert (out / "trajectory.tum").is_file()
    import json

    from vio.evaluate import evaluate_files

    gt = cap / "mav0/state_groundtruth_estimate0/data.csv"
    evaluate_files(gt, out / "trajectory.tum", "se3", tmp_path / "m.json")
    assert json.loads((tmp_path / "m.json").read_text())["ate_rmse_m"] < 0.05
