"""The part-model commands as library functions over files: `measure_file` (what `vio measure` does); `vio model`
is `vio.model.build`, `vio compare` is `vio.model.report.compare`."""

from __future__ import annotations

import logging
import os
from dataclasses import replace
from pathlib import Path

import numpy as np

from vio.atomic import ensure_dir, write_json, write_text
from vio.errors import ModelError
from vio.model import primitives as prim
from vio.model.closest import build_index
from vio.model.deviation import OVERLAP_MM, signed_deviations
from vio.model.measure import measure
from vio.model.measure_report import inspection_report, report_dict
from vio.model.register import register
from vio.model.report import check_overlap, load_cad, load_model, resolve_units
from vio.model.run_trust import run_trust_beside
from vio.sim.parts import UNITS_TO_MM

log = logging.getLogger(__name__)

SAMPLES = 200_000  # points sampled on a model mesh for the fits
OVERLAP_POINTS = 20_000  # of them, checked for overlap with the CAD after registration


def measure_file(
    model_path: str | os.PathLike[str],
    shape: str = "auto",
    cad_path: str | os.PathLike[str] | None = None,
    out_dir: str | os.PathLike[str] | None = None,
    units: str | None = None,
    scale_sigma_rel: float | None = None,
    u_model_mm: float = 0.0,
    seed: int = 0,
) -> str:
    """Measure a model file (mesh or point cloud): with a CAD, registered to it first (rigid, no scale) so the
    CAD says what to measure and the nominals. The scale uncertainty is `scale_sigma_rel`, else the one in the
    model.json beside the model (from the run's factor graph), else 0 with a warning. Returns the inspection
    report (markdown); with `out_dir` also writes measure.md and then measure.json there.

    The run's health comes from that model.json too: a `failed` run (or one that never finished) is refused
    (ModelError, nothing written); from a `degraded` one every dimension is flagged, with a warning at the top of
    the report and in the log."""
    model_path = Path(model_path)
    for what, value in (("relative scale sigma", scale_sigma_rel), ("model uncertainty u_model_mm", u_model_mm)):
        if value is not None and not (np.isfinite(value) and value >= 0.0):
            raise ModelError(f"the {what} must be a finite number >= 0, not {value}")
    trust = run_trust_beside(model_path)
    if trust.untrusted:
        raise ModelError(f"{model_path}: the run it was built from {trust.state()} ({trust.why()}); not measured")
    warnings = list(trust.warnings("every dimension here"))
    flags = ("degraded run",) if trust.run_status == "degraded" else ()
    for w in warnings:
        log.warning("%s: %s", model_path, w)
    loaded = load_model(model_path)  # logs its own warnings
    model = loaded.geometry
    warnings += loaded.warnings
    if loaded.inside_out:  # the fits take face normals as outward
        model.invert()
        warnings[-1] += "; its normals are turned outward for the fits"
    cad = load_cad(cad_path, "mm") if cad_path is not None else None
    if cad is not None:
        units, _ = resolve_units(model, cad, units, loaded.file_units, model_path)
    else:
        units = units or loaded.file_units or "mm"
    rng = np.random.default_rng(seed)
    scale_mm = UNITS_TO_MM[units]
    if hasattr(model, "faces") and len(model.faces):
        pts, nrm, _ = prim.sample_surface(np.asarray(model.vertices) * scale_mm, np.asarray(model.faces), SAMPLES, rng)
    else:
        pts, nrm = np.asarray(model.vertices, float) * scale_mm, None
    notes = [f"model {model_path.name}: {len(pts)} points ({units})"]
    if cad is not None:
        index = build_index(cad.vertices, cad.faces)
        try:
            reg = register(pts, cad, index=index, rng=rng)
        except ModelError as exc:
            raise ModelError(f"{model_path}: {exc}") from None
        R, t = reg.cad_T_model[:3, :3], reg.cad_T_model[:3, 3]
        pts = pts @ R.T + t
        subset = pts[rng.choice(len(pts), min(len(pts), OVERLAP_POINTS), replace=False)]
        within = float(np.mean(np.abs(signed_deviations(subset, index)) <= OVERLAP_MM))
        check_overlap(model_path, cad_path, reg.rms_mm, within)  # a wrong part is not measured against this CAD
        nrm = None if nrm is None else nrm @ R.T
        notes.append(f"registered to {Path(cad_path).name}: RMS {reg.rms_mm:.3f} mm (rigid, no scale)")
    if scale_sigma_rel is None:
        scale_sigma_rel = trust.scale_sigma_rel
        if scale_sigma_rel is None:
            log.warning("no scale uncertainty given or found beside the model; U95 leaves the scale out")
            notes.append("scale uncertainty unknown: not included in U95")
            scale_sigma_rel = 0.0
        else:
            notes.append(f"scale uncertainty {100 * scale_sigma_rel:.3f} % (1 sigma, the run's factor graph)")
    base_closed = (model_path.with_name("model.json")).is_file()  # our models close the base on the support
    base_sigma = trust.base_sigma_mm or 0.0
    if base_closed:
        notes.append(
            "base: unknown uncertainty of the support plane it closes on (not in U95)"
            if trust.base_sigma_mm is None
            else f"base: closed on the support plane, +-{base_sigma:.3f} mm (1 sigma, in U95 of the dimensions to it)"
        )
    try:
        dims = measure(
            pts, nrm, shape, cad, scale_sigma_rel, u_model_mm, base_is_closure=base_closed, u_base_mm=base_sigma
        )
    except ModelError as exc:
        raise ModelError(f"{model_path}: {exc}") from None
    if not dims:
        raise ModelError(f"{model_path}: no dimension could be measured as a {shape}")
    dims = [replace(d, flags=flags) for d in dims]
    title = f"Inspection report: {model_path.name}"
    text = inspection_report(dims, title, tuple(notes), tuple(warnings))
    if out_dir is not None:
        out = ensure_dir(out_dir)
        write_text(out / "measure.md", text)
        write_json(out / "measure.json", report_dict(dims, tuple(notes), tuple(warnings), trust.run_status))
    return text
