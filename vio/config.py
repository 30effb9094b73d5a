"""Configuration: one YAML file, one frozen dataclass per section; unknown keys are errors.

Each stage gets its own section as an argument; there is no global parameter object. Command-line overrides
use `--set section.key=value` (the value is parsed as YAML, so `--set tracker.max_features=200` is an int).
"""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from vio.errors import ConfigError


@dataclass(frozen=True)
class TrackerConfig:
    max_features: int = 150  # target number of tracked features per frame
    grid_rows: int = 6  # bucketing grid for new detections
    grid_cols: int = 8
    min_distance_px: float = 12.0  # minimum distance between corners, px
    quality_level: float = 0.01  # Shi-Tomasi quality relative to the strongest corner
    klt_window: int = 21  # KLT window size, px
    klt_levels: int = 3  # pyramid levels above the base
    fb_threshold_px: float = 0.5  # forward-backward consistency threshold, px
    min_ncc: float = 0.95  # a track whose patch correlates less than this with the previous frame's is dropped
    ncc_radius_px: int = 5  # half-size of the patch compared by min_ncc, px
    ransac_threshold_px: float = 0.3  # essential-matrix inlier threshold, px at the focal length (method-specific)
    border_px: int = 8  # features closer than this to the border are dropped
    subpix_window: int = 3  # half-size of the cornerSubPix search window for new corners (0: off), px
    essential_method: str = "usac_magsac"  # usac_magsac | usac_accurate | usac_default | ransac | lmeds | none
    essential_min_flow_px: float = 1.0  # skip the essential-matrix check below this median flow, px
    essential_lag_frames: int = 5  # also check against the frame this many frames back (slow drift); 0/1: off


@dataclass(frozen=True)
class KeyframeConfig:
    min_parallax_px: float = 20.0  # median track displacement since the last keyframe that makes one, px (IMU-free: 12)
    min_survival: float = 0.7  # fraction of last keyframe's tracks still alive below which a keyframe is made
    max_interval_s: float = 0.2  # a keyframe at least this often, s
    min_interval_s: float = 0.05  # never closer than this, s


@dataclass(frozen=True)
class ImuConfig:
    max_gap_s: float = 0.05  # an IMU gap longer than this between samples is reported
    integration_sigma: float = 1e-4  # sigma of the position-integration error (gtsam cov = sigma^2), m/sqrt(s)
    bias_init_sigma_gyro: float = 0.01  # prior sigma on the initial gyro bias, rad/s
    bias_init_sigma_acc: float = 0.1  # prior sigma on the initial accelerometer bias, m/s^2
    noise_inflation: float = 1.0  # multiplies the capture's Kalibr noise densities and random walks


@dataclass(frozen=True)
class BackendConfig:
    pixel_sigma: float = 1.0  # projection noise, px
    huber_k: float = 1.345  # robust loss threshold, in sigmas
    min_views: int = 3  # a landmark needs this many views before it enters the graph
    min_parallax_deg: float = 2.0  # ... and this much ray parallax, deg
    max_reprojection_px: float = 3.0  # admission and re-check threshold, px
    landmark_prior_sigma_m: float = 5.0  # weak prior on each landmark at its triangulated position, m
    max_track_keyframes: int = 0  # a track becomes a new landmark after this many keyframe views (0: only on drift)
    relinearize_threshold: float = 0.01
    relinearize_skip: int = 10  # relinearize every 10th update (measured: 2x less CPU, same accuracy)
    factorization: str = "CHOLESKY"  # iSAM2: CHOLESKY (25% faster) | QR (survives long IMU-only stretches)
    smoother: str = "isam2"  # isam2 | fixed_lag
    lag_s: float = 3.0  # fixed-lag window when smoother == fixed_lag, s
    init_window_s: float = 1.0  # moving-start initialisation window, s
    static_init_max_gyro: float = 0.02  # std of 0.1 s gyro block means below which the start is static, rad/s
    static_init_max_acc_std: float = 0.15  # std of 0.1 s accelerometer block means for a static start, m/s^2
    still_max_px: float = 0.5  # zero-velocity update when tracks move less than this (median) and the IMU rests, px
    still_window_s: float = 0.5  # IMU window of the at-rest test of the zero-velocity update, s
    reid: bool = True  # re-identify new tracks with map landmarks by descriptor (backend/atlas.py); needs images
    reid_radius_px: float = 20.0  # search radius around a landmark's predicted projection, px
    reid_max_hamming: int = 50  # largest descriptor distance of a re-identification, bits of 256
    reid_ratio: float = 0.8  # best distance must be below this times the second best among the candidates
    reid_max_view_deg: float = 30.0  # compare with snapshots taken within this viewing-direction change, deg
    reid_refresh_keyframes: int = 10  # refresh the atlas' landmark positions from the smoother this often
    reid_defer_keyframes: int = 30  # a landmark unobserved this long is old: its re-observations are batched
    reid_max_age_keyframes: int = 0  # only landmarks observed within this many keyframes are candidates (0: all)
    reid_max_loops: int = 5  # old landmarks re-identified per flush period at most (bounds the solver's cost)
    reid_flush_keyframes: int = 10  # batched re-observations of old landmarks enter the smoother this often
    use_imu: bool = True  # false: projection factors only (backend/visual_only.py; scale unknown, Sim3 only)


@dataclass(frozen=True)
class RunConfig:
    refine: bool = False  # final full batch Levenberg-Marquardt refinement
    max_frames: int = 0  # stop after this many frames (0 = all)
    progress: bool = True  # progress bar on a terminal


@dataclass(frozen=True)
class Config:
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    imu: ImuConfig = field(default_factory=ImuConfig)
    backend: BackendConfig = field(default_factory=BackendConfig)
    run: RunConfig = field(default_factory=RunConfig)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def _coerce(section: str, key: str, kind: Any, value: Any) -> Any:
    """Check a value against the dataclass field type (ints and numeric strings may become floats)."""
    name = kind if isinstance(kind, str) else getattr(kind, "__name__", str(kind))
    if name == "float" and isinstance(value, str):  # YAML 1.1 reads `1e-3` as a string
        try:
            value = float(value)
        except ValueError:
            pass  # reported below as a type error
    ok = {
        "int": isinstance(value, int) and not isinstance(value, bool),
        "float": isinstance(value, (int, float)) and not isinstance(value, bool),
        "bool": isinstance(value, bool),
        "str": isinstance(value, str),
    }
    if name not in ok:
        return value
    if not ok[name]:
        raise ConfigError(f"config {section}.{key}: expected {name}, got {value!r}")
    return float(value) if name == "float" else value


def _build_section(section: str, cls: type, values: dict[str, Any]) -> Any:
    if not isinstance(values, dict):
        raise ConfigError(f"config section '{section}' must be a mapping, got {type(values).__name__}")
    hints = typing.get_type_hints(cls)
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise ConfigError(
            f"config section '{section}': unknown key(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}"
        )
    kwargs = {k: _coerce(section, k, hints[k], v) for k, v in values.items()}
    return cls(**kwargs)


def config_from_dict(data: dict[str, Any] | None) -> Config:
    """Build a Config from nested dicts, rejecting unknown sections and keys."""
    data = data or {}
    if not isinstance(data, dict):
        raise ConfigError("config must be a mapping of sections")
    sections = {f.name: typing.get_type_hints(Config)[f.name] for f in dataclasses.fields(Config)}
    unknown = sorted(set(data) - set(sections))
    if unknown:
        raise ConfigError(f"config: unknown section(s) {', '.join(unknown)}; known: {', '.join(sections)}")
    return Config(**{name: _build_section(name, cls, data.get(name, {})) for name, cls in sections.items()})


def parse_overrides(overrides: list[str] | None) -> dict[str, dict[str, Any]]:
    """Parse `section.key=value` strings into nested dicts (values parsed as YAML scalars)."""
    out: dict[str, dict[str, Any]] = {}
    for item in overrides or []:
        if "=" not in item or "." not in item.split("=", 1)[0]:
            raise ConfigError(f"--set expects section.key=value, got {item!r}")
        lhs, rhs = item.split("=", 1)
        section, key = lhs.strip().split(".", 1)
        try:
            value = yaml.safe_load(rhs) if rhs.strip() else ""
        except yaml.YAMLError as exc:
            raise ConfigError(f"--set {item!r}: value is not valid YAML ({exc.__class__.__name__})") from None
        out.setdefault(section, {})[key] = value
    return out


def load_config(path: str | Path | None = None, overrides: list[str] | None = None) -> Config:
    """Load a YAML config file (optional) and apply `section.key=value` overrides."""
    data: dict[str, Any] = {}
    if path is not None:
        p = Path(path)
        try:
            data = yaml.safe_load(p.read_text(encoding="utf-8")) or {}
        except FileNotFoundError:
            raise ConfigError(f"{p}: config file not found") from None
        except yaml.YAMLError as exc:
            mark = getattr(exc, "problem_mark", None)
            line = f":{mark.line + 1}" if mark is not None else ""
            raise ConfigError(f"{p}{line}: not valid YAML") from None
        if not isinstance(data, dict):
            raise ConfigError(f"{p}: config must be a mapping of sections")
    for section, values in parse_overrides(overrides).items():
        if not isinstance(data.get(section, {}), dict):
            raise ConfigError(f"config section '{section}' must be a mapping")
        data.setdefault(section, {}).update(values)
    return config_from_dict(data)
