"""Bounded memory for the fixed lag (issue 18): the scale's uncertainty chunk by chunk as the run goes, and the
factors of finished chunks let go.

Without `--refine`, `GraphState.all_factors` serves only the scale's uncertainty at the end
(`backend/uncertainty.py`), which on a long run already cuts the trajectory into chunks of at most
`CHUNK_KEYFRAMES` consecutive keyframes and combines their sigmas by inverse variance. `ScaleChunks` does the same
while the run goes: once the keyframes of the next chunk and `CHUNK_KEYFRAMES / 2` after it have left the fixed
lag's window (their estimates are final), the chunk's graph gives its sigma and every factor on its keyframes is
dropped, with the preintegrations that only those factors need. At the end the keyframes not yet in a closed chunk
(between half a chunk and a chunk and a half, plus the window) are chunked as before. The memory the factors hold
is then a chunk and a half, not the whole capture.

A chunk's sigma costs about a second of CPU (the elimination of its graph), too long for a keyframe's update, so
it is computed in a forked copy of the process (copy on write: the graph is not copied or serialised) that sends
the result back through a pipe, read at the end of the run; the keyframe that closes a chunk only pays for the
fork and for keeping the factors that remain, whose positions it knows from `mark` (the graph's size at the start
of each keyframe's update: a factor added at a keyframe's update is on that keyframe or on the few before it).
Without `os.fork` the sigma is computed in place.

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
_LOOK_BACK = 100  # keyframes: a factor added at a keyframe's update is on it or on keyframes at most this far back


class ScaleChunks:
    """Closes chunks of final keyframes as the run goes (module docstring); `finish` gives the run's sigma."""

    def __init__(self, landmark_prior_sigma_m: float, compute: bool, chunk_keyframes: int = CHUNK_KEYFRAMES) -> None:
        self.prior_sigma_m = float(landmark_prior_sigma_m)
        self.compute = compute  # False: the factors are dropped and no sigma is computed (scale_uncertainty off)
        self.chunk = int(chunk_keyframes)
        self.start = 0  # position, in the sorted keyframes, of the first keyframe not in a closed chunk
        self.results: list[ScaleUncertainty | None] = []
        self._pending: list[tuple[int, int, int]] = []  # (place in results, pid, pipe's read end): in a fork
        self._marks: dict[int, int] = {}  # keyframe -> the factor graph's size when its update began
        self.num_dropped = 0  # factors let go
        self.fork = hasattr(os, "fork")

    def mark(self, k: int, num_factors: int) -> None:
        """Keyframe k's update begins with `num_factors` factors in the graph."""
        self._marks[k] = num_factors

    def due(self, num_keyframes: int) -> bool:
        """Enough keyframes for `maybe_close` to look (cheap; the smoother decides when they left it)."""
        return num_keyframes > self.start + self.chunk + self.chunk // 2

    def maybe_close(
        self,
        factors: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        keyframes: list[int],
        smoother: Smoother,
        pims: dict[int, object],
    ) -> gtsam.NonlinearFactorGraph | None:
        """When the next chunk can be closed (see the module docstring): its sigma is kept and the factors that
        remain are returned (the caller keeps them in place of `factors`); else None. `keyframes`: every keyframe
        so far in order; `values`: the latest value of every variable (final for keyframes out of the window)."""
        last = self.start + self.chunk + self.chunk // 2
        if not self.due(len(keyframes)) or smoother.has(X(keyframes[last])):
            return None
        chunk = [k for k in keyframes[self.start : self.start + self.chunk] if values.exists(X(k))]
        end = keyframes[self.start + self.chunk]  # the first keyframe after the chunk
        if self.compute and len(chunk) >= 4:
            self._sigma(factors, values, smoother, chunk, f"chunk {self.start // self.chunk + 1}")
        rest = self._after(factors, end)
        self.num_dropped += factors.size() - rest.size()
        for k in [k for k in pims if k < end]:
            del pims[k]
        for k in [k for k in self._marks if k < end]:
            del self._marks[k]  # (the marks from `end` on were moved by `_after`)
        self.start += self.chunk
        log.debug("scale chunk closed before keyframe %d: %d factors kept", end, rest.size())
        return rest

    def _after(self, factors: gtsam.NonlinearFactorGraph, end: int) -> gtsam.NonlinearFactorGraph:
        """The factors on keyframes from `end` on only (landmark priors go: module docstring), with the marks moved
        to their places in it. A factor added before keyframe `end`'s update is on earlier keyframes; of those
        added after it, only the ones added within `_LOOK_BACK` keyframes can reach before `end`, and only they are
        looked at."""
        first = self._marks.get(end, 0)
        check_until = self._marks.get(end + _LOOK_BACK, factors.size()) if end in self._marks else factors.size()
        moved = sorted((m, k) for k, m in self._marks.items() if k >= end)
        self._marks = {k: m for k, m in self._marks.items() if k < end}
        rest, n_moved = gtsam.NonlinearFactorGraph(), 0
        for i in range(first, factors.size()):
            while n_moved < len(moved) and moved[n_moved][0] <= i:
                self._marks[moved[n_moved][1]] = rest.size()
                n_moved += 1
            factor = factors.at(i)
            if factor is None:
                continue
            if i < check_until:
                syms = [gtsam.Symbol(key) for key in factor.keys()]
                frames = [sym.index() for sym in syms if chr(sym.chr()) != "l"]
                if not frames or min(frames) < end:
                    continue
            rest.add(factor)
        for _, k in moved[n_moved:]:
            self._marks[k] = rest.size()
        return rest

    def _sigma(
        self, factors: gtsam.NonlinearFactorGraph, values: gtsam.Values, smoother: Smoother, chunk: list[int], name: str
    ) -> None:
        """The chunk's sigma into `results`, computed in a forked process when possible (module docstring)."""
        pin = self.start > 0

        def compute() -> ScaleUncertainty | None:
            current = self._current(values, smoother)
            (sub,) = _chunk_graphs(factors, current, [chunk], pin, self.prior_sigma_m)
            return _sub_scale(sub, current, chunk, 5, name)

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
        self, factors: gtsam.NonlinearFactorGraph, values: gtsam.Values, keyframes: list[int], smoother: Smoother
    ) -> ScaleUncertainty | None:
        """The run's sigma: the closed chunks and the keyframes after them (chunked as `scale_uncertainty` does)."""
        self._collect()
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
