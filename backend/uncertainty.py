"""How far to trust the metric scale: the standard deviation of distances between distant keyframes, from the
joint marginal covariance of their positions in the solved factor graph.

The estimator fixes the gauge at its first keyframe; the distance between two keyframes far apart is
gauge-invariant, so its standard deviation divided by its length measures how well the graph pins the scale
(with the drift between them). This takes the median over a few pairs spread along the trajectory. It is the
graph's own answer under its noise model; whether it is calibrated is a matter of Monte-Carlo runs over seeds
(docs/BENCHMARKS.md).

Also the capture advice: how much acceleration the run carried (the accelerometer's own limit on the scale is its
noise density / sqrt of that; issue 15) and, when the stated sigma is large, what to do next time.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import gtsam
import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from backend.keys import X
from backend.smoother import first_line
from vio.records import GRAVITY_WORLD, ImuSeries, StateEstimate

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


ADVISE_ABOVE_REL = 0.003  # `vio run` says how to capture next time when the stated scale sigma exceeds this
TARGET_REL = 0.0015  # the sigma of a 0.1 % median scale error, for the advice
SHAKE_RMS_M_S2 = 5.6  # RMS acceleration of a phone shaken about 5 cm each way at 2 Hz, m/s^2


def motion_excitation(imu: ImuSeries, states: Sequence[StateEstimate], acc_noise_density: float) -> float | None:
    """The integral over the run of the squared body-frame kinematic acceleration, its mean removed, (m/s^2)^2 s:
    what makes the scale observable (docs/BENCHMARKS.md, issue 15). From the IMU samples between the first and last
    state: specific force minus the estimated accelerometer bias plus gravity rotated into the body (orientations
    slerped between keyframes, world z up), less the white noise's share (3 density^2 / dt per second). The
    accelerometer alone limits the relative scale sigma to density / sqrt(excitation). None when too short."""
    if len(states) < 2:
        return None
    kt = np.array([s.t_ns for s in states], np.int64)
    t = np.asarray(imu.t_ns, np.int64)
    inside = (t >= kt[0]) & (t <= kt[-1])
    if inside.sum() < 10:
        return None
    ti = t[inside]
    rot = Slerp(kt * 1e-9, Rotation.from_matrix(np.array([s.world_T_body[:3, :3] for s in states])))(ti * 1e-9)
    j = np.clip(np.searchsorted(kt, ti, side="right") - 1, 0, len(kt) - 1)
    bias = np.array([s.bias_acc for s in states])[j]
    a_body = np.asarray(imu.acc, float)[inside] - bias + rot.inv().apply(GRAVITY_WORLD)
    dt = np.diff(ti) * 1e-9
    raw = float(np.sum((a_body[:-1] - a_body.mean(axis=0)) ** 2 * dt[:, None]))
    noise = 3.0 * acc_noise_density**2 * float(dt.sum()) / float(np.median(dt))
    return max(raw - noise, 0.0)


def scale_advice(sigma_rel: float, excitation: float | None, acc_noise_density: float) -> str | None:
    """One line on how to capture next time when the stated scale sigma exceeds ADVISE_ABOVE_REL, else None: more
    brisk motion when the accelerometer's limit is more than half the stated sigma, else the images limit it."""
    if sigma_rel <= ADVISE_ABOVE_REL or excitation is None:
        return None
    limit = acc_noise_density / np.sqrt(excitation) if excitation > 0 else float("inf")
    allow = f"allow {100 * limit:.2f} % at best" if excitation > 0 else "do not show the scale"
    head = f"scale sigma {100 * sigma_rel:.2f} %; the motion's accelerations alone {allow}"
    missing = (acc_noise_density / TARGET_REL) ** 2 - excitation
    if limit < 0.5 * sigma_rel or missing <= 0:
        return f"{head}: the images limit the scale here, not the motion"
    seconds = max(missing / SHAKE_RMS_M_S2**2, 1.0)
    return (
        f"{head}: next time add about {seconds:.0f} s of brisk motion (the phone shaken about 5 cm each way at "
        f"2 Hz, in all directions), which brings that limit to {100 * TARGET_REL:.2f} %; holding still or filming "
        "longer adds little"
    )
