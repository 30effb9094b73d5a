"""Feature tracking: pyramidal KLT with forward-backward, appearance and epipolar checks, anchored to first patches.

Pixel coordinates are in the *distorted* image (what the camera delivered), x right, y down. Per frame:
1. pyramidal Lucas-Kanade from the previous frame, then back again: a track whose round trip misses its start by
   more than `fb_threshold_px` is dropped (occlusions, ambiguous texture);
2. the patch around the new position must correlate (zero-mean NCC, gain/offset invariant) at least `min_ncc`
   with the patch around the old one: this drops tracks whose appearance changes quickly (strong perspective
   change, e.g. a surface seen at a grazing angle close to the camera), where translation-only KLT drifts;
3. an essential matrix is fitted with OpenCV's USAC (MAGSAC++ by default) to the undistorted normalized bearings
   (`CameraCalib.undistort_to_normalized`), the pixel threshold divided by the mean focal length, first against
   the previous frame and then against the frame `essential_lag_frames` back (a wider baseline exposes slow
   drift that no single frame step shows). When the median flow is below `essential_min_flow_px` the views have
   (almost) no parallax, the essential matrix is degenerate and that check is skipped;
4. with `anchor` (the default), each survivor is re-aligned with the patch it began with (`frontend.anchor`: an
   affine warp with gain and bias), so its error does not add up frame after frame; KLT's next step starts there;
5. new Shi-Tomasi corners (grid-bucketed, away from live tracks, sub-pixel refined; `frontend.detection`) top
   the set up to `max_features`.

Each call to `track` returns every live track: survivors of the previous frame first (in their previous order),
then new detections. Track ids are int64, start at 0 and are never reused.
"""

from __future__ import annotations

import logging
import time
from collections import deque

import cv2
import numpy as np

from frontend.anchor import AnchorAligner, zncc_rows
from frontend.detection import CornerResponse, detect_corners
from frontend.keyframes import KeyframeSelector
from vio.config import KeyframeConfig, TrackerConfig
from vio.errors import CalibrationError, CaptureError, ConfigError
from vio.records import CameraCalib, FeatureTracks, Frame

log = logging.getLogger(__name__)

_ESSENTIAL_METHODS = {
    "usac_magsac": cv2.USAC_MAGSAC,
    "usac_accurate": cv2.USAC_ACCURATE,
    "usac_default": cv2.USAC_DEFAULT,
    "usac_prosac": cv2.USAC_PROSAC,
    "ransac": cv2.RANSAC,
    "lmeds": cv2.LMEDS,
    "none": None,
}
_MIN_POINTS_ESSENTIAL = 8  # fewer correspondences than this: no geometric check
_KLT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)
TIMING_SECTIONS = ("klt", "fb_check", "ncc", "ransac", "anchor", "detect")


def to_gray(image: np.ndarray) -> np.ndarray:
    """(H, W) uint8 grayscale from a grayscale or BGR/BGRA uint8 image."""
    if image.ndim == 2:
        return image if image.dtype == np.uint8 else np.clip(image, 0, 255).astype(np.uint8)
    if image.ndim == 3 and image.shape[2] in (3, 4):
        code = cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        return cv2.cvtColor(image.astype(np.uint8, copy=False), code)
    if image.ndim == 3 and image.shape[2] == 1:
        return image[:, :, 0].astype(np.uint8, copy=False)
    raise CaptureError(f"frame image must be (H, W) or (H, W, 3|4), got shape {image.shape}")


class FeatureTracker:
    """Tracks corners of one camera through consecutive frames (call `track` once per frame, in time order)."""

    def __init__(self, camera: CameraCalib, cfg: TrackerConfig, keyframes: KeyframeConfig | None = None) -> None:
        """With `keyframes`, the tracker also picks the keyframes (`frontend.keyframes`, on KLT's pixels before the
        alignment when `cfg.anchor_keyframes_only`) and says after each `track` whether the frame is one
        (`keyframe`); only then can the alignment be kept to keyframes."""
        if cfg.essential_method not in _ESSENTIAL_METHODS:
            raise ConfigError(
                f"config tracker.essential_method: {cfg.essential_method!r} is not one of "
                f"{', '.join(_ESSENTIAL_METHODS)}"
            )
        if cfg.max_features < 0 or cfg.grid_rows < 1 or cfg.grid_cols < 1 or cfg.klt_window < 3:
            raise ConfigError("config tracker: max_features >= 0, grid_rows/grid_cols >= 1, klt_window >= 3 required")
        self.camera = camera
        self.cfg = cfg
        self._win = (int(cfg.klt_window), int(cfg.klt_window))
        self._focal_px = 0.5 * (camera.fx + camera.fy)
        self._prev_gray: np.ndarray | None = None  # the previous image (OpenCV's Python API takes no pyramids)
        self._prev_t_ns: int | None = None
        self._uv = np.zeros((0, 2))  # (N, 2) px, distorted, of the last returned tracks
        self._ids = np.zeros(0, np.int64)
        self._ages = np.zeros(0, np.int64)
        self._next_id = 0
        self._anchor = AnchorAligner(cfg) if cfg.anchor else None
        self._selector = KeyframeSelector(keyframes) if keyframes is not None else None
        self._align_late = self._anchor is not None and self._selector is not None and cfg.anchor_keyframes_only
        self.keyframe: bool | None = None  # the last frame tracked is a keyframe (None: no keyframe selection)
        self._history: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=max(int(cfg.essential_lag_frames), 1))
        self.num_frames = 0
        self.timings_s = dict.fromkeys(TIMING_SECTIONS, 0.0)  # accumulated wall time per section, s
        self.stats = {
            "fb_rejected": 0,
            "essential_rejected": 0,
            "essential_skipped": 0,
            "ncc_rejected": 0,
            "essential_lag_rejected": 0,
            "detected": 0,
        }

    def ages(self) -> np.ndarray:
        """(N,) int64: for each track last returned, the number of frames it has been seen in (1 = new)."""
        return self._ages.copy()

    def anchor_stats(self) -> dict[str, int] | None:
        """Views aligned with their template, and views re-anchored (the alignment failed), so far; None without
        anchoring."""
        return None if self._anchor is None else dict(self._anchor.stats)

    def reset(self) -> None:
        """Forget all tracks (ids keep counting up, so they stay unique)."""
        self._prev_gray = None
        self._uv = np.zeros((0, 2))
        self._ids = np.zeros(0, np.int64)
        self._ages = np.zeros(0, np.int64)
        self._history.clear()
        if self._anchor is not None:
            self._anchor.keep(np.zeros(0, np.int64))

    def _tick(self, section: str, t0: float) -> float:
        t1 = time.perf_counter()
        self.timings_s[section] += t1 - t0
        return t1

    def track(self, frame: Frame, response: CornerResponse | None = None) -> FeatureTracks:
        """Track the previous frame's features into `frame`, drop outliers, top up with new corners (`response`:
        `frontend.detection.corner_response` of the frame's image, when it was computed ahead)."""
        gray = to_gray(frame.image)
        h, w = gray.shape
        if (w, h) != (self.camera.width, self.camera.height):
            raise CalibrationError(
                f"frame t_ns={frame.t_ns}: image is {w}x{h} px but the camera calibration says "
                f"{self.camera.width}x{self.camera.height}"
            )
        if self._prev_t_ns is not None and frame.t_ns <= self._prev_t_ns:
            raise CaptureError(f"frame t_ns={frame.t_ns} is not after the previous frame ({self._prev_t_ns})")
        prepared = None
        if self._anchor is not None:
            t0 = time.perf_counter()
            prepared = AnchorAligner.prepare(gray)
            self._tick("anchor", t0)
        if self._prev_gray is not None and self._ids.size:
            self._follow(gray, prepared)
        n_old = self._ids.size
        t0 = time.perf_counter()
        want = self.cfg.max_features - self._ids.size
        if want > 0:
            new_uv, _ = detect_corners(gray, self._uv, want, self.cfg, response)
            n = new_uv.shape[0]
            self._uv = np.vstack([self._uv, new_uv])
            self._ids = np.concatenate([self._ids, np.arange(self._next_id, self._next_id + n, dtype=np.int64)])
            self._ages = np.concatenate([self._ages, np.ones(n, np.int64)])
            self._next_id += n
            self.stats["detected"] += n
            if self._anchor is not None:
                self._anchor.add(prepared, new_uv)
        self._tick("detect", t0)
        if self._selector is not None:
            self.keyframe = self._selector.consider(FeatureTracks(int(frame.t_ns), self._ids, self._uv))
            if self.keyframe and self._align_late and n_old:
                t0 = time.perf_counter()
                self._uv[:n_old] = self._anchor.align(prepared, self._uv[:n_old])
                self._tick("anchor", t0)
        self._history.append((self._ids.copy(), self._uv.copy()))
        self._prev_gray = gray
        self._prev_t_ns = frame.t_ns
        self.num_frames += 1
        return FeatureTracks(int(frame.t_ns), self._ids.copy(), self._uv.copy(), int(frame.cam_id))

    def _follow(self, gray: np.ndarray, prepared: np.ndarray | None) -> None:
        """KLT forward and back (forward-backward check), border, appearance (NCC) and essential-matrix checks, then
        the survivors aligned with their first patches (with `anchor`)."""
        cfg = self.cfg
        t0 = time.perf_counter()
        p0 = self._uv.astype(np.float32).reshape(-1, 1, 2)
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(
            self._prev_gray, gray, p0, None, winSize=self._win, maxLevel=cfg.klt_levels, criteria=_KLT_CRITERIA
        )
        t0 = self._tick("klt", t0)
        p0b, st2, _ = cv2.calcOpticalFlowPyrLK(
            gray,
            self._prev_gray,
            p1,
            p0.copy(),
            winSize=self._win,
            maxLevel=cfg.klt_levels,
            criteria=_KLT_CRITERIA,
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        )
        uv0 = self._uv
        uv1 = p1.reshape(-1, 2).astype(np.float64)
        fb_err = np.linalg.norm(p0b.reshape(-1, 2).astype(np.float64) - uv0, axis=1)
        h, w = gray.shape
        b = cfg.border_px
        ok = (st1.ravel() == 1) & (st2.ravel() == 1) & np.isfinite(uv1).all(axis=1)
        ok &= fb_err <= cfg.fb_threshold_px
        self.stats["fb_rejected"] += int((~ok).sum())
        ok &= (uv1[:, 0] >= b) & (uv1[:, 0] <= w - 1 - b) & (uv1[:, 1] >= b) & (uv1[:, 1] <= h - 1 - b)
        t0 = self._tick("fb_check", t0)
        if cfg.min_ncc > -1.0:
            ncc = np.full(ok.shape, -1.0)
            ncc[ok] = patch_ncc(self._prev_gray, uv0[ok], gray, uv1[ok], cfg.ncc_radius_px)
            self.stats["ncc_rejected"] += int((ok & (ncc < cfg.min_ncc)).sum())
            ok &= ncc >= cfg.min_ncc
        t0 = self._tick("ncc", t0)
        idx = np.flatnonzero(ok)
        inliers = self._essential_inliers(uv0[idx], uv1[idx])
        self.stats["essential_rejected"] += int((~inliers).sum())
        idx = idx[inliers]
        lag = int(cfg.essential_lag_frames)
        if lag > 1 and len(self._history) >= lag:
            ref_ids, ref_uv = self._history[-lag]
            _, i_ref, i_cur = np.intersect1d(ref_ids, self._ids[idx], assume_unique=True, return_indices=True)
            far = self._essential_inliers(ref_uv[i_ref], uv1[idx][i_cur])
            drop = np.zeros(idx.size, bool)
            drop[i_cur[~far]] = True
            self.stats["essential_lag_rejected"] += int(drop.sum())
            idx = idx[~drop]
        t0 = self._tick("ransac", t0)
        self._uv = uv1[idx]
        if self._anchor is not None:
            self._anchor.keep(idx)
            if not self._align_late:
                self._uv = self._anchor.align(prepared, self._uv)
            self._tick("anchor", t0)
        self._ids = self._ids[idx]
        self._ages = self._ages[idx] + 1

    def _essential_inliers(self, uv0: np.ndarray, uv1: np.ndarray) -> np.ndarray:
        """(N,) bool inlier mask of an essential matrix fitted to undistorted bearings (all True when skipped)."""
        n = uv0.shape[0]
        keep = np.ones(n, bool)
        method = _ESSENTIAL_METHODS[self.cfg.essential_method]
        if method is None or n < _MIN_POINTS_ESSENTIAL:
            return keep
        if float(np.median(np.linalg.norm(uv1 - uv0, axis=1))) < self.cfg.essential_min_flow_px:
            self.stats["essential_skipped"] += 1
            return keep
        x0 = self.camera.undistort_to_normalized(uv0)
        x1 = self.camera.undistort_to_normalized(uv1)
        thr = self.cfg.ransac_threshold_px / self._focal_px
        try:
            E, mask = cv2.findEssentialMat(x0, x1, np.eye(3), method=method, prob=0.999, threshold=thr)
        except cv2.error as exc:  # degenerate configurations make some solvers throw
            log.debug("essential matrix failed (%s); keeping all %d tracks", exc.msg if hasattr(exc, "msg") else exc, n)
            return keep
        if E is None or mask is None or mask.size != n:
            self.stats["essential_skipped"] += 1
            return keep
        return mask.ravel().astype(bool)


def sample_patches(gray: np.ndarray, uv: np.ndarray, radius: int) -> np.ndarray:
    """(N, 2r+1, 2r+1) float32 patches centred on (N, 2) sub-pixel positions (bilinear; border replicated)."""
    n = uv.shape[0]
    d = np.arange(-radius, radius + 1, dtype=np.float32)
    size = d.size
    map_x = (uv[:, 0].astype(np.float32)[:, None, None] + d[None, None, :]).repeat(size, axis=1)
    map_y = (uv[:, 1].astype(np.float32)[:, None, None] + d[None, :, None]).repeat(size, axis=2)
    out = cv2.remap(
        gray,
        map_x.reshape(n * size, size),
        map_y.reshape(n * size, size),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )
    return out.reshape(n, size, size).astype(np.float32)


def patch_ncc(gray0: np.ndarray, uv0: np.ndarray, gray1: np.ndarray, uv1: np.ndarray, radius: int) -> np.ndarray:
    """(N,) normalized cross-correlation of the patches at uv0 in gray0 and uv1 in gray1 (1: identical up to gain)."""
    if uv0.shape[0] == 0:
        return np.zeros(0)
    a = sample_patches(gray0, uv0, radius).reshape(uv0.shape[0], -1)
    b = sample_patches(gray1, uv1, radius).reshape(uv1.shape[0], -1)
    return zncc_rows(a, b)
