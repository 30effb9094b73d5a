"""Calibration figures of docs/BENCHMARKS.md over seeds (not a test; the tests use other seeds):

python -m tests.vio.calibrate.bench camera chessboard:9x6:30 10 15     # vio simulate calibration, 30 s
python -m tests.vio.calibrate.bench imu 3600 200 100 110               # static phone IMU: duration, rate
python -m tests.vio.calibrate.bench camera-imu excite 8 100 110        # motion, duration, seeds: as a user runs it
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


def camera_imu(motion: str, duration_s: float, seeds: range, spec: str = "chessboard:9x6:30") -> None:
    """Per seed: a calibration capture with a clock offset drawn in +-50 ms, `vio calibrate camera` on it, then
    `vio calibrate camera-imu`; errors against the simulator's truth and against the stated sigmas."""
    import yaml
    from scipy.spatial.transform import Rotation

    from vio.calibrate.board import parse_board
    from vio.calibrate.camera_files import calibrate_camera_files
    from vio.calibrate.camera_imu import calibrate_with_board
    from vio.readers import open_capture
    from vio.sim.calibration import simulate_calibration

    rows = []
    for seed in seeds:
        offset_s = float(np.random.default_rng(seed).uniform(-0.05, 0.05))
        with tempfile.TemporaryDirectory() as tmp:
            cap_dir = simulate_calibration(
                Path(tmp) / "c", spec, seed=seed, duration_s=duration_s, time_offset_s=offset_s, motion=motion
            )
            calibrate_camera_files([cap_dir], spec, Path(tmp) / "calib" / "camchain.yaml")
            truth = yaml.safe_load((cap_dir / "scene" / "board.yaml").read_text())
            cap = open_capture(cap_dir, calib=Path(tmp) / "calib" / "camchain.yaml")
            t0 = time.time()
            res = calibrate_with_board(cap, parse_board(spec), cap.imu_calib)
            took = time.time() - t0
        T = np.asarray(truth["body_T_cam"])
        rot_err = Rotation.from_matrix(T[:3, :3].T @ res.body_T_cam[:3, :3]).as_rotvec()
        rot_err_body = T[:3, :3] @ rot_err
        trans_err = res.body_T_cam[:3, 3] - T[:3, 3]
        off_err = res.timeshift_ns * 1e-9 - truth["timeshift_cam_imu_s"]
        rows.append(
            [
                np.rad2deg(np.linalg.norm(rot_err)),
                1e3 * np.linalg.norm(trans_err),
                1e3 * abs(off_err),
                *(rot_err_body / res.rotation_std_rad),
                *(trans_err / res.translation_std_m),
                off_err / (res.timeshift_std_ns * 1e-9),
            ]
        )
        print(
            f"seed {seed}: offset {offset_s * 1e3:+.1f} ms; errors: rotation {rows[-1][0]:.3f} deg, translation "
            f"{rows[-1][1]:.2f} mm, offset {rows[-1][2]:.3f} ms; sigma: rotation "
            + " ".join(f"{v:.3f}" for v in np.rad2deg(res.rotation_std_rad))
            + " deg, translation "
            + " ".join(f"{v:.2f}" for v in 1e3 * res.translation_std_m)
            + f" mm, offset {res.timeshift_std_ns * 1e-6:.3f} ms; excited {res.excited}; camera-imu {took:.1f} s",
            flush=True,
        )
    r = np.array(rows)
    for k, (name, unit, limit) in enumerate(
        (("rotation", "deg", 0.2), ("translation", "mm", 5.0), ("offset", "ms", 1))
    ):
        print(
            f"{name}: median {np.median(r[:, k]):.3f} {unit}, range {r[:, k].min():.3f}-{r[:, k].max():.3f}; "
            f"within {limit:g} {unit}: {int((r[:, k] < limit).sum())} of {len(r)}"
        )
    z = r[:, 3:]
    print(
        "error / stated sigma, RMS over seeds: rotation "
        + " ".join(f"{v:.2f}" for v in np.sqrt(np.mean(z[:, 0:3] ** 2, 0)))
        + ", translation "
        + " ".join(f"{v:.2f}" for v in np.sqrt(np.mean(z[:, 3:6] ** 2, 0)))
        + f", offset {np.sqrt(np.mean(z[:, 6] ** 2)):.2f}"
    )


if __name__ == "__main__":
    what, *rest = sys.argv[1:]
    if what == "camera":
        camera(rest[0], range(int(rest[1]), int(rest[2])))
    elif what == "camera-imu":
        camera_imu(rest[0], float(rest[1]), range(int(rest[2]), int(rest[3])))
    else:
        imu(float(rest[0]), float(rest[1]), range(int(rest[2]), int(rest[3])))
