"""Trajectory files: TUM (`t_s x y z qx qy qz qw`) and EuRoC/ASL CSV (`t_ns, p, q_wxyz, ...`).

A `Trajectory` is the body (IMU) pose in the world frame over time: positions in metres, orientations as unit
quaternions `world_R_body` stored w first. Timestamps are integer nanoseconds; TUM files carry seconds, which are
parsed and written digit-exact (9 decimals), so a nanosecond timestamp survives a write/read round trip.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vio.atomic import atomic_open
from vio.errors import CaptureError
from vio.geometry import quat_wxyz_to_R
from vio.records import GroundTruth

log = logging.getLogger(__name__)

_NS_PER_S = 1_000_000_000


@dataclass(frozen=True)
class Trajectory:
    """Timestamped body poses in the world frame."""

    t_ns: np.ndarray  # (N,) int64 strictly increasing, ns
    p_world: np.ndarray  # (N, 3) body position in world, m
    q_wxyz: np.ndarray  # (N, 4) world_R_body unit quaternions, w first

    def __post_init__(self) -> None:
        n = self.t_ns.shape[0] if self.t_ns.ndim == 1 else -1
        if n < 0 or self.p_world.shape != (n, 3) or self.q_wxyz.shape != (n, 4):
            raise ValueError(
                f"Trajectory shapes disagree: t_ns {self.t_ns.shape}, p_world {self.p_world.shape}, "
                f"q_wxyz {self.q_wxyz.shape}"
            )

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    @property
    def t_s(self) -> np.ndarray:
        """(N,) seconds relative to the first sample (float; for dt and plotting only)."""
        return (self.t_ns - self.t_ns[0]).astype(np.float64) * 1e-9 if len(self) else np.zeros(0)

    def world_R_body(self) -> np.ndarray:  # noqa: N802
        """(N, 3, 3) rotation matrices."""
        return quat_wxyz_to_R(self.q_wxyz).reshape(-1, 3, 3)

    def world_T_body(self) -> np.ndarray:  # noqa: N802
        """(N, 4, 4) homogeneous poses."""
        T = np.tile(np.eye(4), (len(self), 1, 1))
        T[:, :3, :3] = self.world_R_body()
        T[:, :3, 3] = self.p_world
        return T

    def subset(self, index: np.ndarray) -> Trajectory:
        """The samples selected by an index array or boolean mask."""
        return Trajectory(self.t_ns[index], self.p_world[index], self.q_wxyz[index])

    @staticmethod
    def from_groundtruth(gt: GroundTruth) -> Trajectory:
        return Trajectory(np.asarray(gt.t_ns, np.int64), np.asarray(gt.p_world, float), np.asarray(gt.q_wxyz, float))


def seconds_to_ns(text: str) -> int:
    """Parse a decimal seconds string to integer nanoseconds without going through a float (exact to 1 ns).

    Digits past the ninth decimal are rounded half up. Scientific notation falls back to float parsing.
    """
    s = text.strip()
    if not s:
        raise ValueError("empty timestamp")
    if any(c in s for c in "eE") or s.lower() in ("nan", "inf", "-inf", "+inf"):
        value = float(s)
        if not np.isfinite(value):
            raise ValueError(f"timestamp {s!r} is not finite")
        return int(round(value * _NS_PER_S))
    sign = -1 if s.startswith("-") else 1
    s = s.lstrip("+-")
    whole, _, frac = s.partition(".")
    if not (whole or frac) or not (whole.isdigit() or whole == "") or not (frac.isdigit() or frac == ""):
        raise ValueError(f"timestamp {text.strip()!r} is not a number")
    ns = int(whole or "0") * _NS_PER_S + int((frac[:9] or "0").ljust(9, "0"))
    if len(frac) > 9 and frac[9] >= "5":
        ns += 1
    return sign * ns


def ns_to_seconds_str(t_ns: int) -> str:
    """Integer nanoseconds to a seconds string with exactly 9 decimals (exact)."""
    t = int(t_ns)
    sign = "-" if t < 0 else ""
    whole, frac = divmod(abs(t), _NS_PER_S)
    return f"{sign}{whole}.{frac:09d}"


def _finish(path: Path, t_ns: list[int], vals: list[list[float]], rows: list[int], q_order: str) -> Trajectory:
    """Validate parsed rows (finite, increasing, quaternion norm) and build the Trajectory."""
    if not t_ns:
        raise CaptureError("no trajectory rows", path)
    t = np.asarray(t_ns, np.int64)
    v = np.asarray(vals, np.float64)
    bad = np.flatnonzero(~np.isfinite(v).all(axis=1))
    if bad.size:
        raise CaptureError("NaN or inf in trajectory row", path, rows[int(bad[0])])
    d = np.diff(t)
    back = np.flatnonzero(d <= 0)
    if back.size:
        i = int(back[0]) + 1
        what = "repeats" if d[i - 1] == 0 else "goes backwards from"
        raise CaptureError(f"timestamp {ns_to_seconds_str(t[i])} s {what} the previous row", path, rows[i])
    p = v[:, 0:3]
    q = v[:, [6, 3, 4, 5]] if q_order == "xyzw" else v[:, 3:7]
    norm = np.linalg.norm(q, axis=1)
    off = np.flatnonzero(np.abs(norm - 1.0) > 1e-2)
    if off.size:
        i = int(off[0])
        raise CaptureError(f"quaternion norm {norm[i]:.4g} is not 1 ({q_order} order expected)", path, rows[i])
    return Trajectory(t, p.copy(), q / norm[:, None])


def _read_tum(path: Path, lines: list[tuple[int, str]]) -> Trajectory:
    t_ns: list[int] = []
    vals: list[list[float]] = []
    rows: list[int] = []
    for k, (lineno, s) in enumerate(lines):
        fields = s.split()
        if k == 0 and fields[0][:1].isalpha():
            continue  # a header row without '#'
        if len(fields) != 8:
            raise CaptureError(f"TUM row needs 8 fields 't x y z qx qy qz qw', found {len(fields)}", path, lineno)
        try:
            t_ns.append(seconds_to_ns(fields[0]))
            vals.append([float(f) for f in fields[1:]])
        except ValueError:
            raise CaptureError(f"non-numeric field in {s[:60]!r}", path, lineno) from None
        rows.append(lineno)
    return _finish(path, t_ns, vals, rows, "xyzw")


def _read_asl_csv(path: Path, lines: list[tuple[int, str]]) -> Trajectory:
    t_ns: list[int] = []
    vals: list[list[float]] = []
    rows: list[int] = []
    for k, (lineno, s) in enumerate(lines):
        fields = [f.strip() for f in s.split(",")]
        if k == 0 and fields[0][:1].isalpha():
            continue  # a header row without '#'
        if len(fields) < 8:
            raise CaptureError(f"EuRoC CSV row needs >= 8 fields 't_ns, p, q_wxyz', found {len(fields)}", path, lineno)
        try:
            t_ns.append(int(fields[0]))
        except ValueError:
            raise CaptureError(f"timestamp {fields[0][:30]!r} is not an integer (ns)", path, lineno) from None
        try:
            vals.append([float(f) for f in fields[1:8]])
        except ValueError:
            raise CaptureError(f"non-numeric field in {s[:60]!r}", path, lineno) from None
        rows.append(lineno)
    return _finish(path, t_ns, vals, rows, "wxyz")


def read_trajectory(path: str | os.PathLike[str]) -> Trajectory:
    """Read a TUM or EuRoC/ASL CSV trajectory (format detected from the first data row: commas mean CSV).

    TUM: `t_s x y z qx qy qz qw` space separated, `#` comments. EuRoC: `t_ns, px, py, pz, qw, qx, qy, qz[, ...]`
    (an ASL `state_groundtruth_estimate0/data.csv` is accepted as is; extra columns are ignored). Raises
    CaptureError naming the file and row on malformed input.
    """
    path = Path(path)
    if path.is_dir():
        gt = path / "mav0" / "state_groundtruth_estimate0" / "data.csv"
        if not gt.exists():
            raise CaptureError("is a folder, not a trajectory file", path)
        path = gt
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise CaptureError("trajectory file not found", path) from None
    except UnicodeDecodeError:
        raise CaptureError("not a text file", path) from None
    lines = [(i, s.strip()) for i, s in enumerate(text.splitlines(), start=1)]
    lines = [(i, s) for i, s in lines if s and not s.startswith("#")]
    if not lines:
        raise CaptureError("no trajectory rows", path)
    traj = _read_asl_csv(path, lines) if "," in lines[0][1] else _read_tum(path, lines)
    log.debug("%s: %d poses over %.3f s", path, len(traj), (traj.t_ns[-1] - traj.t_ns[0]) * 1e-9)
    return traj


def write_tum(path: str | os.PathLike[str], traj: Trajectory) -> None:
    """Write `t_s x y z qx qy qz qw` lines atomically (t_s with 9 decimals, exact; metres; unit quaternions)."""
    with atomic_open(path, "w", encoding="utf-8", newline="\n") as f:
        f.write("# t_s x y z qx qy qz qw (IMU body in world, m)\n")
        for t, p, q in zip(traj.t_ns, traj.p_world, traj.q_wxyz, strict=True):
            f.write(
                f"{ns_to_seconds_str(t)} {p[0]:.9f} {p[1]:.9f} {p[2]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f} {q[0]:.9f}\n"
            )
