"""Checks every reader runs on what it read: units, gaps, clock overlap, calibration, image size.

`finish_capture` is the last step of `open_capture`: problems that make an estimate meaningless raise (one line
naming the file and the problem); problems where going on is safe become warnings in `Capture.warnings`.
"""

from __future__ import annotations

import logging
from collections.abc import Collection
from dataclasses import replace
from pathlib import Path

import numpy as np

from vio.capture import Capture
from vio.errors import CalibrationError, CaptureError
from vio.readers.calib import PHONE_IMU_DEFAULT, missing_calibration_message
from vio.records import ImuSeries

log = logging.getLogger(__name__)

G = 9.81
DEG = np.pi / 180.0


def gap_warnings(t_ns: np.ndarray, rows: np.ndarray | None, path: Path, what: str, factor: float) -> list[str]:
    """Warnings for intervals longer than `factor` times the median interval (one line, naming the first row)."""
    if t_ns.shape[0] < 3:
        return []
    dt = np.diff(t_ns)
    med = float(np.median(dt))
    gaps = np.flatnonzero(dt > factor * med)
    if gaps.size == 0:
        return []
    i = int(gaps[0]) + 1
    where = f"{path}:{int(rows[i])}" if rows is not None else f"{path}"
    largest = float(dt[gaps].max()) * 1e-9
    return [
        f"{where}: {gaps.size} {what} gap(s) longer than {factor * med * 1e-6:.1f} ms (nominal {med * 1e-6:.1f} ms), "
        f"largest {largest * 1e3:.1f} ms (first here)"
    ]


def _smooth(x: np.ndarray, n: int) -> np.ndarray:
    if n <= 1:
        return x
    kernel = np.ones(n) / n
    return np.column_stack([np.convolve(x[:, k], kernel, mode="same") for k in range(x.shape[1])])


def gyro_scale_vs_gravity(imu: ImuSeries) -> tuple[float, float]:
    """Scale s in d(g_dir)/dt = s * (-gyro x g_dir), fitted on the low-passed streams, and the rotation seen (rad).

    Only trusted when the fit explains the motion (cosine >= 0.7): a handheld phone's specific force stays close to
    gravity, a multirotor's does not.

    The direction of gravity in the body frame turns exactly as the gyro says when the gyro is in rad/s (s = 1);
    a gyro logged in deg/s gives s = pi/180. Returns (nan, 0) when there is too little rotation to tell.
    """
    if len(imu) < 50:
        return float("nan"), 0.0
    dt_s = float(np.median(np.diff(imu.t_ns))) * 1e-9
    n = max(1, int(round(0.1 / dt_s)))
    acc = _smooth(imu.acc, n)[n:-n]
    gyro = _smooth(imu.gyro, n)[n:-n]
    t_s = (imu.t_ns[n:-n] - imu.t_ns[0]) * 1e-9
    norm = np.linalg.norm(acc, axis=1, keepdims=True)
    if acc.shape[0] < 10 or np.any(norm < 1e-9):
        return float("nan"), 0.0
    g_dir = acc / norm
    k = max(1, n // 2)
    dg = (g_dir[2 * k :] - g_dir[: -2 * k]) / (t_s[2 * k :] - t_s[: -2 * k])[:, None]
    pred = -np.cross(gyro[k:-k], g_dir[k:-k])
    denom = float(np.sum(pred * pred))
    seen = float(np.sum(np.linalg.norm(dg, axis=1)) * dt_s)
    if denom <= 0 or seen < 0.3:
        return float("nan"), seen
    cosine = float(np.sum(dg * pred) / np.sqrt(denom * float(np.sum(dg * dg))))
    if abs(cosine) < 0.7:  # gravity direction is not what turns (e.g. a multirotor's thrust-aligned force)
        return float("nan"), seen
    return float(np.sum(dg * pred) / denom), seen


def unit_problems(imu: ImuSeries, path: Path) -> list[str]:
    """Errors for an accelerometer in g or without gravity, and for a gyro in deg/s."""
    problems: list[str] = []
    a = float(np.median(np.linalg.norm(imu.acc, axis=1)))
    if 0.6 <= a <= 1.6:
        problems.append(f"{path}: accelerometer looks like it is in g (median |a| = {a:.2f}); expected m/s^2")
    elif a > 100.0:
        problems.append(f"{path}: implausible accelerometer values (median |a| = {a:.3g} m/s^2)")
    elif a < 0.6:
        problems.append(
            f"{path}: accelerometer has no gravity (median |a| = {a:.2f} m/s^2): this is linear acceleration; "
            "the estimator needs the total specific force"
        )
    s, _ = gyro_scale_vs_gravity(imu)
    w99 = float(np.percentile(np.linalg.norm(imu.gyro, axis=1), 99))
    if (np.isfinite(s) and 0.3 * DEG < s < 3.0 * DEG) or w99 > 20.0:
        detail = f"gravity turns {s:.4f}x as fast as the gyro says" if np.isfinite(s) else f"99% |w| = {w99:.0f}"
        problems.append(f"{path}: gyro looks like it is in deg/s ({detail}); expected rad/s")
    return problems


MAX_GYRO_RAD_S = 100.0  # phone gyros saturate near 35 rad/s (2000 deg/s)
MAX_ACC_M_S2 = 1000.0  # about 100 g; phone accelerometers saturate at 16 g
MAX_IMPLAUSIBLE = 0.01  # fraction of IMU samples that may be dropped as implausible before it is an error


def _drop_implausible(cap: Capture, source: Path) -> str | None:
    """Drop IMU samples beyond any sensor's range (a corrupt row, e.g. 1e308) with a warning; when more than
    MAX_IMPLAUSIBLE of them are, nothing is dropped and the error message is returned (a unit mistake, e.g. a gyro
    in deg/s, is reported instead when the unit checks find it)."""
    imu = cap.imu
    assert imu is not None
    with np.errstate(over="ignore"):  # 1e308 squared is inf, which is beyond the range too
        bad = (np.linalg.norm(imu.gyro, axis=1) > MAX_GYRO_RAD_S) | (np.linalg.norm(imu.acc, axis=1) > MAX_ACC_M_S2)
    if not bad.any():
        return None
    what = (
        f"{int(bad.sum())} of {len(imu)} IMU samples beyond any sensor's range (|gyro| > {MAX_GYRO_RAD_S:g} rad/s "
        f"or |acc| > {MAX_ACC_M_S2:g} m/s^2)"
    )
    if bad.mean() > MAX_IMPLAUSIBLE or bad.sum() > len(imu) - 2:
        return f"{source}: {what}"
    first = int(imu.t_ns[np.flatnonzero(bad)[0]])
    cap.imu = ImuSeries(imu.t_ns[~bad], imu.gyro[~bad], imu.acc[~bad])
    cap.warn(f"{source}: {what} dropped (first at t={first} ns)")
    return None


def unit_warnings(imu: ImuSeries, path: Path) -> list[str]:
    a = float(np.median(np.linalg.norm(imu.acc, axis=1)))
    if 1.6 < a < 7.0 or a > 14.0:
        return [f"{path}: unusual accelerometer magnitude (median |a| = {a:.2f} m/s^2, gravity is {G})"]
    return []


def _trim_to_imu(cap: Capture, source: Path) -> str | None:
    """Drop frames outside the IMU span; an error message when the clocks do not overlap at all."""
    assert cap.imu is not None
    t0, t1 = int(cap.imu.t_ns[0]), int(cap.imu.t_ns[-1])
    ft = cap.frame_t_ns
    inside = (ft >= t0) & (ft <= t1)
    if not inside.any():
        return (
            f"{source}: camera and IMU clocks do not overlap (frames {ft[0] * 1e-9:.3f}..{ft[-1] * 1e-9:.3f} s, "
            f"IMU {t0 * 1e-9:.3f}..{t1 * 1e-9:.3f} s)"
        )
    if not inside.all():
        idx = np.flatnonzero(inside)
        loader = cap.load_image
        cap.warn(f"{source}: {int((~inside).sum())} of {ft.shape[0]} frames lie outside the IMU span and are skipped")
        cap.frame_t_ns = ft[idx]
        cap.load_image = lambda i, _idx=idx, _load=loader: _load(int(_idx[i]))
    return None


SIZE_CHECK_FRAMES = 10  # the image size is read from the first of this many frames that decodes


def _image_size_problems(cap: Capture, source: Path) -> list[str]:
    """The image size against the calibration's, from the first frame that decodes (a frame that does not decode is
    skipped by `vio run`; when none of the first few decode, that is the problem)."""
    assert cap.camera is not None
    first_error = None
    for i in range(min(cap.num_frames, SIZE_CHECK_FRAMES)):
        try:
            img = cap.load_image(i)
        except CaptureError as exc:
            first_error = first_error or str(exc)
            continue
        h, w = img.shape[:2]
        c = cap.camera
        if (c.width, c.height) == (0, 0):  # a calibration without an image size (ORB-SLAM2 settings): the images'
            cap.camera = replace(c, width=int(w), height=int(h))
            return []
        if (w, h) == (c.width, c.height):
            return []
        rotated = " (rotated video?)" if (h, w) == (c.width, c.height) else ""
        return [f"{source}: images are {w}x{h} but the calibration is for {c.width}x{c.height}{rotated}"]
    n = min(cap.num_frames, SIZE_CHECK_FRAMES)
    return [f"{source}: none of the first {n} images can be decoded (first: {first_error})"]


def finish_capture(
    cap: Capture, source: Path, strict: bool = True, needs: Collection[str] = ("camera", "imu")
) -> list[str]:
    """Run the checks of the streams in `needs` ("camera", "imu"; the clock overlap when both); returns the error
    messages (raises the first one when `strict`)."""
    unknown = set(needs) - {"camera", "imu"}
    if unknown:
        raise ValueError(f"unknown stream(s) {sorted(unknown)} in needs (camera, imu)")
    camera, imu = "camera" in needs, "imu" in needs
    errors: list[tuple[type[Exception], str]] = []
    if imu and (cap.imu is None or len(cap.imu) < 2):
        errors.append((CaptureError, f"{source}: no IMU stream (the estimator needs gyro and accelerometer)"))
    elif imu and cap.imu is not None:
        beyond = _drop_implausible(cap, source)  # a few corrupt samples go first: they would skew the unit checks
        with np.errstate(over="ignore", invalid="ignore"):  # statistics of corrupt values: inf/nan, then reported
            units = unit_problems(cap.imu, source)
        errors += [(CaptureError, m) for m in units]
        if beyond and not units:
            errors.append((CaptureError, beyond))
        for m in unit_warnings(cap.imu, source):
            cap.warn(m)
    if camera and cap.num_frames == 0 and cap.tracks is None:
        errors.append((CaptureError, f"{source}: no camera frames"))
    if camera and imu and cap.num_frames > 0 and cap.imu is not None and len(cap.imu) >= 2:
        msg = _trim_to_imu(cap, source)
        if msg:
            errors.append((CaptureError, msg))
    if camera and cap.num_frames > 0 and cap.camera is None:
        errors.append((CalibrationError, missing_calibration_message(source)))
    if imu and cap.imu is not None and cap.imu_calib is None:
        cap.imu_calib = PHONE_IMU_DEFAULT
        cap.warn(f"{source}: no IMU noise calibration; assuming phone-grade defaults {PHONE_IMU_DEFAULT}")
    if camera and cap.num_frames > 0 and cap.camera is not None and cap.tracks is None:
        errors += [(CalibrationError, m) for m in _image_size_problems(cap, source)]
    if strict and errors:
        cls, msg = errors[0]
        raise cls(msg)
    return [m for _, m in errors]
