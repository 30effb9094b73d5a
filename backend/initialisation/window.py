"""The first window's hand-over: a batch solve of the window graph, then the smoother takes it."""

from __future__ import annotations

import time
from dataclasses import dataclass

import gtsam

from backend.admission import LandmarkAdmission
from backend.fixed_lag import retire, window_stamps
from backend.graph_state import GraphState
from backend.smoother import SolverFailure, batch_solve, first_line


@dataclass(frozen=True)
class Start:
    """A successful start: its kind, the keyframes it estimated, and its solve time."""

    kind: str  # "static" | "moving" | "visual"
    keyframes: list[int]
    solve_ms: float


def start_window(
    state: GraphState,
    admission: LandmarkAdmission,
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    last_k: int,
    what: str,
) -> bool:
    """Solve the first window in batch and hand it to the smoother; on failure undo the admissions and warn (the
    caller slides its window and retries with more keyframes)."""
    try:
        values = batch_solve(graph, values)
        marginalised = state.smoother.update(graph, values, window_stamps(state, values, last_k))
    except (RuntimeError, SolverFailure) as exc:
        state.warn(f"{what} at keyframe {last_k} failed ({first_line(exc)}); retrying later")
        state.smoother.reset()
        admission.undo()
        return False
    retire(state, marginalised)  # a lag shorter than the window: its first keyframes leave at once
    state.absorb(state.smoother.estimate())
    return True


def elapsed_ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1e3
