"""Writes a simulated scenario into an ASL capture: calibration, IMU, ground truth, images, scene."""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np
import yaml

from vio.atomic import write_text
from vio.records import GroundTruth, ImuSeries
from vio.sim.stl import write_stl
from vio.writers.asl import AslWriter

if TYPE_CHECKING:
    from vio.sim.api import Scenario

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
    """Write every file of the capture for scenario `sc` (a `vio.sim.api.Scenario`) into `writer`."""
    comment = f"vio simulator ({sc.name}, seed {sc.seed})"
    writer.write_camera(sc.camera, comment)
    writer.write_imu(sc.imu_calib, imu, f"vio simulator ({sc.name}, seed {sc.seed}, {sc.imu_grade} IMU)")
    writer.write_groundtruth(gt)
    write_stl(writer.scene_dir / "object.stl", sc.scene.object_triangles())
    write_text(writer.scene_dir / "scene.yaml", scene_yaml_text(sc))
    if not images:
        return
    from vio.sim.render import render_pngs

    t_ns = sc.frame_times_ns()
    for t, png in zip(t_ns, render_pngs(sc, t_ns, image_seed, workers), strict=True):
        writer.add_png(int(t), png)
