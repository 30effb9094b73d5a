from __future__ import annotations

import subprocess
import sys

import pytest

from vio.config import Config, load_config, parse_overrides, preset_names
from vio.errors import ConfigError


def test_defaults_and_overrides(tmp_path):
    cfg = load_config(None, ["tracker.max_features=200", "smoother.kind=fixed_lag", "smoother.lag_s=2"])
    assert cfg.tracker.max_features == 200
    assert cfg.smoother.kind == "fixed_lag"
    assert cfg.smoother.lag_s == 2.0 and isinstance(cfg.smoother.lag_s, float)
    assert load_config(None, ["imu.integration_sigma=1e-3"]).imu.integration_sigma == 0.001
    assert Config().tracker.max_features == 150


def test_yaml_file_and_override_precedence(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("tracker:\n  max_features: 90\nrun:\n  refine: true\n")
    cfg = load_config(p, ["tracker.max_features=120"])
    assert cfg.tracker.max_features == 120 and cfg.run.refine is True


@pytest.mark.parametrize(
    "overrides",
    [
        ["tracker.nope=1"],
        ["nosection.x=1"],
        ["tracker.max_features=abc"],
        ["tracker.max_features=1.5"],
        ["estimator.mode=stereo"],
        ["smoother.kind=ekf"],
        ["bad"],
    ],
)
def test_bad_overrides_are_config_errors(overrides):
    with pytest.raises(ConfigError):
        load_config(None, overrides)


def test_bad_yaml_names_file_and_line(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("tracker:\n  max_features: [1,\n")
    with pytest.raises(ConfigError, match="c.yaml"):
        load_config(p)


def test_parse_overrides_types():
    assert parse_overrides(["a.b=true", "a.c=0.5", "d.e=text"]) == {
        "a": {"b": True, "c": 0.5},
        "d": {"e": "text"},
    }


@pytest.mark.parametrize(
    ("old", "new"),
    [
        ("backend.smoother=fixed_lag", "smoother.kind"),
        ("backend.use_imu=false", "estimator.mode"),
        ("backend.reid_radius_px=10", "reidentification.radius_px"),
        ("backend.still_max_px=1", "zero_velocity.max_flow_px"),
        ("imu.bias_init_sigma_acc=0.2", "initialisation.bias_sigma_acc"),
    ],
)
def test_a_key_of_the_former_backend_section_names_its_new_place(old, new):
    with pytest.raises(ConfigError, match=new.replace(".", r"\.")):
        load_config(None, [old])


def test_presets_apply_in_order_before_file_and_overrides(tmp_path):
    assert "vision_only" in preset_names() and "fixed_lag" in preset_names()
    cfg = load_config(None, [], presets=["vision_only"])
    assert cfg.estimator.mode == "vision_only" and not cfg.estimator.use_imu
    assert cfg.keyframes.min_parallax_px == 12.0
    p = tmp_path / "c.yaml"
    p.write_text("keyframes:\n  min_parallax_px: 15\n")
    cfg = load_config(p, ["smoother.lag_s=5"], presets=["vision_only", "fixed_lag"])
    assert cfg.keyframes.min_parallax_px == 15.0  # the file wins over the preset
    assert cfg.smoother.kind == "fixed_lag" and cfg.smoother.lag_s == 5.0  # the override wins over both
    with pytest.raises(ConfigError, match="unknown preset 'nope'; known: fixed_lag, phone, vision_only"):
        load_config(None, [], presets=["nope"])


def test_cli_names_an_unknown_preset_and_a_moved_key_in_one_line(tmp_path):
    for extra, msg in ((["--preset", "nope"], "unknown preset 'nope'"), (["--set", "backend.reid=false"], "is now")):
        cmd = [sys.executable, "-m", "vio.cli", "run", str(tmp_path), "--out", str(tmp_path / "o"), *extra]
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
        assert res.returncode == 2 and msg in res.stderr and "Traceback" not in res.stderr
        assert len(res.stderr.strip().splitlines()) == 1


def test_a_held_start_that_would_never_end_is_refused():
    """The held start leaves at `hold_release_rate` seconds of capture a second: at 1 or less it never catches up
    with the lag and the window would grow with the capture."""
    assert load_config(None, ["smoother.hold_release_rate=1.5"]).smoother.hold_release_rate == 1.5
    with pytest.raises(ConfigError, match="hold_release_rate: must be above 1"):
        load_config(None, ["smoother.hold_release_rate=1.0"], presets=["fixed_lag"])
