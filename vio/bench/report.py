"""Benchmark outputs: `results.json` (one row per run) and `results.md` (medians per scenario / IMU / method).

Row fields (null where not applicable): `ate_se3_m`, `ate_posyaw_m` (RMSE after SE3 / 4-DoF position+yaw
alignment, m; null for `vision_only`, whose scale is unknown), `ate_sim3_m` and `scale` (Sim3 alignment),
`scale_sigma_rel` (the run's stated 1-sigma relative scale uncertainty, `run.json` `scale.sigma_rel`), `drift_pct`
(final position error as % of the ground-truth path length, after the 4-DoF alignment; Sim3 for `vision_only`;
none for `imu_only`, which starts from the ground truth's initial state),
`rtf` (estimation wall time / capture duration), `latency_ms_p50/p95/max` (per-keyframe update time of online
methods), `peak_rss_mb` (peak resident memory of the run's own process, MiB). A failed run has an `error` field.
"""

from __future__ import annotations

import logging
import math
import statistics
from collections import defaultdict
from pathlib import Path
from typing import Any

from vio.atomic import write_json, write_text
from vio.bench.ranking import headline_key, method_rank

log = logging.getLogger(__name__)

ROW_KEYS = (
    "scenario",
    "seed",
    "imu",
    "method",
    "ate_se3_m",
    "ate_posyaw_m",
    "ate_sim3_m",
    "scale",
    "scale_sigma_rel",
    "drift_pct",
    "rtf",
    "latency_ms_p50",
    "latency_ms_p95",
    "latency_ms_max",
    "peak_rss_mb",
)
METRIC_KEYS = ROW_KEYS[4:]


def empty_row(case: Any, method: str) -> dict[str, Any]:
    """A row with the case's identity and every metric null."""
    row: dict[str, Any] = dict.fromkeys(ROW_KEYS)
    row.update(scenario=case.label, seed=case.seed, imu=case.imu, method=method)
    return row


def _clean(v: Any) -> Any:
    """JSON-safe: NaN/inf become null."""
    return None if isinstance(v, float) and not math.isfinite(v) else v


def _median(values: list[Any]) -> float | None:
    vals = [v for v in values if v is not None and math.isfinite(v)]
    return statistics.median(vals) if vals else None


def _fmt(v: float | None, key: str) -> str:
    if v is None:
        return "-"
    if key.startswith(("ate_", "rpe_")):
        return f"{v * 1000:.1f}" if abs(v) < 1.0 else f"{v:.2f} m"
    if key == "scale":
        return f"{v:.4f}"
    if key == "drift_pct":
        return f"{v:.2f}" if abs(v) < 100 else f"{v:.0f}"
    if key == "rtf":
        return f"{v:.2f}"
    return f"{v:.0f}" if abs(v) >= 10 else f"{v:.1f}"


def median_table(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Medians of every metric per (scenario, imu, method) over seeds, with the run and failure counts."""
    groups: dict[tuple[str, str, str], list[dict[str, Any]]] = defaultdict(list)
    for r in rows:
        groups[(str(r["scenario"]), str(r["imu"]), str(r["method"]))].append(r)
    out = []
    for (scen, imu, meth), rs in sorted(groups.items(), key=lambda kv: (kv[0][0], kv[0][1], method_rank(kv[0][2]))):
        ok = [r for r in rs if "error" not in r]
        entry: dict[str, Any] = {
            "scenario": scen,
            "imu": imu,
            "method": meth,
            "runs": len(rs),
            "failed": len(rs) - len(ok),
        }
        entry.update({k: _median([r.get(k) for r in ok]) for k in METRIC_KEYS})
        out.append(entry)
    return out


def overall_medians(rows: list[dict[str, Any]], key: str | None = None) -> dict[str, float | None]:
    """Median of `key` (default: each method's headline ATE) per method over all successful runs."""
    by: dict[str, list[Any]] = defaultdict(list)
    for r in rows:
        if "error" not in r:
            by[str(r["method"])].append(r.get(key or headline_key(str(r["method"]))))
    return {m: _median(v) for m, v in sorted(by.items(), key=lambda kv: method_rank(kv[0]))}


def paired_ratio(rows: list[dict[str, Any]], num: str, den: str, key: str = "ate_se3_m") -> float | None:
    """Median over captures of key(num) / key(den), pairing the two methods' rows on the same capture."""
    by: dict[tuple, dict[str, float]] = defaultdict(dict)
    for r in rows:
        if "error" not in r and r.get(key) is not None:
            by[(r["scenario"], r["imu"], r["seed"])][r["method"]] = r[key]
    ratios = [d[num] / d[den] for d in by.values() if num in d and den in d and d[den] > 0]
    return statistics.median(ratios) if ratios else None


def markdown(rows: list[dict[str, Any]], title: str = "", wall_s: float | None = None, jobs: int = 0) -> str:
    """The results table: medians per scenario / IMU grade / method, then the headline ratios and failures."""
    cols = [
        ("ATE SE3 mm", "ate_se3_m"),
        ("ATE 4-DoF mm", "ate_posyaw_m"),
        ("ATE Sim3 mm", "ate_sim3_m"),
        ("scale", "scale"),
        ("drift %", "drift_pct"),
        ("RTF", "rtf"),
        ("lat p50 ms", "latency_ms_p50"),
        ("lat p95 ms", "latency_ms_p95"),
        ("lat max ms", "latency_ms_max"),
        ("RSS MiB", "peak_rss_mb"),
    ]
    lines = [f"# {title}" if title else "# vio bench", ""]
    if wall_s is not None:
        lines += [f"{len(rows)} runs in {wall_s / 60:.1f} min with {jobs} parallel jobs.", ""]
    lines += [
        "Medians over seeds. ATE is the position RMSE in mm (m where marked) after the named alignment; drift is the "
        "final position error after the 4-DoF alignment (vision_only: Sim3; imu_only: none, it starts from the true "
        "initial state) as % of path length; RTF is wall time "
        "/ capture duration; latency is the per-keyframe update time.",
        "",
        "| scenario | IMU | method | runs | " + " | ".join(c for c, _ in cols) + " |",
        "|---|---|---|---:|" + "---:|" * len(cols),
    ]
    for e in median_table(rows):
        runs = f"{e['runs'] - e['failed']}/{e['runs']}"
        cells = " | ".join(_fmt(e[k], k) for _, k in cols)
        lines.append(f"| {e['scenario']} | {e['imu']} | {e['method']} | {runs} | {cells} |")
    meds = overall_medians(rows)
    lines += [
        "",
        "Median ATE over all captures (SE3; vision_only Sim3): "
        + ", ".join(f"{m} {_fmt(v, 'ate_')}" for m, v in meds.items()),
    ]
    for num in ("vio", "vio_fixed_lag"):
        ratio = paired_ratio(rows, num, "batch")
        if ratio is not None:
            lines.append(f"Median over captures of ATE({num}) / ATE(batch): {ratio:.2f}")
    failed = [r for r in rows if "error" in r]
    if failed:
        lines += ["", "## Failed runs", ""]
        lines += [f"- {r['scenario']} {r['imu']} seed {r['seed']} {r['method']}: {r['error']}" for r in failed]
    return "\n".join(lines) + "\n"


def collect_rpe(out: Path) -> list[dict[str, Any]]:
    """RPE rows (scenario, imu, seed, method, length, trans_mean_m, rot_mean_deg) from runs/*/*/metrics_*.json.

    RPE is taken under the same alignment as the drift figure (it only matters for the Sim3 scale of vision_only).
    """
    import json

    found = []
    for p in sorted(Path(out).glob("runs/*/*/metrics_*.json")):
        try:
            data = json.loads(p.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            continue
        row, metrics = data.get("row", {}), data.get("metrics", {})
        m = metrics.get("posyaw") or metrics.get("sim3") or {}  # RPE does not depend on a rigid alignment
        for seg in (m.get("rpe") or {}).values():
            found.append(
                {
                    **{k: row.get(k) for k in ("scenario", "imu", "seed", "method")},
                    "length_m": seg["length_m"],
                    "trans_mean_m": seg.get("trans_mean_m"),
                    "rot_mean_deg": seg.get("rot_mean_deg"),
                }
            )
    return found


def rpe_markdown(rpe: list[dict[str, Any]]) -> str:
    """Median RPE translation (mm) and rotation (deg) per IMU grade, method and segment length."""
    if not rpe:
        return ""
    lengths = sorted({r["length_m"] for r in rpe})
    groups: dict[tuple[str, str], dict[float, list[dict[str, Any]]]] = defaultdict(lambda: defaultdict(list))
    for r in rpe:
        groups[(str(r["imu"]), str(r["method"]))][r["length_m"]].append(r)
    head = " | ".join(f"{x:g} m" for x in lengths)
    lines = [
        "",
        "## Relative pose error (median over captures of the mean per segment length: translation mm / rotation deg)",
        "",
        f"| IMU | method | {head} |",
        "|---|---|" + "---:|" * len(lengths),
    ]
    for (imu, meth), by_len in sorted(groups.items(), key=lambda kv: (kv[0][0], method_rank(kv[0][1]))):
        cells = []
        for x in lengths:
            t = _median([r["trans_mean_m"] for r in by_len.get(x, [])])
            a = _median([r["rot_mean_deg"] for r in by_len.get(x, [])])
            cells.append("-" if t is None else f"{_fmt(t, 'rpe_')} / {a:.2f}")
        lines.append(f"| {imu} | {meth} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _spread(values: list[Any], fmt: str = "{:.2f}") -> str:
    """`median (min-max)` of the finite values, or `-`."""
    vals = [float(v) for v in values if v is not None and math.isfinite(float(v))]
    if not vals:
        return "-"
    med = fmt.format(statistics.median(vals))
    return med if len(vals) == 1 else f"{med} ({fmt.format(min(vals))}-{fmt.format(max(vals))})"


def model_markdown(rows: list[dict[str, Any]]) -> str:
    """The part-model rows (method kind `model`): one line per run, then medians with their range per part and
    method. Dimension errors are |measured - nominal| of every face-to-face distance the measure step found."""
    runs = [r for r in rows if "part" in r and "error" not in r]
    if not runs:
        return ""
    lines = [
        "",
        "## Part model (run, model, measure, compare against the CAD)",
        "",
        "| part | method | seed | ATE mm | scale err % | scale sigma % | dimensions mm (measured / U95) | "
        "max abs err mm | within U95 | window mm | std mm | completeness % | watertight | model s | model MiB |",
        "|---|---|---:|---:|---:|---:|---|---:|---:|---|---:|---:|---|---:|---:|",
    ]
    for r in sorted(runs, key=lambda r: (r["part"], method_rank(str(r["method"])), r["seed"])):
        dists = [d for d in r.get("dims") or [] if d.get("kind") == "distance"]
        dims = ", ".join(f"{d['measured']:.3f}/{d['U95']:.2f}" for d in dists)
        scale_err = None if r.get("scale") is None else 100 * (1.0 / r["scale"] - 1.0)
        sigma = None if r.get("scale_sigma_rel") is None else 100 * r["scale_sigma_rel"]
        lines.append(
            f"| {r['part']} | {r['method']} | {r['seed']} | {_fmt(r.get('ate_se3_m'), 'ate_')} | "
            + ("-" if scale_err is None else f"{scale_err:+.3f}")
            + f" | {'-' if sigma is None else f'{sigma:.3f}'} | {dims} | "
            f"{_fmt_mm(r.get('dim_abs_err_max_mm'))} | {r.get('dims_within_u95')} | "
            f"+{_fmt_mm(r.get('dev_max_pos_mm'))}/{_fmt_mm(r.get('dev_max_neg_mm'))} | {_fmt_mm(r.get('dev_std_mm'))} "
            f"| {_fmt_mm(None if r.get('completeness') is None else 100 * r['completeness'], 1)} | "
            f"{r.get('watertight')} | {_fmt_mm(r.get('model_s'), 0)} | {_fmt_mm(r.get('model_peak_rss_mb'), 0)} |"
        )
    groups: dict[tuple[str, str], list[dict[str, Any]]] = defaultdict(list)
    for r in runs:
        groups[(str(r["part"]), str(r["method"]))].append(r)
    lines += [
        "",
        "Median (min-max) over seeds:",
        "",
        "| part | method | runs | median abs dimension error mm | max abs dimension error mm | dimensions within U95 "
        "| window + mm | window - mm | std mm | completeness % | model s | model MiB |",
        "|---|---|---:|---|---|---:|---|---|---|---|---|---|",
    ]
    for (part, meth), rs in sorted(groups.items(), key=lambda kv: (kv[0][0], method_rank(kv[0][1]))):
        n_in = sum(int(str(r.get("dims_within_u95") or "0/0").split("/")[0]) for r in rs)
        n_all = sum(int(str(r.get("dims_within_u95") or "0/0").split("/")[1]) for r in rs)
        total = sum(1 for r in rows if r.get("part") == part and r.get("method") == meth)
        lines.append(
            f"| {part} | {meth} | {len(rs)}/{total} | {_spread([r.get('dim_abs_err_med_mm') for r in rs], '{:.3f}')} "
            f"| {_spread([r.get('dim_abs_err_max_mm') for r in rs], '{:.3f}')} | {n_in}/{n_all} "
            f"| {_spread([r.get('dev_max_pos_mm') for r in rs])} | {_spread([r.get('dev_max_neg_mm') for r in rs])} "
            f"| {_spread([r.get('dev_std_mm') for r in rs], '{:.3f}')} "
            f"| {_spread([100 * r['completeness'] for r in rs if r.get('completeness') is not None], '{:.1f}')} "
            f"| {_spread([r.get('model_s') for r in rs], '{:.0f}')} "
            f"| {_spread([r.get('model_peak_rss_mb') for r in rs], '{:.0f}')} |"
        )
    return "\n".join(lines) + "\n"


def _meta_line(meta: dict[str, Any]) -> str:
    """Where the suite ran, and what was resumed, retried or failed."""
    line = f"Scheduler: {meta['scheduler']} ({meta['workers']} workers); {meta['jobs']} jobs"
    extra = [f"{meta[k]} {k}" for k in ("resumed", "retried", "failed") if meta.get(k)]
    line += f" ({', '.join(extra)})" if extra else ""
    if meta.get("resumed"):
        line += f"; this session ran {meta['jobs'] - meta['resumed']} of them in {meta['wall_s'] / 60:.1f} min"
    return "\n" + line + ".\n"


def _fmt_mm(v: float | None, digits: int = 2) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def write_reports(
    suite: Any,
    rows: list[dict[str, Any]],
    out: Path,
    wall_s: float | None = None,
    jobs: int = 0,
    meta: dict[str, Any] | None = None,
    job_records: list[dict[str, Any]] | None = None,
) -> None:
    """results.json (rows, statistics, job records, `bench` facts), results.md and (unless the suite says not to)
    plots/ under `out`."""
    from vio.bench.stats import bench_stats, stats_markdown

    clean = [{k: _clean(v) for k, v in r.items()} for r in rows]
    stats = bench_stats(clean)
    data: dict[str, Any] = {"runs": clean, "stats": stats}
    if job_records is not None:
        data["jobs"] = job_records
    if meta is not None:
        data["bench"] = meta
    write_json(out / "results.json", data)
    resumed = bool(meta and meta.get("resumed"))  # this session's wall time is not the suite's: say so below
    text = markdown(clean, f"vio bench: {suite.name} suite", None if resumed else wall_s, jobs)
    if meta is not None:
        text += _meta_line(meta)
    text += stats_markdown(stats) + rpe_markdown(collect_rpe(out))
    text += model_markdown(clean)
    write_text(out / "results.md", text)
    if getattr(suite, "plots", True):
        from vio.bench.plots import make_plots

        try:
            make_plots(suite, clean, out)
        except Exception as exc:  # noqa: BLE001 - a plotting problem must not lose the numbers
            log.warning("bench: plots failed: %s: %s", exc.__class__.__name__, exc)
