"""Recovery from a solver failure: a failed iSAM2 update leaves the solver half-updated, so the smoother is rebuilt
from the last good keyframe (priors on its pose, velocity and bias, sigmas from the `recovery` section) plus the
factor that bridges to the failed keyframe; landmarks re-enter through admission."""

from __future__ import annotations

import gtsam

from backend import factors as fb
from backend.graph_state import GraphState, value_of
from backend.keys import B, V, X
from backend.smoother import SolverFailure
from vio.config import RecoveryConfig
from vio.records import RecoveryEvent


class Recovery:
    """Rebuilds the smoother and keeps the record of every recovery."""

    def __init__(self, cfg: RecoveryConfig, state: GraphState) -> None:
        self.cfg, self.state = cfg, state
        self.events: list[RecoveryEvent] = []

    def record(self, prev: int, k: int, reason: str) -> None:
        self.state.warn(f"solver failed at keyframe {k} ({reason}); rebuilding from keyframe {prev}")
        self.events.append(RecoveryEvent(k, self.state.t_ns[k], reason, prev))

    def rebuild(self, prev: int, k: int, bridge: gtsam.NonlinearFactor, use_imu: bool) -> gtsam.Values:
        """A new smoother holding keyframes prev (from its last estimate) and k (tied by `bridge`, the inertial
        factor or the vision-only motion prior); returns its estimate, or the prediction when that fails too."""
        st, cfg = self.state, self.cfg
        st.smoother.reset()
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        graph.add(
            gtsam.PriorFactorPose3(
                X(prev), st.values.atPose3(X(prev)), gtsam.noiseModel.Isotropic.Sigma(6, cfg.pose_sigma)
            )
        )
        if use_imu:
            graph.add(fb.velocity_prior(prev, st.values.atVector(V(prev)), cfg.velocity_sigma))
            graph.add(fb.bias_prior(prev, st.values.atConstantBias(B(prev)), cfg.bias_sigma_acc, cfg.bias_sigma_gyro))
            keys = (X(prev), V(prev), B(prev), X(k), V(k), B(k))
        else:
            keys = (X(prev), X(k))
        graph.add(bridge)
        for key in keys:
            values.insert(key, value_of(st.values, key))
        t_s = st.t_ns[k] * 1e-9
        try:
            st.smoother.update(graph, values, {key: t_s for key in values.keys()})
            return st.smoother.estimate()
        except SolverFailure as exc:  # keep the prediction; the next keyframe rebuilds again from here
            st.warn(f"rebuild at keyframe {k} failed too ({exc}); keeping the inertial prediction")
            st.smoother.reset()
            return values
