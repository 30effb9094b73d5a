"""The markdown page of `vio compare` (report.md), from the dict that report.json holds: deviation statistics in
the study's terms (tolerance window, standard deviation), completeness, mesh quality (the study's Table 2), the
registration, and the pictures beside the numbers."""

from __future__ import annotations

_QUALITY_ROWS = (
    ("planar_holes", "planar holes (boundary loops)"),
    ("inverted_triangles", "inverted triangles"),
    ("overlapping_triangles", "overlapping triangles"),
    ("bad_edges", "bad edges (boundary + non-manifold)"),
    ("intersecting_triangles", "intersecting triangles"),
    ("vertices", "vertices"),
    ("faces", "faces"),
    ("watertight", "watertight"),
)


_UNITS_SOURCE = {
    "stated": "as stated",
    "file": "as the file's header says",
    "size": "inferred from its size next to the CAD's",
}
_MEASURED_AT = {
    "surface": "{} points sampled uniformly on its faces",
    "vertices": "its {} vertices",
    "points": "its {} points",
}


def report_markdown(report: dict) -> str:
    """report.md for a `vio compare` result (the dict written to report.json)."""
    d, reg = report["deviation"], report["registration"]
    measured_at = _MEASURED_AT[report["measured_at"]].format(d["count"])
    lo, hi = report["colour_limits_mm"]
    lines = [
        f"# Deviation of `{report['model']}` from its CAD `{report['cad']}`",
        "",
        f"Model: {report['kind']}, units {report['units']} ({_UNITS_SOURCE[report['units_source']]}); deviations "
        f"measured at {measured_at}. Signed distances follow CloudCompare's cloud-to-mesh convention: positive outside "
        "the CAD surface (on its normal side), negative inside. Registration is rigid, without scale, so a scale "
        "error of the model shows here as a tolerance window that grows with the part's size.",
        "",
        *(f"**Warning:** {w}" + "  " for w in report.get("warnings", [])),
        *([""] if report.get("warnings") else []),
        "## Deviation",
        "",
        "| statistic | value |",
        "|---|---|",
        f"| tolerance window | {d['max_positive_mm']:+.3f} / {d['max_negative_mm']:+.3f} mm |",
        f"| mean | {d['mean_mm']:+.3f} mm |",
        f"| standard deviation | {d['std_mm']:.3f} mm |",
        f"| RMS | {d['rms_mm']:.3f} mm |",
        f"| 1st / 99th percentile | {d['p01_mm']:+.3f} / {d['p99_mm']:+.3f} mm |",
        f"| completeness (CAD surface that could be seen within {report['completeness_mm']:g} mm of the model) | "
        f"{100 * report['completeness']:.1f} % |",
        f"| points within 2 mm of the CAD | {100 * d['within_overlap']:.1f} % |",
        f"| points measured | {d['count']} |",
        "",
        "![histogram of signed deviations](histogram.png)",
        "",
        f"Colour scale of the pictures and of `deviation.ply`: diverging RdBu_r from {lo:g} mm (blue, inside) to "
        f"{hi:g} mm (red, outside), saturated beyond.",
        "",
        "![the model coloured by signed deviation](deviation.png)",
        "",
        "## Mesh quality",
        "",
    ]
    if report["quality"] is None:
        lines.append("The model is a point cloud: no mesh quality to report.")
    else:
        lines += ["| check | count |", "|---|---|"]
        lines += [f"| {label} | {report['quality'][key]} |" for key, label in _QUALITY_ROWS]
    lines += [
        "",
        "## Registration",
        "",
        f"Rigid, robust point-to-plane ICP (Huber weights; residuals beyond 6 robust scales of the median ignored): "
        f"RMS {reg['rms_mm']:.4f} mm on the {100 * reg['inlier_fraction']:.1f} % of the points kept, after "
        f"{reg['iterations']} iterations, from coarse candidate {reg['candidate']} of {reg['num_candidates']} "
        f"(box axes / principal axes; RMS of its best 90 % {reg['coarse_rms_mm']:.3f} mm after a short ICP).",
        "",
        "`cad_T_model` (model frame, mm, to CAD frame, mm):",
        "",
        "```",
        *("  ".join(f"{x:12.6f}" for x in row) for row in reg["cad_T_model"]),
        "```",
        "",
        "Timings: " + ", ".join(f"{k[:-2]} {v:.2f} s" for k, v in report["timings_s"].items()) + ".",
        "",
    ]
    return "\n".join(lines)
