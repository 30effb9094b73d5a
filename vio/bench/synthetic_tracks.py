"""A simulated capture's estimate with true feature tracks (issue 15): the KLT tracker replaced by the true
projections of scene points, with white pixel noise of a chosen sigma.

The scene is the capture's own (rebuilt from scene/scene.yaml): each new track starts at a random pixel and follows
the surface point that pixel sees (the renderer's ray caster); it lives for a geometric number of frames (mean
`lifetime` frames, as KLT tracks end) and ends earlier when the point leaves the image or is hidden (the ray from the
camera hits another surface first). Every frame holds `features` tracks when the view allows. The observations are
the true distorted projections plus N(0, noise_px^2) per axis, independent between observations: white noise with
a known sigma, which the estimator's noise model can match (`--set estimator.pixel_sigma=...`), unlike KLT's
drift. Same images, IMU and ground truth as the capture; only the tracks differ.

    python -m vio.bench.synthetic_tracks CAPTURE OUT --noise-px 0.2 [--features 150] [--lifetime 25] [--seed 0]
        [--set section.key=value ...]
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np

from vio.bench.imu_ablation import simulated_scenario
from vio.capture import Capture
from vio.errors import VioError
from vio.records import FeatureTracks

_BORDER_PX = 3.0  # a track ends this close to the image border
_HIDDEN_M = 1e-3  # a point is hidden when the surface along its ray is this much nearer (plus 0.1 % of the range)


def true_tracks(
    cap: Capture, noise_px: float, features: int = 150, lifetime: float = 25.0, seed: int = 0
) -> tuple[list[FeatureTracks], np.ndarray]:
    """Tracks of true scene points for every frame of the simulated capture `cap` (see the module docstring), and
    the world point (m) of each track id: (tracks, points (num_tracks, 3))."""
    from vio.sim.render import Renderer, camera_poses

    if cap.camera is None:
        raise VioError(f"{cap.root}: the capture has no camera calibration")
    if noise_px < 0 or features < 1 or lifetime < 1:
        raise VioError("noise must be >= 0 px, features >= 1 and the lifetime >= 1 frame")
    sc = simulated_scenario(Path(cap.root))
    cam = cap.camera
    renderer = Renderer(sc.scene, cam)
    poses = camera_poses(sc, np.asarray(cap.frame_t_ns, np.int64), cam)
    rng = np.random.default_rng(seed)
    points = np.zeros((0, 3))  # track id -> world point
    life = np.zeros(0, np.int64)  # frames left
    active = np.zeros(0, np.int64)  # ids of the live tracks
    out = []
    for i, world_T_cam in enumerate(poses):
        uv, ok = _visible(renderer, cam, world_T_cam, points[active])
        keep = ok & (life[active] > 0)
        active = active[keep]
        uv = uv[keep]
        life[active] -= 1
        need = features - len(active)
        if need > 0:
            cand = np.column_stack([rng.uniform(_BORDER_PX, cam.width - _BORDER_PX, 2 * need),
                                    rng.uniform(_BORDER_PX, cam.height - _BORDER_PX, 2 * need)])  # fmt: skip
            X, _ = renderer.surface_points(world_T_cam, cand)
            good = np.all(np.isfinite(X), axis=1)
            X, cand = X[good][:need], cand[good][:need]
            new = np.arange(len(points), len(points) + len(X))
            points = np.vstack([points, X])
            life = np.concatenate([life, rng.geometric(1.0 / lifetime, len(X)).astype(np.int64)])
            active = np.concatenate([active, new])
            uv = np.vstack([uv, cand])
        obs = uv + rng.normal(0.0, noise_px, uv.shape) if noise_px > 0 else uv.copy()
        out.append(FeatureTracks(int(cap.frame_t_ns[i]), active.copy(), obs))
    return out, points


def _visible(renderer, cam, world_T_cam: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(uv (N, 2), visible (N,)): the true distorted projections of world points X and whether the camera sees them."""
    if len(X) == 0:
        return np.zeros((0, 2)), np.zeros(0, bool)
    R, o = world_T_cam[:3, :3], world_T_cam[:3, 3]
    pc = (X - o) @ R
    front = pc[:, 2] > 1e-3
    uv = np.full((len(X), 2), np.nan)
    uv[front] = cam.project(pc[front])
    ok = front & np.all(np.isfinite(uv), axis=1)
    ok &= (uv[:, 0] > _BORDER_PX) & (uv[:, 0] < cam.width - _BORDER_PX)
    ok &= (uv[:, 1] > _BORDER_PX) & (uv[:, 1] < cam.height - _BORDER_PX)
    if ok.any():
        hit, _ = renderer.surface_points(world_T_cam, uv[ok])
        rng_pt = np.linalg.norm(X[ok] - o, axis=1)
        rng_hit = np.linalg.norm(hit - o, axis=1)
        idx = np.flatnonzero(ok)
        ok[idx] = np.isfinite(rng_hit) & (rng_hit > rng_pt - _HIDDEN_M - 1e-3 * rng_pt)
    return uv, ok


def main(argv: list[str] | None = None) -> int:
    from vio.config import load_config
    from vio.errors import VioError
    from vio.pipeline import run_capture
    from vio.readers import open_capture

    ap = argparse.ArgumentParser(prog="python -m vio.bench.synthetic_tracks", description=__doc__.splitlines()[0])
    ap.add_argument("capture", help="a built-in simulated capture (orbit, figure8, room)")
    ap.add_argument("out", help="the run's output folder")
    ap.add_argument("--noise-px", type=float, required=True, help="white pixel noise sigma, px")
    ap.add_argument("--features", type=int, default=150, help="tracks per frame (default 150, the tracker's)")
    ap.add_argument("--lifetime", type=float, default=25.0, help="mean track length, frames")
    ap.add_argument("--seed", type=int, default=0, help="seed of the track starts and the pixel noise")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE", help="estimator override")
    args = ap.parse_args(argv)
    try:
        cap = open_capture(args.capture, needs=("imu",))
        cap.tracks, _ = true_tracks(cap, args.noise_px, args.features, args.lifetime, args.seed)
        result = run_capture(cap, os.fspath(args.out), load_config(None, args.set))
    except VioError as exc:
        print(f"synthetic_tracks: {exc}")
        return 2
    gt = Path(args.capture) / "mav0/state_groundtruth_estimate0/data.csv"
    est = Path(args.out) / "trajectory.tum"
    status = result.summary.get("status", "?")
    print(f"{args.out}: {status}; evaluate with `vio eval --gt {gt} --est {est} --align sim3`")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
