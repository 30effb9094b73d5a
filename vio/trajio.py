"""Trajectory files: TUM (`t_s x y z qx qy qz qw`) and EuRoC/ASL CSV (`t_ns, p, q_wxyz, ...`).

A `Trajectory` is the body (IMU) pose in the world frame over time: positions in metres, orientations as unit
quaternions `world_R_body` stored w first. Timestamps are integer nanoseconds; TUM files carry seconds, which are
parsed (`vio.readers.tables`, the CSV helper every reader shares) and written digit-exact (9 decimals), so a
nanosecond timestamp survives a write/read round trip.
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
from vio.readers.tables import NS_PER_S, Table, data_lines, read_strict_table
from vio.records import GroundTruth

log = logging.getLogger(__name__)


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


def ns_to_seconds_str(t_ns: int) -> str:
    """Integer nanoseconds to a seconds string with exactly 9 decimals (exact)."""
    t = int(t_ns)
    sign = "-" if t < 0 else ""
    whole, frac = divmod(abs(t), NS_PER_S)
    return f"{sign}{whole}.{frac:09d}"


def _finish(table: Table, q_order: str) -> Trajectory:
    """Validate parsed rows (finite, strictly increasing, quaternion norm) and build the Trajectory."""
    path, rows, v = table.path, table.rows, table.values
    if len(table) == 0:
        raise CaptureError("no trajectory rows", path)
    bad = np.flatnonzero(~np.isfinite(v).all(axis=1))
    if bad.size:
        raise CaptureError("NaN or inf in trajectory row", path, int(rows[bad[0]]))
    d = np.diff(table.t_ns)
    back = np.flatnonzero(d <= 0)
    if back.size:
        i = int(back[0]) + 1
        what = "repeats" if d[i - 1] == 0 else "goes backwards from"
        t_s = ns_to_seconds_str(table.t_ns[i])
        raise CaptureError(f"timestamp {t_s} s {what} the previous row", path, int(rows[i]))
    p = v[:, 0:3]
    q = v[:, [6, 3, 4, 5]] if q_order == "xyzw" else v[:, 3:7]
    norm = np.linalg.norm(q, axis=1)
    off = np.flatnonzero(np.abs(norm - 1.0) > 1e-2)
    if off.size:
        i = int(off[0])
        raise CaptureError(f"quaternion norm {norm[i]:.4g} is not 1 ({q_order} order expected)", path, int(rows[i]))
    return Trajectory(table.t_ns, p.copy(), q / norm[:, None])


def read_trajectory(path: str | os.PathLike[str]) -> Trajectory:
    """Read a TUM or EuRoC/ASL CSV trajectory (format detected from the first data row: commas mean CSV).

    TUM: `t_s x y z qx qy qz qw` space separated, `#` comments. EuRoC: `t_ns, px, py, pz, qw, qx, qy, qz[, ...]`
    (an ASL `state_groundtruth_estimate0/data.csv` is accepted as is; extra columns are ignored). A header line
    without `#` is skipped. Raises CaptureError naming the file and row on malformed input.
    """
    path = Path(path)
    if path.is_dir():
        gt = path / "mav0" / "state_groundtruth_estimate0" / "data.csv"
        if not gt.exists():
            raise CaptureError("is a folder, not a trajectory file", path)
        path = gt
    lines, _ = data_lines(path)
    if not lines:
        raise CaptureError("no trajectory rows", path)
    if "," in lines[0][1]:
        table = read_strict_table(path, 8, "EuRoC CSV", "t_ns, p, q_wxyz", at_least=True, lines=lines)
        traj = _finish(table, "wxyz")
    else:
        layout = "t x y z qx qy qz qw"
        table = read_strict_table(path, 8, "TUM", layout, unit_ns=NS_PER_S, sep=None, lines=lines)
        traj = _finish(table, "xyzw")
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
