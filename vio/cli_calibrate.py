"""The calibration commands of the command line: `vio calibrate camera`, `vio calibrate imu`, `vio calibrate
imu-axes` and `vio calibrate camera-imu` (thin over vio.calibrate)."""

from __future__ import annotations

import argparse


def _cmd_camera(args: argparse.Namespace) -> int:
    from vio.calibrate.camera_files import calibrate_camera_files

    print(
        calibrate_camera_files(
            args.inputs,
            args.board,
            args.out,
            model=args.model,
            detector=args.detector,
            max_views=args.max_views,
            mount=args.mount,
            rate_hz=args.rate,
        )
    )
    return 0


def _cmd_imu(args: argparse.Namespace) -> int:
    from vio.calibrate.imu_files import calibrate_imu_files

    print(calibrate_imu_files(args.log, args.out, inflation=args.inflation))
    return 0


def _cmd_imu_axes(args: argparse.Namespace) -> int:
    from vio.calibrate.imu_axes import calibrate_imu_axes_files

    print(calibrate_imu_axes_files(args.log, args.out, args.gravity, args.latitude, args.height))
    return 0


def _cmd_camera_imu(args: argparse.Namespace) -> int:
    from vio.calibrate.camera_imu_files import calibrate_camera_imu_files

    print(
        calibrate_camera_imu_files(
            args.capture,
            args.calib,
            args.out,
            board=args.board,
            detector=args.detector,
            max_offset_ms=args.max_offset_ms,
        )
    )
    return 0


def add_calibrate_commands(sub: argparse._SubParsersAction) -> None:
    """Register `vio calibrate camera|imu|camera-imu` on the top-level subcommands."""
    cal = sub.add_parser(
        "calibrate",
        help="camera intrinsics (board), IMU noise (Allan deviation), camera-IMU extrinsics and time offset; "
        "Kalibr YAML out",
    )
    csub = cal.add_subparsers(dest="what", metavar="WHAT", required=True)

    p = csub.add_parser("camera", help="camera intrinsics from images or a video of a board")
    p.add_argument("inputs", nargs="+", metavar="IMAGES...|VIDEO", help="images of the board, or one video file")
    p.add_argument(
        "--board",
        required=True,
        help="chessboard:COLSxROWS:SQUARE_MM (inner corners) or charuco:COLSxROWS:SQUARE_MM:MARKER_MM[:DICT] "
        "(squares; DICT default DICT_6X6_250)",
    )
    p.add_argument("--out", required=True, help="the Kalibr camchain YAML to write (other files go beside it)")
    p.add_argument("--model", choices=["radtan", "equidistant"], default="radtan", help="distortion model")
    p.add_argument(
        "--detector",
        choices=["classic", "sb"],
        default="classic",
        help="chessboard corners: findChessboardCorners + cornerSubPix (classic) or findChessboardCornersSB",
    )
    p.add_argument("--max-views", type=int, default=40, help="views kept from a video, picked for coverage")
    p.add_argument(
        "--mount",
        choices=["phone", "identity"],
        default="phone",
        help="nominal camera pose in the IMU frame written as T_cam_imu (not calibrated)",
    )
    p.add_argument("--rate", type=float, default=None, help="camera frame rate, Hz (default: the video's, or 30)")
    p.set_defaults(func=_cmd_camera)

    p = csub.add_parser("imu", help="IMU noise (Allan deviation) from a static log")
    p.add_argument("log", metavar="STATIC_LOG", help="a capture (any format vio reads) recorded with the IMU at rest")
    p.add_argument("--out", required=True, help="the Kalibr imu.yaml to write (plot and report go beside it)")
    p.add_argument(
        "--inflation",
        type=float,
        default=10.0,
        help="the factor VIO users commonly multiply the noise by (reported, not applied)",
    )
    p.set_defaults(func=_cmd_imu)

    p = csub.add_parser(
        "imu-axes",
        help="the accelerometer's scale factors and axis angles from the phone laid still in many orientations",
    )
    p.add_argument(
        "log", metavar="LOG", help="a capture (any format vio reads): still 2-3 s in each of 20-30 orientations"
    )
    p.add_argument("--out", required=True, help="the YAML to write (give it to vio run as --set imu.axes=FILE)")
    p.add_argument("--latitude", type=float, default=None, help="where the log was recorded, deg: local gravity")
    p.add_argument("--height", type=float, default=0.0, help="with --latitude: height above sea level, m")
    p.add_argument("--gravity", type=float, default=None, help="local gravity, m/s^2 (default 9.81)")
    p.set_defaults(func=_cmd_imu_axes)

    p = csub.add_parser("camera-imu", help="camera-IMU extrinsics and time offset from a capture of the board")
    p.add_argument(
        "capture", metavar="CAPTURE", help="a capture (any format vio reads) filming the board while turning"
    )
    p.add_argument(
        "--calib",
        help="the camera's camchain YAML (vio calibrate camera --out); default: the capture's own calibration",
    )
    p.add_argument("--out", required=True, help="the Kalibr camchain-imu YAML to write (report goes beside it)")
    p.add_argument(
        "--board",
        help="the board (as for vio calibrate camera); default: the one named in camera_calibration.json beside "
        "--calib; without a board, a capture with feature tracks gives the rotation and time offset only",
    )
    p.add_argument("--detector", choices=["classic", "sb"], default="classic", help="chessboard corner detector")
    p.add_argument("--max-offset-ms", type=float, default=200.0, help="time offsets searched, +- ms")
    p.set_defaults(func=_cmd_camera_imu)
