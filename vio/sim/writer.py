"""Writes a simulated scenario into an ASL capture: calibration, IMU, ground truth, images, scene."""

from __future__ import annotations

import logging
from collections.abc import Iterator

import numpy as np
import yaml

from vio.atomic import write_text
from vio.records import GroundTruth, ImuSeries
from vio.sim.render import Renderer, camera_poses
from vio.sim.scenario import Scenario
from vio.sim.stl import write_stl
from vio.sim.workers import render_in_workers
from vio.writers.asl import AslWriter, encode_png

log = logging.getLogger(__name__)


def scene_yaml_text(sc: Scenario) -> str:
    """scene/scene.yaml: what was simulated (scenario, seed, IMU grade, object size and pose, room bounds)."""
    obj = sc.scene.object_box
    meta = {
        "scenario": sc.name,
        "seed": int(sc.seed),
        "imu_grade": sc.imu_grade,
        "duration_s": float(sc.duration_s),
        "t0_ns": int(sc.t0_ns),
        "camera_rate_hz": float(sc.camera_rate_hz),
        "imu_rate_hz": float(sc.imu_rate_hz),
        "object": {
            "shape": "cube",
            "mesh": "object.stl",
            "size_m": [round(float(v), 9) for v in obj.hi - obj.lo],
            "centre_world_m": [round(float(v), 9) for v in 0.5 * (obj.lo + obj.hi)],
        },
        "boxes": [
            {
                "name": b.name,
                "lo_m": [round(float(v), 9) for v in b.lo],
                "hi_m": [round(float(v), 9) for v in b.hi],
                "inside": bool(b.inside),
            }
            for b in sc.scene.boxes
        ],
        "frames": "world z up, gravity (0, 0, -9.81) m/s^2; body = IMU",
    }
    return "# vio simulated scene (ground truth)\n" + yaml.safe_dump(meta, sort_keys=False)


def write_capture(
    writer: AslWriter,
    sc: Scenario,
    imu: ImuSeries,
    gt: GroundTruth,
    images: bool,
    image_seed: np.random.SeedSequence,
    workers: int | None = None,
) -> None:
    """Write every file of the capture for scenario `sc` into `writer`."""
    comment = f"vio simulator ({sc.name}, seed {sc.seed})"
    writer.write_camera(sc.camera, comment)
    writer.write_imu(sc.imu_calib, imu, f"vio simulator ({sc.name}, seed {sc.seed}, {sc.imu_grade} IMU)")
    writer.write_groundtruth(gt)
    write_stl(writer.scene_dir / "object.stl", sc.scene.object_triangles())
    write_text(writer.scene_dir / "scene.yaml", scene_yaml_text(sc))
    if not images:
        return
    t_ns = sc.frame_times_ns()
    for t, png in zip(t_ns, render_pngs(sc, t_ns, image_seed, workers), strict=True):
        writer.add_png(int(t), png)


def render_pngs(
    sc: Scenario, t_ns: np.ndarray, image_seed: np.random.SeedSequence, workers: int | None = None
) -> Iterator[bytes]:
    """Yield the PNG bytes of each frame in order; frame i's noise comes from image_seed.spawn(F)[i].

    Frames are rendered in this process or by `workers` processes (default 2 when there are 40+ frames, see
    `vio.sim.workers`); the bytes do not depend on the number of workers.
    """
    poses = camera_poses(sc, t_ns)
    jobs = list(zip(poses, image_seed.spawn(len(t_ns)), strict=True))
    if workers is None:
        workers = 2 if len(jobs) >= 40 else 1
    if workers <= 1:
        renderer = Renderer(sc.scene, sc.camera)
        for world_T_cam, seq in jobs:
            yield encode_png(renderer.render(world_T_cam, np.random.default_rng(seq)))
        return
    yield from render_in_workers(sc.scene, sc.camera, jobs, workers)
