"""FeatureTracker on synthetic images with known motion, and the geometric check on known epipolar geometry."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from frontend.detection import cell_index, detect_corners
from frontend.tracker import FeatureTracker
from tests.conftest import shared_path
from vio.config import TrackerConfig
from vio.errors import CalibrationError, CaptureError, ConfigError
from vio.geometry import skew
from vio.records import CameraCalib, Frame

W, H = 640, 480


def camera(dist=(0.0, 0.0, 0.0, 0.0), width: int = W, height: int = H) -> CameraCalib:
    return CameraCalib(width, height, 450.0, 450.0, width / 2 - 0.5, height / 2 - 0.5, np.array(dist), np.eye(4))


def texture(seed: int = 0, size: tuple[int, int] = (H + 200, W + 200)) -> np.ndarray:
    """A blurred-noise image (float, 0..255) larger than the frame so that shifted crops stay inside it."""
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.uniform(0, 255, size).astype(np.float32), (0, 0), 2.0)
    img = (img - img.min()) / (img.max() - img.min()) * 255.0
    return img


def shifted(tex: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """Frame whose pixel (x, y) shows the texture at (x - dx + 100, y - dy + 100): content moves by (+dx, +dy)."""
    M = np.array([[1.0, 0.0, 100.0 - dx], [0.0, 1.0, 100.0 - dy]])
    out = cv2.warpAffine(tex, M, (W, H), flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP)
    return np.clip(out, 0, 255).astype(np.uint8)


def test_translation_is_tracked_with_stable_ids_and_ages():
    tex = texture()
    trk = FeatureTracker(camera(), TrackerConfig())
    first = trk.track(Frame(0, 0, shifted(tex, 0.0, 0.0)))
    assert first.ids.dtype == np.int64 and first.uv.shape == (150, 2)
    assert np.array_equal(first.ids, np.arange(150)) and np.all(trk.ages() == 1)
    step = np.array([2.5, -1.25])
    born = dict.fromkeys(first.ids.tolist(), 0)
    for k in range(1, 6):
        tr = trk.track(Frame(k * 50_000_000, 0, shifted(tex, *(k * step))))
        _, i0, i1 = np.intersect1d(first.ids, tr.ids, return_indices=True)
        assert i0.size >= 140  # a pure shift loses only the tracks that leave through the border
        err = tr.uv[i1] - (first.uv[i0] + k * step)
        assert np.median(np.linalg.norm(err, axis=1)) < 0.05
        assert tr.ids.size == 150 and np.unique(tr.ids).size == 150
        new = np.array([i not in born for i in tr.ids.tolist()])
        assert tr.ids[new].min(initial=10**9) > max(born)  # new ids never reuse old ones
        born.update(dict.fromkeys(tr.ids[new].tolist(), k))
        assert np.array_equal(trk.ages(), [k - born[i] + 1 for i in tr.ids.tolist()])


def test_still_images_give_still_tracks_and_skip_the_essential_check():
    tex = texture(1)
    img = shifted(tex, 0, 0)
    trk = FeatureTracker(camera(), TrackerConfig())
    tr0 = trk.track(Frame(0, 0, img))
    for k in range(1, 4):
        tr = trk.track(Frame(k, 0, img))
        assert np.array_equal(tr.ids, tr0.ids)
        assert np.abs(tr.uv - tr0.uv).max() < 0.01
    assert trk.stats["essential_skipped"] == 3 and trk.stats["essential_rejected"] == 0


def test_featureless_then_textured_then_featureless():
    trk = FeatureTracker(camera(), TrackerConfig())
    blank = np.full((H, W), 128, np.uint8)
    tr = trk.track(Frame(0, 0, blank))
    assert tr.ids.shape == (0,) and tr.uv.shape == (0, 2) and trk.ages().shape == (0,)
    tr = trk.track(Frame(1, 0, shifted(texture(2), 0, 0)))
    assert tr.ids.size == 150
    tr = trk.track(Frame(2, 0, blank))  # everything is lost; nothing is invented
    assert tr.ids.size == 0
    tr = trk.track(Frame(3, 0, cv2.cvtColor(shifted(texture(3), 0, 0), cv2.COLOR_GRAY2BGR)))  # BGR input
    assert tr.ids.size == 150 and tr.ids.min() >= 150


def test_detection_spreads_over_the_grid_and_keeps_distance():
    cfg = TrackerConfig()
    gray = shifted(texture(4), 0, 0)
    # make one quadrant far more textured than the rest: without bucketing it would take most corners
    gray[: H // 2, : W // 2] = np.clip(gray[: H // 2, : W // 2].astype(np.float32) * 3 - 250, 0, 255).astype(np.uint8)
    uv, _ = detect_corners(gray, np.zeros((0, 2)), cfg.max_features, cfg)
    assert uv.shape[0] == cfg.max_features
    cells = np.bincount(cell_index(uv, (H, W), cfg.grid_rows, cfg.grid_cols), minlength=cfg.grid_rows * cfg.grid_cols)
    assert np.count_nonzero(cells) >= 0.9 * cells.size
    assert cells.max() <= int(np.ceil(cfg.max_features / cells.size)) + 1
    d = np.linalg.norm(uv[:, None] - uv[None], axis=2) + np.eye(uv.shape[0]) * 1e9
    assert d.min() >= cfg.min_distance_px - cfg.subpix_window  # refinement moves a corner by <= subpix_window / 2
    b = cfg.border_px
    assert uv[:, 0].min() >= b and uv[:, 1].min() >= b and uv[:, 0].max() <= W - 1 - b and uv[:, 1].max() <= H - 1 - b


def test_texture_in_one_corner_still_reaches_the_target():
    cfg = TrackerConfig(max_features=100)
    gray = np.full((H, W), 100, np.uint8)
    gray[: H // 2, : W // 2] = shifted(texture(5), 0, 0)[: H // 2, : W // 2]
    uv, _ = detect_corners(gray, np.zeros((0, 2)), cfg.max_features, cfg)
    assert uv.shape[0] == 100
    assert np.all(uv[:, 0] < W // 2 + cfg.min_distance_px) and np.all(uv[:, 1] < H // 2 + cfg.min_distance_px)


def test_detection_avoids_existing_tracks():
    cfg = TrackerConfig()
    gray = shifted(texture(6), 0, 0)
    existing, _ = detect_corners(gray, np.zeros((0, 2)), 60, cfg)
    new, _ = detect_corners(gray, existing, 90, cfg)
    assert new.shape[0] == 90
    d = np.linalg.norm(new[:, None] - existing[None], axis=2)
    assert d.min() >= cfg.min_distance_px - cfg.subpix_window


def test_subpixel_refinement_finds_true_corners():
    """Checkerboard corners rendered at known sub-pixel positions are found to a small fraction of a pixel."""
    s = 8  # render at 8x and downsample by area: the corner sits at a known non-integer pixel position
    big = np.zeros((H * s, W * s), np.uint8)
    ox, oy, sq = 0.375, 0.625, 40.0  # grid origin offset and square size in output pixels
    yy, xx = np.mgrid[0 : H * s, 0 : W * s]
    u = (xx + 0.5) / s - 0.5 - ox
    v = (yy + 0.5) / s - 0.5 - oy
    big[((np.floor(u / sq) + np.floor(v / sq)) % 2).astype(bool)] = 200
    big += 25
    gray = cv2.resize(big, (W, H), interpolation=cv2.INTER_AREA)
    cfg = TrackerConfig(max_features=60, min_distance_px=20.0)
    uv, _ = detect_corners(gray, np.zeros((0, 2)), cfg.max_features, cfg)
    assert uv.shape[0] >= 40
    nearest = np.round((uv - [ox, oy]) / sq) * sq + [ox, oy]
    err = np.linalg.norm(uv - nearest, axis=1)
    assert np.median(err) < 0.1


def _two_view(n: int, rng: np.random.Generator, cam: CameraCalib) -> tuple[np.ndarray, np.ndarray]:
    """Projections (distorted px) of n random points in two views related by a rotation and a translation."""
    p_c0 = np.column_stack([rng.uniform(-2, 2, n), rng.uniform(-1.5, 1.5, n), rng.uniform(3, 8, n)])
    R = cv2.Rodrigues(np.array([0.01, -0.02, 0.005]))[0]
    t = np.array([0.15, 0.02, 0.03])
    p_c1 = p_c0 @ R.T + t
    return cam.project(p_c0), cam.project(p_c1)


@pytest.mark.parametrize("method", ["usac_magsac", "usac_accurate", "ransac"])
def test_essential_check_rejects_outliers_on_distorted_views(method):
    cam = camera(dist=(-0.28, 0.07, 2e-4, 2e-5))
    rng = np.random.default_rng(7)
    uv0, uv1 = _two_view(150, rng, cam)
    uv1 = uv1 + rng.normal(0, 0.1, uv1.shape)  # well inside the default 0.5 px threshold
    bad = rng.choice(150, 15, replace=False)
    direction = rng.normal(size=(15, 2))
    uv1[bad] += direction / np.linalg.norm(direction, axis=1, keepdims=True) * rng.uniform(4, 15, (15, 1))
    trk = FeatureTracker(cam, TrackerConfig(essential_method=method, ransac_threshold_px=0.5))
    inl = trk._essential_inliers(uv0, uv1)
    outlier = np.zeros(150, bool)
    outlier[bad] = True
    # an outlier moved along its epipolar line is undetectable; allow one of those
    assert np.count_nonzero(inl & outlier) <= 1
    assert np.count_nonzero(~inl & ~outlier) <= 4


def test_bad_inputs_raise_clear_errors():
    with pytest.raises(ConfigError, match="essential_method"):
        FeatureTracker(camera(), TrackerConfig(essential_method="magic"))
    trk = FeatureTracker(camera(), TrackerConfig())
    with pytest.raises(CalibrationError, match="320x240 px but the camera calibration says 640x480"):
        trk.track(Frame(5, 0, np.zeros((240, 320), np.uint8)))
    trk.track(Frame(5, 0, np.zeros((H, W), np.uint8)))
    with pytest.raises(CaptureError, match="not after"):
        trk.track(Frame(5, 0, np.zeros((H, W), np.uint8)))


# --- real images -------------------------------------------------------------------------------------------------


def _middlebury_views() -> tuple[list, CameraCalib]:
    """(name, image, K, R, t) of the consecutive templeRing views; x_cam = R @ X + t, pixels = K @ x_cam."""
    d = shared_path("middlebury_temple", "templeRing_subset_13-31")
    par = {}
    for line in (d / "templeR_par.txt").read_text().splitlines()[1:]:
        f = line.split()
        v = np.array(f[1:], float)
        par[f[0]] = (v[:9].reshape(3, 3), v[9:18].reshape(3, 3), v[18:21])
    names = sorted(p.name for p in d.glob("templeR0*.png"))
    views = [(n, cv2.imread(str(d / n), cv2.IMREAD_GRAYSCALE), *par[n]) for n in names]
    K = views[0][2]
    cam = CameraCalib(640, 480, K[0, 0], K[1, 1], K[0, 2], K[1, 2], np.zeros(4), np.eye(4))
    return views, cam


def sampson_px(F: np.ndarray, uv0: np.ndarray, uv1: np.ndarray) -> np.ndarray:
    """(N,) first-order geometric (Sampson) distance, px, of correspondences uv0 <-> uv1 to x1^T F x0 = 0."""
    x0 = np.column_stack([uv0, np.ones(len(uv0))])
    x1 = np.column_stack([uv1, np.ones(len(uv1))])
    Fx0, Ftx1 = x0 @ F.T, x1 @ F
    num = np.abs(np.sum(x1 * Fx0, axis=1))
    return num / np.sqrt(Fx0[:, 0] ** 2 + Fx0[:, 1] ** 2 + Ftx1[:, 0] ** 2 + Ftx1[:, 1] ** 2)


def middlebury_sampson(cfg: TrackerConfig) -> dict:
    """Track the consecutive templeRing views; Sampson distances (px) of shared tracks to the calibrated geometry.

    Run from the project root: `.venv/bin/python -c "import tests.frontend.test_tracker
    as t; from vio.config import TrackerConfig; print(t.summary(t.middlebury_sampson(TrackerConfig())))"`.
    """
    views, cam = _middlebury_views()
    trk = FeatureTracker(cam, cfg)
    errors, counts, common, prev = [], [], [], None
    for k, (_, img, K, R, t) in enumerate(views):
        tr = trk.track(Frame(k * 100_000_000, 0, img))
        counts.append(tr.ids.size)
        if prev is not None:
            tr0, K0, R0, t0 = prev
            _, i0, i1 = np.intersect1d(tr0.ids, tr.ids, return_indices=True)
            common.append(i0.size)
            R10 = R @ R0.T
            t10 = t - R10 @ t0
            F = np.linalg.inv(K).T @ skew(t10) @ R10 @ np.linalg.inv(K0)
            errors.append(sampson_px(F, tr0.uv[i0], tr.uv[i1]))
        prev = (tr, K, R, t)
    e = np.concatenate(errors)
    return {"pairs": len(errors), "min_tracks": min(counts), "min_common": min(common), "errors_px": e}


def summary(stats: dict) -> dict:
    """Printable summary: arrays become median / 99th percentile / max / fraction over 2 px."""
    out = {k: v for k, v in stats.items() if not isinstance(v, np.ndarray)}
    for k, v in stats.items():
        if isinstance(v, np.ndarray):
            out[k] = {
                "n": v.size,
                "median": round(float(np.median(v)), 3),
                "p99": round(float(np.percentile(v, 99)), 3),
                "max": round(float(v.max()), 2),
                "frac_over_2px": round(float(np.mean(v > 2.0)), 4),
            }
    return out


def test_middlebury_temple_tracks_satisfy_the_known_epipolar_geometry():
    """Views 7.7 deg apart around a real object: tracks agree with F from the calibrated K, R, t.

    Measured (this machine, default config): median Sampson distance 0.066 px, 99th percentile 0.41 px, worst
    0.50 px, at least 52 tracks shared by consecutive views. With `essential_method=none` (no epipolar check) the 99th
    percentile is 1.13 px, 0.3% exceed 2 px and the worst is 38 px.
    """
    stats = middlebury_sampson(TrackerConfig())
    e = stats["errors_px"]
    assert stats["pairs"] == 18 and stats["min_tracks"] >= 100 and stats["min_common"] >= 40
    assert np.median(e) < 0.2
    assert np.percentile(e, 99) < 1.0
    assert np.mean(e > 2.0) < 0.002 and e.max() < 5.0


def test_euroc_still_camera_gives_still_tracks():
    """95 real frames of a parked drone: tracks neither drift nor wander apart.

    The camera itself rotates by about 0.17 deg in these frames (ground truth; ~1.4 px), so raw displacement is
    bounded loosely and the tight bounds are on the motion relative to the common image motion and on chaining
    (frame-to-frame tracking compared with tracking from the first frame directly).
    Measured: 98% of the first frame's tracks survive; median per-track max displacement 1.71 px; relative 0.42 px;
    chaining 0.013 px.
    """
    from vio.readers.asl import read_asl

    cap = read_asl(shared_path("euroc_v1_01"))
    trk = FeatureTracker(cap.camera, TrackerConfig())
    uv_by_frame = []
    first = None
    for frame in cap.frames():
        tr = trk.track(frame)
        first = tr if first is None else first
        _, i0, i1 = np.intersect1d(first.ids, tr.ids, return_indices=True)
        uv = np.full(first.uv.shape, np.nan)
        uv[i0] = tr.uv[i1]
        uv_by_frame.append(uv)
        assert tr.ids.size >= 140
    uv = np.stack(uv_by_frame)  # (F, N, 2) positions of the first frame's tracks
    alive = np.isfinite(uv[-1, :, 0])
    assert alive.mean() >= 0.9
    d = uv[:, alive] - uv[0, alive]
    assert np.median(np.linalg.norm(d, axis=2).max(axis=0)) < 3.0
    rel = np.linalg.norm(d - np.median(d, axis=1, keepdims=True), axis=2)
    assert np.median(rel.max(axis=0)) < 0.8
    direct, st, _ = cv2.calcOpticalFlowPyrLK(
        cap.load_image(0),
        cap.load_image(cap.num_frames - 1),
        first.uv[alive].astype(np.float32),
        None,
        winSize=(21, 21),
        maxLevel=3,
    )
    ok = st.ravel() == 1
    assert np.median(np.linalg.norm(direct[ok] - uv[-1, alive][ok], axis=1)) < 0.1


# --- rendered capture with ground truth ----------------------------------------------------------------------------


def triangulate(cam_T_world: np.ndarray, xy: np.ndarray, iterations: int = 5) -> np.ndarray:
    """World point (3,) from (M, 4, 4) camera poses and (M, 2) undistorted normalized observations.

    Linear (DLT) solution refined by Gauss-Newton on the normalized-plane residuals.
    """
    P = cam_T_world[:, :3, :]
    A = np.concatenate([xy[:, :1] * P[:, 2] - P[:, 0], xy[:, 1:2] * P[:, 2] - P[:, 1]])
    X = np.linalg.svd(A)[2][-1]
    X = X[:3] / X[3]
    for _ in range(iterations):
        pc = P[:, :, :3] @ X + P[:, :, 3]
        z = pc[:, 2:3]
        r = (pc[:, :2] / z - xy).ravel()
        J = np.stack([P[:, 0, :3] - pc[:, :1] / z * P[:, 2, :3], P[:, 1, :3] - pc[:, 1:2] / z * P[:, 2, :3]], axis=1)
        X = X - np.linalg.lstsq((J / z[:, :, None]).reshape(-1, 3), r, rcond=None)[0]
    return X


def orbit_reprojection(capture_root, cfg: TrackerConfig) -> dict:
    """Track a simulated capture; triangulate every track seen >= 3 times from the ground-truth camera poses.

    Residuals are distorted-pixel reprojection errors. Run from the project root (after `vio simulate orbit --out
    CAP --duration 3`): `.venv/bin/python -c "import tests.frontend.test_tracker as t;
    from vio.config import TrackerConfig; print(t.summary(t.orbit_reprojection('CAP', TrackerConfig())))"`.
    """
    from vio.readers.asl import read_asl

    cap = read_asl(capture_root)
    cam = cap.camera
    trk = FeatureTracker(cam, cfg)
    counts = []
    obs: dict[int, list[tuple[int, np.ndarray]]] = {}
    for k, frame in enumerate(cap.frames()):
        tr = trk.track(frame)
        counts.append(tr.ids.size)
        for i, uv in zip(tr.ids.tolist(), tr.uv, strict=True):
            obs.setdefault(i, []).append((k, uv))
    gt = cap.ground_truth
    idx = np.searchsorted(gt.t_ns, cap.frame_t_ns)
    assert np.array_equal(gt.t_ns[idx], cap.frame_t_ns), "ground truth must be sampled at the frame times"
    cam_T_world = np.stack([np.linalg.inv(gt.world_T_body(int(i)) @ cam.body_T_cam) for i in idx])
    residuals, track_rms, track_max = [], [], []
    for lst in obs.values():
        if len(lst) < 3:
            continue
        ks = np.array([k for k, _ in lst])
        uv = np.array([u for _, u in lst])
        X = triangulate(cam_T_world[ks], cam.undistort_to_normalized(uv))
        p_cam = X @ cam_T_world[ks, :3, :3].transpose(0, 2, 1) + cam_T_world[ks, :3, 3]
        if np.any(p_cam[:, 2] <= 0):
            track_rms.append(np.inf)
            track_max.append(np.inf)
            continue
        r = np.linalg.norm(cam.project(p_cam) - uv, axis=1)
        residuals.append(r)
        track_rms.append(float(np.sqrt(np.mean(r**2))))
        track_max.append(float(r.max()))
    return {
        "min_tracks": min(counts),
        "tracks": len(track_rms),
        "residuals_px": np.concatenate(residuals),
        "track_rms_px": np.asarray(track_rms),
        "track_max_px": np.asarray(track_max),
    }


def test_orbit_tracks_triangulate_with_ground_truth_poses(sim_capture):
    """Rendered orbit (3 s, 60 frames, 640x480, phone-like radtan lens): tracks are geometrically right.

    Each track seen in >= 3 frames is triangulated from the ground-truth camera poses (world_T_body of the capture's
    ground truth composed with body_T_cam) and reprojected into every frame that saw it (distorted pixels).
    A track's error is its RMS reprojection error. Measured: 150 tracks every frame, 520 tracks, median residual
    0.16 px, 0.19% of tracks with RMS above 2 px (0.58% with their worst observation above 2 px; such tracks are
    on the table top seen at a grazing angle). Without the NCC and lagged epipolar checks: 3.5% (8.4% by worst
    observation); with no checks at all 26%.
    """
    stats = orbit_reprojection(sim_capture("orbit", duration_s=3.0), TrackerConfig())
    assert stats["min_tracks"] >= 80
    assert stats["tracks"] >= 300
    assert np.median(stats["residuals_px"]) < 0.5
    assert np.mean(stats["track_rms_px"] > 2.0) < 0.05
