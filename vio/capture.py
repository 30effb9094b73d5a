"""The capture: what a recording holds, read from and written to the EuRoC/ASL layout.

Layout (`mav0/` under the capture root):
  cam0/data.csv (`#timestamp [ns],filename`), cam0/data/<t_ns>.png, cam0/sensor.yaml (Kalibr names)
  imu0/data.csv (`#timestamp [ns],w_x,w_y,w_z [rad/s],a_x,a_y,a_z [m/s^2]`), imu0/sensor.yaml
  state_groundtruth_estimate0/data.csv (t_ns, p, q_wxyz, v, b_w, b_a), optional
and, for synthetic captures, `scene/` with `object.stl` (metres) and `scene.yaml`.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from vio.csvio import read_numeric_csv
from vio.errors import CaptureError
from vio.kalibr import read_camera_yaml, read_imu_yaml
from vio.records import CameraCalib, FeatureTracks, Frame, GroundTruth, ImuCalib, ImuSeries

log = logging.getLogger(__name__)


@dataclass
class Capture:
    """A recording: calibration, IMU stream, frame times with an image loader, optional ground truth."""

    root: Path
    camera: CameraCalib | None
    imu_calib: ImuCalib | None
    imu: ImuSeries | None
    frame_t_ns: np.ndarray  # (F,) int64 ns
    load_image: Callable[[int], np.ndarray]  # frame index -> (H, W) uint8 grayscale
    ground_truth: GroundTruth | None = None
    scene_dir: Path | None = None
    warnings: list[str] = field(default_factory=list)
    format: str = "asl"
    tracks: list[FeatureTracks] | None = None  # precomputed feature tracks (e.g. gtsam's eqvio file); no images

    @property
    def num_frames(self) -> int:
        return int(self.frame_t_ns.shape[0])

    def frames(self, start: int = 0, stop: int | None = None) -> Iterator[Frame]:
        stop = self.num_frames if stop is None else min(stop, self.num_frames)
        for i in range(start, stop):
            yield Frame(int(self.frame_t_ns[i]), 0, self.load_image(i))

    def warn(self, message: str) -> None:
        self.warnings.append(message)
        log.warning(message)


def _check_monotonic(path: Path, t_ns: np.ndarray, rows: list[int], what: str) -> np.ndarray:
    """Return a keep-mask: exact duplicate timestamps are dropped; going backwards is an error."""
    d = np.diff(t_ns)
    back = np.flatnonzero(d < 0)
    if back.size:
        i = int(back[0]) + 1
        raise CaptureError(f"{what} timestamp goes backwards ({t_ns[i]} after {t_ns[i - 1]})", path, rows[i])
    keep = np.ones(t_ns.shape[0], bool)
    keep[1:] = d != 0
    return keep


def read_imu_csv(path: Path, warnings: list[str] | None = None) -> ImuSeries:
    """Read `imu0/data.csv` (t_ns, gyro rad/s, acc m/s^2). Bad rows follow `vio.readers.tables`' policy; gaps warn."""
    from vio.readers.tables import ensure_increasing, read_table
    from vio.readers.validate import gap_warnings

    warn: list[str] = [] if warnings is None else warnings
    table = read_table(path, 0, [1, 2, 3, 4, 5, 6], warnings=warn, what="IMU")
    if len(table) == 0:
        raise CaptureError("no IMU samples", path)
    table = ensure_increasing(table, "IMU", warn)
    if len(table) < 2:
        raise CaptureError(f"only {len(table)} IMU sample(s)", path)
    warn += gap_warnings(table.t_ns, table.rows, Path(path), "IMU", 4.0)
    return ImuSeries(table.t_ns, table.values[:, 0:3].copy(), table.values[:, 3:6].copy())


def read_groundtruth_csv(path: Path) -> GroundTruth:
    t, v, rows = read_numeric_csv(path, 17)
    if t.size == 0:
        raise CaptureError("no ground-truth rows", path)
    if not np.isfinite(v).all():
        i = int(np.flatnonzero(~np.isfinite(v).all(axis=1))[0])
        raise CaptureError("NaN in ground truth", path, rows[i])
    keep = _check_monotonic(path, t, rows, "ground-truth")
    v = v[keep]
    q = v[:, 3:7] / np.linalg.norm(v[:, 3:7], axis=1, keepdims=True)
    return GroundTruth(t[keep], v[:, 0:3], q, v[:, 7:10], v[:, 10:13], v[:, 13:16])


def _read_cam_csv(path: Path) -> tuple[np.ndarray, list[str], list[int]]:
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except FileNotFoundError:
        raise CaptureError("file not found", path) from None
    t_ns: list[int] = []
    names: list[str] = []
    rows: list[int] = []
    for lineno, line in enumerate(lines, start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = [p.strip() for p in s.split(",")]
        if len(parts) != 2:
            raise CaptureError(f"expected 'timestamp,filename', found {len(parts)} fields", path, lineno)
        try:
            t_ns.append(int(parts[0]))
        except ValueError:
            raise CaptureError(f"timestamp {parts[0][:30]!r} is not an integer (ns)", path, lineno) from None
        names.append(parts[1])
        rows.append(lineno)
    return np.asarray(t_ns, np.int64), names, rows


def find_mav0(root: Path) -> Path:
    root = Path(root)
    if not root.exists():
        raise CaptureError("capture folder not found", root)
    for cand in (root / "mav0", root):
        if (cand / "cam0").is_dir() or (cand / "imu0").is_dir():
            return cand
    raise CaptureError("not an ASL/EuRoC capture (no mav0/cam0 or mav0/imu0 folder)", root)


def read_asl(root: str | os.PathLike[str]) -> Capture:
    """Read an ASL/EuRoC capture folder (the folder holding `mav0/`, or `mav0/` itself)."""
    root = Path(root)
    mav0 = find_mav0(root)
    warnings: list[str] = []
    camera = read_camera_yaml(mav0 / "cam0" / "sensor.yaml") if (mav0 / "cam0" / "sensor.yaml").exists() else None
    imu_calib = read_imu_yaml(mav0 / "imu0" / "sensor.yaml") if (mav0 / "imu0" / "sensor.yaml").exists() else None
    imu = read_imu_csv(mav0 / "imu0" / "data.csv", warnings) if (mav0 / "imu0" / "data.csv").exists() else None
    frame_t = np.zeros(0, np.int64)
    paths: list[Path] = []
    cam_csv = mav0 / "cam0" / "data.csv"
    if cam_csv.exists():
        frame_t, names, rows = _read_cam_csv(cam_csv)
        keep = _check_monotonic(cam_csv, frame_t, rows, "frame")
        if not keep.all():
            warnings.append(f"{cam_csv}: {int((~keep).sum())} duplicate frame timestamp(s) dropped")
        data_dir = mav0 / "cam0" / "data"
        present = set(os.listdir(data_dir)) if data_dir.is_dir() else set()
        exists = np.array([n in present for n in names], bool)
        if not exists.all():
            first = int(np.flatnonzero(~exists)[0])
            if not exists.any():
                raise CaptureError(f"none of the {len(names)} listed images exist in {data_dir}", cam_csv, rows[first])
            warnings.append(
                f"{cam_csv}:{rows[first]}: {int((~exists).sum())} listed image(s) missing, frames skipped "
                f"(first: {names[first]})"
            )
        keep &= exists
        frame_t = frame_t[keep]
        paths = [data_dir / n for n, k in zip(names, keep, strict=True) if k]
        from vio.readers.validate import gap_warnings

        kept_rows = np.asarray(rows)[keep]
        warnings += gap_warnings(frame_t, kept_rows, cam_csv, "frame", 2.5)
    gt = None
    gt_csv = mav0 / "state_groundtruth_estimate0" / "data.csv"
    if gt_csv.exists():
        gt = read_groundtruth_csv(gt_csv)
    scene = root / "scene" if (root / "scene").is_dir() else None

    def load(i: int) -> np.ndarray:
        p = paths[i]
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise CaptureError("image missing or cannot be decoded", p)
        return img

    fmt = "tumvi" if (mav0 / "mocap0").is_dir() or (root / "dso").is_dir() else "asl"
    cap = Capture(root, camera, imu_calib, imu, frame_t, load, gt, scene, [], fmt)
    for w in warnings:
        cap.warn(w)
    return cap
