"""Writes a capture in the Android MARS logger layout, with H.264 video as the phone records it (through PyAV).

```
<out>/movie.mp4             H.264 (libx264, yuv420p), frames in the sensor's orientation; a portrait recording
                            carries the display rotation (+90 deg) in the MP4 display matrix, as phones store it
<out>/frame_timestamps.txt  one camera-clock timestamp, ns, per frame
<out>/gyro_accel.csv        Timestamp[nanosec],gx[rad/s],gy,gz,ax[m/s^2],ay,az,Unix time[nanosec]
<out>/movie_metadata.csv    MARS's per-frame camera metadata, with the exposure and the rolling-shutter readout
<out>/calib.yaml, imu.yaml  the calibration (Kalibr camchain and IMU noise), which MARS users add themselves
<out>/scene/                a simulated capture's ground truth (`scene/` of the ASL capture plus groundtruth.csv)
```
The folder is built under a temporary name and renamed into place, so a failed write never appears complete.
"""

from __future__ import annotations

import fractions
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
import yaml

from vio.atomic import write_text
from vio.capture import Capture
from vio.errors import CaptureError, SimulationError
from vio.kalibr import camchain_yaml_text, kalibr_imu_yaml_text

UNIX_OFFSET_NS = 1_600_000_000_000_000_000  # a fixed sensor-clock to Unix-time offset for the last column
METADATA_HEADER = (
    "Timestamp[nanosec],fx[px],fy[px],Frame No.,Exposure time[nanosec],Sensor frame duration[nanosec],"
    "Frame readout time[nanosec],ISO,Focal length,Focus distance,AF mode"
)
IMU_HEADER = "Timestamp[nanosec],gx[rad/s],gy[rad/s],gz[rad/s],ax[m/s^2],ay[m/s^2],az[m/s^2],Unix time[nanosec]"
FOCAL_LENGTH_MM = 4.38  # nominal phone lens (not used by any reader)
DEFAULT_CRF = 20  # x264 constant-rate factor: a phone's video quality at this size (0 lossless, 51 worst)


def write_mars_from_asl(
    asl: str | os.PathLike[str], out: str | os.PathLike[str], overwrite: bool = False, crf: int = DEFAULT_CRF
) -> Path:
    """Write the ASL capture `asl` (e.g. written by `vio simulate`) as a MARS folder `out`; returns `out`.

    The camera timing (readout, exposure) and the portrait flag come from the capture's `scene/scene.yaml` when it
    has a `camera:` section (`vio simulate --camera phone`), else a global-shutter landscape camera is described.
    """
    from vio.readers import read_capture

    cap = read_capture(asl)
    if cap.camera is None or cap.imu is None or cap.num_frames == 0:
        raise CaptureError("needs a camera calibration, an IMU stream and frames to write a MARS folder", asl)
    scene = Path(asl) / "scene"
    camera_meta = _camera_meta(scene / "scene.yaml")
    gains = _gains(scene / "camera_frames.csv", cap.num_frames)
    out = Path(out)
    if out.exists() and not overwrite and any(out.iterdir()):
        raise CaptureError("output folder exists and is not empty (use --force to replace it)", out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        write_h264(tmp / "movie.mp4", cap, portrait=bool(camera_meta.get("portrait", False)), crf=crf)
        write_text(tmp / "frame_timestamps.txt", "".join(f"{int(t)}\n" for t in cap.frame_t_ns))
        write_text(tmp / "gyro_accel.csv", _imu_text(cap))
        write_text(tmp / "movie_metadata.csv", _metadata_text(cap, camera_meta, gains))
        write_text(tmp / "calib.yaml", camchain_yaml_text(cap.camera, comment="vio simulator: MARS calibration"))
        if cap.imu_calib is not None:
            write_text(tmp / "imu.yaml", kalibr_imu_yaml_text(cap.imu_calib))
        if scene.is_dir():
            shutil.copytree(scene, tmp / "scene")
            gt = Path(asl) / "mav0" / "state_groundtruth_estimate0" / "data.csv"
            if gt.is_file():
                shutil.copy2(gt, tmp / "scene" / "groundtruth.csv")
        if out.exists():
            shutil.rmtree(out)
        os.replace(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out


def write_h264(path: Path, cap: Capture, portrait: bool = False, crf: int = DEFAULT_CRF) -> None:
    """H.264 video of the capture's frames (grayscale, coded as yuv420p), presentation times from the frame times
    (microseconds), written atomically. `portrait` stores a +90 deg display rotation (the pixels are not turned)."""
    try:
        import av
    except ImportError:
        raise SimulationError("writing H.264 needs PyAV: pip install 'vio[video]' (optional: GPL codecs)") from None

    t0 = int(cap.frame_t_ns[0])
    tmp = path.with_name(f".{path.name}.tmp")
    with av.open(str(tmp), "w", format="mp4") as container:
        rate = fractions.Fraction(round(cap.camera.rate_hz or 30.0)).limit_denominator(1000)
        stream = container.add_stream("libx264", rate=rate)
        stream.width, stream.height, stream.pix_fmt = cap.camera.width, cap.camera.height, "yuv420p"
        stream.options = {"crf": str(int(crf)), "preset": "veryfast"}
        if portrait:
            stream.set_display_rotation(90)
        for i in range(cap.num_frames):
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(cap.load_image(i)), format="gray")
            frame.pts = (int(cap.frame_t_ns[i]) - t0) // 1000
            frame.time_base = fractions.Fraction(1, 1_000_000)
            for packet in stream.encode(frame):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    os.replace(tmp, path)


def _camera_meta(scene_yaml: Path) -> dict:
    if not scene_yaml.is_file():
        return {}
    meta = yaml.safe_load(scene_yaml.read_text()) or {}
    return meta.get("camera") or {}


def _gains(frames_csv: Path, n: int) -> np.ndarray:
    """Per-frame auto-exposure gains of a simulated phone capture (1 without `scene/camera_frames.csv`)."""
    if not frames_csv.is_file():
        return np.ones(n)
    rows = [line.split(",") for line in frames_csv.read_text().splitlines() if line and not line.startswith("#")]
    gains = np.array([float(r[2]) for r in rows])
    return gains if len(gains) == n else np.ones(n)


def _imu_text(cap: Capture) -> str:
    lines = [IMU_HEADER]
    for t, w, a in zip(cap.imu.t_ns, cap.imu.gyro, cap.imu.acc, strict=True):
        vals = ",".join(f"{x:.9g}" for x in (*w, *a))
        lines.append(f"{int(t)},{vals},{int(t) + UNIX_OFFSET_NS}")
    return "\n".join(lines) + "\n"


def _metadata_text(cap: Capture, camera_meta: dict, gains: np.ndarray) -> str:
    exposure_ns = int(round(float(camera_meta.get("exposure_s", 0.0)) * 1e9))
    readout_ns = int(round(float(camera_meta.get("readout_s", 0.0)) * 1e9))
    period_ns = int(round(1e9 / (cap.camera.rate_hz or 30.0)))
    lines = [METADATA_HEADER]
    for i, t in enumerate(cap.frame_t_ns):
        iso = int(round(100 * gains[i]))
        lines.append(
            f"{int(t)},{cap.camera.fx:.6f},{cap.camera.fy:.6f},{i},{exposure_ns},{period_ns},{readout_ns},{iso},"
            f"{FOCAL_LENGTH_MM},0.0,0"
        )
    return "\n".join(lines) + "\n"
