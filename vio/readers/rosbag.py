"""ROS 1 (`.bag`) and ROS 2 (folder with `metadata.yaml` and `.db3`/`.mcap`) bags through the `rosbags` library.

Topics are found by message type: `sensor_msgs/msg/Imu` for the IMU and `sensor_msgs/msg/Image` or
`sensor_msgs/msg/CompressedImage` for the camera. With several candidates the one with the most messages is used
(ties: the first by name) and a warning names the others; `image_topic=`/`imu_topic=` choose explicitly.
Times are the message header stamps (sensor time), not the bag's receive times. Images are decoded lazily: the
first pass keeps only the stamps, and frames are re-read from the bag on demand (sequential access streams).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from vio.capture import Capture
from vio.errors import CaptureError
from vio.readers.common import collect, frame_times, imu_from_table, make_capture, resolve_calibration
from vio.readers.tables import Table
from vio.records import ImuSeries

log = logging.getLogger(__name__)

IMU_TYPE = "sensor_msgs/msg/Imu"
IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")


def _reader(path: Path) -> Any:
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    try:
        reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except Exception as exc:  # rosbags raises several unrelated types for unreadable bags
        first = (str(exc).strip().splitlines() or [""])[0]
        raise CaptureError(f"cannot read the bag ({exc.__class__.__name__}: {first[:120]})", path) from None
    return reader


def _stamp_ns(msg: Any) -> int:
    st = msg.header.stamp
    return int(st.sec) * 1_000_000_000 + int(st.nanosec)


def _pick(reader: Any, types: tuple[str, ...], name: str | None, what: str, path: Path, warnings: list[str]) -> Any:
    conns = [c for c in reader.connections if c.msgtype in types]
    if name is not None:
        conns = [c for c in conns if c.topic == name]
        if not conns:
            raise CaptureError(f"no {what} topic named {name!r}", path)
    if not conns:
        return None
    counts: dict[str, int] = {}
    for c in conns:
        counts[c.topic] = counts.get(c.topic, 0) + c.msgcount
    best = sorted(counts, key=lambda t: (-counts[t], t))[0]
    if len(counts) > 1:
        others = ", ".join(t for t in sorted(counts) if t != best)
        warnings.append(f"{path}: several {what} topics; using {best} (others: {others})")
    return [c for c in conns if c.topic == best]


def decode_image(msg: Any, msgtype: str, where: str) -> np.ndarray:
    """(H, W) uint8 grayscale from a sensor_msgs Image or CompressedImage."""
    if msgtype.endswith("CompressedImage"):
        img = cv2.imdecode(np.asarray(msg.data, np.uint8), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise CaptureError("compressed image cannot be decoded", where)
        return img
    h, w, step, enc = int(msg.height), int(msg.width), int(msg.step), str(msg.encoding).lower()
    data = np.asarray(msg.data, np.uint8)
    if data.size < h * step or h <= 0 or w <= 0:
        raise CaptureError(f"image data truncated ({data.size} bytes for {w}x{h}, step {step})", where)
    rows = data[: h * step].reshape(h, step)
    if enc in ("mono8", "8uc1"):
        return rows[:, :w].copy()
    if enc in ("mono16", "16uc1"):
        dt = ">u2" if msg.is_bigendian else "<u2"
        return (rows[:, : 2 * w].copy().view(dt) >> 8).astype(np.uint8)
    chans = {"bgr8": 3, "rgb8": 3, "bgra8": 4, "rgba8": 4, "8uc3": 3}.get(enc)
    if chans is None:
        raise CaptureError(f"image encoding {enc!r} is not supported (mono8/16, bgr8, rgb8, bgra8, rgba8)", where)
    img = rows[:, : chans * w].reshape(h, w, chans)
    code = {
        ("bgr8", 3): cv2.COLOR_BGR2GRAY,
        ("8uc3", 3): cv2.COLOR_BGR2GRAY,
        ("rgb8", 3): cv2.COLOR_RGB2GRAY,
        ("bgra8", 4): cv2.COLOR_BGRA2GRAY,
        ("rgba8", 4): cv2.COLOR_RGBA2GRAY,
    }[(enc, chans)]
    return cv2.cvtColor(img, code)


class _BagFrames:
    """Frame loader that streams image messages from an open bag (restarts at the requested bag time on a jump)."""

    def __init__(self, reader: Any, conns: list[Any], bag_t_ns: np.ndarray, path: Path) -> None:
        self.reader, self.conns, self.bag_t_ns, self.path = reader, conns, bag_t_ns, path
        self._it: Any = None
        self._next = -1

    def __call__(self, i: int) -> np.ndarray:
        if self._it is None or i != self._next:
            self._it = self.reader.messages(connections=self.conns, start=int(self.bag_t_ns[i]))
            self._next = i
            self._skip = int(np.sum(self.bag_t_ns[:i] == self.bag_t_ns[i]))
        try:
            while True:
                conn, _, raw = next(self._it)
                if self._skip:
                    self._skip -= 1
                    continue
                break
        except StopIteration:
            raise CaptureError(f"image message {i} missing from the bag", self.path) from None
        self._next = i + 1
        msg = self.reader.deserialize(raw, conn.msgtype)
        return decode_image(msg, conn.msgtype, f"{self.path} (topic {conn.topic}, image {i})")


def _read_imu(reader: Any, conns: list[Any], path: Path, warnings: list[str]) -> ImuSeries:
    """The IMU messages of `conns` as an ImuSeries (header stamps; messages with NaN/inf dropped with a warning)."""
    t, vals = [], []
    try:
        for conn, _, raw in reader.messages(connections=conns):
            m = reader.deserialize(raw, conn.msgtype)
            w, a = m.angular_velocity, m.linear_acceleration
            t.append(_stamp_ns(m))
            vals.append((w.x, w.y, w.z, a.x, a.y, a.z))
    except Exception as exc:
        raise CaptureError(f"IMU message cannot be decoded ({exc.__class__.__name__})", path) from None
    v = np.asarray(vals, float).reshape(-1, 6)
    rows = np.arange(1, len(t) + 1)
    good = np.isfinite(v).all(axis=1)
    if not good.all():
        warnings.append(f"{path}: {int((~good).sum())} IMU message(s) with NaN/inf dropped (topic {conns[0].topic})")
    return imu_from_table(Table(path, None, np.asarray(t, np.int64)[good], v[good], rows[good]), warnings)


def _image_times(reader: Any, conns: list[Any], path: Path, warnings: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """(frame times ns, bag receive times ns of those frames) of the image messages of `conns`."""
    stamps: list[int] = []
    bag_times: list[int] = []
    try:
        for conn, bag_t, raw in reader.messages(connections=conns):
            m = reader.deserialize(raw, conn.msgtype)
            stamps.append(_stamp_ns(m))
            bag_times.append(bag_t)
    except Exception as exc:
        raise CaptureError(f"image message cannot be decoded ({exc.__class__.__name__})", path) from None
    st = np.asarray(stamps, np.int64)
    bt = np.asarray(bag_times, np.int64)
    if st.size and not st.any():
        warnings.append(f"{path}: image header stamps are all zero; using the bag's receive times")
        st = bt.copy()
    ft, idx = frame_times(Table(path, None, st, np.zeros((st.size, 0)), np.arange(1, st.size + 1)), warnings)
    return ft, bt[idx]


def read_bag(
    path: Path,
    calib: str | Path | None = None,
    image_topic: str | None = None,
    imu_topic: str | None = None,
    problems: list[str] | None = None,
) -> Capture:
    """Read a ROS 1 `.bag` file or a ROS 2 bag folder. With a `problems` list (`vio info`), a stream that cannot
    be read (a topic not there, messages that do not decode, bad stamps, the calibration) is left out and its
    error appended there; a bag that cannot be opened raises."""
    path = Path(path)
    warnings: list[str] = []
    reader = _reader(path)
    imu_conns = collect(lambda: _pick(reader, (IMU_TYPE,), imu_topic, "IMU", path, warnings), None, problems)
    img_conns = collect(lambda: _pick(reader, IMAGE_TYPES, image_topic, "image", path, warnings), None, problems)
    imu = collect(lambda: _read_imu(reader, imu_conns, path, warnings), None, problems) if imu_conns else None
    no_frames = (np.zeros(0, np.int64), np.zeros(0, np.int64))
    ft, bt = (
        collect(lambda: _image_times(reader, img_conns, path, warnings), no_frames, problems)
        if img_conns
        else no_frames
    )
    loader = _BagFrames(reader, img_conns or [], bt, path)
    cal = collect(lambda: resolve_calibration(path if path.is_dir() else path.parent, calib), None, problems)
    fmt = "ros2" if path.is_dir() else "ros1"
    return make_capture(path, fmt, cal, imu, ft, loader, warnings)
