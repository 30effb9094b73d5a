"""The tracker's error by track age against the true surface point (vio.bench.klt_error)."""

from __future__ import annotations

import subprocess
import sys

from vio.bench.klt_error import by_age, track_errors
from vio.config import load_config
from vio.readers import open_capture


def test_frame_to_frame_error_grows_with_age_and_anchored_tracks_do_not_drift(sim_capture):
    """Seed 0's 3 s orbit, measured: frame-to-frame KLT 0.10 px median at ages 1-2, 0.67 px at 21-30, 0.95 px at
    31-50; anchored (the default) 0.11, 0.067 and 0.075 px (seed 401's first 400 frames: docs/BENCHMARKS.md)."""
    cap = open_capture(sim_capture("orbit", 3.0))
    plain = track_errors(cap, load_config(None, ["tracker.anchor=false"]))
    anchored = track_errors(cap, load_config())
    for errors in (plain, anchored):
        assert len(errors) > 5000
        assert errors[:, 0].min() >= 1
    plain_bins = {lo: med for lo, _, _, med, _, _ in by_age(plain)}
    bins = {lo: med for lo, _, _, med, _, _ in by_age(anchored)}
    assert plain_bins[1] < 0.5 and bins[1] < 0.5
    assert plain_bins[21] > 2.0 * plain_bins[1]  # KLT from frame to frame wanders off its point
    assert bins[21] < 1.5 * bins[1] and bins[31] < 0.5 * plain_bins[31]  # the template holds it


def test_command_line(sim_capture, tmp_path):
    cap = sim_capture("orbit", 3.0)
    res = subprocess.run([sys.executable, "-m", "vio.bench.klt_error", str(cap), "--frames", "20"],
                         capture_output=True, text=True, check=False)  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert res.stdout.splitlines()[1].startswith("1-2 |")
    key = subprocess.run([sys.executable, "-m", "vio.bench.klt_error", str(cap), "--frames", "20", "--keyframes"],
                         capture_output=True, text=True, check=False)  # fmt: skip
    assert key.returncode == 0, key.stderr

    def views(out: str) -> int:
        return sum(int(line.split("|")[1]) for line in out.splitlines()[1:])

    assert 0 < views(key.stdout) < 0.7 * views(res.stdout)  # only the keyframes' views (about 1 frame in 3)
    bad = subprocess.run([sys.executable, "-m", "vio.bench.klt_error", str(tmp_path)], capture_output=True, text=True,
                         check=False)  # fmt: skip
    assert bad.returncode == 2 and "Traceback" not in bad.stdout + bad.stderr
    assert len(bad.stdout.strip().splitlines()) == 1
