"""`vio eval`: read two trajectory files, score the estimate against ground truth, format a short report."""

from __future__ import annotations

import logging
import os
from pathlib import Path

from vio.atomic import write_json
from vio.errors import CaptureError
from vio.metrics import ALIGNMENTS, evaluate
from vio.trajio import read_trajectory

log = logging.getLogger(__name__)

_ALIGN_NAMES = {
    "se3": "SE3 (Umeyama, rotation + translation)",
    "sim3": "Sim3 (Umeyama with scale)",
    "posyaw": "4-DoF (yaw about gravity + translation)",
    "none": "none",
}


def format_report(metrics: dict, gt_name: str = "ground truth", est_name: str = "estimate") -> str:
    """A short human-readable report of `vio.metrics.evaluate` output (mm, deg, %)."""
    m = metrics
    lines = [
        f"{est_name} vs {gt_name}",
        f"  poses      {m['pairs']} associated by {m.get('sync', 'nearest')} time ({m['est_poses']} estimated, "
        f"{m['gt_poses']} ground truth)",
        f"  coverage   {m['coverage_s']:.2f} s of {m['gt_span_s']:.2f} s ground truth "
        f"({100 * m['coverage_frac']:.1f} %)",
        f"  alignment  {_ALIGN_NAMES[m['align']]}",
        f"  ATE        rmse {1e3 * m['ate_rmse_m']:.2f} mm, mean {1e3 * m['ate_mean_m']:.2f}, "
        f"median {1e3 * m['ate_median_m']:.2f}, max {1e3 * m['ate_max_m']:.2f} mm; "
        f"rotation rmse {m['ate_rot_rmse_deg']:.3f} deg",
        f"  scale      {m['scale']:.5f} (Sim3 correction; the estimate is {abs(m['estimate_scale_error_pct']):.3f} % "
        f"too {'large' if m['estimate_scale_error_pct'] > 0 else 'small'})",
        f"  drift      {m['drift_pct']:.3f} % of {m['path_length_m']:.2f} m path "
        f"(final error {1e3 * m['final_error_m']:.2f} mm)",
    ]
    if m["rpe"]:
        lines.append("  RPE        segment   pairs   trans rmse   trans %   rot rmse")
        for entry in m["rpe"].values():
            lines.append(
                f"             {entry['length_m']:>5g} m  {entry['pairs']:>6d}  {1e3 * entry['trans_rmse_m']:>8.2f} mm"
                f"  {entry['trans_pct']:>7.3f}  {entry['rot_rmse_deg']:>7.3f} deg"
            )
    else:
        lines.append("  RPE        (path too short for the segment lengths)")
    return "\n".join(lines)


def evaluate_files(
    gt_path: str | os.PathLike[str],
    est_path: str | os.PathLike[str],
    align: str = "se3",
    json_out: str | os.PathLike[str] | None = None,
    sync: str = "nearest",
) -> str:
    """Score `est_path` against `gt_path` (TUM or EuRoC CSV each); optionally write the metrics as JSON atomically.

    `sync` is `nearest` (evo's default association) or `interpolate` (ground truth interpolated at the estimate's
    times when it is the denser one). Returns the report text. Raises CaptureError (one line, naming the files)
    on unreadable or non-overlapping input.
    """
    if align not in ALIGNMENTS:
        raise CaptureError(f"unknown alignment {align!r}; choose one of {', '.join(ALIGNMENTS)}")
    gt = read_trajectory(gt_path)
    est = read_trajectory(est_path)
    try:
        metrics = evaluate(gt, est, align=align, sync=sync)
    except CaptureError as exc:
        raise CaptureError(f"{exc} (ground truth {gt_path}, estimate {est_path})") from None
    metrics["gt_path"] = str(gt_path)
    metrics["est_path"] = str(est_path)
    if json_out is not None:
        write_json(json_out, metrics)
        log.info("metrics written to %s", json_out)
    return format_report(metrics, Path(gt_path).name, Path(est_path).name)
