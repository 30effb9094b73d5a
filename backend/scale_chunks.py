"""Bounded memory for the fixed lag (issue 18): the scale's uncertainty chunk by chunk as the run goes, and the
factors of finished chunks let go.

Without `--refine`, `GraphState.all_factors` serves only the scale's uncertainty at the end
(`backend/uncertainty.py`), which on a long run already cuts the trajectory into chunks of at most
`CHUNK_KEYFRAMES` consecutive keyframes and combines their sigmas by inverse variance. `ScaleChunks` does the same
while the run goes: once the keyframes of the next chunk and `CHUNK_KEYFRAMES / 2` after it have left the fixed
lag's window (their estimates are final), the chunk's graph gives its sigma and every factor on its keyframes is
dropped, with the preintegrations that only those factors need. At the end the keyframes not yet in a closed chunk
(between half a chunk and a chunk and a half, plus the window) are chunked as before. The memory the factors hold
is then a chunk and a half, not the whole capture. While the run goes `GraphState.all_factors` is the block being
filled; `finish` (the estimator's) puts every kept factor back in it.

The factors are kept in blocks, a new one every `BLOCK_KEYFRAMES` keyframes' updates (`mark`): a factor added at
a keyframe's update is on that keyframe or on earlier ones, so a block whose next block began at or before a
closed chunk's end holds only factors of closed chunks and goes whole, in one step whatever its size (the factors
of a later block that reach into a closed chunk stay until their block goes; every chunk's graph leaves out
factors across its border). A chunk's sigma costs about a second of CPU (the elimination of its graph), too long
for a keyframe's update, so it is computed in a forked copy of the process (copy on write: the graph is not
copied or serialised) that sends the result back through a pipe, read at the end of the run; the keyframe that
closes a chunk pays for the fork and little else. Freeing the factors is not free either (about 2 us a factor), so
the blocks let go are freed one per keyframe's update. Measured on the 10-minute orbit, the first two closes took
13 and 21 ms (the fork 6 ms); 99-122 ms with the blocks freed at once, and 135-143 ms before the blocks, when the
factors that remain were copied one by one. Without `os.fork` the sigma is computed in place.

What differs from the end-of-run computation: the chunk borders (chunks of exactly `CHUNK_KEYFRAMES` first, where
the end-of-run split makes equal ones), and the landmarks' weak priors, which are dropped with the chunk and added
back in each chunk's graph at the landmark's value (the same information: a prior's Hessian does not depend on its
mean). A run short enough for one chunk (the 60 s orbit) never closes one and is unchanged.
"""

from __future__ import annotations

import logging
import os
import pickle
import select
import signal

import gtsam

from backend.keys import X
from backend.smoother import Smoother, SolverFailure
from backend.uncertainty import CHUNK_KEYFRAMES, ScaleUncertainty, _chunk_graphs, _sub_scale, combine, scale_uncertainty

log = logging.getLogger(__name__)

_CHILD_TIMEOUT_S = 300.0  # a chunk's fork that has not answered by the end of the run after this is stopped
BLOCK_KEYFRAMES = 25  # keyframes' updates whose factors share a block (module docstring)


class ScaleChunks:
    """Closes chunks of final keyframes as the run goes (module docstring); `finish` gives the run's sigma."""

    def __init__(
        self,
        landmark_prior_sigma_m: float,
        compute: bool,
        chunk_keyframes: int = CHUNK_KEYFRAMES,
        block_keyframes: int = BLOCK_KEYFRAMES,
    ) -> None:
        self.prior_sigma_m = float(landmark_prior_sigma_m)
        self.compute = compute  # False: the factors are dropped and no sigma is computed (scale_uncertainty off)
        self.chunk = int(chunk_keyframes)
        self.block = int(block_keyframes)
        self.start = 0  # position, in the sorted keyframes, of the first keyframe not in a closed chunk
        self.results: list[ScaleUncertainty | None] = []
        self._pending: list[tuple[int, int, int]] = []  # (place in results, pid, pipe's read end): in a fork
        self._blocks: list[tuple[int, gtsam.NonlinearFactorGraph]] = []  # (first keyframe added, factors): full
        self._first = -1  # the first keyframe whose update adds to the current block (-1: the start's factors)
        self._updates = 0  # keyframes' updates in the current block
        self._gone: list[gtsam.NonlinearFactorGraph] = []  # blocks let go, freed one per keyframe (`mark`)
        self.num_dropped = 0  # factors let go
        self.fork = hasattr(os, "fork")

    def mark(self, k: int, current: gtsam.NonlinearFactorGraph) -> gtsam.NonlinearFactorGraph:
        """Keyframe k's update begins; `current` holds the factors added since the last block began. Returns the
        graph that k's factors go into: `current`, or a new one when a block is full (`current` is then kept)."""
        self._updates += 1
        if self._gone:
            self._gone.pop()  # freeing a block's factors takes a few ms: one block per keyframe
        if self._updates <= self.block:
            return current
        self._blocks.append((self._first, current))
        self._first, self._updates = k, 1
        return gtsam.NonlinearFactorGraph()

    def whole(self, current: gtsam.NonlinearFactorGraph) -> gtsam.NonlinearFactorGraph:
        """Every factor kept: the full blocks and `current`, in the order they were added."""
        if not self._blocks:
            return current
        graph = gtsam.NonlinearFactorGraph()
        for _, block in self._blocks:
            graph.push_back(block)
        graph.push_back(current)
        return graph

    def gather(self, current: gtsam.NonlinearFactorGraph) -> gtsam.NonlinearFactorGraph:
        """At the end of the run: `whole`, which becomes the caller's one block (a later `whole` is just it)."""
        graph = self.whole(current)
        self._blocks, self._first, self._updates = [], -1, 0
        return graph

    def due(self, num_keyframes: int) -> bool:
        """Enough keyframes for `maybe_close` to look (cheap; the smoother decides when they left it)."""
        return num_keyframes > self.start + self.chunk + self.chunk // 2

    def maybe_close(
        self,
        current: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        keyframes: list[int],
        smoother: Smoother,
        pims: dict[int, object],
    ) -> bool:
        """When the next chunk can be closed (see the module docstring): its sigma is kept, the blocks of closed
        chunks and their preintegrations go, and True is returned. `current`: the block being filled;
        `keyframes`: every keyframe so far in order; `values`: the latest value of every variable (final for
        keyframes out of the window)."""
        last = self.start + self.chunk + self.chunk // 2
        if not self.due(len(keyframes)) or smoother.has(X(keyframes[last])):
            return False
        chunk = [k for k in keyframes[self.start : self.start + self.chunk] if values.exists(X(k))]
        end = keyframes[self.start + self.chunk]  # the first keyframe after the chunk
        if self.compute and len(chunk) >= 4:
            self._sigma(current, values, smoother, chunk, f"chunk {self.start // self.chunk + 1}")
        firsts = [first for first, _ in self._blocks[1:]] + [self._first]
        gone = sum(1 for nxt in firsts if nxt <= end)  # blocks whose next block began by `end`
        self.num_dropped += sum(block.size() for _, block in self._blocks[:gone])
        self._gone += [block for _, block in self._blocks[:gone]]
        del self._blocks[:gone]
        for k in [k for k in pims if k < end]:
            del pims[k]
        self.start += self.chunk
        log.debug("scale chunk closed before keyframe %d: %d blocks let go", end, gone)
        return True

    def _sigma(
        self, current: gtsam.NonlinearFactorGraph, values: gtsam.Values, smoother: Smoother, chunk: list[int], name: str
    ) -> None:
        """The chunk's sigma into `results`, computed in a forked process when possible (module docstring)."""
        pin = self.start > 0

        def compute() -> ScaleUncertainty | None:
            latest = self._current(values, smoother)
            (sub,) = _chunk_graphs(self.whole(current), latest, [chunk], pin, self.prior_sigma_m)
            return _sub_scale(sub, latest, chunk, 5, name)

        if self.fork:
            try:
                read, write = os.pipe()
                pid = os.fork()
            except OSError as exc:
                log.debug("scale chunk: no fork (%s); computed in place", exc)
            else:
                if pid == 0:  # the child: compute, answer, leave without running the parent's exit handlers
                    code = 0
                    try:
                        os.close(read)
                        with os.fdopen(write, "wb") as pipe:
                            pickle.dump(compute(), pipe)
                    except BaseException:  # noqa: BLE001 - a child must never return into the parent's code
                        code = 1
                    os._exit(code)
                os.close(write)
                self._pending.append((len(self.results), pid, read))
                self.results.append(None)  # its place, filled by `_collect`
                return
        self.results.append(compute())

    def _collect(self) -> None:
        """The forked chunks' answers, in their places in `results`."""
        for i, pid, read in self._pending:
            data = b""
            with os.fdopen(read, "rb") as pipe:
                if select.select([pipe], [], [], _CHILD_TIMEOUT_S)[0]:
                    data = pipe.read()
                else:
                    os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            try:
                self.results[i] = pickle.loads(data) if data else None
            except (pickle.UnpicklingError, EOFError):
                self.results[i] = None
            if self.results[i] is None:
                log.warning("scale uncertainty: chunk %d left out (its computation gave no answer)", i + 1)
        self._pending = []

    @staticmethod
    def _current(values: gtsam.Values, smoother: Smoother) -> gtsam.Values:
        """`values` with the smoother's current estimate of the variables it still holds."""
        merged = gtsam.Values(values)
        try:
            merged.insert_or_assign(smoother.estimate())
        except SolverFailure as exc:
            log.debug("scale chunk: the smoother's estimate failed (%s); using the last values", exc)
        return merged

    def finish(
        self, current: gtsam.NonlinearFactorGraph, values: gtsam.Values, keyframes: list[int], smoother: Smoother
    ) -> ScaleUncertainty | None:
        """The run's sigma: the closed chunks and the keyframes after them (chunked as `scale_uncertainty` does);
        `current`: the block being filled."""
        self._collect()
        factors = self.whole(current)
        if not self.results and self.start == 0:
            return scale_uncertainty(factors, values, keyframes, chunk_keyframes=self.chunk)
        tail = scale_uncertainty(
            factors,
            values,
            keyframes[self.start :],
            chunk_keyframes=self.chunk,
            pin_first=True,
            landmark_prior_sigma_m=self.prior_sigma_m,
        )
        return combine([*self.results, tail])
