"""The stereo's depth maps against the true depth, by distance to the part's edges in the image.

The stills of a simulated capture are posed by its ground truth; every k-th still (as `vio model` picks its
references) gets a depth map from the plane sweep (`vio.model.dense`, the part's box grown by `--margin-mm` as the
region, as `vio.bench.fusion_truth` does); `--views` of them are compared with the true depth, the capture's CAD
placed by `scene/part_pose.yaml` and the plane of its base (the table) ray-cast through every pixel (Embree). A
pixel's distance to an edge is its image distance to the nearest silhouette of the part or crease between two of
its faces (normals more than 8 deg apart). Printed per band of that distance: the share of the part's pixels
with a depth, the median and 99th percentile of |error|, the share more than 1 mm off; then the pixels within 4 px
of a silhouette (nearer than to any crease) and of a crease, with the share of their depths more than 1 mm behind
and in front of the truth. It showed that a tenth of the depths found near creases lie more than 1 mm behind the
surface (docs/BENCHMARKS.md, "What sets the window with true poses").

    python -m vio.bench.depth_truth CAPTURE [--views 6] [--margin-mm 10] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from vio.model.records import View
from vio.sim.part_render import PartSurface
from vio.sim.parts import Part
from vio.sim.scene import PlacedPart

BANDS_PX = (0.0, 2.0, 4.0, 8.0, 16.0, np.inf)  # distance to the nearest edge, px
NEAR_EDGE_PX = 4.0  # "near" a silhouette or a crease
OFF_M = 1e-3  # a depth this far from the truth is counted as off
_CREASE_COS = 0.99  # neighbouring pixels whose normals are further apart than this straddle a crease (8 deg)


def part_surface(placed: PlacedPart) -> PartSurface:
    """The placed part as the simulator ray-casts it, without its speckle (nothing to shade here)."""
    return PartSurface(replace(placed, surface="plain"), 0)


def true_depth(surface: PartSurface, view: View) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(z-depth (H, W) m, part mask (H, W), unit normals (H, W, 3) of the part's faces, zero off the part) of `view`:
    the part of `surface` (`part_surface`), and the plane z = 0 of the part frame (its base's table); inf where a
    ray meets neither."""
    placed = surface.placed
    w, h = view.size
    u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    K = np.asarray(view.K, float)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1).reshape(-1, 3)
    R, t = view.world_T_cam[:3, :3], view.world_T_cam[:3, 3]
    d = rays @ R.T  # world direction per pixel, z-component 1 in the camera: ray parameter = z-depth
    t_part, prim = surface.intersect(t, d, np.full(len(d), np.inf))
    part = prim >= 0
    up, base = placed.world_T_part[:3, 2], placed.world_T_part[:3, 3]
    along = d @ up
    with np.errstate(divide="ignore", invalid="ignore"):
        t_plane = np.where(along < 0, (base - t) @ up / along, np.inf)
    z = np.where(part, t_part, np.where(t_plane > 0, t_plane, np.inf))
    normals = np.where(part[:, None], surface.normals[np.maximum(prim, 0)], 0.0)
    return z.reshape(h, w), part.reshape(h, w), normals.reshape(h, w, 3)


def edge_distance(part: np.ndarray, normals: np.ndarray, which: str = "all") -> np.ndarray:
    """(H, W) distance (px) of each pixel to the nearest pixel pair that straddles a silhouette (`which` "sil"),
    a crease ("crease") or either ("all")."""
    h, w = part.shape
    edge = np.zeros((h, w), bool)
    for dy, dx in ((0, 1), (1, 0)):
        a, b = (slice(0, h - dy), slice(0, w - dx)), (slice(dy, h), slice(dx, w))
        sil = part[a] != part[b]
        crease = (np.einsum("ijk,ijk->ij", normals[a], normals[b]) < _CREASE_COS) & ~sil
        cut = {"sil": sil, "crease": crease, "all": sil | crease}[which]
        edge[a] |= cut
        edge[b] |= cut
    if not edge.any():
        return np.full((h, w), np.inf, np.float32)
    return cv2.distanceTransform((~edge).astype(np.uint8), cv2.DIST_L2, 5)


class DepthErrors:
    """Counts over views: per band of distance to an edge, and near silhouettes and creases."""

    def __init__(self) -> None:
        n = len(BANDS_PX) - 1
        self.pixels, self.found, self.off = np.zeros(n, int), np.zeros(n, int), np.zeros(n, int)
        self.errors: list[list[np.ndarray]] = [[] for _ in range(n)]
        self.near = {k: np.zeros(4, int) for k in ("silhouette", "crease")}  # pixels, found, behind, in front

    def add(self, depth: np.ndarray, z: np.ndarray, part: np.ndarray, normals: np.ndarray) -> None:
        """One view: its depth map (NaN unknown) against the true depth of `true_depth`."""
        found = np.isfinite(depth)
        err = np.where(found & part, depth - z, np.nan)
        d_sil, d_crease = edge_distance(part, normals, "sil"), edge_distance(part, normals, "crease")
        dist = np.minimum(d_sil, d_crease)  # to the nearest edge of either kind
        for k in range(len(BANDS_PX) - 1):
            band = part & (dist >= BANDS_PX[k]) & (dist < BANDS_PX[k + 1])
            e = err[band & found]
            self.pixels[k] += int(band.sum())
            self.found[k] += len(e)
            self.off[k] += int((np.abs(e) > OFF_M).sum())
            self.errors[k].append(np.abs(e))
        for name, d, other in (("silhouette", d_sil, d_crease), ("crease", d_crease, d_sil)):
            near = part & (d < NEAR_EDGE_PX) & (d < other)  # nearer to an edge of this kind than of the other
            e = err[near & found]
            self.near[name] += [int(near.sum()), len(e), int((e > OFF_M).sum()), int((e < -OFF_M).sum())]

    def table(self) -> dict:
        bands = []
        for k in range(len(BANDS_PX) - 1):
            e = np.concatenate(self.errors[k]) if self.errors[k] else np.zeros(0)
            bands.append({
                "from_px": BANDS_PX[k],
                "to_px": BANDS_PX[k + 1],
                "pixels": int(self.pixels[k]),
                "coverage": float(self.found[k] / max(self.pixels[k], 1)),
                "median_abs_error_mm": float(np.median(e) * 1e3) if len(e) else None,
                "p99_abs_error_mm": float(np.percentile(e, 99) * 1e3) if len(e) else None,
                "off_1mm": float(self.off[k] / max(self.found[k], 1)),
            })  # fmt: skip
        near = {
            name: {"pixels": int(c[0]), "coverage": float(c[1] / max(c[0], 1)),
                   "behind_1mm": float(c[2] / max(c[1], 1)), "in_front_1mm": float(c[3] / max(c[1], 1))}
            for name, c in self.near.items()
        }  # fmt: skip
        return {"bands": bands, "near_edges": near}


def depth_truth(capture: str | Path, num_views: int = 6, margin_m: float = 0.01) -> dict:
    """The table of `DepthErrors` for `num_views` of the capture's reference stills (evenly spread)."""
    import yaml

    from vio.bench.fusion_truth import part_roi
    from vio.model import dense
    from vio.model.build import MAX_DEPTH_MAPS
    from vio.model.views import views_from_run
    from vio.readers import open_capture
    from vio.sim.parts import read_stl_mesh
    from vio.trajio import Trajectory

    cap = open_capture(capture)
    if cap.ground_truth is None:
        raise ValueError(f"{capture}: no ground truth")
    views = views_from_run(cap, Trajectory.from_groundtruth(cap.ground_truth), "stills")
    step = max(1, int(np.ceil(len(views) / MAX_DEPTH_MAPS)))
    refs = list(range(0, len(views), step))
    refs = refs[:: max(1, len(refs) // max(num_views, 1))][:num_views]
    root = Path(capture) / "scene"
    vertices_mm, faces = read_stl_mesh(root / "cad.stl")  # the part frame as simulated
    pose = yaml.safe_load((root / "part_pose.yaml").read_text(encoding="utf-8"))
    surface = part_surface(PlacedPart(Part("cad", vertices_mm, faces, "", {}), np.asarray(pose["world_T_part"], float)))
    errors = DepthErrors()
    for dm in dense.depth_maps(views, part_roi(capture, margin_m), dense.DenseConfig(), references=refs):
        z, part, normals = true_depth(surface, views[dm.view])
        errors.add(dm.depth_m, z, part, normals)
    return {"capture": str(capture), "views": refs, **errors.table()}


def main(argv: list[str] | None = None) -> int:
    from vio.errors import VioError

    ap = argparse.ArgumentParser(prog="python -m vio.bench.depth_truth", description=__doc__.splitlines()[0])
    ap.add_argument("capture", help="a simulated capture with stills (it carries ground truth and its CAD)")
    ap.add_argument("--views", type=int, default=6, help="reference stills compared (evenly spread)")
    ap.add_argument("--margin-mm", type=float, default=10.0, help="the part's box grown by this much, mm")
    ap.add_argument("--json", help="also write the table as JSON here")
    args = ap.parse_args(argv)
    try:
        rep = depth_truth(args.capture, args.views, args.margin_mm * 1e-3)
    except (VioError, ValueError, OSError) as exc:
        print(f"{args.capture}: {exc}")
        return 2
    print("distance to an edge | part pixels with a depth | median |error| | p99 |error| | more than 1 mm off")
    for b in rep["bands"]:
        med, p99 = b["median_abs_error_mm"], b["p99_abs_error_mm"]
        print(f"{b['from_px']:g}-{b['to_px']:g} px | {100 * b['coverage']:.1f} % of {b['pixels']} | "
              f"{'-' if med is None else f'{med:.3f} mm'} | {'-' if p99 is None else f'{p99:.2f} mm'} | "
              f"{100 * b['off_1mm']:.2f} %")  # fmt: skip
    for name, c in rep["near_edges"].items():
        behind, front = 100 * c["behind_1mm"], 100 * c["in_front_1mm"]
        print(f"within {NEAR_EDGE_PX:g} px of a {name}: {100 * c['coverage']:.1f} % of {c['pixels']} with a depth, "
              f"{behind:.1f} % of them more than 1 mm behind, {front:.1f} % in front")  # fmt: skip
    if args.json:
        from vio.atomic import atomic_open

        with atomic_open(args.json) as f:
            json.dump(rep, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
