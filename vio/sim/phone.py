"""The phone camera: rolling shutter, motion blur, auto exposure, sensor noise, vignetting and a clock offset.

Timing (all in the IMU clock unless said otherwise). Frame k's top row is exposed around its true time `t_true`;
row v (0 = top, read first) is exposed over [t_true + readout * v / H - exposure / 2, ... + exposure / 2], so the
rows' mid-exposure times run from t_true (top) to t_true + readout * (H - 1) / H (bottom). The frame's timestamp, on
the camera clock, is `t_stamp = t_true - time_offset` (Kalibr's `timeshift_cam_imu`: t_imu = t_cam + shift), so an
estimator that adds the shift to the stamp finds the top row's mid-exposure time.

Rendering: the rows are read in `bands` bands of equal height, each rendered from the poses at its centre row's
time (48 bands of 10 rows at 480 px: within 0.2 ms of each row's own time at 20 ms readout); motion blur averages
`blur_samples(...)` renders per band at times spread evenly over the exposure (one per pixel of image motion, at
most `MAX_BLUR_SAMPLES`). The sensor then applies, frame by frame in order: vignetting (gain 1 - v r^2 at relative
radius r from the centre, r = 1 in a corner), auto exposure (a gain that follows `ae_target / mean brightness` with
a first-order lag), shot and read noise (variance read^2 + shot * signal, DN), rounding and clipping to 8 bits.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from vio.errors import SimulationError
from vio.sim.imu import PhoneImu

MAX_BLUR_SAMPLES = 8


@dataclass(frozen=True)
class PhoneCamera:
    """A rolling-shutter phone camera; times in s, noise in grey levels (DN) of the 8-bit image."""

    readout_s: float = 0.020  # top row to bottom row (Android SENSOR_ROLLING_SHUTTER_SKEW; MARS movie_metadata)
    exposure_s: float = 0.010  # per row
    time_offset_s: float = 0.015  # Kalibr timeshift_cam_imu: t_imu = t_cam + shift
    auto_exposure: bool = True  # gain follows the scene brightness
    ae_target: float = 0.45  # mean brightness (fraction of white) the auto exposure aims at
    ae_time_constant_s: float = 0.3  # lag of the auto exposure
    ae_gain_range: tuple[float, float] = (0.5, 4.0)
    vignetting: float = 0.25  # brightness lost in the corners (after the phone's lens-shading correction)
    read_noise_dn: float = 1.0  # DN at gain 1, scales with the gain
    shot_noise: float = 0.05  # shot-noise variance per DN of signal at gain 1 (scales with the gain)
    portrait: bool = True  # phone held upright: image rows run vertically in the world (camera-driven scenarios)
    bands: int = 48  # rolling-shutter bands (rows rendered from one pose)

    def validate(self, rate_hz: float, height: int) -> None:
        """One-line SimulationError for values a camera at `rate_hz` frames per second cannot have."""
        period = 1.0 / rate_hz
        for name, v in (("readout", self.readout_s), ("exposure", self.exposure_s)):
            if not np.isfinite(v) or v < 0 or v > period:
                raise SimulationError(
                    f"{name} must be between 0 and the frame period {period * 1e3:g} ms, got {v * 1e3:g}"
                )
        if not np.isfinite(self.time_offset_s) or abs(self.time_offset_s) > 0.5:
            raise SimulationError(f"time offset must be within +-500 ms, got {self.time_offset_s * 1e3:g}")
        if not 1 <= self.bands <= height:
            raise SimulationError(f"rolling-shutter bands must be between 1 and the image height, got {self.bands}")

    def yaml_dict(self, height: int) -> dict:
        """The true camera timing and sensor model, for the ground truth (`scene/scene.yaml`); `height` in px.

        `timeshift_image_centre_s` is the shift that puts a stamp at the middle row's mid-exposure: what an
        estimator that treats the frame as a global-shutter image taken at one time should find."""
        return {
            "model": "phone (rolling shutter)",
            "readout_s": float(self.readout_s),
            "exposure_s": float(self.exposure_s),
            "timeshift_cam_imu_s": float(self.time_offset_s),
            "timeshift_image_centre_s": float(self.time_offset_s + self.readout_s * (height - 1) / (2.0 * height)),
            "convention": "t_imu = t_cam + timeshift_cam_imu is the top row's mid-exposure; row v of H is read "
            "readout_s * v / H later",
            "auto_exposure": bool(self.auto_exposure),
            "vignetting": float(self.vignetting),
            "read_noise_dn": float(self.read_noise_dn),
            "shot_noise": float(self.shot_noise),
            "portrait": bool(self.portrait),
            "bands": int(self.bands),
        }


PRESETS = {"phone": PhoneCamera()}
# Knobs alone on the default camera (global shutter, no offset): everything else as the default renderer
# (1.5 DN Gaussian noise, no auto exposure, no vignetting, landscape).
KNOBS_ONLY = PhoneCamera(0.0, 0.0, 0.0, False, vignetting=0.0, read_noise_dn=1.5, shot_noise=0.0, portrait=False)


def camera_model(
    preset: str = "default",
    readout_ms: float | None = None,
    exposure_ms: float | None = None,
    time_offset_ms: float | None = None,
) -> PhoneCamera | None:
    """The camera model from the command line: None for the default camera with no knob set (the renderer of
    before issue 16, byte for byte), else the preset (`phone`) or the default camera with the knobs applied."""
    knobs = {"readout_s": readout_ms, "exposure_s": exposure_ms, "time_offset_s": time_offset_ms}
    knobs = {k: float(v) * 1e-3 for k, v in knobs.items() if v is not None}
    if preset == "default":
        return replace(KNOBS_ONLY, **knobs) if knobs else None
    if preset not in PRESETS:
        raise SimulationError(f"unknown camera '{preset}' (choose default or {', '.join(PRESETS)})")
    return replace(PRESETS[preset], **knobs)


PHONE_IMU_RATE_HZ = 100.0  # typical Android gyro/accelerometer rate (SENSOR_DELAY_FASTEST is often 200-500 Hz)


def simulate_options(
    preset: str = "default",
    readout_ms: float | None = None,
    exposure_ms: float | None = None,
    time_offset_ms: float | None = None,
    imu_rate_hz: float | None = None,
) -> dict:
    """`simulate(...)` keyword arguments of `vio simulate --camera ... --imu-rate ...`: the camera model, the IMU
    rate and the phone IMU's errors. The `phone` preset brings a phone IMU (100 Hz unless `imu_rate_hz`, with
    `PhoneImu`'s scale factors, misalignment and jitter); nothing set gives {} (the default capture)."""
    opts: dict = {}
    model = camera_model(preset, readout_ms, exposure_ms, time_offset_ms)
    if model is not None:
        opts["phone"] = model
    if preset == "phone":
        opts["phone_imu"] = PhoneImu()
        opts["imu_rate_hz"] = PHONE_IMU_RATE_HZ
    if imu_rate_hz is not None:
        opts["imu_rate_hz"] = float(imu_rate_hz)
    return opts


def portrait_camera(cam_fn):
    """Camera pose function of the phone turned upright: the image turned 90 deg about the optical axis (image x
    points up in the world, y to the right; turning the frame 90 deg counter-clockwise shows it upright, the display
    rotation `vio.writers.mars` stores), so the rolling shutter sweeps sideways as on a real phone."""
    cam_R_portrait = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])

    def fn(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p, world_R_cam = cam_fn(t)
        return p, world_R_cam @ cam_R_portrait

    return fn


def frame_times(t0_ns: int, duration_s: float, rate_hz: float, phone: PhoneCamera) -> tuple[np.ndarray, np.ndarray]:
    """(stamps on the camera clock, true top-row times on the IMU clock), ns, of the frames on the grid
    t0 + k / rate whose exposure and stamp both lie within the capture [t0, t0 + duration]."""
    n = int(np.floor(duration_s * rate_hz + 1e-9)) + 1
    t_true = np.int64(t0_ns) + np.round(np.arange(n) * (1e9 / rate_hz)).astype(np.int64)
    shift_ns = int(round(phone.time_offset_s * 1e9))
    stamps = t_true - shift_ns
    t_end = np.int64(t0_ns) + int(round(duration_s * 1e9))
    half_exp = int(round(phone.exposure_s * 0.5e9))
    ok = (t_true - half_exp >= t0_ns) & (t_true + int(round(phone.readout_s * 1e9)) + half_exp <= t_end)
    ok &= (stamps >= t0_ns) & (stamps <= t_end)
    return stamps[ok], t_true[ok]


def band_rows(height: int, bands: int) -> np.ndarray:
    """(B + 1,) row boundaries of the rolling-shutter bands."""
    return np.round(np.linspace(0, height, bands + 1)).astype(int)


def blur_samples(world_T_cam_a: np.ndarray, world_T_cam_b: np.ndarray, camera, depth_m: float = 0.5) -> int:
    """Renders per band for motion blur: one per pixel that points `depth_m` in front of the camera at the image
    centre and corners move between the exposure's start (pose a) and end (pose b), between 1 and
    MAX_BLUR_SAMPLES."""
    w, h = camera.width, camera.height
    uv = np.array([[w / 2, h / 2], [0, 0], [w, 0], [0, h], [w, h]], float)
    xy = np.column_stack([(uv[:, 0] - camera.cx) / camera.fx, (uv[:, 1] - camera.cy) / camera.fy])
    p_a = np.column_stack([xy * depth_m, np.full(len(xy), depth_m)])
    p_world = p_a @ world_T_cam_a[:3, :3].T + world_T_cam_a[:3, 3]
    p_b = (p_world - world_T_cam_b[:3, 3]) @ world_T_cam_b[:3, :3]
    uv_b = np.column_stack(
        [camera.fx * p_b[:, 0] / p_b[:, 2] + camera.cx, camera.fy * p_b[:, 1] / p_b[:, 2] + camera.cy]
    )
    motion_px = float(np.linalg.norm(uv_b - uv, axis=1).max())
    return int(np.clip(np.ceil(motion_px), 1, MAX_BLUR_SAMPLES))


def exposure_times_ns(t_true_ns: int, phone: PhoneCamera, height: int, samples: int) -> np.ndarray:
    """(B, S) times, ns, at which band b is rendered: S times evenly inside each band's exposure."""
    rows = band_rows(height, phone.bands)
    centre = 0.5 * (rows[:-1] + rows[1:] - 1)  # band centre row
    t_row = t_true_ns + phone.readout_s * 1e9 * centre / height
    frac = (np.arange(samples) + 0.5) / samples - 0.5
    return np.round(t_row[:, None] + frac[None, :] * phone.exposure_s * 1e9).astype(np.int64)


def render_radiance(renderer, poses: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """(H, W) float32 radiance of one rolling-shutter frame: band b (rows[b]:rows[b + 1]) is the mean of renders
    from poses[b] (S, 4, 4) world_T_cam."""
    out = np.empty((renderer.camera.height, renderer.camera.width), np.float32)
    for b in range(len(rows) - 1):
        r0, r1 = int(rows[b]), int(rows[b + 1])
        if r1 <= r0:
            continue
        acc = renderer.radiance(poses[b][0], (r0, r1))
        for pose in poses[b][1:]:
            acc = acc + renderer.radiance(pose, (r0, r1))
        out[r0:r1] = acc / np.float32(len(poses[b]))
    return out


class Sensor:
    """The phone's image sensor and auto exposure, applied to frames in order (the gain has a memory)."""

    def __init__(self, phone: PhoneCamera, width: int, height: int, rate_hz: float) -> None:
        self.phone = phone
        u, v = np.meshgrid(np.arange(width) - (width - 1) / 2.0, np.arange(height) - (height - 1) / 2.0)
        r2 = (u * u + v * v) / (((width - 1) / 2.0) ** 2 + ((height - 1) / 2.0) ** 2)
        self.shading = (1.0 - phone.vignetting * r2).astype(np.float32)
        self.alpha = 1.0 - np.exp(-1.0 / (rate_hz * phone.ae_time_constant_s))
        self.gain: float | None = None

    def expose(self, radiance: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, float]:
        """(H, W) uint8 image of a frame's radiance in [0, 1], and the gain the auto exposure applied."""
        ph = self.phone
        lit = radiance * self.shading
        gain = 1.0
        if ph.auto_exposure:
            lo, hi = ph.ae_gain_range
            want = float(np.clip(ph.ae_target / max(float(lit.mean()), 1e-3), lo, hi))
            self.gain = want if self.gain is None else self.gain * (want / self.gain) ** self.alpha
            gain = self.gain
        signal = lit * np.float32(255.0 * gain)
        var = np.float32((ph.read_noise_dn * gain) ** 2) + np.float32(ph.shot_noise * gain) * signal
        signal += rng.standard_normal(signal.shape, dtype=np.float32) * np.sqrt(var)
        return np.clip(np.rint(signal), 0, 255).astype(np.uint8), gain
