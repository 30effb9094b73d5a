"""OpenCamera Sensors recordings (Android).

The app writes the video `DCIM/OpenCamera/VID_<date>.mp4` and, in the folder `DCIM/OpenCamera/<date>/`,
`VID_<date>_gyro.csv` and `VID_<date>_accel.csv` (rows `x,y,z,timestamp_ns`, no header; rad/s and m/s^2 including
gravity, Android sensor frame) and `VID_<date>_timestamps.csv` (one frame timestamp in ns per line, same clock).
Point the reader at the folder with the CSV files; the video is looked up there and in its parent folder.
Calibration: `--calib`, or `calib.yaml` beside the CSV files.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from vio.capture import Capture
from vio.errors import CaptureError
from vio.readers.common import collect, frame_times, make_capture, merge_gyro_acc, no_frames, resolve_calibration
from vio.readers.tables import read_table
from vio.readers.video import VideoFrames, find_video, match_frame_count
from vio.records import ImuSeries


def find_prefix(folder: Path) -> str | None:
    gyros = sorted(Path(folder).glob("*_gyro.csv"))
    return gyros[0].name[: -len("_gyro.csv")] if gyros else None


def read_opencamera(folder: Path, calib: str | Path | None = None, problems: list[str] | None = None) -> Capture:
    """Read an OpenCamera Sensors folder. With a `problems` list, a stream that cannot be read is left out and its
    error appended there (`vio info`)."""
    folder = Path(folder)
    prefix = find_prefix(folder)
    if prefix is None:
        raise CaptureError("no *_gyro.csv (not an OpenCamera Sensors folder)", folder)
    warnings: list[str] = []
    imu = collect(lambda: _imu(folder, prefix, warnings), None, problems)
    empty = (np.zeros(0, np.int64), no_frames(folder, "the frames could not be read"))
    ft, load = collect(lambda: _frames(folder, prefix, warnings), empty, problems)
    cal = collect(lambda: resolve_calibration(folder, calib), None, problems)
    return make_capture(folder, "opencamera", cal, imu, ft, load, warnings)


def _imu(folder: Path, prefix: str, warnings: list[str]) -> ImuSeries:
    gyro = read_table(folder / f"{prefix}_gyro.csv", 3, [0, 1, 2], warnings=warnings, what="gyro")
    acc_path = folder / f"{prefix}_accel.csv"
    if not acc_path.is_file():
        raise CaptureError(f"accelerometer file {acc_path.name} missing", folder)
    acc = read_table(acc_path, 3, [0, 1, 2], warnings=warnings, what="accelerometer")
    return merge_gyro_acc(gyro, acc, warnings)


def _frames(folder: Path, prefix: str, warnings: list[str]) -> tuple[np.ndarray, Callable[[int], np.ndarray]]:
    times = folder / f"{prefix}_timestamps.csv"
    table = read_table(times, 0, [], warnings=warnings, what="frame")
    if len(table) == 0:
        raise CaptureError("no frame timestamps", times)
    video_path = find_video(folder, prefix) or find_video(folder.parent, prefix)
    if video_path is None:
        raise CaptureError(f"video {prefix}.mp4 not found here or in the parent folder", folder)
    video = VideoFrames(video_path)
    n = match_frame_count(video, len(table), times, warnings)
    ft, idx = frame_times(table.select(slice(0, n)), warnings)
    return ft, lambda i: video(int(idx[i]))
