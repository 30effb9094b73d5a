"""The fuzzer's runner: mutated captures through the readers, as `vio run` and `vio info` read them.

Run as a program (the test runs it in a child process under a memory limit):
    python -m tests.fuzz.run SANDBOX --examples N [--json OUT]
It writes the seed captures under SANDBOX/seeds, replays the checked-in corpus (`corpus.json`), then lets hypothesis
(fixed seed: derandomized, no example database) draw N cases. Each case is a seed copied to SANDBOX/case with 1-3
mutations (tests/fuzz/mutations.py), then: `vio info` (`capture_info`: each stream read on its own, every problem
listed), `open_capture`, every frame's image loaded (a frame that does not decode is skipped, as `vio run` does), and
`vio info`'s description of what opened.

Outcome classes: `error` (a VioError: one line, no newline), `warning` (opened, with warnings or skipped frames),
`success`. Anything else is a finding: `traceback` (any other exception, or an error message of several lines),
`hang` (longer than the per-case limit), `escape` (a file outside the case folder created or changed).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import signal
import sys
import time
from collections import Counter
from pathlib import Path

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.fuzz import mutations
from tests.fuzz.seeds import SEEDS, write_seeds

CASE_LIMIT_S = 20.0  # per case
CORPUS = Path(__file__).with_name("corpus.json")


class Hang(Exception):
    pass


def _alarm(signum, frame):  # noqa: ARG001
    raise Hang()


def _where(exc: BaseException) -> str:
    """file:line of the innermost frame of the project's code in the exception's traceback."""
    import traceback

    frames = [
        f for f in traceback.extract_tb(exc.__traceback__) if "/.venv/" not in f.filename and "<" not in f.filename
    ]
    f = frames[-1] if frames else traceback.extract_tb(exc.__traceback__)[-1]
    return f"{Path(f.filename).name}:{f.lineno}"


def _snapshot(root: Path, skip: Path) -> dict[str, tuple[int, int]]:
    """(size, mtime) of every file under root except under `skip` (symlinks not followed)."""
    out = {}
    for dirpath, dirnames, names in os.walk(root):
        if Path(dirpath) == skip:
            dirnames[:] = []
            continue
        for n in names:
            p = Path(dirpath) / n
            st_ = p.lstat()
            out[str(p)] = (st_.st_size, st_.st_mtime_ns)
    return out


def _one_line(exc: Exception) -> None:
    if "\n" in str(exc) or not str(exc).strip():
        raise AssertionError(f"error message is not one line: {str(exc)!r}") from None


def read_like_vio(path: Path, info: Counter[str] | None = None) -> str:
    """`vio info` (every problem listed, streams read separately), then as `vio run` reads it: open, load every
    frame, describe. The outcome class is the latter's (raises for a finding); `info` counts vio info's outcomes
    (`error`: the capture cannot be read at all; `no problem`, `one problem`, `several problems` listed)."""
    from vio.errors import CaptureError, VioError
    from vio.info import capture_info, describe
    from vio.readers import open_capture

    try:
        text = capture_info(path, offset=False)
    except VioError as exc:  # a capture that cannot be read at all
        _one_line(exc)
        kind = "error"
    else:
        listed = [line for line in text.splitlines() if line.startswith("problems: ")]
        n = int(listed[0].split()[1]) if listed else 0
        kind = "no problem" if n == 0 else "one problem" if n == 1 else "several problems"
    if info is not None:
        info[kind] += 1
    try:
        cap = open_capture(path)
    except VioError as exc:
        _one_line(exc)
        return "error"
    skipped = 0
    if cap.tracks is None:
        for i in range(cap.num_frames):
            try:
                cap.load_image(i)
            except CaptureError:
                skipped += 1
    describe(cap, offset=False)
    return "warning" if cap.warnings or skipped else "success"


class Fuzzer:
    def __init__(self, sandbox: Path) -> None:
        self.sandbox = sandbox
        self.seeds = write_seeds(sandbox / "seeds")
        self.case = sandbox / "case"
        self.outcomes: Counter[str] = Counter()
        self.info_outcomes: Counter[str] = Counter()
        self.findings: list[dict] = []
        self.slowest_s = 0.0

    def run_case(self, seed: str, muts: list[tuple[str, int, float, int]]) -> str:
        if self.case.exists() or self.case.is_symlink():
            shutil.rmtree(self.case)
        src = self.seeds[seed]
        seed_dir = self.sandbox / "seeds" / seed
        shutil.copytree(seed_dir, self.case, copy_function=os.link, symlinks=True)
        target = self.case / src.relative_to(seed_dir)
        for m in muts:
            mutations.apply(self.case, *m)
        before = _snapshot(self.sandbox, self.case)
        t0 = time.perf_counter()
        signal.signal(signal.SIGALRM, _alarm)
        signal.setitimer(signal.ITIMER_REAL, CASE_LIMIT_S)
        try:
            outcome = read_like_vio(target, self.info_outcomes)
        except Hang:
            outcome = "hang"
        except BaseException as exc:  # noqa: BLE001 - every other exception is a finding
            outcome, detail = "traceback", f"{type(exc).__name__}: {str(exc)[:300]} at {_where(exc)}"
        else:
            detail = ""
        finally:
            signal.setitimer(signal.ITIMER_REAL, 0)
        self.slowest_s = max(self.slowest_s, time.perf_counter() - t0)
        if (self.sandbox / mutations.CANARY).exists() or _snapshot(self.sandbox, self.case) != before:
            outcome, detail = "escape", "a file outside the case folder was created or changed"
        if outcome in ("traceback", "hang", "escape"):
            self.findings.append({"seed": seed, "mutations": muts, "outcome": outcome, "detail": detail})
        self.outcomes[outcome] += 1
        return outcome


MUTATION = st.tuples(
    st.sampled_from(mutations.OPS),
    st.integers(0, 10_000),
    st.floats(0.0, 1.0, exclude_max=True, allow_nan=False),
    st.integers(0, 1_000_000),
)


def run(sandbox: Path, examples: int) -> dict:
    fz = Fuzzer(sandbox)
    corpus = json.loads(CORPUS.read_text())
    for case in corpus:
        fz.run_case(case["seed"], [tuple(m) for m in case["mutations"]])

    @settings(
        max_examples=examples,
        derandomize=True,
        database=None,
        deadline=None,
        suppress_health_check=list(HealthCheck),
    )
    @given(st.sampled_from(sorted(SEEDS)), st.lists(MUTATION, min_size=1, max_size=3))
    def case(seed, muts):
        fz.run_case(seed, muts)

    case()
    n = sum(fz.outcomes.values())
    return {
        "cases": n,
        "corpus_cases": len(corpus),
        "outcomes": dict(fz.outcomes),
        "info_outcomes": dict(fz.info_outcomes),
        "findings": fz.findings,
        "slowest_case_s": round(fz.slowest_s, 2),
        "max_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
    }


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("sandbox", type=Path)
    p.add_argument("--examples", type=int, default=200)
    p.add_argument("--json", type=Path)
    args = p.parse_args()
    report = run(args.sandbox, args.examples)
    text = json.dumps(report, indent=1)
    if args.json:
        args.json.write_text(text)
    print(text)
    sys.exit(1 if report["findings"] else 0)


if __name__ == "__main__":
    main()
