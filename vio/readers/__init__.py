"""Capture readers: one entry point, `open_capture`, that detects the format and returns a validated Capture.

Formats (see docs/capture_formats.md): ASL/EuRoC and TUM-VI folders, ROS 1 bags, ROS 2 bags, MARS logger folders,
OpenCamera Sensors folders, Sensor Logger exports, and gtsam's eqvio CSV (precomputed feature tracks).
Format modules are imported lazily, so that opening one format does not import the others' dependencies.
"""

from __future__ import annotations

import os
from collections.abc import Collection
from pathlib import Path

from vio.capture import Capture
from vio.errors import CaptureError

FORMATS = ("asl", "tumvi", "ros1", "ros2", "mars", "opencamera", "sensorlogger", "eqvio")


def detect_format(path: Path) -> str:
    """The format of a capture path, from the files present (CaptureError when it cannot be told)."""
    path = Path(path)
    if not path.exists():
        raise CaptureError("capture not found", path)
    if path.is_file():
        suffix = path.suffix.lower()
        if suffix == ".bag":
            return "ros1"
        if suffix in (".db3", ".mcap") or path.name == "metadata.yaml":
            return "ros2"
        if suffix == ".csv":
            from vio.readers.eqvio import is_eqvio_file

            if is_eqvio_file(path):
                return "eqvio"
        if suffix == ".zip":
            raise CaptureError("a zip archive: unzip it first and pass the folder", path)
        raise CaptureError("not a capture file (expected a folder, a .bag, a ROS 2 bag folder or an eqvio CSV)", path)
    try:
        names = set(os.listdir(path))
    except PermissionError:
        raise CaptureError("folder cannot be read (permission denied)", path) from None
    if not names:
        raise CaptureError("capture folder is empty", path)
    if "mav0" in names or "cam0" in names or "imu0" in names:
        return "asl"
    if "metadata.yaml" in names and any(n.endswith((".db3", ".mcap")) for n in names):
        return "ros2"
    if "gyro_accel.csv" in names:
        return "mars"
    if any(n.endswith("_gyro.csv") for n in names):
        return "opencamera"
    if "Gyroscope.csv" in names:
        return "sensorlogger"
    bags = sorted(n for n in names if n.endswith(".bag"))
    if len(bags) == 1:
        return "ros1"
    raise CaptureError(
        "capture format not recognised (looked for mav0/, a ROS bag, gyro_accel.csv (MARS), *_gyro.csv "
        "(OpenCamera Sensors), Gyroscope.csv (Sensor Logger))",
        path,
    )


def read_capture(
    path: str | os.PathLike[str],
    calib: str | os.PathLike[str] | None = None,
    problems: list[str] | None = None,
    **topics: str,
) -> Capture:
    """Read a capture in any supported format without the final checks (see `open_capture`). With a `problems`
    list, a stream that cannot be read is left out and its error appended there (eqvio files: the first problem of
    each row type); a capture that cannot be read at all (not a bag, not an eqvio header) still raises."""
    path = Path(path)
    fmt = detect_format(path)
    if fmt in ("asl", "tumvi"):
        from vio.readers.asl import open_asl

        return open_asl(path, calib, problems)
    if fmt in ("ros1", "ros2"):
        from vio.readers.rosbag import read_bag

        if path.is_dir() and fmt == "ros1":
            path = path / sorted(n for n in os.listdir(path) if n.endswith(".bag"))[0]
        if path.is_file() and fmt == "ros2":
            path = path.parent
        return read_bag(path, calib, topics.get("image_topic"), topics.get("imu_topic"), problems)
    if fmt == "mars":
        from vio.readers.mars import read_mars

        return read_mars(path, calib, problems)
    if fmt == "opencamera":
        from vio.readers.opencamera import read_opencamera

        return read_opencamera(path, calib, problems)
    if fmt == "sensorlogger":
        from vio.readers.sensorlogger import read_sensorlogger

        return read_sensorlogger(path, calib, problems)
    from vio.readers.eqvio import read_eqvio

    return read_eqvio(path, problems)


def open_capture(
    path: str | os.PathLike[str],
    calib: str | os.PathLike[str] | None = None,
    *,
    strict: bool = True,
    needs: Collection[str] = ("camera", "imu"),
    image_topic: str | None = None,
    imu_topic: str | None = None,
) -> Capture:
    """Open a capture (format detected), apply `calib` (Kalibr camchain YAML or ASL folder), and validate it.

    Problems that make an estimate meaningless raise CaptureError/CalibrationError with one line naming the file,
    row and problem (with `strict=False` they are returned as warnings instead); safe ones go to `Capture.warnings`.
    `needs` names the streams the caller uses ("camera", "imu"): the checks of a stream it does not need are skipped
    (`vio track` needs the camera only, the IMU-only baseline the IMU only, scoring against ground truth neither).
    """
    from vio.readers.common import unreadable
    from vio.readers.validate import finish_capture

    topics = {k: v for k, v in (("image_topic", image_topic), ("imu_topic", imu_topic)) if v}
    problems: list[str] | None = None if strict else []
    try:
        cap = read_capture(path, calib, problems, **topics)
    except OSError as exc:  # e.g. a symbolic link loop, a file that cannot be read: one line naming it
        raise unreadable(exc, path) from None
    for msg in [*(problems or []), *finish_capture(cap, Path(path), strict=strict, needs=needs)]:
        cap.warn(msg)
    cal = None if calib is None else os.fspath(calib)
    cap.reopen = (os.fspath(path), cal, {"strict": strict, "needs": tuple(needs), **topics})
    return cap


__all__ = ["FORMATS", "detect_format", "open_capture", "read_capture"]
