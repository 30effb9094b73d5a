"""Reader throughput: open + decode every frame, per format, against the capture's duration (real-time factor).

Run: .venv/bin/python -m tests.writers.bench [--duration 10] [--repeats 3]
Writes nothing into the repository; prints a markdown table for docs/BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

from tests.writers.phone import write_mars, write_opencamera, write_sensorlogger
from tests.writers.ros import write_ros1, write_ros2
from vio.readers import open_capture


def _time_read(path: Path) -> tuple[float, float, float]:
    """(open CPU s, open + decode-all CPU s, open + decode-all wall s)."""
    t, c = time.perf_counter(), time.process_time()
    cap = open_capture(path)
    c_open = time.process_time() - c
    for i in range(cap.num_frames):
        cap.load_image(i)
    return c_open, time.process_time() - c, time.perf_counter() - t


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--euroc", action="store_true", help="measure the real EuRoC capture instead")
    args = ap.parse_args()
    if args.euroc:
        real_euroc()
        return
    from vio.sim.api import simulate

    with tempfile.TemporaryDirectory() as tmp:
        tmp_path = Path(tmp)
        src = simulate("orbit", tmp_path / "asl", seed=0, duration_s=args.duration, workers=1)
        ref = open_capture(src)
        duration = (max(ref.frame_t_ns[-1], ref.imu.t_ns[-1]) - min(ref.frame_t_ns[0], ref.imu.t_ns[0])) * 1e-9
        (tmp_path / "r1").mkdir()
        paths = {
            "ASL (PNG)": src,
            "ROS 2 bag (sqlite3, raw Image)": write_ros2(ref, tmp_path / "bag2"),
            "ROS 2 bag (mcap, PNG CompressedImage)": write_ros2(ref, tmp_path / "bag2c", compressed=True, mcap=True),
            "ROS 1 bag (raw Image)": write_ros1(ref, tmp_path / "r1" / "c.bag"),
            "MARS (FFV1 lossless video)": write_mars(ref, tmp_path / "mars"),
            "MARS (mp4v lossy video)": write_mars(ref, tmp_path / "mars4", fourcc="mp4v"),
            "OpenCamera Sensors (mp4v)": write_opencamera(ref, tmp_path / "oc", fourcc="mp4v"),
            "Sensor Logger (mp4v)": write_sensorlogger(ref, tmp_path / "sl", fourcc="mp4v"),
        }
        w, h = ref.camera.width, ref.camera.height
        print(f"capture: orbit {duration:.1f} s, {ref.num_frames} frames {w}x{h}, {len(ref.imu)} IMU samples\n")
        print("| format | open, CPU s | open + decode all, CPU s | x real time (CPU) | wall s (loaded machine) |")
        print("|---|---|---|---|---|")
        for name, path in paths.items():
            runs = [_time_read(path) for _ in range(args.repeats)]
            c_open, c_all, wall = (statistics.median(r[k] for r in runs) for k in range(3))
            print(f"| {name} | {c_open:.2f} | {c_all:.2f} | {duration / c_all:.0f} | {wall:.2f} |")


def real_euroc() -> None:
    """Real EuRoC V1_01 (../shared/data): 145.6 s of 200 Hz IMU plus 95 frames 752x480 PNG."""
    from tests.conftest import SHARED_DATA

    path = SHARED_DATA / "euroc_v1_01"
    runs = [_time_read(path) for _ in range(3)]
    c_open, c_all, wall = (statistics.median(r[k] for r in runs) for k in range(3))
    print(
        f"EuRoC V1_01: open (IMU 145.6 s) {c_open:.2f} CPU s = {145.6 / c_open:.0f}x real time; "
        f"+ decode 95 frames (4.7 s) {c_all - c_open:.2f} CPU s = {4.7 / (c_all - c_open):.0f}x; wall {wall:.2f} s"
    )


if __name__ == "__main__":
    main()
