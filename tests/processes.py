"""`vio` started as a user starts it, watched and stopped mid-way: the helpers the kill tests share
(tests/vio/test_kill.py, tests/vio/test_kill_model.py, tests/vio/bench/test_kill_bench.py)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

from tests.conftest import ROOT, default_sigint

VIO = [sys.executable, "-m", "vio.cli"]


def start_vio(*args: str, stdout: int = subprocess.PIPE, **popen) -> subprocess.Popen:
    """`vio ARGS...` in the background with SIGINT at its default (so Ctrl-C is a KeyboardInterrupt in it);
    stderr piped as text."""
    return subprocess.Popen(
        [*VIO, *args],
        cwd=ROOT,
        stdout=stdout,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=default_sigint,
        **popen,
    )


def run_status(run: Path) -> str | None:
    """The `status` a run folder's run.json says, None while there is no readable one."""
    try:
        return json.loads((run / "run.json").read_text())["status"]
    except (FileNotFoundError, json.JSONDecodeError, KeyError):
        return None


def wait_until(proc: subprocess.Popen, ready: Callable[[], bool], timeout_s: float = 300.0) -> None:
    """Poll `ready` every 20 ms while `proc` runs; fail if it ends first or the time runs out."""
    t0 = time.monotonic()
    while not ready():
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() - t0 < timeout_s
        time.sleep(0.02)


def sigkill(proc: subprocess.Popen) -> tuple[bool, int]:
    """SIGKILL `proc` unless it has already ended; (whether it was killed, its return code) once it is gone."""
    killed = proc.poll() is None
    if killed:
        os.kill(proc.pid, signal.SIGKILL)
    rc = proc.wait(timeout=60)
    proc.communicate()
    return killed and rc == -signal.SIGKILL, rc
