"""`vio calibrate`: camera intrinsics from views of a board, IMU noise from a static log (Allan deviation).

One module per step: `board` (board specs, corner detection), `views` (images or video frames), `camera` (OpenCV
calibration, outliers, uncertainties), `figures` (pictures), `camera_files` (the command: Kalibr camchain, ASL
sensor.yaml, report). The command line is `vio/cli_calibrate.py`.
"""
