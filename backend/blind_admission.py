"""Admission while the graph has no visual constraint: the recent keyframes' poses are first adjusted against the
candidate tracks with their own inertial factors, and the usual admission test then runs over the adjusted poses.

Why: a landmark is admitted only when it triangulates within `max_reprojection_px` over the keyframes' current
poses (backend/landmarks.py). While no landmark constrains the keyframes (after a static start, through a
tracking loss) those poses come from the phone IMU alone, which drifts by centimetres a second: integrating a
simulated phone IMU (0.015 m/s^2/sqrt(Hz), 0.002 rad/s/sqrt(Hz)) from the true state with its true biases, the
velocity is 20-85 mm/s off after 1.2 s. A track seen from the still start and through the shaking that the capture
advice asks for then reprojects 5-100 px off its views, so no track is admitted, the drift grows, and the run never
gets its visual constraints back (scale60 suite, seed 318 with a 3 s still start and 5 s of shaking: IMU alone from
3.0 to 7.6 s, 8 % scale error; seed 319: 0.9 m ATE). The images themselves are consistent; only the poses are off.

So, at a keyframe left without a projection factor, the keyframes of the blind stretch (and a few before it) get a
small visual-inertial bundle adjustment: their poses, velocities and biases, the estimator's own `CombinedImuFactor`s
between them, a prior at the current estimate on the window's first keyframe (the gauge: the adjusted poses stay in
the graph's frame), and the candidate tracks (seen now, `min_views` views in the window, in front of every camera,
at least `blind_admission.min_parallax_deg` of parallax: 1 deg, since the shaking's 3-4 cm give some tracks only
1.3-2 deg) as points with Huber-robust projection factors. The tracks that then pass the admission test (the same
reprojection gate, that parallax) over the adjusted poses are admitted into the graph with their views, as any
other landmark; the graph's own poses move to them through the new projection factors. The current keyframe's
initial values (it enters the smoother in this update) are the adjusted ones.
"""

from __future__ import annotations

import logging

import gtsam
import numpy as np

from backend import factors as fb
from backend.admission import LandmarkAdmission
from backend.graph_state import GraphState
from backend.keys import B, L, V, X
from backend.landmarks import LandmarkBook, camera_poses, parallax_deg, project, triangulate
from vio.config import BlindAdmissionConfig

log = logging.getLogger(__name__)

_MIN_DEPTH_M = 0.05  # a candidate must be this far in front of every camera of the window, m


class BlindAdmission:
    """Admits landmarks over bundle-adjusted poses when the latest keyframes have no visual constraint."""

    def __init__(
        self, cfg: BlindAdmissionConfig, state: GraphState, book: LandmarkBook, admission: LandmarkAdmission
    ) -> None:
        self.cfg, self.state, self.book, self.admission = cfg, state, book, admission
        self.num_runs = 0  # adjustments solved
        self.num_admitted = 0  # landmarks admitted over adjusted poses

    def blind(self, k: int, rest: set[int]) -> int | None:
        """The first keyframe of the stretch ending at k without projection factors (keyframes at rest count as
        constrained), or None when k has a projection factor."""
        st = self.state
        if st.projections.get(k, 0) > 0 or k in rest:
            return None
        first = k
        while first - 1 in st.t_ns and st.projections.get(first - 1, 0) == 0 and first - 1 not in rest:
            first -= 1
        return first

    def admit(
        self,
        k: int,
        ids: np.ndarray,
        rest: set[int],
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
    ) -> list[tuple[int, np.ndarray]]:
        """At keyframe k (its values in `values`, not yet in the smoother): when k and the keyframes before it have
        no visual constraint, adjust the window and admit what then triangulates; returns (id, point) of the
        admitted landmarks."""
        cfg, st = self.cfg, self.state
        if cfg.window_keyframes <= 0:
            return []
        first = self.blind(k, rest)
        if first is None or k - first + 1 < cfg.after_keyframes:
            return []
        lo = max(first - cfg.before_keyframes, k - cfg.window_keyframes + 1, 0)
        window = [k]  # the consecutive keyframes before k that the smoother still holds
        while window[0] - 1 >= lo and st.smoother.has(X(window[0] - 1)) and window[0] in st.pims:
            window.insert(0, window[0] - 1)
        if len(window) < self.book.cfg.min_views:
            return []
        poses = {kk: (values.atPose3(X(kk)) if kk == k else st.values.atPose3(X(kk))).matrix() for kk in window}
        candidates = self._candidates(ids, poses)
        if len(candidates) < cfg.min_tracks:
            return []
        adjusted = self._adjust(window, candidates, values)
        if adjusted is None:
            return []
        self.num_runs += 1
        refined = {kk: adjusted.atPose3(X(kk)).matrix() for kk in window}
        values.update(X(k), adjusted.atPose3(X(k)))
        values.update(V(k), adjusted.atVector(V(k)))
        st.set(X(k), adjusted.atPose3(X(k)))
        st.set(V(k), adjusted.atVector(V(k)))
        out = []
        for j in candidates:
            self.book.tracks[j].rejected_until = -1  # its earlier failures were over the unadjusted poses
            p = self.admission.admit(j, refined, graph, values, k_now=k, min_parallax_deg=cfg.min_parallax_deg)
            if p is not None:
                out.append((j, p))
        self.num_admitted += len(out)
        log.debug(
            "keyframe %d: blind since %d, window %d, %d candidates, %d admitted",
            k,
            first,
            len(window),
            len(candidates),
            len(out),
        )
        return out

    def _candidates(self, ids: np.ndarray, poses: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
        """Tracks seen at the latest keyframe, not admitted, with `min_views` views in the window, at least
        `min_parallax_deg` of parallax and in front of every camera: id -> triangulated point (3,)."""
        book, body_T_cam = self.book, self.book.body_T_cam
        out: dict[int, np.ndarray] = {}
        for j in ids.tolist():
            tr = book.tracks.get(j)
            if tr is None or tr.admitted:
                continue
            ks = [kk for kk in tr.views if kk in poses]
            if len(ks) < book.cfg.min_views:
                continue
            Twc = camera_poses(poses, body_T_cam, ks)
            xn = book.normalized(np.stack([tr.views[kk] for kk in ks]))
            if parallax_deg(Twc, xn) < self.cfg.min_parallax_deg:
                continue
            p = triangulate(Twc, xn)
            _, z = project(Twc, p, book.K)
            if np.all(np.isfinite(p)) and np.all(z > _MIN_DEPTH_M):
                out[int(j)] = p
            if len(out) >= self.cfg.max_tracks:
                break
        return out

    def _adjust(
        self, window: list[int], candidates: dict[int, np.ndarray], values: gtsam.Values
    ) -> gtsam.Values | None:
        """Levenberg-Marquardt over the window's X, V, B and the candidates' points; None when it fails."""
        st, cfg = self.state, self.cfg
        g, init = gtsam.NonlinearFactorGraph(), gtsam.Values()
        k = window[-1]
        for kk in window:
            src = values if kk == k else st.values
            init.insert(X(kk), src.atPose3(X(kk)))
            init.insert(V(kk), src.atVector(V(kk)))
            init.insert(B(kk), src.atConstantBias(B(kk)))
        k0 = window[0]
        pose_sigmas = np.array([cfg.prior_sigma_rad] * 3 + [cfg.prior_sigma_m] * 3)
        g.add(gtsam.PriorFactorPose3(X(k0), init.atPose3(X(k0)), gtsam.noiseModel.Diagonal.Sigmas(pose_sigmas)))
        g.add(fb.velocity_prior(k0, init.atVector(V(k0)), cfg.prior_velocity_sigma))
        g.add(fb.bias_prior(k0, init.atConstantBias(B(k0)), cfg.prior_bias_sigma_acc, cfg.prior_bias_sigma_gyro))
        for a, b in zip(window[:-1], window[1:], strict=True):
            g.add(fb.imu_factor(a, b, st.pims[b]))
        noise = st.pixel_noise.at(0.0)
        for j, p in candidates.items():
            init.insert(L(j), p)
            g.add(fb.landmark_prior(j, p, self.book.cfg.prior_sigma_m))
            for kk, uv in self.book.tracks[j].views.items():
                if init.exists(X(kk)):
                    g.add(fb.projection_factor(uv, kk, j, st.K, st.body_P_cam, noise))
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(cfg.max_iterations)
        try:
            return gtsam.LevenbergMarquardtOptimizer(g, init, params).optimize()
        except RuntimeError as exc:
            log.debug("blind admission at keyframe %d: adjustment failed (%s)", k, exc)
            return None
