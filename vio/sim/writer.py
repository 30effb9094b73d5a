"""Writes a simulated scenario into an ASL capture: calibration, IMU, ground truth, images, scene."""

from __future__ import annotations

import logging
from collections.abc import Iterator

import numpy as np
import yaml

from vio.atomic import write_text
from vio.records import CameraCalib, GroundTruth, ImuSeries
from vio.sim.parts import write_stl
from vio.sim.phone import Sensor, band_rows, blur_samples, exposure_times_ns, render_radiance
from vio.sim.render import Renderer, camera_poses
from vio.sim.scenario import Scenario
from vio.sim.workers import render_in_workers
from vio.writers.asl import AslWriter, encode_png

log = logging.getLogger(__name__)


def scene_yaml_text(sc: Scenario) -> str:
    """scene/scene.yaml: what was simulated (scenario, seed, IMU grade, the part and its pose, room bounds)."""
    placed = sc.scene.part
    meta = {
        "scenario": sc.name,
        "seed": int(sc.seed),
        "imu_grade": sc.imu_grade,
        "duration_s": float(sc.duration_s),
        "t0_ns": int(sc.t0_ns),
        "camera_rate_hz": float(sc.camera_rate_hz),
        "imu_rate_hz": float(sc.imu_rate_hz),
        "object": None
        if placed is None
        else {
            "part": placed.part.name,
            "description": placed.part.description,
            "surface": placed.surface,
            "cad": "cad.stl (part frame, mm)",
            "mesh": "object.stl (world frame, m)",
            "pose": "part_pose.yaml (world_T_part)",
            "dimensions_mm": {k: round(float(v), 6) for k, v in placed.part.dimensions_mm.items()},
            "bounds_part_mm": [[round(float(v), 6) for v in row] for row in placed.part.bounds_mm()],
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
    if sc.phone is not None:  # only then: the default capture's scene.yaml stays as it was
        meta["camera"] = {
            **sc.phone.yaml_dict(sc.camera.height),
            "frames": "camera_frames.csv (stamp, true time, gain, blur)",
        }
    if sc.imu_errors is not None:
        meta["imu_errors"] = sc.imu_errors.yaml_dict()
    if sc.real_imu is not None:
        meta["real_imu"] = sc.real_imu
    if sc.phases is not None and sc.motion_s is not None:
        meta["phases"] = {"motion_s": float(sc.motion_s), **sc.phases.as_dict(sc.motion_s)}
    return "# vio simulated scene (ground truth)\n" + yaml.safe_dump(meta, sort_keys=False)


def part_pose_yaml_text(world_T_part: np.ndarray) -> str:
    """scene/part_pose.yaml: the part frame (cad.stl, mm) in the world (object.stl, trajectory; m)."""
    meta = {
        "world_T_part": [[round(float(v), 12) for v in row] for row in world_T_part],
        "units": "rotation unitless, translation m; a CAD point p_mm maps to world as R @ (p_mm / 1000) + t",
    }
    return "# vio simulated part pose (ground truth)\n" + yaml.safe_dump(meta, sort_keys=False, default_flow_style=None)


def write_capture(
    writer: AslWriter,
    sc: Scenario,
    imu: ImuSeries,
    gt: GroundTruth,
    images: bool,
    image_seeds: tuple[np.random.SeedSequence, np.random.SeedSequence],
    workers: int | None = None,
) -> None:
    """Write every file of the capture for scenario `sc` into `writer`; `image_seeds` seed the noise of the video
    frames and of the stills."""
    comment = f"vio simulator ({sc.name}, seed {sc.seed})"
    writer.write_camera(sc.camera, comment)
    writer.write_imu(sc.imu_calib, imu, f"vio simulator ({sc.name}, seed {sc.seed}, {sc.imu_grade} IMU)")
    writer.write_groundtruth(gt)
    placed = sc.scene.part
    if placed is not None:
        part = placed.part
        write_stl(writer.scene_dir / "cad.stl", part.vertices_mm, part.faces, f"vio part {part.name}: part frame, mm")
        write_stl(writer.scene_dir / "object.stl", placed.vertices_world(), part.faces, f"vio {part.name}: world, m")
        write_text(writer.scene_dir / "part_pose.yaml", part_pose_yaml_text(placed.world_T_part))
    write_text(writer.scene_dir / "scene.yaml", scene_yaml_text(sc))
    if not images:
        return
    if sc.phone is not None:
        rows = []
        for t, t_true, gain, samples, png in render_phone_pngs(sc, image_seeds[0], workers):
            writer.add_png(int(t), png)
            rows.append(f"{int(t)},{int(t_true)},{gain:.6f},{samples}")
        header = "#t_stamp [ns] (camera clock),t_true [ns] (IMU clock; top row mid-exposure),gain,blur_samples"
        write_text(writer.scene_dir / "camera_frames.csv", "\n".join([header, *rows]) + "\n")
    else:
        t_ns = sc.frame_times_ns()
        for t, png in zip(t_ns, render_pngs(sc, sc.camera, t_ns, image_seeds[0], workers), strict=True):
            writer.add_png(int(t), png)
    if sc.stills_camera is not None:
        writer.write_camera(sc.stills_camera, f"{comment}: full-resolution stills", cam_id=1)
        t_ns = sc.stills_times_ns()
        for t, png in zip(t_ns, render_pngs(sc, sc.stills_camera, t_ns, image_seeds[1], workers), strict=True):
            writer.add_png(int(t), png, cam_id=1)


def render_pngs(
    sc: Scenario,
    camera: CameraCalib,
    t_ns: np.ndarray,
    image_seed: np.random.SeedSequence,
    workers: int | None = None,
) -> Iterator[bytes]:
    """Yield the PNG bytes of each image of `camera` in order; image i's noise comes from image_seed.spawn(F)[i].

    Frames are rendered in this process or by `workers` processes (default 2 when there are 40+ frames, see
    `vio.sim.workers`); the bytes do not depend on the number of workers.
    """
    poses = camera_poses(sc, t_ns, camera)
    jobs = list(zip(poses, image_seed.spawn(len(t_ns)), strict=True))
    if workers is None:
        workers = 2 if len(jobs) >= 40 else 1
    if workers <= 1:
        renderer = Renderer(sc.scene, camera)
        for world_T_cam, seq in jobs:
            yield encode_png(renderer.render(world_T_cam, np.random.default_rng(seq)))
        return
    yield from render_in_workers(sc.scene, camera, jobs, workers)


def render_phone_pngs(
    sc: Scenario, image_seed: np.random.SeedSequence, workers: int | None = None
) -> Iterator[tuple[int, int, float, int, bytes]]:
    """Yield (stamp ns, true time ns, auto-exposure gain, blur samples, PNG bytes) of each frame of the phone camera
    `sc.phone` (`vio.sim.phone`); frame i's noise comes from image_seed.spawn(F)[i]."""
    phone, cam = sc.phone, sc.camera
    stamps, t_true = sc.phone_frame_times()
    rows = band_rows(cam.height, phone.bands)
    half = int(round(phone.exposure_s * 0.5e9))
    ends = camera_poses(sc, np.concatenate([t_true - half, t_true + half]))
    jobs, samples = [], []
    for i, t in enumerate(t_true):
        s = blur_samples(ends[i], ends[len(t_true) + i], cam) if phone.exposure_s > 0 else 1
        times = exposure_times_ns(int(t), phone, cam.height, s)
        jobs.append(("phone", camera_poses(sc, times.ravel()).reshape(*times.shape, 4, 4), rows))
        samples.append(s)
    if workers is None:
        workers = 2 if len(jobs) >= 20 else 1
    if workers <= 1:
        renderer = Renderer(sc.scene, cam)
        radiances = (render_radiance(renderer, job[1], job[2]) for job in jobs)
    else:
        radiances = render_in_workers(sc.scene, cam, jobs, workers)
    sensor = Sensor(phone, cam.width, cam.height, sc.camera_rate_hz)
    seeds = image_seed.spawn(len(jobs))
    for i, radiance in enumerate(radiances):
        image, gain = sensor.expose(radiance, np.random.default_rng(seeds[i]))
        yield int(stamps[i]), int(t_true[i]), gain, samples[i], encode_png(image)
