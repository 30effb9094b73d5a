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

PRESETS_DIR = Path(__file__).parent / "presets"  # named presets, one YAML each (`vio run --preset NAME`)


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
    # each track re-aligned with the patch it began with (affine + gain/bias; frontend/anchor.py): no
    # drift with age (docs/BENCHMARKS.md, "Anchored tracks"); false: frame-to-frame KLT only
    anchor: bool = True
    anchor_radius_px: int = 7  # half-size of the template, px
    anchor_iterations: int = 4  # Gauss-Newton iterations per alignment at most (2 and 8 gave the same error by age)
    anchor_max_shift_px: float = 2.0  # an alignment further than this from KLT's pixel fails, px
    anchor_min_ncc: float = 0.9  # an alignment correlating less than this with the template fails
    anchor_max_stretch: float = 1.5  # an affine that stretches or shrinks the template more than this fails
    # align only the keyframes' views (the tracker then picks the keyframes, on KLT's pixels): between keyframes,
    # which the estimator does not read, frame-to-frame KLT only; its few frames of drift are undone at the next one
    anchor_keyframes_only: bool = False


@dataclass(frozen=True)
class KeyframeConfig:
    min_parallax_px: float = 20.0  # median track displacement since the last keyframe that makes one, px (IMU-free: 12)
    min_survival: float = 0.7  # fraction of last keyframe's tracks still alive below which a keyframe is made
    max_interval_s: float = 0.2  # a keyframe at least this often, s
    min_interval_s: float = 0.05  # never closer than this, s


@dataclass(frozen=True)
class CameraConfig:
    """The camera's timing (issue 16; backend/time_offset.py): rolling shutter and the camera-IMU time offset."""

    readout_s: float = 0.0  # rolling-shutter readout, top to bottom row, s (0: global shutter; < 0: the capture's own)
    time_offset_s: float = 0.0  # t_imu = t_cam + offset (top row), on top of a calibration's timeshift_cam_imu, s
    estimate_time_offset: bool = False  # estimate the offset from the start window, then online
    time_offset_window: int = 0  # keyframe pairs in the online estimate, the latest (0: every pair since the start)
    time_offset_lag: int = 1  # a pair: a keyframe and the one this many keyframes before it
    time_offset_settle: int = 10  # a pair is read this many keyframes after its later keyframe entered the graph
    # with the offset estimated: the keyframes of the first this many seconds are re-run once the estimate has
    # converged (backend/offset_replay.py), s (0: never)
    time_offset_replay_s: float = 20.0
    time_offset_replay_sigma_s: float = 0.002  # ... once the online estimate's standard error is at most this, s


@dataclass(frozen=True)
class ImuConfig:
    max_gap_s: float = 0.05  # an IMU gap longer than this between samples is reported
    integration_sigma: float = 1e-4  # sigma of the position-integration error (gtsam cov = sigma^2), m/sqrt(s)
    noise_inflation: float = 1.0  # multiplies the capture's Kalibr noise densities and random walks
    # the accelerometer's scale factors and axis angles from `vio calibrate imu-axes` (its YAML), applied to every
    # sample; "": none (vio/calibrate/imu_axes.py)
    axes: str = ""


@dataclass(frozen=True)
class EstimatorConfig:
    mode: str = "visual_inertial"  # visual_inertial | vision_only (projection factors only; scale unknown, Sim3 only)
    # projection noise, px (of a view at the start of its track's run; see pixel_sigma_per_s); 0.5 since the tracker's
    # anchored tracks (about 0.1 px median error up to 80 frames old); with frame-to-frame KLT 1 px was the default
    pixel_sigma: float = 0.5
    # growth of the projection noise with the view's age (time since its track's run of keyframe views began), px/s;
    # 0: every view has pixel_sigma (backend/factors.py PixelNoise)
    pixel_sigma_per_s: float = 0.0
    huber_k: float = 1.345  # robust loss threshold, in sigmas
    scale_uncertainty: bool = True  # at the end, the scale's standard deviation from the graph's marginals

    @property
    def use_imu(self) -> bool:
        return self.mode != "vision_only"


@dataclass(frozen=True)
class SmootherConfig:
    kind: str = "isam2"  # isam2 | fixed_lag
    lag_s: float = 3.0  # fixed-lag window when kind == fixed_lag, s
    map_sigma_m: float = 0.01  # fixed lag: prior on an old landmark that is seen again, at its kept position, m
    marginalise_every_s: float = 0.0  # fixed lag: variables leave in blocks of this length, s (0: at every update)
    # iSAM2 relinearisation threshold (tangent-space norm, every variable kind). 0.01 left the estimate off the
    # graph's optimum by a scale of about 1 % on 60 s orbits (poses move a few mm as the scale settles: never
    # relinearised); 0.001 reaches the batch optimum at the same CPU (docs/BENCHMARKS.md, issue 15)
    relinearize_threshold: float = 0.001
    relinearize_skip: int = 10  # relinearize every 10th update (measured: 2x less CPU, same accuracy)
    factorization: str = "CHOLESKY"  # iSAM2: CHOLESKY (25% faster) | QR (survives long IMU-only stretches)
    # every factor kept to the end (--refine, the scale's sigma); false, fixed lag only: the sigma chunk by chunk as
    # the run goes and each finished chunk's factors let go, so memory stays bounded (backend/scale_chunks.py);
    # --refine keeps them anyway
    keep_factors: bool = True
    # fixed lag only: a keyframe's update adds its factors and solves, nothing more; the relinearisation (every
    # relinearize_skip keyframes) and the marginalisation of what left the lag wait for a background step that the
    # pipeline runs once the keyframe's estimate is out (`Smoother.background`), so neither delays a keyframe
    background: bool = False
    # with background: the variables that left the lag are marginalised in the background step too (their
    # timestamps held back until then); false: in the keyframe's update, as without background
    background_marginalises: bool = True
    # with background_marginalises: the fixed lag runs on gtsam's ISAM2 itself, not its IncrementalFixedLagSmoother.
    # The keyframes' updates never relinearise; the background step relinearises (forced) and marginalises in one
    # update whose order it gives: what leaves first, the newest keyframe's variables last (no priors needed)
    own_marginalisation: bool = False
    # fixed lag only: nothing is marginalised in the capture's first hold_start_s seconds (the window holds every
    # variable while the scale, gravity and biases settle), then the held start leaves at hold_release_rate seconds of
    # capture per second until the window is lag_s again (0: no hold; a large rate, as the preset's 1000, releases it
    # at once, one block after hold_start_s). Measured in docs/BENCHMARKS.md ("The fixed lag's start", "The
    # background step on plain iSAM2")
    hold_start_s: float = 0.0
    hold_release_rate: float = 2.0


@dataclass(frozen=True)
class LandmarkConfig:
    min_views: int = 3  # a landmark needs this many views before it enters the graph
    min_parallax_deg: float = 2.0  # ... and this much ray parallax, deg
    max_reprojection_px: float = 3.0  # admission and re-check threshold, px
    prior_sigma_m: float = 5.0  # weak prior on each landmark at its triangulated position, m
    max_track_keyframes: int = 0  # a track becomes a new landmark after this many keyframe views (0: only on drift)


@dataclass(frozen=True)
class BlindAdmissionConfig:
    """Admission over bundle-adjusted poses while keyframes have no visual constraint (backend/blind_admission.py)."""

    window_keyframes: int = 30  # at most this many recent keyframes are adjusted (0: off)
    after_keyframes: int = 1  # run once this many keyframes in a row have no projection factor
    before_keyframes: int = 3  # constrained keyframes before the blind stretch included in the window
    min_tracks: int = 8  # fewer candidate tracks than this: no adjustment
    min_parallax_deg: float = 1.0  # a candidate's ray parallax over the window, deg (the shaking's is small)
    max_tracks: int = 150  # candidate tracks in one adjustment, at most
    max_iterations: int = 20  # Levenberg-Marquardt iterations
    prior_sigma_rad: float = 1e-3  # prior on the window's first pose (the gauge), rad
    prior_sigma_m: float = 1e-3  # ... m
    prior_velocity_sigma: float = 0.05  # prior on the window's first velocity, m/s
    prior_bias_sigma_acc: float = 0.05  # prior on the window's first accelerometer bias, m/s^2
    prior_bias_sigma_gyro: float = 0.005  # ... gyro bias, rad/s


@dataclass(frozen=True)
class InitialisationConfig:
    window_s: float = 1.0  # first window buffered before the start, s
    static_max_gyro: float = 0.02  # std of 0.1 s gyro block means below which the start is static, rad/s
    static_max_acc_std: float = 0.15  # std of 0.1 s accelerometer block means for a static start, m/s^2
    bias_sigma_gyro: float = 0.01  # prior sigma on the initial gyro bias, rad/s
    bias_sigma_acc: float = 0.1  # prior sigma on the initial accelerometer bias, m/s^2
    tilt_sigma_rad: float = 0.1  # prior on the first pose's roll and pitch (gravity observes them), rad
    gauge_sigma_rad: float = 1e-3  # prior on the first pose's yaw (the unobservable gauge), rad
    gauge_sigma_m: float = 1e-3  # prior on the first pose's position (the unobservable gauge), m
    velocity_sigma_static: float = 0.01  # prior on the first velocity (zero) of a static start, m/s
    velocity_sigma_moving: float = 0.5  # prior on the first velocity of a moving start's closed-form guess, m/s
    # bearing noise the moving start's linear alignment assumes, px: its rows are linearised (depths unknown), so
    # their error is that of the linearisation, not the tracker's (`estimator.pixel_sigma`, the graph's pixel noise)
    alignment_pixel_sigma: float = 1.0
    # moving start: the gyro bias from the images' own rotations before the closed-form alignment (VINS-Mono's
    # step; backend/initialisation/gyro_bias.py); an estimate larger than gyro_bias_max_rad_s is not believed, nor
    # one that leaves the images' rotations more than gyro_bias_max_rms_deg (rms) from the gyro's: a constant bias
    # does not explain them, the images are at fault (an orbit's look-at motion confounds rotation and translation
    # in the essential matrix: on the 60 s orbit, seeds 101, 102, 105 read 0.03-0.05 rad/s too large about x with
    # 1.2-1.9 deg left, and seed 102's run then lost its landmarks; a true 0.077 rad/s bias leaves 0.46 deg)
    gyro_bias_from_images: bool = True
    gyro_bias_max_rad_s: float = 0.3
    gyro_bias_max_rms_deg: float = 0.75


@dataclass(frozen=True)
class ZeroVelocityConfig:
    max_flow_px: float = 0.5  # at rest when tracks move less than this (median) and the IMU rests (0: off), px
    window_s: float = 0.5  # IMU window of the at-rest test, s
    max_gyro_std: float = 0.02  # at-rest test: std of 0.1 s gyro block means, rad/s
    max_acc_std: float = 0.15  # at-rest test: std of 0.1 s accelerometer block means, m/s^2
    sigma_rad: float = 1e-3  # no-rotation factor between the two keyframes at rest, rad
    sigma_m: float = 1e-3  # no-translation factor between the two keyframes at rest, m
    velocity_sigma: float = 0.01  # zero-velocity prior, m/s


@dataclass(frozen=True)
class ReidentificationConfig:
    enabled: bool = True  # re-identify new tracks with map landmarks by descriptor (backend/atlas.py); needs images
    radius_px: float = 20.0  # search radius around a landmark's predicted projection, px
    max_hamming: int = 50  # largest descriptor distance of a re-identification, bits of 256
    ratio: float = 0.8  # best distance must be below this times the second best among the candidates
    max_view_deg: float = 30.0  # compare with snapshots taken within this viewing-direction change, deg
    refresh_keyframes: int = 10  # refresh the atlas' landmark positions from the smoother this often
    defer_keyframes: int = 30  # a landmark unobserved this long is old: its re-observations are batched
    max_age_keyframes: int = 0  # only landmarks observed within this many keyframes are candidates (0: all)
    max_loops: int = 5  # old landmarks re-identified per flush period at most (bounds the solver's cost)
    flush_keyframes: int = 10  # batched re-observations of old landmarks enter the smoother this often
    # fixed lag: a landmark that leaves the window within this of an older retired one leaves the atlas (it stays in
    # the map): the atlas of a long capture of one scene stops growing (0: off; backend/reidentification.py)
    merge_radius_m: float = 0.0
    # with merge_radius_m: such a duplicate also leaves the live bookkeeping (its counts and track; its value stays, and
    # it stays in the run's landmarks.ply: GraphState.archive), so the map costs little more than its values
    archive_merged: bool = True
    # with merge_radius_m: the duplicate's snapshots from new viewpoints go to the older landmark it duplicates
    merge_snapshots: bool = False


@dataclass(frozen=True)
class RecoveryConfig:
    pose_sigma: float = 1e-3  # prior on the restart pose, rad (rotation) and m (position)
    velocity_sigma: float = 0.05  # prior on the restart velocity, m/s
    bias_sigma_acc: float = 0.02  # prior on the restart accelerometer bias, m/s^2
    bias_sigma_gyro: float = 1e-3  # prior on the restart gyro bias, rad/s


@dataclass(frozen=True)
class VisionOnlyConfig:
    start_pose_sigma: float = 1e-4  # prior on the first pose (the gauge), rad and scale units
    baseline_sigma: float = 1e-3  # prior on the second start pose's position (fixes the scale: baseline 1), units
    motion_sigma_rad: float = 0.2  # constant-velocity prior between keyframes, rotation, rad
    motion_sigma_units: float = 1.0  # constant-velocity prior between keyframes, translation, scale units


@dataclass(frozen=True)
class RunConfig:
    refine: bool = False  # final full batch Levenberg-Marquardt refinement
    max_frames: int = 0  # stop after this many frames (0 = all)
    progress: bool = True  # progress bar on a terminal
    # the tracker in a process of its own, beside the estimator (vio/track_worker.py); the same results
    tracker_process: bool = True
    # the tracker's process this much nicer than the estimator's (os.nice; 0: the same priority): the estimator
    # gets a core when it has a keyframe to solve, the tracker the rest; the same results, bit for bit. 10 took the
    # fixed lag's keyframe latency p95 from 73-91 to 40-55 ms on the 10-minute orbit (docs/BENCHMARKS.md)
    tracker_nice: int = 10


@dataclass(frozen=True)
class HealthConfig:
    min_tracked_features: int = (
        10  # fewer tracked features in a frame: thin tracking (none: lost); gtsam eqvio has 12-40
    )
    min_span_s: float = 0.2  # thin or lost tracking shorter than this is not reported, s
    min_keyframe_projections: int = 1  # a keyframe with fewer projection factors ran on the IMU alone
    max_skipped_frames: float = 0.1  # fraction of the frames that may fail to decode before the run fails


@dataclass(frozen=True)
class Config:
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    imu: ImuConfig = field(default_factory=ImuConfig)
    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)
    smoother: SmootherConfig = field(default_factory=SmootherConfig)
    landmarks: LandmarkConfig = field(default_factory=LandmarkConfig)
    blind_admission: BlindAdmissionConfig = field(default_factory=BlindAdmissionConfig)
    initialisation: InitialisationConfig = field(default_factory=InitialisationConfig)
    zero_velocity: ZeroVelocityConfig = field(default_factory=ZeroVelocityConfig)
    reidentification: ReidentificationConfig = field(default_factory=ReidentificationConfig)
    recovery: RecoveryConfig = field(default_factory=RecoveryConfig)
    vision_only: VisionOnlyConfig = field(default_factory=VisionOnlyConfig)
    run: RunConfig = field(default_factory=RunConfig)
    health: HealthConfig = field(default_factory=HealthConfig)

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
    for key, value in kwargs.items():
        allowed = _CHOICES.get(f"{section}.{key}")
        if allowed is not None and value not in allowed:
            raise ConfigError(f"config {section}.{key}: {value!r} is not one of {', '.join(allowed)}")
        above = _ABOVE.get(f"{section}.{key}")
        if above is not None and not value > above[0]:
            raise ConfigError(f"config {section}.{key}: must be above {above[0]:g} ({above[1]}), got {value!r}")
    return cls(**kwargs)


_ABOVE = {  # keys whose value must exceed a bound, and why
    "smoother.hold_release_rate": (1.0, "the held start must leave faster than the capture goes on, or it never ends"),
}

_CHOICES = {  # keys whose value is one of a few names
    "estimator.mode": ("visual_inertial", "vision_only"),
    "smoother.kind": ("isam2", "fixed_lag"),
    "smoother.factorization": ("CHOLESKY", "QR"),
}


# Keys of the former single `backend` section, now in the section of the estimator part that uses them.
_MOVED = {
    "use_imu": "estimator.mode (visual_inertial | vision_only)",
    "pixel_sigma": "estimator.pixel_sigma",
    "huber_k": "estimator.huber_k",
    "smoother": "smoother.kind",
    "lag_s": "smoother.lag_s",
    "relinearize_threshold": "smoother.relinearize_threshold",
    "relinearize_skip": "smoother.relinearize_skip",
    "factorization": "smoother.factorization",
    "min_views": "landmarks.min_views",
    "min_parallax_deg": "landmarks.min_parallax_deg",
    "max_reprojection_px": "landmarks.max_reprojection_px",
    "landmark_prior_sigma_m": "landmarks.prior_sigma_m",
    "max_track_keyframes": "landmarks.max_track_keyframes",
    "init_window_s": "initialisation.window_s",
    "static_init_max_gyro": "initialisation.static_max_gyro",
    "static_init_max_acc_std": "initialisation.static_max_acc_std",
    "still_max_px": "zero_velocity.max_flow_px",
    "still_window_s": "zero_velocity.window_s",
    "reid": "reidentification.enabled",
}


def _moved_key(section: str, key: str) -> str:
    if section == "imu" and key.startswith("bias_init_sigma_"):
        return "initialisation." + key.replace("bias_init_", "bias_")
    if section == "backend":
        if key.startswith("reid_"):
            return "reidentification." + key[len("reid_") :]
        return _MOVED.get(key, "")
    return ""


def config_from_dict(data: dict[str, Any] | None) -> Config:
    """Build a Config from nested dicts, rejecting unknown sections and keys (naming a moved key's new place)."""
    data = data or {}
    if not isinstance(data, dict):
        raise ConfigError("config must be a mapping of sections")
    for section, values in data.items():
        for key in values if isinstance(values, dict) else ():
            if moved := _moved_key(section, key):
                raise ConfigError(f"config key {section}.{key} is now {moved}")
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


def preset_names() -> list[str]:
    """The named presets shipped with vio (`vio/presets/NAME.yaml`)."""
    return sorted(p.stem for p in PRESETS_DIR.glob("*.yaml"))


def _read_yaml_mapping(p: Path) -> dict[str, Any]:
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
    return data


def _merge(data: dict[str, Any], more: dict[str, Any]) -> None:
    for section, values in more.items():
        if not isinstance(values, dict) or not isinstance(data.get(section, {}), dict):
            raise ConfigError(f"config section '{section}' must be a mapping")
        data.setdefault(section, {}).update(values)


def load_config(
    path: str | Path | None = None, overrides: list[str] | None = None, presets: list[str] | tuple[str, ...] = ()
) -> Config:
    """The effective configuration: defaults, then each named preset in order (`vio/presets/NAME.yaml`), then the
    YAML file `path`, then the `section.key=value` overrides."""
    data: dict[str, Any] = {}
    for name in presets:
        p = PRESETS_DIR / f"{name}.yaml"
        if not p.is_file():
            raise ConfigError(f"unknown preset {name!r}; known: {', '.join(preset_names())}")
        _merge(data, _read_yaml_mapping(p))
    if path is not None:
        _merge(data, _read_yaml_mapping(Path(path)))
    _merge(data, parse_overrides(overrides))
    return config_from_dict(data)
