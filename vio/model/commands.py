"""The part-model commands as library functions over files: `measure_file` (what `vio measure` does); `vio model`
is `vio.model.build`, `vio compare` is `vio.model.report.compare`."""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

import numpy as np

from vio.atomic import ensure_dir, write_json, write_text
from vio.errors import ModelError
from vio.model import primitives as prim
from vio.model.measure import measure
from vio.model.measure_report import inspection_report, report_dict
from vio.model.register import register
from vio.model.report import load_cad, load_model, resolve_units
from vio.sim.parts import UNITS_TO_MM

log = logging.getLogger(__name__)

SAMPLES = 200_000  # points sampled on a model mesh for the fits


def scale_sigma_beside(model_path: Path) -> float | None:
    """The run's scale uncertainty recorded in the model.json next to a model written by `vio model`, if any."""
    meta = model_path.with_name("model.json")
    if not meta.is_file():
        return None
    value = json.loads(meta.read_text(encoding="utf-8")).get("scale_sigma_rel")
    return None if value is None else float(value)


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
    report (markdown); with `out_dir` also writes measure.md and measure.json there."""
    model_path = Path(model_path)
    model, file_units = load_model(model_path)
    cad = load_cad(cad_path, "mm") if cad_path is not None else None
    if cad is not None:
        units, _ = resolve_units(model, cad, units, file_units, model_path)
    else:
        units = units or file_units or "mm"
    rng = np.random.default_rng(seed)
    scale_mm = UNITS_TO_MM[units]
    if hasattr(model, "faces") and len(model.faces):
        pts, nrm, _ = prim.sample_surface(np.asarray(model.vertices) * scale_mm, np.asarray(model.faces), SAMPLES, rng)
    else:
        pts, nrm = np.asarray(model.vertices, float) * scale_mm, None
    notes = [f"model {model_path.name}: {len(pts)} points ({units})"]
    if cad is not None:
        reg = register(pts, cad, rng=rng)
        R, t = reg.cad_T_model[:3, :3], reg.cad_T_model[:3, 3]
        pts = pts @ R.T + t
        nrm = None if nrm is None else nrm @ R.T
        notes.append(f"registered to {Path(cad_path).name}: RMS {reg.rms_mm:.3f} mm (rigid, no scale)")
    if scale_sigma_rel is None:
        scale_sigma_rel = scale_sigma_beside(model_path)
        if scale_sigma_rel is None:
            log.warning("no scale uncertainty given or found beside the model; U95 leaves the scale out")
            notes.append("scale uncertainty unknown: not included in U95")
            scale_sigma_rel = 0.0
        else:
            notes.append(f"scale uncertainty {100 * scale_sigma_rel:.3f} % (1 sigma, the run's factor graph)")
    base_closed = (model_path.with_name("model.json")).is_file()  # our models close the base on the support
    dims = measure(pts, nrm, shape, cad, scale_sigma_rel, u_model_mm, base_is_closure=base_closed)
    if not dims:
        raise ModelError(f"{model_path}: no dimension could be measured as a {shape}")
    text = inspection_report(dims, f"Inspection report: {model_path.name}", tuple(notes))
    if out_dir is not None:
        out = ensure_dir(out_dir)
        write_json(out / "measure.json", report_dict(dims, tuple(notes)))
        write_text(out / "measure.md", text)
    return text
