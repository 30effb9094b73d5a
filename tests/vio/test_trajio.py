"""Trajectory file I/O: TUM and EuRoC CSV detection, nanosecond-exact round trips, clear errors."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tests.conftest import shared_path
from vio.errors import CaptureError
from vio.readers.tables import NS_PER_S, parse_time_ns
from vio.trajio import Trajectory, ns_to_seconds_str, read_trajectory, write_tum


def _random_traj(n: int = 50, seed: int = 0) -> Trajectory:
    rng = np.random.default_rng(seed)
    t_ns = 1_403_715_273_262_142_976 + np.cumsum(rng.integers(1, 60_000_000, n)).astype(np.int64)
    q_xyzw = Rotation.random(n, random_state=seed).as_quat()
    return Trajectory(t_ns, rng.normal(size=(n, 3)) * 5.0, q_xyzw[:, [3, 0, 1, 2]])


def test_tum_round_trip_is_nanosecond_exact(tmp_path):
    traj = _random_traj()
    write_tum(tmp_path / "a.tum", traj)
    back = read_trajectory(tmp_path / "a.tum")
    np.testing.assert_array_equal(back.t_ns, traj.t_ns)
    np.testing.assert_allclose(back.p_world, traj.p_world, atol=1e-9)
    np.testing.assert_allclose(back.q_wxyz, traj.q_wxyz, atol=2e-9)
    assert not list(tmp_path.glob(".*tmp")), "atomic write left a temp file"


@pytest.mark.parametrize(
    ("text", "ns"),
    [("1403715274.30214", 1403715274302140000), ("0.000000001", 1), ("12", 12_000_000_000),
     ("1.0000000005", 1_000_000_001), ("-1.5", -1_500_000_000), ("1.5e3", 1_500_000_000_000)],
)  # fmt: skip
def test_seconds_parsing_is_exact(text, ns):
    assert parse_time_ns(text, NS_PER_S) == ns


def test_seconds_string_format():
    assert ns_to_seconds_str(1403715273262142976) == "1403715273.262142976"
    assert ns_to_seconds_str(5) == "0.000000005"
    assert parse_time_ns(ns_to_seconds_str(-7), NS_PER_S) == -7


def test_reads_euroc_groundtruth_csv():
    path = shared_path("euroc_v1_01", "mav0", "state_groundtruth_estimate0", "data.csv")
    traj = read_trajectory(path)
    assert traj.t_ns[0] == 1403715273262142976
    np.testing.assert_allclose(traj.p_world[0], [0.878895, 2.1834, 0.948427])
    q = np.array([0.069433, -0.824237, -0.106942, -0.551702])
    np.testing.assert_allclose(traj.q_wxyz[0], q / np.linalg.norm(q))
    assert len(traj) > 2000 and np.all(np.diff(traj.t_ns) > 0)


def test_reads_euroc_vicon_tum_and_agrees_with_csv():
    vicon = read_trajectory(shared_path("euroc_v1_01", "vicon_groundtruth_200hz.txt"))
    assert vicon.t_ns[0] == 1403715274302140000
    q_xyzw = np.array([-0.828459, -0.058956, -0.553641, 0.060514])
    np.testing.assert_allclose(vicon.q_wxyz[0], q_xyzw[[3, 0, 1, 2]] / np.linalg.norm(q_xyzw))
    # Both describe the same flight: positions at the shared times agree to centimetres.
    gt = read_trajectory(shared_path("euroc_v1_01", "mav0", "state_groundtruth_estimate0", "data.csv"))
    i = np.searchsorted(vicon.t_ns, gt.t_ns[100])
    assert abs(vicon.t_ns[i] - gt.t_ns[100]) < 5_000_000
    assert np.linalg.norm(vicon.p_world[i] - gt.p_world[100]) < 0.05


def test_csv_without_hash_header_and_extra_columns(tmp_path):
    p = tmp_path / "est.csv"
    p.write_text("timestamp,x,y,z,qw,qx,qy,qz,vx\n100,1,2,3,1,0,0,0,9\n200,1,2,4,0,1,0,0,9\n")
    traj = read_trajectory(p)
    np.testing.assert_array_equal(traj.t_ns, [100, 200])
    np.testing.assert_allclose(traj.q_wxyz[1], [0, 1, 0, 0])


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("# only a comment\n", "no trajectory rows"),
        ("1.0 1 2 3 0 0 0 1\n2.0 1 2 3 0 0 1\n", r"t\.tum:2: TUM row needs 8 fields"),
        ("1.0 1 2 3 0 0 0 1\n0.5 1 2 3 0 0 0 1\n", r":2: timestamp 0\.500000000 s goes backwards"),
        ("1.0 1 2 3 0 0 0 1\n1.0 1 2 3 0 0 0 1\n", r":2: timestamp .* repeats"),
        ("1.0 1 2 x 0 0 0 1\n", r":1: non-numeric field"),
        ("1.0 1 2 nan 0 0 0 1\n", r":1: NaN or inf"),
        ("1.0 1 2 3 0 0 0 2\n", r":1: quaternion norm 2"),
        ("1.5,1,2,3,1,0,0,0\n", r":1: timestamp '1.5' is not an integer"),
        ("100,1,2,3,1,0,0\n", r":1: EuRoC CSV row needs >= 8 fields"),
    ],
)
def test_malformed_files_give_one_line_errors(tmp_path, text, match):
    p = tmp_path / "t.tum"
    p.write_text(text)
    with pytest.raises(CaptureError, match=match) as exc:
        read_trajectory(p)
    assert "\n" not in str(exc.value)


def test_missing_file(tmp_path):
    with pytest.raises(CaptureError, match="not found"):
        read_trajectory(tmp_path / "nope.tum")


def test_shape_mismatch_rejected():
    with pytest.raises(ValueError, match="shapes disagree"):
        Trajectory(np.zeros(3, np.int64), np.zeros((2, 3)), np.zeros((3, 4)))


def test_tum_header_without_hash(tmp_path):
    p = tmp_path / "est.txt"
    p.write_text("timestamp tx ty tz qx qy qz qw\n1.5 1 2 3 0 0 0 1\n2.5 1 2 4 0 0 0 1\n")
    np.testing.assert_array_equal(read_trajectory(p).t_ns, [1_500_000_000, 2_500_000_000])


def test_capture_folder_reads_its_groundtruth(sim_capture, tmp_path):
    root = sim_capture("orbit", duration_s=4.0, imu="ideal", images=False)
    traj = read_trajectory(root)
    assert len(traj) > 100 and np.all(np.diff(traj.t_ns) > 0)
    with pytest.raises(CaptureError, match="is a folder"):
        read_trajectory(tmp_path)
