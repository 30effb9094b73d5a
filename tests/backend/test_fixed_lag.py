"""The bounded-cost estimator (`smoother.kind: fixed_lag`, backend/fixed_lag.py) on ideal synthetic tracks.

What it relies on from gtsam's IncrementalFixedLagSmoother is tested here too: which variables an update
marginalises (the smoother predicts them to return their last estimates), and that a landmark leaving with the last
pose that saw it, then coming back as a new variable with a prior, never makes the system indeterminate.
"""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from backend.estimator import VioEstimator
from backend.smoother import Smoother
from frontend.preintegration import ImuPreintegrator
from tests.backend.test_estimator import ate_se3, run_estimator, synthetic_run
from vio.config import ImuConfig, SmootherConfig, load_config
from vio.records import FeatureTracks


def _fixed_lag(*overrides: str):
    """The preset without its held start (these captures are shorter than the hold), unless an override sets it."""
    return load_config(None, ["smoother.hold_start_s=0", *overrides], presets=["fixed_lag"])


@pytest.fixture(scope="module")
def data():
    return synthetic_run(duration_s=6.0, seed=0)


def test_smoother_predicts_the_variables_it_marginalises():
    """A chain of poses one second apart in a 2.5 s lag: `has` and the returned last estimates match what gtsam's
    fixed-lag smoother actually keeps."""
    sm = Smoother(SmootherConfig(kind="fixed_lag", lag_s=2.5))
    noise = gtsam.noiseModel.Isotropic.Sigma(6, 0.1)
    step = gtsam.Pose3(gtsam.Rot3(), np.array([1.0, 0.0, 0.0]))
    X = gtsam.symbol_shorthand.X
    left: list[int] = []
    for k in range(8):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if k == 0:
            graph.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(), noise))
        else:
            graph.add(gtsam.BetweenFactorPose3(X(k - 1), X(k), step, noise))
        values.insert(X(k), gtsam.Pose3(gtsam.Rot3(), np.array([float(k), 0.0, 0.0])))
        marginalised = sm.update(graph, values, {X(k): float(k)})
        left += list(marginalised.keys())
        kept = set(sm.estimate().keys())
        assert {key for key in (X(i) for i in range(k + 1)) if sm.has(key)} == kept
        assert kept == {X(i) for i in range(k + 1) if i >= k - 2.5}
        for key in marginalised.keys():
            assert np.allclose(marginalised.atPose3(key).translation(), [gtsam.Symbol(key).index(), 0, 0], atol=1e-6)
    assert left == [X(i) for i in range(5)]
    assert sm.num_variables() == 3


def test_marginalise_in_blocks():
    """With `marginalise_every_s` the variables leave in whole blocks, not at every update."""
    sm = Smoother(SmootherConfig(kind="fixed_lag", lag_s=1.0, marginalise_every_s=1.0))
    noise = gtsam.noiseModel.Isotropic.Sigma(6, 0.1)
    X = gtsam.symbol_shorthand.X
    sizes = []
    for k in range(40):  # keyframes 0.1 s apart
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        prev = gtsam.PriorFactorPose3(X(0), gtsam.Pose3(), noise) if k == 0 else None
        graph.add(prev or gtsam.BetweenFactorPose3(X(k - 1), X(k), gtsam.Pose3(), noise))
        values.insert(X(k), gtsam.Pose3())
        left = sm.update(graph, values, {X(k): 100.0 + 0.1 * k + 1e-6})
        assert left.size() in (0, 10)  # nothing, or one whole second of keyframes
        sizes.append(sm.num_variables())
    assert set(sm.estimate().keys()) == {X(k) for k in range(20, 40)}  # between one lag and one lag + a block
    assert max(sizes) == 20


def test_a_held_start_stays_in_the_window_then_leaves_at_the_release_rate():
    """`hold_start_s`: poses 0.1 s apart in a 1 s lag, held 3 s, released at 2 s a second. Nothing leaves before
    3 s; then the oldest leave first, two seconds of capture a second, until the release passes the lag's boundary
    (at 5 s); from there the window is the plain lag's. What the smoother says it holds is what gtsam holds."""
    cfg = SmootherConfig(kind="fixed_lag", lag_s=1.0, hold_start_s=3.0, hold_release_rate=2.0)
    sm = Smoother(cfg)
    noise = gtsam.noiseModel.Isotropic.Sigma(6, 0.1)
    X = gtsam.symbol_shorthand.X
    left_at: dict[int, float] = {}
    for k in range(80):
        t = 0.1 * k + 1e-6
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        graph.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(), noise) if k == 0 else
                  gtsam.BetweenFactorPose3(X(k - 1), X(k), gtsam.Pose3(), noise))  # fmt: skip
        values.insert(X(k), gtsam.Pose3())
        for key in sm.update(graph, values, {X(k): t}).keys():
            left_at[gtsam.Symbol(key).index()] = t
        kept = set(sm.estimate().keys())
        assert kept == {X(i) for i in range(k + 1) if sm.has(X(i))}
        if t < 3.0:
            assert len(kept) == k + 1  # held: nothing has left
    order = sorted(left_at)
    assert order == list(range(len(order))) and [left_at[i] for i in order] == sorted(left_at.values())
    assert min(left_at.values()) >= 3.0
    assert left_at[20] == pytest.approx(4.1, abs=0.051)  # t = 2.0 s leaves once the release, 2 (t - 3), passes it
    assert max(i for i in left_at if left_at[i] < 5.0) < 40  # at 5 s the release meets the lag's boundary
    assert set(sm.estimate().keys()) == {X(k) for k in range(69, 80)}  # then the plain 1 s lag


def test_a_held_start_with_the_background_step_leaves_as_without():
    """The held start with `background`: deferring only the relinearisation, the same variables leave at the same
    updates as without the background step; deferring the marginalisation too, they leave in the same order, all of
    them in background steps (none in a keyframe's update), each one update later at most; and so on plain iSAM2
    with the step's own marginalisation (`own_marginalisation`)."""
    left, where = {}, {}
    for mode in ("plain", "relinearisation", "marginalisation", "own"):
        cfg = SmootherConfig(
            kind="fixed_lag", lag_s=1.0, hold_start_s=3.0, relinearize_skip=2, relinearize_threshold=1e-9,
            background=mode != "plain", background_marginalises=mode in ("marginalisation", "own"),
            own_marginalisation=mode == "own",
        )  # fmt: skip
        sm = Smoother(cfg)
        assert sm._holding
        in_steps: list[int] = []

        def step(k, sm=sm, in_steps=in_steps):
            if sm.background_due():
                in_steps.extend(sm.background().keys())

        left[mode] = _chain(sm, 80, step)
        where[mode] = in_steps
    assert len(left["plain"]) > 50 and left["relinearisation"] == left["plain"] and not where["relinearisation"]
    assert not left["marginalisation"] and where["marginalisation"] == left["plain"][: len(where["marginalisation"])]
    assert len(where["marginalisation"]) >= len(left["plain"]) - 10  # the last step's leavers may still be due
    assert not left["own"] and where["own"] == where["marginalisation"]


def _chain(sm: Smoother, n: int, between_calls=None) -> list[int]:
    """Poses 0.1 s apart in a chain with a prior on the first; `between_calls(k)` after each update. Returns the
    keys each update marginalised, in order."""
    noise = gtsam.noiseModel.Isotropic.Sigma(6, 0.1)
    X = gtsam.symbol_shorthand.X
    step = gtsam.Pose3(gtsam.Rot3.Yaw(0.05), np.array([0.1, 0.0, 0.0]))
    left: list[int] = []
    for k in range(n):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if k == 0:
            graph.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(), noise))
        else:
            graph.add(gtsam.BetweenFactorPose3(X(k - 1), X(k), step, noise))
        values.insert(X(k), gtsam.Pose3(gtsam.Rot3(), np.array([0.1 * k + 0.01 * (k % 3), 0.02, 0.0])))
        left += list(sm.update(graph, values, {X(k): 0.1 * k + 1e-6}).keys())
        if between_calls is not None:
            between_calls(k)
    return left


@pytest.mark.parametrize("own", [False, True], ids=["gtsam_fixed_lag", "own_marginalisation"])
def test_background_step_takes_the_relinearisation_and_the_marginalisation_out_of_the_updates(own):
    """`smoother.background`: no keyframe update relinearises or marginalises; the background step, due after every
    `relinearize_skip` updates, does both; and skipping the calls gives the same answer to the bit (the next update
    runs a step that is due first). On gtsam's fixed lag and on plain iSAM2 (`own_marginalisation`)."""
    cfg = SmootherConfig(
        kind="fixed_lag", lag_s=0.5, marginalise_every_s=0.2, relinearize_skip=2, relinearize_threshold=1e-9,
        background=True, own_marginalisation=own,
    )  # fmt: skip
    sm = Smoother(cfg)
    relinearised, steps, left_in_steps = [], [], []

    def after(k: int) -> None:
        relinearised.append(sm.last_result().getVariablesRelinearized())
        if sm.background_due():
            left_in_steps.extend(sm.background().keys())
            steps.append(sm.last_result().getVariablesRelinearized())

    left_in_updates = _chain(sm, 30, after)
    assert not left_in_updates and not any(relinearised)  # the updates did neither
    assert len(steps) == 15 and all(n > 0 for n in steps)  # after updates 1, 3, ..., 29; each relinearises
    X = gtsam.symbol_shorthand.X
    assert left_in_steps == [X(k) for k in range(len(left_in_steps))] and len(left_in_steps) >= 20
    kept = set(sm.estimate().keys())
    assert kept == {X(k) for k in range(len(left_in_steps), 30)} and len(kept) <= 10  # lag + a block + 2 updates
    late = Smoother(cfg)
    with pytest.raises(RuntimeError, match="background step is due"):
        _chain(late, 3)  # an update built while a step is due (it could use a variable the step marginalises)


@pytest.mark.parametrize("own", ["false", "true"], ids=["gtsam_fixed_lag", "own_marginalisation"])
def test_background_steps_left_to_the_estimator_give_the_same_answer(data, own):
    """The pipeline runs the background step after each keyframe; a caller that does not gets it at the start of
    the next keyframe instead, with the same estimate to the bit."""
    cfg = _fixed_lag(
        "smoother.lag_s=1.0", "smoother.background=true", "smoother.relinearize_skip=2",  # as measured
        f"smoother.own_marginalisation={own}",
    )  # fmt: skip
    cam, imu, cal, t_kf, tracks, gt = data
    ests = []
    for call in (True, False):
        est = VioEstimator(cam, imu, ImuPreintegrator(imu, cal, ImuConfig()).between, cfg)
        for t, tr in zip(t_kf, tracks, strict=True):
            est.add_keyframe(int(t), tr)
            if call:
                est.background()
        est.finish()  # runs one that is due after the last keyframe
        ests.append(est)
    steps = [len(est.stats().background_ms) for est in ests]
    assert steps[0] > 20 and steps[1] == steps[0]  # the same steps, run at either place
    a, b = (np.array([s.world_T_body for s in est.states()]) for est in ests)
    assert a.shape == b.shape and np.array_equal(a, b)
    assert not ests[0].stats().recoveries


def test_fixed_lag_is_accurate_on_a_short_capture(data):
    """The preset's online estimate within 20 % of its whole graph's batch solution (`--refine`), which is within
    a centimetre of the truth (measured: 10.0 and 9.5 mm; 6.8 mm online when relinearised every 4th keyframe)."""
    est = run_estimator(data, _fixed_lag())
    stats = est.stats()
    assert stats.initialisation == "moving" and not stats.recoveries
    states = est.states()
    idx = [int(np.searchsorted(data[3], s.t_ns)) for s in states]
    assert len(states) >= len(data[5]) - 12
    p = np.array([s.world_T_body[:3, 3] for s in states])
    online = ate_se3(data[5][idx, :3, 3], p)
    assert est.finish(refine=True)["refined"]  # the batch refinement sees every factor, old and new
    p = np.array([s.world_T_body[:3, 3] for s in est.states()])
    refined = ate_se3(data[5][idx, :3, 3], p)
    assert refined < 0.01 and online < 1.2 * refined


def _occluded(data, first: int, last: int):
    """The same run with a third of the points hidden from keyframe `first` to `last` (they come back after)."""
    cam, imu, cal, t_kf, tracks, gt = data
    out = []
    for i, tr in enumerate(tracks):
        keep = np.ones(len(tr.ids), bool) if not first <= i <= last else tr.ids % 3 != 0
        out.append(FeatureTracks(tr.t_ns, tr.ids[keep], tr.uv[keep]))
    return cam, imu, cal, t_kf, out, gt


def test_fixed_lag_bounds_the_variables_and_brings_old_landmarks_back(data):
    """With a 0.5 s lag (shorter than the start window, whose first keyframes leave at once) the smoother holds
    half a second of keyframes and the landmarks they see, however long the run; landmarks hidden for 1.2 s leave
    the window and come back with a prior, without a solver failure. (The preset's background step marginalises up
    to `relinearize_skip` keyframes late: hidden for 0.8 s, one landmark came back instead of nine.)"""
    hidden = _occluded(data, 25, 36)
    full = run_estimator(hidden).stats().smoother_variables
    est = run_estimator(hidden, _fixed_lag("smoother.lag_s=0.5"))
    stats = est.stats()
    counts = np.asarray(stats.smoother_variables)
    assert not stats.recoveries and len(counts) == len(full)
    half = len(counts) // 2
    assert counts[half:].max() <= 1.2 * counts[:half].max()  # flat, not growing
    assert counts.max() < 0.5 * full[-1]  # full iSAM2 keeps every variable
    assert stats.num_landmarks_revived >= 5
    states = est.states()
    idx = [int(np.searchsorted(data[3], s.t_ns)) for s in states]
    assert ate_se3(data[5][idx, :3, 3], np.array([s.world_T_body[:3, 3] for s in states])) < 0.05  # no divergence


def _landmark_chain(cfg: SmootherConfig, give_newest: bool):
    """60 poses 0.1 m (0.1 s) apart along x, each seeing the landmarks within 25 poses of it; the background step
    run when due, given the newest keyframe's variables or not. Returns (variables re-eliminated by each update after
    a step, the smoother)."""
    X, L = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.L
    K = gtsam.Cal3_S2(500, 500, 0, 320, 240)
    step_noise, pixel = gtsam.noiseModel.Isotropic.Sigma(6, 0.1), gtsam.noiseModel.Isotropic.Sigma(2, 0.5)
    rng = np.random.default_rng(0)
    sm, after_steps, step_done = Smoother(cfg), [], False
    for k in range(60):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if k == 0:
            graph.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(), step_noise))
        else:
            graph.add(gtsam.BetweenFactorPose3(X(k - 1), X(k), gtsam.Pose3(gtsam.Rot3(), [0.1, 0, 0]), step_noise))
        values.insert(X(k), gtsam.Pose3(gtsam.Rot3(), np.array([0.1 * k, 0.01 * (k % 3), 0.0])))
        seen = [j for j in range(40) if abs(2 * j - k) < 25]
        for j in seen:
            p = np.array([0.3 * j, 0.2 * (j % 3), 2.0])
            if not sm.has(L(j)) and not values.exists(L(j)):
                values.insert(L(j), p + 0.05)
                graph.add(gtsam.PriorFactorPoint3(L(j), p + 0.05, gtsam.noiseModel.Isotropic.Sigma(3, 5.0)))
            cam = gtsam.PinholeCameraCal3_S2(gtsam.Pose3(gtsam.Rot3(), np.array([0.1 * k, 0, 0])), K)
            uv = cam.project(p) + rng.normal(0, 0.5, 2)
            graph.add(gtsam.GenericProjectionFactorCal3_S2(uv, pixel, X(k), L(j), K))
        sm.update(graph, values, {X(k): 0.1 * k, **{L(j): 0.1 * k for j in seen}})
        if step_done:
            after_steps.append(sm.last_result().getVariablesReeliminated())
        step_done = sm.background_due()
        if step_done:
            sm.background(sm.estimate_keys([X(k), *(L(j) for j in seen)]) if give_newest else None)
    return after_steps, sm


def _same_estimate(a: gtsam.Values, b: gtsam.Values, tol: float) -> None:
    assert set(a.keys()) == set(b.keys())
    for key in a.keys():
        diff = (a.atPose3(key).translation() - b.atPose3(key).translation()) if gtsam.Symbol(key).chr() == ord("x") \
            else (a.atPoint3(key) - b.atPoint3(key))  # fmt: skip
        assert np.abs(diff).max() < tol


def test_the_background_step_keeps_the_newest_keyframe_at_the_top_of_the_tree():
    """A background step that relinearises everything re-orders the whole tree; given the newest keyframe's
    variables (priors of no weight), it keeps them last, so the next update re-eliminates less of the window. The
    estimate is the same to 1e-9 m."""
    cfg = SmootherConfig(kind="fixed_lag", lag_s=100.0, relinearize_skip=4, relinearize_threshold=0.0, background=True)
    plain, sm_plain = _landmark_chain(cfg, give_newest=False)
    kept, sm_kept = _landmark_chain(cfg, give_newest=True)
    assert len(plain) == len(kept) == 14
    assert sum(kept[-8:]) < 0.8 * sum(plain[-8:])  # measured: 53 against 68-80 variables a time
    _same_estimate(sm_plain.estimate(), sm_kept.estimate(), 1e-9)


def test_own_marginalisation_keeps_the_newest_keyframe_on_top_after_a_marginalising_step(data):
    """gtsam's fixed lag orders a marginalising update itself (what leaves first, everything else in one group), and
    the newest keyframe's variables sink into the tree: the next keyframe's update re-eliminates much of the window
    again. `own_marginalisation` runs the step on plain iSAM2 with the newest keyframe's variables ordered last.
    The steps come after the same keyframes, the same variables leave in the same order, and the estimate is the
    same to a micrometre. A 2 s lag in 0.5 s blocks on the 6 s capture (60 keyframes)."""
    cam, imu, cal, t_kf, tracks, gt = data
    runs = {}
    for own in (False, True):
        cfg = _fixed_lag(
            "smoother.lag_s=2.0", "smoother.marginalise_every_s=0.5", "smoother.background=true",
            "smoother.relinearize_skip=4", f"smoother.own_marginalisation={str(own).lower()}",
        )  # fmt: skip
        est = VioEstimator(cam, imu, ImuPreintegrator(imu, cal, ImuConfig()).between, cfg)
        sm = est.state.smoother
        reeliminated, relinearised, left = [], [], []
        marginalise = sm._update

        def recording(*args, marginalise=marginalise, left=left, **kwargs):
            out = marginalise(*args, **kwargs)
            left.extend(out.keys())
            return out

        sm._update = recording
        for t, tr in zip(t_kf, tracks, strict=True):
            est.add_keyframe(int(t), tr)
            result = sm.last_result()
            reeliminated.append(result.getVariablesReeliminated() if result is not None else 0)
            relinearised.append(result.getVariablesRelinearized() if result is not None else 0)
            est.background()
        est.finish()
        runs[own] = (np.array(reeliminated[15:]), relinearised, left, est)
    (plain, relin_plain, left_plain, est_plain), (own, relin_own, left_own, est_own) = runs[False], runs[True]
    spikes = [int((x > 1.25 * np.median(x)).sum()) for x in (plain, own)]
    assert spikes[0] >= 5 and spikes[1] <= 1  # measured: 7 keyframes re-eliminating 137-157 variables against 1
    assert not any(relin_plain) and not any(relin_own)  # the keyframes' updates relinearise in neither
    assert len(left_plain) > 100 and left_own == left_plain
    assert len(est_own.stats().background_ms) == len(est_plain.stats().background_ms) >= 12
    a, b = (np.array([s.world_T_body[:3, 3] for s in est.states()]) for est in (est_plain, est_own))
    assert a.shape == b.shape and np.abs(a - b).max() < 1e-6
    assert not est_plain.stats().recoveries and not est_own.stats().recoveries


def test_the_landmarks_last_seen_at_a_keyframe_are_what_a_scan_of_last_obs_gives():
    """`GraphState.landmarks_last_seen_at` (the background step's landmarks) against the scan it replaces, after
    views added out of order (a late admission adds views to older keyframes)."""
    import backend.factors as fb
    from backend.graph_state import GraphState
    from tests.backend.test_time_offset import _camera

    st = GraphState(Smoother(SmootherConfig()), fb.calibration(_camera()), fb.PixelNoise(1.0, 0.0, 1.345), 30, print)
    rng = np.random.default_rng(4)
    graph = gtsam.NonlinearFactorGraph()
    for k in range(12):
        st.t_ns[k] = k * 100_000_000
    for _ in range(400):
        k, j = int(rng.integers(12)), int(rng.integers(60))
        st.add_projection(graph, k, j, np.array([320.0, 240.0]))
    for k in range(12):
        assert st.landmarks_last_seen_at(k) == [j for j, kk in st.last_obs.items() if kk == k]
    assert sum(len(st.landmarks_last_seen_at(k)) for k in range(12)) == len(st.last_obs) == 60
    # landmarks that left the lag leave the index (it holds the window's keyframes alone); seen again, they are
    # filed at their new keyframe
    gone = {j for j, kk in st.last_obs.items() if kk < 6}
    st.unlist_retired(gone)
    for k in range(12):
        assert st.landmarks_last_seen_at(k) == [j for j, kk in st.last_obs.items() if kk == k and j not in gone]
    assert sorted(st._last_seen_at) == sorted({kk for j, kk in st.last_obs.items() if j not in gone})
    back = min(gone)
    st.t_ns[12] = 1_200_000_000
    st.add_projection(graph, 12, back, np.array([320.0, 240.0]))
    assert st.landmarks_last_seen_at(12) == [back]


def test_estimate_keys_gives_the_whole_estimates_values_to_the_bit(data):
    """`Smoother.estimate_keys` inserts poses and biases by argument name (pybind11's overload search made a bias
    cost 150 us by position): the same values, to the bit, as the whole estimate, for poses, velocities, biases and
    landmarks; a key the solver does not hold is a SolverFailure."""
    from backend.smoother import SolverFailure

    cam, imu, cal, t_kf, tracks, gt = data
    est = VioEstimator(cam, imu, ImuPreintegrator(imu, cal, ImuConfig()).between, _fixed_lag("smoother.lag_s=2.0"))
    for t, tr in zip(t_kf[:30], tracks[:30], strict=True):
        est.add_keyframe(int(t), tr)
        est.background()
    sm = est.state.smoother
    keys = sorted(sm._keys)
    kinds = {chr(gtsam.Symbol(key).chr()) for key in keys}
    assert kinds == {"x", "v", "b", "l"} and len(keys) > 100
    a, b = sm.estimate_keys(keys), sm.estimate()
    assert a.size() == len(keys) == b.size()
    for key in keys:
        kind = chr(gtsam.Symbol(key).chr())
        if kind == "x":
            assert np.array_equal(a.atPose3(key).matrix(), b.atPose3(key).matrix())
        elif kind == "b":
            assert np.array_equal(a.atConstantBias(key).vector(), b.atConstantBias(key).vector())
        elif kind == "v":
            assert np.array_equal(a.atVector(key), b.atVector(key))
        else:
            assert np.array_equal(a.atPoint3(key), b.atPoint3(key))
    with pytest.raises(SolverFailure):
        sm.estimate_keys([*keys[:3], gtsam.symbol_shorthand.X(10**6)])
