"""How far to trust the metric scale: the standard deviation of distances between distant keyframes, from the
joint marginal covariance of their positions in the solved factor graph.

The estimator fixes the gauge at its first keyframe; the distance between two keyframes far apart is
gauge-invariant, so its standard deviation divided by its length measures how well the graph pins the scale
(with the drift between them). This takes the median over a few pairs spread along the trajectory. It is the
graph's own answer under its noise model; whether it is calibrated is a matter of Monte-Carlo runs over seeds
(docs/BENCHMARKS.md).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import gtsam
import numpy as np

from backend.keys import X
from backend.smoother import first_line

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ScaleUncertainty:
    """The relative standard deviation of the trajectory's scale and the pairs it came from."""

    sigma_rel: float  # median over the pairs of sigma(distance) / distance
    pairs: tuple[tuple[int, int, float, float], ...]  # (k_a, k_b, distance m, sigma m)


def _position_cov_world(cov: np.ndarray, Ra: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    """(6, 6) covariance of the world positions of two poses from their joint (12, 12) tangent covariance
    (gtsam Pose3 tangent: rotation first, then translation in the body frame)."""
    J = np.zeros((6, 12))
    J[:3, 3:6] = Ra
    J[3:, 9:12] = Rb
    return J @ cov @ J.T


def scale_uncertainty(
    graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, keyframes: list[int], num_pairs: int = 5
) -> ScaleUncertainty | None:
    """The scale's relative standard deviation from `graph` linearised at `values`, over `num_pairs` pairs of
    keyframes at least half the trajectory's extent apart; None when the graph cannot be marginalised."""
    ks = [k for k in keyframes if values.exists(X(k))]
    if len(ks) < 4:
        return None
    p = np.array([values.atPose3(X(k)).translation() for k in ks])
    far = np.linalg.norm(p[:, None] - p[None], axis=2)
    extent = float(far.max())
    if extent <= 0:
        return None
    try:
        marginals = gtsam.Marginals(graph, values)
    except RuntimeError as exc:
        log.warning("scale uncertainty: the graph cannot be marginalised (%s)", first_line(exc))
        return None
    pairs = []
    for i in np.linspace(0, len(ks) - 1, num_pairs + 1).astype(int)[:-1]:
        j = int(np.argmax(far[i]))
        if far[i, j] < 0.5 * extent:
            continue
        ka, kb = ks[i], ks[j]
        keys = gtsam.KeyVector([X(ka), X(kb)])
        jm = marginals.jointMarginalCovariance(keys)
        cov = np.block([[jm.at(X(ka), X(ka)), jm.at(X(ka), X(kb))], [jm.at(X(kb), X(ka)), jm.at(X(kb), X(kb))]])
        Ra, Rb = values.atPose3(X(ka)).rotation().matrix(), values.atPose3(X(kb)).rotation().matrix()
        c = _position_cov_world(cov, Ra, Rb)
        u = (p[j] - p[i]) / far[i, j]
        grad = np.concatenate([-u, u])
        pairs.append((ka, kb, float(far[i, j]), float(np.sqrt(max(grad @ c @ grad, 0.0)))))
    if not pairs:
        return None
    return ScaleUncertainty(float(np.median([s / d for _, _, d, s in pairs])), tuple(pairs))
