"""Stereo and fusion alone: the part model of a simulated capture built from its true poses, against its CAD.

The stills are posed by the capture's ground truth (no run, no bundle adjustment), the region of interest is the
part's own box (`scene/cad.stl` placed by `scene/part_pose.yaml`) grown by `--margin-mm`, the support plane its
base. Then the plane sweep (`vio.model.dense`, every k-th still a reference as `vio model` does), the fusion
(`vio.model.fuse`, `--band-mm` the base columns' band, 0 to switch them off), marching cubes, and `vio compare`
against the CAD. What it measures is what the stereo and the fusion add to a perfect trajectory (docs/BENCHMARKS.md,
"The flap along the base").

    python -m vio.bench.fusion_truth CAPTURE [CAPTURE ...] --out DIR [--band-mm 4] [--margin-mm 10] [--no-visibility]
        [--no-creases]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import yaml

from vio.model.records import Roi


def part_roi(capture: str | Path, margin_m: float) -> Roi:
    """The part's box from the capture's CAD and pose, grown by `margin_m` sideways and upwards (not below its
    base), in the part's frame (origin on the base, z up)."""
    from vio.sim.parts import read_stl_mesh

    root = Path(capture) / "scene"
    vertices_mm, _ = read_stl_mesh(root / "cad.stl")
    pose = yaml.safe_load((root / "part_pose.yaml").read_text(encoding="utf-8"))
    world_T_part = np.asarray(pose["world_T_part"], float)
    lo, hi = vertices_mm.min(axis=0) * 1e-3, vertices_mm.max(axis=0) * 1e-3
    grow = np.array([margin_m, margin_m, 0.0])
    return Roi(world_T_part, lo - grow, hi + grow + np.array([0.0, 0.0, margin_m]))


def fusion_truth(
    capture: str | Path,
    out: str | Path,
    band_m: float = 4e-3,
    margin_m: float = 0.01,
    visibility: bool = True,
    creases: bool = True,
) -> dict:
    """The report of `vio compare` (dict) for the model of `capture` from its true poses, written under `out`
    (`visibility`: the depths other views see through dropped before fusion, as `vio model` does; `creases`: holes
    along convex edges filled, `fuse.fill_creases`)."""
    from vio.model import dense, fuse, mesh
    from vio.model.build import MAX_DEPTH_MAPS, ModelOptions
    from vio.model.report import compare
    from vio.model.views import views_from_run
    from vio.readers import open_capture
    from vio.trajio import Trajectory
    from vio.writers import mesh as mesh_io

    cap = open_capture(capture)
    if cap.ground_truth is None:
        raise ValueError(f"{capture}: no ground truth")
    views = views_from_run(cap, Trajectory.from_groundtruth(cap.ground_truth), "stills")
    roi = part_roi(capture, margin_m)
    step = max(1, int(np.ceil(len(views) / MAX_DEPTH_MAPS)))
    maps = dense.depth_maps(views, roi, dense.DenseConfig(), references=range(0, len(views), step))
    if visibility:
        from vio.model.visibility import visibility_filter

        visibility_filter(views, maps, fuse.TRUNC_VOXELS * ModelOptions().voxel_m)
    volume = fuse.fuse_depth_maps(views, maps, roi, base_band_m=band_m, fill_creases=creases)
    part = mesh.to_support(mesh.mesh_from_volume(volume, frame="world"), roi.world_T_support)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    mesh_io.write_stl(out / "part.stl", part.vertices, part.faces, "vio fusion_truth, mm", scale=1e3)
    return compare(out / "part.stl", Path(capture) / "scene" / "cad.stl", out / "compare")


def main(argv: list[str] | None = None) -> int:
    from vio.errors import VioError

    ap = argparse.ArgumentParser(prog="python -m vio.bench.fusion_truth", description=__doc__.splitlines()[0])
    ap.add_argument("captures", nargs="+", help="simulated captures with stills (they carry ground truth)")
    ap.add_argument("--out", required=True, help="output folder (one subfolder per capture)")
    ap.add_argument("--band-mm", type=float, default=4.0, help="the fusion's base band, mm (0: off)")
    ap.add_argument("--no-visibility", dest="visibility", action="store_false", help="no visibility check")
    ap.add_argument("--no-creases", dest="creases", action="store_false", help="no crease filling in the fusion")
    ap.add_argument("--margin-mm", type=float, default=10.0, help="the part's box grown by this much, mm")
    args = ap.parse_args(argv)
    print("capture | window mm | std mm | p99 mm | completeness")
    for path in args.captures:
        try:
            rep = fusion_truth(path, Path(args.out) / Path(path).name, args.band_mm * 1e-3, args.margin_mm * 1e-3,
                               args.visibility, args.creases)  # fmt: skip
        except (VioError, ValueError, OSError) as exc:
            print(f"{path}: {exc}")
            return 2
        d = rep["deviation"]
        print(f"{Path(path).name} | +{d['max_positive_mm']:.2f} / {d['max_negative_mm']:.2f} | {d['std_mm']:.3f} | "
              f"{d['p99_mm']:.2f} | {100 * rep['completeness']:.1f} %")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
