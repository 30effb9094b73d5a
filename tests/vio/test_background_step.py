"""The fixed lag's background step in the pipeline (`smoother.background`, issue 18): the pipeline runs it after
each keyframe's estimate has gone to the sinks, and run.json times it apart from the keyframes."""

from __future__ import annotations

import json

import backend.estimator as be
from vio.config import load_config
from vio.pipeline import run_capture


def test_the_pipeline_runs_the_background_step_after_each_keyframe(sim_capture, tmp_path, monkeypatch):
    cap = sim_capture("orbit", 4.0)
    order: list[str] = []
    real_step, real_background = be.VioEstimator._step, be.VioEstimator.background

    def step(self, *args):
        order.append("keyframe")
        return real_step(self, *args)

    def background(self):
        order.append("background")
        return real_background(self)

    monkeypatch.setattr(be.VioEstimator, "_step", step)
    monkeypatch.setattr(be.VioEstimator, "background", background)
    cfg = load_config(
        None,
        ["run.progress=false", "smoother.background=true", "smoother.hold_start_s=0", "smoother.relinearize_skip=2"],
        presets=["fixed_lag"],
    )
    res = run_capture(cap, tmp_path / "out", cfg)
    assert res.summary["status"] == "ok"
    run = json.loads((tmp_path / "out" / "run.json").read_text())
    steps = run["background_ms"]
    n = order.count("keyframe")
    assert n > 20 and steps["count"] >= n // 2  # a smoother step after every 2nd keyframe, at least
    assert steps["max"] >= steps["p95"] >= steps["median"] > 0 and steps["cpu_total_s"] > 0
    # the pipeline's own call comes right after each keyframe (the estimator's call at the next one is extra)
    after = [order[i + 1] for i, what in enumerate(order[:-1]) if what == "keyframe"]
    assert after == ["background"] * len(after)
