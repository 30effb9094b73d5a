"""`vio bench`: the Monte-Carlo drift benchmark, every method on the same simulated measurements.

Layout of `out/`:
  captures/<case>/            simulated captures, cached by key (scenario, IMU grade, seed, duration, ...)
  runs/<case>/<method>/       one folder per job: task.json, result.json, the estimate (trajectory.tum), logs, and
                              job.json, the record of the finished job (its rows), written last
  results.json                `{"runs": [...], "stats": {...}, "jobs": [...], "bench": {...}}`: one row per
                              (case, method) (a failed run is a row with `error`), the medians with bootstrap
                              intervals and the paired comparisons (`vio.bench.stats`), one record per job
  results.md                  medians per scenario / IMU grade / method, intervals, comparisons, RPE, failures
  ground_truth/<case>.csv     the captures' ground truth, when the captures are elsewhere (for the plots)
  plots/                      trajectories from above, error over time, error distributions (PNG)

A job is one method on one capture (`vio.bench.jobs`); it simulates its capture when no other job has. Jobs run
on a scheduler (`vio.bench.schedulers`: local threads, a Dask LocalCluster, or an existing Dask cluster) and give
identical rows on each. A job that fails (a row with an error, a worker lost) is reported and run once more; a
suite run again into the same `out/` skips the jobs whose record is there and error-free (an interrupted suite
resumes).
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from vio.atomic import ensure_dir, write_bytes, write_json
from vio.bench.jobs import GROUND_TRUTH, error_row, job_spec
from vio.bench.schedulers import open_scheduler
from vio.bench.suites import Case, Method, Suite, get_suite

log = logging.getLogger(__name__)

__all__ = ["error_row", "run_bench", "run_suite"]

JOB_RECORD = "job.json"
MAX_ATTEMPTS = 2  # a failed job is run once more


def _record_path(out: Path, case: Case, method: Method) -> Path:
    return out / "runs" / case.key / method.name / JOB_RECORD


def load_done(out: Path, case: Case, method: Method) -> dict[str, Any] | None:
    """The record of this job from an earlier run into `out`, when it is for the same job and has no error."""
    path = _record_path(out, case, method)
    try:
        rec = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if rec.get("job") != job_spec(case, method) or any("error" in r for r in rec.get("rows", [{"error": 1}])):
        return None
    return rec


def _save(out: Path, case: Case, method: Method, res: dict[str, Any], attempts: int, scheduler: str) -> None:
    """Write the files a remote worker sent back, then the job's record (last: its presence means done)."""
    folder = out / "runs" / case.key / method.name
    for rel, data in (res.get("files") or {}).items():
        target = (folder / rel).resolve()
        if folder.resolve() in target.parents:  # never outside the job's folder
            write_bytes(target, data)
    rec = {
        "job": job_spec(case, method),
        "rows": res["rows"],
        "attempts": attempts,
        "wall_s": res.get("wall_s"),
        "host": res.get("host"),
        "scheduler": scheduler,
    }
    write_json(folder / JOB_RECORD, rec)


def _keep_ground_truth(out: Path, case: Case, captures: str | None, res: dict[str, Any]) -> None:
    """`out/ground_truth/<case>.csv` for the plots, when the capture is not under `out/captures`."""
    target = out / "ground_truth" / f"{case.key}.csv"
    if target.exists() or (out / "captures" / case.key).exists():
        return
    source = Path(captures) / case.key / GROUND_TRUTH if captures else None
    if res.get("ground_truth"):
        write_bytes(target, res["ground_truth"])
    elif source is not None and source.is_file():
        write_bytes(target, source.read_bytes())


REPORTS = ("results.json", "results.md")  # the suite's summary, written when every job is done


def discard_reports(out: Path) -> None:
    """Remove an earlier summary (and temporaries of an interrupted write) from `out` before a suite starts: until
    this suite's own summary is written, none in `out` passes for it (the jobs' records stay, to resume from)."""
    for name in REPORTS:
        (out / name).unlink(missing_ok=True)
        for tmp in out.glob(f".{name}.*.tmp"):
            tmp.unlink(missing_ok=True)


def _minutes(s: float) -> str:
    return f"{s / 60:.1f} min" if s >= 60 else f"{s:.0f} s"


def run_suite(
    suite: Suite,
    out: str | os.PathLike[str],
    jobs: int = 2,
    scheduler: str = "local",
    captures: str | None = None,
    progress: Callable[[str], None] | None = None,
) -> list[dict[str, Any]]:
    """Run every method of `suite` on every case; writes results.json, results.md, plots/ under `out`.

    `scheduler`: `local`, `dask` or a Dask scheduler address; `jobs`: parallel jobs (local threads or LocalCluster
    workers; an existing cluster has its own). `captures`: a folder every worker can read and write, for the
    captures (default: `out/captures`, or each remote worker's own temporary cache). `progress` gets one line
    per finished job (counts, elapsed time, ETA); default: the log at INFO.
    """
    from vio.bench.report import write_reports

    out = ensure_dir(out).resolve()
    discard_reports(out)
    say = progress or log.info
    # method-major order: the first jobs to start are on different captures, which simulate in parallel
    order = [(ci, mi) for mi in range(len(suite.methods)) for ci in range(len(suite.cases))]
    results: dict[tuple[int, int], list[dict[str, Any]]] = {}
    records: dict[tuple[int, int], dict[str, Any]] = {}
    for ci, mi in order:
        rec = load_done(out, suite.cases[ci], suite.methods[mi])
        if rec is not None:
            results[(ci, mi)] = rec["rows"]
            records[(ci, mi)] = {k: v for k, v in rec.items() if k != "rows"} | {"resumed": True}
    todo = [j for j in order if j not in results]
    total, resumed = len(order), len(results)
    t0 = time.perf_counter()
    sch = open_scheduler(scheduler, out, jobs, captures)
    say(
        f"bench {suite.name}: {total} jobs ({len(suite.cases)} captures x {len(suite.methods)} methods) on "
        f"{sch.name} with {sch.workers} workers" + (f"; {resumed} done before, resumed" if resumed else "")
    )
    pending: dict[Any, tuple[tuple[int, int], int]] = {}

    def submit(j: tuple[int, int], attempt: int) -> None:
        case, method = suite.cases[j[0]], suite.methods[j[1]]
        pending[sch.submit(job_spec(case, method), f"{case.key}-{method.name}")] = (j, attempt)

    failed = retried = 0
    try:
        for j in todo:
            submit(j, 1)
        while pending:
            done, _ = sch.wait_first(set(pending))
            for fut in done:
                j, attempt = pending.pop(fut)
                case, method = suite.cases[j[0]], suite.methods[j[1]]
                label = f"{case.key} {method.name}"
                try:
                    res = fut.result()
                except Exception as exc:  # noqa: BLE001 - a lost worker or a task that could not run
                    why = f"{exc.__class__.__name__}: {exc}".splitlines()[0][:300]
                    names = [method.name] + (["batch"] if method.refine else [])
                    res = {"rows": [error_row(case, n, f"job failed: {why}") for n in names]}
                errors = [r["error"] for r in res["rows"] if "error" in r]
                if errors and attempt < MAX_ATTEMPTS:
                    retried += 1
                    say(f"bench {suite.name}: {label} failed ({errors[0]}); retrying")
                    submit(j, attempt + 1)
                    continue
                failed += bool(errors)
                _save(out, case, method, res, attempt, sch.name)
                _keep_ground_truth(out, case, sch.captures, res)
                results[j] = res["rows"]
                records[j] = {"job": job_spec(case, method), "attempts": attempt, "wall_s": res.get("wall_s"),
                              "host": res.get("host"), "resumed": False}  # fmt: skip
                n_done, elapsed = len(results), time.perf_counter() - t0
                eta = elapsed / (n_done - resumed) * (total - n_done)
                say(
                    f"bench {suite.name}: {n_done}/{total} jobs done"
                    + (f" ({failed} failed)" if failed else "")
                    + f", {_minutes(elapsed)} elapsed, ETA {_minutes(eta)}: {label}"
                    + (f" FAILED after {attempt} attempts: {errors[0]}" if errors else "")
                )
    except BaseException:
        sch.cancel(set(pending))
        say(f"bench {suite.name}: stopped with {len(results)}/{total} jobs done; run it again to resume")
        raise
    finally:
        sch.close()
    wall = time.perf_counter() - t0
    # rows carry the case's label as their scenario (resumed records too, whatever label they were written with)
    rows = [
        {**r, "scenario": suite.cases[ci].label}
        for ci in range(len(suite.cases))
        for mi in range(len(suite.methods))
        for r in results[(ci, mi)]
    ]
    jobs_meta = [records[(ci, mi)] for ci in range(len(suite.cases)) for mi in range(len(suite.methods))]
    meta = {"suite": suite.name, "scheduler": sch.name, "workers": sch.workers, "wall_s": wall,
            "jobs": total, "resumed": resumed, "retried": retried, "failed": failed}  # fmt: skip
    log.info("bench %s: %d rows in %.0f s", suite.name, len(rows), wall)
    write_reports(suite, rows, out, wall_s=wall, jobs=sch.workers, meta=meta, job_records=jobs_meta)
    return rows


def run_bench(
    suite: str,
    out: str | os.PathLike[str],
    jobs: int = 2,
    scheduler: str = "local",
    captures: str | None = None,
    progress: Callable[[str], None] | None = None,
) -> list[dict[str, Any]]:
    """`vio bench --suite NAME|FILE.yaml --out DIR [--jobs N] [--scheduler local|dask|ADDRESS]`."""
    return run_suite(get_suite(suite), out, jobs=jobs, scheduler=scheduler, captures=captures, progress=progress)
