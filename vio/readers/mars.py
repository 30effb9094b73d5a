"""MARS logger folders (Mobile AR Sensor logger, Android and iOS).

Android layout: `movie.mp4` (H.264), `frame_timestamps.txt` (one sensor-clock timestamp in ns per video frame,
first field of each line), `gyro_accel.csv` (`Timestamp[nanosec],gx[rad/s],gy,gz,ax[m/s^2],ay,az[,Unix time]`, the
accelerometer interpolated onto the gyro times by the app), `movie_metadata.csv` (per-frame camera metadata;
`readout_ns` reads its `Frame readout time[nanosec]`, the rolling-shutter readout). iOS layout: no
`frame_timestamps.txt`; frame times are the first column of `movie_metadata.csv`, and timestamps are in seconds
when the header says `[sec]`. Calibration: `--calib`, or `calib.yaml` in the folder. The video is decoded by PyAV
(FFmpeg's H.264/HEVC decoders) in the sensor's orientation, which the calibration describes; a portrait
recording's display rotation is not applied (`vio.readers.video_av`). Without a calibration, the logged
per-frame `fx, fy` of `movie_metadata.csv` give an approximate camera, with a warning
(`vio.readers.logged_intrinsics`).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from vio.capture import Capture
from vio.errors import CaptureError
from vio.readers.common import collect, frame_times, imu_from_table, make_capture, no_frames, resolve_calibration
from vio.readers.logged_intrinsics import logged_calibration
from vio.readers.tables import read_lines, read_table
from vio.readers.video import VideoFrames, find_video, match_frame_count
from vio.readers.video_av import AvVideoFrames, av_available
from vio.records import ImuSeries


def _time_scale(path: Path) -> int:
    """1 for ns, 10**9 for seconds, from the header's unit (ns when there is no header)."""
    lines, _ = read_lines(path)
    for line in lines:
        s = line.strip().lower()
        if not s:
            continue
        if "[sec]" in s or "[s]" in s:
            return 1_000_000_000
        return 1
    return 1


def is_mars(folder: Path) -> bool:
    return (folder / "gyro_accel.csv").is_file()


def read_mars(folder: Path, calib: str | Path | None = None, problems: list[str] | None = None) -> Capture:
    """Read a MARS folder. With a `problems` list, a stream that cannot be read is left out and its error appended
    there (`vio info`)."""
    folder = Path(folder)
    warnings: list[str] = []
    imu = collect(lambda: _imu(folder, warnings), None, problems)
    empty = (np.zeros(0, np.int64), no_frames(folder, "the frames could not be read"), (0, 0))
    ft, load, (width, height) = collect(lambda: _frames(folder, warnings), empty, problems)
    cal = collect(lambda: resolve_calibration(folder, calib), None, problems)
    if cal is None and calib is None:  # no calibration anywhere: the logger's own intrinsics, with a warning
        cal = collect(lambda: logged_calibration(folder, width, height, ft, warnings), None, problems)
    return make_capture(folder, "mars", cal, imu, ft, load, warnings)


def _imu(folder: Path, warnings: list[str]) -> ImuSeries:
    imu_csv = folder / "gyro_accel.csv"
    scale = _time_scale(imu_csv)
    table = read_table(imu_csv, 0, [1, 2, 3, 4, 5, 6], time_scale=scale, warnings=warnings, what="IMU")
    return imu_from_table(table, warnings)


def _frames(folder: Path, warnings: list[str]) -> tuple[np.ndarray, Callable[[int], np.ndarray], tuple[int, int]]:
    """Frame times, the frame loader and the video's (width, height) in px as decoded."""
    times = folder / "frame_timestamps.txt"
    if not times.is_file():
        times = folder / "movie_metadata.csv"
    if not times.is_file():
        raise CaptureError("MARS folder lacks frame_timestamps.txt (Android) and movie_metadata.csv (iOS)", folder)
    tscale = _time_scale(times)
    # frame_timestamps.txt may separate fields by spaces; normalise through the table reader's comma split
    table = read_table(times, 0, [], time_scale=tscale, warnings=warnings, what="frame")
    if len(table) == 0:
        raise CaptureError("no frame timestamps", times)
    video_path = folder / "movie.mp4" if (folder / "movie.mp4").is_file() else find_video(folder)
    if video_path is None:
        raise CaptureError("MARS folder has no movie.mp4", folder)
    video = AvVideoFrames(video_path) if av_available() else VideoFrames(video_path)
    n = match_frame_count(video, len(table), times, warnings)
    table = table.select(slice(0, n))
    ft, idx = frame_times(table, warnings)
    return ft, lambda i: video(int(idx[i])), (int(video.width), int(video.height))


READOUT_COLUMN = "frame readout time[nanosec]"


def readout_ns(folder: str | Path) -> int | None:
    """The rolling-shutter readout time (top to bottom row), ns, from an Android MARS `movie_metadata.csv`: the
    median of its `Frame readout time[nanosec]` column; None when the file or the column is absent."""
    path = Path(folder) / "movie_metadata.csv"
    if not path.is_file():
        return None
    lines, _ = read_lines(path)
    header = [h.strip().lower() for h in lines[0].split(",")] if lines else []
    if READOUT_COLUMN not in header:
        return None
    col = header.index(READOUT_COLUMN)
    table = read_table(path, 0, [col], what="frame metadata")
    values = table.values[:, 0] if len(table) else np.zeros(0)
    values = values[np.isfinite(values) & (values > 0)]
    return int(np.median(values)) if values.size else None
