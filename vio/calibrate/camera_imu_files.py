"""`vio calibrate camera-imu CAPTURE --calib camchain.yaml --out camchain-imu.yaml`: a capture of the board (or one
with feature tracks) and the camera's intrinsics in; Kalibr's camchain-imu YAML and a report out.

The camchain (`--out`) is the given one with the calibrated `T_cam_imu` and `timeshift_cam_imu`; beside it goes
`camera_imu_calibration.json` (every figure with its standard deviation, the excitation verdicts and the rotation
step's own estimate) and `camera_imu_alignment.png` (the speeds' cross-correlation and the aligned speeds). All are
written atomically; `vio run --calib` reads the camchain (IMU noise from an `imu0:` section or an IMU YAML beside
it, as for every camchain). The board: `--board`, else the `board_spec` that
`vio calibrate camera` stored in `camera_calibration.json` beside `--calib`; without a board, a capture with feature
tracks (gtsam's eqvio file) gives the rotation and time offset. Without `--calib` the capture's own camera
calibration is used (its intrinsics; its camera-IMU extrinsic only for the translation when there is no board).
"""

from __future__ import annotations

import json
import logging
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from vio.atomic import write_bytes, write_json, write_text
from vio.calibrate.board import parse_board
from vio.calibrate.camera_imu import (
    CameraImuCalibration,
    calibrate_with_board,
    calibrate_with_tracks,
    frame_period_s,
)
from vio.errors import CalibrationError, OutputError
from vio.kalibr import camchain_yaml_text
from vio.readers.calib import PHONE_IMU_DEFAULT, load_calibration

log = logging.getLogger(__name__)


def _board_spec(board: str | None, calib: Path | None) -> str | None:
    if board or calib is None:
        return board
    report = Path(calib).parent / "camera_calibration.json"
    if report.is_file():
        try:
            spec = json.loads(report.read_text(encoding="utf-8")).get("board_spec")
        except (OSError, ValueError):
            spec = None
        if isinstance(spec, str):
            return spec
    return None


def summary_text(res: CameraImuCalibration, noise_source: str) -> str:
    """What a person reads after a camera-IMU calibration."""
    rpy = Rotation.from_matrix(res.body_T_cam[:3, :3]).as_euler("xyz", degrees=True)
    rot_std = np.rad2deg(res.rotation_std_rad)
    yes = {True: "excited", False: "WEAKLY excited", None: "not estimated"}
    lines = [
        f"camera-IMU ({res.method}): {res.frames_used} of {res.frames_total} frames used; IMU noise {noise_source}",
        "  rotation body_R_cam (xyz Euler) "
        + " ".join(f"{a:+.3f}" for a in rpy)
        + " deg, 1 sigma "
        + " ".join(f"{s:.3f}" for s in rot_std)
        + f" deg: {yes[res.excited['rotation']]}",
    ]
    t_mm = res.body_T_cam[:3, 3] * 1e3
    if res.translation_std_m is None:
        lines.append(
            "  translation "
            + " ".join(f"{v:+.1f}" for v in t_mm)
            + " mm: kept from the given calibration (not estimated)"
        )
    else:
        t_std = res.translation_std_m * 1e3
        lines.append(
            "  translation "
            + " ".join(f"{v:+.1f}" for v in t_mm)
            + " mm, 1 sigma "
            + " ".join(f"{s:.1f}" for s in t_std)
            + f" mm: {yes[res.excited['translation']]}"
        )
    lines.append(
        f"  timeshift_cam_imu {res.timeshift_ns * 1e-6:+.2f} ms, 1 sigma {res.timeshift_std_ns * 1e-6:.2f} ms: "
        f"{yes[res.excited['time_offset']]} (t_imu = t_cam + shift; cross-correlation "
        f"{res.rotation_step.offset_xcorr_ns * 1e-6:+.1f} ms)"
    )
    lines += [f"  note: {n}" for n in res.notes]
    return "\n".join(lines)


def calibrate_camera_imu_files(
    capture: str | Path,
    calib: str | Path | None,
    out: str | Path,
    board: str | None = None,
    detector: str = "classic",
    max_offset_ms: float = 200.0,
) -> str:
    """Calibrate and write the files (module docstring); returns the summary text."""
    from vio.readers import open_capture

    out = Path(out)
    if out.suffix.lower() not in (".yaml", ".yml"):
        raise OutputError(f"{out}: --out names the camchain YAML to write, e.g. calib/camchain-imu.yaml")
    if out.parent.exists() and not out.parent.is_dir():
        raise OutputError(f"{out.parent}: a file is in the way of the output folder")
    if not np.isfinite(max_offset_ms) or not 0 < max_offset_ms <= 1000:
        raise CalibrationError(f"--max-offset-ms must be between 0 and 1000, got {max_offset_ms:g}")
    if calib is not None:
        cal = load_calibration(calib)
        if cal.camera is None:
            raise CalibrationError(f"{calib}: no camera in the calibration")
        read_shift_ns = cal.timeshift_cam_imu_ns
    cap = open_capture(capture, calib=calib)
    if calib is None:  # the capture's own calibration (e.g. gtsam's eqvio file, whose tracks are undistorted)
        if cap.camera is None:
            raise CalibrationError(f"{capture}: the capture has no camera calibration; pass --calib camchain.yaml")
        read_shift_ns = 0
    if cap.imu is None or len(cap.imu) < 10:
        raise CalibrationError(f"{capture}: the capture has no IMU stream")
    assert cap.camera is not None
    noise, source = cap.imu_calib, "from the calibration or the capture"
    if noise is None:
        noise, source = PHONE_IMU_DEFAULT, "assumed (a typical phone IMU; pass an imu.yaml beside --calib)"
    spec = _board_spec(board, None if calib is None else Path(calib))
    if spec is not None:
        res = calibrate_with_board(cap, parse_board(spec), noise, detector, max_offset_ms * 1e-3, read_shift_ns)
    elif cap.tracks:
        res = calibrate_with_tracks(cap, max_offset_ms * 1e-3, read_shift_ns)
    else:
        raise CalibrationError(
            f"{capture}: which board? pass --board (e.g. chessboard:9x6:30), or calibrate the camera with "
            "vio calibrate camera, whose camera_calibration.json names it"
        )
    rate_hz = 1.0 / frame_period_s(cap)  # the capture's own (a camchain from still images carries a guess)
    camera = replace(cap.camera, body_T_cam=res.body_T_cam, rate_hz=round(rate_hz, 3))
    given = "the capture's own calibration" if calib is None else Path(calib).name
    header = f"vio calibrate camera-imu ({res.method}) of {Path(capture).name} with {given}"
    note = header + "\n" + summary_text(res, source).replace("  ", "")
    write_text(out, camchain_yaml_text(camera, comment=note, timeshift_s=res.timeshift_ns * 1e-9))
    report = out.parent / "camera_imu_calibration.json"
    write_json(report, {"capture": str(capture), "calib": str(calib), "imu_noise": source, **res.summary()})
    from vio.calibrate.camera_imu_figures import alignment_png

    picture = out.parent / "camera_imu_alignment.png"
    write_bytes(picture, alignment_png(res, cap.imu, read_shift_ns))
    return summary_text(res, source) + f"\nwrote {out}, {report.name}, {picture.name}"
