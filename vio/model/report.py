"""`vio compare`: register a model (ours, or one exported by other software) to its CAD, measure its signed
deviations and its mesh quality, and write the report, so that models from different tools rank on the same page.

Outputs in `out_dir`: `report.md` (with the pictures), `report.json`, `deviation.ply` (the model in the CAD frame,
mm, coloured by deviation, with a `deviation_mm` scalar), `histogram.png`, `deviation.png`. Everything is computed
before anything is written, each file is written atomically (temporary file, then rename), and `report.json` last.
"""

from __future__ import annotations

import logging
import os
import re
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from vio.atomic import ensure_dir, write_bytes, write_json, write_text
from vio.errors import ModelError, PartError
from vio.model import deviation as dev
from vio.model.closest import build_index
from vio.model.figures import deviation_png, histogram_png
from vio.model.quality import mesh_quality
from vio.model.register import register
from vio.model.report_text import report_markdown
from vio.model.run_trust import run_trust_beside

log = logging.getLogger(__name__)

UNITS_TO_MM = {"mm": 1.0, "m": 1000.0}
MAX_RMS_MM = 2.0  # a registration worse than this is not the model of this CAD
MIN_OVERLAP = 0.2  # nor is a model with less than this share of its points within deviation.OVERLAP_MM of the CAD
_UNITS_RE = (
    re.compile(r"\bunits?\s*[:=]?\s*(millimet(?:re|er)s?|met(?:re|er)s?|mm|m)\b", re.IGNORECASE),
    re.compile(r",\s*(mm|m)\s*$"),  # vio's STL headers: "vio part cube: part frame, mm"
)


def compare(
    model_path: str | os.PathLike[str],
    cad_path: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    units: str | None = None,
    *,
    cad_units: str = "mm",
    sampling: str = "surface",
    samples: int = 200_000,
    seed: int = 0,
    max_rms_mm: float = MAX_RMS_MM,
    min_overlap: float = MIN_OVERLAP,
) -> dict:
    """Compare a model (STL, PLY, OBJ, ... mesh, or a PLY point cloud) with its CAD (STL); returns report.json's dict.

    units: the model file's length unit ("mm" | "m"); None reads it from the file's header when the file says
    so, else infers it from its size next to the CAD's (a factor of 1000 cannot be mistaken). The CAD is in
    `cad_units` and must be a closed mesh with outward normals. A mesh is measured at `samples` points uniform on
    its faces (sampling="surface") or at its vertices ("vertices"). Raises ModelError (one line) for a CAD that is
    not a valid STL, a model without points or with an STL without faces, and a model that does not overlap the
    CAD after registration (trimmed RMS above `max_rms_mm`, or under `min_overlap` of it within 2 mm of the CAD).
    A model from a degraded or failed run (the model.json beside it says so), and anything left out of the model
    on loading, is compared with a warning (the log, report.json `warnings`, the top of report.md).
    """
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    if (units is not None and units not in UNITS_TO_MM) or cad_units not in UNITS_TO_MM:
        raise ModelError(f"unknown units {units!r}; use one of {', '.join(UNITS_TO_MM)}")
    cad = load_cad(cad_path, cad_units)
    trust = run_trust_beside(Path(model_path))
    run_warnings = trust.warnings("the deviations here")
    for w in run_warnings:
        log.warning("%s: %s", model_path, w)
    loaded = load_model(model_path)  # logs its own warnings
    model = loaded.geometry  # signed deviations do not depend on its winding
    is_mesh = isinstance(model, trimesh.Trimesh)
    t_quality = time.perf_counter()
    # in the file's own coordinates: moved into the CAD's frame in floating point, the coplanar faces of a flat base
    # touch and read as crossing (67 "intersecting triangles" on one benchmark model that has none)
    quality = mesh_quality(model.vertices, model.faces).as_dict() if is_mesh else None
    timings["quality_s"] = time.perf_counter() - t_quality
    warnings = [*run_warnings, *loaded.warnings]
    units, units_source = resolve_units(model, cad, units, loaded.file_units, model_path)
    model.apply_scale(UNITS_TO_MM[units])
    rng = np.random.default_rng(seed)
    points = dev.model_points(model, sampling, samples, rng)
    timings["load_s"] = time.perf_counter() - t0 - timings["quality_s"]

    t0 = time.perf_counter()
    cad_index = build_index(cad.vertices, cad.faces)
    try:
        reg = register(points, cad, index=cad_index, rng=rng)
    except ModelError as exc:
        raise ModelError(f"{model_path}: {exc}") from None
    timings["register_s"] = time.perf_counter() - t0
    model.apply_transform(reg.cad_T_model)
    points = points @ reg.cad_T_model[:3, :3].T + reg.cad_T_model[:3, 3]

    t0 = time.perf_counter()
    signed = dev.signed_deviations(points, cad_index)
    stats = dev.deviation_stats(signed)
    check_overlap(model_path, cad_path, reg.rms_mm, stats.within_overlap, max_rms_mm, min_overlap)
    vertex_signed = dev.signed_deviations(model.vertices, cad_index) if is_mesh else signed
    complete = dev.completeness(cad, model, rng=rng)
    timings["deviation_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    limit = dev.colour_limit(stats)
    name = Path(model_path).name
    files = {
        "histogram.png": histogram_png(signed, stats, limit, f"{name} vs {Path(cad_path).name}"),
        "deviation.png": deviation_png(points, signed, limit, f"{name}: signed deviation from the CAD"),
        "deviation.ply": dev.ply_bytes(
            model.vertices,
            vertex_signed,
            dev.deviation_colours(vertex_signed, limit),
            model.faces if is_mesh else None,
            f"vio compare: {name} in the CAD frame, mm; colours RdBu_r saturated at +-{limit:g} mm",
        ),
    }
    timings["figures_s"] = time.perf_counter() - t0
    report = {
        "model": str(model_path),
        "cad": str(cad_path),
        "units": units,
        "units_source": units_source,
        "kind": "mesh" if is_mesh else "point cloud",
        "measured_at": sampling if is_mesh else "points",
        "registration": {
            "cad_T_model": np.round(reg.cad_T_model, 6).tolist(),
            "rms_mm": round(reg.rms_mm, 5),
            "inlier_fraction": round(reg.inlier_fraction, 4),
            "iterations": reg.iterations,
            "candidate": reg.candidate,
            "num_candidates": reg.num_candidates,
            "coarse_rms_mm": round(reg.coarse_rms_mm, 4),
        },
        "deviation": stats.as_dict(),
        "completeness": round(complete, 4),
        "completeness_mm": dev.COMPLETENESS_MM,
        "colour_limits_mm": [-limit, limit],
        "quality": quality,
        "timings_s": {k: round(v, 3) for k, v in timings.items()},
        "files": sorted([*files, "report.md", "report.json"]),
        "run_status": trust.run_status,
        "warnings": warnings,
    }
    out = ensure_dir(out_dir)
    for file_name, data in files.items():
        write_bytes(out / file_name, data)
    write_text(out / "report.md", report_markdown(report))
    write_json(out / "report.json", report)
    log.info("compared %s with %s: window %+.3f/%+.3f mm", name, cad_path, stats.max_positive_mm, stats.max_negative_mm)
    return report


def check_overlap(
    model_path: object,
    cad_path: object,
    rms_mm: float,
    within_overlap: float,
    max_rms_mm: float = MAX_RMS_MM,
    min_overlap: float = MIN_OVERLAP,
) -> None:
    """A ModelError (one line) when a registered model does not overlap its CAD: the registration's RMS (mm) above
    `max_rms_mm`, or under `min_overlap` of its points within `deviation.OVERLAP_MM` of the CAD."""
    if rms_mm > max_rms_mm or within_overlap < min_overlap:
        raise ModelError(
            f"{model_path}: the model does not overlap the CAD {cad_path} after registration (RMS {rms_mm:.2f} mm, "
            f"{100 * within_overlap:.0f} % of it within {dev.OVERLAP_MM:g} mm); wrong part, or wrong --units?"
        )


def load_cad(path: str | os.PathLike[str], units: str) -> trimesh.Trimesh:
    """The CAD as a closed, outward-wound mesh in mm (its own frame)."""
    from vio.sim.parts import read_stl_mesh

    try:
        vertices, faces = read_stl_mesh(path)
    except PartError as exc:
        raise ModelError(f"CAD: {_cad_problem(path) or exc}") from None
    return trimesh.Trimesh(vertices * UNITS_TO_MM[units], faces, process=False)


@dataclass(frozen=True)
class LoadedModel:
    """A model file as read: its geometry in the file's units and frame, and what loading had to leave out."""

    geometry: trimesh.Trimesh | trimesh.PointCloud  # the file's units and frame; only finite coordinates
    file_units: str | None  # the length unit its header states ("mm" | "m"), or None
    warnings: tuple[str, ...]  # one line each: what was left out, or looks wrong (also logged)
    inside_out: bool  # a mesh whose faces are wound so that their normals point inward


def _cad_problem(path: str | os.PathLike[str]) -> str | None:
    """Why an STL that failed as a CAD failed, when the reader's own reason hides it: trimesh drops triangles with
    non-finite vertices and the mesh then reads as merely not watertight; triangles all of zero area likewise."""
    try:
        mesh = trimesh.load(str(path), file_type="stl", process=False)
        tri = np.asarray(mesh.triangles, dtype=np.float64)
    except Exception:  # not an STL at all: the reader's reason stands
        return None
    if len(tri) == 0:
        return None
    bad = ~np.isfinite(tri).all(axis=(1, 2))
    if bad.any():
        return f"{path}: {int(bad.sum())} of {len(tri)} triangles have a non-finite vertex coordinate (NaN or Inf)"
    with np.errstate(all="ignore"):
        area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if not (area2 > 0).any():
        return f"{path}: all {len(tri)} triangles have zero area: the CAD has no surface"
    return None


def load_model(path: str | os.PathLike[str]) -> LoadedModel:
    """Read a model (mesh or point cloud). Triangles with a non-finite vertex and non-finite points are left out with
    a warning; a file with nothing left, a mesh without faces or whose triangles all have zero area is a ModelError
    (one line naming the file). A mesh wound inside out is kept as it is, with a warning and `inside_out` set."""
    path = Path(path)
    try:
        head = path.read_bytes()[:4096]
    except OSError as exc:
        raise ModelError(f"{path}: cannot read the model ({exc.strerror or exc})") from None
    kind = path.suffix.lower().lstrip(".")
    try:  # unprocessed: trimesh's processing drops non-finite triangles without a word
        loaded = trimesh.load(str(path), file_type=kind or None, process=False)
    except Exception as exc:  # trimesh raises many kinds on malformed files
        raise ModelError(f"{path}: not a readable mesh or point cloud ({type(exc).__name__}: {exc})") from None
    if isinstance(loaded, trimesh.Scene):  # several bodies, or nothing at all
        meshes = [g for g in loaded.geometry.values() if isinstance(g, trimesh.Trimesh) and len(g.faces)]
        clouds = [g.vertices for g in loaded.geometry.values() if isinstance(g, trimesh.PointCloud)]
        if meshes:
            loaded = trimesh.util.concatenate(meshes)
        elif clouds:
            loaded = trimesh.PointCloud(np.vstack(clouds))
        else:
            loaded = trimesh.PointCloud(np.zeros((0, 3)))
    if isinstance(loaded, trimesh.Trimesh) and len(loaded.faces) == 0 or len(loaded.vertices) == 0:
        if kind in ("stl", "obj", "off") or len(loaded.vertices) == 0:
            raise ModelError(f"{path}: the {'mesh has no faces' if kind != 'ply' else 'file holds no points'}")
        loaded = trimesh.PointCloud(loaded.vertices)
    warnings: list[str] = []
    if isinstance(loaded, trimesh.Trimesh):
        loaded = _finite_mesh(loaded, path, warnings)
    else:
        loaded = _finite_cloud(loaded, path, warnings)
    inside_out = isinstance(loaded, trimesh.Trimesh) and _inside_out(loaded)
    if inside_out:
        warnings.append(f"{path}: the mesh is wound inside out (its face normals point inward)")
    for w in warnings:
        log.warning(w)
    return LoadedModel(loaded, _header_units(head, kind), tuple(warnings), inside_out)


def _finite_mesh(mesh: trimesh.Trimesh, path: Path, warnings: list[str]) -> trimesh.Trimesh:
    """The mesh without triangles that touch a non-finite vertex (warned), vertices merged; a ModelError when no
    triangle with an area is left."""
    vertices, faces = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)
    outside = (faces < 0) | (faces >= len(vertices))
    if outside.any():
        row = int(np.flatnonzero(outside.any(axis=1))[0])
        raise ModelError(f"{path}: face {row} refers to vertex {faces[row][outside[row]][0]} of {len(vertices)}")
    finite = np.isfinite(vertices).all(axis=1)[faces].all(axis=1)
    if not finite.all():
        if not finite.any():
            raise ModelError(f"{path}: every triangle has a non-finite vertex coordinate (NaN or Inf)")
        warnings.append(
            f"{path}: {int((~finite).sum())} of {len(faces)} triangles have a non-finite vertex coordinate "
            "(NaN or Inf) and are left out"
        )
        faces = faces[finite]
    with np.errstate(all="ignore"):
        tri = vertices[faces]
        area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if not (area2 > 0).any():
        raise ModelError(f"{path}: all {len(faces)} triangles have zero area: the mesh has no surface")
    return trimesh.Trimesh(vertices, faces, process=True)


def _finite_cloud(cloud: trimesh.PointCloud, path: Path, warnings: list[str]) -> trimesh.PointCloud:
    """The point cloud without its non-finite points (warned); a ModelError when none is left."""
    points = np.asarray(cloud.vertices, dtype=np.float64)
    finite = np.isfinite(points).all(axis=1)
    if finite.all():
        return cloud
    if not finite.any():
        raise ModelError(f"{path}: every point has a non-finite coordinate (NaN or Inf)")
    warnings.append(
        f"{path}: {int((~finite).sum())} of {len(points)} points have a non-finite coordinate (NaN or Inf) and are "
        "left out"
    )
    return trimesh.PointCloud(points[finite])


def _inside_out(mesh: trimesh.Trimesh) -> bool:
    """Whether most of the surface faces its centroid: the area-weighted mean of n . (p - c) over the faces is
    negative and at least half their absolute mean (for a closed mesh, a negative volume; open scans of a part seen
    from outside are positive; a flat sheet, near 0, is not called inside out)."""
    with np.errstate(all="ignore"):
        area, centre = np.asarray(mesh.area_faces), np.asarray(mesh.triangles_center, dtype=np.float64)
        middle = (area @ centre) / area.sum()
        weighted = area * np.einsum("ij,ij->i", np.asarray(mesh.face_normals), centre - middle)
        total, magnitude = float(np.sum(weighted)), float(np.sum(np.abs(weighted)))
    return bool(np.isfinite(total) and magnitude > 0 and total < -0.5 * magnitude)


def _header_units(head: bytes, kind: str) -> str | None:
    """The length unit a file's header states ("mm" | "m"), or None."""
    if kind == "stl":
        text = head[:80] if not head.lstrip()[:5].lower() == b"solid" else head.split(b"\n", 1)[0]
    elif kind == "ply":
        text = b"\n".join(line for line in head.split(b"end_header")[0].split(b"\n") if line.startswith(b"comment"))
    else:
        text = b"\n".join(line for line in head.split(b"\n")[:50] if line.startswith(b"#"))
    for line in text.decode("latin-1").splitlines():
        for pattern in _UNITS_RE:
            match = pattern.search(line.strip())
            if match:
                word = match.group(1).lower()
                return "mm" if word.startswith(("mm", "milli")) else "m"
    return None


def resolve_units(model, cad: trimesh.Trimesh, units: str | None, file_units: str | None, path) -> tuple[str, str]:
    """(units, how they were chosen: "stated", "file" or "size")."""
    if units is not None:
        return units, "stated"
    if file_units is not None:
        return file_units, "file"
    ratio = float(np.linalg.norm(np.ptp(model.vertices, axis=0)) / np.linalg.norm(np.ptp(cad.vertices, axis=0)))
    for guess, scale in UNITS_TO_MM.items():
        if 0.2 <= ratio * scale <= 5.0:
            log.warning("%s: units not stated; %s inferred from its size next to the CAD's", path, guess)
            return guess, "size"
    raise ModelError(f"{path}: the file does not state its units and its size does not tell; pass --units mm|m")
