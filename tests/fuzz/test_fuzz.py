"""The fuzzer (tests/fuzz/run.py) over every capture format: the checked-in corpus plus hypothesis' derandomized
cases, in a child process under a memory limit. Every case must end as a clear error, a warning or a success:
0 tracebacks, 0 hangs (per-case limit), 0 escapes (no file outside the case folder created or changed)."""

from __future__ import annotations

import json
import resource
import shutil
import subprocess
import sys

from tests.conftest import ROOT

EXAMPLES = 500  # hypothesis cases besides the corpus (about 20 s)
MEMORY_LIMIT_BYTES = 4 << 30  # address space of the child: a huge declared size must not be allocated


def _limit_memory() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT_BYTES, MEMORY_LIMIT_BYTES))


def test_fuzzed_captures_end_in_a_clear_line(tmp_path):
    report_path = tmp_path / "report.json"
    cmd = [sys.executable, "-m", "tests.fuzz.run", str(tmp_path / "sandbox"), "--examples", str(EXAMPLES)]
    res = subprocess.run(
        [*cmd, "--json", str(report_path)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
        preexec_fn=_limit_memory,
    )
    assert report_path.exists(), res.stderr[-3000:]
    report = json.loads(report_path.read_text())
    assert report["findings"] == [], json.dumps(report["findings"][:5], indent=1)
    assert res.returncode == 0, res.stderr[-3000:]
    outcomes = report["outcomes"]
    assert set(outcomes) <= {"error", "warning", "success"}
    assert report["cases"] == EXAMPLES + report["corpus_cases"] and report["corpus_cases"] >= 50
    assert min(outcomes.get(k, 0) for k in ("error", "warning", "success")) > 20  # the mutations reach every class
    info = report["info_outcomes"]  # vio info on the same cases: one line, or every problem listed
    assert set(info) <= {"error", "no problem", "one problem", "several problems"}
    assert sum(info.values()) == report["cases"] and info.get("several problems", 0) > 0
    keys = ("cases", "outcomes", "info_outcomes", "slowest_case_s", "max_rss_mb")
    print(json.dumps({k: report[k] for k in keys}))


RUN_CASES = (  # corpus entries run through the whole of `vio run` (the CLI), by their `what`
    "corrupt image bytes",
    "PNG header declares 2^31-1 squared",
    "1e308 in the gyro",
    "an image that is a symlink loop",
    "image name: absolute path outside the capture",
    "IMU rows in reverse order",
)


def test_vio_run_on_fuzzed_captures_writes_only_its_out_folder(tmp_path):
    """A few corpus cases through `vio run`: exit 0 with a run.json, or exit 2 with one `vio run: error:` line;
    never a traceback, and nothing created or changed outside `--out`."""
    from tests.fuzz.run import Fuzzer, _snapshot

    fz = Fuzzer(tmp_path / "sandbox")
    corpus = {c["what"]: c for c in json.loads((ROOT / "tests" / "fuzz" / "corpus.json").read_text())}
    for what in RUN_CASES:
        case = corpus[what]
        assert fz.run_case(case["seed"], [tuple(m) for m in case["mutations"]]) in ("error", "warning", "success")
        out = tmp_path / "out"
        before = _snapshot(tmp_path, out)
        cmd = [sys.executable, "-m", "vio.cli", "run", str(fz.case), "--out", str(out), "--set", "run.progress=false"]
        res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300, preexec_fn=_limit_memory)
        assert "Traceback" not in res.stderr, (what, res.stderr[-2000:])
        assert res.returncode in (0, 2), (what, res.stderr[-2000:])
        if res.returncode == 2:
            assert res.stderr.strip().splitlines()[-1].startswith("vio run: error: "), (what, res.stderr[-500:])
        assert _snapshot(tmp_path, out) == before, what  # only --out was written
        if res.returncode == 0:
            assert json.loads((out / "run.json").read_text())["status"] in ("ok", "degraded"), what
        elif (out / "run.json").exists():  # an error found before the run started leaves no run.json
            assert json.loads((out / "run.json").read_text())["status"] == "failed", what
        shutil.rmtree(out)
