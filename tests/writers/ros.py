"""Write a capture as a ROS 2 bag (sqlite3 or mcap) or a ROS 1 bag with `rosbags` (Image/CompressedImage + Imu)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore

from vio.capture import Capture

from . import write_calib


def _messages(cap: Capture, ts, ros1: bool, compressed: bool):
    T = ts.types
    Time, Header = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"]
    Vec, Quat = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
    Imu, Image, Comp = T["sensor_msgs/msg/Imu"], T["sensor_msgs/msg/Image"], T["sensor_msgs/msg/CompressedImage"]

    def header(t_ns: int, frame: str, seq: int):
        stamp = Time(sec=int(t_ns // 1_000_000_000), nanosec=int(t_ns % 1_000_000_000))
        return Header(seq=seq, stamp=stamp, frame_id=frame) if ros1 else Header(stamp=stamp, frame_id=frame)

    out = []
    zeros9 = np.zeros(9)
    for k, (t, w, a) in enumerate(zip(cap.imu.t_ns, cap.imu.gyro, cap.imu.acc, strict=True)):
        msg = Imu(
            header=header(int(t), "imu", k),
            orientation=Quat(x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=zeros9,
            angular_velocity=Vec(x=float(w[0]), y=float(w[1]), z=float(w[2])),
            angular_velocity_covariance=zeros9,
            linear_acceleration=Vec(x=float(a[0]), y=float(a[1]), z=float(a[2])),
            linear_acceleration_covariance=zeros9,
        )
        out.append((int(t), "/imu0", Imu.__msgtype__, msg))
    for i in range(cap.num_frames):
        t, img = int(cap.frame_t_ns[i]), cap.load_image(i)
        if compressed:
            ok, buf = cv2.imencode(".png", img)
            assert ok
            msg = Comp(header=header(t, "cam0", i), format="mono8; png compressed", data=buf.reshape(-1))
            out.append((t, "/cam0/image_raw/compressed", Comp.__msgtype__, msg))
        else:
            h, w = img.shape
            msg = Image(
                header=header(t, "cam0", i),
                height=h,
                width=w,
                encoding="mono8",
                is_bigendian=0,
                step=w,
                data=np.ascontiguousarray(img).reshape(-1),
            )
            out.append((t, "/cam0/image_raw", Image.__msgtype__, msg))
    out.sort(key=lambda m: m[0])
    return out


def write_ros2(cap: Capture, out: Path, compressed: bool = False, mcap: bool = False) -> Path:
    """A ROS 2 bag folder `out` (with calib.yaml inside); bag time = header stamp."""
    ts = get_typestore(Stores.ROS2_HUMBLE)
    plugin = StoragePlugin.MCAP if mcap else StoragePlugin.SQLITE3
    with Writer2(out, version=9, storage_plugin=plugin) as writer:
        conns = {}
        for t, topic, msgtype, msg in _messages(cap, ts, False, compressed):
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=ts)
            writer.write(conns[topic], t, ts.serialize_cdr(msg, msgtype))
    write_calib(out, cap)
    return out


def write_ros1(cap: Capture, out: Path, compressed: bool = False) -> Path:
    """A ROS 1 bag file `out` (with calib.yaml beside it)."""
    ts = get_typestore(Stores.ROS1_NOETIC)
    with Writer1(out) as writer:
        conns = {}
        for t, topic, msgtype, msg in _messages(cap, ts, True, compressed):
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=ts)
            writer.write(conns[topic], t, ts.serialize_ros1(msg, msgtype))
    write_calib(Path(out).parent, cap)
    return out
