"""ASL/EuRoC and TUM-VI folders: `read_asl` reads the layout, `open_asl` adds the calibration lookup.

Layout (`mav0/` under the capture root):
  cam0/data.csv (`#timestamp [ns],filename`), cam0/data/<t_ns>.png, cam0/sensor.yaml (Kalibr names)
  imu0/data.csv (`#timestamp [ns],w_x,w_y,w_z [rad/s],a_x,a_y,a_z [m/s^2]`), imu0/sensor.yaml
  state_groundtruth_estimate0/data.csv (t_ns, p [m], q_wxyz, v [m/s], b_w [rad/s], b_a [m/s^2]), optional
and, for synthetic captures, `scene/` with `object.stl` (metres) and `scene.yaml`.

TUM-VI exports the same layout (`mav0/cam0/data.csv`, `mav0/imu0/data.csv`, `mav0/mocap0/data.csv`) but keeps its
Kalibr calibration in `dso/camchain.yaml` with the equidistant (fisheye) model, which this project does not
support: a TUM-VI capture needs a pinhole-radtan calibration through `--calib`.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from vio.capture import Capture, Stills
from vio.errors import CalibrationError, CaptureError
from vio.kalibr import read_camera_yaml, read_imu_yaml
from vio.readers.calib import find_calibration, load_calibration
from vio.readers.common import FRAME_GAP_FACTOR, collect, imu_from_table
from vio.readers.tables import Table, increasing_mask, read_strict_table, read_table, strict_rows
from vio.readers.validate import gap_warnings
from vio.records import CameraCalib, GroundTruth, ImuSeries

GT_LAYOUT = "t_ns, p, q_wxyz, v, b_w, b_a"


def read_imu_csv(path: Path, warnings: list[str] | None = None) -> ImuSeries:
    """Read `imu0/data.csv` (t_ns, gyro rad/s, acc m/s^2). Bad rows follow `vio.readers.tables`' policy; gaps warn."""
    warn: list[str] = [] if warnings is None else warnings
    table = read_table(path, 0, [1, 2, 3, 4, 5, 6], warnings=warn, what="IMU")
    if len(table) == 0:
        raise CaptureError("no IMU samples", path)
    return imu_from_table(table, warn)


def read_groundtruth_csv(path: Path) -> GroundTruth:
    """Read `state_groundtruth_estimate0/data.csv`: 17 columns, t_ns then p, q_wxyz (normalised here), v, b_w, b_a."""
    table = read_strict_table(path, 17, "ground-truth", GT_LAYOUT)
    if len(table) == 0:
        raise CaptureError("no ground-truth rows", path)
    finite = np.isfinite(table.values).all(axis=1)
    if not finite.all():
        raise CaptureError("NaN in ground truth", path, int(table.rows[np.flatnonzero(~finite)[0]]))
    table = table.select(increasing_mask(table, "ground-truth"))
    v = table.values
    q = v[:, 3:7] / np.linalg.norm(v[:, 3:7], axis=1, keepdims=True)
    return GroundTruth(table.t_ns, v[:, 0:3], q, v[:, 7:10], v[:, 10:13], v[:, 13:16])


def _read_frame_list(path: Path) -> tuple[Table, list[str]]:
    """`cam0/data.csv` rows `t_ns,filename`: the times as a Table without value columns, and the file names."""
    t_ns: list[int] = []
    names: list[str] = []
    rows: list[int] = []
    for lineno, _, t, fields in strict_rows(path, 2, "frame", "timestamp,filename"):
        t_ns.append(t)
        names.append(fields[0])
        rows.append(lineno)
    n = len(t_ns)
    return Table(path, None, np.asarray(t_ns, np.int64), np.zeros((n, 0)), np.asarray(rows, np.int64)), names


def find_mav0(root: Path) -> Path:
    """The folder holding `cam0/` or `imu0/`: `root/mav0`, or `root` itself."""
    root = Path(root)
    if not root.exists():
        raise CaptureError("capture folder not found", root)
    for cand in (root / "mav0", root):
        if (cand / "cam0").is_dir() or (cand / "imu0").is_dir():
            return cand
    raise CaptureError("not an ASL/EuRoC capture (no mav0/cam0 or mav0/imu0 folder)", root)


def _frames(cam_csv: Path, warnings: list[str]) -> tuple[np.ndarray, list[Path]]:
    """Frame times (ns) and image paths of `camN/data.csv`: repeated times and missing images are skipped."""
    table, names = _read_frame_list(cam_csv)
    keep = increasing_mask(table, "frame", warnings)
    data_dir = cam_csv.parent / "data"
    present = set(os.listdir(data_dir)) if data_dir.is_dir() else set()
    exists = np.array([n in present for n in names], bool)
    if not exists.all():
        first = int(np.flatnonzero(~exists)[0])
        row = int(table.rows[first])
        if not exists.any():
            raise CaptureError(f"none of the {len(names)} listed images exist in {data_dir}", cam_csv, row)
        warnings.append(
            f"{cam_csv}:{row}: {int((~exists).sum())} listed image(s) missing, frames skipped (first: {names[first]})"
        )
    keep &= exists
    table = table.select(keep)
    warnings += gap_warnings(table.t_ns, table.rows, cam_csv, "frame", FRAME_GAP_FACTOR)
    return table.t_ns, [data_dir / n for n, k in zip(names, keep, strict=True) if k]


def read_asl(root: str | os.PathLike[str], problems: list[str] | None = None) -> Capture:
    """Read an ASL/EuRoC capture folder (the folder holding `mav0/`, or `mav0/` itself) with its own calibration.

    With a `problems` list, a stream that cannot be read is left out and its error appended there (`vio info`)."""
    root = Path(root)
    mav0 = find_mav0(root)
    warnings: list[str] = []
    cam_yaml, imu_yaml, imu_csv = (
        mav0 / "cam0" / "sensor.yaml",
        mav0 / "imu0" / "sensor.yaml",
        mav0 / "imu0" / "data.csv",
    )
    camera = collect(lambda: read_camera_yaml(cam_yaml), None, problems) if cam_yaml.exists() else None
    imu_calib = collect(lambda: read_imu_yaml(imu_yaml), None, problems) if imu_yaml.exists() else None
    imu = collect(lambda: read_imu_csv(imu_csv, warnings), None, problems) if imu_csv.exists() else None
    frame_t, paths = np.zeros(0, np.int64), []
    if (mav0 / "cam0" / "data.csv").exists():
        frame_t, paths = collect(lambda: _frames(mav0 / "cam0" / "data.csv", warnings), (frame_t, paths), problems)
    gt_csv = mav0 / "state_groundtruth_estimate0" / "data.csv"
    gt = collect(lambda: read_groundtruth_csv(gt_csv), None, problems) if gt_csv.exists() else None
    scene = root / "scene" if (root / "scene").is_dir() else None
    fmt = "tumvi" if (mav0 / "mocap0").is_dir() or (root / "dso").is_dir() else "asl"
    cap = Capture(root, camera, imu_calib, imu, frame_t, _loader(paths), gt, scene, [], fmt)
    cap.stills = _stills(mav0, camera, warnings)
    for w in warnings:
        cap.warn(w)
    return cap


def _loader(paths: list[Path]) -> Callable[[int], np.ndarray]:
    def load(i: int) -> np.ndarray:
        p = paths[i]
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise CaptureError("image missing or cannot be decoded", p)
        return img

    return load


def _stills(mav0: Path, video: CameraCalib | None, warnings: list[str]) -> Stills | None:
    """`cam1` as a stills stream: a calibrated camera whose images are larger than cam0's (EuRoC's and TUM-VI's
    cam1, the right camera of a stereo pair of the same size, is not stills)."""
    yaml_path, csv_path = mav0 / "cam1" / "sensor.yaml", mav0 / "cam1" / "data.csv"
    if video is None or not yaml_path.exists() or not csv_path.exists():
        return None
    cam = read_camera_yaml(yaml_path)
    if cam.width * cam.height <= video.width * video.height:
        return None
    t_ns, paths = _frames(csv_path, warnings)
    return Stills(cam, t_ns, _loader(paths))


def open_asl(root: Path, calib: str | Path | None = None, problems: list[str] | None = None) -> Capture:
    """Read an ASL/EuRoC or TUM-VI folder; `calib` (a camchain YAML or ASL folder) replaces its calibration.
    `problems`: see `read_asl`."""
    cap = read_asl(root, problems)
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
    for w in cal.warnings:
        cap.warn(w)
    cap.camera = cal.camera
    if cal.imu is not None:
        cap.imu_calib = cal.imu
    if cal.timeshift_cam_imu_ns:
        cap.frame_t_ns = cap.frame_t_ns + cal.timeshift_cam_imu_ns
    return cap
