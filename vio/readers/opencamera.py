"""OpenCamera Sensors recordings (Android).

The app writes the video `DCIM/OpenCamera/VID_<date>.mp4` and, in the folder `DCIM/OpenCamera/<date>/`,
`VID_<date>_gyro.csv` and `VID_<date>_accel.csv` (rows `x,y,z,timestamp_ns`, no header; rad/s and m/s^2 including
gravity, Android sensor frame) and `VID_<date>_timestamps.csv` (one frame timestamp in ns per line, same clock).
Point the reader at the folder with the CSV files; the video is looked up there and in its parent folder.
Calibration: `--calib`, or `calib.yaml` beside the CSV files.
"""

from __future__ import annotations

from pathlib import Path

from vio.capture import Capture
from vio.errors import CaptureError
from vio.readers.common import frame_times, make_capture, merge_gyro_acc, resolve_calibration
from vio.readers.tables import read_table
from vio.readers.video import VideoFrames, find_video, match_frame_count


def find_prefix(folder: Path) -> str | None:
    gyros = sorted(Path(folder).glob("*_gyro.csv"))
    return gyros[0].name[: -len("_gyro.csv")] if gyros else None


def read_opencamera(folder: Path, calib: str | Path | None = None) -> Capture:
    folder = Path(folder)
    prefix = find_prefix(folder)
    if prefix is None:
        raise CaptureError("no *_gyro.csv (not an OpenCamera Sensors folder)", folder)
    warnings: list[str] = []
    gyro = read_table(folder / f"{prefix}_gyro.csv", 3, [0, 1, 2], warnings=warnings, what="gyro")
    acc_path = folder / f"{prefix}_accel.csv"
    if not acc_path.is_file():
        raise CaptureError(f"accelerometer file {acc_path.name} missing", folder)
    acc = read_table(acc_path, 3, [0, 1, 2], warnings=warnings, what="accelerometer")
    imu = merge_gyro_acc(gyro, acc, warnings)
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
    cal = resolve_calibration(folder, calib)
    return make_capture(folder, "opencamera", cal, imu, ft, lambda i: video(int(idx[i])), warnings)
