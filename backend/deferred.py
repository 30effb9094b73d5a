"""The estimator's work after a keyframe's estimate is out (`smoother.background`, issue 18).

`chores`: housekeeping that leaves the estimate as it is (the pruning of old track views, the scale's chunks).
`background`: those, then the smoother's deferred relinearisation and marginalisation when due. The pipeline calls
`VioEstimator.background` once a keyframe's estimate has gone to the sinks; a caller that does not gets it at the
start of the next keyframe, with the same answer (tests/backend/test_fixed_lag.py).
"""

from __future__ import annotations

import time
from typing import Any

from backend.keys import B, L, V, X
from backend.smoother import SolverFailure

PRUNE_EVERY_KEYFRAMES = 50  # old track views and lost tracks' segments are forgotten this often (bounded memory)


def chores(est: Any) -> bool:  # est: backend.estimator.VioEstimator (not imported: no cycle)
    """Housekeeping after keyframe `est._chores_k` (in the background step, else at the end of the keyframe);
    True when there was some."""
    k, est._chores_k = est._chores_k, None
    if k is None:
        return False
    st = est.state
    worked = k % PRUNE_EVERY_KEYFRAMES == 0
    if worked:
        est._prune(k)
    if est._chunks is not None and est._chunks.due(len(st.t_ns)):
        worked |= est._chunks.maybe_close(st.all_factors, st.values, sorted(st.t_ns), st.smoother, st.pims)
    return worked


def background(est: Any) -> None:
    """The last keyframe's chores, then the smoother's background step when due; each call that did something is
    timed in `EstimatorStats.background_ms`."""
    st = est.state
    if not est.initialised:
        return
    t0, c0 = time.perf_counter(), time.process_time()
    worked = chores(est)  # first: on the state the keyframe left, as when they end the keyframe
    if st.smoother.background_due():
        worked = True
        k = st.last_k
        try:
            keys = [X(k), V(k), B(k), *(L(j) for j in st.landmarks_last_seen_at(k))]
            newest = st.smoother.estimate_keys([key for key in keys if st.smoother.has(key)])
            marginalised = st.smoother.background(newest)
            values = st.smoother.estimate_keys(st.recent_keys(k))
            st.dirty = True
            for j, p in est.old.keep(marginalised).items():
                est.reidentification.on_retired(j, p)
        except SolverFailure as exc:
            values = est._recover(k - 1, k, str(exc))
        st.absorb(values)
        if est.use_imu:
            st.bias = st.values.atConstantBias(B(k))
    if worked:
        est._background_ms.append(((time.perf_counter() - t0) * 1e3, (time.process_time() - c0) * 1e3))
