"""Pieces shared by the phone-log readers: IMU streams from tables, merged gyro/accelerometer, calibration."""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import numpy as np

from vio.capture import Capture
from vio.errors import CaptureError, VioError
from vio.readers.calib import Calibration, find_calibration, load_calibration
from vio.readers.tables import Table, ensure_increasing, increasing_mask
from vio.readers.validate import gap_warnings
from vio.records import ImuSeries

log = logging.getLogger(__name__)

T = TypeVar("T")

IMU_GAP_FACTOR = 4.0  # an IMU interval longer than this many nominal intervals is reported
FRAME_GAP_FACTOR = 2.5  # a frame interval longer than this many nominal intervals is reported (dropped frames)


def collect(read: Callable[[], T], default: T, problems: list[str] | None) -> T:
    """One stream of a capture: its reader's error raises, or (when collecting `problems`, as `vio info` does) is
    appended there and `default` returned, so that every unreadable stream is reported, not only the first (a
    file the system cannot read, such as a symbolic-link loop, in the words `open_capture` uses for it)."""
    if problems is None:
        return read()
    try:
        return read()
    except VioError as exc:
        problems.append(str(exc))
    except OSError as exc:
        problems.append(str(unreadable(exc, "")))
    return default


def unreadable(exc: OSError, path: object) -> CaptureError:
    """A file the system cannot read (a symbolic-link loop, no permission) as one line naming it."""
    return CaptureError(f"cannot be read ({exc.strerror or exc})", exc.filename or path)


def no_frames(source: Path, why: str) -> Callable[[int], np.ndarray]:
    """An image loader for a capture whose frames could not be read."""

    def load(i: int) -> np.ndarray:
        raise CaptureError(why, source)

    return load


def imu_from_table(table: Table, warnings: list[str]) -> ImuSeries:
    """An ImuSeries from a table with columns gyro x,y,z (rad/s) then acc x,y,z (m/s^2)."""
    table = ensure_increasing(table, "IMU", warnings)
    if len(table) < 2:
        raise CaptureError(f"only {len(table)} IMU sample(s)", table.path)
    warnings += gap_warnings(table.t_ns, table.rows, table.path, "IMU", IMU_GAP_FACTOR)
    return ImuSeries(table.t_ns, table.values[:, 0:3].copy(), table.values[:, 3:6].copy())


def merge_gyro_acc(gyro: Table, acc: Table, warnings: list[str]) -> ImuSeries:
    """Join separate gyro and accelerometer streams on the gyro's timestamps (accelerometer linearly interpolated).

    Gyro samples outside the accelerometer's span are dropped. Both tables hold x, y, z columns.
    """
    gyro = ensure_increasing(gyro, "gyro", warnings)
    acc = ensure_increasing(acc, "accelerometer", warnings)
    for t in (gyro, acc):
        if len(t) < 2:
            raise CaptureError(f"only {len(t)} sample(s)", t.path)
    inside = (gyro.t_ns >= acc.t_ns[0]) & (gyro.t_ns <= acc.t_ns[-1])
    if not inside.any():
        raise CaptureError(f"gyro and accelerometer times do not overlap ({acc.path.name})", gyro.path)
    gyro = gyro.select(inside)
    warnings += gap_warnings(gyro.t_ns, gyro.rows, gyro.path, "gyro", IMU_GAP_FACTOR)
    warnings += gap_warnings(acc.t_ns, acc.rows, acc.path, "accelerometer", IMU_GAP_FACTOR)
    t_ref = gyro.t_ns[0]
    tg = (gyro.t_ns - t_ref).astype(np.float64)
    ta = (acc.t_ns - t_ref).astype(np.float64)
    acc_on_gyro = np.column_stack([np.interp(tg, ta, acc.values[:, k]) for k in range(3)])
    return ImuSeries(gyro.t_ns.copy(), gyro.values[:, 0:3].copy(), acc_on_gyro)


def frame_times(table: Table, warnings: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """Validated frame times and the kept row indices into the table (repeats dropped, gaps reported)."""
    keep = increasing_mask(table, "frame", warnings)
    table = table.select(keep)
    warnings += gap_warnings(table.t_ns, table.rows, table.path, "frame", FRAME_GAP_FACTOR)
    return table.t_ns, np.flatnonzero(keep)


def resolve_calibration(folder: Path, calib: str | Path | None) -> Calibration | None:
    """`--calib` wins; otherwise a calibration stored beside the capture; None when there is neither."""
    if calib is not None:
        return load_calibration(calib)
    return find_calibration(folder)


def make_capture(
    root: Path,
    fmt: str,
    cal: Calibration | None,
    imu: ImuSeries | None,
    frame_t_ns: np.ndarray,
    load: Callable[[int], np.ndarray],
    warnings: list[str],
) -> Capture:
    """Assemble a Capture; applies the calibration's camera-IMU time shift to the frame times."""
    shift = cal.timeshift_cam_imu_ns if cal is not None else 0
    cap = Capture(
        root=root,
        camera=cal.camera if cal else None,
        imu_calib=cal.imu if cal else None,
        imu=imu,
        frame_t_ns=np.asarray(frame_t_ns, np.int64) + shift,
        load_image=load,
        format=fmt,
    )
    for w in [*warnings, *(cal.warnings if cal is not None else ())]:
        cap.warn(w)
    if shift:
        log.info("frame times shifted by timeshift_cam_imu = %.3f ms", shift * 1e-6)
    return cap
