"""`vio model` killed mid-run (SIGKILL, SIGINT), as a user runs it: on a capture, making its run first into
OUT/run. model.json goes first and comes last, so a killed model leaves no folder that passes for a model and
nothing of the one before; the same command run again succeeds. The kills land at seeded random points of the
run and of the model steps (an 8 s orbit with 16 stills; a coarse voxel and no bundle adjustment keep it short)."""

from __future__ import annotations

import json
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from tests.processes import run_status as _status
from tests.processes import sigkill, start_vio
from tests.processes import wait_until as _wait

MODEL_FILES = ("model.json", "part.stl", "part.ply", "dense.ply")
RUN_FILES = ("trajectory.tum", "states.csv", "landmarks.ply")
OPTIONS = ("--voxel-mm", "2", "--no-adjust")


def _start(capture: Path, out: Path, *extra: str) -> subprocess.Popen:
    return start_vio("model", str(capture), "--out", str(out), *OPTIONS, *extra)


def _assert_no_model(out: Path, earlier_mtime_ns: dict[str, int]) -> None:
    """Nothing in `out` passes for a model, and nothing of the earlier model is left; OUT/run is a complete run
    or shows none of a run's files."""
    assert not (out / "model.json").exists()
    for name in MODEL_FILES[1:]:
        if (out / name).exists():  # written by the killed command, never the earlier model's
            assert (out / name).stat().st_mtime_ns > earlier_mtime_ns[name]
    run = out / "run"
    if _status(run) in ("ok", "degraded"):
        assert all((run / name).exists() for name in RUN_FILES)
    else:
        assert not any((run / name).exists() for name in RUN_FILES)


def _assert_model(out: Path) -> None:
    assert json.loads((out / "model.json").read_text())["mesh"]["watertight"]
    assert all((out / name).stat().st_size > 0 for name in MODEL_FILES)
    assert _status(out / "run") == "ok"


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    from vio.sim.api import simulate

    out = tmp_path_factory.mktemp("kill_model") / "orbit_8s"
    return simulate("orbit", out, seed=0, duration_s=8.0, stills_hz=2.0, stills_size=(1008, 756))


def _phases(proc: subprocess.Popen, run: Path) -> tuple[float, float]:
    """Wait for a `vio model` that makes its run: (seconds from its run.json saying running to ok, then to exit)."""
    _wait(proc, lambda: _status(run) == "running")
    t0 = time.monotonic()
    _wait(proc, lambda: _status(run) == "ok")
    t1 = time.monotonic()
    assert proc.wait(timeout=900) == 0, proc.stderr.read()[-3000:]
    return t1 - t0, time.monotonic() - t1


@pytest.mark.slow  # an 8 s capture with stills, then six runs of run + model: a few minutes on the busy 2 cores
def test_sigkill_mid_model_leaves_nothing_that_looks_complete_and_a_rerun_succeeds(capture, tmp_path):
    out = tmp_path / "out"
    run = out / "run"
    run_s, model_s = _phases(_start(capture, out), run)
    _assert_model(out)  # a complete earlier model in the same folder: it must not survive a killed rerun
    earlier = {name: (out / name).stat().st_mtime_ns for name in MODEL_FILES}
    fractions = np.random.default_rng(20).uniform(0.05, 0.9, size=4).round(2).tolist()
    killed = 0
    for phase, fraction in zip(("run", "run", "model", "model"), fractions, strict=True):
        proc = _start(capture, out)
        _wait(proc, lambda: _status(run) == "running")  # its run has started (or a killed one's still says so)
        if phase == "model":
            _wait(proc, lambda: _status(run) == "ok")  # its run is done: the model steps go on
        time.sleep(fraction * (run_s if phase == "run" else model_s))
        was_killed, rc = sigkill(proc)
        killed += was_killed
        if was_killed:
            _assert_no_model(out, earlier)
        else:  # it finished before the kill landed: then it is complete
            assert rc == 0
            _assert_model(out)
            earlier = {name: (out / name).stat().st_mtime_ns for name in MODEL_FILES}
    assert killed >= 2
    (out / ".dense.ply.killed.tmp").write_bytes(b"half a point cloud")  # what a kill during a write leaves
    again = _start(capture, out)
    assert again.wait(timeout=900) == 0, again.stderr.read()[-3000:]
    _assert_model(out)
    assert not list(out.glob(".*.tmp"))


@pytest.mark.slow
def test_sigint_says_what_was_kept_and_the_run_it_kept_is_reused(capture, tmp_path):
    out = tmp_path / "out"
    run = out / "run"
    rng = np.random.default_rng(21)
    delay_run_s, delay_model_s = float(rng.uniform(0.2, 1.0)), float(rng.uniform(0.0, 0.2))  # steps of seconds
    # during the run: neither a model nor a run is kept
    proc = _start(capture, out)
    _wait(proc, lambda: _status(run) == "running")
    time.sleep(delay_run_s)
    proc.send_signal(signal.SIGINT)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 130, stderr[-2000:]
    assert "Traceback" not in stderr
    assert stderr.strip().splitlines()[-1] == (
        f"vio model: interrupted; no model kept ({out} has no model.json); no run kept either "
        f"({run}/run.json says interrupted)"
    )
    assert not any((out / name).exists() for name in MODEL_FILES)
    assert not any((run / name).exists() for name in RUN_FILES)
    # during the model steps: the finished run is kept, and the command the message names reuses it
    proc = _start(capture, out)
    _wait(proc, lambda: _status(run) == "ok")
    time.sleep(delay_model_s)
    proc.send_signal(signal.SIGINT)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 130, stderr[-2000:]
    assert "Traceback" not in stderr
    assert stderr.strip().splitlines()[-1] == (
        f"vio model: interrupted; no model kept ({out} has no model.json); kept: the run in {run} (ok), which "
        f"--run {run} reuses"
    )
    assert not any((out / name).exists() for name in MODEL_FILES)  # files of the model being written are removed
    stamp = (run / "trajectory.tum").stat().st_mtime_ns
    again = _start(capture, out, "--run", str(run))
    assert again.wait(timeout=900) == 0, again.stderr.read()[-3000:]
    _assert_model(out)
    assert (run / "trajectory.tum").stat().st_mtime_ns == stamp  # the kept run, not a new one
