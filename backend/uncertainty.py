"""How far to trust the metric scale: the standard deviation of distances between distant keyframes, from the
joint marginal covariance of their positions in the solved factor graph.

The estimator fixes the gauge at its first keyframe; the distance between two keyframes far apart is
gauge-invariant, so its standard deviation divided by its length measures how well the graph pins the scale
(with the drift between them). This takes the median over a few pairs spread along the trajectory. It is the
graph's own answer under its noise model; whether it is calibrated is a matter of Monte-Carlo runs over seeds
(docs/BENCHMARKS.md).

Bounded cost (issue 18). The joint covariance of the pairs' poses is the inverse of the graph's information with
every other variable eliminated first (landmarks, velocities, biases, the other poses; one sparse elimination
with the pairs' keys ordered last), not `gtsam.Marginals` of the whole graph, whose Bayes tree and joint queries
between distant cliques took more CPU than the estimation on a 180 s capture. Up to `CHUNK_KEYFRAMES` keyframes
this is the whole graph's answer to rounding. A longer run is cut into equal chunks of consecutive keyframes of at
most that many; each chunk's graph (the factors among its own keyframes, and the views from them of landmarks seen
at least twice in it; its first pose pinned in the gauge directions, yaw and position, when the run's own prior
is not in it) gives the scale's sigma as above, and the chunks, independent measurements of one scale, combine
by inverse variance. Cost and memory per chunk are those of a chunk-long run, so the whole step grows linearly in
time and not in memory. Measured on the orbit, the combination reads 0-6 % below the whole graph's sigma (3 %
on the 180 s orbit; it treats the chunks as independent and leaves out the drift between them; docs/BENCHMARKS.md,
"Bounded cost").

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

from backend import factors as fb
from backend.keys import X
from backend.smoother import first_line, value_of
from vio.records import GRAVITY_WORLD, ImuSeries, StateEstimate

log = logging.getLogger(__name__)

CHUNK_KEYFRAMES = 400  # a run with more keyframes is cut into chunks of at most this many (the 60 s orbit: 343-359)
GAUGE_SIGMA_M, GAUGE_SIGMA_RAD = 1e-3, 1e-3  # a chunk's first pose pinned in position and yaw (distances ignore it)
FREE_TILT_RAD = 10.0  # ... and left free in roll and pitch, which gravity observes
_ROWS = 256  # keyframe positions compared in blocks of this many rows (no N x N x 3 array)


@dataclass(frozen=True)
class ScaleUncertainty:
    """The relative standard deviation of the trajectory's scale and the pairs it came from."""

    sigma_rel: float  # median over the pairs of sigma(distance) / distance (one chunk); inverse-variance over chunks
    pairs: tuple[tuple[int, int, float, float], ...]  # (k_a, k_b, distance m, sigma m)


def _position_cov_world(cov: np.ndarray, Ra: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    """(6, 6) covariance of the world positions of two poses from their joint (12, 12) tangent covariance
    (gtsam Pose3 tangent: rotation first, then translation in the body frame)."""
    J = np.zeros((6, 12))
    J[:3, 3:6] = Ra
    J[3:, 9:12] = Rb
    return J @ cov @ J.T


def scale_uncertainty(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    keyframes: list[int],
    num_pairs: int = 5,
    chunk_keyframes: int = CHUNK_KEYFRAMES,
    pin_first: bool = False,
    landmark_prior_sigma_m: float | None = None,
) -> ScaleUncertainty | None:
    """The scale's relative standard deviation from `graph` linearised at `values`, over `num_pairs` pairs of
    keyframes at least half the trajectory's extent apart (per chunk of at most `chunk_keyframes` keyframes, the
    chunks combined; module docstring); None when no chunk's graph can be marginalised. `pin_first`: the first
    chunk's first pose is pinned too (the run's prior is not in `graph`); `landmark_prior_sigma_m`: the graph holds
    no landmark priors, each landmark gets one of this sigma (`ScaleChunks`)."""
    ks = [k for k in keyframes if values.exists(X(k))]
    if len(ks) < 4:
        return None
    n = -(-len(ks) // max(int(chunk_keyframes), 4))
    if n == 1 and not pin_first and landmark_prior_sigma_m is None:
        return _graph_scale(graph, values, ks, num_pairs)
    chunks = [[int(k) for k in c] for c in np.array_split(np.asarray(ks, np.int64), n)]
    subs = _chunk_graphs(graph, values, chunks, pin_first, landmark_prior_sigma_m)
    return combine(
        [
            _sub_scale(sub, values, chunk, num_pairs, f"chunk {c + 1} of {n}")
            for c, (sub, chunk) in enumerate(zip(subs, chunks, strict=True))
        ]
    )


def combine(results: Sequence[ScaleUncertainty | None]) -> ScaleUncertainty | None:
    """Independent measurements of one scale (chunks) by inverse variance; None when there is none."""
    found = [r for r in results if r is not None]
    if not found:
        return None
    sigma = float(np.sum([r.sigma_rel**-2.0 for r in found]) ** -0.5)
    return ScaleUncertainty(sigma, tuple(pair for r in found for pair in r.pairs))


def _sub_scale(
    sub: gtsam.NonlinearFactorGraph, values: gtsam.Values, chunk: list[int], num_pairs: int, name: str
) -> ScaleUncertainty | None:
    """`_graph_scale` of one chunk's graph (its values taken from `values`); None, with a warning, when it fails."""
    sub_values = gtsam.Values()
    for key in sub.keyVector():
        sub_values.insert(key, value_of(values, key))
    result = _graph_scale(sub, sub_values, chunk, num_pairs)
    if result is None or not result.sigma_rel > 0:
        log.warning("scale uncertainty: %s (keyframes %d-%d) left out", name, chunk[0], chunk[-1])
        return None
    return result


def _graph_scale(
    graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, ks: list[int], num_pairs: int
) -> ScaleUncertainty | None:
    """The median relative sigma of the distances of `num_pairs` distant pairs among keyframes `ks` in `graph`."""
    p = np.array([values.atPose3(X(k)).translation() for k in ks])
    extent = max(float(np.linalg.norm(p[a : a + _ROWS, None] - p[None], axis=2).max()) for a in range(0, len(p), _ROWS))
    if extent <= 0:
        return None
    chosen = []
    for i in np.linspace(0, len(ks) - 1, num_pairs + 1).astype(int)[:-1]:
        d = np.linalg.norm(p - p[i], axis=1)
        j = int(np.argmax(d))
        if d[j] >= 0.5 * extent:
            chosen.append((int(i), j, float(d[j])))
    if not chosen:
        return None
    keys = sorted({X(ks[i]) for i, _, _ in chosen} | {X(ks[j]) for _, j, _ in chosen})
    try:
        cov = _joint_pose_covariance(graph, values, keys)
    except RuntimeError as exc:
        log.warning("scale uncertainty: the graph cannot be marginalised (%s)", first_line(exc))
        return None
    col = {key: 6 * n for n, key in enumerate(keys)}
    pairs = []
    for i, j, dist in chosen:
        ka, kb = X(ks[i]), X(ks[j])
        rows = np.r_[col[ka] : col[ka] + 6, col[kb] : col[kb] + 6]
        Ra, Rb = values.atPose3(ka).rotation().matrix(), values.atPose3(kb).rotation().matrix()
        c = _position_cov_world(cov[np.ix_(rows, rows)], Ra, Rb)
        u = (p[j] - p[i]) / dist
        grad = np.concatenate([-u, u])
        pairs.append((ks[i], ks[j], dist, float(np.sqrt(max(grad @ c @ grad, 0.0)))))
    return ScaleUncertainty(float(np.median([s / d for _, _, d, s in pairs])), tuple(pairs))


def _joint_pose_covariance(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, keys: list[int]) -> np.ndarray:
    """(6n, 6n) joint tangent covariance of the poses `keys` (in that order): every other variable of the graph
    linearised at `values` eliminated first (COLAMD with `keys` last), then the dense inverse of what remains."""
    marginal = graph.linearize(values).marginal(gtsam.KeyVector(keys))
    ordering = gtsam.Ordering()
    for key in keys:
        ordering.push_back(key)
    information, _ = marginal.hessian(ordering)
    if not np.all(np.isfinite(information)):
        raise RuntimeError("the marginal information is not finite")
    try:
        inverse_factor = np.linalg.inv(np.linalg.cholesky(information))
    except np.linalg.LinAlgError as exc:
        raise RuntimeError(f"the marginal information is not positive definite ({exc})") from exc
    return inverse_factor.T @ inverse_factor


def _chunk_graphs(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    chunks: list[list[int]],
    pin_first: bool = False,
    landmark_prior_sigma_m: float | None = None,
) -> list[gtsam.NonlinearFactorGraph]:
    """One graph per chunk of keyframes: the factors whose keyframe variables (X, V, B) all belong to the chunk,
    those on landmarks only when the chunk sees each of their landmarks at least twice, and landmark-only factors
    likewise; chunks after the first (and the first too with `pin_first`) get their first pose pinned in the gauge
    directions. Factors across a chunk's border (the IMU factor between two chunks) are left out. With
    `landmark_prior_sigma_m` the landmark-only factors are ignored and each landmark of a chunk gets a prior of
    that sigma at its value (the admission's prior: the same information, whatever its mean)."""
    chunk_of = {k: c for c, chunk in enumerate(chunks) for k in chunk}
    kept: list[list[tuple[gtsam.NonlinearFactor, list[int]]]] = [[] for _ in chunks]
    views: list[dict[int, int]] = [{} for _ in chunks]
    landmark_only = []
    for i in range(graph.size()):
        factor = graph.at(i)
        if factor is None:
            continue
        frames, landmarks = set(), []
        for key in factor.keys():
            sym = gtsam.Symbol(key)
            if chr(sym.chr()) == "l":
                landmarks.append(key)
            else:
                frames.add(chunk_of.get(int(sym.index()), -1))
        if not frames:
            landmark_only.append((factor, landmarks))
        elif len(frames) == 1 and -1 not in frames:
            c = frames.pop()
            kept[c].append((factor, landmarks))
            for key in landmarks:
                views[c][key] = views[c].get(key, 0) + 1
    if landmark_prior_sigma_m is not None:
        landmark_only = []
    out = []
    for c, chunk in enumerate(chunks):
        sub = gtsam.NonlinearFactorGraph()
        for factor, landmarks in kept[c] + landmark_only:
            if all(views[c].get(key, 0) >= 2 for key in landmarks):
                sub.add(factor)
        if landmark_prior_sigma_m is not None:
            for key in sorted(key for key, n in views[c].items() if n >= 2):
                sub.add(fb.landmark_prior(gtsam.Symbol(key).index(), values.atPoint3(key), landmark_prior_sigma_m))
        if c > 0 or pin_first:
            k0 = chunk[0]
            sub.add(
                fb.pose_prior_gravity_aware(k0, values.atPose3(X(k0)), FREE_TILT_RAD, GAUGE_SIGMA_RAD, GAUGE_SIGMA_M)
            )
        out.append(sub)
    return out


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
