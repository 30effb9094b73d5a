"""Per-view work of the model stage on every core: OpenCV's SIFT, warps and filters release the GIL, so threads
overlap them. Results come back in input order, identical to a serial loop's."""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")


def workers() -> int:
    """Threads for per-view work: the machine's cores (VIO_MODEL_THREADS overrides; 1 runs serially)."""
    env = os.environ.get("VIO_MODEL_THREADS", "").strip()
    if env.isdigit() and int(env) > 0:
        return int(env)
    return max(1, os.cpu_count() or 1)


def ordered_map(fn: Callable[[T], R], items: Iterable[T], ahead: int | None = None) -> Iterator[R]:
    """fn over items on `workers()` threads, yielded in input order; at most `ahead` results (default: the thread
    count) wait to be taken, so a caller that consumes one at a time holds few of them in memory."""
    n = workers()
    if n == 1:
        yield from map(fn, items)
        return
    ahead = max(ahead or n, 1)
    with ThreadPoolExecutor(max_workers=n) as pool:
        pending: deque[Future[R]] = deque()
        for item in items:
            pending.append(pool.submit(fn, item))
            if len(pending) > ahead:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()
