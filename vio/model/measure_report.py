"""The rows of `vio measure`'s inspection report and the report itself: a dimension with its U95 (k = 1.96) from
its standard uncertainties (see `vio.model.measure`), the names of the features it joins, markdown and JSON.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from vio.model.primitives import Fit

K95 = 1.96


@dataclass(frozen=True)
class Dimension:
    """One measured dimension, as a row of an inspection report."""

    name: str  # the feature(s), in the frame of the fits (the CAD's when given), e.g. "+z@76.20 | -z@0.00"
    kind: str  # "distance" | "length" | "radius" | "diameter" | "angle"
    nominal: float | None  # the same fit on the CAD (mm or deg), None without a CAD
    measured: float  # mm, or deg for angles
    deviation: float | None  # measured - nominal, same unit
    U95: float  # expanded uncertainty (k = 1.96), same unit
    components: dict[str, float]  # standard uncertainties u_fit, u_scale, u_model (same unit) and k
    units: str  # "mm" | "deg"
    inliers: int  # model points used by the fit(s)
    rms_mm: float  # RMS residual of the fit(s), mm
    note: str = ""  # e.g. a face pair's non-parallelism, or "base: closure plane"
    flags: tuple[str, ...] = ()  # reasons not to trust the row as stated, e.g. "degraded run"


def dimension(
    name: str,
    kind: str,
    value: float,
    u_fit: float,
    unc: dict[str, float],
    fits: list[Fit],
    nominal: float | None = None,
    note: str = "",
) -> Dimension:
    """A row with U95 from its components (see the module docstring); the RMS and count pool the fits."""
    angle = kind == "angle"
    u = {
        "u_fit": float(u_fit),
        "u_scale": 0.0 if angle else unc["scale_sigma_rel"] * abs(value),
        "u_model": unc["u_model_deg"] if angle else unc["u_model_mm"],
    }
    expanded = K95 * float(np.sqrt(sum(x * x for x in u.values())))
    nominal = None if nominal is None else float(nominal)
    dev = None if nominal is None else float(value - nominal)
    rms = float(np.sqrt(np.mean([f.rms_mm**2 for f in fits])))
    count = sum(f.count for f in fits)
    return Dimension(name, kind, nominal, float(value), dev, expanded, {**u, "k": K95}, "deg" if angle else "mm",
                     count, rms, note)  # fmt: skip


def _axis_name(direction: np.ndarray) -> str:
    i = int(np.argmax(np.abs(direction)))
    if abs(direction[i]) > np.cos(np.radians(1.0)):
        return ("+" if direction[i] > 0 else "-") + "xyz"[i]
    return "n(" + ",".join(f"{c:.2f}" for c in direction) + ")"


def plane_name(fit: Fit) -> str:
    """E.g. "+z@76.20" (outward normal +z, at z = 76.20 mm), or "n(0.71,0.00,0.71)@12.30" (offset along n)."""
    point, n = fit.point_axis()
    name, i = _axis_name(n), int(np.argmax(np.abs(n)))
    return f"{name}@{(point[i] if name[1] in 'xyz' else point @ n) + 0.0:.2f}"


def curved_name(fit: Fit) -> str:
    """E.g. "cylinder along z at x=20.00 y=20.00" (where the axis crosses the plane of the other two axes)."""
    point, axis = fit.point_axis()
    i = int(np.argmax(np.abs(axis)))
    p = point - axis * point[i] / axis[i]
    j, k = [c for c in range(3) if c != i]
    return f"{fit.kind} along {_axis_name(axis).lstrip('+-')} at {'xyz'[j]}={p[j]:.2f} {'xyz'[k]}={p[k]:.2f}"


def report_dict(
    dimensions: list[Dimension],
    notes: tuple[str, ...] = (),
    warnings: tuple[str, ...] = (),
    run_status: str | None = None,
) -> dict:
    """A JSON-serialisable summary: the run's status (None without a run), warnings (one line each), the coverage
    factor, the dimensions (every field, `flags` as a list) and notes."""
    rows = [{**asdict(d), "flags": list(d.flags)} for d in dimensions]
    return {"run_status": run_status, "warnings": list(warnings), "k": K95, "dimensions": rows, "notes": list(notes)}


def inspection_report(
    dimensions: list[Dimension],
    title: str = "Inspection report",
    notes: tuple[str, ...] = (),
    warnings: tuple[str, ...] = (),
) -> str:
    """A markdown inspection report: the warnings first, then one row per dimension with nominal, measured,
    deviation and U95 (a flagged row's note starts with its flags in capitals)."""

    def num(x: float | None, digits: int = 3) -> str:
        return "" if x is None else f"{x:.{digits}f}"

    lines = [f"# {title}", ""]
    lines += [line for w in warnings for line in (f"> **Warning:** {w}", ">")][:-1]
    lines += [""] if warnings else []
    lines += ["| # | feature | kind | nominal | measured | deviation | U95 (k=1.96) | u_fit | "
             "u_scale | u_model | unit | points | RMS mm | note |", "|" + "---|" * 14]  # fmt: skip
    for i, d in enumerate(dimensions, 1):
        c, note = d.components, "; ".join([*(f.upper() for f in d.flags), *([d.note] if d.note else [])])
        row = [str(i), d.name, d.kind, num(d.nominal), num(d.measured), num(d.deviation), num(d.U95),
               num(c["u_fit"], 4), num(c["u_scale"], 4), num(c["u_model"], 4), d.units, str(d.inliers),
               num(d.rms_mm, 4), note]  # fmt: skip
        lines.append("| " + " | ".join(row) + " |")
    lines += ["", "U95 = 1.96 sqrt(u_fit^2 + u_scale^2 + u_model^2): fit residuals, trajectory scale, reconstruction."]
    return "\n".join(lines + [f"- {n}" for n in notes]) + "\n"
