"""How the cost of `vio run` grows with the capture: per-keyframe latency and resident memory per minute.

`python -m vio.bench.cost_over_time CAPTURE --out DIR [--preset NAME] [--set key=value ...]` runs the estimator on
one capture in this process (as `vio run` does) while a thread samples the process's resident memory twice a second,
tagged with the capture time of the latest frame the estimator took (from the run's health monitor, so also when the
tracker runs in a process of its own, `run.tracker_process`; that process's memory is sampled beside, as
`children_memory`). Each keyframe's update time comes from the run's own record (`keyframe_ms`, wall clock, and
`step_cpu_ms`, this process's CPU time; ms), placed at its keyframe's capture time. Written to DIR: the run's files
in `run/`, `cost.json` (per minute of capture: keyframes, latency p50/p95/p99/max ms, wall and CPU, peak and last
resident memory MiB; the whole run's wall time, real-time factor, peak memory, the load average, ATE against the
ground truth when the capture has one; the smoother's background steps between keyframes, `smoother.background`)
and `cost.png` (latency and memory over the capture).

Replay runs ahead of real time, so a keyframe's update time leaves out the wait behind the work before it (a
background step that outlasts the gap to the next keyframe delays it). `live_*` gives each keyframe's latency had
the frames come at their capture times to a main thread as fast as this run's (`live_latency`, from the wall
intervals of the updates and the background steps in the run's main thread); the main thread's other work per
frame is left out. Its per-minute rows leave out the start (the start window's solve and the keyframes that queue
behind it), which `live_start` reports on its own.

Wall-clock latencies are only comparable between runs made under the same load (the load average at the start and
the end is recorded beside them); CPU latencies much less depend on what else the machine runs.
"""

from __future__ import annotations

import argparse
import logging
import os
import resource
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from vio.atomic import ensure_dir, write_json

log = logging.getLogger(__name__)

SAMPLE_S = 0.5  # memory sampling period, s
_PAGE_MIB = os.sysconf("SC_PAGE_SIZE") / 2**20


def rss_mib(pid: int | str = "self") -> float:
    """Resident memory of this process (or of process `pid`) now, MiB; 0 when it is gone."""
    try:
        with open(f"/proc/{pid}/statm") as f:
            return int(f.read().split()[1]) * _PAGE_MIB
    except (FileNotFoundError, ProcessLookupError, IndexError, ValueError):
        return 0.0


def children_rss_mib() -> float:
    """Resident memory of this process's child processes now (the tracker's, `run.tracker_process`), MiB."""
    pids: list[str] = []
    for task in Path("/proc/self/task").iterdir():
        try:
            pids += (task / "children").read_text().split()
        except OSError:
            continue
    return sum(rss_mib(pid) for pid in pids)


class MemorySampler:
    """A daemon thread recording (capture time s, resident MiB) every `SAMPLE_S` while a run goes."""

    def __init__(self) -> None:
        self.t_capture_s = 0.0  # capture time of the frame being read, s from the first frame
        self.after_last = False  # the last frame was read: what follows is the run's end (final solve, files)
        self.samples: list[tuple[float, float, bool]] = []
        self.children: list[tuple[float, float]] = []  # (capture time s, child processes' resident MiB)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)

    def __enter__(self) -> MemorySampler:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self.samples.append((self.t_capture_s, rss_mib(), True))

    def _loop(self) -> None:
        while not self._stop.wait(SAMPLE_S):
            self.samples.append((self.t_capture_s, rss_mib(), self.after_last))
            self.children.append((self.t_capture_s, children_rss_mib()))


def per_minute(t_s: np.ndarray, values: np.ndarray, minute_s: float = 60.0) -> list[dict[str, float]]:
    """Latency percentiles (ms) of the keyframes in each minute of capture time (t_s from the first frame)."""
    out = []
    for m in range(int(np.ceil(max(t_s.max(initial=0.0), 1e-9) / minute_s))):
        x = values[(t_s >= m * minute_s) & (t_s < (m + 1) * minute_s)]
        if not x.size:
            continue
        row = {"minute": m + 1, "keyframes": int(x.size)}
        row.update({f"p{q}": float(np.percentile(x, q)) for q in (50, 95, 99)})
        row["max"] = float(x.max())
        out.append(row)
    return out


class MainThreadTimeline:
    """Wall intervals of the estimator's work in the run's main thread: each keyframe's update and each background
    step between keyframes (`VioEstimator.add_keyframe`, `VioEstimator.background`; a background step run inside a
    keyframe's update, when the caller did not run it, counts as that update's)."""

    def __init__(self) -> None:
        self.keyframes: list[tuple[int, float]] = []  # (keyframe time ns, update wall s)
        self.after: list[float] = []  # background wall s after each keyframe, before the next one
        self._inside = False

    def __enter__(self) -> MainThreadTimeline:
        from backend.estimator import VioEstimator

        self._saved = (VioEstimator.add_keyframe, VioEstimator.background)
        add_keyframe, background = self._saved
        timeline = self

        def timed_add_keyframe(est: Any, t_ns: int, *args: Any, **kwargs: Any) -> Any:
            t0 = time.perf_counter()
            timeline._inside = True
            try:
                return add_keyframe(est, t_ns, *args, **kwargs)
            finally:
                timeline._inside = False
                timeline.keyframes.append((int(t_ns), time.perf_counter() - t0))
                timeline.after.append(0.0)

        def timed_background(est: Any) -> None:
            t0 = time.perf_counter()
            try:
                background(est)
            finally:
                if not timeline._inside and timeline.after:
                    timeline.after[-1] += time.perf_counter() - t0

        VioEstimator.add_keyframe, VioEstimator.background = timed_add_keyframe, timed_background
        return self

    def __exit__(self, *exc: object) -> None:
        from backend.estimator import VioEstimator

        VioEstimator.add_keyframe, VioEstimator.background = self._saved


def live_latency(arrive_s: np.ndarray, update_s: np.ndarray, after_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each keyframe's latency had the frames come at their capture times (`arrive_s`) to a main thread as fast as
    this run's: the keyframe's update starts when its frame has come and the thread has finished the previous
    keyframe and the background work after it (`after_s`), and its latency runs from its capture time to the end of
    its update. Returns (latency s, wait s: how long it queued behind earlier work). Replay runs ahead of real time,
    so its own update times leave out this queueing."""
    latency, wait = np.empty(len(arrive_s)), np.empty(len(arrive_s))
    free = -np.inf
    for i, (a, d, b) in enumerate(zip(arrive_s, update_s, after_s, strict=True)):
        start = max(a, free)
        wait[i] = start - a
        latency[i] = start + d - a
        free = start + d + b
    return latency, wait


def start_queue(kf_t_ns: np.ndarray, wait_s: np.ndarray, start_t_ns: int | None) -> dict[str, int]:
    """The start in the live timeline: the index of the keyframe whose update solved the start window (its time
    `start_t_ns`; the first keyframe when None) and the index of the first keyframe after it that did not queue."""
    index = int(np.searchsorted(kf_t_ns, start_t_ns)) if start_t_ns is not None else 0
    index = max(0, min(index, len(kf_t_ns) - 1))
    drained = index + 1
    while drained < len(wait_s) and wait_s[drained] > 0:
        drained += 1
    return {"index": index, "drained_index": drained}


def measure(capture: str, out: Path, presets: list[str], overrides: list[str]) -> dict[str, Any]:
    """Run the estimator on `capture` into `out/run` and return the cost record (see the module docstring)."""
    from vio import pipeline
    from vio.config import load_config
    from vio.readers import open_capture

    cfg = load_config(None, overrides + ["run.progress=false"], presets)
    cap = open_capture(capture)
    t0_ns = int(cap.frame_t_ns[0])
    load_start = os.getloadavg()
    with MemorySampler() as sampler:
        last = cap.num_frames - 1 if cfg.run.max_frames <= 0 else min(cap.num_frames, cfg.run.max_frames) - 1
        last_t_ns = int(cap.frame_t_ns[last])
        monitor = pipeline.HealthMonitor

        class TaggingMonitor(monitor):
            """The run's health monitor, which also tells the sampler the capture time of every frame the
            estimator takes (the tracker's images are not read in this process when it runs in its own)."""

            def frame(self, t_ns: int, num_tracked: int) -> None:
                sampler.t_capture_s = (int(t_ns) - t0_ns) * 1e-9
                sampler.after_last = int(t_ns) >= last_t_ns
                super().frame(t_ns, num_tracked)

        pipeline.HealthMonitor = TaggingMonitor
        try:
            with MainThreadTimeline() as timeline:
                t_wall = time.perf_counter()
                result = pipeline.run_capture(capture, out / "run", cfg)
                wall_s = time.perf_counter() - t_wall
        finally:
            pipeline.HealthMonitor = monitor
    stats = result.stats
    steps = np.asarray(stats.keyframe_ms[1:], float)  # the first entry is the whole start window
    kf_t = np.sort(np.array([t for _, t, _ in stats.keyframe_projections], np.int64))
    t_s = (kf_t[len(kf_t) - len(steps) :] - t0_ns) * 1e-9
    samples = np.asarray(sampler.samples, float).reshape(-1, 3)
    mem, end = samples[samples[:, 2] == 0, :2], samples[samples[:, 2] == 1, 1]
    minutes = per_minute(t_s, steps)
    cpu = per_minute(t_s, np.asarray(stats.step_cpu_ms, float))
    kf = np.asarray([t for t, _ in timeline.keyframes], np.int64)
    live_s, wait_s = live_latency(
        (kf - t0_ns) * 1e-9, np.asarray([d for _, d in timeline.keyframes]), np.asarray(timeline.after)
    )
    live_t = (kf - t0_ns) * 1e-9
    start = start_queue(kf, wait_s, int(kf_t[len(kf_t) - len(steps) - 1]) if len(kf_t) > len(steps) else None)
    after = np.arange(len(kf)) >= start["drained_index"]  # the start's solve and what queued behind it apart
    live = per_minute(live_t[after], 1e3 * live_s[after])
    for row, row_cpu in zip(minutes, cpu, strict=True):
        row["cpu"] = {q: row_cpu[q] for q in ("p50", "p95", "p99", "max")}
        row["live"] = next(
            ({q: r[q] for q in ("p50", "p95", "p99", "max")} for r in live if r["minute"] == row["minute"]), None
        )
        m = row["minute"]
        inside = mem[(mem[:, 0] >= (m - 1) * 60.0) & (mem[:, 0] < m * 60.0), 1]
        row["rss_peak_mib"] = float(inside.max()) if inside.size else float("nan")
        row["rss_last_mib"] = float(inside[-1]) if inside.size else float("nan")
    record: dict[str, Any] = {
        "capture": str(capture),
        "presets": presets,
        "overrides": overrides,
        "smoother": cfg.smoother.kind,
        "span_s": result.summary["span_s"],
        "wall_s": wall_s,
        "realtime_factor": result.summary["span_s"] / wall_s,
        "cpu_s": result.summary["cpu_time_s"],
        "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "end_rss_peak_mib": float(end.max()) if end.size else float("nan"),  # from the last frame read to the end
        "children_rss_peak_mib": max((m for _, m in sampler.children), default=0.0),  # the tracker, a scale chunk fork
        "load_average_start": load_start[0],
        "load_average_end": os.getloadavg()[0],
        "keyframes": int(steps.size),
        "smoother_variables_max": result.summary.get("smoother_variables_max"),
        "recoveries": len(stats.recoveries),
        "refine": result.summary["refine"],
        "per_minute": minutes,
        "keyframe_t_s": t_s.round(3).tolist(),
        "keyframe_ms": steps.round(2).tolist(),
        "keyframe_cpu_ms": np.round(stats.step_cpu_ms, 2).tolist(),
        "background": _background(stats.background_ms),
        # had the frames come at their capture times (`live_latency`): per keyframe, ms, every keyframe; the
        # per-minute "live" rows leave out the start (the start window's solve and the keyframes queued behind it)
        "live_t_s": live_t.round(3).tolist(),
        "live_ms": (1e3 * live_s).round(2).tolist(),
        "live_wait_ms": (1e3 * wait_s).round(2).tolist(),
        "live_start": None
        if not len(kf)
        else {
            "t_s": float(live_t[start["index"]]),
            "latency_ms": float(1e3 * live_s[start["index"]]),
            "queued_keyframes": start["drained_index"] - start["index"] - 1,
            "queued_max_ms": float(1e3 * live_s[start["index"] + 1 : start["drained_index"]].max(initial=0.0)),
            "drained_t_s": float(live_t[min(start["drained_index"], len(kf) - 1)]),
        },
        "background_after_ms": (1e3 * np.asarray(timeline.after)).round(2).tolist(),  # after each keyframe
        "memory": mem.round(2).tolist(),  # (capture time s, resident MiB) while the frames are read
        "end_memory": samples[samples[:, 2] == 1, :2].round(2).tolist(),  # the same after the last frame
        "children_memory": np.round(sampler.children, 2).tolist(),  # (capture time s, child processes' MiB)
    }
    if cap.ground_truth is not None:
        record["ate_se3_m"], record["scale"] = _ate(cap, out / "run" / "trajectory.tum")
    return record


def _background(steps: tuple[tuple[float, float], ...]) -> dict[str, Any]:
    """The smoother's background steps between keyframes (`smoother.background`): count, wall and CPU ms
    percentiles, CPU s in all."""
    if not steps:
        return {"count": 0}
    wall, cpu = np.asarray(steps, float).T
    out: dict[str, Any] = {"count": len(steps), "cpu_total_s": float(cpu.sum() * 1e-3)}
    for name, x in (("wall", wall), ("cpu", cpu)):
        out[name] = {f"p{q}": float(np.percentile(x, q)) for q in (50, 95, 99)} | {"max": float(x.max())}
    return out


def _ate(cap: Any, trajectory: Path) -> tuple[float, float]:
    """ATE (SE3, m) and Sim3 scale of the run's trajectory against the capture's ground truth."""
    from vio.metrics import evaluate
    from vio.trajio import read_trajectory

    gt_csv = Path(cap.root) / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    m = evaluate(read_trajectory(gt_csv), read_trajectory(trajectory), align="se3")
    return m["ate_rmse_m"], m["scale"]


def plot(record: dict[str, Any], path: Path, label: str) -> None:
    """Latency of every keyframe and resident memory over the capture, one picture."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from vio.atomic import atomic_open

    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    ax1.plot(record["keyframe_t_s"], record["keyframe_ms"], ".", ms=2, label="wall")
    ax1.plot(record["keyframe_t_s"], record["keyframe_cpu_ms"], ".", ms=2, label="CPU")
    if record.get("live_ms"):
        ax1.plot(record["live_t_s"], record["live_ms"], ".", ms=2, label="at real time (queued behind earlier work)")
    ax1.set_yscale("log")
    ax1.set_ylabel("per keyframe, ms")
    ax1.legend(loc="upper left")
    ax1.set_title(label)
    mem = np.asarray(record["memory"]).reshape(-1, 2)
    ax2.plot(mem[:, 0], mem[:, 1], label="while frames are read")
    if record.get("end_memory"):
        ax2.plot(*np.asarray(record["end_memory"]).T, "r.", ms=3, label="after the last frame (final solve, files)")
    children = np.asarray(record.get("children_memory", [])).reshape(-1, 2)
    if children.size and children[:, 1].max() > 0:
        ax2.plot(children[:, 0], children[:, 1], label="child processes: the tracker, a scale chunk's fork")
    ax2.legend(loc="upper left")
    ax2.set_ylabel("resident memory, MiB")
    ax2.set_xlabel("capture time, s")
    for ax in (ax1, ax2):
        ax.grid(True, alpha=0.3)
    fig.tight_layout()
    with atomic_open(path, "wb") as f:
        fig.savefig(f, format="png", dpi=90)
    plt.close(fig)


def plot_compare(paths: list[str], labels: list[str], out: str) -> None:
    """Several runs' `cost.json` in one picture: per-keyframe CPU latency and resident memory over the capture."""
    import json

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from vio.atomic import atomic_open

    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    for path, label in zip(paths, labels, strict=True):
        record = json.loads(Path(path).read_text())
        ax1.plot(record["keyframe_t_s"], record["keyframe_cpu_ms"], ".", ms=2, label=label)
        mem = np.asarray(record["memory"]).reshape(-1, 2)
        ax2.plot(mem[:, 0], mem[:, 1], label=label)
    ax1.set_yscale("log")
    ax1.set_ylabel("keyframe update, CPU ms")
    ax2.set_ylabel("resident memory, MiB")
    ax2.set_xlabel("capture time, s")
    for ax in (ax1, ax2):
        ax.grid(True, alpha=0.3)
        ax.legend(loc="upper left", markerscale=4)
    fig.tight_layout()
    with atomic_open(out, "wb") as f:
        fig.savefig(f, format="png", dpi=90)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m vio.bench.cost_over_time", description=__doc__.split("\n")[0])
    ap.add_argument("capture")
    ap.add_argument("--out", required=True)
    ap.add_argument("--preset", action="append", default=[])
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    out = ensure_dir(args.out)
    record = measure(args.capture, out, args.preset, args.overrides)
    write_json(out / "cost.json", record)
    plot(record, out / "cost.png", f"{Path(args.capture).name}: {record['smoother']} {' '.join(args.overrides)}")
    for row in record["per_minute"]:
        print(
            f"minute {row['minute']}: {row['keyframes']} keyframes, latency ms p50 {row['p50']:.0f} p95 "
            f"{row['p95']:.0f} p99 {row['p99']:.0f} max {row['max']:.0f} (CPU p95 {row['cpu']['p95']:.0f} p99 "
            f"{row['cpu']['p99']:.0f} max {row['cpu']['max']:.0f}), RSS peak {row['rss_peak_mib']:.0f} MiB"
        )
        if row.get("live"):
            live = row["live"]
            print(
                f"          at real time: latency ms p50 {live['p50']:.0f} p95 {live['p95']:.0f} p99 "
                f"{live['p99']:.0f} max {live['max']:.0f}"
            )
    st = record["live_start"]
    if st:
        print(
            f"the start at real time: the start window's solve done {st['latency_ms']:.0f} ms after its keyframe "
            f"({st['t_s']:.2f} s), {st['queued_keyframes']} keyframes queued behind it (at most "
            f"{st['queued_max_ms']:.0f} ms), none from {st['drained_t_s']:.2f} s on"
        )
    bg = record["background"]
    if bg["count"]:
        print(
            f"background steps between keyframes: {bg['count']}, ms p50 {bg['wall']['p50']:.0f} p95 "
            f"{bg['wall']['p95']:.0f} max {bg['wall']['max']:.0f} (CPU p95 {bg['cpu']['p95']:.0f}), "
            f"{bg['cpu_total_s']:.1f} CPU s in all"
        )
    ate = f", ATE {1e3 * record['ate_se3_m']:.2f} mm" if "ate_se3_m" in record else ""
    print(
        f"wall {record['wall_s']:.0f} s ({record['realtime_factor']:.2f}x real time), peak RSS "
        f"{record['peak_rss_mib']:.0f} MiB (after the last frame {record['end_rss_peak_mib']:.0f}; child "
        f"processes {record['children_rss_peak_mib']:.0f}), load "
        f"{record['load_average_start']:.1f}-{record['load_average_end']:.1f}{ate}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
