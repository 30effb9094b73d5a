"""The calibration commands of the command line: `vio calibrate camera`, `vio calibrate imu` (thin over
vio.calibrate). The camera-IMU calibration (issue 17's third part) is not implemented yet."""

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


def add_calibrate_commands(sub: argparse._SubParsersAction) -> None:
    """Register `vio calibrate camera|imu` on the top-level subcommands."""
    cal = sub.add_parser("calibrate", help="camera intrinsics (board), IMU noise (Allan deviation); Kalibr YAML out")
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
