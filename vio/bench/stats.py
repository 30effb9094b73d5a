"""Statistics a reader can trust: medians with 95 % bootstrap intervals, ratios to the batch optimum, and paired
comparisons between methods on the same captures.

The interval of a median is a percentile bootstrap: resample the n values with replacement `N_RESAMPLES` times,
take each resample's median, and report the 2.5th and 97.5th percentiles of those. Each interval's generator is
seeded from the name of what it describes (`seed_for`), so the same rows always give the same intervals. With
one value there is no interval; with two or three it spans nearly the whole data (a bootstrap cannot know more
than the sample): the number of captures is always printed beside it.

Metrics: `ate_m` (the method's headline ATE: SE3, Sim3 for vision_only; m), `scale_err_pct` (100 (1/s - 1) with
s the Sim3 scale that maps the estimate onto the truth: positive when the estimate is too large),
`scale_sigma_pct` (the run's stated 1-sigma scale uncertainty, %), `drift_pct`; and `scale_within_95`, how many
runs' scale error lies within 1.96 of their stated sigmas (the stated uncertainty's honesty).
"""

from __future__ import annotations

import math
import zlib
from collections import defaultdict
from itertools import combinations
from typing import Any

import numpy as np

from vio.bench.ranking import has_metric_scale, headline_key, method_rank

N_RESAMPLES = 4000
LEVEL = 0.95
METRICS = ("ate_m", "scale_err_pct", "scale_sigma_pct", "drift_pct")
Z95 = 1.959964  # two-sided 95 % of a normal distribution


def seed_for(label: str) -> int:
    """A generator seed from a text label (stable across runs, machines and Python versions)."""
    return zlib.crc32(label.encode("utf-8"))


def median_ci(values: list[float], seed: int, level: float = LEVEL, n_resamples: int = N_RESAMPLES) -> dict[str, Any]:
    """`{"n", "median", "lo", "hi"}`: the median of the finite values and its percentile-bootstrap interval
    (lo/hi None with fewer than two values; median None with none)."""
    x = np.asarray([v for v in values if v is not None and math.isfinite(v)], float)
    n = int(x.size)
    if n == 0:
        return {"n": 0, "median": None, "lo": None, "hi": None}
    med = float(np.median(x))
    if n < 2:
        return {"n": n, "median": med, "lo": None, "hi": None}
    rng = np.random.default_rng(seed)
    meds = np.median(x[rng.integers(0, n, size=(n_resamples, n))], axis=1)
    alpha = 100.0 * (1.0 - level) / 2.0
    lo, hi = np.percentile(meds, [alpha, 100.0 - alpha])
    return {"n": n, "median": med, "lo": float(lo), "hi": float(hi)}


def _metric(row: dict[str, Any], metric: str) -> float | None:
    if metric == "ate_m":
        return row.get(headline_key(str(row["method"])))
    if metric == "scale_err_pct":
        if not has_metric_scale(str(row["method"])):
            return None
        s = row.get("scale")
        return None if s is None or s <= 0 else 100.0 * (1.0 / s - 1.0)
    if metric == "scale_sigma_pct":
        sigma = row.get("scale_sigma_rel")
        return None if sigma is None else 100.0 * sigma
    return row.get(metric)


def scale_coverage(rows: list[dict[str, Any]]) -> dict[str, int]:
    """How many runs' scale error lies within the run's own stated 95 % interval (|1/s - 1| <= 1.96 sigma_rel):
    `{"within": k, "n": runs that state a sigma}`. About 95 % of n when the stated sigma is honest."""
    pairs = [(_metric(r, "scale_err_pct"), _metric(r, "scale_sigma_pct")) for r in rows]
    pairs = [(e, s) for e, s in pairs if e is not None and s is not None and math.isfinite(e) and math.isfinite(s)]
    return {"within": sum(abs(e) <= Z95 * s for e, s in pairs), "n": len(pairs)}


def _ok(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [r for r in rows if "error" not in r]


def group_stats(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per (scenario, IMU grade, method), then per method over all captures (scenario and imu `all`): the
    number of runs and each metric's median with its interval."""
    groups: dict[tuple[str, str, str], list[dict[str, Any]]] = defaultdict(list)
    for r in _ok(rows):
        groups[(str(r["scenario"]), str(r["imu"]), str(r["method"]))].append(r)
        groups[("all", "all", str(r["method"]))].append(r)

    def order(k: tuple[str, str, str]) -> tuple:
        return (k[0] == "all", k[0], k[1], method_rank(k[2]))

    out = []
    for key in sorted(groups, key=order):
        entry: dict[str, Any] = {"scenario": key[0], "imu": key[1], "method": key[2], "runs": len(groups[key])}
        for m in METRICS:
            entry[m] = median_ci([_metric(r, m) for r in groups[key]], seed_for("|".join((*key, m))))
        entry["scale_within_95"] = scale_coverage(groups[key])
        out.append(entry)
    return out


def _paired(rows: list[dict[str, Any]], a: str, b: str, key: str) -> list[tuple[float, float]]:
    """(value of a, value of b) per capture (scenario, IMU grade, seed) where both ran."""
    by: dict[tuple, dict[str, float]] = defaultdict(dict)
    for r in _ok(rows):
        v = r.get(key)
        if v is not None and math.isfinite(v):
            by[(r["scenario"], r["imu"], r["seed"])][str(r["method"])] = float(v)
    return [(d[a], d[b]) for _, d in sorted(by.items(), key=lambda kv: str(kv[0])) if a in d and b in d]


def compare(rows: list[dict[str, Any]], a: str, b: str, key: str | None = None) -> dict[str, Any] | None:
    """Method `a` against `b` on the same captures: the median over captures of key(a)/key(b) with its interval,
    how often a was lower, and the two-sided sign-test p-value (ties left out). Key: both methods' headline ATE
    when they share it, else the Sim3 ATE. None when no capture has both."""
    from scipy.stats import binomtest

    if key is None:
        ka, kb = headline_key(a), headline_key(b)
        key = ka if ka == kb else "ate_sim3_m"
    pairs = [(x, y) for x, y in _paired(rows, a, b, key) if y > 0]
    if not pairs:
        return None
    ratio = median_ci([x / y for x, y in pairs], seed_for(f"{a}/{b}|{key}"))
    lower = sum(x < y for x, y in pairs)
    higher = sum(x > y for x, y in pairs)
    p = float(binomtest(lower, lower + higher, 0.5).pvalue) if lower + higher else None
    return {"a": a, "b": b, "key": key, "n": len(pairs), "ratio": ratio, "a_lower": lower, "sign_test_p": p}


def comparisons(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """`ratio_to_batch` (each method's ATE over the batch optimum's, same captures) and `paired` (every pair of
    methods), for results.json."""
    methods = sorted({str(r["method"]) for r in _ok(rows)}, key=method_rank)
    to_batch = [c for m in methods if m != "batch" and (c := compare(rows, m, "batch", "ate_se3_m")) is not None]
    paired = [c for a, b in combinations(methods, 2) if (c := compare(rows, a, b)) is not None]
    return {"ratio_to_batch": to_batch, "paired": paired}


def bench_stats(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Everything this module computes, JSON-ready: `groups`, `ratio_to_batch`, `paired`, and the method."""
    return {
        "method": f"median; {LEVEL:.0%} percentile bootstrap, {N_RESAMPLES} resamples, seeded by label",
        "groups": group_stats(rows),
        **comparisons(rows),
    }


def _ci(s: dict[str, Any], scale: float = 1.0, digits: int = 1) -> str:
    """`median [lo, hi]` (no interval with one value), values multiplied by `scale`."""
    if s["median"] is None:
        return "-"
    text = f"{s['median'] * scale:.{digits}f}"
    return text if s["lo"] is None else f"{text} [{s['lo'] * scale:.{digits}f}, {s['hi'] * scale:.{digits}f}]"


def _ratio_ci(s: dict[str, Any]) -> str:
    """A ratio's `median [lo, hi]` to three significant digits (0.00123 and 1049 alike)."""
    if s["median"] is None:
        return "-"
    text = f"{s['median']:.3g}"
    return text if s["lo"] is None else f"{text} [{s['lo']:.3g}, {s['hi']:.3g}]"


def _ate_ci(s: dict[str, Any]) -> str:
    """ATE in mm, or in m (marked) for a method that is off by metres."""
    if s["median"] is not None and abs(s["median"]) >= 1.0:
        return _ci(s, 1.0, 2) + " m"
    return _ci(s, 1000.0, 1)


def stats_markdown(stats: dict[str, Any]) -> str:
    """The intervals and comparisons of `bench_stats` as results.md sections."""
    lines = [
        "",
        f"## Medians with {LEVEL:.0%} bootstrap intervals",
        "",
        f"Median [interval] over seeds ({stats['method']}); `all` pools every capture of a method. ATE in mm "
        "(SE3; vision_only Sim3), scale error in % (positive: the estimate is too large), the run's stated 1-sigma "
        "scale uncertainty in % and how many runs' scale error lies within 1.96 of it (about 95 % if the stated "
        "sigma is honest), drift in % of path length. With n below 4 an interval is only as wide as the data.",
        "",
        "| scenario | IMU | method | n | ATE mm | scale error % | stated scale sigma % | within 1.96 sigma | drift % |",
        "|---|---|---|---:|---|---|---|---:|---|",
    ]
    for g in stats["groups"]:
        cov = g["scale_within_95"]
        within = f"{cov['within']}/{cov['n']}" if cov["n"] else "-"
        lines.append(
            f"| {g['scenario']} | {g['imu']} | {g['method']} | {g['ate_m']['n']} | {_ate_ci(g['ate_m'])} | "
            f"{_ci(g['scale_err_pct'], 1.0, 3)} | {_ci(g['scale_sigma_pct'], 1.0, 3)} | {within} | "
            f"{_ci(g['drift_pct'], 1.0, 2)} |"
        )
    if stats["ratio_to_batch"]:
        lines += [
            "",
            "## Ratio to the batch optimum (ATE SE3 of the method / of batch, on the same captures)",
            "",
            "| method | captures | median ratio [interval] | lower than batch in |",
            "|---|---:|---|---:|",
        ]
        for c in stats["ratio_to_batch"]:
            lines.append(f"| {c['a']} | {c['n']} | {_ratio_ci(c['ratio'])} | {c['a_lower']}/{c['n']} |")
    if stats["paired"]:
        lines += [
            "",
            "## Paired comparisons (same captures: scenario, IMU grade, seed)",
            "",
            "Ratio of A's ATE to B's per capture (SE3 when both are metric, else Sim3); the sign test's p-value is "
            "two-sided over the captures where they differ.",
            "",
            "| A | B | ATE | captures | median A/B [interval] | A lower in | sign test p |",
            "|---|---|---|---:|---|---:|---:|",
        ]
        for c in stats["paired"]:
            p = "-" if c["sign_test_p"] is None else f"{c['sign_test_p']:.3g}"
            lines.append(
                f"| {c['a']} | {c['b']} | {c['key'].removeprefix('ate_').removesuffix('_m')} | {c['n']} | "
                f"{_ratio_ci(c['ratio'])} | {c['a_lower']}/{c['n']} | {p} |"
            )
    return "\n".join(lines) + "\n"
