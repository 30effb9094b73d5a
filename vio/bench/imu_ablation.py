"""Which of the IMU's errors moves an estimate: a simulated capture copied with its images linked and its IMU
simulated again from the same noise draws with some error terms switched off (issue 15).

    python -m vio.bench.imu_ablation CAPTURE OUT --drop acc_white,gyro_walk,...

The copy keeps the capture's `imu0/sensor.yaml` (the noise the estimator assumes), ground truth and scene, so an
estimator run on it differs from one on the capture only in the IMU's true errors. Error terms (`TERMS`): the white
noise of the gyro and the accelerometer, their bias random walks, their initial biases. With nothing dropped the
copy's IMU equals the capture's (the simulator's draws are per stream; `same_as_capture` checks it). Captures of the
built-in scenarios (orbit, figure8, room), with or without capture phases, and without the phone camera's IMU
errors (scale factors, misalignment, jitter) are supported.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import yaml

from vio.errors import VioError

TERMS = {
    "gyro_white": "gyro_noise",
    "acc_white": "acc_noise",
    "gyro_walk": "gyro_walk",
    "acc_walk": "acc_walk",
    "gyro_bias0": "gyro_bias0",
    "acc_bias0": "acc_bias0",
}


def _scene(capture: Path) -> dict:
    path = capture / "scene" / "scene.yaml"
    try:
        scene = yaml.safe_load(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise VioError(f"{capture}: not a simulated capture (no readable scene/scene.yaml: {exc.strerror})") from exc
    if scene.get("scenario") not in ("orbit", "figure8", "room"):
        raise VioError(f"{capture}: only the built-in scenarios are supported, not {scene.get('scenario')!r}")
    if "camera" in scene or "imu_errors" in scene or "real_imu" in scene:
        raise VioError(f"{capture}: a phone-camera or real-IMU capture is not supported")
    return scene


def simulated_scenario(capture: Path):
    """The `Scenario` (trajectory, scene, sensors) a built-in simulated capture was made from, rebuilt from its
    scene.yaml (the same seed gives the same trajectory, scene and noise streams)."""
    from vio.sim.api import load_scenario
    from vio.sim.phases import PhasedMotion

    scene = _scene(capture)
    phases = scene.get("phases")
    motion_s = float(phases["motion_s"]) if phases else float(scene["duration_s"])
    kw = {}
    if phases:
        kw["phases"] = PhasedMotion(phases["still_start_s"], phases["excite_s"], phases["still_end_s"])
    return load_scenario(scene["scenario"], int(scene["seed"]), motion_s, scene["imu_grade"], **kw)


def resimulated_imu(capture: Path, drop: tuple[str, ...] = ()):
    """The capture's IMU simulated again with the terms in `drop` switched off: (ImuSeries, GroundTruth)."""
    from vio.sim.api import imu_noise_stream
    from vio.sim.imu import grade_by_name, simulate_imu

    unknown = set(drop) - set(TERMS)
    if unknown:
        raise VioError(f"unknown IMU error term(s) {', '.join(sorted(unknown))}; known: {', '.join(TERMS)}")
    sc = simulated_scenario(capture)
    scene = _scene(capture)
    grade = replace(grade_by_name(scene["imu_grade"]), **{TERMS[t]: 0.0 for t in drop})
    rng = np.random.default_rng(imu_noise_stream(int(scene["seed"])))
    return simulate_imu(sc.trajectory, sc.t0_ns, sc.duration_s, sc.imu_rate_hz, grade, rng)


def _read_imu(path: Path) -> tuple[np.ndarray, np.ndarray]:
    t = np.loadtxt(path, delimiter=",", comments="#", usecols=0, dtype=np.int64)
    v = np.loadtxt(path, delimiter=",", comments="#", usecols=range(1, 7))
    return t, v


def same_as_capture(capture: Path, imu) -> float:
    """Largest difference between `imu` and the capture's own imu0/data.csv (its 9 significant digits)."""
    t, v = _read_imu(capture / "mav0" / "imu0" / "data.csv")
    if not np.array_equal(t, imu.t_ns):
        raise VioError(f"{capture}: the IMU's timestamps differ from the simulator's (not the capture it says)")
    return float(np.abs(v - np.column_stack([imu.gyro, imu.acc])).max())


def write_ablation(capture: str | os.PathLike[str], out: str | os.PathLike[str], drop: tuple[str, ...]) -> Path:
    """OUT: the capture with cam0 (and cam1) linked, ground truth, scene and sensor.yaml copied, the IMU
    re-simulated without the terms in `drop`."""
    capture, out = Path(capture).resolve(), Path(out)
    imu, _ = resimulated_imu(capture, drop)
    gap = same_as_capture(capture, imu if not drop else resimulated_imu(capture)[0])
    if gap > 1e-6:
        raise VioError(f"{capture}: the simulator no longer reproduces this capture's IMU (off by {gap:.3g})")
    if out.exists():
        raise VioError(f"{out} exists: choose a new folder")
    tmp = out.with_name(f".{out.name}.tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "mav0" / "imu0").mkdir(parents=True)
    for cam in ("cam0", "cam1"):
        if (capture / "mav0" / cam).exists():
            os.symlink(capture / "mav0" / cam, tmp / "mav0" / cam)
    shutil.copytree(capture / "mav0" / "state_groundtruth_estimate0", tmp / "mav0" / "state_groundtruth_estimate0")
    shutil.copytree(capture / "scene", tmp / "scene")
    shutil.copy(capture / "mav0" / "imu0" / "sensor.yaml", tmp / "mav0" / "imu0" / "sensor.yaml")
    src = capture / "mav0" / "imu0" / "data.csv"
    with open(src, encoding="utf-8") as f:
        header = f.readline()
    lines = [header.rstrip("\n")]
    for t, row in zip(imu.t_ns, np.column_stack([imu.gyro, imu.acc]), strict=True):
        lines.append(f"{t}," + ",".join(f"{x:.9g}" for x in row))
    (tmp / "mav0" / "imu0" / "data.csv").write_text("\n".join(lines) + "\n", encoding="utf-8")
    (tmp / "scene" / "imu_ablation.yaml").write_text(
        yaml.safe_dump({"from": str(capture), "dropped": list(drop)}, sort_keys=False), encoding="utf-8"
    )
    tmp.rename(out)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m vio.bench.imu_ablation", description=__doc__.splitlines()[0])
    p.add_argument("capture")
    p.add_argument("out")
    p.add_argument("--drop", default="", help=f"comma-separated terms to switch off: {', '.join(TERMS)}")
    args = p.parse_args(argv)
    drop = tuple(t for t in args.drop.split(",") if t)
    try:
        out = write_ablation(args.capture, args.out, drop)
    except VioError as exc:
        print(f"imu_ablation: error: {exc}", file=sys.stderr)
        return 2
    print(f"{out}: the IMU without {', '.join(drop) or 'nothing'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
