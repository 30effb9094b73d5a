"""`vio info CAPTURE`: what is in a capture (streams, rates, spans, gaps, clock overlap, camera-IMU time offset)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from vio.capture import Capture
from vio.errors import VioError


def _rate(t_ns: np.ndarray) -> tuple[float, float]:
    """(nominal rate Hz from the median interval, median interval ms)."""
    if t_ns.shape[0] < 2:
        return float("nan"), float("nan")
    med = float(np.median(np.diff(t_ns)))
    return 1e9 / med, med * 1e-6


def _span(t_ns: np.ndarray) -> str:
    if t_ns.shape[0] == 0:
        return "empty"
    return f"{(t_ns[-1] - t_ns[0]) * 1e-9:.3f} s [{t_ns[0] * 1e-9:.3f} .. {t_ns[-1] * 1e-9:.3f}]"


def _gaps(t_ns: np.ndarray, factor: float) -> str:
    if t_ns.shape[0] < 3:
        return "n/a"
    dt = np.diff(t_ns)
    med = float(np.median(dt))
    big = dt > factor * med
    if not big.any():
        return "none"
    return f"{int(big.sum())} longer than {factor:g}x nominal, largest {dt.max() * 1e-6:.1f} ms"


def _offset_lines(cap: Capture) -> list[str]:
    """The camera-IMU time offset estimated from rotation rates (readers/offset.py)."""
    from vio.readers.offset import estimate_time_offset

    try:
        est = estimate_time_offset(cap)
    except VioError as exc:  # e.g. an image that does not decode: reported, the rest of the summary stands
        return [f"camera-IMU time offset: not estimated ({exc})"]
    if est.offset_ns is None:
        return [f"camera-IMU time offset: not estimated ({est.note})"]
    return [
        f"camera-IMU time offset: {est.offset_ns * 1e-6:+.1f} ms (t_imu = t_cam + offset, Kalibr's "
        f"timeshift_cam_imu; correlation {est.correlation:.2f} over {est.pairs} frame pairs)"
        + (f" [{est.note}]" if est.note else ""),
        f"  image rotation rate / gyro rate: {est.rate_ratio:.3f} (1: consistent; 0.017: gyro in deg/s)",
    ]


def describe(cap: Capture, offset: bool = True, problems: Sequence[str] = ()) -> list[str]:
    """The lines of `vio info`: streams, rates, spans, gaps, clock overlap, time offset; then every problem that
    would stop `vio run` (`problems`) and the warnings."""
    lines = [f"capture: {cap.root} (format: {cap.format})"]
    if cap.num_frames:
        rate, med = _rate(cap.frame_t_ns)
        kind = "frames of precomputed feature tracks (no images)" if cap.tracks is not None else "frames"
        lines.append(f"camera: {cap.num_frames} {kind}, {rate:.2f} Hz (median interval {med:.2f} ms)")
        lines.append(f"  span: {_span(cap.frame_t_ns)}; gaps: {_gaps(cap.frame_t_ns, 2.5)}")
    elif cap.tracks is not None:
        lines.append(f"camera: no images; {len(cap.tracks)} frames of precomputed feature tracks")
    else:
        lines.append("camera: none")
    if cap.camera is not None:
        c = cap.camera
        lines.append(
            f"  calibration: {c.width}x{c.height}, fx {c.fx:.2f} fy {c.fy:.2f} cx {c.cx:.2f} cy {c.cy:.2f}, "
            f"radtan {np.array2string(np.asarray(c.dist), precision=4)}"
        )
    else:
        lines.append("  calibration: MISSING (pass --calib, see docs/capture_formats.md)")
    if cap.imu is not None and len(cap.imu):
        imu = cap.imu
        rate, med = _rate(imu.t_ns)
        lines.append(f"imu: {len(imu)} samples, {rate:.1f} Hz (median interval {med:.3f} ms)")
        lines.append(f"  span: {_span(imu.t_ns)}; gaps: {_gaps(imu.t_ns, 4.0)}")
        acc = np.linalg.norm(imu.acc, axis=1)
        gyro = np.linalg.norm(imu.gyro, axis=1)
        lines.append(
            f"  |acc| median {np.median(acc):.3f} m/s^2; |gyro| median {np.median(gyro):.3f}, "
            f"max {gyro.max():.3f} rad/s"
        )
        if cap.imu_calib is not None:
            k = cap.imu_calib
            lines.append(
                f"  noise: gyro {k.gyroscope_noise_density:.2e} rad/s/sqrt(Hz), acc "
                f"{k.accelerometer_noise_density:.2e} m/s^2/sqrt(Hz)"
            )
    else:
        lines.append("imu: none")
    if cap.num_frames and cap.imu is not None and len(cap.imu):
        f0, f1 = cap.frame_t_ns[0], cap.frame_t_ns[-1]
        i0, i1 = cap.imu.t_ns[0], cap.imu.t_ns[-1]
        overlap = max(0, min(f1, i1) - max(f0, i0)) * 1e-9
        lines.append(
            f"clock overlap: {overlap:.3f} s of the camera's {(f1 - f0) * 1e-9:.3f} s; "
            f"IMU starts {(f0 - i0) * 1e-6:.3f} ms before the first frame"
        )
    if cap.stills is not None:
        st, c = cap.stills, cap.stills.camera
        rate = f"{1e9 / np.median(np.diff(st.t_ns)):.2f} Hz" if len(st) > 1 else "one image"
        lines.append(f"stills: {len(st)} images {c.width}x{c.height}, {rate}, fx {c.fx:.1f} px; span {_span(st.t_ns)}")
    if cap.ground_truth is not None:
        lines.append(f"ground truth: {len(cap.ground_truth)} poses, span {_span(cap.ground_truth.t_ns)}")
    if offset and cap.num_frames >= 10 and cap.imu is not None and cap.tracks is None:
        lines += _offset_lines(cap)
    if problems:
        lines.append(f"problems: {len(problems)} (vio run stops at the first)")
        lines += [f"  error: {p}" for p in problems]
    for w in cap.warnings:
        lines.append(f"warning: {w}")
    return lines


def capture_info(path: str | os.PathLike[str], calib: str | os.PathLike[str] | None = None, offset: bool = True) -> str:
    """A human-readable summary of a capture. Every error that would stop `vio run` is listed, not raised (a
    stream that cannot be read is left out and its error listed), except when the capture cannot be read at all
    (then the error propagates: one line on the command line). `offset`: estimate the camera-IMU time offset."""
    from vio.readers import read_capture
    from vio.readers.common import unreadable
    from vio.readers.validate import finish_capture

    problems: list[str] = []
    try:
        cap = read_capture(Path(path), calib, problems)
    except OSError as exc:  # not one stream: the capture itself (e.g. a symbolic-link loop), as open_capture says
        raise unreadable(exc, path) from None
    problems += finish_capture(cap, Path(path), strict=False)
    return "\n".join(describe(cap, offset=offset, problems=problems))
