from __future__ import annotations

import pytest

from vio.config import Config, load_config, parse_overrides
from vio.errors import ConfigError


def test_defaults_and_overrides(tmp_path):
    cfg = load_config(None, ["tracker.max_features=200", "backend.smoother=fixed_lag", "backend.lag_s=2"])
    assert cfg.tracker.max_features == 200
    assert cfg.backend.smoother == "fixed_lag"
    assert cfg.backend.lag_s == 2.0 and isinstance(cfg.backend.lag_s, float)
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
