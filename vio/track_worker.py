"""The tracker in a process of its own (issue 18): `python -m vio.track_worker`, fed over pipes by `vio run`.

A thread does not overlap the tracker with the estimator (gtsam's wrapper keeps the GIL through an iSAM2 update:
docs/BENCHMARKS.md, "The two cores, measured"); a second interpreter does. The worker opens the same capture, decodes
and tracks every frame with the same code as the single-process path (`vio.tracking.tracked_frames`, whose tracker
also picks the keyframes), at a lower priority than the estimator (`run.tracker_nice`), and samples each new track's
colour (a thread of its own decodes the next `PREFETCH_FRAMES` images meanwhile, on whatever core the estimator
leaves idle), and sends per frame: the tracks, their ages, the new colours and the image only where the estimator
needs it (keyframes, for the re-identification's descriptors; every frame when a viewer is attached). The pipe is
enlarged so that it holds a few keyframes while the estimator solves. Results are the single-process path's, frame
for frame.

Protocol (length-prefixed pickles, `vio.pipes`): in, one ((capture path, calibration path, options), config,
frames, every image?); out, per frame ("frame", t_ns, image or None, tracks, ages, new colour ids, their RGB,
keyframe?) or ("skip", t_ns, frame index, reason), then ("end",); an error is ("error", one line).
"""

from __future__ import annotations

import fcntl
import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from typing import Any

from vio.children import die_with_parent
from vio.errors import EstimationError, VioError
from vio.pipes import recv, send
from vio.records import Frame

_F_SETPIPE_SZ = 1031  # Linux fcntl: set a pipe's capacity
_PIPE_BYTES = 1 << 20  # 1 MiB: about three 640x480 keyframe images ahead (the default 64 KiB holds none)
PREFETCH_FRAMES = 4  # images decoded ahead in a thread of the worker (vio.tracking.images)


def tracked_in_worker(
    reopen: tuple[str, str | None, dict[str, Any]], cfg: Any, stop: int, every_image: bool
) -> Iterator[tuple[str, Any]]:
    """Start the worker and yield what `vio.tracking.tracked_frames` yields there: ("frame", (frame or None, tracks,
    ages, new colours, keyframe?)) or ("skip", (t_ns, frame index, reason)). Raises VioError when the
    worker reports an error or stops; the worker is killed when the caller stops early."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "vio.track_worker"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        preexec_fn=die_with_parent,  # noqa: PLW1509 - prctl only, see vio.children
    )
    try:
        try:
            fcntl.fcntl(proc.stdout.fileno(), _F_SETPIPE_SZ, _PIPE_BYTES)
        except OSError:  # not Linux, or above /proc/sys/fs/pipe-max-size: the default pipe still works
            pass
        send(proc.stdin, (reopen, cfg, stop, every_image))
        while True:
            try:
                msg = recv(proc.stdout)
            except EOFError:
                raise EstimationError(f"the tracker process stopped (exit code {proc.wait()})") from None
            if msg[0] == "end":
                break
            if msg[0] == "error":
                raise VioError(msg[1])
            if msg[0] == "skip":
                yield "skip", msg[1:]
                continue
            _, t_ns, image, tracks, ages, cids, crgb, keyframe = msg
            frame = None if image is None else Frame(t_ns, 0, image)
            yield "frame", (frame, tracks, ages, (cids, crgb), keyframe)
        proc.wait()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def main() -> int:
    import cv2

    from vio.readers import open_capture
    from vio.tracking import tracked_frames

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle; it stops this process
    cv2.setNumThreads(1)
    stdin, stdout = sys.stdin.buffer, sys.stdout.buffer
    (path, calib, options), cfg, stop, every_image = recv(stdin)
    if cfg.run.tracker_nice > 0:
        os.nice(cfg.run.tracker_nice)
    try:
        cap = open_capture(path, calib, **options)
        for kind, payload in tracked_frames(cap, cfg, stop, PREFETCH_FRAMES):
            if kind == "skip":
                send(stdout, ("skip", *payload))
                continue
            frame, tracks, ages, (ids, rgb), keyframe = payload
            image = frame.image if (every_image or keyframe) else None
            send(stdout, ("frame", tracks.t_ns, image, tracks, ages, ids, rgb, keyframe))
    except VioError as exc:
        send(stdout, ("error", str(exc)))
        return 1
    except BrokenPipeError:
        return 1
    send(stdout, ("end",))
    return 0


if __name__ == "__main__":
    sys.exit(main())
