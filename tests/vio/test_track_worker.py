"""The tracker in a process of its own (vio.track_worker): the same results as in the estimator's process, and the
worker really runs (issue 18)."""

from __future__ import annotations

import vio.track_worker as tw
from vio.config import load_config
from vio.pipeline import run_capture


def test_worker_gives_the_single_process_results(sim_capture, tmp_path, monkeypatch):
    cap = sim_capture("orbit", 4.0)
    calls = []
    real = tw.tracked_in_worker

    def spy(*args, **kwargs):
        calls.append(args)
        yield from real(*args, **kwargs)

    monkeypatch.setattr(tw, "tracked_in_worker", spy)
    outs = {}
    for on in (True, False):
        out = tmp_path / str(on)
        res = run_capture(cap, out, load_config(None, ["run.progress=false", f"run.tracker_process={str(on).lower()}"]))
        assert res.summary["status"] == "ok"
        outs[on] = out
    assert len(calls) == 1  # the worker ran once (tracker_process=true), not for the false run
    for name in ("trajectory.tum", "landmarks.ply", "states.csv"):
        assert (outs[True] / name).read_bytes() == (outs[False] / name).read_bytes(), name


def test_a_worker_that_cannot_open_the_capture_is_one_error(tmp_path):
    from vio.config import load_config as lc
    from vio.errors import VioError

    items = tw.tracked_in_worker((str(tmp_path / "missing"), None, {}), lc(), 10, False)
    try:
        next(items)
    except VioError as exc:
        assert "missing" in str(exc) and "\n" not in str(exc)
    else:  # pragma: no cover - the assertion below names the failure
        raise AssertionError("no error from a missing capture")


def test_the_worker_runs_nicer_than_the_estimator(sim_capture, monkeypatch):
    import os
    from pathlib import Path

    import pytest

    from vio.readers import open_capture

    if not Path("/proc/self/stat").exists():
        pytest.skip("needs Linux /proc to read a process's nice value")
    procs = []
    real_popen = tw.subprocess.Popen

    def popen(*args, **kwargs):
        procs.append(real_popen(*args, **kwargs))
        return procs[-1]

    cap = open_capture(sim_capture("orbit", 2.0))
    monkeypatch.setattr(tw.subprocess, "Popen", popen)
    cfg = load_config(None, ["run.tracker_nice=7"])
    items = tw.tracked_in_worker(cap.reopen, cfg, 5, False)
    kind, _ = next(items)  # the worker has read its config (and set its priority) before the first frame
    assert len(procs) == 1
    nice = int(Path(f"/proc/{procs[0].pid}/stat").read_text().rsplit(")", 1)[1].split()[16])
    items.close()
    assert kind == "frame" and nice == os.nice(0) + 7
