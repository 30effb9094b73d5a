"""Calibration figures of docs/BENCHMARKS.md over seeds (not a test; the tests use other seeds):

python -m tests.vio.calibrate.bench camera chessboard:9x6:30 10 15     # vio simulate calibration, 30 s
python -m tests.vio.calibrate.bench imu 3600 200 100 110               # static phone IMU: duration, rate
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def camera(spec: str, seeds: range) -> None:
    from vio.calibrate.board import BoardDetector, parse_board
    from vio.calibrate.camera import calibrate_camera
    from vio.calibrate.views import find_views
    from vio.sim import rig
    from vio.sim.calibration import simulate_calibration

    cam = rig.default_camera()
    truth = [cam.fx, cam.fy, cam.cx, cam.cy, *cam.dist]
    board = parse_board(spec)
    rows = []
    for seed in seeds:
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.time()
            simulate_calibration(Path(tmp) / "c", spec, seed=seed)
            t1 = time.time()
            vs = find_views([Path(tmp) / "c"], BoardDetector(board), max_views=40)
            cal = calibrate_camera(vs.views, board, vs.image_size, "radtan")
            t2 = time.time()
        got = list(cal.params().values())
        rel = [g / t - 1 for g, t in zip(got[:6], truth[:6], strict=True)]
        absolute = [g - t for g, t in zip(got[6:], truth[6:], strict=True)]
        rows.append([*rel, *absolute])
        print(
            f"seed {seed}: simulate {t1 - t0:.1f} s, calibrate {t2 - t1:.1f} s, {len(vs.views)} views, "
            f"RMS {cal.rms_px:.3f} px; fx fy cx cy k1 k2 error % "
            + " ".join(f"{100 * e:+.3f}" for e in rel)
            + "; p1 p2 error "
            + " ".join(f"{e:+.1e}" for e in absolute),
            flush=True,
        )
    r = np.abs(np.array(rows))
    print("largest |error|: fx fy cx cy k1 k2 % " + " ".join(f"{100 * e:.3f}" for e in r.max(0)[:6]), end="")
    print("; p1 p2 " + " ".join(f"{e:.1e}" for e in r.max(0)[6:]))


def imu(duration_s: float, rate_hz: float, seeds: range) -> None:
    from vio.calibrate.imu import imu_noise
    from vio.sim.api import load_scenario
    from vio.sim.imu import grade_by_name, simulate_imu

    g = grade_by_name("phone")
    rows = []
    for seed in seeds:
        sc = load_scenario("static", seed, duration_s, "phone")
        rng = np.random.default_rng(np.random.SeedSequence(seed).spawn(5)[1])  # the simulator's IMU stream
        series, _ = simulate_imu(sc.trajectory, sc.t0_ns, duration_s, rate_hz, g, rng)
        t0 = time.time()
        noise = imu_noise(series)
        k = noise.kalibr()
        worst = [
            k.gyroscope_noise_density / g.gyro_noise - 1,
            k.accelerometer_noise_density / g.acc_noise - 1,
            k.gyroscope_random_walk / g.gyro_walk - 1,
            k.accelerometer_random_walk / g.acc_walk - 1,
        ]
        axes = [f.random_walk / g.gyro_walk - 1 for f in noise.gyro] + [
            f.random_walk / g.acc_walk - 1 for f in noise.acc
        ]
        rows.append(worst + axes)
        print(
            f"seed {seed}: fit {time.time() - t0:.1f} s; worst axis error % gyro N, acc N, gyro K, acc K "
            + " ".join(f"{100 * e:+.1f}" for e in worst)
            + "; K per axis % "
            + " ".join(f"{100 * e:+.0f}" for e in axes),
            flush=True,
        )
    r = np.array(rows)
    print("largest |error| % " + " ".join(f"{100 * e:.1f}" for e in np.abs(r[:, :4]).max(0)), end="")
    print("; median % " + " ".join(f"{100 * e:.1f}" for e in np.median(np.abs(r[:, :4]), 0)), end="")
    print(f"; all four within 10 %: {int((np.abs(r[:, :4]) < 0.1).all(1).sum())} of {len(r)}", end="")
    print(f"; per-axis K spread gyro {100 * r[:, 4:7].std():.1f} %, acc {100 * r[:, 7:10].std():.1f} %")


if __name__ == "__main__":
    what, *rest = sys.argv[1:]
    if what == "camera":
        camera(rest[0], range(int(rest[1]), int(rest[2])))
    else:
        imu(float(rest[0]), float(rest[1]), range(int(rest[2]), int(rest[3])))
