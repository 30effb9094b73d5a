"""Run health (vio/health.py): spans with start, end and cause; status ok | degraded | failed; frames that fail to
decode are skipped and counted; a run that cannot go on leaves a run.json that says so."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.conftest import ROOT
from vio.config import load_config
from vio.health import HealthMonitor, TooManySkipped, imu_only_spans, runs
from vio.pipeline import run_capture
from vio.records import EstimatorStats, ImuSeries, RecoveryEvent

RUN_SET = ["run.progress=false"]
MS = 1_000_000


def _copy(capture: Path, dst: Path) -> Path:
    """A copy of a capture whose files are hard links (cheap); replaced images do not touch the original."""
    shutil.copytree(capture, dst, copy_function=os.link)
    return dst


def _images(capture: Path) -> list[Path]:
    return sorted((capture / "mav0" / "cam0" / "data").iterdir())


def _replace(path: Path, data: bytes) -> None:
    path.unlink()  # a new file, not a write through the hard link
    path.write_bytes(data)


def _stats(keyframes=(), recoveries=()) -> EstimatorStats:
    return EstimatorStats("moving", (), 0, 0, 0, 0, 0, tuple(recoveries), (), (), keyframe_projections=keyframes)


def test_runs_of_true_values():
    assert runs(np.array([0, 1, 1, 0, 1], bool)) == [(1, 3), (4, 5)]
    assert runs(np.zeros(3, bool)) == [] and runs(np.ones(2, bool)) == [(0, 2)]


def test_spans_from_frames_keyframes_imu_and_recoveries():
    cfg = load_config(None, ["health.min_tracked_features=10", "health.min_span_s=0.2"])
    mon = HealthMonitor(cfg, 100)
    counts = [150] * 10 + [0] * 5 + [150] * 10 + [5] * 3 + [150] * 10  # 50 ms frames
    for i, n in enumerate(counts):
        mon.frame(i * 50 * MS, n)
    kfs = tuple((k, k * 200 * MS, 0 if k in (3, 4) else 40) for k in range(10))
    rec = RecoveryEvent(7, 7 * 200 * MS, "IndeterminantLinearSystemException\nmore", 6)
    t_imu = np.concatenate([np.arange(0, 900 * MS, 5 * MS), np.arange(1000 * MS, 2000 * MS, 5 * MS)])
    imu = ImuSeries(t_imu, np.zeros((t_imu.size, 3)), np.zeros((t_imu.size, 3)))
    mon.keyframe_skipped(1800 * MS, "RuntimeError: boom")
    health = mon.report(_stats(kfs, [rec]), [t for _, t, _ in kfs], imu)
    got = [(s.kind, s.start_t_ns // MS, s.end_t_ns // MS) for s in health.spans]
    assert got == [
        ("imu_only", 400, 1000),  # keyframes 3 and 4, bridged from keyframe 2 to keyframe 5
        ("tracking_lost", 500, 750),  # 5 frames without features, until the first good frame
        ("imu_gap", 895, 1000),
        ("recovery", 1200, 1400),  # rebuilt from keyframe 6 after keyframe 7 failed
        ("keyframe_skipped", 1800, 1800),
    ]  # the 3 thin frames (150 ms) are shorter than min_span_s
    assert health.status == "degraded" and len(health.reasons) == 5
    assert health.reasons[1].startswith("tracking lost 0.50-0.75 s (0.25 s): no tracked features in 5 frames")
    assert "IndeterminantLinearSystemException; rebuilt" in health.spans[3].cause
    ok = HealthMonitor(cfg, 10)
    ok.frame(0, 100)
    assert ok.report(_stats(), [], None).status == "ok"
    assert ok.report(_stats(), [], None, failure="no estimate").status == "failed"


def test_imu_only_counts_only_keyframes_with_an_estimate():
    kfs = ((0, 0, 0), (1, 10, 0), (2, 20, 5), (3, 30, 0))
    spans = imu_only_spans(kfs, {20, 30}, 1)  # 0 and 1 were buffered before the start and dropped
    assert [(s.start_t_ns, s.end_t_ns) for s in spans] == [(20, 30)]


def test_keyframes_at_rest_are_not_imu_alone():
    """A still start (as `vio run`'s advice asks) gives keyframes without projections that zero-velocity updates
    hold: not a degraded run; keyframes without either still are."""
    kfs = ((0, 0, 0), (1, 10, 0), (2, 20, 0), (3, 30, 0), (4, 40, 5), (5, 50, 0), (6, 60, 5))
    est = {0, 10, 20, 30, 40, 50, 60}
    spans = imu_only_spans(kfs, est, 1, still=(0, 10, 20))
    assert [(s.start_t_ns, s.end_t_ns) for s in spans] == [(20, 40), (40, 60)]  # 30 moved without images; 50 too
    assert "1 keyframe(s)" in spans[0].cause
    assert [(s.start_t_ns, s.end_t_ns) for s in imu_only_spans(kfs, est, 1)] == [(0, 40), (40, 60)]


def test_too_many_skipped_frames_stop_the_run():
    mon = HealthMonitor(load_config(None, ["health.max_skipped_frames=0.1"]), 30)
    for i in range(3):
        mon.skip(i, "bad")
    with pytest.raises(TooManySkipped, match="4 frames failed to decode"):
        mon.skip(3, "bad")


@pytest.fixture(scope="module")
def orbit(sim_capture):
    return sim_capture("orbit", 6.0)


def test_a_covered_lens_is_reported_as_degraded_with_its_span(orbit, tmp_path):
    """1 s of black frames (3.0-4.0 s) in a 6 s orbit: the run goes on, and says when and why it was degraded."""
    cap = _copy(orbit, tmp_path / "cap")
    images = _images(cap)
    shape = cv2.imread(str(images[0]), cv2.IMREAD_GRAYSCALE).shape
    black = cv2.imencode(".png", np.zeros(shape, np.uint8))[1].tobytes()
    for p in images[60:80]:
        _replace(p, black)
    res = run_capture(cap, tmp_path / "out", load_config(None, RUN_SET))
    run = json.loads((tmp_path / "out" / "run.json").read_text())
    assert run["status"] == "degraded" == res.summary["status"]
    lost = [s for s in run["health"]["spans"] if s["kind"] == "tracking_lost"]
    assert len(lost) == 1 and (lost[0]["start_s"], lost[0]["end_s"]) == (3.0, 4.0)
    assert "no tracked features in 20 frames" in lost[0]["cause"]
    imu_only = [s for s in run["health"]["spans"] if s["kind"] == "imu_only"]
    assert len(imu_only) == 1 and imu_only[0]["start_s"] <= 3.0 and imu_only[0]["end_s"] >= 4.0
    assert any(r.startswith("tracking lost 3.00-4.00 s") for r in run["reasons"])
    assert 0.0 <= run["health"]["first_estimate_s"] < 2.0  # the moving start's end
    assert (tmp_path / "out" / "trajectory.tum").exists() and res.summary["span_s"] > 5.9


def test_a_corrupt_frame_is_skipped_and_counted(orbit, tmp_path):
    cap = _copy(orbit, tmp_path / "cap")
    images = _images(cap)
    _replace(images[0], b"\x89PNG\r\n\x1a\n garbage")  # the first frame too: the size check uses the next one
    _replace(images[50], images[51].read_bytes()[:100])  # truncated
    cfg = load_config(None, [*RUN_SET, "run.max_frames=80"])
    res = run_capture(cap, tmp_path / "out", cfg)
    health = res.summary["health"]
    assert res.summary["status"] == "degraded" and health["num_frames_skipped"] == 2
    skipped = [s for s in health["spans"] if s["kind"] == "frames_skipped"]
    assert [(s["start_s"], s["end_s"]) for s in skipped] == [(0.0, 0.05), (2.5, 2.55)]
    assert images[50].name in skipped[1]["cause"] and "cannot be decoded" in skipped[1]["cause"]
    assert res.summary["num_frames"] == 78 and len(res.states) > 10


def test_too_many_corrupt_frames_end_with_one_line_and_a_failed_run_json(orbit, tmp_path):
    cap = _copy(orbit, tmp_path / "cap")
    for p in _images(cap)[10:20]:
        _replace(p, b"not an image")
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "vio.cli", "run", str(cap), "--out", str(out), "--set", "run.max_frames=60"]
    res = subprocess.run([*cmd, "--set", "run.progress=false"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert res.returncode == 2 and "Traceback" not in res.stderr
    last = res.stderr.strip().splitlines()[-1]
    assert last.startswith("vio run: error: ") and "7 frames failed to decode" in last, res.stderr[-1500:]
    run = json.loads((out / "run.json").read_text())
    assert run["status"] == "failed" and "health.max_skipped_frames" in run["reasons"][0]
    assert not (out / "trajectory.tum").exists()


def test_a_diverged_estimate_is_a_one_line_failure_not_a_traceback():
    """Measured: vision-only on a 15 s figure eight blew up (rotations of 1e10) and writing trajectory.tum raised a
    scipy traceback. A pose that is not one now ends the run as failed, in one line naming the keyframe."""
    import numpy as np
    import pytest

    from vio.errors import EstimationError
    from vio.outputs import trajectory_of
    from vio.records import StateEstimate

    def state(k: int, T: np.ndarray) -> StateEstimate:
        return StateEstimate(k, 1_000_000_000 * k, T, np.zeros(3), np.zeros(3), np.zeros(3))

    good = [state(k, np.eye(4)) for k in range(3)]
    assert len(trajectory_of(good).t_ns) == 3
    blown = np.eye(4)
    blown[:3, :3] = [[1.7e9, 5.5e10, -6e8], [-7e8, -2.3e10, 2.5e8], [-2e9, -6.5e10, 7e8]]
    with pytest.raises(EstimationError, match=r"diverged: keyframe 3 \(t = 3.000 s\).*1 of 4"):
        trajectory_of([*good, state(3, blown)])
    far = np.eye(4)
    far[0, 3] = np.nan
    with pytest.raises(EstimationError, match="keyframe 0"):
        trajectory_of([state(0, far)])
