"""ASL/EuRoC and TUM-VI folders (`mav0/cam0`, `mav0/imu0`, ...): `vio.capture.read_asl` plus calibration lookup.

TUM-VI exports the same layout (`mav0/cam0/data.csv`, `mav0/imu0/data.csv`, `mav0/mocap0/data.csv`) but keeps its
Kalibr calibration in `dso/camchain.yaml` with the equidistant (fisheye) model, which this project does not
support: a TUM-VI capture needs a pinhole-radtan calibration through `--calib`.
"""

from __future__ import annotations

from pathlib import Path

from vio.capture import Capture, read_asl
from vio.errors import CalibrationError
from vio.readers.calib import find_calibration, load_calibration


def open_asl(root: Path, calib: str | Path | None = None) -> Capture:
    """Read an ASL/EuRoC or TUM-VI folder; `calib` (a camchain YAML or ASL folder) replaces its calibration."""
    cap = read_asl(root)
    if calib is not None:
        cal = load_calibration(calib)
    elif cap.camera is None:
        cal = find_calibration(Path(root))
        dso = Path(root) / "dso" / "camchain.yaml"
        if cal is None and dso.is_file():
            try:
                cal = load_calibration(dso)
            except CalibrationError as exc:
                cap.warn(f"{exc}; pass --calib with a pinhole-radtan calibration")
                return cap
    else:
        return cap
    if cal is None:
        return cap
    cap.camera = cal.camera
    if cal.imu is not None:
        cap.imu_calib = cal.imu
    if cal.timeshift_cam_imu_ns:
        cap.frame_t_ns = cap.frame_t_ns + cal.timeshift_cam_imu_ns
    return cap
