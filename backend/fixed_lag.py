"""Bounded cost: the map of landmarks that left the fixed-lag window, and their way back in.

With `smoother.kind: fixed_lag` the smoother holds only the variables stamped within the last `lag_s` seconds
(gtsam's `IncrementalFixedLagSmoother`): an older keyframe's pose, velocity and bias, and every landmark last seen
before it, are marginalised into a linear prior on what remains, so the cost of a keyframe and the solver's
memory do not grow with the capture. A landmark's timestamp is that of its latest view, so it leaves together
with the last pose that saw it; it never stays behind without a measurement (the indeterminate system that a
landmark left alone would make).

A landmark that leaves is not forgotten: `OldLandmarks.keep` files it in `GraphState.retired` (its last estimate,
world, m, stays in `GraphState.values`), and the landmark stays a candidate for re-identification. When it is seen
again, by its own track or through re-identification, `revive` puts it back into the smoother as a new variable
with a prior at the kept position (`smoother.map_sigma_m`). The old map then anchors the window: a revisit corrects
the drift of the live estimate without re-eliminating the old part of the graph, the cost that makes full iSAM2's
loop closures slow. The prior counts again some of the information already marginalised into the window, so its
sigma is set wider than the landmark's own uncertainty; the batch refinement (`--refine`) does not use it and joins
the old and new views of the landmark as one variable (every factor stays in `GraphState.all_factors`).
"""

from __future__ import annotations

import gtsam
import numpy as np

from backend import factors as fb
from backend.graph_state import GraphState
from backend.keys import L


class OldLandmarks:
    """Files marginalised landmarks in `state.retired` and brings them back when they are seen again."""

    def __init__(self, state: GraphState, sigma_m: float) -> None:
        self.state, self.sigma_m = state, sigma_m
        self.num_revived = 0  # re-entries of old landmarks into the window

    def keep(self, marginalised: gtsam.Values) -> dict[int, np.ndarray]:
        """See `retire`."""
        return retire(self.state, marginalised)

    def position(self, j: int) -> np.ndarray | None:
        """The kept world position (3,) m of old landmark j, or None when j is not an old landmark."""
        return np.asarray(self.state.values.atPoint3(L(j)), float) if j in self.state.retired else None

    def revive(self, j: int, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> np.ndarray:
        """Old landmark j enters the smoother again at its kept position, with the map prior; returns the position."""
        self.state.retired.remove(j)
        p = np.asarray(self.state.values.atPoint3(L(j)), float)
        values.insert(L(j), p)
        graph.add(fb.landmark_prior(j, p, self.sigma_m))
        self.num_revived += 1
        return p


def retire(state: GraphState, marginalised: gtsam.Values) -> dict[int, np.ndarray]:
    """Keep the last estimates of the variables an update marginalised (`Smoother.update` returns them) and file
    the landmarks among them as old landmarks; returns those landmarks' positions by id. `state.retired` holds their
    ids only: the positions are in `state.values` already, and a (3,) array per landmark came to 4.0 MiB in seven
    minutes of the 10-minute orbit (tracemalloc; docs/BENCHMARKS.md, "The fixed lag's factor slots")."""
    state.absorb(marginalised)
    kept = {}
    for key in marginalised.keys():
        sym = gtsam.Symbol(key)
        if chr(sym.chr()) == "l":
            kept[int(sym.index())] = np.asarray(marginalised.atPoint3(key), float)
    state.retired.update(kept.keys())
    state.unlist_retired(kept.keys())
    return kept


def window_stamps(state: GraphState, values: gtsam.Values, last_k: int) -> dict[int, float]:
    """Timestamps (s) of the start window's variables for the fixed lag: a keyframe's pose, velocity and bias at
    its time, a landmark at the time of its latest view (of keyframe `last_k` when it has none yet)."""
    stamps = {}
    for key in values.keys():
        sym = gtsam.Symbol(key)
        if chr(sym.chr()) == "l":
            k = state.last_obs.get(int(sym.index()), last_k)
        else:
            k = int(sym.index())
        stamps[key] = state.t_ns[k] * 1e-9
    return stamps
