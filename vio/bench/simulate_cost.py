"""Cost of `vio simulate`: wall time, CPU time and peak memory of the whole process tree.

`/usr/bin/time -v` reports the peak memory of the largest single process, not of the tree (frames are rendered in
worker processes, `vio.sim.workers`), so this samples /proc every 0.1 s for the command and all its descendants.
CPU in seconds, memory in MiB (`peak_rss_mb`, summed over the tree).

    .venv/bin/python -m vio.bench.simulate_cost --out /tmp/o60 -- orbit --duration 60
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

_TICK = os.sysconf("SC_CLK_TCK")
_PAGE = os.sysconf("SC_PAGE_SIZE")


def _children(pid: int) -> list[int]:
    out = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            out += [int(c) for c in (task / "children").read_text().split()]
        except OSError:
            pass
    return out


def _tree(pid: int) -> list[int]:
    todo, seen = [pid], []
    while todo:
        p = todo.pop()
        seen.append(p)
        todo += _children(p)
    return seen


def _stat(pid: int) -> tuple[float, int] | None:
    """(user + system CPU seconds, resident bytes) of one process."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        rss_pages = int(Path(f"/proc/{pid}/statm").read_text().split()[1])
    except (OSError, IndexError, ValueError):
        return None
    return (int(fields[11]) + int(fields[12])) / _TICK, rss_pages * _PAGE


def measure(cmd: list[str]) -> dict[str, float]:
    """Run cmd; return wall_s, cpu_s (all processes), peak_rss_mb (sum over the tree), load averages."""
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd)
    cpu: dict[int, float] = {}
    peak = 0
    while proc.poll() is None:
        total = 0
        for pid in _tree(proc.pid):
            st = _stat(pid)
            if st is not None:
                cpu[pid] = max(cpu.get(pid, 0.0), st[0])
                total += st[1]
        peak = max(peak, total)
        time.sleep(0.1)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"command failed with exit code {proc.returncode}: {' '.join(cmd)}")
    return {
        "wall_s": wall,
        "cpu_s": sum(cpu.values()),
        "peak_rss_mb": peak / 2**20,
        "load_before": load0,
        "load_after": os.getloadavg()[0],
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, help="capture folder (replaced)")
    ap.add_argument("simulate_args", nargs="+", help="arguments of `vio simulate` after --")
    args = ap.parse_args(argv)
    vio = str(Path(sys.executable).with_name("vio"))
    r = measure([vio, "simulate", *args.simulate_args, "--out", args.out, "--force"])
    print(
        f"wall {r['wall_s']:.1f} s, CPU {r['cpu_s']:.1f} s (all processes), peak RSS {r['peak_rss_mb']:.0f} MB "
        f"(process tree), load average {r['load_before']:.1f} -> {r['load_after']:.1f} on {os.cpu_count()} cores"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
