"""`vio run` killed mid-run (SIGKILL, SIGINT): no output left looking complete, and the same command run again
succeeds. The kill lands at seeded random points after the run has started (its run.json says `running`)."""

from __future__ import annotations

import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from tests.processes import run_status as _status
from tests.processes import sigkill, start_vio, wait_until

ESTIMATE_FILES = ("trajectory.tum", "states.csv", "landmarks.ply")


def _start(capture: Path, out: Path) -> subprocess.Popen:
    return start_vio("run", str(capture), "--out", str(out), "--set", "run.progress=false")


def _wait_running(proc: subprocess.Popen, out: Path) -> None:
    wait_until(proc, lambda: _status(out) == "running", timeout_s=120.0)


def _assert_not_complete(out: Path) -> None:
    """Nothing in `out` passes for a finished run: run.json does not say ok/degraded and no estimate is there."""
    assert _status(out) not in ("ok", "degraded")
    assert not any((out / name).exists() for name in ESTIMATE_FILES)


@pytest.fixture(scope="module")
def capture(sim_capture):
    return sim_capture("orbit", 4.0)


@pytest.fixture(scope="module")
def delays_s():
    """Seeded random kill points within the run (it lasts a few seconds after run.json says running)."""
    return np.random.default_rng(20).uniform(0.0, 2.5, size=3).round(2).tolist()


def test_sigkill_mid_run_leaves_nothing_that_looks_complete_and_a_rerun_succeeds(capture, tmp_path, delays_s):
    out = tmp_path / "out"
    first = _start(capture, out)
    assert first.wait(timeout=300) == 0, first.stderr.read()
    assert _status(out) == "ok"  # a complete earlier run in the same folder: it must not survive a killed rerun
    killed = 0
    for delay in delays_s:
        proc = _start(capture, out)
        _wait_running(proc, out)
        time.sleep(delay)
        was_killed, rc = sigkill(proc)
        killed += was_killed
        if was_killed:
            _assert_not_complete(out)
        else:  # it finished before the kill landed: then it is complete
            assert rc == 0 and _status(out) == "ok"
    assert killed >= 2
    again = _start(capture, out)
    assert again.wait(timeout=300) == 0, again.stderr.read()
    assert _status(out) == "ok" and all((out / name).exists() for name in ESTIMATE_FILES)
    assert not list(out.glob(".*.tmp"))  # temporaries a killed run left are cleaned


def test_sigint_ends_with_a_short_message_and_says_what_was_kept(capture, tmp_path, delays_s):
    out = tmp_path / "out"
    proc = _start(capture, out)
    _wait_running(proc, out)
    time.sleep(min(delays_s))
    proc.send_signal(signal.SIGINT)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 130, stderr[-2000:]
    assert "Traceback" not in stderr
    assert stderr.strip().splitlines()[-1] == f"vio run: interrupted; nothing kept ({out}/run.json says interrupted)"
    assert _status(out) == "interrupted"
    _assert_not_complete(out)
    again = _start(capture, out)
    assert again.wait(timeout=300) == 0 and _status(out) == "ok"
