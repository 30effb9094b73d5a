"""The camera's timing through `vio run` (issue 16): a global-shutter capture's run is unchanged by default, run.json
states the readout and the time offset, the readout comes from a MARS capture when asked, and the offset is
recovered on a short simulated phone capture (rolling shutter, blur, clock offset, 100 Hz jittery IMU)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from backend.time_offset import CameraTiming
from frontend.track_velocity import TrackVelocity
from vio import pipeline
from vio.capture import Capture
from vio.config import Config, load_config
from vio.pipeline import run_capture

QUIET = ["run.progress=false"]


def test_global_shutter_run_is_unchanged_by_default(sim_capture, tmp_path, monkeypatch):
    """The default run equals, number for number, a run with the camera-timing code taken out (no velocities,
    keyframes at the frame times, views as tracked)."""
    capture = sim_capture("orbit", 4.0)
    cfg = load_config(None, QUIET)
    assert cfg.camera.readout_s == 0.0 and cfg.camera.time_offset_s == 0.0 and not cfg.camera.estimate_time_offset
    run_capture(capture, tmp_path / "now", cfg)
    monkeypatch.setattr(TrackVelocity, "add", lambda self, tracks: tracks)
    monkeypatch.setattr(CameraTiming, "pose_time_ns", lambda self, t_ns: int(t_ns))
    monkeypatch.setattr(CameraTiming, "correct", lambda self, tracks, uv: uv)
    run_capture(capture, tmp_path / "without", cfg)
    for name in ("trajectory.tum", "states.csv", "landmarks.ply"):
        assert (tmp_path / "now" / name).read_bytes() == (tmp_path / "without" / name).read_bytes(), name
    timing = json.loads((tmp_path / "now" / "run.json").read_text())["camera_timing"]
    assert timing["readout_s"] == 0.0 and timing["time_offset_s"] == 0.0
    assert timing["time_offset_method"].startswith("fixed") and timing["time_offset_sigma_s"] is None


def _capture(fmt: str) -> Capture:
    return Capture(Path("somewhere"), None, None, None, np.zeros(0, np.int64), lambda i: np.zeros((1, 1)), format=fmt)


def test_readout_comes_from_the_config_or_a_mars_capture(monkeypatch):
    import vio.readers.mars as mars

    monkeypatch.setattr(mars, "readout_ns", lambda folder: 20_700_000)
    cfg = load_config(None, ["camera.readout_s=0.01"])
    assert pipeline._with_readout(_capture("mars"), cfg) == (cfg, "config")  # the config's own value wins
    auto = load_config(None, ["camera.readout_s=-1"])
    got, source = pipeline._with_readout(_capture("mars"), auto)
    assert got.camera.readout_s == pytest.approx(0.0207) and source.startswith("capture")
    got, source = pipeline._with_readout(_capture("asl"), auto)  # nothing recorded: global shutter
    assert got.camera.readout_s == 0.0 and source.startswith("none")
    monkeypatch.setattr(mars, "readout_ns", lambda folder: None)
    assert pipeline._with_readout(_capture("mars"), auto)[0].camera.readout_s == 0.0
    assert Config().camera.readout_s == 0.0  # default: global shutter, whatever the capture says


@pytest.fixture(scope="module")
def phone_capture(tmp_path_factory):
    """A 4 s phone orbit (seed 7): top row stamped 15 ms early, 20 ms readout."""
    from vio.sim.api import simulate
    from vio.sim.phone import simulate_options

    out = tmp_path_factory.mktemp("phone") / "orbit"
    return simulate("orbit", out, seed=7, duration_s=4.0, **simulate_options("phone"))


@pytest.mark.slow
def test_time_offset_is_recovered_on_a_short_phone_capture(phone_capture, tmp_path):
    truth = yaml.safe_load((phone_capture / "scene" / "scene.yaml").read_text())["camera"]
    sets = [*QUIET, f"camera.readout_s={truth['readout_s']}", "camera.estimate_time_offset=true"]
    summary = run_capture(phone_capture, tmp_path, load_config(None, sets)).summary
    timing = summary["camera_timing"]
    assert timing["readout_s"] == truth["readout_s"] and timing["time_offset_method"].startswith("estimated")
    assert abs(timing["time_offset_s"] - truth["timeshift_cam_imu_s"]) < 0.003  # 15 ms: within 3 ms after 4 s
    assert abs(timing["time_offset_after_initialisation_s"] - truth["timeshift_cam_imu_s"]) < 0.005
    assert timing["time_offset_sigma_s"] > 0 and timing["time_offset_keyframes"] > 10


@pytest.mark.slow
def test_the_start_re_run_goes_through_the_pipeline(phone_capture, tmp_path):
    """With the re-run's threshold loosened to what 4 s reach (3 ms standard error), the first keyframes are run
    again with the converged offset: with the tracker's tracks and the re-identification describers kept, every
    keyframe is in the outputs once, and run.json says what was re-run."""
    truth = yaml.safe_load((phone_capture / "scene" / "scene.yaml").read_text())["camera"]
    sets = [*QUIET, f"camera.readout_s={truth['readout_s']}", "camera.estimate_time_offset=true"]
    summary = run_capture(
        phone_capture, tmp_path, load_config(None, [*sets, "camera.time_offset_replay_sigma_s=0.003"])
    ).summary
    timing = summary["camera_timing"]
    assert timing["time_offset_replayed_keyframes"] > 10 and timing["time_offset_replayed_span_s"] > 1.0
    assert timing["time_offset_replayed_from_s"][0] == 0.0  # the start window was placed at the initial 0
    assert abs(timing["time_offset_s"] - truth["timeshift_cam_imu_s"]) < 0.003
    t = np.loadtxt(tmp_path / "trajectory.tum", ndmin=2)[:, 0]
    assert len(t) == summary["num_states"] == summary["num_keyframes"] and np.all(np.diff(t) > 0)
    frames = np.loadtxt(phone_capture / "mav0" / "cam0" / "data.csv", delimiter=",", usecols=0, dtype=np.int64)
    first_placed_s = t[0] - frames[0] * 1e-9 - 0.5 * truth["readout_s"]  # the first keyframe is the first frame
    assert abs(first_placed_s - truth["timeshift_cam_imu_s"]) < 0.005  # not at the initial 0 any more


def test_phone_preset_estimates_the_offset_with_the_capture_readout():
    cfg = load_config(None, [], presets=["phone"])
    assert cfg.camera.estimate_time_offset and cfg.camera.readout_s < 0


def test_a_readout_longer_than_the_frame_interval_is_one_line(sim_capture, tmp_path):
    from vio.errors import ConfigError

    capture = sim_capture("orbit", 4.0)
    with pytest.raises(ConfigError, match=r"camera.readout_s: 0.06 s is not shorter than the frame interval"):
        run_capture(capture, tmp_path, load_config(None, [*QUIET, "camera.readout_s=0.06"]))
    assert json.loads((tmp_path / "run.json").read_text())["status"] == "failed"
