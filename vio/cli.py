"""The `vio` command line: parses arguments and calls library functions (heavy imports stay inside commands)."""

from __future__ import annotations

import argparse
import dataclasses
import logging
import sys

from vio import __version__
from vio.errors import VioError

log = logging.getLogger("vio")


def _add_config_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", help="YAML config file, one section per stage (see vio/config.py)")
    p.add_argument(
        "--preset",
        action="append",
        default=[],
        metavar="NAME",
        help="named preset applied before --config and --set (vio/presets/NAME.yaml: vision_only, fixed_lag)",
    )
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE", help="override")


def _cmd_simulate(args: argparse.Namespace) -> int:
    from vio.sim.api import simulate
    from vio.sim.phone import simulate_options

    phone = simulate_options(args.camera, args.readout_ms, args.exposure_ms, args.time_offset_ms, args.imu_rate)
    real = {}
    if args.real_imu is not None:
        if args.imu is not None:
            raise VioError("--imu chooses a simulated IMU's grade; with --real-imu the noise comes from --imu-calib")
        real = {"real_imu": args.real_imu, "real_imu_calib": args.imu_calib}
    elif args.imu_calib is not None:
        raise VioError("--imu-calib goes with --real-imu")
    if args.start is not None:
        phone["start_s"] = args.start
    if args.close_fit:
        phone["close_fit"] = True
    simulate(
        args.scenario,
        args.out,
        seed=args.seed,
        duration_s=args.duration,
        imu_grade=args.imu or "phone",
        overwrite=args.force,
        images=not args.no_images,
        part=args.object,
        part_units=args.object_units,
        surface=args.surface,
        stills_hz=args.stills,
        stills_size=args.stills_size,
        board=args.board,
        calibration_motion=args.motion,
        mars=args.mars,
        **real,
        **phone,
        **_phases(args),
    )
    return 0


def _phases(args: argparse.Namespace) -> dict:
    """`phases=` for simulate when a still start, excitation or still end is asked for (else nothing)."""
    from vio.sim.phases import PhasedMotion

    phases = PhasedMotion(args.still_start, args.excite, args.still_end)
    return {"phases": phases} if phases.active else {}


def _size(text: str) -> tuple[int, int]:
    """`WxH` -> (W, H) for argparse."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT, e.g. 2016x1512, got {text!r}") from None
    return w, h


def _cmd_track(args: argparse.Namespace) -> int:
    from vio.config import load_config
    from vio.track import track_capture

    cfg = load_config(args.config, args.overrides, args.preset)
    track_capture(args.capture, args.out, cfg, calib=args.calib)
    return 0


def _cmd_run(args: argparse.Namespace) -> int:
    from vio.atomic import ensure_dir
    from vio.config import load_config
    from vio.pipeline import run_capture
    from vio.readers import open_capture

    cfg = load_config(args.config, args.overrides, args.preset)
    ensure_dir(args.out)  # first: a folder in the way fails before any work
    capture = open_capture(args.capture, calib=args.calib)  # a bad capture fails before a viewer starts
    sinks = []
    if args.rrd or args.serve or args.spawn:
        from vio.viz.rerun_sink import make_rerun_sink

        if args.serve:  # the viewer's address (and serving until Ctrl-C) must reach the user
            logging.getLogger("vio.viz.rerun_sink").setLevel(logging.INFO)
        sinks.append(make_rerun_sink(rrd=args.rrd, serve=args.serve, spawn=args.spawn, port=args.port))
    if args.refine:
        cfg = dataclasses.replace(cfg, run=dataclasses.replace(cfg.run, refine=True))
    try:
        result = run_capture(capture, args.out, cfg, positions=args.positions, sinks=sinks)
    except KeyboardInterrupt:
        print(f"vio run: interrupted; nothing kept ({args.out}/run.json says interrupted)", file=sys.stderr)
        return 130
    from vio.health import summary_lines

    print("\n".join(summary_lines(result.summary)))
    return 0


def _cmd_eval(args: argparse.Namespace) -> int:
    from vio.evaluate import evaluate_files

    print(evaluate_files(args.gt, args.est, align=args.align, json_out=args.json))
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    from vio.bench import run_bench

    def progress(line: str) -> None:
        print(line, file=sys.stderr, flush=True)

    run_bench(args.suite, args.out, jobs=args.jobs, scheduler=args.scheduler, captures=args.captures,
              progress=progress)  # fmt: skip
    return 0


def _cmd_info(args: argparse.Namespace) -> int:
    from vio.info import capture_info

    print(capture_info(args.capture, calib=args.calib))
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from vio.demo import run_demo

    print(run_demo(args.out, duration_s=args.duration, seed=args.seed))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="vio", description="Metric visual-inertial odometry with GTSAM.")
    parser.add_argument("--version", action="version", version=f"vio {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-v info, -vv debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    p = sub.add_parser("simulate", help="write a synthetic capture (ASL layout)")
    p.add_argument(
        "scenario", help="orbit | figure8 | room | static | tumble | calibration | a trajectory file (EuRoC CSV or TUM)"
    )
    p.add_argument("--out", required=True, help="output capture folder")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--duration", type=float, default=None, help="seconds (default: the scenario's own)")
    p.add_argument("--imu", choices=["phone", "tactical", "euroc", "ideal"], help="simulated IMU grade (default phone)")
    p.add_argument("--force", action="store_true", help="replace an existing output folder")
    p.add_argument("--no-images", action="store_true", help="skip rendering (IMU and ground truth only)")
    p.add_argument(
        "--object", default="cube", metavar="NAME|FILE.stl", help="the part: cube, cube_features, freeform, or an STL"
    )
    p.add_argument("--object-units", choices=["mm", "m"], default="mm", help="units of an --object STL file")
    p.add_argument("--surface", choices=["speckle", "plain"], default="speckle", help="the part's paint")
    p.add_argument("--stills", type=float, default=0.0, metavar="HZ", help="full-resolution stills rate (0: off)")
    p.add_argument("--stills-size", type=_size, default=(2016, 1512), metavar="WxH", help="stills size, px")
    p.add_argument("--board", help="calibration scenario's board: chessboard:COLSxROWS:SQUARE_MM | charuco:...")
    p.add_argument(
        "--motion",
        choices=["sway", "excite"],
        help="calibration scenario's motion: sway (default; for intrinsics) or excite (brisk turns about every axis, "
        "for camera-IMU calibration)",
    )
    p.add_argument(
        "--camera",
        choices=["default", "phone"],
        default="default",
        help="phone: rolling shutter, motion blur, auto exposure, noise, vignetting, clock offset, portrait, and a "
        "100 Hz IMU with jitter, scale-factor and misalignment errors",
    )
    p.add_argument("--readout-ms", type=float, help="rolling-shutter readout, top to bottom row (phone: 20)")
    p.add_argument("--exposure-ms", type=float, help="exposure per row, motion blur (phone: 10)")
    p.add_argument("--time-offset-ms", type=float, help="camera clock offset, t_imu = t_cam + offset (phone: 15)")
    p.add_argument("--imu-rate", type=float, metavar="HZ", help="IMU rate (default 200; phone: 100)")
    p.add_argument("--mars", metavar="DIR", help="also write the capture as a MARS logger folder (H.264 video)")
    p.add_argument(
        "--real-imu",
        metavar="IMU.csv",
        help="write this real IMU recording (EuRoC/ASL imu0/data.csv, on the trajectory file's clock; the trajectory "
        "is the IMU's pose) instead of a simulated IMU: the semi-real capture",
    )
    p.add_argument(
        "--imu-calib",
        metavar="YAML",
        help="the real IMU's noise (Kalibr IMU YAML or ASL sensor.yaml; default: sensor.yaml beside --real-imu)",
    )
    p.add_argument("--start", type=float, metavar="S", help="start this many seconds into a trajectory file")
    p.add_argument(
        "--close-fit",
        action="store_true",
        help="follow a trajectory file's poses closely instead of smoothing them (always so with --real-imu; give "
        "it to a simulated-IMU twin of a --real-imu capture for the same images)",
    )
    p.add_argument(
        "--still-start", type=float, default=0.0, metavar="S", help="hold the phone still this long before moving"
    )
    p.add_argument(
        "--excite",
        type=float,
        default=0.0,
        metavar="S",
        help="then shake it this long in all directions (about 2 Hz, 5.6 m/s^2 RMS: makes the scale observable)",
    )
    p.add_argument("--still-end", type=float, default=0.0, metavar="S", help="hold it still this long at the end")
    p.set_defaults(func=_cmd_simulate)

    p = sub.add_parser("track", help="track features through a capture; writes t_ns,track_id,u,v")
    p.add_argument("capture")
    p.add_argument("--out", required=True, help="tracks CSV")
    p.add_argument(
        "--calib", help="Kalibr YAML, ASL mav0 folder, or OpenCV/ORB-SLAM FileStorage YAML with the calibration"
    )
    _add_config_args(p)
    p.set_defaults(func=_cmd_track)

    p = sub.add_parser("run", help="estimate poses, velocities, biases and landmarks")
    p.add_argument("capture", help="capture folder, bag, phone log, or gtsam's eqvio CSV")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--positions", help="known positions CSV: t_s,x,y,z,sigma_m")
    p.add_argument("--calib", help="Kalibr YAML or ASL mav0 folder with the calibration")
    p.add_argument("--refine", action="store_true", help="final full batch refinement (same as --set run.refine=true)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--rrd", help="save a rerun recording")
    g.add_argument("--serve", action="store_true", help="serve the rerun web viewer on 127.0.0.1")
    g.add_argument("--spawn", action="store_true", help="spawn the native rerun viewer")
    p.add_argument("--port", type=int, default=0, help="web viewer port with --serve (0: choose)")
    _add_config_args(p)
    p.set_defaults(func=_cmd_run)

    p = sub.add_parser("eval", help="score a trajectory against ground truth")
    p.add_argument("--gt", required=True, help="ground truth (TUM or EuRoC CSV)")
    p.add_argument("--est", required=True, help="estimate (TUM or EuRoC CSV)")
    p.add_argument("--align", choices=["se3", "posyaw", "sim3", "none"], default="se3")
    p.add_argument("--json", help="also write the metrics as JSON")
    p.set_defaults(func=_cmd_eval)

    p = sub.add_parser("bench", help="Monte-Carlo drift benchmark against baselines")
    p.add_argument(
        "--suite",
        default="quick",
        help="tiny | quick | full | drift60 | model | model_guided | parts | scale | scale60, or a suite YAML",
    )
    p.add_argument("--out", required=True, help="output folder; a suite run again into it resumes")
    p.add_argument("--jobs", type=int, default=2, help="parallel jobs (local threads or LocalCluster workers)")
    p.add_argument(
        "--scheduler",
        default="local",
        help="local (default) | dask (a dask.distributed LocalCluster of --jobs workers) | tcp://HOST:PORT "
        "(an existing Dask scheduler)",
    )
    p.add_argument("--captures", help="a captures folder every worker shares (default: OUT/captures, or each "
                   "remote worker's temporary cache)")  # fmt: skip
    p.set_defaults(func=_cmd_bench)

    p = sub.add_parser("info", help="what is in a capture")
    p.add_argument("capture")
    p.add_argument("--calib", help="Kalibr YAML or ASL mav0 folder with the calibration")
    p.set_defaults(func=_cmd_info)

    from vio.cli_model import add_model_commands

    add_model_commands(sub)

    from vio.cli_calibrate import add_calibrate_commands

    add_calibrate_commands(sub)

    p = sub.add_parser("demo", help="simulate the orbit capture, run, evaluate, report")
    p.add_argument("--out", default="out/demo")
    p.add_argument("--duration", type=float, default=30.0)
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=_cmd_demo)
    return parser


def main(argv: list[str] | None = None) -> int:
    from vio.log import setup_logging

    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    setup_logging(args.verbose)
    try:
        return int(args.func(args) or 0)
    except VioError as exc:
        print(f"vio {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # an unforeseen file-system problem (disk full, permissions): one line, no traceback
        print(f"vio {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"vio {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
