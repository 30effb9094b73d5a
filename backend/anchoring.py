"""Known positions (tripod ring, turntable, GNSS) as GPS-like factors, in the estimator's own frame.

The estimator fixes its gauge at the first keyframe (position 0, yaw 0), while known positions live in their own
world frame (same z-up gravity; yaw and origin differ). Adding them at once would fight the gauge prior, so the
anchor first collects (estimated, known) position pairs; once they span `min_spread_m`, it fits the 4-DoF
transform known_T_est (yaw about z + translation) and from then on adds every known position, mapped into the
estimator's frame, as a `GPSFactor`. The positions then correct scale and drift; outputs are mapped back with
known_T_est so that trajectory and landmarks come out in the positions' frame.
"""

from __future__ import annotations

import logging

import gtsam
import numpy as np

from backend import factors as fb
from backend.keys import X

log = logging.getLogger(__name__)

KnownPosition = tuple[int, np.ndarray, float]  # (t_ns, p_world (3,) m in the known frame, sigma m)


def fit_yaw_translation(p_est: np.ndarray, p_known: np.ndarray) -> np.ndarray:
    """(4, 4) known_T_est: rotation about z and translation minimising the squared position differences."""
    me, mk = p_est.mean(axis=0), p_known.mean(axis=0)
    e, k = p_est - me, p_known - mk
    yaw = np.arctan2(np.sum(e[:, 0] * k[:, 1] - e[:, 1] * k[:, 0]), np.sum(e[:, 0] * k[:, 0] + e[:, 1] * k[:, 1]))
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = mk - T[:3, :3] @ me
    return T


class PositionAnchor:
    """Matches known positions to keyframes and decides when they can enter the graph."""

    def __init__(self, positions: list[KnownPosition], max_dt_s: float, min_spread_m: float = 0.5) -> None:
        self.positions = sorted(positions, key=lambda p: p[0])
        self.t_ns = np.array([p[0] for p in self.positions], np.int64)
        self.max_dt_s = max_dt_s
        self.min_spread_m = min_spread_m
        self.pairs: list[tuple[int, np.ndarray, float]] = []  # (k, p_known, sigma) matched to keyframes
        self.known_T_est: np.ndarray | None = None
        self.num_factors = 0

    def match(self, k: int, t_ns: int) -> tuple[np.ndarray, float] | None:
        """The known position nearest to keyframe time t_ns (within max_dt_s), sigma inflated by the offset."""
        if self.t_ns.size == 0:
            return None
        i = int(np.argmin(np.abs(self.t_ns - t_ns)))
        dt = abs(int(self.t_ns[i]) - t_ns) * 1e-9
        if dt > self.max_dt_s:
            return None
        _, p, sigma = self.positions[i]
        out = (p, float(np.hypot(sigma, dt * 1.0)))  # ~1 m/s motion over the offset
        self.pairs.append((k, *out))
        return out

    def try_align(self, p_est_of: dict[int, np.ndarray]) -> bool:
        """Fit known_T_est once the matched known positions span min_spread_m; True when newly aligned."""
        if self.known_T_est is not None or len(self.pairs) < 3:
            return False
        pairs = [(p_est_of[k], p) for k, p, _ in self.pairs if k in p_est_of]
        if len(pairs) < 3:
            return False
        est, known = (np.array(x) for x in zip(*pairs, strict=True))
        if np.linalg.norm(known - known.mean(axis=0), axis=1).max() * 2 < self.min_spread_m:
            return False
        self.known_T_est = fit_yaw_translation(est, known)
        return True

    def to_est(self, p_known: np.ndarray) -> np.ndarray:
        """A known position in the estimator's frame (after alignment)."""
        T = np.linalg.inv(self.known_T_est)
        return T[:3, :3] @ p_known + T[:3, 3]

    def factors(self, k: int, t_ns: int, values: gtsam.Values) -> list[gtsam.NonlinearFactor]:
        """GPS-like factors for keyframe k at t_ns: its matched known position, plus all earlier matches at the
        keyframe where the alignment first succeeds (`values` holds the estimated poses)."""
        matched = self.match(k, t_ns) is not None
        p_est = {kk: values.atPose3(X(kk)).translation() for kk, _, _ in self.pairs if values.exists(X(kk))}
        if self.try_align(p_est):
            todo = [pair for pair in self.pairs if values.exists(X(pair[0]))]
            log.info("known positions aligned (yaw + translation) after %d matches", len(todo))
        elif self.known_T_est is not None and matched:
            todo = self.pairs[-1:]
        else:
            return []
        out = [fb.position_factor(kk, self.to_est(p), sigma) for kk, p, sigma in todo]
        self.num_factors += len(out)
        return out
