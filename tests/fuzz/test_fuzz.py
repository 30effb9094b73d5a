"""The fuzzer (tests/fuzz/run.py) over every capture format: the checked-in corpus plus hypothesis' derandomized
cases, in a child process under a memory limit. Every case must end as a clear error, a warning or a success:
0 tracebacks, 0 hangs (per-case limit), 0 escapes (no file outside the case folder created or changed)."""

from __future__ import annotations

import json
import resource
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
    print(json.dumps({k: report[k] for k in ("cases", "outcomes", "slowest_case_s", "max_rss_mb")}))
