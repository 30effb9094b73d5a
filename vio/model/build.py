"""`vio model`: the part from a run (or from images with known cameras), step by step.

views (vio.model.views) -> support plane and region of interest (isolate) -> multi-view stereo depth maps (dense)
-> depth fusion (fuse) -> watertight mesh (mesh) -> files: `part.stl` (millimetres, the part on its base: support
frame, z up), `part.ply` (the same mesh with grey levels from the images), `dense.ply` (the fused depth points,
world frame, m), `model.json` (parameters, counts, timings, mesh checks, the run's scale uncertainty, warnings).
Every file is written atomically; a model that is not watertight is written but flagged in model.json and the log.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from vio.atomic import ensure_dir, write_json
from vio.errors import ModelError
from vio.model.records import Mesh, Roi, SupportPlane, View

log = logging.getLogger(__name__)

MAX_DEPTH_MAPS = 60  # reference views at most (every k-th still): 60 full-size maps with confidence are 1.4 GB
SPARSE_MIN_HEIGHT_M = 8e-3  # from landmarks, the part is what stands at least this far above the support, and
# more where the table's landmarks scatter more (isolate.haze_height: 17-20 mm on 60 s orbits)


@dataclass(frozen=True)
class ModelOptions:
    """What `vio model` can be told (lengths in m unless stated)."""

    source: str = "auto"  # auto | stills | video: which images of a capture
    max_views: int = 0  # use at most this many views, evenly spread (0: all)
    voxel_m: float = 4e-4  # fusion voxel edge
    margin_m: float = 0.01  # region of interest grown by this much around the part
    roi_world: np.ndarray | None = None  # (2, 3) world min/max corners given by the user (--roi)
    dense_method: str = "sweep"  # sweep | sgbm (vio.model.dense)
    adjust: bool = True  # bundle-adjust the views (vio.model.adjust) before stereo, anchored to their positions
    # ... with features inside the region of interest's window only: faster, but the cameras are posed by the table
    # and the room (seed 105: camera centres 0.74 mm off the truth against 0.09 mm from the whole still): not the
    # default; the whole still's SIFT runs on an image of at most 1.5 MP instead (vio.model.matches)
    adjust_in_roi: bool = False
    seed: int = 0  # RANSAC
    backdrop_below: int = 0  # > 0: image regions at or below this grey level are an empty backdrop (vio.model.fuse)
    visibility: bool = True  # drop the depths other views see through before fusion (vio.model.visibility)
    fill_creases: bool = True  # fill the stereo's holes along convex edges with the two faces' planes (vio.model.fuse)


@dataclass
class ModelResult:
    out: Path
    mesh_world: Mesh
    mesh_support: Mesh
    plane: SupportPlane | None
    roi: Roi
    summary: dict[str, Any] = field(default_factory=dict)


MODEL_FILES = ("model.json", "part.stl", "part.ply", "dense.ply")  # model.json last in, first out


def discard_model(out: Path) -> None:
    """Remove a model's files from `out`, model.json first (a folder without it holds no model, so a killed
    `vio model` mixes nothing old with anything new), and the temporaries an interrupted write left."""
    for name in MODEL_FILES:
        (out / name).unlink(missing_ok=True)
        for tmp in out.glob(f".{name}.*.tmp"):
            tmp.unlink(missing_ok=True)


def _timed(timings: dict[str, float], name: str, t0: float) -> float:
    now = time.perf_counter()
    timings[name] = round(now - t0, 3)
    return now


def _up_hint(views: Sequence[View], points: np.ndarray) -> np.ndarray:
    centres = np.array([v.world_T_cam[:3, 3] for v in views])
    up = centres.mean(axis=0) - np.median(points, axis=0)
    return up / max(np.linalg.norm(up), 1e-12)


def model_from_views(
    views: list[View],
    sparse_world: np.ndarray | None,
    out: str | Path,
    options: ModelOptions = ModelOptions(),
    extra: dict[str, Any] | None = None,
    up_world: np.ndarray | None = None,
) -> ModelResult:
    """Build the part from calibrated views; `sparse_world` (N, 3) m are points that find the support plane and
    the part (a run's landmarks), or None to take them from a first depth pass. `up_world` is the world's up
    (a visual-inertial run's world is gravity-aligned: +z); None guesses it from where the cameras are."""
    from vio.model import dense, fuse, isolate, mesh
    from vio.writers import mesh as mesh_io

    out = ensure_dir(out)
    discard_model(out)
    timings: dict[str, float] = {}
    warnings: list[str] = []
    if (extra or {}).get("run_status") == "degraded":
        reasons = "; ".join((extra or {}).get("run_reasons") or []) or "see its run.json"
        warnings.append(f"the run was degraded ({reasons}): its scale and poses may be worse than its sigma says")
    t0 = time.perf_counter()
    if len(views) < 3:
        raise ModelError(f"{len(views)} view(s): multi-view stereo needs at least 3 images")
    rng = np.random.default_rng(options.seed)
    cfg = dense.DenseConfig(method=options.dense_method)
    sparse_from_run = sparse_world is not None and len(sparse_world) >= 50
    if not sparse_from_run:  # a reduced-resolution pass on a few references, every view a neighbour
        first_cfg = dense.DenseConfig(method=options.dense_method, max_image_pixels=300_000)
        first = dense.depth_maps(views, None, first_cfg, references=range(0, len(views), max(1, len(views) // 8)))
        sparse_world = _depth_points(views, first, 20000, rng)
        t0 = _timed(timings, "first_pass", t0)
    plane = None
    try:
        if sparse_from_run:
            up = _up_hint(views, sparse_world) if up_world is None else np.asarray(up_world, float)
            plane = isolate.support_plane(sparse_world, up, rng)
        else:
            plane = isolate.support_plane_from_depth(sparse_world, views, up_world, rng)
    except ModelError as exc:
        if options.roi_world is None:
            raise
        warnings.append(f"no support plane ({exc}); the model's bottom is not closed")
    # sparse landmarks scatter mm about the table: the part is what stands clear of that (3 robust sigmas of it)
    min_height = SPARSE_MIN_HEIGHT_M if sparse_from_run else 1e-3
    if plane is not None:
        min_height = max(min_height, isolate.haze_height(plane, sparse_world))
    roi = isolate.region_of_interest(plane, views, sparse_world, options.margin_m, options.roi_world, min_height)
    fuse.check_grid(roi, options.voxel_m)  # before the stereo: a region that swallowed the table fails now
    t0 = _timed(timings, "isolate", t0)
    adjust_report = None
    if options.adjust:
        from vio.model.adjust import adjust_views

        views, adjust_report = adjust_views(views, roi if options.adjust_in_roi else None)
        t0 = _timed(timings, "adjust", t0)
    step = max(1, int(np.ceil(len(views) / MAX_DEPTH_MAPS)))  # bounds memory: a 2016x1512 map is 24 MB
    maps = dense.depth_maps(views, roi, cfg, references=range(0, len(views), step))
    t0 = _timed(timings, "dense", t0)
    refit = None
    if plane is not None:  # the base closes on this plane: fitted again on the table's dense depth
        plane, roi, refit = isolate.refine_plane(plane, roi, views, maps, rng)
        if not refit["refined"]:
            log.info("support plane kept from the landmarks: %s", refit["reason"])
    seen = None
    if options.visibility:  # after the plane's refit: on the table's noisy depth (mm) the check would clip one side
        from vio.model.visibility import visibility_filter

        seen = visibility_filter(views, maps, fuse.TRUNC_VOXELS * options.voxel_m)
        t0 = _timed(timings, "visibility", t0)
    volume = fuse.fuse_depth_maps(views, maps, roi, voxel_m=options.voxel_m, backdrop_below=options.backdrop_below,
                                  fill_creases=options.fill_creases)  # fmt: skip
    points, colours = fuse.fused_points(views, maps, volume)
    t0 = _timed(timings, "fuse", t0)
    mesh_world = mesh.mesh_from_volume(volume, frame="world")
    mesh_support = mesh.to_support(mesh_world, roi.world_T_support)
    checks = mesh.mesh_checks(mesh_world)
    t0 = _timed(timings, "mesh", t0)
    if not checks.get("watertight", False):
        warnings.append("the mesh is not watertight; part.stl is not a closed solid")
    mesh_io.write_stl(out / "part.stl", mesh_support.vertices, mesh_support.faces, "vio part model, mm", scale=1e3)
    mesh_io.write_mesh_ply(out / "part.ply", mesh_support.vertices, mesh_support.faces, mesh_support.colours)
    mesh_io.write_points_ply(out / "dense.ply", points, colours)
    _timed(timings, "write", t0)
    summary = {
        "status": "ok" if not warnings else "degraded",
        "files": {"part.stl": "mm, support frame", "part.ply": "m, support frame", "dense.ply": "m, world"},
        "num_views": len(views),
        "num_depth_maps": len(maps),
        "num_dense_points": int(len(points)),
        "voxel_m": options.voxel_m,
        "dense_method": options.dense_method,
        "fill_creases": options.fill_creases,
        "support_plane": None
        if plane is None
        else {"normal": plane.normal.tolist(), "d_m": plane.d_m, "inlier_rms_m": plane.inlier_rms_m, "refit": refit},
        "world_T_support": roi.world_T_support.tolist(),
        "roi_support_m": {"lo": roi.lo.tolist(), "hi": roi.hi.tolist()},
        "mesh": {k: (v.item() if isinstance(v, np.generic) else v) for k, v in checks.items()},
        "base_sigma_mm": None if not (refit or {}).get("refined") else refit["u_base_mm"],
        "adjust": None if adjust_report is None else _plain(adjust_report),
        "visibility": None if seen is None else _plain(seen),
        "timings_s": timings,
        "warnings": warnings,
        **(extra or {}),
    }
    write_json(out / "model.json", summary)
    for w in warnings:
        log.warning(w)
    return ModelResult(out, mesh_world, mesh_support, plane, roi, summary)


def _plain(record: Any) -> dict[str, Any]:
    """A dataclass record as JSON-safe numbers and lists."""
    from dataclasses import asdict

    return {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in asdict(record).items()}


def _depth_points(views: Sequence[View], maps: Sequence[Any], n: int, rng: np.random.Generator) -> np.ndarray:
    """Up to n world points from depth maps (m)."""
    from vio.model.dense_common import depth_points

    pts = [depth_points(views[dm.view], dm) for dm in maps]
    p = np.concatenate(pts) if pts else np.zeros((0, 3))
    return p[rng.choice(len(p), size=min(n, len(p)), replace=False)] if len(p) else p


def model_capture(
    capture: str | Path,
    run_dir: str | Path | None,
    out: str | Path,
    options: ModelOptions = ModelOptions(),
    positions: str | Path | None = None,
) -> ModelResult:
    """The part from a capture and its run (`vio run` first, into `out/run`, when `run_dir` is None; with
    `positions`, a known-positions CSV that run is anchored to, as `vio run --positions`)."""
    from vio.model.views import views_from_run
    from vio.readers import open_capture
    from vio.trajio import read_trajectory

    out = ensure_dir(out)
    discard_model(out)  # before the run it may make: a model killed during that run leaves no old model behind
    t0 = time.perf_counter()
    if run_dir is None:
        from vio.config import load_config
        from vio.pipeline import run_capture

        run_dir = out / "run"
        run_capture(capture, run_dir, load_config(None, ["run.progress=false"]), positions=positions)
    elif positions is not None:
        raise ModelError("--positions anchors the run that `vio model` makes itself: give it to `vio run` instead")
    run_dir = Path(run_dir)
    if not (run_dir / "trajectory.tum").is_file():
        raise ModelError(f"{run_dir}: no trajectory.tum (a `vio run` output folder is needed)")
    run = json.loads((run_dir / "run.json").read_text(encoding="utf-8")) if (run_dir / "run.json").is_file() else {}
    if run.get("status") in ("failed", "running", "interrupted"):
        raise ModelError(f"{run_dir}: the run is {run['status']} (run.json); no model from it")
    cap = open_capture(capture)
    views = views_from_run(cap, read_trajectory(run_dir / "trajectory.tum"), options.source, options.max_views)
    scale = (run.get("scale") or {}).get("sigma_rel")
    sparse = _read_ply_points(run_dir / "landmarks.ply")
    extra = {
        "capture": str(capture),
        "run": str(run_dir),
        "source": "stills" if cap.stills is not None and options.source != "video" else "video",
        "scale_sigma_rel": scale,
        "run_status": run.get("status"),
        "run_reasons": run.get("reasons") or [],
        "views_s": round(time.perf_counter() - t0, 3),
    }
    return model_from_views(views, sparse, out, options, extra, up_world=np.array([0.0, 0.0, 1.0]))


def _read_ply_points(path: Path) -> np.ndarray | None:
    """x y z (m) of a point PLY such as the run's landmarks.ply, or None when missing."""
    if not path.is_file():
        return None
    import trimesh

    return np.asarray(trimesh.load(str(path)).vertices, float).reshape(-1, 3)


def model_from_image_set(
    out: str | Path,
    options: ModelOptions = ModelOptions(),
    middlebury: str | Path | None = None,
    colmap: str | Path | None = None,
    images: str | Path | None = None,
) -> ModelResult:
    """The part from images with known cameras and no IMU: a Middlebury `*_par.txt`, or a COLMAP text model with
    its images folder (metric when the cameras are). Without a run's landmarks, the support plane and the part
    are found from a first depth pass; give `options.roi_world` when the part stands on no plane."""
    from vio.model.views import views_from_colmap, views_from_middlebury

    if middlebury is not None:
        views, source = views_from_middlebury(middlebury), {"middlebury": str(middlebury)}
    elif colmap is not None and images is not None:
        views, source = views_from_colmap(colmap, images), {"colmap": str(colmap), "images": str(images)}
    else:
        raise ModelError("give a Middlebury *_par.txt, or a COLMAP text model with its images folder")
    if options.max_views and len(views) > options.max_views:
        views = [views[i] for i in np.linspace(0, len(views) - 1, options.max_views).round().astype(int)]
    return model_from_views(views, None, out, options, {"source": source, "scale_sigma_rel": None})
