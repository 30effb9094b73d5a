"""The part-model commands of the command line: `vio model`, `vio compare`, `vio measure` (thin over vio.model)."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import numpy as np

log = logging.getLogger("vio")


def _box(text: str) -> np.ndarray:
    """`xmin,ymin,zmin,xmax,ymax,zmax` (world, m) -> (2, 3) for argparse."""
    try:
        v = np.array([float(x) for x in text.split(",")])
    except ValueError:
        v = np.zeros(0)
    if v.shape != (6,) or np.any(v[3:] <= v[:3]):
        raise argparse.ArgumentTypeError(
            f"expected xmin,ymin,zmin,xmax,ymax,zmax in metres with min < max, got {text!r}"
        )
    return v.reshape(2, 3)


def _cmd_model(args: argparse.Namespace) -> int:
    from vio.model.build import ModelOptions, model_capture, model_from_image_set

    voxel_m = args.voxel_mm * 1e-3
    opts = ModelOptions(args.source, args.max_views, voxel_m, roi_world=args.roi, adjust=args.adjust,
                        backdrop_below=args.backdrop_below, visibility=args.visibility,
                        fill_creases=args.fill_creases)  # fmt: skip
    try:
        if args.middlebury or args.colmap:
            res = model_from_image_set(
                args.out, opts, middlebury=args.middlebury, colmap=args.colmap, images=args.images
            )
        else:
            if args.capture is None:
                raise SystemExit("vio model: error: give a CAPTURE, or --middlebury PAR / --colmap MODEL --images DIR")
            res = model_capture(args.capture, args.run, args.out, opts, positions=args.positions)
    except KeyboardInterrupt:
        print(_interrupted(Path(args.out), args.run is None and not (args.middlebury or args.colmap)), file=sys.stderr)
        return 130
    s = res.summary
    mesh = s["mesh"]
    print(
        f"part: {res.out / 'part.stl'} ({mesh['faces']} faces, watertight {mesh['watertight']}, "
        f"volume {mesh['volume_m3'] * 1e9:.0f} mm^3), {s['num_views']} views, {s['num_dense_points']} dense points, "
        f"{sum(s['timings_s'].values()):.1f} s"
    )
    return 0


def _interrupted(out: Path, made_run: bool) -> str:
    """The line `vio model` ends with on Ctrl-C: no model is kept (the files of one that was being written are
    removed; model.json is written last), and whether the run it made in OUT/run is complete and can be reused."""
    from vio.model.build import discard_model

    if (out / "model.json").is_file():  # the interrupt came after the last file: the model is complete
        return f"vio model: interrupted after the model was written; kept: the model in {out} (model.json)"
    if out.is_dir():
        discard_model(out)
    line = f"vio model: interrupted; no model kept ({out} has no model.json)"
    if not made_run:
        return line
    run = out / "run"
    try:
        status = json.loads((run / "run.json").read_text(encoding="utf-8")).get("status")
    except (OSError, ValueError, AttributeError):
        status = None
    if status in ("ok", "degraded"):
        return f"{line}; kept: the run in {run} ({status}), which --run {run} reuses"
    return f"{line}; no run kept either" + (f" ({run}/run.json says {status})" if status else "")


def _cmd_compare(args: argparse.Namespace) -> int:
    from vio.model.report import compare

    rep = compare(args.model, args.cad, args.out, units=args.units)
    st = rep["deviation"]
    print(
        f"tolerance window {st['max_positive_mm']:+.3f}/{st['max_negative_mm']:+.3f} mm, std {st['std_mm']:.3f} mm, "
        f"RMS {st['rms_mm']:.3f} mm, completeness {100 * rep['completeness']:.1f} %; report: {args.out}/report.md"
    )
    return 0


def _cmd_measure(args: argparse.Namespace) -> int:
    from vio.model.commands import measure_file

    print(
        measure_file(
            args.model,
            args.shape,
            args.cad,
            args.out,
            units=args.units,
            scale_sigma_rel=args.scale_sigma,
            u_model_mm=args.u_model_mm,
        )  # fmt: skip
    )
    return 0


def add_model_commands(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("model", help="the part: dense reconstruction, watertight part.stl (mm), dense.ply")
    p.add_argument("capture", nargs="?", help="capture folder (its stills when present, else video frames)")
    p.add_argument("--run", help="a `vio run` output folder (default: run it first, into OUT/run)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--source", choices=["auto", "stills", "video"], default="auto", help="which images")
    p.add_argument("--max-views", type=int, default=0, help="use at most this many images (0: all)")
    p.add_argument("--positions", help="known body positions CSV (t_s,x,y,z,sigma_m) for the run it makes")
    p.add_argument("--voxel-mm", type=float, default=0.4, help="fusion voxel edge, mm")
    p.add_argument(
        "--no-adjust", dest="adjust", action="store_false", help="use the poses as given (no bundle adjustment)"
    )
    p.add_argument("--no-visibility", dest="visibility", action="store_false",
                   help="fuse every depth, also those other views see through (no visibility check)")  # fmt: skip
    p.add_argument("--no-crease-fill", dest="fill_creases", action="store_false",
                   help="leave the stereo's holes along convex edges open in the fusion")  # fmt: skip
    p.add_argument("--roi", type=_box, metavar="XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX", help="region of interest (world, m)")
    p.add_argument("--backdrop-below", type=int, default=0, metavar="GREY",
                   help="an object shot against black: image regions at or below this grey level (0-255) are empty "
                        "space (silhouette carving; 0: off)")  # fmt: skip
    p.add_argument("--middlebury", metavar="PAR_TXT", help="images with known cameras: a Middlebury *_par.txt")
    p.add_argument("--colmap", metavar="MODEL_DIR", help="images with known cameras: a COLMAP text model")
    p.add_argument("--images", metavar="DIR", help="the images of --colmap")
    p.set_defaults(func=_cmd_model)

    p = sub.add_parser("compare", help="deviation of a model (mesh or cloud) against its CAD, mesh quality")
    p.add_argument("model", help="STL, PLY or OBJ: ours or another program's")
    p.add_argument("--cad", required=True, help="the CAD as STL (mm)")
    p.add_argument("--out", required=True, help="report folder (report.md, report.json, pictures, deviation.ply)")
    p.add_argument("--units", choices=["mm", "m"], help="the model's units (default: from the file, else its size)")
    p.set_defaults(func=_cmd_compare)

    p = sub.add_parser("measure", help="dimensions with 95 %% uncertainty, as an inspection report")
    p.add_argument("model", help="STL, PLY or OBJ")
    p.add_argument("--shape", choices=["box", "auto"], default="auto")
    p.add_argument("--cad", help="CAD (STL, mm): what to measure and the nominals")
    p.add_argument("--out", help="also write measure.md and measure.json here")
    p.add_argument("--units", choices=["mm", "m"], help="the model's units (default: from the file, else mm)")
    p.add_argument("--scale-sigma", type=float, help="relative sigma of the scale (default: from model.json)")
    p.add_argument("--u-model-mm", type=float, default=0.0, help="the reconstruction's own standard uncertainty, mm")
    p.set_defaults(func=_cmd_measure)
