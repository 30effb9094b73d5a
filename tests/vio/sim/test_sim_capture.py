"""Simulated captures: determinism, ASL round trip, the trajectory-file scenario, the command line and its errors."""

from __future__ import annotations

import hashlib
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import ROOT
from vio.errors import CaptureError, SimulationError
from vio.readers import open_capture
from vio.readers.asl import read_asl
from vio.sim.api import load_scenario, simulate
from vio.sim.parts import read_stl_mesh
from vio.sim.render import Renderer, camera_poses
from vio.trajio import Trajectory, write_tum
from vio.writers.asl import AslWriter

VIO = [sys.executable, "-m", "vio.cli"]


def _digests(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def test_same_seed_gives_identical_files_and_another_seed_does_not(tmp_path):
    a = simulate("figure8", tmp_path / "a", seed=11, duration_s=0.6, workers=1)
    b = simulate("figure8", tmp_path / "b", seed=11, duration_s=0.6, workers=2)  # worker count does not matter
    c = simulate("figure8", tmp_path / "c", seed=12, duration_s=0.6, workers=1)
    da, db, dc = _digests(a), _digests(b), _digests(c)
    assert len(da) == 5 + 12 + 5  # csv/yaml files, 12 frames, scene (object.stl, cad.stl, part_pose.yaml,
    # scene.yaml) and the ground-truth yaml
    assert da == db
    differs = {k for k in da if da[k] != dc.get(k)}
    for stream in ("mav0/imu0/data.csv", "mav0/state_groundtruth_estimate0/data.csv", "mav0/cam0/data/"):
        assert any(k.startswith(stream) for k in differs), stream
    assert da["scene/object.stl"] == dc["scene/object.stl"]  # the same cube


def test_capture_round_trip(tmp_path, sim_capture):
    root = sim_capture("orbit", duration_s=1.0, imu="phone", seed=3, images=True)
    cap = read_asl(root)
    sc = load_scenario("orbit", seed=3, duration_s=1.0)
    # What was written is what the simulator computed.
    assert np.array_equal(cap.frame_t_ns, sc.frame_times_ns()) and cap.num_frames == 20
    assert cap.imu is not None and len(cap.imu) == 201 and cap.imu.t_ns[0] == sc.t0_ns
    truth = sc.trajectory.sample((cap.ground_truth.t_ns - sc.t0_ns) * 1e-9)
    assert np.abs(cap.ground_truth.p_world - truth.p_world).max() < 1e-9
    assert np.allclose(cap.camera.body_T_cam, sc.camera.body_T_cam, atol=1e-12) and cap.camera.fx == sc.camera.fx
    assert cap.imu_calib == sc.imu_calib
    img = Renderer(sc.scene, sc.camera).render(camera_poses(sc, cap.frame_t_ns[:1])[0], None)
    diff = np.abs(cap.load_image(0).astype(int) - img)
    assert diff.mean() < 2.0 and diff.max() <= 12  # the same view up to the pixel noise (sigma 1.5)
    v, f = read_stl_mesh(cap.scene_dir / "object.stl")
    assert f.shape == (12, 3) and np.allclose(v.max(axis=0) - v.min(axis=0), 0.0762)
    # Written again with AslWriter and read back: equal.
    with AslWriter(tmp_path / "copy") as w:
        w.write_camera(cap.camera)
        w.write_imu(cap.imu_calib, cap.imu)
        w.write_groundtruth(cap.ground_truth)
        for i, t in enumerate(cap.frame_t_ns):
            w.add_frame(int(t), cap.load_image(i))
    back = read_asl(tmp_path / "copy")
    assert np.array_equal(back.imu.t_ns, cap.imu.t_ns) and np.array_equal(back.imu.acc, cap.imu.acc)
    assert np.array_equal(back.imu.gyro, cap.imu.gyro)
    for field in ("t_ns", "p_world", "v_world", "b_w", "b_a"):
        assert np.array_equal(getattr(back.ground_truth, field), getattr(cap.ground_truth, field)), field
    # The reader re-normalises quaternions, which may move the last of the 12 written digits.
    assert np.abs(back.ground_truth.q_wxyz - cap.ground_truth.q_wxyz).max() < 1e-12
    assert back.camera.fx == cap.camera.fx and np.array_equal(back.camera.dist, cap.camera.dist)
    assert all(np.array_equal(back.load_image(i), cap.load_image(i)) for i in range(cap.num_frames))


@pytest.mark.parametrize(("images", "needs"), [(True, ("camera", "imu")), (False, ("imu",))])
def test_open_capture_checks_a_simulated_capture_without_changing_it(sim_capture, images, needs):
    """`open_capture` (what the pipeline, the bench, `vio track` and `vio info` use) validates, and returns the
    very data `read_asl` reads."""
    root = sim_capture("orbit", duration_s=1.0, imu="phone", seed=3, images=images)
    raw, cap = read_asl(root), open_capture(root, needs=needs)
    assert cap.format == raw.format == "asl" and cap.warnings == raw.warnings == []
    assert np.array_equal(cap.frame_t_ns, raw.frame_t_ns) and cap.num_frames == (20 if images else 0)
    for field in ("t_ns", "gyro", "acc"):
        assert np.array_equal(getattr(cap.imu, field), getattr(raw.imu, field)), field
    for field in ("t_ns", "p_world", "q_wxyz", "v_world", "b_w", "b_a"):
        assert np.array_equal(getattr(cap.ground_truth, field), getattr(raw.ground_truth, field)), field
    assert cap.imu_calib == raw.imu_calib and cap.camera.fx == raw.camera.fx
    assert np.array_equal(cap.camera.body_T_cam, raw.camera.body_T_cam)
    if images:
        assert np.array_equal(cap.load_image(19), raw.load_image(19))
    else:
        with pytest.raises(CaptureError, match="no camera frames"):
            open_capture(root)  # the estimator's checks: an IMU-only capture is refused


def test_trajectory_file_drives_the_simulator(tmp_path, sim_capture):
    """A TUM file made from an orbit's ground truth: the spline reproduces it and the capture is complete."""
    gt = read_asl(sim_capture("orbit", duration_s=4.0, imu="ideal", images=False)).ground_truth
    keep = np.arange(0, len(gt), 4)  # 50 Hz, like a motion-capture export
    write_tum(tmp_path / "traj.tum", Trajectory(gt.t_ns[keep], gt.p_world[keep], gt.q_wxyz[keep]))
    sc = load_scenario(tmp_path / "traj.tum")
    assert sc.t0_ns == int(gt.t_ns[0]) + 50_000_000 and sc.duration_s == pytest.approx(3.9)
    t = np.arange(0.0, sc.duration_s, 0.01)
    s = sc.trajectory.sample(t)
    ref_t = (gt.t_ns - sc.t0_ns) * 1e-9
    for k in range(3):
        assert np.abs(np.interp(t, ref_t, gt.p_world[:, k]) - s.p_world[:, k]).max() < 2e-3
    assert sc.scene.room.contains(s.p_world).all()
    out = simulate(tmp_path / "traj.tum", tmp_path / "cap", duration_s=0.5, imu_grade="tactical")
    cap = read_asl(out)
    assert cap.num_frames == 10 and cap.load_image(9).std() > 10.0  # textured walls in view


def test_cli_simulate_smoke(tmp_path):
    r = subprocess.run(
        [*VIO, "simulate", "room", "--out", str(tmp_path / "r"), "--duration", "0.3", "--seed", "2", "--imu", "ideal"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr
    cap = read_asl(tmp_path / "r")
    assert cap.num_frames == 6 and len(cap.imu) == 61 and cap.load_image(5).shape == (480, 640)
    assert "imu_grade: ideal" in (tmp_path / "r" / "scene" / "scene.yaml").read_text()


def test_cli_simulate_a_user_part_with_stills(tmp_path):
    """A user's STL in metres, plain paint, stills: the CAD comes back in millimetres on its base."""
    from vio.sim.parts import build_part, read_stl_mesh, write_stl

    cube = build_part("cube")
    stl = tmp_path / "block.stl"
    write_stl(stl, cube.vertices_mm * [1e-3, 0.5e-3, 0.25e-3] + [1.0, 2.0, 3.0], cube.faces, "a user part in metres")
    cmd = [*VIO, "simulate", "orbit", "--out", str(tmp_path / "o"), "--duration", "0.6", "--object", str(stl)]
    cmd += ["--object-units", "m", "--surface", "plain", "--stills", "2", "--stills-size", "800x600"]
    r = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert r.returncode == 0, r.stderr
    v, _ = read_stl_mesh(tmp_path / "o" / "scene" / "cad.stl")
    assert np.allclose(v.min(axis=0), [-38.1, -19.05, 0.0], atol=1e-3)
    assert np.allclose(v.max(axis=0), [38.1, 19.05, 19.05], atol=1e-3)
    cap = open_capture(tmp_path / "o")
    assert cap.stills is not None and len(cap.stills) == 2 and cap.stills.load_image(0).shape == (600, 800)
    assert "part: block" in (tmp_path / "o" / "scene" / "scene.yaml").read_text()
    cmd = [*VIO, "simulate", "orbit", "--out", str(tmp_path / "x"), "--object", str(tmp_path / "no.stl")]
    bad = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert bad.returncode != 0 and "no.stl" in bad.stderr and "Traceback" not in bad.stderr


@pytest.mark.parametrize(
    ("content", "match"),
    [
        (None, "unknown scenario 'nosuch'"),
        ("0.0 1 2 3 0 0 0 1\n0.1 1 2 3 0 0 1\n", "traj.tum:2: TUM row needs 8 fields"),
        ("0.0 1 2 3 0 0 0 1\n0.1 1 2 3 0 0 0 1\n", "needs at least 10 poses"),
    ],
)
def test_bad_scenario_is_one_clear_line(tmp_path, content, match):
    scenario = "nosuch"
    if content is not None:
        scenario = str(tmp_path / "traj.tum")
        Path(scenario).write_text(content)
    with pytest.raises((SimulationError, CaptureError), match=match):
        load_scenario(scenario)
    r = subprocess.run(
        [*VIO, "simulate", scenario, "--out", str(tmp_path / "o")],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
    )
    assert r.returncode != 0 and "Traceback" not in r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and match in lines[0], r.stderr
    assert not (tmp_path / "o").exists()


def test_scenario_definitions_match_the_builtins(tmp_path):
    for name in ("orbit", "figure8", "room"):
        a = load_scenario(name, seed=3)
        b = load_scenario(ROOT / "data" / "synthetic" / f"{name}.yaml", seed=3)
        t = np.linspace(0.0, a.duration_s, 200)
        assert a.duration_s == b.duration_s and np.array_equal(a.trajectory.pose(t)[0], b.trajectory.pose(t)[0])
    quick = load_scenario(ROOT / "data" / "synthetic" / "orbit_quick.yaml")
    s = quick.trajectory.sample(np.arange(0.0, quick.duration_s, 0.05))
    top = quick.scene.object_corners_world()[:, 2].max()
    rel = s.p_world - quick.scene.object_corners_world().mean(axis=0)
    elevation = np.degrees(np.arctan2(rel[:, 2], np.linalg.norm(rel[:, :2], axis=1)))
    assert quick.duration_s == 20.0 and elevation.max() > 55.0 and np.abs(elevation[:10]).max() < 8.0 and top > 0
    bad = tmp_path / "bad.yaml"
    bad.write_text("scenario: orbit\nmotion:\n  ring_seconds: 3\n")
    with pytest.raises(SimulationError, match="bad.yaml: unknown motion key"):
        load_scenario(bad)


@pytest.mark.parametrize("name", ["orbit", "figure8", "room"])
def test_camera_stays_in_free_space(name):
    """The camera never enters the table, the cube or furniture, and keeps 0.3 m from the walls."""
    sc = load_scenario(name)
    p, R = sc.trajectory.pose(np.arange(0.0, sc.duration_s, 0.01))
    p_cam = p + R @ sc.camera.body_T_cam[:3, 3]
    assert np.all(p_cam > sc.scene.room.lo + 0.3) and np.all(p_cam < sc.scene.room.hi - 0.3)
    for box in sc.scene.solids:
        outside = np.maximum(np.maximum(box.lo - p_cam, p_cam - box.hi), 0.0)
        assert np.linalg.norm(outside, axis=1).min() > 0.01, box.name


def test_real_euroc_ground_truth_drives_the_simulator():
    """EuRoC V1_01's ground truth as the scenario: the simulated ideal IMU matches the real one (frames, signs)."""
    from scipy.ndimage import uniform_filter1d

    from tests.conftest import shared_path
    from vio.sim.imu import IMU_GRADES, simulate_imu

    root = shared_path("euroc_v1_01")
    gt_csv = root / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    sc = load_scenario(gt_csv, duration_s=30.0)
    sim, gt = simulate_imu(sc.trajectory, sc.t0_ns, 30.0, 200.0, IMU_GRADES["ideal"], np.random.default_rng(0))
    real = read_asl(root)
    inside = (real.ground_truth.t_ns >= gt.t_ns[0]) & (real.ground_truth.t_ns <= gt.t_ns[-1])
    p_sim = np.column_stack([np.interp(real.ground_truth.t_ns[inside], gt.t_ns, gt.p_world[:, k]) for k in range(3)])
    assert np.abs(p_sim - real.ground_truth.p_world[inside]).max() < 5e-3  # the spline follows the recording
    k = np.searchsorted(real.imu.t_ns, gt.t_ns).clip(0, len(real.imu) - 1)
    ok = np.abs(real.imu.t_ns[k] - gt.t_ns) < 3_000_000
    b = np.searchsorted(real.ground_truth.t_ns, gt.t_ns[ok]).clip(0, len(real.ground_truth) - 1)
    gyro_real = real.imu.gyro[k[ok]] - real.ground_truth.b_w[b]
    acc_real = real.imu.acc[k[ok]] - real.ground_truth.b_a[b]
    # Averaged over 0.2 s (the drone's vibration is not in the smoothed ground truth) they agree closely.
    smooth = lambda x: uniform_filter1d(x, 40, axis=0)  # noqa: E731
    assert np.sqrt(np.mean((smooth(gyro_real) - smooth(sim.gyro[ok])) ** 2)) < 0.02  # rad/s
    assert np.sqrt(np.mean((smooth(acc_real) - smooth(sim.acc[ok])) ** 2)) < 0.3  # m/s^2
