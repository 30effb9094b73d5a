"""`vio calibrate camera`: images or a video in, a Kalibr camchain, an ASL `sensor.yaml`, pictures and a report out.

Beside the camchain (`--out`, e.g. `calib/camchain.yaml`) go `cam0/sensor.yaml` (ASL), `camera_coverage.png`,
`camera_residuals.png` and `camera_calibration.json`; every file is written atomically. `vio run --calib` reads the
camchain or the folder. A camera calibration does not observe the camera-IMU extrinsic: `T_cam_imu` is the nominal
`mount` (see MOUNTS), marked as such in the files, until a camera-IMU calibration replaces it.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from vio.atomic import write_bytes, write_json, write_text
from vio.calibrate.board import BoardDetector, parse_board
from vio.calibrate.camera import CameraCalibration, calibrate_camera
from vio.calibrate.views import ViewSet, find_views
from vio.errors import CalibrationError, OutputError
from vio.kalibr import camchain_yaml_text, camera_yaml_text
from vio.records import CameraCalib

# Nominal camera poses in the IMU body frame (body_T_cam rotation), used until camera-IMU calibration exists.
# phone: the rear camera of an Android phone in its sensor's native (landscape) orientation: IMU x right, y up,
# z out of the screen; the camera looks along body -z, image x along body -y, image y along body -x.
MOUNTS = {
    "phone": np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]),
    "identity": np.eye(3),
}
MAX_NAMES_SHOWN = 5  # views named per reason in the summary (camera_calibration.json lists them all)
DEFAULT_RATE_HZ = 30.0  # written for still images, whose frame rate the calibration cannot know
KALIBR_MODEL = {"radtan": "radtan", "equidistant": "equidistant"}
ASL_MODEL = {"radtan": "radial-tangential", "equidistant": "equidistant"}


def _camera_record(cal: CameraCalibration, mount: str, rate_hz: float) -> CameraCalib:
    body_T_cam = np.eye(4)
    body_T_cam[:3, :3] = MOUNTS[mount]
    return CameraCalib(cal.width, cal.height, cal.fx, cal.fy, cal.cx, cal.cy, cal.dist, body_T_cam, rate_hz)


def _report(cal: CameraCalibration, vs: ViewSet, board_text: str, mount: str, rate_hz: float, spec: str) -> dict:
    return {
        "board": board_text,
        "board_spec": spec,  # read back by vio calibrate camera-imu
        "model": cal.model,
        "resolution": [cal.width, cal.height],
        "params": cal.params(),
        "std": cal.std,
        "rms_px": cal.rms_px,
        "coverage": cal.coverage,
        "views": [{"name": n, "rms_px": float(r)} for n, r in zip(cal.view_names, cal.view_rms_px, strict=True)],
        "dropped": [{"name": n, "reason": r} for n, r in list(vs.rejected) + list(cal.dropped)],
        "rate_hz": rate_hz,
        "T_cam_imu": f"nominal '{mount}' mount, not calibrated",
    }


def summary_text(cal: CameraCalibration, vs: ViewSet, board_text: str) -> str:
    """What a person reads after a camera calibration: parameters with one sigma, RMS, coverage, dropped views."""
    n_seen = len(vs.views) + len(vs.rejected)
    lines = [
        f"camera: pinhole-{cal.model} {cal.width}x{cal.height} from {len(cal.view_names)} of {n_seen} views "
        f"({board_text})",
        "  " + "  ".join(f"{k} {v:.3f} +- {cal.std[k]:.3f} px" for k, v in list(cal.params().items())[:4]),
        "  " + "  ".join(f"{k} {v:.5g} +- {cal.std[k]:.2g}" for k, v in list(cal.params().items())[4:]),
        f"  RMS {cal.rms_px:.3f} px (views {cal.view_rms_px.min():.3f}-{cal.view_rms_px.max():.3f} px), "
        f"coverage {100 * cal.coverage:.0f} % of the image cells",
    ]
    for name, reason in cal.dropped:  # outliers: each by name
        lines.append(f"  dropped {name}: {reason}")
    by_reason: dict[str, list[str]] = {}
    for name, reason in vs.rejected:
        by_reason.setdefault(reason, []).append(name)
    for reason, names in by_reason.items():
        shown = ", ".join(names[:MAX_NAMES_SHOWN]) + (", ..." if len(names) > MAX_NAMES_SHOWN else "")
        lines.append(f"  not used ({reason}): {len(names)} view(s): {shown}")
    return "\n".join(lines)


def calibrate_camera_files(
    inputs: Sequence[str | Path],
    board_spec: str,
    out: str | Path,
    model: str = "radtan",
    detector: str = "classic",
    max_views: int = 40,
    mount: str = "phone",
    rate_hz: float | None = None,
) -> str:
    """Calibrate from images or one video and write the files (module docstring); returns the summary text."""
    out = Path(out)
    if out.suffix.lower() not in (".yaml", ".yml"):
        raise OutputError(f"{out}: --out names the camchain YAML to write, e.g. calib/camchain.yaml")
    if model not in KALIBR_MODEL:
        raise CalibrationError(f"--model must be radtan or equidistant, got {model!r}")
    if mount not in MOUNTS:
        raise CalibrationError(f"--mount must be one of {', '.join(MOUNTS)}, got {mount!r}")
    board = parse_board(board_spec)
    vs = find_views(inputs, BoardDetector(board, detector), max_views=max_views)
    cal = calibrate_camera(vs.views, board, vs.image_size, model)
    rate = float(rate_hz or vs.rate_hz or DEFAULT_RATE_HZ)
    cam = _camera_record(cal, mount, rate)
    note = (
        f"vio calibrate camera: {board.describe()}, {len(cal.view_names)} views, RMS {cal.rms_px:.3f} px\n"
        f"T_cam_imu: the nominal '{mount}' mount, NOT calibrated (replace it with a camera-IMU calibration)"
    )
    folder = out.parent
    sensor_yaml = folder / "cam0" / "sensor.yaml"
    for path in (sensor_yaml.parent, folder):
        if path.exists() and not path.is_dir():
            raise OutputError(f"{path}: a file is in the way of the output folder")
    write_text(out, camchain_yaml_text(cam, KALIBR_MODEL[model], comment=note))
    write_text(sensor_yaml, camera_yaml_text(cam, note.replace("\n", "; "), ASL_MODEL[model]))
    from vio.calibrate.figures import coverage_png, residuals_png

    write_bytes(folder / "camera_coverage.png", coverage_png(cal))
    write_bytes(folder / "camera_residuals.png", residuals_png(cal))
    write_json(folder / "camera_calibration.json", _report(cal, vs, board.describe(), mount, rate, board_spec))
    lines = [summary_text(cal, vs, board.describe())]
    lines.append(f"  T_cam_imu: nominal '{mount}' mount, not calibrated")
    if model != "radtan":
        lines.append(f"  note: vio run reads pinhole-radtan only; this {model} calibration is for other tools")
    lines.append(f"wrote {out}, {sensor_yaml}, camera_coverage.png, camera_residuals.png, camera_calibration.json")
    return "\n".join(lines)
