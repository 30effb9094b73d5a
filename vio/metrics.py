"""Trajectory accuracy metrics: association, alignment (SE3, Sim3, 4-DoF position+yaw, none), ATE, RPE, drift.

Our own small module (evo is GPL and lacks the 4-DoF alignment VIO evaluation uses); tests check the numbers
against evo's command-line tools run as a separate program. Definitions (all on the associated pose pairs):

- association: each pose of the shorter trajectory is paired with the nearest-in-time pose of the other one,
  if within `max_dt_s` (10 ms by default), as evo's `nearest_time` does; with `sync="interpolate"` the longer
  trajectory is instead interpolated (linear position, slerp) at the paired times, as evo's `interpolation`;
- alignment maps the estimate onto the ground truth: `se3`/`sim3` by Umeyama's least squares on positions
  (sim3 with scale), `posyaw` by rotation about the gravity axis z plus translation (the 4 unobservable DoF of
  VIO), `none` leaves it as is;
- ATE: position error after alignment (rmse, mean, median, max) and the rotation error angle;
- RPE per segment length L metres (default 1, 2, 5, 10 m): every associated pose i is paired with the pose j
  whose ground-truth path distance from i is nearest to L (within 10 % of L), as evo's `--all_pairs
  --pairs_from_reference -u m`; the error is the relative pose E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j) of the aligned
  estimate P against the truth Q: translation |t(E)| m and rotation angle(R(E)) deg, and `trans_pct`, the mean of
  |t(E)| over each pair's ground-truth path distance, in %; lengths without pairs are left out;
- scale: the Sim3 Umeyama scale that maps the estimate onto the truth (evo's "scale correction"), whatever the
  chosen alignment; `scale_error_pct` = 100 |scale - 1|; `estimate_scale_error_pct` = 100 (1 / scale - 1), signed:
  positive when the estimate is too large (the benchmark's and `vio measure`'s convention);
- drift_pct: final position error after the chosen alignment as a percentage of the ground-truth path length;
- coverage_s: seconds of the ground-truth span covered by associated poses (steps longer than
  `coverage_gap_s` between consecutive associated poses do not count).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from vio.errors import CaptureError
from vio.trajio import Trajectory

ALIGNMENTS = ("se3", "posyaw", "sim3", "none")
DEFAULT_SEGMENTS_M = (1.0, 2.0, 5.0, 10.0)


def associate(gt: Trajectory, est: Trajectory, max_dt_s: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Index arrays (i_gt, i_est) of nearest-time pairs within max_dt_s, walking the shorter trajectory."""
    short, long_ = (gt, est) if len(est) > len(gt) else (est, gt)
    if len(short) == 0 or len(long_) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    max_dt = int(round(max_dt_s * 1e9))
    k = np.clip(np.searchsorted(long_.t_ns, short.t_ns, side="right"), 1, len(long_) - 1)
    if len(long_) == 1:
        k = np.zeros(len(short), int)
        best = k
    else:
        d_up = np.abs(long_.t_ns[k] - short.t_ns)
        d_lo = np.abs(short.t_ns - long_.t_ns[k - 1])
        best = np.where(d_up < d_lo, k, k - 1)
    ok = np.abs(long_.t_ns[best] - short.t_ns) <= max_dt
    i_short, i_long = np.flatnonzero(ok), best[ok]
    return (i_long, i_short) if short is est else (i_short, i_long)


def interpolate(traj: Trajectory, t_ns: np.ndarray) -> Trajectory:
    """Poses at t_ns: positions linear, orientations slerped between the neighbouring poses (clamped at the ends)."""
    t_ns = np.asarray(t_ns, np.int64)
    idx = np.clip(np.searchsorted(traj.t_ns, t_ns, side="left"), 1, len(traj) - 1)
    t_prev, t_next = traj.t_ns[idx - 1], traj.t_ns[idx]
    frac = np.clip((t_ns - t_prev) / (t_next - t_prev), 0.0, 1.0)
    p = traj.p_world[idx - 1] + frac[:, None] * (traj.p_world[idx] - traj.p_world[idx - 1])
    r_prev = Rotation.from_quat(traj.q_wxyz[idx - 1][:, [1, 2, 3, 0]])
    r_next = Rotation.from_quat(traj.q_wxyz[idx][:, [1, 2, 3, 0]])
    r = r_prev * Rotation.from_rotvec((r_prev.inv() * r_next).as_rotvec() * frac[:, None])
    return Trajectory(t_ns, p, r.as_quat()[:, [3, 0, 1, 2]])


def synchronize(
    gt: Trajectory, est: Trajectory, max_dt_s: float = 0.01, sync: str = "nearest"
) -> tuple[Trajectory, Trajectory]:
    """Pose-by-pose matched copies of (gt, est).

    `nearest`: the associated poses themselves. `interpolate`: the sparser trajectory's associated poses, and the
    denser trajectory interpolated at exactly their times (evo's `--sync_method interpolation`).
    """
    i_gt, i_est = associate(gt, est, max_dt_s)
    if sync == "nearest" or i_gt.size == 0:
        return gt.subset(i_gt), est.subset(i_est)
    if sync != "interpolate":
        raise ValueError(f"unknown sync {sync!r}; choose nearest or interpolate")
    if len(gt) < 2 or len(est) < 2:
        raise CaptureError("interpolation needs at least 2 poses in each trajectory")
    if len(est) > len(gt):
        g = gt.subset(i_gt)
        return g, interpolate(est, g.t_ns)
    e = est.subset(i_est)
    return interpolate(gt, e.t_ns), e


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares (s, R, t) with dst ~ s R src + t for (N, 3) point sets (Umeyama 1991)."""
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / src.shape[0]
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    s = float(np.trace(np.diag(D) @ S) / (xs**2).sum(axis=1).mean()) if with_scale else 1.0
    return s, R, mu_d - s * R @ mu_s


def align_posyaw(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares rotation about world z and translation with dst ~ Rz src + t (4-DoF, no scale)."""
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    xs, xd = src - mu_s, dst - mu_d
    yaw = np.arctan2(
        np.sum(xs[:, 0] * xd[:, 1] - xs[:, 1] * xd[:, 0]), np.sum(xs[:, 0] * xd[:, 0] + xs[:, 1] * xd[:, 1])
    )
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return 1.0, R, mu_d - R @ mu_s


def alignment(gt_p: np.ndarray, est_p: np.ndarray, align: str) -> tuple[float, np.ndarray, np.ndarray]:
    """(scale, R, t) of the chosen alignment, mapping estimated positions onto ground-truth positions."""
    if align == "se3":
        return umeyama(est_p, gt_p, with_scale=False)
    if align == "sim3":
        return umeyama(est_p, gt_p, with_scale=True)
    if align == "posyaw":
        return align_posyaw(est_p, gt_p)
    if align == "none":
        return 1.0, np.eye(3), np.zeros(3)
    raise ValueError(f"unknown alignment {align!r}; choose one of {', '.join(ALIGNMENTS)}")


def path_distances(p: np.ndarray) -> np.ndarray:
    """(N,) path length travelled from the first position to each position, m."""
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(p[1:] - p[:-1], axis=1))])


def _stats(x: np.ndarray, unit: str) -> dict[str, float]:
    if x.size == 0:
        return {}
    return {
        f"rmse_{unit}": float(np.sqrt(np.mean(x**2))),
        f"mean_{unit}": float(np.mean(x)),
        f"median_{unit}": float(np.median(x)),
        f"max_{unit}": float(np.max(x)),
    }


def segment_pairs(dist: np.ndarray, length: float, rel_tol: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """All pairs (i, j>i) whose path distance is nearest to `length` (earliest j on ties), within rel_tol."""
    n = dist.size
    if n < 2:
        return np.zeros(0, int), np.zeros(0, int)
    i = np.arange(n - 1)
    k = np.searchsorted(dist, dist[i] + length, side="left")  # first index reaching the target
    up = np.maximum(k, i + 1)
    lo = np.searchsorted(dist, dist[np.minimum(k, n) - 1], side="left")  # earliest index with the value below
    lo = np.maximum(lo, i + 1)
    has_up = up < n
    up_c = np.minimum(up, n - 1)
    err_up = np.where(has_up, np.abs((dist[up_c] - dist[i]) - length), np.inf)
    err_lo = np.where(k - 1 > i, np.abs((dist[lo] - dist[i]) - length), np.inf)
    j = np.where(err_lo <= err_up, lo, up_c)
    err = np.minimum(err_lo, err_up)
    ok = err <= length * rel_tol
    return i[ok], j[ok]


def _relative_errors(Q: np.ndarray, P: np.ndarray, i: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Translation (m) and rotation (deg) of E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j) for (N, 4, 4) pose stacks."""
    inv = np.linalg.inv
    E = inv(inv(Q[i]) @ Q[j]) @ (inv(P[i]) @ P[j])
    return np.linalg.norm(E[:, :3, 3], axis=1), np.degrees(Rotation.from_matrix(E[:, :3, :3]).magnitude())


def evaluate(
    gt: Trajectory,
    est: Trajectory,
    align: str = "se3",
    max_dt_s: float = 0.01,
    segments_m: tuple[float, ...] = DEFAULT_SEGMENTS_M,
    rpe_rel_tol: float = 0.1,
    coverage_gap_s: float = 1.0,
    sync: str = "nearest",
) -> dict:
    """Score an estimated trajectory against ground truth (see the module docstring for the definitions)."""
    if align not in ALIGNMENTS:
        raise ValueError(f"unknown alignment {align!r}; choose one of {', '.join(ALIGNMENTS)}")
    g, e = synchronize(gt, est, max_dt_s, sync)
    if len(g) < 3:
        raise CaptureError(
            f"only {len(g)} estimated pose(s) within {max_dt_s * 1e3:g} ms of a ground-truth pose; need >= 3 "
            "(do the clocks overlap?)"
        )
    s, R, t = alignment(g.p_world, e.p_world, align)
    p_aligned = s * e.p_world @ R.T + t
    R_aligned = R @ e.world_R_body()
    pos_err = np.linalg.norm(p_aligned - g.p_world, axis=1)
    rot_err = np.degrees(Rotation.from_matrix(np.swapaxes(g.world_R_body(), 1, 2) @ R_aligned).magnitude())
    sim3_scale = umeyama(e.p_world, g.p_world, with_scale=True)[0]

    Q = g.world_T_body()
    P = np.tile(np.eye(4), (len(e), 1, 1))
    P[:, :3, :3], P[:, :3, 3] = R_aligned, p_aligned
    dist = path_distances(g.p_world)
    rpe: dict[str, dict] = {}
    for length in segments_m:
        si, sj = segment_pairs(dist, float(length), rpe_rel_tol)
        if si.size == 0:
            continue
        te, re = _relative_errors(Q, P, si, sj)
        entry = {"length_m": float(length), "pairs": int(si.size)}
        entry.update({f"trans_{k}": v for k, v in _stats(te, "m").items()})
        entry.update({f"rot_{k}": v for k, v in _stats(re, "deg").items()})
        entry["trans_pct"] = float(100.0 * np.mean(te / (dist[sj] - dist[si])))
        rpe[f"{length:g}m"] = entry

    steps = np.diff(g.t_ns) * 1e-9
    path_m = float(dist[-1])
    gt_span_s = float((gt.t_ns[-1] - gt.t_ns[0]) * 1e-9)
    coverage_s = float(steps[steps <= coverage_gap_s].sum())
    return {
        "align": align,
        "sync": sync,
        "pairs": len(g),
        "gt_poses": len(gt),
        "est_poses": len(est),
        "ate_rmse_m": float(np.sqrt(np.mean(pos_err**2))),
        "ate_mean_m": float(pos_err.mean()),
        "ate_median_m": float(np.median(pos_err)),
        "ate_max_m": float(pos_err.max()),
        "ate_rot_rmse_deg": float(np.sqrt(np.mean(rot_err**2))),
        "scale": float(sim3_scale),
        "scale_error_pct": float(100.0 * abs(sim3_scale - 1.0)),
        "estimate_scale_error_pct": float(100.0 * (1.0 / sim3_scale - 1.0)),
        "alignment": {"scale": float(s), "R": R.tolist(), "t": t.tolist()},
        "path_length_m": path_m,
        "final_error_m": float(pos_err[-1]),
        "drift_pct": float(100.0 * pos_err[-1] / path_m) if path_m > 0 else float("nan"),
        "rpe": rpe,
        "gt_span_s": gt_span_s,
        "coverage_s": coverage_s,
        "coverage_frac": coverage_s / gt_span_s if gt_span_s > 0 else 0.0,
    }
