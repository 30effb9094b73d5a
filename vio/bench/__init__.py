"""`vio bench`: the Monte-Carlo drift benchmark, every method on the same simulated measurements.

Layout of `out/`:
  captures/<case>/            simulated captures, cached by key (scenario, IMU grade, seed, duration)
  runs/<case>/<method>/       one folder per run: task.json, result.json, the estimate (trajectory.tum), logs
  results.json                `{"runs": [...]}` one row per (case, method); a failed run is a row with `error`
  results.md                  medians per scenario / IMU grade / method, plus RPE and the failures
  plots/                      trajectories from above, error over time, error distributions (PNG)

Each capture is simulated, and each method run, in its own child process (`python -m vio.bench.worker`), at most
`jobs` at a time. A child that raises, or dies (a segfault in a native library, the out-of-memory killer), costs
one row with an `error` field, never the whole benchmark; the peak RSS of a row is that of its own process.
"""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from vio.atomic import ensure_dir, write_json
from vio.bench.suites import Case, Method, Suite, get_suite

log = logging.getLogger(__name__)

__all__ = ["run_bench", "run_suite"]

TASK_TIMEOUT_S = 1800.0  # a single simulation or method run taking longer than this is recorded as failed


def _run_child(task: dict[str, Any], folder: Path) -> dict[str, Any]:
    """Run one task in a child process; returns its result dict (or an `error` dict when the child failed)."""
    folder.mkdir(parents=True, exist_ok=True)
    task_path = folder / "task.json"
    result_path = folder / "result.json"
    result_path.unlink(missing_ok=True)
    write_json(task_path, task)
    cmd = [sys.executable, "-m", "vio.bench.worker", str(task_path)]
    env = dict(os.environ, PYTHONUNBUFFERED="1", OMP_NUM_THREADS="1")
    t0 = time.perf_counter()
    with open(folder / "worker.log", "w", encoding="utf-8") as logf:
        try:
            proc = subprocess.run(cmd, stdout=logf, stderr=subprocess.STDOUT, env=env, timeout=TASK_TIMEOUT_S)
            code = proc.returncode
        except subprocess.TimeoutExpired:
            code = None
    if result_path.exists():
        return json.loads(result_path.read_text(encoding="utf-8"))
    tail = (folder / "worker.log").read_text(encoding="utf-8", errors="replace").strip().splitlines()[-1:]
    if code is None:
        why = f"timed out after {TASK_TIMEOUT_S:.0f} s"
    elif code < 0:
        why = f"worker killed by signal {-code}"
    else:
        why = f"worker exited with status {code}"
    return {"error": f"{why}: {tail[0] if tail else 'no output'}", "wall_s": time.perf_counter() - t0}


def _simulate_task(case: Case, captures: Path) -> dict[str, Any]:
    folder = captures / case.key
    if (folder / "mav0" / "cam0" / "data.csv").exists():
        return {"capture": str(folder), "cached": True}
    task = {"kind": "simulate", "case": case.__dict__, "capture": str(folder)}
    return _run_child(task, captures / ".logs" / case.key)


def _method_task(case: Case, method: Method, capture: str, runs: Path) -> list[dict[str, Any]]:
    folder = runs / case.key / method.name
    task = {"kind": "method", "case": case.__dict__, "method": method.__dict__, "capture": capture, "out": str(folder)}
    res = _run_child(task, folder)
    if "rows" in res:
        return res["rows"]
    names = [method.name] + (["batch"] if method.refine else [])
    return [error_row(case, name, res.get("error", "no result")) for name in names]


def error_row(case: Case, method: str, error: str) -> dict[str, Any]:
    """A results.json row for a run that produced no estimate."""
    from vio.bench.report import empty_row

    row = empty_row(case, method)
    row["error"] = error
    return row


def run_suite(suite: Suite, out: str | os.PathLike[str], jobs: int = 2) -> list[dict[str, Any]]:
    """Simulate every capture of `suite` and run every method on it; writes results.json, results.md, plots/."""
    from vio.bench.report import write_reports

    out = ensure_dir(out)
    captures, runs = out / "captures", out / "runs"
    jobs = max(1, int(jobs))
    t0 = time.perf_counter()
    log.info("bench %s: %d captures x %d methods, %d jobs", suite.name, len(suite.cases), len(suite.methods), jobs)
    with ThreadPoolExecutor(max_workers=jobs) as pool:
        sims = list(pool.map(lambda c: _simulate_task(c, captures), suite.cases))
        futures = []
        rows: list[dict[str, Any]] = []
        for case, sim in zip(suite.cases, sims, strict=True):
            if "error" in sim:
                log.warning("bench: simulating %s failed: %s", case.key, sim["error"])
                for m in suite.methods:
                    names = [m.name] + (["batch"] if m.refine else [])
                    rows += [error_row(case, n, f"simulation failed: {sim['error']}") for n in names]
                continue
            for m in suite.methods:
                futures.append(pool.submit(_method_task, case, m, sim["capture"], runs))
        for f in futures:
            rows += f.result()
    wall = time.perf_counter() - t0
    log.info("bench %s: %d rows in %.0f s", suite.name, len(rows), wall)
    write_reports(suite, rows, out, wall_s=wall, jobs=jobs)
    return rows


def run_bench(suite: str, out: str | os.PathLike[str], jobs: int = 2) -> list[dict[str, Any]]:
    """`vio bench --suite NAME --out DIR --jobs N`: run a named suite (`quick`, `full`, or `tiny`)."""
    return run_suite(get_suite(suite), out, jobs=jobs)
