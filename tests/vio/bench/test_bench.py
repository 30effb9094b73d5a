"""`vio bench`: the harness, results.json schema, the markdown table and the plots."""

from __future__ import annotations

import importlib.util
import json
import shutil
import subprocess
import sys

import pytest

from vio.bench import run_suite
from vio.bench.report import ROW_KEYS, markdown, median_table, paired_ratio
from vio.bench.suites import IMU_ONLY, VIO, VISION_ONLY, Case, Method, Suite, get_suite


def _needs_sim() -> None:
    if importlib.util.find_spec("vio.sim.api") is None:
        pytest.skip("the simulator (vio.sim.api) has not landed")


def _row(method: str, seed: int, ate: float, **kw) -> dict:
    row = dict.fromkeys(ROW_KEYS)
    row.update(scenario="orbit", imu="phone", seed=seed, method=method, ate_se3_m=ate, **kw)
    return row


def test_median_table_and_paired_ratio():
    rows = [
        _row("vio", 0, 0.002, rtf=0.5),
        _row("vio", 1, 0.004, rtf=0.7),
        _row("vio", 2, 0.009, rtf=0.6),
        _row("batch", 0, 0.001),
        _row("batch", 1, 0.004),
        _row("batch", 2, 0.003),
        {**_row("imu_only", 0, None), "error": "boom"},
    ]
    table = {e["method"]: e for e in median_table(rows)}
    assert table["vio"]["ate_se3_m"] == pytest.approx(0.004)
    assert table["vio"]["rtf"] == pytest.approx(0.6)
    assert table["imu_only"]["failed"] == 1 and table["imu_only"]["ate_se3_m"] is None
    assert paired_ratio(rows, "vio", "batch") == pytest.approx(2.0)  # ratios 2, 1, 3 paired by seed
    md = markdown(rows, "t")
    assert "| orbit | phone | vio | 3/3 | 4.0 |" in md
    assert "ATE(vio) / ATE(batch): 2.00" in md
    assert "imu_only: boom" in md


def test_named_suites():
    quick = get_suite("quick")
    assert len({(c.scenario, c.seed) for c in quick.cases}) >= 4
    assert {"vio", "imu_only", "vision_only"} <= {m.name for m in quick.methods}
    assert any(m.refine for m in quick.methods)  # the batch optimum comes with the online run
    full = get_suite("full")
    assert {c.imu for c in full.cases} == {"phone", "tactical"}
    with pytest.raises(Exception, match="unknown benchmark suite"):
        get_suite("nope")


def test_suite_methods_name_presets_that_exist():
    """Built-in methods select configurations by preset name (no `--set` strings in library code)."""
    from vio.config import load_config

    methods = {m.name: m for m in get_suite("quick").methods}
    assert load_config(None, list(methods["vision_only"].overrides), methods["vision_only"].presets).estimator.mode == (
        "vision_only"
    )
    assert load_config(None, [], methods["vio_fixed_lag"].presets).smoother.kind == "fixed_lag"
    assert all(not m.overrides for m in methods.values())


def test_failed_run_is_a_row_not_a_crash(tmp_path):
    """A method on an unreadable capture gives an error row; results.json and results.md are still written."""
    case = Case("orbit", 0, "phone", 2.0)
    cap = tmp_path / "captures" / case.key / "mav0" / "cam0"
    cap.mkdir(parents=True)
    (cap / "data.csv").write_text("#timestamp [ns],filename\n")  # a cached capture without IMU or ground truth
    rows = run_suite(Suite("broken", (case,), (IMU_ONLY, Method("x", "nonsense"))), tmp_path, jobs=2)
    assert [r["method"] for r in rows] == ["imu_only", "x"]
    assert all("error" in r for r in rows)
    data = json.loads((tmp_path / "results.json").read_text())
    assert len(data["runs"]) == 2 and "unknown method kind" in data["runs"][1]["error"]
    assert "## Failed runs" in (tmp_path / "results.md").read_text()


def _check_schema(rows: list[dict]) -> None:
    for r in rows:
        assert set(ROW_KEYS) <= set(r) and set(r) <= set(ROW_KEYS) | {"error"}


@pytest.fixture(scope="module")
def tiny_bench(tmp_path_factory):
    _needs_sim()
    methods = (IMU_ONLY, VIO, VISION_ONLY) if importlib.util.find_spec("vio.pipeline") else (IMU_ONLY,)
    suite = Suite("tiny", get_suite("tiny").cases, methods)
    out = tmp_path_factory.mktemp("bench")
    run_suite(suite, out, jobs=2)
    return out


def test_tiny_suite_schema_and_outputs(tiny_bench):
    data = json.loads((tiny_bench / "results.json").read_text())
    rows = data["runs"]
    _check_schema(rows)
    imu = next(r for r in rows if r["method"] == "imu_only")
    assert "error" not in imu, imu.get("error")
    for key in ("ate_se3_m", "ate_posyaw_m", "ate_sim3_m", "scale", "drift_pct", "rtf", "peak_rss_mb"):
        assert isinstance(imu[key], float) and imu[key] >= 0, key
    assert imu["latency_ms_p50"] is None  # not an online keyframe method
    assert imu["ate_se3_m"] > 0.01  # 4 s of phone IMU alone: centimetres at least
    md = (tiny_bench / "results.md").read_text()
    assert "| orbit | phone | imu_only | 1/1 |" in md
    for name in ("trajectories.png", "error_over_time.png", "error_distribution.png"):
        png = tiny_bench / "plots" / name
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000


def test_tiny_suite_vio_row(tiny_bench):
    if importlib.util.find_spec("vio.pipeline") is None:
        pytest.skip("the estimator pipeline (vio.pipeline) has not landed")
    rows = json.loads((tiny_bench / "results.json").read_text())["runs"]
    vio = next(r for r in rows if r["method"] == "vio")
    assert "error" not in vio, vio.get("error")
    assert vio["ate_se3_m"] < 0.05  # 4 s orbit, phone IMU: the estimator must be far better than imu_only
    assert vio["latency_ms_p50"] is not None and vio["latency_ms_max"] >= vio["latency_ms_p50"]
    assert 0 < vio["scale_sigma_rel"] < 0.5  # the run's stated scale uncertainty, from run.json
    vo = next(r for r in rows if r["method"] == "vision_only")
    assert "error" not in vo, vo.get("error")
    assert vo["ate_se3_m"] is None and vo["ate_posyaw_m"] is None  # no metric scale: Sim3 only
    assert vo["ate_sim3_m"] is not None and vo["scale"] > 0 and vo["scale_sigma_rel"] is None


def test_cli_bench_help():
    exe = shutil.which("vio", path=str(__import__("pathlib").Path(sys.executable).parent))
    cmd = [exe] if exe else [sys.executable, "-m", "vio.cli"]
    out = subprocess.run([*cmd, "bench", "--help"], capture_output=True, text=True, check=True).stdout
    assert "--suite" in out and "--jobs" in out
