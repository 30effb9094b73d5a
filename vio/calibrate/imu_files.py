"""`vio calibrate imu`: a static log in, a Kalibr `imu.yaml`, an ASL `imu0/sensor.yaml`, plots and a report out.

Beside `--out` (e.g. `calib/imu.yaml`, which `vio run --calib calib/camchain.yaml` finds next to the camchain) go
`imu0/sensor.yaml`, `imu_allan_gyro.png`, `imu_allan_acc.png` and `imu_calibration.json`, written atomically.
"""

from __future__ import annotations

from pathlib import Path

from vio.atomic import write_bytes, write_json, write_text
from vio.calibrate.imu import AXES, RECOMMENDED_DURATION_S, ImuNoise, imu_noise
from vio.errors import OutputError
from vio.kalibr import imu_yaml_text, kalibr_imu_yaml_text


def _report(noise: ImuNoise, inflation: float) -> dict:
    def axes(fits):
        return {
            a: {
                "white": f.white,
                "random_walk": f.random_walk,
                "bias_instability": f.bias_instability,
                "tau_min_s": f.tau_min_s,
            }
            for a, f in zip(AXES, fits, strict=True)
        }

    k = noise.kalibr()
    values = {
        "gyroscope_noise_density": k.gyroscope_noise_density,
        "gyroscope_random_walk": k.gyroscope_random_walk,
        "accelerometer_noise_density": k.accelerometer_noise_density,
        "accelerometer_random_walk": k.accelerometer_random_walk,
    }
    return {
        "rate_hz": noise.rate_hz,
        "duration_s": noise.duration_s,
        "span_s": list(noise.span_s),
        "log_duration_s": noise.log_duration_s,
        "kalibr_worst_axis": values,
        "inflation": {"factor": inflation, "applied": False, "inflated": {n: v * inflation for n, v in values.items()}},
        "gyro_per_axis": axes(noise.gyro),
        "acc_per_axis": axes(noise.acc),
        "units": "gyro: rad/s/sqrt(Hz), rad/s^2/sqrt(Hz), bias instability rad/s; acc: m/s^2/sqrt(Hz), "
        "m/s^3/sqrt(Hz), m/s^2",
    }


def summary_text(noise: ImuNoise, inflation: float) -> str:
    k = noise.kalibr()
    lines = [f"imu: {noise.duration_s:.0f} s static at {noise.rate_hz:.1f} Hz (overlapping Allan deviation)"]
    if noise.duration_s < noise.log_duration_s - 1.5:
        a, b = noise.span_s
        lines.append(f"  used {a:.0f}-{b:.0f} s of the {noise.log_duration_s:.0f} s log (the IMU moved outside it)")
    for name, fits, u in (
        ("gyro", noise.gyro, ("rad/s/sqrt(Hz)", "rad/s^2/sqrt(Hz)", "deg/h")),
        ("acc", noise.acc, ("m/s^2/sqrt(Hz)", "m/s^3/sqrt(Hz)", "mg")),
    ):
        for a, f in zip(AXES, fits, strict=True):
            b = f.bias_instability * (180 / 3.141592653589793 * 3600 if name == "gyro" else 1e3 / 9.80665)
            lines.append(
                f"  {name} {a}: N {f.white:.3e} {u[0]}  K {f.random_walk:.3e} {u[1]}  "
                f"B {b:.3g} {u[2]} (at {f.tau_min_s:.0f} s)"
            )
    lines.append(
        f"  Kalibr (worst axis): gyroscope_noise_density {k.gyroscope_noise_density:.3e}, gyroscope_random_walk "
        f"{k.gyroscope_random_walk:.3e}, accelerometer_noise_density {k.accelerometer_noise_density:.3e}, "
        f"accelerometer_random_walk {k.accelerometer_random_walk:.3e}"
    )
    lines.append(
        f"  VIO users commonly inflate these x{inflation:g} for unmodelled effects (not applied; the inflated values "
        "are in imu_calibration.json)"
    )
    if noise.duration_s < 0.9 * RECOMMENDED_DURATION_S:
        lines.append(
            f"  note: {noise.duration_s:.0f} s is short for the random walk (the +1/2 line); record "
            f"{RECOMMENDED_DURATION_S / 3600:g} h or more"
        )
    return "\n".join(lines)


def calibrate_imu_files(log_path: str | Path, out: str | Path, inflation: float = 10.0) -> str:
    """Read a static log (any capture format vio reads), write the files (module docstring); returns the summary."""
    from vio.readers import open_capture

    out = Path(out)
    if out.suffix.lower() not in (".yaml", ".yml"):
        raise OutputError(f"{out}: --out names the Kalibr IMU YAML to write, e.g. calib/imu.yaml")
    if out.parent.exists() and not out.parent.is_dir():
        raise OutputError(f"{out.parent}: a file is in the way of the output folder")
    capture = open_capture(log_path, needs=("imu",))
    noise = imu_noise(capture.imu, str(log_path))
    k = noise.kalibr()
    comment = (
        f"vio calibrate imu: {noise.duration_s:.0f} s static log {Path(log_path).name}, overlapping Allan deviation, "
        "worst axis, continuous time, NOT inflated"
    )
    folder = out.parent
    write_text(out, kalibr_imu_yaml_text(k, comment))
    write_text(folder / "imu0" / "sensor.yaml", imu_yaml_text(k, comment))
    from vio.calibrate.figures import allan_png

    write_bytes(folder / "imu_allan_gyro.png", allan_png(noise.taus_s, noise.gyro_adev, noise.gyro, "rad/s", "gyro"))
    write_bytes(folder / "imu_allan_acc.png", allan_png(noise.taus_s, noise.acc_adev, noise.acc, "m/s^2", "acc"))
    write_json(folder / "imu_calibration.json", _report(noise, inflation))
    return (
        summary_text(noise, inflation) + f"\nwrote {out}, {folder / 'imu0' / 'sensor.yaml'}, imu_allan_gyro.png, "
        "imu_allan_acc.png, imu_calibration.json"
    )
