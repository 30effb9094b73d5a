"""Landmark admission into the graph, the one place where a track becomes a landmark (at the start window and at
every later keyframe): triangulated by the landmark book (backend/landmarks.py), given a weak prior, and
connected to the graph by the projection factors of its views."""

from __future__ import annotations

import gtsam
import numpy as np

from backend import factors as fb
from backend.graph_state import GraphState
from backend.keys import L, X
from backend.landmarks import LandmarkBook


class LandmarkAdmission:
    """Admits book tracks into the graph held by `state`."""

    def __init__(self, book: LandmarkBook, state: GraphState, prior_sigma_m: float) -> None:
        self.book, self.state, self.prior_sigma_m = book, state, prior_sigma_m

    def ready(self, j: int) -> bool:
        """Track j is not yet admitted and has enough views to try."""
        tr = self.book.tracks[j]
        return not tr.admitted and len(tr.views) >= self.book.cfg.min_views

    def admit(
        self,
        j: int,
        world_T_body: dict[int, np.ndarray],
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        k_now: int | None = None,
        min_parallax_deg: float | None = None,
    ) -> np.ndarray | None:
        """Admit track j if it triangulates over the poses `world_T_body` (keyframe -> (4, 4)); returns its world
        point (3,) m, or None. Its views at those keyframes become projection factors: at a steady-state keyframe
        `k_now`, only views of keyframes still in the smoother, plus k_now's own. `min_parallax_deg` replaces the
        config's."""
        p = self.book.try_admit(j, world_T_body, min_parallax_deg)
        if p is None:
            return None
        values.insert(L(j), p)
        graph.add(fb.landmark_prior(j, p, self.prior_sigma_m))
        tr = self.book.tracks[j]
        for kk, uv in tr.views.items():
            if kk in world_T_body and (k_now is None or self.state.smoother.has(X(kk))) or kk == k_now:
                self.state.add_projection(graph, kk, j, uv, tr.run_start(kk))
        tr.admitted = True
        return p

    def admit_window(
        self, world_T_body: dict[int, np.ndarray], graph: gtsam.NonlinearFactorGraph, values: gtsam.Values
    ) -> None:
        """Admit every track that triangulates over the start window's poses."""
        for j in self.book.tracks:
            self.admit(j, world_T_body, graph, values)

    def undo(self) -> None:
        """Forget every admission (the start window failed and will be retried)."""
        for j in self.state.num_obs:
            self.book.tracks[j].admitted = False
        self.state.num_obs.clear()
