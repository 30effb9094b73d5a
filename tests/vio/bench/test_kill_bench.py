"""`vio bench` killed mid-suite (SIGKILL, and Ctrl-C to its process group as a terminal sends it) at seeded random
points: no summary is left that passes for the suite (an earlier suite's results.json in the same folder is gone
from the start), every job record left is a complete, error-free job, and the same command run again resumes from
those records and succeeds. Three IMU-only jobs on 2 s captures without images keep it short."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import ROOT
from tests.processes import VIO, sigkill, start_vio
from vio.bench import JOB_RECORD

SCENARIOS = ("orbit", "room", "figure8")
KEYS = [f"{s}_phone_s0_2s_noimg" for s in SCENARIOS]


def _suite(path: Path, name: str, scenarios: tuple[str, ...], seed: int) -> Path:
    path.write_text(
        f"name: {name}\nplots: false\nmethods: [{{name: imu_only, kind: imu_only}}]\n"
        f"cases:\n  - grid: {{scenario: [{', '.join(scenarios)}]}}\n"
        f"    seed: {seed}\n    imu: phone\n    duration_s: 2\n    images: false\n"
    )
    return path


def _bench_args(suite: Path, out: Path) -> list[str]:
    return ["bench", "--suite", str(suite), "--jobs", "1", "--out", str(out)]


def _start(suite: Path, out: Path) -> subprocess.Popen:
    # its own process group: Ctrl-C reaches the bench and its jobs' children
    return start_vio(*_bench_args(suite, out), stdout=subprocess.DEVNULL, start_new_session=True)


def _wait_line(proc: subprocess.Popen, text: str) -> None:
    """Read the bench's progress until a line with `text` (or its end)."""
    for line in proc.stderr:
        if text in line:
            return


def _done_jobs(out: Path) -> int:
    """Job records left in `out`, each checked to be a complete job: error-free rows, its estimate written, its
    capture complete. Captures are either complete or absent (a simulation goes to a hidden folder first)."""
    done = 0
    for key in KEYS:
        folder = out / "runs" / key / "imu_only"
        capture = out / "captures" / key / "mav0"
        if capture.parent.exists():
            assert (capture / "imu0" / "data.csv").is_file()
            assert (capture / "state_groundtruth_estimate0" / "data.csv").is_file()
        if (folder / JOB_RECORD).exists():
            rec = json.loads((folder / JOB_RECORD).read_text())
            assert rec["rows"] and not any("error" in r for r in rec["rows"])
            assert (folder / "trajectory.tum").stat().st_size > 0
            done += 1
    return done


def _assert_complete(out: Path, resumed: int) -> None:
    data = json.loads((out / "results.json").read_text())
    assert data["bench"]["suite"] == "three" and data["bench"]["resumed"] == resumed
    assert len(data["runs"]) == 3 and not any("error" in r for r in data["runs"])
    assert (out / "results.md").is_file()


@pytest.fixture
def earlier(tmp_path):
    """`out` holding a complete summary of another suite (one job), and that suite's wall time (s)."""
    out = tmp_path / "out"
    t0 = time.monotonic()
    proc = _start(_suite(tmp_path / "earlier.yaml", "earlier", ("orbit",), 1), out)
    assert proc.wait(timeout=600) == 0, proc.stderr.read()[-3000:]
    assert json.loads((out / "results.json").read_text())["bench"]["suite"] == "earlier"
    return out, time.monotonic() - t0


def test_sigkill_mid_suite_leaves_no_summary_and_the_rerun_resumes(tmp_path, earlier):
    out, job_s = earlier
    suite = _suite(tmp_path / "three.yaml", "three", SCENARIOS, 0)
    fractions = np.random.default_rng(20).uniform(0.0, 0.8, size=3).round(2).tolist()
    killed = 0
    for i, fraction in enumerate(fractions):  # each run resumes what the ones before finished
        proc = _start(suite, out)
        _wait_line(proc, "jobs (")  # started: the earlier summary is removed, the job records read
        if i:  # the first kill lands in the first job; the others in the job after one this run finished
            _wait_line(proc, "jobs done")
        time.sleep(fraction * job_s)
        was_killed, rc = sigkill(proc)
        killed += was_killed
        if was_killed:
            assert not (out / "results.json").exists() and not (out / "results.md").exists()
            _done_jobs(out)
        else:  # it finished before the kill landed: then it is complete
            assert rc == 0
            _assert_complete(out, json.loads((out / "results.json").read_text())["bench"]["resumed"])
    assert killed >= 2
    done = _done_jobs(out)
    again = subprocess.run([*VIO, *_bench_args(suite, out)], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert again.returncode == 0, again.stderr[-3000:]
    assert ("3/3 jobs done" in again.stderr) == (done < 3)  # a kill can land after the last job, before the summary
    assert (f"{done} done before, resumed" in again.stderr) == (done > 0)
    _assert_complete(out, done)


def test_ctrl_c_mid_job_says_what_was_kept_and_the_rerun_resumes(tmp_path, earlier):
    out, job_s = earlier
    suite = _suite(tmp_path / "three.yaml", "three", SCENARIOS, 0)
    delay_s = float(np.random.default_rng(21).uniform(0.1, 0.5)) * job_s
    proc = _start(suite, out)
    _wait_line(proc, "jobs done")  # the first job is done: Ctrl-C lands in the second
    time.sleep(delay_s)
    assert proc.poll() is None
    os.killpg(proc.pid, signal.SIGINT)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 130, stderr[-3000:]
    assert "Traceback" not in stderr
    done = _done_jobs(out)
    assert stderr.strip().splitlines()[-2:] == [
        f"bench three: stopped with {done}/3 jobs done; run it again to resume",
        "vio bench: interrupted",
    ]
    assert not (out / "results.json").exists()
    again = subprocess.run([*VIO, *_bench_args(suite, out)], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert again.returncode == 0, again.stderr[-3000:]
    assert (f"{done} done before, resumed" in again.stderr) == (done > 0)
    _assert_complete(out, done)
