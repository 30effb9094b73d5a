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


def read_eqvio(path: str | Path | None = None, problems: list[str] | None = None) -> Capture:
    """Read the eqvio CSV into a Capture with `imu`, `camera`, `imu_calib`, `frame_t_ns` and `tracks` (no images).

    Times: `t_ns = t0_abs (ns, exact decimal) + round(t_rel * 1e9)`. Track pixels: `u = fx * u_norm + cx`,
    `v = fy * v_norm + cy` (undistorted, so the camera's distortion is zero). The first bad row raises; with a
    `problems` list (`vio info`) the first problem of each row type is appended there, with the count of bad rows
    of that type, and the stream it spoils is left out (meta: the camera and the feature tracks).
    """
    path = Path(path) if path is not None else default_eqvio_path()
    if not path.is_file():
        raise CaptureError("file not found", path)
    try:
        return _read_rows(path, _RowProblems(problems))
    except UnicodeDecodeError:
        raise CaptureError("not a text file (cannot decode as UTF-8)", path) from None


class _RowProblems:
    """Problems per row type (`imu`, `vision_feature`, `meta`, or `other` rows): raised at once, or collected."""

    def __init__(self, problems: list[str] | None) -> None:
        self.problems = problems
        self.first: dict[str, str] = {}
        self.count: dict[str, int] = {}

    def add(self, stream: str, exc: CaptureError) -> None:
        if self.problems is None:
            raise exc
        self.first.setdefault(stream, str(exc))
        self.count[stream] = self.count.get(stream, 0) + 1

    def spoilt(self, stream: str) -> bool:
        return stream in self.first

    def report(self) -> None:
        if self.problems is None:
            return
        for stream, msg in self.first.items():
            n = self.count[stream]
            self.problems.append(msg + (f" (the first of {n} bad {stream} rows)" if n > 1 else ""))


def _read_row(
    path: Path,
    row_no: int,
    row: list[str],
    n_fields: int,
    col: dict[str, int],
    meta: dict[str, str],
    imu: tuple[list[float], list[list[float]]],
    feats: dict[int, list[tuple[int, float, float]]],
    frame_t: dict[int, float],
) -> None:
    """One row into `meta`, `imu` (times, values) or `feats`/`frame_t`; a CaptureError names the row."""
    if len(row) != n_fields:
        raise CaptureError(f"expected {n_fields} fields, found {len(row)}", path, row_no)
    kind = row[0]
    if kind == "meta":
        meta[row[col["key"]]] = row[col["value"]]
    elif kind == "imu":
        t = _float(path, row_no, row[col["t_rel"]], "t_rel")
        values = [_float(path, row_no, row[col[c]], c) for c in ("gx", "gy", "gz", "ax", "ay", "az")]
        imu[0].append(t)
        imu[1].append(values)
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


def _read_rows(path: Path, bad: _RowProblems) -> Capture:
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
            try:
                _read_row(path, row_no, row, len(header), col, meta, (imu_t, imu_v), feats, frame_t)
            except CaptureError as exc:
                bad.add(row[0] if row[0] in ("imu", "vision_feature", "meta") else "other", exc)
    missing = [k for k in _META_KEYS if k not in meta]
    if missing:
        bad.add("meta", CaptureError(f"meta rows missing: {', '.join(missing)}", path))
    if bad.problems is None and (not imu_t or not frame_t):
        raise CaptureError("no imu or no vision_feature rows", path)
    t0_ns = 0  # when t0_abs is unusable (collecting problems only): times relative to it
    try:
        t0_ns = int(Decimal(meta.get("t0_abs", "0")) * 1_000_000_000)
    except InvalidOperation:
        bad.add("meta", CaptureError(f"meta t0_abs {meta['t0_abs'][:30]!r} is not a number", path))
    m: dict[str, float] = {}
    for k in (k for k in _META_KEYS if k != "t0_abs"):
        if k in meta:
            try:
                m[k] = _float(path, 0, meta[k], k)
            except CaptureError as exc:
                bad.add("meta", exc)

    imu = None
    if imu_t and not bad.spoilt("imu"):
        imu_t_ns = t0_ns + np.round(np.asarray(imu_t) * 1e9).astype(np.int64)
        if np.any(np.diff(imu_t_ns) <= 0):
            bad.add("imu", CaptureError("imu times are not strictly increasing", path))
        else:
            gyro_acc = np.asarray(imu_v)
            imu = ImuSeries(imu_t_ns, gyro_acc[:, 0:3].copy(), gyro_acc[:, 3:6].copy())

    camera, tracks = None, None
    frame_t_ns = np.zeros(0, np.int64)
    if frame_t and not bad.spoilt("meta") and not bad.spoilt("vision_feature"):
        camera, frame_t_ns, tracks = _camera_and_tracks(path, m, t0_ns, frame_t, feats, bad)
    bad.report()

    def no_images(i: int) -> np.ndarray:
        raise CaptureError("the eqvio file holds feature tracks, not images", path)

    return Capture(path, camera, EUROC_IMU, imu, frame_t_ns, no_images, None, None, [], "eqvio", tracks)


def _camera_and_tracks(
    path: Path,
    m: dict[str, float],
    t0_ns: int,
    frame_t: dict[int, float],
    feats: dict[int, list[tuple[int, float, float]]],
    bad: _RowProblems,
) -> tuple[CameraCalib | None, np.ndarray, list[FeatureTracks] | None]:
    """The camera from the meta values, the frame times (ns) and the tracks in pixels; (None, [], None) when the
    frame times are not increasing and the problems are collected."""
    q = np.array([m["T_ci_qw"], m["T_ci_qx"], m["T_ci_qy"], m["T_ci_qz"]])
    body_T_cam = make_T(quat_wxyz_to_R(q / np.linalg.norm(q)), [m["T_ci_tx"], m["T_ci_ty"], m["T_ci_tz"]])
    fx, fy, cx, cy = m["camera_fx"], m["camera_fy"], m["camera_cx"], m["camera_cy"]
    camera = CameraCalib(EUROC_WIDTH, EUROC_HEIGHT, fx, fy, cx, cy, np.zeros(4), body_T_cam, rate_hz=20.0)

    frames = sorted(frame_t)
    frame_t_ns = t0_ns + np.round(np.array([frame_t[k] for k in frames]) * 1e9).astype(np.int64)
    if np.any(np.diff(frame_t_ns) <= 0):
        bad.add("vision_feature", CaptureError("frame times are not strictly increasing", path))
        return None, np.zeros(0, np.int64), None
    tracks = []
    for k, t_ns in zip(frames, frame_t_ns, strict=True):
        obs = np.array(feats[k], dtype=float).reshape(-1, 3)
        uv = np.column_stack([fx * obs[:, 1] + cx, fy * obs[:, 2] + cy])
        tracks.append(FeatureTracks(int(t_ns), obs[:, 0].astype(np.int64), uv))
    return camera, frame_t_ns, tracks
