"""Seed captures for the fuzzer, one per supported format, written from one small synthetic recording (a camera
spinning in front of a textured plane: 1.5 s, 10 frames per second, 480x360, IMU at 200 Hz)."""

from __future__ import annotations

from pathlib import Path

from tests.rotation_capture import rotation_capture
from tests.writers.phone import write_mars, write_opencamera, write_sensorlogger
from tests.writers.ros import write_ros1, write_ros2

EQVIO_LINES = 6000  # the first lines of gtsam's eqvio file (about 3 s of IMU and tracks)

# seed name -> path of the capture relative to its folder ("." for the folder itself)
SEEDS = {
    "asl": ".",
    "mars": ".",
    "opencamera": "20240101_120000",
    "sensorlogger": ".",
    "ros1": "capture.bag",
    "ros2": ".",
    "eqvio": "tracks.csv",
}


def write_seeds(root: Path) -> dict[str, Path]:
    """Write every seed capture under `root/<name>/`; returns name -> the path to open."""
    from vio.readers.eqvio import default_eqvio_path
    from vio.writers.asl import AslWriter

    cap = rotation_capture(duration_s=1.5, fps=10.0)
    root.mkdir(parents=True, exist_ok=True)
    with AslWriter(root / "asl") as w:
        w.write_camera(cap.camera)
        w.write_imu(cap.imu_calib, cap.imu)
        for i in range(cap.num_frames):
            w.add_frame(int(cap.frame_t_ns[i]), cap.load_image(i))
    write_mars(cap, root / "mars")
    (root / "opencamera").mkdir()
    write_opencamera(cap, root / "opencamera")
    write_sensorlogger(cap, root / "sensorlogger", camera="images")
    (root / "ros1").mkdir()
    write_ros1(cap, root / "ros1" / "capture.bag")
    write_ros2(cap, root / "ros2")
    (root / "eqvio").mkdir()
    with default_eqvio_path().open(encoding="utf-8") as f:
        head = [next(f) for _ in range(EQVIO_LINES)]
    (root / "eqvio" / "tracks.csv").write_text("".join(head), encoding="utf-8")
    return {name: root / name / rel for name, rel in SEEDS.items()}
