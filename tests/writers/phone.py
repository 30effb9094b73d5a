"""Write a capture as the phone apps do: MARS logger, OpenCamera Sensors, Sensor Logger (Android or iOS)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from vio.capture import Capture

from . import fmt_row, write_calib, write_video

STANDARD_G = 9.80665


def _seconds(t_ns: int) -> str:
    return f"{t_ns // 1_000_000_000}.{t_ns % 1_000_000_000:09d}"


def write_mars(cap: Capture, out: Path, fourcc: str = "FFV1", platform: str = "Android") -> Path:
    """MARS logger folder: movie.mp4 (lossless FFV1 here; H.264 on the phone) and gyro_accel.csv.

    Android: frame_timestamps.txt (ns) and ns IMU times; iOS: frame times in movie_metadata.csv and every time in
    seconds (`[sec]` headers, 9 decimals).
    """
    out.mkdir(parents=True)
    write_video(out / "movie.mp4", cap, fourcc=fourcc)
    ios = platform.lower() == "ios"
    if ios:
        rows = [
            f"{_seconds(int(t))},{cap.camera.fx!r},{cap.camera.fy!r},{cap.camera.width},{cap.camera.height},0.01"
            for t in cap.frame_t_ns
        ]
        header = "Timestamp[sec],fx[px],fy[px],Frame W[px],Frame H[px],Exposure duration[sec]"
        (out / "movie_metadata.csv").write_text("\n".join([header, *rows]) + "\n")
        lines = ["Timestamp[sec],gx[rad/s],gy[rad/s],gz[rad/s],ax[m/s^2],ay[m/s^2],az[m/s^2]"]
        for t, w, a in zip(cap.imu.t_ns, cap.imu.gyro, cap.imu.acc, strict=True):
            lines.append(f"{_seconds(int(t))},{fmt_row(w)},{fmt_row(a)}")
    else:
        (out / "frame_timestamps.txt").write_text("".join(f"{int(t)}\n" for t in cap.frame_t_ns))
        lines = ["Timestamp[nanosec],gx[rad/s],gy[rad/s],gz[rad/s],ax[m/s^2],ay[m/s^2],az[m/s^2],Unix time[nanosec]"]
        for t, w, a in zip(cap.imu.t_ns, cap.imu.gyro, cap.imu.acc, strict=True):
            lines.append(f"{int(t)},{fmt_row(w)},{fmt_row(a)},{int(t) + 1_600_000_000_000_000_000}")
    (out / "gyro_accel.csv").write_text("\n".join(lines) + "\n")
    write_calib(out, cap)
    return out


def write_opencamera(cap: Capture, out: Path, name: str = "VID_20240101_120000", fourcc: str = "FFV1") -> Path:
    """OpenCamera Sensors: video in `out`, CSVs (x,y,z,t_ns, no header) in `out/<date>/`; returns the CSV folder."""
    csv_dir = out / name[4:]
    csv_dir.mkdir(parents=True)
    write_video(out / f"{name}.mp4", cap, fourcc=fourcc)
    g = "".join(f"{fmt_row(w)},{int(t)}\n" for t, w in zip(cap.imu.t_ns, cap.imu.gyro, strict=True))
    a = "".join(f"{fmt_row(v)},{int(t)}\n" for t, v in zip(cap.imu.t_ns, cap.imu.acc, strict=True))
    (csv_dir / f"{name}_gyro.csv").write_text(g)
    (csv_dir / f"{name}_accel.csv").write_text(a)
    (csv_dir / f"{name}_timestamps.csv").write_text("".join(f"{int(t)}\n" for t in cap.frame_t_ns))
    write_calib(csv_dir, cap)
    return csv_dir


def _xyz_csv(path: Path, t_ns: np.ndarray, xyz: np.ndarray) -> None:
    t0 = int(t_ns[0])
    lines = ["time,seconds_elapsed,z,y,x"]
    for t, v in zip(t_ns, xyz, strict=True):
        lines.append(f"{int(t)},{(int(t) - t0) * 1e-9!r},{float(v[2])!r},{float(v[1])!r},{float(v[0])!r}")
    path.write_text("\n".join(lines) + "\n")


def write_sensorlogger(
    cap: Capture,
    out: Path,
    platform: str = "Android",
    camera: str = "video",
    total: bool | None = None,
    fourcc: str = "FFV1",
) -> Path:
    """Sensor Logger export. Android: TotalAcceleration.csv (unless total=False) plus Accelerometer.csv (user
    acceleration) and Gravity.csv; iOS: Accelerometer.csv + Gravity.csv in CoreMotion's sign convention.

    The gravity split uses the low-passed specific force as "gravity", so user + gravity = specific force exactly.
    Camera: "video" (Camera/<ms>.mp4 + Camera/frame_times.csv), "video-noframes" (no frame_times.csv),
    "images" (Camera/<ms>.png, millisecond file names), or "none".
    """
    out.mkdir(parents=True)
    ios = platform.lower() == "ios"
    t, acc = cap.imu.t_ns, cap.imu.acc
    n = 25
    kernel = np.ones(n) / n
    grav = np.column_stack([np.convolve(acc[:, k], kernel, mode="same") for k in range(3)])
    user = acc - grav
    sign = -1.0 if ios else 1.0
    _xyz_csv(out / "Gyroscope.csv", t, cap.imu.gyro)
    _xyz_csv(out / "Accelerometer.csv", t, sign * user)
    _xyz_csv(out / "Gravity.csv", t, sign * grav)
    if total if total is not None else not ios:
        _xyz_csv(out / "TotalAcceleration.csv", t, acc)
    (out / "Metadata.csv").write_text(f"version,device name,recording time,platform\n3,test,2024-01-01,{platform}\n")
    cam = out / "Camera"
    if camera.startswith("video"):
        cam.mkdir()
        write_video(cam / f"{int(cap.frame_t_ns[0]) // 1_000_000}.mp4", cap, fourcc=fourcc)
        if camera == "video":
            (cam / "frame_times.csv").write_text("".join(f"{int(x)}\n" for x in cap.frame_t_ns))
    elif camera == "images":
        cam.mkdir()
        for i in range(cap.num_frames):
            cv2.imwrite(str(cam / f"{int(cap.frame_t_ns[i]) // 1_000_000}.png"), cap.load_image(i))
    if cap.camera is not None:
        write_calib(out, cap)
    return out
