"""`vio track`: run the feature tracker through a capture and write `t_ns,track_id,u,v` (distorted pixels).

The CSV has one header line `t_ns,track_id,u,v` and one row per track per frame, frames in time order; `u, v`
are pixel coordinates in the distorted image (x right, y down), written with 4 decimals. The file is written
atomically: a failed run leaves no partial CSV.
"""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

from vio.atomic import atomic_open
from vio.config import Config
from vio.records import Frame

log = logging.getLogger(__name__)

CSV_HEADER = "t_ns,track_id,u,v"


def track_capture(
    capture_path: str | os.PathLike[str],
    out_csv: str | os.PathLike[str],
    cfg: Config,
    calib: str | os.PathLike[str] | None = None,
) -> dict:
    """Track every frame of a capture; write the tracks CSV; return a summary.

    The capture is opened by `vio.readers.open_capture` (format detected, `calib` as in `vio run --calib`) with the
    camera's checks only (frames, calibration, image size): tracking needs no IMU.

    Summary keys: `frames`, `rows` (observations written), `tracks` (distinct ids), `mean_tracks_per_frame`,
    `min_tracks_per_frame`, `wall_s`, `fps`, `realtime_factor` (capture duration / wall time; 0 for one frame),
    `timings_s` (wall time per section: open (reading the capture's index, calibration, IMU), decode (images),
    klt, fb_check, ncc, ransac, anchor, detect, write), `stats` (tracker counters, with the anchor's aligned and
    re-anchored views).
    """
    from frontend.tracker import FeatureTracker
    from vio.readers import open_capture

    t_start = time.perf_counter()
    capture = open_capture(capture_path, calib, needs=("camera",))
    assert capture.camera is not None  # checked by open_capture
    tracker = FeatureTracker(capture.camera, cfg.tracker, cfg.keyframes)  # its keyframes as `vio run` picks them
    open_s = time.perf_counter() - t_start
    decode_s = write_s = 0.0
    rows = 0
    counts: list[int] = []
    max_id = -1
    out_csv = Path(out_csv)
    with atomic_open(out_csv, "w", encoding="utf-8", newline="\n") as f:
        f.write(CSV_HEADER + "\n")
        for i in range(capture.num_frames):
            t0 = time.perf_counter()
            frame = Frame(int(capture.frame_t_ns[i]), 0, capture.load_image(i))
            t1 = time.perf_counter()
            tracks = tracker.track(frame)
            t2 = time.perf_counter()
            t_ns = int(tracks.t_ns)
            f.write(
                "".join(
                    f"{t_ns},{int(j)},{u:.4f},{v:.4f}\n"
                    for j, (u, v) in zip(tracks.ids, tracks.uv.tolist(), strict=True)
                )
            )
            decode_s += t1 - t0
            write_s += time.perf_counter() - t2
            rows += tracks.ids.size
            counts.append(int(tracks.ids.size))
            if tracks.ids.size:
                max_id = max(max_id, int(tracks.ids.max()))
    wall_s = time.perf_counter() - t_start
    span_s = float(capture.frame_t_ns[-1] - capture.frame_t_ns[0]) * 1e-9
    duration_s = span_s * capture.num_frames / (capture.num_frames - 1) if capture.num_frames > 1 else 0.0
    timings = {"open": open_s, "decode": decode_s, **tracker.timings_s, "write": write_s}
    summary = {
        "frames": capture.num_frames,
        "rows": rows,
        "tracks": max_id + 1,
        "mean_tracks_per_frame": rows / capture.num_frames,
        "min_tracks_per_frame": min(counts),
        "wall_s": wall_s,
        "fps": capture.num_frames / wall_s if wall_s > 0 else 0.0,
        "realtime_factor": duration_s / wall_s if wall_s > 0 else 0.0,
        "timings_s": timings,
        "stats": dict(tracker.stats) | (tracker.anchor_stats() or {}),
    }
    log.info(
        "tracked %d frames at %.1f fps (%.1fx real time), %.1f tracks per frame -> %s; ms per frame: %s",
        summary["frames"],
        summary["fps"],
        summary["realtime_factor"],
        summary["mean_tracks_per_frame"],
        out_csv,
        ", ".join(f"{k} {1000 * v / summary['frames']:.2f}" for k, v in timings.items()),
    )
    return summary
