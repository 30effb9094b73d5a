"""The tracker's error by track age on a simulated capture (issue 15): each track's pixels against the true surface
point its first pixel saw.

The frontend (`frontend.tracker.FeatureTracker`, the configuration's `tracker` section) runs on the capture's
images; when a track starts, the renderer's ray caster finds the scene point under its first pixel; every later
pixel of the track is compared with that point's true projection (the scenario's camera pose). The error therefore
holds the start's detection error, the tracker's noise and its drift along the surface; a track on an occluding
edge may follow another surface (the tails). It is what the estimator's pixel noise model has to describe.

`--keyframes` keeps only the views of the keyframes the tracker picks (what the estimator reads; with
`tracker.anchor_keyframes_only` the only aligned ones).

    python -m vio.bench.klt_error CAPTURE [--frames N] [--keyframes] [--set tracker.key=value ...]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from vio.bench.imu_ablation import simulated_scenario
from vio.capture import Capture
from vio.config import Config
from vio.records import Frame

AGE_BINS = ((1, 2), (3, 5), (6, 10), (11, 20), (21, 30), (31, 50), (51, 80), (81, 150), (151, 100000))


def track_errors(cap: Capture, cfg: Config, frames: int | None = None, keyframes: bool = False) -> np.ndarray:
    """(N, 2) rows of (age in frames, pixel error) for every observation after a track's first (see the docstring),
    or with `keyframes` for those in keyframes only."""
    from frontend.tracker import FeatureTracker
    from vio.sim.render import Renderer, camera_poses

    sc = simulated_scenario(Path(cap.root))
    cam = cap.camera
    renderer = Renderer(sc.scene, cam)
    n = cap.num_frames if frames is None else min(frames, cap.num_frames)
    poses = camera_poses(sc, np.asarray(cap.frame_t_ns[:n], np.int64), cam)
    tracker = FeatureTracker(cam, cfg.tracker, cfg.keyframes)
    first: dict[int, tuple[int, np.ndarray]] = {}  # track id -> (frame, world point)
    rows = []
    for i in range(n):
        tracks = tracker.track(Frame(int(cap.frame_t_ns[i]), 0, cap.load_image(i)))
        ids = [int(j) for j in tracks.ids]
        new = [k for k, j in enumerate(ids) if j not in first]
        if new:
            X, _ = renderer.surface_points(poses[i], tracks.uv[new])
            for k, x in zip(new, X, strict=True):
                first[ids[k]] = (i, x)
        old = [k for k, j in enumerate(ids) if first[j][0] < i and (tracker.keyframe or not keyframes)]
        if not old:
            continue
        X = np.array([first[ids[k]][1] for k in old])
        age = np.array([i - first[ids[k]][0] for k in old])
        R, o = poses[i][:3, :3], poses[i][:3, 3]
        err = np.linalg.norm(cam.project((X - o) @ R) - tracks.uv[old], axis=1)
        rows.append(np.column_stack([age, err]))
    return np.vstack(rows) if rows else np.zeros((0, 2))


def by_age(errors: np.ndarray) -> list[tuple[int, int, int, float, float, float]]:
    """(age from, to, count, median, 90th percentile, rms) per age bin with observations."""
    out = []
    for lo, hi in AGE_BINS:
        e = errors[(errors[:, 0] >= lo) & (errors[:, 0] <= hi), 1]
        if e.size:
            out.append((lo, hi, int(e.size), float(np.median(e)), float(np.percentile(e, 90)),
                        float(np.sqrt(np.mean(e**2)))))  # fmt: skip
    return out


def main(argv: list[str] | None = None) -> int:
    from vio.config import load_config
    from vio.errors import VioError
    from vio.readers import open_capture

    ap = argparse.ArgumentParser(prog="python -m vio.bench.klt_error", description=__doc__.splitlines()[0])
    ap.add_argument("capture", help="a built-in simulated capture with images")
    ap.add_argument("--frames", type=int, default=None, help="only the first N frames")
    ap.add_argument("--keyframes", action="store_true", help="only the views in keyframes")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE", help="tracker override")
    args = ap.parse_args(argv)
    try:
        cap = open_capture(args.capture)
        errors = track_errors(cap, load_config(None, args.set), args.frames, args.keyframes)
    except VioError as exc:
        print(f"klt_error: {exc}")
        return 2
    print("age (frames) | observations | median px | 90th percentile px | rms px")
    for lo, hi, count, med, p90, rms in by_age(errors):
        print(f"{lo}-{hi} | {count} | {med:.3f} | {p90:.3f} | {rms:.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
