"""`vio bench --scheduler`: a real Dask cluster gives the local numbers; bad addresses are one line; failed jobs
are retried once; an interrupted suite resumes from the jobs on disk."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.conftest import ROOT, default_sigint
from vio.bench import JOB_RECORD, load_done, run_suite
from vio.bench.suites import IMU_ONLY, Case, Method, Suite

SAME = ("ate_se3_m", "ate_posyaw_m", "ate_sim3_m", "scale", "drift_pct", "scenario", "imu", "seed", "method")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _vio(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "vio.cli", *args]
    return subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=timeout)


def _stop(procs: list[subprocess.Popen]) -> None:
    for p in procs:
        p.terminate()
    for p in procs:
        try:
            p.wait(timeout=20)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


@pytest.mark.slow  # two simulations of the 4 s capture and four runs: about a minute on 2 cores
def test_a_dask_cluster_gives_the_local_numbers(tmp_path):
    """`dask scheduler` + two `dask worker` processes on 127.0.0.1: the tiny suite through tcp://127.0.0.1:PORT
    (captures simulated inside the workers, run files sent back) equals `--scheduler local` number for number."""
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    logs = tmp_path / "dask_logs"
    logs.mkdir()
    dask = [sys.executable, "-m", "dask"]
    procs = [
        subprocess.Popen(
            [*dask, "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"],
            stdout=subprocess.DEVNULL,
            stderr=open(logs / "scheduler.log", "w"),
        )  # fmt: skip
    ]
    try:
        for i in range(2):
            procs.append(
                subprocess.Popen(
                    [
                        *dask,
                        "worker",
                        address,
                        "--nthreads",
                        "1",
                        "--nworkers",
                        "1",
                        "--no-dashboard",
                        "--local-directory",
                        str(tmp_path / f"w{i}"),
                    ],
                    stdout=subprocess.DEVNULL,
                    stderr=open(logs / f"worker{i}.log", "w"),
                )  # fmt: skip
            )
        from dask.distributed import Client

        with Client(address, timeout="30s") as client:  # both workers in before the suite starts
            client.wait_for_workers(2, timeout=60)
        remote = _vio("bench", "--suite", "tiny", "--scheduler", address, "--out", str(tmp_path / "remote"))
        assert remote.returncode == 0, remote.stderr[-3000:]
    finally:
        _stop(procs)
    local = _vio("bench", "--suite", "tiny", "--scheduler", "local", "--out", str(tmp_path / "local"))
    assert local.returncode == 0, local.stderr[-3000:]
    a = json.loads((tmp_path / "remote" / "results.json").read_text())
    b = json.loads((tmp_path / "local" / "results.json").read_text())
    assert [{k: r[k] for k in SAME} for r in a["runs"]] == [{k: r[k] for k in SAME} for r in b["runs"]]
    assert all("error" not in r for r in a["runs"]) and len(a["runs"]) == 2
    assert a["stats"]["groups"] == b["stats"]["groups"]  # medians and intervals of ATE, scale error, drift
    assert a["bench"]["scheduler"] == address and a["bench"]["workers"] == 2 and b["bench"]["scheduler"] == "local"
    # the workers simulated their own capture and sent the run folders back: the report has what it needs
    assert not (tmp_path / "remote" / "captures").exists()
    for method in ("imu_only", "vio"):
        run = tmp_path / "remote" / "runs" / "orbit_phone_s0_4s" / method
        assert (run / f"metrics_{method}.json").exists() and (run / f"aligned_{method}.csv").exists()
        assert json.loads((run / JOB_RECORD).read_text())["scheduler"] == address
    assert "Relative pose error" in (tmp_path / "remote" / "results.md").read_text()
    assert (tmp_path / "remote" / "ground_truth" / "orbit_phone_s0_4s.csv").exists()  # sent back for the plots
    assert (tmp_path / "remote" / "plots" / "trajectories.png").stat().st_size > 10_000
    assert "2/2 jobs done" in remote.stderr and "ETA" in remote.stderr


def test_an_unreachable_scheduler_is_one_line(tmp_path):
    r = _vio("bench", "--suite", "tiny", "--scheduler", f"tcp://127.0.0.1:{_free_port()}", "--out", str(tmp_path))
    assert r.returncode == 2
    assert r.stderr.strip().startswith("vio bench: error: cannot reach the Dask scheduler at tcp://127.0.0.1:")
    assert len(r.stderr.strip().splitlines()) == 1
    r = _vio("bench", "--suite", "tiny", "--scheduler", "slurm", "--out", str(tmp_path))
    assert r.returncode == 2 and r.stderr.strip() == (
        "vio bench: error: unknown scheduler 'slurm'; use local, dask or a Dask scheduler address tcp://HOST:PORT"
    )
    r = _vio("bench", "--suite", "tiny", "--scheduler", "tcp://127.0.0.1:port", "--out", str(tmp_path))
    assert r.returncode == 2 and r.stderr.strip() == (
        "vio bench: error: 'tcp://127.0.0.1:port' is not a Dask scheduler address (tcp://HOST:PORT)"
    )
    r = _vio("bench", "--suite", str(tmp_path / "none.yaml"), "--out", str(tmp_path))
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "cannot read the suite" in r.stderr


def test_a_failed_job_is_retried_once_and_reported(tmp_path):
    case = Case("orbit", 0, "phone", 2.0)
    cap = tmp_path / "captures" / case.key / "mav0" / "cam0"
    cap.mkdir(parents=True)
    (cap / "data.csv").write_text("#timestamp [ns],filename\n")  # a cached capture without IMU or ground truth
    lines: list[str] = []
    rows = run_suite(Suite("broken", (case,), (Method("x", "nonsense"),)), tmp_path, jobs=1, progress=lines.append)
    assert rows[0]["error"].startswith("ValueError: unknown method kind")
    assert any("orbit_phone_s0_2s x failed (ValueError: unknown method kind" in s and "retrying" in s for s in lines)
    assert "1/1 jobs done (1 failed)" in lines[-1] and "FAILED after 2 attempts" in lines[-1]
    data = json.loads((tmp_path / "results.json").read_text())
    assert data["bench"]["retried"] == 1 and data["bench"]["failed"] == 1 and data["jobs"][0]["attempts"] == 2
    assert "1 retried, 1 failed" in (tmp_path / "results.md").read_text()


def test_an_interrupted_suite_resumes_from_the_jobs_on_disk(tmp_path):
    cases = (Case("orbit", 0, "phone", 2.0, images=False), Case("room", 0, "phone", 2.0, images=False))
    suite = Suite("resume", cases, (IMU_ONLY,), plots=False)
    first = run_suite(suite, tmp_path, jobs=2)
    kept = tmp_path / "runs" / cases[0].key / "imu_only"
    lost = tmp_path / "runs" / cases[1].key / "imu_only"
    stamp = (kept / "trajectory.tum").stat().st_mtime_ns
    (lost / JOB_RECORD).unlink()  # as if the suite had been stopped before this job finished
    time.sleep(0.01)
    lines: list[str] = []
    again = run_suite(suite, tmp_path, jobs=2, progress=lines.append)
    assert "1 done before, resumed" in lines[0] and "2/2 jobs done" in lines[-1] and cases[1].key in lines[-1]
    assert (kept / "trajectory.tum").stat().st_mtime_ns == stamp  # not run again
    assert [{k: r[k] for k in SAME} for r in again] == [{k: r[k] for k in SAME} for r in first]
    data = json.loads((tmp_path / "results.json").read_text())
    assert [j["resumed"] for j in data["jobs"]] == [True, False] and data["bench"]["resumed"] == 1
    assert "2 jobs (1 resumed); this session ran 1 of them in" in (tmp_path / "results.md").read_text()
    # a record of another job (the method changed since) is not taken as done
    assert load_done(tmp_path, cases[0], IMU_ONLY) is not None
    assert load_done(tmp_path, cases[0], Method("imu_only", "imu_only", overrides=("run.progress=true",))) is None


def test_ctrl_c_stops_the_suite_and_the_same_command_resumes_it(tmp_path):
    suite = tmp_path / "two.yaml"
    suite.write_text(
        "name: two\nplots: false\nmethods: [{name: imu_only, kind: imu_only}]\n"
        "cases:\n  - grid: {scenario: [orbit, room]}\n"
        "    seed: 0\n    imu: phone\n    duration_s: 2\n    images: false\n"
    )
    cmd = [sys.executable, "-m", "vio.cli", "bench", "--suite", str(suite), "--jobs", "1", "--out", str(tmp_path / "o")]
    proc = subprocess.Popen(cmd, cwd=ROOT, stderr=subprocess.PIPE, text=True, preexec_fn=default_sigint)
    lines = []
    for line in proc.stderr:  # interrupt as soon as the first job is done
        lines.append(line)
        if "1/2 jobs done" in line:
            proc.send_signal(signal.SIGINT)
            break
    rest = proc.stderr.read()
    assert proc.wait(timeout=120) == 130, "".join(lines) + rest
    assert "stopped with 1/2 jobs done; run it again to resume" in rest and "interrupted" in rest
    assert "Traceback" not in rest
    again = _vio("bench", "--suite", str(suite), "--jobs", "1", "--out", str(tmp_path / "o"))
    assert again.returncode == 0 and "1 done before, resumed" in again.stderr and "2/2 jobs done" in again.stderr


def _children(pid: int) -> list[int]:
    found = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            found += [int(c) for c in (task / "children").read_text().split()]
        except OSError:
            pass
    return found


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_a_killed_bench_leaves_no_job_running(tmp_path):
    """SIGKILL to `vio bench` (no chance to clean up) takes its running job's child process with it."""
    cmd = [sys.executable, "-m", "vio.cli", "bench", "--suite", "tiny", "--jobs", "1", "--out", str(tmp_path)]
    bench = subprocess.Popen(cmd, cwd=ROOT, stderr=subprocess.DEVNULL)
    child = None
    for _ in range(600):  # the simulation's child process starts within a few seconds
        kids = [c for c in _children(bench.pid) if b"vio.bench.worker" in Path(f"/proc/{c}/cmdline").read_bytes()]
        if kids:
            child = kids[0]
            break
        time.sleep(0.1)
    assert child is not None, "no job child process appeared"
    bench.kill()
    bench.wait()
    for _ in range(100):
        if not Path(f"/proc/{child}").exists() or "Z" in Path(f"/proc/{child}/stat").read_text().split()[2]:
            return
        time.sleep(0.1)
    os.kill(child, signal.SIGKILL)
    raise AssertionError("the job's child process outlived the bench")


def test_cli_bench_help_names_the_schedulers():
    r = _vio("bench", "--help")
    assert "--scheduler" in r.stdout and "tcp://HOST:PORT" in r.stdout and "--captures" in r.stdout
