"""Entity paths, the timeline name and the default rerun viewer layout (rerun is imported in `vio.viz` only).

Entity tree (world is z-up; the camera frame is OpenCV's x right, y down, z forward):
  world                          ViewCoordinates RIGHT_HAND_Z_UP (static)
  world/camera                   Transform3D world_T_cam at each keyframe
  world/camera/image             Pinhole (static, downscaled intrinsics) + the current JPEG image
  world/camera/image/features    Points2D, tracked features coloured by track age
  world/trajectory/estimate      LineStrips3D of the estimated body positions so far
  world/trajectory/ground_truth  LineStrips3D of the ground-truth body positions (static), when the capture has it
  world/landmarks                Points3D, landmarks coloured by height
  plots/...                      Scalars time series (IMU, velocity, biases, solver, tracked features)
  health                         TextLog: the run's health spans (at their start) and its status (at the end)
"""

from __future__ import annotations

import rerun.blueprint as rrb

APP_ID = "vio"
TIMELINE = "sensor_time"  # timestamps from the capture's t_ns (ns)

WORLD = "world"
CAMERA = "world/camera"
IMAGE = "world/camera/image"
FEATURES = "world/camera/image/features"
TRAJ_EST = "world/trajectory/estimate"
TRAJ_GT = "world/trajectory/ground_truth"
LANDMARKS = "world/landmarks"

PLOT_GYRO = "plots/imu/gyro_rad_s"
PLOT_ACC = "plots/imu/acc_m_s2"
PLOT_VEL = "plots/velocity_m_s"
PLOT_BIAS_GYRO = "plots/bias_gyro_rad_s"
PLOT_BIAS_ACC = "plots/bias_acc_m_s2"
PLOT_SOLVER = "plots/solver"
EST = "estimate"  # leaf name of an estimated series under a plot
GT = "ground_truth"  # leaf name of a ground-truth series under a plot
SOLVE_MS = f"{PLOT_SOLVER}/solve_ms"
REPROJ_PX = f"{PLOT_SOLVER}/reproj_px_median"
NUM_LANDMARKS = f"{PLOT_SOLVER}/num_landmarks"
NUM_TRACKED = f"{PLOT_SOLVER}/num_tracked"
HEALTH = "health"


IMU_WINDOW_S = 10.0  # the IMU plots show this much history before the time cursor


def _series(origin: str, name: str, window_s: float | None = None) -> rrb.TimeSeriesView:
    """A time series view showing data up to the time cursor (the last `window_s` seconds, or all of it)."""
    start = (
        rrb.TimeRangeBoundary.infinite()
        if window_s is None
        else rrb.TimeRangeBoundary.cursor_relative(seconds=-window_s)
    )
    visible = rrb.VisibleTimeRange(TIMELINE, start=start, end=rrb.TimeRangeBoundary.cursor_relative())
    return rrb.TimeSeriesView(origin=origin, name=name, time_ranges=visible)


def default_blueprint() -> rrb.Blueprint:
    """3D scene big on the left; camera image and the time series panels on the right."""
    series = rrb.Grid(
        _series(PLOT_GYRO, "gyro (rad/s)", IMU_WINDOW_S),
        _series(PLOT_ACC, "accelerometer (m/s²)", IMU_WINDOW_S),
        _series(PLOT_VEL, "velocity (m/s)"),
        _series(PLOT_BIAS_GYRO, "gyro bias (rad/s)"),
        _series(PLOT_BIAS_ACC, "acc bias (m/s²)"),
        _series(SOLVE_MS, "solve time (ms)"),
        _series(REPROJ_PX, "reprojection error (px)"),
        _series(NUM_LANDMARKS, "landmarks"),
        _series(NUM_TRACKED, "tracked features"),
        rrb.TextLogView(origin=HEALTH, name="run health"),
        grid_columns=2,
    )
    right = rrb.Vertical(rrb.Spatial2DView(origin=IMAGE, name="camera"), series, row_shares=[2, 3])
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin=WORLD, name="3D: trajectory, landmarks, camera"),
            right,
            column_shares=[3, 2],
        ),
        rrb.TimePanel(timeline=TIMELINE, state="collapsed"),
        collapse_panels=True,
    )
