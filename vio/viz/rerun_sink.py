"""The rerun viewer sink: logs what the pipeline reports to rerun. The estimator never draws.

`make_rerun_sink(rrd=..., serve=..., spawn=...)` returns a `RerunSink` (a `vio.sinks.EstimateSink`) that logs on the
`sensor_time` timeline: the camera (Pinhole + world_T_cam), the current image (downscaled JPEG) with its tracked
features coloured by track age, the estimated trajectory beside the ground truth, landmarks, IMU signals, velocity,
biases, solver statistics, the number of tracked features and, at the end, the run's health (vio/health.py).
Frames: world z-up; camera OpenCV; world_T_cam = world_T_body @ body_T_cam.
"""

from __future__ import annotations

import logging
import sys
import time
from collections import OrderedDict
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import rerun as rr

from vio.atomic import ensure_dir
from vio.errors import VioError
from vio.health import RunHealth, describe_span
from vio.records import CameraCalib, Frame, GroundTruth, ImuSeries, StateEstimate
from vio.viz import blueprint as bp
from vio.viz.geometry import anchor_yaw_translation, reprojection_errors_px
from vio.viz.server import ViewerProcess, start_viewer_process

log = logging.getLogger(__name__)

IMAGE_MAX_WIDTH_PX = 400  # images are downscaled by an integer factor to at most this width, then JPEG-encoded
JPEG_QUALITY = 75
TRACKS_KEPT = 400  # recent frames whose tracks are kept to compute a keyframe's reprojection error
GT_ANCHOR_MAX_GAP_NS = 100_000_000
AGE_SATURATION_FRAMES = 30  # track age at which the feature colour stops changing
FEATURE_RADIUS = rr.Radius.ui_points(3.0)  # screen size, whatever the zoom
LANDMARK_RADIUS = rr.Radius.ui_points(2.0)
LINE_RADIUS = rr.Radius.ui_points(1.5)
XYZ_COLORS = np.array([[230, 60, 60], [60, 180, 60], [60, 100, 230]], np.uint8)  # x, y, z series
GT_XYZ_COLORS = np.array([[240, 160, 160], [160, 220, 160], [160, 180, 240]], np.uint8)  # lighter: ground truth
EST_COLOR = [255, 140, 0]
GT_COLOR = [40, 200, 255]


_LUTS: dict[int, np.ndarray] = {}


def _colormap(values: np.ndarray, lo: float, hi: float, cmap: int) -> np.ndarray:
    """(N,) floats -> (N, 3) uint8 RGB through an OpenCV colour map, with lo..hi spread over the map."""
    lut = _LUTS.get(cmap)
    if lut is None:
        ramp = np.arange(256, dtype=np.uint8).reshape(-1, 1)
        lut = _LUTS[cmap] = cv2.applyColorMap(ramp, cmap).reshape(-1, 3)[:, ::-1].copy()
    span = max(hi - lo, 1e-9)
    return lut[np.clip((np.asarray(values, float) - lo) / span * 255.0, 0, 255).astype(np.intp)]


def _time_column(t_ns: np.ndarray) -> rr.TimeColumn:
    return rr.TimeColumn(bp.TIMELINE, timestamp=np.asarray(t_ns, np.int64).astype("datetime64[ns]"))


class RerunSink:
    """Logs everything the pipeline reports to one rerun recording stream (file, web viewer and/or native viewer)."""

    def __init__(self, rec: rr.RecordingStream, rrd_tmp: Path | None, rrd: Path | None, viewer: ViewerProcess | None):
        self.rec = rec
        self.viewer = viewer  # the loopback server or native viewer we started, if any
        self._rrd_tmp, self._rrd = rrd_tmp, rrd
        self._scale = 1.0  # image downscale factor
        self._body_T_cam = np.eye(4)
        self._camera: CameraCalib | None = None
        self._traj: dict[int, np.ndarray] = {}  # keyframe index -> body position (latest estimate wins)
        self._gt: GroundTruth | None = None  # logged at the first estimate, anchored in the estimate's world
        self._tracks: OrderedDict[int, tuple[np.ndarray, np.ndarray]] = OrderedDict()  # t_ns -> (ids, uv) recent
        self._closed = False
        self._last_t_ns: int | None = None  # the last frame's time, ns

    def _set_time(self, t_ns: int) -> None:
        self.rec.set_time(bp.TIMELINE, timestamp=np.datetime64(int(t_ns), "ns"))

    def on_start(self, camera: CameraCalib | None, imu: ImuSeries | None, ground_truth: GroundTruth | None) -> None:
        """Static calibration, the whole IMU stream (one send_columns per signal) and the ground truth if any."""
        rec = self.rec
        rec.log(bp.WORLD, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        if camera is not None:
            self._camera = camera
            self._body_T_cam = np.asarray(camera.body_T_cam, float)
            self._scale = 1.0 / int(np.ceil(camera.width / IMAGE_MAX_WIDTH_PX))
            s = self._scale
            # rerun puts pixel corners on integers, OpenCV pixel centres: shift by half a pixel, then scale.
            K = np.array(
                [[camera.fx * s, 0, (camera.cx + 0.5) * s], [0, camera.fy * s, (camera.cy + 0.5) * s], [0, 0, 1]]
            )
            res = [round(camera.width * s), round(camera.height * s)]
            rec.log(bp.IMAGE, rr.Pinhole(image_from_camera=K, resolution=res, image_plane_distance=0.1), static=True)
        self._log_series_styles(ground_truth is not None)
        if imu is not None and len(imu):
            times = [_time_column(imu.t_ns)]
            rec.send_columns(bp.PLOT_GYRO, times, rr.Scalars.columns(scalars=imu.gyro).partition([3] * len(imu)))
            rec.send_columns(bp.PLOT_ACC, times, rr.Scalars.columns(scalars=imu.acc).partition([3] * len(imu)))
        if ground_truth is not None and len(ground_truth):
            self._gt = ground_truth

    def _log_ground_truth(self, est_world_T_gt_world: np.ndarray | None) -> None:
        """The ground-truth trajectory (static) and velocity/bias series, in the estimate's world when anchored."""
        gt, self._gt = self._gt, None
        T = np.eye(4) if est_world_T_gt_world is None else est_world_T_gt_world
        p_world = gt.p_world @ T[:3, :3].T + T[:3, 3]
        self.rec.log(bp.TRAJ_GT, rr.LineStrips3D([p_world], colors=[GT_COLOR], radii=LINE_RADIUS), static=True)
        times = [_time_column(gt.t_ns)]
        lens = [3] * len(gt)
        for path, values in (
            (bp.PLOT_VEL, gt.v_world @ T[:3, :3].T),
            (bp.PLOT_BIAS_GYRO, gt.b_w),
            (bp.PLOT_BIAS_ACC, gt.b_a),
        ):
            self.rec.send_columns(f"{path}/{bp.GT}", times, rr.Scalars.columns(scalars=values).partition(lens))

    def _log_series_styles(self, with_gt: bool) -> None:
        xyz = ["x", "y", "z"]
        for path in (bp.PLOT_GYRO, bp.PLOT_ACC):
            self.rec.log(path, rr.SeriesLines(colors=XYZ_COLORS, names=xyz, widths=1.0), static=True)
        for path in (bp.PLOT_VEL, bp.PLOT_BIAS_GYRO, bp.PLOT_BIAS_ACC):
            names = [f"est {a}" for a in xyz]
            self.rec.log(f"{path}/{bp.EST}", rr.SeriesLines(colors=XYZ_COLORS, names=names, widths=2.0), static=True)
            if with_gt:
                gt_names = [f"gt {a}" for a in xyz]
                self.rec.log(f"{path}/{bp.GT}", rr.SeriesLines(colors=GT_XYZ_COLORS, names=gt_names), static=True)
        self.rec.log(bp.SOLVE_MS, rr.SeriesLines(names="solve ms", colors=[200, 120, 0]), static=True)
        self.rec.log(bp.REPROJ_PX, rr.SeriesLines(names="median px", colors=[150, 0, 200]), static=True)
        self.rec.log(bp.NUM_LANDMARKS, rr.SeriesLines(names="landmarks", colors=[0, 150, 150]), static=True)
        self.rec.log(bp.NUM_TRACKED, rr.SeriesLines(names="tracked", colors=[60, 160, 60]), static=True)

    def on_frame(self, frame: Frame, ids: np.ndarray, uv: np.ndarray, ages: np.ndarray) -> None:
        """The downscaled JPEG image and its tracked features (distorted px), coloured by age in frames."""
        self._set_time(frame.t_ns)
        img = frame.image
        if self._scale < 1.0:
            h, w = img.shape[:2]
            size = (round(w * self._scale), round(h * self._scale))
            img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
        ok, jpeg = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        if ok:
            self.rec.log(bp.IMAGE, rr.EncodedImage(contents=jpeg.tobytes(), media_type="image/jpeg"))
        uv_rr = (np.asarray(uv, float).reshape(-1, 2) + 0.5) * self._scale
        colors = _colormap(ages, 0.0, AGE_SATURATION_FRAMES, cv2.COLORMAP_VIRIDIS)
        self.rec.log(bp.FEATURES, rr.Points2D(uv_rr, colors=colors, radii=FEATURE_RADIUS))
        self.rec.log(bp.NUM_TRACKED, rr.Scalars(float(len(ids))))
        self._last_t_ns = int(frame.t_ns)
        self._tracks[int(frame.t_ns)] = (np.asarray(ids), np.asarray(uv, float).reshape(-1, 2))
        while len(self._tracks) > TRACKS_KEPT:
            self._tracks.popitem(last=False)

    def on_estimate(self, estimate: StateEstimate, stats: dict[str, Any]) -> None:
        """Camera pose, trajectory so far, landmarks, velocity, biases and solver scalars at the keyframe time."""
        rec = self.rec
        self._set_time(estimate.t_ns)
        world_T_body = np.asarray(estimate.world_T_body, float)
        world_T_cam = world_T_body @ self._body_T_cam
        if self._gt is not None:
            self._log_ground_truth(self._anchor(estimate.t_ns, world_T_body))
        rec.log(bp.CAMERA, rr.Transform3D(translation=world_T_cam[:3, 3], mat3x3=world_T_cam[:3, :3]))
        self._traj[estimate.k] = world_T_body[:3, 3].copy()
        strip = np.array([self._traj[k] for k in sorted(self._traj)])
        rec.log(bp.TRAJ_EST, rr.LineStrips3D([strip], colors=[EST_COLOR], radii=LINE_RADIUS))
        pts = np.asarray(estimate.landmarks_world, float).reshape(-1, 3)
        if pts.shape[0]:  # an estimate without landmarks leaves the last cloud on screen
            lo, hi = np.percentile(pts[:, 2], [2, 98])
            colors = _colormap(pts[:, 2], lo, hi, cv2.COLORMAP_TURBO)
            rec.log(bp.LANDMARKS, rr.Points3D(pts, colors=colors, radii=LANDMARK_RADIUS))
        rec.log(f"{bp.PLOT_VEL}/{bp.EST}", rr.Scalars(np.asarray(estimate.v_world, float)))
        rec.log(f"{bp.PLOT_BIAS_GYRO}/{bp.EST}", rr.Scalars(np.asarray(estimate.bias_gyro, float)))
        rec.log(f"{bp.PLOT_BIAS_ACC}/{bp.EST}", rr.Scalars(np.asarray(estimate.bias_acc, float)))
        solve_ms = float(stats.get("solve_ms", estimate.solve_ms))
        rec.log(bp.SOLVE_MS, rr.Scalars(solve_ms))
        reproj = stats.get("reproj_px_median")
        if reproj is None:
            reproj = self._reprojection_median(estimate, world_T_cam)
        if reproj is not None and np.isfinite(reproj):
            rec.log(bp.REPROJ_PX, rr.Scalars(float(reproj)))
        rec.log(bp.NUM_LANDMARKS, rr.Scalars(float(stats.get("num_landmarks", pts.shape[0]))))

    def on_health(self, health: RunHealth) -> None:
        """Each health span as a warning at its start time, and the run's status at the last frame's time."""
        for span in health.spans:
            self._set_time(span.start_t_ns)
            self.rec.log(bp.HEALTH, rr.TextLog(describe_span(span, health.t0_ns), level=rr.TextLogLevel.WARN))
        self._set_time(self._last_t_ns if self._last_t_ns is not None else health.t0_ns)
        level = {"ok": rr.TextLogLevel.INFO, "degraded": rr.TextLogLevel.WARN}.get(health.status, rr.TextLogLevel.ERROR)
        self.rec.log(bp.HEALTH, rr.TextLog(f"status: {health.status}", level=level))

    def _anchor(self, t_ns: int, est_world_T_body: np.ndarray) -> np.ndarray | None:
        """est_world_T_gt_world from the ground-truth sample nearest t_ns; None (drawn as is) if none is close."""
        gt = self._gt
        i = int(np.argmin(np.abs(gt.t_ns - np.int64(t_ns))))  # once per run
        if abs(int(gt.t_ns[i]) - t_ns) > GT_ANCHOR_MAX_GAP_NS:
            log.warning("ground truth has no sample within 0.1 s of the first keyframe; drawn in its own world frame")
            return None
        return anchor_yaw_translation(est_world_T_body, gt.world_T_body(i))

    def _reprojection_median(self, estimate: StateEstimate, world_T_cam: np.ndarray) -> float | None:
        """Median reprojection error (px) of the keyframe's tracked features on the estimate's landmarks, if any."""
        seen = self._tracks.get(int(estimate.t_ns))
        if seen is None or self._camera is None or len(estimate.landmark_ids) == 0:
            return None
        err = reprojection_errors_px(self._camera, world_T_cam, estimate.landmark_ids, estimate.landmarks_world, *seen)
        return float(np.median(err)) if err.size else None

    def close(self) -> None:
        """Flush; finish the .rrd (renamed into place only now, so it is never seen half-written)."""
        if self._closed:
            return
        self._closed = True
        if self._gt is not None:  # no estimate ever came: show the ground truth in its own frame
            self._log_ground_truth(None)
        try:
            self.rec.flush()
        except RuntimeError as exc:  # a viewer that went away must not lose the saved recording or the run
            log.warning("rerun viewer unreachable, its stream was dropped: %s", str(exc).splitlines()[0])
        self.rec.disconnect()  # drops the sinks: the file sink writes its footer and closes
        if self._rrd_tmp is not None and self._rrd is not None:
            self._rrd_tmp.replace(self._rrd)
            log.info("rerun recording saved: %s (open with: rerun %s)", self._rrd, self._rrd)
        if self.viewer is not None and self.viewer.kind == "web":
            self._serve_until_interrupted()

    def _serve_until_interrupted(self) -> None:
        """At an interactive terminal where the user can see the log, keep serving the finished run until Ctrl-C.
        Otherwise return at once: the server then stops when this process exits (or with `viewer.stop()`)."""
        if not (sys.stdin.isatty() and log.isEnabledFor(logging.INFO)) or self.viewer.process.poll() is not None:
            return
        log.info("run finished; still serving it at %s - press Ctrl-C to stop", self.viewer.url)
        try:
            while self.viewer.process.poll() is None:
                time.sleep(0.5)
        except KeyboardInterrupt:
            pass
        self.viewer.stop()


def make_rerun_sink(
    rrd: str | Path | None = None, serve: bool = False, spawn: bool = False, port: int = 0
) -> RerunSink:
    """A sink logging to a .rrd file, a loopback web viewer (`serve`, `port` 0: chosen) and/or a native viewer.

    `serve` starts `rerun --serve-web` bound to 127.0.0.1 only and logs (INFO) the URL to open in a browser; after
    `close()` it keeps serving until Ctrl-C at an interactive terminal showing INFO logs, else until the process
    exits. `spawn` starts the native viewer (needs a display); with
    both, `serve` wins. The .rrd is written to a temporary file beside `rrd` and renamed in `close()`.
    """
    rec = rr.RecordingStream(bp.APP_ID, send_properties=False)
    rec.set_log_time_enabled(False)
    rec.set_log_tick_enabled(False)
    sinks: list[Any] = []
    viewer = None
    if serve or spawn:  # first, so that a viewer that cannot start leaves no temporary file behind
        viewer = start_viewer_process("web" if serve else "native", web_port=port)
        sinks.append(rr.GrpcSink(viewer.grpc_url))
        if serve:
            log.info("rerun web viewer (loopback only): open %s", viewer.url)
    rrd_path = rrd_tmp = None
    if rrd is not None:
        rrd_path = Path(rrd)
        ensure_dir(rrd_path.parent)
        rrd_tmp = rrd_path.with_name(f".{rrd_path.name}.tmp")
        sinks.append(rr.FileSink(str(rrd_tmp)))
    if not sinks:
        raise VioError("make_rerun_sink: nothing to log to (give rrd, serve or spawn)")
    rec.set_sinks(*sinks, default_blueprint=bp.default_blueprint())
    return RerunSink(rec, rrd_tmp, rrd_path, viewer)
