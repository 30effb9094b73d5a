"""Where benchmark jobs run: `local` (threads of this process, each job in a child process), `dask` (a
dask.distributed LocalCluster started for the run) or a Dask scheduler's address (`tcp://HOST:PORT`, a cluster
the user started with `dask scheduler` / `dask worker`, dask-jobqueue or Kubernetes).

Every scheduler runs the same function, `vio.bench.jobs.execute`, on the same job data; only where captures and
run folders live differs. Local threads and a LocalCluster share this machine's file system, so jobs use
`OUT/captures` and write `OUT/runs` directly. The workers of an address may not see `OUT`: they simulate into a
temporary cache of their own (or into `--captures DIR`, a folder they all share) and send the run's files back.
"""

from __future__ import annotations

import concurrent.futures as cf
import logging
import uuid
from pathlib import Path
from typing import Any

from vio.bench.jobs import execute, remove_scratch
from vio.errors import VioError

log = logging.getLogger(__name__)

CONNECT_TIMEOUT_S = 10.0  # to reach a scheduler's address
WORKERS_TIMEOUT_S = 60.0  # for the first worker to be there


class SchedulerError(VioError):
    """The scheduler cannot be used: an unknown name, an unreachable address, a cluster without workers."""


class Scheduler:
    """Submits jobs and waits for them. `captures` / `runs`: the folders jobs use (None: the worker's own
    temporary cache / results sent back as files)."""

    def __init__(self, name: str, captures: str | None, runs: str | None, workers: int) -> None:
        self.name = name
        self.captures = captures
        self.runs = runs
        self.workers = workers
        self.tag = uuid.uuid4().hex[:12]  # names this run's temporary capture caches

    def submit(self, spec: dict[str, Any], label: str) -> Any:
        raise NotImplementedError

    def wait_first(self, pending: set[Any]) -> tuple[set[Any], set[Any]]:
        raise NotImplementedError

    def cancel(self, pending: set[Any]) -> None:
        """Give up the jobs not yet finished (an interrupted suite)."""
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError


class LocalScheduler(Scheduler):
    """Threads of this process, `workers` jobs at a time (each job's work is in child processes)."""

    def __init__(self, out: Path, captures: str | None, workers: int) -> None:
        super().__init__("local", captures or str(out / "captures"), str(out / "runs"), workers)
        self.pool = cf.ThreadPoolExecutor(max_workers=workers)

    def submit(self, spec: dict[str, Any], label: str) -> cf.Future:
        return self.pool.submit(execute, spec, self.captures, self.runs, self.tag)

    def wait_first(self, pending: set[Any]) -> tuple[set[Any], set[Any]]:
        done, rest = cf.wait(pending, return_when=cf.FIRST_COMPLETED)
        return set(done), set(rest)

    def cancel(self, pending: set[Any]) -> None:
        for f in pending:
            f.cancel()
        self.pool.shutdown(wait=False, cancel_futures=True)

    def close(self) -> None:
        self.pool.shutdown(wait=True)


class DaskScheduler(Scheduler):
    """A dask.distributed client, on a LocalCluster it started (`address` None) or on an existing cluster."""

    def __init__(self, out: Path, captures: str | None, workers: int, address: str | None) -> None:
        try:
            from dask.distributed import Client, LocalCluster
        except ImportError as exc:  # pragma: no cover - a dependency of the package
            raise SchedulerError(f"--scheduler dask needs dask[distributed] ({exc})") from None
        if logging.getLogger().getEffectiveLevel() >= logging.WARNING:  # Dask's own INFO lines only with -v
            logging.getLogger("distributed").setLevel(logging.ERROR)
        self.cluster = None
        if address is None:
            try:
                self.cluster = LocalCluster(
                    n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None,
                    silence_logs=logging.ERROR,
                )  # fmt: skip
            except (OSError, RuntimeError, TimeoutError) as exc:
                raise SchedulerError(f"cannot start a Dask LocalCluster of {workers} workers: {exc}") from None
            super().__init__("dask", captures or str(out / "captures"), str(out / "runs"), workers)
        else:
            super().__init__(address, captures, None, 0)
        try:
            self.client = Client(
                self.cluster if self.cluster is not None else address,
                timeout=f"{CONNECT_TIMEOUT_S}s",
                set_as_default=False,
            )
        except (OSError, TimeoutError, ValueError) as exc:  # refused, timed out, or not an address
            self._close_cluster()
            first = str(exc).splitlines()[0] if str(exc) else exc.__class__.__name__
            raise SchedulerError(f"cannot reach the Dask scheduler at {address}: {first}") from None
        try:
            self.client.wait_for_workers(1, timeout=WORKERS_TIMEOUT_S)
        except (OSError, TimeoutError):
            self.close()
            raise SchedulerError(f"no Dask worker joined {address} within {WORKERS_TIMEOUT_S:.0f} s") from None
        self.workers = len(self.client.scheduler_info(n_workers=-1).get("workers", {}))

    def submit(self, spec: dict[str, Any], label: str) -> Any:
        key = f"vio-bench-{label}-{uuid.uuid4().hex[:8]}"
        return self.client.submit(execute, spec, self.captures, self.runs, self.tag, key=key, pure=False)

    def wait_first(self, pending: set[Any]) -> tuple[set[Any], set[Any]]:
        from dask.distributed import wait

        with self.client.as_current():
            done, rest = wait(list(pending), return_when="FIRST_COMPLETED")
        return set(done), set(rest)

    def cancel(self, pending: set[Any]) -> None:
        self.client.cancel(list(pending))

    def close(self) -> None:
        try:
            if self.captures is None:  # the workers' temporary capture caches of this run
                self.client.run(remove_scratch, self.tag)
        except Exception as exc:  # noqa: BLE001 - closing must not hide the run's own outcome
            log.warning("bench: cleaning up the Dask workers failed: %s", exc)
        finally:
            self.client.close()
            self._close_cluster()

    def _close_cluster(self) -> None:
        if self.cluster is not None:
            self.cluster.close()
            self.cluster = None


def open_scheduler(spec: str, out: Path, workers: int, captures: str | None = None) -> Scheduler:
    """`local`, `dask` (a LocalCluster of `workers` single-threaded workers) or `tcp://HOST:PORT` (or any address
    dask.distributed accepts: tls://, ucx://, inproc://)."""
    workers = max(1, int(workers))
    if captures is not None:
        captures = str(Path(captures).resolve())
    if spec == "local":
        return LocalScheduler(out, captures, workers)
    if spec == "dask":
        return DaskScheduler(out, captures, workers, None)
    if "://" in spec:
        from urllib.parse import urlsplit

        try:
            parts = urlsplit(spec)
            ok = bool(parts.hostname) and (parts.port is not None or parts.netloc.lower() == parts.hostname)
        except ValueError:
            ok = False
        if not ok or parts.path or parts.query:
            raise SchedulerError(f"{spec!r} is not a Dask scheduler address (tcp://HOST:PORT)")
        return DaskScheduler(out, captures, workers, spec)
    raise SchedulerError(f"unknown scheduler {spec!r}; use local, dask or a Dask scheduler address tcp://HOST:PORT")
