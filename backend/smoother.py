"""The incremental solvers behind one small interface: full iSAM2, iSAM2 in a fixed lag, and batch LM.

`Smoother.update()` raises `SolverFailure` when GTSAM throws (for example `IndeterminantLinearSystemException`);
after that the solver is half-updated and must be rebuilt (`Smoother.reset()`), never retried.
"""

from __future__ import annotations

import logging
import math
from typing import Any

import gtsam
import numpy as np

from vio.config import SmootherConfig

log = logging.getLogger(__name__)


class SolverFailure(RuntimeError):
    """GTSAM failed inside an incremental update; the solver state is no longer usable."""


def first_line(exc: BaseException) -> str:
    """The first non-empty line of an exception message (GTSAM's start with a newline)."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    return " ".join(lines[:2]) if lines else type(exc).__name__


def value_of(values: gtsam.Values, key: int) -> Any:
    """The value of a key of any of the four kinds (X pose, V velocity, B bias, L point)."""
    sym = chr(gtsam.Symbol(key).chr())
    if sym == "x":
        return values.atPose3(key)
    if sym == "v":
        return values.atVector(key)
    if sym == "b":
        return values.atConstantBias(key)
    return values.atPoint3(key)


def isam2_params(cfg: SmootherConfig) -> gtsam.ISAM2Params:
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(cfg.relinearize_threshold)
    params.relinearizeSkip = int(cfg.relinearize_skip)
    # Cholesky is ~25% faster but declares long inertial-only stretches indeterminate once the pose uncertainty
    # dwarfs the priors (measured on the EuRoC IMU before zero-velocity updates: 2-10 s); QR is the robust option.
    # A failure is not fatal either way (the estimator rebuilds from the last good state).
    params.setFactorization(cfg.factorization)
    # New factors take the slots of removed ones. A fixed lag removes every factor it marginalises, and without this
    # iSAM2's factor list kept a null slot for each: 52,000 more a minute on the 10-minute orbit, 306,000 by minute six
    # (docs/BENCHMARKS.md, "The fixed lag's factor slots"). iSAM2 alone removes none, so it is unchanged.
    params.findUnusedFactorSlots = True
    return params


class Smoother:
    """iSAM2 (`cfg.kind == "isam2"`) or an incremental fixed-lag smoother (`"fixed_lag"`, `cfg.lag_s`)."""

    def __init__(self, cfg: SmootherConfig) -> None:
        self.cfg = cfg
        self.kind = cfg.kind
        self._getter_of: dict[int, str] = {}  # key -> the name of its estimate getter
        if self.kind not in ("isam2", "fixed_lag"):
            raise ValueError(f"smoother.kind must be isam2 or fixed_lag, got {cfg.kind!r}")
        self.deferred = self.kind == "fixed_lag" and cfg.background
        self._holding = self.kind == "fixed_lag" and cfg.hold_start_s > 0
        self._own_lag = self.deferred and cfg.background_marginalises and cfg.own_marginalisation
        self._t0: float | None = None  # fixed lag with a held start: the first timestamp (kept through a reset)
        self.reset()

    def reset(self) -> None:
        params = isam2_params(self.cfg)
        if self._own_lag:
            params.relinearizeSkip = 2**31 - 1  # never by the counter: the background step forces it
        elif self.deferred:
            # gtsam relinearises in its updates number n, 2n, ... counted from 1 (n = relinearizeSkip): with
            # n = skip + 1 those are the background steps, each after `relinearize_skip` updates (tested)
            params.relinearizeSkip = int(self.cfg.relinearize_skip) + 1
        if self.kind == "isam2" or self._own_lag:
            self._isam = gtsam.ISAM2(params)
        else:
            self._isam = gtsam.IncrementalFixedLagSmoother(self.cfg.lag_s, params)
        self._keys: set[int] = set()
        self._result: gtsam.ISAM2Result | None = None  # iSAM2's account of the last update (plain iSAM2)
        self._stamps: dict[int, float] = {}  # fixed lag: key -> its latest timestamp, s (as the smoother holds it)
        self._num_updates = 0  # gtsam updates since the reset (its relinearisation counter)
        self._held: dict[int, float] = {}  # deferred: key -> its timestamp, held back until the background step
        self._own: dict[int, float] = {}  # held start: key -> its own timestamp (the smoother may hold another)

    def last_result(self) -> gtsam.ISAM2Result | None:
        """iSAM2's account of the last update (variables relinearised, re-eliminated, ...)."""
        return (
            self._isam.getISAM2Result() if isinstance(self._isam, gtsam.IncrementalFixedLagSmoother) else self._result
        )

    def factors(self) -> gtsam.NonlinearFactorGraph:
        """iSAM2's factor list (a removed factor leaves a null slot until a new one takes it)."""
        if isinstance(self._isam, gtsam.IncrementalFixedLagSmoother):
            return self._isam.getFactors()
        return self._isam.getFactorsUnsafe()

    def num_variables(self) -> int:
        """Variables in the solver now (fixed lag: the window only)."""
        return len(self._keys)

    def has(self, key: int) -> bool:
        """True while `key` is a variable of the solver (fixed lag: not yet marginalised)."""
        return key in self._keys

    def update(
        self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, timestamps: dict[int, float]
    ) -> gtsam.Values:
        """Add factors and new variables; timestamps (s) are used by the fixed-lag smoother only. Returns the last
        estimate of the variables that this update marginalised (fixed lag; always empty for iSAM2).

        Deferred (`smoother.background`): the update does not relinearise, and with `background_marginalises` it
        does not marginalise either: a timestamp newer than the smoother's newest is given that newest, one older
        than its lag's boundary (the held start's released variables) that boundary, and the true one is held back
        for the background step. A step that is due must have run before the caller built this update's factors
        (it may marginalise variables they would use): a RuntimeError if not."""
        if self.kind == "fixed_lag" and self.cfg.marginalise_every_s > 0:
            timestamps = {key: self._block(t) for key, t in timestamps.items()}
        if self._holding:
            timestamps = self._hold(timestamps)
        if not self.deferred or self._num_updates == 0:
            return self._update(graph, values, timestamps)
        if self.background_due():
            raise RuntimeError("the smoother's background step is due: run background() before building the update")
        if not self.cfg.background_marginalises:
            return self._update(graph, values, timestamps)
        newest = max(self._stamps.values(), default=math.inf)
        boundary = newest - self.cfg.lag_s  # gtsam's rule is strict: a variable stamped here stays
        out: dict[int, float] = {}
        for key, t in timestamps.items():
            out[key] = min(max(t, boundary), newest)
            if out[key] != t:
                self._held[key] = t
            else:
                self._held.pop(key, None)  # seen again: an older held stamp must not marginalise it later
        return self._update(graph, values, out)

    def background_due(self) -> bool:
        """Deferred: True when the background step should run now (after every `relinearize_skip` keyframes)."""
        n = self.cfg.relinearize_skip + 1
        return self.deferred and self._num_updates > 0 and (self._num_updates + 1) % n == 0

    def background(self, newest: gtsam.Values | None = None) -> gtsam.Values:
        """Deferred: relinearise the window and marginalise what left the lag with the held-back timestamps (one
        gtsam update); returns the last estimate of what it marginalised, as `update` does.

        `newest`: the latest keyframe's variables and the landmarks it saw, at their estimates. Each gets a prior
        of no weight (`NO_WEIGHT` sigma) in this update, so that iSAM2, which eliminates the variables of an
        update's factors last, keeps them at the top of the tree, where the next keyframe's factors attach. An
        update without factors leaves the order to COLAMD alone (a step that relinearises most of the window
        re-eliminates all of it), and the next keyframe's update then cost 48 ms instead of 8.5 ms in the median
        on the 60 s orbit's first 36 s (docs/BENCHMARKS.md, "The held start in the background").

        A step that marginalises lets gtsam's fixed lag order its update (what leaves first, every other variable in
        one group), and the newest variables sink whatever the priors say. With `own_marginalisation` the step runs
        on plain iSAM2 and gives the order itself (`_ordered_update`), and needs no priors."""
        held, self._held = self._held, {}
        if self._own_lag:
            return self._update(gtsam.NonlinearFactorGraph(), gtsam.Values(), held, newest, step=True)
        graph = gtsam.NonlinearFactorGraph()
        for key in [] if newest is None else newest.keys():
            graph.add(_no_weight_prior(key, newest))
        return self._update(graph, gtsam.Values(), held)

    def _update(
        self,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        timestamps: dict[int, float],
        newest: gtsam.Values | None = None,
        step: bool = False,
    ) -> gtsam.Values:
        leaving = self._leaving(timestamps)
        try:
            retired = self.estimate_keys([key for key in leaving if key in self._keys])
            for key in leaving:
                if not retired.exists(key):  # new in this update and already older than the lag
                    retired.insert(key, value_of(values, key))
            if step or (self._own_lag and leaving):  # the latter: the first update, before any clamping
                self._ordered_update(graph, values, leaving, newest, relinearise=step)
            elif self.kind == "isam2" or self._own_lag:
                self._result = self._isam.update(graph, values)
            else:
                self._isam.update(graph, values, timestamps)
        except (RuntimeError, ValueError) as exc:  # gtsam raises both (ValueError: std::invalid_argument)
            raise SolverFailure(first_line(exc)) from exc
        self._num_updates += 1
        self._keys.update(values.keys())
        self._keys.difference_update(leaving)
        for key in leaving:
            del self._stamps[key]
            self._getter_of.pop(key, None)
        return retired

    def _ordered_update(
        self,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        leaving: list[int],
        newest: gtsam.Values | None,
        relinearise: bool,
    ) -> None:
        """The background step on plain iSAM2 (`own_marginalisation`): one update that relinearises (forced) and
        re-eliminates in the order given: the variables that leave first (so that they are leaves), the newest
        keyframe's last (where the next keyframe's factors attach), then the leavers marginalised. With nothing
        leaving only what relinearisation touches is re-eliminated; with leavers, the whole window (gtsam's fixed
        lag marks the subtrees under them instead, which needs the Bayes tree's cliques: not in the Python API).
        Also the first update when its start window is already longer than the lag (`relinearise` False, nothing to
        relinearise yet; its new variables among the leavers)."""
        params = gtsam.ISAM2UpdateParams()
        params.force_relinearize = relinearise
        window = self._keys | set(values.keys())
        groups = gtsam.KeyGroupMap()
        top = 2 if leaving else 1
        for key in leaving:  # first: a leaver must be eliminated first, whatever else it is
            groups.insert2(key, 0)
        for key in [] if newest is None else newest.keys():
            groups.insert2(key, top)
        for key in window:
            groups.insert2(key, top - 1)  # insert2 keeps a key's first group
        params.constrainedKeys = groups
        if leaving:
            extra = gtsam.KeyList()
            for key in self._keys:  # those already in iSAM2
                extra.push_back(key)
            params.extraReelimKeys = extra
        self._result = self._isam.update(graph, values, params)
        if leaving:
            leaves = gtsam.KeyList()
            for key in leaving:
                if key in window:
                    leaves.push_back(key)
            self._isam.marginalizeLeaves(leaves)

    def _hold(self, timestamps: dict[int, float]) -> dict[int, float]:
        """The held start (`hold_start_s`): the timestamps that keep the start in the window. gtsam marginalises a
        variable whose timestamp is older than the newest one minus the lag, so a held variable is given that
        boundary as its timestamp (the rule is strict: it stays). Nothing leaves before `hold_start_s`; from then
        on the variables older than `release` leave, `release` moving from the first timestamp at
        `hold_release_rate` seconds a second until it passes the lag's boundary, where the hold ends and every
        later update is the plain fixed lag's. Every held variable is re-stamped in each update (a few thousand at
        most, at the hold's end)."""
        self._own.update(timestamps)
        if self._t0 is None:
            self._t0 = min(timestamps.values())
        newest = max(self._own.values())
        boundary = newest - self.cfg.lag_s
        release = self._t0 + self.cfg.hold_release_rate * max(0.0, newest - self._t0 - self.cfg.hold_start_s)
        out = dict(timestamps)
        if newest > self._t0 + self.cfg.hold_start_s and release >= boundary:  # caught up: the plain fixed lag
            self._holding = False  # from now on, every variable at its own time
            out.update({key: t for key, t in self._own.items() if key not in out})
            self._own = {}
            return out
        for key, t in self._own.items():
            out[key] = t if t < release else max(t, boundary)
        self._own = {key: t for key, t in self._own.items() if t >= release}
        return out

    def _block(self, t_s: float) -> float:
        """A timestamp rounded down to its block of `marginalise_every_s`: variables then leave the window in whole
        blocks, once per block, and the updates in between are plain iSAM2 updates (no ordering constraint)."""
        block = self.cfg.marginalise_every_s
        return math.floor(t_s / block) * block

    def _leaving(self, timestamps: dict[int, float]) -> list[int]:
        """Keys the fixed-lag smoother marginalises in an update with these new timestamps: the same rule as
        gtsam's IncrementalFixedLagSmoother (a timestamp older than the newest one minus the lag, strictly)."""
        if self.kind != "fixed_lag":
            return []
        self._stamps.update(timestamps)
        if not self._stamps:
            return []
        cutoff = max(self._stamps.values()) - self.cfg.lag_s
        return [key for key, t in self._stamps.items() if t < cutoff]

    def estimate_keys(self, keys: list[int]) -> gtsam.Values:
        """Current estimate of some pose/velocity/bias/point keys only (cheaper than `estimate()` on long runs).

        Poses and biases are inserted by argument name (`_INSERT_KEYWORDS`): a keyframe's 50-100 recent keys took
        5.96 ms with every value passed by position and 1.1-1.2 ms this way (60 s orbit 402; docs/BENCHMARKS.md)."""
        out = gtsam.Values()
        try:
            for key in keys:
                getter = self._getter_of.get(key)
                if getter is None:  # a gtsam.Symbol per key and keyframe cost more than the estimate itself
                    getter = _GETTERS.get(chr(gtsam.Symbol(key).chr()), "calculateEstimatePoint3")
                    self._getter_of[key] = getter
                keyword = _INSERT_KEYWORDS.get(getter)
                if keyword is None:
                    out.insert(key, getattr(self._isam, getter)(key))
                else:  # by name: pybind11 then skips the other overloads without trying to convert the value
                    out.insert(key, **{keyword: getattr(self._isam, getter)(key)})
        except (RuntimeError, IndexError) as exc:  # IndexError: a key the solver does not hold
            raise SolverFailure(first_line(exc)) from exc
        return out

    def estimate_points(self, keys: list[int]) -> np.ndarray:
        """(N, 3) current estimates of point keys (landmarks), m, world frame."""
        out = np.empty((len(keys), 3))
        try:
            get = self._isam.calculateEstimatePoint3
            for i, key in enumerate(keys):
                out[i] = get(key)
        except RuntimeError as exc:
            raise SolverFailure(first_line(exc)) from exc
        return out

    def estimate(self) -> gtsam.Values:
        """Current estimate of every variable still in the solver (raises SolverFailure like `update`)."""
        try:
            return self._isam.calculateEstimate()
        except RuntimeError as exc:
            raise SolverFailure(first_line(exc)) from exc


NO_WEIGHT = 1e6  # sigma of the background step's priors: 1e-12 of information against about 1e4-1e8 per variable


def _no_weight_prior(key: int, values: gtsam.Values) -> gtsam.NonlinearFactor:
    """A prior of no practical weight on a pose, velocity, bias or landmark (`Smoother.background`)."""
    kind = chr(gtsam.Symbol(key).chr())
    if kind == "x":
        return gtsam.PriorFactorPose3(key, values.atPose3(key), gtsam.noiseModel.Isotropic.Sigma(6, NO_WEIGHT))
    if kind == "b":
        noise = gtsam.noiseModel.Isotropic.Sigma(6, NO_WEIGHT)
        return gtsam.PriorFactorConstantBias(key, values.atConstantBias(key), noise)
    if kind == "l":
        return gtsam.PriorFactorPoint3(key, values.atPoint3(key), gtsam.noiseModel.Isotropic.Sigma(3, NO_WEIGHT))
    return gtsam.PriorFactorVector(key, values.atVector(key), gtsam.noiseModel.Isotropic.Sigma(3, NO_WEIGHT))


_GETTERS = {"x": "calculateEstimatePose3", "v": "calculateEstimateVector", "b": "calculateEstimateConstantBias"}
# `Values.insert`'s argument names for the kinds whose overload comes late (poses 10th, biases 44th of 46): by name
# a pose took 3 us instead of 20, a bias 10 instead of 48-187 (2,000 inserts). Vectors and points stay positional:
# their overload comes early, and a point by name would be stored as a fixed-size vector, not as the dynamic one
# every other place stores
_INSERT_KEYWORDS = {"calculateEstimatePose3": "pose3", "calculateEstimateConstantBias": "constant_bias"}


def batch_solve(graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values, max_iterations: int = 100) -> gtsam.Values:
    """Levenberg-Marquardt on the whole graph (the reference answer)."""
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(1e-6)
    params.setAbsoluteErrorTol(1e-6)
    return gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()
