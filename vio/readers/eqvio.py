"""Reader of gtsam's `eqvio_processed_30s.csv`: 30 s of the real EuRoC V1_01 flight as IMU plus feature tracks.

The file (shipped in the gtsam wheel; find it with `gtsam.findExampleDataFile("eqvio_processed_30s.csv")`) has one
header and three row types in the columns `row_type,t_abs,t_rel,seq,frame_idx,landmark_id,gx..az,bgx..baz,u_norm,
v_norm,key,value`:
  meta            key/value pairs: `camera_fx/fy/cx/cy` (px), `T_ci_t{x,y,z}` (m) and `T_ci_q{w,x,y,z}`: the camera
                  pose in the IMU (body) frame, i.e. `body_T_cam` (Kalibr's T_BS), and `t0_abs` (s, decimal).
  imu             gyro gx,gy,gz (rad/s) and accelerometer ax,ay,az (m/s^2), body frame, at t_rel seconds.
  vision_feature  one observation: frame_idx, landmark_id, (u_norm, v_norm) undistorted normalized coordinates.
The features are converted to pixels with the meta intrinsics, so the returned camera has zero distortion.
"""

from __future__ import annotations

import csv
import math
from decimal import Decimal, InvalidOperation
from pathlib import Path

import numpy as np

from vio.capture import Capture
from vio.errors import CaptureError
from vio.geometry import make_T, quat_wxyz_to_R
from vio.readers.calib import EUROC_IMU
from vio.records import CameraCalib, FeatureTracks, ImuSeries

EQVIO_NAME = "eqvio_processed_30s.csv"
_HEADER = ("row_type", "t_abs", "t_rel", "seq", "frame_idx", "landmark_id")
EUROC_WIDTH, EUROC_HEIGHT = 752, 480  # EuRoC's image size, px (its IMU noise is `vio.readers.calib.EUROC_IMU`)
_COLUMNS = ("gx", "gy", "gz", "ax", "ay", "az", "u_norm", "v_norm", "key", "value")  # besides _HEADER
_META_KEYS = ("camera_fx", "camera_fy", "camera_cx", "camera_cy", "t0_abs") + tuple(
    f"T_ci_{c}" for c in ("tx", "ty", "tz", "qw", "qx", "qy", "qz")
)


def default_eqvio_path() -> Path:
    """The file inside the installed gtsam wheel."""
    import gtsam

    return Path(gtsam.findExampleDataFile(EQVIO_NAME))


def is_eqvio_file(path: str | Path) -> bool:
    """True when `path` is a file whose header is the eqvio header."""
    p = Path(path)
    if not p.is_file():
        return False
    with p.open(encoding="utf-8", errors="replace") as f:
        return tuple(f.readline().strip().split(",")[:6]) == _HEADER


def _float(path: Path, row: int, text: str, what: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise CaptureError(f"{what} {text[:30]!r} is not a number", path, row) from None
    if not math.isfinite(value):
        raise CaptureError(f"{what} is not finite", path, row)
    return value


def read_eqvio(path: str | Path | None = None) -> Capture:
    """Read the eqvio CSV into a Capture with `imu`, `camera`, `imu_calib`, `frame_t_ns` and `tracks` (no images).

    Times: `t_ns = t0_abs (ns, exact decimal) + round(t_rel * 1e9)`. Track pixels: `u = fx * u_norm + cx`,
    `v = fy * v_norm + cy` (undistorted, so the camera's distortion is zero).
    """
    path = Path(path) if path is not None else default_eqvio_path()
    if not path.is_file():
        raise CaptureError("file not found", path)
    try:
        return _read_rows(path)
    except UnicodeDecodeError:
        raise CaptureError("not a text file (cannot decode as UTF-8)", path) from None


def _read_rows(path: Path) -> Capture:
    meta: dict[str, str] = {}
    imu_t: list[float] = []
    imu_v: list[list[float]] = []
    feats: dict[int, list[tuple[int, float, float]]] = {}
    frame_t: dict[int, float] = {}
    with path.open(encoding="utf-8", newline="") as f:
        reader = csv.reader(f)
        header = next(reader, None)
        if header is None or tuple(header[:6]) != _HEADER:
            raise CaptureError("not an eqvio CSV (header must start with row_type,t_abs,t_rel,...)", path, 1)
        col = {name: i for i, name in enumerate(header)}
        lacking = [c for c in _COLUMNS if c not in col]
        if lacking:
            raise CaptureError(f"header lacks column(s) {', '.join(lacking)}", path, 1)
        for row_no, row in enumerate(reader, start=2):
            if not row:
                continue
            if len(row) != len(header):
                raise CaptureError(f"expected {len(header)} fields, found {len(row)}", path, row_no)
            kind = row[0]
            if kind == "meta":
                meta[row[col["key"]]] = row[col["value"]]
            elif kind == "imu":
                imu_t.append(_float(path, row_no, row[col["t_rel"]], "t_rel"))
                imu_v.append([_float(path, row_no, row[col[c]], c) for c in ("gx", "gy", "gz", "ax", "ay", "az")])
            elif kind == "vision_feature":
                try:
                    k, lid = int(row[col["frame_idx"]]), int(row[col["landmark_id"]])
                except ValueError:
                    raise CaptureError("frame_idx/landmark_id must be integers", path, row_no) from None
                t = _float(path, row_no, row[col["t_rel"]], "t_rel")
                if frame_t.setdefault(k, t) != t:
                    raise CaptureError(f"frame {k} has two times ({frame_t[k]} and {t} s)", path, row_no)
                u = _float(path, row_no, row[col["u_norm"]], "u_norm")
                v = _float(path, row_no, row[col["v_norm"]], "v_norm")
                feats.setdefault(k, []).append((lid, u, v))
            else:
                raise CaptureError(f"unknown row_type {kind[:20]!r}", path, row_no)
    missing = [k for k in _META_KEYS if k not in meta]
    if missing:
        raise CaptureError(f"meta rows missing: {', '.join(missing)}", path)
    if not imu_t or not frame_t:
        raise CaptureError("no imu or no vision_feature rows", path)
    try:
        t0_ns = int(Decimal(meta["t0_abs"]) * 1_000_000_000)
    except InvalidOperation:
        raise CaptureError(f"meta t0_abs {meta['t0_abs'][:30]!r} is not a number", path) from None
    m = {k: _float(path, 0, meta[k], k) for k in _META_KEYS if k != "t0_abs"}

    imu_t_ns = t0_ns + np.round(np.asarray(imu_t) * 1e9).astype(np.int64)
    if np.any(np.diff(imu_t_ns) <= 0):
        raise CaptureError("imu times are not strictly increasing", path)
    gyro_acc = np.asarray(imu_v)
    imu = ImuSeries(imu_t_ns, gyro_acc[:, 0:3].copy(), gyro_acc[:, 3:6].copy())

    q = np.array([m["T_ci_qw"], m["T_ci_qx"], m["T_ci_qy"], m["T_ci_qz"]])
    body_T_cam = make_T(quat_wxyz_to_R(q / np.linalg.norm(q)), [m["T_ci_tx"], m["T_ci_ty"], m["T_ci_tz"]])
    fx, fy, cx, cy = m["camera_fx"], m["camera_fy"], m["camera_cx"], m["camera_cy"]
    camera = CameraCalib(EUROC_WIDTH, EUROC_HEIGHT, fx, fy, cx, cy, np.zeros(4), body_T_cam, rate_hz=20.0)

    frames = sorted(frame_t)
    frame_t_ns = t0_ns + np.round(np.array([frame_t[k] for k in frames]) * 1e9).astype(np.int64)
    if np.any(np.diff(frame_t_ns) <= 0):
        raise CaptureError("frame times are not strictly increasing", path)
    tracks = []
    for k, t_ns in zip(frames, frame_t_ns, strict=True):
        obs = np.array(feats[k], dtype=float).reshape(-1, 3)
        uv = np.column_stack([fx * obs[:, 1] + cx, fy * obs[:, 2] + cy])
        tracks.append(FeatureTracks(int(t_ns), obs[:, 0].astype(np.int64), uv))

    def no_images(i: int) -> np.ndarray:
        raise CaptureError("the eqvio file holds feature tracks, not images", path)

    return Capture(path, camera, EUROC_IMU, imu, frame_t_ns, no_images, None, None, [], "eqvio", tracks)
