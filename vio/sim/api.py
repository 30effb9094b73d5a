"""The simulator's public functions: `load_scenario` (the oracle other tests use) and `simulate` (writes a capture).

Seeds are split by stream with `np.random.SeedSequence(seed).spawn(7)`: trajectory (motion phases), IMU (noise
and biases), image noise, scene (textures), stills noise, the phone IMU's scale factors and misalignment, and its
timestamp jitter (the first four are those of the earlier `spawn(4)` and the first five those of `spawn(5)`, so
adding a stream changed no other stream); an eighth, `spawn(8)[7]`, shakes the `--excite` phase. The same seed
gives byte-identical files.
"""

from __future__ import annotations

import logging
import os
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from vio.errors import SimulationError
from vio.sim import rig, scenarios
from vio.sim.definitions import read_definition
from vio.sim.imu import PhoneImu, grade_by_name, imu_calib, simulate_imu
from vio.sim.parts import build_part
from vio.sim.phases import PhasedMotion, phased
from vio.sim.phone import KNOBS_ONLY, PhoneCamera, portrait_camera
from vio.sim.scenario import Scenario
from vio.sim.scene import SURFACES
from vio.sim.trajectory import Trajectory, camera_driven, spline_trajectory
from vio.sim.writer import write_capture
from vio.writers.asl import AslWriter

log = logging.getLogger(__name__)

BUILTIN = ("orbit", "figure8", "room", "static", "tumble")
DEFAULT_DURATION_S = {
    "orbit": 60.0,
    "figure8": 30.0,
    "room": 60.0,
    "static": 3600.0,
    "tumble": scenarios.TUMBLE_POSES * (scenarios.TUMBLE_HOLD_S + scenarios.TUMBLE_TURN_S),
}


def _phases_stream(seed: int) -> np.random.SeedSequence:
    """The excitation's phases: an eighth stream (the first seven, and so every default capture, unchanged)."""
    return np.random.SeedSequence(seed).spawn(8)[7]


def imu_noise_stream(seed: int) -> np.random.SeedSequence:
    """The seed sequence of a capture's IMU noise and biases (for drawing its IMU again, `vio.bench.imu_ablation`)."""
    return _streams(seed)[1]


def _streams(seed: int) -> list[np.random.SeedSequence]:
    if seed < 0:
        raise SimulationError(f"seed must be non-negative, got {seed}")
    return np.random.SeedSequence(seed).spawn(7)


def load_scenario(
    scenario: str | os.PathLike[str],
    seed: int = 0,
    duration_s: float | None = None,
    imu_grade_name: str = "phone",
    part: str = "cube",
    part_units: str = "mm",
    surface: str = "speckle",
    stills_hz: float = 0.0,
    stills_size: tuple[int, int] = rig.STILLS_SIZE,
    phone: PhoneCamera | None = None,
    imu_rate_hz: float | None = None,
    phone_imu: PhoneImu | None = None,
    start_s: float = 0.0,
    file_clock: bool = False,
    phases: PhasedMotion | None = None,
    close_fit: bool = False,
) -> Scenario:
    """Build a scenario by name (`orbit`, `figure8`, `room`), from a scenario YAML (`data/synthetic/*.yaml`), or
    from a trajectory file (EuRoC CSV or TUM) that drives a smooth spline through its poses.

    `part` is the measured object (`vio.sim.parts`: cube, cube_features, freeform, or an STL file in `part_units`),
    painted with `surface` (speckle | plain). `stills_hz` > 0 adds full-resolution stills of `stills_size`
    (width, height) px taken by the same camera (`mav0/cam1`). `phone` is the rolling-shutter camera model
    (`vio.sim.phone`; None: the default global-shutter camera), `imu_rate_hz` the IMU rate (None: 200 Hz) and
    `phone_imu` the magnitudes of the IMU's scale-factor, misalignment and timestamp errors (None: none).
    `start_s` (trajectory files only) starts the capture that many seconds into the trajectory; a trajectory
    file's own clock is kept when its times are epoch-sized or `file_clock` (a real IMU on that clock);
    `close_fit` follows a trajectory file's poses closely instead of smoothing them (`spline_trajectory`).
    `phases` (`vio.sim.phases`) adds a still start, brisk excitation and a still end around the scenario's motion:
    `duration_s` is then the motion's length and the capture lasts `phases.total_s(duration_s)`."""
    if surface not in SURFACES:
        raise SimulationError(f"surface must be one of {', '.join(SURFACES)}, got {surface!r}")
    the_part = build_part(part, part_units)
    stills = _stills_camera(stills_hz, stills_size)
    ss_traj, _, _, ss_scene, _, ss_imu_errors, _ = _streams(seed)
    rng = np.random.default_rng(ss_traj)
    texture_seed = int(ss_scene.generate_state(1)[0])
    camera = rig.default_camera()
    imu_rate = rig.IMU_RATE_HZ if imu_rate_hz is None else float(imu_rate_hz)
    if not np.isfinite(imu_rate) or not 50.0 <= imu_rate <= 2000.0:
        raise SimulationError(f"IMU rate must be between 50 and 2000 Hz, got {imu_rate:g}")
    if phone is not None:
        phone.validate(rig.CAMERA_RATE_HZ, camera.height)
    name = str(scenario)
    t0_ns = rig.T0_NS
    if not np.isfinite(start_s) or start_s < 0:
        raise SimulationError(f"start must be a non-negative number of seconds, got {start_s:g}")
    span = None
    definition = None
    if name not in BUILTIN and name.lower().endswith((".yaml", ".yml")) and Path(name).is_file():
        definition = read_definition(Path(name))
    if (name in BUILTIN or definition is not None) and (start_s or close_fit):
        raise SimulationError("--start and --close-fit are for a trajectory file scenario (EuRoC CSV or TUM)")
    if name in BUILTIN or definition is not None:
        base = name if definition is None else definition.base
        motion = {} if definition is None else definition.motion
        if base == "room":
            scene = scenarios.room_scene(texture_seed, the_part, surface)
            cam_fn = scenarios.room_camera(rng, **motion)
        else:
            scene = scenarios.tabletop_scene(texture_seed, the_part, surface)
            centre = scene.object_corners_world().mean(axis=0)
            make = {
                "orbit": scenarios.orbit_camera,
                "static": scenarios.static_camera,
                "tumble": scenarios.tumble_camera,
            }.get(base, scenarios.figure8_camera)
            cam_fn = make(rng, centre, **motion)
        if phone is not None and phone.portrait:
            cam_fn = portrait_camera(cam_fn)
        default_s = DEFAULT_DURATION_S[base]
        if definition is not None and definition.duration_s is not None:
            default_s = definition.duration_s
        traj_fn = camera_driven(cam_fn, camera.body_T_cam)
    else:
        path = Path(name)
        if not path.is_file():
            raise SimulationError(
                f"unknown scenario '{name}': choose orbit, figure8, room, a scenario YAML, "
                "or a trajectory file (EuRoC CSV or TUM)"
            )
        traj0, t_first_ns, p_world = _from_file(path, close=close_fit)
        scene = scenarios.trajectory_room_scene(p_world, texture_seed, the_part, surface)
        if start_s >= traj0.duration_s - 1.0:
            raise SimulationError(f"{name}: start {start_s:g} s leaves less than 1 s of the {traj0.duration_s:.3f} s")
        span = traj0.duration_s - start_s
        default_s = span
        traj_fn = _shifted(traj0, start_s)
        if t_first_ns > 10**17 or file_clock:
            t0_ns = t_first_ns
        t0_ns += int(round(start_s * 1e9))
    dur = default_s if duration_s is None else float(duration_s)
    if not np.isfinite(dur) or dur <= 0:
        raise SimulationError(f"duration must be positive, got {duration_s}")
    if span is not None and dur > span + 1e-9:
        raise SimulationError(f"{name}: duration {dur:g} s is longer than the trajectory ({span:.3f} s)")
    grade = grade_by_name(imu_grade_name)
    motion_s = None
    if phases is not None:
        phases.validate()
    if phases is not None and phases.active:
        traj_fn = phased(traj_fn, phases, dur, np.random.default_rng(_phases_stream(seed)))
        motion_s, dur = dur, phases.total_s(dur)
    return Scenario(
        name=name,
        seed=seed,
        trajectory=Trajectory(traj_fn, dur),
        scene=scene,
        camera=camera,
        imu_calib=imu_calib(grade, imu_rate),
        imu_grade=grade.name,
        t0_ns=int(t0_ns),
        duration_s=dur,
        camera_rate_hz=rig.CAMERA_RATE_HZ,
        imu_rate_hz=imu_rate,
        stills_camera=stills,
        stills_offset_ns=rig.STILLS_OFFSET_NS,
        phone=phone,
        imu_errors=None if phone_imu is None else phone_imu.draw(np.random.default_rng(ss_imu_errors)),
        phases=phases if motion_s is not None else None,
        motion_s=motion_s,
    )


def _shifted(traj: Trajectory, start_s: float):
    """The pose function of `traj` started `start_s` seconds in."""
    if not start_s:
        return traj.pose
    return lambda t: traj.pose(t + start_s)


MAX_STILLS_SIZE = (4032, 3024)


def _stills_camera(hz: float, size: tuple[int, int]):
    """The stills camera, or None when stills are off (hz 0); a one-line error for a bad rate or size."""
    if hz == 0:
        return None
    if not np.isfinite(hz) or not 0 < hz <= 10:
        raise SimulationError(f"stills rate must be between 0 and 10 Hz, got {hz:g}")
    w, h = (int(v) for v in size)
    if not (64 <= w <= MAX_STILLS_SIZE[0] and 48 <= h <= MAX_STILLS_SIZE[1]) or h > w:
        raise SimulationError(
            f"stills size must be landscape, at most {MAX_STILLS_SIZE[0]}x{MAX_STILLS_SIZE[1]}, got {w}x{h}"
        )
    return rig.stills_camera(w, h, float(hz))


def _from_file(path: Path, close: bool = False) -> tuple[Trajectory, int, np.ndarray]:
    """The spline through a trajectory file's poses (`close`: following them closely, see `spline_trajectory`), its
    first time (ns) and its positions (N, 3) m."""
    from vio.trajio import read_trajectory

    traj = read_trajectory(path)
    if len(traj) < 10:
        raise SimulationError(f"{path}: needs at least 10 poses to fit a spline, found {len(traj)}")
    span_s = (int(traj.t_ns[-1]) - int(traj.t_ns[0])) * 1e-9
    if span_s < 1.0:
        raise SimulationError(f"{path}: trajectory spans {span_s:.3f} s; at least 1 s is needed")
    gaps = np.diff(traj.t_ns) * 1e-9
    if gaps.max() > 1.0:
        i = int(np.argmax(gaps))
        raise SimulationError(f"{path}: {gaps[i]:.2f} s gap between poses {i} and {i + 1}; the spline needs < 1 s")
    spline, t_first_ns = spline_trajectory(traj.t_ns, traj.p_world, traj.q_wxyz, close=close)
    return spline, t_first_ns, traj.p_world


def _calibration_time_offset(phone: PhoneCamera | None) -> float:
    """The calibration scenario's camera clock offset, s: of the camera knobs it takes `--time-offset-ms` alone."""
    if phone is None:
        return 0.0
    if replace(phone, time_offset_s=KNOBS_ONLY.time_offset_s) != KNOBS_ONLY:
        raise SimulationError(
            "the calibration scenario takes --time-offset-ms but not --camera, --readout-ms or --exposure-ms"
        )
    return float(phone.time_offset_s)


def simulate(
    scenario: str | os.PathLike[str],
    out: str | os.PathLike[str],
    seed: int = 0,
    duration_s: float | None = None,
    imu_grade: str = "phone",
    overwrite: bool = False,
    images: bool = True,
    workers: int | None = None,
    mars: str | os.PathLike[str] | None = None,
    real_imu: str | os.PathLike[str] | None = None,
    real_imu_calib: str | os.PathLike[str] | None = None,
    **scene: Any,
) -> Path:
    """Simulate a capture and write it in the ASL layout under `out`; returns `out` as a Path.

    `images=False` writes IMU, ground truth, calibration and scene only (cam0/data.csv lists no frames).
    The scenario `calibration` (a board on a wall, `vio.sim.calibration`) takes `board=SPEC`,
    `calibration_motion=sway|excite` and, of the camera knobs, the time offset alone in `scene`.
    `workers` render processes (default: 2, or 1 for short captures). `scene` holds `load_scenario`'s part,
    part_units, surface, stills_hz, stills_size, phone, imu_rate_hz and phone_imu; `mars` (a folder) also
    writes the capture as a MARS logger folder with H.264 video (`vio.writers.mars`). `real_imu` (an EuRoC/ASL
    `imu0/data.csv` on the trajectory file's clock) replaces the simulated IMU with the recording's samples, its
    noise from `real_imu_calib` or the `sensor.yaml` beside it (`vio.sim.real_imu`), along the trajectory followed
    closely (`close_fit`, which a simulated-IMU twin of the same images needs too). `scene` may also hold `start_s`,
    the start within a trajectory file. `scene` may also hold `phases` (`vio.sim.phases`).
    """
    board = scene.pop("board", None)
    motion = scene.pop("calibration_motion", None)
    if str(scenario) == "calibration":  # a board on a wall (vio.sim.calibration), not a scene with the part
        from vio.sim.calibration import DEFAULT_BOARD, simulate_calibration

        offset_s = _calibration_time_offset(scene.pop("phone", None))
        if {"phone_imu", "imu_rate_hz", "phases"} & set(scene) or mars is not None:
            raise SimulationError(
                "--camera, --imu-rate, --mars and the still/excite phases are not available for the calibration "
                "scenario"
            )
        return simulate_calibration(
            out,
            board or DEFAULT_BOARD,
            seed,
            duration_s,
            imu_grade,
            overwrite,
            images,
            time_offset_s=offset_s,
            motion=motion or "sway",
        )
    for name, value in (("--board", board), ("--motion", motion)):
        if value is not None:
            raise SimulationError(f"{name} is for the calibration scenario (vio simulate calibration {name} ...)")
    if real_imu is not None:
        return _simulate_real_imu(scenario, out, seed, duration_s, overwrite, images, workers, mars, real_imu,
                                  real_imu_calib, scene)  # fmt: skip
    if real_imu_calib is not None:
        raise SimulationError("--imu-calib goes with --real-imu (the simulated IMU's noise is --imu's grade)")
    sc = load_scenario(scenario, seed, duration_s, imu_grade, **scene)
    _, ss_imu, ss_img, _, ss_stills, _, ss_jitter = _streams(seed)
    imu, gt = simulate_imu(
        sc.trajectory,
        sc.t0_ns,
        sc.duration_s,
        sc.imu_rate_hz,
        grade_by_name(sc.imu_grade),
        np.random.default_rng(ss_imu),
        sc.imu_errors,
        np.random.default_rng(ss_jitter),
    )
    with AslWriter(out, overwrite=overwrite) as writer:
        write_capture(writer, sc, imu, gt, images, (ss_img, ss_stills), workers)
    if mars is not None:
        from vio.writers.mars import write_mars_from_asl

        write_mars_from_asl(out, mars, overwrite=overwrite)
    log.info("simulated %s (%.1f s, seed %d, %s IMU) into %s", sc.name, sc.duration_s, seed, sc.imu_grade, out)
    return Path(out)


def _simulate_real_imu(
    scenario: str | os.PathLike[str],
    out: str | os.PathLike[str],
    seed: int,
    duration_s: float | None,
    overwrite: bool,
    images: bool,
    workers: int | None,
    mars: str | os.PathLike[str] | None,
    real_imu: str | os.PathLike[str],
    real_imu_calib: str | os.PathLike[str] | None,
    scene: dict[str, Any],
) -> Path:
    """`simulate` with a real IMU recording (`vio.sim.real_imu`): the vision rendered along the trajectory file,
    the IMU stream and its noise calibration from the recording, the ground truth at the real IMU's times."""
    from vio.sim.real_imu import ground_truth_at, imu_window, load_real_imu, trajectory_biases

    if str(scenario) in BUILTIN or str(scenario).lower().endswith((".yaml", ".yml")):
        raise SimulationError("--real-imu needs a trajectory file scenario (EuRoC CSV or TUM) on the IMU's clock")
    if {"phone_imu", "imu_rate_hz"} & set(scene):
        raise SimulationError("--real-imu replaces the simulated IMU: --imu-rate and the phone IMU do not apply")
    if "phases" in scene:
        raise SimulationError("--real-imu records the real motion: the still/excite phases cannot be added to it")
    real = load_real_imu(real_imu, real_imu_calib)
    scene.pop("close_fit", None)  # always: the real IMU measured the recorded motion, not a smoothed one
    sc = load_scenario(scenario, seed, duration_s, "ideal", file_clock=True, close_fit=True, **scene)
    imu = imu_window(real, sc.t0_ns, sc.duration_s)
    biases = trajectory_biases(scenario)
    sc = replace(
        sc,
        imu_calib=real.calib,
        imu_grade="real",
        imu_rate_hz=real.calib.rate_hz,
        real_imu={
            "imu": str(real.source),
            "noise_from": str(real.calib_source),
            "start_s": float(scene.get("start_s", 0.0)),
            "biases": "interpolated from the trajectory file" if biases is not None else "unknown (written as 0)",
            "ground_truth": "the trajectory's spline at the real IMU's times; the IMU measured the real motion",
        },
    )
    gt = ground_truth_at(sc.trajectory, sc.t0_ns, imu.t_ns, biases)
    _, _, ss_img, _, ss_stills, _, _ = _streams(seed)
    with AslWriter(out, overwrite=overwrite) as writer:
        write_capture(writer, sc, imu, gt, images, (ss_img, ss_stills), workers)
    if mars is not None:
        from vio.writers.mars import write_mars_from_asl

        write_mars_from_asl(out, mars, overwrite=overwrite)
    log.info("simulated vision along %s (%.1f s from %.1f s, seed %d) with the real IMU %s into %s", sc.name,
             sc.duration_s, float(scene.get("start_s", 0.0)), seed, real.source, out)  # fmt: skip
    return Path(out)
