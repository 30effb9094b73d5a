"""One benchmark job: one method on one capture, wherever it runs (a thread of `vio bench`, or a Dask worker).

A job carries only what identifies it (the case: scenario, seed, IMU grade, duration...; the method: kind,
presets, overrides) and where to keep captures and runs. `execute` makes sure the capture exists (simulating it
under a file lock, so that two jobs of one capture on one machine simulate it once), then runs the method. Both
steps run in a child process (`python -m vio.bench.worker`): a segfault or the out-of-memory killer costs one
job, never the worker, and the peak RSS of a row is that of its own process.

`execute` returns plain data (rows, and the run folder's files when asked), so that a worker without the
client's file system can send its results back.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from vio.atomic import write_json
from vio.bench.suites import Case, Method, method_from_dict
from vio.children import die_with_parent

log = logging.getLogger(__name__)

TASK_TIMEOUT_S = 1800.0  # a single simulation or method run taking longer than this is recorded as failed
MODEL_TASK_TIMEOUT_S = 4 * 3600.0  # a part-model task (run, model, measure, compare): the first one on a busy
# machine took 44 min for the model step alone
GROUND_TRUTH = Path("mav0") / "state_groundtruth_estimate0" / "data.csv"  # in a capture
MAX_RETURNED_FILE_BYTES = 5_000_000  # larger files of a run (dense clouds, meshes) stay on the worker


def job_spec(case: Case, method: Method) -> dict[str, Any]:
    """The job as JSON-ready data: `{"case": {...}, "method": {...}}` (what a record of a finished job repeats)."""
    return json.loads(json.dumps({"case": case.__dict__, "method": method.__dict__}))


def _timeout(task: dict[str, Any]) -> float:
    """The time limit of a task: longer for the part-model methods."""
    return MODEL_TASK_TIMEOUT_S if (task.get("method") or {}).get("kind") == "model" else TASK_TIMEOUT_S


def run_child(task: dict[str, Any], folder: Path) -> dict[str, Any]:
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
            proc = subprocess.run(
                cmd, stdout=logf, stderr=subprocess.STDOUT, env=env, timeout=_timeout(task),
                preexec_fn=die_with_parent,  # only prctl between fork and exec: no locks, no threads
            )  # fmt: skip
            code = proc.returncode
        except subprocess.TimeoutExpired:
            code = None
    if result_path.exists():
        return json.loads(result_path.read_text(encoding="utf-8"))
    tail = (folder / "worker.log").read_text(encoding="utf-8", errors="replace").strip().splitlines()[-1:]
    if code is None:
        why = f"timed out after {_timeout(task):.0f} s"
    elif code < 0:
        why = f"worker killed by signal {-code}"
    else:
        why = f"worker exited with status {code}"
    return {"error": f"{why}: {tail[0] if tail else 'no output'}", "wall_s": time.perf_counter() - t0}


@contextlib.contextmanager
def _locked(path: Path) -> Iterator[None]:
    """An exclusive advisory lock on `path` (created), held for the block."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a+") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def is_cached(folder: Path) -> bool:
    return (folder / "mav0" / "cam0" / "data.csv").exists()


def ensure_capture(case: Case, captures: Path) -> dict[str, Any]:
    """`{"capture": path, "cached": bool}` for the case's capture under `captures`, simulated when absent, or
    `{"error": ...}`. The simulation goes to a temporary folder renamed into place, so a killed simulation never
    leaves a capture that looks complete."""
    folder = captures / case.key
    if is_cached(folder):
        return {"capture": str(folder), "cached": True}
    with _locked(captures / ".locks" / f"{case.key}.lock"):
        if is_cached(folder):  # another job simulated it while this one waited
            return {"capture": str(folder), "cached": True}
        partial = captures / f".{case.key}.partial-{uuid.uuid4().hex[:8]}"
        task = {"kind": "simulate", "case": case.__dict__, "capture": str(partial)}
        res = run_child(task, captures / ".logs" / case.key)
        if "error" in res:
            shutil.rmtree(partial, ignore_errors=True)
            return res
        if folder.exists():  # a leftover without data.csv (an older interrupted run)
            shutil.rmtree(folder)
        os.replace(partial, folder)
        return {"capture": str(folder), "cached": False, "sim_wall_s": res.get("wall_s")}


def error_row(case: Case, method: str, error: str) -> dict[str, Any]:
    """A results.json row for a run that produced no estimate."""
    from vio.bench.report import empty_row

    row = empty_row(case, method)
    row["error"] = error
    return row


def _row_names(method: Method) -> list[str]:
    return [method.name] + (["batch"] if method.refine else [])


def _collect_files(folder: Path) -> dict[str, bytes]:
    files = {}
    for p in sorted(folder.rglob("*")):
        if p.is_file() and p.stat().st_size <= MAX_RETURNED_FILE_BYTES:
            files[str(p.relative_to(folder))] = p.read_bytes()
    return files


def scratch_captures(tag: str) -> Path:
    """This machine's temporary capture cache for the suite run named `tag` (one per run: a capture cached by an
    older version of the simulator is never reused)."""
    return Path(tempfile.gettempdir()) / f"vio-bench-{tag}" / "captures"


def _worker_name() -> str:
    """The Dask worker's address when a Dask worker runs this job, else the host name."""
    if "distributed" in sys.modules:
        from distributed import get_worker

        try:
            return str(get_worker().address)
        except ValueError:  # not inside a Dask task
            pass
    return socket.gethostname()


def execute(spec: dict[str, Any], captures: str | None, runs: str | None, tag: str = "") -> dict[str, Any]:
    """Run one job (`job_spec`). Captures are kept under `captures` (None: `scratch_captures(tag)` on the machine
    that runs the job); the run goes to `runs/<case>/<method>` (None: a temporary folder, deleted after its files
    are read into the result's `files`). Returns `{"rows": [...], "files": {...}, "wall_s", "host",
    "capture_cached"}`; a failure is rows with an `error` field, never an exception."""
    t0 = time.perf_counter()
    case = Case(**spec["case"])
    m = spec["method"]
    method = method_from_dict(m)
    cap_root = Path(captures) if captures else scratch_captures(tag)
    tmp = None
    if runs is None:
        tmp = Path(tempfile.mkdtemp(prefix="vio-bench-run-"))
        folder = tmp
    else:
        folder = Path(runs) / case.key / method.name
    result: dict[str, Any] = {"host": _worker_name(), "files": {}}
    try:
        sim = ensure_capture(case, cap_root)
        result["capture_cached"] = bool(sim.get("cached"))
        if "error" in sim:
            result["rows"] = [error_row(case, n, f"simulation failed: {sim['error']}") for n in _row_names(method)]
        else:
            task = {
                "kind": "method",
                "case": case.__dict__,
                "method": method.__dict__,
                "capture": sim["capture"],
                "out": str(folder),
            }
            res = run_child(task, folder)
            rows = res.get("rows")
            if not rows:
                rows = [error_row(case, n, res.get("error", "no result")) for n in _row_names(method)]
            result["rows"] = rows
        if tmp is not None:
            result["files"] = _collect_files(folder)
            gt = Path(sim.get("capture", "")) / GROUND_TRUTH
            if "error" not in sim and gt.is_file():
                result["ground_truth"] = gt.read_bytes()
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    result["wall_s"] = time.perf_counter() - t0
    return result


def remove_scratch(tag: str) -> None:
    """Delete this machine's temporary capture cache of the suite run `tag`, at the end of the run."""
    shutil.rmtree(scratch_captures(tag).parent, ignore_errors=True)
