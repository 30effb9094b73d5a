"""The rerun sink: a saved recording verifies and holds every archetype; --serve binds only to the loopback address.

Records are built from a real capture: real images, features tracked by OpenCV's pyramidal LK on its pixels (ages
counted here), keyframe states and landmarks from the capture's ground truth. Run this file as a script for the
sink's logging cost: `.venv/bin/python -m tests.vio.viz.test_viz --bench [CAPTURE]`.
"""

from __future__ import annotations

import re
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.conftest import ROOT, shared_path
from vio.capture import Capture
from vio.readers.asl import read_asl
from vio.records import StateEstimate

RERUN = Path(sys.executable).parent / "rerun"  # installed beside the interpreter running the tests
KEYFRAME_EVERY = 3  # frames
N_FRAMES = 40
EST_WORLD_T_GT_WORLD = np.array(  # yaw 40 deg and an offset: the estimate's world is not the ground truth's
    [[np.cos(0.7), -np.sin(0.7), 0, 1.0], [np.sin(0.7), np.cos(0.7), 0, -2.0], [0, 0, 1, 0.5], [0, 0, 0, 1]]
)
EXPECTED = ["EncodedImage", "Pinhole", "Transform3D", "Points2D", "Points3D", "LineStrips3D", "Scalars"]


def _gt_at(capture: Capture, t_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Nearest ground-truth sample: world_T_body (4, 4), v_world, b_w, b_a."""
    gt = capture.ground_truth
    i = int(np.clip(np.searchsorted(gt.t_ns, t_ns), 0, len(gt) - 1))
    return gt.world_T_body(i), gt.v_world[i], gt.b_w[i], gt.b_a[i]


def feed(
    sink,
    capture: Capture,
    max_frames: int | None = None,
    timings: list[float] | None = None,
    est_world_T_gt_world: np.ndarray | None = None,
) -> int:
    """Drive `sink` with the capture's records the way the pipeline does; returns the number of keyframes.

    Estimates are the ground truth moved into another world by `est_world_T_gt_world` (as an estimator's world
    differs from the ground truth's by yaw and position); landmarks are the keyframe's rays at made-up depths."""
    T_est_gt = np.eye(4) if est_world_T_gt_world is None else est_world_T_gt_world
    cam = capture.camera
    sink.on_start(cam, capture.imu, capture.ground_truth)
    prev, pts, ids, ages = None, np.zeros((0, 2), np.float32), np.zeros(0, np.int64), np.zeros(0, int)
    next_id, landmarks, k = 0, {}, 0
    for n, frame in enumerate(capture.frames(0, max_frames)):
        t0 = time.perf_counter()
        img = frame.image
        if prev is not None and len(pts):
            new, st, _ = cv2.calcOpticalFlowPyrLK(prev, img, pts, None, winSize=(21, 21), maxLevel=3)
            keep = st.ravel() == 1
            pts, ids, ages = new[keep], ids[keep], ages[keep] + 1
        if len(pts) < 120:
            mask = np.full(img.shape[:2], 255, np.uint8)
            for u, v in pts:
                cv2.circle(mask, (int(u), int(v)), 15, 0, -1)
            c = cv2.goodFeaturesToTrack(img, 150 - len(pts), 0.01, 15, mask=mask)
            if c is not None:
                c = c.reshape(-1, 2)
                pts = np.vstack([pts, c]).astype(np.float32)
                ids = np.concatenate([ids, np.arange(next_id, next_id + len(c))])
                ages = np.concatenate([ages, np.zeros(len(c), int)])
                next_id += len(c)
        prev = img
        t_sink = time.perf_counter()
        sink.on_frame(frame, ids.copy(), pts.astype(np.float64), ages.copy())
        spent = time.perf_counter() - t_sink
        if n % KEYFRAME_EVERY == 0:
            world_T_body, v, bw, ba = _gt_at(capture, frame.t_ns)
            world_T_body, v = T_est_gt @ world_T_body, T_est_gt[:3, :3] @ v
            world_T_cam = world_T_body @ cam.body_T_cam
            rays = np.column_stack([cam.undistort_to_normalized(pts), np.ones(len(pts))])
            depth = 2.0 + (ids % 7) * 0.3  # metres, varied per track so the cloud has relief
            p_world = (world_T_cam[:3, :3] @ (rays * depth[:, None]).T).T + world_T_cam[:3, 3]
            for j, p in zip(ids.tolist(), p_world, strict=True):
                landmarks.setdefault(j, p)
            lm_ids = np.array(sorted(landmarks), np.int64)
            est = StateEstimate(
                k, frame.t_ns, world_T_body, v, bw, ba, lm_ids, np.array([landmarks[j] for j in lm_ids])
            )
            stats = {"solve_ms": 5.0 + k % 4, "num_landmarks": len(lm_ids)}  # the sink computes the reprojection
            t_sink = time.perf_counter()
            sink.on_estimate(est, stats)
            spent += time.perf_counter() - t_sink
            k += 1
        if timings is not None:
            timings.append(spent)
        del t0
    return k


@pytest.fixture(scope="module", params=["sim", "euroc"])
def capture(request, sim_capture) -> Capture:
    """A short simulated orbit (rendered images, exact ground truth) and the real EuRoC frames."""
    if request.param == "sim":
        return read_asl(sim_capture("orbit", 4.0))
    return read_asl(shared_path("euroc_v1_01"))


@pytest.fixture(scope="module")
def recording(capture, tmp_path_factory) -> Path:
    from vio.viz.rerun_sink import make_rerun_sink

    rrd = tmp_path_factory.mktemp("viz") / "run.rrd"
    sink = make_rerun_sink(rrd=rrd)
    assert not rrd.exists()  # only renamed into place by close()
    assert feed(sink, capture, max_frames=N_FRAMES, est_world_T_gt_world=EST_WORLD_T_GT_WORLD) > 5
    sink.close()
    return rrd


def test_rrd_verifies(recording):
    res = subprocess.run([str(RERUN), "rrd", "verify", str(recording)], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert not list(recording.parent.glob(".*.tmp"))


CHUNK_LINE = re.compile(r"with (\d+) rows .* - (/\S*) - data columns: \[([^\]]*)\]")


def chunk_summary(rrd: Path) -> dict[tuple[str, str], int]:
    """(entity path, archetype) -> number of rows logged, parsed from `rerun rrd print` (recording and blueprint)."""
    res = subprocess.run([str(RERUN), "rrd", "print", str(rrd)], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    rows: dict[tuple[str, str], int] = {}
    for m in CHUNK_LINE.finditer(res.stdout):
        for arch in {c.split(":")[0] for c in m.group(3).split()}:
            rows[(m.group(2), arch)] = rows.get((m.group(2), arch), 0) + int(m.group(1))
    return rows


def test_rrd_holds_every_archetype(recording, capture):
    from vio.viz import blueprint as bp

    rows = chunk_summary(recording)
    archetypes = {arch for _, arch in rows}
    assert set(EXPECTED) <= archetypes, f"missing: {set(EXPECTED) - archetypes}"
    n_kf = -(-N_FRAMES // KEYFRAME_EVERY)
    assert rows[("/" + bp.IMAGE, "EncodedImage")] == N_FRAMES
    assert rows[("/" + bp.FEATURES, "Points2D")] == N_FRAMES
    assert rows[("/" + bp.IMAGE, "Pinhole")] == 1  # static
    assert rows[("/" + bp.CAMERA, "Transform3D")] == n_kf
    assert rows[("/" + bp.TRAJ_EST, "LineStrips3D")] == n_kf
    assert rows[("/" + bp.TRAJ_GT, "LineStrips3D")] == 1  # static
    assert rows[("/" + bp.LANDMARKS, "Points3D")] == n_kf
    assert rows[("/" + bp.SOLVE_MS, "Scalars")] == n_kf
    assert rows[("/" + bp.REPROJ_PX, "Scalars")] == n_kf
    assert rows[("/" + bp.PLOT_GYRO, "Scalars")] == len(capture.imu)  # the whole stream, one send_columns
    assert rows[("/" + bp.PLOT_VEL + "/" + bp.GT, "Scalars")] == len(capture.ground_truth)
    assert rows[("/" + bp.PLOT_VEL + "/" + bp.EST, "Scalars")] == n_kf
    assert ("/" + bp.WORLD, "ViewCoordinates") in rows


def read_column(rrd: Path, entity: str, column: str) -> list:
    """All rows of one component column of one entity in the recording, ordered by sensor time (static first)."""
    from rerun.chunk import RrdReader

    from vio.viz import blueprint as bp

    rows = []
    for chunk in RrdReader(rrd).stream():
        if chunk.entity_path == "/" + entity:
            rb = chunk.to_record_batch()
            if column in rb.schema.names:
                t = rb.column(bp.TIMELINE).cast("int64").to_pylist() if bp.TIMELINE in rb.schema.names else None
                vals = rb.column(column).to_pylist()
                rows += list(zip(t or [-1] * len(vals), vals, strict=True))
    return [v for _, v in sorted(rows, key=lambda r: r[0])]


def test_ground_truth_is_drawn_in_the_estimates_world(recording, capture):
    from vio.viz import blueprint as bp

    (gt_strip,) = read_column(recording, bp.TRAJ_GT, "LineStrips3D:strips")
    T = EST_WORLD_T_GT_WORLD
    expected = capture.ground_truth.p_world @ T[:3, :3].T + T[:3, 3]
    np.testing.assert_allclose(np.array(gt_strip[0]), expected, atol=1e-4)
    est_strips = read_column(recording, bp.TRAJ_EST, "LineStrips3D:strips")
    first_est = np.array(est_strips[-1][0][0])
    world_T_body, *_ = _gt_at(capture, int(capture.frame_t_ns[0]))
    np.testing.assert_allclose(first_est, (T @ world_T_body)[:3, 3], atol=1e-4)


def test_reprojection_error_is_computed_from_the_landmarks(recording):
    from vio.viz import blueprint as bp

    values = [v[0] for v in read_column(recording, bp.REPROJ_PX, "Scalars:scalars")]
    assert len(values) == -(-N_FRAMES // KEYFRAME_EVERY)
    assert values[0] < 1e-3  # keyframe 0's landmarks are its own rays: they reproject exactly
    assert np.isfinite(values).all()


def test_reprojection_error_is_logged_on_a_real_run(sim_capture, tmp_path):
    """`vio run --rrd` on a simulated orbit: the reprojection panel gets a value at every keyframe whose estimate
    carries the landmarks (all but the initialisation's earlier keyframes), from the estimator's own landmarks.

    The landmarks shown live are the admission-time triangulations (`landmarks(sync=False)`), not refined online,
    so the median error is large (~8 px) while the first seconds' estimate settles; a mismatch between landmark and
    track ids gives none (an empty panel) or hundreds of pixels."""
    from vio.config import load_config
    from vio.pipeline import run_capture
    from vio.viz import blueprint as bp
    from vio.viz.rerun_sink import make_rerun_sink

    rrd = tmp_path / "run.rrd"
    result = run_capture(sim_capture("orbit", 4.0), tmp_path / "run", load_config(), sinks=[make_rerun_sink(rrd=rrd)])
    values = np.array([v[0] for v in read_column(rrd, bp.REPROJ_PX, "Scalars:scalars")])
    n_solves = len(read_column(rrd, bp.SOLVE_MS, "Scalars:scalars"))
    assert n_solves == len(result.states) > 10
    assert len(values) >= n_solves - 10  # only the keyframes produced together at initialisation have none
    assert np.isfinite(values).all()
    assert values[0] < 1.0  # at initialisation the landmarks are triangulated from the same poses
    assert np.median(values) < 15.0
    tracked = read_column(rrd, bp.NUM_TRACKED, "Scalars:scalars")
    assert len(tracked) == result.summary["num_frames"] and max(v[0] for v in tracked) > 100
    assert [t[0] for t in read_column(rrd, bp.HEALTH, "TextLog:text")] == [f"status: {result.summary['status']}"]


def test_health_spans_are_logged_at_their_start(tmp_path):
    from vio.health import HealthSpan, RunHealth
    from vio.viz import blueprint as bp
    from vio.viz.rerun_sink import make_rerun_sink

    rrd = tmp_path / "health.rrd"
    sink = make_rerun_sink(rrd=rrd)
    sink.on_start(None, None, None)
    span = HealthSpan("tracking_lost", 3_000_000_000, 4_000_000_000, "no tracked features in 20 frames")
    sink.on_health(RunHealth("degraded", ("x",), (span,), 1_000_000_000, 0, {"min": 0.0, "median": 150.0}))
    sink.close()
    texts = [t[0] for t in read_column(rrd, bp.HEALTH, "TextLog:text")]
    assert texts == ["status: degraded", "tracking lost 2.00-3.00 s (1.00 s): no tracked features in 20 frames"]


def test_default_blueprint_is_in_the_recording(recording):
    res = subprocess.run(
        [str(RERUN), "rrd", "print", "-v", str(recording)], capture_output=True, text=True, timeout=120
    )
    assert "Blueprint" in res.stdout
    assert res.stdout.count("ViewBlueprint:class") >= 12  # 3D, camera, 9 time series views and the health log


def test_feature_colours_follow_track_age():
    import cv2

    from vio.viz.rerun_sink import AGE_SATURATION_FRAMES, _colormap

    ages = np.array([0, AGE_SATURATION_FRAMES // 2, AGE_SATURATION_FRAMES, 10 * AGE_SATURATION_FRAMES])
    rgb = _colormap(ages, 0.0, AGE_SATURATION_FRAMES, cv2.COLORMAP_VIRIDIS)
    assert rgb.shape == (4, 3) and rgb.dtype == np.uint8
    assert len({tuple(c) for c in rgb[:3]}) == 3  # young, middle-aged and old tracks look different
    assert (rgb[2] == rgb[3]).all()  # saturates
    assert rgb[0, 2] > rgb[0, 1] and rgb[2, 1] > rgb[2, 2]  # viridis: young purple-blue, old yellow (RGB order)


def _listening(pid: int) -> list[tuple[str, int]]:
    psutil = pytest.importorskip("psutil")

    conns = psutil.Process(pid).net_connections("inet")
    return [(c.laddr.ip, c.laddr.port) for c in conns if c.status == psutil.CONN_LISTEN]


def test_serve_binds_only_loopback(sim_capture):
    import urllib.request

    from vio.viz.rerun_sink import make_rerun_sink

    sink = make_rerun_sink(serve=True)
    viewer = sink.viewer
    try:
        assert viewer is not None and viewer.kind == "web"
        assert viewer.url.startswith(f"http://127.0.0.1:{viewer.web_port}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A")
        feed(sink, read_asl(sim_capture("orbit", 4.0)), max_frames=6)
        sink.close()
        listening = _listening(viewer.pid)
        ports = {port for _, port in listening}
        assert {viewer.grpc_port, viewer.web_port} <= ports, listening
        assert all(ip == "127.0.0.1" for ip, _ in listening), listening
        with urllib.request.urlopen(viewer.url, timeout=10) as r:  # the web viewer page is served
            assert r.status == 200 and b"<html" in r.read().lower()
        assert viewer.process.poll() is None  # still serving the finished run
    finally:
        viewer.stop()
    assert viewer.process.poll() is not None


@pytest.mark.parametrize("end", ["exit", "sigkill"])
def test_web_server_stops_with_the_process(end):
    psutil = pytest.importorskip("psutil")
    if end == "sigkill" and not sys.platform.startswith("linux"):
        pytest.skip("dying with the parent relies on Linux prctl(PR_SET_PDEATHSIG)")
    code = (
        "import os, signal, sys; from vio.viz.rerun_sink import make_rerun_sink; s = make_rerun_sink(serve=True); "
        "print(s.viewer.pid, flush=True); " + ("s.close()" if end == "exit" else "os.kill(os.getpid(), signal.SIGKILL)")
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT)
    pid = int(res.stdout.split()[-1])

    def alive() -> bool:
        return psutil.pid_exists(pid) and psutil.Process(pid).status() != psutil.STATUS_ZOMBIE

    deadline = time.monotonic() + 10
    while alive() and time.monotonic() < deadline:
        time.sleep(0.2)
    if alive():  # clean up the server this test started before failing
        psutil.Process(pid).terminate()
        pytest.fail(f"rerun server {pid} outlived its process ({end})")


def test_spawn_without_display_is_one_clear_error(monkeypatch, tmp_path):
    from vio.errors import VioError
    from vio.viz.rerun_sink import make_rerun_sink

    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(VioError, match="no display"):
        make_rerun_sink(rrd=tmp_path / "x.rrd", spawn=True)
    assert not list(tmp_path.iterdir())  # no temporary recording left behind


def test_recording_survives_a_viewer_that_went_away(sim_capture, tmp_path):
    from vio.viz.rerun_sink import make_rerun_sink

    rrd = tmp_path / "both.rrd"
    sink = make_rerun_sink(rrd=rrd, serve=True)
    sink.viewer.stop()  # the user closed it, or it crashed
    feed(sink, read_asl(sim_capture("orbit", 4.0)), max_frames=6)
    sink.close()
    res = subprocess.run([str(RERUN), "rrd", "verify", str(rrd)], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert chunk_summary(rrd)[("/world/camera/image", "EncodedImage")] == 6


class _NullSink:
    def on_start(self, *a) -> None: ...
    def on_frame(self, *a) -> None: ...
    def on_estimate(self, *a) -> None: ...
    def close(self) -> None: ...


def bench(capture_dir: str, repeats: int = 5) -> None:
    """Print the sink's cost: wall ms per frame inside its calls (median, p95) and the extra process CPU per frame
    (all threads, so rerun's encoder and file writer count) of feeding the capture with the sink over without it."""
    import tempfile

    from vio.viz.rerun_sink import make_rerun_sink

    capture = read_asl(capture_dir)
    frames = [f.image for f in capture.frames()]  # decode once so PNG reading is not part of any figure
    capture.load_image = lambda i: frames[i]
    cpu_none: list[float] = []
    for r in range(repeats):
        for name in ("none", "rrd"):
            with tempfile.TemporaryDirectory() as d:
                timings: list[float] = []
                c0 = time.process_time()
                sink = _NullSink() if name == "none" else make_rerun_sink(rrd=Path(d) / "b.rrd")
                feed(sink, capture, timings=timings)
                sink.close()
                cpu = time.process_time() - c0
                size = (Path(d) / "b.rrd").stat().st_size if name == "rrd" else 0
            ms = np.array(timings) * 1e3
            if name == "none":
                cpu_none.append(cpu)
                continue
            extra = (cpu - cpu_none[-1]) / len(ms) * 1e3
            print(
                f"run {r}: {len(ms)} frames, sink call wall ms/frame median {np.median(ms):.2f} "
                f"p95 {np.percentile(ms, 95):.2f}; extra CPU {extra:.2f} ms/frame; rrd {size / 1e6:.1f} MB"
            )


if __name__ == "__main__":
    if len(sys.argv) >= 2 and sys.argv[1] == "--bench":
        bench(sys.argv[2] if len(sys.argv) > 2 else str(ROOT.parent / "shared" / "data" / "euroc_v1_01"))
