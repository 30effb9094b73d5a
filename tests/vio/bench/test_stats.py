"""Benchmark statistics: seeded bootstrap intervals of medians, ratios to batch, paired comparisons."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats as sps

from vio.bench.report import ROW_KEYS
from vio.bench.stats import bench_stats, compare, group_stats, median_ci, stats_markdown


def _row(method: str, seed: int, ate: float | None, scenario: str = "orbit", **kw) -> dict:
    row = dict.fromkeys(ROW_KEYS)
    row.update(scenario=scenario, imu="phone", seed=seed, method=method, ate_se3_m=ate, **kw)
    return row


def test_median_ci_is_seeded_and_covers_the_median():
    x = list(np.random.default_rng(3).lognormal(-5.0, 0.5, 9))
    a, b = median_ci(x, seed=1), median_ci(x, seed=1)
    assert a == b and a["n"] == 9 and a["median"] == pytest.approx(np.median(x))
    assert min(x) <= a["lo"] < a["median"] < a["hi"] <= max(x)
    y = list(np.random.default_rng(4).normal(0.0, 1.0, 200))
    assert median_ci(y, seed=2) != median_ci(y, seed=1)  # the seed is used
    assert median_ci([0.004], seed=1) == {"n": 1, "median": 0.004, "lo": None, "hi": None}
    assert median_ci([None, float("nan")], seed=1)["median"] is None


def test_median_ci_agrees_with_scipy_percentile_bootstrap():
    x = np.random.default_rng(5).normal(10.0, 2.0, 200)
    ours = median_ci(list(x), seed=0)
    ref = sps.bootstrap((x,), np.median, method="percentile", n_resamples=4000, random_state=0).confidence_interval
    assert ours["lo"] == pytest.approx(ref.low, abs=0.15) and ours["hi"] == pytest.approx(ref.high, abs=0.15)
    narrow = median_ci(list(x[:20]), seed=0)
    assert ours["hi"] - ours["lo"] < narrow["hi"] - narrow["lo"]  # more seeds, a narrower interval


def test_groups_ratio_to_batch_and_paired_comparisons():
    rows = []
    for seed, (v, b) in enumerate([(0.002, 0.001), (0.006, 0.002), (0.012, 0.003), (0.004, 0.004)]):
        rows += [_row("vio", seed, v, scale=1.01, drift_pct=0.5), _row("batch", seed, b, scale=0.99)]
    rows.append({**_row("vio", 9, None), "error": "boom"})
    st = bench_stats(rows)
    vio = next(g for g in st["groups"] if g["method"] == "vio" and g["scenario"] == "orbit")
    assert vio["runs"] == 4 and vio["ate_m"]["median"] == pytest.approx(0.005)
    assert vio["scale_err_pct"]["median"] == pytest.approx(100 * (1 / 1.01 - 1))
    assert any(g["scenario"] == "all" and g["method"] == "batch" for g in st["groups"])
    (ratio,) = st["ratio_to_batch"]
    assert ratio["a"] == "vio" and ratio["n"] == 4 and ratio["ratio"]["median"] == pytest.approx(2.5)  # 2, 3, 4, 1
    assert ratio["ratio"]["lo"] >= 1.0 and ratio["ratio"]["hi"] <= 4.0
    c = compare(rows, "batch", "vio")
    assert c["a_lower"] == 3 and c["n"] == 4 and c["sign_test_p"] == pytest.approx(0.25)  # 3 of 3 unequal
    md = stats_markdown(st)
    assert "| orbit | phone | vio | 4 | 5.0 [" in md and "| vio | 4 | 2.5 [" in md
    assert "| vio | batch | se3 | 4 | 2.5 [" in md


def test_vision_only_is_compared_on_sim3_and_single_runs_have_no_interval():
    rows = [
        _row("vio", 0, 0.002, ate_sim3_m=0.0019),
        _row("vision_only", 0, None, ate_sim3_m=0.0038, scenario="orbit"),
    ]
    assert compare(rows, "vio", "vision_only")["key"] == "ate_sim3_m"
    assert compare(rows, "vio", "vision_only")["ratio"]["median"] == pytest.approx(0.5)
    g = group_stats(rows)[0]
    assert g["ate_m"]["lo"] is None and "| orbit | phone | vio | 1 | 2.0 |" in stats_markdown(bench_stats(rows))


def test_scale_coverage_counts_errors_within_the_stated_sigma():
    """Scale errors of +0.5 %, -1.0 % and +3.0 % against a stated sigma of 1 %: two lie within 1.96 sigma."""
    rows = [_row("vio", i, 0.003, scale=1 / (1 + e), scale_sigma_rel=0.01) for i, e in enumerate((0.005, -0.01, 0.03))]
    rows.append(_row("vio", 9, 0.003, scale=1.0))  # a run that states no sigma is not counted
    g = next(g for g in group_stats(rows) if g["scenario"] == "orbit")
    assert g["scale_within_95"] == {"within": 2, "n": 3}
    assert g["scale_sigma_pct"]["median"] == pytest.approx(1.0) and g["scale_err_pct"]["median"] == pytest.approx(0.25)
    assert "| orbit | phone | vio | 4 | 3.0 [3.0, 3.0] | 0.250 [" in stats_markdown(bench_stats(rows))
    assert "| 1.000 [1.000, 1.000] | 2/3 |" in stats_markdown(bench_stats(rows))


def test_methods_without_metric_scale_state_no_scale_error():
    """vision_only's Sim3 scale is its first baseline's and imu_only's that of a trajectory off by metres: neither
    is a scale error (the quick suite's table once read 2290 % and 21550 % for them)."""
    rows = [_row(m, 0, 0.01, scale=0.04, ate_sim3_m=0.05) for m in ("vio", "vision_only", "imu_only")]
    groups = {g["method"]: g for g in group_stats(rows) if g["scenario"] == "orbit"}
    assert groups["vio"]["scale_err_pct"]["median"] == pytest.approx(2400.0)
    assert groups["vision_only"]["scale_err_pct"]["median"] is None
    assert groups["imu_only"]["scale_err_pct"]["median"] is None
