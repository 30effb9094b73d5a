"""`vio calibrate`: camera intrinsics from views of a board, IMU noise from a static log (Allan deviation), and the
camera-IMU extrinsic and time offset from a capture of the board (or of feature tracks).

One module per step: `board` (board specs, corner detection), `views` (images or video frames), `camera` (OpenCV
calibration, outliers, uncertainties), `figures` (pictures), `camera_files` (the command: Kalibr camchain, ASL
sensor.yaml, report); `allan`, `imu`, `imu_files` (the IMU); `board_motion` (the board's pose per frame), `gyro`
(the integrated gyro), `rotation_align` (time offset and rotation from turns), `extrinsic_graph` (the GTSAM batch
graph), `track_turns` and `epipolar_align` (feature tracks instead of a board), `camera_imu` (the steps wired),
`camera_imu_figures`, `camera_imu_files` (the command: Kalibr camchain-imu, report, picture). The command line is
`vio/cli_calibrate.py`.
"""
