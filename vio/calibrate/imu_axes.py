"""The accelerometer's scale factors and axis non-orthogonality from a multi-position log (`vio calibrate imu-axes`).

A phone accelerometer's axes are off by about 1 % in scale and some tenths of a degree in angle (datasheet tolerances;
the simulator's `PhoneImu`), and an orbit cannot find them: the phone keeps nearly the same attitude, so gravity
stays on the same axes and a scale error there reads as bias. They matter: over thirty simulated phone IMUs on the
60 s orbit, with perfect images, they nearly double the spread of the metric scale (docs/BENCHMARKS.md, "The phone
accelerometer's axes"). They are found the way a multi-position calibration finds them (Tedaldi, Pretto and
Menegatti, ICRA 2014): lay the phone still in many orientations (at least 15; 20-30 with the six faces among them),
turning it between them. In each still stretch the accelerometer reads gravity alone, whose magnitude is known.

Model: measured = T a + b + noise, with a the true specific force. K = T^-1 is fitted as an upper-triangular matrix
(three scales and three axis angles; the rotation part of T does not change a magnitude, so it is not observable
here and is left to the camera-IMU extrinsic) together with b, by least squares on |K (m_i - b)| = g over the still
stretches' mean readings m_i. `vio run --imu-axes FILE` applies K to every accelerometer sample; the bias stays the
estimator's to find (it drifts from day to day anyway).

The scale of K is that of the gravity it is fitted to, and the metric scale of every run with it inherits that:
gravity is 9.780 m/s^2 at the equator and 9.832 at the poles, 0.3 % either side of the 9.81 assumed when nothing is
given. `--latitude` (and `--height`) gives the local value by the WGS 84 normal gravity formula (Somigliana's, with
the free-air gradient), `--gravity` a measured one.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml
from scipy.optimize import least_squares

from vio.atomic import write_text
from vio.errors import CalibrationError, OutputError
from vio.kalibr import read_yaml
from vio.records import GRAVITY_M_S2, ImuSeries

STILL_WINDOW_S = 0.2  # the gyro rate is smoothed over this before the still test
STILL_GYRO_RAD_S = 0.05  # smoothed |gyro| under this: at rest (phone gyro biases are up to ~0.02 rad/s)
MIN_STILL_S = 1.0  # a still stretch shorter than this (after the trims) is not used
TRIM_S = 0.25  # cut at both ends of a still stretch: the turn's last and first moments
# nine unknowns, but with 9-12 orientations the fit can land far off with a small stated sigma (simulated tumbles, seeds
# 201-230: 11 of 30 off by more than 0.5 % with 9, 1 with 12, none with 16; docs/BENCHMARKS.md)
MIN_POSES = 15
MAX_SPREAD_DEG = 2.0  # the same orientation twice (within this) counts once for the coverage test
MAX_CORRECTION = 0.1  # a correction further than this from identity (10 %) is not a phone's axes
MIN_COVERAGE = 0.25  # smallest singular value of the unit gravity directions / sqrt(n) (1/sqrt(3) at best): below,
# gravity did not cover the axes well enough (a phone turned about one axis only)


@dataclass(frozen=True)
class AccAxes:
    """The fit: `correction` K (3, 3) applied to measured specific force (a = K (m - b)), with its bias and figures."""

    correction: np.ndarray  # (3, 3) upper triangular K
    bias: np.ndarray  # (3,) m/s^2, at the time of the log (informative only: the estimator finds its own)
    gravity_m_s2: float
    poses: int  # still stretches used
    residual_rms_m_s2: float  # of |K (m_i - b)| - g
    before_rms_m_s2: float  # the same with K = I, b = 0
    scale_sigma: np.ndarray  # (3,) 1-sigma of the diagonal of K (fraction)
    coverage: float  # smallest singular value of the unit gravity directions over sqrt(poses)

    def yaml_dict(self, comment: str) -> dict:
        return {
            "comment": comment,
            "model": "a = K (m - b); K upper triangular (scale factors and axis non-orthogonality)",
            "accelerometer_correction": [[round(float(v), 9) for v in row] for row in self.correction],
            "accelerometer_bias_at_log": [round(float(v), 6) for v in self.bias],
            "gravity_m_s2": self.gravity_m_s2,
            "poses": self.poses,
            "residual_rms_m_s2": round(self.residual_rms_m_s2, 6),
            "scale_sigma": [round(float(v), 7) for v in self.scale_sigma],
        }


def still_stretches(imu: ImuSeries) -> list[tuple[int, int]]:
    """Index ranges [i0, i1) where the IMU is at rest for at least `MIN_STILL_S` (after `TRIM_S` at each end)."""
    t = (imu.t_ns - imu.t_ns[0]) * 1e-9
    if len(t) < 10:
        return []
    dt = float(np.median(np.diff(t)))
    w = max(int(round(STILL_WINDOW_S / dt)), 1)
    rate = np.convolve(np.linalg.norm(imu.gyro, axis=1), np.ones(w) / w, mode="same")
    still = np.concatenate([[False], rate < STILL_GYRO_RAD_S, [False]])
    edges = np.flatnonzero(np.diff(still.astype(np.int8)))
    out = []
    for a, b in zip(edges[::2], edges[1::2], strict=True):
        i0 = int(np.searchsorted(t, t[a] + TRIM_S))
        i1 = int(np.searchsorted(t, t[b - 1] - TRIM_S, side="right"))
        if i1 > i0 and t[i1 - 1] - t[i0] >= MIN_STILL_S:
            out.append((i0, i1))
    return out


def _upper(x: np.ndarray) -> np.ndarray:
    K = np.diag(x[:3])
    K[0, 1], K[0, 2], K[1, 2] = x[3], x[4], x[5]
    return K


def fit_acc_axes(imu: ImuSeries, gravity_m_s2: float = GRAVITY_M_S2) -> AccAxes:
    """Fit K and b (module docstring) from the log's still stretches; CalibrationError when the log cannot tell."""
    spans = still_stretches(imu)
    if len(spans) < MIN_POSES:
        raise CalibrationError(
            f"{len(spans)} still orientations found, {MIN_POSES} needed (lay the phone still for 2-3 s in 20-30 "
            "orientations, turning it between them)"
        )
    m = np.array([imu.acc[i0:i1].mean(axis=0) for i0, i1 in spans])
    u = m / np.linalg.norm(m, axis=1, keepdims=True)
    coverage = float(np.linalg.svd(u, compute_uv=False)[-1] / np.sqrt(len(u)))
    if coverage < MIN_COVERAGE:
        raise CalibrationError(
            f"gravity did not cover the accelerometer's axes (coverage {coverage:.2f} < {MIN_COVERAGE}): turn the "
            "phone onto each of its six faces and in between, not about one axis only"
        )

    def residual(x: np.ndarray) -> np.ndarray:
        return np.linalg.norm((m - x[6:]) @ _upper(x[:6]).T, axis=1) - gravity_m_s2

    x0 = np.array([1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    sol = least_squares(residual, x0, method="lm")
    r = sol.fun
    dof = max(len(r) - len(x0), 1)
    s2 = float(r @ r) / dof
    try:
        cov = np.linalg.inv(sol.jac.T @ sol.jac) * s2
    except np.linalg.LinAlgError as exc:
        raise CalibrationError("the multi-position fit is singular (too few distinct orientations)") from exc
    return AccAxes(
        correction=_upper(sol.x[:6]),
        bias=sol.x[6:].copy(),
        gravity_m_s2=float(gravity_m_s2),
        poses=len(spans),
        residual_rms_m_s2=float(np.sqrt(np.mean(r**2))),
        before_rms_m_s2=float(np.sqrt(np.mean((np.linalg.norm(m, axis=1) - gravity_m_s2) ** 2))),
        scale_sigma=np.sqrt(np.diag(cov)[:3]),
        coverage=coverage,
    )


def corrected(imu: ImuSeries, correction: np.ndarray) -> ImuSeries:
    """The same series with every accelerometer sample multiplied by `correction` (K)."""
    K = np.asarray(correction, float).reshape(3, 3)
    return ImuSeries(imu.t_ns, imu.gyro, np.ascontiguousarray(imu.acc @ K.T))


def read_correction(path: str | Path) -> np.ndarray:
    """K (3, 3) from a file written by `vio calibrate imu-axes`; CalibrationError naming the file otherwise."""
    data = read_yaml(Path(path))
    try:
        K = np.asarray(data["accelerometer_correction"], float)
    except (KeyError, TypeError, ValueError):
        raise CalibrationError(f"{path}: no accelerometer_correction (a 3 x 3 matrix) in it") from None
    if K.shape != (3, 3) or not np.isfinite(K).all() or np.abs(K - np.eye(3)).max() > MAX_CORRECTION:
        raise CalibrationError(
            f"{path}: accelerometer_correction must be a finite 3 x 3 matrix within {MAX_CORRECTION:g} of identity"
        )
    return K


def normal_gravity(latitude_deg: float, height_m: float = 0.0) -> float:
    """WGS 84 normal gravity, m/s^2, at a geodetic latitude and a height above the ellipsoid (Somigliana's closed
    form; free-air gradient 3.086e-6 s^-2: good to about 0.01 % away from mountains and gravity anomalies)."""
    s2 = np.sin(np.radians(latitude_deg)) ** 2
    g0 = 9.7803253359 * (1.0 + 0.00193185265241 * s2) / np.sqrt(1.0 - 0.00669437999013 * s2)
    return float(g0 - 3.086e-6 * height_m)


def local_gravity(gravity: float | None, latitude_deg: float | None, height_m: float) -> tuple[float, str]:
    """The gravity to fit to and where it came from; CalibrationError for a value no place on Earth has."""
    if gravity is not None and latitude_deg is not None:
        raise CalibrationError("give --gravity or --latitude, not both")
    if latitude_deg is not None:
        if not -90.0 <= latitude_deg <= 90.0:
            raise CalibrationError(f"--latitude must be between -90 and 90 degrees, got {latitude_deg:g}")
        g, source = normal_gravity(latitude_deg, height_m), f"WGS 84 normal gravity at {latitude_deg:g} deg"
    elif gravity is not None:
        g, source = float(gravity), "given"
    else:
        g, source = GRAVITY_M_S2, "assumed (give --latitude for your local gravity: the scale inherits its error)"
    if not 9.7 <= g <= 9.9:
        raise CalibrationError(f"gravity {g:g} m/s^2 is not a surface gravity on Earth (9.7-9.9 accepted)")
    return g, source


def calibrate_imu_axes_files(
    log_path: str | Path,
    out: str | Path,
    gravity: float | None = None,
    latitude_deg: float | None = None,
    height_m: float = 0.0,
) -> str:
    """`vio calibrate imu-axes LOG --out FILE.yaml [--gravity G | --latitude DEG [--height M]]`: fit (module
    docstring), write the YAML, return the summary."""
    from vio.readers import open_capture

    out = Path(out)
    if out.suffix.lower() not in (".yaml", ".yml"):
        raise OutputError(f"{out}: --out names the YAML to write, e.g. calib/imu_axes.yaml")
    g, source = local_gravity(gravity, latitude_deg, height_m)
    capture = open_capture(log_path, needs=("imu",))
    fit = fit_acc_axes(capture.imu, g)
    comment = f"vio calibrate imu-axes: {fit.poses} still orientations of {Path(log_path).name}"
    write_text(out, yaml.safe_dump(fit.yaml_dict(comment), sort_keys=False))
    K = fit.correction
    return "\n".join(
        [
            f"{fit.poses} still orientations (gravity coverage {fit.coverage:.2f} of at most 0.58)",
            "scale corrections x / y / z: "
            + " / ".join(f"{(K[i, i] - 1) * 100:+.3f} %" for i in range(3))
            + " (1 sigma "
            + " / ".join(f"{s * 100:.3f}" for s in fit.scale_sigma)
            + " %)",
            "axis angles (non-orthogonality) xy / xz / yz: "
            + " / ".join(f"{np.degrees(v):+.3f} deg" for v in (K[0, 1], K[0, 2], K[1, 2])),
            f"gravity {g:.5f} m/s^2, {source}",
            f"|gravity| misfit RMS {fit.before_rms_m_s2:.4f} -> {fit.residual_rms_m_s2:.4f} m/s^2",
            f"wrote {out} (use it with: vio run CAPTURE --set imu.axes={out})",
        ]
    )
