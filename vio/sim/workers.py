"""Render worker processes: fresh interpreters (`python -m vio.sim.workers`) fed over pipes.

Not `multiprocessing`: forking a process whose OpenCV thread pool has run can deadlock the child, and the
spawn/fork-server methods re-run the caller's `__main__` script in every worker (a script without a main guard
then never finishes). Frame i goes to worker i % W; results are read back in frame order, so the output does not
depend on W. Protocol: length-prefixed pickles; the first message is (scene, camera), then one (pose, seed) per
frame, answered by the frame's PNG bytes, or one ("phone", poses (B, S, 4, 4), band rows (B + 1,)) per
rolling-shutter frame, answered by its float32 radiance (`vio.sim.phone.render_radiance`); an empty message ends
the worker.
"""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from typing import Any

import numpy as np

from vio.errors import SimulationError
from vio.pipes import recv, send


def render_in_workers(scene, camera, jobs: list[tuple], workers: int) -> Iterator[Any]:
    """Yield the answer to each job in order (PNG bytes of a (world_T_cam, seed) job, the radiance of a phone
    job), rendered by `workers` processes."""
    procs = [
        subprocess.Popen([sys.executable, "-m", "vio.sim.workers"], stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        for _ in range(workers)
    ]
    try:
        for p in procs:
            send(p.stdin, (scene, camera))
        ahead = 2  # jobs queued per worker
        for i in range(min(len(jobs), ahead * workers)):
            send(procs[i % workers].stdin, jobs[i])
        for i in range(len(jobs)):
            p = procs[i % workers]
            try:
                png = recv(p.stdout)
            except EOFError:
                raise SimulationError(f"render worker {i % workers} stopped (exit code {p.wait()})") from None
            nxt = i + ahead * workers
            if nxt < len(jobs):
                send(p.stdin, jobs[nxt])
            yield png
        for p in procs:
            send(p.stdin, None)
            p.wait()
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()


def main() -> int:
    import cv2

    from vio.sim.phone import render_radiance
    from vio.sim.render import Renderer
    from vio.writers.asl import encode_png

    cv2.setNumThreads(1)
    stdin, stdout = sys.stdin.buffer, sys.stdout.buffer
    scene, camera = recv(stdin)
    renderer = Renderer(scene, camera)
    while True:
        job = recv(stdin)
        if job is None:
            return 0
        if len(job) == 3 and job[0] == "phone":
            send(stdout, render_radiance(renderer, job[1], job[2]))
            continue
        world_T_cam, seed = job
        send(stdout, encode_png(renderer.render(world_T_cam, np.random.default_rng(seed))))


if __name__ == "__main__":
    sys.exit(main())
