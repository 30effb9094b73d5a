"""Overlapping Allan deviation of a rate signal (gyro rad/s, accelerometer m/s^2), and the IEEE 952 noise terms.

For samples y_k at rate f (tau0 = 1/f) and cluster time tau = m tau0, with theta_k = tau0 * sum_{i<k} y_i:
    sigma^2(tau) = sum_{k=0}^{N-2m} (theta_{k+2m} - 2 theta_{k+m} + theta_k)^2 / (2 tau^2 (N - 2m + 1))
(N + 1 values of theta), the estimator of allantools' `oadev(data_type="freq")`, against which the tests check it.

Noise terms (IEEE Std 952, Annex C): white noise N gives sigma = N / sqrt(tau) (slope -1/2; read at tau = 1 s),
rate random walk K gives sigma = K sqrt(tau / 3) (slope +1/2; read at tau = 3 s), bias instability B gives a floor
sigma = sqrt(2 ln 2 / pi) B ~ 0.664 B at the minimum. N and K are fitted together to the whole curve by
non-negative least squares on sigma^2 = N^2 / tau + K^2 tau / 3, each tau weighted by the square root of its number
of independent clusters over the model's sigma^2 (iteratively reweighted), so that neither line is read where the
other term still bends the curve. B is read at the curve's minimum.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

BIAS_INSTABILITY_FACTOR = float(np.sqrt(2.0 * np.log(2.0) / np.pi))  # 0.664: sigma floor / B
TAUS_PER_DECADE = 10
MIN_CLUSTERS = 9
IRLS_ROUNDS = 4  # the longest tau leaves at least this many non-overlapping clusters


def cluster_sizes(n: int, per_decade: int = TAUS_PER_DECADE) -> np.ndarray:
    """Log-spaced cluster sizes m (in samples) from 1 to n / MIN_CLUSTERS, unique integers."""
    m_max = max(1, n // MIN_CLUSTERS)
    m = np.unique(np.round(np.logspace(0, np.log10(m_max), int(np.log10(m_max) * per_decade) + 1)).astype(np.int64))
    return m[m >= 1]


def overlapping_adev(y: np.ndarray, rate_hz: float, m: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(taus s, adev) of the rate samples y (N,) at rate_hz for cluster sizes m (default `cluster_sizes`)."""
    y = np.asarray(y, dtype=np.float64)
    tau0 = 1.0 / rate_hz
    m = cluster_sizes(len(y)) if m is None else np.asarray(m, np.int64)
    theta = np.concatenate([[0.0], np.cumsum(y - y.mean()) * tau0])  # the mean cancels; removing it keeps precision
    n = len(theta)
    adev = np.empty(len(m))
    for i, mi in enumerate(m):
        d = theta[2 * mi :] - 2.0 * theta[mi : n - mi] + theta[: n - 2 * mi]
        adev[i] = np.sqrt(np.mean(d * d) / 2.0) / (mi * tau0)
    return m * tau0, adev


@dataclass(frozen=True)
class NoiseFit:
    """IEEE 952 terms of one axis, in continuous-time units (rate units r: rad/s or m/s^2)."""

    white: float  # noise density N, r/sqrt(Hz) (the -1/2 line at tau = 1 s)
    random_walk: float  # K, r/s/sqrt(Hz) (the +1/2 line at tau = 3 s)
    bias_instability: float  # B, r (the curve's minimum / 0.664)
    tau_min_s: float  # where the curve has its minimum, s


def fit_noise(taus: np.ndarray, adev: np.ndarray, duration_s: float) -> NoiseFit:
    """White noise, random walk and bias instability from an Allan deviation curve (module docstring)."""
    from scipy.optimize import nnls

    taus = np.asarray(taus, float)
    var = np.asarray(adev, float) ** 2
    clusters = np.sqrt(np.maximum(duration_s / taus - 1.0, 1.0))  # 1 / relative standard error of sigma^2
    G = np.column_stack([1.0 / taus, taus / 3.0])
    model = var
    for _ in range(IRLS_ROUNDS):  # weights from the model, not the noisy curve (which would bias the fit low)
        w = clusters / model
        coef, _ = nnls(G * w[:, None], var * w)
        model = np.maximum(G @ coef, 1e-300)
    i = int(np.argmin(adev))
    return NoiseFit(
        white=float(np.sqrt(coef[0])),
        random_walk=float(np.sqrt(coef[1])),
        bias_instability=float(adev[i] / BIAS_INSTABILITY_FACTOR),
        tau_min_s=float(taus[i]),
    )
