"""Sensor Logger exports (unzipped; iOS and Android), one CSV per sensor with a header.

Every CSV has `time` (UNIX epoch, ns) and `seconds_elapsed`, then named columns (`z,y,x` for the motion sensors).
- `Gyroscope.csv`: rad/s.
- `Accelerometer.csv`: acceleration WITHOUT gravity (m/s^2); `TotalAcceleration.csv` (Android): with gravity;
  `Gravity.csv`: the gravity vector. The specific force the estimator needs is TotalAcceleration, or
  Accelerometer + Gravity; with neither a gravity stream nor TotalAcceleration the capture is refused.
- `AccelerometerUncalibrated.csv` includes gravity, but is in g on iOS (unless "Standardise Units & Frames").
- iOS reports acceleration and gravity with the opposite sign to Android (CoreMotion convention) unless the export
  was standardised; `Metadata.csv` (`platform`, `standardisation`) tells which.
- Camera: `Camera/<epoch_ms>.jpg` per frame (Images mode), or `Camera/<epoch_ms>.mp4` (Video mode). The video's
  file name is the session start, not the first frame; per-frame times are read from `Camera/frame_times.csv` (one
  epoch-ns time per frame, e.g. exported from the video's timed-metadata track, see docs/capture_formats.md); without
  it frames are placed at start + n / fps with a warning.
"""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np

from vio.capture import Capture
from vio.errors import CaptureError
from vio.readers.common import collect, frame_times, make_capture, merge_gyro_acc, no_frames, resolve_calibration
from vio.readers.tables import Table, read_lines, read_table
from vio.readers.video import VIDEO_SUFFIXES, VideoFrames, match_frame_count
from vio.records import ImuSeries

log = logging.getLogger(__name__)

STANDARD_G = 9.80665


def is_sensorlogger(folder: Path) -> bool:
    return (folder / "Gyroscope.csv").is_file()


def _metadata(folder: Path) -> dict[str, str]:
    path = folder / "Metadata.csv"
    if not path.is_file():
        path = folder / "metadata.csv"
    if not path.is_file():
        return {}
    lines, _ = read_lines(path)
    rows = [line.split(",") for line in lines if line.strip()]
    if len(rows) < 2:
        return {}
    return {k.strip().lower(): v.strip() for k, v in zip(rows[0], rows[1], strict=False)}


def _xyz(path: Path, warnings: list[str], what: str) -> Table:
    return read_table(path, "time", ["x", "y", "z"], warnings=warnings, what=what)


def _specific_force(folder: Path, ios: bool, warnings: list[str]) -> Table:
    """Accelerometer including gravity, in m/s^2 and Android's sign convention (+z up when lying flat)."""
    sign = -1.0 if ios else 1.0
    total = folder / "TotalAcceleration.csv"
    if total.is_file():
        t = _xyz(total, warnings, "accelerometer")
        return Table(t.path, t.header, t.t_ns, sign * t.values, t.rows)
    user, grav = folder / "Accelerometer.csv", folder / "Gravity.csv"
    if user.is_file() and grav.is_file():
        a, g = _xyz(user, warnings, "accelerometer"), _xyz(grav, warnings, "gravity")
        if len(g) < 2:
            raise CaptureError("too few gravity samples", grav)
        gi = np.column_stack([np.interp(a.t_ns - a.t_ns[0], g.t_ns - a.t_ns[0], g.values[:, k]) for k in range(3)])
        return Table(a.path, a.header, a.t_ns, sign * (a.values + gi), a.rows)
    raw = folder / "AccelerometerUncalibrated.csv"
    if raw.is_file():
        t = _xyz(raw, warnings, "accelerometer")
        scale = STANDARD_G if ios else 1.0
        return Table(t.path, t.header, t.t_ns, sign * scale * t.values, t.rows)
    if user.is_file():
        raise CaptureError(
            "Accelerometer.csv excludes gravity and there is no Gravity.csv or TotalAcceleration.csv to restore it "
            "(enable the Gravity sensor in Sensor Logger)",
            user,
        )
    raise CaptureError("no accelerometer file (TotalAcceleration.csv or Accelerometer.csv + Gravity.csv)", folder)


def _camera(folder: Path, warnings: list[str]) -> tuple[np.ndarray, object] | None:
    cam = folder / "Camera"
    if not cam.is_dir():
        return None
    videos = sorted(p for p in cam.iterdir() if p.suffix.lower() in VIDEO_SUFFIXES)
    if videos:
        video = VideoFrames(videos[0])
        times = cam / "frame_times.csv"
        if times.is_file():
            table = read_table(times, 0, [], warnings=warnings, what="frame")
            n = match_frame_count(video, len(table), times, warnings)
            table = table.select(slice(0, n))
        else:
            try:
                start_ns = int(videos[0].stem) * 1_000_000
            except ValueError:
                raise CaptureError("video name is not an epoch-ms timestamp", videos[0]) from None
            fps = video.fps if video.fps > 0 else 30.0
            n = video.frame_count
            t = start_ns + np.round(np.arange(n) * 1e9 / fps).astype(np.int64)
            table = Table(videos[0], None, t, np.zeros((n, 0)), np.arange(1, n + 1))
            warnings.append(
                f"{videos[0]}: no Camera/frame_times.csv; frame times assumed start + n/{fps:g} fps from the name, "
                "which is the session start (often hundreds of ms early): check `vio info` for the time offset"
            )
        ft, idx = frame_times(table, warnings)
        return ft, (lambda i, _v=video, _idx=idx: _v(int(_idx[i])))
    images = sorted((p for p in cam.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png")), key=lambda p: p.stem)
    stamps = []
    for p in images:
        try:
            stamps.append(int(p.stem) * 1_000_000)
        except ValueError:
            raise CaptureError("image name is not an epoch-ms timestamp", p) from None
    order = np.argsort(np.asarray(stamps, np.int64), kind="stable")
    files = [images[i] for i in order]
    t = np.asarray(stamps, np.int64)[order]
    ft, idx = frame_times(Table(cam, None, t, np.zeros((t.size, 0)), np.arange(1, t.size + 1)), warnings)

    def load(i: int) -> np.ndarray:
        p = files[int(idx[i])]
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise CaptureError("image missing or cannot be decoded", p)
        return img

    return ft, load


def read_sensorlogger(folder: Path, calib: str | Path | None = None, problems: list[str] | None = None) -> Capture:
    """Read a Sensor Logger export. With a `problems` list, a stream that cannot be read is left out and its error
    appended there (`vio info`)."""
    folder = Path(folder)
    warnings: list[str] = []
    meta = _metadata(folder)
    ios = meta.get("platform", "").lower() == "ios" and meta.get("standardisation", "false").lower() != "true"

    def imu() -> ImuSeries:
        gyro = _xyz(folder / "Gyroscope.csv", warnings, "gyro")
        return merge_gyro_acc(gyro, _specific_force(folder, ios, warnings), warnings)

    series = collect(imu, None, problems)
    camera = collect(lambda: _camera(folder, warnings), None, problems)
    ft, load = camera if camera else (np.zeros(0, np.int64), no_frames(folder, "this export has no readable camera"))
    cal = collect(lambda: resolve_calibration(folder, calib), None, problems)
    return make_capture(folder, "sensorlogger", cal, series, ft, load, warnings)
